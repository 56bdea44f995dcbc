"""The command line under faults: usage mistakes, bad output paths, interruptions, a full
disk, races, and nothing overwritten or dropped by surprise (one row of the faults table each)."""

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from nap3d_graph.cli import main
from nap3d_graph.datasets import DatasetError, TumSequence, read_tum_trajectory


@pytest.fixture(scope="module")
def walk(sim_walk):
    return sim_walk(24, seed=2)


def _cli(capsys, *argv):
    rc = main([str(a) for a in argv])
    # stderr without the progress bars (tqdm redraws with carriage returns)
    lines = capsys.readouterr().err.replace("\r", "\n").splitlines()
    err = "\n".join(line for line in lines if line.strip() and "frame/s" not in line and "it/s" not in line)
    return rc, err


RUN = ("run", "--traj", "sim", "--field", "oracle")


@pytest.mark.parametrize("extra, message", [
    (("--keyframe-every", "0"), "--keyframe-every: must be an integer >= 1, got 0"),
    (("--max-frames", "0"), "--max-frames: must be an integer >= 1"),
    (("--gate-p", "1.5"), "--gate-p: must be a probability in (0, 1), got 1.5"),
    (("--iterations", "0"), "--iterations: must be an integer >= 1"),
    (("--odom-trans-sigma", "-1"), "--odom-trans-sigma: must be a finite number > 0"),
    (("--odom-rot-sigma", "nan"), "--odom-rot-sigma: must be a finite number > 0"),
    (("--vo-width", "0"), "--vo-width: must be an integer >= 1"),
    (("--odom", "dense", "--vo-width", "160"), "--vo-width is for --odom vo, not --odom dense"),
])
def test_usage_mistakes_are_one_line_with_the_range(walk, tmp_path, capsys, extra, message):
    rc, err = _cli(capsys, *RUN, "--data", walk, "--out", tmp_path / "out", *extra)
    assert rc == 2 and message in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "out").exists()  # nothing computed, nothing written


def test_bad_output_paths_are_refused_before_any_work(walk, tmp_path, capsys):
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    for out, message in ((a_file, "is a file"), (a_file / "sub", "not writable")):
        started = time.perf_counter()
        rc, err = _cli(capsys, *RUN, "--data", walk, "--out", out)
        assert rc == 2 and message in err and len(err.splitlines()) == 1, err
        assert time.perf_counter() - started < 20  # checked first: no run happened
    rc, err = _cli(capsys, "train-field", walk, "--out", a_file / "f.pt", "--steps", "5")
    assert rc == 2 and "is a file" in err


def test_a_read_only_output_folder_is_refused_before_any_work(walk, tmp_path, capsys, monkeypatch):
    """A folder the run may not write into: a one-line error before any work. As a user the
    folder is made read-only; root writes anywhere, so there the OS's refusal is simulated
    where the check writes its probe file (the same code path, the same error)."""
    import tempfile

    read_only = tmp_path / "ro"
    read_only.mkdir(mode=0o555)
    if os.geteuid() == 0:
        real_mkstemp = tempfile.mkstemp

        def refuse_here(*args, dir=None, **kwargs):
            if dir is not None and Path(dir).resolve() == read_only.resolve():
                raise PermissionError(errno.EACCES, "Permission denied", str(dir))
            return real_mkstemp(*args, dir=dir, **kwargs)

        monkeypatch.setattr(tempfile, "mkstemp", refuse_here)
    rc, err = _cli(capsys, *RUN, "--data", walk, "--out", read_only)
    assert rc == 2 and "not writable (Permission denied)" in err and len(err.splitlines()) == 1, err
    assert list(read_only.iterdir()) == []


def test_wrong_sources_say_what_to_use(walk, tum_path, tmp_path, capsys):
    rc, err = _cli(capsys, "run", "--traj", "tum", "--data", tum_path, "--field", "none", "--odom", "recorded",
                   "--out", tmp_path)
    assert rc == 2 and "use --odom noisy or --odom vo" in err
    no_gt = tmp_path / "no_gt"
    shutil.copytree(tum_path, no_gt)
    (no_gt / "groundtruth.txt").unlink()
    rc, err = _cli(capsys, "run", "--traj", "tum", "--data", no_gt, "--field", "none", "--odom", "noisy",
                   "--out", tmp_path)
    assert rc == 2 and "use --odom vo" in err
    # Odometry alone on a camera without ground truth has no map to be placed in: it starts at
    # the identity and says so (issue 42), rather than asking for a pose nobody has.
    assert main(["run", "--traj", "tum", "--data", str(no_gt), "--field", "none", "--odom", "vo", "--matcher", "sift",
                 "--out", str(tmp_path / "odometry_only")]) == 0
    assert "start: the identity" in capsys.readouterr().out
    rc, err = _cli(capsys, "eval-k", walk, "--field", "oracle", "--scenarios", "0", "--out", tmp_path)
    assert rc == 2 and "--scenarios" in err
    broken = tmp_path / "broken_sim"
    shutil.copytree(walk, broken)
    (broken / "scene.json").write_text("{not json")
    rc, err = _cli(capsys, *RUN, "--data", broken, "--out", tmp_path / "o")
    assert rc == 2 and "scene.json" in err and len(err.splitlines()) == 1, err


def test_nothing_is_overwritten_without_force(walk, tum_path, tmp_path, capsys):
    real = tmp_path / "real_tum"
    shutil.copytree(tum_path, real)
    before = {p.name: p.stat().st_mtime_ns for p in real.iterdir()}
    rc, err = _cli(capsys, "simulate", real, "--count", "4", "--width", "64", "--height", "48")
    assert rc == 2 and "not empty" in err and "--force" in err
    assert {p.name: p.stat().st_mtime_ns for p in real.iterdir()} == before
    ns = tmp_path / "ns"
    ns.mkdir()
    (ns / "keep.txt").write_text("mine")
    rc, err = _cli(capsys, "export-nerfstudio", walk, ns)
    assert rc == 2 and (ns / "keep.txt").read_text() == "mine"


