"""Error-state EKF on SE(3) (filterpy): the filtering baseline against the graph.

The nominal state lives outside the filter; filterpy's ``KalmanFilter`` carries only the
error state (zero after every reset) and its covariance. Perturbations are on the right,
GTSAM order ``[rotation, translation]``, so a NAP3D covariance is used exactly as the graph's
prior factor uses it.

* :class:`ErrorStateEKF` (odometry path): nominal ``T_world_cam``; at each keyframe the
  prediction composes the interval odometry (``F = Ad(T_int^-1)``, ``Q`` = the interval's
  covariance: the drift model the graph's odometry factor has); frames between keyframes are
  the keyframe's nominal pose with the increments chained on.
* :class:`ImuErrorStateEKF` (IMU path): nominal IMU attitude, position, velocity and biases
  (15-dim error ``[dtheta (body), dp (world), dv (world), dba, dbg]``), propagated sample by
  sample between frames (zero-order hold, the pieces GTSAM's preintegration uses).

A correction ``Z`` with covariance ``R`` is the innovation ``y = Log(T^-1 Z)`` with ``H`` the
pose's right perturbation, gated with the graph's chi-square test
(:func:`~nap3d_graph.factors.gate.chi2_gate_with_marginal`, probability ``stream.gate_p``)
before the update; the nominal state then absorbs the error (``T <- T Exp(dx)``) and the
covariance takes the reset Jacobian ``G = I - ad(dx)/2``.
"""

from __future__ import annotations

import logging

import numpy as np
from filterpy.kalman import KalmanFilter

from nap3d_graph.conventions import adjoint, exp_se3, exp_so3, inv_T, log_se3, make_T, skew
from nap3d_graph.factors.gate import chi2_gate_with_marginal

__all__ = ["ErrorStateEKF", "ImuErrorStateEKF"]

log = logging.getLogger(__name__)


def _ad_se3(xi: np.ndarray) -> np.ndarray:
    """Small adjoint ``ad(xi)`` (6, 6) of a twist in GTSAM order ``[w, v]``."""
    ad = np.zeros((6, 6))
    ad[:3, :3] = skew(xi[:3])
    ad[3:, :3] = skew(xi[3:])
    ad[3:, 3:] = skew(xi[:3])
    return ad


class _PoseCorrections:
    """The measurement update both filters share: gate, update, accepted list."""

    def _start_corrections(self, stream) -> None:
        self.stream = stream
        self.accepted: list[int] = []
        self.gate_d2: dict[int, float] = {}

    def _innovation(self, T_cam: np.ndarray, Z: np.ndarray) -> np.ndarray:
        return log_se3(inv_T(T_cam) @ Z)

    def _correct(self, i: int, T_cam: np.ndarray, H: np.ndarray) -> np.ndarray | None:
        """The error-state update for frame i's correction, or None (none, or gated out)."""
        if i not in self.stream.corrections:
            return None
        Z, R = self.stream.corrections[i]
        y = self._innovation(T_cam, np.asarray(Z, float))
        # The graph's test: the prior factor's error Log(Z^-1 T) ~ -y, S = R + H P H^T.
        gate = chi2_gate_with_marginal(-y, R, self.kf.P, p=self.stream.gate_p, dof=6, jacobian=H)
        self.gate_d2[i] = gate.d2
        if not gate.accepted:
            log.debug("%s: correction at frame %d gated out (%s)", self.name, i, gate.reason)
            return None
        self.kf.update(y.reshape(-1, 1), R=np.asarray(R, float), H=H)
        dx = self.kf.x.reshape(-1).copy()
        self.kf.x[:] = 0.0
        self.accepted.append(i)
        return dx


class ErrorStateEKF(_PoseCorrections):
    """Error-state EKF on the camera pose, driven by the interval odometry (6-dim error)."""

    name = "eskf"
    reports = ("causal",)

    def start(self, stream) -> None:
        self._start_corrections(stream)
        self.kf = KalmanFilter(dim_x=6, dim_z=6)
        self.kf.P = np.asarray(stream.P0, float).copy()
        self.T_world_kf = np.asarray(stream.T_world_cam0, float).copy()
        self.T = self.T_world_kf.copy()
        self.at_keyframe = True

    def step(self, i: int) -> None:
        s = self.stream
        if i not in s.interval_odometry:  # between keyframes: the odometry chained on
            self.T = self.T @ s.increments[i]
            self.at_keyframe = False
            return
        T_int, Q = s.interval_odometry[i]
        self.kf.predict(F=adjoint(inv_T(T_int)), Q=np.asarray(Q, float))
        self.T_world_kf = self.T_world_kf @ T_int
        dx = self._correct(i, self.T_world_kf, np.eye(6))
        if dx is not None:
            self.T_world_kf = self.T_world_kf @ exp_se3(dx)
            G = np.eye(6) - 0.5 * _ad_se3(dx)
            self.kf.P = G @ self.kf.P @ G.T
        self.T = self.T_world_kf.copy()
        self.at_keyframe = True

    def current(self):
        # The filter's covariance describes the keyframe's pose; between keyframes the
        # interval's covariance is not in the stream, so none is claimed there.
        return self.T.copy(), (0.5 * (self.kf.P + self.kf.P.T) if self.at_keyframe else None)

    def final(self):
        return None


