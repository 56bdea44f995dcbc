"""EKF vs graph: the estimators, the IMU path and the comparison command."""

import csv
import json
import re

import gtsam
import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

from nap3d_graph.conventions import exp_se3, inv_T, log_se3, pose3_to_T
from nap3d_graph.datasets.sim import SimSequence
from nap3d_graph.estimators import (
    BatchLM,
    ErrorStateEKF,
    ImuErrorStateEKF,
    Isam2Estimator,
    NavStateEKF,
    OdometryOnly,
    default_estimators,
    run_estimator,
    stream_from_run,
)
from nap3d_graph.estimators.synthetic import synthetic_stream
from nap3d_graph.evaluation.compare import compare, comparison_rows
from nap3d_graph.motion.imu import ImuConfig, ImuStream
from nap3d_graph.motion.odometry import make_odometry
from nap3d_graph.run.config import PipelineConfig
from nap3d_graph.run.imu import ImuOdometry
from nap3d_graph.run.pipeline import Pipeline

CONFIG = PipelineConfig(keyframe_every=5, render_width=None, render_height=None, progress=False)


@pytest.fixture(scope="module")
def walk(sim_walk):
    """A 60-frame traversal at 10 Hz with drifting odometry and a 200 Hz IMU."""
    return sim_walk(60, fps=10.0, width=192, height=144)


@pytest.fixture(scope="module")
def odometry_run(walk):
    seq = SimSequence(walk)
    result = Pipeline(seq, seq.oracle_field(), make_odometry("recorded", seq), CONFIG).run()
    return seq, result, stream_from_run(result, seq, CONFIG)


@pytest.fixture(scope="module")
def imu_run(walk):
    seq = SimSequence(walk)
    odometry = ImuOdometry.from_sequence(seq)
    result = Pipeline(seq, seq.oracle_field(), odometry, CONFIG).run()
    return seq, result, stream_from_run(result, seq, CONFIG, imu=odometry.stream, velocity0=odometry.velocity0)


# --- the error-state EKF is a Kalman filter -------------------------------------------------

def test_eskf_matches_a_plain_kalman_filter_on_a_linear_gaussian_case():
    # Pure translations (the camera's attitude is constant): the SE(3) error-state filter is
    # then exactly a linear KF on the world position (body-frame quantities rotated by R0).
    stream = synthetic_stream(120, keyframe_every=4, seed=5, rotate=False, gate_p=1 - 1e-12)
    R0 = stream.T_world_cam0[:3, :3]
    eskf = ErrorStateEKF()
    result = run_estimator(eskf, stream)
    kf = KalmanFilter(dim_x=3, dim_z=3)
    kf.x = stream.T_world_cam0[:3, 3].reshape(3, 1).copy()
    kf.P = stream.P0[3:, 3:].copy()
    kf.F, kf.H = np.eye(3), np.eye(3)
    for k in stream.keyframes[1:]:
        T_int, Q = stream.interval_odometry[k]
        kf.predict(u=(R0 @ T_int[:3, 3]).reshape(3, 1), B=np.eye(3), Q=R0 @ Q[3:, 3:] @ R0.T)
        Z, R = stream.corrections[k]
        kf.update(Z[:3, 3].reshape(3, 1), R=R0 @ R[3:, 3:] @ R0.T)
        np.testing.assert_allclose(result.T_causal[k][:3, 3], kf.x.ravel(), rtol=0, atol=1e-12)
        np.testing.assert_allclose(result.T_causal[k][:3, :3], R0, atol=1e-12)
        np.testing.assert_allclose(R0 @ result.P_causal[k][3:, 3:] @ R0.T, kf.P, rtol=1e-9, atol=1e-18)
    assert len(eskf.accepted) == len(stream.keyframes) - 1


