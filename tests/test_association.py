"""Timestamp association (optimal and TUM's greedy) and ground-truth interpolation."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import TUM_FR1_XYZ as TUM_DIR
from scipy.optimize import linear_sum_assignment

from nap3d_graph.camera import Intrinsics
from nap3d_graph.conventions import make_T
from nap3d_graph.datasets import DatasetError
from nap3d_graph.datasets.association import associate
from nap3d_graph.datasets.tum import read_file_list
from nap3d_graph.trajectory import interpolate_poses

FR1 = Intrinsics(517.3, 516.5, 318.6, 255.3, 640, 480)
FR1_DISTORTION = (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)


# --- association ------------------------------------------------------------------------------


def _reference_associate(first, second, offset, max_difference):
    """TUM associate.py's algorithm, literally (quadratic), on index lists."""
    candidates = sorted(
        (abs(a - (b + offset)), a, b, i, j)
        for i, a in enumerate(first)
        for j, b in enumerate(second)
        if abs(a - (b + offset)) < max_difference
    )
    free_a, free_b, matches = set(range(len(first))), set(range(len(second))), []
    for _, a, _, i, j in candidates:
        if i in free_a and j in free_b:
            free_a.remove(i)
            free_b.remove(j)
            matches.append((a, i, j))
    return [(i, j) for _, i, j in sorted(matches)]


def test_associate_offset_stamps():
    a = np.arange(20) * 0.033
    b = a - 0.015  # depth 15 ms early, as on the Kinect
    assert associate(a, b, 0.02, offset=0.015).tolist() == [[i, i] for i in range(20)]
    shifted = associate(a, b + 10.0, 0.02, offset=-9.985)
    assert shifted.tolist() == [[i, i] for i in range(20)]
    assert len(associate(a, b + 10.0, 0.02)) == 0


def _assignment_reference(a, b, offset, max_difference):
    """Optimal association as the dense assignment problem: (number of pairs, total |diff|).

    Infeasible pairs cost more than any feasible total (costs in units of max_difference
    are < 1 each, so min(Na, Nb) + 1 is enough): the assignment first avoids them, which
    maximises the pairs, then minimises the total difference.
    """
    diff = np.abs(np.asarray(a)[:, None] - (np.asarray(b)[None, :] + offset))
    feasible = diff < max_difference
    cost = np.where(feasible, diff / max_difference, min(len(a), len(b)) + 1.0)
    rows, cols = linear_sum_assignment(cost)
    kept = feasible[rows, cols]
    return int(kept.sum()), float(diff[rows[kept], cols[kept]].sum())


def _check_one_to_one(pairs, a, b, offset, max_difference):
    assert len(set(pairs[:, 0].tolist())) == len(set(pairs[:, 1].tolist())) == len(pairs)
    diff = np.abs(np.asarray(a)[pairs[:, 0]] - (np.asarray(b)[pairs[:, 1]] + offset))
    assert np.all(diff < max_difference)
    assert np.all(np.diff(np.asarray(a)[pairs[:, 0]]) >= 0)  # sorted by the first stamp
    return float(diff.sum())


def test_associate_greedy_is_tums_and_unique():
    # (a1, b0) is the closest pair, so greedy gives a0 nothing although b0 is a0's only
    # neighbour; optimal pairs both (a0-b0 10 ms, a1-b1 18 ms).
    assert associate([0.0, 0.012], [0.010, 0.030], 0.02, association="greedy").tolist() == [[1, 0]]
    assert associate([0.0, 0.012], [0.010, 0.030], 0.02).tolist() == [[0, 0], [1, 1]]
    # One b stamp between two a stamps is used once, by the nearer a (both methods).
    for method in ("greedy", "optimal"):
        assert associate([0.0, 0.01], [0.006], 0.02, association=method).tolist() == [[1, 0]]
        # Output sorted by the first stamp, whatever the input order.
        assert associate([0.2, 0.1, 0.0], [0.0, 0.1, 0.2], 0.02, association=method).tolist() == [
            [2, 0], [1, 1], [0, 2]
        ]
        assert associate([], [1.0], association=method).shape == (0, 2)
    with pytest.raises(ValueError, match="association must be one of"):
        associate([0.0], [0.0], association="hungarian")


