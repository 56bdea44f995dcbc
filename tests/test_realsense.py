"""RealSense recordings: written offline through pyrealsense2, read back at the sensor level,
registered depth, the drift-correction run on a recording, and the one-line errors."""

import dataclasses
import json
import logging

import numpy as np
import pytest
import yaml
from conftest import DATA

from nap3d_graph.camera import Intrinsics
from nap3d_graph.cli import main
from nap3d_graph.conventions import T_to_tum
from nap3d_graph.datasets import RealSenseRecording, SimSequence, open_sequence, read_tum_trajectory
from nap3d_graph.datasets.realsense_io import RecordingWriter, StreamIntrinsics, read_recording
from nap3d_graph.datasets.realsense_sim import write_realsense_recording
from nap3d_graph.errors import DatasetError
from nap3d_graph.sims.sequence import SimConfig, simulate_sequence

SMALL = StreamIntrinsics(64, 48, 52.0, 51.0, 31.5, 23.5)


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    """A 36-frame traversal at 6 Hz with a 200 Hz IMU, and two recordings of it: with the
    simulator's depth noise, and without (for the registration's geometry)."""
    root = tmp_path_factory.mktemp("rs")
    sim = simulate_sequence(root / "walk", SimConfig(frames=36, fps=6.0, width=192, height=144, scene_seed=11,
                                                     seed=4, timing=None), workers=1)
    noisy = write_realsense_recording(sim, root / "walk.db3")
    clean = write_realsense_recording(sim, root / "clean.db3", depth_noise=False)
    return sim, noisy, clean


def _cli(capsys, *argv):
    rc = main(list(map(str, argv)))
    captured = capsys.readouterr()
    return rc, captured.err.strip()


# --- the file format ------------------------------------------------------------------------

def test_writer_and_reader_round_trip_bit_exact(tmp_path):
    rng = np.random.default_rng(0)
    T_colour_depth = np.eye(4)
    T_colour_depth[:3, :3] = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # not symmetric
    T_colour_depth[:3, 3] = [0.015, -0.002, 0.001]
    writer = RecordingWriter(tmp_path / "r.db3", SMALL, SMALL, depth_units=0.00025, T_colour_depth=T_colour_depth)
    stamps = 100.0 + np.arange(8) / 15.0
    depth = rng.integers(0, 65535, size=(8, 48, 64), dtype=np.uint16)
    colour = rng.integers(0, 255, size=(8, 48, 64, 3), dtype=np.uint8)
    imu_t = 100.0 + np.arange(100) / 200.0
    accel, gyro = rng.normal(0, 5, (100, 3)), rng.normal(0, 1, (100, 3))
    for i in reversed(range(8)):  # added out of order: the writer sorts
        writer.add_depth(stamps[i] - 0.004, depth[i])
        writer.add_colour(stamps[i], colour[i])
    writer.add_imu(imu_t, accel, gyro)
    writer.close()

    raw = read_recording(tmp_path / "r.db3")
    assert [len(raw.depth[0]), len(raw.colour[0]), len(raw.accel[0]), len(raw.gyro[0])] == [8, 8, 100, 100]
    for kind in (raw.depth, raw.colour, raw.accel, raw.gyro):
        assert np.all(np.diff(kind[0]) > 0)  # timestamp order
    np.testing.assert_allclose(raw.colour[0], stamps, atol=1e-6)
    np.testing.assert_allclose(raw.depth[0], stamps - 0.004, atol=1e-6)
    np.testing.assert_array_equal(raw.depth[1], np.arange(1, 9))
    for i in range(8):
        np.testing.assert_array_equal(raw.depth[2][i], depth[i])
        np.testing.assert_array_equal(raw.colour[2][i], colour[i])
    np.testing.assert_allclose(raw.accel[0], imu_t, atol=1e-6)
    np.testing.assert_array_equal(raw.accel[1], accel.astype(np.float32))
    np.testing.assert_array_equal(raw.gyro[1], gyro.astype(np.float32))
    assert raw.depth_units == pytest.approx(0.00025, rel=1e-6)
    np.testing.assert_allclose(raw.T_colour_depth, T_colour_depth, atol=1e-7)
    assert raw.colour_intrinsics.fx == pytest.approx(52.0) and raw.colour_intrinsics.ppy == pytest.approx(23.5)


