"""Every conversion in conventions.py and camera.py round-trips."""

import numpy as np
import pytest

from nap3d_graph.camera import CameraError, Intrinsics, RenderedView, RGBDFrame, backproject, backproject_depth, project
from nap3d_graph.conventions import (
    OPENCV_FROM_OPENGL,
    R_to_quat_xyzw,
    T_opencv_to_opengl,
    T_opengl_to_opencv,
    T_to_pose3,
    T_to_tum,
    compose,
    exp_se3,
    inv_T,
    log_se3,
    make_T,
    pose3_to_T,
    quat_xyzw_to_R,
    ray_length_to_z_depth,
    transform_points,
    tum_to_T,
    z_depth_to_ray_length,
)


def random_T(rng, n=None):
    from scipy.spatial.transform import Rotation

    if n is None:
        return make_T(Rotation.random(random_state=rng.integers(1 << 31)).as_matrix(), rng.normal(size=3))
    return np.stack([random_T(rng) for _ in range(n)])


@pytest.fixture
def rng():
    return np.random.default_rng(0)


def test_inverse_and_compose(rng):
    T_a_b, T_b_c = random_T(rng), random_T(rng)
    np.testing.assert_allclose(compose(T_a_b, inv_T(T_a_b)), np.eye(4), atol=1e-12)
    p_c = rng.normal(size=(5, 3))
    np.testing.assert_allclose(transform_points(compose(T_a_b, T_b_c), p_c),
                               transform_points(T_a_b, transform_points(T_b_c, p_c)), atol=1e-12)
    stacked = random_T(rng, 4)
    np.testing.assert_allclose(inv_T(stacked) @ stacked, np.broadcast_to(np.eye(4), (4, 4, 4)), atol=1e-12)


def test_gtsam_round_trip(rng):
    T = random_T(rng)
    np.testing.assert_allclose(pose3_to_T(T_to_pose3(T)), T, atol=1e-12)
    with pytest.raises(ValueError, match="finite 4x4"):
        T_to_pose3(np.full((4, 4), np.nan))


def test_se3_exp_log_matches_gtsam_order(rng):
    xi = rng.normal(size=6) * 0.3
    T = exp_se3(xi)
    np.testing.assert_allclose(log_se3(T), xi, atol=1e-10)
    # Rotation first: a pure [0,0,0,tx,ty,tz] is a pure translation.
    np.testing.assert_allclose(exp_se3([0, 0, 0, 1, 2, 3])[:3, 3], [1, 2, 3], atol=1e-12)
    np.testing.assert_allclose(exp_se3([0, 0, 0.1, 0, 0, 0])[:3, 3], 0, atol=1e-12)


def test_tum_round_trip(rng):
    T = random_T(rng, 6)
    rows = T_to_tum(T)
    assert rows.shape == (6, 7) and np.all(rows[:, 6] >= 0)
    np.testing.assert_allclose(tum_to_T(rows), T, atol=1e-12)
    # A TUM quaternion is [qx qy qz qw]: 90 deg about z.
    np.testing.assert_allclose(quat_xyzw_to_R([0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)]),
                               [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    R = quat_xyzw_to_R(R_to_quat_xyzw(T[0, :3, :3]))
    np.testing.assert_allclose(R, T[0, :3, :3], atol=1e-12)


def test_opencv_opengl_round_trip(rng):
    T_world_cam_cv = random_T(rng)
    T_gl = T_opencv_to_opengl(T_world_cam_cv)
    np.testing.assert_allclose(T_opengl_to_opencv(T_gl), T_world_cam_cv, atol=1e-12)
    # A point in front of an OpenCV camera (z > 0) is at negative z for OpenGL, same world point.
    p_cv = np.array([0.1, 0.2, 2.0])
    p_gl = transform_points(OPENCV_FROM_OPENGL, p_cv)
    assert p_gl[2] < 0 and p_gl[1] < 0
    np.testing.assert_allclose(transform_points(T_gl, p_gl), transform_points(T_world_cam_cv, p_cv), atol=1e-12)


def test_depth_ray_round_trip(rng):
    K = Intrinsics(500, 510, 160.3, 119.7, 320, 240)
    z = rng.uniform(0.5, 5, size=(240, 320))
    norms = K.ray_norms()
    ray = z_depth_to_ray_length(z, norms)
    np.testing.assert_allclose(ray_length_to_z_depth(ray, norms), z)
    # The ray length is the distance to the back-projected point.
    pts, uv = backproject_depth(z.astype(np.float32), K, stride=7)
    lengths = np.linalg.norm(pts, axis=1)
    np.testing.assert_allclose(lengths, ray[uv[:, 1].astype(int), uv[:, 0].astype(int)], rtol=1e-6)


def test_backproject_project_round_trip(rng):
    K = Intrinsics(525, 525, 319.5, 239.5, 640, 480)
    uv = rng.uniform(0, [640, 480], size=(100, 2))
    z = rng.uniform(0.3, 8, size=100)
    uv2, z2 = project(backproject(uv, z, K), K)
    np.testing.assert_allclose(uv2, uv, atol=1e-9)
    np.testing.assert_allclose(z2, z, atol=1e-12)
    uv_behind, _ = project(np.array([[0, 0, -1.0]]), K)
    assert np.all(np.isnan(uv_behind))


def test_intrinsics_scaling_and_shift():
    K = Intrinsics(525, 525, 319.5, 239.5, 640, 480)
    half = K.scaled(320, 240)
    assert (half.fx, half.cx, half.cy) == (262.5, 159.5, 119.5)
    # Scaling back returns the original camera; the image centre stays the image centre.
    back = half.scaled(640, 480)
    np.testing.assert_allclose([back.fx, back.fy, back.cx, back.cy], [525, 525, 319.5, 239.5])
    harsh = K.shifted(1.10, 10.0)
    np.testing.assert_allclose([harsh.fx, harsh.fy, harsh.cx, harsh.cy], [577.5, 577.5, 329.5, 249.5])
    assert Intrinsics.from_dict(K.to_dict()) == K
    with pytest.raises(CameraError, match="focal"):
        Intrinsics(-1, 525, 319.5, 239.5, 640, 480)
    with pytest.raises(CameraError, match="lack the key"):
        Intrinsics.from_dict({"fx": 1})


def test_value_objects_validate():
    K = Intrinsics(100, 100, 15.5, 11.5, 32, 24)
    rgb = np.zeros((24, 32, 3), np.uint8)
    depth = np.ones((24, 32), np.float32)
    frame = RGBDFrame(rgb, depth, K, 1.0)
    assert frame.depth_m.dtype == np.float32
    with pytest.raises(CameraError, match="uint8"):
        RGBDFrame(rgb.astype(float), depth, K)
    with pytest.raises(CameraError, match="float metres"):
        RGBDFrame(rgb, (depth * 5000).astype(np.uint16), K)
    with pytest.raises(CameraError, match=r"shape \(24, 31\)"):
        RGBDFrame(rgb, depth[:, :31], K)
    with pytest.raises(CameraError, match="HxWx3"):
        RGBDFrame(rgb[..., 0], depth, K)
    view = RenderedView(rgb, depth, np.full((24, 32), 0.5, np.float32), K)
    assert view.opacity.max() == 0.5
    with pytest.raises(CameraError, match=r"opacity must lie in \[0, 1\]"):
        RenderedView(rgb, depth, np.full((24, 32), 2.0, np.float32), K)
