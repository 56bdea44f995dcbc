"""Keyframes by sharpness on real data: TUM fr1/desk's second half (fast, blurred hand-held
motion) corrected with a field built on its first half, keyframe every 5 frames as it comes
against the sharpest-in-a-window choice (``--keyframe-window``) and keyframes on the
odometry's doubt (``--keyframe-on-doubt``). Per setting: ATE (no alignment) with p90 and max,
causal ATE, keyframes, corrections accepted, median inliers, the sharpness of the chosen
keyframes. Writes JSON.

    python benchmarks/keyframes_desk.py --field FIELD.pt [--data ../shared/data/tum/rgbd_dataset_freiburg1_desk] \\
        [--odom vo] [--matcher xfeat] [--out benchmarks/results/keyframes_fr1_desk.json]
"""

from __future__ import annotations

import argparse
import csv
import json
import tempfile
from pathlib import Path

import numpy as np
from provenance import write_result

SETTINGS = {
    "every 5 (as they come)": [],
    "window 3": ["--keyframe-window", "3"],
    "window 3 + on doubt": ["--keyframe-window", "3", "--keyframe-on-doubt"],
}


def run_one(data: Path, field: Path, odom: str, matcher: str, extra: list, out: Path) -> dict:
    from nap3d_graph.cli import main

    rc = main(["run", "--traj", "tum", "--data", str(data), "--frames", "0.5:1", "--field", str(field), "--odom", odom,
               "--matcher", matcher, "--out", str(out), *extra])
    if rc != 0:
        return {"error": f"exit {rc}"}
    metrics = json.loads((out / "latest" / "metrics.json").read_text())
    with open(out / "latest" / "corrections.csv") as f:
        rows = list(csv.DictReader(f))
    inliers = [int(r["inliers"]) for r in rows]
    ate = metrics["estimate"]["ate_m"]
    return {"ate_odometry_m": metrics["odometry"]["ate_m"]["rmse"], "ate_estimate_m": ate["rmse"],
            "ate_estimate_median_m": ate["median"], "ate_estimate_max_m": ate["max"],
            "ate_causal_m": metrics.get("estimate_online", {}).get("ate_m", {}).get("rmse"),
            "keyframes": len(rows), "accepted": metrics["corrections_accepted"],
            "median_inliers": float(np.median(inliers)) if inliers else 0.0,
            "postponed": sum(int(r["postponed_frames"]) > 0 for r in rows),
            "doubt_keyframes": sum(r["keyframe_why"] == "doubt" for r in rows),
            "keyframe_sharpness_median": _nan_median([float(r["sharpness"]) for r in rows])}


def _nan_median(values: list) -> float | None:
    """Median of the finite values; None where none is (keyframes as they come are not scored)."""
    finite = [v for v in values if np.isfinite(v)]
    return float(np.median(finite)) if finite else None


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=Path("../shared/data/tum/rgbd_dataset_freiburg1_desk"))
    p.add_argument("--field", type=Path, required=True, help="a field built on frames 0:0.5 by train-field")
    p.add_argument("--odom", default="vo")
    p.add_argument("--matcher", default="xfeat")
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/keyframes_fr1_desk.json"))
    args = p.parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="keyframes_desk_"))
    result = {"data": str(args.data), "field": str(args.field), "frames": "0.5:1 (field from 0:0.5)",
              "odometry": args.odom, "matcher": args.matcher, "settings": {}}
    for k, (name, extra) in enumerate(SETTINGS.items()):
        result["settings"][name] = r = run_one(args.data, args.field, args.odom, args.matcher, extra, work / str(k))
        print(f"{name:24s} ATE {r['ate_estimate_m'] * 100:.2f} cm (max {r['ate_estimate_max_m'] * 100:.1f}, causal "
              f"{r['ate_causal_m'] * 100:.2f}; odometry {r['ate_odometry_m'] * 100:.2f}), accepted "
              f"{r['accepted']}/{r['keyframes']}, inliers {r['median_inliers']}, postponed {r['postponed']}, "
              f"doubt {r['doubt_keyframes']}", flush=True)
    write_result(args.out, result, args)


if __name__ == "__main__":
    main()
