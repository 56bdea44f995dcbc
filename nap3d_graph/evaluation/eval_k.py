"""The paper's Evaluation K: NAP3D vs PnP-RANSAC under blur and intrinsics noise, and the
project's variants beside it.

For each scenario: a random frame, a random perturbation of its ground-truth pose
(translation uniform in +-10 cm per axis, rotation up to 5 deg), the field renders at the
perturbed pose. Each scenario is evaluated 16 times: Gaussian blur of the real image with
sigma in {0, 1.0, 1.8, 2.2} x intrinsics given to the methods shifted by (focal scale,
principal-point offset px) in CLEAN (1.0, 0), MILD (1.03, 2), MEDIUM (1.06, 5), HARSH
(1.10, 10). The field renders with its true intrinsics, as the paper's renders were made
once per scenario before the 16 evaluations. ``shift="real"`` (default) gives the shifted
intrinsics for the real camera only; ``shift="both"`` tells the methods the shifted
intrinsics for the rendered view too (one wrong calibration for both cameras, the renders
still made with the true one). Every method runs on the *same* matches of each cell.

Methods, and which is compared with which:

* the paper's pair (its Figure 4): ``nap3d-plain`` (RANSAC + opacity-weighted Procrustes,
  the paper's NAP3D) against ``pnp`` (PnP-RANSAC + LM);
* the project's refinement, both trusting the given intrinsics: ``nap3d-refined`` (least
  squares over every inlier's pixels and depth) against ``pnp``;
* self-calibration, both estimating the real camera's intrinsics when the data call for it:
  ``nap3d-selfcal`` (the library's default, ``align_views``) against ``pnp-selfcal``;
* the PnP at its best where the calibration is wrong (selected with ``methods``):
  ``nap3d-selfcal`` against ``pnp-calibrated``, which estimates the real camera's intrinsics
  at every frame. ``pnp-selfcal`` decides by NAP3D's own test on pixels alone, which can keep
  the given calibration where calibrating would have helped it: this pair compares NAP3D
  with a PnP that is never held back by that test;
* optionally ``nap3d-iter`` (``correct_pose``: nap3d-selfcal re-rendered at the corrected pose).

A failed correction counts: it scores the error of the uncorrected (perturbed) pose, and the
success rate is reported beside it. Per cell and method the summary gives the mean, median,
p90 and max of each metric, and the mean NEES of the successful corrections (is the
covariance honest?).

Metrics: rotation error (deg), translation error (m) and 3D RMSE: over the real frame's valid
depth pixels on a fixed grid (every ``grid_stride`` px), the RMSE between their world points
under the estimated and under the true camera pose.
"""

from __future__ import annotations

import csv
import json
import logging
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from nap3d_graph.baselines.pnp import pnp_from_correspondences
from nap3d_graph.camera import RenderedView, RGBDFrame, backproject_depth, warp_depth
from nap3d_graph.conventions import inv_T, log_se3, pose_error, transform_points
from nap3d_graph.datasets.depth_timing import CaptureTiming
from nap3d_graph.nap3d.align import align_correspondences, prepare_correspondences, view_features
from nap3d_graph.nap3d.config import AlignConfig
from nap3d_graph.nap3d.correct import correct_pose, render_safely
from nap3d_graph.nap3d.matching import detect_features
from nap3d_graph.progress import progress_bar
from nap3d_graph.provenance import provenance
from nap3d_graph.results import Alignment

from .perturb import random_perturbation

__all__ = ["EvalKConfig", "BLUR_SIGMAS", "INTRINSICS_NOISE", "METHODS", "PAIRS", "run_eval_k", "rmse_3d",
           "summarise", "write_table"]

log = logging.getLogger(__name__)