def test_estimators_are_consistent_on_known_noise():
    """On a stream drawn from exactly the stated noise, filters and smoothers agree with
    theory: NEES near 6, the smoother no worse than the filter, causal EKF ~ causal iSAM2."""
    stream = synthetic_stream(600, seed=2)
    rows = {r["estimator"]: r for r in comparison_rows(stream, compare(stream))}
    for name in ("eskf", "isam2-causal", "isam2-final", "batch-lm"):
        assert 4.5 < rows[name]["nees_mean"] < 7.5, (name, rows[name]["nees_mean"])
    assert rows["isam2-final"]["ate_rmse_m"] < rows["eskf"]["ate_rmse_m"]
    assert rows["batch-lm"]["ate_rmse_m"] < rows["eskf"]["ate_rmse_m"]
    assert rows["isam2-causal"]["ate_rmse_m"] == pytest.approx(rows["eskf"]["ate_rmse_m"], rel=0.1)


# --- the simulator: every estimator beats odometry alone -----------------------------------

def test_every_estimator_beats_odometry_on_the_simulator(odometry_run, imu_run):
    for _, _, stream in (odometry_run, imu_run):
        rows = {r["estimator"]: r for r in comparison_rows(stream, compare(stream))}
        odometry = rows.pop("odometry")["ate_rmse_m"]
        assert len(rows) == (6 if stream.imu is not None else 4) - 1 + (1 if stream.imu is None else 0)
        for name, row in rows.items():
            assert row["ate_rmse_m"] < 0.5 * odometry, (name, row["ate_rmse_m"], odometry)
            assert row["ate_rmse_m"] < 0.02, name
        assert rows["isam2-final"]["ate_rmse_m"] <= 1.1 * rows["eskf"]["ate_rmse_m"]


def test_isam2_estimator_reproduces_the_run(odometry_run):
    """The graph estimator on the stream is the run's own graph: its causal trajectory is the
    run's estimate_online, to well under a millimetre."""
    seq, result, stream = odometry_run
    est = run_estimator(Isam2Estimator(), stream)
    diff = np.linalg.norm(est.T_causal[:, :3, 3] - result.T_world_cam_online[:, :3, 3], axis=1)
    assert diff.max() < 2e-4


# --- causality ------------------------------------------------------------------------------

def _perturbed(stream, frame: int, shift_m: float):
    import copy

    other = copy.deepcopy(stream)
    Z, R = other.corrections[frame]
    other.corrections[frame] = (Z @ exp_se3(np.r_[0, 0, 0, shift_m, 0, 0]), R)
    return other


@pytest.mark.parametrize("imu", [False, True])
def test_causal_trajectories_never_use_a_later_measurement(imu):
    stream = synthetic_stream(150, seed=4, imu=imu)
    late = stream.keyframes[-5]
    moved = _perturbed(stream, late, 0.006)  # 1.5 sigma: inside every gate
    for a, b in zip(default_estimators(stream), default_estimators(moved)):
        ra, rb = run_estimator(a, stream), run_estimator(b, moved)
        np.testing.assert_array_equal(ra.T_causal[:late], rb.T_causal[:late], err_msg=a.name)
        if a.name not in ("odometry", "batch-lm"):  # batch LM has no causal estimate of its own
            assert np.abs(ra.T_causal[late:] - rb.T_causal[late:]).max() > 1e-4, a.name
        if "final" in ra.reports:  # a smoother's final trajectory does move before it
            assert np.abs(ra.T_final[:late] - rb.T_final[:late]).max() > 1e-5, a.name


def test_the_runs_causal_trajectory_never_uses_a_later_correction(walk, odometry_run):
    import dataclasses

    seq, result, _ = odometry_run
    late = result.keyframe_indices[-3]

    def hook(i, correction):
        if i != late or not correction.success:
            return correction
        T = correction.T_world_cam_corrected @ exp_se3(np.r_[0, 0, 0, 0.004, 0, 0])
        return dataclasses.replace(correction, T_world_cam_corrected=T)

    moved = Pipeline(seq, seq.oracle_field(), make_odometry("recorded", seq), CONFIG, correction_hook=hook).run()
    np.testing.assert_allclose(moved.T_world_cam_online[:late], result.T_world_cam_online[:late], atol=1e-12)
    assert np.abs(moved.T_world_cam_estimate[:late] - result.T_world_cam_estimate[:late]).max() > 1e-5


# --- the IMU path ---------------------------------------------------------------------------

