"""Sensor models: RGB-D camera noise, drifting odometry and an IMU.

All models take a ``numpy.random.Generator`` so every simulation is reproducible.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from nap3d_graph.camera import DEPTH_SIGMA_Z2_PER_M, RGBDFrame
from nap3d_graph.conventions import exp_se3, inv_T

from .trajectories import Trajectory

__all__ = [
    "DepthNoise",
    "CameraTiming",
    "ExposureNoise",
    "exposure_gains",
    "blur_poses",
    "add_depth_noise",
    "add_rgb_noise",
    "OdometryNoise",
    "drifting_odometry",
    "ImuNoise",
    "simulate_imu",
    "GRAVITY_M_S2",
    "sensor_frame",
]

GRAVITY_M_S2 = 9.81


@dataclass(frozen=True)
class DepthNoise:
    """Structured-light-like depth: ``sigma(z) = sigma_z2_per_m * z^2`` (Khoshelham's Kinect
    model is ~1.4e-3 z^2), random holes, no return beyond ``max_range_m`` or at grazing
    angles, and *flying pixels*: at a depth edge (a neighbour more than ``flying_jump_rel``
    of the depth away) a ``flying_fraction`` of the pixels report a depth between the two
    surfaces, as a Kinect's mixed pixels do."""

    sigma_z2_per_m: float = DEPTH_SIGMA_Z2_PER_M
    hole_fraction: float = 0.01
    hole_radius_px: int = 4
    max_range_m: float = 6.0
    min_range_m: float = 0.3
    flying_fraction: float = 0.3
    flying_jump_rel: float = 0.05

    def sigma_m(self, z_m: np.ndarray) -> np.ndarray:
        return self.sigma_z2_per_m * np.asarray(z_m) ** 2


@dataclass(frozen=True)
class CameraTiming:
    """When a simulated RGB-D camera captures, and how it stamps, its images.

    Colour is captured at its stamp, over ``exposure_s`` (so a moving camera blurs it, with
    up to ``max_blur_samples`` sub-frame renders). Depth is captured ``depth_capture_offset_s``
    from the colour (a Kinect's is some 30 ms earlier) and stamped ``depth_stamp_lag_s``
    after its capture, with ``stamp_jitter_s`` of uniform jitter: so its stamp is ~15 ms
    before the colour's, as on TUM's Kinect, while its true capture is 30 ms before.
    """

    depth_capture_offset_s: float = -0.030
    depth_stamp_lag_s: float = 0.015
    stamp_jitter_s: float = 0.003
    exposure_s: float = 0.015
    max_blur_samples: int = 5

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class ExposureNoise:
    """Auto-exposure and white balance: each frame's colours are multiplied per channel by
    ``exp(g_f + w_c,f)``: a log gain ``g`` that random-walks by ``gain_walk`` per frame
    (kept within ``gain_limit``) and a white balance ``w`` drawn once per sequence
    (``white_balance_sigma`` per channel) that wanders by ``white_balance_walk``."""

    gain_walk: float = 0.03
    gain_limit: float = 0.3
    white_balance_sigma: float = 0.03
    white_balance_walk: float = 0.005

    def to_dict(self) -> dict:
        return asdict(self)


def exposure_gains(frames: int, noise: ExposureNoise | None, rng: np.random.Generator) -> np.ndarray:
    """Per-frame, per-channel colour gains (frames, 3); ones without ``noise``."""
    if noise is None:
        return np.ones((frames, 3))
    gain = np.clip(np.cumsum(rng.normal(size=frames) * noise.gain_walk), -noise.gain_limit, noise.gain_limit)
    balance = rng.normal(size=3) * noise.white_balance_sigma + np.cumsum(
        rng.normal(size=(frames, 3)) * noise.white_balance_walk, axis=0)
    return np.exp(gain[:, None] + balance)


def blur_poses(trajectory, t_colour: float, timing: CameraTiming | None, intrinsics,
               typical_depth_m: float = 2.5) -> tuple[list[np.ndarray], float]:
    """Poses to average the colour image over during the exposure, one per pixel of apparent
    motion at ``typical_depth_m`` (at least 1, at most ``max_blur_samples``), and the sigma
    (px) of a Gaussian that fills the gaps between the samples when the motion is longer
    than that (so the blur is a smear, not a few sharp copies)."""
    if timing is None or timing.exposure_s <= 0:
        return [trajectory.T_world_cam(t_colour)], 0.0
    start, end = t_colour - timing.exposure_s / 2, t_colour + timing.exposure_s / 2
    T0, T1 = trajectory.T_world_cam(start), trajectory.T_world_cam(end)
    moved_m = float(np.linalg.norm(T1[:3, 3] - T0[:3, 3]))
    turned = float(np.arccos(np.clip((np.trace(T0[:3, :3].T @ T1[:3, :3]) - 1) / 2, -1, 1)))
    motion_px = 0.5 * (intrinsics.fx + intrinsics.fy) * (moved_m / typical_depth_m + turned)
    samples = int(np.clip(np.ceil(motion_px), 1, timing.max_blur_samples))
    gap_sigma = 0.5 * motion_px / samples if motion_px > samples else 0.0
    if samples == 1:
        return [trajectory.T_world_cam(t_colour)], gap_sigma
    return [trajectory.T_world_cam(float(t)) for t in np.linspace(start, end, samples)], gap_sigma

    def sigma_m(self, z_m: np.ndarray) -> np.ndarray:
        return self.sigma_z2_per_m * np.asarray(z_m) ** 2


