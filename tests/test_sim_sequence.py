"""Simulated sequences read back as TUM sequences (no special case) and as SimSequence."""

from __future__ import annotations

import shutil
import subprocess
import sys

import numpy as np
import pytest

from nap3d_graph.camera import Intrinsics
from nap3d_graph.datasets import SOURCES, DatasetError, SimSequence, TumSequence, read_tum_trajectory
from nap3d_graph.sims.scene import OracleField, Scene, make_scene
from nap3d_graph.sims.sensors import DepthNoise
from nap3d_graph.sims.sequence import SimConfig, simulate_sequence

FRAMES, WIDTH, HEIGHT = 12, 160, 120


@pytest.fixture(scope="module")
def sim_dir(tmp_path_factory):
    """An ideal camera (both images at the frame instant, no blur, fixed exposure, no flying
    pixels): what the exactness checks need."""
    ideal = SimConfig(frames=FRAMES, width=WIDTH, height=HEIGHT, timing=None, exposure=None,
                      depth=DepthNoise(flying_fraction=0.0))
    return simulate_sequence(tmp_path_factory.mktemp("sim") / "room", ideal)


@pytest.fixture(scope="module")
def kinect_dir(tmp_path_factory):
    """The default, Kinect-like camera."""
    return simulate_sequence(tmp_path_factory.mktemp("sim") / "kinect", SimConfig(frames=FRAMES, width=WIDTH,
                                                                                    height=HEIGHT, seed=2))


@pytest.fixture(scope="module")
def tum(sim_dir) -> TumSequence:
    return TumSequence(sim_dir)


@pytest.fixture(scope="module")
def sim(sim_dir) -> SimSequence:
    return SimSequence(sim_dir)


def test_reads_as_plain_tum_sequence(tum, sim_dir):
    # Every frame associated, although the depth stamps are a few ms off the colour stamps
    # (the ideal camera; the Kinect-like one is checked below).
    rgb_stamps = np.loadtxt(sim_dir / "rgb.txt", usecols=0)
    assert len(tum) == FRAMES and tum.has_gt.all()
    assert np.array_equal(tum.timestamps, rgb_stamps)
    offsets = tum.depth_timestamps - tum.timestamps
    assert np.all(np.abs(offsets) < 0.0081) and np.all(offsets != 0)
    assert [p.name for p in tum.depth_paths] == sorted(p.name for p in (sim_dir / "depth").glob("*.png"))
    # Intrinsics from intrinsics.json (the folder name says nothing), no distortion.
    assert tum.intrinsics == Intrinsics(131.25, 131.25, 79.5, 59.5, WIDTH, HEIGHT)
    assert not tum.undistort and not tum.undistort_depth
    frame = tum[0]
    assert frame.rgb.shape == (HEIGHT, WIDTH, 3) and frame.depth_m.shape == (HEIGHT, WIDTH)
    assert frame.intrinsics == tum.intrinsics


def test_ground_truth_at_frames_is_exact(tum, sim_dir):
    # The writer includes the exact frame instants in groundtruth.txt: interpolation there
    # returns those rows.
    stamps_gt, T_world_cam_gt = read_tum_trajectory(sim_dir / "groundtruth.txt")
    rows = np.searchsorted(stamps_gt, tum.timestamps)
    assert np.array_equal(stamps_gt[rows], tum.timestamps)
    assert np.allclose(tum.T_world_cam_gt, T_world_cam_gt[rows], rtol=0, atol=1e-6)
    # Ground truth really is the rendering pose: re-rendering it gives the written colour
    # up to the image noise (sigma 0.01, i.e. ~2.5 grey levels).
    scene = Scene.load(sim_dir / "scene.json")
    rgb01, _, hit = scene.render(tum.T_world_cam_gt[3], tum.intrinsics)
    diff = tum[3].rgb.astype(float) - np.round(rgb01 * 255)
    assert abs(diff[hit].mean()) < 0.5 and 2.0 < diff[hit].std() < 3.2


