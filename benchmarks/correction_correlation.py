"""Are a run's corrections honest about their error, and is that error their own? (issue 62)

The run report's gate consistency weighs each correction against the odometry's prediction
(its innovation). It reads "too cautious" on some clean runs. This measures, on runs in fields
posed by the ground truth (so the field's frame is the ground truth's), each accepted or
refused correction's error against the ground truth, its NEES under the correction's own
covariance (6 dof: median 5.35, mean 6 when honest), and how alike consecutive corrections'
errors are (lag-1 correlation per axis). A field error shared by neighbouring keyframes is in
the prediction too (it carries the previous correction), so the innovation cancels it: the
gate then reads too cautious while the corrections' covariance is honest about their error.

    python benchmarks/correction_correlation.py \\
        --case desk,tum,../shared/data/tum/rgbd_dataset_freiburg1_desk,0.5:1,/tmp/ms_desk2/gt_field.pt \\
        --case kitchen,7scenes,../shared/data/7scenes/redkitchen,0.5:1,/tmp/ms_rk2/gt_field.pt \\
        --work /tmp/corr --out benchmarks/results/correction_correlation.json

Fields: the ground-truth-posed fields map_survey.py trains (``--work``'s ``gt_field.pt``).
"""

from __future__ import annotations

import argparse
import csv
import shutil
from pathlib import Path

import gtsam
import numpy as np
from provenance import write_result
from scoring import spread

import nap3d_graph.run.graph as run_graph
from nap3d_graph.cli import main as cli_main
from nap3d_graph.conventions import inv_T, log_se3
from nap3d_graph.factors.gate import factor_error_and_covariance
from nap3d_graph.trajectory import read_tum_trajectory

AXES = ("rx", "ry", "rz", "tx", "ty", "tz")
STATS = ("median", "mean", "p90")


def gated_corrections(argv: list[str]) -> list[dict]:
    """Run ``nap3d-graph run ARGV`` in this process and return what its gate saw, in order:
    each correction's measured ``T_world_cam`` (4, 4), its covariance (6, 6) and the gate's d2."""
    seen: list[dict] = []
    gate = run_graph.chi2_gate_isam2

    def watched(factor, isam, **kwargs):
        result = gate(factor, isam, **kwargs)
        values = gtsam.Values()
        for key in factor.keys():
            values.insert(key, isam.calculateEstimatePose3(key))
        _, covariance = factor_error_and_covariance(factor, values)
        seen.append({"T": factor.prior().matrix(), "R": covariance, "d2": result.d2})
        return result

    run_graph.chi2_gate_isam2 = watched
    try:
        if cli_main(argv) not in (0, None):
            raise SystemExit(f"the run failed: {' '.join(argv)}")
    finally:
        run_graph.chi2_gate_isam2 = gate
    return seen


def case_figures(seen: list[dict], run_dir: Path) -> dict:
    """The corrections' errors against the run's ground truth (matched by stamp through
    corrections.csv's gated rows) and their figures."""
    rows = [r for r in csv.DictReader((run_dir / "corrections.csv").open(newline=""))
            if r["gate_d2"] not in ("", "nan")]
    if len(rows) != len(seen):
        raise SystemExit(f"{run_dir}: {len(rows)} gated rows against {len(seen)} gate calls")
    stamps, T_gt = read_tum_trajectory(run_dir / "groundtruth.txt")
    errors, nees = [], []
    for row, s in zip(rows, seen):
        k = int(np.argmin(np.abs(stamps - float(row["timestamp"]))))
        e = log_se3(inv_T(T_gt[k]) @ s["T"])  # GTSAM order [rot, trans], right perturbation
        errors.append(e)
        nees.append(float(e @ np.linalg.solve(s["R"], e)))
    E = np.asarray(errors)
    sigma = np.sqrt(np.array([np.diag(s["R"]) for s in seen]))
    return {"corrections": len(seen), "gate_d2": spread([s["d2"] for s in seen], STATS),
            "nees_against_ground_truth": spread(nees, STATS),
            "error_rms_mrad_mm": dict(zip(AXES, np.round(np.sqrt((E**2).mean(axis=0)) * 1e3, 2).tolist())),
            "sigma_median_mrad_mm": dict(zip(AXES, np.round(np.median(sigma, axis=0) * 1e3, 2).tolist())),
            "lag1_correlation": dict(zip(AXES, [round(float(np.corrcoef(E[:-1, a], E[1:, a])[0, 1]), 2)
                                               for a in range(6)]))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--case", action="append", required=True, metavar="NAME,TRAJ,DATA,FRAMES,FIELD",
                    help="a run: its name, source, recording, frames and a field posed by its ground truth")
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    cases = {}
    for text in args.case:
        name, traj, data, frames, field = text.split(",")
        out = args.work / name
        shutil.rmtree(out, ignore_errors=True)
        seen = gated_corrections(["run", "--traj", traj, "--data", data, "--frames", frames, "--field", field,
                                  "--odom", "vo", "--out", str(out)])
        cases[name] = {"traj": traj, "data": data, "frames": frames, "field": field,
                       **case_figures(seen, out / "latest")}
        c = cases[name]
        print(f"{name}: gate d2 median {c['gate_d2']['median']}; NEES against the ground truth median "
              f"{c['nees_against_ground_truth']['median']}, mean {c['nees_against_ground_truth']['mean']}; lag-1 "
              f"correlation {c['lag1_correlation']}")
    write_result(args.out, {"cases": cases}, args)


if __name__ == "__main__":
    main()
