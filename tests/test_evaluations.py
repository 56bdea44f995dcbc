"""Evaluation K and J: the files, their columns, reproducibility, sane numbers."""

import csv
import json

import numpy as np
import pytest

from nap3d_graph.evaluation.eval_j import EvalJConfig, run_eval_j
from nap3d_graph.evaluation.eval_k import CSV_COLUMNS, DEFAULT_METHODS, EvalKConfig, rmse_3d, run_eval_k
from nap3d_graph.sims.scene import OracleField, Scene
from nap3d_graph.sims.sequence import SimConfig, default_intrinsics, simulate_sequence


@pytest.fixture(scope="module")
def sim_room(tmp_path_factory):
    from nap3d_graph.datasets import TumSequence

    # Twelve frames one second apart along a traversal (a walking pace), from a camera that
    # takes colour and depth at the same instant: these tests check the protocol's files and
    # figures, not a sensor's timing (which the field and pipeline tests cover).
    path = simulate_sequence(tmp_path_factory.mktemp("evk") / "seq", SimConfig(frames=12, width=192, height=144,
                                                                                scene_seed=11, seed=3, fps=1.0,
                                                                                timing=None))
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


@pytest.mark.slow
def test_eval_k_writes_files_and_reproduces(sim_room, tmp_path):
    seq, field = sim_room
    config = EvalKConfig(scenarios=2, seed=4)
    summary = run_eval_k(seq, field, tmp_path / "a", config)
    for name in ("results.csv", "summary.json", "table.md", "fig4_paper_pnp_vs_nap3d-plain.png",
                 "heatmap_refined_pnp_vs_nap3d-refined.png", "heatmap_selfcal_pnp-selfcal_vs_nap3d-selfcal.png"):
        assert (tmp_path / "a" / name).stat().st_size > 0
    with open(tmp_path / "a" / "results.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == CSV_COLUMNS
    assert len(rows) == 2 * 16 * 5  # scenarios x cells x methods
    assert {r["intrinsics"] for r in rows} == {"CLEAN", "MILD", "MEDIUM", "HARSH"}
    assert {float(r["blur_sigma"]) for r in rows} == {0.0, 1.0, 1.8, 2.2}
    assert {r["method"] for r in rows} == set(DEFAULT_METHODS)
    # Every row has errors, failures included (scored as the uncorrected pose).
    assert all(r["trans_err_m"] != "" and r["rot_err_deg"] != "" for r in rows)
    clean = [r for r in rows if r["intrinsics"] == "CLEAN" and float(r["blur_sigma"]) == 0]
    for method in ("nap3d-plain", "nap3d-refined", "nap3d-selfcal", "pnp"):
        mine = [r for r in clean if r["method"] == method]
        assert all(r["success"] == "True" for r in mine), method
        assert max(float(r["trans_err_m"]) for r in mine) < 0.01, method  # from +-10 cm to millimetres
        assert all(float(r["nees"]) > 0 for r in mine)
    cell = summary["cells"]["blur0/CLEAN"]
    assert set(cell["methods"]) == set(DEFAULT_METHODS)
    assert set(cell["pairs"]) == {"paper", "refined", "selfcal"}
    assert (cell["pairs"]["paper"]["pnp_side"], cell["pairs"]["paper"]["nap3d_side"]) == ("pnp", "nap3d-plain")
    for stats in cell["methods"]["nap3d-selfcal"]["trans_err_m"], cell["methods"]["pnp"]["rot_err_deg"]:
        assert stats["median"] <= stats["p90"] <= stats["max"] and stats["mean"] <= stats["max"]
    assert cell["methods"]["nap3d-selfcal"]["success_rate"] == 1.0
    # Wrong intrinsics hurt the methods that trust them (HARSH: x1.10 focal, +10 px); the
    # self-calibrating ones recognise the wrong calibration and estimate it.
    harsh = summary["cells"]["blur0/HARSH"]["methods"]
    for method in ("nap3d-refined", "nap3d-plain", "pnp"):
        assert harsh[method]["trans_err_m"]["median"] > 3 * cell["methods"][method]["trans_err_m"]["median"], method
    assert harsh["nap3d-selfcal"]["calibrated_share"] == 1.0 and cell["methods"]["nap3d-selfcal"]["calibrated_share"] == 0
    assert harsh["nap3d-selfcal"]["trans_err_m"]["median"] < harsh["nap3d-refined"]["trans_err_m"]["median"]
    # The table has a line per cell and method.
    table = (tmp_path / "a" / "table.md").read_text()
    assert table.count("| blur0/CLEAN |") == 5 and "nap3d-selfcal" in table
    # Same seed, same numbers.
    again = run_eval_k(seq, field, tmp_path / "b", config)
    assert json.dumps(again["cells"], sort_keys=True) == json.dumps(summary["cells"], sort_keys=True)
    with open(tmp_path / "b" / "results.csv") as fh:
        rows_b = list(csv.DictReader(fh))
    assert [{k: v for k, v in r.items() if k != "time_s"} for r in rows] == \
        [{k: v for k, v in r.items() if k != "time_s"} for r in rows_b]


def test_eval_k_failure_counts_as_uncorrected(sim_room, tmp_path):
    """A field that renders nothing: every method fails, and every row scores the error of
    the perturbed pose it could not correct (not a missing value that flatters the mean)."""
    from nap3d_graph.camera import RenderedView

    seq, field = sim_room

    class Blank:
        def render(self, T, K):
            view = field.render(T, K)
            return RenderedView(view.rgb, view.depth_m, np.zeros_like(view.opacity), K)

    config = EvalKConfig(scenarios=2, seed=4, blur_sigmas=(0.0,), intrinsics_noise={"CLEAN": (1.0, 0.0)})
    summary = run_eval_k(seq, Blank(), tmp_path, config)
    with open(tmp_path / "results.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert all(r["success"] == "False" and "opacity" in r["reason"] for r in rows)
    # The perturbations are up to 10 cm per axis and 5 deg: the scored errors are that size.
    assert all(0.005 < float(r["trans_err_m"]) < 0.18 for r in rows)
    stats = summary["cells"]["blur0/CLEAN"]["methods"]["nap3d-plain"]
    assert stats["success_rate"] == 0.0 and stats["trans_err_m"]["median"] > 0.005
    assert stats["nees"]["mean"] is None


def test_eval_k_shift_on_both_cameras(sim_room, tmp_path):
    seq, field = sim_room
    config = EvalKConfig(scenarios=1, seed=4, blur_sigmas=(0.0,), shift="both",
                         methods=("nap3d-plain", "pnp", "nap3d-selfcal"))
    summary = run_eval_k(seq, field, tmp_path, config)
    assert summary["config"]["shift"] == "both"
    clean = summary["cells"]["blur0/CLEAN"]["methods"]["nap3d-selfcal"]["trans_err_m"]["median"]
    harsh = summary["cells"]["blur0/HARSH"]["methods"]["nap3d-plain"]["trans_err_m"]["median"]
    assert clean < 0.005 and harsh > clean  # both cameras told a wrong calibration: still hurts the plain fit
    with pytest.raises(ValueError, match="shift"):
        EvalKConfig(shift="left")


def test_eval_k_pnp_calibrated_is_the_pnp_at_its_best(sim_room, tmp_path):
    """``pnp-calibrated`` estimates the real camera's intrinsics at every frame (not only when
    NAP3D's test on pixels calls for it, as ``pnp-selfcal``): with a wrong calibration it beats
    the plain PnP and the one that calibrates only when the test calls for it, every row says
    it calibrated, and it is compared with nap3d-selfcal."""
    seq, field = sim_room
    methods = ("pnp", "pnp-selfcal", "pnp-calibrated", "nap3d-selfcal")
    noise = {"CLEAN": (1.0, 0.0), "MILD": (1.03, 2.0), "HARSH": (1.10, 10.0)}
    config = EvalKConfig(scenarios=8, seed=4, blur_sigmas=(0.0,), intrinsics_noise=noise, methods=methods)
    assert "pnp-calibrated" not in DEFAULT_METHODS  # selected, not a default: the default tables keep their size
    summary = run_eval_k(seq, field, tmp_path, config)
    with open(tmp_path / "results.csv") as fh:
        rows = [r for r in csv.DictReader(fh) if r["method"] == "pnp-calibrated"]
    assert len(rows) == 8 * 3 and all(r["success"] == "True" for r in rows)
    # Calibrated at every frame, the CLEAN cell's too (where pnp-selfcal keeps the given model).
    assert {r["intrinsics_model"] for r in rows} == {"calibrated"}
    cells = summary["cells"]
    assert cells["blur0/CLEAN"]["methods"]["pnp-selfcal"]["calibrated_share"] == 0
    for name in ("MILD", "HARSH"):
        mine = cells[f"blur0/{name}"]["methods"]
        assert mine["pnp-calibrated"]["calibrated_share"] == 1.0
        # A wrong calibration costs the PnP that trusts it tens of mm; calibrating at every
        # frame recovers a good part of that, which pnp-selfcal's test may leave on the table.
        calibrated = mine["pnp-calibrated"]["trans_err_m"]["median"]
        assert calibrated < 0.75 * mine["pnp"]["trans_err_m"]["median"], name
        assert calibrated < 0.75 * mine["pnp-selfcal"]["trans_err_m"]["median"], name
    pair = cells["blur0/HARSH"]["pairs"]["calibrated"]
    assert (pair["pnp_side"], pair["nap3d_side"], pair["pairs"]) == ("pnp-calibrated", "nap3d-selfcal", 8)
    assert summary["pairs"]["calibrated"] == {"pnp_side": "pnp-calibrated", "nap3d_side": "nap3d-selfcal"}
    assert (tmp_path / "heatmap_calibrated_pnp-calibrated_vs_nap3d-selfcal.png").stat().st_size > 0
    assert (tmp_path / "table.md").read_text().count("| pnp-calibrated |") == 3
    # The file says how it was made: the settings it ran with, the command, the commit.
    import json

    record = json.loads((tmp_path / "summary.json").read_text())["provenance"]
    assert record["settings"]["scenarios"] == 8 and "pnp-calibrated" in record["settings"]["methods"]
    assert set(record) == {"commit", "command", "settings", "written"} and record["command"]


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
    assert len(rows) == 2 * 3 * 3  # sublocations x trials x methods
    # The paper's offsets are the first trials.
    a1 = next(r for r in rows if r["trial"] == "A1" and r["method"] == "nap3d")
    assert (float(a1["true_x"]), float(a1["true_z"])) == (-0.12, 0.36)
    assert "as in the paper" in text
    for sub in ("A", "B"):
        assert summary[sub]["nap3d-plain"]["success_rate"] == 1.0 and summary[sub]["nap3d-plain"]["rmse_m"] < 0.03
        assert summary[sub]["nap3d"]["success_rate"] == 1.0
        # Offsets up to half a metre recovered to about a centimetre with the exact field.
        assert summary[sub]["nap3d"]["rmse_m"] < 0.02


def test_eval_k_moves_each_depth_to_its_colour_instant(tmp_path):
    """A Kinect-like camera (depth captured 30 ms before colour) moving at walking pace: as
    stamped, a scenario's depth is centimetres from the colour camera's geometry, and a 3D-3D
    method would measure that; moved to the colour's instant with the true timing it agrees
    with the room rendered at the colour pose to the sensor's noise."""
    from nap3d_graph.datasets import SimSequence
    from nap3d_graph.evaluation.eval_k import at_colour_instant

    seq = SimSequence(simulate_sequence(tmp_path / "kinect", SimConfig(frames=16, width=160, height=120,
                                                                      scene_seed=11, seed=3, fps=15.0)))
    capture = np.asarray(seq.config["depth_capture_stamps"])
    timing = {"depth_offset_s": float(np.mean(capture - seq.depth_timestamps)), "colour_offset_s": 0.0}
    stamped, moved = [], []
    for i in range(2, 14):
        truth = seq.scene.render_depth(seq.T_world_cam_gt[i], seq.intrinsics)
        for frame, errors in ((seq[i], stamped), (at_colour_instant(seq, i, timing), moved)):
            ok = (frame.depth_m > 0) & (truth > 0)
            errors.append(np.median(np.abs(frame.depth_m - truth)[ok]))
    assert np.median(moved) < 0.5 * np.median(stamped), (np.median(moved), np.median(stamped))
    assert at_colour_instant(seq, 5, None) is not None and np.array_equal(at_colour_instant(seq, 5, None).depth_m,
                                                                         seq[5].depth_m)


def test_survey_alignment_reports_orientation_errors_and_their_common_part():
    """A trajectory whose every camera is turned by the same 1.15 deg (a reference's
    camera-to-marker offset) in another frame: after the SE(3) alignment its orientation
    errors are that turn, nearly all of it common to every frame; a trajectory turned at
    random has no common part."""
    from nap3d_graph.conventions import exp_se3
    from nap3d_graph.evaluation.alignment import aligned_errors

    rng = np.random.default_rng(0)
    T_ref = np.stack([exp_se3(rng.normal(size=6) * [0.3, 0.3, 0.3, 1.0, 1.0, 1.0]) for _ in range(50)])
    T_other_ref = exp_se3(np.array([0.1, 0.2, 0.3, 1.0, 2.0, 3.0]))
    turn = exp_se3(np.array([0.02, 0.0, 0.0, 0.0, 0.0, 0.0]))
    fixed = aligned_errors(np.arange(50.0), T_ref, T_other_ref @ T_ref @ turn).summary()
    assert 0.9 < fixed["rotation_median_deg"] < 1.2 and fixed["rotation_common_deg"] > 0.9
    T_random = np.stack([T @ exp_se3(np.r_[rng.normal(size=3) * 0.02, 0.0, 0.0, 0.0]) for T in T_ref])
    scattered = aligned_errors(np.arange(50.0), T_ref, T_other_ref @ T_random).summary()
    assert scattered["rotation_median_deg"] > 1.0 and scattered["rotation_common_deg"] < 0.4


def test_a_result_made_outside_a_checkout_names_the_commit_it_was_given(tmp_path, monkeypatch):
    """A copy of the checkout without its .git records the commit named in
    NAP3D_GRAPH_COMMIT; a git checkout records its own and ignores the variable."""
    from nap3d_graph import provenance as prov

    monkeypatch.setenv("NAP3D_GRAPH_COMMIT", "0123456789ab")
    own = prov.provenance()["commit"]
    assert own is not None and own.split("+")[0] != "0123456789ab"
    monkeypatch.setattr(prov, "ROOT", tmp_path)
    assert prov.provenance()["commit"] == "0123456789ab"
    monkeypatch.delenv("NAP3D_GRAPH_COMMIT")
    assert prov.provenance()["commit"] is None
