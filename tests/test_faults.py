"""Runs that accept no wrong correction: injected faults on a simulated walk.

Every run is compared with the clean run of the same walk: wrong corrections (20% of the
keyframes, 5-50 cm and 2-20 deg off), wrong depth scales on some frames, and a depth sensor
whose every frame is 3.5% off (which the run must calibrate)."""

import dataclasses

import numpy as np
import pytest

from nap3d_graph.conventions import exp_se3, pose_error
from nap3d_graph.datasets import SimSequence
from nap3d_graph.motion.odometry import make_odometry
from nap3d_graph.results import Correction
from nap3d_graph.run.config import PipelineConfig
from nap3d_graph.run.pipeline import Pipeline
from nap3d_graph.sims.faults import ScaledDepth
from nap3d_graph.sims.sensors import OdometryNoise

CONFIG = PipelineConfig(keyframe_every=3, render_width=None, render_height=None, odom_drift_m_per_s=0.03,
                        odom_drift_rad_per_s=0.02)


def ate(result) -> float:
    return float(np.sqrt(np.mean([pose_error(a, b)[0] ** 2 for a, b in
                                  zip(result.T_world_cam_estimate, result.T_world_cam_gt)])))


@pytest.fixture(scope="module")
def walk(sim_walk):
    drift = OdometryNoise(bias_init=(0.0, 0.0, 0.01, 0.025, 0.0, 0.01), heading_bias_rad_s=0.015)
    return SimSequence(sim_walk(60, seed=8, width=192, height=144, odometry=drift))


@pytest.fixture(scope="module")
def clean(walk):
    return Pipeline(walk, walk.oracle_field(), make_odometry("recorded", walk), CONFIG).run()


@pytest.mark.slow
def test_wrong_corrections_do_not_move_the_trajectory(walk, clean):
    rng = np.random.default_rng(21)
    keyframes = clean.keyframe_indices[1:]
    wrong = set(rng.choice(keyframes, size=int(round(0.2 * len(keyframes))), replace=False).tolist())

    def inject(i, c: Correction):
        if i not in wrong or not c.success:
            return c
        direction = rng.normal(size=3)
        axis = rng.normal(size=3)
        offset = np.r_[axis / np.linalg.norm(axis) * np.radians(rng.uniform(2, 20)),
                       direction / np.linalg.norm(direction) * rng.uniform(0.05, 0.5)]
        return dataclasses.replace(c, T_world_cam_corrected=c.T_world_cam_corrected @ exp_se3(offset))

    faulty = Pipeline(walk, walk.oracle_field(), make_odometry("recorded", walk), CONFIG, correction_hook=inject).run()
    accepted_wrong = [k.frame_index for k in faulty.keyframes if k.frame_index in wrong and k.accepted]
    # Every wrong one is either gated out or weighed out by the final solve.
    assert set(accepted_wrong) <= set(faulty.gnc_outliers), (accepted_wrong, faulty.gnc_outliers)
    assert ate(faulty) <= 1.1 * ate(clean), (ate(faulty), ate(clean))


def test_some_frames_with_a_wrong_depth_scale_are_refused(walk, clean):
    rng = np.random.default_rng(22)
    keyframes = clean.keyframe_indices[2:]
    bad = rng.choice(keyframes, size=int(round(0.2 * len(keyframes))), replace=False)
    factors = {int(i): float(rng.uniform(1.03, 1.05)) for i in bad}
    faulty = Pipeline(ScaledDepth(walk, factors), walk.oracle_field(), make_odometry("recorded", walk), CONFIG).run()
    refused = {k.frame_index for k in faulty.keyframes if not k.accepted and "depth scale" in k.reason}
    assert refused == set(factors), (refused, sorted(factors))
    assert ate(faulty) <= 1.1 * ate(clean), (ate(faulty), ate(clean))


def test_a_sensor_whose_every_depth_is_off_is_calibrated(walk, clean):
    factors = {i: 1.035 for i in range(len(walk))}
    run = Pipeline(ScaledDepth(walk, factors), walk.oracle_field(), make_odometry("recorded", walk), CONFIG).run()
    # The run measures the sensor: its depth must be multiplied by 1/1.035.
    assert run.depth_scale == pytest.approx(1 / 1.035, rel=0.005)
    assert run.num_accepted >= 0.9 * clean.num_accepted
    assert ate(run) <= 1.5 * ate(clean), (ate(run), ate(clean))


def test_a_non_rigid_estimate_is_refused(walk):
    from nap3d_graph import correct_pose

    T = np.array(walk.T_world_cam_gt[5])
    T[:3, :3] *= 2.0
    c = correct_pose(walk[5], walk.oracle_field(), T)
    assert not c.success and "not a rigid transform" in c.reason


