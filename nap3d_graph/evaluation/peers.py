"""NAP3D against its peers on the same perturbed poses, and against the physical limit.

Each trial draws a frame with ground truth and a perturbation of its pose (Evaluation K's:
+-``max_trans_m`` per axis, up to ``max_rot_deg``), moves the frame's depth to its colour's
instant (:func:`~nap3d_graph.evaluation.eval_k.at_colour_instant`), renders the field at the
perturbed pose and runs every method of :data:`~nap3d_graph.baselines.PEERS` on that one
frame and view. A failure scores the uncorrected pose's error. The Cramer-Rao bound of the
trial is computed from the refined NAP3D's inlier matches at the true pose
(:mod:`nap3d_graph.crb`); each method's error is reported against it.

Writes ``trials.csv`` (one row per trial and method), ``summary.json`` (per method: success
rate, median / p90 / max of translation and rotation error, median milliseconds, median
error over the bound) and ``accuracy_vs_time.png``.
"""

from __future__ import annotations

import csv
import json
import logging
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from nap3d_graph.conventions import inv_T, pose_error
from nap3d_graph.crb import bound_sigmas, cramer_rao_bound
from nap3d_graph.datasets.depth_timing import CaptureTiming
from nap3d_graph.nap3d.config import AlignConfig
from nap3d_graph.nap3d.correct import render_safely, resize_frame
from nap3d_graph.nap3d.correspondences import subset
from nap3d_graph.progress import progress_bar
from nap3d_graph.provenance import provenance

from .perturb import random_perturbation

log = logging.getLogger(__name__)

__all__ = ["PeersConfig", "run_bench_peers"]


@dataclass
class PeersConfig:
    trials: int = 40
    seed: int = 0
    max_trans_m: float = 0.10
    max_rot_deg: float = 5.0
    render_size: tuple[int, int] | None = (320, 240)
    methods: tuple[str, ...] = ("nap3d-plain", "nap3d-refined", "nap3d-iter", "pnp-ransac", "gicp", "dense-rgbd",
                                "photometric")
    timing: CaptureTiming | None = None
    matcher: str = "sift"


def run_bench_peers(sequence, field, out_dir, config: PeersConfig | None = None, progress: bool = False) -> dict:
    """Run the comparison; write the files into ``out_dir``; return the summary."""
    from nap3d_graph.baselines import run_peers

    from .eval_k import at_colour_instant

    config = config or PeersConfig()
    if sequence.T_world_cam_gt is None:
        raise ValueError(f"{getattr(sequence, 'path', 'the sequence')}: the peer comparison needs ground truth")
    posed = np.flatnonzero(np.all(np.isfinite(np.asarray(sequence.T_world_cam_gt)), axis=(1, 2)))
    if posed.size == 0:
        raise ValueError("no frame has a ground-truth pose")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(config.seed)
    rows: list[dict] = []
    for trial in progress_bar(range(config.trials), desc="bench-peers", unit="trial", disable=not progress):
        index = int(posed[rng.integers(len(posed))])
        T_world_cam_gt = sequence.T_world_cam_gt[index]
        T_world_cam_est = T_world_cam_gt @ random_perturbation(rng, config.max_trans_m, config.max_rot_deg)
        frame = at_colour_instant(sequence, index, config.timing)
        if config.render_size is not None and tuple(config.render_size) != frame.intrinsics.shape[::-1]:
            frame = resize_frame(frame, *config.render_size)
        t_unc, r_unc = pose_error(T_world_cam_est, T_world_cam_gt)
        base = {"trial": trial, "frame_index": index, "uncorrected_trans_m": t_unc, "uncorrected_rot_deg": r_unc}
        view, reason = render_safely(field, T_world_cam_est, frame.intrinsics)
        if view is None:
            rows += [{**base, "method": m, "success": False, "reason": reason, "trans_err_m": t_unc,
                      "rot_err_deg": r_unc} for m in config.methods]
            continue
        results, corr = run_peers(frame, view, config.methods, field, T_world_cam_est,
                                      align_config=AlignConfig(matcher=config.matcher))
        bound_r = bound_t = float("nan")
        refined = results.get("nap3d-refined")
        if corr is not None and refined is not None and refined.success and refined.inlier_mask is not None:
            # The bound for the noise these inliers carry (their residuals at the true pose).
            bound = cramer_rao_bound(inv_T(T_world_cam_gt) @ T_world_cam_est, subset(corr, refined.inlier_mask), frame.intrinsics,
                                     noise="measured")
            bound_r, bound_t = bound_sigmas(bound)
        for name, a in results.items():
            t_err, r_err = pose_error(a.corrected_pose(T_world_cam_est), T_world_cam_gt) if a.success else (t_unc, r_unc)
            rows.append({**base, "method": name, "success": a.success, "reason": a.reason, "trans_err_m": t_err,
                         "rot_err_deg": r_err, "ms": 1000 * a.timings_s.get("total", np.nan),
                         "num_inliers": a.num_inliers, "crb_trans_m": bound_t, "crb_rot_deg": np.degrees(bound_r)})
    summary = summarise(rows, config)
    _write(out, rows, summary, config)
    return summary


