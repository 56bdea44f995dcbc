"""Gravity in a field's frame that is not z-up: given as a vector, it lets the IMU path run
where assuming z-up loses it; estimated from the accelerometer at the start with the starting
pose, it is found within a few degrees, and the run's graph (the field's frame a variable whose
tilt is free) refines it to a tenth of a degree, which keeps every correction where the
estimate held fixed loses the run."""

import numpy as np
import pytest

from nap3d_graph.conventions import pose_error
from nap3d_graph.datasets import SimSequence
from nap3d_graph.motion.imu import ImuConfig, estimate_gravity, gravity_angle_deg
from nap3d_graph.run.config import PipelineConfig
from nap3d_graph.run.imu import ImuOdometry
from nap3d_graph.run.pipeline import Pipeline
from nap3d_graph.sims.reframe import FieldInFrame, SequenceInFrame

# The field's frame: the simulated z-up world turned 90 deg about x (its gravity along +y,
# a y-down room as a camera-based mapping might leave it).
T_F_W = np.array([[1.0, 0, 0, 0.3], [0, 0, -1, 0.1], [0, 1, 0, -0.2], [0, 0, 0, 1]])


@pytest.fixture(scope="module")
def walk(sim_walk):
    return SimSequence(sim_walk(40, fps=10.0))


def test_gravity_is_found_in_the_fields_frame(walk):
    odometry = ImuOdometry.from_sequence(walk)
    g_world, spread = estimate_gravity(odometry.stream, odometry.T_world_cam0)
    # The walk moves from its first frame: its acceleration (and the accelerometer's bias)
    # tilt the estimate by a few degrees (3.6 here), which the graph's bias then takes up.
    assert gravity_angle_deg(g_world, np.array([0.0, 0.0, -1.0])) < 5.0 and abs(np.linalg.norm(g_world) - 9.81) < 1e-9
    turned = ImuOdometry.from_sequence(SequenceInFrame(walk, T_F_W))
    g_field, _ = estimate_gravity(turned.stream, turned.T_world_cam0)
    assert gravity_angle_deg(g_field, T_F_W[:3, :3] @ np.array([0.0, 0.0, -9.81])) < 5.0


def ate(seq, field, config, imu_config):
    """(ATE m, accepted corrections, RunResult) of the IMU path with ``imu_config``."""
    odometry = ImuOdometry.from_sequence(seq, imu_config)
    result = Pipeline(seq, field, odometry, config).run()
    error = np.sqrt(np.mean([pose_error(a, b)[0] ** 2 for a, b in zip(result.T_world_cam_estimate, seq.T_world_cam_gt)]))
    return error, result.num_accepted, result


def test_the_imu_path_runs_in_a_frame_that_is_not_z_up(walk):
    seq, field = SequenceInFrame(walk, T_F_W), FieldInFrame(walk.oracle_field(), T_F_W)
    config = PipelineConfig(keyframe_every=4, render_width=None, render_height=None)

    g_field = T_F_W[:3, :3] @ np.array([0.0, 0.0, -9.81])
    given, accepted, _ = ate(seq, field, config, ImuConfig(gravity_world=tuple(g_field)))  # --gravity 'gx gy gz'
    z_up, accepted_z_up, _ = ate(seq, field, config, ImuConfig())  # z-up, wrong here by 90 deg: the run is lost
    # Measured: 1.8 mm and 10/10 accepted; z-up 48 m and 1/10.
    assert given < 0.01 and accepted >= 9
    assert z_up > 1.0 and accepted_z_up <= 2


def test_the_graph_refines_the_accelerometers_gravity(walk):
    seq, field = SequenceInFrame(walk, T_F_W), FieldInFrame(walk.oracle_field(), T_F_W)
    config = PipelineConfig(keyframe_every=4, render_width=None, render_height=None)
    g_field = T_F_W[:3, :3] @ np.array([0.0, 0.0, -9.81])
    start = ImuOdometry.from_sequence(seq)
    g_accel, _ = estimate_gravity(start.stream, start.T_world_cam0)
    assert 2.0 < gravity_angle_deg(g_accel, g_field) < 5.0  # 3.6 deg: the walk moves from its first frame

    refined, accepted, result = ate(seq, field, config, ImuConfig(gravity_world=tuple(g_accel)))
    # Measured: 1.3 mm, 10/10 accepted, gravity refined to 0.08 deg.
    assert refined < 0.01 and accepted >= 9
    assert gravity_angle_deg(result.gravity_world, g_field) < 0.5
    assert abs(np.linalg.norm(result.gravity_world) - 9.81) < 1e-6
    np.testing.assert_allclose(result.gravity_world_prior, g_accel)
    # The same start held fixed (no tilt allowed): the run loses its corrections (measured 2/10, 1.2 m).
    fixed, accepted_fixed, _ = ate(seq, field, config, ImuConfig(gravity_world=tuple(g_accel), gravity_sigma_deg=1e-3))
    assert fixed > 0.1 and accepted_fixed <= 4


def test_the_run_warns_when_the_accelerometer_disagrees_with_z_up(walk, capsys):
    from argparse import Namespace

    from nap3d_graph.arguments import gravity as _gravity
    from nap3d_graph.cli.sources import _checked_gravity

    turned = ImuOdometry.from_sequence(SequenceInFrame(walk, T_F_W))
    config = _checked_gravity(Namespace(gravity=9.81), turned)
    assert "deg from the one assumed" in capsys.readouterr().err and config.gravity_world is None
    for option in ("auto", "check"):  # check (the default) takes the accelerometer's when z-up is 90 deg off
        config = _checked_gravity(Namespace(gravity=option), turned)
        assert gravity_angle_deg(np.asarray(config.gravity_world), T_F_W[:3, :3] @ [0, 0, -1.0]) < 5.0
        assert "from the accelerometer" in capsys.readouterr().out
    # In the z-up world it was simulated in: no warning, and the default keeps z-up.
    upright = ImuOdometry.from_sequence(walk)
    _checked_gravity(Namespace(gravity=9.81), upright)
    assert "warning" not in capsys.readouterr().err
    assert _checked_gravity(Namespace(gravity="check"), upright).gravity_world is None
    assert _gravity("0 9.81 0") == [0.0, 9.81, 0.0] and _gravity("auto") == "auto" and _gravity("9.8") == 9.8
    assert _gravity("check") == "check"
