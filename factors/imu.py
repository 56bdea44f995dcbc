"""IMU preintegration and ``CombinedImuFactor`` builders.

Frames: the IMU body frame B is the frame of the pose variable ``X(k)`` (if the camera is
not at the IMU, set ``params.setBodyPSensor``). The navigation frame is the world frame
with +Z up: ``MakeSharedU(g)`` sets gravity to ``(0, 0, -g)``, so an accelerometer at rest
and level reads ``(0, 0, +g)`` (specific force).

Noise parameters are *continuous-time* densities, as on IMU datasheets and in Kalibr's
``imu.yaml``:

* ``accel_noise_density``: m/s^2/sqrt(Hz); ``gyro_noise_density``: rad/s/sqrt(Hz);
* ``accel_bias_rw``: m/s^3/sqrt(Hz); ``gyro_bias_rw``: rad/s^2/sqrt(Hz).

GTSAM discretises them itself (covariance / dt), so they are squared here, not divided.
"""

from __future__ import annotations

import logging
from typing import Optional

import gtsam
import numpy as np

__all__ = ["imu_params", "imu_pieces", "integrate_pieces", "preintegrate", "imu_factor"]

logger = logging.getLogger(__name__)

# Integration covariance models the error of integrating velocity into position with
# piecewise-constant samples; GTSAM's examples use a tiny value (1e-8 m^2), since the
# measurement noise, not integration, dominates at IMU rates.
DEFAULT_INTEGRATION_SIGMA = 1e-4


def _positive(value: float, name: str) -> float:
    v = float(value)
    if not np.isfinite(v) or v <= 0.0:
        raise ValueError(f"{name} must be finite and > 0, got {value}")
    return v


def imu_params(accel_noise_density: float, gyro_noise_density: float,
               accel_bias_rw: float, gyro_bias_rw: float, gravity=9.81,
               integration_sigma: float = DEFAULT_INTEGRATION_SIGMA,
               ) -> gtsam.PreintegrationCombinedParams:
    """Preintegration parameters with isotropic IMU noise, for a Z-up world or any other.

    Args:
        accel_noise_density: m/s^2/sqrt(Hz).
        gyro_noise_density: rad/s/sqrt(Hz).
        accel_bias_rw: accelerometer bias random walk, m/s^3/sqrt(Hz).
        gyro_bias_rw: gyroscope bias random walk, rad/s^2/sqrt(Hz).
        gravity: magnitude of gravity (m/s^2), the world's gravity then ``(0, 0, -gravity)``;
            or the gravity vector (3,) in the world frame (m/s^2), for a world that is not
            Z-up (a nerfstudio or COLMAP frame, a y-down room).
        integration_sigma: integration uncertainty (m/sqrt(Hz)); small.

    Returns:
        ``gtsam.PreintegrationCombinedParams`` with the 3x3 covariances set.
    """
    I3 = np.eye(3)
    if np.ndim(gravity) == 0:
        params = gtsam.PreintegrationCombinedParams.MakeSharedU(_positive(float(gravity), "gravity"))
    else:
        g = np.asarray(gravity, dtype=float).reshape(3)
        _positive(float(np.linalg.norm(g)), "|gravity|")
        params = gtsam.PreintegrationCombinedParams(g)
    params.setAccelerometerCovariance(_positive(accel_noise_density, "accel_noise_density") ** 2 * I3)
    params.setGyroscopeCovariance(_positive(gyro_noise_density, "gyro_noise_density") ** 2 * I3)
    params.setBiasAccCovariance(_positive(accel_bias_rw, "accel_bias_rw") ** 2 * I3)
    params.setBiasOmegaCovariance(_positive(gyro_bias_rw, "gyro_bias_rw") ** 2 * I3)
    params.setIntegrationCovariance(_positive(integration_sigma, "integration_sigma") ** 2 * I3)
    return params


