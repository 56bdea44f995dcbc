"""The drift-correction pipeline on the simulator with the oracle field."""

import dataclasses
import json
import os
import shutil
import subprocess

import numpy as np
import pytest

from nap3d_graph.conventions import compose_covariance, exp_se3, pose_error
from nap3d_graph.datasets import SimSequence, TumSequence, read_tum_trajectory
from nap3d_graph.motion.odometry import make_odometry
from nap3d_graph.results import Correction
from nap3d_graph.run.config import PipelineConfig
from nap3d_graph.run.intrinsics_model import FIXED_ONLY
from nap3d_graph.run.output import write_results
from nap3d_graph.run.pipeline import Pipeline
from nap3d_graph.run.report import read_run_report
from nap3d_graph.sims.sensors import CameraTiming, OdometryNoise
from nap3d_graph.sims.sequence import SimConfig, simulate_sequence


def ate(result):
    return float(np.sqrt(np.mean([pose_error(a, b)[0] ** 2 for a, b in
                                  zip(result.T_world_cam_estimate, result.T_world_cam_gt)])))


def ate_odometry(result):
    return float(np.sqrt(np.mean([pose_error(a, b)[0] ** 2 for a, b in
                                  zip(result.T_world_cam_odometry, result.T_world_cam_gt)])))


DRIFT = OdometryNoise(bias_init=(0.0, 0.0, 0.01, 0.03, 0.0, 0.01), heading_bias_rad_s=0.02)


@pytest.fixture(scope="module")
def walk(sim_walk):
    """A 48-frame traversal of a room with strongly drifting odometry, seen by a camera that
    takes colour and depth at one instant (the graph's logic is what these tests check)."""
    return sim_walk(48, width=192, height=144, odometry=DRIFT)


@pytest.fixture(scope="module")
def kinect_walk(sim_walk):
    """The same walk seen by the Kinect-like camera: depth captured 30 ms before its colour."""
    return sim_walk(48, width=192, height=144, odometry=DRIFT, timing=CameraTiming())


# The drift model says what this odometry does: 3 cm/s and 0.02 rad/s of bias, moving or not.
CONFIG = PipelineConfig(keyframe_every=4, render_width=None, render_height=None, correction_iterations=2,
                        odom_drift_m_per_s=0.035, odom_drift_rad_per_s=0.025)


@pytest.fixture(scope="module")
def baseline(walk):
    seq = SimSequence(walk)
    return Pipeline(seq, seq.oracle_field(), make_odometry("recorded", seq), CONFIG).run()


def test_run_removes_drift(baseline):
    assert baseline.num_accepted >= 10 and len(baseline.keyframes) == 12
    assert ate_odometry(baseline) > 0.05  # the odometry alone drifts by centimetres
    # Frames between keyframes carry the odometry's drift since the nearest keyframe (up to
    # 2 frames of a 1.5 cm/s bias here); the keyframes themselves are at millimetres (192x144
    # images of walls 3-4 m away: sigma 1-4 mm per correction).
    assert ate(baseline) < 0.015
    assert ate(baseline) < ate_odometry(baseline) / 4
    kf = baseline.keyframe_indices
    kf_ate = np.sqrt(np.mean([pose_error(baseline.T_world_cam_estimate[i], baseline.T_world_cam_gt[i])[0] ** 2
                              for i in kf]))
    assert kf_ate < 0.008
    # Flat: the second half is no worse than the bar either.
    half = len(baseline.timestamps) // 2
    late = np.sqrt(np.mean([pose_error(a, b)[0] ** 2 for a, b in
                            zip(baseline.T_world_cam_estimate[half:], baseline.T_world_cam_gt[half:])]))
    assert late < 0.015


@pytest.mark.slow
def test_capture_timing_is_compensated(kinect_walk, baseline):
    """With the depth taken 30 ms before the colour, the run is centimetres off unless it moves
    each keyframe's depth to the colour's instant; with the timing estimated from the data
    (as train-field does) it is back near the ideal camera's."""
    from nap3d_graph.datasets.depth_timing import estimate_timing

    seq = SimSequence(kinect_walk)
    timing = estimate_timing(seq)
    uncompensated = Pipeline(seq, seq.oracle_field(), make_odometry("recorded", seq),
                             dataclasses.replace(CONFIG, compensate_timing=False)).run()
    compensated = Pipeline(seq, seq.oracle_field(), make_odometry("recorded", seq),
                           dataclasses.replace(CONFIG, timing=timing)).run()
    assert ate(compensated) < 0.6 * ate(uncompensated), (ate(compensated), ate(uncompensated))
    assert ate(compensated) < 1.5 * ate(baseline) + 0.002


