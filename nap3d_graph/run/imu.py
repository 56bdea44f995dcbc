"""The IMU between keyframes (``run --odom imu``): a motion model for the run.

:class:`ImuMotion` is what :class:`~nap3d_graph.run.pipeline.Pipeline` moves by when its
odometry is an :class:`ImuOdometry` (:mod:`nap3d_graph.run.motion`): each keyframe has a pose ``X(k)``, a world-frame velocity
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
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, M, V, X

from nap3d_graph.conventions import T_to_pose3, compose_covariance, inv_T, pose3_to_T, pose_error
from nap3d_graph.factors import imu_factor, noise_model, odometry_factor
from nap3d_graph.motion.imu import ImuConfig, ImuStream
from nap3d_graph.run.config import PipelineConfig
from nap3d_graph.run.graph import KeyframeGraph
from nap3d_graph.run.history import FrameLog
from nap3d_graph.run.motion import KeyframeEntry
from nap3d_graph.run.records import RunResult

__all__ = ["ImuOdometry", "ImuMotion", "gravity_aligned_frame"]

log = logging.getLogger(__name__)


@dataclass
class ImuOdometry:
    """The IMU as a run's motion source: its stream and the state it starts from."""

    stream: ImuStream
    T_world_cam0: np.ndarray
    velocity0: np.ndarray
    name: str = "imu"
    #: A frame odometry (``increment``, ``prime``) the run falls back on when corrections stop.
    fallback: Any = None

    def initial_pose(self) -> np.ndarray:
        return np.asarray(self.T_world_cam0, dtype=float).copy()

    @classmethod
    def from_sequence(cls, sequence, config: ImuConfig | None = None, initial_pose=None) -> "ImuOdometry":
        """The sequence's IMU, starting at its ground truth's first pose and velocity (or
        ``initial_pose`` at rest)."""
        stream = ImuStream.from_sequence(sequence, config)
        T_world_cam_gt = getattr(sequence, "T_world_cam_gt", None)
        if initial_pose is not None:
            return cls(stream, np.asarray(initial_pose, float), np.zeros(3))
        if T_world_cam_gt is None or not np.all(np.isfinite(T_world_cam_gt[:2])):
            raise ValueError(f"{sequence.path}: `odometry='imu'` needs the starting pose: give `initial_pose`")
        dt = float(sequence.timestamps[1] - sequence.timestamps[0])
        velocity = (T_world_cam_gt[1][:3, 3] - T_world_cam_gt[0][:3, 3]) / dt
        return cls(stream, T_world_cam_gt[0], velocity)


def gravity_aligned_frame(g_field: np.ndarray) -> np.ndarray:
    """``T_nav_field`` (4, 4): the smallest turn taking gravity as seen in the field's frame,
    ``g_field`` (3,), to ``-z`` (a navigation frame's), with no offset."""
    from scipy.spatial.transform import Rotation

    down = np.asarray(g_field, dtype=float) / np.linalg.norm(g_field)
    T_nav_field = np.eye(4)
    T_nav_field[:3, :3] = Rotation.align_vectors([[0.0, 0.0, -1.0]], [down])[0].as_matrix()
    return T_nav_field


