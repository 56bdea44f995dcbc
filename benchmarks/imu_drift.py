"""IMU alone (NAP3D off): does the drift grow as the IMU's noise and bias model predict?

Monte Carlo: one smooth 60 s walk (the synthetic figure of eight), the simulator's 200 Hz
IMU drawn with ``--seeds`` different noise and bias realisations (initial biases 0.02 m/s^2
and 0.002 rad/s per axis, bias random walks 1e-4 m/s^3/sqrt(Hz) and 2e-6 rad/s^2/sqrt(Hz),
white noise 2e-3 and 2.4e-4 per sqrt(Hz)), dead-reckoned with GTSAM's preintegration from
the exact first state with a zero bias, as ``run --odom imu`` does without NAP3D.

Prediction: the error-state covariance (the filterpy ESKF's 15-state model) propagated
along the true motion from a covariance holding only the initial bias uncertainty, once
with everything, and once per source (initial bias, bias random walk, white noise) to show
which one drives the drift when. Reported: the RMS position error over the seeds against
the predicted RMS at 1, 2, 5, 10, 20, 30, 60 s, and a figure.

    python benchmarks/imu_drift.py [--seeds 40] [--out benchmarks/results/imu_drift.json]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from provenance import write_result

DURATION_S = 60.0
EVAL_HZ = 10.0


def _stream(trajectory, samples, config):
    from nap3d_graph.estimators import MeasurementStream
    from nap3d_graph.motion.imu import ImuStream

    stamps = np.arange(0.0, DURATION_S + 1e-9, 1.0 / EVAL_HZ)
    T_world_cam_gt = trajectory.poses(stamps)
    stream = MeasurementStream(stamps, [np.eye(4)] * len(stamps), [0], {}, {}, T_world_cam_gt[0], np.eye(6) * 1e-24,
                               T_world_cam_gt=T_world_cam_gt)
    stream.imu = ImuStream(samples["stamps"], samples["accel"], samples["gyro"], config)
    stream.velocity0 = trajectory.velocity_world(0.0)
    return stream


def dead_reckoning_errors(trajectory, seeds: int) -> np.ndarray:
    """(seeds, T) position error (m) of the IMU alone at the evaluation stamps."""
    from nap3d_graph.estimators import OdometryOnly, run_estimator
    from nap3d_graph.motion.imu import ImuConfig
    from nap3d_graph.sims.sensors import ImuNoise, simulate_imu

    errors = []
    for seed in range(seeds):
        samples = simulate_imu(trajectory, -0.05, DURATION_S + 0.05, ImuNoise(), np.random.default_rng(1000 + seed))
        stream = _stream(trajectory, samples, ImuConfig())
        result = run_estimator(OdometryOnly(), stream)
        errors.append(np.linalg.norm(result.T_causal[:, :3, 3] - stream.T_world_cam_gt[:, :3, 3], axis=1))
        print(f"seed {seed}: error at 10 s {errors[-1][int(10 * EVAL_HZ)] * 100:.1f} cm, at 60 s "
              f"{errors[-1][-1]:.2f} m", flush=True)
    return np.array(errors)


def predicted_rms(trajectory, which: str) -> np.ndarray:
    """RMS position error (m) the error-state model predicts, from the given sources only."""
    from nap3d_graph.estimators import ImuErrorStateEKF
    from nap3d_graph.motion.imu import ImuConfig
    from nap3d_graph.sims.sensors import ImuNoise, simulate_imu

    noise, tiny = ImuNoise(), 1e-12
    on = {"all": {"bias0", "walk", "white"}, "initial bias": {"bias0"}, "bias random walk": {"walk"},
          "white noise": {"white"}}[which]
    config = ImuConfig(
        accel_noise_density=noise.accel_noise_density if "white" in on else tiny,
        gyro_noise_density=noise.gyro_noise_density if "white" in on else tiny,
        accel_bias_rw=noise.accel_bias_walk if "walk" in on else tiny,
        gyro_bias_rw=noise.gyro_bias_walk if "walk" in on else tiny,
        velocity_prior_sigma=tiny,
        accel_bias_prior_sigma=noise.accel_bias_init_sigma if "bias0" in on else tiny,
        gyro_bias_prior_sigma=noise.gyro_bias_init_sigma if "bias0" in on else tiny)
    exact = simulate_imu(trajectory, -0.05, DURATION_S + 0.05, None, np.random.default_rng(0))
    stream = _stream(trajectory, exact, config)
    filt = ImuErrorStateEKF()
    rms = [0.0]
    filt.start(stream)
    for i in range(1, len(stream)):
        filt.step(i)
        rms.append(float(np.sqrt(np.trace(filt.kf.P[3:6, 3:6]))))
    return np.array(rms)


def main(argv=None) -> None:
    from nap3d_graph.estimators.synthetic import _trajectory

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=int, default=40)
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/imu_drift.json"))
    args = p.parse_args(argv)
    trajectory = _trajectory(DURATION_S + 1.0, rotate=True)
    errors = dead_reckoning_errors(trajectory, args.seeds)
    t = np.arange(errors.shape[1]) / EVAL_HZ
    mc_rms = np.sqrt(np.mean(errors**2, axis=0))
    predictions = {name: predicted_rms(trajectory, name)
                   for name in ("all", "initial bias", "bias random walk", "white noise")}
    at = [1, 2, 5, 10, 20, 30, 60]
    idx = [int(round(s * EVAL_HZ)) for s in at]
    table = [{"t_s": s, "mc_rms_m": float(mc_rms[i]), "predicted_rms_m": float(predictions["all"][i]),
              "ratio": float(mc_rms[i] / predictions["all"][i]),
              **{f"predicted_{k.replace(' ', '_')}_m": float(v[i]) for k, v in predictions.items() if k != "all"}}
             for s, i in zip(at, idx)]
    for row in table:
        print(f"t={row['t_s']:3d} s: Monte Carlo RMS {row['mc_rms_m']:.4f} m, predicted {row['predicted_rms_m']:.4f} m "
              f"(ratio {row['ratio']:.2f})")
    result = {"seeds": args.seeds, "duration_s": DURATION_S, "table": table,
              "note": "RMS over seeds; with N seeds a ratio within about 1 +- 2/sqrt(2N) agrees (chi distribution)"}
    write_result(args.out, result, args)
    _plot(args.out.with_suffix(".png"), t, errors, mc_rms, predictions)
    print(f"wrote {args.out} and {args.out.with_suffix('.png')}")


def _plot(path: Path, t, errors, mc_rms, predictions) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for e in errors:
        ax.plot(t[1:], e[1:], color="0.8", lw=0.6)
    ax.plot(t[1:], mc_rms[1:], "k-", lw=2.2, label=f"IMU alone, RMS over {len(errors)} seeds")
    styles = {"all": ("tab:red", "--", 2.0), "initial bias": ("tab:blue", ":", 1.4),
              "bias random walk": ("tab:green", ":", 1.4), "white noise": ("tab:purple", ":", 1.4)}
    for name, rms in predictions.items():
        colour, ls, lw = styles[name]
        ax.plot(t[1:], rms[1:], ls, color=colour, lw=lw, label=f"predicted: {name}")
    ax.set(xscale="log", yscale="log", xlabel="time (s)", ylabel="position error (m)",
           title="IMU dead reckoning: drift against the noise model's prediction")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
