"""The factor graph on the stream: iSAM2 (causal and final) and batch Levenberg-Marquardt.

The graph is the drift-correction run's (:mod:`nap3d_graph.run.pipeline`): a pose per keyframe
(and, on the IMU path, a velocity and a bias: ``CombinedImuFactor`` between keyframes), a
prior on the first, the interval odometry as between factors, and each NAP3D correction as a
Huber-robust pose prior with its covariance.

* :class:`Isam2Estimator` adds a keyframe at a time, gates each correction against iSAM2's
  joint marginal (:func:`~nap3d_graph.factors.chi2_gate_isam2`) exactly as the run does,
  and reports two trajectories: **causal** (each keyframe as iSAM2 knew it right after its
  own correction, the frames after it predicted forward) and **final** (iSAM2's estimate
  after the last frame, every frame from its nearest keyframe).
* :class:`BatchLM` solves the whole graph once after the last frame with GTSAM's
  Levenberg-Marquardt (the offline optimum). It has no prediction to gate against, so it
  takes every correction, with the same Huber kernel.
"""

from __future__ import annotations

import logging
import time

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, V, X

from nap3d_graph.conventions import T_to_pose3, pose3_to_T
from nap3d_graph.factors import imu_factor, nap3d_prior_factor, odometry_factor
from nap3d_graph.results import Alignment, Correction
from nap3d_graph.run.chain import chain_from_nearest_keyframe
from nap3d_graph.run.config import PipelineConfig
from nap3d_graph.run.graph import KeyframeGraph

__all__ = ["GraphModel", "Isam2Estimator", "BatchLM"]

log = logging.getLogger(__name__)