def test_associate_optimal_least_total_difference():
    # Both ways pair both stamps: greedy takes the 1 ms pair first and is left with 19 ms
    # (20 ms in all); optimal pairs in order, 9 + 9 ms.
    a, b = [0.0, 0.010], [0.009, 0.019]
    assert associate(a, b, 0.02, association="greedy").tolist() == [[0, 1], [1, 0]]
    assert associate(a, b, 0.02).tolist() == [[0, 0], [1, 1]]
    # A chain where greedy's first choice (a1-b0, 1 ms) costs two pairs.
    a, b = [0.0, 0.019, 0.038], [0.018, 0.037, 0.056]
    assert associate(a, b, 0.02, association="greedy").tolist() == [[1, 0], [2, 1]]
    assert associate(a, b, 0.02).tolist() == [[0, 0], [1, 1], [2, 2]]


def test_associate_tolerance_is_strict():
    for method in ("greedy", "optimal"):
        assert associate([0.0], [0.019], 0.02, association=method).tolist() == [[0, 0]]
        assert associate([0.0], [0.021], 0.02, association=method).tolist() == []
        assert associate([0.0], [0.25], 0.3, association=method).tolist() == [[0, 0]]


def test_associate_greedy_matches_tum_reference():
    rng = np.random.default_rng(7)
    for _ in range(20):
        a = np.sort(rng.uniform(0, 2, rng.integers(1, 60)))
        b = np.sort(rng.uniform(0, 2, rng.integers(1, 60)))
        offset = rng.uniform(-0.02, 0.02)
        expected = _reference_associate(a.tolist(), b.tolist(), offset, 0.03)
        assert associate(a, b, 0.03, offset, association="greedy").tolist() == [list(p) for p in expected]


def test_associate_optimal_matches_assignment_reference():
    rng = np.random.default_rng(11)
    greedy_short = 0
    for trial in range(300):
        na, nb = rng.integers(1, 50, size=2)
        if trial % 3 == 0:  # unordered, arbitrary stamps
            a, b = rng.uniform(0, 1, na), rng.uniform(0, 1, nb)
        elif trial % 3 == 1:  # ties: 10 ms grid
            a, b = np.round(rng.uniform(0, 1, na), 2), np.round(rng.uniform(0, 1, nb), 2)
        else:  # camera-like: 30 Hz streams, depth ~15 ms early, jitter
            a = np.arange(na) / 30 + rng.normal(0, 0.003, na)
            b = np.arange(nb) / 30 - 0.015 + rng.normal(0, 0.003, nb)
        max_difference, offset = rng.uniform(0.005, 0.1), rng.uniform(-0.02, 0.02)
        pairs = associate(a, b, max_difference, offset)
        count, total = _assignment_reference(a, b, offset, max_difference)
        assert len(pairs) == count, trial
        assert _check_one_to_one(pairs, a, b, offset, max_difference) == pytest.approx(total, abs=1e-9)
        greedy_short += len(associate(a, b, max_difference, offset, association="greedy")) < count
    assert greedy_short > 30  # greedy loses pairs often on such lists


def test_associate_long_streams():
    # 5000 frames of 30 Hz colour and depth 15 ms early with jitter: each colour frame has
    # its own depth frame within 20 ms (so all 5000 can pair), often a second one too.
    # (Its speed is measured in benchmarks/association.py.)
    rng = np.random.default_rng(3)
    a = np.arange(5000) / 30 + rng.uniform(-0.002, 0.002, 5000)
    b = a - 0.015 + rng.uniform(-0.003, 0.003, 5000)
    pairs = associate(a, b, 0.02)
    assert len(pairs) == 5000 and pairs.tolist() == [[i, i] for i in range(5000)]
    greedy = associate(a, b, 0.02, association="greedy")
    assert 4000 < len(greedy) < 5000  # greedy takes the later depth frame when it is nearer
    _check_one_to_one(greedy, a, b, 0.0, 0.02)


