"""The undistortion's black corners (no colour data) on the real fr1/xyz frames in tests/data:
found by the reader's camera, never warped into a view field's renders, never a training
target, never scored in a held-out PSNR."""

from __future__ import annotations

from unittest import mock

import numpy as np
import pytest
from conftest import TUM_FR1_XYZ

from nap3d_graph.camera import RenderedView, colour_coverage
from nap3d_graph.datasets import TumSequence
from nap3d_graph.fields import views as view_module
from nap3d_graph.fields.evaluation import evaluate_field, psnr
from nap3d_graph.fields.views import ViewField, ViewFieldConfig, build_view_field


@pytest.fixture(scope="module")
def seq() -> TumSequence:
    return TumSequence(TUM_FR1_XYZ)


def test_coverage_is_where_the_undistorted_image_holds_data(seq):
    covered = colour_coverage(seq)
    assert covered.shape == (480, 640) and covered.dtype == bool and not covered.flags.writeable
    # fr1's strong distortion (k1 0.26) pulls 6% of the undistorted image from outside the raw one.
    assert 0.05 < 1.0 - covered.mean() < 0.07
    assert not covered[:5, :5].any() and covered[240, 320]
    black = np.stack([seq[i].rgb.sum(axis=2) == 0 for i in (0, 6, 11)])
    assert not (black & covered).any()  # no black corner pixel is taken as data
    assert (black & ~covered).sum(axis=(1, 2)).min() > 0.85 * (~covered).sum()
    # At the renders' size: the frames shrunk by area, a pixel covered only when all of it is.
    small = colour_coverage(seq, (320, 240))
    assert small.shape == (240, 320) and 0.05 < 1.0 - small.mean() < 0.075
    # Raw images (no undistortion) and cameras without distortion: every pixel holds data.
    assert colour_coverage(TumSequence(TUM_FR1_XYZ, undistort=False)) is None
    assert colour_coverage(object()) is None


def _black_in_covered(field, seq, frames) -> list[float]:
    K = seq.intrinsics.scaled(320, 240)
    covered = colour_coverage(seq, (320, 240))
    return [float(((field.render(seq.T_world_cam_gt[i], K).rgb.sum(axis=2) == 0) & covered).mean()) for i in frames]


def test_a_view_field_never_warps_the_black_corners_into_a_render(seq, tmp_path):
    config = ViewFieldConfig(min_spacing_m=0.0)
    field, _ = build_view_field(seq, [0, 2, 4, 6, 8, 10], config)
    covered = colour_coverage(seq, (320, 240))
    assert np.array_equal(field.coverage, covered)
    assert not (field.depth_m[:, ~covered] > 0).any()  # no view puts a surface where it has no colour
    held_out = (1, 9)
    assert max(_black_in_covered(field, seq, held_out)) < 0.001
    # Without the coverage the views' corners land, black, inside the held-out frames' images.
    with mock.patch.object(view_module, "colour_coverage", lambda sequence, size=None: None):
        blind, _ = build_view_field(seq, [0, 2, 4, 6, 8, 10], config)
    assert blind.coverage is None
    assert max(_black_in_covered(blind, seq, held_out)) > 0.005
    # The checkpoint keeps it.
    again = ViewField.load(field.save(tmp_path / "views.pt"))
    assert np.array_equal(again.coverage, covered)


class _ImageField:
    """A stand-in field that renders the real frame nearest the asked pose, with its black
    corners painted white: right wherever the image holds data, wrong where it holds none."""

    def __init__(self, seq, size):
        self.seq, self.size = seq, size

    def render(self, T_world_cam, intrinsics):
        import cv2

        i = int(np.argmin([np.abs(T - T_world_cam).sum() for T in self.seq.T_world_cam_gt]))
        rgb = cv2.resize(self.seq[i].rgb, self.size, interpolation=cv2.INTER_AREA)
        rgb[~colour_coverage(self.seq, self.size)] = 255
        depth = np.ones(rgb.shape[:2], np.float32)
        return RenderedView(rgb, depth, np.ones_like(depth), intrinsics)


