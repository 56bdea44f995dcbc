"""Timestamp association of two streams and pose interpolation (TUM RGB-D conventions).

``associate`` pairs two stamp lists one-to-one within a tolerance: ``"optimal"`` (default)
keeps the most pairs with the least total time difference, ``"greedy"`` is TUM's
``associate.py``. ``estimate_stream_offset`` finds one stream's typical lead over the other;
``interpolate_poses`` brings ground truth to other stamps (linear translation + SLERP).
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from nap3d_graph.trajectory import interpolate_poses

__all__ = ["ASSOCIATION_METHODS", "associate", "estimate_stream_offset", "pair_streams",
           "GroundTruthLookup"]



# --- association and interpolation ----------------------------------------------------------


ASSOCIATION_METHODS = ("optimal", "greedy")


def _candidate_pairs(a: np.ndarray, b: np.ndarray, max_difference: float):
    """All ``(i_a, i_b, |a - b|)`` with ``|a - b| < max_difference`` (b already offset).

    Binary search per ``a`` (O((Na + Nb) log Nb + candidates), not Na x Nb); the window is
    widened a little, then filtered with TUM's exact test so rounding cannot change pairs.
    """
    order_b = np.argsort(b, kind="stable")
    b_sorted = b[order_b]
    slack = max_difference * 1e-9 + 1e-12
    lo = np.searchsorted(b_sorted, a - max_difference - slack, side="left")
    hi = np.searchsorted(b_sorted, a + max_difference + slack, side="right")
    counts = hi - lo
    ia = np.repeat(np.arange(len(a)), counts)
    starts = np.repeat(np.cumsum(counts) - counts, counts)
    ib = order_b[np.repeat(lo, counts) + (np.arange(counts.sum()) - starts)]
    diff = np.abs(a[ia] - b[ib])
    keep = diff < max_difference
    return ia[keep], ib[keep], diff[keep]


def _greedy_pairs(a, b, ia, ib, diff) -> list[tuple[int, int]]:
    """TUM's associate.py: candidates by increasing difference (ties by a, then b), each
    stamp used once. Sequential, but over the few candidates only."""
    order = np.lexsort((b[ib], a[ia], diff))  # sort by diff, then a, then b (TUM's tuple sort)
    used_a = np.zeros(len(a), dtype=bool)
    used_b = np.zeros(len(b), dtype=bool)
    pairs = []
    for i, j in zip(ia[order].tolist(), ib[order].tolist()):
        if not used_a[i] and not used_b[j]:
            used_a[i] = used_b[j] = True
            pairs.append((i, j))
    return pairs


def _optimal_pairs(a, b, ia, ib, diff, max_difference: float) -> list[tuple[int, int]]:
    """Most one-to-one pairs among the candidates and, among those, least total |a - b|.

    Exact, in O(candidates), by dynamic programming over *order-preserving* matchings. On a
    line, two crossing pairs ``(a1, b1), (a2, b2)`` with ``a1 <= a2``, ``b2 <= b1`` can be
    swapped to ``(a1, b2), (a2, b1)``: both stay within ``max_difference`` and the total
    ``|a - b|`` does not grow (``|x|`` is convex). So some optimum pairs the stamps in order,
    and an LCS-like scan over ``a`` in time order, looking only at each stamp's candidate
    band, finds it. This is the assignment problem ``linear_sum_assignment`` solves on the
    dense Na x Nb cost matrix (infeasible pairs costing more than any feasible total), which
    the tests use as the reference; the scan needs no dense matrix, no splitting into
    components and no windows, so long sequences are neither slow nor approximated.
    """
    if len(ia) == 0:
        return []
    order_b, ia, rb, cost = _candidates_in_scan_order(a, b, ia, ib, diff, max_difference)
    best, node, pair_a, pair_b, parent = _scan(ia.tolist(), rb.tolist(), cost.tolist(), len(b),
                                               float(min(len(a), len(b)) + 1))
    pairs, m = [], node[max(range(len(b) + 1), key=best.__getitem__)]
    while m >= 0:  # back along the winning matching's pairs
        pairs.append((pair_a[m], int(order_b[pair_b[m]])))
        m = parent[m]
    return pairs


def _candidates_in_scan_order(a, b, ia, ib, diff, max_difference: float):
    """``(order_b, ia, rb, cost)``: b's stamps in time order (``order_b``: rank -> index), and
    the candidates with a in time order (ties in index order), each a's candidates by
    increasing b rank ``rb``, their cost ``|a - b| / max_difference`` in [0, 1)."""
    order_b = np.argsort(b, kind="stable")
    rank_b = np.empty(len(b), dtype=int)
    rank_b[order_b] = np.arange(len(b))
    rb = rank_b[ib]
    order = np.lexsort((rb, ia, a[ia]))
    return order_b, ia[order], rb[order], diff[order] / max_difference


def _scan(ia: list, rb: list, cost: list, n_b: int, big: float):
    """The order-preserving scan of :func:`_optimal_pairs` over the candidates (in scan order).
    Score = pairs * ``big`` - total cost: with ``big`` above any total cost, one more pair always
    wins, and among equally many pairs the cheaper total does. Returns ``best[p]`` (the best
    score whose last used b has rank p - 1; p = 0: none), ``node[p]`` (its last pair) and the
    pairs' tree: ``pair_a``, ``pair_b`` (b's rank), ``parent``."""
    best = [-math.inf] * (n_b + 1)
    node = [-1] * (n_b + 1)
    best[0] = 0.0
    pair_a: list[int] = []
    pair_b: list[int] = []
    parent: list[int] = []
    done, done_best, done_node = 0, -math.inf, -1  # running max over best[:done], final
    start, n = 0, len(ia)
    while start < n:
        stop = start
        while stop < n and ia[stop] == ia[start]:
            stop += 1
        i, lo = ia[start], rb[start]
        # Later stamps only write at positions > lo, so best[:lo + 1] is final: fold it.
        while done <= lo:
            if best[done] > done_best:
                done_best, done_node = best[done], node[done]
            done += 1
        # For each candidate rank k: the best matching using only b ranks < k (positions
        # <= k, old values), plus the pair (i, k).
        run_best, run_node, p = done_best, done_node, done
        scored = []
        for t in range(start, stop):
            k = rb[t]
            while p <= k:
                if best[p] > run_best:
                    run_best, run_node = best[p], node[p]
                p += 1
            scored.append((k, run_best + big - cost[t], run_node))
        for k, score, parent_node in scored:
            if score > best[k + 1]:
                best[k + 1] = score
                node[k + 1] = len(pair_a)
                pair_a.append(i)
                pair_b.append(k)
                parent.append(parent_node)
        start = stop
    return best, node, pair_a, pair_b, parent


def associate(
    stamps_a: Sequence[float],
    stamps_b: Sequence[float],
    max_difference: float = 0.02,
    offset: float = 0.0,
    association: str = "optimal",
) -> np.ndarray:
    """Pair two timestamp lists one-to-one; a pair needs ``|a - (b + offset)| < max_difference``.

    ``association="optimal"`` (default) keeps the most pairs and, among those, the least
    total time difference (exact; see ``_optimal_pairs``). ``"greedy"`` is TUM's
    ``associate.py``: candidates taken in order of increasing difference (ties by ``a``
    then ``b``), each stamp used once. Greedy can lose pairs: on fr1/xyz the depth frame
    ~18 ms after a colour frame is sometimes taken, leaving the next colour frame with none
    (of the first 37 frames greedy keeps 32, optimal 36: colour frame 31's own depth frame
    is 20.2 ms before it; ``offset=0.015``, the Kinect's depth lead, pairs all 37).

    Returns index pairs ``(K, 2)`` int ``[i_a, i_b]`` sorted by ``stamps_a[i_a]``.
    """
    if association not in ASSOCIATION_METHODS:
        raise ValueError(f"association must be one of {ASSOCIATION_METHODS}, got {association!r}")
    a = np.asarray(stamps_a, dtype=float).reshape(-1)
    b = np.asarray(stamps_b, dtype=float).reshape(-1) + offset
    if len(a) == 0 or len(b) == 0:
        return np.zeros((0, 2), dtype=int)
    ia, ib, diff = _candidate_pairs(a, b, max_difference)
    if association == "greedy":
        pairs = _greedy_pairs(a, b, ia, ib, diff)
    else:
        pairs = _optimal_pairs(a, b, ia, ib, diff, max_difference)
    if not pairs:
        return np.zeros((0, 2), dtype=int)
    pairs = np.asarray(pairs, dtype=int)
    return pairs[np.lexsort((pairs[:, 0], a[pairs[:, 0]]))]


def estimate_stream_offset(stamps_a, stamps_b, max_difference: float = 0.02) -> float:
    """The typical lead of stream b over stream a, as ``associate``'s ``offset``.

    The median of ``a - nearest(b)`` over the stamps of a that have a partner within
    ``max_difference``: a Kinect stamps depth 12-20 ms before colour, and pairing with that
    lead removed associates every frame of fr1/xyz (37 of 37) where a zero offset leaves
    one without a partner inside TUM's 20 ms. 0.0 when nothing is near.
    """
    a = np.sort(np.asarray(stamps_a, dtype=float).reshape(-1))
    b = np.sort(np.asarray(stamps_b, dtype=float).reshape(-1))
    if a.size == 0 or b.size == 0:
        return 0.0
    j = np.clip(np.searchsorted(b, a), 1, max(b.size - 1, 1))
    left = b[np.clip(j - 1, 0, b.size - 1)]
    right = b[np.clip(j, 0, b.size - 1)]
    nearest = np.where(np.abs(a - left) <= np.abs(a - right), left, right)
    lead = a - nearest
    lead = lead[np.abs(lead) < max_difference]
    return float(np.median(lead)) if lead.size else 0.0


class GroundTruthLookup:
    """Ground-truth queries shared by the sequence classes. A sequence sets ``T_world_cam_gt``
    ((N, 4, 4) at its frames, NaN where none; or None) and ``_gt_raw`` (the raw ``(stamps,
    poses)`` or None)."""

    T_world_cam_gt: np.ndarray | None
    _gt_raw: tuple[np.ndarray, np.ndarray] | None
    #: Written by nap3d-graph's simulator (a room it rendered), not recorded by a camera.
    simulated: bool = False

    @property
    def has_gt(self) -> np.ndarray:
        """(N,) bool: frames with a ground-truth pose (all False without ground truth)."""
        if self.T_world_cam_gt is None:
            return np.zeros(len(self), dtype=bool)
        return np.all(np.isfinite(self.T_world_cam_gt), axis=(1, 2))

    @property
    def ground_truth_samples(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The ground truth as recorded: ``(stamps (M,), T_world_cam (M, 4, 4))``, or None."""
        return self._gt_raw

    def ground_truth_at(self, stamps) -> np.ndarray | None:
        """Ground-truth poses (M, 4, 4) interpolated at any times (M,) (NaN outside or in a
        gap of the ground truth), e.g. at the depth stamps; None without ground truth."""
        if self._gt_raw is None:
            return None
        return interpolate_poses(*self._gt_raw, np.asarray(stamps, dtype=float))


def pair_streams(stamps_a, stamps_b, max_difference: float = 0.02, association: str = "optimal"
                 ) -> tuple[float, np.ndarray]:
    """``(offset, pairs)``: stream b paired to stream a with its estimated lead removed
    (:func:`estimate_stream_offset`), unless a zero offset pairs more frames.

    The lead estimate helps raw recordings (fr1/xyz: 37 of 37 frames instead of 36), but
    lists that were already associated (every colour stamp has its partner, as in a
    subsampled copy of a sequence) can lose frames by it: fr1/desk at 15 Hz kept 211 of its
    277 listed pairs with the 7 ms estimate. Keeping whichever pairs more frames never drops
    a frame the plain pairing had.
    """
    estimated = estimate_stream_offset(stamps_a, stamps_b, max_difference)
    with_lead = associate(stamps_a, stamps_b, max_difference, estimated, association)
    plain = associate(stamps_a, stamps_b, max_difference, 0.0, association)
    if len(plain) > len(with_lead):
        return 0.0, plain
    return estimated, with_lead
