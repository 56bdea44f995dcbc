"""A simulated traversal written as a RealSense recording (``simulate --realsense OUT.db3``).

For users without a camera and for the tests: the colour frames, IMU and stamps of a
simulated sequence folder, with the depth seen by a depth camera ``baseline_m`` to the side
of the colour camera, as on a D435i (rendered from the room at that camera's pose at the
depth frame's capture instant, with the simulator's depth noise, quantised to the depth
units), written through pyrealsense2's ``software_device`` and ``recorder``. Beside it,
``OUT.yaml`` holds what the format cannot (the IMU's extrinsics, here co-located with the
colour camera, and its noise densities); the folder's ``groundtruth.txt`` is the poses of the
recording's frames.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nap3d_graph.camera import Intrinsics
from nap3d_graph.datasets import SimSequence
from nap3d_graph.datasets.realsense import RealSenseConfig
from nap3d_graph.datasets.realsense_io import RecordingWriter, StreamIntrinsics
from nap3d_graph.motion.imu import ImuConfig
from nap3d_graph.progress import progress_bar
from nap3d_graph.sims.sensors import DepthNoise, add_depth_noise

__all__ = ["write_realsense_recording"]


def write_realsense_recording(sim_dir, out_path, baseline_m: float = 0.015, depth_units: float = 0.001,
                              depth_noise: bool = True, seed: int = 0, progress: bool = False) -> Path:
    """Write ``out_path`` (``.db3``) and its ``.yaml`` from the simulated folder ``sim_dir``."""
    seq = SimSequence(sim_dir)
    K: Intrinsics = seq.intrinsics
    stream_K = StreamIntrinsics(K.width, K.height, K.fx, K.fy, K.cx, K.cy)
    T_colour_depth = np.eye(4)
    T_colour_depth[0, 3] = baseline_m  # the depth camera sits baseline_m along the colour camera's +x
    fps = int(round(1.0 / float(np.median(np.diff(seq.timestamps))))) if len(seq) > 1 else 15
    writer = RecordingWriter(out_path, stream_K, stream_K, depth_units, T_colour_depth, fps=fps, imu_hz=200)
    capture = np.asarray(seq.config.get("depth_capture_stamps") or seq.depth_timestamps, dtype=float)
    gt_stamps = seq.ground_truth_samples[0]
    # The ground truth covers every capture instant to the microsecond it is written with.
    capture = np.clip(capture, gt_stamps[0], gt_stamps[-1])
    T_world_colour = seq.ground_truth_at(capture)  # the colour camera's pose when the depth was taken
    if not np.all(np.isfinite(T_world_colour)):
        raise ValueError(f"{sim_dir}: its ground truth does not cover every depth capture instant")
    T_depth_colour = np.linalg.inv(T_colour_depth)
    rng = np.random.default_rng(seed)
    noise = DepthNoise(**seq.config["depth"]) if depth_noise and "depth" in seq.config else DepthNoise()
    for i in progress_bar(range(len(seq)), desc="realsense", unit="frame", disable=not progress):
        writer.add_colour(float(seq.timestamps[i]), seq[i].rgb)
        depth_m = seq.scene.render_depth(T_world_colour[i] @ T_colour_depth, K)
        if depth_noise:
            depth_m = add_depth_noise(depth_m, noise, rng)
        units = np.round(np.nan_to_num(depth_m, nan=0.0) / depth_units)
        writer.add_depth(float(seq.depth_timestamps[i]), np.clip(units, 0, 65535).astype(np.uint16))
    writer.add_imu(seq.imu["stamps"], seq.imu["accel"], seq.imu["gyro"])
    out = writer.close()
    imu = ImuConfig()
    RealSenseConfig(T_depth_imu=T_depth_colour, accel_noise_density=imu.accel_noise_density,
                    gyro_noise_density=imu.gyro_noise_density, accel_bias_rw=imu.accel_bias_rw,
                    gyro_bias_rw=imu.gyro_bias_rw, simulated=True).save(out.with_suffix(".yaml"))
    return out