def test_wrong_correction_is_gated_out(walk, baseline):
    seq = SimSequence(walk)
    target = baseline.keyframe_indices[6]

    def wrong(i, c: Correction):
        if i != target:
            return c
        return dataclasses.replace(c, T_world_cam_corrected=c.T_world_cam_corrected @ exp_se3([0, 0, 0, 0.5, 0, 0]))

    def skipped(i, c: Correction):
        return dataclasses.replace(c, success=False, reason="skipped by the test") if i == target else c

    gated = Pipeline(seq, seq.oracle_field(), make_odometry("recorded", seq), CONFIG, correction_hook=wrong).run()
    record = next(k for k in gated.keyframes if k.frame_index == target)
    assert not record.accepted and "innovation" in record.reason and record.gate_d2 > 5 * 19.8
    without = Pipeline(seq, seq.oracle_field(), make_odometry("recorded", seq), CONFIG, correction_hook=skipped).run()
    # Gated out means exactly as if that correction never existed.
    assert ate(gated) == pytest.approx(ate(without), abs=1e-4)  # to the optimiser tolerance
    assert ate(gated) < 0.015


class OffsetField:
    """The oracle of a room whose frame is displaced from the world by ``T_world_map``."""

    name = "offset-oracle"

    def __init__(self, oracle, T_world_map):
        self.oracle, self.T_world_map = oracle, T_world_map
        self.bounds = oracle.bounds

    def render(self, T_map_cam, intrinsics):
        return self.oracle.render(self.T_world_map @ T_map_cam, intrinsics)


def test_anchor_recovers_field_frame_offset(walk):
    seq = SimSequence(walk)
    T_world_map = exp_se3([0, 0, np.radians(2.0), 0.05, -0.04, 0.02])
    field = OffsetField(seq.oracle_field(), T_world_map)
    result = Pipeline(seq, field, make_odometry("recorded", seq), dataclasses.replace(CONFIG, use_anchor=True)).run()
    assert result.num_accepted >= 8
    t_err, r_err = pose_error(result.T_world_map, T_world_map)
    assert t_err < 0.01 and r_err < 0.2
    assert ate(result) < 0.02


def test_results_folder_loads_with_evo(baseline, tmp_path):
    from evo.tools import file_interface

    run, metrics = write_results(baseline, tmp_path, {"test": True}, "sim")
    for name in ("estimate.txt", "odometry.txt", "groundtruth.txt"):
        traj = file_interface.read_tum_trajectory_file(str(run / name))
        assert traj.num_poses == len(baseline.timestamps)
    stamps, T = read_tum_trajectory(run / "estimate.txt")
    np.testing.assert_allclose(T, baseline.T_world_cam_estimate, atol=1e-6)
    assert (tmp_path / "latest").resolve() == run.resolve()
    for name in ("config.yaml", "corrections.csv", "metrics.json", "trajectory_top_view.png", "translation_error.png"):
        assert (run / name).stat().st_size > 0
    assert metrics["estimate"]["ate_m"]["rmse"] == pytest.approx(ate(baseline), rel=1e-6)
    # evo_ape on the written files agrees with metrics.json.
    env = dict(os.environ, HOME=str(tmp_path), MPLBACKEND="Agg")
    out = subprocess.run(["evo_ape", "tum", str(run / "groundtruth.txt"), str(run / "estimate.txt")],
                         capture_output=True, text=True, env=env, check=True).stdout
    rmse = float(next(line.split()[-1] for line in out.splitlines() if line.strip().startswith("rmse")))
    assert rmse == pytest.approx(json.loads((run / "metrics.json").read_text())["estimate"]["ate_m"]["rmse"], rel=1e-4)
    lines = (run / "corrections.csv").read_text().splitlines()
    assert lines[0].startswith("frame_index,run_index,timestamp,key,matches,inliers") and len(lines) == 1 + len(baseline.keyframes)
    # The report built again from the folder's files is the report.md the run wrote.
    again = read_run_report(run)
    report_md = (run / "report.md").read_text()
    assert len(again.rows) >= 4 and all(f"| {a} | {b} | {c} | {d} |" in report_md for a, b, c, d in again.rows)


