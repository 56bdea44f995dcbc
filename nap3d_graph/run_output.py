"""The results folder of a run (KISS-ICP style).

``config.yaml``, TUM trajectories ``estimate.txt``, ``odometry.txt``, ``groundtruth.txt``
(one pose per input frame at its timestamp; load with ``evo_ape tum``), ``corrections.csv``
(one row per keyframe), ``metrics.json`` (evo ATE/RPE) and PNG plots; a ``latest`` link in
the parent folder points at the newest run.
"""

from __future__ import annotations

import csv
import json
import logging
import time
from pathlib import Path

import numpy as np

from .datasets.tum import write_tum_trajectory
from .evaluation.metrics import trajectory_metrics
from .plots import plot_error_over_time, plot_top_view

__all__ = ["write_results", "new_run_dir", "keyframe_timing_summary"]

log = logging.getLogger(__name__)

TIMING_STAGES = ("render", "sift", "flann", "ransac", "refine", "gate", "isam")


def new_run_dir(root: str | Path, name: str = "") -> Path:
    """``root/<date>_<time>[_name]``, unique, created."""
    root = Path(root)
    stamp = time.strftime("%Y-%m-%d_%H-%M-%S")
    run = root / (f"{stamp}_{name}" if name else stamp)
    suffix = 1
    while run.exists():
        run = root / f"{stamp}_{name}_{suffix}" if name else root / f"{stamp}_{suffix}"
        suffix += 1
    run.mkdir(parents=True)
    return run


def _link_latest(run: Path) -> None:
    latest = run.parent / "latest"
    try:
        if latest.is_symlink() or latest.exists():
            latest.unlink()
        latest.symlink_to(run.name, target_is_directory=True)
    except OSError as exc:  # e.g. a filesystem without symlinks: not worth failing a run
        log.warning("could not update %s: %s", latest, exc)


def keyframe_timing_summary(result) -> dict:
    """Median seconds per keyframe for each stage, over keyframes that ran it."""
    out = {}
    for stage in TIMING_STAGES:
        values = [k.timings_s[stage] for k in result.keyframes if stage in k.timings_s]
        if values:
            out[stage] = float(np.median(values))
    totals = [sum(k.timings_s.get(s, 0.0) for s in ("render", "align", "gate", "isam")) for k in result.keyframes]
    if totals:
        out["total_per_keyframe"] = float(np.median(totals))
    return out


def _write_corrections(path: Path, result) -> None:
    columns = ["frame_index", "timestamp", "key", "matches", "inliers", "iterations", "accepted", "reason",
               "gate_d2", "correction_m", "correction_deg", *[f"t_{s}_s" for s in TIMING_STAGES]]
    with open(path, "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(columns)
        for k in result.keyframes:
            writer.writerow([k.frame_index, f"{k.timestamp:.6f}", k.key, k.matches, k.inliers, k.iterations,
                             int(k.accepted), k.reason, f"{k.gate_d2:.4g}", f"{k.correction_m:.6f}",
                             f"{k.correction_deg:.5f}", *[k.timings_s.get(s, "") for s in TIMING_STAGES]])


def write_results(result, out_dir: str | Path, config: dict, name: str = "") -> tuple[Path, dict]:
    """Write a run into a new folder under ``out_dir``; return the folder and metrics."""
    import yaml

    run = new_run_dir(out_dir, name)
    (run / "config.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    write_tum_trajectory(run / "estimate.txt", result.timestamps, result.T_world_cam_estimate)
    write_tum_trajectory(run / "odometry.txt", result.timestamps, result.T_world_cam_odometry)
    metrics: dict = {
        "frames": int(len(result.timestamps)),
        "keyframes": len(result.keyframes),
        "corrections_accepted": result.num_accepted,
        "corrections_rejected_or_skipped": result.num_rejected,
        "seconds_per_keyframe_median": keyframe_timing_summary(result),
        "wall_time_s": result.wall_time_s,
    }
    if result.T_world_cam_gt is not None:
        write_tum_trajectory(run / "groundtruth.txt", result.timestamps, result.T_world_cam_gt)
        metrics.update(trajectory_metrics(result.timestamps, result.T_world_cam_gt,
                                          {"odometry": result.T_world_cam_odometry,
                                           "estimate": result.T_world_cam_estimate}))
    if result.T_world_map is not None:
        metrics["T_world_map"] = result.T_world_map.tolist()
    _write_corrections(run / "corrections.csv", result)
    (run / "metrics.json").write_text(json.dumps(metrics, indent=1))
    plot_top_view(run / "trajectory_top_view.png", result)
    plot_error_over_time(run / "translation_error.png", result)
    _link_latest(run)
    return run, metrics
