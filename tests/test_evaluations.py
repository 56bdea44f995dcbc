"""Evaluation K and J: the files, their columns, reproducibility, sane numbers."""

import csv
import json

import numpy as np
import pytest

from nap3d_graph.evaluation.eval_j import EvalJConfig, run_eval_j
from nap3d_graph.evaluation.eval_k import CSV_COLUMNS, EvalKConfig, rmse_3d, run_eval_k
from nap3d_graph.sims.scene import OracleField, Scene
from nap3d_graph.sims.sequence import SimConfig, default_intrinsics, simulate_sequence


@pytest.fixture(scope="module")
def sim_room(tmp_path_factory):
    from nap3d_graph.datasets import TumSequence

    path = simulate_sequence(tmp_path_factory.mktemp("evk") / "seq", SimConfig(frames=12, width=192, height=144,
                                                                                scene_seed=11, seed=3))
    return TumSequence(path), OracleField(Scene.load(path / "scene.json"))


def test_rmse_3d_is_zero_for_the_true_pose_and_grows_with_error():
    from nap3d_graph.conventions import exp_se3

    K = default_intrinsics(64, 48)
    depth = np.full((48, 64), 2.0, np.float32)
    T = np.eye(4)
    assert rmse_3d(depth, K, T, T) == 0.0
    shifted = T @ exp_se3([0, 0, 0, 0.01, 0, 0])
    assert rmse_3d(depth, K, shifted, T) == pytest.approx(0.01, rel=1e-9)
    # A small rotation moves far points more: RMSE grows with depth.
    rot = T @ exp_se3([0, np.radians(1.0), 0, 0, 0, 0])
    assert rmse_3d(depth * 2, K, rot, T) > rmse_3d(depth, K, rot, T)


def test_eval_k_writes_files_and_reproduces(sim_room, tmp_path):
    seq, field = sim_room
    config = EvalKConfig(scenarios=2, seed=4)
    summary = run_eval_k(seq, field, tmp_path / "a", config)
    for name in ("results.csv", "summary.json", "heatmap_rmse_3d_m.png", "heatmap_rot_err_deg.png",
                 "heatmap_trans_err_m.png"):
        assert (tmp_path / "a" / name).stat().st_size > 0
    with open(tmp_path / "a" / "results.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == CSV_COLUMNS
    assert len(rows) == 2 * 16 * 4  # scenarios x cells x methods
    assert {r["intrinsics"] for r in rows} == {"CLEAN", "MILD", "MEDIUM", "HARSH"}
    assert {float(r["blur_sigma"]) for r in rows} == {0.0, 1.0, 1.8, 2.2}
    clean = [r for r in rows if r["intrinsics"] == "CLEAN" and float(r["blur_sigma"]) == 0 and r["method"] == "nap3d"]
    assert all(r["success"] == "True" for r in clean)
    assert max(float(r["trans_err_m"]) for r in clean) < 0.01  # from +-10 cm to millimetres
    cell = summary["cells"]["blur0/CLEAN"]
    assert set(cell["methods"]) == {"nap3d", "nap3d-fixed-k", "nap3d-plain", "pnp"}
    assert cell["methods"]["nap3d"]["success_rate"] == 1.0
    # Wrong intrinsics hurt: HARSH is worse than CLEAN for every method.
    harsh = summary["cells"]["blur0/HARSH"]["methods"]
    for method in ("nap3d-fixed-k", "pnp"):
        if harsh[method]["trans_err_m"]["median"] is not None:
            assert harsh[method]["trans_err_m"]["median"] > cell["methods"][method]["trans_err_m"]["median"]
    # Same seed, same numbers.
    again = run_eval_k(seq, field, tmp_path / "b", config)
    assert json.dumps(again["cells"], sort_keys=True) == json.dumps(summary["cells"], sort_keys=True)
    with open(tmp_path / "b" / "results.csv") as fh:
        rows_b = list(csv.DictReader(fh))
    assert [{k: v for k, v in r.items() if k != "time_s"} for r in rows] == \
        [{k: v for k, v in r.items() if k != "time_s"} for r in rows_b]


def test_eval_k_needs_ground_truth(sim_room, tmp_path):
    seq, field = sim_room

    class NoGT:
        T_world_cam_gt = None
        path = "somewhere"

    with pytest.raises(ValueError, match="ground-truth"):
        run_eval_k(NoGT(), field, tmp_path, EvalKConfig(scenarios=1))


def test_eval_j_tables(sim_room, tmp_path):
    _, field = sim_room
    summary = run_eval_j(field.scene, field, default_intrinsics(320, 240), tmp_path, EvalJConfig(trials_per_sublocation=3))
    text = (tmp_path / "tables.md").read_text()
    assert "A1" in text and "B3" in text and "PnP" in text
    with open(tmp_path / "results.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 2 * 3 * 2
    # The paper's offsets are the first trials.
    a1 = next(r for r in rows if r["trial"] == "A1" and r["method"] == "nap3d")
    assert (float(a1["true_x"]), float(a1["true_z"])) == (-0.12, 0.36)
    for sub in ("A", "B"):
        assert summary[sub]["nap3d"]["success_rate"] == 1.0
        # Offsets up to half a metre recovered to about a centimetre with the exact field.
        assert summary[sub]["nap3d"]["rmse_m"] < 0.02
