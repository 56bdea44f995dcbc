"""Pipeline latency: per-keyframe time by stage, and iSAM2 update time at 1,000 and 5,000 poses.

    python benchmarks/pipeline.py [--field oracle|FIELD.pt] [--out benchmarks/results/pipeline.json]

Stages (median seconds per keyframe) on the default room's traversal at a 320x240 render:
render, SIFT, FLANN, RANSAC, refinement, gate, iSAM2 update; aim <= 0.5 s per keyframe on
the 2-core reference CPU. Then a synthetic odometry chain with a NAP3D-like prior every 5th
pose is grown to 5,000 poses in iSAM2 (the pipeline's parameters) and the update time of one
keyframe (between factor + prior) is measured around 1,000 and 5,000 poses; aim < 5 ms.
"""

from __future__ import annotations

import argparse
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
from provenance import write_result


def keyframe_latency(field_arg: str, frames: int, iterations: int) -> dict:
    from nap3d_graph.datasets import open_sequence
    from nap3d_graph.fields import resolve_field
    from nap3d_graph.motion.odometry import make_odometry
    from nap3d_graph.run.config import PipelineConfig
    from nap3d_graph.run.output import keyframe_timing_summary
    from nap3d_graph.run.pipeline import Pipeline
    from nap3d_graph.sims.sequence import SimConfig, simulate_sequence

    with tempfile.TemporaryDirectory() as tmp:
        path = simulate_sequence(Path(tmp) / "walk", SimConfig(frames=frames, scene_seed=0, seed=2, width=640,
                                                               height=480))
        seq = open_sequence(path)
        field = resolve_field(field_arg, seq)
        config = PipelineConfig(keyframe_every=5, correction_iterations=iterations, render_width=320,
                                render_height=240)
        result = Pipeline(seq, field, make_odometry("recorded", seq), config).run()
    summary = keyframe_timing_summary(result)
    summary["keyframes"] = len(result.keyframes)
    summary["accepted"] = result.num_accepted
    summary["correction_iterations"] = iterations
    return summary


def isam_scaling(sizes=(1000, 5000), prior_every: int = 5, samples: int = 50) -> dict:
    import gtsam
    from gtsam.symbol_shorthand import X

    from nap3d_graph.conventions import exp_se3
    from nap3d_graph.factors import nap3d_prior_factor, odometry_factor, pose_prior_factor
    from nap3d_graph.results import Correction

    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(1e-3)  # as the pipeline
    params.relinearizeSkip = 10
    isam = gtsam.ISAM2(params)
    rng = np.random.default_rng(0)
    step = exp_se3([0, 0, 0.01, 0.1, 0, 0])
    cov_odom = np.diag([1e-4] * 3 + [1e-4] * 3)
    cov_nap3d = np.diag([1e-6] * 3 + [4e-6] * 3)
    T = np.eye(4)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(pose_prior_factor(X(0), T, rot_sigma_rad=1e-3, trans_sigma_m=1e-3))
    values.insert(X(0), gtsam.Pose3(T))
    isam.update(graph, values)
    timings: dict[int, list[float]] = {n: [] for n in sizes}
    with_marginal: dict[int, list[float]] = {n: [] for n in sizes}
    for k in range(1, max(sizes) + 1):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        noisy = step @ exp_se3(rng.normal(size=6) * 1e-3)
        graph.add(odometry_factor(X(k - 1), X(k), noisy, cov_odom))
        T = T @ step
        values.insert(X(k), gtsam.Pose3(T @ exp_se3(rng.normal(size=6) * 1e-3)))
        if k % prior_every == 0:
            c = Correction(T, T @ exp_se3(rng.normal(size=6) * 1e-3), cov_nap3d, None, 1, True)
            graph.add(nap3d_prior_factor(X(k), None, c))
        t0 = time.perf_counter()
        isam.update(graph, values)
        isam.calculateEstimatePose3(X(k))
        dt = time.perf_counter() - t0
        isam.marginalCovariance(X(k))  # the pipeline's gate needs it
        dt_marginal = time.perf_counter() - t0
        for n in sizes:
            if n - samples < k <= n:
                timings[n].append(dt)
                with_marginal[n].append(dt_marginal)
    out = {f"update_ms_at_{n}_poses": float(np.median(v) * 1e3) for n, v in timings.items()}
    out |= {f"update_and_marginal_ms_at_{n}_poses": float(np.median(v) * 1e3) for n, v in with_marginal.items()}
    return out | {"target_ms": 5.0}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--field", default="oracle", help="'oracle' or a field checkpoint of the default room")
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--iterations", type=int, default=1, help="correction rounds per keyframe (the pipeline default)")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/pipeline.json"))
    args = parser.parse_args()
    result = {"machine": platform.processor() or platform.machine(), "field": args.field}
    result["per_keyframe_s"] = keyframe_latency(args.field, args.frames, args.iterations)
    result["isam2"] = isam_scaling()
    per = result["per_keyframe_s"]
    print("per keyframe (median s): " + ", ".join(f"{k} {v:.4f}" for k, v in per.items() if isinstance(v, float)))
    print(f"  total {per.get('total_per_keyframe', float('nan')):.3f} s (aim <= 0.5 s at 320x240)")
    print("iSAM2 update: " + ", ".join(f"{k} {v:.2f}" for k, v in result["isam2"].items()))
    write_result(args.out, result, args)


if __name__ == "__main__":
    main()