def test_simulated_recording_holds_every_frame_and_imu_sample(walk):
    sim, noisy, _ = walk
    seq = SimSequence(sim)
    rec = RealSenseRecording(noisy, groundtruth=sim / "groundtruth.txt")
    assert rec.simulated  # its sidecar says the simulator wrote it (the run's matcher follows)
    assert len(rec) == len(seq) and rec.intrinsics == seq.intrinsics
    assert rec.pairing_clock == "sensor" and rec.depth_clock_offset == 0.0  # one clock: its own stamps
    np.testing.assert_allclose(rec.timestamps, seq.timestamps, atol=1e-6)
    np.testing.assert_allclose(rec.T_world_cam_gt, seq.T_world_cam_gt, atol=1e-6)
    for i in (0, 17, 35):
        np.testing.assert_array_equal(rec[i].rgb, seq[i].rgb)
    # Every IMU sample, as float32, on the frames' clock.
    assert len(rec.imu["stamps"]) == len(seq.imu["stamps"])
    np.testing.assert_allclose(rec.imu["stamps"], seq.imu["stamps"], atol=1e-6)
    np.testing.assert_array_equal(rec.imu["gyro"], seq.imu["gyro"].astype(np.float32))
    np.testing.assert_allclose(rec.imu["accel"], seq.imu["accel"], atol=1e-5 * np.abs(seq.imu["accel"]).max())
    # The sidecar YAML puts the IMU (co-located with the colour camera here) where it was.
    np.testing.assert_allclose(rec.imu_config.T_cam_imu, np.eye(4), atol=1e-9)
    # Depth to the file's depth scale: 1 mm units.
    assert rec.raw.depth_units == pytest.approx(0.001)


def test_real_d435_file_with_two_hardware_clocks_pairs_by_arrival(caplog):
    """librealsense's own D435 sample (tests/data/realsense/README.md): depth and colour are
    stamped in each sensor's hardware clock, so no pair within 20 ms by those stamps; the
    frames' arrival on the host pairs them."""
    path = DATA / "realsense" / "single_depth_color_640x480.bag"
    with caplog.at_level(logging.INFO, logger="nap3d_graph.datasets.realsense"):
        rec = open_sequence(path)
    assert isinstance(rec, RealSenseRecording)
    assert rec.pairing_clock == "arrival"
    assert sum("paired by arrival time" in r.getMessage() for r in caplog.records) == 1  # said once
    assert len(rec) == 1
    assert rec.timestamps[0] == pytest.approx(360.713523, abs=1e-6)  # the colour frame's own stamp
    # The depth frame that arrived 54 ms before the colour frame (not the one 114 ms after),
    # its stamp moved onto the colour clock.
    assert rec.raw.depth[1][rec._depth_index[0]] == 169
    assert rec.depth_timestamps[0] - rec.timestamps[0] == pytest.approx(-0.054, abs=0.002)
    frame = rec[0]
    assert frame.rgb.shape == (480, 640, 3) and frame.rgb.dtype == np.uint8
    depth = frame.depth_m
    assert depth.shape == (480, 640) and depth.dtype == np.float32
    valid = depth[depth > 0]
    assert valid.size > 0.2 * depth.size
    assert 0.2 < float(np.median(valid)) < 10.0  # metres
    assert rec.raw.depth_units == pytest.approx(0.001)
    # The file's own calibration: its depth unit and the depth camera's stereo baseline (a
    # D435's 50 mm), which the map's bundle adjustment takes instead of a Kinect's 75 mm.
    assert rec.depth_units_per_m == pytest.approx(1000.0)
    assert rec.stereo_baseline_m == pytest.approx(0.0502, abs=0.0005)
    from nap3d_graph.mapping.build import MapSettings, _bundle_settings

    assert _bundle_settings(rec, MapSettings()).baseline_m == pytest.approx(rec.stereo_baseline_m)
    chosen = MapSettings(bundle_settings=dataclasses.replace(MapSettings().bundle_settings, baseline_m=0.06))
    assert _bundle_settings(rec, chosen).baseline_m == 0.06  # a baseline set by hand is kept