class ImuMotion:
    """IMU preintegration between keyframes, as the run's motion model (see the module
    docstring and :mod:`nap3d_graph.run.motion`)."""

    allows_overlap = False  # the keyframe's IMU state is taken right after its correction
    allows_graph_window = False  # velocities and biases would need marginalising too
    estimates_field_frame = True  # the gravity frame M(0)

    #: How firmly the gravity frame's heading (rad) and origin (m) are held: they are the
    #: gauge of a gravity-aligned frame, which no IMU measurement can tell.
    GAUGE_SIGMA = 1e-4

    #: Keyframes refused in a row before the run falls back on the visual odometry (fewer than
    #: the run's warning streak: the IMU alone drifts quadratically and faster).
    FALLBACK_STREAK = 3

    def __init__(self, odometry: ImuOdometry, config: PipelineConfig, t0: float):
        self.odometry, self.config = odometry, config
        self.name = odometry.name
        field_config = odometry.stream.config
        self.g_field0 = field_config.gravity_vector()
        self.T_nav_field0 = gravity_aligned_frame(self.g_field0)
        # The states and the IMU factors live in the navigation frame (gravity -z).
        self.imu: ImuStream = odometry.stream.with_config(field_config.in_gravity_frame())
        T_nav_cam0 = self.T_nav_field0 @ odometry.initial_pose()
        self.velocity0_nav = self.T_nav_field0[:3, :3] @ np.asarray(odometry.velocity0, float)
        self.nav_kf = gtsam.NavState(T_to_pose3(T_nav_cam0), self.velocity0_nav)
        self.bias_kf = gtsam.imuBias.ConstantBias()
        self.t_kf = t0
        # Each keyframe's state as known then, with the gravity frame's estimate then (causal).
        self.kf_states: list[tuple[float, gtsam.NavState, gtsam.imuBias.ConstantBias, np.ndarray]] = []
        # Dead reckoning for "odometry alone": in the field's frame with the gravity as given.
        # A running preintegration from the start, extended a frame at a time (as the estimators'
        # IMU-alone row does), on the field-frame stream.
        self._dead_nav0 = gtsam.NavState(T_to_pose3(odometry.initial_pose()), np.asarray(odometry.velocity0, float))
        self._dead_pim = gtsam.PreintegratedCombinedMeasurements(odometry.stream.params, gtsam.imuBias.ConstantBias())
        self._dead_t = t0
        # The fallback's last IMU prediction from the keyframe state: (t_kf, t, NavState).
        self._fallback_nav: tuple[float, float, gtsam.NavState] | None = None
        self.T_world_cam_odom: FrameLog[np.ndarray] = FrameLog([odometry.initial_pose()])
        self.increments: FrameLog[np.ndarray] = FrameLog([np.eye(4)])
        self._notes: list[str] = []
        self.dt_since_kf = 0.0
        self.T_world_kf = self.T_world_cam_odom[0]  # the latest keyframe's estimate in the field's frame
        # The visual odometry fallback: its chain since the last keyframe, the frame it started
        # at (None: the IMU alone), its increments (frame -> T_prev_cur), and the spans it ran.
        self.T_kf_cam = np.eye(4)
        self.cov_since_kf = np.zeros((6, 6))
        self._vo_since: int | None = None
        self._vo_increments: dict[int, np.ndarray] = {}
        self._refused_in_row = 0
        self.fallback_intervals: list[list[int | None]] = []

    @property
    def needs_frames(self) -> bool:
        return self._vo_since is not None  # the fallback reads every frame

    @property
    def doubted(self) -> bool:
        return False

    def anchor_prior(self) -> tuple[gtsam.NonlinearFactor, np.ndarray]:
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

    def prime(self, frame) -> None:
        pass  # the fallback is primed when it starts

    @staticmethod
    def _field_from_nav(values: gtsam.Values) -> np.ndarray:
        """``T_field_nav`` (4, 4) as estimated in ``values``."""
        return inv_T(pose3_to_T(values.atPose3(M(0))))

    def _predict(self, t_from: float, nav: gtsam.NavState, bias, t_to: float) -> gtsam.NavState:
        if t_to <= t_from:
            return nav
        return self.imu.preintegrate(t_from, t_to, bias).predict(nav, bias)

    def frame(self, i: int, frame, t: float, dt: float) -> None:
        # Dead reckoning from the start with the prior bias: the IMU alone, for comparison.
        if t > self._dead_t:
            self.odometry.stream.extend(self._dead_pim, self._dead_t, t)
            self._dead_t = t
        dead = self._dead_pim.predict(self._dead_nav0, gtsam.imuBias.ConstantBias())
        self.T_world_cam_odom.append(pose3_to_T(dead.pose()))
        self.increments.append(np.linalg.inv(self.T_world_cam_odom[-2]) @ self.T_world_cam_odom[-1])
        self.dt_since_kf += dt
        if self._vo_since is not None:
            inc = self.odometry.fallback.increment(i, frame)
            T_prev_cur, covariance = self._checked_step(inc, t - dt, t)
            self._vo_increments[i] = T_prev_cur
            self.T_kf_cam = self.T_kf_cam @ T_prev_cur
            self.cov_since_kf = compose_covariance(self.cov_since_kf, T_prev_cur, covariance)

    #: A fallback step that disagrees with the IMU's own motion over the frame by more than
    #: this (m, deg) is replaced by the IMU's: over one frame the IMU does not drift, a visual
    #: odometry's wrong minimum (a one-frame jump) does.
    STEP_GATE = (0.03, 3.0)

    def _checked_step(self, inc, t_prev: float, t: float) -> tuple[np.ndarray, np.ndarray]:
        """The fallback's step, or the IMU's over the same frame (predicted from the last
        keyframe's state) when the two disagree beyond ``STEP_GATE``."""
        cached = self._fallback_nav
        if cached is not None and cached[0] == self.t_kf and cached[1] == t_prev:
            nav_prev = cached[2]  # the previous frame's prediction from the same keyframe state
        else:
            nav_prev = self._predict(self.t_kf, self.nav_kf, self.bias_kf, t_prev)
        nav_cur = self._predict(self.t_kf, self.nav_kf, self.bias_kf, t)
        self._fallback_nav = (self.t_kf, t, nav_cur)
        T_imu = inv_T(pose3_to_T(nav_prev.pose())) @ pose3_to_T(nav_cur.pose())
        moved_m, turned_deg = pose_error(inc.T_prev_cur, T_imu)
        if moved_m <= self.STEP_GATE[0] and turned_deg <= self.STEP_GATE[1]:
            return inc.T_prev_cur, inc.covariance
        log.debug("fallback step at t=%.3f disagrees with the IMU by %.3f m / %.2f deg: the IMU's is used", t,
                  moved_m, turned_deg)
        return T_imu, np.asarray(inc.covariance) + np.diag([np.radians(1.0) ** 2] * 3 + [0.02 ** 2] * 3)

    def since_keyframe(self) -> np.ndarray:
        return self.T_kf_cam

    def reframe(self, T_new_old: np.ndarray) -> None:
        raise ValueError("the IMU path cannot move into another frame mid-run (its gravity and velocities are "
                         "in its own): give it its start in the map")

    def add_keyframe(self, j: int, i: int, t: float) -> KeyframeEntry:
        """Keyframe ``j`` (frame ``i`` at ``t``): its pose, velocity and bias, tied to the last
        keyframe's by a ``CombinedImuFactor`` (and the fallback's between factor while it runs),
        or, the first, held by priors; the prediction (navigation frame) and the fallback's
        interval ``(T_prev_kf_kf, covariance)`` when it ran (see :class:`KeyframeEntry`)."""
        cfg = self.imu.config
        interval = None
        factors: list = []
        self._notes = []
        if j == 0:
            # The starting pose is known in the field's frame: a prior on between(M(0), X(0)).
            factors.append(gtsam.BetweenFactorPose3(
                M(0), X(0), T_to_pose3(self.T_world_cam_odom[0]),
                noise_model(rot_sigma_rad=self.config.prior_rot_sigma_rad, trans_sigma_m=self.config.prior_trans_sigma_m)))
            factors.append(gtsam.PriorFactorVector(V(0), self.velocity0_nav,
                                              gtsam.noiseModel.Isotropic.Sigma(3, cfg.velocity_prior_sigma)))
            bias_sigmas = np.r_[[cfg.accel_bias_prior_sigma] * 3, [cfg.gyro_bias_prior_sigma] * 3]
            factors.append(gtsam.PriorFactorConstantBias(B(0), gtsam.imuBias.ConstantBias(),
                                                    gtsam.noiseModel.Diagonal.Sigmas(bias_sigmas)))
            pose, velocity = self.nav_kf.pose(), self.velocity0_nav
        else:
            pim = self.imu.preintegrate(self.t_kf, t, self.bias_kf)
            self._notes = self.imu.notes_between(self.t_kf, t)
            factors.append(imu_factor(X(j - 1), V(j - 1), X(j), V(j), B(j - 1), B(j), pim))
            predicted = pim.predict(self.nav_kf, self.bias_kf)
            pose, velocity = predicted.pose(), predicted.velocity()
            if self._vo_since is not None:  # the fallback: its chain is the prediction and a factor
                cov = self.cov_since_kf + self.config.drift_covariance(self.T_kf_cam, self.dt_since_kf)
                factors.append(odometry_factor(X(j - 1), X(j), self.T_kf_cam, cov))
                interval = (self.T_kf_cam.copy(), cov.copy())
                T_nav_kf = pose3_to_T(self.nav_kf.pose())
                pose = T_to_pose3(T_nav_kf @ self.T_kf_cam)
                velocity = (pose.translation() - T_nav_kf[:3, 3]) / max(self.dt_since_kf, 1e-6)
        values = [(X(j), pose), (V(j), velocity), (B(j), self.bias_kf if j else gtsam.imuBias.ConstantBias())]
        self.dt_since_kf = 0.0
        self.T_kf_cam = np.eye(4)
        self.cov_since_kf = np.zeros((6, 6))
        return KeyframeEntry(pose3_to_T(pose), factors, values, interval)

    def interval_notes(self) -> str:
        """The IMU's skipped samples and bridged gaps in the interval that ended at the keyframe."""
        return "; ".join(self._notes)

    def after_correction(self, i: int, frame, accepted: bool) -> None:
        """Fall back on the visual odometry after FALLBACK_STREAK refused keyframes (from
        keyframe i, whose frame primes it); back to the IMU alone once a correction lands."""
        self._refused_in_row = 0 if accepted else self._refused_in_row + 1
        fallback = self.odometry.fallback
        if accepted and self._vo_since is not None:
            log.warning("a correction landed again at frame %d: back on the IMU alone between keyframes", i)
            self.fallback_intervals[-1][1] = i
            self._vo_since = None
        elif (self._refused_in_row >= self.FALLBACK_STREAK and self._vo_since is None and frame is not None
              and fallback is not None):
            log.warning("the last %d keyframes (to frame %d) were refused: the IMU alone drifts by metres within "
                        "seconds, so the run falls back on the visual odometry (%s) between keyframes until a "
                        "correction lands", self._refused_in_row, i, getattr(fallback, "name", "vo"))
            fallback.prime(frame)
            self._vo_since = i
            self.fallback_intervals.append([i, None])

    def keyframe_estimated(self, graph: KeyframeGraph, j: int, t: float) -> np.ndarray:
        """Keyframe j's state after its correction: the IMU predicts the next frames from it."""
        estimate = graph.estimate()
        self.nav_kf = gtsam.NavState(estimate.atPose3(X(j)), estimate.atVector(V(j)))
        self.bias_kf = estimate.atConstantBias(B(j))
        self.t_kf = t
        T_field_nav = self._field_from_nav(estimate)
        self.kf_states.append((self.t_kf, self.nav_kf, self.bias_kf, T_field_nav))
        self.T_world_kf = T_field_nav @ pose3_to_T(estimate.atPose3(X(j)))  # the causal pose, field's frame
        return self.T_world_kf

    def causal_pose(self) -> np.ndarray:
        """The last keyframe's estimate and the fallback's chain since (identity on the IMU alone:
        the frames between keyframes are predicted at the end, :meth:`causal`)."""
        return self.T_world_kf @ self.T_kf_cam

    def twist(self, i: int, t: float, dt: float) -> np.ndarray | None:
        """Body twist (GTSAM order) at frame i: the gyro's rate and the velocity in the body."""
        if not self.kf_states:
            return None
        k = int(np.clip(np.searchsorted(self.imu.stamps, t) - 1, 0, len(self.imu.stamps) - 1))
        nav = self._predict(self.t_kf, self.nav_kf, self.bias_kf, t)
        v_body = nav.pose().rotation().matrix().T @ nav.velocity()
        return np.r_[self.imu.gyro[k] - self.bias_kf.gyroscope(), v_body]

    # --- per-frame trajectories: predicted from keyframe states -----------------------------

    def _frames_from_states(self, states: list[tuple[float, gtsam.NavState, gtsam.imuBias.ConstantBias, np.ndarray]],
                            stamps: np.ndarray) -> np.ndarray:
        """(n, 4, 4) ``T_field_cam``: each frame predicted from the latest keyframe state at or
        before it (navigation frame), taken into the field's frame with that state's
        ``T_field_nav``."""
        T_field_cam = np.empty((len(stamps), 4, 4))
        kf_times = np.array([s[0] for s in states])
        for i, t in enumerate(stamps):
            k = int(np.searchsorted(kf_times, t + 1e-9) - 1)
            if k < 0:
                T_field_cam[i] = self.T_world_cam_odom[i]
                continue
            t_k, nav, bias, T_field_nav = states[k]
            T_field_cam[i] = T_field_nav @ pose3_to_T(self._predict(t_k, nav, bias, float(t)).pose())
        return T_field_cam

    def smoothed(self, values: gtsam.Values, T_world_kf_by_frame: dict[int, np.ndarray], keyframe_indices: FrameLog[int],
                 stamps: np.ndarray) -> np.ndarray:
        T_field_nav = self._field_from_nav(values)
        states = []
        for j, idx in enumerate(keyframe_indices):
            nav = gtsam.NavState(values.atPose3(X(j)), values.atVector(V(j)))
            states.append((float(stamps[idx]) if idx < len(stamps) else float("inf"), nav,
                           values.atConstantBias(B(j)), T_field_nav))
        T_field_cam = self._frames_from_states(states, stamps)
        # The frames the fallback chained, chained again from their keyframe's final pose.
        keyframes = set(keyframe_indices)
        for i in sorted(self._vo_increments):
            if i < len(T_field_cam) and i not in keyframes:
                T_field_cam[i] = T_field_cam[i - 1] @ self._vo_increments[i]
        return T_field_cam

    def causal(self, online: FrameLog[np.ndarray], stamps: np.ndarray) -> np.ndarray:
        T_field_cam = self._frames_from_states(self.kf_states, stamps)
        for i in self._vo_increments:  # frames the fallback chained, as the run had them
            if i < len(stamps):
                T_field_cam[i] = online[i]
        return T_field_cam

    def finish(self, values: gtsam.Values, graph: KeyframeGraph, accepted: set[int], keyframe_indices: FrameLog[int],
               result: RunResult) -> None:
        """The refined gravity, the biases and their sigmas, the IMU's notes, the fallback's spans."""
        n = len(result.timestamps)
        g = float(np.linalg.norm(self.g_field0))
        result.gravity_world = self._field_from_nav(values)[:3, :3] @ np.array([0.0, 0.0, -g])
        result.gravity_world_prior = self.g_field0.copy()
        result.imu_biases = np.array([np.r_[values.atConstantBias(B(j)).accelerometer(),
                                            values.atConstantBias(B(j)).gyroscope()]
                                      for j in range(len(keyframe_indices))])
        try:
            marginals = gtsam.Marginals(graph.accepted_graph(accepted), values)
            result.imu_bias_sigmas = np.array([np.sqrt(np.diag(marginals.marginalCovariance(B(j))))
                                               for j in range(len(keyframe_indices))])
        except RuntimeError as exc:  # an ill-posed graph still has its estimate
            log.warning("bias marginals not computed: %s", exc)
        result.imu_skipped = list(self.imu.skipped)
        result.fallback_intervals = [[a, n - 1 if b is None else b] for a, b in self.fallback_intervals]