def add_depth_noise(depth_m: np.ndarray, noise: DepthNoise, rng: np.random.Generator) -> np.ndarray:
    """Noisy sensor depth (H, W) float32 from noise-free z-depth; 0 marks missing."""
    import cv2

    depth = depth_m.astype(np.float64)
    noisy = depth + rng.normal(size=depth.shape) * noise.sigma_m(depth)
    missing = (depth <= noise.min_range_m) | (depth > noise.max_range_m) | ~np.isfinite(depth)
    if noise.hole_fraction > 0:
        # Holes come in blobs (specular spots, IR shadows), not as salt noise.
        seeds = (rng.random(depth.shape) < noise.hole_fraction / (np.pi * noise.hole_radius_px**2)).astype(np.uint8)
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * noise.hole_radius_px + 1,) * 2)
        missing |= cv2.dilate(seeds, kernel).astype(bool)
    noisy = _flying_pixels(depth, noisy, noise, rng)
    noisy[missing] = 0.0
    return noisy.astype(np.float32)


def _flying_pixels(depth: np.ndarray, noisy: np.ndarray, noise: DepthNoise, rng: np.random.Generator) -> np.ndarray:
    """At depth edges, a fraction of pixels report a depth between the two surfaces."""
    if noise.flying_fraction <= 0:
        return noisy
    out = noisy.copy()
    finite = np.isfinite(depth) & (depth > 0)
    for axis, step in ((0, 1), (0, -1), (1, 1), (1, -1)):
        other = np.roll(depth, step, axis=axis)
        edge = finite & np.isfinite(other) & (other > 0) & (np.abs(other - depth) > noise.flying_jump_rel * depth)
        flying = edge & (rng.random(depth.shape) < noise.flying_fraction / 4)
        alpha = rng.random(depth.shape)
        out = np.where(flying, alpha * depth + (1 - alpha) * other, out)
    return out


