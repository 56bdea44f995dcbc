"""GTSAM's ``NavStateImuEKF`` on the IMU path: predict with each IMU piece, update with NAP3D.

The filter's state is a ``NavState`` (attitude, position, velocity: 9-dim, GTSAM's tangent
order ``[rotation, position, velocity]``, right perturbation); it has no bias states, so the
IMU is fed with the prior bias (zero) and the unknown bias has to live in the process noise:
the accelerometer and gyroscope densities are inflated by the prior bias sigma over the
keyframe interval (``density^2 + sigma_b^2 * T_world_kf``: a constant bias acting for ``T_world_kf``
seconds moves the velocity as much as white noise of that density would). Without it the
filter believes its IMU, refuses the first correction the bias has pushed off, and never
recovers. It is the reason to compare it with the bias-estimating filter and graph.

A correction ``Z`` enters through ``updateWithVector(prediction=Log(Z^-1 T), H=[I6 | 0],
z=0, R)``: the prior factor's error, which the update drives to zero; it is gated first with
the graph's chi-square test.
"""

from __future__ import annotations

import logging

import gtsam
import numpy as np

from nap3d_graph.conventions import T_to_pose3, inv_T, log_se3, pose3_to_T
from nap3d_graph.factors.gate import chi2_gate_with_marginal

__all__ = ["NavStateEKF"]

log = logging.getLogger(__name__)

_H = np.hstack([np.eye(6), np.zeros((6, 3))])


class NavStateEKF:
    """``gtsam.NavStateImuEKF`` behind the estimator interface (IMU path only)."""

    name = "navstate-ekf"
    reports = ("causal",)

    def start(self, stream) -> None:
        if stream.imu is None:
            raise ValueError("NavStateImuEKF needs the IMU path (`odometry='imu'`)")
        cfg = stream.imu.config
        if not np.allclose(np.asarray(cfg.T_cam_imu, float), np.eye(4)):
            # The filter integrates the IMU at the body origin: no lever arm or rotation.
            raise ValueError("NavStateImuEKF assumes the IMU at the camera (identity extrinsics)")
        self.stream = stream
        self.accepted: list[int] = []
        self.gate_d2: dict[int, float] = {}
        pose0 = T_to_pose3(np.asarray(stream.T_world_cam0, float))
        P0 = np.zeros((9, 9))
        P0[:6, :6] = np.asarray(stream.P0, float)
        P0[6:, 6:] = np.eye(3) * cfg.velocity_prior_sigma**2
        nav0 = gtsam.NavState(pose0.rotation(), pose0.translation(), np.asarray(stream.velocity0, float))
        self.ekf = gtsam.NavStateImuEKF(nav0, P0, self._params(stream))

    @staticmethod
    def _params(stream) -> gtsam.PreintegrationParams:
        """The stream's IMU parameters with the prior bias folded into the noise densities."""
        cfg = stream.imu.config
        stamps = np.asarray(stream.timestamps, float)[list(stream.keyframes)]
        t_kf = float(np.median(np.diff(stamps))) if len(stamps) > 1 else 1.0
        params = gtsam.PreintegrationParams(cfg.gravity_vector())
        params.setAccelerometerCovariance(np.eye(3) * (cfg.accel_noise_density**2 + cfg.accel_bias_prior_sigma**2 * t_kf))
        params.setGyroscopeCovariance(np.eye(3) * (cfg.gyro_noise_density**2 + cfg.gyro_bias_prior_sigma**2 * t_kf))
        params.setIntegrationCovariance(np.asarray(stream.imu.params.getIntegrationCovariance()))
        return params

    def step(self, i: int) -> None:
        s = self.stream
        accel, gyro, dts = s.imu.pieces(float(s.timestamps[i - 1]), float(s.timestamps[i]))
        for a, w, dt in zip(accel, gyro, dts):
            self.ekf.predict(w, a, float(dt))
        if i not in s.corrections:
            return
        Z, R = s.corrections[i]
        T = pose3_to_T(self.ekf.state().pose())
        error = log_se3(inv_T(np.asarray(Z, float)) @ T)
        gate = chi2_gate_with_marginal(error, R, self.ekf.covariance(), p=s.gate_p, dof=6, jacobian=_H)
        self.gate_d2[i] = gate.d2
        if not gate.accepted:
            log.debug("navstate-ekf: correction at frame %d gated out (%s)", i, gate.reason)
            return
        self.ekf.updateWithVector(error, _H, np.zeros(6), np.asarray(R, float))
        self.accepted.append(i)

    def current(self):
        P = np.asarray(self.ekf.covariance())[:6, :6]
        return pose3_to_T(self.ekf.state().pose()), 0.5 * (P + P.T)

    def final(self):
        return None
