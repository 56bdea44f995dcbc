"""Does moving each keyframe's real points to the middle row's instant (``run
--rolling-shutter S``) help on a real rolling-shutter camera?

A recording's second half is corrected with the field built on its first half, by each field
(``--field NAME=FIELD.pt``) and odometry (``--odom``), once per readout time (``--readout``,
seconds; 0: a global shutter; ``auto``, the default run: the readout ``train-field``
estimated with the recording's capture timing and recorded in the field, 0 where it found
none). A nominal readout is not fitted to the recording: a CMOS camera at its highest frame
rate reads its rows for about a frame period (1/30 s for the Kinect's colour camera of TUM
and 7-Scenes). Per run: the ATE (no alignment) of the smoothed
and causal trajectories and the odometry's, corrections accepted, the keyframes' own errors
against the ground truth (median and p90, all and the faster half by the odometry's speed),
and the corrections' NEES (mean with the 95% band of a mean of k chi-square(6) values, median).
Writes JSON.

    python benchmarks/rolling_shutter.py --data ../shared/data/tum/rgbd_dataset_freiburg1_desk \\
        --field views=VIEWS.pt --field grid=GRID.pt [--odom vo dense] [--readout 0 auto 0.033] --out OUT.json
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from provenance import write_result


def run_one(data: Path, field, odom: str, readout_s: float | None, frames: str) -> dict:
    from scipy.stats import chi2

    from nap3d_graph.conventions import pose_error
    from nap3d_graph.datasets import open_sequence
    from nap3d_graph.evaluation.compare import correction_nees
    from nap3d_graph.evaluation.metrics import ate
    from nap3d_graph.motion.odometry import make_odometry
    from nap3d_graph.nap3d.config import AlignConfig
    from nap3d_graph.nap3d.keyframe import readout_of
    from nap3d_graph.nap3d.matching import choose_matcher
    from nap3d_graph.run.config import PipelineConfig
    from nap3d_graph.run.pipeline import Pipeline

    sequence = open_sequence(data, frames=frames)
    matcher, _ = choose_matcher("auto", sequence)
    odometry = make_odometry(odom, sequence, 0, 2e-3, 2e-3, matcher=matcher)
    config = PipelineConfig(rolling_shutter_s=readout_s, align=AlignConfig(matcher=matcher))
    pipeline = Pipeline(sequence, field, odometry, config)
    result = pipeline.run()
    nees = correction_nees(result)
    k = len(nees)
    posed = np.all(np.isfinite(result.T_world_cam_gt), axis=(1, 2))
    stamps = result.timestamps[posed]
    errors_mm, speeds = [], []
    T_gt = result.T_world_cam_gt
    for i, (T_corrected, _) in sorted(result.corrections.items()):  # every successful correction
        if not np.all(np.isfinite(T_gt[i])):
            continue
        errors_mm.append(pose_error(T_corrected, T_gt[i])[0] * 1000)
        j = max(i - 1, 0)
        dt = float(sequence.timestamps[i] - sequence.timestamps[j]) or 1.0
        speeds.append(np.linalg.norm(result.T_world_cam_odometry[i][:3, 3] - result.T_world_cam_odometry[j][:3, 3]) / dt)
    errors_mm, speeds = np.array(errors_mm), np.array(speeds)
    fast = speeds > np.median(speeds) if speeds.size else np.zeros(0, bool)
    return {
        "odometry": odom, "matcher": matcher, "readout_s": readout_s,
        "readout_used_s": readout_of(config, pipeline.jobs.timing()),
        "ate_odometry_m": ate(stamps, T_gt[posed], result.T_world_cam_odometry[posed])["rmse"],
        "ate_estimate_m": ate(stamps, T_gt[posed], result.T_world_cam_estimate[posed])["rmse"],
        "ate_causal_m": ate(stamps, T_gt[posed], result.T_world_cam_online[posed])["rmse"],
        "keyframes": len(result.keyframes), "accepted": result.num_accepted,
        "keyframe_error_mm": {"median": float(np.median(errors_mm)), "p90": float(np.percentile(errors_mm, 90)),
                              "fast_half_median": float(np.median(errors_mm[fast])) if fast.any() else None,
                              "slow_half_median": float(np.median(errors_mm[~fast])) if (~fast).any() else None}
        if errors_mm.size else None,
        "nees_mean": float(np.mean(nees)) if k else None,
        "nees_band_95": [chi2.ppf(0.025, 6 * k) / k, chi2.ppf(0.975, 6 * k) / k] if k else None,
        "nees_median": float(np.median(nees)) if k else None,
    }


def _readout(text: str) -> float | None:
    return None if text == "auto" else float(text)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, required=True)
    p.add_argument("--field", action="append", required=True, metavar="NAME=FIELD.pt",
                   help="a field built on the recording's first half (repeat for several)")
    p.add_argument("--odom", nargs="+", default=["vo", "dense"])
    p.add_argument("--readout", type=_readout, nargs="+", default=[0.0, None],
                   help="readout times, seconds, or auto: the field's estimate (default: 0 auto)")
    p.add_argument("--frames", default="0.5:1")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args()
    from nap3d_graph.fields import load_field

    out = {"data": str(args.data), "frames": f"{args.frames} (fields from the first half)", "runs": {}}
    for spec in args.field:
        name, _, path = spec.partition("=")
        field = load_field(Path(path))
        for odom in args.odom:
            for readout in args.readout:
                row = run_one(args.data, field, odom, readout, args.frames)
                row["field"] = path
                key = f"{name} {odom} readout={'auto' if readout is None else f'{readout:g}'}"
                out["runs"][key] = row
                e = row["keyframe_error_mm"] or {}
                print(f"{key}: ATE {row['ate_estimate_m'] * 100:.2f} cm (causal {row['ate_causal_m'] * 100:.2f}, "
                      f"odometry {row['ate_odometry_m'] * 100:.2f}), {row['accepted']}/{row['keyframes']} accepted, "
                      f"keyframes {e.get('median', float('nan')):.1f} mm median (fast half "
                      f"{e.get('fast_half_median') or float('nan'):.1f}), NEES {row['nees_mean'] or float('nan'):.2f}",
                      flush=True)
                write_result(args.out, out, args)


if __name__ == "__main__":
    main()
