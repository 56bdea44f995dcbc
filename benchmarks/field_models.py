"""How well does each field type let NAP3D measure a real keyframe? For fields built on the
first half of a real recording (``--field NAME=FIELD.pt``, e.g. the ones
``benchmarks/sweep_fields.yaml`` built), every ``--step``-th frame of the second half (never
seen by the field) is measured as a run measures a keyframe (depth at the colour's instant,
the field's capture timing, 320x240 render, the run's matcher) from a render 2 cm / 1 deg
(per axis, seeded) off its true pose. Per field: the error of the correction against the
ground truth (translation mm and rotation deg: median, p90, max), failures, inliers, the
render time, and the field's own held-out figures from its report. Also the translation errors
in the world frame, frame by frame, and their lag-1 correlation: near 0 for independent
errors, near 1 for an offset that drifts slowly along the recording (a ground truth that is
not consistent between the two halves, such as a tracker's, shows as that). Writes JSON.

    python benchmarks/field_models.py --data ../shared/data/tum/rgbd_dataset_freiburg1_desk \\
        --field views=F1.pt --field splat=F2.pt --field grid=F3.pt [--matcher xfeat] --out OUT.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from provenance import write_result


def measure(data: Path, field_path: Path, matcher: str, step: int, seed: int) -> dict:
    from nap3d_graph.conventions import exp_se3, inv_T, log_se3
    from nap3d_graph.datasets import open_sequence
    from nap3d_graph.datasets.depth_timing import CaptureTiming
    from nap3d_graph.fields import load_field
    from nap3d_graph.fields.field_error import measure_frame
    from nap3d_graph.nap3d.config import AlignConfig
    from nap3d_graph.run.config import PipelineConfig

    sequence = open_sequence(data, frames="0.5:1")
    field = load_field(field_path)
    timing = CaptureTiming.of(field.meta.get("timing"))
    config = PipelineConfig(field_sigma_m=0.0, align=AlignConfig(matcher=matcher))
    rng = np.random.default_rng(seed)
    err_mm, err_deg, inliers, render_s, failures, world_mm, gaps = [], [], [], [], [], [], []
    for i in range(0, len(sequence), step):
        offset = exp_se3(rng.normal(0.0, [0.0175] * 3 + [0.02] * 3))  # drawn whatever fails: same offsets per field
        T = sequence.T_world_cam_gt[i]
        if not np.all(np.isfinite(T)):
            continue
        if hasattr(field, "nearest_gap_m"):  # a view field: how far its nearest view sees from here
            gaps.append(field.nearest_gap_m(T))
        correction = measure_frame(sequence, i, field, T @ offset, config, timing)
        render_s.append(correction.timings_s.get("render", np.nan))
        if not correction.success:
            failures.append({"frame": i, "reason": correction.reason})
            continue
        e = log_se3(inv_T(T) @ correction.T_world_cam_corrected)
        err_mm.append(float(np.linalg.norm(e[3:]) * 1000))
        err_deg.append(float(np.degrees(np.linalg.norm(e[:3]))))
        world_mm.append([i, *((correction.T_world_cam_corrected[:3, 3] - T[:3, 3]) * 1000).round(2).tolist()])
        inliers.append(int(correction.alignment.num_inliers))
    report_path = field_path.with_name(field_path.name[:-3] + ".report.json")
    report = json.loads(report_path.read_text()) if report_path.is_file() else {}
    held = report.get("held_out") or {}

    def spread(values):
        return {"median": float(np.median(values)), "p90": float(np.percentile(values, 90)),
                "max": float(np.max(values))} if values else None

    return {"field": str(field_path), "model": field.meta.get("model"), "frames": len(err_mm) + len(failures),
            "failed": len(failures), "failures": failures, "translation_mm": spread(err_mm),
            "rotation_deg": spread(err_deg), "inliers_median": float(np.median(inliers)) if inliers else None,
            "render_ms_median": float(np.nanmedian(render_s) * 1000) if render_s else None,
            "held_out_psnr_db": held.get("psnr_db"), "held_out_psnr_affine_db": held.get("psnr_affine_db"),
            "held_out_depth_err_median_m": (held.get("depth_abs_err_m") or {}).get("median"),
            "held_out_opaque": held.get("opaque_fraction"), "field_error": report.get("field_error"),
            "build_seconds": report.get("train_seconds"), "lag1_correlation": lag1(world_mm),
            "nearest_view_gap_m_median": float(np.median(gaps)) if gaps else None,
            "world_error_mm": world_mm}


def lag1(rows: list) -> float | None:
    """Lag-1 correlation of successive world-frame error vectors (rows of [frame, x, y, z])."""
    if len(rows) < 3:
        return None
    d = np.asarray(rows, dtype=float)[:, 1:]
    return float(np.sum(d[1:] * d[:-1]) / np.sqrt(np.sum(d[1:] ** 2) * np.sum(d[:-1] ** 2)))


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, required=True, help="the recording the fields were built on (first half)")
    p.add_argument("--field", action="append", required=True, metavar="NAME=FIELD.pt")
    p.add_argument("--matcher", default="xfeat")
    p.add_argument("--step", type=int, default=5, help="every STEP-th second-half frame (default 5: the keyframes)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args(argv)
    result = {"data": str(args.data), "frames": "0.5:1 (fields from 0:0.5)", "matcher": args.matcher,
              "perturbation": "2 cm / 1 deg per axis, seeded", "step": args.step, "fields": {}}
    for item in args.field:
        name, _, path = item.partition("=")
        started = time.perf_counter()
        r = result["fields"][name] = measure(args.data, Path(path), args.matcher, args.step, args.seed)
        t, d = r["translation_mm"], r["rotation_deg"]
        psnr = "-" if r["held_out_psnr_db"] is None else f"{r['held_out_psnr_db']:.1f}"
        print(f"{name:8s} {t['median']:5.1f} / {t['p90']:5.1f} / {t['max']:5.1f} mm, {d['median']:.2f} / "
              f"{d['p90']:.2f} deg (median / p90 / max), {r['failed']} failed of {r['frames']}, "
              f"{r['inliers_median']:.0f} inliers, render {r['render_ms_median']:.0f} ms, held-out "
              f"{psnr} dB, lag-1 correlation {r['lag1_correlation']:.2f} ({time.perf_counter() - started:.0f} s)", flush=True)
    write_result(args.out, result, args)


if __name__ == "__main__":
    main()
