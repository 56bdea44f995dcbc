"""One small interface for every estimator, and the measurement stream they all consume.

Filtering and smoothing are compared on identical inputs: a :class:`MeasurementStream`
holds, per frame, the odometry increment (for the trajectory between keyframes), per
keyframe the interval odometry exactly as the graph's odometry factor has it (the
increments composed, with the drift model), or the IMU samples on the IMU path, and every
successful NAP3D correction (pose and 6x6 covariance). Corrections are measured once, by a
reference run that rendered at its own predictions: they are absolute pose measurements,
the same whoever uses them.

An estimator is driven frame by frame (:func:`run_estimator`): ``start`` at the first
frame, then ``step(i)`` for each frame (propagate to it; at a keyframe, take its
correction if the estimator's own chi-square gate accepts it), and ``current()`` is what it
knows about frame ``i`` right then: the causal estimate, which never uses the future.
``final()`` is the smoothed trajectory after the last frame (None for a filter: its final
trajectory is its causal one).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

__all__ = ["MeasurementStream", "Estimator", "EstimatorResult", "run_estimator", "stream_from_run"]


@dataclass
class MeasurementStream:
    """Inputs every estimator sees (poses are ``T_world_cam``, covariances GTSAM order).

    timestamps (N,); increments: N (4, 4) frame-to-frame odometry (the first unused);
    keyframes: indices; interval_odometry: {keyframe index: (T_prev_kf_kf, cov)} for every
    keyframe but the first; corrections: {keyframe index: (T_world_cam, cov)};
    T_world_cam0 (4, 4), P0 (6, 6): the first pose and its covariance; imu: an
    :class:`~nap3d_graph.motion.imu.ImuStream` on the IMU path (velocity0 (3,) then); gate_p: the
    chi-square gate probability every estimator uses; T_world_cam_gt (N, 4, 4) or None.
    """

    timestamps: np.ndarray
    increments: list
    keyframes: list
    interval_odometry: dict
    corrections: dict
    T_world_cam0: np.ndarray
    P0: np.ndarray
    gate_p: float = 0.997
    imu: object | None = None
    velocity0: np.ndarray | None = None
    T_world_cam_gt: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.timestamps)


class Estimator(Protocol):
    name: str

    def start(self, stream: MeasurementStream) -> None: ...

    def step(self, i: int) -> None: ...

    def current(self) -> tuple[np.ndarray, np.ndarray | None]: ...

    def final(self) -> tuple[np.ndarray, np.ndarray | None] | None: ...


@dataclass
class EstimatorResult:
    """T_causal (N, 4, 4) and P_causal (N, 6, 6) as known at each frame (NaN where the
    estimator claims no covariance); T_final / P_final after the last (smoothers; the causal
    ones for filters); step_seconds (N,); final_seconds: the solve after the last frame;
    accepted: frames whose correction the estimator took; reports: which of "causal" and
    "final" are the estimator's own results (a filter: causal; batch: final; iSAM2: both)."""

    name: str
    T_causal: np.ndarray
    P_causal: np.ndarray
    T_final: np.ndarray
    P_final: np.ndarray | None
    step_seconds: np.ndarray
    accepted: list = field(default_factory=list)
    final_seconds: float = 0.0
    reports: tuple = ("causal",)


def run_estimator(estimator, stream: MeasurementStream) -> EstimatorResult:
    """Drive ``estimator`` over ``stream`` frame by frame; collect the causal estimate of
    each frame right after its step, the time of each step, and the final trajectory."""
    n = len(stream)
    T_causal = np.empty((n, 4, 4))
    P_causal = np.full((n, 6, 6), np.nan)
    seconds = np.zeros(n)
    started = time.perf_counter()
    estimator.start(stream)
    seconds[0] = time.perf_counter() - started
    T_causal[0], P = estimator.current()
    if P is not None:
        P_causal[0] = P
    for i in range(1, n):
        started = time.perf_counter()
        estimator.step(i)
        seconds[i] = time.perf_counter() - started
        T_causal[i], P = estimator.current()
        if P is not None:
            P_causal[i] = P
    started = time.perf_counter()
    final = estimator.final()
    final_seconds = time.perf_counter() - started
    T_final, P_final = (T_causal, P_causal) if final is None else final
    return EstimatorResult(estimator.name, T_causal, P_causal, T_final, P_final, seconds,
                           list(getattr(estimator, "accepted", [])), final_seconds,
                           tuple(getattr(estimator, "reports", ("causal",))))


def stream_from_run(result, sequence, config, imu=None, velocity0=None) -> MeasurementStream:
    """The stream a reference :class:`~nap3d_graph.run.pipeline.Pipeline` run measured."""
    P0 = np.diag([config.prior_rot_sigma_rad**2] * 3 + [config.prior_trans_sigma_m**2] * 3)
    T_world_cam_gt = None if getattr(sequence, "T_world_cam_gt", None) is None else np.asarray(sequence.T_world_cam_gt)[
        :len(result.timestamps)]
    return MeasurementStream(np.asarray(result.timestamps), list(result.increments), list(result.keyframe_indices),
                             dict(result.interval_odometry), dict(result.corrections),
                             np.asarray(result.T_world_cam_odometry[0]), P0, config.gate_p, imu, velocity0, T_world_cam_gt)
