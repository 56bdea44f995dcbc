"""nap3d-graph sweep: the grid, the merged table against the cells' own files, resuming after a
kill, failures recorded after one retry, one folder per cell and per sweep, and Ray."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from nap3d_graph.cli.sweep import check_argv
from nap3d_graph.sims.sensors import DepthNoise
from nap3d_graph.sims.sequence import SimConfig, simulate_sequence
from nap3d_graph.sweep.spec import SweepError, SweepSpec

IDEAL = dict(width=160, height=120, timing=None, exposure=None, depth=DepthNoise(flying_fraction=0.0))


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    root = tmp_path_factory.mktemp("rec")
    walk = simulate_sequence(root / "walk", SimConfig(frames=12, seed=5, **IDEAL))
    other = simulate_sequence(root / "other", SimConfig(frames=12, seed=6, **IDEAL))
    return root, walk, other


def _spec(root: Path, text: str) -> Path:
    path = root / f"sweep_{abs(hash(text)) % 10**8}.yaml"
    path.write_text(text)
    return path


SMALL = """
recordings:
  - {name: walk, map: walk, query: walk}
  - {name: other, map: other, query: other}
field: {model: [oracle, none]}
run: {odom: noisy, keyframe_every: 3, render_size: 160x120, odom_trans_sigma: 0.004, odom_rot_sigma: 0.004}
seeds: [0, 1]
"""


def _rows(folder: Path) -> list[dict]:
    with open(folder / "sweep.csv") as handle:
        return list(csv.DictReader(handle))


def test_spec_grid_and_checks(recordings):
    root = recordings[0]
    spec = SweepSpec.load(_spec(root, SMALL), check_argv)
    assert len(spec.fields()) == 4 and len(spec.cells()) == 8
    assert spec.swept_keys() == ["field.model"]
    ids = [c.id for c in spec.cells()]
    assert len(set(ids)) == len(ids)
    argv = spec.cells()[0].argv(None, Path("out"))
    assert argv[:4] == ["run", "--traj", "sim", "--data"] and "--keyframe-every" in argv and "oracle" in argv
    for bad, message in (("run: {keyframe_evry: 3}", "unrecognized arguments: --keyframe-evry"),
                         ("run: {keyframe_every: 0}", "--keyframe-every"),
                         ("run: {seed: 3}", "seed are set by the sweep"),
                         ("field: {model: [grud]}", "invalid choice: 'grud'"),
                         ("seeds: [a]", "seeds must be a list of integers")):
        with pytest.raises(SweepError, match=message):
            SweepSpec.load(_spec(root, "recordings: [{data: walk}]\n" + bad), check_argv)
    with pytest.raises(SweepError, match="does not exist"):
        SweepSpec.load(_spec(root, "recordings: [{data: nowhere}]"))


@pytest.mark.slow
def test_sweep_table_agrees_with_the_cells_and_fields_are_shared(recordings, tmp_path):
    from nap3d_graph.cli import main

    root = recordings[0]
    spec_path = _spec(root, SMALL.replace("[oracle, none]", "[splat, oracle]"))
    out = tmp_path / "sweep"
    assert main(["sweep", str(spec_path), "--out", str(out), "--workers", "2"]) == 0
    rows = _rows(out)
    assert len(rows) == 8 and all(r["status"] == "ok" for r in rows)
    assert len(list((out / "fields").glob("*.pt"))) == 2  # one per recording: shared by its two seeds
    cells = sorted(p.name for p in (out / "cells").iterdir())
    assert cells == sorted(r["cell"] for r in rows)  # one folder per cell
    for row in rows:
        metrics = json.loads((out / "cells" / row["cell"] / "run" / "latest" / "metrics.json").read_text())
        assert float(row["ate_estimate_cm"]) == pytest.approx(metrics["estimate"]["ate_m"]["rmse"] * 100, abs=1e-3)
        assert int(row["accepted"]) == metrics["corrections_accepted"]
        assert row["command"].startswith("nap3d-graph run --traj sim")
    oracle = [float(r["ate_estimate_cm"]) / float(r["ate_odometry_cm"]) for r in rows if r["field.model"] == "oracle"]
    assert sum(oracle) / len(oracle) < 0.8, oracle  # the exact field removes drift in this grid
    summary = (out / "summary.md").read_text()
    assert "## field.model" in summary and "| oracle | 4 | 0 |" in summary
    assert (out / "plot_field_model.png").stat().st_size > 1000


@pytest.mark.slow
def test_failed_cells_are_retried_once_and_recorded(recordings, tmp_path):
    from nap3d_graph.cli import main

    root = recordings[0]
    # --odom recorded needs the simulator's odometry.txt: the TUM-layout copy below has none (its camera,
    # intrinsics.json, it keeps: without it the folder is refused before the odometry is asked for).
    bare = tmp_path / "bare"
    bare.mkdir()
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt", "rgb", "depth", "intrinsics.json"):
        (bare / name).symlink_to(recordings[1] / name)
    spec_path = _spec(root, f"recordings: [{{data: {bare}}}]\nfield: {{model: none}}\nrun: {{odom: recorded}}\n")
    out = tmp_path / "failing"
    assert main(["sweep", str(spec_path), "--out", str(out), "--workers", "1"]) == 1
    (row,) = _rows(out)
    error = json.loads((out / "cells" / row["cell"] / "error.json").read_text())
    assert row["status"] == "failed" and error["attempts"] == 2
    assert "odometry" in error["error"]
    assert "## Failed cells" in (out / "summary.md").read_text()
    # Resuming does not run a recorded failure again, unless asked to.
    assert main(["sweep", str(spec_path), "--out", str(out)]) == 1
    assert "0 cells run, 1 already finished" in (out / "summary.md").read_text()


def test_one_sweep_per_folder(recordings, tmp_path):
    from nap3d_graph.cli import main

    root = recordings[0]
    out = tmp_path / "locked"
    out.mkdir()
    spec_path = _spec(root, SMALL)
    (out / "sweep.yaml").write_text(spec_path.read_text())
    (out / "sweep.lock").write_text(json.dumps({"host": os.uname().nodename, "pid": os.getpid()}))  # alive
    assert main(["sweep", str(spec_path), "--out", str(out)]) == 2
    other = _spec(root, SMALL.replace("seeds: [0, 1]", "seeds: [7]"))
    assert main(["sweep", str(other), "--out", str(out)]) == 2  # another sweep's folder


@pytest.mark.slow
def test_a_killed_sweep_resumes_with_only_the_unfinished_cells(recordings, tmp_path):
    from nap3d_graph.cli import main

    root = recordings[0]
    spec_path = _spec(root, SMALL.replace("seeds: [0, 1]", "seeds: [0, 1, 2]"))
    out = tmp_path / "killed"
    process = subprocess.Popen([sys.executable, "-m", "nap3d_graph", "sweep", str(spec_path), "--out", str(out),
                                "--workers", "1"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                               start_new_session=True)
    try:
        deadline = time.monotonic() + 300
        while len(list(out.glob("cells/*/result.json"))) < 3 and time.monotonic() < deadline:
            assert process.poll() is None, "the sweep ended before it was killed"
            time.sleep(0.2)
    finally:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait()
    finished = {p.parent.name: p.stat().st_mtime_ns for p in out.glob("cells/*/result.json")}
    assert 3 <= len(finished) < 12
    assert (out / "sweep.lock").is_file()  # left by the killed sweep: taken over
    assert main(["sweep", str(spec_path), "--out", str(out), "--workers", "2"]) == 0
    rows = _rows(out)
    assert len(rows) == 12 and all(r["status"] == "ok" for r in rows)
    for cell, mtime in finished.items():
        assert (out / "cells" / cell / "result.json").stat().st_mtime_ns == mtime, f"{cell} was run again"
    assert f"{12 - len(finished)} cells run, {len(finished)} already finished" in (out / "summary.md").read_text()
    assert not (out / "sweep.lock").exists()


@pytest.mark.slow
def test_ray_sweep_gives_the_pools_table(recordings, tmp_path):
    """A local Ray instance with 2 CPUs runs the cells; the table is the process pool's."""
    from nap3d_graph.cli import main

    root = recordings[0]
    spec_path = _spec(root, SMALL)
    assert main(["sweep", str(spec_path), "--out", str(tmp_path / "pool"), "--workers", "2"]) == 0
    assert main(["sweep", str(spec_path), "--out", str(tmp_path / "ray"), "--workers", "2", "--ray", "auto"]) == 0
    timing = ("seconds",)
    pool, ray = _rows(tmp_path / "pool"), _rows(tmp_path / "ray")
    assert [{k: v for k, v in r.items() if k not in timing and k != "command"} for r in pool] == \
        [{k: v for k, v in r.items() if k not in timing and k != "command"} for r in ray]
    assert "on ray with 2 workers" in (tmp_path / "ray" / "summary.md").read_text()
