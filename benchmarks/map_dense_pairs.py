"""Would a dense refinement make a finished survey better than its bundle adjustment?
(issue 48, item 2: "align every keyframe's depth and colour with its covisible keyframes").

For each map given, every pair of keyframes within ``--max-distance`` / ``--max-angle`` of
each other at the map's (bundle-adjusted) poses is aligned by OpenCV 5's dense RGB-D
odometry (``cv2.Odometry``: photometric ``rgb``, depth ICP ``icp``, both ``rgbd``, the
methods of DVO and KinectFusion) at ``--width`` px, started from the map's relative pose.
A pair is kept when the solve converges within ``--gate-m`` / ``--gate-deg`` of that start.
The kept pairs are then solved as a pose graph (GTSAM, Huber) with the map's consecutive
relative poses as a weaker backbone, and the keyframes' ATE (SE(3)-aligned) compared with
the map's own. The ground truth is read only to score; nothing is tuned on it.

    python benchmarks/map_dense_pairs.py --map /tmp/anywhere/survey_first/map \\
        --map /tmp/anywhere/survey_second/map --out benchmarks/results/map_dense_pairs_fr1_desk.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from provenance import write_result

from nap3d_graph.conventions import T_to_pose3, inv_T, pose3_to_T, pose_error

KINDS = ("rgb", "icp", "rgbd")


def _gray(rgb: np.ndarray) -> np.ndarray:
    import cv2

    rgb = rgb if rgb.dtype == np.uint8 else np.clip(np.asarray(rgb) * 255.0, 0, 255).astype(np.uint8)
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)


def dense_pairs(frames, T_map_key: np.ndarray, pairs, kind: str, gate: tuple[float, float]) -> dict:
    """Each pair (a, b) aligned densely from the map's ``T_b_a``: {(a, b): T_b_a} of those kept,
    and the counts of converged and gated."""
    import cv2

    otype = {"rgb": cv2.OdometryType_RGB, "icp": cv2.OdometryType_DEPTH, "rgbd": cv2.OdometryType_RGB_DEPTH}[kind]
    settings = cv2.OdometrySettings()
    settings.setCameraMatrix(frames[0].intrinsics.K.astype(np.float32))
    odometry = cv2.Odometry(otype, settings, cv2.OdometryAlgoType_COMMON)
    kept, converged = {}, 0
    for a, b in pairs:
        src, dst = (cv2.OdometryFrame(np.nan_to_num(f.depth_m).astype(np.float32), _gray(f.rgb))
                    for f in (frames[a], frames[b]))
        odometry.prepareFrames(src, dst)
        T_start = inv_T(T_map_key[b]) @ T_map_key[a]
        try:
            ok, T = odometry.compute(src, dst, T_start.copy())
        except cv2.error:
            continue
        if not ok or not np.all(np.isfinite(T)):
            continue
        converged += 1
        moved_m, turned_deg = pose_error(np.asarray(T), T_start)
        if moved_m <= gate[0] and turned_deg <= gate[1]:
            kept[(a, b)] = np.asarray(T, dtype=float)
    return {"kept": kept, "converged": converged}


def resolve(T_map_key: np.ndarray, kept: dict, sigma_m: float, sigma_deg: float) -> np.ndarray:
    """Keyframe poses (K, 4, 4) from the dense pairs (sigma_m, sigma_deg) and the map's
    consecutive relative poses (three times looser), gauge at the first keyframe."""
    import gtsam

    def noise(m, deg):
        base = gtsam.noiseModel.Diagonal.Sigmas(np.array([np.radians(deg)] * 3 + [m] * 3))
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(1.345), base)

    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for (a, b), T_b_a in kept.items():
        graph.add(gtsam.BetweenFactorPose3(a, b, T_to_pose3(inv_T(T_b_a)), noise(sigma_m, sigma_deg)))
    backbone = noise(3 * sigma_m, 3 * sigma_deg)
    for a in range(len(T_map_key) - 1):
        graph.add(gtsam.BetweenFactorPose3(a, a + 1, T_to_pose3(inv_T(T_map_key[a]) @ T_map_key[a + 1]), backbone))
    graph.add(gtsam.PriorFactorPose3(0, T_to_pose3(T_map_key[0]), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    for i, T in enumerate(T_map_key):
        values.insert(i, T_to_pose3(T))
    result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    return np.stack([pose3_to_T(result.atPose3(i)) for i in range(len(T_map_key))])


def one_map(map_dir: Path, args) -> dict:
    from nap3d_graph.datasets import open_sequence
    from nap3d_graph.evaluation.alignment import aligned_errors
    from nap3d_graph.nap3d.correct import at_width

    info = json.loads((map_dir / "map.json").read_text())
    start, stop = info["frame_range"]
    sequence = open_sequence(info["data"], frames=f"{start}:{stop}")
    with np.load(map_dir / "keyframes.npz") as data:
        keys = data["indices"]
    T_map_key = np.load(map_dir / "keyframe_poses.npy")
    frames = [at_width(sequence[int(i)], args.width) for i in keys]
    pairs = [(a, b) for a in range(len(keys)) for b in range(a + 1, len(keys))
             if (lambda e: e[0] <= args.max_distance and e[1] <= args.max_angle)(pose_error(T_map_key[a], T_map_key[b]))]
    T_gt = np.asarray(sequence.T_world_cam_gt)[keys]  # scoring only, after every pose is made
    stamps = np.asarray(sequence.timestamps)[keys]

    def rel_error(T_b_a: np.ndarray, a: int, b: int) -> tuple[float, float]:
        return pose_error(T_b_a, inv_T(T_gt[b]) @ T_gt[a])

    out = {"map": str(map_dir), "data": info["data"], "frame_range": [start, stop], "keyframes": len(keys),
           "pairs": len(pairs), "keyframe_ate_map_m": aligned_errors(stamps, T_gt, T_map_key).rmse_m, "kinds": {}}
    for kind in KINDS:
        t0 = time.perf_counter()
        got = dense_pairs(frames, T_map_key, pairs, kind, (args.gate_m, args.gate_deg))
        seconds = time.perf_counter() - t0
        kept = got["kept"]
        dense_err = np.array([rel_error(T, a, b) for (a, b), T in kept.items()]).reshape(-1, 2)
        map_err = np.array([rel_error(inv_T(T_map_key[b]) @ T_map_key[a], a, b) for a, b in kept]).reshape(-1, 2)
        T_new = resolve(T_map_key, kept, args.sigma_m, args.sigma_deg) if kept else T_map_key
        out["kinds"][kind] = {
            "converged": got["converged"], "kept": len(kept), "seconds": round(seconds, 2),
            "pair_error_dense_median_cm": float(np.median(dense_err[:, 0]) * 100) if len(kept) else None,
            "pair_error_dense_median_deg": float(np.median(dense_err[:, 1])) if len(kept) else None,
            "pair_error_map_median_cm": float(np.median(map_err[:, 0]) * 100) if len(kept) else None,
            "pair_error_map_median_deg": float(np.median(map_err[:, 1])) if len(kept) else None,
            "keyframe_ate_resolved_m": aligned_errors(stamps, T_gt, T_new).rmse_m}
        print(f"{map_dir} {kind}: {len(kept)}/{len(pairs)} kept, keyframe ATE {out['keyframe_ate_map_m'] * 100:.2f} -> "
              f"{out['kinds'][kind]['keyframe_ate_resolved_m'] * 100:.2f} cm")
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--map", type=Path, action="append", required=True, help="a map folder (repeat for more)")
    parser.add_argument("--width", type=int, default=320, help="working width of the dense alignment (px)")
    parser.add_argument("--max-distance", type=float, default=0.4, help="pairs within this distance (m)")
    parser.add_argument("--max-angle", type=float, default=25.0, help="pairs within this angle (deg)")
    parser.add_argument("--gate-m", type=float, default=0.05)
    parser.add_argument("--gate-deg", type=float, default=3.0)
    parser.add_argument("--sigma-m", type=float, default=0.003)
    parser.add_argument("--sigma-deg", type=float, default=0.3)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    maps = [one_map(m, args) for m in args.map]
    write_result(args.out, {"maps": maps}, args)


if __name__ == "__main__":
    main()
