"""The IMU path when the views leave the field: the IMU alone against the visual-odometry fallback.

Simulated walks (benchmark rooms 31-33, one walk each, 9 s at 10 Hz, 160x120) whose field covers
only where the first 30 frames went (the exact field, empty beyond 5 cm of those positions: a
survey that mapped the start of the walk). Each walk runs on the IMU path three ways: the IMU
alone between keyframes (``--fallback-odom none``), and falling back on the dense or the
feature visual odometry after 3 refused keyframes (``dense``, ``vo``). Reported per walk and
pooled: the smoothed and causal error at the last frame and their maxima over the frames after
the field was left, corrections accepted, and where the fallback started.

    python benchmarks/imu_fallback.py [--out benchmarks/results/imu_fallback.json]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
from provenance import write_result

ROOMS = (31, 32, 33)
MAPPED_FRAMES = 30


def run_walk(room: int, folder: Path) -> dict:
    from nap3d_graph.conventions import pose_error
    from nap3d_graph.datasets import SimSequence
    from nap3d_graph.motion.odometry import DenseVisualOdometry, VisualOdometry
    from nap3d_graph.run.config import PipelineConfig
    from nap3d_graph.run.imu import ImuOdometry
    from nap3d_graph.run.pipeline import Pipeline
    from nap3d_graph.sims.reframe import PartlyMappedField
    from nap3d_graph.sims.sequence import SimConfig, simulate_sequence

    path = simulate_sequence(folder / f"room{room}", SimConfig(frames=90, fps=10.0, width=160, height=120,
                                                               scene_seed=room, seed=4, timing=None))
    walk = SimSequence(path)
    config = PipelineConfig(keyframe_every=4, render_width=None, render_height=None, progress=False)
    row: dict = {"room": room}
    for name, fallback in (("imu_alone", None), ("dense", DenseVisualOdometry()), ("vo", VisualOdometry())):
        odometry = ImuOdometry.from_sequence(walk)
        odometry.fallback = fallback
        result = Pipeline(walk, PartlyMappedField(walk, MAPPED_FRAMES), odometry, config).run()
        smoothed = np.array([pose_error(a, b)[0] for a, b in zip(result.T_world_cam_estimate, walk.T_world_cam_gt)])
        causal = np.array([pose_error(a, b)[0] for a, b in zip(result.T_world_cam_online, walk.T_world_cam_gt)])
        row[name] = {"end_m": float(smoothed[-1]), "end_causal_m": float(causal[-1]),
                     "max_after_field_m": float(smoothed[MAPPED_FRAMES:].max()),
                     "max_causal_after_field_m": float(causal[MAPPED_FRAMES:].max()),
                     "accepted": result.num_accepted, "keyframes": len(result.keyframes),
                     "fallback_intervals": result.fallback_intervals}
    return row


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/imu_fallback.json"))
    args = p.parse_args()
    folder = Path(tempfile.mkdtemp(prefix="imu_fallback_"))
    rows = [run_walk(room, folder) for room in ROOMS]
    pooled = {}
    for name in ("imu_alone", "dense", "vo"):
        pooled[name] = {key: {"median": float(np.median([r[name][key] for r in rows])),
                              "max": float(np.max([r[name][key] for r in rows]))}
                        for key in ("end_m", "end_causal_m", "max_after_field_m", "max_causal_after_field_m")}
        print(f"{name:10s} end {pooled[name]['end_m']['median'] * 100:7.1f} cm median (max "
              f"{pooled[name]['end_m']['max'] * 100:7.1f}); causal end {pooled[name]['end_causal_m']['median'] * 100:7.1f}"
              f" cm; worst after the field {pooled[name]['max_after_field_m']['max'] * 100:7.1f} cm")
    write_result(args.out, {"command": "python benchmarks/imu_fallback.py", "rooms": list(ROOMS),
                            "mapped_frames": MAPPED_FRAMES, "rows": rows, "pooled": pooled}, args)


if __name__ == "__main__":
    main()
