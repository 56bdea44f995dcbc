"""IMU samples as a source of motion between keyframes: cleaning, gaps, preintegration.

An :class:`ImuStream` holds a sensor's samples on the frames' clock (specific force m/s^2
and angular rate rad/s in the IMU frame). Samples with a NaN are skipped, and a gap in the
stream (longer than ``max_gap_s``) is integrated across with the last sample held: both are
recorded with their time and reason, never a crash. :meth:`ImuStream.preintegrate` gives
GTSAM's ``PreintegratedCombinedMeasurements`` over any interval, for a ``CombinedImuFactor``
between two keyframes.

:class:`ImuConfig` holds what recordings do not store: the noise densities, the gravity and
the camera-IMU extrinsics (``T_cam_imu``). Its defaults are the simulator's (a BMI055-like
IMU, as in RealSense D435i/D455, co-located with the camera).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import gtsam
import numpy as np

from nap3d_graph.factors import imu_params, imu_pieces, integrate_pieces
from nap3d_graph.factors.imu import preintegrate as _preintegrate

__all__ = ["ImuConfig", "ImuStream", "estimate_gravity", "gravity_angle_deg"]

log = logging.getLogger(__name__)


@dataclass
class ImuConfig:
    """Noise densities (continuous time, per sqrt(Hz)), gravity (m/s^2; ``gravity_world``, the
    gravity vector in the world (field) frame when it is not ``(0, 0, -gravity)``: see
    :func:`estimate_gravity`), the camera-IMU extrinsics ``T_cam_imu`` (4, 4) (IMU frame ->
    camera frame), the prior sigmas of the first velocity and biases, and how far (deg, one
    sigma per tilt axis) the run's graph may turn gravity's direction away from
    ``gravity_vector()`` (``gravity_sigma_deg``; see :mod:`nap3d_graph.run.imu`)."""

    accel_noise_density: float = 2.0e-3
    gyro_noise_density: float = 2.4e-4
    accel_bias_rw: float = 1.0e-4
    gyro_bias_rw: float = 2.0e-6
    gravity: float = 9.81
    gravity_world: tuple[float, float, float] | None = None
    T_cam_imu: np.ndarray = field(default_factory=lambda: np.eye(4))
    velocity_prior_sigma: float = 0.1
    accel_bias_prior_sigma: float = 0.05
    gyro_bias_prior_sigma: float = 0.005
    max_gap_s: float = 0.05
    gravity_sigma_deg: float = 5.0

    def gravity_vector(self) -> np.ndarray:
        """Gravity (3,) in the world frame, m/s^2."""
        if self.gravity_world is not None:
            return np.asarray(self.gravity_world, dtype=float).reshape(3)
        return np.array([0.0, 0.0, -self.gravity])

    def in_gravity_frame(self) -> "ImuConfig":
        """This config in a world whose gravity is ``(0, 0, -g)`` (a navigation frame)."""
        import dataclasses

        return dataclasses.replace(self, gravity=float(np.linalg.norm(self.gravity_vector())), gravity_world=None)

    def params(self) -> gtsam.PreintegrationCombinedParams:
        params = imu_params(self.accel_noise_density, self.gyro_noise_density, self.accel_bias_rw,
                            self.gyro_bias_rw, self.gravity_vector())
        T = np.asarray(self.T_cam_imu, dtype=float)
        if not np.allclose(T, np.eye(4)):
            params.setBodyPSensor(gtsam.Pose3(T))  # body = camera, sensor = IMU
        return params

    def to_dict(self) -> dict:
        return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in self.__dict__.items()}


def estimate_gravity(stream: "ImuStream", T_world_cam0: np.ndarray, magnitude: float = 9.81,
                     window_s: float = 0.5) -> tuple[np.ndarray, float]:
    """Gravity (3,) in the world frame from the accelerometer over the first ``window_s`` and
    the camera's starting pose ``T_world_cam0`` (4, 4): at rest the accelerometer reads minus
    gravity in its own frame, so ``g_world = -R_world_imu mean(f)``, scaled to ``magnitude``.
    Returns it with the spread (m/s^2) of the samples' norm in the window: a camera that
    moved meanwhile (spread of tenths of m/s^2) gives a rougher direction, which the graph's
    accelerometer bias then partly takes up."""
    t0 = float(stream.stamps[0])
    inside = stream.stamps <= t0 + window_s
    f = stream.accel[inside] if inside.sum() >= 3 else stream.accel[:3]
    R_world_imu = (np.asarray(T_world_cam0, dtype=float) @ np.asarray(stream.config.T_cam_imu, dtype=float))[:3, :3]
    down = -R_world_imu @ f.mean(axis=0)
    norm = float(np.linalg.norm(down))
    if not norm > 1.0:
        raise ValueError(f"the accelerometer's mean over the first {window_s} s is {norm:.2f} m/s^2: no gravity in "
                         "it (is it in m/s^2?)")
    return down / norm * magnitude, float(np.std(np.linalg.norm(f, axis=1)))


def gravity_angle_deg(g_a: np.ndarray, g_b: np.ndarray) -> float:
    """The angle (deg) between two gravity vectors."""
    c = float(np.dot(g_a, g_b) / (np.linalg.norm(g_a) * np.linalg.norm(g_b)))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


class ImuStream:
    """Cleaned IMU samples: ``stamps`` (M,), ``accel`` (M, 3), ``gyro`` (M, 3); ``skipped``
    lists ``(time, reason)`` of every NaN sample dropped and every gap bridged."""

    def __init__(self, stamps, accel, gyro, config: ImuConfig | None = None):
        stamps = np.asarray(stamps, dtype=float).reshape(-1)
        accel = np.asarray(accel, dtype=float).reshape(-1, 3)
        gyro = np.asarray(gyro, dtype=float).reshape(-1, 3)
        if not (len(stamps) == len(accel) == len(gyro)):
            raise ValueError(f"IMU arrays disagree: {len(stamps)} stamps, {len(accel)} accel, {len(gyro)} gyro rows")
        self.config = config or ImuConfig()
        self.skipped: list[tuple[float, str]] = []
        finite = np.isfinite(stamps) & np.all(np.isfinite(accel), axis=1) & np.all(np.isfinite(gyro), axis=1)
        for t in stamps[~finite]:
            self.skipped.append((float(t), "non-finite IMU sample skipped"))
        stamps, accel, gyro = stamps[finite], accel[finite], gyro[finite]
        order = np.argsort(stamps, kind="stable")
        self.stamps, self.accel, self.gyro = stamps[order], accel[order], gyro[order]
        if len(self.stamps) < 2:
            raise ValueError("an IMU stream needs at least two valid samples")
        gaps = np.flatnonzero(np.diff(self.stamps) > self.config.max_gap_s)
        for k in gaps:
            self.skipped.append((float(self.stamps[k]), f"IMU gap of {self.stamps[k + 1] - self.stamps[k]:.3f} s "
                                 f"bridged by holding the last sample"))
        if self.skipped:
            log.warning("IMU stream: %d samples skipped or gaps bridged (first at t=%.3f: %s)", len(self.skipped),
                        self.skipped[0][0], self.skipped[0][1])
        self._params = self.config.params()

    @classmethod
    def from_sequence(cls, sequence, config: ImuConfig | None = None) -> "ImuStream":
        imu = getattr(sequence, "imu", None)
        if imu is None:
            raise ValueError(f"{getattr(sequence, 'path', 'the sequence')}: no IMU samples (imu.txt)")
        return cls(imu["stamps"], imu["accel"], imu["gyro"], config)

    def with_config(self, config: ImuConfig) -> "ImuStream":
        """The same cleaned samples under another config (its gravity, say); the noise,
        extrinsics and gap rule must be this one's."""
        import copy

        other = copy.copy(self)
        other.config, other._params = config, config.params()
        return other

    def covers(self, t0: float, t1: float) -> bool:
        return bool(self.stamps[0] <= t0 + self.config.max_gap_s and self.stamps[-1] >= t1 - self.config.max_gap_s)

    def notes_between(self, t0: float, t1: float) -> list[str]:
        """The skipped samples and bridged gaps inside ``[t0, t1)``."""
        return [reason for t, reason in self.skipped if t0 <= t < t1]

    def preintegrate(self, t0: float, t1: float, bias: gtsam.imuBias.ConstantBias | None = None):
        """``PreintegratedCombinedMeasurements`` over exactly ``[t0, t1)``."""
        return _preintegrate(self._params, bias, self.stamps, self.accel, self.gyro, t0, t1)

    def pieces(self, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Zero-order-hold pieces of ``[t0, t1)``: accel (K, 3), gyro (K, 3), dt (K,)."""
        return imu_pieces(self.stamps, self.accel, self.gyro, t0, t1)

    def extend(self, pim, t0: float, t1: float):
        """Integrate ``[t0, t1)`` into an existing preintegration ``pim`` (a running one)."""
        if t1 > t0:
            integrate_pieces(pim, *self.pieces(t0, t1))
        return pim

    @property
    def params(self) -> gtsam.PreintegrationCombinedParams:
        return self._params
