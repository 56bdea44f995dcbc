"""The survey's motion from the camera alone: frame-to-frame odometry from the first frame
(the map's origin), the longest stretch it tracked, and the keyframes.

The odometry is the run's own (:func:`~nap3d_graph.motion.odometry.make_odometry`, ``vo`` or
``dense``), started at the identity: the map's frame is the first tracked frame's camera.
A step the odometry guessed (``ok`` False: constant velocity) is kept when it is alone; after
``max_guesses`` guesses in a row the odometry has lost the camera (a blank wall, a dark
doorway), and the stretches either side are separate (:func:`tracked_segments`). Each stretch
gives keyframes; once loops are verified, two stretches either side of a loss are one when
enough verified loops tie them (:func:`joined_run`: the camera came back to what it saw before
the loss), and the map keeps the longest run of joined stretches. The frames of a loss itself
are never placed: their poses would be the odometry's guess.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from nap3d_graph.conventions import compose_covariance, inv_T, rotation_angle_deg
from nap3d_graph.motion.odometry import make_odometry
from nap3d_graph.progress import progress_bar

__all__ = ["SurveyOdometry", "track", "tracked_segment", "tracked_segments", "segment_keyframes", "stretch_of",
           "joined_run", "lost_frames", "keyframe_indices"]

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


def tracked_segments(ok: np.ndarray, max_guesses: int = 3) -> list[tuple[int, int]]:
    """``[(start, stop), ...]`` in order: the runs of frames the odometry never lost, where lost
    means ``max_guesses`` or more guessed steps in a row (a lone guess is bridged). Frames of a
    lost stretch belong to neither side; the stretch after it starts at its last guessed frame
    (every step after it was measured)."""
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
    return [(a, b) for a, b in zip(starts, stops) if b > a]


def tracked_segment(ok: np.ndarray, max_guesses: int = 3) -> tuple[int, int]:
    """``(start, stop)``: the longest of :func:`tracked_segments`."""
    segments = tracked_segments(ok, max_guesses)
    return max(segments, key=lambda s: s[1] - s[0])


def segment_keyframes(T_odom_cam: np.ndarray, segments: list[tuple[int, int]], **keyframe_rules) -> np.ndarray:
    """Every stretch's keyframes (:func:`keyframe_indices` of each, its first and last frame
    among them), in frame order: none in a lost stretch."""
    return np.concatenate([keyframe_indices(T_odom_cam, a, b, **keyframe_rules) for a, b in segments]).astype(int)


def stretch_of(segments: list[tuple[int, int]], keys: np.ndarray) -> np.ndarray:
    """(K,) the position in ``segments`` of the stretch each keyframe (frame index) lies in."""
    return np.searchsorted([b for _, b in segments], keys, side="right")


def joined_run(segments: list[tuple[int, int]], keys: np.ndarray, loop_ends: list[tuple[int, int]],
               min_loops: int) -> tuple[int, int]:
    """``(first, last)`` keyframe positions (inclusive) of the longest run of stretches, in
    frames, where every two neighbours are tied by at least ``min_loops`` verified loops
    between them. ``keys`` (K,): keyframe frame indices; ``loop_ends``: each verified loop's
    keyframe positions ``(a, b)``. Only neighbours count, so dropping the other stretches keeps
    the same run (a map resumed from its kept keyframes joins them again)."""
    owner = stretch_of(segments, keys)
    ties = np.zeros(len(segments), dtype=int)  # ties[s]: loops between stretch s and s + 1
    for a, b in loop_ends:
        sa, sb = sorted((int(owner[a]), int(owner[b])))
        if sb == sa + 1:
            ties[sa] += 1
    runs, first = [], 0
    for s in range(len(segments)):
        if s == len(segments) - 1 or ties[s] < min_loops:
            runs.append((first, s))
            first = s + 1
    held = [r for r in runs if np.any((owner >= r[0]) & (owner <= r[1]))]
    best = max(held, key=lambda r: segments[r[1]][1] - segments[r[0]][0])
    positions = np.flatnonzero((owner >= best[0]) & (owner <= best[1]))
    return int(positions[0]), int(positions[-1])


def lost_frames(segments: list[tuple[int, int]], start: int, stop: int) -> list[tuple[int, int]]:
    """``[(first, stop), ...]``: the frames of ``start:stop`` in no stretch (the losses a
    joined run spans)."""
    gaps = []
    for (_, b), (a, _) in zip(segments[:-1], segments[1:]):
        if start < a and b < stop:
            gaps.append((b, a))
    return gaps


def keyframe_indices(T_odom_cam: np.ndarray, start: int, stop: int, every: int = 5, distance_m: float = 0.1,
                     angle_deg: float = 10.0) -> np.ndarray:
    """Keyframes of frames ``start:stop``: the first, then every ``every`` frames, or sooner
    after ``distance_m`` metres or ``angle_deg`` degrees of motion since the last (so a fast
    stretch still overlaps its neighbours), and the last."""
    keys = [start]
    for i in range(start + 1, stop):
        T_rel = inv_T(T_odom_cam[keys[-1]]) @ T_odom_cam[i]
        moved = np.linalg.norm(T_rel[:3, 3]) >= distance_m or float(rotation_angle_deg(T_rel[:3, :3])) >= angle_deg
        if i - keys[-1] >= every or moved:
            keys.append(i)
    if keys[-1] != stop - 1 and stop - 1 > start:
        keys.append(stop - 1)
    return np.asarray(keys, dtype=int)