BLUR_SIGMAS = (0.0, 1.0, 1.8, 2.2)
INTRINSICS_NOISE = {"CLEAN": (1.0, 0.0), "MILD": (1.03, 2.0), "MEDIUM": (1.06, 5.0), "HARSH": (1.10, 10.0)}
METHODS = {
    "nap3d-plain": "NAP3D as in the paper: RANSAC + opacity-weighted Procrustes",
    "pnp": "PnP-RANSAC + LM, the paper's baseline",
    "nap3d-refined": "NAP3D + refinement over pixels and depth, given intrinsics",
    "pnp-selfcal": "PnP-RANSAC + LM + intrinsics refinement when the data call for it",
    "pnp-calibrated": "PnP-RANSAC + LM + intrinsics refinement at every frame",
    "nap3d-selfcal": "NAP3D refined + intrinsics estimated when the data call for it (the default)",
    "nap3d-iter": "correct_pose: nap3d-selfcal re-rendered at the corrected pose",
}
DEFAULT_METHODS = ("nap3d-plain", "pnp", "nap3d-refined", "pnp-selfcal", "nap3d-selfcal")
#: (name, PnP-side method, NAP3D-side method): what each heatmap compares (a pair whose two
#: methods both ran).
PAIRS = (("paper", "pnp", "nap3d-plain"), ("refined", "pnp", "nap3d-refined"),
         ("selfcal", "pnp-selfcal", "nap3d-selfcal"), ("calibrated", "pnp-calibrated", "nap3d-selfcal"))
#: How each PnP method is told to treat the real camera's intrinsics
#: (:func:`~nap3d_graph.baselines.pnp.pnp_from_correspondences`'s ``estimate_intrinsics``).
PNP_INTRINSICS = {"pnp": False, "pnp-selfcal": "auto", "pnp-calibrated": True}
METRICS = ("rot_err_deg", "trans_err_m", "rmse_3d_m")
CSV_COLUMNS = ["scenario", "frame_index", "timestamp", "blur_sigma", "intrinsics", "method", "success", "reason",
               "rot_err_deg", "trans_err_m", "rmse_3d_m", "nees", "num_matches", "num_inliers", "intrinsics_model",
               "time_s"]


@dataclass
class EvalKConfig:
    scenarios: int = 40
    seed: int = 0
    max_trans_m: float = 0.10
    max_rot_deg: float = 5.0
    methods: tuple[str, ...] = DEFAULT_METHODS
    blur_sigmas: tuple[float, ...] = BLUR_SIGMAS
    intrinsics_noise: dict = field(default_factory=lambda: dict(INTRINSICS_NOISE))
    shift: str = "real"
    grid_stride: int = 8
    iterations: int = 3  # for nap3d-iter
    align: AlignConfig = field(default_factory=AlignConfig)
    #: Capture timing ``{"depth_offset_s", "colour_offset_s", "depth_scale"}`` (as
    #: :func:`~nap3d_graph.datasets.depth_timing.estimate_timing` gives): each scenario's depth is moved
    #: to its colour's capture instant with the ground-truth motion, so that the scenario
    #: measures the correction and not the sensor's colour/depth asynchrony. None: as stamped.
    timing: CaptureTiming | None = None

    def __post_init__(self) -> None:
        unknown = set(self.methods) - set(METHODS)
        if unknown:
            raise ValueError(f"unknown method(s) {sorted(unknown)}; choose from {list(METHODS)}")
        if self.shift not in ("real", "both"):
            raise ValueError(f"shift must be 'real' or 'both', got {self.shift!r}")
        if self.scenarios < 1:
            raise ValueError(f"scenarios must be at least 1, got {self.scenarios}")


def rmse_3d(depth_m: np.ndarray, intrinsics, T_world_cam_est: np.ndarray, T_world_cam_true: np.ndarray,
            stride: int = 8) -> float:
    """RMSE (m) between the frame's valid depth points on a ``stride`` grid placed in the
    world by the estimated and by the true camera pose."""
    points_cam, _ = backproject_depth(depth_m, intrinsics, stride)
    if len(points_cam) == 0:
        return float("nan")
    diff = transform_points(T_world_cam_est, points_cam) - transform_points(T_world_cam_true, points_cam)
    return float(np.sqrt(np.mean(np.sum(diff**2, axis=1))))