def test_the_held_out_psnr_scores_only_the_pixels_the_image_holds(seq):
    size = (320, 240)
    report = evaluate_field(_ImageField(seq, size), seq, [1, 5], size=size)
    assert report["psnr_db"] > 40.0 and report["psnr_affine_db"] > 40.0
    # Scored over every pixel, the white corners alone would hold it near 12 dB.
    real = seq[1].rgb.astype(np.float64) / 255.0
    import cv2

    real = cv2.resize(real, size, interpolation=cv2.INTER_AREA)
    rendered = _ImageField(seq, size).render(seq.T_world_cam_gt[1], seq.intrinsics.scaled(*size)).rgb / 255.0
    assert psnr(float(np.mean((rendered - real) ** 2))) < 20.0


def test_the_trained_fields_take_no_colour_from_the_corners(seq):
    import torch

    from nap3d_graph.fields.grid import GridField
    from nap3d_graph.fields.splat import SplatConfig, _frame_points
    from nap3d_graph.fields.training import TrainConfig, _Trainer
    from nap3d_graph.fields.training_data import TrainingRays, ray_poses, scene_bounds_from_depth

    covered = colour_coverage(seq)
    # The grid's training rays: every pixel with a depth trains the geometry, only those
    # holding colour data the colour (a black corner is no target).
    rays = TrainingRays.from_sequence(seq, [0, 4, 8], TrainConfig(), "cpu")
    assert np.array_equal(rays.coverage.numpy(), covered)
    assert (rays.depth.numpy()[:, ~covered] > 0).any()
    config = TrainConfig(rays_per_step=20_000)
    bounds = scene_bounds_from_depth(rays.depth.numpy(), ray_poses(rays), rays.intrinsics)
    grid = GridField.empty(bounds, 0.05, device="cpu", color_voxel_size=0.025)
    trainer = _Trainer(grid, rays, config, torch.Generator().manual_seed(0))
    origins, dirs, z, target, has_colour = trainer.sample_batch()
    assert has_colour.float().mean() > 0.9
    # Rays without colour data come from the few corner pixels that hold a depth.
    corner_share = (rays.depth.numpy()[:, ~covered] > 0).sum() / (rays.depth.numpy() > 0).sum()
    assert 0 < int((~has_colour).sum()) and float((~has_colour).float().mean()) < 2 * corner_share
    # The splats' colours: sampled only where all four bilinear neighbours hold data; the
    # points elsewhere keep their geometry without a colour.
    frame, T = seq[0], seq.T_world_cam_gt[0]
    everywhere = _frame_points(frame, T, T, 1.0, SplatConfig(), None)
    inside = _frame_points(frame, T, T, 1.0, SplatConfig(), covered)
    nowhere = _frame_points(frame, T, T, 1.0, SplatConfig(), np.zeros_like(covered))
    assert everywhere[3].all() and not nowhere[3].any() and (nowhere[1] == 0).all()
    np.testing.assert_array_equal(inside[0], everywhere[0])
    K = frame.intrinsics
    p = inside[0] @ np.linalg.inv(T)[:3, :3].T + np.linalg.inv(T)[:3, 3]
    u = np.round(K.fx * p[:, 0] / p[:, 2] + K.cx).astype(int)
    v = np.round(K.fy * p[:, 1] / p[:, 2] + K.cy).astype(int)
    assert covered[v, u][inside[3]].all() and 0 < (~inside[3]).sum() and not covered[v, u][~inside[3]].all()


def test_train_field_reports_the_share_without_colour_data(tmp_path, capsys):
    import json

    from nap3d_graph.cli import main

    out = tmp_path / "views.pt"
    assert main(["train-field", str(TUM_FR1_XYZ), "--model", "views", "--out", str(out), "--eval-frames", "2",
                 "--quiet"]) == 0
    report = json.loads(out.with_name("views.report.json").read_text())
    assert 0.05 < report["colour_without_data"] < 0.07
    assert "6.0% of each image holds no data" in capsys.readouterr().out
