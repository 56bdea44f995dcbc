"""TUM RGB-D reader and trajectory files under bad input: every mistake a one-line
DatasetError that names the file, or a warning that says what was left out."""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import TUM_FR1_XYZ

from nap3d_graph.camera import Intrinsics
from nap3d_graph.datasets import DatasetError, TumSequence, read_tum_trajectory, write_tum_trajectory

TUM_DIR = TUM_FR1_XYZ


def small_copy(tmp_path: Path, frames: int = 4, name: str = "rgbd_dataset_freiburg1_xyz") -> Path:
    """First ``frames`` colour and depth frames of fr1/xyz in TUM's layout, writable."""
    out = tmp_path / name
    (out / "rgb").mkdir(parents=True)
    (out / "depth").mkdir()
    for list_name in ("rgb.txt", "depth.txt"):
        lines = (TUM_DIR / list_name).read_text().splitlines()
        header = [line for line in lines if line.startswith("#")]
        data = [line for line in lines if line and not line.startswith("#")][:frames]
        (out / list_name).write_text("\n".join(header + data) + "\n")
        for line in data:
            rel = line.split()[1]
            shutil.copyfile(TUM_DIR / rel, out / rel)
    shutil.copyfile(TUM_DIR / "groundtruth.txt", out / "groundtruth.txt")
    return out


def test_write_refuses_bad_poses(tmp_path):
    path = tmp_path / "bad.txt"
    with pytest.raises(DatasetError, match="bad.txt"):
        write_tum_trajectory(path, [0.0], np.full((1, 4, 4), np.nan))
    with pytest.raises(DatasetError, match="bad.txt"):
        write_tum_trajectory(path, [0.0, 1.0], np.eye(4)[None])


def test_read_trajectory_errors(tmp_path):
    path = tmp_path / "traj.txt"
    path.write_text("# header\n0.0 0 0 0 0 0 0 1\n1.0 0 0 0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"traj\.txt:3: expected 8 columns"):
        read_tum_trajectory(path)
    path.write_text("0.0 0 0 0 0 0 0 x\n")
    with pytest.raises(DatasetError, match=r"traj\.txt:1: 'x' is not a number"):
        read_tum_trajectory(path)
    path.write_text("0.0 0 0 0 0 0 0 0\n")
    with pytest.raises(DatasetError, match="zero norm"):
        read_tum_trajectory(path)
    path.write_text("# only a comment\n")
    with pytest.raises(DatasetError, match="no poses"):
        read_tum_trajectory(path)
    with pytest.raises(DatasetError, match="missing.txt"):
        read_tum_trajectory(tmp_path / "missing.txt")


# --- intrinsics resolution --------------------------------------------------------------------


def test_intrinsics_resolution(tmp_path, caplog):
    fr1_copy = small_copy(tmp_path / "a")
    custom = Intrinsics(500.0, 501.0, 320.0, 240.0, 640, 480)
    assert TumSequence(fr1_copy, intrinsics=custom).intrinsics == custom
    assert TumSequence(fr1_copy, intrinsics=custom.to_dict()).intrinsics == custom
    (fr1_copy / "intrinsics.json").write_text(json.dumps(custom.to_dict()))
    from_json = TumSequence(fr1_copy)
    assert from_json.intrinsics == custom and from_json[0].intrinsics == custom
    (fr1_copy / "intrinsics.json").write_text('{"fx": 1}')
    with pytest.raises(DatasetError, match=r"intrinsics\.json"):
        TumSequence(fr1_copy)

    fr3 = small_copy(tmp_path / "b", name="rgbd_dataset_freiburg3_office")
    assert TumSequence(fr3).intrinsics == Intrinsics(535.4, 539.2, 320.1, 247.6, 640, 480)
    fr2 = small_copy(tmp_path / "c", name="rgbd_dataset_freiburg2_desk")
    fr2_distortion = (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)
    assert TumSequence(fr2).raw_intrinsics.distortion == pytest.approx(fr2_distortion)

    unnamed = small_copy(tmp_path / "d", name="my_recording")
    with caplog.at_level(logging.WARNING, logger="nap3d_graph.datasets.tum"):
        default = TumSequence(unnamed)
    assert default.intrinsics == Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)
    assert "default camera" in caplog.text


