"""Every command of the RealSense owner's walkthrough (docs/usage/8-realsense-walkthrough.md),
run as written on the project's own recordings: two simulated D435i traversals of one room
written through pyrealsense2's recorder (a survey, and a later walk on another path). The
live capture, without a camera here, must say so in one line."""

from __future__ import annotations

import shlex
from pathlib import Path

import pytest

PAGE = Path(__file__).resolve().parents[1] / "docs" / "usage" / "8-realsense-walkthrough.md"


def _commands() -> list[str]:
    """The page's bash block, one command per line (comments dropped)."""
    text = PAGE.read_text()
    block = text.split("```bash\n", 1)[1].split("```", 1)[0]
    return [line.strip() for line in block.splitlines() if line.strip() and not line.lstrip().startswith("#")]


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    from nap3d_graph.cli import main

    root = tmp_path_factory.mktemp("walkthrough")
    for name, seed, count in (("survey", 0, 60), ("walk", 1, 40)):
        assert main(["simulate", str(root / f"{name}_sim"), "--path", "traverse", "--seed", str(seed), "--count",
                     str(count), "--width", "320", "--height", "240", "--realsense", str(root / f"{name}.db3")]) == 0
    return root


@pytest.mark.slow
def test_every_command_of_the_walkthrough_runs_as_written(recordings, monkeypatch, capsys):
    from nap3d_graph.cli import main

    monkeypatch.chdir(recordings)
    commands = _commands()
    assert [c.split()[:2] for c in commands] == [["nap3d-graph", "run"], ["nap3d-graph", "map"], ["nap3d-graph", "run"],
                                                  ["nap3d-graph", "run"], ["cat", "my_map/report.md"]]
    for command in commands:
        words = [w.replace("survey.bag", "survey.db3").replace("walk.bag", "walk.db3") for w in shlex.split(command)]
        if words[0] == "cat":
            for path in words[1:]:
                text = Path(path).read_text()
                assert "| figure | value | good when | verdict |" in text and "BAD" not in text, (path, text)
            continue
        rc = main(words[1:])
        out, err = capsys.readouterr()
        if "live" in words:  # no camera on a test machine: one line, nothing half-written
            assert rc == 2 and "no RealSense camera connected" in err and len(err.strip().splitlines()) == 1, err
            assert not Path("survey.bag").exists()
        elif words[1] == "map":
            assert rc == 0 and "report: my_map/report.md (nothing past its bad line)" in out, out
        else:
            assert rc == 0 and "placed in the map at frame" in out and "(nothing past its bad line)" in out, out
            if "--pace" in words:  # fed at the camera's rate: overlapped, as live
                assert "paced at 1x the camera's rate (overlapped" in out, out
