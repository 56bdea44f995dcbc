"""One entry point for making a field from a posed RGB-D sequence, whatever its type.

``build_field(sequence, model=...)`` estimates the recording's depth / colour capture
timing (when it has the stamps and ground truth to do so; the depth scale stays 1, see
:mod:`nap3d_graph.datasets.depth_timing`), builds or trains
the field on the training frames with them, evaluates it on held-out frames at the size the
pipeline renders at, and records in the field what it was made from (the timestamps it saw,
the timing) so runs can warn about reuse and compensate real frames the same way.

Models (``train-field --model``):

* ``splat``: surface splats fused from the frames, no gradient training
  (:mod:`nap3d_graph.fields.splat`);
* ``grid``: the dense voxel-grid radiance field trained with torch
  (:mod:`nap3d_graph.fields.training`);
* ``views``: the survey's sharpest frames re-projected into the asked view, no training
  (:mod:`nap3d_graph.fields.views`).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace

from nap3d_graph.arguments import RUN_MATCHER, matcher_option, non_negative_int, positive_float, positive_int, setting
from nap3d_graph.camera import colour_coverage
from nap3d_graph.datasets.depth_timing import CaptureTiming, estimate_timing, multiview_agreement_mm
from nap3d_graph.datasets.depth_unit import check_depth_unit
from nap3d_graph.nap3d.config import AlignConfig

from .base import FieldError
from .depth_refinement import DepthRefinementConfig, refine_poses_by_depth
from .error_growth import measure_error_growth
from .evaluation import evaluate_field, oracle_for
from .field_error import measure_error_by_view, measure_field_error
from .pose_refinement import PoseCorrectedSequence, PoseRefinementConfig, refine_training_poses
from .train_config import TrainConfig

__all__ = ["MODELS", "DEFAULT_MODEL", "REFINE_METHODS", "FieldSettings", "build_field", "error_growth_for"]

log = logging.getLogger(__name__)

MODELS = ("splat", "grid", "views")
DEFAULT_MODEL = "grid"


def error_growth_for(value: bool | str, sequence) -> tuple[bool, str]:
    """``(on, why)``: whether a grid or splat field measures its error's growth away from its
    frames. ``"auto"``: on for a camera's recording, off for a simulated one. Why: on real
    recordings the error a field leaves grows with the distance from the frames it was built
    from (their poses and capture timing are not the scene's), and without the growth the
    corrections' NEES sat far above the chi-square band (fr1/desk grid 9.0 and 17.3 in two
    trainings, redkitchen 37.5; with it 5.4, 6.8 and 7.8, the ATE the same or better); the
    simulator's poses are exact, its grid renders true geometry at any distance, and there
    the growth the view field measures is its own warp's (ATE +4% on the hold-out rooms)."""
    if value in (True, False):
        return bool(value), "as given"
    if value != "auto":
        raise FieldError(f"error_growth must be True, False or 'auto', got {value!r}")
    if getattr(sequence, "simulated", False):
        return False, "auto: a simulated recording (exact poses)"
    return True, "auto: a camera's recording"


