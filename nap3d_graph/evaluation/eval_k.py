"""The paper's Evaluation K: NAP3D vs PnP-RANSAC under blur and intrinsics noise.

For each scenario: a random frame, a random perturbation of its ground-truth pose
(translation uniform in +-10 cm per axis, rotation up to 5 deg), the field renders at the
perturbed pose. Each scenario is evaluated 16 times: Gaussian blur of the real image with
sigma in {0, 1.0, 1.8, 2.2} x the intrinsics given to the methods for the real camera
shifted by (focal scale, principal-point offset px) in CLEAN (1.0, 0), MILD (1.03, 2),
MEDIUM (1.06, 5), HARSH (1.10, 10). The field renders with its true intrinsics, as the
paper's renders were made once per scenario before the 16 evaluations. Every method runs on
the *same* matches of each cell. Methods: ``nap3d`` (the default: refined, estimating the
real camera's intrinsics when the pixels call for it), ``nap3d-fixed-k`` (refined, trusting
the given intrinsics), ``nap3d-plain`` (the paper's RANSAC + weighted Procrustes), ``pnp``
(PnP-RANSAC) and optionally ``nap3d-iter`` (correct_pose, re-rendering at the corrected pose).

Metrics per method: rotation error (deg), translation error (m) and 3D RMSE: over the real
frame's valid depth pixels on a fixed grid (every ``grid_stride`` px), the RMSE between
their world points under the estimated and under the true camera pose.
"""

from __future__ import annotations

import csv
import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from nap3d_graph.alignment import AlignConfig, align_correspondences, prepare_correspondences, view_features
from nap3d_graph.matching import detect_features
from nap3d_graph.camera import RGBDFrame, backproject_depth
from nap3d_graph.conventions import pose_error, transform_points
from nap3d_graph.nap3d import correct_pose, render_safely
from nap3d_graph.pnp import pnp_from_correspondences
from nap3d_graph.results import Alignment

from .perturb import random_perturbation

__all__ = ["EvalKConfig", "BLUR_SIGMAS", "INTRINSICS_NOISE", "run_eval_k", "rmse_3d", "METHODS"]

log = logging.getLogger(__name__)

BLUR_SIGMAS = (0.0, 1.0, 1.8, 2.2)
INTRINSICS_NOISE = {"CLEAN": (1.0, 0.0), "MILD": (1.03, 2.0), "MEDIUM": (1.06, 5.0), "HARSH": (1.10, 10.0)}
METHODS = ("nap3d", "nap3d-fixed-k", "nap3d-plain", "pnp", "nap3d-iter")
CSV_COLUMNS = ["scenario", "frame_index", "timestamp", "blur_sigma", "intrinsics", "method", "success", "reason",
               "rot_err_deg", "trans_err_m", "rmse_3d_m", "num_matches", "num_inliers", "time_s"]


@dataclass
class EvalKConfig:
    scenarios: int = 40
    seed: int = 0
    max_trans_m: float = 0.10
    max_rot_deg: float = 5.0
    methods: tuple[str, ...] = ("nap3d", "nap3d-fixed-k", "nap3d-plain", "pnp")
    blur_sigmas: tuple[float, ...] = BLUR_SIGMAS
    intrinsics_noise: dict = field(default_factory=lambda: dict(INTRINSICS_NOISE))
    grid_stride: int = 8
    iterations: int = 3  # for nap3d-iter
    align: AlignConfig = field(default_factory=AlignConfig)

    def __post_init__(self) -> None:
        unknown = set(self.methods) - set(METHODS)
        if unknown:
            raise ValueError(f"unknown method(s) {sorted(unknown)}; choose from {list(METHODS)}")


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
    return RGBDFrame(rgb, frame.depth_m, frame.intrinsics, frame.timestamp)