def test_associate_real_lists():
    stamps_rgb, names_rgb = read_file_list(TUM_DIR / "rgb.txt")
    stamps_depth, names_depth = read_file_list(TUM_DIR / "depth.txt")
    assert len(stamps_rgb) == len(stamps_depth) == 12
    assert names_rgb[0] == "rgb/1305031102.175304.png" and stamps_rgb[0] == 1305031102.175304
    expected = _reference_associate(stamps_rgb.tolist(), stamps_depth.tolist(), 0.0, 0.02)
    greedy = associate(stamps_rgb, stamps_depth, association="greedy")
    assert greedy.tolist() == [list(p) for p in expected]
    # Greedy pairs colour 1 with depth 2 (16.5 ms after it... before colour 2), and colour 10
    # with depth 11: two frames lost, two wrong partners.
    assert len(expected) == 10 and [1, 2] in greedy.tolist() and [10, 11] in greedy.tolist()
    # Optimal: every frame with its own depth frame, the most any pairing can have.
    optimal = associate(stamps_rgb, stamps_depth)
    assert optimal.tolist() == [[i, i] for i in range(12)]
    assert len(optimal) == _assignment_reference(stamps_rgb, stamps_depth, 0.0, 0.02)[0]
    # With the Kinect's ~15 ms depth lead as offset, greedy pairs them all correctly too.
    pairs = associate(stamps_rgb, stamps_depth, 0.02, offset=0.015, association="greedy")
    assert pairs.tolist() == [[i, i] for i in range(12)]


def test_read_file_list_errors(tmp_path):
    path = tmp_path / "rgb.txt"
    path.write_text("# colour\n\n1.0 rgb/1.png\n2.0\n")
    with pytest.raises(DatasetError, match=r"rgb\.txt:4: expected 'timestamp filename'"):
        read_file_list(path)
    path.write_text("abc rgb/1.png\n")
    with pytest.raises(DatasetError, match=r"rgb\.txt:1: 'abc' is not a number"):
        read_file_list(path)


# --- interpolation ----------------------------------------------------------------------------


def test_interpolate_poses():
    from scipy.spatial.transform import Rotation

    T0 = make_T(np.eye(3), [0.0, 0.0, 0.0])
    T1 = make_T(Rotation.from_euler("z", 90, degrees=True).as_matrix(), [1.0, 2.0, 0.0])
    T2 = make_T(Rotation.from_euler("z", 90, degrees=True).as_matrix(), [5.0, 2.0, 0.0])
    stamps = np.array([0.0, 0.1, 1.0])  # a 0.9 s hole between the last two
    queries = [-0.01, 0.0, 0.025, 0.05, 0.1, 0.5, 1.0, 1.01]
    T = interpolate_poses(stamps, np.stack([T0, T1, T2]), queries, max_gap=0.2)
    ok = np.all(np.isfinite(T), axis=(1, 2))
    # Outside the span, or inside the hole, is NaN; the stamps on either side of it are not.
    assert ok.tolist() == [False, True, True, True, True, False, True, False]
    assert np.allclose(T[1], T0) and np.allclose(T[4], T1) and np.allclose(T[6], T2)
    assert np.allclose(T[3][:3, 3], [0.5, 1.0, 0.0])
    assert Rotation.from_matrix(T[3][:3, :3]).as_euler("zyx", degrees=True) == pytest.approx([45, 0, 0])
    assert Rotation.from_matrix(T[2][:3, :3]).as_euler("zyx", degrees=True) == pytest.approx([22.5, 0, 0])
    # A wide enough max_gap bridges the hole; the last stamp itself is inside the span.
    T = interpolate_poses(stamps, np.stack([T0, T1, T2]), [0.55, 1.0], max_gap=1.0)
    assert np.allclose(T[0][:3, 3], [3.0, 2.0, 0.0]) and np.allclose(T[1], T2)