# --- bad input --------------------------------------------------------------------------------


def test_missing_folder_and_lists(tmp_path):
    with pytest.raises(DatasetError, match="nowhere"):
        TumSequence(tmp_path / "nowhere")
    folder = small_copy(tmp_path)
    (folder / "rgb.txt").unlink()
    with pytest.raises(DatasetError, match=r"rgb\.txt: file not found"):
        TumSequence(folder)
    folder = small_copy(tmp_path / "b")
    (folder / "depth.txt").unlink()
    with pytest.raises(DatasetError, match=r"depth\.txt: file not found"):
        TumSequence(folder)


def test_missing_image_file(tmp_path):
    folder = small_copy(tmp_path)
    seq = TumSequence(folder)
    seq.rgb_paths[1].unlink()
    # The sequence still opens (a run can skip the frame); reading that frame names the file.
    again = TumSequence(folder)
    assert again.missing_images == [seq.rgb_paths[1]]
    again[0]
    with pytest.raises(DatasetError, match=re.escape(seq.rgb_paths[1].name) + ".*not found"):
        again[1]
    for p in (*seq.rgb_paths, *seq.depth_paths):
        p.unlink(missing_ok=True)
    with pytest.raises(DatasetError, match="none of the listed images exist"):
        TumSequence(folder)


def test_corrupt_png(tmp_path):
    seq = TumSequence(small_copy(tmp_path))
    seq.rgb_paths[0].write_bytes(b"\x89PNG garbage, not an image" * 10)
    with pytest.raises(DatasetError, match=re.escape(seq.rgb_paths[0].name) + ".*corrupt"):
        seq[0]
    seq.depth_paths[1].write_bytes(os.urandom(500))
    with pytest.raises(DatasetError, match=re.escape(seq.depth_paths[1].name)):
        seq[1]


def test_depth_of_wrong_size_or_type(tmp_path):
    seq = TumSequence(small_copy(tmp_path))
    cv2.imwrite(str(seq.depth_paths[0]), np.full((240, 320), 5000, np.uint16))
    with pytest.raises(DatasetError, match=re.escape(seq.depth_paths[0].name) + ".*320x240"):
        seq[0]
    cv2.imwrite(str(seq.depth_paths[1]), np.full((480, 640), 50, np.uint8))
    with pytest.raises(DatasetError, match=re.escape(seq.depth_paths[1].name) + ".*uint16"):
        seq[1]