def test_frames_without_ground_truth_stay_in_the_run(tum_path, tmp_path, capsys):
    """Ground truth covering only the first frames: every frame keeps its pose and its
    rgb.txt line index; the frames without truth are named in a warning."""
    partial = tmp_path / "partial_gt"
    shutil.copytree(tum_path, partial)
    seq = TumSequence(tum_path)
    lines = [line for line in (partial / "groundtruth.txt").read_text().splitlines()
             if line.startswith("#") or float(line.split()[0]) <= seq.timestamps[7] + 0.02]
    (partial / "groundtruth.txt").write_text("\n".join(lines) + "\n")
    rc, err = _cli(capsys, "run", "--traj", "tum", "--data", partial, "--field", "none", "--odom", "vo",
                   "--out", tmp_path / "out")
    assert rc == 0, err
    stamps, _ = read_tum_trajectory(tmp_path / "out" / "latest" / "estimate.txt")
    assert len(stamps) == len(seq)
    gt_stamps, _ = read_tum_trajectory(tmp_path / "out" / "latest" / "groundtruth.txt")
    assert 7 <= len(gt_stamps) < len(seq)


def test_run_folders_created_at_the_same_moment_never_collide(tmp_path):
    from nap3d_graph.run.output import new_run_dir

    made, errors = [], []
    barrier = threading.Barrier(16, timeout=30)

    def create():
        barrier.wait()
        try:
            made.append(new_run_dir(tmp_path, "sim"))
        except OSError as exc:
            errors.append(exc)

    threads = [threading.Thread(target=create) for _ in range(16)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors and len(set(made)) == 16


@pytest.mark.slow
def test_a_full_disk_mid_run_is_one_line_and_keeps_what_was_written(walk, tmp_path, capsys, monkeypatch):
    from nap3d_graph.run.output import RunWriter

    original = RunWriter.add_keyframe
    calls = {"n": 0}

    def add_keyframe(self, record):
        calls["n"] += 1
        if calls["n"] > 3:
            raise OSError(errno.ENOSPC, "No space left on device", str(self.dir / "corrections.csv"))
        original(self, record)

    monkeypatch.setattr(RunWriter, "add_keyframe", add_keyframe)
    rc, err = _cli(capsys, *RUN, "--data", walk, "--keyframe-every", "3", "--out", tmp_path)
    assert rc == 2 and "No space left on device" in err and len(err.splitlines()) == 1, err
    run = next(p for p in tmp_path.iterdir() if p.is_dir() and p.name != "latest")
    assert (run / "config.yaml").is_file()
    assert len((run / "corrections.csv").read_text().splitlines()) == 1 + 3


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
@pytest.mark.slow
def test_an_interrupted_run_leaves_its_config_corrections_and_partial_trajectories(walk, tmp_path, sig):
    out = tmp_path / "out"
    env = dict(os.environ, MPLBACKEND="Agg", PYTHONUNBUFFERED="1")
    proc = subprocess.Popen([sys.executable, "-m", "nap3d_graph.cli", *RUN, "--data", str(walk), "--keyframe-every",
                             "1", "--iterations", "3", "--out", str(out)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, env=env)
    deadline = time.monotonic() + 240
    corrections = None
    while time.monotonic() < deadline and proc.poll() is None:
        found = list(out.glob("*/corrections.csv")) if out.exists() else []
        if found and len(found[0].read_text().splitlines()) >= 4:  # header + 3 keyframes
            corrections = found[0]
            break
        time.sleep(0.2)
    assert corrections is not None and proc.poll() is None, "the run ended before it could be interrupted"
    proc.send_signal(sig)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130, stderr.decode()[-500:]
    run = corrections.parent
    assert (run / "config.yaml").is_file()
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["partial"] is True and 3 <= metrics["frames"] < 24
    from evo.tools import file_interface

    trajectory = file_interface.read_tum_trajectory_file(str(run / "estimate.txt"))
    assert trajectory.num_poses == metrics["frames"] and np.all(np.isfinite(trajectory.positions_xyz))
    assert len(corrections.read_text().splitlines()) - 1 >= 3


@pytest.mark.slow
def test_simulate_stops_at_once_on_sigint(tmp_path):
    """Its worker pool shuts down with it: no hang after 'interrupted'."""
    env = dict(os.environ, MPLBACKEND="Agg")
    for trial in range(3):
        out = tmp_path / f"sim{trial}"
        proc = subprocess.Popen([sys.executable, "-m", "nap3d_graph.cli", "simulate", str(out), "--count", "400",
                                 "--width", "320", "--height", "240"], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, env=env)
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None and not list(out.glob("rgb/*.png")):
            time.sleep(0.1)  # until the workers are rendering
        assert proc.poll() is None, "simulate ended before it could be interrupted"
        proc.send_signal(signal.SIGINT)
        try:
            proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            pytest.fail(f"simulate still running 60 s after SIGINT (trial {trial})")
        assert proc.returncode == 130
        # The folder says it is partial, is refused as data, and is redone only with --force.
        assert (out / "PARTIAL.txt").is_file() and not (out / "rgb.txt").exists()
        with pytest.raises(DatasetError, match="did not finish"):
            TumSequence(out)
        assert main(["simulate", str(out), "--count", "3", "--width", "64", "--height", "48"]) == 2
        assert main(["simulate", str(out), "--count", "3", "--width", "64", "--height", "48", "--force"]) == 0
        assert not (out / "PARTIAL.txt").exists() and len(TumSequence(out)) == 3
