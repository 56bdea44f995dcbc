"""Is the NAP3D covariance honest where it is used? NEES per configuration, method and block.

On simulated rooms that neither the tests (room 11) nor the covariance calibration (rooms 21
and 22) used, with the exact field and sensor noise, ``--trials`` random poses per room and
configuration are corrected and the normalised estimation error squared of the corrected
pose is computed with its covariance, for the 6-dof pose and for each 3-dof block:

* ``pipeline``: one render-align round at 320x240, the estimate +-3 cm / 1.5 deg off (the
  odometry's prediction at a keyframe), refined and the paper's plain method;
* ``eval-k``: one round at 640x480, +-10 cm / 5 deg (Evaluation K's perturbation), both
  methods;
* ``iterated``: ``correct_pose`` with up to 3 rounds at 320x240, +-10 cm / 5 deg, refined.

A consistent covariance gives a mean NEES of 6 (pose) and 3 (each block); the 95% band of the
mean over the trials is printed beside it. Writes JSON.

    python benchmarks/covariance.py [--rooms 31 32 33] [--trials 100] \
        [--matcher sift|xfeat|xfeat-lighterglue] [--out benchmarks/results/covariance.json]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from provenance import write_result

CONFIGS = {
    "pipeline": dict(size=(320, 240), rounds=1, max_trans_m=0.03, max_rot_deg=1.5, methods=("refined", "plain")),
    "eval-k": dict(size=(640, 480), rounds=1, max_trans_m=0.10, max_rot_deg=5.0, methods=("refined", "plain")),
    "iterated": dict(size=(320, 240), rounds=3, max_trans_m=0.10, max_rot_deg=5.0, methods=("refined",)),
}


def nees_trials(room: int, settings: dict, method: str, trials: int, seed: int, matcher: str = "sift") -> dict:
    from nap3d_graph import correct_pose
    from nap3d_graph.conventions import inv_T, log_se3
    from nap3d_graph.evaluation.perturb import random_perturbation
    from nap3d_graph.nap3d.config import AlignConfig
    from nap3d_graph.sims.scene import OracleField, make_scene
    from nap3d_graph.sims.sensors import sensor_frame
    from nap3d_graph.sims.sequence import default_intrinsics
    from nap3d_graph.sims.trajectories import make_trajectory

    scene = make_scene(room)
    field = OracleField(scene)
    K = default_intrinsics(*settings["size"])
    traj = make_trajectory("traverse", scene, np.random.default_rng(seed), 20.0)
    rng = np.random.default_rng(seed + 1)
    config = AlignConfig(method=method, matcher=matcher)
    values, failures = [], 0
    while len(values) < trials:
        T_world_cam_gt = traj.T_world_cam(rng.uniform(0, 20))
        frame = sensor_frame(scene, T_world_cam_gt, K, rng)
        T_world_cam_est = T_world_cam_gt @ random_perturbation(rng, settings["max_trans_m"], settings["max_rot_deg"])
        c = correct_pose(frame, field, T_world_cam_est, iterations=settings["rounds"], config=config)
        if not c.success:
            failures += 1
            continue
        e = log_se3(inv_T(c.T_world_cam_corrected) @ T_world_cam_gt)
        P = c.covariance
        values.append([e @ np.linalg.solve(P, e), e[:3] @ np.linalg.solve(P[:3, :3], e[:3]),
                       e[3:] @ np.linalg.solve(P[3:, 3:], e[3:]), np.linalg.norm(e[3:])])
    a = np.array(values)
    return {"trials": trials, "failures_skipped": failures, "nees_pose": float(a[:, 0].mean()),
            "nees_rotation": float(a[:, 1].mean()), "nees_translation": float(a[:, 2].mean()),
            "nees_pose_median": float(np.median(a[:, 0])), "trans_err_median_mm": float(np.median(a[:, 3]) * 1000)}


def main(argv=None) -> None:
    from scipy.stats import chi2

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rooms", type=int, nargs="+", default=[31, 32, 33])
    p.add_argument("--trials", type=int, default=100)
    p.add_argument("--configs", nargs="+", default=list(CONFIGS), choices=list(CONFIGS))
    p.add_argument("--matcher", default="sift", choices=("sift", "xfeat", "xfeat-lighterglue"))
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/covariance.json"))
    args = p.parse_args(argv)
    result = {"rooms": args.rooms, "trials_per_room": args.trials, "matcher": args.matcher, "per_room": {},
              "pooled": {}}
    for name in args.configs:
        settings = CONFIGS[name]
        for method in settings["methods"]:
            key = f"{name}/{method}"
            rows = []
            for room in args.rooms:
                r = nees_trials(room, settings, method, args.trials, seed=room, matcher=args.matcher)
                result["per_room"].setdefault(key, {})[room] = r
                rows.append(r)
                print(f"{key:18s} room {room}: NEES pose {r['nees_pose']:.2f} rotation {r['nees_rotation']:.2f} "
                      f"translation {r['nees_translation']:.2f} (median error {r['trans_err_median_mm']:.2f} mm)",
                      flush=True)
            n = args.trials * len(args.rooms)
            pooled = {block: float(np.mean([r[f"nees_{block}"] for r in rows]))
                      for block in ("pose", "rotation", "translation")}
            bands = {block: [float(v) for v in chi2.ppf([0.025, 0.975], dof * n) / n]
                     for block, dof in (("pose", 6), ("rotation", 3), ("translation", 3))}
            spread = {block: [float(min(r[f"nees_{block}"] for r in rows)), float(max(r[f"nees_{block}"] for r in rows))]
                      for block in ("pose", "rotation", "translation")}
            result["pooled"][key] = {"mean": pooled, "band_95": bands, "room_min_max": spread,
                                     "settings": {k: v for k, v in settings.items() if k != "methods"}}
            print(f"{key:18s} pooled: " + ", ".join(f"{b} {pooled[b]:.2f} [{bands[b][0]:.2f}, {bands[b][1]:.2f}]"
                                                      for b in pooled), flush=True)
    write_result(args.out, result, args)


if __name__ == "__main__":
    main()
