"""The 7-Scenes reader: its own written layout read back bit-exactly, the colour camera of a
recording whose depth is not registered to colour recovered from the data, and bad input
refused in one line. No 7-Scenes image is in the repository: every folder is written here."""

import numpy as np
import pytest

from nap3d_graph.camera import Intrinsics
from nap3d_graph.cli import main
from nap3d_graph.datasets import DatasetError, SevenScenesSequence, open_sequence
from nap3d_graph.datasets.sevenscenes import (
    DEPTH_MISSING,
    NOMINAL_COLOUR_CAMERA,
    NOMINAL_DEPTH_CAMERA,
    write_sevenscenes_frame,
)
from nap3d_graph.fields import frames_seen_in_training


def _random_recording(folder, count=6, step=2, seed=0):
    rng = np.random.default_rng(seed)
    written = []
    for k in range(0, count * step, step):
        rgb = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
        depth_m = rng.integers(300, 4000, (48, 64)).astype(np.float64) / 1000.0
        depth_m[rng.random((48, 64)) < 0.1] = 0.0
        T = np.eye(4)
        T[:3, :3] = np.linalg.qr(rng.normal(size=(3, 3)))[0] * np.array([1, 1, 1])
        T[:3, :3] *= np.sign(np.linalg.det(T[:3, :3]))
        T[:3, 3] = rng.normal(size=3)
        write_sevenscenes_frame(folder, k, rgb, depth_m, T)
        written.append((k, rgb, depth_m, T))
    return written


def test_own_layout_reads_back_bit_exactly(tmp_path):
    written = _random_recording(tmp_path / "seq-01")
    camera = Intrinsics(58.5, 58.5, 32.0, 24.0, 64, 48)
    seq = SevenScenesSequence(tmp_path, depth_intrinsics=camera, registration="none")  # the scene folder
    assert len(seq) == 6 and seq.name == f"{tmp_path.name}_seq-01"
    np.testing.assert_array_equal(seq.timestamps, [k / 30.0 for k, *_ in written])
    for i, (k, rgb, depth_m, T) in enumerate(written):
        frame = seq[i]
        np.testing.assert_array_equal(frame.rgb, rgb)
        np.testing.assert_array_equal(frame.depth_m, (np.rint(depth_m * 1000) / 1000).astype(np.float32))
        assert frame.intrinsics == camera and frame.timestamp == k / 30.0
        np.testing.assert_allclose(seq.T_world_cam_gt[i], np.loadtxt(tmp_path / "seq-01" / f"frame-{k:06d}.pose.txt"),
                                   atol=1e-15)
        np.testing.assert_allclose(seq.T_world_cam_gt[i], T, atol=1e-15)
    # A part of it: same frames, same recording.
    half = SevenScenesSequence(tmp_path / "seq-01", depth_intrinsics=camera, registration="none", frames="0.5:1")
    np.testing.assert_array_equal(half.frame_numbers, [6, 8, 10])
    np.testing.assert_array_equal(half[0].rgb, written[3][1])
    assert half.recording_id == seq.recording_id


def test_missing_depth_and_lost_poses(tmp_path):
    import cv2

    _random_recording(tmp_path, count=3)
    raw = cv2.imread(str(tmp_path / "frame-000002.depth.png"), cv2.IMREAD_UNCHANGED)
    raw[:5] = DEPTH_MISSING  # the original release marks missing depth so
    cv2.imwrite(str(tmp_path / "frame-000002.depth.png"), raw)
    (tmp_path / "frame-000004.pose.txt").write_text("\n".join(["-inf -inf -inf -inf"] * 4) + "\n")
    seq = SevenScenesSequence(tmp_path, depth_intrinsics=Intrinsics(58.5, 58.5, 32, 24, 64, 48),
                              registration="none")
    assert np.all(seq[1].depth_m[:5] == 0) and np.all(seq[1].depth_m[5:][raw[5:] > 0] > 0)
    np.testing.assert_array_equal(seq.has_gt, [True, True, False])


@pytest.mark.parametrize("damage, message", [
    (lambda d: (d / "frame-000002.color.png").unlink(), "has a pose but no .color"),
    (lambda d: (d / "frame-000002.pose.txt").write_text("1 2 3\n"), "expected a 4x4"),
    (lambda d: (d / "camera-intrinsics.txt").write_text("1 0\n0 1\n"), "3x3 camera matrix"),
])
def test_bad_folders_are_refused_in_one_line(tmp_path, damage, message):
    _random_recording(tmp_path, count=3)
    np.savetxt(tmp_path / "camera-intrinsics.txt", Intrinsics(58.5, 58.5, 32, 24, 64, 48).K)
    damage(tmp_path)
    with pytest.raises(DatasetError, match=message) as info:
        SevenScenesSequence(tmp_path, registration="none")
    assert "\n" not in str(info.value)


