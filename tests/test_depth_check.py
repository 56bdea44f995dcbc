"""The depth against the images' triangulation (``map.json``'s ``bundle.depth_against_images``
and the map's report): a depth camera with a wrong disparity offset is told, one that agrees
with its images is not, and a survey without wide enough baselines says why it has no figure."""

from __future__ import annotations

import numpy as np

from nap3d_graph.camera import Intrinsics
from nap3d_graph.mapping.bundle import PairMatches
from nap3d_graph.mapping.depth_check import DEPTH_OFFSET_BAD_PER_M, DEPTH_SHAPE_BAD, depth_against_images

K = Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)


def _looking_at(centre: np.ndarray, eye: np.ndarray) -> np.ndarray:
    """A camera (map <- camera, OpenCV axes) at ``eye`` looking at ``centre``, y down."""
    z = (centre - eye) / np.linalg.norm(centre - eye)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    T[:3, 3] = eye
    return T


def _survey(offset_per_m: float, spread_deg: float, seed: int = 0, depth_span_m: float = 1.2,
            width_m: float = 1.0, noise: float = 0.003):
    """Keyframes on an arc 2 m from a cloud of points 2 m +- ``depth_span_m`` away,
    ``spread_deg`` between neighbours, every pair's matches with pixels (0.3 px noise) and
    depths read through a disparity offset: ``1 / z_depth = 1 / z - offset_per_m`` (and 0.3%
    noise)."""
    rng = np.random.default_rng(seed)
    centre = np.array([0.0, 0.0, 2.0])
    points = centre + rng.uniform(-1.0, 1.0, (2000, 3)) * [width_m, 0.7 * width_m, depth_span_m]
    angles = np.radians(spread_deg * (np.arange(6) - 2.5))
    T = np.stack([_looking_at(centre, centre + 2.0 * np.array([np.sin(a), 0.0, -np.cos(a)])) for a in angles])
    seen = []
    for T_key in T:
        p = (points - T_key[:3, 3]) @ T_key[:3, :3]
        uv = np.c_[K.fx * p[:, 0] / p[:, 2] + K.cx, K.fy * p[:, 1] / p[:, 2] + K.cy]
        inside = (p[:, 2] > 0.3) & np.all((uv >= 0) & (uv < [K.width, K.height]), axis=1)
        z = 1.0 / (1.0 / p[:, 2] - offset_per_m) * (1 + rng.normal(0, noise, len(p)))
        seen.append((uv + rng.normal(0, 0.3, uv.shape), z, inside))
    pairs = []
    for a in range(len(T)):
        for b in range(a + 1, len(T)):
            both = seen[a][2] & seen[b][2]
            pairs.append(PairMatches(a, b, seen[a][0][both], seen[b][0][both], seen[a][1][both], seen[b][1][both]))
    return pairs, T


def test_a_depth_camera_that_agrees_with_its_images_is_not_told():
    pairs, T = _survey(0.0, spread_deg=8.0)
    check = depth_against_images(pairs, T, K)
    assert check["observations"] > 5000
    assert abs(check["slope"] - 1.0) < 0.02 and abs(check["intercept_per_m"]) < 0.005
    assert check["worst"] < 0.01 and not check["bad"]
    near, far = check["bins"][0][0], check["bins"][-1][0]
    assert near < 1.4 and far > 2.4  # nearest first, over the cloud's depths


def test_a_wrong_disparity_offset_is_measured_and_told():
    pairs, T = _survey(0.05, spread_deg=8.0)  # far depth reads long: 3 m as 3.5 m
    check = depth_against_images(pairs, T, K)
    # 1 / z_images = 1 / z_depth + 0.05: the fit finds the offset the depth was read through
    assert abs(check["intercept_per_m"] - 0.05) < 0.005 and abs(check["slope"] - 1.0) < 0.02
    ratios = [r for _, r in check["bins"]]
    assert ratios[-1] > 1.02 > 0.98 > ratios[0]  # far reads long against the median bin, near short
    assert check["worst"] > DEPTH_SHAPE_BAD and check["bad"]
    milder = depth_against_images(*_survey(0.01, spread_deg=8.0), K)  # 3 m as 3.1 m: within the lines
    assert abs(milder["intercept_per_m"] - 0.01) < 0.005 and not milder["bad"]
    # A survey that saw depths within 30 cm of each other: its bins cannot show the offset, the line does.
    narrow = depth_against_images(*_survey(0.05, spread_deg=8.0, depth_span_m=0.3), K)
    assert narrow["worst"] < DEPTH_SHAPE_BAD
    assert abs(narrow["intercept_per_m"] - 0.05) < 0.01 and narrow["intercept_per_m"] > DEPTH_OFFSET_BAD_PER_M
    assert narrow["bad"]


def test_a_survey_without_wide_baselines_says_why_it_has_no_figure():
    pairs, T = _survey(0.0, spread_deg=0.3)  # the widest pair 1.5 deg apart: few rays reach 8 deg
    check = depth_against_images(pairs, T, K)
    assert "reason" in check and "bins" not in check
    assert check["observations"] < 150
    empty = depth_against_images([PairMatches(0, 1, np.empty((0, 2)), np.empty((0, 2)), np.empty(0), np.empty(0))],
                                 T, K)
    assert empty["observations"] == 0 and "reason" in empty
    wide, T_wide = _survey(0.0, spread_deg=8.0)
    one_depth = [PairMatches(p.a, p.b, p.uv_a, p.uv_b, np.full(len(p.z_a), 2.0), np.full(len(p.z_b), 2.0))
                 for p in wide]
    assert depth_against_images(one_depth, T_wide, K)["reason"] == "every match at the same depth"


def test_an_offset_the_survey_cannot_measure_carries_its_uncertainty_and_no_verdict():
    """A survey of one small object, its depths within a few centimetres (the D435 desk survey's
    bins at 0.46 and 0.52 m), with a sensor's 1% noise: the fitted offset comes with an
    the bins sort the sensor's noise rather than the depth (an offset of tenths per metre fitted
    from none), so it is not measurable: no verdict from it. The same camera over a room's
    depths measures it."""
    small = depth_against_images(*_survey(0.0, spread_deg=8.0, depth_span_m=0.03, width_m=0.08, noise=0.01), K)
    assert small["bins"][-1][0] - small["bins"][0][0] < 0.15
    assert abs(small["intercept_per_m"]) > DEPTH_OFFSET_BAD_PER_M  # what a fit through sorted noise finds
    assert small["offset_measurable"] is False and not small["bad"] and small["intercept_sigma_per_m"] > 0
    room = depth_against_images(*_survey(0.0, spread_deg=8.0, noise=0.01), K)
    assert room["offset_measurable"] is True and room["intercept_sigma_per_m"] < 0.005 and not room["bad"]
    assert 5 < room["scatter_at_1m_mm"] < 30  # 1% of a metre, and the triangulation's own noise