def imu_pieces(stamps: np.ndarray, accel: np.ndarray, gyro: np.ndarray, t_start: float,
               t_end: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The zero-order-hold pieces of ``[t_start, t_end)``: ``(accel (K, 3), gyro (K, 3), dt (K,))``.

    Samples are held constant until the next sample (as GTSAM's ``integrateMeasurement``
    assumes). The interval is cut at ``t_start``, every sample time inside it, and
    ``t_end``; each piece carries the sample active at its start, so the partial first
    piece uses the last sample *before* ``t_start`` and the partial last piece is cut at
    ``t_end``. The pieces add up to ``t_end - t_start`` exactly, so consecutive intervals
    neither lose nor double-count time. Before the first sample, the first sample is held
    backwards (logged). Empty pieces (duplicate stamps) are dropped.

    Args:
        stamps: (N,) sample times, seconds, non-decreasing.
        accel: (N, 3) specific force in the IMU body frame, m/s^2.
        gyro: (N, 3) angular rate in the IMU body frame, rad/s.
        t_start, t_end: interval, seconds, ``t_end > t_start``.

    Raises:
        ValueError: bad shapes, non-finite samples in the interval, unsorted stamps,
            no samples, or ``t_end <= t_start``.
    """
    stamps = np.asarray(stamps, dtype=float).reshape(-1)
    accel = np.asarray(accel, dtype=float)
    gyro = np.asarray(gyro, dtype=float)
    n = stamps.shape[0]
    if n == 0:
        raise ValueError("preintegrate needs at least one IMU sample")
    if accel.shape != (n, 3) or gyro.shape != (n, 3):
        raise ValueError(f"accel and gyro must have shape ({n}, 3), got {accel.shape} and {gyro.shape}")
    if not (np.isfinite(t_start) and np.isfinite(t_end)) or t_end <= t_start:
        raise ValueError(f"need finite t_end > t_start, got [{t_start}, {t_end})")
    if not np.all(np.isfinite(stamps)) or np.any(np.diff(stamps) < 0.0):
        raise ValueError("IMU stamps must be finite and non-decreasing")

    if t_start < stamps[0]:
        logger.debug("IMU: holding the first sample back from %.6f to t_start %.6f", stamps[0], t_start)
    first = np.searchsorted(stamps, t_start, side="right")
    last = np.searchsorted(stamps, t_end, side="left")
    cuts = np.concatenate([[t_start], stamps[first:last], [t_end]])
    # The sample active at time t is the last one with stamp <= t (clamped to the first).
    active = np.clip(np.searchsorted(stamps, cuts[:-1], side="right") - 1, 0, n - 1)
    dts = np.diff(cuts)
    keep = dts > 0.0
    active, dts = active[keep], dts[keep]
    if not (np.all(np.isfinite(accel[active])) and np.all(np.isfinite(gyro[active]))):
        raise ValueError(f"non-finite IMU samples in [{t_start}, {t_end})")
    return accel[active], gyro[active], dts


def integrate_pieces(pim, accel: np.ndarray, gyro: np.ndarray, dts: np.ndarray):
    """Feed :func:`imu_pieces` into a preintegration ``pim`` (in place; returned)."""
    for a, w, dt in zip(accel, gyro, dts):
        pim.integrateMeasurement(a, w, float(dt))
    return pim


def preintegrate(params: gtsam.PreintegrationCombinedParams,
                 bias: Optional[gtsam.imuBias.ConstantBias],
                 stamps: np.ndarray, accel: np.ndarray, gyro: np.ndarray,
                 t_start: float, t_end: float) -> gtsam.PreintegratedCombinedMeasurements:
    """Preintegrate IMU samples over exactly ``[t_start, t_end)`` (pieces as :func:`imu_pieces`).

    Args:
        params: from :func:`imu_params`.
        bias: bias estimate to preintegrate with (``None``: zero bias).
        stamps, accel, gyro, t_start, t_end: as in :func:`imu_pieces`.

    Returns:
        ``PreintegratedCombinedMeasurements`` with ``deltaTij() == t_end - t_start``.

    Raises:
        ValueError: as :func:`imu_pieces`.
    """
    pieces = imu_pieces(stamps, accel, gyro, t_start, t_end)
    pim = gtsam.PreintegratedCombinedMeasurements(
        params, gtsam.imuBias.ConstantBias() if bias is None else bias)
    return integrate_pieces(pim, *pieces)


def imu_factor(pose_i: int, vel_i: int, pose_j: int, vel_j: int, bias_i: int, bias_j: int,
               pim: gtsam.PreintegratedCombinedMeasurements) -> gtsam.CombinedImuFactor:
    """``CombinedImuFactor`` between two keyframes (15-dim error: nav state + bias).

    Keys: ``X(i), V(i), X(j), V(j), B(i), B(j)``; velocities are world-frame (3,) vectors,
    biases ``imuBias.ConstantBias``. The bias random walk is inside the factor, so no
    separate bias between-factor is needed.
    """
    return gtsam.CombinedImuFactor(pose_i, vel_i, pose_j, vel_j, bias_i, bias_j, pim)