def test_imu_factors_reproduce_ground_truth_motion_between_keyframes():
    from nap3d_graph.sims.sensors import simulate_imu

    stream = synthetic_stream(60, seed=1)
    from nap3d_graph.estimators.synthetic import _trajectory

    trajectory = _trajectory(5.0, rotate=True)
    exact = simulate_imu(trajectory, -0.05, 4.5, None, np.random.default_rng(0))
    imu = ImuStream(exact["stamps"], exact["accel"], exact["gyro"])
    for a, b in zip(stream.keyframes[:-1], stream.keyframes[1:]):
        ta, tb = stream.timestamps[a], stream.timestamps[b]
        Ta = trajectory.T_world_cam(ta)
        nav = gtsam.NavState(gtsam.Rot3(Ta[:3, :3]), Ta[:3, 3], trajectory.velocity_world(ta))
        predicted = pose3_to_T(imu.preintegrate(ta, tb).predict(nav, gtsam.imuBias.ConstantBias()).pose())
        error = log_se3(inv_T(trajectory.T_world_cam(tb)) @ predicted)
        assert np.linalg.norm(error[3:]) < 2e-4 and np.linalg.norm(error[:3]) < 1e-4


def test_imu_run_removes_drift_and_estimates_the_biases(walk, imu_run):
    seq, result, _ = imu_run
    from nap3d_graph.evaluation.metrics import ate

    drift = ate(result.timestamps, result.T_world_cam_gt, result.T_world_cam_odometry)["rmse"]
    fixed = ate(result.timestamps, result.T_world_cam_gt, result.T_world_cam_estimate)["rmse"]
    assert drift > 0.05 and fixed < 0.01
    truth = np.loadtxt(walk / "imu_bias.txt")
    kf_stamps = result.timestamps[result.keyframe_indices]
    true_at_kf = np.array([truth[np.argmin(np.abs(truth[:, 0] - t)), 1:] for t in kf_stamps])
    z = (result.imu_biases - true_at_kf) / result.imu_bias_sigmas
    assert np.all(np.abs(z[-1]) < 3.0), z[-1]
    assert np.all(result.imu_bias_sigmas[-1] < [0.05] * 3 + [0.005] * 3)  # learnt something


def test_imu_gaps_and_nan_samples_are_recorded_skips(walk):
    seq = SimSequence(walk)
    imu = {k: np.array(v, dtype=float, copy=True) for k, v in seq.imu.items()}
    imu["accel"][300] = np.nan  # one bad sample
    t_gap = float(seq.timestamps[33])
    keep = (imu["stamps"] < t_gap - 0.1) | (imu["stamps"] > t_gap + 0.05)  # 150 ms lost
    seq.imu = {k: v[keep] if len(v) == len(keep) else v for k, v in imu.items()}
    odometry = ImuOdometry.from_sequence(seq)
    reasons = [r for _, r in odometry.stream.skipped]
    assert any("non-finite" in r for r in reasons) and any(re.search(r"IMU gap of 0\.1[56]\d s", r) for r in reasons)
    result = Pipeline(seq, seq.oracle_field(), odometry, CONFIG).run()
    noted = [k for k in result.keyframes if "IMU gap" in k.reason or "non-finite" in k.reason]
    assert noted and result.imu_skipped
    assert np.all(np.isfinite(result.T_world_cam_estimate))


def test_navstate_ekf_refuses_the_odometry_path_and_a_lever_arm():
    stream = synthetic_stream(30, seed=1)
    with pytest.raises(ValueError, match="IMU path"):
        NavStateEKF().start(stream)
    stream = synthetic_stream(30, seed=1, imu=True)
    stream.imu.config = ImuConfig(T_cam_imu=exp_se3(np.r_[0, 0, 0, 0.02, 0, 0]))
    with pytest.raises(ValueError, match="identity extrinsics"):
        NavStateEKF().start(stream)
    assert not any(isinstance(e, NavStateEKF) for e in default_estimators(stream))
    assert any(isinstance(e, ImuErrorStateEKF) for e in default_estimators(stream))


# --- the command ----------------------------------------------------------------------------