class HalfField:
    """Covers only the first half of the path: renders nothing beyond a time."""

    name = "half"

    def __init__(self, oracle, poses_covered):
        self.oracle = oracle
        self.centre = poses_covered[:, :3, 3].mean(axis=0)
        self.radius = np.linalg.norm(poses_covered[:, :3, 3] - self.centre, axis=1).max() + 0.05
        self.bounds = oracle.bounds

    def render(self, T, intrinsics):
        view = self.oracle.render(T, intrinsics)
        if np.linalg.norm(T[:3, 3] - self.centre) > self.radius:
            view = dataclasses.replace(view, opacity=np.zeros_like(view.opacity))
        return view


@pytest.mark.slow
def test_damaged_tum_folder_runs_to_the_end(walk, tmp_path):
    import cv2

    damaged = tmp_path / "damaged"
    shutil.copytree(walk, damaged)
    seq0 = TumSequence(damaged)
    # A listed frame whose image is gone, and frames whose depth is all missing.
    seq0.rgb_paths[13].unlink()
    for k in (20, 21):
        cv2.imwrite(str(seq0.depth_paths[k]), np.zeros((144, 192), np.uint16))
    seq = TumSequence(damaged)  # plain TUM reader: noise injected on the ground truth
    oracle = SimSequence(walk).oracle_field()
    field = HalfField(oracle, seq.T_world_cam_gt[:30])
    config = dataclasses.replace(CONFIG, keyframe_every=1)
    result = Pipeline(seq, field, make_odometry("noisy", seq, seed=1), config).run()
    assert len(result.timestamps) == len(seq) and len(result.keyframes) == len(seq)
    reasons = {k.frame_index: k.reason for k in result.keyframes}
    assert "unreadable" in reasons[13] and "rgb" in reasons[13]
    assert "no valid depth" in reasons[20] and "no valid depth" in reasons[21]
    assert all("low opacity" in reasons[i] for i in range(40, 48))
    assert result.num_accepted >= 20
    assert np.all(np.isfinite(result.T_world_cam_estimate))


def test_compose_covariance_matches_monte_carlo():
    rng = np.random.default_rng(0)
    T_b = exp_se3([0.1, -0.2, 0.3, 0.5, 0.2, -0.1])
    cov_a = np.diag([1e-4, 2e-4, 1e-4, 4e-4, 1e-4, 2e-4])
    cov_b = np.diag([2e-4, 1e-4, 1e-4, 1e-4, 3e-4, 1e-4])
    from nap3d_graph.conventions import inv_T, log_se3

    samples = []
    for _ in range(4000):
        Ta = exp_se3(rng.multivariate_normal(np.zeros(6), cov_a))
        Tb = T_b @ exp_se3(rng.multivariate_normal(np.zeros(6), cov_b))
        samples.append(log_se3(inv_T(T_b) @ Ta @ Tb))
    np.testing.assert_allclose(np.cov(np.array(samples).T), compose_covariance(cov_a, T_b, cov_b), atol=4e-5)


def test_field_sigma_makes_a_biased_fields_corrections_honest(walk, baseline):
    """A field whose geometry is 3 cm off (every correction shifted alike) claims millimetre
    sigmas: the gate refuses what disagrees with the odometry and keeps what does not, and
    the covariances are wrong either way. Stating the field's error (field_sigma_m) widens
    each correction's covariance by exactly that and lets the gate take them back."""
    seq = SimSequence(walk)
    shift = exp_se3([0, 0, 0, 0.03, 0, 0])

    def biased(i, c):
        return dataclasses.replace(c, T_world_cam_corrected=c.T_world_cam_corrected @ shift) if c.success else c

    def run(sigma):
        config = dataclasses.replace(CONFIG, field_sigma_m=sigma)
        pipeline = Pipeline(seq, seq.oracle_field(), make_odometry("recorded", seq), config, correction_hook=biased)
        return pipeline, pipeline.run()

    tight, tight_result = run(0.0)
    loose, loose_result = run(0.03)
    k = max(loose.state.stream.corrections)
    added = loose.state.stream.corrections[k][1] - tight.state.stream.corrections[k][1]
    # (the two runs render from slightly different poses: their own covariances differ by ~1e-8)
    np.testing.assert_allclose(added, np.diag([(0.03 / 2.0) ** 2] * 3 + [0.03**2] * 3), atol=1e-6)
    assert loose_result.num_accepted > tight_result.num_accepted
    with pytest.raises(ValueError, match="field_sigma_m"):
        PipelineConfig(field_sigma_m=-0.01)


class _SlowField:
    """The oracle field, ``delay_s`` (40 ms) slower per render: its corrections come back frames late."""

    def __init__(self, field, delay_s: float = 0.04):
        self.field, self.name, self.bounds, self.delay_s = field, field.name, field.bounds, delay_s

    def render(self, T_world_cam, intrinsics):
        import time

        time.sleep(self.delay_s)
        return self.field.render(T_world_cam, intrinsics)


