"""The measurement stream of a run, for estimators compared on the same inputs
(:mod:`nap3d_graph.estimators`)."""

from __future__ import annotations

import numpy as np

__all__ = ["MeasurementStream"]


class MeasurementStream:
    """Each keyframe interval's odometry as its motion factor has it, and every successful
    correction (gated out or not), keyed by frame: ``(T (4, 4), covariance (6, 6))`` each
    (GTSAM order: rotation, then translation)."""

    def __init__(self):
        self.interval_odometry: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.corrections: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def add_interval(self, frame: int, interval: tuple[np.ndarray, np.ndarray]) -> None:
        """The odometry of the interval that ends at keyframe ``frame``."""
        self.interval_odometry[frame] = interval

    def add_correction(self, frame: int, T_world_cam: np.ndarray, covariance: np.ndarray) -> None:
        """Keyframe ``frame``'s measured pose and its covariance (copied)."""
        self.corrections[frame] = (np.array(T_world_cam), np.array(covariance))

    def forget_before(self, frame: int) -> None:
        """Drop what is older than ``frame`` (it left a bounded graph)."""
        for kept in (self.interval_odometry, self.corrections):
            for old in [k for k in kept if k < frame]:
                del kept[old]
