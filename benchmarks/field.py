"""Benchmark the torch grid field on the default simulated room (issue 5's targets).

Simulates the default room's (scene seed 0) mapping survey and a second survey path as a
novel-view set, trains a field for ``--minutes`` (evaluated at 60 s on the way), and measures:

* held-out PSNR and median / p90 absolute depth error against the simulator's noise-free
  depth, on frames of the survey kept out of training and on the second path's frames;
* mean opacity on surfaces and the paper's unit check (sensor vs field depth, R^2);
* render time (RGB + depth + opacity) at 320x240 and 640x480;
* peak memory (``resource.getrusage`` max RSS of this process);
* NAP3D: ``align_views`` between held-out sensor frames and the field's render at a 5 cm /
  3 degree perturbed pose: inliers and the corrected pose's error (oracle field alongside).

Prints a table and writes JSON (``--out``). Usage::

    python benchmarks/field.py --minutes 5 --out benchmarks/results/field.json
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from provenance import write_result

TARGETS = {
    "psnr_db": (">=", 28.0),
    "depth_median_cm": ("<=", 0.5),
    "render_320x240_s": ("<=", 0.25),
    "render_640x480_s": ("<=", 0.8),
    "peak_memory_gib": ("<=", 4.0),
    "nap3d_median_inliers": (">=", 100),
}


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--minutes", type=float, default=5.0, help="training budget (default 5)")
    p.add_argument("--frames", type=int, default=300, help="survey frames (default 300)")
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--novel-frames", type=int, default=40, help="frames of the second survey path (default 40)")
    p.add_argument("--nap3d-frames", type=int, default=12, help="frames for the NAP3D check (default 12)")
    p.add_argument("--threads", type=int, default=None,
                   help="torch threads for training and rendering (default 1, see nap3d_graph.torch_threads)")
    p.add_argument("--workdir", type=Path, default=None, help="where to simulate (default: a temp folder)")
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/field.json"))
    p.add_argument("--seed", type=int, default=0)
    return p.parse_args(argv)


def simulate(workdir: Path, args):
    from nap3d_graph.datasets import SimSequence
    from nap3d_graph.sims.sequence import SimConfig, simulate_sequence

    survey = workdir / "room0_survey"
    novel = workdir / "room0_novel"
    if not (survey / "scene.json").exists():
        simulate_sequence(survey, SimConfig(frames=args.frames, path="mapping", scene_seed=0, seed=1,
                                            width=args.width, height=args.height), progress=True)
    if not (novel / "scene.json").exists():
        simulate_sequence(novel, SimConfig(frames=args.novel_frames, path="mapping", scene_seed=0, seed=2,
                                           width=args.width, height=args.height), progress=True)
    return SimSequence(survey), SimSequence(novel)


def render_times(field, poses, intrinsics, repeats: int = 8) -> dict:
    out = {}
    for width, height in ((320, 240), (640, 480)):
        K = intrinsics.scaled(width, height)
        field.render(poses[0], K)  # warm-up (occupancy cache, allocator)
        times = []
        for k in range(repeats):
            started = time.perf_counter()
            field.render(poses[k % len(poses)], K)
            times.append(time.perf_counter() - started)
        out[f"{width}x{height}"] = {"median_s": float(np.median(times)), "max_s": float(np.max(times)),
                                    "min_s": float(np.min(times))}
    return out


def nap3d_check(field, sequence, indices, seed: int) -> dict:
    """align_views between sensor frames and renders at 5 cm / 3 deg perturbed poses."""
    from nap3d_graph import align_views
    from nap3d_graph.conventions import exp_so3, inv_T, pose_error

    rng = np.random.default_rng(seed)
    rows = []
    for i in indices:
        T_true = sequence.T_world_cam_gt[i]
        axis = rng.normal(size=3)
        direction = rng.normal(size=3)
        dT = np.eye(4)
        dT[:3, :3] = exp_so3(axis / np.linalg.norm(axis) * np.radians(3.0))
        dT[:3, 3] = direction / np.linalg.norm(direction) * 0.05
        T_world_cam_est = T_true @ dT
        view = field.render(T_world_cam_est, sequence.intrinsics)
        alignment = align_views(sequence[i], view)
        row = {"frame": int(i), "inliers": int(alignment.num_inliers), "matches": int(alignment.num_matches),
               "success": bool(alignment.success), "reason": alignment.reason}
        if alignment.success:
            T_corr = T_world_cam_est @ inv_T(alignment.T_real_rendered)
            t_err, r_err = pose_error(T_corr, T_true)
            row.update({"corrected_err_cm": 100 * t_err, "corrected_err_deg": r_err})
        rows.append(row)
    inliers = np.array([r["inliers"] for r in rows])
    ok = [r for r in rows if r["success"]]
    return {
        "frames": rows,
        "median_inliers": float(np.median(inliers)) if len(inliers) else 0.0,
        "fraction_ge_100": float(np.mean(inliers >= 100)) if len(inliers) else 0.0,
        "success_rate": len(ok) / max(len(rows), 1),
        "median_corrected_err_cm": float(np.median([r["corrected_err_cm"] for r in ok])) if ok else None,
        "median_corrected_err_deg": float(np.median([r["corrected_err_deg"] for r in ok])) if ok else None,
    }


def summarise(evaluation: dict) -> dict:
    depth = evaluation["depth_abs_err_m"]
    return {
        "psnr_db": evaluation["psnr_db"],
        "depth_median_cm": None if depth["median"] is None else 100 * depth["median"],
        "depth_p90_cm": None if depth["p90"] is None else 100 * depth["p90"],
        "opacity_on_surfaces": evaluation["opacity_on_surfaces"],
        "unit_check": evaluation["unit_check"],
    }


def _fmt(value, digits=2):
    if value is None:
        return "n/a"
    return f"{value:.{digits}f}"


def _verdict(key, value):
    if key not in TARGETS or value is None:
        return ""
    op, bound = TARGETS[key]
    ok = value >= bound if op == ">=" else value <= bound
    return f"{op} {bound}  {'ok' if ok else 'MISS'}"


def main(argv=None) -> int:
    args = parse_args(argv)
    from nap3d_graph.fields.evaluation import evaluate_field
    from nap3d_graph.fields.train_config import TrainConfig
    from nap3d_graph.fields.training import train_field

    tmp = None
    workdir = args.workdir
    if workdir is None:
        tmp = tempfile.TemporaryDirectory(prefix="nap3d_field_bench_")
        workdir = Path(tmp.name)
    workdir.mkdir(parents=True, exist_ok=True)

    started = time.perf_counter()
    survey, novel = simulate(workdir, args)
    simulate_s = time.perf_counter() - started

    config = TrainConfig(minutes=args.minutes, seed=args.seed)
    if args.threads:
        config.threads = args.threads
    snapshots = [60.0] if args.minutes * 60 > 60 else []
    cpu0 = time.process_time()
    field, report = train_field(survey, config, progress=True, snapshot_seconds=snapshots)
    train_cpu_s = time.process_time() - cpu0
    peak_gib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2  # Linux: KiB

    if args.threads:
        from dataclasses import replace

        field.render_config = replace(field.render_config, threads=args.threads)
    novel_indices = np.unique(np.round(np.linspace(0, len(novel) - 1, min(10, len(novel)))).astype(int))
    novel_eval = evaluate_field(field, novel, novel_indices, novel.oracle_field())
    timing = render_times(field, novel.T_world_cam_gt[novel_indices], novel.intrinsics)
    nap_indices = np.unique(np.round(np.linspace(0, len(novel) - 1, min(args.nap3d_frames, len(novel)))).astype(int))
    nap = nap3d_check(field, novel, nap_indices, args.seed)
    nap_oracle = nap3d_check(novel.oracle_field(), novel, nap_indices, args.seed)

    at_60 = next((s for s in report["snapshots"] if abs(s["train_seconds"] - 60.0) < 5.0), None)
    results = {
        "machine": {"platform": platform.platform(), "python": sys.version.split()[0], "torch": torch.__version__,
                    "cpu_count": os.cpu_count(), "train_threads": config.threads,
                    "render_threads": field.render_config.threads, "cuda": torch.cuda.is_available(),
                    "load_average_after": list(os.getloadavg())},
        "data": {"survey_frames": len(survey), "novel_frames": len(novel), "size": [args.width, args.height],
                 "simulate_s": simulate_s},
        "minutes": args.minutes,
        "field": report["field"],
        "train_seconds": report["train_seconds"],
        "train_cpu_seconds": train_cpu_s,
        "steps": report["steps"],
        "held_out": summarise(report["held_out"]),
        "held_out_at_60s": summarise(at_60) if at_60 else None,
        "novel_path": summarise(novel_eval),
        "render": timing,
        "peak_memory_gib": peak_gib,
        "nap3d": nap,
        "nap3d_oracle": nap_oracle,
        "targets": {k: list(v) for k, v in TARGETS.items()},
    }
    print_table(results)
    write_result(args.out, results, args)
    print(f"\nwrote {args.out}")
    if tmp is not None:
        tmp.cleanup()
    return 0


def print_table(r: dict) -> None:
    held, novel, at60 = r["held_out"], r["novel_path"], r["held_out_at_60s"] or {}
    minutes = r["minutes"]
    lines = [
        ("held-out PSNR (dB)", at60.get("psnr_db"), held["psnr_db"], "psnr_db"),
        ("held-out depth err median (cm)", at60.get("depth_median_cm"), held["depth_median_cm"], "depth_median_cm"),
        ("held-out depth err p90 (cm)", at60.get("depth_p90_cm"), held["depth_p90_cm"], None),
        ("held-out opacity on surfaces", at60.get("opacity_on_surfaces"), held["opacity_on_surfaces"], None),
        ("novel-path PSNR (dB)", None, novel["psnr_db"], None),
        ("novel-path depth err median (cm)", None, novel["depth_median_cm"], None),
        ("novel-path depth err p90 (cm)", None, novel["depth_p90_cm"], None),
        ("unit check R^2 (held-out)", None, held["unit_check"]["r2"], None),
        ("render 320x240 median (s)", None, r["render"]["320x240"]["median_s"], "render_320x240_s"),
        ("render 640x480 median (s)", None, r["render"]["640x480"]["median_s"], "render_640x480_s"),
        ("peak memory (GiB)", None, r["peak_memory_gib"], "peak_memory_gib"),
        ("NAP3D median inliers (5 cm / 3 deg)", None, r["nap3d"]["median_inliers"], "nap3d_median_inliers"),
        ("NAP3D frames with >= 100 inliers", None, r["nap3d"]["fraction_ge_100"], None),
        ("NAP3D corrected error median (cm)", None, r["nap3d"]["median_corrected_err_cm"], None),
        ("NAP3D oracle median inliers", None, r["nap3d_oracle"]["median_inliers"], None),
    ]
    m = r["machine"]
    print(f"\nfield benchmark: {r['field']}, {r['steps']} steps in {r['train_seconds']:.0f} s "
          f"(torch threads: training {m['train_threads']}, rendering {m['render_threads']}; "
          f"load average after {m['load_average_after'][0]:.1f} on {m['cpu_count']} CPUs)")
    print(f"{'metric':40s} {'60 s':>9s} {f'{minutes:g} min':>9s}   target")
    for name, v60, vend, key in lines:
        print(f"{name:40s} {_fmt(v60):>9s} {_fmt(vend, 3 if 'render' in name else 2):>9s}   {_verdict(key, vend)}")


if __name__ == "__main__":
    sys.exit(main())
