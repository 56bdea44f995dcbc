"""run --viz: a rerun recording read back with rerun's own reader holds one entry per keyframe."""

from __future__ import annotations

import csv
import sys

import pytest

from nap3d_graph.sims.sequence import SimConfig, simulate_sequence


@pytest.fixture(scope="module")
def sim_dir(tmp_path_factory):
    return simulate_sequence(tmp_path_factory.mktemp("sim") / "room", SimConfig(frames=16, width=160, height=120, seed=5))


@pytest.mark.slow
def test_run_writes_a_rerun_recording_with_every_keyframe(sim_dir, tmp_path):
    from nap3d_graph.cli import main
    from nap3d_graph.run.viz import keyframe_entries

    rrd = tmp_path / "run.rrd"
    assert main(["run", "--traj", "sim", "--data", str(sim_dir), "--field", "oracle", "--odom", "noisy",
                 "--keyframe-every", "2", "--render-size", "160x120", "--out", str(tmp_path / "r"),
                 "--viz", str(rrd)]) == 0
    with open(tmp_path / "r" / "latest" / "corrections.csv") as handle:
        rows = list(csv.DictReader(handle))
    accepted = sum(r["accepted"] in ("True", "1", "true") for r in rows)
    entries = keyframe_entries(rrd)
    assert entries["/keyframes/status"] == len(rows) == 8  # one entry per keyframe, accepted or refused
    assert entries["/keyframes/real"] == len(rows)  # every keyframe was measured (the oracle renders all)
    assert entries["/keyframes/render"] == len(rows) == entries["/keyframes/matches"]
    ellipsoids = {kind: sorted(int(p.rsplit("/", 1)[1]) for p in entries if p.startswith(f"/world/corrections/{kind}/"))
                  for kind in ("accepted", "refused")}
    assert accepted >= 3
    assert ellipsoids["accepted"] == [int(r["frame_index"]) for r in rows if r["accepted"] in ("True", "1", "true")]
    gated = [int(r["frame_index"]) for r in rows if r["reason"].startswith("innovation")]
    assert ellipsoids["refused"] == gated  # measured, then refused by the gate: drawn in the refused colour
    for name in ("odometry", "causal", "smoothed", "truth"):
        assert entries[f"/world/trajectory/{name}"] == 1
    assert entries["/world/camera_causal"] == 16


def test_bad_viz_targets_are_refused_before_the_run(sim_dir, tmp_path, monkeypatch, capsys):
    from nap3d_graph.cli import main

    base = ["run", "--traj", "sim", "--data", str(sim_dir), "--field", "oracle", "--out", str(tmp_path / "r")]
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    cases = {"spawn": "no display here", str(tmp_path / "run.txt"): "ends in .rrd",
             str(tmp_path / "nowhere" / "run.rrd"): "does not exist"}
    if not sys.platform.startswith("linux"):
        cases.pop("spawn")
    for target, message in cases.items():
        assert main([*base, "--viz", target]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0], err
    monkeypatch.setitem(sys.modules, "rerun", None)  # rerun-sdk not installed
    assert main([*base, "--viz", str(tmp_path / "run.rrd")]) == 2
    assert "pip install 'nap3d-graph[viz]'" in capsys.readouterr().err
    assert not (tmp_path / "r").exists() or not any((tmp_path / "r").iterdir()), "refused: nothing written"