def test_overlapped_run_lands_late_corrections_at_their_keyframes(walk, baseline):
    """With overlap the odometry goes on while a keyframe is measured on the worker thread;
    a correction that lands frames later still constrains its own keyframe, so the smoothed
    trajectory is as good as the run that waited, and the causal one is what was known at
    each frame (before a keyframe's correction lands, its prediction)."""
    seq = SimSequence(walk)
    landed = []
    result = Pipeline(seq, _SlowField(seq.oracle_field()), make_odometry("recorded", seq),
                      dataclasses.replace(CONFIG, overlap=True)).run(on_keyframe=landed.append)
    assert result.keyframe_indices == baseline.keyframe_indices
    assert [r.frame_index for r in result.keyframes] == [r.frame_index for r in landed] == result.keyframe_indices
    # The recorded odometry needs no image: the loop outruns the correction, which lands late.
    late = [r.timings_s["landed_frame"] - r.frame_index for r in result.keyframes]
    assert all(d >= 0 for d in late) and sum(d > 0 for d in late) >= len(late) // 2, late
    assert result.num_accepted >= baseline.num_accepted - 1
    assert ate(result) < 0.015 and ate(result) < ate(baseline) + 0.003
    # Causal: at a keyframe whose correction had not landed, the pose is its prediction, so
    # the online trajectory is worse than the smoothed one (here each correction lands a whole
    # keyframe interval late: measured 3.1 cm against 1.4 cm when the run waits) but well
    # below the odometry's 5.6 cm.
    online = float(np.sqrt(np.mean([pose_error(a, b)[0] ** 2 for a, b in
                                    zip(result.T_world_cam_online, result.T_world_cam_gt)])))
    assert ate(result) <= online < 0.65 * ate_odometry(result)


def test_an_overlapped_run_given_time_lands_each_correction_at_its_own_frame(walk, baseline):
    """``land_within_s``: before a frame's pose is given, the run waits up to that long (from
    the frame's arrival) for the correction in flight. Given time enough, every correction
    lands at its own keyframe's frame, though the field is slow and the odometry would have
    outrun it: the causal trajectory is then the inline run's, not the late-landing one's."""
    seq = SimSequence(walk)
    config = dataclasses.replace(CONFIG, overlap=True, land_within_s=30.0)
    result = Pipeline(seq, _SlowField(seq.oracle_field()), make_odometry("recorded", seq), config).run()
    assert result.keyframe_indices == baseline.keyframe_indices
    assert [r.timings_s["landed_frame"] for r in result.keyframes] == result.keyframe_indices
    assert all(r.timings_s["wait"] > 0.02 for r in result.keyframes[1:])  # each waited for its slow render
    assert result.num_accepted == baseline.num_accepted
    for name in ("T_world_cam_online", "T_world_cam_estimate"):
        moved = [pose_error(a, b) for a, b in zip(getattr(result, name), getattr(baseline, name))]
        assert max(m[0] for m in moved) < 1e-6 and max(m[1] for m in moved) < 1e-4, (name, max(moved))
    with pytest.raises(ValueError, match="land_within_s"):
        PipelineConfig(land_within_s=-0.01)


def _idle_worker_before_each_frame(pipeline):
    """A ``stop()`` hook that hands each frame over only once the pipeline's worker is idle
    (a camera slower than the measurement)."""
    import time

    def hook() -> bool:
        deadline = time.monotonic() + 120.0  # a worker that never goes idle fails the test, never hangs it
        while pipeline.worker is not None and not pipeline.worker.idle():
            if time.monotonic() > deadline:
                raise AssertionError("the pipeline's worker stayed busy for 120 s")
            time.sleep(0.002)
        return False

    return hook


