"""A measurement stream drawn from known noise, for tests and timing benchmarks.

The trajectory is a smooth figure of eight (about 4 x 2 m, with heading, pitch and roll
sweeps, or translation only). Its odometry increments carry Gaussian noise of exactly the
covariance the stream states; each keyframe's correction is the true pose with Gaussian
noise of its stated covariance; the IMU (optional) is the simulator's. Every estimator is
then consistent by construction: its NEES should sit at 6.
"""

from __future__ import annotations

import numpy as np

from nap3d_graph.conventions import compose_covariance, exp_se3, inv_T
from nap3d_graph.motion.imu import ImuStream
from nap3d_graph.sims.sensors import ImuNoise, simulate_imu
from nap3d_graph.sims.trajectories import Trajectory

from .base import MeasurementStream

__all__ = ["synthetic_stream"]


def _trajectory(duration_s: float, rotate: bool):
    w = 2 * np.pi / 40.0  # one figure of eight every 40 s

    def position(t: float) -> np.ndarray:
        return np.array([2.0 * np.sin(w * t), 1.0 * np.sin(2 * w * t), 1.3 + 0.05 * np.sin(0.7 * t)])

    def angles(t: float) -> tuple[float, float, float]:
        if not rotate:
            return 0.0, 0.0, 0.0
        return 0.6 * np.sin(w * t) + 0.2 * np.sin(0.9 * t), 0.1 * np.sin(0.5 * t), 0.05 * np.sin(0.3 * t)

    return Trajectory(position, angles, duration_s, "figure-eight")


def synthetic_stream(n_frames: int, fps: float = 15.0, keyframe_every: int = 5, seed: int = 0, *,
                     rotate: bool = True, imu: bool = False, odom_rot_sigma: float = 1e-3,
                     odom_trans_sigma: float = 2e-3, corr_rot_sigma: float = 2e-3, corr_trans_sigma: float = 4e-3,
                     prior_rot_sigma: float = 1e-3, prior_trans_sigma: float = 1e-3,
                     gate_p: float = 0.997) -> MeasurementStream:
    """A stream of ``n_frames`` frames at ``fps``, a keyframe (with a correction) every
    ``keyframe_every`` frames. ``rotate=False`` keeps every pose and every noise a pure
    translation (a linear-Gaussian problem; its rotation sigmas only fill the covariances)."""
    rng = np.random.default_rng(seed)
    stamps = np.arange(n_frames) / fps
    trajectory = _trajectory(float(stamps[-1]) + 1.0, rotate)
    T_world_cam_gt = trajectory.poses(stamps)
    rot_on = 1.0 if rotate else 0.0
    Q = np.diag([odom_rot_sigma**2 * rot_on] * 3 + [odom_trans_sigma**2] * 3)
    R = np.diag([corr_rot_sigma**2] * 3 + [corr_trans_sigma**2] * 3)
    P0 = np.diag([prior_rot_sigma**2 * rot_on] * 3 + [prior_trans_sigma**2] * 3)
    noise_Q = np.sqrt(np.diag(Q))
    noise_R = np.sqrt(np.diag(R)) * np.r_[[rot_on] * 3, [1.0] * 3]
    T0 = T_world_cam_gt[0] @ exp_se3(rng.normal(size=6) * np.sqrt(np.diag(P0)))
    increments = [np.eye(4)]
    for i in range(1, n_frames):
        increments.append(inv_T(T_world_cam_gt[i - 1]) @ T_world_cam_gt[i] @ exp_se3(rng.normal(size=6) * noise_Q))
    keyframes = list(range(0, n_frames, keyframe_every))
    interval, corrections = {}, {}
    for a, b in zip(keyframes[:-1], keyframes[1:]):
        T_int, cov = np.eye(4), np.zeros((6, 6))
        for m in range(a + 1, b + 1):
            cov = compose_covariance(cov, increments[m], Q)
            T_int = T_int @ increments[m]
        interval[b] = (T_int, cov)
    for k in keyframes:
        corrections[k] = (T_world_cam_gt[k] @ exp_se3(rng.normal(size=6) * noise_R), R.copy())
    stream = MeasurementStream(stamps, increments, keyframes, interval, corrections, T0, P0, gate_p,
                               T_world_cam_gt=T_world_cam_gt)
    if imu:
        _add_imu(stream, trajectory, rng)
    return stream


def _add_imu(stream: MeasurementStream, trajectory, rng) -> None:
    stamps = stream.timestamps
    samples = simulate_imu(trajectory, float(stamps[0]) - 0.05, float(stamps[-1]) + 0.05, ImuNoise(), rng)
    stream.imu = ImuStream(samples["stamps"], samples["accel"], samples["gyro"])
    stream.velocity0 = trajectory.velocity_world(float(stamps[0]))
    stream.T_world_cam0 = stream.T_world_cam_gt[0].copy()
    stream.true_biases = np.column_stack([samples["stamps"], samples["accel_bias"], samples["gyro_bias"]])
