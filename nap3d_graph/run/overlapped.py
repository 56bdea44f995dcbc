"""The overlapped run's frame step: the keyframe's measurement goes to a worker thread
(:class:`~nap3d_graph.run.keyframe.CorrectionWorker`) and the odometry goes on; the correction
enters the graph when it lands, at a later frame or, with ``land_within_s``, at its own.

:class:`OverlappedSteps` drives a :class:`~nap3d_graph.run.pipeline.Pipeline` through its
public steps and parts (``predict``, ``is_keyframe``, ``add_keyframe``, ``frames``, ``jobs``,
``corrections``, ``recovery``), the same ones the inline path takes, plus what only the overlap
needs: detecting a due keyframe's features ahead, rendering ahead, launching and landing. The
pipeline makes one per worker (``Pipeline.step(i, worker)``).
"""

from __future__ import annotations

import dataclasses
import time

from gtsam.symbol_shorthand import X

from nap3d_graph.conventions import inv_T
from nap3d_graph.run.keyframe import CorrectionWorker
from nap3d_graph.run.records import tell

__all__ = ["OverlappedSteps"]


class OverlappedSteps:
    """Frame steps of ``pipeline`` with its keyframes measured on ``worker``."""

    def __init__(self, pipeline, worker: CorrectionWorker):
        self.pipeline = pipeline
        self.worker = worker

    def step(self, i: int, on_keyframe=None) -> None:
        """Frame i: features detected ahead when it is due, its odometry, a correction that is
        ready landed, and when it is a keyframe its node and its measurement handed over; then
        a correction landed within ``land_within_s``, the frame's causal pose, a render ahead."""
        p, worker = self.pipeline, self.worker
        t_arrived = time.perf_counter()
        frame = p.predict(i, self._detect_ahead(i, p.frames.for_odometry(i)))
        idle = worker.free()
        keyframe = p.is_keyframe(i, frame, idle)
        if keyframe:
            p.frames.hold_back = not idle  # the last correction is still being measured
        if worker.ready() or (worker.busy and keyframe):
            self._land(on_keyframe)  # a late correction enters the graph now
        if keyframe:
            p.add_keyframe(i)
            self._launch(i, p.frames.for_keyframe(i, frame, needed=p.field is not None), on_keyframe)
        self._land_within(t_arrived, on_keyframe)
        p.online.append(p.motion.causal_pose())
        self._render_ahead(i)

    def land_pending(self, on_keyframe=None) -> None:
        """The measurement still in flight, if any, waited for and put in the graph."""
        if self.worker.busy:
            self._land(on_keyframe)

    def _last_keyframe(self) -> int | None:
        """The last keyframe's frame (None before the first)."""
        indices = self.pipeline.keyframe_indices
        return indices[-1] if indices else None

    def _detect_ahead(self, i: int, frame):
        """Before frame i's odometry: when frame i is due to be a keyframe (by count, or by
        ``keyframe_when_idle`` with the worker idle now), the worker detects its features now,
        on the other core, while the odometry runs (``PipelineConfig.detect_ahead``). Returns
        the frame (read now if it was not yet)."""
        p, worker = self.pipeline, self.worker
        last = self._last_keyframe()
        idle_due = worker.free() and p.selector.idle_due(i, last)
        if not p.config.detect_ahead or p.field is None or not (p.selector.due_by_count(i, last) or idle_due):
            return frame
        frame = frame if frame is not None else p.frames.read(i)
        if frame is not None and not p.jobs.shares_features(frame.intrinsics):  # else its odometry detects them
            worker.detect_ahead(i, frame, p.jobs.render_intrinsics(frame.intrinsics))
        return frame

    def _launch(self, i: int, frame, on_keyframe) -> None:
        """Hand keyframe i's measurement to the worker and go on; until it lands, the keyframe
        is known by its prediction."""
        p, worker = self.pipeline, self.worker
        if p.recovery.placing():  # finding the run in the map: inline (nothing is in flight then)
            p.recovery.place_keyframe(p.pending(), i, frame)
            tell(on_keyframe, p.finish_keyframe())
            return
        record = p.pending()
        job = p.jobs.job(record, i, frame)
        prepared, detected = worker.take_prepared(), worker.take_detected(i)
        if job is not None:
            job = dataclasses.replace(job, prepared=prepared, feats_real=job.feats_real if detected is None else detected)
        p.pending_record = None  # in flight: _land keeps it
        p.motion.keyframe_estimated(p.graph, len(p.keyframe_indices) - 1, record.timestamp)
        if job is None:  # nothing to measure: the keyframe is done (its reason recorded)
            p.records.append(record)
            tell(on_keyframe, record)
            return
        worker.submit((record, job.T_field_cam_render, job.frame), job)

    def _land(self, on_keyframe, waited_s: float = 0.0) -> None:
        """The measurement in flight (waited for if need be) enters the graph at its keyframe,
        and the latest keyframe's estimate is refreshed. ``waited_s``: how long the run already
        waited for it."""
        p = self.pipeline
        (record, T_field_cam_render, frame), correction, took_s = self.worker.take()
        p.corrections.apply(record, record.frame_index, correction, T_field_cam_render)
        if record.key == X(len(p.keyframe_indices) - 1):  # a recovery places the latest keyframe (an older one has moved on)
            p.recovery.recover_if_lost(record, record.frame_index, frame)
        record.timings_s["wait"] = round(waited_s + took_s, 5)
        record.timings_s["landed_frame"] = len(p.motion.T_world_cam_odom) - 1
        j = len(p.keyframe_indices) - 1
        p.motion.keyframe_estimated(p.graph, j, float(p.sequence.timestamps[p.keyframe_indices[j]]))
        p.records.append(record)
        tell(on_keyframe, record)

    def _land_within(self, t_arrived: float, on_keyframe) -> None:
        """Before the frame's pose is given: a correction in flight that is done within
        ``land_within_s`` of the frame's arrival (``t_arrived``, perf_counter seconds) lands
        now, at this frame."""
        worker, within_s = self.worker, self.pipeline.config.land_within_s
        left_s = t_arrived + within_s - time.perf_counter()
        if worker.busy and within_s > 0 and left_s > 0:
            t0 = time.perf_counter()
            if worker.wait(left_s):
                self._land(on_keyframe, waited_s=time.perf_counter() - t0)

    def _render_ahead(self, i: int) -> None:
        """After frame i: when frame i + 1 is due to be a keyframe and the worker is idle, it
        renders at i + 1's predicted pose (frame i's, one more step of the same motion) so that
        keyframe's measurement finds its render made (``PipelineConfig.render_ahead``)."""
        p, worker = self.pipeline, self.worker
        intrinsics = p.frames.intrinsics
        if (not p.config.render_ahead or worker.busy or worker.preparing or intrinsics is None
                or not p.selector.due_by_count(i + 1, self._last_keyframe()) or i + 1 >= len(p.sequence)):
            return
        T_world_cam_next = p.motion.causal_pose() @ p.motion.increments[i]
        if p.anchored:
            T_world_cam_next = inv_T(p.graph.anchor()) @ T_world_cam_next  # the field's frame
        worker.prepare(T_world_cam_next, p.jobs.render_intrinsics(intrinsics))