def test_registered_depth_lands_where_the_simulator_says(walk):
    sim, _, clean = walk
    seq = SimSequence(sim)
    rec = RealSenseRecording(clean)
    assert rec.T_colour_depth[0, 3] == pytest.approx(0.015)
    for i in (0, 12, 24, 35):
        truth = seq.scene.render_depth(seq.T_world_cam_gt[i], seq.intrinsics)  # the colour camera's own view
        registered = rec.registered_depth(i)
        unregistered = rec.raw.depth[2][rec._depth_index[i]] * rec.raw.depth_units
        both = (truth > 0) & (registered > 0)
        assert both.mean() > 0.97  # holes only where the colour camera sees what the depth camera does not
        err_mm = np.abs(registered - truth)[both] * 1000
        # 1 mm depth units alone give ~0.25 mm median: the registration adds little to it.
        assert np.median(err_mm) < 0.35 and np.percentile(err_mm, 90) < 0.6, (i, np.median(err_mm))
        raw_err_mm = np.abs(unregistered - truth)[(truth > 0) & (unregistered > 0)] * 1000
        assert np.percentile(raw_err_mm, 90) > 5 * np.percentile(err_mm, 90)


# --- the run on a recording -----------------------------------------------------------------

@pytest.mark.slow
def test_run_on_a_recording_removes_drift_as_on_the_sequence_folder(walk, tmp_path, capsys):
    sim, noisy, _ = walk
    common = ("--field", sim, "--keyframe-every", 3)
    rc, err = _cli(capsys, "run", "--traj", "realsense", "--data", noisy, "--groundtruth", sim / "groundtruth.txt",
                   "--out", tmp_path / "rs", *common)
    assert rc == 0, err
    rc, err = _cli(capsys, "run", "--traj", "sim", "--data", sim, "--odom", "imu", "--out", tmp_path / "sim", *common)
    assert rc == 0, err
    rs = json.loads((tmp_path / "rs" / "latest" / "metrics.json").read_text())
    folder = json.loads((tmp_path / "sim" / "latest" / "metrics.json").read_text())
    config = (tmp_path / "rs" / "latest" / "config.yaml").read_text()
    assert "kind: imu" in config  # a recording with an IMU drives the run with it by default
    odometry, corrected = rs["odometry"]["ate_m"]["rmse"], rs["estimate"]["ate_m"]["rmse"]
    assert odometry > 0.1 and corrected < 0.006 and corrected < odometry / 20
    assert rs["corrections_accepted"] >= 11
    # The recording's depth comes from a camera 1.5 cm to the side, in 1 mm units and
    # registered: within a few millimetres of the folder's colour-camera depth.
    assert corrected < folder["estimate"]["ate_m"]["rmse"] + 0.003
    # Output stamps are the recording's frame stamps.
    stamps, _ = read_tum_trajectory(tmp_path / "rs" / "latest" / "estimate.txt")
    np.testing.assert_allclose(stamps, SimSequence(sim).timestamps, atol=1e-6)


