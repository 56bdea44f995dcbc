"""TUM RGB-D reader on the real fr1/xyz and fr1/desk frames in tests/data and trajectory files
(checked against evo). Bad input: test_tum_errors.py; association and interpolation:
test_association.py."""

from __future__ import annotations

import os
import re
import shutil
import subprocess

import cv2
import numpy as np
import pytest
from conftest import TUM_FR1_DESK, TUM_FR1_XYZ

from nap3d_graph.camera import Intrinsics, RGBDFrame, backproject_depth, project
from nap3d_graph.conventions import inv_T, make_T, rotation_angle_deg, transform_points
from nap3d_graph.datasets import SOURCES, DatasetError, TumSequence, read_tum_trajectory, write_tum_trajectory
from nap3d_graph.datasets.tum import read_file_list
from nap3d_graph.trajectory import interpolate_poses

TUM_DIR = TUM_FR1_XYZ
FR1 = Intrinsics(517.3, 516.5, 318.6, 255.3, 640, 480)
FR1_DISTORTION = (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)


@pytest.fixture(scope="module")
def seq() -> TumSequence:
    return TumSequence(TUM_DIR)


@pytest.fixture(scope="module")
def raw_gt():
    return read_tum_trajectory(TUM_DIR / "groundtruth.txt")


# --- the real sequence ------------------------------------------------------------------------


def test_real_sequence_association_and_intrinsics(seq):
    # Every colour frame is associated: the depth stream's lead (12-17 ms on these frames) is
    # estimated and removed before pairing within TUM's 0.02 s.
    assert len(seq) == 12 and seq.association == "optimal"
    assert 0.012 < seq.offset < 0.017
    assert seq.timestamps.shape == (12,) and seq.depth_timestamps.shape == (12,)
    assert np.all(np.diff(seq.timestamps) > 0) and np.all(np.diff(seq.depth_timestamps) > 0)
    assert np.all(np.abs(seq.timestamps - seq.depth_timestamps - seq.offset) < 0.02)
    assert len(seq.rgb_paths) == len(seq.depth_paths) == 12
    assert len(set(seq.depth_paths)) == 12
    assert seq.has_gt.all()  # the ground truth spans the whole excerpt
    assert seq.name == "rgbd_dataset_freiburg1_xyz" and seq.path == TUM_DIR
    # fr1 calibration, reported without distortion because the images are undistorted.
    assert seq.intrinsics == FR1
    assert seq.intrinsics.distortion == ()
    assert seq.raw_intrinsics.distortion == pytest.approx(FR1_DISTORTION)
    assert SOURCES["tum"] is TumSequence


def test_real_sequence_every_frame_associated():
    stamps_rgb, _ = read_file_list(TUM_DIR / "rgb.txt")
    # Without the offset (TUM associate.py's default), TUM's greedy pairing gives two depth
    # frames to the wrong colour frame (each depth frame is 12-17 ms before its own colour
    # frame, and 16-21 ms after the previous one) and loses two of the twelve frames.
    greedy = TumSequence(TUM_DIR, association="greedy", offset=0.0)
    assert len(greedy) == 10 and greedy.association == "greedy"
    # Allowing for the depth lead (estimated, or TUM's --offset), or the optimal pairing,
    # every colour frame gets its own depth frame.
    for kwargs in ({}, {"offset": 0.015}, {"offset": 0.0}, {"offset": 0.0, "max_difference": 0.021}):
        every = TumSequence(TUM_DIR, **kwargs)
        assert len(every) == 12, kwargs
        assert np.array_equal(every.timestamps, stamps_rgb)
        assert [p.name for p in every.depth_paths] == sorted(p.name for p in (TUM_DIR / "depth").glob("*.png"))
    with pytest.raises(DatasetError, match="association must be one of"):
        TumSequence(TUM_DIR, association="nearest")