def test_timestamps_that_never_associate(tmp_path):
    folder = small_copy(tmp_path)
    lines = []
    for line in (folder / "depth.txt").read_text().splitlines():
        if line.startswith("#"):
            lines.append(line)
        else:
            stamp, name = line.split()
            lines.append(f"{float(stamp) + 10.0:.6f} {name}")
    (folder / "depth.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=r"depth\.txt: no depth timestamp within 0\.02 s"):
        TumSequence(folder)


def test_malformed_list_line(tmp_path):
    folder = small_copy(tmp_path)
    with open(folder / "rgb.txt", "a") as f:
        f.write("not-a-stamp rgb/x.png\n")
    with pytest.raises(DatasetError, match=r"rgb\.txt:8: 'not-a-stamp' is not a number"):
        TumSequence(folder)


def test_ground_truth_outside_frames(tmp_path, caplog):
    folder = small_copy(tmp_path, frames=8)
    full = TumSequence(folder)
    # Keep only ground truth up to the middle of the frames: the later frames stay in the
    # sequence (a run still runs them), with no pose to compare with, and a warning says so.
    cut = full.timestamps[3] + 0.02  # past frame 3 (GT every 10 ms), before frame 4 (+33 ms)
    lines = (folder / "groundtruth.txt").read_text().splitlines()
    kept = [line for line in lines if line.startswith("#") or float(line.split()[0]) <= cut]
    (folder / "groundtruth.txt").write_text("\n".join(kept) + "\n")
    with caplog.at_level(logging.WARNING, logger="nap3d_graph.datasets.tum"):
        partial = TumSequence(folder)
    assert len(partial) == len(full) and np.array_equal(partial.timestamps, full.timestamps)
    assert partial.has_gt.tolist() == [True] * 4 + [False] * (len(full) - 4)
    assert np.all(np.isnan(partial.T_world_cam_gt[4:])) and np.allclose(partial.T_world_cam_gt[:4], full.T_world_cam_gt[:4])
    assert "4 of 8 frames have no ground truth" in caplog.text and "frames 4, 5, 6, 7" in caplog.text
    assert partial.rgb_line_index.tolist() == list(range(8))
    (folder / "groundtruth.txt").write_text("1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"groundtruth\.txt: ground truth covers none"):
        TumSequence(folder)
    (folder / "groundtruth.txt").unlink()
    assert TumSequence(folder).T_world_cam_gt is None


# --- stamps that go backwards -------------------------------------------------------------------


def backwards_folder(tmp_path: Path) -> Path:
    """Six tiny frames in TUM's layout whose lists' stamps go backwards at two lines, as a
    recording script that prints a stamp's fraction without its leading zeros writes them
    (``10.0154`` for 10.154 s after ``10.121``)."""
    folder = tmp_path / "backwards"
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    stamps = ["10.000000", "10.033000", "10.066000", "10.010000", "10.132000", "10.016500"]  # lines 4 and 6 go back
    for list_name, sub in (("rgb.txt", "rgb"), ("depth.txt", "depth")):
        lines = ["# timestamp filename"]
        for i, stamp in enumerate(stamps):
            name = f"{sub}/{i:02d}.png"
            if sub == "rgb":
                cv2.imwrite(str(folder / name), np.full((8, 10, 3), 40 * i, np.uint8))
            else:
                cv2.imwrite(str(folder / name), np.full((8, 10), 5000 + 100 * i, np.uint16))
            lines.append(f"{stamp} {name}")
        (folder / list_name).write_text("\n".join(lines) + "\n")
    return folder


TINY = Intrinsics(10.0, 10.0, 4.5, 3.5, 10, 8)


def test_stamps_that_go_backwards_are_refused(tmp_path):
    folder = backwards_folder(tmp_path)
    with pytest.raises(DatasetError) as caught:
        TumSequence(folder, intrinsics=TINY)
    message = str(caught.value)
    assert "\n" not in message
    assert re.search(r"rgb\.txt: stamps go backwards at 2 of 6 lines", message)
    assert re.search(r"depth\.txt: stamps go backwards at 2 of 6 lines", message)
    assert "stamps='file-order'" in message
    with pytest.raises(DatasetError, match="stamps must be one of"):
        TumSequence(folder, intrinsics=TINY, stamps="sorted")


def test_stamps_file_order_keeps_the_file_order_with_increasing_stamps(tmp_path, caplog):
    folder = backwards_folder(tmp_path)
    with caplog.at_level(logging.WARNING, logger="nap3d_graph.datasets.tum"):
        seq = TumSequence(folder, intrinsics=TINY, stamps="file-order")
    assert seq.stamps_mode == "file-order"
    assert len(seq) == 6
    assert np.all(np.diff(seq.timestamps) > 0) and np.all(np.diff(seq.depth_timestamps) > 0)
    # The median forward step of the stamps as written (33 ms, 33 ms, 122 ms, 6.5 ms: 33 ms).
    np.testing.assert_allclose(seq.timestamps, 10.0 + 0.033 * np.arange(6), atol=1e-9)
    assert [p.name for p in seq.rgb_paths] == [f"{i:02d}.png" for i in range(6)]  # file order
    assert seq.rgb_line_index.tolist() == list(range(6))
    assert seq[3].rgb[0, 0, 0] == 120 and seq[3].depth_m[0, 0] == pytest.approx(5300 / 5000)
    warnings = [r.getMessage() for r in caplog.records if "go backwards" in r.getMessage()]
    assert len(warnings) == 2 and all("at 2 of 6 lines" in w for w in warnings)
    # A folder whose stamps increase is the same either way.
    plain = small_copy(tmp_path / "plain")
    np.testing.assert_array_equal(TumSequence(plain, stamps="file-order").timestamps, TumSequence(plain).timestamps)


def test_trajectory_writer_refuses_stamps_out_of_order(tmp_path):
    from nap3d_graph.trajectory import Trajectory

    poses = np.repeat(np.eye(4)[None], 3, axis=0)
    path = tmp_path / "traj.txt"
    for stamps in ([0.0, 2.0, 1.0], [0.0, 1.0, 1.0], [0.0, 1.0, 1.0000001]):  # back, repeated, same microsecond
        with pytest.raises(ValueError, match=r"traj\.txt: refusing to write stamps that do not strictly increase"):
            write_tum_trajectory(path, stamps, poses)
        assert not path.exists()
    with open(tmp_path / "appended.txt", "w") as handle, pytest.raises(ValueError, match="strictly increase"):
        Trajectory(np.array([1.0, 0.5, 2.0]), poses).append_tum(handle)
    write_tum_trajectory(path, [0.0, 1.0, 2.0], poses)
    assert read_tum_trajectory(path)[0].tolist() == [0.0, 1.0, 2.0]


def test_the_command_line_names_stamps_file_order_and_reads_the_folder_with_it(tmp_path, capsys):
    """A recording script's per-frame intervals (stamps that restart) on real frames: the run
    refuses in one line naming ``--stamps file-order`` and runs with it; the source is found
    from the path (no ``--traj``)."""
    import yaml

    from nap3d_graph.cli import main

    folder = small_copy(tmp_path, frames=6)
    for list_name in ("rgb.txt", "depth.txt"):
        lines = (folder / list_name).read_text().splitlines()
        data = [line.split() for line in lines if line and not line.startswith("#")]
        # Each stamp is the time since the previous frame, as the script writes it.
        (folder / list_name).write_text("".join(f"{0.033 + 0.001 * (k % 2):.6f} {name}\n"
                                                for k, (_, name) in enumerate(data)))
    (folder / "groundtruth.txt").unlink()
    out = tmp_path / "runs"
    assert main(["run", "--data", str(folder), "--field", "none", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "stamps go backwards" in err and "pass --stamps file-order to keep" in err and "\n" not in err, err
    assert main(["run", "--data", str(folder), "--field", "none", "--out", str(out), "--stamps", "file-order"]) == 0
    run = next(p for p in out.iterdir() if p.is_dir() and not p.is_symlink())
    settings = yaml.safe_load((run / "config.yaml").read_text())["settings"]["source"]
    assert settings["traj"] == "tum" and settings["stamps"] == "file-order"
    stamps, _ = read_tum_trajectory(run / "estimate.txt")
    # The intervals' running sum: 33-34 ms apart, as the camera took them.
    assert len(stamps) == 6 and np.all((np.diff(stamps) > 0.0325) & (np.diff(stamps) < 0.0345)), stamps


def test_mixed_sizes_unregistered_depth_and_a_wrong_camera_are_refused_before_any_frame(tmp_path, capsys):
    """Real frames: one colour image of another size, depth of another size than colour, and
    images of another size than the camera each stop the command in one line (exit 2), before
    any frame is read."""
    from nap3d_graph.cli import main

    def shrink(path: Path) -> None:
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(path), cv2.resize(image, (320, 240), interpolation=cv2.INTER_NEAREST))

    mixed = small_copy(tmp_path / "mixed")
    shrink(sorted((mixed / "rgb").glob("*.png"))[2])
    with pytest.raises(DatasetError, match=r"the colour images are of 2 sizes .* mix recordings"):
        TumSequence(mixed)
    unregistered = small_copy(tmp_path / "unregistered")
    for png in (unregistered / "depth").glob("*.png"):
        shrink(png)
    with pytest.raises(DatasetError, match=r"depth is 320x240, colour 640x480: the depth is not registered to colour"):
        TumSequence(unregistered)
    small = small_copy(tmp_path / "small")
    for png in [*(small / "depth").glob("*.png"), *(small / "rgb").glob("*.png")]:
        shrink(png)
    with pytest.raises(DatasetError, match=r"images are 320x240 but the camera \(freiburg1\) is 640x480"):
        TumSequence(small)
    assert main(["map", str(mixed), "--out", str(tmp_path / "map")]) == 2
    err = capsys.readouterr().err.strip()
    assert "mix recordings" in err and "\n" not in err and not (tmp_path / "map").exists()


def test_stamps_that_are_not_a_clock_are_warned_about_and_fps_gives_the_cameras_rate(tmp_path, capsys, caplog):
    """The popular RealSense script's stamps: each frame's processing time (6-15 ms, not the
    33 ms between frames of a 30 Hz camera). Their running sum implies over 100 frames a second,
    which no RGB-D camera has: a warning names ``--fps``; with ``--fps 30`` the frames, in file
    order, are 1/30 s apart, through the library and the command line."""
    import yaml

    from nap3d_graph.cli import main
    from nap3d_graph.datasets import open_sequence

    folder = small_copy(tmp_path, frames=6)
    processing_s = [0.0059, 0.0071, 0.0154, 0.0148, 0.0063, 0.0090]
    for list_name in ("rgb.txt", "depth.txt"):
        lines = (folder / list_name).read_text().splitlines()
        data = [line.split() for line in lines if line and not line.startswith("#")]
        (folder / list_name).write_text("".join(f"{t:.4f} {name}\n" for t, (_, name) in zip(processing_s, data)))
    (folder / "groundtruth.txt").unlink()
    seq = open_sequence(folder, stamps="file-order")
    rate = 1.0 / np.median(np.diff(seq.timestamps))
    assert rate > 100  # what a run would take for the camera's rate without --fps
    assert open_sequence(folder, fps=30).timestamps.tolist() == pytest.approx([i / 30 for i in range(6)])

    out = tmp_path / "runs"
    with caplog.at_level(logging.WARNING, logger="nap3d_graph.datasets.tum"):
        assert main(["run", "--data", str(folder), "--field", "none", "--out", str(out), "--stamps", "file-order"]) == 0
    warned = [r.getMessage() for r in caplog.records if "no RGB-D camera" in r.getMessage()]
    assert warned and "`fps`, e.g. 30" in warned[0] and "frames a second" in warned[0], warned
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="nap3d_graph.datasets.tum"):
        assert main(["run", "--data", str(folder), "--field", "none", "--out", str(out), "--fps", "30"]) == 0
    assert not [r for r in caplog.records if "no RGB-D camera" in r.getMessage()]
    run = sorted(p for p in out.iterdir() if p.is_dir() and not p.is_symlink())[-1]
    assert yaml.safe_load((run / "config.yaml").read_text())["settings"]["source"]["fps"] == 30.0
    stamps, _ = read_tum_trajectory(run / "estimate.txt")
    np.testing.assert_allclose(np.diff(stamps), 1 / 30, atol=1e-6)

    # The two lists must pair line by line.
    (folder / "depth.txt").write_text("".join((folder / "depth.txt").read_text().splitlines(True)[:5]))
    with pytest.raises(DatasetError, match="they list 6 and 5 images"):
        open_sequence(folder, fps=30)