@dataclass(frozen=True)
class FieldSettings:
    """How a field is made (:func:`build_field`; ``train-field``'s flags are its fields').

    ``model``: one of :data:`MODELS`. ``steps`` / ``minutes``: the grid's training budget
    (ignored by ``splat``). ``every``, ``eval_frames``: training frames and held-out frames
    (:func:`~nap3d_graph.fields.training_data.split_posed_frames`). ``voxel_size_m``: the model's
    voxel (default: the model's own). ``timing``: ``"auto"`` (estimate it), ``None`` (use the
    stamps as they are) or a dict. ``render_size``: the held-out evaluation renders at this size
    (the pipeline's; the frames' own when they are smaller, or with ``None``).
    ``measure_error``: measure the field's own error on the held-out frames with ``matcher``
    (:mod:`~nap3d_graph.fields.field_error`), recorded in ``field.meta["field_error"]`` and used
    by every run of the field to widen its corrections. ``refine_poses``: rounds of
    training-pose refinement (0: the poses as given), by ``refine_method``: ``"depth"``
    (neighbouring frames' depths aligned with ICP, a pose graph holding them to their input
    poses: :mod:`~nap3d_graph.fields.depth_refinement`) or ``"map"`` (each frame aligned with
    NAP3D to a splat map of the others: :mod:`~nap3d_graph.fields.pose_refinement`); the field
    is built with the refined poses, which it records (``meta["pose_corrections"]``), and the
    report holds each round and the frames' multi-view depth agreement before and after.
    ``error_growth``: a grid or splat field also measures how its error grows away from its
    training frames, with a view field of them (:mod:`~nap3d_graph.fields.error_growth`; a
    view field always measures its own); ``"auto"`` (default): on for a camera's recording,
    off for a simulated one (:func:`error_growth_for`). ``depth_unit``: ``"check"`` (default)
    looks, before any work, whether the depth agrees across the posed frames only at another
    unit's scale (:mod:`~nap3d_graph.datasets.depth_unit`) and raises :class:`DepthUnitError`
    if so; ``"trust"`` builds with the depth as read. ``slab_m``: a grid trains only on the
    depth points within this slab of the sequence's frame
    (:class:`~nap3d_graph.fields.train_config.TrainConfig`; a submap's part of a floor); the
    other models ignore it. ``device``: torch's (None: cuda if available, else cpu).
    """

    model: str = setting(DEFAULT_MODEL, "--model", choices=("grid", "splat", "views"),
        help="grid (default, chosen by measurement: see the README): a voxel-grid radiance field trained with "
             "torch; splat: surface splats fused from the frames, no training (seconds, not minutes); views: "
             "the survey's sharpest frames re-projected into the asked view, no training")
    timing: str | dict | None = setting("auto", "--timing", choices=("auto", "none"),
        help="auto: estimate when depth and colour were captured relative to the poses, and the colour camera's "
             "rolling-shutter readout, from the data (for recordings with depth stamps and ground truth; the "
             "depth scale is left to the run's calibration); none: use the stamps")
    minutes: float | None = setting(None, "--minutes", command_default=5.0, type=positive_float,
        help="grid: optimisation budget in minutes (default 5)")
    steps: int | None = setting(None, "--steps", type=positive_int,
        help="optimisation budget in steps instead of minutes: the same field on any machine (--minutes is "
             "ignored when given)")
    every: int = setting(1, "--every", type=positive_int,
        help="train on every K-th frame, hold out the rest for evaluation (default 1: every tenth frame is held "
             "out)")
    seed: int = setting(0, "--seed", type=int, help="random seed (default 0)")
    voxel_size_m: float | None = setting(None, "--voxel-size", type=positive_float,
        help="voxel in metres (default: 0.006 for splat, 0.03 for grid)")
    eval_frames: int = setting(8, "--eval-frames", type=non_negative_int,
        help="held-out frames to evaluate (default 8)")
    device: str | None = setting(None, "--device", help="torch device (default: cuda if available, else cpu)")
    matcher: str = setting("sift", "--matcher", command_default=RUN_MATCHER, **matcher_option(RUN_MATCHER))
    refine_poses: int = setting(0, "--refine-poses", type=non_negative_int, metavar="ROUNDS",
        help="refine the training frames' poses first, for ROUNDS rounds (default 0: the poses as given; see "
             "--refine-method). The report gives each round and the multi-view depth agreement before and after")
    refine_method: str = setting("depth", "--refine-method", choices=("depth", "map"),
        help="depth (default): each frame's depth aligned with its neighbours' (ICP), the poses solved in a "
             "graph that holds each to its input pose; map: each frame aligned (as a run would) with a splat "
             "map of the other half of the frames, fused with its input pose, the maps rebuilt")
    error_growth: bool | str = setting("auto", "--error-growth", nargs="?", const="on", choices=("auto", "on", "off"),
        help="grid / splat: also measure how the field's error grows away from its training frames, with a view "
             "field of the same frames (seconds), and record it: runs then add to each correction the error at "
             "its own distance from the frames, not the error near them everywhere (a view field always "
             "measures its own). auto (default): on for a camera's recording, off for a simulated one. On "
             "fr1/desk and redkitchen it took the grid's corrections' NEES from 9-37 to 5.4-7.8, at the "
             "chi-square band, the ATE the same or better; on the simulator's rooms, whose poses are exact, it "
             "did not help (README)")
    measure_error: bool = setting(True, "--no-field-error", action="store_false",
        help="do not measure the field's own error (by default each held-out frame is aligned with the render "
             "at its true pose, as a run would, and what the corrections miss beyond their covariance is "
             "recorded: runs of this field add it to every correction; --matcher picks the matcher of those "
             "alignments, use the runs' own)")
    depth_unit: str = setting("check", "--depth-unit", choices=("check", "trust"),
        help="check (default): before any work, stop when the depth agrees across the posed frames only at "
             "another unit's scale (e.g. millimetre PNGs read at TUM's 5000 per metre, 5x short); trust: build "
             "with the depth as read")
    render_size: tuple[int, int] | None = (320, 240)
    progress: bool = True
    slab_m: tuple | None = None


