"""Does a recording's ground truth agree with itself between its two halves? Measured without
any field.

Every ``--step``-th frame of the second half is measured, as a run measures a keyframe
(``measure_frame``: depth at the colour's instant, the run's matcher and alignment, 320x240),
against each of the ``--nearest`` real frames of the first half that saw most nearly what it
sees (the nearest views of a view field built on the first half, ``--field``, by camera plus
viewing centre), one at a time, each placed at its ground-truth pose: no map, only real images
and their recorded poses; the per-axis median of the world-frame errors is kept. Where the
ground truth is consistent, the measured pose lands on the frame's own ground truth within the
alignment's error; where the two halves' poses disagree (a tracker's drift), it lands off by
that disagreement, in the same direction as every field built on the first half does. Per
frame: the error against the ground truth (translation mm, rotation deg: median over the
frames), its world-frame vector, the first-half frames used and the nearest gap; with ``--compare
field_models_*.json``, each field's world-frame errors at the same frames and their agreement
with these (cosine of the vectors, and how much of each field's error these explain). Writes
JSON.

    python benchmarks/ground_truth_consistency.py --data ../shared/data/7scenes/redkitchen \\
        --field VIEWS.pt --compare benchmarks/results/field_models_redkitchen.json --out OUT.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def nearest_real_frame(field, j: int):
    """A view field holding only view ``j`` of ``field``: it renders that real frame as itself
    at its own pose."""
    from nap3d_graph.fields.views import ViewField

    return ViewField(field.rgb[j:j + 1], field.depth_m[j:j + 1], field.T_world_cam[j:j + 1], field.intrinsics,
                     field.config, meta=field.meta)


def measure(data: Path, field_path: Path, matcher: str, step: int, nearest: int = 1) -> dict:
    from nap3d_graph.conventions import inv_T, log_se3
    from nap3d_graph.datasets import open_sequence
    from nap3d_graph.datasets.depth_timing import CaptureTiming
    from nap3d_graph.fields import load_field
    from nap3d_graph.fields.field_error import measure_frame
    from nap3d_graph.nap3d.config import AlignConfig
    from nap3d_graph.run.config import PipelineConfig

    sequence = open_sequence(data, frames="0.5:1")
    field = load_field(field_path)
    if not hasattr(field, "nearest_views"):
        raise SystemExit(f"{field_path}: a view field (train-field --model views) is needed, to find the real frames")
    timing = CaptureTiming.of(field.meta.get("timing"))
    config = PipelineConfig(field_sigma_m=0.0, align=AlignConfig(matcher=matcher))
    frames, failures = [], []
    for i in range(0, len(sequence), step):
        T = sequence.T_world_cam_gt[i]
        if not np.all(np.isfinite(T)):
            continue
        near = field.nearest_views(T, nearest)
        if len(near) == 0:
            failures.append({"frame": i, "reason": "no first-half frame looks this way"})
            continue
        world, rot, inliers = [], [], []
        for j in near:  # each real frame alone, at its own ground-truth pose
            correction = measure_frame(sequence, i, nearest_real_frame(field, int(j)), field.T_world_cam[j], config,
                                       timing)
            if correction.success:
                world.append(correction.T_world_cam_corrected[:3, 3] - T[:3, 3])
                rot.append(np.degrees(np.linalg.norm(log_se3(inv_T(T) @ correction.T_world_cam_corrected)[:3])))
                inliers.append(int(correction.alignment.num_inliers))
        gap = float(field.nearest_gap_m(T))
        if not world:
            failures.append({"frame": i, "views": near.tolist(), "gap_m": gap, "reason": correction.reason})
            continue
        error = np.median(np.array(world), axis=0)  # per axis over the frames measured against
        frames.append({"frame": i, "views": near.tolist(), "measured_against": len(world), "gap_m": round(gap, 3),
                       "translation_mm": round(float(np.linalg.norm(error) * 1000), 2),
                       "rotation_deg": round(float(np.median(rot)), 3),
                       "world_error_mm": (error * 1000).round(2).tolist(),
                       "inliers": int(np.median(inliers))})
    t = np.array([f["translation_mm"] for f in frames]) if frames else np.zeros(0)
    return {"data": data.name, "field": str(field_path), "matcher": matcher, "step": step, "nearest": nearest,
            "measured": len(frames), "failed": len(failures), "failures": failures,
            "translation_mm": {"median": float(np.median(t)), "p90": float(np.percentile(t, 90)),
                               "max": float(t.max())} if t.size else None,
            "rotation_deg_median": float(np.median([f["rotation_deg"] for f in frames])) if frames else None,
            "gap_m_median": float(np.median([f["gap_m"] for f in frames])) if frames else None,
            "frames": frames}


def compare(result: dict, models_path: Path) -> dict:
    """Each field's world-frame errors (``field_models_*.json``) against these, frame by frame:
    median cosine between the two vectors, and the share of the field's squared error left once
    these are subtracted (1: these explain nothing; 0: all)."""
    models = json.loads(models_path.read_text())
    ours = {f["frame"]: np.asarray(f["world_error_mm"]) for f in result["frames"]}
    out = {}
    for name, entry in models["fields"].items():
        theirs = {int(row[0]): np.asarray(row[1:]) for row in entry.get("world_error_mm", [])}
        common = sorted(set(ours) & set(theirs))
        if not common:
            continue
        a = np.array([ours[k] for k in common])
        b = np.array([theirs[k] for k in common])
        cos = np.sum(a * b, axis=1) / np.maximum(np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-9)
        out[name] = {"frames": len(common), "median_cosine": float(np.median(cos)),
                     "field_rms_mm": float(np.sqrt(np.mean(np.sum(b**2, axis=1)))),
                     "field_rms_after_subtracting_mm": float(np.sqrt(np.mean(np.sum((b - a) ** 2, axis=1)))),
                     "share_left": float(np.sum((b - a) ** 2) / max(np.sum(b**2), 1e-12))}
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, required=True)
    p.add_argument("--field", type=Path, required=True, help="a view field built on the first half")
    p.add_argument("--matcher", default="xfeat")
    p.add_argument("--step", type=int, default=5)
    p.add_argument("--nearest", type=int, default=5, help="first-half frames each frame is measured against, "
                   "one at a time (the per-axis median of their world-frame errors is kept)")
    p.add_argument("--compare", type=Path, default=None, help="field_models_*.json of the same recording")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args()
    result = measure(args.data, args.field, args.matcher, args.step, args.nearest)
    if args.compare is not None:
        result["against_fields"] = compare(result, args.compare)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    t = result["translation_mm"]
    print(f"{args.data.name}: {result['measured']} frames, each against its {args.nearest} nearest first-half frames (gap "
          f"{result['gap_m_median']:.2f} m median), {result['failed']} failed; error against the ground truth "
          f"{t['median']:.1f} mm median, p90 {t['p90']:.1f}, max {t['max']:.1f}")
    for name, c in result.get("against_fields", {}).items():
        print(f"  {name}: cosine {c['median_cosine']:.2f}, field rms {c['field_rms_mm']:.1f} mm -> "
              f"{c['field_rms_after_subtracting_mm']:.1f} mm with these subtracted")


if __name__ == "__main__":
    main()