def test_depth_is_noisy_quantised_render(tum, sim_dir):
    scene = Scene.load(sim_dir / "scene.json")
    model = DepthNoise(**SimSequence(sim_dir).config["depth"])
    normalised, valid_fraction = [], []
    for i in range(0, FRAMES, 3):
        depth = tum[i].depth_m.astype(np.float64)
        # 5000 units per metre, stored as uint16: depth * 5000 is an integer (up to float32
        # rounding of depth_m, < 0.005 units; unquantised values would be off by up to 0.5).
        units = depth * 5000.0
        assert np.abs(units - np.round(units)).max() < 0.005
        _, true, hit = scene.render(tum.T_world_cam_gt[i], tum.intrinsics)
        valid = depth > 0
        assert np.all(hit[valid])  # no depth where the render has none
        valid_fraction.append(valid.mean())
        # Noise model: sigma(z) = 1.4e-3 z^2, plus rounding to 1/5000 m (uniform, var q^2/12).
        sigma = np.sqrt(model.sigma_m(true[valid]) ** 2 + (1 / 5000) ** 2 / 12)
        normalised.append((depth[valid] - true[valid]) / sigma)
    z = np.concatenate(normalised)
    assert z.size > 40_000
    assert abs(z.mean()) < 0.05
    assert 0.8 < z.std() < 1.2  # the noise has the modelled size (measured ~1.0)
    assert np.abs(z).max() < 6.5
    assert 0.85 < np.mean(valid_fraction) < 1.0  # holes: about hole_fraction, plus range limits


def test_kinect_like_camera_timing_exposure_and_blur(kinect_dir):
    """Depth is captured 30 ms before the colour and stamped 15 ms after its capture; the
    written depth is the render at its capture pose; colour carries the frame's exposure
    gains and the motion blur of its exposure."""
    seq = SimSequence(kinect_dir)
    truth = seq.config
    capture = np.asarray(truth["depth_capture_stamps"])
    assert np.allclose(capture - seq.timestamps, -0.030, atol=1e-6)
    lag = seq.depth_timestamps - capture
    assert np.all(np.abs(lag - 0.015) <= 0.003 + 1e-6)
    # The depth image is the scene at the depth's capture pose, not at the colour's.
    for i in (2, 8):
        depth = seq[i].depth_m
        at_capture = seq.scene.render_depth(seq.ground_truth_at([capture[i]])[0], seq.intrinsics)
        at_colour = seq.scene.render_depth(seq.T_world_cam_gt[i], seq.intrinsics)
        both = (depth > 0) & (at_capture > 0) & (at_colour > 0)
        err_capture = np.median(np.abs(depth - at_capture)[both])
        err_colour = np.median(np.abs(depth - at_colour)[both])
        assert err_capture < 0.5 * err_colour, (err_capture, err_colour)
    # Exposure: the image's mean colour over a clean render's is the recorded per-channel gain
    # (blur moves colour around but keeps its mean).
    gains = np.asarray(truth["exposure_gains"])
    assert gains.shape == (FRAMES, 3) and gains.std() > 0.005
    for i in (3, 9):
        rgb01, _, hit = seq.scene.render(seq.T_world_cam_gt[i], seq.intrinsics)
        ratio = (seq[i].rgb[hit].astype(float) / 255.0).mean(axis=0) / rgb01[hit].mean(axis=0)
        assert np.allclose(ratio, gains[i], rtol=0.03), (ratio, gains[i])


