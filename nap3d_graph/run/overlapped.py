"""The overlapped run's frame step: the keyframe's measurement goes to a worker thread
(:class:`~nap3d_graph.run.keyframe.CorrectionWorker`) and the odometry goes on; the correction
enters the graph when it lands, at a later frame or, with ``land_within_s``, at its own.

:class:`OverlappedSteps` drives a :class:`~nap3d_graph.run.pipeline.Pipeline` through its
public steps (``predict``, ``is_keyframe``, ``add_keyframe``, ``place_keyframe``,
``apply_correction``, ``keyframe_estimated``) and parts (the frame reader, the keyframe
selector, the keyframe jobs), the same ones the inline path takes, plus what only the overlap
needs: detecting a due keyframe's features ahead, rendering ahead, launching and landing. The
pipeline makes one per worker and hands it the run's state at each frame
(``Pipeline.step(i, worker)``).
"""

from __future__ import annotations

import dataclasses
import time

from gtsam.symbol_shorthand import X

from nap3d_graph.run.frames import FrameReader
from nap3d_graph.run.jobs import KeyframeJobs
from nap3d_graph.run.keyframe import CorrectionWorker
from nap3d_graph.run.records import tell
from nap3d_graph.run.selection import KeyframeSelector
from nap3d_graph.run.state import RunState

__all__ = ["OverlappedSteps"]


class OverlappedSteps:
    """Frame steps of ``run`` (a :class:`~nap3d_graph.run.pipeline.Pipeline`, through its public
    steps) with its keyframes measured on ``worker``; ``frames``, ``selector`` and ``jobs`` are
    the run's parts, ``config`` its settings, ``sequence`` its frames (their count and stamps)."""

    def __init__(self, run, worker: CorrectionWorker, frames: FrameReader, selector: KeyframeSelector,
                 jobs: KeyframeJobs, config, sequence):
        self.run, self.worker = run, worker
        self.frames, self.selector, self.jobs, self.config, self.sequence = frames, selector, jobs, config, sequence

    def step(self, state: RunState, i: int, on_keyframe=None) -> None:
        """Frame i: features detected ahead when it is due, its odometry, a correction that is
        ready landed, and when it is a keyframe its node and its measurement handed over; then
        a correction landed within ``land_within_s``, the frame's causal pose, a render ahead."""
        run, worker = self.run, self.worker
        t_arrived = time.perf_counter()
        frame = run.predict(i, self._detect_ahead(state, i, self.frames.for_odometry(i)))
        idle = worker.free()
        keyframe = run.is_keyframe(i, frame, idle)
        if keyframe:
            self.frames.hold_back = not idle  # the last correction is still being measured
        if worker.ready() or (worker.busy and keyframe):
            self._land(state, on_keyframe)  # a late correction enters the graph now
        if keyframe:
            run.add_keyframe(i)
            self._launch(state, i, self.frames.for_keyframe(i, frame, needed=self.jobs.field is not None),
                         on_keyframe)
        self._land_within(state, t_arrived, on_keyframe)
        state.online.append(state.motion.causal_pose())
        self._render_ahead(state, i)

    def land_pending(self, state: RunState, on_keyframe=None) -> None:
        """The measurement still in flight, if any, waited for and put in the graph."""
        if self.worker.busy:
            self._land(state, on_keyframe)

    def _detect_ahead(self, state: RunState, i: int, frame):
        """Before frame i's odometry: when frame i is due to be a keyframe (by count, or by
        ``keyframe_when_idle`` with the worker idle now), the worker detects its features now,
        on the other core, while the odometry runs (``PipelineConfig.detect_ahead``). Returns
        the frame (read now if it was not yet)."""
        worker, jobs = self.worker, self.jobs
        last = state.last_keyframe
        idle_due = worker.free() and self.selector.idle_due(i, last)
        if not self.config.detect_ahead or jobs.field is None or not (self.selector.due_by_count(i, last)
                                                                       or idle_due):
            return frame
        frame = frame if frame is not None else self.frames.read(i)
        if frame is not None and not jobs.shares_features(frame.intrinsics):  # else its odometry detects them
            worker.detect_ahead(i, frame, jobs.render_intrinsics(frame.intrinsics))
        return frame

    def _launch(self, state: RunState, i: int, frame, on_keyframe) -> None:
        """Hand keyframe i's measurement to the worker and go on; until it lands, the keyframe
        is known by its prediction."""
        run, worker = self.run, self.worker
        if run.placing():  # finding the run in the map: inline (nothing is in flight then)
            run.place_keyframe(i, frame)
            tell(on_keyframe, run.finish_keyframe())
            return
        record = state.pending()
        job = self.jobs.job(state, record, i, frame)
        prepared, detected = worker.take_prepared(), worker.take_detected(i)
        if job is not None:
            job = dataclasses.replace(job, prepared=prepared, feats_real=job.feats_real if detected is None else detected)
        state.pending_record = None  # in flight: _land keeps it
        run.keyframe_estimated()
        if job is None:  # nothing to measure: the keyframe is done (its reason recorded)
            state.records.append(record)
            tell(on_keyframe, record)
            return
        worker.submit((record, job.T_field_cam_render, job.frame), job)

    def _land(self, state: RunState, on_keyframe, waited_s: float = 0.0) -> None:
        """The measurement in flight (waited for if need be) enters the graph at its keyframe,
        and the latest keyframe's estimate is refreshed. ``waited_s``: how long the run already
        waited for it."""
        (record, T_field_cam_render, frame), correction, took_s = self.worker.take()
        # A recovery places the latest keyframe (an older one has moved on).
        latest = record.key == X(len(state.keyframe_indices) - 1)
        self.run.apply_correction(record, record.frame_index, correction, T_field_cam_render, frame, latest)
        record.timings_s["wait"] = round(waited_s + took_s, 5)
        record.timings_s["landed_frame"] = len(state.motion.T_world_cam_odom) - 1
        self.run.keyframe_estimated()
        state.records.append(record)
        tell(on_keyframe, record)

    def _land_within(self, state: RunState, t_arrived: float, on_keyframe) -> None:
        """Before the frame's pose is given: a correction in flight that is done within
        ``land_within_s`` of the frame's arrival (``t_arrived``, perf_counter seconds) lands
        now, at this frame."""
        worker, within_s = self.worker, self.config.land_within_s
        left_s = t_arrived + within_s - time.perf_counter()
        if worker.busy and within_s > 0 and left_s > 0:
            t0 = time.perf_counter()
            if worker.wait(left_s):
                self._land(state, on_keyframe, waited_s=time.perf_counter() - t0)

    def _render_ahead(self, state: RunState, i: int) -> None:
        """After frame i: when frame i + 1 is due to be a keyframe and the worker is idle, it
        renders at i + 1's predicted pose (frame i's, one more step of the same motion) so that
        keyframe's measurement finds its render made (``PipelineConfig.render_ahead``)."""
        worker = self.worker
        intrinsics = self.frames.intrinsics
        if (not self.config.render_ahead or worker.busy or worker.preparing or intrinsics is None
                or not self.selector.due_by_count(i + 1, state.last_keyframe) or i + 1 >= len(self.sequence)):
            return
        T_world_cam_next = state.motion.causal_pose() @ state.motion.increments[i]
        worker.prepare(state.in_field_frame(T_world_cam_next), self.jobs.render_intrinsics(intrinsics))
