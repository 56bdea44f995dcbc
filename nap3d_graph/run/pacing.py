"""Feeding a recording to a run as its camera delivered it (``run --pace``).

A replay goes as fast as the machine allows, so what an overlapped run knows at each frame
(its causal trajectory) depends on the machine's speed, not on the camera's. Paced, frame i
is handed over no earlier than ``(t_i - t_0) / speed`` seconds after the start, as a live
camera would give it, and the run's lateness is recorded: the causal trajectory is then the
one a robot riding along would have had.
"""

from __future__ import annotations

import time
from typing import Callable

import numpy as np

__all__ = ["CameraPace"]


class CameraPace:
    """``stop()`` hook for :meth:`~nap3d_graph.run.pipeline.Pipeline.run` that waits for each
    frame's delivery time before the run takes it.

    timestamps: (N,) the frames' stamps, seconds. speed: > 0, 1 the camera's own rate, 2 twice
    as fast. then: another stop hook asked after the wait (e.g. Ctrl-C), or None.
    ``behind_s`` holds, per frame, how late the run took it (0 when it had to wait).
    """

    def __init__(self, timestamps, speed: float = 1.0, then: Callable[[], bool] | None = None):
        if not speed > 0:
            raise ValueError(f"speed must be > 0, got {speed}")
        stamps = np.asarray(timestamps, dtype=float)
        self.speed = float(speed)
        self.due_s = (stamps - stamps[0]) / self.speed if stamps.size else stamps
        self.then = then
        self.behind_s: list[float] = []
        self._t0: float | None = None

    def __call__(self) -> bool:
        i = len(self.behind_s)
        now = time.perf_counter()
        if self._t0 is None:
            self._t0 = now
        wait_s = self._t0 + float(self.due_s[min(i, len(self.due_s) - 1)]) - now if len(self.due_s) else 0.0
        if wait_s > 0:
            time.sleep(wait_s)
        self.behind_s.append(max(-wait_s, 0.0))
        return bool(self.then()) if self.then is not None else False

    def summary(self) -> dict:
        """How the run kept up: ``speed``, the rate the frames were handed over at
        (``camera_hz``, the recording's times ``speed``), how late the run took them (median,
        p90, max seconds) and how many it took more than one frame period late."""
        behind = np.asarray(self.behind_s, dtype=float)
        if behind.size == 0:
            return {"speed": self.speed, "frames": 0}
        period_s = float(np.median(np.diff(self.due_s))) if len(self.due_s) > 1 else float("inf")
        return {"speed": self.speed, "frames": int(behind.size), "camera_hz": round(1.0 / period_s, 3),
                "behind_camera_s": {"median": round(float(np.median(behind)), 4),
                                    "p90": round(float(np.percentile(behind, 90)), 4),
                                    "max": round(float(behind.max()), 4)},
                "frames_over_a_period_late": int((behind > period_s).sum())}