@pytest.mark.slow
def test_an_overlapped_run_takes_a_keyframe_whenever_its_worker_is_idle(walk):
    """``keyframe_when_idle``: any frame at least N after the last keyframe is one while the
    worker has nothing in flight. Fed so that the worker is idle before each frame (a camera
    slower than the measurement), every second frame is a keyframe ('idle'), and given time to
    land each correction at its frame, the run is the inline run with a keyframe every 2: the
    second core measures as often as it keeps up. Busy all the time instead (a slow field,
    frames as fast as they come), keyframes fall back to ``keyframe_every``."""
    seq = SimSequence(walk)
    inline = Pipeline(seq, seq.oracle_field(), make_odometry("recorded", seq),
                      dataclasses.replace(CONFIG, keyframe_every=2)).run()
    config = dataclasses.replace(CONFIG, overlap=True, keyframe_when_idle=2, land_within_s=30.0)
    pipeline = Pipeline(seq, seq.oracle_field(), make_odometry("recorded", seq), config)

    result = pipeline.run(stop=_idle_worker_before_each_frame(pipeline))
    assert result.keyframe_indices == inline.keyframe_indices == list(range(0, len(seq), 2))
    assert [r.why for r in result.keyframes] == ["first"] + ["idle"] * (len(result.keyframes) - 1)
    assert result.num_accepted == inline.num_accepted
    for name in ("T_world_cam_online", "T_world_cam_estimate"):
        moved = max(pose_error(a, b)[0] for a, b in zip(getattr(result, name), getattr(inline, name)))
        assert moved < 1e-6, (name, moved)
    # A worker that is never idle when a frame comes: the count takes over (every 4th frame).
    busy = Pipeline(seq, _SlowField(seq.oracle_field()), make_odometry("recorded", seq),
                    dataclasses.replace(CONFIG, overlap=True, keyframe_when_idle=1)).run()
    whys = {r.why for r in busy.keyframes}
    assert "every" in whys and len(busy.keyframes) < len(seq) // 2, (whys, busy.keyframe_indices)
    with pytest.raises(ValueError, match="keyframe_when_idle"):
        PipelineConfig(keyframe_when_idle=2)  # no worker to wait for without overlap


def test_overlapped_run_renders_the_next_keyframe_ahead(walk, baseline):
    """While the worker is idle and the next frame is due to be a keyframe, it renders at that
    frame's predicted pose and detects the render's features; the keyframe's measurement then
    starts from them. Fed so that the worker is idle before each frame (a camera slower than
    the measurement), every keyframe after the first finds its render made, and the result is
    the run that rendered at each keyframe's own prediction, to a fraction of its error."""
    seq = SimSequence(walk)
    # A 6 Hz walk: the one-step guess of the next pose is up to 6 cm / 1.7 deg off (at 30 Hz,
    # millimetres), so the render made ahead is taken within 8 cm / 3 deg here.
    config = dataclasses.replace(CONFIG, overlap=True, render_ahead=True, render_ahead_m=0.08, render_ahead_deg=3.0)
    pipeline = Pipeline(seq, seq.oracle_field(), make_odometry("recorded", seq), config)

    result = pipeline.run(stop=_idle_worker_before_each_frame(pipeline))
    assert result.keyframe_indices == baseline.keyframe_indices
    prepared = [r.timings_s.get("prepared") for r in result.keyframes]
    assert prepared[0] == 0.0 and all(p == 1.0 for p in prepared[1:]), prepared
    assert all("render_ahead" in r.timings_s for r in result.keyframes[1:])
    # The keyframe's own features were detected as it arrived, beside its odometry.
    assert all("detect_ahead" in r.timings_s for r in result.keyframes[1:])
    assert result.num_accepted >= baseline.num_accepted - 1
    assert ate(result) < ate(baseline) + 0.002, (ate(result), ate(baseline))
    moved = [pose_error(a, b)[0] for a, b in zip(result.T_world_cam_estimate, baseline.T_world_cam_estimate)]
    assert float(np.median(moved)) < 0.5 * ate(baseline), (np.median(moved), ate(baseline))


def test_a_capture_timing_the_data_cannot_tell_is_not_applied(tmp_path, caplog):
    """12 frames of a camera that captures at its stamps: the timing search's minimum is noise
    (here +40 ms, the edge of the range, agreeing worse than the stamps): not compensated."""
    from nap3d_graph.datasets import SimSequence
    from nap3d_graph.datasets.depth_timing import estimate_timing
    from nap3d_graph.sims.sensors import DepthNoise

    ideal = SimConfig(frames=12, seed=5, width=160, height=120, timing=None, exposure=None,
                      depth=DepthNoise(flying_fraction=0.0))
    sequence = SimSequence(simulate_sequence(tmp_path / "w", ideal))
    with caplog.at_level("WARNING"):
        assert estimate_timing(sequence) is None
    assert "capture timing not compensated" in caplog.text


