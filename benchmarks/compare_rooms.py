"""EKF vs graph on simulated rooms: every estimator, odometry and IMU paths, several seeds.

Sequences: the embedded default's room (scene 0) with its default traversal and with three
more traversals (noise seeds 12-14), all corrected with the default room's trained field
(the embedded default's, cached in ``--cache``); and rooms 31-34 with the fields that
``benchmarks/drift_rooms.py`` trained and saved in its ``--workdir``. For each sequence and
path (the simulator's drifting odometry, and its IMU) one reference run measures the NAP3D
corrections, then every estimator runs on that stream (``nap3d_graph.evaluation.compare``).

Reported per sequence and pooled (mean, min, max over sequences): ATE of each row, NEES at
keyframes, ms per step; on the IMU path the final bias estimate of the run against the
simulator's true bias in sigmas. The default traversal's full comparison (CSV, JSON, TUM
trajectories, figures) is written to ``benchmarks/results/compare_default_<path>/``.

    python benchmarks/compare_rooms.py [--cache DIR] [--workdir /tmp/bench/drift_n]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from provenance import write_result


def sequences(cache: Path, workdir: Path, rooms) -> list[tuple[str, Path, object, dict | None]]:
    """(name, folder, field, timing override) of every sequence compared."""
    from nap3d_graph.fields import load_field
    from nap3d_graph.run.default import DEFAULT_SCENE_SEED, DEFAULT_TRAVERSE, embedded_default_inputs
    from nap3d_graph.sims.sequence import SimConfig, simulate_sequence

    walk, field, _, _ = embedded_default_inputs(cache, progress=True, say=print)
    out = [("room0_seed2", Path(walk), field, None)]
    for seed in (12, 13, 14):
        folder = cache / "compare" / f"room0_seed{seed}"
        if not (folder / "scene.json").exists():
            simulate_sequence(folder, SimConfig(scene_seed=DEFAULT_SCENE_SEED, **{**DEFAULT_TRAVERSE, "seed": seed}),
                              progress=True)
        out.append((f"room0_seed{seed}", folder, field, None))
    for room in rooms:
        folder, field_path = workdir / f"room{room}_walk", workdir / f"room{room}_field.pt"
        if field_path.exists():
            out.append((f"room{room}", folder, load_field(field_path), None))
        else:
            print(f"room {room}: no field at {field_path} (run benchmarks/drift_rooms.py first); skipped")
    return out


def compare_one(folder: Path, field, path: str, out_dir: Path | None) -> dict:
    from nap3d_graph.datasets import SimSequence
    from nap3d_graph.estimators import stream_from_run
    from nap3d_graph.evaluation.compare import compare, comparison_rows, write_comparison
    from nap3d_graph.motion.odometry import make_odometry
    from nap3d_graph.run.config import PipelineConfig
    from nap3d_graph.run.imu import ImuOdometry
    from nap3d_graph.run.pipeline import Pipeline

    seq = SimSequence(folder)
    config = PipelineConfig(progress=False)
    if path == "imu":
        odometry = ImuOdometry.from_sequence(seq)
        result = Pipeline(seq, field, odometry, config).run()
        stream = stream_from_run(result, seq, config, imu=odometry.stream, velocity0=odometry.velocity0)
    else:
        result = Pipeline(seq, field, make_odometry("recorded", seq), config).run()
        stream = stream_from_run(result, seq, config)
    results = compare(stream)
    rows = comparison_rows(stream, results)
    if out_dir is not None:
        write_comparison(out_dir, stream, results, rows, meta={"source": str(folder), "path": path})
    out = {"rows": {r["estimator"]: r for r in rows}, "corrections": len(stream.corrections),
           "keyframes": len(stream.keyframes)}
    if path == "imu" and result.imu_biases is not None and result.imu_bias_sigmas is not None:
        truth = np.loadtxt(folder / "imu_bias.txt")
        t_last = result.timestamps[result.keyframe_indices[-1]]
        true_last = truth[np.argmin(np.abs(truth[:, 0] - t_last)), 1:]
        z = (result.imu_biases[-1] - true_last) / result.imu_bias_sigmas[-1]
        out["bias_z_final"] = z.tolist()
        out["bias_true_final"] = true_last.tolist()
        out["bias_estimate_final"] = result.imu_biases[-1].tolist()
        out["bias_sigma_final"] = result.imu_bias_sigmas[-1].tolist()
    return out


def pooled(per_sequence: dict) -> dict:
    names = next(iter(per_sequence.values()))["rows"].keys()
    out = {}
    for name in names:
        stats = {}
        for key in ("ate_rmse_m", "ate_max_m", "nees_mean", "step_ms_mean"):
            values = np.array([s["rows"][name][key] for s in per_sequence.values()], dtype=float)
            values = values[np.isfinite(values)]
            if values.size:
                stats[key] = {"mean": float(values.mean()), "min": float(values.min()), "max": float(values.max())}
        out[name] = stats
    z = [s["bias_z_final"] for s in per_sequence.values() if "bias_z_final" in s]
    if z:
        z = np.abs(np.array(z))
        out["bias_abs_z_final"] = {"max": float(z.max()), "within_3_sigma": int((z < 3).all(axis=1).sum()),
                                   "sequences": len(z)}
    return out


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cache", type=Path, default=Path("/tmp/bench/cache"))
    p.add_argument("--workdir", type=Path, default=Path("/tmp/bench/drift_n"))
    p.add_argument("--rooms", type=int, nargs="+", default=[31, 32, 33, 34])
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/compare_rooms.json"))
    args = p.parse_args(argv)
    result = {"paths": {}}
    for path in ("odometry", "imu"):
        per_sequence = {}
        for name, folder, field, _ in sequences(args.cache, args.workdir, args.rooms):
            out_dir = args.out.parent / f"compare_default_{path}" if name == "room0_seed2" else None
            per_sequence[name] = compare_one(folder, field, path, out_dir)
            rows = per_sequence[name]["rows"]
            print(f"{path:8s} {name:12s} " + ", ".join(f"{k} {r['ate_rmse_m'] * 100:.2f} cm" for k, r in rows.items())
                  + (f"; bias |z| max {np.max(np.abs(per_sequence[name]['bias_z_final'])):.1f}"
                     if "bias_z_final" in per_sequence[name] else ""), flush=True)
        result["paths"][path] = {"per_sequence": per_sequence, "pooled": pooled(per_sequence)}
    write_result(args.out, result, args)


if __name__ == "__main__":
    main()
