"""A field's error by how differently it saw a pose: the gap between a camera and the views a
field was built from (camera plus viewing centre), and the stored model of the error at each
gap that runs read (a view field's own, or a grid's or splat field's from
:mod:`~nap3d_graph.fields.error_growth`)."""

from __future__ import annotations

import numpy as np

__all__ = ["view_gap_m", "interp_extend", "sigmas_at_gap", "has_error_by_view", "error_sigmas_at"]


def view_gap_m(T_world_views: np.ndarray, look_depth_m: np.ndarray, T_world_cam: np.ndarray) -> np.ndarray:
    """(V,) how differently each view sees from a camera at ``T_world_cam``: the distance of
    the camera centres plus that of the viewing centres (the point ``look_depth_m`` ahead on
    each optical axis; the asked camera's at each view's depth), in metres."""
    T = np.asarray(T_world_cam)
    centres = T_world_views[:, :3, 3]
    looks = centres + T_world_views[:, :3, 2] * look_depth_m[:, None]
    asked_looks = T[:3, 3] + T[:3, 2][None, :] * look_depth_m[:, None]
    return np.linalg.norm(centres - T[:3, 3], axis=1) + np.linalg.norm(looks - asked_looks, axis=1)


def interp_extend(x: float, xs: np.ndarray, ys: np.ndarray) -> float:
    """``ys(x)`` interpolated on increasing ``xs``, extended with the last segment's slope
    (never below the last value) beyond ``xs[-1]``; ``ys[0]`` before ``xs[0]``."""
    if len(xs) > 1 and x > xs[-1]:
        slope = max((ys[-1] - ys[-2]) / max(xs[-1] - xs[-2], 1e-9), 0.0)
        return float(ys[-1] + slope * (x - xs[-1]))
    return float(np.interp(x, xs, ys))


def sigmas_at_gap(model: dict, gap_m: float) -> tuple[float, float]:
    """``(sigma_m, sigma_rad)`` of an error-by-gap ``model`` (``gap_m``, ``sigma_m``,
    ``sigma_rad`` at increasing gaps) at ``gap_m``, interpolated and extended linearly beyond
    the largest measured gap; an infinite gap (no view looks that way) counts as far."""
    gaps = np.asarray(model["gap_m"], dtype=float)
    gap_m = float(gaps[-1] * 4) if not np.isfinite(gap_m) else float(gap_m)
    return (interp_extend(gap_m, gaps, np.asarray(model["sigma_m"], dtype=float)),
            interp_extend(gap_m, gaps, np.asarray(model["sigma_rad"], dtype=float)))


def has_error_by_view(field) -> bool:
    """Whether ``field`` knows how its error grows with the distance from what it saw: a view
    field's own measurement, or a stored model with the views' geometry."""
    if hasattr(field, "has_error_by_view"):
        return bool(field.has_error_by_view)
    model = ((getattr(field, "meta", None) or {}).get("field_error") or {}).get("by_view") or {}
    return bool(model.get("gap_m")) and bool(model.get("views"))


def error_sigmas_at(field, T_world_cam: np.ndarray) -> tuple[float, float] | None:
    """``(sigma_m, sigma_rad)`` of ``field``'s error at ``T_world_cam`` (4x4, world <- camera)
    by its distance from the nearest view, or None when the field has no such model."""
    if hasattr(field, "error_sigmas_at"):
        return field.error_sigmas_at(T_world_cam)
    if not has_error_by_view(field):
        return None
    model = field.meta["field_error"]["by_view"]
    geometry = model["views"]
    axes = np.asarray(geometry["axes"], float)
    T_world_views = np.tile(np.eye(4), (len(axes), 1, 1))  # only the centres and axes count
    T_world_views[:, :3, 3], T_world_views[:, :3, 2] = np.asarray(geometry["centres"], float), axes
    T = np.asarray(T_world_cam, float)
    gap = view_gap_m(T_world_views, np.asarray(geometry["look_depth_m"], float), T)
    gap[axes @ T[:3, 2] < np.cos(np.radians(geometry["max_angle_deg"]))] = np.inf
    return sigmas_at_gap(model, float(gap.min()) if gap.size else np.inf)
