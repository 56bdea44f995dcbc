"""The survey's motion from the camera alone: frame-to-frame odometry from the first frame
(the map's origin), the longest stretch it tracked, and the keyframes.

The odometry is the run's own (:func:`~nap3d_graph.motion.odometry.make_odometry`, ``vo`` or
``dense``), started at the identity: the map's frame is the first tracked frame's camera.
A step the odometry guessed (``ok`` False: constant velocity) is kept when it is alone; after
``max_guesses`` guesses in a row the odometry has lost the camera, and the stretches either
side are separate: the map keeps the longest one and says which frames it dropped.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from nap3d_graph.conventions import compose_covariance, inv_T

__all__ = ["SurveyOdometry", "track", "tracked_segment", "keyframe_indices"]

log = logging.getLogger(__name__)


@dataclass
class SurveyOdometry:
    """``T_odom_cam`` (N, 4, 4): each frame in the first frame's camera by the chained steps;
    ``step_cov`` (N, 6, 6): each step's covariance (frame i-1 <- i; row 0 zero); ``ok`` (N,):
    the step was measured, not guessed (row 0 True); ``reasons``: why each guessed step was."""

    T_odom_cam: np.ndarray
    step_cov: np.ndarray
    ok: np.ndarray
    reasons: list

    def save(self, path) -> None:
        np.savez_compressed(path, T_odom_cam=self.T_odom_cam, step_cov=self.step_cov, ok=self.ok,
                            reasons=np.array(self.reasons, dtype=object))

    @classmethod
    def load(cls, path) -> "SurveyOdometry":
        with np.load(path, allow_pickle=True) as data:
            return cls(data["T_odom_cam"], data["step_cov"], data["ok"], list(data["reasons"]))

    def between(self, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
        """``(T_a_b, covariance)``: frame b in frame a's camera by the chained steps, and the
        covariance of that chain (right perturbation at b, GTSAM order)."""
        T = inv_T(self.T_odom_cam[a]) @ self.T_odom_cam[b]
        cov = np.zeros((6, 6))
        for k in range(a + 1, b + 1):
            step = inv_T(self.T_odom_cam[k - 1]) @ self.T_odom_cam[k]
            cov = compose_covariance(cov, step, self.step_cov[k])
        return T, cov


def track(sequence, kind: str = "vo", matcher: str | None = None, width: int | None = None,
          progress: bool = True) -> SurveyOdometry:
    """Run the odometry over every frame of ``sequence`` from the identity. An unreadable
    frame is a guessed step (the odometry restarts after it)."""
    from nap3d_graph.motion.odometry import make_odometry
    from nap3d_graph.progress import progress_bar

    odometry = make_odometry(kind, sequence, initial_pose=np.eye(4), matcher=matcher,
                             vo_width=width if kind == "vo" else None)
    n = len(sequence)
    T = np.repeat(np.eye(4)[None], n, axis=0)
    cov = np.zeros((n, 6, 6))
    ok = np.ones(n, dtype=bool)
    reasons = [""] * n
    odometry.prime(_read(sequence, 0))
    for i in progress_bar(range(1, n), desc="survey odometry", unit="frame", disable=not progress, mininterval=2.0):
        increment = odometry.increment(i, _read(sequence, i))
        T[i] = T[i - 1] @ increment.T_prev_cur
        cov[i] = increment.covariance
        ok[i] = increment.ok
        reasons[i] = increment.reason
    return SurveyOdometry(T, cov, ok, reasons)


def _read(sequence, i: int):
    """Frame i, or None when it cannot be read (the odometry then guesses one step)."""
    try:
        return sequence[i]
    except (OSError, ValueError) as exc:
        log.warning("survey frame %d unreadable (%s): the odometry guesses across it", i, exc)
        return None


def tracked_segment(ok: np.ndarray, max_guesses: int = 3) -> tuple[int, int]:
    """``(start, stop)``: the longest run of frames the odometry never lost, where lost means
    ``max_guesses`` or more guessed steps in a row (a lone guess is bridged). Frames of the
    lost stretch itself belong to neither side."""
    n = len(ok)
    breaks = []  # (first guessed step, last guessed step) of every loss
    k = 1
    while k < n:
        if not ok[k]:
            j = k
            while j + 1 < n and not ok[j + 1]:
                j += 1
            if j - k + 1 >= max_guesses:
                breaks.append((k, j))
            k = j + 1
        else:
            k += 1
    starts = [0] + [j for _, j in breaks]
    stops = [k for k, _ in breaks] + [n]
    lengths = [b - a for a, b in zip(starts, stops)]
    best = int(np.argmax(lengths))
    return starts[best], stops[best]


def keyframe_indices(T_odom_cam: np.ndarray, start: int, stop: int, every: int = 5, distance_m: float = 0.1,
                     angle_deg: float = 10.0) -> np.ndarray:
    """Keyframes of frames ``start:stop``: the first, then every ``every`` frames, or sooner
    after ``distance_m`` metres or ``angle_deg`` degrees of motion since the last (so a fast
    stretch still overlaps its neighbours), and the last."""
    from nap3d_graph.conventions import rotation_angle_deg

    keys = [start]
    for i in range(start + 1, stop):
        T_rel = inv_T(T_odom_cam[keys[-1]]) @ T_odom_cam[i]
        moved = np.linalg.norm(T_rel[:3, 3]) >= distance_m or float(rotation_angle_deg(T_rel[:3, :3])) >= angle_deg
        if i - keys[-1] >= every or moved:
            keys.append(i)
    if keys[-1] != stop - 1 and stop - 1 > start:
        keys.append(stop - 1)
    return np.asarray(keys, dtype=int)
