"""The drift-correction run with an IMU between keyframes (``run --odom imu``).

The graph of :class:`~nap3d_graph.run.pipeline.Pipeline`, with the odometry between keyframes
replaced by IMU preintegration: each keyframe has a pose ``X(k)``, a world-frame velocity
``V(k)`` and an IMU bias ``B(k)``; consecutive keyframes are tied by a ``CombinedImuFactor``
(GTSAM's preintegration, bias random walk inside); priors hold the first pose, velocity and
bias; the NAP3D corrections are gated and added exactly as on the odometry path. Frames
between keyframes are predicted from the nearest earlier keyframe's state with the IMU (the
causal trajectory from each keyframe as it was known then). The biases are estimated and
written out (``RunResult.imu_biases``).

Gravity in the field's frame is refined in the graph. A field's frame is whatever its
mapping gave it, so the graph's world is a gravity-aligned navigation frame N (gravity
``(0, 0, -g)``), in which the states and the IMU factors live, and the field's frame is a
variable ``M(0)`` = ``T_nav_field``, as the map anchor is on the odometry path: the NAP3D
corrections measure ``between(M(0), X(k))`` = ``T_field_cam``. Its prior starts from the gravity
given or estimated (``ImuConfig.gravity_vector()``, e.g. the accelerometer at the start) and
lets its tilt move by ``ImuConfig.gravity_sigma_deg`` per axis, while its heading about gravity
and its origin, which no IMU measurement can tell, are held (the gauge). Every trajectory the
run writes is in the field's frame (``T_field_nav`` estimated then, for the causal one); the
refined gravity is ``RunResult.gravity_world``.

When corrections stop landing (the views left the field, say), the IMU alone drifts by metres
within seconds. After ``FALLBACK_STREAK`` (3) keyframes refused in a row, the run says so and falls
back on a visual odometry (``ImuOdometry.fallback``: ``run --fallback-odom``, dense by default)
from that keyframe on: its increments chain the frames between keyframes and enter the graph as
a between factor beside each IMU factor, until a correction is accepted again
(``RunResult.fallback_intervals``).

The "odometry alone" trajectory of an IMU run is the IMU dead-reckoned from the first
state with the prior bias (zero) and the gravity as given: what the robot would have without
NAP3D.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, M, V, X

from nap3d_graph.conventions import T_to_pose3, compose_covariance, inv_T, pose3_to_T
from nap3d_graph.factors import imu_factor, noise_model, odometry_factor
from nap3d_graph.imu import ImuConfig, ImuStream
from nap3d_graph.run.pipeline import Pipeline

__all__ = ["ImuOdometry", "ImuPipeline", "gravity_aligned_frame"]

log = logging.getLogger(__name__)


@dataclass
class ImuOdometry:
    """The IMU as a run's motion source: its stream and the state it starts from."""

    stream: ImuStream
    T_world_cam0: np.ndarray
    velocity0: np.ndarray
    name: str = "imu"
    #: A frame odometry (``increment``, ``prime``) the run falls back on when corrections stop.
    fallback: object | None = None

    def initial_pose(self) -> np.ndarray:
        return np.asarray(self.T_world_cam0, dtype=float).copy()

    @classmethod
    def from_sequence(cls, sequence, config: ImuConfig | None = None, initial_pose=None) -> "ImuOdometry":
        """The sequence's IMU, starting at its ground truth's first pose and velocity (or
        ``initial_pose`` at rest)."""
        stream = ImuStream.from_sequence(sequence, config)
        T_gt = getattr(sequence, "T_world_cam_gt", None)
        if initial_pose is not None:
            return cls(stream, np.asarray(initial_pose, float), np.zeros(3))
        if T_gt is None or not np.all(np.isfinite(T_gt[:2])):
            raise ValueError(f"{sequence.path}: --odom imu needs the starting pose: give --initial-pose")
        dt = float(sequence.timestamps[1] - sequence.timestamps[0])
        velocity = (T_gt[1][:3, 3] - T_gt[0][:3, 3]) / dt
        return cls(stream, T_gt[0], velocity)