@pytest.mark.slow
def test_compare_on_a_recording_runs_every_estimator_with_its_imu(walk, tmp_path, capsys):
    sim, noisy, _ = walk
    rc, err = _cli(capsys, "compare", "--traj", "realsense", "--data", noisy, "--groundtruth", sim / "groundtruth.txt",
                   "--field", sim, "--keyframe-every", 3, "--out", tmp_path / "cmp")
    assert rc == 0, err
    rows = {r["estimator"]: r for r in json.loads((tmp_path / "cmp" / "comparison.json").read_text())["rows"]}
    assert set(rows) == {"odometry", "eskf", "navstate-ekf", "isam2-causal", "isam2-final", "batch-lm"}
    assert rows["odometry"]["ate_rmse_m"] > 0.1
    for name in ("eskf", "navstate-ekf", "isam2-causal", "isam2-final", "batch-lm"):
        assert rows[name]["ate_rmse_m"] < 0.02, name
    assert rows["batch-lm"]["ate_rmse_m"] <= rows["eskf"]["ate_rmse_m"]


def test_run_without_ground_truth_reports_correction_statistics(walk, tmp_path, capsys):
    sim, noisy, _ = walk
    start = " ".join(f"{v:.9f}" for v in T_to_tum(SimSequence(sim).T_world_cam_gt[0]))
    rc, err = _cli(capsys, "run", "--traj", "realsense", "--data", noisy, "--field", sim, "--keyframe-every", 6,
                   "--initial-pose", start, "--out", tmp_path)
    assert rc == 0, err
    metrics = json.loads((tmp_path / "latest" / "metrics.json").read_text())
    assert "no ATE" in metrics["ground_truth"] and "estimate" not in metrics
    assert metrics["corrections_accepted"] >= 5 and metrics["median_inliers"] > 30
    config = yaml.safe_load((tmp_path / "latest" / "config.yaml").read_text())
    assert config["resolved"]["imu"]["fallback_odometry"] == "dense" and "vo_fallback" not in metrics  # never needed here
    # Gravity as the graph refined it, in the simulated z-up world: within a degree of -z.
    gravity = metrics["gravity_world_m_s2"]
    assert gravity["given"] == [0.0, 0.0, -9.81] and gravity["turned_deg"] < 1.0
    assert np.degrees(np.arccos(-gravity["refined"][2] / np.linalg.norm(gravity["refined"]))) < 1.0
    # The corrected trajectory still starts where it was told and ends near the truth.
    _, T = read_tum_trajectory(tmp_path / "latest" / "estimate.txt")
    assert np.linalg.norm(T[-1][:3, 3] - SimSequence(sim).T_world_cam_gt[-1][:3, 3]) < 0.01


# --- bad input: one line, exit 2 --------------------------------------------------------------

def _colour_only(path):
    writer = RecordingWriter(path, SMALL, SMALL, imu_hz=0)
    for i in range(4):
        writer.add_colour(i / 15, np.zeros((48, 64, 3), np.uint8))
    return writer.close()


def _without_imu(path):
    writer = RecordingWriter(path, SMALL, SMALL, imu_hz=0)
    for i in range(4):
        writer.add_colour(i / 15, np.zeros((48, 64, 3), np.uint8))
        writer.add_depth(i / 15, np.full((48, 64), 1500, np.uint16))
    return writer.close()


