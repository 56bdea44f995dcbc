"""The field stage of a map cut into submaps: one field per submap, trained side by side.

Each submap's field is built as a one-room map's is (:func:`~nap3d_graph.fields.build.build_field`
at the map's poses, the frames outside the submap left unposed) with the capture timing
estimated once for the whole survey, and each gets the training time a one-room map of its size
gets: what the map's per-room budget leaves once its share of the stages before the field ran.
The submaps are independent jobs on a pool (:mod:`nap3d_graph.pools`): processes on this
machine, or Ray tasks on this machine or a cluster. A map interrupted here resumes with the
submaps already trained. ``field.report.json`` then holds the submaps' reports and, for the
map's report, the held-out figures of the map's field: the submaps' held-out frames that no
submap trained on, each rendered as a run renders it (from the submap it looks into, what lies
past that submap's grid from the next ones). A submap's own held-out figures score its field
alone, so what its views see past its part of the floor is empty there.
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from nap3d_graph.datasets.depth_timing import estimate_timing
from nap3d_graph.datasets.posed import PosedSequence
from nap3d_graph.fields import load_field
from nap3d_graph.fields.build import build_field
from nap3d_graph.fields.evaluation import evaluate_field, oracle_for
from nap3d_graph.fields.submaps import Submap, SubmapSettings, load_submap_field, write_submaps_index
from nap3d_graph.pools import peak_memory_gb
from nap3d_graph.textfiles import write_json_atomic
from nap3d_graph.torch_threads import torch_threads

__all__ = ["train_submap_fields", "train_one_submap", "submap_job", "submap_minutes"]

log = logging.getLogger(__name__)


def submap_minutes(budget_minutes: float | None, min_minutes: float, reserve_s: float, elapsed_s: float,
                   submaps: int) -> float | None:
    """Training minutes of each submap: a one-room map's budget less its share of the
    ``elapsed_s`` the stages before the field spent and the ``reserve_s`` kept for what follows
    its training, at least ``min_minutes`` (None: no budget, the trainer's own default)."""
    if budget_minutes is None:
        return None
    left_s = budget_minutes * 60.0 - elapsed_s / max(submaps, 1) - reserve_s
    return max(min_minutes, left_s / 60.0)


def submap_job(sequence, T_map_cam: np.ndarray, submap: Submap, settings, minutes: float | None, device: str | None,
               timing: dict | None, out: Path) -> dict:
    """What :func:`train_one_submap` needs to train ``submap``'s field (of ``settings.model``, on
    its frames of ``sequence`` at ``T_map_cam``, in its grid's frame) into ``out``, as one
    picklable job."""
    return {"sequence": sequence, "T_map_cam": np.asarray(T_map_cam, dtype=float), "frames": submap.frames,
            "R_grid_map": submap.R_grid_map, "slab_m": submap.slab_m(settings.submaps.reach_m),
            "index": submap.index, "model": settings.model, "steps": settings.steps, "minutes": minutes,
            "seed": settings.seed, "device": device, "matcher": settings.matcher,
            "refine_rounds": settings.refine_rounds, "timing": timing, "out": str(out)}


def train_one_submap(job: dict) -> dict:
    """One submap's field (runs in a worker): ``job`` holds the survey, the map's poses, the
    submap's frames, the build's settings and the file to write. Returns its report."""
    t0 = time.perf_counter()
    T = np.full_like(job["T_map_cam"], np.nan)
    frames = np.asarray(job["frames"], dtype=int)
    T_grid_map = np.eye(4)
    if job.get("R_grid_map") is not None:
        T_grid_map[:3, :3] = job["R_grid_map"]
    T[frames] = T_grid_map @ job["T_map_cam"][frames]
    with torch_threads(1):
        field, report = build_field(PosedSequence(job["sequence"], T, "grid"), job["model"], steps=job["steps"],
                                    minutes=job["minutes"], seed=job["seed"], device=job["device"], progress=False,
                                    matcher=job["matcher"], refine_poses=job["refine_rounds"], refine_method="depth",
                                    timing=job["timing"], slab_m=job["slab_m"])
    field.meta["submap"] = int(job["index"])
    out = Path(job["out"])
    out.parent.mkdir(parents=True, exist_ok=True)
    field.save(out)
    report["submap_seconds"] = round(time.perf_counter() - t0, 2)
    report["peak_memory_gb"] = peak_memory_gb()  # of the worker, by the end of this submap
    return report


def train_submap_fields(sequence, T_map_cam: np.ndarray, folder, submaps: list[Submap], settings,
                        submap_settings: SubmapSettings, field_settings: dict, minutes: float | None, pool,
                        device: str | None, say=None) -> dict:
    """Every submap's field not already trained with ``field_settings``, as jobs on ``pool``;
    ``submaps.json`` and the merged ``field.report.json`` written. Returns the merged report."""
    done = folder.info["stages"].get("field", {}).get("submaps", {})
    timing = estimate_timing(PosedSequence(sequence, T_map_cam, "map"))
    timing_dict = None if timing is None else timing.to_dict()
    jobs = {}
    for s in submaps:
        key = str(s.index)
        if done.get(key, {}).get("settings") == field_settings and (folder.root / s.file).is_file():
            continue
        jobs[key] = submap_job(sequence, T_map_cam, s, settings, minutes, device, timing_dict, folder.root / s.file)
    if say is not None and jobs:
        say(f"field: {len(jobs)} submap field(s) of {len(submaps)} to train on {getattr(pool, 'workers', 1)} "
            f"worker(s) ({pool.name})" + (f", {minutes:.1f} min each" if minutes is not None else ""))
    reports = {key: value.get("report") for key, value in done.items()}
    started = time.perf_counter()
    pending = {pool.submit(train_one_submap, job): key for key, job in jobs.items()}
    while pending:
        finished, _ = pool.wait_any(list(pending))
        for ref in finished:
            key = pending.pop(ref)
            report = pool.result(ref)
            reports[key] = _summary(report)
            done[key] = {"settings": field_settings, "seconds": report.get("submap_seconds"), "report": reports[key]}
            folder.info["stages"].setdefault("field", {})["submaps"] = done
            folder.save()  # a map interrupted now resumes with this submap trained
            log.info("submap %s trained in %.0f s", key, report.get("submap_seconds", 0.0))
    write_submaps_index(folder.root, submaps, submap_settings,
                        {"timing": timing_dict, "wall_seconds": round(time.perf_counter() - started, 2)})
    merged = _merged_report(submaps, reports, timing_dict)
    merged["held_out"] = _held_out_of_map(sequence, T_map_cam, folder.root, (merged["held_out"] or {}).get("frames"),
                                          timing)
    write_json_atomic(folder.field_report, merged, default=float)
    return merged


#: What the map keeps of a held-out evaluation (:func:`~nap3d_graph.fields.evaluation.evaluate_field`).
HELD_OUT_KEYS = ("frames", "psnr_db", "psnr_affine_db", "depth_abs_err_m", "opaque_fraction")


def _held_out_of_map(sequence, T_map_cam: np.ndarray, root: Path, frames, timing) -> dict | None:
    """The map's field (:func:`~nap3d_graph.fields.submaps.load_submap_field` of ``root``) on
    ``frames`` of ``sequence`` at ``T_map_cam`` that no submap trained on, rendered at the
    pipeline's 320 x 240 (the frames' size when smaller), as ``build_field`` scores a field: None
    without such frames."""
    field = load_submap_field(root, load_field)
    # One field loaded at a time (the frames taken submap by submap): the map's process holds
    # the survey too, and two floor-sized fields here were its peak.
    field.settings = replace(field.settings, resident=1)
    trained = set(int(i) for i in field.meta.get("train_frames", []))
    held = [int(i) for i in frames or () if int(i) not in trained]
    if not held:
        return None
    held.sort(key=lambda i: (field.submap_at(T_map_cam[i]), i))
    K = sequence.intrinsics
    size = (320, 240) if K.width >= 320 and K.height >= 240 else None
    posed = PosedSequence(sequence, T_map_cam, "map")
    result = evaluate_field(field, posed, held, oracle_for(posed), size=size, timing=timing)
    return {k: result.get(k) for k in HELD_OUT_KEYS}


def _summary(report: dict) -> dict:
    """What the map keeps of a submap's report: its held-out figures (without the per-frame
    rows' images), its field error and its times."""
    held = dict(report.get("held_out") or {})
    keep = {k: held.get(k) for k in HELD_OUT_KEYS}
    error = {k: v for k, v in (report.get("field_error") or {}).items() if k != "by_view"}
    return {"held_out": keep, "field_error": error, "train_seconds": report.get("train_seconds"),
            "total_seconds": report.get("total_seconds"), "submap_seconds": report.get("submap_seconds"),
            "train_frames": report.get("train_frames"), "model": report.get("model"),
            "peak_memory_gb": report.get("peak_memory_gb")}


def _merged_report(submaps: list[Submap], reports: dict, timing: dict | None) -> dict:
    """The map's ``field.report.json`` over its submaps: the held-out figures over all their
    held-out frames (PSNR and cover weighted by frames, the median depth error the median of
    theirs), the largest field error, and each submap's report."""
    parts = [reports[str(s.index)] for s in submaps if reports.get(str(s.index))]
    held = [p["held_out"] for p in parts if (p.get("held_out") or {}).get("frames")]
    weights = np.array([len(h["frames"]) for h in held], dtype=float)

    def weighted(key: str):
        values = [(h.get(key), w) for h, w in zip(held, weights) if h.get(key) is not None]
        return float(np.average([v for v, _ in values], weights=[w for _, w in values])) if values else None

    medians = [h["depth_abs_err_m"]["median"] for h in held if (h.get("depth_abs_err_m") or {}).get("median") is not None]
    merged_held = {"frames": [f for h in held for f in h["frames"]], "psnr_db": weighted("psnr_db"),
                   "psnr_affine_db": weighted("psnr_affine_db"), "opaque_fraction": weighted("opaque_fraction"),
                   "depth_abs_err_m": {"median": float(np.median(medians)) if medians else None}} if held else None
    errors = [p["field_error"] for p in parts if p.get("field_error")]
    worst = max(errors, key=lambda e: float(e.get("sigma_m", 0.0) or 0.0)) if errors else None
    return {"model": parts[0].get("model") if parts else None, "submaps": [reports.get(str(s.index)) for s in submaps],
            "timing": timing, "held_out": merged_held, "field_error": worst,
            "train_seconds": max((p.get("train_seconds") or 0.0) for p in parts) if parts else None}
