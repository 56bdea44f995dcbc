"""Which frames are keyframes: every N-th, after a distance or a turn, right after the odometry
doubted itself, whenever an overlapped run's worker is idle, and, with a window, the first
sharp frame once one is due."""

from __future__ import annotations

import numpy as np

from nap3d_graph.camera import sharpness
from nap3d_graph.conventions import pose_error
from nap3d_graph.run.config import PipelineConfig

__all__ = ["KeyframeSelector"]


class KeyframeSelector:
    """The run's keyframe choice (``PipelineConfig.keyframe_*``). Per frame :meth:`is_keyframe`;
    at a keyframe, :meth:`take` gives why it is one, its sharpness and how many frames it was
    postponed for (a sharper one than the due frame), and starts the next interval."""

    def __init__(self, config: PipelineConfig):
        self.config = config
        self._due_since: int | None = None  # the frame a keyframe fell due at, while its window is open
        self._due_why = ""
        self._sharpness_since_kf: list[float] = []
        self._chosen: tuple[str, float, int] = ("first", float("nan"), 0)

    @property
    def reads_every_frame(self) -> bool:
        """With a keyframe window every frame is read (the frames since the last keyframe are
        the reference a due one is judged by)."""
        return self.config.keyframe_window > 1

    def due(self, i: int, last_keyframe: int | None, doubted: bool, T_kf_cam: np.ndarray,
            worker_idle: bool = False) -> str:
        """Why frame i is due to be a keyframe ("" when it is not): ``last_keyframe`` the last
        keyframe's frame (None before the first), ``doubted`` the odometry guessed a step since,
        ``T_kf_cam`` (4, 4) the motion since, ``worker_idle`` an overlapped run's worker has no
        measurement in flight (``keyframe_when_idle``)."""
        if last_keyframe is None:
            return "first" if i == 0 else ""
        if self.config.keyframe_on_doubt and doubted:
            return "doubt"
        if self.due_by_count(i, last_keyframe):
            return "every"
        if worker_idle and self.idle_due(i, last_keyframe):
            return "idle"
        moved_m, turned_deg = pose_error(T_kf_cam, np.eye(4))
        if self.config.keyframe_distance_m > 0 and moved_m >= self.config.keyframe_distance_m:
            return "distance"
        return "angle" if self.config.keyframe_angle_deg > 0 and turned_deg >= self.config.keyframe_angle_deg else ""

    def due_by_count(self, i: int, last_keyframe: int | None) -> bool:
        """Frame i is due to be a keyframe by ``keyframe_every`` alone (what can be known before
        its odometry; the other reasons a keyframe is taken cannot). ``last_keyframe``: the last
        keyframe's frame (None before the first)."""
        return last_keyframe is not None and i - last_keyframe >= self.config.keyframe_every

    def idle_due(self, i: int, last_keyframe: int | None) -> bool:
        """Frame i is far enough from the last keyframe to be taken while the worker is idle
        (``keyframe_when_idle``)."""
        gap = self.config.keyframe_when_idle
        return bool(gap) and last_keyframe is not None and i - last_keyframe >= gap

    def is_keyframe(self, i: int, frame, last_keyframe: int | None, doubted: bool, T_kf_cam: np.ndarray,
                    worker_idle: bool = False) -> bool:
        """Frame i is a keyframe: it is due (:meth:`due`) and, with a keyframe window, sharp
        enough or the window's last frame."""
        if self._due_since is None:
            why = self.due(i, last_keyframe, doubted, T_kf_cam, worker_idle)
            if not why:
                self._note_sharpness(frame)
                return False
            self._due_since, self._due_why = i, why
        sharpness = self._note_sharpness(frame)
        waited = i - self._due_since
        window = self.config.keyframe_window
        if window > 1 and waited < window - 1 and self._due_why != "first":
            recent = self._sharpness_since_kf[:-1]
            reference = float(np.median(recent)) if recent else sharpness
            if not sharpness >= self.config.keyframe_sharpness_fraction * reference:
                return False  # blurred: a sharper one may follow within the window
        self._chosen = (self._due_why, sharpness, waited)
        self._due_since = None
        return True

    def take(self) -> tuple[str, float, int]:
        """``(why, sharpness, frames postponed)`` of the keyframe just chosen; the next
        interval's sharpness reference starts empty."""
        self._sharpness_since_kf = []
        return self._chosen

    def _note_sharpness(self, frame) -> float:
        """The frame's sharpness (NaN without a frame or a window), kept for the reference."""
        if frame is None or self.config.keyframe_window <= 1:
            return float("nan")

        value = sharpness(frame.rgb)
        self._sharpness_since_kf.append(value)
        return value