class ImuErrorStateEKF(_PoseCorrections):
    """Error-state EKF with the IMU as its process model (15-dim error state).

    The nominal state is the IMU's (``T_world_imu = T_world_cam @ T_cam_imu``); the camera's
    pose and the measurement Jacobian go through the extrinsics.
    """

    name = "eskf"
    reports = ("causal",)

    def start(self, stream) -> None:
        self._start_corrections(stream)
        cfg = stream.imu.config
        self.T_cam_imu = np.asarray(cfg.T_cam_imu, float)
        self.T_imu_cam = inv_T(self.T_cam_imu)
        self.Ad_cam_imu = adjoint(self.T_cam_imu)
        T_world_imu = np.asarray(stream.T_world_cam0, float) @ self.T_cam_imu
        self.R, self.p = T_world_imu[:3, :3].copy(), T_world_imu[:3, 3].copy()
        self.v = np.asarray(stream.velocity0, float).copy()
        self.ba, self.bg = np.zeros(3), np.zeros(3)
        self.g = cfg.gravity_vector()
        self.noise = (cfg.gyro_noise_density**2, cfg.accel_noise_density**2, cfg.accel_bias_rw**2, cfg.gyro_bias_rw**2)
        self.kf = KalmanFilter(dim_x=15, dim_z=6)
        P0 = np.zeros((15, 15))
        A = np.linalg.inv(self.Ad_cam_imu)  # camera-pose perturbation -> IMU-pose perturbation
        P_imu = A @ np.asarray(stream.P0, float) @ A.T
        P0[:3, :3] = P_imu[:3, :3]
        P0[3:6, 3:6] = self.R @ P_imu[3:, 3:] @ self.R.T  # body-frame translation -> world
        P0[6:9, 6:9] = np.eye(3) * cfg.velocity_prior_sigma**2
        P0[9:12, 9:12] = np.eye(3) * cfg.accel_bias_prior_sigma**2
        P0[12:, 12:] = np.eye(3) * cfg.gyro_bias_prior_sigma**2
        self.kf.P = P0

    def _T_world_cam(self) -> np.ndarray:
        return make_T(self.R, self.p) @ self.T_imu_cam

    def _H(self) -> np.ndarray:
        """d(camera pose right perturbation) / d(error state) (6, 15)."""
        H_imu = np.zeros((6, 15))
        H_imu[:3, :3] = np.eye(3)
        H_imu[3:, 3:6] = self.R.T
        return self.Ad_cam_imu @ H_imu

    def _propagate(self, t0: float, t1: float) -> None:
        accel, gyro, dts = self.stream.imu.pieces(t0, t1)
        q_g, q_a, q_ba, q_bg = self.noise
        Phi, Qd = np.eye(15), np.zeros((15, 15))
        I3 = np.eye(3)
        for a, w, dt in zip(accel, gyro, dts):
            omega, f = w - self.bg, a - self.ba
            dR = exp_so3(omega * dt)
            F = np.eye(15)
            F[:3, :3] = dR.T
            F[:3, 12:] = -I3 * dt
            F[3:6, 6:9] = I3 * dt
            F[6:9, :3] = -self.R @ skew(f) * dt
            F[6:9, 9:12] = -self.R * dt
            Q = np.zeros((15, 15))
            Q[:3, :3], Q[6:9, 6:9] = I3 * q_g * dt, I3 * q_a * dt
            Q[9:12, 9:12], Q[12:, 12:] = I3 * q_ba * dt, I3 * q_bg * dt
            Phi, Qd = F @ Phi, F @ Qd @ F.T + Q
            acc_world = self.R @ f + self.g
            self.p = self.p + self.v * dt + 0.5 * acc_world * dt * dt
            self.v = self.v + acc_world * dt
            self.R = self.R @ dR
        # One filterpy prediction for the whole frame interval: Phi and Qd compose the pieces.
        self.kf.predict(F=Phi, Q=Qd)

    def step(self, i: int) -> None:
        s = self.stream
        self._propagate(float(s.timestamps[i - 1]), float(s.timestamps[i]))
        dx = self._correct(i, self._T_world_cam(), self._H())
        if dx is None:
            return
        self.R = self.R @ exp_so3(dx[:3])
        self.p, self.v = self.p + dx[3:6], self.v + dx[6:9]
        self.ba, self.bg = self.ba + dx[9:12], self.bg + dx[12:]
        G = np.eye(15)
        G[:3, :3] -= 0.5 * skew(dx[:3])
        self.kf.P = G @ self.kf.P @ G.T

    def pose_covariance(self) -> np.ndarray:
        """The camera pose's covariance (6, 6), GTSAM order, right perturbation."""
        H = self._H()
        P = H @ self.kf.P @ H.T
        return 0.5 * (P + P.T)

    def current(self):
        return self._T_world_cam(), self.pose_covariance()

    def final(self):
        return None

    @property
    def biases(self) -> np.ndarray:
        """Current bias estimate ``[ba (3), bg (3)]`` (m/s^2, rad/s)."""
        return np.r_[self.ba, self.bg]
