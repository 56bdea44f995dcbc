"""Alignment speed: milliseconds per NAP3D stage, and RANSAC-Procrustes alone.

    python benchmarks/alignment.py [--out benchmarks/results/alignment.json] [--repeats 5]

Stages at 640x480 and 320x240 on the simulated hold-out room with the oracle field at a
+-10 cm / +-5 deg perturbation: SIFT on both images, FLANN matching, back-projection,
RANSAC, refinement + covariance; and RANSAC-Procrustes on 1,000 correspondences with
exactly 500 hypotheses (target <= 5 ms on the 2-core reference CPU).
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import numpy as np
from provenance import write_result


def stage_timings(width: int, height: int, repeats: int) -> dict:
    from nap3d_graph.evaluation.perturb import random_perturbation
    from nap3d_graph.nap3d.align import align_correspondences, view_features
    from nap3d_graph.nap3d.config import AlignConfig
    from nap3d_graph.nap3d.correspondences import build_correspondences
    from nap3d_graph.nap3d.matching import detect_features, match_features
    from nap3d_graph.sims.scene import OracleField, make_scene
    from nap3d_graph.sims.sensors import sensor_frame
    from nap3d_graph.sims.sequence import default_intrinsics
    from nap3d_graph.sims.trajectories import make_trajectory

    scene = make_scene(11)
    field = OracleField(scene)
    K = default_intrinsics(width, height)
    traj = make_trajectory("traverse", scene, np.random.default_rng(0), 20.0)
    rng = np.random.default_rng(1)
    config = AlignConfig()
    rows = []
    for i in range(repeats):
        T_world_cam_gt = traj.T_world_cam(2.0 + 16.0 * i / max(repeats - 1, 1))
        frame = sensor_frame(scene, T_world_cam_gt, K, rng)
        view = field.render(T_world_cam_gt @ random_perturbation(rng), K)
        t = {}
        t0 = time.perf_counter()
        fr = detect_features(frame.rgb, matcher=config.matcher)
        fv = view_features(view, config)
        t["detect_both_ms"] = (time.perf_counter() - t0) * 1e3
        t0 = time.perf_counter()
        matches = match_features(fr, fv, ratio=config.ratio, nn_search=config.nn_search)
        t["match_ms"] = (time.perf_counter() - t0) * 1e3
        t0 = time.perf_counter()
        corr = build_correspondences(frame, view, matches, config)
        t["backproject_ms"] = (time.perf_counter() - t0) * 1e3
        timings: dict = {}
        a = align_correspondences(corr, K, config, timings)
        t["ransac_ms"] = timings.get("ransac", np.nan) * 1e3
        t["refine_covariance_ms"] = timings.get("refine", np.nan) * 1e3
        t["matches"] = len(matches)
        t["inliers"] = a.num_inliers
        rows.append(t)
    return {k: float(np.median([r[k] for r in rows])) for k in rows[0]}


def ransac_only(n: int = 1000, hypotheses: int = 500, repeats: int = 20) -> dict:
    from scipy.spatial.transform import Rotation

    from nap3d_graph.nap3d.config import AlignConfig
    from nap3d_graph.nap3d.ransac import ransac_procrustes

    rng = np.random.default_rng(0)
    x = rng.uniform([-1.5, -1, 1], [1.5, 1, 4], size=(n, 3))
    R = Rotation.from_rotvec([0.02, -0.05, 0.03]).as_matrix()
    y = x @ R.T + [0.05, -0.03, 0.08] + rng.normal(size=(n, 3)) * 0.003
    out = rng.random(n) < 0.3
    y[out] += rng.normal(size=(out.sum(), 3)) * 0.3
    s = np.full(n, 0.004)
    # Exactly `hypotheses` hypotheses: one batch, no adaptive early stop.
    config = AlignConfig(ransac_max_iterations=hypotheses, ransac_batch=hypotheses, ransac_confidence=1.0)
    ransac_procrustes(x, y, np.ones(n), s, s, config)  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        res = ransac_procrustes(x, y, np.ones(n), s, s, config)
        times.append((time.perf_counter() - t0) * 1e3)
    return {"correspondences": n, "hypotheses": res.iterations, "median_ms": float(np.median(times)),
            "min_ms": float(np.min(times)), "target_ms": 5.0}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/alignment.json"))
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    result = {"machine": platform.processor() or platform.machine(), "ransac_1000x500": ransac_only()}
    for w, h in ((640, 480), (320, 240)):
        result[f"stages_{w}x{h}"] = stage_timings(w, h, args.repeats)
    print(f"RANSAC-Procrustes, 1000 correspondences x 500 hypotheses: {result['ransac_1000x500']['median_ms']:.2f} ms "
          f"(target <= 5 ms)")
    for key in ("stages_640x480", "stages_320x240"):
        st = result[key]
        print(f"{key}: " + ", ".join(f"{k} {v:.1f}" for k, v in st.items()))
    write_result(args.out, result, args)


if __name__ == "__main__":
    main()
