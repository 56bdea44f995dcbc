"""The covariance of a chain of odometry steps (one keyframe interval), where part of each
step's covariance is its two frames' own registration noise.

A frame's registration error (its depth against its colour, its features' positions) enters
the step into it and the step out of it with opposite signs, so inside a chain it cancels and
only the chain's two end frames keep theirs; the rest of a step's error is a walk that adds up
step by step. Chaining every step's covariance as independent (the walk alone) makes a
keyframe interval's covariance grow like the number of steps where its error grows far slower.

Measured on the feature odometry (``benchmarks/results/odometry_consistency.json``, issue
62): with the whole step covariance chained as a walk, the NEES over the run's 5-frame
keyframe interval was 0.79 on fr1/desk and 1.87 on the 7-Scenes kitchen, against 5.35 for
a consistent covariance (too cautious), while single steps read 5.1 and 4.6.
"""

from __future__ import annotations

import numpy as np

from ..conventions import compose_covariance

__all__ = ["IntervalCovariance"]

_ZERO = np.zeros((6, 6))


class IntervalCovariance:
    """Accumulates the (6, 6) covariance (GTSAM order, right perturbation) of
    ``T_first_last``, the composition of the steps :meth:`add`-ed since :meth:`reset`.

    Each step gives its covariance and ``frame_noise`` (6, 6), the part of it that is its two
    frames' own registration noise, half each (zeros: all of it a walk, the steps chained as
    independent). The chain's covariance is the walk of ``covariance - frame_noise`` composed
    step by step, plus half the first step's frame noise carried to the last frame, plus half
    the last step's. One step alone keeps its whole covariance."""

    def __init__(self):
        self.reset()

    def reset(self) -> None:
        self._walk = _ZERO.copy()
        self._first_end: np.ndarray | None = None  # the first frame's noise, seen from the latest frame
        self._last_end = _ZERO.copy()

    def add(self, T_prev_cur: np.ndarray, covariance: np.ndarray, frame_noise: np.ndarray | None = None) -> None:
        """Chain one step ``T_prev_cur`` (4, 4) with its ``covariance`` and ``frame_noise`` (6, 6)."""
        noise = _ZERO if frame_noise is None else np.asarray(frame_noise, dtype=float)
        self._walk = compose_covariance(self._walk, T_prev_cur, covariance - noise)
        if self._first_end is None:
            self._first_end = 0.5 * noise
        else:
            # The previous step's end frame is inside the chain now: its noise cancels.
            self._first_end = compose_covariance(self._first_end, T_prev_cur, _ZERO)
        self._last_end = 0.5 * noise

    @property
    def value(self) -> np.ndarray:
        """(6, 6) the covariance of the chain so far (zeros before any step)."""
        if self._first_end is None:
            return _ZERO.copy()
        return self._walk + self._first_end + self._last_end
