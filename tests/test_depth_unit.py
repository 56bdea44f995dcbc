"""The depth unit is checked before a field is built: millimetre PNGs read at TUM's 5000 per
metre (every depth 5x short) stop ``train-field`` at once, with the factor, instead of a
warning after a whole field was trained."""

from __future__ import annotations

import shutil

import cv2
import numpy as np
import pytest

from nap3d_graph.datasets import open_sequence
from nap3d_graph.datasets.depth_unit import check_depth_unit
from nap3d_graph.sims.faults import ScaledDepth


@pytest.fixture(scope="module")
def walk(sim_walk):
    return sim_walk(40)


def _with_depth_times(src, dst, factor: float):
    """A copy of the TUM-layout folder ``src`` whose depth PNGs hold ``factor`` x their values."""
    shutil.copytree(src, dst)
    for png in (dst / "depth").glob("*.png"):
        raw = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(png), np.clip(np.rint(raw * factor), 0, 65535).astype(np.uint16))
    return dst


def test_the_right_unit_and_the_two_tum_mistakes_are_told_apart(walk, tmp_path):
    right = check_depth_unit(open_sequence(walk))
    assert right is not None and right.scale == 1.0 and right.mistake is None and right.pairs >= 3
    assert right.disagreement[1.0] < 0.5 * min(v for s, v in right.disagreement.items() if s != 1.0 and np.isfinite(v))
    millimetres = check_depth_unit(open_sequence(_with_depth_times(walk, tmp_path / "mm", 0.2)))
    assert millimetres.scale == 5.0 and "x5 = 5000/1000" in millimetres.message()
    # TUM's PNGs read at 1000 per metre: 5x long (scaled on reading: x5 would overflow uint16 PNGs).
    sequence = open_sequence(walk)
    fifths = check_depth_unit(ScaledDepth(sequence, {i: 5.0 for i in range(len(sequence))}))
    assert fifths.scale == 0.2 and "x0.2 = 1000/5000" in fifths.message()


@pytest.mark.slow
def test_train_field_stops_before_training_and_trains_when_told(walk, tmp_path, capsys):
    from nap3d_graph.cli import main

    folder = _with_depth_times(walk, tmp_path / "mm", 0.2)
    out = tmp_path / "f.pt"
    rc = main(["train-field", str(folder), "--model", "splat", "--out", str(out), "--quiet", "--no-field-error"])
    err = capsys.readouterr().err
    assert rc == 2 and "looks like millimetres read at TUM's 5000 per metre (x5 = 5000/1000)" in err, err
    assert "--depth-unit trust" in err and len(err.strip().splitlines()) == 1 and not out.exists()
    assert main(["train-field", str(folder), "--model", "splat", "--out", str(out), "--quiet", "--no-field-error",
                 "--depth-unit", "trust"]) == 0
    assert out.is_file()


def test_a_sequence_without_poses_is_not_checked(walk):
    class Unposed:
        T_world_cam_gt = None

    assert check_depth_unit(Unposed()) is None


# --- without poses: the three unit mistakes on real recordings, before any work --------------

def _tum_as_millimetres(src, dst, every: int = 1):
    """A copy of TUM frames ``src`` whose depth PNGs (every ``every``-th) hold millimetres, as a
    Kinect's driver and 7-Scenes store them (TUM's values / 5)."""
    shutil.copytree(src, dst)
    for k, png in enumerate(sorted((dst / "depth").glob("*.png"))):
        if k % every == 0:
            raw = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
            cv2.imwrite(str(png), np.rint(raw / 5.0).astype(np.uint16))
    return dst


def _bag_as_tum_folder(bag, dst, ):
    """The D435 recording's frame written as a recording script writes it: TUM layout, depth in
    millimetres, the camera in intrinsics.json, two frames."""
    import json

    frame = open_sequence(bag)[0]
    (dst / "rgb").mkdir(parents=True)
    (dst / "depth").mkdir()
    for k in range(2):
        cv2.imwrite(str(dst / f"rgb/{k}.png"), frame.rgb[..., ::-1])
        cv2.imwrite(str(dst / f"depth/{k}.png"), np.rint(frame.depth_m * 1000).astype(np.uint16))
    (dst / "rgb.txt").write_text("0.0 rgb/0.png\n0.2 rgb/1.png\n")
    (dst / "depth.txt").write_text("0.0 depth/0.png\n0.2 depth/1.png\n")
    K = frame.intrinsics
    (dst / "intrinsics.json").write_text(json.dumps({"fx": K.fx, "fy": K.fy, "cx": K.cx, "cy": K.cy,
                                                     "width": K.width, "height": K.height}))
    return dst


