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

With ``--by-baseline OFFSETS``, each of those frames is also measured against real frames of
its *own* half, ``OFFSETS`` frames before and after it, each alone at its recorded pose
(warped to a render 2 cm / 1 deg off the frame's true pose, as ``field_models.py`` measures): the
error against the ground truth binned by how differently the two cameras see (``gap_m``, as
for the first half's frames). Frames a few centimetres apart share their views and their sensor's biases,
so what is left there is the recorded poses' own disagreement (motion-capture jitter, stamps
against capture instants); how it grows with the baseline is what aligning across that
distance adds. A run's keyframes sit at the second half's distance from the first half's
frames (``gap_m_median``), so the two together say how much of a keyframe's error any map built
from the first half with these poses must keep.

    python benchmarks/ground_truth_consistency.py --data ../shared/data/7scenes/redkitchen \\
        --field VIEWS.pt --compare benchmarks/results/field_models_redkitchen.json --out OUT.json \\
        [--by-baseline 1 2 4 8 16]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from provenance import write_result


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


#: Upper edges (metres) of the bins of ``--by-baseline``: how differently the two cameras see
#: (camera plus viewing centre distance, as the first-half frames' ``gap_m``).
BASELINE_BINS_M = (0.05, 0.1, 0.2, 0.4, 0.8, 1.6)


def measure_by_baseline(data: Path, field_path: Path, matcher: str, step: int, offsets: list[int],
                        seed: int = 0) -> dict:
    """Every ``step``-th second-half frame against the second-half frames ``offsets`` before and
    after it, each alone at its recorded pose (see the module docstring), measured as
    ``field_models.py`` measures a field: from a render 2 cm / 1 deg (per axis, seeded) off the
    frame's true pose, here the other frame warped there. The errors binned by how differently
    the two cameras see (``gap_m``: camera plus viewing centre distance)."""
    from nap3d_graph.conventions import exp_se3, inv_T, log_se3
    from nap3d_graph.datasets import open_sequence
    from nap3d_graph.datasets.depth_timing import CaptureTiming
    from nap3d_graph.fields import load_field
    from nap3d_graph.fields.field_error import measure_frame
    from nap3d_graph.fields.views import ViewFieldConfig, build_view_field
    from nap3d_graph.nap3d.config import AlignConfig
    from nap3d_graph.run.config import PipelineConfig

    sequence = open_sequence(data, frames="0.5:1")
    first_half = load_field(field_path)  # its capture timing, as a run of a field of that recording uses
    timing = CaptureTiming.of(first_half.meta.get("timing"))
    t = timing or CaptureTiming()  # none recorded: the stamps as they are
    # Every frame of the half a view of its own (no spacing): view k is frame frames[k].
    own, report = build_view_field(sequence, np.arange(len(sequence)), ViewFieldConfig(min_spacing_m=0.0),
                                   t.depth_offset_s, t.colour_offset_s, t.depth_scale)
    view_of = {frame: k for k, frame in enumerate(report["view_frames"])}
    config = PipelineConfig(field_sigma_m=0.0, align=AlignConfig(matcher=matcher))
    pairs, failures = [], 0
    rng = np.random.default_rng(seed)
    for i in range(0, len(sequence), step):
        T = sequence.T_world_cam_gt[i]
        for j in sorted({i + sign * o for o in offsets for sign in (-1, 1)}):
            if j not in view_of or not np.all(np.isfinite(T)):
                continue
            k = view_of[j]
            view = nearest_real_frame(own, k)
            offset = exp_se3(rng.normal(0.0, [0.0175] * 3 + [0.02] * 3))
            correction = measure_frame(sequence, i, view, T @ offset, config, timing)
            baseline = float(np.linalg.norm(own.T_world_cam[k][:3, 3] - T[:3, 3]))
            gap = view.nearest_gap_m(T)  # camera plus viewing centre, as the first-half gaps
            if not correction.success:
                failures += 1
                continue
            error = inv_T(T) @ correction.T_world_cam_corrected
            pairs.append({"frame": i, "against": j, "baseline_m": round(baseline, 4), "gap_m": round(gap, 4),
                          "translation_mm": round(float(np.linalg.norm(correction.T_world_cam_corrected[:3, 3]
                                                                       - T[:3, 3]) * 1000), 2),
                          "rotation_deg": round(float(np.degrees(np.linalg.norm(log_se3(error)[:3]))), 3),
                          "inliers": int(correction.alignment.num_inliers)})
    bins, lo = [], 0.0
    for hi in BASELINE_BINS_M:
        inside = [p for p in pairs if lo <= p["gap_m"] < hi]
        if inside:
            e = np.array([p["translation_mm"] for p in inside])
            bins.append({"gap_m": [lo, hi], "pairs": len(inside),
                         "baseline_m_median": float(np.median([p["baseline_m"] for p in inside])),
                         "translation_mm_median": float(np.median(e)),
                         "translation_mm_p90": float(np.percentile(e, 90)),
                         "rotation_deg_median": float(np.median([p["rotation_deg"] for p in inside])),
                         "inliers_median": float(np.median([p["inliers"] for p in inside]))})
        lo = hi
    return {"offsets": list(offsets), "pairs": len(pairs), "failed": failures, "bins": bins, "pair_errors": pairs}


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
    p.add_argument("--by-baseline", type=int, nargs="+", default=None, metavar="OFFSET",
                   help="also measure each frame against its own half's frames OFFSET frames away (e.g. 1 2 4 8 16)")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args()
    result = measure(args.data, args.field, args.matcher, args.step, args.nearest)
    if args.compare is not None:
        result["against_fields"] = compare(result, args.compare)
    if args.by_baseline:
        result["by_baseline"] = measure_by_baseline(args.data, args.field, args.matcher, args.step, args.by_baseline)
    write_result(args.out, result, args)
    t = result["translation_mm"]
    print(f"{args.data.name}: {result['measured']} frames, each against its {args.nearest} nearest first-half frames (gap "
          f"{result['gap_m_median']:.2f} m median), {result['failed']} failed; error against the ground truth "
          f"{t['median']:.1f} mm median, p90 {t['p90']:.1f}, max {t['max']:.1f}")
    for b in result.get("by_baseline", {}).get("bins", []):
        print(f"  against its own half, gap {b['gap_m'][0]:.2f}-{b['gap_m'][1]:.2f} m "
              f"(cameras {b['baseline_m_median']:.2f} m apart): "
              f"{b['translation_mm_median']:.1f} mm median (p90 {b['translation_mm_p90']:.1f}), "
              f"{b['rotation_deg_median']:.2f} deg, {b['pairs']} pairs")
    for name, c in result.get("against_fields", {}).items():
        print(f"  {name}: cosine {c['median_cosine']:.2f}, field rms {c['field_rms_mm']:.1f} mm -> "
              f"{c['field_rms_after_subtracting_mm']:.1f} mm with these subtracted")


if __name__ == "__main__":
    main()
