"""The simulator: exact geometry, deterministic output, sensor statistics, IMU, TUM layout."""


import gtsam
import numpy as np
import pytest

from nap3d_graph.conventions import inv_T, log_se3, pose_error
from nap3d_graph.sims.scene import Cylinder, OracleField, Scene, Sphere, make_scene
from nap3d_graph.sims.sensors import (
    DepthNoise,
    ImuNoise,
    OdometryNoise,
    add_depth_noise,
    drifting_odometry,
    simulate_imu,
)
from nap3d_graph.sims.sequence import default_intrinsics
from nap3d_graph.sims.trajectories import make_trajectory


@pytest.fixture(scope="module")
def scene():
    return make_scene(3)


def test_scene_is_deterministic_and_round_trips(scene, tmp_path):
    assert make_scene(3).to_dict() == scene.to_dict()
    assert make_scene(4).to_dict() != scene.to_dict()
    assert any(isinstance(o, (Cylinder, Sphere)) for o in scene.objects), "needs a curved primitive"
    scene.save(tmp_path / "scene.json")
    again = Scene.load(tmp_path / "scene.json")
    T = make_trajectory("traverse", scene, np.random.default_rng(0), 10.0).T_world_cam(3.0)
    K = default_intrinsics(160, 120)
    a, b = OracleField(scene).render(T, K), OracleField(again).render(T, K)
    np.testing.assert_array_equal(a.rgb, b.rgb)
    np.testing.assert_array_equal(a.depth_m, b.depth_m)
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(ValueError, match="bad.json"):
        Scene.load(tmp_path / "bad.json")


def test_oracle_depth_is_exact_z_depth(scene):
    """Back-projected oracle depth lands exactly on the primitives' surfaces."""
    from nap3d_graph.camera import backproject_depth
    from nap3d_graph.conventions import transform_points

    traj = make_trajectory("mapping", scene, np.random.default_rng(1), 30.0)
    K = default_intrinsics(160, 120)
    for t in (0.0, 7.0, 15.0):
        T = traj.T_world_cam(t)
        view = OracleField(scene).render(T, K)
        assert view.opacity.min() == 1.0  # closed room: every ray hits something
        pts_cam, uv = backproject_depth(view.depth_m, K, stride=3)
        pts_world = transform_points(T, pts_cam)
        # Re-cast the same rays: the hit point must be the back-projected one (float32 depth).
        dirs = pts_world - T[:3, 3]
        t_hit, hit_pts, _, _ = scene.cast(T[:3, 3], dirs)
        np.testing.assert_allclose(t_hit, 1.0, atol=1e-5)


def test_sift_finds_features(scene):
    import cv2

    traj = make_trajectory("traverse", scene, np.random.default_rng(2), 10.0)
    view = OracleField(scene).render(traj.T_world_cam(5.0), default_intrinsics(320, 240))
    keypoints = cv2.SIFT_create().detect(cv2.cvtColor(view.rgb, cv2.COLOR_RGB2GRAY))
    assert len(keypoints) > 150


def test_traverse_never_revisits_and_stays_in_free_space(scene):
    traj = make_trajectory("traverse", scene, np.random.default_rng(5), 12.0)
    stamps = np.linspace(0, 12.0, 200)
    positions = traj.poses(stamps)[:, :3, 3]
    assert all(scene.inside_free_space(p) for p in positions)
    # Never revisits: progress along the start->end axis only ever increases.
    axis = positions[-1, :2] - positions[0, :2]
    progress = positions[:, :2] @ axis / np.linalg.norm(axis)
    assert np.all(np.diff(progress) >= -1e-9)
    assert progress[-1] - progress[0] > 2.0


def test_depth_noise_grows_with_z_squared():
    rng = np.random.default_rng(0)
    model = DepthNoise(hole_fraction=0.0)
    for z in (1.0, 2.0, 4.0):
        noisy = add_depth_noise(np.full((200, 200), z, np.float32), model, rng)
        assert np.std(noisy - z) == pytest.approx(model.sigma_z2_per_m * z**2, rel=0.05)
    beyond = add_depth_noise(np.full((10, 10), 7.0, np.float32), model, rng)
    assert np.all(beyond == 0)
    holes = add_depth_noise(np.full((240, 320), 2.0, np.float32), DepthNoise(hole_fraction=0.02), rng)
    assert 0.005 < np.mean(holes == 0) < 0.05