@pytest.mark.slow
def test_a_wrong_correction_that_passes_the_gate_is_weighed_out(walk, clean):
    """After a stretch without corrections (the field covered none of it) the prediction is
    uncertain enough for the gate to let a 16 cm wrong correction in, and then to refuse the
    good ones that follow (they disagree with the now wrong prediction). The final solve's
    graduated non-convexity, over every correction the gate saw, weighs the wrong one out and
    takes the good ones back. (At 8 cm after this 3 s blind stretch neither can tell: the
    odometry's own uncertainty over it is about that size.)"""
    keyframes = clean.keyframe_indices
    blind, target = set(keyframes[4:10]), keyframes[10]

    def inject(i, c: Correction):
        if i in blind:
            return dataclasses.replace(c, success=False, reason="the field does not cover this view (test)")
        if i == target and c.success:
            return dataclasses.replace(c, T_world_cam_corrected=c.T_world_cam_corrected @ exp_se3([0, 0, 0, 0.16, 0, 0]))
        return c

    def skip(i, c: Correction):
        if i in blind or i == target:
            return dataclasses.replace(c, success=False, reason="skipped (test)")
        return c

    honest = Pipeline(walk, walk.oracle_field(), make_odometry("recorded", walk), CONFIG, correction_hook=skip).run()
    faulty = Pipeline(walk, walk.oracle_field(), make_odometry("recorded", walk), CONFIG, correction_hook=inject).run()
    record = next(k for k in faulty.keyframes if k.frame_index == target)
    assert record.accepted, record.reason  # the gate could not tell
    refused_after = [k.frame_index for k in faulty.keyframes if k.frame_index > target and not k.accepted]
    assert refused_after, "the good corrections after the wrong one were expected to be refused online"
    assert faulty.gnc_outliers == [target] and set(refused_after) <= set(faulty.gnc_recovered)
    without_gnc = Pipeline(walk, walk.oracle_field(), make_odometry("recorded", walk),
                           dataclasses.replace(CONFIG, final_gnc=False), correction_hook=inject).run()
    assert ate(without_gnc) > 1.2 * ate(honest), (ate(without_gnc), ate(honest))
    assert ate(faulty) <= 1.1 * ate(honest), (ate(faulty), ate(honest), ate(without_gnc))


def test_a_frame_whose_metre_is_off_is_aligned_in_one_pass(walk):
    """A keyframe whose depth is 3.5% long is fitted to its rescaled points in the alignment's
    own pass: the same correction as aligning the frame with its depth divided by the scale
    from scratch (what runs did before, repeating the render and the matching), once."""
    from nap3d_graph import correct_pose
    from nap3d_graph.nap3d.keyframe import KeyframeJob, measure_keyframe

    i = 12
    frame = ScaledDepth(walk, {i: 1.035})[i]
    T_render = walk.T_world_cam_gt[i] @ exp_se3(np.r_[0.01, -0.005, 0.008, 0.02, -0.01, 0.015])
    config = dataclasses.replace(CONFIG, field_sigma_m=0.0, field_sigma_rad=0.0)
    job = KeyframeJob(i, frame, T_render, None, None, 1.0, frame.intrinsics)
    once = measure_keyframe(job, walk.oracle_field(), config)
    assert once.success and once.alignment.diagnostics["depth_scale"] == pytest.approx(1.035, rel=0.003)
    assert once.timings_s.get("render", 0) > 0 and "rescale_retry" not in once.timings_s
    scale = once.alignment.diagnostics["depth_scale"]
    again = correct_pose(frame.with_depth(frame.depth_m / np.float32(scale)), walk.oracle_field(), T_render,
                         iterations=config.correction_iterations, config=config.align)
    dt, dr = pose_error(once.T_world_cam_corrected, again.T_world_cam_corrected)
    assert dt < 1e-3 and np.degrees(dr) < 0.05, (dt, np.degrees(dr))
    truth_t, _ = pose_error(once.T_world_cam_corrected, walk.T_world_cam_gt[i])
    assert truth_t < 0.01


def _correct_in_child(args):
    from nap3d_graph import correct_pose

    frame, field, T = args
    return correct_pose(frame, field, T).T_world_cam_corrected


def test_correct_pose_detects_beside_the_render_and_survives_a_fork(walk):
    """The real frame's features are detected on a helper thread while the render is made:
    the same correction as ever, and a forked process (a multiprocessing pool's default on
    Linux) gets its own helper instead of waiting on the parent's."""
    import multiprocessing

    from nap3d_graph import correct_pose

    i = 20
    T = walk.T_world_cam_gt[i] @ exp_se3(np.r_[0.01, 0.0, -0.01, 0.02, 0.01, -0.01])
    first = correct_pose(walk[i], walk.oracle_field(), T)
    again = correct_pose(walk[i], walk.oracle_field(), T)
    assert first.success and first.timings_s["detect"] > 0 and first.timings_s["render"] > 0
    np.testing.assert_array_equal(first.T_world_cam_corrected, again.T_world_cam_corrected)
    with multiprocessing.get_context("fork").Pool(1) as pool:
        child = pool.map_async(_correct_in_child, [(walk[i], walk.oracle_field(), T)]).get(timeout=120)[0]
    np.testing.assert_allclose(child, first.T_world_cam_corrected, atol=1e-9)
