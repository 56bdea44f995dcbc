"""One keyframe's NAP3D measurement, apart from any graph: the render, the alignment and the
correction a run (or a field's own error check) computes for one frame.

:func:`measure_keyframe` reads nothing a run changes while it works (its inputs are copied
in), so a run can hand it to a worker thread and go on with the odometry; what it reads of the
run's settings is :class:`MeasureSettings` (a run's ``PipelineConfig`` has the same fields and
adds the field's own error to the covariance). Below both the run and the fields: building a
field measures its error the way a run measures a keyframe.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from concurrent.futures import Future
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from ..camera import Intrinsics, RGBDFrame
from ..conventions import pose_error
from ..results import Correction
from .config import AlignConfig
from .correct import PreparedView, correct_pose, prepare_view_beside
from .rolling_shutter import at_one_instant

if TYPE_CHECKING:
    from ..datasets.depth_timing import CaptureTiming

log = logging.getLogger(__name__)

__all__ = ["MeasureSettings", "KeyframeJob", "measure_keyframe", "readout_of", "usable_prepared_view"]


@dataclass(frozen=True)
class MeasureSettings:
    """What one keyframe's measurement reads of a run's settings; the run's
    :class:`~nap3d_graph.run.config.PipelineConfig` takes its defaults from here. ``align``:
    NAP3D's settings; ``correction_iterations``: render-align rounds; ``depth_scale_check``:
    measure the frame's depth scale in the same pass; ``rolling_shutter_s``: the colour camera's
    readout (None: the capture timing's); ``render_ahead_m`` / ``render_ahead_deg``: how near
    a render made ahead must be to be used."""

    align: AlignConfig = dataclasses.field(default_factory=AlignConfig)
    correction_iterations: int = 1
    depth_scale_check: bool = True
    rolling_shutter_s: float | None = None
    render_ahead_m: float = 0.05
    render_ahead_deg: float = 3.0

    def field_covariance(self, field=None, T_field_cam: np.ndarray | None = None) -> np.ndarray | None:
        """No field error added: the field is taken as exact (what a field's own error check
        needs: the error is what it measures)."""
        return None


@dataclass(frozen=True)
class KeyframeJob:
    """Everything one measurement needs. frame: the keyframe as read; T_field_cam_render: (4, 4) the
    pose to render at (the field's frame); twist: (6,) body twist per second (GTSAM order)
    of the camera at the frame, or None; timing: the :class:`~nap3d_graph.datasets.depth_timing.CaptureTiming` (``depth_offset_s``,
    ``colour_offset_s``) or None; depth_scale: the run's current factor on the sensor's
    depth; render_intrinsics: the virtual camera of the render; prepared: a render made ahead
    at the keyframe's predicted pose (a :class:`~nap3d_graph.nap3d.correct.PreparedView`, or
    the worker's future of one), used when it is near ``T_field_cam_render``; feats_real: the
    frame's features at the render size, detected as soon as it arrived (the worker's future
    of ``(features, seconds)``), or as the feature odometry detected them (``(features, 0.0)``),
    or None; fit_intrinsics: whether the alignment also fits the self-calibrated camera model
    where ``AlignConfig.estimate_intrinsics`` is "auto" (False once the run has settled on the
    given intrinsics, :class:`~nap3d_graph.run.intrinsics_model.IntrinsicsModelTracker`)."""

    frame_index: int
    frame: RGBDFrame
    T_field_cam_render: np.ndarray
    twist: np.ndarray | None
    timing: CaptureTiming | None
    depth_scale: float
    render_intrinsics: Intrinsics
    prepared: Any = None
    feats_real: Any = None
    fit_intrinsics: bool = True


def measure_keyframe(job: KeyframeJob, field, config) -> Correction:
    """The correction of one keyframe (``config``: the run's :class:`PipelineConfig`): depth to
    the colour instant, ``correct_pose``, the result moved back to the frame's stamp and the
    field's own error (``config.field_covariance()``) added to its covariance.

    With ``config.depth_scale_check`` the alignment measures the frame's depth scale against
    the field's and, when it is off by more than ``AlignConfig.scale_tolerance``, fits the pose
    to the rescaled real points in the same pass (``AlignConfig.rescale_depth``): the render,
    the features and the matches do not depend on the depth's metre, so aligning again from
    scratch (as earlier versions did, for 21 of 28 keyframes on fr1/desk, +165 ms each) only
    repeated them.

    With a rolling-shutter readout (:func:`readout_of`) the real points are aligned as of the
    frame's middle row, moved there along ``job.twist`` (:mod:`nap3d_graph.nap3d.rolling_shutter`).
    """
    t0 = time.perf_counter()
    align = config.align
    if config.depth_scale_check and not align.rescale_depth:
        align = dataclasses.replace(align, rescale_depth=True)
    if not job.fit_intrinsics and align.estimate_intrinsics == "auto":
        align = dataclasses.replace(align, estimate_intrinsics=False)
    prepared = usable_prepared_view(job, config)
    feats_real, detect_s = _resolved(job.feats_real, (None, 0.0), "the frame's features detected ahead")
    rendering = None
    if prepared is None and feats_real is not None:
        # The real frame's features are known: its render (and the render's features) need not
        # wait for the depth to be moved to the colour instant; the side thread makes it now.
        rendering = prepare_view_beside(field, job.T_field_cam_render, job.render_intrinsics, align)
    frame, motion, shift = at_one_instant(job.frame, job.timing, job.twist, readout_of(config, job.timing),
                                          job.depth_scale)
    beside = _resolved(rendering, None, "the render") if rendering is not None else None
    correction = correct_pose(frame, field, job.T_field_cam_render, iterations=config.correction_iterations,
                              config=align, render_intrinsics=job.render_intrinsics, prepared=prepared or beside,
                              feats_real=feats_real, motion=motion)
    correction.timings_s["prepared"] = float(prepared is not None)
    if beside is not None:  # rendered at the keyframe's own prediction (and its features), beside the depth warp
        correction.timings_s["render_beside"] = correction.timings_s.pop("render_ahead", 0.0)
    if feats_real is not None:
        correction.timings_s["detect_ahead"] = detect_s
    if correction.success:  # measured at the colour's instant: moved to the frame's stamp
        correction = dataclasses.replace(correction, T_world_cam_corrected=correction.T_world_cam_corrected @ shift)
    field_cov = config.field_covariance(field, job.T_field_cam_render)
    if correction.success and field_cov is not None:
        correction = dataclasses.replace(correction, covariance=correction.covariance + field_cov)
    correction.timings_s["measure"] = time.perf_counter() - t0
    return correction


def readout_of(config, timing: CaptureTiming | None) -> float:
    """The colour camera's rolling-shutter readout (s) a run compensates: the config's, else the
    capture timing's (0: a global shutter)."""
    if config.rolling_shutter_s is not None:
        return float(config.rolling_shutter_s)
    return float(timing.readout_s) if timing is not None else 0.0


def usable_prepared_view(job: KeyframeJob, config) -> PreparedView | None:
    """The job's render made ahead, when there is one and it was made within
    ``config.render_ahead_m`` / ``render_ahead_deg`` of the pose the keyframe is to be rendered at
    (farther, the alignment would compare more distant viewpoints than a fresh render gives)."""
    prepared = _resolved(job.prepared, None, "the render made ahead")
    if prepared is None:
        return None
    moved_m, turned_deg = pose_error(prepared.T_world_cam, job.T_field_cam_render)
    return prepared if moved_m <= config.render_ahead_m and turned_deg <= config.render_ahead_deg else None


def _resolved(value, fallback, what: str):
    """``value``, or its result when it is the worker's future (done: it ran before the job
    that asks); ``fallback`` when there is none or it failed (the job then does the work)."""
    if value is None:
        return fallback
    if not isinstance(value, Future):
        return value
    try:
        return value.result()
    except Exception as exc:  # a field is user code: do the work in the measurement instead
        log.warning("%s failed (%s); the keyframe's measurement does it", what, exc)
        return fallback
