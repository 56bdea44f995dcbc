"""What a drift-correction run gives back: one :class:`KeyframeRecord` per keyframe and the
:class:`RunResult` (:class:`~nap3d_graph.run.pipeline.Pipeline` writes both)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable

import numpy as np

from nap3d_graph.trajectory import Trajectory

if TYPE_CHECKING:
    from nap3d_graph.trajectory import Trajectory

__all__ = ["KeyframeRecord", "RunResult", "ground_truth_reader", "refusal_kind", "tell"]


def refusal_kind(reason: str) -> str:
    """A refusal's kind: its words before the first number or detail."""
    import re

    return re.split(r"[(:=0-9]", reason or "unknown")[0].strip() or "unknown"


def ground_truth_reader(sequence, start: int, stop: int) -> Callable[[], np.ndarray | None]:
    """A function reading ``sequence``'s ground truth of frames ``start:stop`` (None when it
    has none) when a result is asked for it, not before: the run never sees it."""

    def read():
        T = sequence.T_world_cam_gt
        return None if T is None else np.asarray(T[start:stop])

    return read


@dataclass
class KeyframeRecord:
    """What happened at one keyframe (one row of corrections.csv)."""

    frame_index: int
    timestamp: float
    key: int
    matches: int = 0
    inliers: int = 0
    iterations: int = 0
    accepted: bool = False
    reason: str = ""
    gate_d2: float = float("nan")
    correction_m: float = float("nan")
    correction_deg: float = float("nan")
    timings_s: dict = field(default_factory=dict)
    trained_frame: bool = False
    why: str = "every"  # why a keyframe here: every (due), distance, angle, first, doubt
    sharpness: float = float("nan")
    postponed: int = 0  # frames it was taken after it was due (keyframe_window)
    depth_scale: float = float("nan")
    intrinsics_model: str = ""  # the camera model its alignment kept (IntrinsicsModelTracker.observe)


def tell(on_keyframe: Callable[[KeyframeRecord], object] | None, record: KeyframeRecord | None) -> None:
    """Tell ``on_keyframe`` (a caller's hook, or None) about a finished keyframe."""
    if on_keyframe is not None and record is not None:
        on_keyframe(record)


@dataclass
class RunResult:
    """Per-frame trajectories (N, 4, 4) at ``timestamps`` (N,) and per-keyframe records.

    ``T_world_cam_estimate``: the smoothed trajectory (every correction, past and future,
    used). ``T_world_cam_online``: the causal one, what a robot had at each frame: each
    keyframe as iSAM2 knew it right after its own correction, the frames after it chained
    with the odometry. ``partial``: the run was stopped before its last frame. ``first_frame``:
    the frame the arrays start at (0 but for a run that handed its older frames to
    ``on_retire``, :mod:`nap3d_graph.run.history`); ``keyframe_indices`` and the records'
    ``frame_index`` count from the run's first frame all the same. ``placement``: for a run
    that started from anywhere in a map, whether and when it was placed in it
    (:meth:`~nap3d_graph.mapping.start.MapPlacement.summary`); never placed, its poses are in
    its own provisional frame (its first camera), not the map's.
    """

    timestamps: np.ndarray
    T_world_cam_estimate: np.ndarray
    T_world_cam_odometry: np.ndarray
    #: The ground truth (``T_world_cam_gt``), or a function that reads it: a run reads its
    #: sequence's ground truth only when asked, once its trajectories are final.
    ground_truth: np.ndarray | None | Callable[[], np.ndarray | None]
    keyframes: list[KeyframeRecord]
    keyframe_indices: list[int]
    T_world_map: np.ndarray | None = None
    wall_time_s: float = 0.0
    T_world_cam_online: np.ndarray | None = None
    partial: bool = False
    gnc_outliers: list = field(default_factory=list)
    gnc_recovered: list = field(default_factory=list)
    depth_scale: float = 1.0
    interval_odometry: dict = field(default_factory=dict)
    corrections: dict = field(default_factory=dict)
    increments: list = field(default_factory=list)
    imu_biases: np.ndarray | None = None
    imu_bias_sigmas: np.ndarray | None = None
    imu_skipped: list = field(default_factory=list)
    gravity_world: np.ndarray | None = None
    gravity_world_prior: np.ndarray | None = None
    fallback_intervals: list = field(default_factory=list)
    first_frame: int = 0
    placement: dict | None = None

    @property
    def T_world_cam_gt(self) -> np.ndarray | None:
        """(N, 4, 4) the ground truth at the run's frames (NaN where none), or None; read from
        the sequence on first use."""
        if callable(self.ground_truth):
            self.ground_truth = self.ground_truth()
        return self.ground_truth

    def trajectories(self, with_ground_truth: bool = True) -> dict[str, Trajectory]:
        """The run's trajectories as :class:`~nap3d_graph.trajectory.Trajectory`:
        ``estimate`` (smoothed), ``estimate_online`` (causal), ``odometry`` and, when there is
        one and ``with_ground_truth``, ``groundtruth`` (NaN where the frames have none)."""
        out = {"estimate": Trajectory(self.timestamps, self.T_world_cam_estimate),
               "odometry": Trajectory(self.timestamps, self.T_world_cam_odometry)}
        if self.T_world_cam_online is not None:
            out["estimate_online"] = Trajectory(self.timestamps, self.T_world_cam_online)
        if with_ground_truth and self.T_world_cam_gt is not None:
            out["groundtruth"] = Trajectory(self.timestamps, self.T_world_cam_gt)
        return out

    @property
    def num_accepted(self) -> int:
        return sum(k.accepted for k in self.keyframes)

    @property
    def num_rejected(self) -> int:
        return len(self.keyframes) - self.num_accepted