class _ThreadNotingSequence(SimSequence):
    """A simulated sequence that notes which thread read each frame."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.read_on: dict[int, str] = {}

    def __getitem__(self, i):
        import threading

        self.read_on[int(i)] = threading.current_thread().name
        return super().__getitem__(i)


def test_a_replay_reads_its_next_frames_on_another_thread_with_the_same_result(walk):
    """``read_ahead``: a run that reads every frame (here the dense odometry) decodes the next
    frames on a background thread while it works on this one; the frames, and so the run, are
    the same as reading each frame when its step comes."""
    config = dataclasses.replace(CONFIG, max_frames=24)
    runs = {}
    for ahead in (0, 2):
        seq = _ThreadNotingSequence(walk)
        runs[ahead] = (seq, Pipeline(seq, seq.oracle_field(), make_odometry("dense", seq),
                                     dataclasses.replace(config, read_ahead=ahead)).run())
    (plain_seq, plain), (ahead_seq, ahead) = runs[0], runs[2]
    assert set(plain_seq.read_on.values()) == {"MainThread"}
    read_ahead = [i for i, name in ahead_seq.read_on.items() if name.startswith("nap3d-read-ahead")]
    assert sorted(read_ahead) == list(range(1, 24))  # all but the first, which nothing read before
    assert ahead.keyframe_indices == plain.keyframe_indices
    for name in ("T_world_cam_odometry", "T_world_cam_online", "T_world_cam_estimate"):
        assert np.array_equal(np.asarray(getattr(ahead, name)), np.asarray(getattr(plain, name))), name
    assert ate(ahead) < 0.8 * ate_odometry(ahead)


@pytest.mark.slow
def test_an_overlapped_run_waiting_for_its_second_thread_reads_on_its_own(walk):
    """With a field slower than the odometry, an overlapped run's keyframes wait for the
    correction in flight: the run then reads each frame itself (a reader thread would compete
    with the second thread it waits for); handed each frame once that thread is idle, it reads ahead."""
    config = dataclasses.replace(CONFIG, overlap=True, max_frames=24)
    threads = {}
    for name in ("slow", "idle"):
        seq = _ThreadNotingSequence(walk)
        # Slow: each render takes far longer than the 4 frames of odometry between keyframes.
        # Idle: each frame is handed over once the second thread is idle (a slow camera).
        field = _SlowField(seq.oracle_field(), delay_s=0.5) if name == "slow" else seq.oracle_field()
        pipeline = Pipeline(seq, field, make_odometry("dense", seq), config)
        result = pipeline.run(stop=_idle_worker_before_each_frame(pipeline) if name == "idle" else None)
        assert ate(result) < ate_odometry(result)
        threads[name] = sum(t.startswith("nap3d-read-ahead") for t in seq.read_on.values())
    # Slow: frames 1-2 before the first wait, 2 more after the first keyframe, the rest on the
    # run's thread. Idle: every frame after the first.
    assert threads["slow"] <= 6 and threads["idle"] == 23, threads


def test_reading_ahead_hands_over_each_frame_and_its_error_when_asked():
    """A frame that cannot be read raises its own error when the run asks for it (the run
    records it and goes on), not earlier and not for its neighbours; nothing is read past the end."""
    from nap3d_graph.datasets import DatasetError
    from nap3d_graph.run.read_ahead import FrameReadAhead, reads_concurrently

    asked = []

    class Frames:
        def __getitem__(self, i):
            asked.append(i)
            if i == 3:
                raise DatasetError("frame 3: rgb image unreadable")
            return f"frame {i}"

    with FrameReadAhead(Frames(), ahead=2, stop=6) as reader:
        assert reader[0] == "frame 0" and reader[1] == "frame 1" and reader[2] == "frame 2"
        with pytest.raises(DatasetError, match="frame 3"):
            reader[3]
        assert reader[5] == "frame 5"  # frame 4, read ahead and never asked for, is dropped
    assert sorted(set(asked)) == [0, 1, 2, 3, 4, 5] and max(asked) < 6
    # Not wanted (an overlapped run waiting for its second thread): each frame is read when asked.
    asked.clear()
    want = [True]
    with FrameReadAhead(Frames(), ahead=2, stop=6, wanted=lambda: want[0]) as reader:
        assert reader[0] == "frame 0"  # reads 1 and 2 ahead
        want[0] = False
        assert reader[1] == "frame 1" and reader[2] == "frame 2" and reader[4] == "frame 4"
        assert reader.read_ahead_count == 2
    assert sorted(asked) == [0, 1, 2, 4]
    assert not reads_concurrently(Frames()) and reads_concurrently(SimSequence) and reads_concurrently(TumSequence)
    with pytest.raises(ValueError, match="read_ahead"):
        PipelineConfig(read_ahead=-1)


def test_the_feature_odometry_at_the_renders_width_hands_its_features_to_the_correction(walk, monkeypatch):
    """``--odom vo --vo-width`` at the render's width: the odometry resizes each frame as the
    correction does and detects the same features on it, so a keyframe's correction takes them
    instead of detecting them again (inline and overlapped): one detection fewer per keyframe,
    the same trajectory to the bit."""
    import nap3d_graph.nap3d.correct as correct_module
    from nap3d_graph.motion.odometry import VisualOdometry
    from nap3d_graph.nap3d.matching import detect_features

    calls = []

    def counted(*args, **kwargs):
        calls.append(1)
        return detect_features(*args, **kwargs)

    monkeypatch.setattr(correct_module, "detect_features", counted)  # the real frames' detections
    config = dataclasses.replace(CONFIG, max_frames=24, render_width=160, render_height=120)
    seq = SimSequence(walk)
    field = seq.oracle_field()

    def run(shared: bool, overlap: bool = False):
        calls.clear()
        odometry = make_odometry("vo", seq, vo_width=160)
        assert odometry.shares_features(seq.intrinsics.scaled(160, 120), config.align)
        if not shared:
            monkeypatch.setattr(odometry, "features_of", lambda *args: None)
        result = Pipeline(seq, field, odometry, dataclasses.replace(config, overlap=overlap)).run()
        return result, len(calls)

    (plain, plain_calls), (shared, shared_calls) = run(False), run(True)
    # Every keyframe but the first (the odometry detects from frame 1 on) reuses the odometry's:
    # one detection per frame in all.
    assert shared_calls == plain_calls - (len(shared.keyframe_indices) - 1) == config.max_frames
    assert shared.keyframe_indices == plain.keyframe_indices
    for name in ("T_world_cam_odometry", "T_world_cam_online", "T_world_cam_estimate"):
        assert np.array_equal(np.asarray(getattr(shared, name)), np.asarray(getattr(plain, name))), name
    assert all(k.accepted for k in shared.keyframes)
    assert ate(shared) < 0.5 * ate_odometry(shared)
    overlapped, overlapped_calls = run(True, overlap=True)
    assert overlapped_calls == config.max_frames
    assert np.array_equal(np.asarray(overlapped.T_world_cam_estimate), np.asarray(shared.T_world_cam_estimate))
    # A width the render does not have: nothing to share, and it is said so.
    assert not VisualOdometry(width=128).shares_features(seq.intrinsics.scaled(160, 120), config.align)
    with pytest.raises(ValueError, match="`vo_width` is for `odometry='vo'`"):
        make_odometry("dense", seq, vo_width=160)


def test_a_run_holds_blas_to_one_thread_and_its_trajectory_does_not_change(kinect_walk):
    """``library_threads``: while a run goes (inline or overlapped) numpy's BLAS works on one
    thread and OpenCV's pool is left alone; the BLAS pool comes back after the run; the poses
    are the same to the last bit as with the pool as it comes."""
    import cv2
    from threadpoolctl import threadpool_info

    def blas_threads() -> int:
        return max(p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas")

    seq = SimSequence(kinect_walk)
    seen = []

    class Counting:  # the dense odometry, reporting the pools' sizes it ran with
        def __init__(self, inner):
            self.inner = inner

        def __getattr__(self, name):
            return getattr(self.inner, name)

        def increment(self, *args, **kwargs):
            seen.append((cv2.getNumThreads(), blas_threads()))
            return self.inner.increment(*args, **kwargs)

    blas_before, opencv_before = blas_threads(), cv2.getNumThreads()
    config = dataclasses.replace(CONFIG, keyframe_every=8, max_frames=24)
    runs = {}
    for overlap, count in ((True, 1), (False, 1), (False, None)):
        seen.clear()
        odometry = Counting(make_odometry("dense", seq))
        run_config = dataclasses.replace(config, library_threads=count, overlap=overlap)
        runs[overlap, count] = Pipeline(seq, seq.oracle_field(), odometry, run_config).run()
        assert (blas_threads(), cv2.getNumThreads()) == (blas_before, opencv_before)
        assert seen and {opencv for opencv, _ in seen} == {opencv_before}
        assert {blas for _, blas in seen} == ({1} if count == 1 else {blas_before})
    reference = runs[False, None]
    for key in ((True, 1), (False, 1)):
        np.testing.assert_array_equal(runs[key].T_world_cam_estimate, reference.T_world_cam_estimate)
        np.testing.assert_array_equal(runs[key].T_world_cam_odometry, reference.T_world_cam_odometry)
    assert ate(reference) < ate_odometry(reference)


def _correction(model: str | None, success: bool = True) -> Correction:
    from nap3d_graph.results import Alignment

    diagnostics = {} if model is None else {"intrinsics_model": model}
    alignment = Alignment(success=success, diagnostics=diagnostics, reason="" if success else "too few inliers")
    return Correction(np.eye(4), np.eye(4), np.eye(6), alignment, 1, success, alignment.reason, {})


def test_the_intrinsics_tracker_settles_after_wins_in_a_row_and_a_calibrated_win_unsettles_it():
    """``IntrinsicsModelTracker``: both camera models until the given intrinsics won
    ``check_every`` keyframes in a row, then the given alone but every ``check_every``-th; a
    self-calibrated win brings back both at every keyframe; failures count for nothing."""
    from nap3d_graph.run.intrinsics_model import IntrinsicsModelTracker

    tracker = IntrinsicsModelTracker(3, active=True)
    plan = []
    choices = iter(["fixed", "fixed", None, "fixed",  # a failure between the wins does not count
                    FIXED_ONLY, FIXED_ONLY, "fixed", FIXED_ONLY, FIXED_ONLY,
                    "calibrated", "fixed", "fixed", "fixed", FIXED_ONLY])
    for k in range(14):
        both = tracker.fits_both(k)
        plan.append(both)
        choice = next(choices)
        failed = choice is None
        label = tracker.observe(k, _correction(None if (failed or choice == FIXED_ONLY) else choice, not failed))
        assert label == ("" if failed else choice), (k, label, choice)
    assert plan == [True, True, True, True, False, False, True, False, False, True, True, True, True, False]
    # Off (0), or alignments that do not fit both anyway: every job as AlignConfig says.
    for tracker in (IntrinsicsModelTracker(0, active=True), IntrinsicsModelTracker(3, active=False)):
        for k in range(6):
            assert tracker.fits_both(k) and tracker.observe(k, _correction("fixed")) == "fixed"
    with pytest.raises(ValueError, match="intrinsics_check_every"):
        PipelineConfig(intrinsics_check_every=-1)


def test_a_run_stops_fitting_the_self_calibrated_camera_once_the_given_one_keeps_winning(walk, baseline):
    """The given intrinsics are right: after ``intrinsics_check_every`` keyframes the run fits
    them alone (both again every ``intrinsics_check_every``-th), and the trajectory is the one
    a run fitting both at every keyframe gives, to the bit."""
    seq = SimSequence(walk)
    both_always = Pipeline(seq, seq.oracle_field(), make_odometry("recorded", seq),
                           dataclasses.replace(CONFIG, intrinsics_check_every=0)).run()
    np.testing.assert_array_equal(baseline.T_world_cam_estimate, both_always.T_world_cam_estimate)
    models = [k.intrinsics_model for k in baseline.keyframes]
    assert CONFIG.intrinsics_check_every == 5 and models[:5] == ["fixed"] * 5, models
    assert models[5:] == [("fixed" if (k + 1) % 5 == 0 else FIXED_ONLY) for k in range(5, len(models))], models
    assert all(k.intrinsics_model == "fixed" for k in both_always.keyframes)


@pytest.mark.slow
def test_a_run_whose_camera_is_wrong_keeps_fitting_both_models(walk):
    """Frames whose intrinsics are 10% and 10 px off (Evaluation K's HARSH cell): the
    self-calibrated model wins again and again, so the run never settles on the given
    camera, and its trajectory is that of a run fitting both at every keyframe."""
    seq = SimSequence(walk)

    class WrongCamera:
        def __init__(self, inner):
            self.inner = inner

        def __getattr__(self, name):
            return getattr(self.inner, name)

        def __len__(self):
            return len(self.inner)

        def __getitem__(self, i):
            frame = self.inner[i]
            return frame.with_intrinsics(frame.intrinsics.shifted(1.10, 10.0))

    wrong = WrongCamera(seq)
    runs = {every: Pipeline(wrong, seq.oracle_field(), make_odometry("recorded", seq),
                            dataclasses.replace(CONFIG, intrinsics_check_every=every)).run() for every in (5, 0)}
    models = [k.intrinsics_model for k in runs[5].keyframes]
    # Measured: 4 of 12 keyframes kept the self-calibrated model, never 5 fixed in a row.
    assert FIXED_ONLY not in models and sum(m.startswith("calibrated") for m in models) >= 3, models
    np.testing.assert_array_equal(runs[5].T_world_cam_estimate, runs[0].T_world_cam_estimate)