def summarise(rows: list[dict], config: PeersConfig) -> dict:
    """Per method: success rate, error statistics over every trial, time, error / bound."""
    methods = {}
    for name in config.methods:
        mine = [r for r in rows if r["method"] == name]
        t = np.array([r["trans_err_m"] for r in mine]) * 1000
        r = np.array([r["rot_err_deg"] for r in mine])
        ms = np.array([r.get("ms", np.nan) for r in mine], dtype=float)
        ratio_t = np.array([r["trans_err_m"] / r["crb_trans_m"] for r in mine
                            if r.get("crb_trans_m", np.nan) > 0], dtype=float)
        methods[name] = {
            "success_rate": float(np.mean([r["success"] for r in mine])) if mine else 0.0,
            "trans_mm": _stats(t), "rot_deg": _stats(r),
            "ms_median": float(np.nanmedian(ms)) if np.isfinite(ms).any() else None,
            "trans_over_crb_median": float(np.median(ratio_t)) if len(ratio_t) else None,
        }
    bound = np.array([r["crb_trans_m"] for r in rows if r["method"] == config.methods[0]
                      and np.isfinite(r.get("crb_trans_m", np.nan))]) * 1000
    return {"config": {"trials": config.trials, "seed": config.seed, "max_trans_m": config.max_trans_m,
                       "max_rot_deg": config.max_rot_deg, "render_size": config.render_size,
                       "matcher": config.matcher,
                       "capture_timing": None if not config.timing else
                       {k: CaptureTiming.of(config.timing).to_dict()[k] for k in ("depth_offset_s", "colour_offset_s", "depth_scale")},
                       "failures": "scored as the uncorrected pose's error"},
            "methods": methods, "crb_trans_mm": _stats(bound)}


def _stats(values: np.ndarray) -> dict:
    if not len(values):
        return {"median": None, "p90": None, "max": None}
    return {"median": float(np.median(values)), "p90": float(np.percentile(values, 90)), "max": float(values.max())}


def _write(out: Path, rows: list[dict], summary: dict, config) -> None:
    columns = ["trial", "frame_index", "method", "success", "reason", "trans_err_m", "rot_err_deg", "ms",
               "num_inliers", "crb_trans_m", "crb_rot_deg", "uncorrected_trans_m", "uncorrected_rot_deg"]
    with open(out / "trials.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    (out / "summary.json").write_text(json.dumps({"provenance": provenance(asdict(config)), **summary},
                                                 indent=1))
    _plot(summary, out / "accuracy_vs_time.png")


def _plot(summary: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for name, m in summary["methods"].items():
        if m["ms_median"] is None or m["trans_mm"]["median"] is None:
            continue
        x = m["ms_median"]
        ax.errorbar([x], [m["trans_mm"]["median"]], yerr=[[0], [m["trans_mm"]["p90"] - m["trans_mm"]["median"]]],
                    fmt="o", capsize=4, label=f"{name} ({m['success_rate']:.0%} ok)")
    crb = summary["crb_trans_mm"]["median"]
    if crb:
        ax.axhline(crb, color="grey", ls="--", lw=1, label=f"Cramer-Rao bound (median) {crb:.2f} mm")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("milliseconds per correction (median)")
    ax.set_ylabel("translation error, mm (median, bar to p90)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
