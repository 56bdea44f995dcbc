"""A step measured by depth alone when the colour has nothing to match: what a wall's depth
says (its distance and tilt) is measured, what it cannot say stays the guess, and a walk that
slows to a stop facing a blank wall is not carried on through it."""

import numpy as np
import pytest

from nap3d_graph.camera import Intrinsics
from nap3d_graph.conventions import exp_se3, inv_T, log_se3
from nap3d_graph.motion.depth_step import depth_step
from nap3d_graph.motion.odometry import VisualOdometry
from nap3d_graph.sims.building import make_building
from nap3d_graph.sims.sensors import sensor_frame
from nap3d_graph.sims.sequence import default_intrinsics
from nap3d_graph.sims.trajectories import R_world_cam_from_angles

K = Intrinsics(fx=260.0, fy=260.0, cx=160.0, cy=120.0, width=320, height=240)


def _wall_depth(T_wall_cam: np.ndarray, distance_m: float = 1.2) -> np.ndarray:
    """Exact z-depth (H, W) of the plane z = ``distance_m`` of a frame seen from ``T_wall_cam``."""
    v, u = np.mgrid[0 : K.height, 0 : K.width]
    rays = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones(u.shape)], axis=-1) @ T_wall_cam[:3, :3].T
    return ((distance_m - T_wall_cam[2, 3]) / rays[..., 2]).astype(np.float32)


def test_a_wall_gives_its_distance_and_tilt_and_the_guess_keeps_the_rest():
    """Facing a plane, the step along its normal and the tilts about the two axes in it are
    measured; the slide along it and the turn about its normal are the guess's, and the
    covariance says so."""
    true = exp_se3(np.array([0.01, -0.02, 0.0, 0.01, 0.0, 0.05]))  # tilts, a slide, 5 cm on
    guess = exp_se3(np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.15]))  # the walk as it was: 15 cm a step
    step = depth_step(_wall_depth(np.eye(4)), K, _wall_depth(true), K, guess)
    assert step is not None and step.residual_m < 1e-4
    xi, xi_true = log_se3(step.T_prev_cur), log_se3(true)
    np.testing.assert_allclose(xi[[0, 1, 5]], xi_true[[0, 1, 5]], atol=5e-4)  # tilts and distance
    np.testing.assert_allclose(xi[[2, 3, 4]], 0.0, atol=2e-3)  # turn about the normal, slide: the guess's
    sigma = np.sqrt(np.diag(step.covariance))
    assert sigma[5] < 0.005 and sigma[0] < np.radians(0.5) and sigma[1] < np.radians(0.5)
    # The slide: the heading held within 10 deg of the 5 cm found (9 mm); the turn: the guess's 3 deg.
    assert min(sigma[3], sigma[4]) > 0.005 > 3 * sigma[5] and sigma[2] > np.radians(2.0)


def test_depths_that_do_not_agree_give_no_step():
    """A wall that jumped 30 cm between frames (another surface) is no step of the camera."""
    guess = exp_se3(np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.05]))
    wall = _wall_depth(np.eye(4))
    rough = wall + np.random.default_rng(0).choice([0.0, 0.3], size=wall.shape).astype(np.float32)
    assert depth_step(wall, K, rough, K, guess) is None
    assert depth_step(wall, K, np.zeros_like(wall), K, guess) is None  # no depth at all


def _walk_to_the_end_wall(sweep_deg: float = 0.0):
    """A walk along the simulated floor's middle that slows to a stop 1.2 m from its last room's
    end wall (painted, no panel near the doorway it does not have), with sensor noise: its colour
    runs out of features half-way. The camera turns its head ``sweep_deg`` left and right about
    the walk's heading (one sweep over the walk)."""
    floor = make_building(1, seed=1)
    K_sim = default_intrinsics(160, 120)
    s = np.linspace(0.0, 1.0, 40)
    xs = floor.walls_x[-1] - 3.0 + 1.8 * (3 * s**2 - 2 * s**3)  # eased: starts and stops at rest
    yaws = np.radians(sweep_deg) * np.sin(2 * np.pi * s)
    rng = np.random.default_rng(0)
    poses, frames = [], []
    for x, yaw in zip(xs, yaws):
        T = np.eye(4)
        T[:3, :3] = R_world_cam_from_angles(yaw, np.radians(10.0), 0.0)  # 10 deg down
        T[:3, 3] = [x, floor.door_y_m, 1.35]
        poses.append(T)
        frames.append(sensor_frame(floor, T, K_sim, rng))
    return poses, frames


@pytest.fixture(scope="module")
def blank_wall_walk():
    return _walk_to_the_end_wall()


def _walk_end_error(poses, frames, depth_fallback: bool) -> tuple[np.ndarray, int]:
    odometry = VisualOdometry(initial_pose=poses[0], width=160, depth_fallback=depth_fallback)
    odometry.prime(frames[0])
    T, lost = poses[0].copy(), 0
    for i in range(1, len(frames)):
        step = odometry.increment(i, frames[i])
        T, lost = T @ step.T_prev_cur, lost + (not step.ok)
    return T[:3, 3] - poses[-1][:3, 3], lost