def _blur(frame: RGBDFrame, sigma: float) -> RGBDFrame:
    import cv2

    if sigma <= 0:
        return frame
    rgb = cv2.GaussianBlur(frame.rgb, (0, 0), sigmaX=sigma, sigmaY=sigma)
    return RGBDFrame(rgb, frame.depth_m, frame.intrinsics, frame.timestamp, frame.depth_timestamp)


class _ToldShiftedIntrinsics:
    """A field that renders with the true intrinsics but labels the view with the shifted
    ones (``shift="both"`` for ``correct_pose``)."""

    def __init__(self, field_obj, K_true, K_told):
        self.field, self.K_true, self.K_told = field_obj, K_true, K_told

    def render(self, T_world_cam, intrinsics):
        view = self.field.render(T_world_cam, self.K_true)
        return RenderedView(view.rgb, view.depth_m, view.opacity, self.K_told)


def _single_alignment(method: str, corr, K_real, config: EvalKConfig) -> Alignment:
    """One method (other than ``nap3d-iter``) on one cell's correspondences, told ``K_real``."""
    if method in PNP_INTRINSICS:
        return pnp_from_correspondences(corr, K_real, align_config=config.align,
                                        estimate_intrinsics=PNP_INTRINSICS[method])
    changes = {"nap3d-plain": {"method": "plain"}, "nap3d-refined": {"estimate_intrinsics": False},
               "nap3d-selfcal": {"estimate_intrinsics": "auto"}}[method]
    return align_correspondences(corr, K_real, replace(config.align, **changes))


def _run_methods(frame_given: RGBDFrame, view, field_obj, T_world_cam_est, config: EvalKConfig, feats_real, feats_view):
    """Every method on one cell, sharing one set of matches. Yields (method, success,
    reason, corrected pose, covariance, matches, inliers, intrinsics model, seconds)."""
    timings: dict = {}
    t0 = time.perf_counter()
    corr, reason = prepare_correspondences(frame_given, view, config.align, timings, feats_real, feats_view)
    t_match = time.perf_counter() - t0
    for method in config.methods:
        t0 = time.perf_counter()
        if method == "nap3d-iter":
            c = correct_pose(frame_given, field_obj, T_world_cam_est, iterations=config.iterations, config=config.align,
                             render_intrinsics=view.intrinsics)
            model = c.alignment.diagnostics.get("intrinsics_model", "")
            yield (method, c.success, c.reason, c.T_world_cam_corrected, c.covariance, c.num_matches,
                   c.num_inliers, model, time.perf_counter() - t0)
            continue
        result = Alignment.failure(reason) if corr is None else _single_alignment(method, corr,
                                                                                 frame_given.intrinsics, config)
        T_corr = result.corrected_pose(T_world_cam_est) if result.success else T_world_cam_est
        yield (method, result.success, result.reason, T_corr, result.covariance, result.num_matches,
               result.num_inliers, result.diagnostics.get("intrinsics_model", ""),
               time.perf_counter() - t0 + t_match)


def _nees(T_corr: np.ndarray, covariance: np.ndarray, T_world_cam_gt: np.ndarray) -> float | str:
    """Normalised estimation error squared of a corrected pose (GTSAM order, right perturbation)."""
    e = log_se3(inv_T(T_corr) @ T_world_cam_gt)
    try:
        value = float(e @ np.linalg.solve(covariance, e))
    except np.linalg.LinAlgError:
        return ""
    return value if np.isfinite(value) else ""


