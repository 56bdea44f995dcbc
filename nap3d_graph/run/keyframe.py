"""One keyframe's NAP3D measurement, apart from the graph: what a run computes for a keyframe
before its correction meets iSAM2.

:func:`measure_keyframe` reads nothing a run changes while it works (its inputs are copied
in), so a run can hand it to a worker thread and go on with the odometry
(``PipelineConfig.overlap``); :class:`CorrectionWorker` is that thread. The graph half (the
depth-scale check, the gate, the factor) stays with the run, on its own thread.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import wait as futures_wait
from dataclasses import dataclass
from typing import Any

import numpy as np

from nap3d_graph.camera import Intrinsics, RGBDFrame
from nap3d_graph.conventions import pose_error
from nap3d_graph.datasets.depth_timing import CaptureTiming
from nap3d_graph.nap3d.correct import PreparedView, correct_pose, prepare_view, prepare_view_beside, real_features
from nap3d_graph.nap3d.rolling_shutter import at_one_instant
from nap3d_graph.results import Correction

log = logging.getLogger(__name__)

__all__ = ["KeyframeJob", "measure_keyframe", "CorrectionWorker",
           "DepthScaleTracker"]


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


class DepthScaleTracker:
    """The run's factor on the sensor's depth (``scale``), learnt from the corrections: each
    one measures its frame's depth against the field's metre (``PipelineConfig.depth_scale_*``).
    """

    def __init__(self, scale: float, config):
        self.scale = float(scale)
        self.config = config
        self.observations: list[float] = []

    def check(self, correction: Correction, record) -> Correction:
        """Update the running estimate with this frame's scale (kept on ``record``); the
        correction failed when its scale disagrees with the estimate."""
        diagnostics = correction.alignment.diagnostics
        scale, sigma = diagnostics.get("depth_scale"), diagnostics.get("depth_scale_sigma")
        if scale is None or not np.isfinite(scale):
            return correction
        # ``self.scale`` is the factor the sensor's depth was multiplied by; this frame's depth
        # measured ``scale`` times the field's metre, so it asks for self.scale / scale.
        wanted = float(self.scale / scale)
        self.observations.append(wanted)
        record.depth_scale = wanted
        recent = self.observations[-self.config.depth_scale_window:]
        self.scale = float(np.exp(np.median(np.log(recent))))
        allowed = max(self.config.depth_scale_tolerance, self.config.depth_scale_sigmas * (sigma or 0.0))
        off = wanted / self.scale - 1.0
        if abs(off) > allowed:
            reason = (f"depth scale: this frame's depth needs x{wanted:.4f}, the run's x{self.scale:.4f} "
                      f"({off * 100:+.1f}%): its depth or its matches disagree with the field")
            return dataclasses.replace(correction, success=False, reason=reason)
        return correction


class CorrectionWorker:
    """Runs :func:`measure_keyframe` on one worker thread; at most one measurement is in flight.

    Why a thread and not a process: the measurement spends its time in torch, OpenCV and numpy,
    which release the GIL, and it needs the field, which a process would have to copy.
    """

    def __init__(self, field, config):
        self.field, self.config = field, config
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="nap3d-correction")
        self._flight: tuple[Any, Future] | None = None
        self._prepared: Future | None = None
        self._detected: tuple[int, Future] | None = None

    def prepare(self, T_field_cam: np.ndarray, intrinsics: Intrinsics) -> None:
        """Render at the next keyframe's predicted pose and detect its features while the worker
        is idle (:func:`~nap3d_graph.nap3d.correct.prepare_view`); the next :meth:`take_prepared`
        hands it to that keyframe's job. The worker runs its tasks in order, so the measurement
        never waits on a render in progress for longer than it would have rendered itself."""
        self._prepared = self._pool.submit(prepare_view, self.field, T_field_cam, intrinsics, self.config.align)

    def detect_ahead(self, frame_index: int, frame: RGBDFrame, intrinsics: Intrinsics) -> None:
        """Detect the features of a frame due to be a keyframe as soon as it arrives (at the
        render size ``intrinsics``), while the run computes its odometry;
        :meth:`take_detected` hands them to its job."""
        self._detected = (frame_index, self._pool.submit(real_features, frame, intrinsics, self.config.align))

    def take_detected(self, frame_index: int) -> Future | None:
        """The features detected ahead for ``frame_index`` (None when there are none; those of
        another frame are dropped)."""
        detected, self._detected = self._detected, None
        return detected[1] if detected is not None and detected[0] == frame_index else None

    @property
    def preparing(self) -> bool:
        """A render made ahead waits for its keyframe (done or not)."""
        return self._prepared is not None

    def idle(self) -> bool:
        """Nothing submitted is still running."""
        running = (self._prepared, self._flight[1] if self._flight else None,
                   self._detected[1] if self._detected else None)
        return all(f is None or f.done() for f in running)

    def take_prepared(self) -> Future | None:
        prepared, self._prepared = self._prepared, None
        return prepared

    def submit(self, tag, job: KeyframeJob) -> None:
        """Start measuring ``job``; ``tag`` comes back with its result. One in flight only:
        :meth:`take` it first."""
        if self._flight is not None:
            raise RuntimeError("a correction is already in flight; take() it first")
        self._flight = (tag, self._pool.submit(measure_keyframe, job, self.field, self.config))

    @property
    def busy(self) -> bool:
        return self._flight is not None

    def ready(self) -> bool:
        """A measurement is in flight and done."""
        return self._flight is not None and self._flight[1].done()

    def free(self) -> bool:
        """No measurement in flight, or the one in flight is done (it lands next): a new
        keyframe would not wait."""
        return self._flight is None or self._flight[1].done()

    def wait(self, timeout_s: float) -> bool:
        """Wait at most ``timeout_s`` seconds for the measurement in flight; whether it is done."""
        if self._flight is None:
            return False
        done, _ = futures_wait([self._flight[1]], timeout=max(timeout_s, 0.0))
        return bool(done)

    def take(self) -> tuple[Any, Correction, float]:
        """``(tag, correction, seconds waited)`` of the measurement in flight, waiting for it
        if it is not done (an exception it raised is raised here)."""
        if self._flight is None:
            raise RuntimeError("no correction in flight; submit() one first")
        tag, future = self._flight
        self._flight = None
        t0 = time.perf_counter()
        result = future.result()
        return tag, result, time.perf_counter() - t0

    def close(self) -> None:
        self._pool.shutdown(wait=True)
