"""Plug your own estimator into the EKF-vs-graph comparison.

An estimator is any object with a ``name``, ``start(stream)``, ``step(i)``, ``current()`` and
``final()`` (see ``nap3d_graph.estimators.base``). Here: a fixed-gain complementary filter
that moves the pose a fixed fraction of the way to each NAP3D correction, whatever the
covariances say. It runs next to the library's estimators on one measurement stream, and the
comparison scores them all the same way.

On your own data, make the stream from a run (``stream_from_run``) or use
``nap3d-graph compare``; here a synthetic stream (known noise) keeps the example fast.

    python examples/own_estimator.py
"""

from __future__ import annotations

import numpy as np

from nap3d_graph.conventions import exp_se3, inv_T, log_se3
from nap3d_graph.estimators import ErrorStateEKF, Isam2Estimator, OdometryOnly
from nap3d_graph.estimators.synthetic import synthetic_stream
from nap3d_graph.evaluation.compare import compare, comparison_rows, format_table


class ComplementaryFilter:
    """Odometry between keyframes; at each correction ``T <- T Exp(gain * Log(T^-1 Z))``."""

    name = "complementary"
    reports = ("causal",)  # a filter: its causal trajectory is its only one

    def __init__(self, gain: float = 0.5):
        self.gain = gain

    def start(self, stream) -> None:
        self.stream = stream
        self.T = np.asarray(stream.T_world_cam0, float).copy()
        self.accepted: list[int] = []

    def step(self, i: int) -> None:
        self.T = self.T @ self.stream.increments[i]  # the odometry increment into frame i
        if i in self.stream.corrections:  # a keyframe with a NAP3D correction
            Z, _covariance = self.stream.corrections[i]
            self.T = self.T @ exp_se3(self.gain * log_se3(inv_T(self.T) @ Z))
            self.accepted.append(i)

    def current(self):
        return self.T.copy(), None  # (pose now, covariance or None)

    def final(self):
        return None  # a filter has no smoothed trajectory


def main() -> list[dict]:
    stream = synthetic_stream(450, keyframe_every=5, seed=3)
    results = compare(stream, [OdometryOnly(), ComplementaryFilter(0.5), ErrorStateEKF(), Isam2Estimator()])
    rows = comparison_rows(stream, results)
    print(format_table(rows))
    return rows


if __name__ == "__main__":
    main()
