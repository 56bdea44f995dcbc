"""The survey's robust pose graph in GTSAM.

One ``Pose3`` per keyframe (keys X), the first held at the identity (the gauge: the map's
frame is the first keyframe's camera; depth gives the metric scale). Consecutive keyframes
are tied by their own real-vs-real alignment where it verified and agrees with the odometry,
else by the odometry's chained steps; every verified loop is a between factor weighted by
its covariance. GTSAM's graduated non-convexity (``GncLMOptimizer``, truncated least
squares; Yang et al., RA-L 2020) solves it with the consecutive edges known inliers, so a
false loop (a repeated texture) gets weight 0 and cannot bend the map. A loop GNC keeps is
checked once more against the chi-square gate at the solution.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from nap3d_graph.conventions import T_to_pose3, pose3_to_T
from nap3d_graph.factors import mahalanobis_sq as factor_mahalanobis_sq
from nap3d_graph.factors import noise_model
from nap3d_graph.factors.gate import chi2_threshold

__all__ = ["Edge", "GraphResult", "solve", "floor_covariance", "mahalanobis_sq", "between_factor"]

log = logging.getLogger(__name__)


@dataclass
class Edge:
    """A between factor ``T_a_b`` (4, 4) with its covariance (6, 6), between keyframe
    positions a and b; ``kind``: 'odometry', 'alignment' (consecutive) or 'loop'."""

    a: int
    b: int
    T_a_b: np.ndarray
    covariance: np.ndarray
    kind: str


@dataclass
class GraphResult:
    """``T_map_key`` (K, 4, 4) the keyframes' poses; ``loop_weights`` (L,) GNC's final
    weight of each loop edge (1 kept, 0 rejected); ``loop_kept`` (L,) bool after the gate;
    ``loop_d2`` (L,) each loop's squared Mahalanobis distance at the solution."""

    T_map_key: np.ndarray
    loop_weights: np.ndarray
    loop_kept: np.ndarray
    loop_d2: np.ndarray


def floor_covariance(covariance: np.ndarray, rot_sigma_rad: float, trans_sigma_m: float) -> np.ndarray:
    """The covariance with at least these sigmas added on its diagonal: what an alignment's
    residuals do not see (capture timing, rolling shutter, the calibration) is not zero."""
    return np.asarray(covariance, dtype=float) + np.diag([rot_sigma_rad**2] * 3 + [trans_sigma_m**2] * 3)


def mahalanobis_sq(T_a: np.ndarray, T_b: np.ndarray, edge: Edge) -> float:
    """Squared Mahalanobis distance of ``edge`` at poses ``T_a``, ``T_b``: the gate's
    (:func:`nap3d_graph.factors.mahalanobis_sq`) on the edge's between factor."""
    import gtsam
    from gtsam.symbol_shorthand import X


    values = gtsam.Values()
    values.insert(X(edge.a), T_to_pose3(T_a))
    values.insert(X(edge.b), T_to_pose3(T_b))
    return factor_mahalanobis_sq(between_factor(edge), values)


def between_factor(edge: Edge):
    """The edge as a GTSAM between factor of keys X(a), X(b), weighted by its covariance."""
    import gtsam
    from gtsam.symbol_shorthand import X


    return gtsam.BetweenFactorPose3(X(edge.a), X(edge.b), T_to_pose3(edge.T_a_b), noise_model(covariance=edge.covariance))


def _graph(num_keys: int, edges: list[Edge], held: np.ndarray | None = None):
    """The factor graph: the gauge (keyframe 0 at the identity), or with ``held`` (H, 4, 4) the
    first H keyframes held at those poses; then a between factor per edge."""
    import gtsam
    from gtsam.symbol_shorthand import X


    graph = gtsam.NonlinearFactorGraph()
    pin = noise_model(rot_sigma_rad=1e-6, trans_sigma_m=1e-6)
    for k, T in enumerate([np.eye(4)] if held is None else held):
        graph.add(gtsam.PriorFactorPose3(X(k), T_to_pose3(T), pin))
    for edge in edges:
        graph.add(between_factor(edge))
    return graph


def _values(T_map_key: np.ndarray):
    import gtsam
    from gtsam.symbol_shorthand import X

    values = gtsam.Values()
    for k, T in enumerate(T_map_key):
        values.insert(X(k), T_to_pose3(T))
    return values


def _poses(values, num_keys: int) -> np.ndarray:
    from gtsam.symbol_shorthand import X

    return np.stack([pose3_to_T(values.atPose3(X(k))) for k in range(num_keys)])


def solve(T_init: np.ndarray, chain: list[Edge], loops: list[Edge], gate_p: float = 0.999, held: int = 0
          ) -> GraphResult:
    """Solve the graph from ``T_init`` (K, 4, 4): ``chain`` edges are trusted, ``loops`` are
    decided by GNC and then gated at probability ``gate_p`` (chi-square, 6 dof). ``held``: the
    first so many keyframes stay where ``T_init`` puts them (a map being extended: its fields
    were trained at those poses) instead of the gauge at keyframe 0."""
    import gtsam

    num_keys = len(T_init)
    edges = chain + loops
    pinned = np.asarray(T_init, dtype=float)[:held] if held else None
    priors = held or 1
    graph = _graph(num_keys, edges, pinned)
    initial = _values(T_init)
    if loops:
        params = gtsam.GncLMParams(gtsam.LevenbergMarquardtParams())
        params.setKnownInliers(list(range(priors + len(chain))))  # the priors and the consecutive edges
        params.setLossType(gtsam.GncLossType.TLS)
        optimizer = gtsam.GncLMOptimizer(graph, initial, params)
        optimizer.setInlierCostThresholdsAtProbability(gate_p)
        values = optimizer.optimize()
        weights = np.asarray(optimizer.getWeights())[priors + len(chain):]
    else:
        values = gtsam.LevenbergMarquardtOptimizer(graph, initial, gtsam.LevenbergMarquardtParams()).optimize()
        weights = np.zeros(0)
    kept = weights > 0.5
    # Once more with the kept loops alone, as Gaussians, and each one gated at the solution.
    threshold = chi2_threshold(gate_p, 6)
    for _ in range(len(loops) + 1):
        graph = _graph(num_keys, chain + [e for e, k in zip(loops, kept) if k], pinned)
        values = gtsam.LevenbergMarquardtOptimizer(graph, values, gtsam.LevenbergMarquardtParams()).optimize()
        T_map_key = _poses(values, num_keys)
        d2 = np.array([mahalanobis_sq(T_map_key[e.a], T_map_key[e.b], e) for e in loops])
        worst = np.argmax(np.where(kept, d2, -np.inf)) if kept.any() else None
        if worst is None or d2[worst] <= threshold:
            break
        kept[worst] = False  # drop the worst offender, solve again
    T_map_key = _poses(values, num_keys)
    d2 = np.array([mahalanobis_sq(T_map_key[e.a], T_map_key[e.b], e) for e in loops])
    return GraphResult(T_map_key, weights, kept, d2)
