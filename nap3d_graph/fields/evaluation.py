"""How good is a field? Held-out renders against the sensor (or the simulator's exact room).

One protocol for every field type (grid, splat, oracle, nerfstudio), so candidates can be
compared on the same frames: render at each frame's pose, at the resolution the pipeline
renders at, and compare with the frame itself.

* colour: PSNR raw, over the pixels the real image holds data for (an undistorting reader's
  black corners are no measurement, :func:`~nap3d_graph.camera.colour_coverage`), and after a per-image, per-channel affine colour fit of the render onto
  the image (a real camera's exposure and white balance change from frame to frame; the
  alignment's SIFT does not care, a raw PSNR does);
* depth: the median / p90 of |field - reference| where the field is opaque, the reference
  being the simulator's noise-free depth when there is one, else the sensor's depth; and the
  fraction of the pixels with a reference depth where the field is opaque (> 0.5);
* the paper's unit check: a linear fit of sensor depth against field depth;
* the render time.

With ``timing`` (a real recording's depth and colour capture offsets and depth scale, see
:mod:`nap3d_graph.datasets.depth_timing`) colour is compared at the pose of the colour's
capture time and depth at the pose of the depth's, with the sensor depth scaled; without,
both at the frame's ground-truth pose.
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from nap3d_graph.camera import colour_coverage
from nap3d_graph.datasets.depth_timing import CaptureTiming
from nap3d_graph.sims.scene_file import oracle_from_file

__all__ = ["evaluate_field", "psnr", "oracle_for", "affine_fit_psnr"]

log = logging.getLogger(__name__)


def psnr(mse: float) -> float:
    """Peak signal-to-noise ratio (dB) of a mean squared error on [0, 1] colours."""
    return float(-10.0 * math.log10(max(mse, 1e-12)))


def oracle_for(sequence):
    """The noise-free oracle of a simulated sequence, or None for real data.

    Uses ``sequence.oracle_field()`` when the sequence offers one (``SimSequence``), else a
    ``scene.json`` in the sequence's folder. None for a simulated sequence posed by anything but
    the simulator (a map's poses, a reframed ground truth: ``pose_source``): the oracle renders in
    the simulator's world frame, and at a map's poses it would be another view of the room.
    """
    if getattr(sequence, "pose_source", None) is not None:
        return None
    if hasattr(sequence, "oracle_field"):
        try:
            return sequence.oracle_field()
        except Exception as exc:  # a broken scene only costs the noise-free figures
            log.warning("cannot build the oracle field: %s", exc)
            return None
    folder = getattr(sequence, "path", None)
    if folder is not None and (Path(folder) / "scene.json").is_file():
        try:
            return oracle_from_file(Path(folder) / "scene.json")
        except ValueError as exc:
            log.warning("cannot build the oracle field: %s", exc)
    return None


def affine_fit_psnr(rendered01: np.ndarray, real01: np.ndarray, mask: np.ndarray,
                    scored: np.ndarray | None = None) -> float:
    """PSNR after mapping each channel of the render (H, W, 3) in [0, 1] onto the image by
    the least-squares affine fit over ``mask`` (H, W) pixels (the ``scored`` (H, W) pixels
    count in the PSNR; all when None)."""
    fitted = rendered01.copy()
    if mask.sum() >= 10:
        for k in range(3):
            x, y = rendered01[..., k][mask], real01[..., k][mask]
            A = np.stack([x, np.ones_like(x)], axis=1)
            (a, b), *_ = np.linalg.lstsq(A, y, rcond=None)
            fitted[..., k] = a * rendered01[..., k] + b
    err = (np.clip(fitted, 0, 1) - real01) ** 2
    return psnr(float(np.mean(err if scored is None else err[scored])))


def _poses(sequence, indices, timing):
    """Colour and depth poses (N, 4, 4) of frames ``indices`` and the depth scale."""
    indices = np.asarray(indices, dtype=int)
    poses = np.asarray(sequence.T_world_cam_gt, dtype=np.float64)[indices]
    at = getattr(sequence, "ground_truth_at", None)
    if timing is None or at is None:
        return poses, poses, 1.0
    T_colour = at(np.asarray(sequence.timestamps)[indices] + timing.colour_offset_s)
    T_depth = at(np.asarray(sequence.depth_timestamps)[indices] + timing.depth_offset_s)
    return T_colour, T_depth, float(timing.depth_scale)


def evaluate_field(field, sequence, indices: Sequence[int], oracle=None, size: tuple[int, int] | None = None,
                   timing: CaptureTiming | None = None) -> dict:
    """Held-out metrics of any field on frames ``indices`` of a posed ``sequence``.

    ``size``: (width, height) the field renders at (frames are downscaled to it; default the
    sequence's own). ``oracle``: the simulator's exact field, the depth reference when given.
    ``timing``: the :class:`~nap3d_graph.datasets.depth_timing.CaptureTiming` of a real recording.
    Returns a dict (see the module docstring) with a ``per_frame`` list.
    """
    timing = CaptureTiming.of(timing)
    if getattr(sequence, "T_world_cam_gt", None) is None:
        raise ValueError("evaluating a field needs ground-truth poses")
    K_full = sequence.intrinsics.without_distortion()
    K = K_full if size is None else K_full.scaled(*size)
    T_colour, T_depth, scale = _poses(sequence, indices, timing)
    scored = colour_coverage(sequence, None if size is None else (K.width, K.height))
    if scored is None:
        scored = np.ones((K.height, K.width), bool)  # every pixel holds data
    sq_err, n_px = 0.0, 0
    abs_errs, opac, opaque, xs, ys, secs, per_frame, affine = [], [], [], [], [], [], [], []
    for k, i in enumerate(indices):
        if not (np.all(np.isfinite(T_colour[k])) and np.all(np.isfinite(T_depth[k]))):
            continue
        rgb_real, sensor = _frame_at(sequence[int(i)], K, size, scale)
        started = time.perf_counter()
        view = field.render(T_colour[k], K)
        secs.append(time.perf_counter() - started)
        depth_view = view if T_depth[k] is T_colour[k] or np.allclose(T_depth[k], T_colour[k]) else \
            field.render(T_depth[k], K)
        real01 = rgb_real.astype(np.float64) / 255.0
        rend01 = view.rgb.astype(np.float64) / 255.0
        err2 = (rend01 - real01) ** 2
        frame_mse = float(np.mean(err2[scored]))
        sq_err += frame_mse * int(scored.sum())
        n_px += int(scored.sum())
        frame_affine = affine_fit_psnr(rend01, real01, (view.opacity > 0.5) & scored, scored)
        affine.append(frame_affine)
        reference = oracle.render(T_depth[k], K).depth_m if oracle is not None else sensor
        surface = reference > 0
        seen = surface & (depth_view.opacity > 0.5)
        err = np.abs(depth_view.depth_m - reference)[seen]
        abs_errs.append(err)
        opac.append(depth_view.opacity[surface])
        opaque.append(seen.sum() / max(surface.sum(), 1))
        fit = (sensor > 0) & (depth_view.opacity > 0.5) & (depth_view.depth_m > 0)
        xs.append(depth_view.depth_m[fit])
        ys.append(sensor[fit])
        per_frame.append({"index": int(i), "psnr_db": psnr(frame_mse), "psnr_affine_db": frame_affine,
                          "depth_abs_err_median_m": float(np.median(err)) if err.size else None,
                          "opaque_fraction": float(opaque[-1])})
    errs = np.concatenate(abs_errs) if abs_errs else np.zeros(0)
    x, y = (np.concatenate(xs), np.concatenate(ys)) if xs else (np.zeros(0), np.zeros(0))
    return {
        "frames": [int(i) for i in indices],
        "render_size": [K.width, K.height],
        "psnr_db": psnr(sq_err / max(n_px, 1)),
        "psnr_affine_db": float(np.mean(affine)) if affine else None,
        "depth_reference": "noise-free (simulator oracle)" if oracle is not None else "sensor depth",
        "depth_abs_err_m": {
            "median": float(np.median(errs)) if errs.size else None,
            "p90": float(np.percentile(errs, 90)) if errs.size else None,
            "mean": float(np.mean(errs)) if errs.size else None,
        },
        "opaque_fraction": float(np.mean(opaque)) if opaque else None,
        "opacity_on_surfaces": float(np.mean(np.concatenate(opac))) if opac else None,
        "unit_check": _unit_check(x, y),
        "render_seconds": float(np.median(secs)) if secs else None,
        "timing": None if timing is None else timing.to_dict(),
        "per_frame": per_frame,
    }


def _frame_at(frame, K, size: tuple[int, int] | None, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """One held-out frame at the render's size ``K`` (``size`` None: as it is): its colour
    (area-averaged) and its depth (nearest, missing as 0) times ``scale``."""
    rgb = frame.rgb if size is None else cv2.resize(frame.rgb, (K.width, K.height), interpolation=cv2.INTER_AREA)
    sensor = np.nan_to_num(frame.depth_m, nan=0.0) * scale
    if size is not None:
        sensor = cv2.resize(sensor, (K.width, K.height), interpolation=cv2.INTER_NEAREST)
    return rgb, sensor


def _unit_check(x: np.ndarray, y: np.ndarray) -> dict:
    """Least-squares ``y = a x + b`` and its R^2 (the paper's check that field depth is metric)."""
    if len(x) < 10 or np.ptp(x) <= 0:
        return {"a": None, "b": None, "r2": None, "pixels": int(len(x))}
    a, b = np.polyfit(x, y, 1)
    residual = y - (a * x + b)
    total = np.sum((y - y.mean()) ** 2)
    r2 = 1.0 - np.sum(residual**2) / total if total > 0 else None
    return {"a": float(a), "b": float(b), "r2": None if r2 is None else float(r2), "pixels": int(len(x))}
