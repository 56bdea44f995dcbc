"""The results folder of a run (KISS-ICP style), written as the run goes.

``config.yaml`` (at once), ``corrections.csv`` (a row per keyframe, appended and flushed as
each is corrected), then at the end (or when the run is interrupted) the TUM trajectories
``estimate.txt``, ``estimate_online.txt`` (each keyframe as it was known when it was
added), ``odometry.txt``, ``groundtruth.txt`` (frames with ground truth; every file loads
with ``evo_ape tum``), ``metrics.json`` (evo ATE/RPE; ``"partial": true`` for an
interrupted run) and PNG plots. A ``latest`` link in the parent folder is moved atomically
to the newest run.
"""

from __future__ import annotations

import csv
import json
import logging
import os
import time
from pathlib import Path

import numpy as np

from nap3d_graph.conventions import inv_T
from nap3d_graph.evaluation.alignment import aligned_errors
from nap3d_graph.evaluation.metrics import trajectory_metrics
from nap3d_graph.motion.imu import gravity_angle_deg
from nap3d_graph.plots import plot_error_over_time, plot_top_view

from .records import refusal_kind
from .report import write_run_report

__all__ = ["RunWriter", "write_results", "new_run_dir", "keyframe_timing_summary", "CORRECTION_COLUMNS",
           "refusal_reasons"]

log = logging.getLogger(__name__)

TIMING_STAGES = ("render", "detect", "match", "ransac", "refine", "gate", "isam", "measure", "wait",
                 "render_beside", "render_ahead", "detect_ahead")  # the last three: overlapped runs (--overlap)
CORRECTION_COLUMNS = ["frame_index", "run_index", "timestamp", "key", "matches", "inliers", "iterations", "accepted",
                      "reason", "gate_d2", "correction_m", "correction_deg", "trained_frame", "keyframe_why",
                      "sharpness", "postponed_frames", "intrinsics_model", *[f"t_{s}_s" for s in TIMING_STAGES]]