def add_rgb_noise(rgb01: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """uint8 image (H, W, 3) from a float image in [0, 1] plus Gaussian noise of ``sigma``
    (in 0..1 units)."""
    noisy = rgb01 + rng.normal(scale=sigma, size=rgb01.shape)
    return np.clip(np.round(noisy * 255.0), 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class OdometryNoise:
    """Drift of frame-to-frame odometry.

    Each increment ``T_k_k+1`` is perturbed on the right by ``Exp(xi_k)`` with
    ``xi_k = b_k * dt + h * dt + w_k``:

    * white noise ``w_k ~ N(0, diag(sigma^2))`` per frame (rotation rad, translation m, GTSAM
      order, camera frame);
    * a slowly wandering bias ``b`` (rad/s, m/s) *in the camera frame* that follows a random
      walk with ``bias_walk`` per sqrt(second), starting at ``bias_init``. Its rotation
      components are about the camera's x (pitch), y (yaw of a level camera... only while it
      is level) and z axes; z is the *optical* axis, so the third component is a roll, which
      barely bends a forward path (it used to be called a heading bias: it is not);
    * a heading bias ``h`` of ``heading_bias_rad_s`` about *gravity* (world +Z), expressed in
      the camera frame at each step: what a visual odometry's or gyro's yaw drift does, and
      what bends a path sideways.

    The biases make the error grow like real odometry's (faster than a random walk), with the
    time travelled as much as with the distance: they act while the camera stands still.
    """

    rot_sigma_rad: float = 2e-3
    trans_sigma_m: float = 2e-3
    bias_init: tuple[float, float, float, float, float, float] = (0.0, 0.0, 0.004, 0.01, 0.0, 0.0)
    bias_walk: float = 1e-3
    heading_bias_rad_s: float = 0.004

    @property
    def sigmas(self) -> np.ndarray:
        return np.array([self.rot_sigma_rad] * 3 + [self.trans_sigma_m] * 3)

    def to_dict(self) -> dict:
        return asdict(self)


def drifting_odometry(
    T_world_cam_gt: np.ndarray, stamps: np.ndarray, noise: OdometryNoise, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Drifting odometry poses (N, 4, 4) starting at the true first pose, and the
    per-increment errors ``xi`` (N-1, 6) that were applied (GTSAM order, camera frame)."""
    n = len(T_world_cam_gt)
    T_odom = np.empty_like(T_world_cam_gt)
    T_odom[0] = T_world_cam_gt[0]
    bias = np.asarray(noise.bias_init, dtype=float).copy()
    errors = np.zeros((max(n - 1, 0), 6))
    for k in range(n - 1):
        dt = float(stamps[k + 1] - stamps[k])
        increment = inv_T(T_world_cam_gt[k]) @ T_world_cam_gt[k + 1]
        xi = bias * dt + rng.normal(size=6) * noise.sigmas
        # The heading bias turns about gravity (world +Z), whatever the camera's attitude:
        # world +Z expressed in the frame the perturbation applies to (after the increment).
        R_world_next = T_odom[k][:3, :3] @ increment[:3, :3]
        xi[:3] += R_world_next.T @ np.array([0.0, 0.0, noise.heading_bias_rad_s * dt])
        errors[k] = xi
        T_odom[k + 1] = T_odom[k] @ increment @ exp_se3(xi)
        bias = bias + rng.normal(size=6) * noise.bias_walk * np.sqrt(dt)
    return T_odom, errors


@dataclass(frozen=True)
class ImuNoise:
    """Continuous-time IMU noise (BMI055-like, as in RealSense D435i/D455):
    white noise densities and bias random walks per sqrt(Hz)."""

    rate_hz: float = 200.0
    accel_noise_density: float = 2.0e-3  # m/s^2/sqrt(Hz)
    gyro_noise_density: float = 2.4e-4  # rad/s/sqrt(Hz)
    accel_bias_walk: float = 1.0e-4  # m/s^3/sqrt(Hz)
    gyro_bias_walk: float = 2.0e-6  # rad/s^2/sqrt(Hz)
    accel_bias_init_sigma: float = 0.02  # m/s^2
    gyro_bias_init_sigma: float = 0.002  # rad/s

    def to_dict(self) -> dict:
        return asdict(self)


def simulate_imu(
    trajectory: Trajectory,
    t_start: float,
    t_end: float,
    noise: ImuNoise | None,
    rng: np.random.Generator,
) -> dict[str, np.ndarray]:
    """IMU samples in the camera frame (the IMU is taken as co-located with the camera).

    The accelerometer measures specific force ``R^T (a - g)`` with ``g = (0, 0, -9.81)``
    (world +Z up); the gyroscope the body angular velocity. ``noise=None`` gives exact
    samples. Returns ``stamps`` (M,), ``accel`` (M, 3), ``gyro`` (M, 3) and the true biases
    ``accel_bias`` and ``gyro_bias`` (M, 3).
    """
    rate = noise.rate_hz if noise is not None else 200.0
    dt = 1.0 / rate
    stamps = np.arange(t_start, t_end, dt)
    g_world = np.array([0.0, 0.0, -GRAVITY_M_S2])
    accel = np.empty((len(stamps), 3))
    gyro = np.empty((len(stamps), 3))
    for i, t in enumerate(stamps):
        # Sample at the middle of the interval the measurement will be integrated over:
        # preintegration holds each sample constant over [t, t + dt].
        tm = float(t) + dt / 2
        R = trajectory.T_world_cam(tm)[:3, :3]
        accel[i] = R.T @ (trajectory.acceleration_world(tm) - g_world)
        gyro[i] = trajectory.angular_velocity_cam(tm)
    accel_bias = np.zeros_like(accel)
    gyro_bias = np.zeros_like(gyro)
    if noise is not None:
        ba = rng.normal(size=3) * noise.accel_bias_init_sigma
        bg = rng.normal(size=3) * noise.gyro_bias_init_sigma
        walk_a = np.cumsum(rng.normal(size=accel.shape) * noise.accel_bias_walk * np.sqrt(dt), axis=0)
        walk_g = np.cumsum(rng.normal(size=gyro.shape) * noise.gyro_bias_walk * np.sqrt(dt), axis=0)
        accel_bias = ba + walk_a
        gyro_bias = bg + walk_g
        # Discrete white-noise sigma = density * sqrt(rate).
        accel = accel + accel_bias + rng.normal(size=accel.shape) * noise.accel_noise_density * np.sqrt(rate)
        gyro = gyro + gyro_bias + rng.normal(size=gyro.shape) * noise.gyro_noise_density * np.sqrt(rate)
    return {"stamps": stamps, "accel": accel, "gyro": gyro, "accel_bias": accel_bias, "gyro_bias": gyro_bias}


def sensor_frame(scene, T_world_cam: np.ndarray, intrinsics, rng: np.random.Generator,
                 depth_noise: DepthNoise | None = DepthNoise(), rgb_noise_sigma: float = 0.01,
                 depth_scale: float = 5000.0, timestamp: float = 0.0):
    """What the simulated RGB-D sensor sees at ``T_world_cam``: an :class:`RGBDFrame` with
    RGB noise, z^2 depth noise and holes, and depth quantised like TUM's PNGs
    (1/``depth_scale`` m). ``depth_noise=None`` gives exact depth."""
    rgb01, depth, _ = scene.render(T_world_cam, intrinsics)
    if depth_noise is not None:
        depth = np.round(add_depth_noise(depth, depth_noise, rng) * depth_scale) / depth_scale
    return RGBDFrame(add_rgb_noise(rgb01, rgb_noise_sigma, rng), depth.astype(np.float32), intrinsics, timestamp)