def test_sim_sequence_extras(sim, tum, sim_dir):
    assert SOURCES["sim"] is SimSequence and isinstance(sim, TumSequence)
    assert np.array_equal(sim.timestamps, tum.timestamps)
    assert np.array_equal(sim.T_world_cam_gt, tum.T_world_cam_gt)
    # Odometry: written at the colour stamps, so the frame values are the file's rows.
    stamps_odom, T_odom = read_tum_trajectory(sim_dir / "odometry.txt")
    assert np.array_equal(stamps_odom, sim.timestamps)
    assert sim.T_world_cam_odom.shape == (FRAMES, 4, 4)
    assert np.allclose(sim.T_world_cam_odom, T_odom, rtol=0, atol=1e-12)
    # It starts at the truth and drifts a little.
    assert np.allclose(sim.T_world_cam_odom[0], sim.T_world_cam_gt[0], atol=1e-6)
    drift = np.linalg.norm(sim.T_world_cam_odom[:, :3, 3] - sim.T_world_cam_gt[:, :3, 3], axis=1)
    assert 0 < drift[-1] < 0.2
    # IMU: the file's rows, at 200 Hz over the sequence.
    imu = sim.imu
    rows = np.loadtxt(sim_dir / "imu.txt")
    assert np.array_equal(imu["stamps"], rows[:, 0])
    assert np.array_equal(imu["accel"], rows[:, 1:4]) and np.array_equal(imu["gyro"], rows[:, 4:7])
    assert set(imu) == {"stamps", "accel", "gyro"}
    m = len(imu["stamps"])
    assert imu["accel"].shape == imu["gyro"].shape == (m, 3)
    assert np.allclose(np.diff(imu["stamps"]), 0.005, atol=2e-6)
    assert imu["stamps"][0] == pytest.approx(sim.timestamps[0], abs=1e-6)
    assert imu["stamps"][-1] <= sim.timestamps[-1] + 1e-6
    # Scene and settings.
    assert sim.scene.to_dict() == make_scene(0).to_dict()
    assert sim.config["frames"] == FRAMES and sim.config["width"] == WIDTH and sim.config["path"] == "traverse"


def test_oracle_field_renders_the_scene(sim):
    field = sim.oracle_field()
    assert isinstance(field, OracleField)
    T = sim.T_world_cam_gt[5]
    view = field.render(T, sim.intrinsics)
    rgb01, depth, hit = sim.scene.render(T, sim.intrinsics)
    assert np.array_equal(view.rgb, np.round(rgb01 * 255).astype(np.uint8))
    assert np.allclose(view.depth_m, depth, atol=1e-5)
    assert np.array_equal(view.opacity > 0.5, hit)
    # And matches the written image up to the sensor noise.
    assert np.abs(view.rgb.astype(float) - sim[5].rgb).mean() < 3.5


def test_not_a_simulated_sequence(sim_dir, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(sim_dir, copy)
    (copy / "scene.json").unlink()
    assert len(TumSequence(copy)) == FRAMES  # still a TUM sequence
    with pytest.raises(DatasetError, match="not a simulated sequence"):
        SimSequence(copy)
    shutil.copy(sim_dir / "scene.json", copy / "scene.json")
    (copy / "imu.txt").unlink()
    with pytest.raises(DatasetError, match=r"imu\.txt: file not found"):
        SimSequence(copy)
    with pytest.raises(DatasetError, match="nowhere"):
        SimSequence(tmp_path / "nowhere")


def test_datasets_import_does_not_import_torch():
    code = "import sys, nap3d_graph.datasets; assert 'torch' not in sys.modules, 'torch imported'"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr


def test_cli_simulate_writes_a_loadable_folder(tmp_path):
    from nap3d_graph.cli import main

    out = tmp_path / "cli_room"
    assert main(["simulate", str(out), "--count", "3", "--width", "64", "--height", "48", "--seed", "4"]) == 0
    seq = SimSequence(out)
    assert len(seq) == 3 and seq[2].rgb.shape == (48, 64, 3)
    assert seq.intrinsics == Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480).scaled(64, 48)
    assert seq.config["seed"] == 4 and seq.T_world_cam_odom.shape == (3, 4, 4)
    assert len(TumSequence(out)) == 3


def test_cli_simulate_takes_the_deprecated_frames_count_with_a_warning(tmp_path, capsys):
    """``simulate --frames N`` (a count, while --frames is a range everywhere else) still writes
    N frames and says to use --count; a range is refused in one line."""
    from nap3d_graph.cli import main

    out = tmp_path / "old"
    assert main(["simulate", str(out), "--frames", "2", "--width", "64", "--height", "48"]) == 0
    assert len(SimSequence(out)) == 2
    assert "taken as --count 2" in capsys.readouterr().err
    assert main(["simulate", str(tmp_path / "range"), "--frames", "0:10"]) == 2
    err = capsys.readouterr().err
    assert "give --count N" in err and len(err.strip().splitlines()) == 1