def new_run_dir(root: str | Path, name: str = "") -> Path:
    """``root/<date>_<time>[_name][_k]``, unique and created atomically (two processes
    starting at the same second get different folders, never an error)."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    stamp = time.strftime("%Y-%m-%d_%H-%M-%S")
    base = f"{stamp}_{name}" if name else stamp
    for suffix in range(10_000):
        run = root / (base if suffix == 0 else f"{base}_{suffix}")
        try:
            run.mkdir()  # atomic: exactly one creator succeeds
            return run
        except FileExistsError:
            continue
    raise OSError(f"{root}: could not create a new run folder named {base}_*")


def link_latest(run: Path) -> None:
    """Point ``run.parent/latest`` at ``run``, replacing the old link atomically."""
    latest = run.parent / "latest"
    temporary = run.parent / f".latest-{os.getpid()}-{time.monotonic_ns()}"
    try:
        temporary.symlink_to(run.name, target_is_directory=True)
        os.replace(temporary, latest)
    except OSError as exc:  # e.g. a filesystem without symlinks: not worth failing a run
        temporary.unlink(missing_ok=True)
        log.warning("could not update %s: %s", latest, exc)


def keyframe_timing_summary(result) -> dict:
    """Median seconds per keyframe for each stage, over keyframes that ran it."""
    out = {}
    for stage in TIMING_STAGES:
        values = [k.timings_s[stage] for k in result.keyframes if stage in k.timings_s]
        if values:
            out[stage] = float(np.median(values))
    # "measure" is the whole measurement (depth warp, render, align); the run's graph work
    # comes on top.
    totals = [sum(k.timings_s.get(s, 0.0) for s in ("measure", "gate", "isam")) for k in result.keyframes]
    if totals:
        out["total_per_keyframe"] = float(np.median(totals))
    return out


#: What to check when corrections keep failing for one reason (the reason's first words).
REFUSAL_HINTS = {
    "low opacity": "the field does not cover these views: have they left the mapped area, or is it a field of "
                   "another place or in another frame (--anchor estimates an offset)?",
    "too few matches": "the frames and the renders hardly match: is the field of this place, and the depth in "
                       "metres (TUM PNGs: 5000 per metre)?",
    "too few inliers": "matches do not agree in 3D: is the depth in metres (TUM PNGs: 5000 per metre), and the "
                       "camera's intrinsics right?",
    "depth scale": "the frames' depth disagrees with the field's metre: by a few percent in fast, blurred motion "
                   "(depth and colour are captured at different instants; corrections resume as it slows), by x5 "
                   "or x1000 with a wrong depth unit (TUM PNGs: 5000 per metre)",
    "innovation": "the corrections disagree with the odometry's prediction: is the field in this recording's "
                  "frame (--anchor), or the odometry noisier than its model (--odom-rot-sigma, --odom-trans-sigma)?",
}


def refusal_hint_for(kind: str) -> str:
    """What a kind of refusal usually means ("" when there is nothing to add)."""
    return next((text for key, text in REFUSAL_HINTS.items() if kind.startswith(key)), "")


def refusal_reasons(keyframes) -> dict[str, int]:
    """How many keyframes were refused for each kind of reason (its words before the first
    number or detail: "too few inliers", "low opacity", "innovation", ...), most first."""
    counts: dict[str, int] = {}
    for k in keyframes:
        if not k.accepted:
            kind = refusal_kind(k.reason)
            counts[kind] = counts.get(kind, 0) + 1
    return dict(sorted(counts.items(), key=lambda item: -item[1]))


def _correction_row(k, frame_index: int) -> list:
    return [frame_index, k.frame_index, f"{k.timestamp:.6f}", k.key, k.matches, k.inliers, k.iterations, int(k.accepted),
            k.reason, f"{k.gate_d2:.4g}", f"{k.correction_m:.6f}", f"{k.correction_deg:.5f}",
            int(getattr(k, "trained_frame", False)), k.why, f"{k.sharpness:.4g}", k.postponed,
            getattr(k, "intrinsics_model", ""), *[k.timings_s.get(s, "") for s in TIMING_STAGES]]


class RunWriter:
    """A run's folder, filled as the run goes.

    ``RunWriter(root, name, config)`` creates the folder and writes ``config.yaml`` at once;
    :meth:`add_keyframe` appends a row to ``corrections.csv`` (flushed, so a crash or an
    interruption loses nothing of what was corrected); :meth:`finish` writes the
    trajectories, ``metrics.json`` and the plots and moves ``latest``. ``frame_index`` in
    the rows is the frame's line among ``rgb.txt``'s data lines when the source says
    (``rgb_line_index``), so it names the same image whatever association dropped.
    """

    def __init__(self, root: str | Path, name: str, config: dict, source_indices=None):
        import yaml

        self.dir = new_run_dir(root, name)
        (self.dir / "config.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
        self.source_indices = None if source_indices is None else np.asarray(source_indices, dtype=int)
        self._csv = open(self.dir / "corrections.csv", "w", newline="")
        self._writer = csv.writer(self._csv)
        self._writer.writerow(CORRECTION_COLUMNS)
        self._csv.flush()

    def add_keyframe(self, record) -> None:
        index = record.frame_index if self.source_indices is None else int(self.source_indices[record.frame_index])
        self._writer.writerow(_correction_row(record, index))
        self._csv.flush()

    def close(self) -> None:
        if not self._csv.closed:
            self._csv.close()

    def _write_biases(self, result) -> None:
        np.savetxt(self.dir / "biases.txt", _bias_rows(result), fmt="%.9f",
                   header="IMU bias estimate at each keyframe (final solve) and its sigma\n"
                          "timestamp bax bay baz bgx bgy bgz sigma_bax sigma_bay sigma_baz sigma_bgx sigma_bgy sigma_bgz")

    def finish(self, result, partial: bool = False, extra: dict | None = None) -> dict:
        """Write everything the finished (or interrupted: ``partial``) run has, with ``extra``
        entries in metrics.json; returns the metrics and moves ``latest`` here."""
        self.close()
        run = self.dir
        # The run's own trajectories are written before its ground truth is first read.
        for name, trajectory in result.trajectories(with_ground_truth=False).items():
            trajectory.write_tum(run / f"{name}.txt")
        online = result.T_world_cam_online
        metrics: dict = {
            "partial": bool(partial),
            "frames": int(len(result.timestamps)),
            "keyframes": len(result.keyframes),
            "corrections_accepted": result.num_accepted,
            "corrections_rejected_or_skipped": result.num_rejected,
            "refused_reasons": refusal_reasons(result.keyframes),
            "median_inliers": float(np.median([k.inliers for k in result.keyframes])) if result.keyframes else 0.0,
            "seconds_per_keyframe_median": keyframe_timing_summary(result),
            "wall_time_s": result.wall_time_s,
        }
        trajectories = {"odometry": result.T_world_cam_odometry, "estimate": result.T_world_cam_estimate}
        if online is not None:
            trajectories["estimate_online"] = online
        if result.T_world_cam_gt is not None:
            posed = np.all(np.isfinite(result.T_world_cam_gt), axis=(1, 2))
            if posed.any():
                result.trajectories()["groundtruth"].write_tum(run / "groundtruth.txt", skip_unknown=True)
            if posed.sum() >= 2:
                metrics.update(trajectory_metrics(result.timestamps, result.T_world_cam_gt, trajectories))
            metrics["frames_without_ground_truth"] = int((~posed).sum())
        else:
            metrics["ground_truth"] = "none: no ATE/RPE; see the correction statistics"
        if result.T_world_map is not None:
            metrics["T_world_map"] = result.T_world_map.tolist()
        metrics.update(self._motion_metrics(result))
        metrics.update(extra or {})
        plotted = result
        if "scored" in metrics and result.T_world_cam_gt is not None:
            untie_metrics(metrics, trajectories, str(metrics["scored"]))
            plotted = _ground_truth_in_run_frame(result)

        report = write_run_report(run, result.keyframes, metrics)
        metrics["report"] = {"file": "report.md", "past_bad_line": report.bad}
        (run / "metrics.json").write_text(json.dumps(metrics, indent=1))
        plot_top_view(run / "trajectory_top_view.png", plotted)
        plot_error_over_time(run / "translation_error.png", plotted)
        link_latest(run)
        return metrics


    def _motion_metrics(self, result) -> dict:
        """metrics.json's entries of the motion model, where the run has them: the IMU's final
        biases (``imu_biases.txt`` written) and skipped samples, the visual fallback's frames,
        the refined gravity."""
        metrics: dict = {}
        if getattr(result, "imu_biases", None) is not None:
            self._write_biases(result)
            metrics["imu_bias_final"] = {"accel_m_s2": result.imu_biases[-1, :3].tolist(),
                                         "gyro_rad_s": result.imu_biases[-1, 3:].tolist()}
            if result.imu_bias_sigmas is not None:
                metrics["imu_bias_final"]["sigma"] = result.imu_bias_sigmas[-1].tolist()
            metrics["imu_samples_skipped_or_gaps"] = [{"t": t, "reason": r} for t, r in result.imu_skipped]
        if getattr(result, "fallback_intervals", None):
            metrics["vo_fallback"] = {"frame_intervals": result.fallback_intervals,
                                      "frames": int(sum(b - a for a, b in result.fallback_intervals))}
        if getattr(result, "gravity_world", None) is not None:
            metrics["gravity_world_m_s2"] = {"refined": np.round(result.gravity_world, 4).tolist(),
                                             "given": np.round(result.gravity_world_prior, 4).tolist(),
                                             "turned_deg": round(gravity_angle_deg(result.gravity_world,
                                                                                   result.gravity_world_prior), 3)}
        return metrics


def untie_metrics(metrics: dict, names, why: str) -> None:
    """A run whose frame no survey alignment ties to its ground truth's (``why``): every figure
    that compares the two frames directly (each trajectory's ``ate_m`` and its halves) is null
    with the reason, so no script reads it; the SE(3)-aligned ATE and the RPE (frame-free) stay."""
    for name in names:
        entry = metrics.get(name)
        if not isinstance(entry, dict):
            continue
        entry.update(ate_m=None, ate_first_half_m=None, ate_second_half_m=None,
                     ate_m_reason=f"not tied: {why}; read ate_se3_aligned_m")


def _ground_truth_in_run_frame(result):
    """The result with its ground truth moved into the run's frame by the estimate's own SE(3)
    alignment (for the plots of an untied run: the paths are drawn as the aligned ATE scores them)."""
    import copy

    aligned = aligned_errors(result.timestamps, result.T_world_cam_gt, result.T_world_cam_estimate)
    if aligned is None:
        return result
    moved = copy.copy(result)
    moved.ground_truth = inv_T(aligned.T_ref_est)[None] @ np.asarray(result.T_world_cam_gt, dtype=float)
    return moved


def _bias_rows(result) -> np.ndarray:
    stamps = np.asarray(result.timestamps)[np.asarray(result.keyframe_indices, dtype=int)]
    sigmas = result.imu_bias_sigmas if result.imu_bias_sigmas is not None else np.full_like(result.imu_biases, np.nan)
    return np.column_stack([stamps, result.imu_biases, sigmas])


def write_results(result, out_dir: str | Path, config: dict, name: str = "", source_indices=None) -> tuple[Path, dict]:
    """Write a finished run into a new folder under ``out_dir``; return the folder and metrics."""
    writer = RunWriter(out_dir, name, config, source_indices)
    for record in result.keyframes:
        writer.add_keyframe(record)
    return writer.dir, writer.finish(result)
