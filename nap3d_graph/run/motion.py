"""How the run moves between keyframes: a motion model handed to the run.

A motion model keeps the motion since the last keyframe, puts the first pose's prior and each
keyframe's motion factor into the :class:`~nap3d_graph.run.graph.KeyframeGraph` (with the
keyframe's starting value: the prediction), and chains every frame's pose from the keyframes'.
Two exist: :class:`OdometryMotion` (a frame odometry: the increments composed into a
``BetweenFactorPose3``, covariance propagated, plus the drift the per-frame sigmas cannot
describe) and :class:`~nap3d_graph.run.imu.ImuMotion` (IMU preintegration). The run
(:class:`~nap3d_graph.run.pipeline.Pipeline`) calls, per frame, :meth:`frame`; per keyframe
:meth:`add_keyframe`, then (after the correction) :meth:`after_correction` and
:meth:`keyframe_estimated`; at its end :meth:`smoothed`, :meth:`causal` and :meth:`finish`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from nap3d_graph.conventions import T_to_pose3, log_se3
from nap3d_graph.factors import odometry_factor, pose_prior_factor
from nap3d_graph.motion.interval import IntervalCovariance
from nap3d_graph.run.chain import chain_from_nearest_keyframe
from nap3d_graph.run.config import PipelineConfig
from nap3d_graph.run.graph import KeyframeGraph
from nap3d_graph.run.history import FrameLog
from nap3d_graph.run.records import RunResult

__all__ = ["MotionModel", "Odometry", "OdometryMotion"]


class Odometry(Protocol):
    """A frame odometry (:mod:`nap3d_graph.motion.odometry`): where it starts and each frame's step
    ``increment(i, frame) -> Increment`` (``T_prev_cur``, ``covariance``, ``ok``). Optional:
    ``needs_frames`` (it reads the images), ``prime(frame)`` (given frame 0 first)."""

    def initial_pose(self) -> np.ndarray: ...

    def increment(self, i: int, frame: Any) -> Any: ...


@dataclass
class KeyframeEntry:
    """What a new keyframe brings to the graph, as its motion model predicts it: ``factors``
    (its prior or motion factors) and ``values`` (``(key, initial value)`` pairs), which
    :meth:`KeyframeGraph.enter` puts in (the graph's only writer); the prediction
    ``T_world_kf_pred`` (4, 4); the interval's odometry ``(T_prev_kf_kf, covariance)`` as its
    factor has it (None for the first keyframe, or when no odometry factor was made)."""

    T_world_kf_pred: np.ndarray
    factors: list = field(default_factory=list)
    values: list = field(default_factory=list)
    interval: tuple[np.ndarray, np.ndarray] | None = None


class MotionModel(Protocol):
    """What the run asks of its motion between keyframes (see the module docstring)."""

    name: str
    allows_overlap: bool
    allows_graph_window: bool
    #: It puts the field's frame in the graph itself (``anchor_prior``): ``--anchor`` does not apply.
    estimates_field_frame: bool
    T_world_cam_odom: FrameLog[np.ndarray]  # per frame (a run that retires its past drops the oldest)
    increments: FrameLog[np.ndarray]

    @property
    def needs_frames(self) -> bool: ...

    @property
    def doubted(self) -> bool: ...

    def anchor_prior(self) -> tuple[gtsam.NonlinearFactor, np.ndarray] | None: ...

    def prime(self, frame) -> None: ...

    def frame(self, i: int, frame, t: float, dt: float) -> None: ...

    def since_keyframe(self) -> np.ndarray: ...

    def reframe(self, T_new_old: np.ndarray) -> None: ...

    def add_keyframe(self, j: int, i: int, t: float) -> KeyframeEntry: ...

    def after_correction(self, i: int, frame, accepted: bool) -> None: ...

    def interval_notes(self) -> str: ...

    def keyframe_estimated(self, graph: KeyframeGraph, j: int, t: float) -> np.ndarray: ...

    def causal_pose(self) -> np.ndarray: ...

    def twist(self, i: int, t: float, dt: float) -> np.ndarray | None: ...

    def smoothed(self, values: gtsam.Values, T_world_kf_by_frame: dict[int, np.ndarray],
                 keyframe_indices: FrameLog[int], stamps: np.ndarray) -> np.ndarray: ...

    def causal(self, online: FrameLog[np.ndarray], stamps: np.ndarray) -> np.ndarray: ...

    def finish(self, values: gtsam.Values, graph: KeyframeGraph, accepted: set[int], keyframe_indices: FrameLog[int],
               result: RunResult) -> None: ...


class OdometryMotion:
    """A frame odometry between keyframes. Each keyframe's factor is the increments since the
    last one composed, their covariances chained (:class:`~nap3d_graph.motion.interval.IntervalCovariance`:
    what an increment says is its frames' own noise cancels inside the interval), plus
    ``PipelineConfig.drift_covariance`` of the interval; frames are chained from the keyframes
    with the increments."""

    allows_overlap = True
    allows_graph_window = True
    estimates_field_frame = False

    def __init__(self, odometry: Odometry, config: PipelineConfig):
        self.odometry, self.config = odometry, config
        self.name = str(getattr(odometry, "name", "odometry"))
        # Indexed by frame; a run that retires its past drops their oldest items (FrameLog).
        self.T_world_cam_odom: FrameLog[np.ndarray] = FrameLog([odometry.initial_pose()])
        self.increments: FrameLog[np.ndarray] = FrameLog([np.eye(4)])
        self.T_kf_cam = np.eye(4)
        self.interval = IntervalCovariance()  # the steps' covariance since the last keyframe
        self.dt_since_kf = 0.0
        self.T_world_kf = self.T_world_cam_odom[0]  # the latest keyframe's estimate (frame 0 is always one)
        self._doubted = False

    @property
    def needs_frames(self) -> bool:
        return bool(getattr(self.odometry, "needs_frames", False))

    @property
    def doubted(self) -> bool:
        """Whether the odometry guessed a step since the last keyframe (visual odometry lost)."""
        return self._doubted

    def anchor_prior(self) -> None:
        return None  # the world is the odometry's; --anchor puts the field's frame in it

    def prime(self, frame) -> None:
        if hasattr(self.odometry, "prime"):
            self.odometry.prime(frame)

    def frame(self, i: int, frame, t: float, dt: float) -> None:
        inc = self.odometry.increment(i, frame)
        self._doubted = self._doubted or not getattr(inc, "ok", True)
        self.increments.append(inc.T_prev_cur)
        self.T_world_cam_odom.append(self.T_world_cam_odom[-1] @ inc.T_prev_cur)
        self.interval.add(inc.T_prev_cur, inc.covariance, getattr(inc, "frame_noise", None))
        self.T_kf_cam = self.T_kf_cam @ inc.T_prev_cur
        self.dt_since_kf += dt

    def since_keyframe(self) -> np.ndarray:
        """(4, 4) ``T_kf_cam``: the motion since the last keyframe."""
        return self.T_kf_cam

    def reframe(self, T_new_old: np.ndarray) -> None:
        """Every world pose kept moved into another frame: ``T_new_cam = T_new_old @ T_old_cam``
        (a run placed in a map after it started; the increments are relative and stay)."""
        self.T_world_cam_odom = self.T_world_cam_odom.mapped(lambda T_old_cam: T_new_old @ T_old_cam)
        self.T_world_kf = T_new_old @ self.T_world_kf

    def add_keyframe(self, j: int, i: int, t: float) -> KeyframeEntry:
        """Keyframe ``j`` (frame ``i``) with its prior (the first) or its odometry factor, its
        prediction and the interval's odometry (see :class:`KeyframeEntry`)."""
        interval = None
        if j == 0:
            T_world_kf_pred = self.T_world_cam_odom[0]
            factor = pose_prior_factor(X(0), T_world_kf_pred, rot_sigma_rad=self.config.prior_rot_sigma_rad,
                                       trans_sigma_m=self.config.prior_trans_sigma_m)
        else:
            cov = self.interval.value + self.config.drift_covariance(self.T_kf_cam, self.dt_since_kf)
            factor = odometry_factor(X(j - 1), X(j), self.T_kf_cam, cov)
            interval = (self.T_kf_cam.copy(), cov.copy())
            T_world_kf_pred = self.T_world_kf @ self.T_kf_cam
        self.T_kf_cam = np.eye(4)
        self.interval.reset()
        self.dt_since_kf = 0.0
        self._doubted = False
        return KeyframeEntry(T_world_kf_pred, [factor], [(X(j), T_to_pose3(T_world_kf_pred))], interval)

    def after_correction(self, i: int, frame, accepted: bool) -> None:
        pass

    def interval_notes(self) -> str:
        return ""

    def keyframe_estimated(self, graph: KeyframeGraph, j: int, t: float) -> np.ndarray:
        """The keyframe's estimate after its correction: the causal chain starts there."""
        self.T_world_kf = graph.pose(X(j))
        return self.T_world_kf

    def causal_pose(self) -> np.ndarray:
        """(4, 4) the latest frame as known now: the last keyframe's estimate and the odometry since."""
        return self.T_world_kf @ self.T_kf_cam

    def twist(self, i: int, t: float, dt: float) -> np.ndarray | None:
        """Body twist per second (GTSAM order) of the odometry's last step into frame i (``dt``
        seconds long)."""
        if i < 1 or i >= len(self.increments):
            return None
        return log_se3(self.increments[i]) / dt if dt > 0 else None

    def smoothed(self, values, T_world_kf_by_frame, keyframe_indices, stamps) -> np.ndarray:
        """The frames from the oldest kept one (``stamps``: theirs) chained from the keyframes."""
        first = self.increments.start
        return chain_from_nearest_keyframe(T_world_kf_by_frame, self.increments, first + len(stamps), start=first)

    def causal(self, online: FrameLog[np.ndarray], stamps: np.ndarray) -> np.ndarray:
        first = online.start
        return np.stack(online[first:first + len(stamps)])

    def finish(self, values, graph, accepted, keyframe_indices, result) -> None:
        pass