def test_real_frames(seq):
    frame = seq[0]
    assert isinstance(frame, RGBDFrame)
    assert frame.rgb.shape == (480, 640, 3) and frame.rgb.dtype == np.uint8
    assert frame.depth_m.shape == (480, 640) and frame.depth_m.dtype == np.float32
    assert frame.timestamp == seq.timestamps[0]
    assert frame.intrinsics == FR1
    valid = frame.depth_m > 0
    # A desk scene about 1.2 m away; a fifth to a third of the pixels have no depth.
    assert 0.6 < valid.mean() < 0.8
    assert 1.0 < np.median(frame.depth_m[valid]) < 1.4
    assert frame.depth_m.max() < 10.0
    # Depth is delivered as stored (registered by the Kinect driver): raw uint16 / 5000.
    raw = cv2.imread(str(seq.depth_paths[0]), cv2.IMREAD_UNCHANGED)
    assert not seq.undistort_depth
    assert np.array_equal(frame.depth_m, raw.astype(np.float32) / np.float32(5000))
    # RGB order: the colour image equals OpenCV's own undistortion of the BGR file, flipped.
    bgr = cv2.imread(str(seq.rgb_paths[0]))
    expected = cv2.undistort(bgr, FR1.K, np.array(FR1_DISTORTION))[..., ::-1]
    inner = (slice(40, -40), slice(40, -40))  # black borders differ by a pixel
    assert np.abs(frame.rgb[inner].astype(int) - expected[inner]).mean() < 1.0
    # Undistortion keeps the principal point and pulls the corners from outside the raw
    # image (fr1's distortion maps undistorted pixel (0, 0) to raw (-24, -21)): black corners.
    plain = TumSequence(TUM_DIR, undistort=False)
    assert plain.intrinsics.distortion == pytest.approx(FR1_DISTORTION)  # raw images say so
    raw_frame = plain[0]
    assert np.array_equal(raw_frame.rgb[255, 318], frame.rgb[255, 318])
    assert np.all(frame.rgb[:5, :5] == 0)
    assert (raw_frame.rgb.sum(axis=2) == 0).sum() == 0
    assert (frame.rgb.sum(axis=2) == 0).sum() > 10_000
    # Depth undistorted on request: nearest neighbour invents no values, corners go empty.
    remapped = TumSequence(TUM_DIR, undistort_depth=True)[0].depth_m
    valid_remapped = remapped > 0
    assert np.isin(np.round(remapped[valid_remapped] * 5000).astype(np.uint16), raw).all()
    assert np.all(remapped[:5, :5] == 0)
    assert np.array_equal(remapped[255, 318], frame.depth_m[255, 318])


def test_indexing_and_iteration(seq):
    assert seq[-1].timestamp == seq.timestamps[-1]
    assert seq[np.int64(3)].timestamp == seq.timestamps[3]
    with pytest.raises(IndexError):
        seq[len(seq)]
    with pytest.raises(IndexError):
        seq[-len(seq) - 1]
    stamps = [frame.timestamp for _, frame in zip(range(3), seq)]
    assert stamps == list(seq.timestamps[:3])


def test_ground_truth_interpolated_to_rgb_stamps(seq, raw_gt):
    stamps_gt, T_world_cam_gt = raw_gt
    assert stamps_gt.shape == (238,) and T_world_cam_gt.shape == (238, 4, 4)
    T = seq.T_world_cam_gt
    assert T.shape == (12, 4, 4) and np.all(np.isfinite(T))
    nearest = np.abs(stamps_gt[None, :] - seq.timestamps[:, None]).argmin(axis=1)
    assert np.abs(stamps_gt[nearest] - seq.timestamps).max() < 0.0051  # 100 Hz ground truth
    dist_mm = 1000 * np.linalg.norm(T[:, :3, 3] - T_world_cam_gt[nearest, :3, 3], axis=1)
    angle_deg = rotation_angle_deg(np.swapaxes(T[:, :3, :3], 1, 2) @ T_world_cam_gt[nearest, :3, :3])
    assert dist_mm.max() < 3.0  # <= 5 ms of motion at fr1/xyz's ~0.4 m/s
    assert angle_deg.max() < 0.3
    assert np.allclose(T[:, :3, :3] @ np.swapaxes(T[:, :3, :3], 1, 2), np.eye(3), atol=1e-9)


def _depth_agreement_mm(depth_a, depth_b, K, T_world_a, T_world_b):
    """Median |z_b - z(a moved into b)| (mm) and count over pixels valid in both within 5 cm.

    Every second pixel of a is back-projected (the median barely moves; 4x faster).
    """
    points_a, _ = backproject_depth(depth_a, K, stride=2)
    points_b = transform_points(inv_T(T_world_b) @ T_world_a, points_a)
    uv, z = project(points_b, K)
    u, v = np.rint(uv[:, 0]), np.rint(uv[:, 1])
    inside = (u >= 0) & (u < K.width) & (v >= 0) & (v < K.height)
    measured = depth_b[v[inside].astype(int), u[inside].astype(int)]
    diff = measured - z[inside]
    same_surface = (measured > 0) & (np.abs(diff) < 0.05)
    return 1000 * float(np.median(np.abs(diff[same_surface]))), int(same_surface.sum())


