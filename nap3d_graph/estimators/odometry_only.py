"""Odometry alone: the trajectory the robot has without NAP3D (the comparison's baseline).

On the odometry path every frame's pose is the increments chained from the first pose and the
covariance grows by the interval odometry's covariance at each keyframe (the drift model the
graph's odometry factors carry). On the IMU path it is the IMU dead-reckoned from the first
state with the prior bias (zero); its covariance is GTSAM's preintegrated one plus the effect
of the prior bias uncertainty (one running preintegration per bias axis, shifted by its
prior sigma).
"""

from __future__ import annotations

import gtsam
import numpy as np

from nap3d_graph.conventions import T_to_pose3, compose_covariance, inv_T, log_se3, pose3_to_T

__all__ = ["OdometryOnly"]


class OdometryOnly:
    """Chains the stream's motion and never takes a correction."""

    name = "odometry"

    def start(self, stream) -> None:
        self.stream = stream
        self.T = np.asarray(stream.T_world_cam0, float).copy()
        self.P0 = np.asarray(stream.P0, float).copy()
        self.P = self.P0.copy()
        self.accepted: list[int] = []
        if stream.imu is not None:
            pose0 = T_to_pose3(self.T)
            self.nav0 = gtsam.NavState(pose0.rotation(), pose0.translation(), np.asarray(stream.velocity0, float))
            cfg = stream.imu.config
            sigmas = np.r_[[cfg.accel_bias_prior_sigma] * 3, [cfg.gyro_bias_prior_sigma] * 3]
            self.biases = [gtsam.imuBias.ConstantBias()] + [
                gtsam.imuBias.ConstantBias(v[:3], v[3:]) for v in np.diag(sigmas)]
            # One running preintegration per bias (linear in the samples, not quadratic).
            self.pims = [gtsam.PreintegratedCombinedMeasurements(stream.imu.params, b) for b in self.biases]

    def step(self, i: int) -> None:
        s = self.stream
        if s.imu is not None:
            self._step_imu(i)
            return
        self.T = self.T @ s.increments[i]
        if i in s.interval_odometry:
            T_int, cov = s.interval_odometry[i]
            self.P = compose_covariance(self.P, T_int, cov)

    def _step_imu(self, i: int) -> None:
        t0, t1 = float(self.stream.timestamps[i - 1]), float(self.stream.timestamps[i])
        accel, gyro, dts = self.stream.imu.pieces(t0, t1)
        poses = []
        for pim, bias in zip(self.pims, self.biases):
            for a, w, dt in zip(accel, gyro, dts):
                pim.integrateMeasurement(a, w, float(dt))
            # predict() applies the bias-correction Jacobians to the pim's own biasHat (= the
            # bias it integrates with); asking for zero bias gives the bias-free motion.
            poses.append(pose3_to_T(pim.predict(self.nav0, bias).pose()))
        self.T = poses[0]
        cov = np.asarray(self.pims[0].preintMeasCov())[:6, :6]
        # Preintegrated position error is in the first body's frame; the pose's right
        # perturbation wants it in the current body: rotate by dR^T.
        J = np.eye(6)
        J[3:, 3:] = np.asarray(self.pims[0].deltaRij().matrix()).T
        shifts = np.array([log_se3(inv_T(self.T) @ T_b) for T_b in poses[1:]])
        A = np.asarray(T_to_pose3(inv_T(self.T) @ np.asarray(self.stream.T_world_cam0)).AdjointMap())
        P = J @ cov @ J.T + shifts.T @ shifts + A @ self.P0 @ A.T
        self.P = 0.5 * (P + P.T)

    def current(self):
        return self.T.copy(), self.P.copy()

    def final(self):
        return None
