"""The one-command study on a tiny simulated recording: it runs end to end and its table is
its files."""

import json

import numpy as np
import pytest

from nap3d_graph.sims.sequence import SimConfig, simulate_sequence


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    path = tmp_path_factory.mktemp("study") / "rec"
    # A survey that comes back over the same room: the first half maps, the second is corrected.
    simulate_sequence(path, SimConfig(frames=60, path="mapping", width=160, height=120, scene_seed=11, seed=7))
    return path


@pytest.mark.slow
def test_study_runs_and_its_table_is_its_files(recording, tmp_path, capsys):
    from nap3d_graph.cli import main

    out = tmp_path / "study"
    assert main(["study", str(recording), "--out", str(out), "--scenarios", "3", "--odom", "vo,noisy",
                 "--keyframe-every", "3", "--train-steps", "300"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    for name in ("field.pt", "field_report.json", "summary.md", "eval_k/results.csv"):
        assert (out / name).is_file(), name
    # The drift runs' figures are their own metrics.json, rounded into the table.
    table = (out / "summary.md").read_text()
    for odom in ("vo", "noisy"):
        run = summary["runs"][odom]
        metrics = json.loads((out / run["folder"] / "metrics.json").read_text())
        assert run["ate_estimate_m"] == pytest.approx(metrics["estimate"]["ate_m"]["rmse"])
        assert run["ate_odometry_m"] == pytest.approx(metrics["odometry"]["ate_m"]["rmse"])
        assert f"| {odom} | {run['ate_odometry_m'] * 100:.2f} cm | {run['ate_estimate_m'] * 100:.2f} cm |" in table
        # The field never saw these frames (300 training steps), and NAP3D still removes a
        # third of the drift or more (measured: noisy 2.61 against 4.05 cm, 0.64x; vo below 0.5x).
        assert run["ate_estimate_m"] < 0.7 * run["ate_odometry_m"], (odom, run["ate_estimate_m"], run["ate_odometry_m"])
    eval_k = summary["eval_k"]["nap3d-selfcal"]
    assert f"| nap3d-selfcal | {eval_k['success_rate'] * 100:.0f}% | {eval_k['trans_median_m'] * 1000:.1f} / " in table
    with open(out / "eval_k" / "results.csv") as fh:
        rows = [line for line in fh.read().splitlines()[1:] if ",nap3d-selfcal," in line]
    assert len(rows) == 3
    field = json.loads((out / "field_report.json").read_text())
    assert summary["field"]["psnr_db"] == pytest.approx(field["held_out"]["psnr_db"])
    assert "study in" in capsys.readouterr().out
    # The field was built on the first half only; the runs used the second half.
    trained = np.array(json.loads((out / "field_report.json").read_text())["train_frames"])
    assert trained.max() < 30


def test_study_refuses_a_bad_split(recording, tmp_path, capsys):
    from nap3d_graph.cli import main

    assert main(["study", str(recording), "--out", str(tmp_path / "s"), "--split", "1.5"]) == 2
    assert "--split must be in" in capsys.readouterr().err


@pytest.mark.slow
def test_cross_recording_study_corrects_one_recording_with_anothers_map(tmp_path, capsys):
    """The product's use case: a map made from one recording (a survey), a robot's other
    recording of the same room (a traversal, another day) corrected with it."""
    from nap3d_graph.cli import main
    from nap3d_graph.datasets import SimSequence
    from nap3d_graph.fields import load_field
    from nap3d_graph.sweep.study import StudyConfig, shared_world_check

    recording = simulate_sequence(tmp_path / "survey", SimConfig(frames=60, path="mapping", width=320, height=240,
                                                                 scene_seed=11, seed=7))
    query = simulate_sequence(tmp_path / "walk", SimConfig(frames=30, fps=6.0, width=320, height=240, scene_seed=11,
                                                           seed=3))
    out = tmp_path / "cross"
    assert main(["study", "--map", str(recording), "--query", str(query), "--out", str(out), "--model", "splat",
                 "--odom", "recorded", "--scenarios", "2", "--keyframe-every", "3"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["query"] == str(query) and summary["shared_world"]["shared"] is True
    assert summary["shared_world"]["median_correction_m"] < 0.03
    run = summary["runs"]["recorded"]  # the walk's own drifting odometry
    assert run["ate_estimate_m"] < 0.6 * run["ate_odometry_m"]
    assert "they share a world frame" in (out / "summary.md").read_text()
    # A recording of another room does not share the map's frame, and is said not to.
    other = SimSequence(simulate_sequence(tmp_path / "elsewhere", SimConfig(frames=6, fps=2.0, width=320, height=240,
                                                                            scene_seed=5, seed=3)))
    assert shared_world_check(load_field(out / "field.pt"), other, StudyConfig())["shared"] is False
    # Usage: --map without --query, or both forms at once, are one-line errors.
    assert main(["study", "--map", str(recording), "--out", str(tmp_path / "x")]) == 2
    assert main(["study", str(recording), "--map", str(recording), "--query", str(query),
                 "--out", str(tmp_path / "y")]) == 2
    assert "--map and --query go together" in capsys.readouterr().err


@pytest.mark.slow
def test_a_study_is_reproduced_from_its_config(recording, tmp_path, capsys):
    """study --config CONFIG.yaml: the recording, frames and settings it wrote come back; flags
    given beside it win; the study's figures are identical."""
    import yaml

    from nap3d_graph.cli import main

    first, again = tmp_path / "first", tmp_path / "again"
    assert main(["study", str(recording), "--out", str(first), "--model", "splat", "--scenarios", "2",
                 "--odom", "noisy", "--keyframe-every", "4", "--split", "0.4", "--seed", "3"]) == 0
    config = yaml.safe_load((first / "config.yaml").read_text())
    study = config["settings"]["study"]
    assert study["split"] == 0.4 and study["odometries"] == ["noisy"] and study["keyframe_every"] == 4
    assert config["settings"]["recordings"]["data"] == str(recording.resolve())
    assert main(["study", "--config", str(first / "config.yaml"), "--out", str(again)]) == 0
    a, b = (json.loads((folder / "summary.json").read_text()) for folder in (first, again))
    assert a["runs"]["noisy"]["ate_estimate_m"] == b["runs"]["noisy"]["ate_estimate_m"]
    assert a["eval_k"] == b["eval_k"] and a["train_frames"] == b["train_frames"] == "0:0.4"
    # A flag beside the file overrides it.
    other = tmp_path / "other"
    assert main(["study", "--config", str(first / "config.yaml"), "--out", str(other), "--keyframe-every", "6"]) == 0
    assert json.loads((other / "summary.json").read_text())["config"]["keyframe_every"] == 6
    assert main(["study", "--config", str(tmp_path / "missing.yaml"), "--out", str(tmp_path / "x")]) == 2
    assert "file not found" in capsys.readouterr().err