def _pair_agreements(sequence, T_world_cam, k, step):
    """Depth agreement (mm, count) of the frame pairs (i, i + k), i = 0, step, 2 step, ..."""
    depths = {}

    def depth(i):
        if i not in depths:
            depths[i] = sequence[i].depth_m
        return depths[i]

    return [
        _depth_agreement_mm(depth(i), depth(i + k), sequence.intrinsics, T_world_cam[i], T_world_cam[i + k])
        for i in range(0, len(sequence) - k, step)
    ]


@pytest.fixture(scope="module")
def T_at_depth(seq, raw_gt):
    # Depth is stamped 12-20 ms before colour; at fr1/xyz's ~0.4 m/s that is several mm, so
    # the geometric checks take the ground truth at the depth timestamps.
    return interpolate_poses(*raw_gt, seq.depth_timestamps)


# Measured on every pair (i, i + k) of the 12 frames (each pair's median |diff|; raw depth,
# ground truth at the depth stamps; stride 2):
#   k               1     5     10
#   median, mm      3.1   4.7   8.7
#   worst pair, mm  6.1   5.8   8.9
# (on the 37 first frames of the sequence: 2.4 / 3.6 / 3.5 mm median). The floor is the
# Kinect (one disparity step, 1/8 px, is ~4 mm of depth at this scene's 1.2 m); it grows
# with the baseline as more of each pair is seen obliquely.
@pytest.mark.parametrize(
    ("k", "median_limit_mm", "worst_limit_mm"), [(1, 3.5, 6.5), (5, 5.5, 7.0), (10, 9.5, 9.5)]
)
def test_depth_reprojects_consistently_with_ground_truth(seq, T_at_depth, k, median_limit_mm, worst_limit_mm):
    results = _pair_agreements(seq, T_at_depth, k, step=1)
    medians = np.array([m for m, _ in results])
    assert np.median(medians) < median_limit_mm
    assert medians.max() < worst_limit_mm
    assert min(count for _, count in results) > 20_000  # stride 2: a quarter of the pixels
    if k == 1:
        # Neighbouring frames see the same surfaces: under 5 mm for all but one pair.
        assert (medians < 5.0).sum() >= len(medians) - 1
    # A 3 cm error in the relative pose must show clearly against that floor.
    frame_0, frame_k = seq[0], seq[k]
    shifted = T_at_depth[k] @ make_T(np.eye(3), [0.0, 0.0, 0.03])
    wrong_mm, _ = _depth_agreement_mm(frame_0.depth_m, frame_k.depth_m, FR1, T_at_depth[0], shifted)
    assert wrong_mm > medians[0] + 10.0


def test_depth_choices_raw_depth_and_depth_stamps(seq, T_at_depth):
    # Ground truth at the colour stamps (what T_world_cam_gt holds) is ~15 ms off for depth:
    # 3.6 instead of 3.1 mm for neighbouring frames.
    at_depth = np.median([m for m, _ in _pair_agreements(seq, T_at_depth, 1, step=1)])
    at_rgb = np.median([m for m, _ in _pair_agreements(seq, seq.T_world_cam_gt, 1, step=1)])
    assert at_depth < at_rgb - 0.3
    # Depth remapped with the colour distortion agrees worse at long baselines (10.1 against
    # 8.7 mm 10 frames apart), hence the default.
    remapped = TumSequence(TUM_DIR, undistort_depth=True)
    raw_mm = np.median([m for m, _ in _pair_agreements(seq, T_at_depth, 10, step=1)])
    remapped_mm = np.median([m for m, _ in _pair_agreements(remapped, T_at_depth, 10, step=1)])
    assert raw_mm < remapped_mm - 0.5


def test_subsampled_desk_keeps_every_listed_pair():
    """fr1/desk at 15 Hz: rgb.txt and depth.txt list already-associated pairs, line by line.
    The depth-lead estimate must not cost any of them (it used to drop 66 of 277)."""
    desk = TumSequence(TUM_FR1_DESK)
    stamps_rgb, _ = read_file_list(TUM_FR1_DESK / "rgb.txt")
    stamps_depth, _ = read_file_list(TUM_FR1_DESK / "depth.txt")
    assert len(desk) == 6 and np.array_equal(desk.timestamps, stamps_rgb)
    assert np.array_equal(desk.depth_timestamps, stamps_depth)
    assert desk.has_gt.all() and np.all(np.isfinite(desk.T_world_cam_gt))
    # The camera moves at about half a metre per second here.
    speed = np.linalg.norm(np.diff(desk.T_world_cam_gt[:, :3, 3], axis=0), axis=1) / np.diff(desk.timestamps)
    assert 0.3 < np.median(speed) < 0.8


# --- laziness ---------------------------------------------------------------------------------


