"""Is the visual odometry's covariance consistent over a keyframe interval? (issue 62)

The run's gate compares each correction with the graph's prediction, whose covariance is the
odometry's over the interval since the last keyframe: its steps' covariances chained
(``conventions.compose_covariance``, as ``run.motion`` does) plus the drift model
(``PipelineConfig.drift_covariance``). The fault benchmark's clean fr1/desk run reads "too
cautious" (median d2 0.36 against a chi-square band from 0.87). This measures, on recordings
with ground truth, the NEES (e^T C^-1 e, 6 dof: median 5.35 when consistent) of the odometry
against the ground truth over intervals of 1, 2, 3, 5 (the default keyframe interval) and 10
frames, for the chained step covariances alone and with the drift model, with spread; and for
the steps chained as if a share of each step's covariance were its frames' own registration
noise (:func:`frame_noise_chain`), a model of why the chain is too cautious; and as the run
chains them since 4283ecb (:class:`~nap3d_graph.motion.interval.IntervalCovariance`: each
step's disagreement with constant velocity taken as its frames' own noise), alone and with the
drift model.

    nap3d-graph simulate /tmp/sim_walk30 --count 300 --path traverse --scene-seed 3 --seed 2
    python benchmarks/odometry_consistency.py --data /tmp/sim_walk30 ../shared/data/tum/rgbd_dataset_freiburg1_desk \
        ../shared/data/7scenes/redkitchen ../shared/data/tum/rgbd_dataset_freiburg1_xyz \
        --out benchmarks/results/odometry_consistency.json

No setting is chosen from it: it says where the prediction's covariance is too large. The
interval model was chosen by these recordings' figures (the simulated walk, fr1/desk, the
kitchen's first 500 frames, the fr1/xyz frames), so it is named as their tuning data.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from provenance import write_result
from scoring import spread

from nap3d_graph.conventions import compose_covariance, inv_T, log_se3
from nap3d_graph.datasets import open_sequence
from nap3d_graph.motion.interval import IntervalCovariance
from nap3d_graph.motion.odometry import VisualOdometry
from nap3d_graph.run.config import PipelineConfig

INTERVALS = (1, 2, 3, 5, 10)
CHI2_6_MEDIAN = 5.348
STATS = ("median", "p10", "p90")


def odometry_steps(sequence, width: int) -> list:
    """The feature odometry's increments over the whole recording (frame i-1 -> i)."""
    odometry = VisualOdometry(width=width)
    odometry.prime(sequence[0])
    return [odometry.increment(i, sequence[i]) for i in range(1, len(sequence))]


def frame_noise_chain(steps, share: float) -> np.ndarray:
    """(6, 6) the covariance of ``steps`` chained as if ``share`` of each step's covariance were
    its two frames' own registration noise (half each), which a chain of steps cancels inside
    (a frame's error enters the step into it and the step out of it with opposite signs) and
    keeps only at its two ends, and the rest a walk that adds up step by step. ``share`` 0: the
    steps' covariances chained as independent (what the run does)."""
    walk, first = np.zeros((6, 6)), share / 2 * steps[0].covariance
    for k, step in enumerate(steps):
        walk = compose_covariance(walk, step.T_prev_cur, (1.0 - share) * step.covariance)
        if k:  # the first frame's noise carried to the interval's end frame
            first = compose_covariance(first, step.T_prev_cur, np.zeros((6, 6)))
    return walk + first + share / 2 * steps[-1].covariance