class GraphModel:
    """Factors of the stream's graph, keyframe by keyframe, and its per-frame trajectories."""

    def __init__(self, stream, robust: str | None = "huber"):
        self.stream = stream
        self.robust = robust
        self.imu = stream.imu
        self.kf_index = {idx: j for j, idx in enumerate(stream.keyframes)}

    def first(self) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
        s, graph, values = self.stream, gtsam.NonlinearFactorGraph(), gtsam.Values()
        T0 = np.asarray(s.T_world_cam0, float)
        graph.add(gtsam.PriorFactorPose3(X(0), T_to_pose3(T0), gtsam.noiseModel.Gaussian.Covariance(s.P0)))
        values.insert(X(0), T_to_pose3(T0))
        if self.imu is not None:
            cfg = self.imu.config
            graph.add(gtsam.PriorFactorVector(V(0), np.asarray(s.velocity0, float),
                                              gtsam.noiseModel.Isotropic.Sigma(3, cfg.velocity_prior_sigma)))
            sigmas = np.r_[[cfg.accel_bias_prior_sigma] * 3, [cfg.gyro_bias_prior_sigma] * 3]
            graph.add(gtsam.PriorFactorConstantBias(B(0), gtsam.imuBias.ConstantBias(),
                                                    gtsam.noiseModel.Diagonal.Sigmas(sigmas)))
            values.insert(V(0), np.asarray(s.velocity0, float))
            values.insert(B(0), gtsam.imuBias.ConstantBias())
        return graph, values

    def motion(self, j: int, state) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
        """Keyframe j's motion factor from keyframe j-1 and its initial value predicted from
        ``state`` (keyframe j-1's: a pose, or ``(NavState, bias)`` on the IMU path)."""
        s, graph, values = self.stream, gtsam.NonlinearFactorGraph(), gtsam.Values()
        i_prev, i = s.keyframes[j - 1], s.keyframes[j]
        if self.imu is None:
            T_int, cov = s.interval_odometry[i]
            graph.add(odometry_factor(X(j - 1), X(j), T_int, cov))
            values.insert(X(j), T_to_pose3(state @ T_int))
            return graph, values
        nav, bias = state
        pim = self.imu.preintegrate(float(s.timestamps[i_prev]), float(s.timestamps[i]), bias)
        graph.add(imu_factor(X(j - 1), V(j - 1), X(j), V(j), B(j - 1), B(j), pim))
        predicted = pim.predict(nav, bias)
        values.insert(X(j), predicted.pose())
        values.insert(V(j), predicted.velocity())
        values.insert(B(j), bias)
        return graph, values

    def measured(self, j: int) -> Correction | None:
        """Keyframe j's NAP3D correction as the run measured it (None: there was none)."""
        i = self.stream.keyframes[j]
        if i not in self.stream.corrections:
            return None
        Z, R = (np.asarray(a, float) for a in self.stream.corrections[i])
        return Correction(Z, Z, R, Alignment(covariance=R, success=True), 1, True)

    def correction(self, j: int):
        """Keyframe j's NAP3D factor (the run's: ``nap3d_prior_factor``), or None (no correction,
        or an unusable covariance)."""
        correction = self.measured(j)
        if correction is None:
            return None
        try:
            return nap3d_prior_factor(X(j), None, correction, robust=self.robust)
        except ValueError as exc:
            log.warning("correction at frame %d not usable: %s", self.stream.keyframes[j], exc)
            return None

    def state(self, values: gtsam.Values, j: int):
        """Keyframe j's state in ``values``: a pose (4, 4), or ``(NavState, bias)``."""
        if self.imu is None:
            return pose3_to_T(values.atPose3(X(j)))
        return gtsam.NavState(values.atPose3(X(j)), values.atVector(V(j))), values.atConstantBias(B(j))

    def pose(self, state) -> np.ndarray:
        return state if self.imu is None else pose3_to_T(state[0].pose())

    def frames(self, states: list, n: int) -> np.ndarray:
        """Every frame's pose (n, 4, 4) from the keyframe states: on the odometry path from
        the nearest keyframe, the increments forwards or backwards (the run's own chaining,
        :func:`~nap3d_graph.run.chain.chain_from_nearest_keyframe`), on the IMU path predicted
        forward from the keyframe at or before it."""
        kf = np.asarray(self.stream.keyframes[:len(states)])
        if self.imu is None:
            return chain_from_nearest_keyframe({int(k): states[j] for j, k in enumerate(kf)}, self.stream.increments, n)
        T_world_cam = np.empty((n, 4, 4))
        for i in range(n):
            j = max(int(np.searchsorted(kf, i, side="right")) - 1, 0)
            T_world_cam[i] = self.predict(states[j], int(kf[j]), i)
        return T_world_cam

    def predict(self, state, i_from: int, i_to: int) -> np.ndarray:
        """Pose of frame ``i_to`` predicted from the state at frame ``i_from`` (not before it)."""
        s = self.stream
        if i_to <= i_from:
            return self.pose(state)
        if self.imu is None:
            pose = state
            for m in range(i_from + 1, i_to + 1):
                pose = pose @ s.increments[m]
            return pose
        nav, bias = state
        pim = self.imu.preintegrate(float(s.timestamps[i_from]), float(s.timestamps[i_to]), bias)
        return pose3_to_T(pim.predict(nav, bias).pose())


