"""SIFT vs XFeat on real data: the drift-correction run on TUM fr1/desk, matcher by matcher.

The field is built on the first half of the recording (``--field``, default: a splat field
built here, seconds); the second half, which it never saw, is corrected with visual odometry
(whose matcher is the same) and the run's defaults otherwise. Per matcher: ATE of the odometry
and of the estimate (no alignment: drift is what is measured), p90 and max of the estimate's
error, corrections accepted, median inliers, median time per keyframe. Writes JSON.

    python benchmarks/matchers_desk.py [--data ../shared/data/tum/rgbd_dataset_freiburg1_desk] \
        [--field FIELD.pt] [--matchers sift xfeat] [--out benchmarks/results/matchers_fr1_desk.json]
"""

from __future__ import annotations

import argparse
import csv
import json
import re
import tempfile
from pathlib import Path

import numpy as np
from provenance import write_result


def run_one(data: Path, field: Path, matcher: str, out: Path) -> dict:
    from nap3d_graph.cli import main

    rc = main(["run", "--traj", "tum", "--data", str(data), "--frames", "0.5:1", "--field", str(field),
               "--odom", "vo", "--matcher", matcher, "--out", str(out)])
    if rc != 0:
        return {"error": f"exit {rc}"}
    metrics = json.loads((out / "latest" / "metrics.json").read_text())
    with open(out / "latest" / "corrections.csv") as f:
        rows = list(csv.DictReader(f))
    inliers = [int(r["inliers"]) for r in rows if r.get("inliers") not in (None, "", "0")]
    reasons: dict[str, int] = {}
    for r in rows:
        if r.get("accepted") not in ("True", "1", "true"):
            reason = re.split(r"[(:=]", r.get("reason") or "?")[0].strip()
            reasons[reason] = reasons.get(reason, 0) + 1
    ate = metrics["estimate"]["ate_m"]
    return {"ate_odometry_m": metrics["odometry"]["ate_m"]["rmse"], "ate_estimate_m": ate["rmse"],
            "ate_estimate_median_m": ate["median"], "ate_estimate_max_m": ate["max"],
            "ate_causal_m": metrics.get("estimate_online", {}).get("ate_m", {}).get("rmse"),
            "keyframes": len(rows), "accepted": metrics["corrections_accepted"],
            "refused_reasons": reasons, "median_inliers": float(np.median(inliers)) if inliers else 0.0,
            "seconds_per_keyframe_median": metrics["seconds_per_keyframe_median"]}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=Path("../shared/data/tum/rgbd_dataset_freiburg1_desk"))
    p.add_argument("--field", type=Path, default=None, help="a field built on frames 0:0.5 (default: build a splat)")
    p.add_argument("--matchers", nargs="+", default=["sift", "xfeat"])
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/matchers_fr1_desk.json"))
    args = p.parse_args(argv)
    from nap3d_graph.cli import main as cli

    work = Path(tempfile.mkdtemp(prefix="matchers_desk_"))
    field = args.field
    if field is None:
        field = work / "splat.pt"
        assert cli(["train-field", str(args.data), "--frames", "0:0.5", "--model", "splat", "--out", str(field),
                    "--quiet"]) == 0
    result = {"data": str(args.data), "field": str(field), "frames": "0.5:1 (field from 0:0.5)", "odometry": "vo",
              "matchers": {}}
    for matcher in args.matchers:
        result["matchers"][matcher] = r = run_one(args.data, field, matcher, work / matcher)
        print(f"{matcher:18s} ATE {r.get('ate_estimate_m', float('nan')) * 100:.2f} cm (odometry "
              f"{r.get('ate_odometry_m', float('nan')) * 100:.2f} cm), accepted {r.get('accepted')}/{r.get('keyframes')}, "
              f"median inliers {r.get('median_inliers')}", flush=True)
    write_result(args.out, result, args)


if __name__ == "__main__":
    main()