@pytest.mark.slow
def test_compare_command_writes_what_evo_loads_and_prints_the_same_numbers(walk, tmp_path, capsys):
    import csv
    import json

    from evo.core import metrics, sync
    from evo.tools import file_interface

    from nap3d_graph.cli import main

    out = tmp_path / "cmp"
    assert main(["compare", "--traj", "sim", "--data", str(walk), "--field", "oracle", "--odom", "imu",
                 "--render-size", "192x144", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    # Its configuration is written first (an interrupted comparison still says what it was);
    # a finished one carries no PARTIAL marker.
    assert json.loads((out / "config.json").read_text())["settings"]["odometry"]["kind"] == "imu"
    assert not (out / "PARTIAL.txt").exists()
    with open(out / "comparison.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["estimator"] for r in rows] == ["odometry", "eskf", "navstate-ekf", "isam2-causal", "isam2-final",
                                              "batch-lm"]
    gt = file_interface.read_tum_trajectory_file(str(out / "groundtruth.txt"))
    for row in rows:
        line = next(l for l in printed.splitlines() if l.startswith(row["estimator"] + " "))
        values = re.split(r"\s+", line.strip())
        assert float(values[1]) == pytest.approx(float(row["ate_rmse_m"]) * 100, abs=6e-4)
        assert float(values[3]) == pytest.approx(float(row["ate_max_m"]) * 100, abs=6e-4)
        if row["nees_mean"] not in ("", "nan"):
            assert float(values[5]) == pytest.approx(float(row["nees_mean"]), abs=6e-3)
        est = file_interface.read_tum_trajectory_file(str(out / "trajectories" / f"{row['estimator']}.txt"))
        ref, est = sync.associate_trajectories(gt, est, max_diff=1e-3)
        ape = metrics.APE(metrics.PoseRelation.translation_part)
        ape.process_data((ref, est))
        assert ape.get_statistic(metrics.StatisticsType.rmse) == pytest.approx(float(row["ate_rmse_m"]), abs=2e-6)
    assert (out / "trajectories.png").stat().st_size > 10_000 and (out / "errors.png").stat().st_size > 10_000


def test_batch_lm_takes_every_correction_and_odometry_none():
    stream = synthetic_stream(60, seed=3)
    assert len(run_estimator(BatchLM(), stream).accepted) == len(stream.corrections)
    assert run_estimator(OdometryOnly(), stream).accepted == []


@pytest.mark.slow
def test_run_command_with_the_imu_writes_the_biases(walk, tmp_path, capsys):
    import json

    from nap3d_graph.cli import main

    assert main(["run", "--traj", "sim", "--data", str(walk), "--field", "oracle", "--odom", "imu",
                 "--render-size", "192x144", "--imu-noise", "2e-3 2.4e-4 1e-4 2e-6", "--out", str(tmp_path)]) == 0
    run = tmp_path / "latest"
    biases = np.loadtxt(run / "biases.txt")
    assert biases.shape[1] == 13 and np.all(np.isfinite(biases))
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["estimate"]["ate_m"]["rmse"] < 0.01
    assert metrics["estimate_online"]["ate_m"]["rmse"] < 0.02  # the causal trajectory is written too
    assert metrics["odometry"]["ate_m"]["rmse"] > 0.05
    assert "with NAP3D, causal" in capsys.readouterr().out
    assert main(["run", "--traj", "sim", "--data", str(walk), "--field", "oracle", "--odom", "imu",
                 "--imu-noise", "1 2 3", "--out", str(tmp_path)]) == 2
    assert "--imu-noise needs 4 positive numbers" in capsys.readouterr().err
    assert main(["run", "--traj", "sim", "--data", str(walk), "--field", "oracle", "--odom", "imu", "--overlap",
                 "--out", str(tmp_path)]) == 2
    assert "--overlap does not apply to --odom imu" in capsys.readouterr().err


@pytest.mark.slow
def test_an_overlapped_run_from_the_command_line(walk, tmp_path, capsys):
    """``run --overlap --render-ahead``: the keyframes are measured on the second thread, each
    due keyframe's features detected beside its odometry, the next one rendered ahead; the
    choice is recorded in config.yaml and the drift is removed as inline."""
    import yaml

    from nap3d_graph.cli import main

    assert main(["run", "--traj", "sim", "--data", str(walk), "--field", "oracle", "--render-ahead",
                 "--out", str(tmp_path)]) == 2
    assert "--render-ahead works ahead on the second thread: it needs --overlap" in capsys.readouterr().err
    assert main(["run", "--traj", "sim", "--data", str(walk), "--field", "oracle", "--land-within", "frame",
                 "--out", str(tmp_path)]) == 2
    assert "--land-within waits for the second thread's correction: it needs --overlap" in capsys.readouterr().err
    assert main(["run", "--traj", "sim", "--data", str(walk), "--field", "oracle", "--keyframe-when-idle", "2",
                 "--out", str(tmp_path)]) == 2
    assert "--keyframe-when-idle takes keyframes while the second thread is idle" in capsys.readouterr().err
    assert main(["run", "--traj", "sim", "--data", str(walk), "--field", "oracle", "--land-within", "-1"]) == 2
    assert main(["run", "--traj", "sim", "--data", str(walk), "--field", "oracle", "--overlap", "--render-ahead",
                 "--pace", "4", "--out", str(tmp_path)]) == 0  # paced and overlapped: --land-within frame
    run = tmp_path / "latest"
    config = yaml.safe_load((run / "config.yaml").read_text())
    pipeline = config["resolved"]["pipeline"]
    assert pipeline["overlap"] is True and pipeline["render_ahead"] is True and pipeline["detect_ahead"] is True
    # 'frame': 0.9 of the walk's frame period, recorded in seconds; fed at 4x the camera's rate.
    period_s = float(np.median(np.diff(SimSequence(walk).timestamps)))
    assert pipeline["land_within_s"] == pytest.approx(0.9 * period_s)
    assert config["settings"]["source"]["pace"] == 4.0
    paced = json.loads((run / "metrics.json").read_text())["paced"]
    assert paced["speed"] == 4.0 and paced["frames"] == 60 and paced["behind_camera_s"]["max"] >= 0
    assert "paced at 4x the camera's rate" in capsys.readouterr().out
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["corrections_accepted"] >= 0.8 * metrics["keyframes"]
    assert metrics["estimate"]["ate_m"]["rmse"] < 0.4 * metrics["odometry"]["ate_m"]["rmse"], metrics
    with open(run / "corrections.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == metrics["keyframes"]
    # Every keyframe after the first had its features detected ahead; its time is in the row.
    assert all(float(r["t_detect_ahead_s"]) > 0 for r in rows[1:]), [r["t_detect_ahead_s"] for r in rows]


@pytest.mark.slow
def test_a_paced_run_takes_the_live_settings_by_default(walk, tmp_path, capsys):
    """``run --pace`` without ``--overlap``: fed as a camera delivers the frames, the run
    overlaps, waits up to 0.9 of a frame period for a correction and takes a keyframe whenever
    the second thread is idle; ``--no-overlap`` keeps it inline, and an unpaced replay is inline."""
    import yaml

    from nap3d_graph.cli import main

    period_s = float(np.median(np.diff(SimSequence(walk).timestamps)))
    settings = {}
    for name, extra in (("live", ["--pace", "8"]), ("inline", ["--pace", "8", "--no-overlap"]), ("replay", [])):
        out = tmp_path / name
        assert main(["run", "--traj", "sim", "--data", str(walk), "--field", "oracle", "--max-frames", "30",
                     "--out", str(out), *extra]) == 0
        settings[name] = yaml.safe_load((out / "latest" / "config.yaml").read_text())["resolved"]["pipeline"]
        said = capsys.readouterr().out
        if name == "live":
            assert "paced at 8x the camera's rate (overlapped, waiting up to" in said and "whenever" in said
        elif name == "inline":
            assert "paced at 8x the camera's rate (inline)" in said
        metrics = json.loads((out / "latest" / "metrics.json").read_text())
        assert metrics["estimate"]["ate_m"]["rmse"] < 0.5 * metrics["odometry"]["ate_m"]["rmse"], (name, metrics)
    live = settings["live"]
    assert live["overlap"] is True and live["keyframe_when_idle"] == 1
    assert live["land_within_s"] == pytest.approx(0.9 * period_s)
    for name in ("inline", "replay"):
        assert settings[name]["overlap"] is False and settings[name]["keyframe_when_idle"] == 0
        assert settings[name]["land_within_s"] == 0.0


@pytest.mark.slow
def test_a_paced_feature_odometry_works_at_the_renders_width(walk, tmp_path, capsys):
    """``run --pace --odom vo``: fed as a live camera, the feature odometry works at the
    render's width and hands its features to the corrections, said on the terminal and kept in
    config.yaml; an unpaced run keeps the frames as read, and ``--vo-width`` overrides."""
    import yaml

    from nap3d_graph.cli import main

    widths = {}
    for name, extra in (("paced", ["--pace", "8"]), ("replay", []), ("given", ["--pace", "8", "--vo-width", "96"])):
        out = tmp_path / name
        assert main(["run", "--traj", "sim", "--data", str(walk), "--field", "oracle", "--odom", "vo",
                     "--render-size", "128x96", "--max-frames", "12", "--out", str(out), *extra]) == 0
        widths[name] = yaml.safe_load((out / "latest" / "config.yaml").read_text())["settings"]["odometry"]["vo_width"]
        said = capsys.readouterr().out
        assert ("frames resized to 128 px wide" in said) == (name == "paced"), (name, said)
    assert widths == {"paced": 128, "replay": None, "given": 96}


@pytest.mark.slow
def test_a_paced_run_that_falls_behind_its_camera_says_what_keeps_up(walk, tmp_path, capsys):
    """Fed far faster than it measures (500x the walk's camera), an inline run falls behind:
    the run warns, with a keyframe's measurement time, and names what keeps up."""
    from nap3d_graph.cli import main

    assert main(["run", "--traj", "sim", "--data", str(walk), "--field", "oracle", "--max-frames", "20",
                 "--pace", "500", "--no-overlap", "--out", str(tmp_path)]) == 0
    err = capsys.readouterr().err
    assert "the run fell behind the camera at " in err and "keyframe's measurement took" in err, err
    assert "train-field --model views" in err
    paced = json.loads((tmp_path / "latest" / "metrics.json").read_text())["paced"]
    assert paced["frames_over_a_period_late"] > 2
    # Handed over at 500x the walk's own rate.
    period_s = float(np.median(np.diff(SimSequence(walk).timestamps)))
    assert paced["camera_hz"] == pytest.approx(500.0 / period_s, rel=1e-3)
    assert f"against the camera's {paced['camera_hz']:.1f} Hz" in err


def test_imu_run_survives_a_failed_isam2_update(walk, monkeypatch):
    """iSAM2's Cholesky step can report an indeterminate system on a graph that is well posed
    as a whole (seen on the IMU path: a loosely weighted first correction beside the bias
    random walk's ~1e12 information). The run then rebuilds iSAM2 from every factor so far
    (batch LM, then QR) and goes on; here the fourth update is made to fail."""
    import gtsam

    seq = SimSequence(walk)
    real_isam2 = gtsam.ISAM2
    calls = {"n": 0}

    class Flaky:
        def __init__(self, params):
            self._isam = real_isam2(params)

        def update(self, *args):
            calls["n"] += 1
            if calls["n"] == 4:
                raise RuntimeError("\nIndeterminate linear system detected while working near variable x1")
            return self._isam.update(*args)

        def __getattr__(self, name):
            return getattr(self._isam, name)

    monkeypatch.setattr(gtsam, "ISAM2", Flaky)
    odometry = ImuOdometry.from_sequence(seq)
    pipeline = Pipeline(seq, seq.oracle_field(), odometry, CONFIG)
    result = pipeline.run()
    assert pipeline.state.graph.rebuilds == 1
    assert result.num_accepted >= 0.8 * len(result.keyframes)
    errors = [np.linalg.norm(a[:3, 3] - b[:3, 3]) for a, b in zip(result.T_world_cam_estimate, result.T_world_cam_gt)]
    assert np.sqrt(np.mean(np.square(errors))) < 0.01
