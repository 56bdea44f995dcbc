"""How a grid's or splat field's own error grows away from the frames it was built from.

``train-field`` measures a field's error on held-out frames (:mod:`.field_error`), and those
sit between training frames: 0.08 m from the nearest (camera plus viewing centre,
:func:`~nap3d_graph.fields.gap_error.view_gap_m`) on fr1/desk, where a later traversal's keyframes
are 0.62 m away. A view field measures how its error grows by hiding its views near each
held-out frame; a trained grid cannot hide what it learned. What grows with the distance is
mostly the recording's own inconsistency (its poses, timing and depth registration seen from
further apart), which the survey's frames show whatever represents them. So the growth is
measured with a view field of the same training frames, and added to the field's own error
near its frames as an independent source:

    sigma(gap)^2 = sigma_field^2 + max(sigma_views(gap)^2 - sigma_views(near)^2, 0)

The model, with the views' geometry a run needs to find its gap, is stored as the field's
``meta["field_error"]["by_view"]``; :func:`~nap3d_graph.fields.gap_error.error_sigmas_at`
reads it for any field.
Measured on fr1/desk (`benchmarks/field_error_desk.py --error-growth`): the grid's
corrections' NEES went from 9.0 to inside the chi-square band (5.4). On simulated rooms, where a
grid renders true geometry at any distance and only the view field's warps degrade, it
lowered a NEES that was mostly in the band already and cost 4% of ATE
(`benchmarks/error_growth_rooms.py`). So ``train-field --error-growth auto`` (the default)
measures it on a camera's recording and not on a simulated one
(:func:`~nap3d_graph.fields.build.error_growth_for`).
"""

from __future__ import annotations

import logging

import numpy as np

from nap3d_graph.datasets.depth_timing import CaptureTiming

from .field_error import measure_error_by_view

__all__ = ["measure_error_growth", "combined_by_view", "views_geometry"]

log = logging.getLogger(__name__)


def views_geometry(view_field) -> dict:
    """What a run needs of a view field to find a pose's gap to its nearest view: each view's
    camera centre (V, 3), optical axis (V, 3) and look depth (V,), and the angle beyond which a
    view does not count."""
    T = np.asarray(view_field.T_world_cam)
    return {"centres": np.round(T[:, :3, 3], 5).tolist(), "axes": np.round(T[:, :3, 2], 6).tolist(),
            "look_depth_m": np.round(np.asarray(view_field._look_depth_m), 4).tolist(),
            "max_angle_deg": float(view_field.config.max_angle_deg)}


def combined_by_view(sigma_m: float, sigma_rad: float, views_by_view: dict, geometry: dict) -> dict:
    """The field's error model by gap: its own near-frame sigmas with the view field's growth
    (``views_by_view``, :func:`~nap3d_graph.fields.field_error.measure_error_by_view`) added in
    quadrature; ``geometry`` from :func:`views_geometry`."""
    vm, vr = np.asarray(views_by_view["sigma_m"], float), np.asarray(views_by_view["sigma_rad"], float)
    grown_m = np.sqrt(sigma_m**2 + np.maximum(vm**2 - vm[0] ** 2, 0.0))
    grown_rad = np.sqrt(sigma_rad**2 + np.maximum(vr**2 - vr[0] ** 2, 0.0))
    return {"gap_m": list(views_by_view["gap_m"]), "sigma_m": np.round(grown_m, 6).tolist(),
            "sigma_rad": np.round(grown_rad, 7).tolist(), "frames": list(views_by_view["frames"]),
            "radii_m": list(views_by_view["radii_m"]), "growth_from": "views",
            "views_sigma_m": list(views_by_view["sigma_m"]), "views_sigma_rad": list(views_by_view["sigma_rad"]),
            "views": geometry}


def measure_error_growth(error: dict, sequence, train_idx, error_idx, timing=None, align=None,
                         render_size=(320, 240)) -> dict | None:
    """How a field whose own error near its frames is ``error`` (its ``sigma_m`` /
    ``sigma_rad``, :func:`~nap3d_graph.fields.field_error.measure_field_error`) errs away from
    its training frames ``train_idx`` of ``sequence``: a view field of them, measured on the
    held-out frames ``error_idx`` with its views near each hidden. Returns the combined model
    (:func:`combined_by_view`, to store as ``meta["field_error"]["by_view"]``), or None when the
    growth could not be measured."""
    from .views import ViewFieldConfig, build_view_field

    if not error.get("sigma_m"):
        return None
    timing = CaptureTiming.of(timing) or CaptureTiming()
    config = ViewFieldConfig() if render_size is None else ViewFieldConfig(width=render_size[0], height=render_size[1])
    views, _ = build_view_field(sequence, train_idx, config, timing.depth_offset_s, timing.colour_offset_s,
                                timing.depth_scale, progress=False)
    grown = measure_error_by_view(views, sequence, error_idx, timing, align, render_size)
    if grown is None:
        return None
    model = combined_by_view(float(error["sigma_m"]), float(error.get("sigma_rad") or 0.0), grown,
                             views_geometry(views))
    log.info("field error by gap (its own near its frames, the view field's growth added): %s",
             ", ".join(f"{g:.2f} m -> {m * 1000:.1f} mm / {np.degrees(r):.2f} deg"
                       for g, m, r in zip(model["gap_m"], model["sigma_m"], model["sigma_rad"])))
    return model