def run_eval_k(sequence, field_obj, out_dir: str | Path, config: EvalKConfig | None = None,
               progress: bool = False) -> dict:
    """Run Evaluation K on ``sequence`` (with ground truth) and ``field_obj``; write
    ``results.csv``, ``summary.json``, ``table.md`` and heatmaps into ``out_dir``; return
    the summary."""
    config = config or EvalKConfig()
    if sequence.T_world_cam_gt is None:
        raise ValueError(f"{sequence.path}: Evaluation K needs ground-truth poses (groundtruth.txt)")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(config.seed)
    rows: list[dict] = []
    cells = len(config.blur_sigmas) * len(config.intrinsics_noise)
    bar = progress_bar(total=config.scenarios * cells, desc="eval-k", unit="cell", disable=not progress)
    posed = np.flatnonzero(np.all(np.isfinite(np.asarray(sequence.T_world_cam_gt)), axis=(1, 2)))
    if posed.size == 0:
        raise ValueError(f"{sequence.path}: no frame has a ground-truth pose")
    for scenario in range(config.scenarios):
        index = int(posed[rng.integers(len(posed))])
        T_world_cam_gt = sequence.T_world_cam_gt[index]
        T_world_cam_est = T_world_cam_gt @ random_perturbation(rng, config.max_trans_m, config.max_rot_deg)
        frame = at_colour_instant(sequence, index, config.timing)
        uncorrected = _errors(frame, T_world_cam_est, T_world_cam_gt, config)
        view, render_reason = render_safely(field_obj, T_world_cam_est, frame.intrinsics)
        # Features depend on the image only: once per view and per blur level, reused by
        # the four intrinsics settings (which only change the back-projection).
        feats_view = view_features(view, config.align) if view is not None else None
        for sigma in config.blur_sigmas:
            blurred = _blur(frame, sigma)
            feats_real = detect_features(blurred.rgb, config.align.max_features, matcher=config.align.matcher)
            for name, (focal_scale, offset_px) in config.intrinsics_noise.items():
                K_given = frame.intrinsics.shifted(focal_scale, offset_px)
                given = blurred.with_intrinsics(K_given)
                base = {"scenario": scenario, "frame_index": index, "timestamp": f"{frame.timestamp:.6f}",
                        "blur_sigma": sigma, "intrinsics": name}
                if view is None:
                    for method in config.methods:
                        rows.append({**base, "method": method, "success": False, "reason": render_reason,
                                     **uncorrected})
                    bar.update()
                    continue
                view_told, field_told = view, field_obj
                if config.shift == "both":
                    view_told = RenderedView(view.rgb, view.depth_m, view.opacity, K_given)
                    field_told = _ToldShiftedIntrinsics(field_obj, view.intrinsics, K_given)
                for method, ok, reason, T_corr, cov, n_match, n_in, model, secs in _run_methods(
                        given, view_told, field_told, T_world_cam_est, config, feats_real, feats_view):
                    row = {**base, "method": method, "success": ok, "reason": reason, "num_matches": n_match,
                           "num_inliers": n_in, "intrinsics_model": model, "time_s": round(secs, 4)}
                    if ok:
                        row.update(_errors(frame, T_corr, T_world_cam_gt, config), nees=_nees(T_corr, cov, T_world_cam_gt))
                    else:
                        row.update(uncorrected)
                    rows.append(row)
                bar.update()
    bar.close()
    _write_csv(out / "results.csv", rows)
    summary = summarise(rows, config)
    record = {"provenance": provenance(asdict(config)), **summary}
    (out / "summary.json").write_text(json.dumps(record, indent=1))
    write_table(summary, out / "table.md")
    plot_heatmaps(summary, out, config)
    return summary


def at_colour_instant(sequence, index: int, timing: CaptureTiming | None) -> RGBDFrame:
    """Frame ``index`` with its depth warped (and scaled) to its colour's capture instant by
    the ground-truth motion between the two instants; as it is without ``timing``, without a
    depth stamp, or where the ground truth does not cover both instants."""
    timing = CaptureTiming.of(timing)

    frame = sequence[index]
    if not timing or frame.depth_timestamp is None or getattr(sequence, "ground_truth_at", None) is None:
        return frame
    t_depth = frame.depth_timestamp + timing.depth_offset_s
    t_colour = frame.timestamp + timing.colour_offset_s
    T_world_colour, T_world_depth = sequence.ground_truth_at(np.array([t_colour, t_depth]))
    if not (np.all(np.isfinite(T_world_colour)) and np.all(np.isfinite(T_world_depth))):
        return frame
    T_colour_depth = np.linalg.inv(T_world_colour) @ T_world_depth
    depth = warp_depth(frame.depth_m, frame.intrinsics, T_colour_depth, timing.depth_scale)
    return frame.with_depth(depth)


