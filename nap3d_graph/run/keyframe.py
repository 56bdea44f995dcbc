"""A run's keyframe measurements beside its odometry: :class:`CorrectionWorker`, the thread
that runs :func:`~nap3d_graph.nap3d.keyframe.measure_keyframe` while the odometry goes on
(``PipelineConfig.overlap``), and :class:`DepthScaleTracker`, the run's factor on the sensor's
depth learnt from the corrections. The graph half (the depth-scale check, the gate, the factor)
stays with the run, on its own thread.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import wait as futures_wait
from typing import Any

import numpy as np

from nap3d_graph.camera import Intrinsics, RGBDFrame
from nap3d_graph.nap3d.correct import prepare_view, real_features
from nap3d_graph.nap3d.keyframe import KeyframeJob, measure_keyframe
from nap3d_graph.results import Correction

log = logging.getLogger(__name__)

__all__ = ["CorrectionWorker", "DepthScaleTracker"]


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