def build_field(sequence, model: str | None = None, settings: FieldSettings | None = None, **changes):
    """Make a field from ``sequence`` as ``settings`` say (:class:`FieldSettings`; its defaults
    when None), with ``model`` and ``changes`` (its fields by name) in their place; returns
    ``(field, report)``."""
    settings = replace(settings or FieldSettings(), **({"model": model} if model is not None else {}), **changes)
    return _build(sequence, settings)


def _build(sequence, s: FieldSettings):
    """:func:`build_field` with its settings resolved."""
    model, steps, minutes, every, eval_frames, seed = s.model, s.steps, s.minutes, s.every, s.eval_frames, s.seed
    voxel_size_m, timing, render_size, device, progress = s.voxel_size_m, s.timing, s.render_size, s.device, s.progress
    matcher, refine_poses, refine_method, slab_m = s.matcher, s.refine_poses, s.refine_method, s.slab_m
    error_growth, depth_unit, measure_error = s.error_growth, s.depth_unit, s.measure_error
    from .training_data import split_posed_frames

    error_growth, growth_why = error_growth_for(error_growth, sequence)
    if model not in MODELS:
        raise FieldError(f"unknown field model {model!r}; choose from {', '.join(MODELS)}")
    started = time.perf_counter()
    unit_check = _check_depth_unit(sequence, depth_unit)
    train_idx, held_idx = split_posed_frames(sequence, every, eval_frames)
    timing = estimate_timing(sequence) if timing == "auto" else CaptureTiming.of(timing)
    timing_seconds = time.perf_counter() - started
    refinement = None
    if refine_poses > 0:
        sequence, refinement = _refined(sequence, train_idx, timing, refine_poses, refine_method, matcher, render_size,
                                        progress)
    oracle = oracle_for(sequence)
    if model == "splat":
        field, report = _build_splat(sequence, train_idx, voxel_size_m, timing, progress)
    elif model == "views":
        field, report = _build_views(sequence, train_idx, timing, render_size, progress)
    else:
        field, report = _train_grid(sequence, steps, minutes, every, eval_frames, seed, voxel_size_m, timing, device,
                                    progress, slab_m)
    stored_timing = None if timing is None else timing.to_dict()
    field.meta.update(_provenance_meta(sequence, model, stored_timing, train_idx))
    K = sequence.intrinsics
    if render_size is not None and (render_size[0] > K.width or render_size[1] > K.height):
        render_size = None  # never evaluate above the frames' own resolution
    held = evaluate_field(field, sequence, held_idx, oracle, size=render_size, timing=timing) if len(held_idx) else None
    report.update({"model": model, "timing": stored_timing, "timing_seconds": round(timing_seconds, 2),
                   "train_frames": int(len(train_idx)), "held_out": held, "depth_unit": unit_check})
    _add_colour_coverage(report, sequence)
    if refinement is not None:
        report["pose_refinement"] = refinement
        field.meta["pose_corrections"] = {int(i): D.tolist() for i, D in sequence.corrections.items()}
    if measure_error and model != "views":
        report["error_growth"] = {"measured": error_growth, "why": growth_why}
    if measure_error:
        report["field_error"] = field.meta["field_error"] = _field_error(field, sequence, every, timing, render_size,
                                                                         matcher, train_idx if error_growth else None)
    report["total_seconds"] = round(time.perf_counter() - started, 2)
    return field, report


def _provenance_meta(sequence, model: str, stored_timing: dict | None, train_idx) -> dict:
    """What a field records of where it came from: its model, capture timing, recording, frame
    range and training frames (indices and stamps)."""
    return {"model": model, "timing": stored_timing, "source": str(getattr(sequence, "path", "")),
            "frame_range": list(getattr(sequence, "frame_range", (0, len(sequence)))),
            "train_frames": [int(i) for i in train_idx],
            "train_timestamps": [float(sequence.timestamps[int(i)]) for i in train_idx],
            "train_recording": getattr(sequence, "recording_id", None)}


def _add_colour_coverage(report: dict, sequence) -> None:
    """The share of the frame without colour (an undistortion's black corners: no colour target,
    not scored), where the sequence has such corners."""
    coverage = colour_coverage(sequence)
    if coverage is not None:
        report["colour_without_data"] = round(float(1.0 - coverage.mean()), 4)


class DepthUnitError(FieldError):
    """The depth is not in metres (see :mod:`~nap3d_graph.datasets.depth_unit`); ``check``
    holds the evidence."""

    def __init__(self, check):
        super().__init__(f"{check.message()}; fix the depth files, or build with `depth_unit='trust'` to use them as read")
        self.check = check