def gravity_aligned_frame(g_field: np.ndarray) -> np.ndarray:
    """``T_nav_field`` (4, 4): the smallest turn taking gravity as seen in the field's frame,
    ``g_field`` (3,), to ``-z`` (a navigation frame's), with no offset."""
    from scipy.spatial.transform import Rotation

    down = np.asarray(g_field, dtype=float) / np.linalg.norm(g_field)
    T_nav_field = np.eye(4)
    T_nav_field[:3, :3] = Rotation.align_vectors([[0.0, 0.0, -1.0]], [down])[0].as_matrix()
    return T_nav_field


class ImuPipeline(Pipeline):
    """:class:`Pipeline` with IMU preintegration between keyframes (see the module docstring)."""

    supports_graph_window = False  # velocities and biases would need marginalising too

    #: How firmly the gravity frame's heading (rad) and origin (m) are held: they are the
    #: gauge of a gravity-aligned frame, which no IMU measurement can tell.
    GAUGE_SIGMA = 1e-4

    def __init__(self, sequence, field, odometry, config=None, correction_hook=None):
        super().__init__(sequence, field, odometry, config, correction_hook)
        if self.config.use_anchor:
            raise ValueError("--anchor does not apply with --odom imu: the IMU path estimates the field's frame's "
                             "tilt (its gravity) itself")

    def _start(self) -> None:
        field_config = self.odometry.stream.config
        self.g_field0 = field_config.gravity_vector()
        self.T_nav_field0 = gravity_aligned_frame(self.g_field0)
        # The states and the IMU factors live in the navigation frame (gravity -z).
        self.imu: ImuStream = self.odometry.stream.with_config(field_config.in_gravity_frame())
        super()._start()  # the gravity frame enters as the anchor M(0) (see _anchor_prior)
        t0 = float(self.sequence.timestamps[0])
        T_nav_cam0 = self.T_nav_field0 @ self.odometry.initial_pose()
        self.velocity0_nav = self.T_nav_field0[:3, :3] @ np.asarray(self.odometry.velocity0, float)
        self.nav_kf = gtsam.NavState(T_to_pose3(T_nav_cam0), self.velocity0_nav)
        self.bias_kf = gtsam.imuBias.ConstantBias()
        self.t_kf = t0
        # Each keyframe's state as known then, with the gravity frame's estimate then (causal).
        self.kf_states: list[tuple[float, gtsam.NavState, gtsam.imuBias.ConstantBias, np.ndarray]] = []
        # Dead reckoning for "odometry alone": in the field's frame with the gravity as given.
        field_pose = T_to_pose3(self.odometry.initial_pose())
        self._dead_start = (t0, gtsam.NavState(field_pose, np.asarray(self.odometry.velocity0, float)))
        self._notes: list[str] = []
        # The visual odometry fallback: the frame it started at (None: the IMU alone), its
        # increments (frame -> T_prev_cur), and the frame spans it ran.
        self._vo_since: int | None = None
        self._vo_increments: dict[int, np.ndarray] = {}
        self._refused_in_row = 0
        self.fallback_intervals: list[list[int | None]] = []

    def _anchored(self) -> bool:
        return True

    def _anchor_prior(self):
        """``M(0)`` = ``T_nav_field``: tilt free by ``gravity_sigma_deg``, heading and origin held.
        The prior's rotation is in the field's axes (GTSAM's right perturbation), where the
        heading is the turn about gravity's direction."""
        g_hat = self.g_field0 / np.linalg.norm(self.g_field0)
        tilt = np.radians(self.odometry.stream.config.gravity_sigma_deg)
        about_g = np.outer(g_hat, g_hat)
        covariance = np.zeros((6, 6))
        covariance[:3, :3] = tilt ** 2 * (np.eye(3) - about_g) + self.GAUGE_SIGMA ** 2 * about_g
        covariance[3:, 3:] = self.GAUGE_SIGMA ** 2 * np.eye(3)
        prior = gtsam.PriorFactorPose3(M(0), T_to_pose3(self.T_nav_field0), noise_model(covariance=covariance))
        return prior, self.T_nav_field0

    def _field_from_nav(self, values: gtsam.Values | None = None) -> np.ndarray:
        """``T_field_nav`` (4, 4) as estimated in ``values`` (iSAM2's estimate now by default)."""
        T_nav_field = (pose3_to_T(values.atPose3(M(0))) if values is not None
                       else pose3_to_T(self.isam.calculateEstimatePose3(M(0))))
        return inv_T(T_nav_field)

    def _odometry_needs_frames(self) -> bool:
        return self._vo_since is not None  # the fallback reads every frame

    def _overlapping(self) -> bool:
        # The IMU keyframe state (nav_kf, bias_kf) is taken right after each correction.
        return False

    def _predict(self, t_from: float, nav: gtsam.NavState, bias, t_to: float) -> gtsam.NavState:
        if t_to <= t_from:
            return nav
        return self.imu.preintegrate(t_from, t_to, bias).predict(nav, bias)

    def _propagate_odometry(self, i: int, frame) -> None:
        t = float(self.sequence.timestamps[i])
        # Dead reckoning from the start with the prior bias: the IMU alone, for comparison.
        dead = self._predict(self._dead_start[0], self._dead_start[1], gtsam.imuBias.ConstantBias(), t)
        self.T_odom.append(pose3_to_T(dead.pose()))
        self.increments.append(np.linalg.inv(self.T_odom[-2]) @ self.T_odom[-1])
        self.dt_since_kf += float(self.sequence.timestamps[i] - self.sequence.timestamps[i - 1])
        if self._vo_since is not None:
            inc = self.odometry.fallback.increment(i, frame)
            self._vo_increments[i] = inc.T_prev_cur
            self.T_since_kf = self.T_since_kf @ inc.T_prev_cur
            self.cov_since_kf = compose_covariance(self.cov_since_kf, inc.T_prev_cur, inc.covariance)

    def _add_keyframe(self, i: int) -> None:
        j = len(self.keyframe_indices)
        self.keyframe_indices.append(i)
        t = float(self.sequence.timestamps[i])
        cfg = self.imu.config
        if j == 0:
            # The starting pose is known in the field's frame: a prior on between(M(0), X(0)).
            T_field_cam0 = self.T_odom[0]
            self._add_factor(gtsam.BetweenFactorPose3(
                M(0), X(0), T_to_pose3(T_field_cam0),
                noise_model(rot_sigma_rad=self.config.prior_rot_sigma_rad, trans_sigma_m=self.config.prior_trans_sigma_m)))
            self._add_factor(gtsam.PriorFactorVector(V(0), self.velocity0_nav,
                                                     gtsam.noiseModel.Isotropic.Sigma(3, cfg.velocity_prior_sigma)))
            bias_sigmas = np.r_[[cfg.accel_bias_prior_sigma] * 3, [cfg.gyro_bias_prior_sigma] * 3]
            self._add_factor(gtsam.PriorFactorConstantBias(B(0), gtsam.imuBias.ConstantBias(),
                                                           gtsam.noiseModel.Diagonal.Sigmas(bias_sigmas)))
            self.new_values.insert(X(0), self.nav_kf.pose())
            self.new_values.insert(V(0), self.velocity0_nav)
            self.new_values.insert(B(0), gtsam.imuBias.ConstantBias())
            self.T_pred = pose3_to_T(self.nav_kf.pose())
        else:
            pim = self.imu.preintegrate(self.t_kf, t, self.bias_kf)
            self._notes = self.imu.notes_between(self.t_kf, t)
            self._add_factor(imu_factor(X(j - 1), V(j - 1), X(j), V(j), B(j - 1), B(j), pim))
            predicted = pim.predict(self.nav_kf, self.bias_kf)
            pose, velocity = predicted.pose(), predicted.velocity()
            if self._vo_since is not None:  # the fallback: its chain is the prediction and a factor
                cov = self.cov_since_kf + self.config.drift_covariance(self.T_since_kf, self.dt_since_kf)
                self._add_factor(odometry_factor(X(j - 1), X(j), self.T_since_kf, cov))
                self.interval_odometry[i] = (self.T_since_kf.copy(), cov.copy())
                T_nav_kf = pose3_to_T(self.nav_kf.pose())
                pose = T_to_pose3(T_nav_kf @ self.T_since_kf)
                velocity = (pose.translation() - T_nav_kf[:3, 3]) / max(self.dt_since_kf, 1e-6)
            self.T_pred = pose3_to_T(pose)
            self.new_values.insert(X(j), pose)
            self.new_values.insert(V(j), velocity)
            self.new_values.insert(B(j), self.bias_kf)
        self.dt_since_kf = 0.0
        self.T_since_kf = np.eye(4)
        self.cov_since_kf = np.zeros((6, 6))
        self._pending_record = self._keyframe_record(i, X(j), reason="; ".join(self._notes))
        self._update_isam()

    def _correct_keyframe(self, i: int, frame) -> None:
        notes = self._pending().reason
        self._pending().reason = ""
        super()._correct_keyframe(i, frame)
        record = self._pending()
        if notes:  # the IMU notes of this interval stay with the keyframe's row
            record.reason = f"{record.reason}; {notes}" if record.reason else notes
        self._switch_motion(i, frame, record.accepted)

    #: Keyframes refused in a row before the run falls back on the visual odometry (fewer than
    #: the warning's REFUSAL_STREAK: the IMU alone drifts quadratically and faster).
    FALLBACK_STREAK = 3

    def _switch_motion(self, i: int, frame, accepted: bool) -> None:
        """Fall back on the visual odometry after FALLBACK_STREAK refused keyframes (from
        keyframe i, whose frame primes it); back to the IMU alone once a correction lands."""
        self._refused_in_row = 0 if accepted else self._refused_in_row + 1
        if accepted and self._vo_since is not None:
            log.warning("a correction landed again at frame %d: back on the IMU alone between keyframes", i)
            self.fallback_intervals[-1][1] = i
            self._vo_since = None
        elif (self._refused_in_row >= self.FALLBACK_STREAK and self._vo_since is None and frame is not None
              and getattr(self.odometry, "fallback", None) is not None):
            log.warning("the last %d keyframes (to frame %d) were refused: the IMU alone drifts by metres within "
                        "seconds, so the run falls back on the visual odometry (%s) between keyframes until a "
                        "correction lands", self._refused_in_row, i, getattr(self.odometry.fallback, "name", "vo"))
            self.odometry.fallback.prime(frame)
            self._vo_since = i
            self.fallback_intervals.append([i, None])

    def _finish_keyframe(self):
        j = len(self.keyframe_indices) - 1
        estimate = self.isam.calculateEstimate()
        self.nav_kf = gtsam.NavState(estimate.atPose3(X(j)), estimate.atVector(V(j)))
        self.bias_kf = estimate.atConstantBias(B(j))
        self.t_kf = float(self.sequence.timestamps[self.keyframe_indices[-1]])
        T_field_nav = self._field_from_nav(estimate)
        self.kf_states.append((self.t_kf, self.nav_kf, self.bias_kf, T_field_nav))
        record = super()._finish_keyframe()
        self.T_last_kf_est = T_field_nav @ self.T_last_kf_est  # the causal pose, in the field's frame
        return record

    def _velocity(self, i: int) -> np.ndarray | None:
        """Body twist (GTSAM order) at frame i: the gyro's rate and the velocity in the body."""
        if not self.kf_states:
            return None
        t = float(self.sequence.timestamps[i])
        k = int(np.clip(np.searchsorted(self.imu.stamps, t) - 1, 0, len(self.imu.stamps) - 1))
        nav = self._predict(self.t_kf, self.nav_kf, self.bias_kf, t)
        v_body = nav.pose().rotation().matrix().T @ nav.velocity()
        return np.r_[self.imu.gyro[k] - self.bias_kf.gyroscope(), v_body]

    # --- per-frame trajectories: predicted from keyframe states -----------------------------

    def _frames_from_states(self, states: list[tuple[float, gtsam.NavState, gtsam.imuBias.ConstantBias, np.ndarray]],
                            n: int) -> np.ndarray:
        """(n, 4, 4) ``T_field_cam``: each frame predicted from the latest keyframe state at or
        before it (navigation frame), taken into the field's frame with that state's
        ``T_field_nav``."""
        stamps = np.asarray(self.sequence.timestamps[:n], dtype=float)
        T_field_cam = np.empty((n, 4, 4))
        kf_times = np.array([s[0] for s in states])
        for i, t in enumerate(stamps):
            k = int(np.searchsorted(kf_times, t + 1e-9) - 1)
            if k < 0:
                T_field_cam[i] = self.T_odom[i]
                continue
            t_k, nav, bias, T_field_nav = states[k]
            T_field_cam[i] = T_field_nav @ pose3_to_T(self._predict(t_k, nav, bias, float(t)).pose())
        return T_field_cam

    def _chain_between_keyframes(self, T_kf: dict[int, np.ndarray], n: int) -> np.ndarray:
        estimate = self._final_values
        T_field_nav = self._field_from_nav(estimate)
        states = []
        for j, idx in enumerate(self.keyframe_indices):
            nav = gtsam.NavState(estimate.atPose3(X(j)), estimate.atVector(V(j)))
            states.append((float(self.sequence.timestamps[idx]), nav, estimate.atConstantBias(B(j)), T_field_nav))
        return self._with_fallback_chains(self._frames_from_states(states, n))

    def _chain_forward(self, n: int) -> np.ndarray:
        T_field_cam = self._frames_from_states(self.kf_states, n)
        for i in self._vo_increments:  # frames the fallback chained, as the run had them
            if i < n:
                T_field_cam[i] = self._online[i]
        return T_field_cam

    def _with_fallback_chains(self, T_field_cam: np.ndarray) -> np.ndarray:
        """The frames the fallback chained, chained again from their keyframe's final pose."""
        keyframes = set(self.keyframe_indices)
        for i in sorted(self._vo_increments):
            if i < len(T_field_cam) and i not in keyframes:
                T_field_cam[i] = T_field_cam[i - 1] @ self._vo_increments[i]
        return T_field_cam

    def _final_estimate(self) -> gtsam.Values:
        self._final_values = super()._final_estimate()
        return self._final_values

    def _finish(self, n: int):
        result = super()._finish(n)
        if self.keyframe_indices:
            values = self._final_values
            g = float(np.linalg.norm(self.g_field0))
            result.gravity_world = self._field_from_nav(values)[:3, :3] @ np.array([0.0, 0.0, -g])
            result.gravity_world_prior = self.g_field0.copy()
            result.imu_biases = np.array([np.r_[values.atConstantBias(B(j)).accelerometer(),
                                                values.atConstantBias(B(j)).gyroscope()]
                                          for j in range(len(self.keyframe_indices))])
            try:
                marginals = gtsam.Marginals(self._final_graph(), values)
                result.imu_bias_sigmas = np.array([np.sqrt(np.diag(marginals.marginalCovariance(B(j))))
                                                   for j in range(len(self.keyframe_indices))])
            except RuntimeError as exc:  # an ill-posed graph still has its estimate
                log.warning("bias marginals not computed: %s", exc)
            result.imu_skipped = list(self.imu.skipped)
        result.fallback_intervals = [[a, n - 1 if b is None else b] for a, b in self.fallback_intervals]
        return result

    def _final_graph(self) -> gtsam.NonlinearFactorGraph:
        graph = gtsam.NonlinearFactorGraph()
        accepted = {r.frame_index for r in self.records if r.accepted}
        for factor, is_nap3d, frame in self.factor_log:
            if not is_nap3d or frame in accepted:
                graph.add(factor)
        return graph
