"""Time per step of every estimator at 1,000 and 10,000 frames (odometry and IMU paths).

Each estimator runs over a synthetic measurement stream (``nap3d_graph.estimators.synthetic``:
a figure-of-eight walk at 15 Hz, a keyframe with a NAP3D-like correction every 5 frames,
odometry and corrections drawn from their stated covariances; on the IMU path the
simulator's 200 Hz IMU with its biases). Reported per estimator: mean, median, p99 and max
time per frame step (ms), the time of the solve after the last frame (s), and, as a check
that the fast ones are not fast by doing nothing, the ATE and the NEES at keyframes.

    python benchmarks/estimators.py [--frames 1000 10000] [--out benchmarks/results/estimators_timing.json]
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import numpy as np
from provenance import write_result


def bench(frames: int, imu: bool, seed: int) -> dict:
    from nap3d_graph.estimators import default_estimators, run_estimator
    from nap3d_graph.estimators.synthetic import synthetic_stream
    from nap3d_graph.evaluation.compare import comparison_rows

    started = time.perf_counter()
    stream = synthetic_stream(frames, seed=seed, imu=imu)
    made_s = time.perf_counter() - started
    out = {"stream_seconds": made_s, "keyframes": len(stream.keyframes), "estimators": {}}
    for estimator in default_estimators(stream):
        started = time.perf_counter()
        result = run_estimator(estimator, stream)
        total = time.perf_counter() - started
        steps = result.step_seconds[1:] * 1000.0
        rows = {r["estimator"]: r for r in comparison_rows(stream, [result])}
        out["estimators"][estimator.name] = {
            "step_ms_mean": float(steps.mean()), "step_ms_median": float(np.median(steps)),
            "step_ms_p99": float(np.percentile(steps, 99)), "step_ms_max": float(steps.max()),
            "final_s": float(result.final_seconds), "total_s": total,
            "rows": {name: {"ate_rmse_m": r["ate_rmse_m"], "nees_mean": r["nees_mean"]} for name, r in rows.items()},
        }
        print(f"{frames:6d} frames {'imu' if imu else 'odometry':8s} {estimator.name:14s} "
              f"{steps.mean():7.3f} ms/step mean, p99 {np.percentile(steps, 99):7.3f}, max {steps.max():7.2f}; "
              f"final {result.final_seconds:7.3f} s; total {total:6.1f} s", flush=True)
    return out


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, nargs="+", default=[1000, 10000])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/estimators_timing.json"))
    args = p.parse_args(argv)
    result = {"machine": {"cpu": platform.processor() or platform.machine(), "python": platform.python_version()},
              "fps": 15.0, "keyframe_every": 5, "runs": {}}
    for frames in args.frames:
        for imu in (False, True):
            result["runs"][f"{frames}_{'imu' if imu else 'odometry'}"] = bench(frames, imu, args.seed)
    write_result(args.out, result, args)


if __name__ == "__main__":
    main()