def test_bad_recordings_give_one_line_errors(walk, tmp_path, capsys):
    sim, noisy, _ = walk
    truncated = tmp_path / "truncated.db3"
    truncated.write_bytes(noisy.read_bytes()[: noisy.stat().st_size // 2])
    cases = {
        "missing": (tmp_path / "nothing.db3", "no such recording"),
        "truncated": (truncated, "not a readable RealSense recording"),
        "no depth": (_colour_only(tmp_path / "colour_only.db3"), "no depth stream"),
        "no imu": (_without_imu(tmp_path / "no_imu.db3"), "IMU"),
    }
    for name, (path, expected) in cases.items():
        rc, err = _cli(capsys, "run", "--traj", "realsense", "--data", path, "--field", "none", "--odom", "imu",
                       "--initial-pose", "0 0 0 0 0 0 1", "--out", tmp_path / "out")
        assert rc == 2 and expected in err and len(err.splitlines()) == 1, (name, err)
    with pytest.raises(DatasetError, match="no depth stream"):
        open_sequence(tmp_path / "colour_only.db3")


def test_live_without_a_camera_says_so(tmp_path, capsys):
    rc, err = _cli(capsys, "run", "--traj", "realsense", "--data", "live", "--seconds", 1, "--field", "none",
                   "--record", tmp_path / "live.bag", "--out", tmp_path / "out")
    assert rc == 2 and "no RealSense camera connected" in err and len(err.splitlines()) == 1, err


def test_realsense_options_belong_to_realsense(walk, tmp_path, capsys):
    sim, noisy, _ = walk
    rc, err = _cli(capsys, "run", "--traj", "sim", "--data", sim, "--field", "oracle", "--groundtruth",
                   sim / "groundtruth.txt", "--out", tmp_path)
    assert rc == 2 and "--traj realsense" in err
    rc, err = _cli(capsys, "run", "--traj", "tum", "--data", noisy, "--field", "none", "--out", tmp_path)
    assert rc == 2 and "use --traj realsense" in err


def test_realsense_config_yaml_round_trip_and_errors(tmp_path):
    from nap3d_graph.datasets.realsense import D435I_T_DEPTH_IMU, RealSenseConfig

    config = RealSenseConfig(gyro_noise_density=1e-3)
    loaded = RealSenseConfig.load(config.save(tmp_path / "c.yaml"))
    assert loaded.gyro_noise_density == 1e-3
    np.testing.assert_allclose(loaded.T_depth_imu, D435I_T_DEPTH_IMU, atol=1e-9)
    (tmp_path / "bad.yaml").write_text("gyro_noise: 1\n")
    with pytest.raises(DatasetError, match="unknown settings"):
        RealSenseConfig.load(tmp_path / "bad.yaml")
    (tmp_path / "short.yaml").write_text("T_depth_imu: [0, 0, 0]\n")
    with pytest.raises(DatasetError, match="7 numbers"):
        RealSenseConfig.load(tmp_path / "short.yaml")


def test_intrinsics_match_the_simulator(walk):
    sim, noisy, _ = walk
    K: Intrinsics = RealSenseRecording(noisy).intrinsics
    assert (K.width, K.height) == (192, 144) and K.fx == pytest.approx(SimSequence(sim).intrinsics.fx)


@pytest.mark.slow
def test_train_field_and_export_take_a_recording_with_poses(walk, tmp_path, capsys):
    from nap3d_graph.fields import load_field

    sim, noisy, _ = walk
    seq = SimSequence(sim)
    rc, err = _cli(capsys, "train-field", noisy, "--poses", sim / "groundtruth.txt", "--out", tmp_path / "f.pt",
                   "--steps", 60, "--voxel-size", 0.08, "--every", 2, "--eval-frames", 2, "--quiet")
    assert rc == 0, err
    report = json.loads((tmp_path / "f.report.json").read_text())
    assert report["held_out"]["depth_abs_err_m"]["median"] < 0.05  # a coarse, short training: centimetres
    trained = np.asarray(load_field(tmp_path / "f.pt").meta["train_timestamps"])
    assert np.isin(np.round(trained, 6), np.round(seq.timestamps, 6)).all()

    rc, err = _cli(capsys, "export-nerfstudio", noisy, tmp_path / "ns", "--poses", sim / "groundtruth.txt")
    assert rc == 0, err
    frames = json.loads((tmp_path / "ns" / "transforms.json").read_text())["frames"]
    assert len(frames) == len(seq)
    import cv2

    depth_mm = cv2.imread(str(tmp_path / "ns" / frames[0]["depth_file_path"]), cv2.IMREAD_UNCHANGED)
    registered = RealSenseRecording(noisy).registered_depth(0)
    assert np.abs(depth_mm / 1000.0 - registered).max() < 0.0006  # the registered depth, to the millimetre
    # Without poses a recording cannot train a field.
    rc, err = _cli(capsys, "train-field", noisy, "--out", tmp_path / "g.pt", "--steps", 10, "--quiet")
    assert rc == 2 and "pose" in err.lower(), err
