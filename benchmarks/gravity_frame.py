"""Gravity in a field's frame that is not z-up, refined in the IMU run's graph.

Simulated walks (several seeds and rooms), each mapped into a frame F turned away from the
simulator's z-up world (90 deg about x: a y-down room; 30 deg about a tilted axis), run with
``--odom imu`` on the exact field, four ways: gravity as the true vector; from the
accelerometer over the first 0.5 s (``--gravity auto``), refined by the graph (the default
behaviour); the same start held fixed (``gravity_sigma_deg`` ~ 0: what the run did before
gravity was refined); and z-up assumed. Per walk: the accelerometer's and the refined
gravity's angle to the truth, ATE and accepted corrections.

    python benchmarks/gravity_frame.py [--seeds 6] [--out benchmarks/results/gravity_frame.json]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
from provenance import write_result


def turned(axis, angle_deg: float) -> np.ndarray:
    """``T_F_W`` (4, 4): a turn by angle_deg about axis, with an offset."""
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians(angle_deg) * np.asarray(axis, float) / np.linalg.norm(axis)).as_matrix()
    T[:3, 3] = [0.3, 0.1, -0.2]
    return T


FRAMES = {"y_down_90deg_about_x": turned([1, 0, 0], 90.0), "30deg_about_xy": turned([1, 1, 0], 30.0)}


def run_walk(seed: int, T_F_W: np.ndarray, folder: Path) -> dict:
    from nap3d_graph.conventions import pose_error
    from nap3d_graph.datasets import SimSequence
    from nap3d_graph.motion.imu import ImuConfig, estimate_gravity, gravity_angle_deg
    from nap3d_graph.run.config import PipelineConfig
    from nap3d_graph.run.imu import ImuOdometry
    from nap3d_graph.run.pipeline import Pipeline
    from nap3d_graph.sims.reframe import FieldInFrame, SequenceInFrame
    from nap3d_graph.sims.sequence import SimConfig, simulate_sequence

    path = folder / f"walk_{seed}"
    if not path.exists():
        simulate_sequence(path, SimConfig(frames=40, fps=10.0, width=160, height=120, scene_seed=11 + seed,
                                          seed=4 + seed, timing=None))
    walk = SimSequence(path)
    seq, field = SequenceInFrame(walk, T_F_W), FieldInFrame(walk.oracle_field(), T_F_W)
    g_true = T_F_W[:3, :3] @ np.array([0.0, 0.0, -9.81])
    start = ImuOdometry.from_sequence(seq)
    g_accel, spread = estimate_gravity(start.stream, start.T_world_cam0)
    config = PipelineConfig(keyframe_every=4, render_width=None, render_height=None, progress=False)
    row = {"seed": seed, "accel_off_deg": round(gravity_angle_deg(g_accel, g_true), 3),
           "accel_spread_m_s2": round(spread, 3)}
    ways = {"true_vector": ImuConfig(gravity_world=tuple(g_true)),
            "accel_refined": ImuConfig(gravity_world=tuple(g_accel)),
            "accel_held": ImuConfig(gravity_world=tuple(g_accel), gravity_sigma_deg=1e-3),
            "z_up_refined": ImuConfig()}
    for name, imu_config in ways.items():
        result = Pipeline(seq, field, ImuOdometry.from_sequence(seq, imu_config), config).run()
        errors = [pose_error(a, b)[0] for a, b in zip(result.T_world_cam_estimate, seq.T_world_cam_gt)]
        row[name] = {"ate_m": float(np.sqrt(np.mean(np.square(errors)))), "accepted": result.num_accepted,
                     "keyframes": len(result.keyframes),
                     "gravity_off_deg": round(gravity_angle_deg(result.gravity_world, g_true), 3)}
    return row


def summary(rows: list[dict], way: str) -> dict:
    ate = np.array([r[way]["ate_m"] for r in rows])
    off = np.array([r[way]["gravity_off_deg"] for r in rows])
    lost = sum(r[way]["accepted"] < 0.8 * r[way]["keyframes"] for r in rows)
    return {"ate_median_m": float(np.median(ate)), "ate_p90_m": float(np.percentile(ate, 90)),
            "ate_max_m": float(ate.max()), "gravity_off_median_deg": float(np.median(off)),
            "gravity_off_max_deg": float(off.max()), "runs_with_under_80pct_accepted": int(lost), "runs": len(rows)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=6)
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/gravity_frame.json"))
    args = p.parse_args()
    folder = Path(tempfile.mkdtemp(prefix="gravity_frame_"))
    out = {"command": "python benchmarks/gravity_frame.py --seeds %d" % args.seeds, "frames": {}}
    for name, T_F_W in FRAMES.items():
        rows = [run_walk(seed, T_F_W, folder) for seed in range(args.seeds)]
        accel = np.array([r["accel_off_deg"] for r in rows])
        out["frames"][name] = {"rows": rows, "accel_off_deg": {"median": float(np.median(accel)), "max": float(accel.max())},
                               **{way: summary(rows, way) for way in ("true_vector", "accel_refined", "accel_held",
                                                                      "z_up_refined")}}
        s = out["frames"][name]
        print(f"{name}: accelerometer {s['accel_off_deg']['median']:.2f} deg (max {s['accel_off_deg']['max']:.2f})")
        for way in ("true_vector", "accel_refined", "accel_held", "z_up_refined"):
            w = s[way]
            print(f"  {way:14s} ATE median {w['ate_median_m'] * 1000:8.1f} mm p90 {w['ate_p90_m'] * 1000:8.1f} max "
                  f"{w['ate_max_m'] * 1000:8.1f}; gravity off {w['gravity_off_median_deg']:.2f} deg (max "
                  f"{w['gravity_off_max_deg']:.2f}); lost {w['runs_with_under_80pct_accepted']}/{w['runs']}")
    write_result(args.out, out, args)


if __name__ == "__main__":
    main()
