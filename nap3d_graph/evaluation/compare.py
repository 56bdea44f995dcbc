"""EKF vs graph: every estimator on one measurement stream, scored against ground truth.

:func:`compare` runs each estimator (:mod:`nap3d_graph.estimators`) over the same
:class:`~nap3d_graph.estimators.MeasurementStream` and turns the results into rows: one per
reported trajectory (a filter's causal one, iSAM2's causal and final, batch LM's final, the
odometry alone). Each row has the evo ATE (rmse, mean, max) and RPE, the NEES at keyframes
against ground truth with its 95% band, the time per step and the time of the final solve.
:func:`write_comparison` writes ``comparison.csv`` / ``.json``, the trajectories (TUM, for
evo) and two figures; :func:`format_table` is the table the command prints (the same
numbers as the files, rounded as printed).
"""

from __future__ import annotations

import csv
import json
import logging
from pathlib import Path

import numpy as np

from nap3d_graph.conventions import inv_T, log_se3
from nap3d_graph.factors.gate import chi2_threshold
from nap3d_graph.plots import plot_errors, plot_trajectories
from nap3d_graph.provenance import provenance
from nap3d_graph.trajectory import Trajectory

from .metrics import ate, rpe

__all__ = ["compare", "comparison_rows", "write_comparison", "format_table", "nees_at_keyframes", "COLUMNS"]

log = logging.getLogger(__name__)

COLUMNS = ("estimator", "ate_rmse_m", "ate_mean_m", "ate_max_m", "rpe_rmse_m", "nees_mean", "nees_band_low",
           "nees_band_high", "nees_keyframes", "step_ms_mean", "step_ms_p99", "final_s", "corrections_taken")


def compare(stream, estimators=None) -> list:
    """Run every estimator on ``stream`` (default: all that apply); their results, in order."""
    from nap3d_graph.estimators import default_estimators, run_estimator

    estimators = default_estimators(stream) if estimators is None else estimators
    results = []
    for estimator in estimators:
        log.info("estimator %s", estimator.name)
        results.append(run_estimator(estimator, stream))
    return results


def nees_at_keyframes(T_world_cam_est: np.ndarray, P: np.ndarray, T_world_cam_gt: np.ndarray, keyframes) -> np.ndarray:
    """NEES ``e^T P^-1 e`` (6 dof) with ``e = Log(T_world_cam_est^-1 T_world_cam_gt)`` at each keyframe that has a
    covariance and ground truth."""
    out = []
    for i in keyframes:
        if not (np.all(np.isfinite(P[i])) and np.all(np.isfinite(T_world_cam_gt[i]))):
            continue
        e = log_se3(inv_T(T_world_cam_est[i]) @ T_world_cam_gt[i])
        try:
            out.append(float(e @ np.linalg.solve(P[i], e)))
        except np.linalg.LinAlgError:
            continue
    return np.asarray(out)


def correction_nees(result) -> np.ndarray:
    """NEES (6 dof) of each successful correction of a run (``RunResult.corrections``: the
    corrected pose and its covariance) against the ground truth at its frame, frame order."""
    idx = sorted(result.corrections)
    if not idx or result.T_world_cam_gt is None:
        return np.zeros(0)
    T = np.stack([result.corrections[i][0] for i in idx])
    P = np.stack([result.corrections[i][1] for i in idx])
    return nees_at_keyframes(T, P, np.asarray(result.T_world_cam_gt)[idx], range(len(idx)))


def _row(name: str, T: np.ndarray, P, stream, result, which: str) -> dict:
    T_world_cam_gt = stream.T_world_cam_gt
    posed = np.all(np.isfinite(T_world_cam_gt), axis=(1, 2))
    stamps = np.asarray(stream.timestamps)[posed]
    a = ate(stamps, T_world_cam_gt[posed], T[posed])
    r = rpe(stamps, T_world_cam_gt[posed], T[posed])
    nees = nees_at_keyframes(T, P, T_world_cam_gt, stream.keyframes) if P is not None else np.array([])
    k = len(nees)
    # Band of the mean of k chi-square(6) values, were they independent (95%).
    band = (chi2_threshold(0.025, 6 * k) / k, chi2_threshold(0.975, 6 * k) / k) if k else (np.nan, np.nan)
    steps = np.asarray(result.step_seconds[1:]) * 1000.0
    online = which == "causal" and len(steps)
    return {"estimator": name, "ate_rmse_m": a["rmse"], "ate_mean_m": a["mean"], "ate_max_m": a["max"],
            "rpe_rmse_m": r.get("rmse", np.nan), "nees_mean": float(np.mean(nees)) if k else np.nan,
            "nees_band_low": float(band[0]), "nees_band_high": float(band[1]), "nees_keyframes": k,
            "step_ms_mean": float(np.mean(steps)) if online else np.nan,
            "step_ms_p99": float(np.percentile(steps, 99)) if online else np.nan,
            "final_s": float(result.final_seconds) if which == "final" else np.nan,
            "corrections_taken": len(result.accepted) if name != "odometry" else 0}


