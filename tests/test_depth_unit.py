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