def _errors(frame: RGBDFrame, T_corr: np.ndarray, T_world_cam_gt: np.ndarray, config: EvalKConfig) -> dict:
    t_err, r_err = pose_error(T_corr, T_world_cam_gt)
    return {"rot_err_deg": r_err, "trans_err_m": t_err,
            "rmse_3d_m": rmse_3d(frame.depth_m, frame.intrinsics, T_corr, T_world_cam_gt, config.grid_stride)}


def _write_csv(path: Path, rows: list[dict]) -> None:
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=CSV_COLUMNS)
        writer.writeheader()
        for row in rows:
            writer.writerow({k: row.get(k, "") for k in CSV_COLUMNS})


def _stats(values) -> dict:
    arr = np.array([v for v in values if v != ""], dtype=float)
    arr = arr[np.isfinite(arr)]
    if arr.size == 0:
        return {"mean": None, "median": None, "p90": None, "max": None}
    return {"mean": float(np.mean(arr)), "median": float(np.median(arr)), "p90": float(np.percentile(arr, 90)),
            "max": float(np.max(arr))}


def summarise(rows: list[dict], config: EvalKConfig) -> dict:
    """Per cell (blur x intrinsics) and method: success rate, mean / median / p90 / max of each
    metric over *all* trials (a failure scored as the uncorrected pose), the NEES of the
    successful ones; and per pair of :data:`PAIRS` the mean paired difference PnP - NAP3D."""
    cells: dict = {}
    for sigma in config.blur_sigmas:
        for name in config.intrinsics_noise:
            key = f"blur{sigma:g}/{name}"
            cell = {"blur_sigma": sigma, "intrinsics": name, "methods": {}, "pairs": {}}
            in_cell = [r for r in rows if r["blur_sigma"] == sigma and r["intrinsics"] == name]
            for method in config.methods:
                mine = [r for r in in_cell if r["method"] == method]
                ok = [r for r in mine if r["success"]]
                cell["methods"][method] = {
                    "trials": len(mine),
                    "success_rate": len(ok) / len(mine) if mine else None,
                    **{m: _stats([r[m] for r in mine]) for m in METRICS},
                    "nees": _stats([r.get("nees", "") for r in ok]),
                    "calibrated_share": (sum(r.get("intrinsics_model", "").startswith("calibrated") for r in ok)
                                         / len(ok)) if ok else None,
                }
            for pair, a, b in PAIRS:
                if a in config.methods and b in config.methods:
                    cell["pairs"][pair] = _paired_difference(in_cell, a, b)
            cells[key] = cell
    return {"config": {"scenarios": config.scenarios, "seed": config.seed, "methods": list(config.methods),
                       "max_trans_m": config.max_trans_m, "max_rot_deg": config.max_rot_deg,
                       "blur_sigmas": list(config.blur_sigmas), "intrinsics_noise": config.intrinsics_noise,
                       "shift": config.shift, "grid_stride": config.grid_stride, "matcher": config.align.matcher,
                       "failures": "scored as the uncorrected pose's error",
                       "capture_timing": None if config.timing is None else {
                           k: CaptureTiming.of(config.timing).to_dict()[k] for k in ("depth_offset_s", "colour_offset_s", "depth_scale")}},
            "methods": {m: METHODS[m] for m in config.methods},
            "pairs": {p: {"pnp_side": a, "nap3d_side": b} for p, a, b in PAIRS
                      if a in config.methods and b in config.methods},
            "cells": cells}


def _paired_difference(rows: list[dict], a: str, b: str) -> dict:
    """Mean over scenarios of ``metric(a) - metric(b)`` (failures scored, so every scenario counts)."""
    by_scenario: dict = {}
    for r in rows:
        by_scenario.setdefault(r["scenario"], {})[r["method"]] = r
    both = [v for v in by_scenario.values() if a in v and b in v]
    return {m: (float(np.mean([v[a][m] - v[b][m] for v in both])) if both else None) for m in METRICS} | \
        {"pairs": len(both), "pnp_side": a, "nap3d_side": b}