def _run_methods(frame_given: RGBDFrame, view, field_obj, T_est, config: EvalKConfig, feats_real, feats_view):
    """Every method on one cell, sharing one set of matches. Yields (method, success,
    reason, corrected pose, matches, inliers, seconds)."""
    timings: dict = {}
    t0 = time.perf_counter()
    corr, reason = prepare_correspondences(frame_given, view, config.align, timings, feats_real, feats_view)
    t_match = time.perf_counter() - t0
    for method in config.methods:
        t0 = time.perf_counter()
        if method == "nap3d-iter":
            c = correct_pose(frame_given, field_obj, T_est, iterations=config.iterations, config=config.align,
                             render_intrinsics=view.intrinsics)
            yield method, c.success, c.reason, c.T_world_cam_corrected, c.num_matches, c.num_inliers, \
                time.perf_counter() - t0
            continue
        if corr is None:
            result = Alignment.failure(reason)
        elif method == "pnp":
            result = pnp_from_correspondences(corr, frame_given.intrinsics, align_config=config.align)
        else:
            cfg = {"nap3d": config.align, "nap3d-plain": _with(config.align, method="plain"),
                   "nap3d-fixed-k": _with(config.align, estimate_intrinsics=False)}[method]
            result = align_correspondences(corr, frame_given.intrinsics, cfg)
        T_corr = result.corrected_pose(T_est) if result.success else T_est
        yield method, result.success, result.reason, T_corr, result.num_matches, result.num_inliers, \
            time.perf_counter() - t0 + t_match


def _with(config: AlignConfig, **changes) -> AlignConfig:
    from dataclasses import replace

    return replace(config, **changes)


def run_eval_k(sequence, field_obj, out_dir: str | Path, config: EvalKConfig | None = None,
               progress: bool = False) -> dict:
    """Run Evaluation K on ``sequence`` (with ground truth) and ``field_obj``; write
    ``results.csv``, ``summary.json`` and heatmaps into ``out_dir``; return the summary."""
    from tqdm import tqdm

    config = config or EvalKConfig()
    if sequence.T_world_cam_gt is None:
        raise ValueError(f"{sequence.path}: Evaluation K needs ground-truth poses (groundtruth.txt)")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(config.seed)
    rows: list[dict] = []
    cells = len(config.blur_sigmas) * len(config.intrinsics_noise)
    bar = tqdm(total=config.scenarios * cells, desc="eval-k", unit="cell", disable=not progress)
    for scenario in range(config.scenarios):
        index = int(rng.integers(len(sequence)))
        T_gt = sequence.T_world_cam_gt[index]
        T_est = T_gt @ random_perturbation(rng, config.max_trans_m, config.max_rot_deg)
        frame = sequence[index]
        view, render_reason = render_safely(field_obj, T_est, frame.intrinsics)
        # Features depend on the image only: once per view and per blur level, reused by
        # the four intrinsics settings (which only change the back-projection).
        feats_view = view_features(view, config.align) if view is not None else None
        for sigma in config.blur_sigmas:
            blurred = _blur(frame, sigma)
            feats_real = detect_features(blurred.rgb, config.align.max_features)
            for name, (focal_scale, offset_px) in config.intrinsics_noise.items():
                given = blurred.with_intrinsics(frame.intrinsics.shifted(focal_scale, offset_px))
                base = {"scenario": scenario, "frame_index": index, "timestamp": f"{frame.timestamp:.6f}",
                        "blur_sigma": sigma, "intrinsics": name}
                if view is None:
                    for method in config.methods:
                        rows.append({**base, "method": method, "success": False, "reason": render_reason})
                    bar.update()
                    continue
                for method, ok, reason, T_corr, n_match, n_in, secs in _run_methods(
                        given, view, field_obj, T_est, config, feats_real, feats_view):
                    row = {**base, "method": method, "success": ok, "reason": reason, "num_matches": n_match,
                           "num_inliers": n_in, "time_s": round(secs, 4)}
                    if ok:
                        t_err, r_err = pose_error(T_corr, T_gt)
                        row.update(rot_err_deg=r_err, trans_err_m=t_err,
                                   rmse_3d_m=rmse_3d(frame.depth_m, frame.intrinsics, T_corr, T_gt,
                                                     config.grid_stride))
                    rows.append(row)
                bar.update()
    bar.close()
    _write_csv(out / "results.csv", rows)
    summary = summarise(rows, config)
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    plot_heatmaps(summary, out, config)
    return summary


def _write_csv(path: Path, rows: list[dict]) -> None:
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=CSV_COLUMNS)
        writer.writeheader()
        for row in rows:
            writer.writerow({k: row.get(k, "") for k in CSV_COLUMNS})