def test_odometry_drift_statistics_match_config(scene):
    """Increment errors have the configured white sigma; the bias makes drift grow."""
    traj = make_trajectory("traverse", scene, np.random.default_rng(0), 60.0)
    stamps = np.arange(0, 60.0, 1 / 15)
    T_world_cam_gt = traj.poses(stamps)
    white = OdometryNoise(rot_sigma_rad=3e-3, trans_sigma_m=5e-3, bias_init=(0,) * 6, bias_walk=0.0,
                          heading_bias_rad_s=0.0)
    T_odom, xi = drifting_odometry(T_world_cam_gt, stamps, white, np.random.default_rng(1))
    # Recover the errors from the poses alone: inc_gt^-1 inc_odom = Exp(xi).
    measured = np.array([log_se3(inv_T(inv_T(T_world_cam_gt[k]) @ T_world_cam_gt[k + 1]) @ inv_T(T_odom[k]) @ T_odom[k + 1])
                         for k in range(len(stamps) - 1)])
    np.testing.assert_allclose(measured, xi, atol=1e-8)
    np.testing.assert_allclose(measured.std(axis=0), white.sigmas, rtol=0.08)
    assert np.all(np.abs(measured.mean(axis=0)) < 4 * white.sigmas / np.sqrt(len(measured)))
    # A constant camera-frame bias about the optical axis (a roll) shows up as the mean
    # rotation error per second about camera z.
    rolled = OdometryNoise(rot_sigma_rad=1e-3, trans_sigma_m=1e-3, bias_init=(0, 0, 0.01, 0, 0, 0), bias_walk=0.0,
                           heading_bias_rad_s=0.0)
    _, xi_b = drifting_odometry(T_world_cam_gt, stamps, rolled, np.random.default_rng(2))
    assert xi_b[:, 2].mean() * 15 == pytest.approx(0.01, rel=0.1)
    # A heading bias turns the odometry about gravity: after 60 s its heading (the forward
    # axis projected on the floor) is off by bias x time, while the camera's tilt is not.
    heading = OdometryNoise(rot_sigma_rad=0.0, trans_sigma_m=0.0, bias_init=(0,) * 6, bias_walk=0.0,
                            heading_bias_rad_s=0.004)
    T_h, _ = drifting_odometry(T_world_cam_gt, stamps, heading, np.random.default_rng(2))

    def floor_heading(T):
        forward = T[:3, :3] @ np.array([0.0, 0.0, 1.0])
        return np.arctan2(forward[1], forward[0])

    turned = np.angle(np.exp(1j * (floor_heading(T_h[-1]) - floor_heading(T_world_cam_gt[-1]))))
    assert turned == pytest.approx(0.004 * stamps[-1], rel=0.02)
    tilt = lambda T: np.arcsin(np.clip((T[:3, :3] @ [0.0, 0.0, 1.0])[2], -1, 1))  # noqa: E731
    assert abs(tilt(T_h[-1]) - tilt(T_world_cam_gt[-1])) < 1e-6
    # ... and it bends the path: at the same rate, a roll about the optical axis barely moves
    # the camera's position (measured: 0.75 cm RMS over the minute against 23 cm).
    roll_only = OdometryNoise(rot_sigma_rad=0.0, trans_sigma_m=0.0, bias_init=(0, 0, 0.004, 0, 0, 0), bias_walk=0.0,
                              heading_bias_rad_s=0.0)
    T_r, _ = drifting_odometry(T_world_cam_gt, stamps, roll_only, np.random.default_rng(2))

    def rms(T):
        return np.sqrt(np.mean([pose_error(a, b)[0] ** 2 for a, b in zip(T, T_world_cam_gt)]))

    assert rms(T_h) > 10 * rms(T_r) and rms(T_h) > 0.1
    # Drift grows: the end-point error is far above the start.
    T_d, _ = drifting_odometry(T_world_cam_gt, stamps, OdometryNoise(), np.random.default_rng(3))
    early = pose_error(T_d[30], T_world_cam_gt[30])[0]
    late = pose_error(T_d[-1], T_world_cam_gt[-1])[0]
    assert late > 5 * early and late > 0.05


def test_noise_free_imu_preintegrates_to_ground_truth(scene):
    """GTSAM's preintegration of the exact IMU reproduces the motion over 1 s."""
    traj = make_trajectory("traverse", scene, np.random.default_rng(4), 10.0)
    t0, t1 = 3.0, 4.0
    imu = simulate_imu(traj, t0, t1, None, np.random.default_rng(0))
    params = gtsam.PreintegrationParams.MakeSharedU(9.81)
    params.setAccelerometerCovariance(np.eye(3) * 1e-6)
    params.setGyroscopeCovariance(np.eye(3) * 1e-8)
    params.setIntegrationCovariance(np.eye(3) * 1e-8)
    pim = gtsam.PreintegratedImuMeasurements(params, gtsam.imuBias.ConstantBias())
    dt = imu["stamps"][1] - imu["stamps"][0]
    for a, w in zip(imu["accel"], imu["gyro"]):
        pim.integrateMeasurement(a, w, dt)
    T0 = traj.T_world_cam(t0)
    state0 = gtsam.NavState(gtsam.Rot3(T0[:3, :3]), T0[:3, 3], traj.velocity_world(t0))
    predicted = pim.predict(state0, gtsam.imuBias.ConstantBias())
    T_pred = predicted.pose().matrix()
    t_err, r_err = pose_error(T_pred, traj.T_world_cam(imu["stamps"][-1] + dt))
    assert t_err < 0.01 and r_err < 0.1
    assert np.linalg.norm(predicted.velocity() - traj.velocity_world(imu["stamps"][-1] + dt)) < 0.01


def test_noisy_imu_statistics(scene):
    traj = make_trajectory("traverse", scene, np.random.default_rng(4), 10.0)
    noise = ImuNoise(accel_bias_walk=0.0, gyro_bias_walk=0.0)
    clean = simulate_imu(traj, 0.0, 10.0, None, np.random.default_rng(0))
    noisy = simulate_imu(traj, 0.0, 10.0, noise, np.random.default_rng(0))
    resid = noisy["gyro"] - clean["gyro"] - noisy["gyro_bias"]
    np.testing.assert_allclose(resid.std(axis=0), noise.gyro_noise_density * np.sqrt(noise.rate_hz), rtol=0.1)
    resid_a = noisy["accel"] - clean["accel"] - noisy["accel_bias"]
    np.testing.assert_allclose(resid_a.std(axis=0), noise.accel_noise_density * np.sqrt(noise.rate_hz), rtol=0.1)
    # At rest the accelerometer would read +g up; moving slowly it stays near |g|.
    assert np.median(np.linalg.norm(clean["accel"], axis=1)) == pytest.approx(9.81, abs=0.3)
