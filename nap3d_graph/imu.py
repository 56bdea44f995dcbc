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

__all__ = ["ImuConfig", "ImuStream"]

log = logging.getLogger(__name__)


@dataclass
class ImuConfig:
    """Noise densities (continuous time, per sqrt(Hz)), gravity (m/s^2, world +Z up), the
    camera-IMU extrinsics ``T_cam_imu`` (4, 4) (IMU frame -> camera frame) and the prior
    sigmas of the first velocity and biases."""

    accel_noise_density: float = 2.0e-3
    gyro_noise_density: float = 2.4e-4
    accel_bias_rw: float = 1.0e-4
    gyro_bias_rw: float = 2.0e-6
    gravity: float = 9.81
    T_cam_imu: np.ndarray = field(default_factory=lambda: np.eye(4))
    velocity_prior_sigma: float = 0.1
    accel_bias_prior_sigma: float = 0.05
    gyro_bias_prior_sigma: float = 0.005
    max_gap_s: float = 0.05

    def params(self) -> gtsam.PreintegrationCombinedParams:
        params = imu_params(self.accel_noise_density, self.gyro_noise_density, self.accel_bias_rw,
                            self.gyro_bias_rw, self.gravity)
        T = np.asarray(self.T_cam_imu, dtype=float)
        if not np.allclose(T, np.eye(4)):
            params.setBodyPSensor(gtsam.Pose3(T))  # body = camera, sensor = IMU
        return params

    def to_dict(self) -> dict:
        return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in self.__dict__.items()}


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