def test_construction_reads_no_images(monkeypatch):
    calls = []
    real_imread = cv2.imread

    def counting_imread(*args, **kwargs):
        calls.append(args[0])
        return real_imread(*args, **kwargs)

    monkeypatch.setattr(cv2, "imread", counting_imread)
    lazy = TumSequence(TUM_DIR)
    assert calls == []
    lazy[5]
    assert sorted(calls) == sorted([str(lazy.rgb_paths[5]), str(lazy.depth_paths[5])])


# --- trajectory files -------------------------------------------------------------------------


def test_trajectory_round_trip_and_evo(seq, tmp_path):
    from evo.tools import file_interface

    a = tmp_path / "a.txt"
    write_tum_trajectory(a, seq.timestamps, seq.T_world_cam_gt)
    lines = a.read_text().splitlines()
    assert lines[0].startswith("#")
    assert all(len(line.split(" ")) == 8 for line in lines[1:])
    stamps, T = read_tum_trajectory(a)
    assert np.allclose(stamps, seq.timestamps, rtol=0, atol=1e-6)
    assert np.allclose(T, seq.T_world_cam_gt, rtol=0, atol=1e-6)

    traj = file_interface.read_tum_trajectory_file(str(a))
    assert traj.num_poses == len(seq)
    assert np.allclose(traj.timestamps, seq.timestamps, atol=1e-6)
    assert np.allclose(traj.positions_xyz, seq.T_world_cam_gt[:, :3, 3], atol=1e-6)
    assert np.allclose(np.stack(traj.poses_se3), seq.T_world_cam_gt, atol=1e-6)


def test_evo_ape_cli_reads_written_files(seq, tmp_path):
    evo_ape = shutil.which("evo_ape")
    assert evo_ape is not None, "evo_ape console script not on PATH (evo is a dependency)"
    a, b = tmp_path / "a.txt", tmp_path / "b.txt"
    write_tum_trajectory(a, seq.timestamps, seq.T_world_cam_gt)
    shifted = seq.T_world_cam_gt.copy()
    shifted[:, 0, 3] += 0.01  # 1 cm along world x: unaligned APE is exactly 1 cm everywhere
    write_tum_trajectory(b, seq.timestamps, shifted)
    # HOME in tmp_path: evo writes its settings file there instead of the user's home.
    env = {**os.environ, "HOME": str(tmp_path), "MPLBACKEND": "Agg"}
    result = subprocess.run(
        [evo_ape, "tum", str(a), str(b)], capture_output=True, text=True, env=env, timeout=60, check=False
    )
    assert result.returncode == 0, result.stderr
    rmse = re.search(r"rmse\s+([0-9.]+)", result.stdout)
    assert rmse is not None, result.stdout
    assert float(rmse.group(1)) == pytest.approx(0.01, abs=1e-6)


def test_a_trajectory_travels_with_its_unknown_poses_and_round_trips(tmp_path):
    """Trajectory: TUM out and back to the file's precision, unknown poses refused or left
    out, rigid-and-ordered check, evo's type from the known poses only."""
    from nap3d_graph.conventions import exp_se3
    from nap3d_graph.datasets import Trajectory

    rng = np.random.default_rng(0)
    T = np.stack([exp_se3(rng.normal(0, 0.3, 6)) for _ in range(5)])
    trajectory = Trajectory(np.arange(5) * 0.1 + 100.0, T).check()
    back = Trajectory.read_tum(trajectory.write_tum(tmp_path / "t.txt", header="a test"))
    np.testing.assert_allclose(back.T_world_cam, T, atol=2e-8)
    np.testing.assert_allclose(back.stamps, trajectory.stamps, atol=1e-6)
    assert (tmp_path / "t.txt").read_text().startswith("# a test\n# timestamp tx ty tz qx qy qz qw\n")
    T_gaps = T.copy()
    T_gaps[2] = np.nan
    gaps = Trajectory(trajectory.stamps, T_gaps)
    assert gaps.valid.tolist() == [True, True, False, True, True]
    with pytest.raises(DatasetError, match="non-finite"):
        gaps.write_tum(tmp_path / "refused.txt")
    assert len(Trajectory.read_tum(gaps.write_tum(tmp_path / "kept.txt", skip_unknown=True))) == 4
    assert gaps.to_evo().num_poses == 4
    not_rigid = T.copy()
    not_rigid[1, :3, :3] *= 1.1
    with pytest.raises(DatasetError, match="not rigid"):
        Trajectory(trajectory.stamps, not_rigid).check()
    with pytest.raises(DatasetError, match="strictly increase"):
        Trajectory(trajectory.stamps[::-1], T).check()
    with pytest.raises(DatasetError, match=r"\(N, 4, 4\)"):
        Trajectory(trajectory.stamps, T[:3])
