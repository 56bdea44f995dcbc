"""The survey's bundle adjustment on a simulated rolling-shutter camera: the readout is found
from the pixels alone, and undoing it brings the keyframes back to where they were."""

from __future__ import annotations

import numpy as np
import pytest

from nap3d_graph.camera import Intrinsics
from nap3d_graph.conventions import exp_se3, inv_T
from nap3d_graph.mapping.bundle import BundleSettings, PairMatches, bundle_adjust, keyframe_twists

K = Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)
KEYFRAME_GAP_S = 0.2


def _path(n: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """``(T_world_key (n, 4, 4), twists (n, 6))``: a hand-held sweep at about 0.5 m/s and 30
    deg/s whose twist changes from keyframe to keyframe (each keyframe the last carried along
    its twist, so the twist is the camera's at that instant)."""
    T = [np.eye(4)]
    twists = []
    for _ in range(n):
        xi = np.concatenate([rng.normal(0, 0.25, 3) + [0.0, 0.4, 0.0], rng.normal(0, 0.15, 3) + [0.45, 0.0, 0.0]])
        twists.append(xi)
        T.append(T[-1] @ exp_se3(xi * KEYFRAME_GAP_S))
    return np.stack(T[:n]), np.stack(twists)


def _observe(T_world_key, twist, points_world, readout_s, rng):
    """Pixels (N, 2) and depths (N,) of ``points_world`` in a rolling-shutter keyframe: each row
    read at ``(v / H - 0.5) readout_s`` from the middle row, the camera carried along
    ``twist``; the row a point lands on solved by fixed-point iteration. NaN where unseen."""
    v = np.full(len(points_world), K.cy)
    for _ in range(6):
        dt = (v / K.height - 0.5) * readout_s
        T_cam_world = np.stack([inv_T(T_world_key @ exp_se3(twist * d)) for d in dt])
        p = np.einsum("nij,nj->ni", T_cam_world[:, :3, :3], points_world) + T_cam_world[:, :3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = K.fx * p[:, 0] / p[:, 2] + K.cx, K.fy * p[:, 1] / p[:, 2] + K.cy
        v = np.where(np.isfinite(v), v, K.cy)
    seen = (p[:, 2] > 0.3) & (u >= 0) & (u < K.width) & (v >= 0) & (v < K.height)
    uv = np.stack([u, v], 1) + rng.normal(0, 0.3, (len(u), 2))
    z = p[:, 2] * (1 + rng.normal(0, 0.002, len(u)))
    uv[~seen] = np.nan
    return uv, np.where(seen, z, np.nan)


def _survey(readout_s: float, seed: int = 0):
    """True keyframe poses, their twists, the verified matches between keyframes within three
    of each other, and starting poses 1 cm / 0.5 deg off."""
    rng = np.random.default_rng(seed)
    T_true, twists = _path(10, rng)
    centre = T_true[:, :3, 3].mean(0)
    points = centre + rng.uniform([-2.5, -2.0, 1.5], [2.5, 2.0, 4.0], (1500, 3))
    seen = [_observe(T, xi, points, readout_s, rng) for T, xi in zip(T_true, twists)]
    pairs = []
    for a in range(len(T_true)):
        for b in range(a + 1, min(a + 4, len(T_true))):
            both = np.all(np.isfinite(seen[a][0]), 1) & np.all(np.isfinite(seen[b][0]), 1)
            pairs.append(PairMatches(a, b, seen[a][0][both], seen[b][0][both], seen[a][1][both], seen[b][1][both]))
    T_start = np.stack([T if k == 0 else T @ exp_se3(np.concatenate([rng.normal(0, 0.005, 3), rng.normal(0, 0.006, 3)]))
                        for k, T in enumerate(T_true)])
    return T_true, twists, pairs, T_start


def _position_error_m(T_est, T_true) -> float:
    """RMS keyframe position error (m); the first keyframe holds the gauge in both."""
    return float(np.sqrt(np.mean(np.sum((T_est[:, :3, 3] - T_true[:, :3, 3]) ** 2, axis=1))))


@pytest.fixture(scope="module")
def rolling():
    return _survey(readout_s=0.025)


def test_the_bundle_finds_a_rolling_shutters_readout_from_the_pixels_and_undoes_it(rolling):
    T_true, twists, pairs, T_start = rolling
    T_global, global_report = bundle_adjust(T_start, pairs, K, BundleSettings(readout_s=0.0), twists)
    T_found, report = bundle_adjust(T_start, pairs, K, BundleSettings(), twists)
    assert report["readout_s"] == pytest.approx(0.025, abs=0.004)
    searched = dict(map(tuple, report["readout_search"]))
    assert searched[0.0] > 1.2 * min(searched.values())  # the global shutter's pixels agree worse
    assert _position_error_m(T_found, T_true) < 0.5 * _position_error_m(T_global, T_true)
    assert _position_error_m(T_found, T_true) < 0.004


def test_the_bundle_keeps_a_global_shutter_and_without_twists_reads_none(rolling):
    T_true, twists, pairs, T_start = _survey(readout_s=0.0, seed=1)
    T_found, report = bundle_adjust(T_start, pairs, K, BundleSettings(), twists)
    assert report["readout_s"] <= 0.005
    assert _position_error_m(T_found, T_true) < 0.002
    _, rolling_pairs, rolling_start = rolling[1], rolling[2], rolling[3]
    _, plain = bundle_adjust(rolling_start, rolling_pairs, K, BundleSettings(), None)
    assert plain["readout_s"] == 0.0 and plain["readout_search"] == []


def test_keyframe_twists_are_the_odometrys_relative_motion_per_second():
    rng = np.random.default_rng(3)
    xi = np.array([0.1, -0.3, 0.2, 0.4, 0.05, -0.1])
    stamps = np.arange(20) / 30.0
    # The odometry's frame is arbitrary (it drifts): start it anywhere.
    T0 = exp_se3(rng.normal(0, 1, 6))
    T_odom = np.stack([T0 @ exp_se3(xi * t) for t in stamps])
    twists = keyframe_twists(T_odom, stamps, np.array([0, 7, 19]))
    np.testing.assert_allclose(twists, np.tile(xi, (3, 1)), atol=1e-9)
    T_odom[8] = np.nan  # a frame the odometry never placed gives no twist rather than a wrong one
    assert np.all(keyframe_twists(T_odom, stamps, np.array([7]))[0] == 0.0)


def test_loops_the_graph_turned_away_are_admitted_when_their_matches_agree_and_a_false_one_never(rolling):
    from nap3d_graph.mapping.build import adjust_keyframes
    from nap3d_graph.mapping.loops import Loop

    T_true, twists, pairs, T_start = rolling
    by_pair = {(p.a, p.b): p for p in pairs}
    chain = [by_pair[(a, a + 1)] for a in range(len(T_true) - 1)]

    def loop(a, b, matches, status):
        return Loop(a, b, a, b, "appearance", status=status, matches_kept=matches)

    kept = [loop(a, a + 2, by_pair[(a, a + 2)], "accepted") for a in range(len(T_true) - 2)]
    turned_away = [loop(a, a + 3, by_pair[(a, a + 3)], "rejected") for a in range(0, len(T_true) - 3, 2)]
    # A false loop: keyframes 0 and 3's matches, claimed between keyframes 0 and 8.
    wrong = by_pair[(0, 3)]
    false = loop(0, 8, PairMatches(0, 8, wrong.uv_a, wrong.uv_b, wrong.z_a, wrong.z_b), "rejected")
    T_key, report = adjust_keyframes(T_start, chain, kept + turned_away + [false], K, BundleSettings(), twists)
    assert [lp.status for lp in turned_away] == ["admitted"] * len(turned_away)
    assert all("admitted by the bundle adjustment" in lp.reason for lp in turned_away)
    assert false.status == "rejected"
    assert report["loops_admitted"] == len(turned_away)
    gate = report["admission"]["gate_px"]
    assert report["admission"]["turned_away_px"][-1] > 10 * gate  # the false loop is far outside, not near the gate
    assert report["readout_s"] == pytest.approx(0.025, abs=0.004)
    assert _position_error_m(T_key, T_true) < 0.004
    # Without admission (factor 0) nothing changes status.
    for lp in turned_away:
        lp.status = "rejected"
    adjust_keyframes(T_start, chain, kept + turned_away + [false], K, BundleSettings(admit_factor=0.0), twists)
    assert {lp.status for lp in turned_away + [false]} == {"rejected"}


def test_a_keyframe_that_sees_little_is_held_by_its_odometry_edge():
    """The last keyframe faces a blank wall: its only matches are three, to the keyframe before,
    and wrong (other points of the scene). On their own they carry it metres away; with the
    chain's odometry edge (the frames between the two measured the step, 1 cm / 0.6 deg) the
    robust kernel lets the edge hold it within a third of a metre, and the other keyframes stay
    as they were. (A 6-room simulated floor's survey: four keyframes at the edge of a loss
    floated 0.9 m; with the edges, 8.7 cm at most.)"""
    from nap3d_graph.mapping.pose_graph import Edge

    T_true, twists, pairs, T_start = _survey(readout_s=0.0, seed=2)
    last = len(T_true) - 1
    kept = [p for p in pairs if last not in (p.a, p.b)]
    rng = np.random.default_rng(5)
    before = next(p for p in pairs if (p.a, p.b) == (last - 1, last))
    pick, wrong = rng.choice(len(before.uv_a), 3, replace=False), rng.choice(len(before.uv_b), 3, replace=False)
    kept.append(PairMatches(last - 1, last, before.uv_a[pick], before.uv_b[wrong], before.z_a[pick],
                            before.z_b[wrong]))
    step = Edge(last - 1, last, inv_T(T_true[last - 1]) @ T_true[last], np.diag([1e-4] * 3 + [4e-4] * 3), "odometry")
    T_alone, _ = bundle_adjust(T_start, kept, K, BundleSettings(readout_s=0.0), None)
    T_held, _ = bundle_adjust(T_start, kept, K, BundleSettings(readout_s=0.0), None, odometry=[step])
    alone_m = np.linalg.norm(T_alone[last, :3, 3] - T_true[last, :3, 3])
    held_m = np.linalg.norm(T_held[last, :3, 3] - T_true[last, :3, 3])
    assert alone_m > 2.0 and held_m < 0.4
    assert _position_error_m(T_held[:last], T_true[:last]) < 0.002
