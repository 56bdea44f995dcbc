"""``warp_depth``'s splat: the compiled kernel gives the numpy path's bytes, and both put a
known surface where the destination camera sees it."""

import numpy as np
import pytest

from nap3d_graph import camera
from nap3d_graph.camera import Intrinsics, warp_depth
from nap3d_graph.conventions import exp_se3
from nap3d_graph.datasets.tum import TumSequence


def _numpy_warp(*args, **kwargs) -> np.ndarray:
    compiled = camera._compiled_splat
    camera._compiled_splat = lambda: None
    try:
        return warp_depth(*args, **kwargs)
    finally:
        camera._compiled_splat = compiled


def test_the_compiled_splat_gives_the_numpy_splats_bytes_on_real_depth(tum_path):
    pytest.importorskip("numba", reason="optional extra not installed: numba")
    assert camera._compiled_splat() is not None
    seq = TumSequence(tum_path)
    rng = np.random.default_rng(3)
    half = seq.intrinsics.scaled(320, 240)
    for i in range(0, len(seq), 3):
        depth = seq[i].depth_m.copy()
        depth[5:40, 100:180] = np.nan  # holes as NaN as well as 0
        # Capture-timing motions (millimetres) and registration-sized ones (centimetres, degrees).
        for sigma in (0.002, 0.05):
            T = exp_se3(rng.normal(0.0, sigma, 6))
            for kwargs in ({}, {"scale": 1.013}, {"dst_intrinsics": half}):
                compiled = warp_depth(depth, seq.intrinsics, T, **kwargs)
                reference = _numpy_warp(depth, seq.intrinsics, T, **kwargs)
                assert compiled.dtype == np.float32 and compiled.shape == reference.shape
                assert np.array_equal(compiled.view(np.uint32), reference.view(np.uint32)), (i, sigma, kwargs)


@pytest.mark.parametrize("use_numpy", [False, True])
def test_a_plane_moved_towards_the_camera_lands_nearer_by_the_motion(use_numpy):
    K = Intrinsics(200.0, 200.0, 79.5, 59.5, 160, 120)
    depth = np.full((120, 160), 2.0, np.float32)
    depth[60:, :] = 3.0  # a step: rows 0-59 a plane at 2 m, rows 60- one at 3 m
    T = np.eye(4)
    T[2, 3] = -0.25  # the destination camera 25 cm in front of the source
    warp = _numpy_warp if use_numpy else warp_depth
    out = warp(depth, K, T)
    hit = out > 0
    assert 0.6 < hit.mean() < 0.95  # moving closer magnifies the image: some pixels get nothing
    assert set(np.unique(out[hit])) == {np.float32(1.75), np.float32(2.75)}
    # Each plane's edge row lands where the pinhole model puts it: v' = cy + (v - cy) z / z'.
    near_rows = np.flatnonzero((out == np.float32(1.75)).any(axis=1))
    far_rows = np.flatnonzero((out == np.float32(2.75)).any(axis=1))
    assert near_rows.max() == np.rint(59.5 + (59 - 59.5) * 2.0 / 1.75)
    assert far_rows.min() == np.rint(59.5 + (60 - 59.5) * 3.0 / 2.75)
