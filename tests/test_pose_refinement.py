"""Training poses refined, against the map they build or against each other's depth: on a
simulated survey whose poses carry injected errors (1 cm and 0.5 deg per axis), each
refinement recovers part of them, holds the gauge to the input, and the field built with them
records what it did."""

import numpy as np
import pytest

from nap3d_graph.conventions import exp_se3, inv_T, log_se3
from nap3d_graph.datasets import SimSequence
from nap3d_graph.fields.build import build_field
from nap3d_graph.fields.depth_refinement import DepthRefinementConfig, refine_poses_by_depth
from nap3d_graph.fields.pose_refinement import PoseCorrectedSequence, PoseRefinementConfig, refine_training_poses
from nap3d_graph.sims.sequence import SimConfig, simulate_sequence


@pytest.fixture(scope="module")
def noisy_survey(tmp_path_factory):
    path = simulate_sequence(tmp_path_factory.mktemp("refine") / "survey",
                             SimConfig(frames=80, path="mapping", width=192, height=144, scene_seed=11, seed=1,
                                       timing=None))
    truth = SimSequence(path)
    rng = np.random.default_rng(0)
    injected = {i: exp_se3(np.r_[rng.normal(0, 0.0087, 3), rng.normal(0, 0.01, 3)]) for i in range(len(truth))}
    return truth, PoseCorrectedSequence(truth, injected)


def _errors(truth, poses) -> tuple[float, float]:
    e = np.array([log_se3(inv_T(truth.T_world_cam_gt[i]) @ T) for i, T in enumerate(poses)])
    return float(np.median(np.linalg.norm(e[:, 3:], axis=1))), float(np.median(np.linalg.norm(e[:, :3], axis=1)))


@pytest.mark.slow
def test_refinement_recovers_part_of_injected_pose_errors(noisy_survey):
    truth, noisy = noisy_survey
    idx = np.arange(len(noisy))
    corrections, report = refine_training_poses(noisy, idx, None, PoseRefinementConfig(rounds=3, render_size=None))
    refined = PoseCorrectedSequence(noisy, corrections).T_world_cam_gt
    t_before, r_before = _errors(truth, noisy.T_world_cam_gt)
    t_after, r_after = _errors(truth, refined)
    # Measured: 15.4 -> 13.9 mm, 0.76 -> 0.53 deg (median over the 80 frames) with the libraries
    # pip resolves now (13.2 mm when this test was written; the commit before issue 42's work
    # gives 13.9 mm here too, so the libraries moved it, not the code).
    assert t_after < 0.93 * t_before and r_after < 0.75 * r_before
    assert len(report["rounds"]) == 3 and all(r["frames_measured"] >= 40 for r in report["rounds"])
    # The gauge stays the input's: no net shift of the trajectory.
    shift = np.mean([refined[i][:3, 3] - noisy.T_world_cam_gt[i][:3, 3] for i in idx], axis=0)
    assert np.linalg.norm(shift) < 1e-3


@pytest.mark.slow
def test_a_field_built_with_refined_poses_records_them(noisy_survey):
    _, noisy = noisy_survey
    field, report = build_field(noisy, "splat", timing=None, refine_poses=1, refine_method="map", measure_error=False,
                                render_size=None, progress=False)
    corrections = field.meta["pose_corrections"]
    assert sorted(int(i) for i in corrections) == sorted(field.meta["train_frames"])
    assert report["pose_refinement"]["rounds"][0]["frames_measured"] >= 25
    moved = [np.linalg.norm(np.asarray(D)[:3, 3]) for D in corrections.values()]
    assert 0.001 < np.median(moved) < 0.02


def test_depth_refinement_recovers_the_rotations_of_injected_pose_errors(noisy_survey):
    """Neighbouring frames' depths aligned with ICP, the poses solved against their (noisy)
    input priors: the frames' relative rotations come from the depth, so most of the injected
    rotation noise goes. Their translations do not improve here: the simulated room is
    mostly flat walls, along which depth alone cannot tell a slide (each pair's covariance
    says so, so the translations stay near their inputs)."""
    truth, noisy = noisy_survey
    idx = np.arange(len(noisy))
    corrections, report = refine_poses_by_depth(noisy, idx, None, DepthRefinementConfig(rounds=2))
    refined = PoseCorrectedSequence(noisy, corrections).T_world_cam_gt
    t_before, r_before = _errors(truth, noisy.T_world_cam_gt)
    t_after, r_after = _errors(truth, refined)
    # Measured: 15.4 -> 16.0 mm, 0.76 -> 0.41 deg (median over the 80 frames).
    assert r_after < 0.6 * r_before and t_after < 1.1 * t_before, (t_before, t_after, r_before, r_after)
    assert report["method"] == "depth" and len(report["rounds"]) == 2
    assert report["rounds"][-1]["pairs_used"] >= 0.5 * report["rounds"][-1]["pairs_tried"]  # measured 198 of 301
    shift = np.mean([refined[i][:3, 3] - noisy.T_world_cam_gt[i][:3, 3] for i in idx], axis=0)
    assert np.linalg.norm(shift) < 1e-3  # the priors hold the gauge


def test_a_field_built_with_depth_refined_poses_agrees_with_itself(noisy_survey):
    _, noisy = noisy_survey
    field, report = build_field(noisy, "views", timing=None, refine_poses=1, measure_error=False, render_size=None,
                                progress=False)
    refinement = report["pose_refinement"]
    assert refinement["method"] == "depth"
    assert sorted(int(i) for i in field.meta["pose_corrections"]) == sorted(field.meta["train_frames"])
    # Measured: the training frames' depths agree to 7.3 mm after, 14.0 before.
    assert refinement["agreement_after_mm"] < 0.6 * refinement["agreement_before_mm"], refinement