def _check_depth_unit(sequence, depth_unit: str) -> dict | None:
    """The unit check's figures for the report (None when trusted or not checkable); raises
    :class:`DepthUnitError` when the depth agrees across views only at another unit's scale."""
    if depth_unit not in ("check", "trust"):
        raise FieldError(f"depth_unit must be 'check' or 'trust', got {depth_unit!r}")
    if depth_unit == "trust":
        return None
    check = check_depth_unit(sequence)
    if check is None:
        return None
    if check.mistake is not None:
        raise DepthUnitError(check)
    return {"scale": check.scale, "pairs": check.pairs,
            "disagreement": {f"x{s:g}": round(v, 5) for s, v in check.disagreement.items()}}


REFINE_METHODS = ("depth", "map")


def _refined(sequence, train_idx, timing, rounds, method, matcher, render_size, progress):
    """The sequence with its training frames' poses refined (a PoseCorrectedSequence) and the
    refinement's report, with the multi-view depth agreement before and after."""
    if method not in REFINE_METHODS:
        raise FieldError(f"unknown pose refinement {method!r}; choose from {', '.join(REFINE_METHODS)}")
    started = time.perf_counter()
    if method == "depth":
        corrections, report = refine_poses_by_depth(sequence, train_idx, timing, DepthRefinementConfig(rounds=rounds),
                                                    progress)
    else:
        config = PoseRefinementConfig(rounds=rounds, matcher=matcher, render_size=render_size)
        corrections, report = refine_training_poses(sequence, train_idx, timing, config, progress)
        report["method"] = "map"
    refined = PoseCorrectedSequence(sequence, corrections)
    offset = timing.depth_offset_s if timing is not None else 0.0
    if getattr(sequence, "ground_truth_at", None) is not None and getattr(sequence, "depth_timestamps", None) is not None:
        report["agreement_before_mm"] = round(multiview_agreement_mm(sequence, offset), 3)
        report["agreement_after_mm"] = round(multiview_agreement_mm(refined, offset), 3)
    report["seconds"] = round(time.perf_counter() - started, 2)
    return refined, report


#: Held-out frames the field's error is measured on, at most (spread over all held-out ones).
ERROR_FRAMES = 40


def _field_error(field, sequence, every, timing, render_size, matcher, growth_train_idx=None) -> dict:
    from .training_data import split_posed_frames

    _, error_idx = split_posed_frames(sequence, every, ERROR_FRAMES)
    started = time.perf_counter()
    error = measure_field_error(field, sequence, error_idx, timing, AlignConfig(matcher=matcher), render_size)
    if hasattr(field, "hiding_near"):  # a view field: also how its error grows away from its views

        by_view = measure_error_by_view(field, sequence, error_idx, timing, AlignConfig(matcher=matcher), render_size)
        if by_view is not None:
            error["by_view"] = by_view
    elif growth_train_idx is not None and error.get("sigma_m"):  # a grid or splat: its growth, from its frames' views

        grown = measure_error_growth(error, sequence, growth_train_idx, error_idx, timing, AlignConfig(matcher=matcher),
                                     render_size)
        if grown is not None:
            error["by_view"] = grown
    error.update({"matcher": matcher, "seconds": round(time.perf_counter() - started, 2)})
    return error


def _build_splat(sequence, train_idx, voxel_size_m, timing, progress):
    from .splat import SplatConfig, build_splat_field

    config = SplatConfig() if voxel_size_m is None else SplatConfig(voxel_size_m=voxel_size_m)
    timing = timing or CaptureTiming()
    field, report = build_splat_field(sequence, train_idx, config, timing.depth_offset_s, timing.colour_offset_s,
                                      timing.depth_scale,
                                      progress=progress)
    report["config"] = config.to_dict()
    report["train_seconds"] = report["build_seconds"]
    return field, report


def _build_views(sequence, train_idx, timing, render_size, progress):
    from .views import ViewFieldConfig, build_view_field

    config = ViewFieldConfig() if render_size is None else ViewFieldConfig(width=render_size[0], height=render_size[1])
    timing = timing or CaptureTiming()
    field, report = build_view_field(sequence, train_idx, config, timing.depth_offset_s, timing.colour_offset_s,
                                     timing.depth_scale, progress=progress)
    report["config"] = config.to_dict()
    report["train_seconds"] = report["build_seconds"]
    return field, report


def _train_grid(sequence, steps, minutes, every, eval_frames, seed, voxel_size_m, timing, device, progress, slab_m):
    from .training import train_field

    config = TrainConfig(every=every, eval_frames=0, seed=seed, device=device, slab_m=slab_m)
    if steps is not None:
        config.max_steps = int(steps)
    if minutes is not None:
        config.minutes = float(minutes)
    if voxel_size_m is not None:
        config.voxel_size_m = float(voxel_size_m)
    field, report = train_field(sequence, config, progress=progress, timing=timing)
    report.pop("held_out", None)  # evaluated by build_field at the pipeline's render size
    return field, report