def test_a_walk_that_stops_at_a_blank_wall_is_not_carried_through_it(blank_wall_walk):
    """Constant velocity carries the camera on at walking pace after the features run out (36 cm
    past where it stopped, 52 cm off in all); stepped by depth, it stops where it stopped."""
    poses, frames = blank_wall_walk
    guessed, lost = _walk_end_error(poses, frames, depth_fallback=False)
    stepped, lost_too = _walk_end_error(poses, frames, depth_fallback=True)
    assert lost == lost_too >= 15  # the same steps without features, both ways
    assert guessed[0] > 0.3  # through the wall
    # Forward, the wall's distance holds it (36 against 2.3 cm); across, the heading the last
    # few steps with features had (2.6 cm off to the side at this resolution, against 27).
    assert abs(stepped[0]) < 0.05 and np.linalg.norm(stepped) < 0.5 * np.linalg.norm(guessed)
    # Its steps say they are doubtful where the wall cannot see (along it), in proportion to the
    # step (at walking pace, the first without features; at rest, the last).
    odometry = VisualOdometry(initial_pose=poses[0], width=160)
    odometry.prime(frames[0])
    steps = [odometry.increment(i, frames[i]) for i in range(1, len(frames))]
    first, last = next(s for s in steps if not s.ok), steps[-1]
    assert "depth alone" in first.reason and "depth alone" in last.reason
    assert np.sqrt(first.covariance[3, 3]) > 3 * np.sqrt(first.covariance[5, 5])
    assert np.linalg.norm((inv_T(poses[-2]) @ poses[-1])[:3, 3] - last.T_prev_cur[:3, 3]) < 0.01


def test_a_step_far_from_the_guess_is_not_taken(monkeypatch):
    """At a fast swing the guess is far off and the depths can settle anywhere: a step its guess's
    covariance cannot reach (here 5 deg and 30 cm from it) falls back to the guess."""
    import nap3d_graph.motion.depth_step as module

    true = exp_se3(np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.05]))
    guess = exp_se3(np.array([0.0, np.radians(5.0), 0.0, 0.0, 0.0, 0.35]))
    wall, moved = _wall_depth(np.eye(4), 3.0), _wall_depth(true, 3.0)
    assert depth_step(wall, K, moved, K, guess) is None
    monkeypatch.setattr(module, "MAX_GUESS_D2", np.inf)
    assert depth_step(wall, K, moved, K, guess) is not None


def test_a_walker_keeps_its_heading_while_the_camera_turns_its_head():
    """The walk with the head sweeping 15 deg either way while the walker walks straight on (and
    the straight walk): the steps without features keep the heading the last measured steps had
    in the odometry's frame, weighted by their covariance, not in the camera's as an equal mean
    (the two last steps before the features run out rest on a few inliers and are 7 and 3 cm
    off). What the walk gained while blind: 12.5 and 8.9 cm before, 2.6 and 2.7 cm now."""
    for sweep_deg in (15.0, 0.0):
        poses, frames = _walk_to_the_end_wall(sweep_deg)
        odometry = VisualOdometry(initial_pose=poses[0], width=160)
        odometry.prime(frames[0])
        T, error_m, ok = poses[0].copy(), [], []
        for i in range(1, len(frames)):
            step = odometry.increment(i, frames[i])
            T = T @ step.T_prev_cur
            error_m.append(T[:3, 3] - poses[i][:3, 3])
            ok.append(step.ok)
        first_blind = ok.index(False)
        assert ok[first_blind:].count(False) >= 10
        assert np.linalg.norm(error_m[-1] - error_m[first_blind - 1]) < 0.04


def test_a_step_on_few_inliers_as_the_colour_runs_out_is_fused_with_the_depth(monkeypatch):
    """The last steps before the features run out rest on a handful of inliers and are 7 cm off
    (their covariance says so, but nothing later corrects them): their translations fused with
    the depth's own step's, each by its information, none is 2 cm off, and the walk ends within
    5 cm of where it stopped (4.2 / 1.4 cm; 4.9 / 10.3 cm unfused)."""
    fused_steps = {}
    for fuse in (True, False):
        if not fuse:
            monkeypatch.setattr(VisualOdometry, "_with_depth", lambda self, prev, frame, T, cov, timings: (T, cov))
        for sweep_deg in (0.0, 15.0):
            poses, frames = _walk_to_the_end_wall(sweep_deg)
            odometry = VisualOdometry(initial_pose=poses[0], width=160)
            odometry.prime(frames[0])
            T, errors = poses[0].copy(), []
            for i in range(1, len(frames)):
                step = odometry.increment(i, frames[i])
                T = T @ step.T_prev_cur
                assert np.linalg.eigvalsh(step.covariance).min() > 0  # a covariance GTSAM takes
                if step.ok:  # measured by the features
                    errors.append(np.linalg.norm((inv_T(poses[i - 1]) @ poses[i])[:3, 3] - step.T_prev_cur[:3, 3]))
            fused_steps[fuse, sweep_deg] = (max(errors), np.linalg.norm(T[:3, 3] - poses[-1][:3, 3]))
    for sweep_deg in (0.0, 15.0):
        assert fused_steps[False, sweep_deg][0] > 0.05 and fused_steps[True, sweep_deg][0] < 0.02
        assert fused_steps[True, sweep_deg][1] < 0.05