def test_rounded_rotations_are_made_rigid_and_wrong_ones_refused(tmp_path):
    """Poses stored with rounding (as 7-Scenes' are: |R^T R - I| up to 2e-4) come out as exact
    rotations; a matrix that is no rotation at all is a one-line error."""
    _random_recording(tmp_path, count=2)
    T = np.loadtxt(tmp_path / "frame-000000.pose.txt")
    rounded = np.round(T, 4)
    np.savetxt(tmp_path / "frame-000000.pose.txt", rounded)
    seq = SevenScenesSequence(tmp_path, depth_intrinsics=Intrinsics(58.5, 58.5, 32, 24, 64, 48), registration="none")
    R = seq.T_world_cam_gt[0][:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(seq.T_world_cam_gt[0], T, atol=2e-4)
    rounded[:3, :3] *= 1.1
    np.savetxt(tmp_path / "frame-000000.pose.txt", rounded)
    with pytest.raises(DatasetError, match="not a rotation"):
        SevenScenesSequence(tmp_path, depth_intrinsics=Intrinsics(58.5, 58.5, 32, 24, 64, 48), registration="none")


def test_a_scene_with_several_sequences_asks_which(tmp_path):
    _random_recording(tmp_path / "seq-01", count=2)
    _random_recording(tmp_path / "seq-02", count=2, seed=1)
    with pytest.raises(DatasetError, match="holds 2 sequences"):
        open_sequence(tmp_path)
    seq = SevenScenesSequence(tmp_path, sequence="seq-02", depth_intrinsics=Intrinsics(58.5, 58.5, 32, 24, 64, 48),
                              registration="none")
    assert len(seq) == 2


def _simulated_kinect(folder, offset_m: float):
    """A simulated Kinect v1 at 320x240: colour f = 262.5 (525 at 640), its centre 4 and 3 px
    off the depth camera's (f = 292.5), ``offset_m`` beside it; poses of the depth camera."""
    from nap3d_graph.datasets.sevenscenes_sim import simulate_sevenscenes

    colour = NOMINAL_COLOUR_CAMERA.scaled(320, 240)
    colour = Intrinsics(colour.fx, colour.fy, colour.cx + 4.0, colour.cy - 3.0, 320, 240)
    T_colour_depth = np.eye(4)
    T_colour_depth[0, 3] = offset_m
    folder = simulate_sevenscenes(folder, frames=40, colour=colour, depth=NOMINAL_DEPTH_CAMERA.scaled(320, 240),
                                  T_colour_depth=T_colour_depth)
    return folder, colour, T_colour_depth


@pytest.fixture(scope="module")
def unregistered(tmp_path_factory):
    return _simulated_kinect(tmp_path_factory.mktemp("sevenscenes") / "seq-01", 0.0)


def test_the_default_colour_camera_is_the_nominal_kinect_and_reads_nothing(unregistered, tmp_path, monkeypatch):
    """registration='nominal' (the default): 525 px at the image's centre, scaled to the
    images; no pose file read, nothing estimated or cached; the depth warped into it."""
    from nap3d_graph.datasets import sevenscenes

    folder, _, _ = unregistered
    monkeypatch.setattr(sevenscenes.SevenScenesSequence, "_read_pose", lambda self, k: np.full((4, 4), np.nan))
    seq = open_sequence(folder, cache_dir=tmp_path)
    assert seq.intrinsics == NOMINAL_COLOUR_CAMERA.scaled(320, 240)
    assert np.allclose(seq.registration.T_colour_depth, np.eye(4))
    assert not (tmp_path / "registration").exists()
    stored = SevenScenesSequence(folder, registration="none")[10].depth_m
    warped = seq[10].depth_m
    # The depth camera's f = 292.5 against the colour's 262.5: the warp shrinks the image about
    # the centre, so the stored frame's middle pixel keeps its depth and its border does not.
    assert abs(warped[120, 160] - stored[120, 160]) < 0.02
    assert np.mean(warped > 0) < np.mean(stored > 0)


def test_a_map_folder_refuses_a_survey_read_through_another_colour_camera(unregistered, tmp_path):
    from nap3d_graph.mapping.build import MapSettings, _open_folder

    folder, _, _ = unregistered
    _open_folder(open_sequence(folder, frames="0:10"), tmp_path / "map", MapSettings())
    _open_folder(open_sequence(folder, frames="0:10"), tmp_path / "map", MapSettings())  # the same: resumed
    with pytest.raises(FileExistsError, match="other data or settings"):
        _open_folder(open_sequence(folder, frames="0:10", registration="none"), tmp_path / "map", MapSettings())


@pytest.mark.slow
def test_colour_camera_is_recovered_from_the_data(unregistered, tmp_path):
    """The fit, with each pair's motion from the (exact, simulated) pose files."""
    folder, colour, _ = unregistered
    seq = open_sequence(folder, cache_dir=tmp_path, registration="poses")
    assert isinstance(seq, SevenScenesSequence)
    reg = seq.registration
    # The focal length and centre: what moves every pixel (the nominal 525-px start is 5 px
    # off the centre).
    assert abs(reg.colour.fx / colour.fx - 1) < 0.002
    assert abs(reg.colour.cx - colour.cx) < 0.7 and abs(reg.colour.cy - colour.cy) < 0.7
    assert reg.residual_px < 0.5 and reg.residual_px < 0.5 * reg.start_residual_px
    # Frames and ground truth are the colour camera's.
    assert seq.intrinsics == reg.colour
    np.testing.assert_allclose(seq.T_world_cam_gt[0], np.loadtxt(folder / "frame-000000.pose.txt"))
    # Cached per recording: the second open reads it back.
    assert list((tmp_path / "registration").glob("7scenes_*.json"))
    again = open_sequence(folder, cache_dir=tmp_path, registration="poses")
    assert again.registration.colour == reg.colour


def test_colour_camera_is_recovered_from_the_images_alone(unregistered, tmp_path, monkeypatch):
    """registration='images': each pair's motion by depth-only ICP; no pose file is read. The simulated
    traversal is fast (metres in 2.6 s), so ICP poses only the slowest pairs; the fit still
    finds the focal length and the centre to a pixel."""
    from nap3d_graph.datasets import sevenscenes

    folder, colour, _ = unregistered
    monkeypatch.setattr(sevenscenes.SevenScenesSequence, "_read_pose", lambda self, k: np.full((4, 4), np.nan))
    seq = open_sequence(folder, cache_dir=tmp_path, registration="images")  # a pose file read would show as no GT
    reg = seq.registration
    assert not seq.has_gt.any()
    assert abs(reg.colour.fx / colour.fx - 1) < 0.003
    assert abs(reg.colour.cx - colour.cx) < 1.0 and abs(reg.colour.cy - colour.cy) < 1.0
    assert reg.residual_px < 0.8 * reg.start_residual_px


def test_registered_depth_meets_the_colour_surfaces(unregistered, tmp_path):
    """Depth warped into the estimated colour camera agrees with the colour camera's true depth."""
    from nap3d_graph.sims.scene import make_scene

    folder, colour, _ = unregistered
    seq = open_sequence(folder, cache_dir=tmp_path, registration="poses")
    truth = make_scene(11).render_depth(np.loadtxt(folder / "frame-000020.pose.txt"), colour)
    frame = seq[10]
    both = (frame.depth_m > 0) & (truth > 0)
    error_mm = np.abs(frame.depth_m - truth)[both] * 1000
    assert both.mean() > 0.8 and np.median(error_mm) < 3.0 and np.percentile(error_mm, 90) < 20.0
    # Against the images as stored (the depth camera's grid): many times worse.
    stored = SevenScenesSequence(folder, registration="none")[10].depth_m
    both_stored = (stored > 0) & (truth > 0)
    assert np.median(np.abs(stored - truth)[both_stored]) * 1000 > 5 * np.median(error_mm)


@pytest.mark.slow
def test_an_offset_between_the_cameras_is_left_to_the_principal_point(tmp_path):
    """The documented limit: a 25 mm offset is not estimated; the fit still improves on the
    nominal camera and finds the focal length."""
    folder, colour, _ = _simulated_kinect(tmp_path / "seq-01", 0.025)
    reg = SevenScenesSequence(folder, cache_dir=False, registration="poses").registration
    assert np.allclose(reg.T_colour_depth, np.eye(4))
    assert abs(reg.colour.fx / colour.fx - 1) < 0.003 and abs(reg.colour.cx - colour.cx) < 3.0
    assert reg.residual_px < 0.8 * reg.start_residual_px


def test_trained_frames_of_another_sequence_with_the_same_numbers_are_not_reported(tmp_path):
    _random_recording(tmp_path / "a", count=4)
    _random_recording(tmp_path / "b", count=4, seed=3)
    camera = Intrinsics(58.5, 58.5, 32, 24, 64, 48)
    a, b = (SevenScenesSequence(tmp_path / x, depth_intrinsics=camera, registration="none") for x in "ab")

    class Field:
        meta = {"train_timestamps": a.timestamps.tolist(), "train_recording": a.recording_id}

    assert frames_seen_in_training(Field(), a).all() and not frames_seen_in_training(Field(), b).any()


def test_run_with_traj_7scenes_on_another_layout_is_a_usage_error(tmp_path, capsys):
    (tmp_path / "rgb.txt").write_text("")
    rc = main(["run", "--traj", "7scenes", "--data", str(tmp_path), "--field", "none", "--out", str(tmp_path / "o")])
    assert rc == 2 and "not a 7-Scenes folder" in capsys.readouterr().err