def write_table(summary: dict, path: Path) -> None:
    """A Markdown table: per cell and method, success rate, translation and rotation error
    (median / p90 / max), mean 3D RMSE and mean NEES."""
    lines = [f"# Evaluation K ({summary['config']['scenarios']} scenarios, intrinsics shift on "
             f"{summary['config']['shift']} camera{'s' if summary['config']['shift'] == 'both' else ''})", "",
             "Failures are scored as the uncorrected pose's error. NEES: mean over successful corrections "
             "(chi2(6) mean is 6).", "",
             "| cell | method | success | trans median / p90 / max (mm) | rot median / p90 / max (deg) | "
             "3D RMSE mean (mm) | NEES |", "|---|---|---|---|---|---|---|"]
    for key, cell in summary["cells"].items():
        for method, s in cell["methods"].items():
            t, r, e, n = s["trans_err_m"], s["rot_err_deg"], s["rmse_3d_m"], s["nees"]["mean"]
            if t["median"] is None:
                lines.append(f"| {key} | {method} | - | - | - | - | - |")
                continue
            lines.append(f"| {key} | {method} | {s['success_rate'] * 100:.0f}% | {t['median'] * 1000:.2f} / "
                         f"{t['p90'] * 1000:.2f} / {t['max'] * 1000:.1f} | {r['median']:.3f} / {r['p90']:.3f} / "
                         f"{r['max']:.2f} | {e['mean'] * 1000:.2f} | {'-' if n is None else f'{n:.1f}'} |")
    path.write_text("\n".join(lines) + "\n")


def plot_heatmaps(summary: dict, out: Path, config: EvalKConfig) -> list[Path]:
    """One PNG per compared pair, three panels (rotation, translation, 3D RMSE): the mean
    per-scenario difference PnP - NAP3D per cell (positive: NAP3D better), rows blur sigma,
    columns intrinsics noise. The paper's pair is the paper's Figure 4."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(config.intrinsics_noise)
    labels = {"rot_err_deg": ("rotation error", "deg", 1.0), "trans_err_m": ("translation error", "mm", 1000.0),
              "rmse_3d_m": ("3D RMSE", "mm", 1000.0)}
    paths = []
    for pair, info in summary["pairs"].items():
        a, b = info["pnp_side"], info["nap3d_side"]
        fig, axes = plt.subplots(1, 3, figsize=(16, 4.4))
        for ax, (metric, (title, unit, factor)) in zip(axes, labels.items()):
            grid = np.full((len(config.blur_sigmas), len(names)), np.nan)
            for i, sigma in enumerate(config.blur_sigmas):
                for j, name in enumerate(names):
                    value = summary["cells"][f"blur{sigma:g}/{name}"]["pairs"][pair][metric]
                    if value is not None:
                        grid[i, j] = value * factor
            limit = np.nanmax(np.abs(grid)) if np.any(np.isfinite(grid)) else 1.0
            im = ax.imshow(grid, cmap="RdBu", vmin=-limit, vmax=limit)
            for (i, j), value in np.ndenumerate(grid):
                ax.text(j, i, "n/a" if np.isnan(value) else f"{value:.3g}", ha="center", va="center", fontsize=9)
            ax.set_xticks(range(len(names)), names)
            ax.set_yticks(range(len(config.blur_sigmas)), [f"{s:g}" for s in config.blur_sigmas])
            ax.set_xlabel("intrinsics noise")
            ax.set_ylabel("blur sigma (px)")
            ax.set_title(f"{title} ({unit})")
            fig.colorbar(im, ax=ax, shrink=0.8)
        heading = "the paper's Figure 4: " if pair == "paper" else ""
        fig.suptitle(f"Evaluation K, {heading}mean {a} - {b} per scenario (> 0: {b} better; failures scored "
                     f"as uncorrected; intrinsics shift on {config.shift})")
        fig.tight_layout()
        path = out / (f"fig4_paper_{a}_vs_{b}.png" if pair == "paper" else f"heatmap_{pair}_{a}_vs_{b}.png")
        fig.savefig(path, dpi=100, bbox_inches="tight")  # tight: the long x tick labels are not clipped
        plt.close(fig)
        paths.append(path)
    return paths