def _stats(values: list[float]) -> dict:
    arr = np.array(values, dtype=float)
    if arr.size == 0:
        return {"mean": None, "median": None}
    return {"mean": float(np.mean(arr)), "median": float(np.median(arr))}


def summarise(rows: list[dict], config: EvalKConfig) -> dict:
    """Per cell (blur x intrinsics) and method: mean and median of each metric over the
    successful trials, success rate; plus paired mean differences PnP - NAP3D."""
    cells: dict = {}
    for sigma in config.blur_sigmas:
        for name in config.intrinsics_noise:
            key = f"blur{sigma:g}/{name}"
            cell = {"blur_sigma": sigma, "intrinsics": name, "methods": {}}
            in_cell = [r for r in rows if r["blur_sigma"] == sigma and r["intrinsics"] == name]
            for method in config.methods:
                mine = [r for r in in_cell if r["method"] == method]
                ok = [r for r in mine if r["success"]]
                cell["methods"][method] = {
                    "trials": len(mine),
                    "success_rate": len(ok) / len(mine) if mine else None,
                    **{m: _stats([r[m] for r in ok]) for m in ("rot_err_deg", "trans_err_m", "rmse_3d_m")},
                }
            if "pnp" in config.methods and "nap3d" in config.methods:
                cell["pnp_minus_nap3d"] = _paired_difference(in_cell, "pnp", "nap3d")
            cells[key] = cell
    return {"config": {"scenarios": config.scenarios, "seed": config.seed, "methods": list(config.methods),
                       "max_trans_m": config.max_trans_m, "max_rot_deg": config.max_rot_deg,
                       "blur_sigmas": list(config.blur_sigmas), "intrinsics_noise": config.intrinsics_noise,
                       "grid_stride": config.grid_stride},
            "cells": cells}


def _paired_difference(rows: list[dict], a: str, b: str) -> dict:
    by_scenario: dict = {}
    for r in rows:
        if r["success"]:
            by_scenario.setdefault(r["scenario"], {})[r["method"]] = r
    both = [v for v in by_scenario.values() if a in v and b in v]
    return {m: (float(np.mean([v[a][m] - v[b][m] for v in both])) if both else None)
            for m in ("rot_err_deg", "trans_err_m", "rmse_3d_m")} | {"pairs": len(both)}


def plot_heatmaps(summary: dict, out: Path, config: EvalKConfig) -> list[Path]:
    """One PNG per metric: mean per-cell difference PnP - NAP3D (positive: NAP3D better),
    rows blur sigma, columns intrinsics noise (the paper's Figure 4)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not ("pnp" in config.methods and "nap3d" in config.methods):
        return []
    names = list(config.intrinsics_noise)
    labels = {"rot_err_deg": ("rotation error", "deg"), "trans_err_m": ("translation error", "mm"),
              "rmse_3d_m": ("3D RMSE", "mm")}
    paths = []
    for metric, (title, unit) in labels.items():
        grid = np.full((len(config.blur_sigmas), len(names)), np.nan)
        for i, sigma in enumerate(config.blur_sigmas):
            for j, name in enumerate(names):
                value = summary["cells"][f"blur{sigma:g}/{name}"]["pnp_minus_nap3d"][metric]
                if value is not None:
                    grid[i, j] = value * (1000.0 if unit == "mm" else 1.0)
        fig, ax = plt.subplots(figsize=(5.5, 4.2))
        limit = np.nanmax(np.abs(grid)) if np.any(np.isfinite(grid)) else 1.0
        im = ax.imshow(grid, cmap="RdBu", vmin=-limit, vmax=limit)
        for (i, j), value in np.ndenumerate(grid):
            ax.text(j, i, "n/a" if np.isnan(value) else f"{value:.3g}", ha="center", va="center", fontsize=9)
        ax.set_xticks(range(len(names)), names)
        ax.set_yticks(range(len(config.blur_sigmas)), [f"{s:g}" for s in config.blur_sigmas])
        ax.set_xlabel("intrinsics noise")
        ax.set_ylabel("blur sigma (px)")
        ax.set_title(f"{title}: PnP - NAP3D ({unit}); > 0: NAP3D better")
        fig.colorbar(im, ax=ax, shrink=0.8)
        fig.tight_layout()
        path = out / f"heatmap_{metric}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        paths.append(path)
    return paths