def _look(path, **kwargs):
    from nap3d_graph.datasets.depth_unit import inspect_depth_unit

    return inspect_depth_unit(open_sequence(path, **kwargs))


def test_the_three_unit_mistakes_are_told_from_the_depth_alone_and_the_recordings_as_they_are_pass(tum_path,
                                                                                                   tmp_path):
    from conftest import DATA

    from nap3d_graph.datasets.sevenscenes import write_sevenscenes_frame

    # As they are: TUM's PNGs, a D435 recording (its own units), a Kinect's millimetres.
    tum = _look(tum_path)
    assert tum.warnings == () and tum.mixed is None and 0.5 < tum.median_m < 2.0
    assert all(abs(u / 5000 - 1) < 0.03 for u in tum.kinect_units_per_m)  # Kinect v1's steps at TUM's unit
    bag = DATA / "realsense" / "single_depth_color_640x480.bag"
    assert _look(bag).warnings == ()
    d435 = _bag_as_tum_folder(bag, tmp_path / "d435")
    assert _look(d435, depth_scale=1000).warnings == ()
    mm = _tum_as_millimetres(tum_path, tmp_path / "freiburg1_mm")
    assert _look(mm, depth_scale=1000).warnings == ()
    # TUM read as millimetres: 5x too far, told by the Kinect's steps (the range is plausible).
    (line,) = _look(tum_path, depth_scale=1000).warnings
    assert "Kinect v1's at 5000 units per metre, but it is read at 1000" in line and "x5 (too far)" in line
    # Millimetres read as TUM: the D435's by its range, the Kinect's by its steps.
    (line,) = _look(d435).warnings
    assert "nearer than 0.2 m" in line and "declare depth_scale 1000" in line
    near, steps = _look(mm).warnings  # fr1/xyz's desk at 0.9 m: 0.18 m read this way
    assert "nearer than 0.2 m" in near
    assert "Kinect v1's at 1000 units per metre, but it is read at 5000" in steps and "x0.2 (too near)" in steps
    # 7-Scenes (a Kinect's millimetres in its layout) read at 5000.
    sequence = open_sequence(tum_path)
    for k in range(0, 12, 2):
        frame = sequence[k]
        write_sevenscenes_frame(tmp_path / "7s", k, frame.rgb, frame.depth_m, np.eye(4))
    assert _look(tmp_path / "7s", registration="none").warnings == ()
    assert any("at 1000 units per metre, but it is read at 5000" in line
               for line in _look(tmp_path / "7s", registration="none", depth_scale=5000).warnings)


def test_a_folder_that_mixes_units_is_refused_in_one_line(tum_path, tmp_path, capsys):
    from nap3d_graph.cli import main

    mixed = _tum_as_millimetres(tum_path, tmp_path / "freiburg1_mixed", every=2)
    look = _look(mixed)
    assert look.mixed is not None and "different units" in look.mixed
    rc = main(["map", str(mixed), "--out", str(tmp_path / "map"), "--no-field", "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and "different units" in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "map").exists()


def test_a_declared_unit_is_read_and_a_wrong_one_refused(tum_path, tmp_path, capsys):
    import json

    from conftest import DATA

    from nap3d_graph.cli import main
    from nap3d_graph.datasets import DatasetError

    mm = _tum_as_millimetres(tum_path, tmp_path / "freiburg1_mm")
    (mm / "intrinsics.json").write_text(json.dumps({"fx": 517.3, "fy": 516.5, "cx": 318.6, "cy": 255.3,
                                                   "width": 640, "height": 480, "depth_scale": 1000}))
    declared, tum = open_sequence(mm), open_sequence(tum_path)
    assert declared.depth_units_per_m == 1000 and declared.depth_scale_source == "intrinsics.json"
    a, b = declared[3].depth_m, tum[3].depth_m
    both = (a > 0) & (b > 0)
    assert np.abs(a[both] - b[both]).max() <= 0.0006  # the same metres, to the millimetre's rounding
    assert open_sequence(mm, depth_scale=5000).depth_units_per_m == 5000  # the argument wins
    with pytest.raises(DatasetError, match="looks like metres per unit .* write 1000"):
        open_sequence(mm, depth_scale=0.001)
    rc = main(["map", str(DATA / "realsense" / "single_depth_color_640x480.bag"), "--depth-scale", "1000",
               "--out", str(tmp_path / "m"), "--no-field"])
    err = capsys.readouterr().err
    assert rc == 2 and "--depth-scale is for folders of depth PNGs" in err and "carries its own depth units" in err