def comparison_rows(stream, results) -> list[dict]:
    """One row per reported trajectory (see the module docstring)."""
    if stream.T_world_cam_gt is None:
        raise ValueError("a comparison needs ground truth (ATE, NEES): this sequence has none")
    rows = []
    for result in results:
        if result.name == "odometry":
            rows.append(_row("odometry", result.T_causal, result.P_causal, stream, result, "causal"))
            continue
        for which in result.reports:
            T, P = (result.T_causal, result.P_causal) if which == "causal" else (result.T_final, result.P_final)
            name = result.name if len(result.reports) == 1 else f"{result.name}-{which}"
            rows.append(_row(name, T, P, stream, result, which))
    return rows


def _trajectories(results) -> dict[str, np.ndarray]:
    out = {}
    for result in results:
        if result.name == "odometry":
            out["odometry"] = result.T_causal
            continue
        for which in result.reports:
            name = result.name if len(result.reports) == 1 else f"{result.name}-{which}"
            out[name] = result.T_causal if which == "causal" else result.T_final
    return out


def write_comparison(out_dir: str | Path, stream, results, rows: list[dict], meta: dict | None = None) -> Path:
    """``comparison.csv`` / ``comparison.json``, ``trajectories/<row>.txt`` and
    ``groundtruth.txt`` (TUM), ``trajectories.png`` and ``errors.png`` into ``out_dir``."""
    out = Path(out_dir)
    (out / "trajectories").mkdir(parents=True, exist_ok=True)
    with open(out / "comparison.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    summary = {"rows": rows, "frames": len(stream), "keyframes": len(stream.keyframes),
               "corrections_measured": len(stream.corrections), "path": "imu" if stream.imu is not None else "odometry",
               "gate_p": stream.gate_p, **(meta or {}), "provenance": provenance(meta)}
    (out / "comparison.json").write_text(json.dumps(summary, indent=1, default=_json_default))
    stamps = np.asarray(stream.timestamps)
    trajectories = _trajectories(results)
    for name, T in trajectories.items():
        Trajectory(stamps, T).write_tum(out / "trajectories" / f"{name}.txt", skip_unknown=True)
    Trajectory(stamps, stream.T_world_cam_gt).write_tum(out / "groundtruth.txt", skip_unknown=True)
    _plot(out, stamps, stream.T_world_cam_gt, trajectories)
    return out


def _json_default(value):
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    raise TypeError(f"not JSON: {type(value).__name__}")


def _plot(out: Path, stamps, T_world_cam_gt, trajectories: dict) -> None:
    plot_trajectories(out / "trajectories.png", trajectories, T_world_cam_gt, title="estimators")
    plot_errors(out / "errors.png", stamps - stamps[0], trajectories, T_world_cam_gt, title="error over time")


def _fmt(value, scale: float, digits: int, width: int) -> str:
    """A right-aligned number (always one space before it, however large)."""
    if value is None or not np.isfinite(value):
        return f"{'-':>{width}}"
    return " " + f"{value * scale:.{digits}f}".rjust(width - 1)


def format_table(rows: list[dict]) -> str:
    """The printed table: ATE/RPE in cm, NEES with its band, ms per step, seconds of the final
    solve (rounded as printed; the files hold the full values)."""
    head = (f"{'estimator':<16}{'ATE cm':>10}{'mean cm':>10}{'max cm':>10}{'RPE cm':>10}{'NEES':>8}{'band':>12}"
            f"{'ms/step':>9}{'p99 ms':>9}{'final s':>9}{'taken':>7}")
    lines = [head]
    for r in rows:
        band = (f"{r['nees_band_low']:.2f}-{r['nees_band_high']:.2f}" if np.isfinite(r["nees_band_low"]) else "-")
        lines.append(f"{r['estimator']:<16}{_fmt(r['ate_rmse_m'], 100, 3, 10)}{_fmt(r['ate_mean_m'], 100, 3, 10)}"
                     f"{_fmt(r['ate_max_m'], 100, 3, 10)}{_fmt(r['rpe_rmse_m'], 100, 3, 10)}"
                     f"{_fmt(r['nees_mean'], 1, 2, 8)}{band:>12}{_fmt(r['step_ms_mean'], 1, 3, 9)}"
                     f"{_fmt(r['step_ms_p99'], 1, 3, 9)}{_fmt(r['final_s'], 1, 3, 9)}{r['corrections_taken']:>7}")
    return "\n".join(lines)