class Isam2Estimator:
    """The run's iSAM2 graph on the stream, reported causal and final: the run's own
    :class:`~nap3d_graph.run.graph.KeyframeGraph` (its updates, its gate, its rebuild after a
    failed update) fed with the stream's factors."""

    name = "isam2"
    reports = ("causal", "final")

    def __init__(self, relinearize_threshold: float = 1e-3, robust: str | None = "huber"):
        self.relinearize_threshold = relinearize_threshold
        self.robust = robust

    def start(self, stream) -> None:
        self.stream, self.model = stream, GraphModel(stream, self.robust)
        config = PipelineConfig(relinearize_threshold=self.relinearize_threshold, gate_p=stream.gate_p,
                                robust=self.robust)
        self.graph = KeyframeGraph(config, anchored=False)
        self.accepted: list[int] = []
        self.gate_d2: dict[int, float] = {}
        self.states: list = []  # each keyframe's state right after its own update (causal)
        self._add(*self.model.first())
        self._keyframe_done(0)

    @property
    def isam(self) -> gtsam.ISAM2:
        return self.graph.isam

    def _add(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> None:
        for k in range(graph.size()):
            self.graph.add(graph.at(k))
        self.graph.new_values.insert(values)
        self.graph.update()

    def _keyframe_done(self, j: int) -> None:
        i = self.stream.keyframes[j]
        correction = self.model.measured(j)
        if correction is not None:
            factor, gate = self.graph.gated_correction(X(j), correction, i)
            if gate is not None:
                self.gate_d2[i] = gate.d2
            if factor is not None:
                self.graph.update(extra_step=True)  # a correction can move the pose far from its linearisation
                self.accepted.append(i)
        estimate = self.isam.calculateEstimate()
        self.states.append(self.model.state(estimate, j))
        self.kf_frame, self.T = i, self.model.pose(self.states[-1])
        self.P = np.asarray(self.isam.marginalCovariance(X(j)))
        self.pim = None

    def step(self, i: int) -> None:
        j = self.model.kf_index.get(i)
        if j is None or j == 0:
            self._between(i)
            return
        self._add(*self.model.motion(j, self.states[-1]))
        self._keyframe_done(j)

    def _between(self, i: int) -> None:
        """A frame between keyframes: predicted from the latest keyframe's state."""
        s = self.stream
        if self.model.imu is None:
            self.T = self.T @ s.increments[i]
        else:  # a running preintegration from the keyframe, extended frame by frame
            nav, bias = self.states[-1]
            if self.pim is None:
                self.pim = gtsam.PreintegratedCombinedMeasurements(self.model.imu.params, bias)
            self.model.imu.extend(self.pim, float(s.timestamps[i - 1]), float(s.timestamps[i]))
            self.T = pose3_to_T(self.pim.predict(nav, bias).pose())
        self.P = None

    def current(self):
        return self.T.copy(), (None if self.P is None else 0.5 * (self.P + self.P.T))

    def final(self):
        started = time.perf_counter()
        estimate = self.isam.calculateEstimate()
        k = len(self.states)
        states = [self.model.state(estimate, j) for j in range(k)]
        T = self.model.frames(states, len(self.stream))
        P = np.full((len(self.stream), 6, 6), np.nan)
        for j, i in enumerate(self.stream.keyframes[:k]):
            P[i] = np.asarray(self.isam.marginalCovariance(X(j)))
        self.final_seconds = time.perf_counter() - started
        self.final_states = states
        return T, P


class BatchLM:
    """The whole graph, solved once after the last frame (GTSAM Levenberg-Marquardt)."""

    name = "batch-lm"
    reports = ("final",)

    def __init__(self, robust: str | None = "huber"):
        self.robust = robust

    def start(self, stream) -> None:
        self.stream, self.model = stream, GraphModel(stream, self.robust)
        self.accepted: list[int] = []
        self.T = np.asarray(stream.T_world_cam0, float).copy()

    def step(self, i: int) -> None:
        """Offline: nothing is known before the end (the causal pose is odometry's)."""
        if self.model.imu is None:
            self.T = self.T @ self.stream.increments[i]

    def current(self):
        return self.T.copy(), None

    def final(self):
        started = time.perf_counter()
        s, model = self.stream, self.model
        graph, values = model.first()
        state = model.state(values, 0)
        self.accepted = []
        for j, i in enumerate(s.keyframes):
            if j > 0:
                g, v = model.motion(j, state)  # initial values: the motion chained (dead reckoning)
                graph.push_back(g)
                values.insert(v)
                state = model.state(values, j)
            factor = model.correction(j)
            if factor is not None:
                graph.add(factor)
                self.accepted.append(i)
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(100)
        estimate = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
        states = [model.state(estimate, j) for j in range(len(s.keyframes))]
        T = model.frames(states, len(s))
        P = np.full((len(s), 6, 6), np.nan)
        try:
            marginals = gtsam.Marginals(graph, estimate)
            for j, i in enumerate(s.keyframes):
                P[i] = np.asarray(marginals.marginalCovariance(X(j)))
        except RuntimeError as exc:  # an ill-posed graph still has its estimate
            log.warning("batch LM marginals not computed: %s", exc)
        self.final_seconds = time.perf_counter() - started
        self.final_states = states
        return T, P