def interval_nees(sequence, steps, n: int, config: PipelineConfig, shares=()) -> dict:
    """NEES over non-overlapping intervals of ``n`` frames: chained step covariances alone and
    with the drift model; the error's norm (mm, mrad) against the covariance's per-axis sigma;
    for each of ``shares``, the NEES of the steps chained by :func:`frame_noise_chain` (alone)."""
    T_gt, stamps = np.asarray(sequence.T_world_cam_gt), np.asarray(sequence.timestamps)
    alone, with_drift, err_mm, sigma_mm, err_mrad, sigma_mrad = [], [], [], [], [], []
    run_alone, run_with_drift = [], []
    by_share: dict[float, list] = {f: [] for f in shares}
    for a in range(0, len(steps) - n + 1, n):
        if not (np.isfinite(T_gt[a]).all() and np.isfinite(T_gt[a + n]).all()):
            continue
        T, C, interval = np.eye(4), np.zeros((6, 6)), IntervalCovariance()
        for step in steps[a:a + n]:
            T, C = T @ step.T_prev_cur, compose_covariance(C, step.T_prev_cur, step.covariance)
            interval.add(step.T_prev_cur, step.covariance, step.frame_noise)
        drift = config.drift_covariance(T, float(stamps[a + n] - stamps[a]))
        D = C + drift
        e = log_se3(inv_T(inv_T(T_gt[a]) @ T_gt[a + n]) @ T)
        for f in shares:
            by_share[f].append(float(e @ np.linalg.solve(frame_noise_chain(steps[a:a + n], f), e)))
        alone.append(float(e @ np.linalg.solve(C, e)))
        run_alone.append(float(e @ np.linalg.solve(interval.value, e)))
        run_with_drift.append(float(e @ np.linalg.solve(interval.value + drift, e)))
        with_drift.append(float(e @ np.linalg.solve(D, e)))
        err_mm.append(1e3 * float(np.linalg.norm(e[3:])) / np.sqrt(3))
        sigma_mm.append(1e3 * float(np.sqrt(np.trace(D[3:, 3:]) / 3)))
        err_mrad.append(1e3 * float(np.linalg.norm(e[:3])) / np.sqrt(3))
        sigma_mrad.append(1e3 * float(np.sqrt(np.trace(D[:3, :3]) / 3)))
    figures = {"nees_steps_alone": alone, "nees_with_drift": with_drift, "nees_run_interval_alone": run_alone,
               "nees_run_interval_with_drift": run_with_drift, "error_mm_per_axis": err_mm,
               "sigma_mm_per_axis": sigma_mm, "error_mrad_per_axis": err_mrad, "sigma_mrad_per_axis": sigma_mrad}
    return {"frames": n, **{name: spread(v, STATS) for name, v in figures.items()},
            "nees_by_frame_share": {str(f): spread(v, STATS) for f, v in by_share.items()}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, nargs="+", required=True, help="recordings with ground truth")
    ap.add_argument("--width", type=int, default=320, help="the odometry's width (the run's --vo-width at pace)")
    ap.add_argument("--frame-shares", type=float, nargs="*", default=[0.0, 0.2, 0.4, 0.6, 0.8],
                    help="shares of a step's covariance taken as its frames' own noise (frame_noise_chain)")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    config = PipelineConfig()
    recordings = {}
    for path in args.data:
        sequence = open_sequence(path)
        steps = odometry_steps(sequence, args.width)
        rows = [interval_nees(sequence, steps, n, config, args.frame_shares) for n in INTERVALS if n < len(steps)]
        recordings[path.name] = {"frames": len(sequence), "steps_without_features": sum(not s.ok for s in steps),
                                 "intervals": rows}
        for r in rows:
            print(f"{path.name} {r['frames']:2d} frames: NEES alone {r['nees_steps_alone']['median']:.2f}, "
                  f"with drift {r['nees_with_drift']['median']:.2f}; as the run chains them "
                  f"{r['nees_run_interval_alone']['median']:.2f}, with drift "
                  f"{r['nees_run_interval_with_drift']['median']:.2f} (consistent: {CHI2_6_MEDIAN}); error "
                  f"{r['error_mm_per_axis']['median']:.1f} mm against sigma {r['sigma_mm_per_axis']['median']:.1f}; "
                  "by frame share " + ", ".join(f"{f}: {v['median']:.2f}" for f, v in r["nees_by_frame_share"].items()))
    write_result(args.out, {"width": args.width, "keyframe_every": config.keyframe_every,
                            "chi2_6_median": CHI2_6_MEDIAN, "recordings": recordings}, args)


if __name__ == "__main__":
    main()
