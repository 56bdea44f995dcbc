"""The drift-correction run: a motion model between keyframes in an iSAM2 graph, NAP3D
corrections as factors.

Graph (:class:`~nap3d_graph.run.graph.KeyframeGraph`): one ``Pose3`` node ``X(k)`` per keyframe
(``T_world_cam``, OpenCV camera), what the motion model puts between keyframes
(:class:`~nap3d_graph.run.motion.OdometryMotion`: the frame-to-frame increments composed into a
``BetweenFactorPose3``, covariance propagated; :class:`~nap3d_graph.run.imu.ImuMotion`: a
``CombinedImuFactor`` with velocities and biases), and at each keyframe the NAP3D correction as
a robust ``PriorFactorPose3`` (or, with an anchor, a between factor from ``M(0)``, the field's
frame in the world). Each keyframe first enters iSAM2 with its motion factor alone (the
prediction); a correction then enters only if it passes the chi-square gate against that
prediction. The motion model chains the frames between keyframes.

``Pipeline.run()`` reads as its steps; no failed correction stops a run or reaches the graph.
Its parts, each with a public interface the overlapped path (:mod:`nap3d_graph.run.overlapped`)
uses as the inline one does: :class:`~nap3d_graph.run.frames.FrameReader` (``frames``),
:class:`~nap3d_graph.run.jobs.KeyframeJobs` (``jobs``: what measuring a keyframe needs),
:class:`~nap3d_graph.run.corrections.CorrectionGate` (``corrections``: the gate, with the
refusal watch; it returns the factor it added, and the run solves),
:class:`~nap3d_graph.run.recovery.MapRecovery` (``recovery``: placement in a map and recovery)
and :func:`~nap3d_graph.run.retire.retired_segment` (a bounded graph's retirement). None of
them holds the run: what the run holds between frames is one
:class:`~nap3d_graph.run.state.RunState` (``state``), handed to a part for the length of its call.
"""

from __future__ import annotations

import logging
import time

import gtsam
import numpy as np
from gtsam.symbol_shorthand import M, X

from nap3d_graph.conventions import pose3_to_T
from nap3d_graph.datasets.protocol import FrameSource
from nap3d_graph.factors import anchor_prior_factor
from nap3d_graph.fields import frames_seen_in_training
from nap3d_graph.mapping.start import MapPlacement, PlacementSettings
from nap3d_graph.nap3d.keyframe import measure_keyframe
from nap3d_graph.progress import progress_bar
from nap3d_graph.results import Correction
from nap3d_graph.run.config import PipelineConfig, with_field_error
from nap3d_graph.run.corrections import CorrectionGate
from nap3d_graph.run.frames import FrameReader
from nap3d_graph.run.graph import KeyframeGraph
from nap3d_graph.run.history import FrameLog
from nap3d_graph.run.imu import ImuMotion, ImuOdometry
from nap3d_graph.run.intrinsics_model import IntrinsicsModelTracker
from nap3d_graph.run.jobs import KeyframeJobs
from nap3d_graph.run.keyframe import CorrectionWorker, DepthScaleTracker
from nap3d_graph.run.library_threads import library_threads
from nap3d_graph.run.motion import MotionModel, OdometryMotion
from nap3d_graph.run.overlapped import OverlappedSteps
from nap3d_graph.run.records import KeyframeRecord, RunResult, ground_truth_reader, tell
from nap3d_graph.run.recovery import MapRecovery
from nap3d_graph.run.retire import retired_segment
from nap3d_graph.run.selection import KeyframeSelector
from nap3d_graph.run.state import RunState
from nap3d_graph.run.stream import MeasurementStream

__all__ = ["Pipeline", "motion_model", "motion_kind", "trained_frames"]

log = logging.getLogger(__name__)


def motion_model(odometry, config: PipelineConfig, t0: float) -> MotionModel:
    """The motion model an odometry source calls for: the IMU's preintegration for an
    :class:`~nap3d_graph.run.imu.ImuOdometry`, a frame odometry's increments otherwise."""
    if isinstance(odometry, ImuOdometry):
        return ImuMotion(odometry, config, t0)
    return OdometryMotion(odometry, config)


def motion_kind(odometry) -> type[ImuMotion] | type[OdometryMotion]:
    """The class :func:`motion_model` makes for ``odometry`` (what it allows, before a run)."""
    return ImuMotion if isinstance(odometry, ImuOdometry) else OdometryMotion


class Pipeline:
    """One drift-correction run over a sequence.

    sequence: a :class:`~nap3d_graph.datasets.protocol.Sequence`, or anything the run can read
        frames from (:class:`~nap3d_graph.datasets.protocol.FrameSource`: ``len``,
        ``seq[i] -> RGBDFrame``, ``timestamps``, ``T_world_cam_gt``; a live caller's sequence).
    field: anything with ``render(T_world_cam, intrinsics)`` (None: odometry only).
    odometry: a frame odometry (``initial_pose()``, ``increment(i, frame)``), or an
        :class:`~nap3d_graph.run.imu.ImuOdometry`: its motion model (:func:`motion_model`)
        moves the run between keyframes.
    correction_hook: optional ``f(frame_index, Correction) -> Correction`` applied before the
        gate (tests use it to inject a wrong correction).
    on_retire: optional ``f(RunResult)``. With a bounded graph (``config.graph_window``), each
        time keyframes leave the window with their poses fixed, the frames up to the last of
        them are final: they are handed over as a :class:`RunResult` segment (``first_frame``
        says where it starts) and forgotten, so a long run's memory stays flat; the run's own
        result then holds the frames after them (:func:`~nap3d_graph.run.history.join_segments`
        puts the pieces together). Without it the run keeps everything.
    """

    # The run's state and parts, made fresh by start().
    state: RunState
    selector: KeyframeSelector
    frames: FrameReader
    jobs: KeyframeJobs
    corrections: CorrectionGate
    recovery: MapRecovery
    _trained: np.ndarray

    def __init__(self, sequence: FrameSource, field, odometry, config: PipelineConfig | None = None,
                 correction_hook=None, on_retire=None):
        self.sequence = sequence
        self.on_retire = on_retire
        self.worker: CorrectionWorker | None = None  # an overlapped run's, while it runs
        self._overlap: OverlappedSteps | None = None  # its steps (nap3d_graph.run.overlapped)
        self.field = field
        self.odometry = odometry
        # The field's own error, as it measured it when it was built, unless told otherwise.
        self._config = with_field_error(config or PipelineConfig(), field)
        self.correction_hook = correction_hook
        self.relocaliser = None  # a map's (recover_in_map, start_in_map)
        self._recoveries: list[dict] = []
        # Placing the run in the map (nap3d_graph.mapping.start): None when the start is given;
        # set by start_in_map for a run that starts from anywhere in a map.
        self._placement_settings: PlacementSettings | None = None
        self._starts_unplaced = False
        self._placement: MapPlacement | None = None
        motion = motion_kind(odometry)
        if self.config.use_anchor and motion.estimates_field_frame:
            raise ValueError("`use_anchor` does not apply with `odometry='imu'`: the IMU path estimates the field's frame's "
                             "tilt (its gravity) itself")
        if self.config.graph_window and (self.config.use_anchor or not motion.allows_graph_window):
            raise ValueError("graph_window (a bounded graph) does not apply with the map anchor or the IMU path")

    def recover_in_map(self, relocaliser) -> None:
        """Recover in a map when lost (before :meth:`run` or :meth:`start`): after
        ``config.relocalise_after`` keyframes refused in a row, the frame is found afresh by
        ``relocaliser`` (the map's :class:`~nap3d_graph.mapping.relocalise.Relocaliser`) and,
        once the next keyframes confirm it, enters as a correction past the gate (the
        prediction it would be gated against is what went wrong). Each recovery is listed in
        ``recoveries``."""
        self.relocaliser = relocaliser

    def start_in_map(self, relocaliser, settings: PlacementSettings | None = None) -> None:
        """Start from anywhere in a map (before :meth:`run` or :meth:`start`): the odometry
        runs from its own first camera (a provisional frame) until ``relocaliser`` (the map's
        :class:`~nap3d_graph.mapping.relocalise.Relocaliser`) finds a keyframe and the next
        keyframes confirm it (:class:`~nap3d_graph.mapping.start.MapPlacement`); then every pose
        so far moves into the map's frame and corrections begin. The same relocaliser then
        recovers a run lost later. ``placement.summary()`` says when and how it was placed."""
        if not motion_kind(self.odometry).allows_graph_window:
            raise ValueError("starting from anywhere in a map needs a frame odometry ('vo', 'dense', 'recorded'), "
                             "not odometry='imu' (its gravity and velocities are in a frame of their own)")
        if self.config.use_anchor:
            raise ValueError("`use_anchor` does not apply when the start is found in the map (the map is the world)")
        self.relocaliser = relocaliser
        self._placement_settings = settings
        self._starts_unplaced = True

    # --- what a caller reads --------------------------------------------------------------

    @property
    def config(self) -> PipelineConfig:
        """The run's settings, with the field's own error resolved (:func:`with_field_error`)."""
        return self._config

    @property
    def placement(self) -> MapPlacement | None:
        """Where the run is in its map (None: no map, or before :meth:`start`)."""
        return self._placement

    @property
    def placed(self) -> bool:
        """Whether the run's poses are in the field's (map's) frame: always, unless it started
        from anywhere in a map and has not been placed yet."""
        return self._placement is None or self._placement.placed

    @property
    def recoveries(self) -> list[dict]:
        """Each relocalisation tried after refusals and each recovery (metrics.json's record)."""
        return self._recoveries

    @property
    def records(self) -> FrameLog[KeyframeRecord]:
        """Each keyframe's record, in the order they were done (with ``on_retire`` the oldest
        are dropped)."""
        return self.state.records

    @property
    def keyframe_indices(self) -> FrameLog[int]:
        """The frame of each keyframe, by keyframe number."""
        return self.state.keyframe_indices

    @property
    def last_correction(self) -> Correction | None:
        """The latest correction measured in this frame's step (None: none), its factor when it
        entered the graph (:attr:`last_factor`) and its keyframe (:attr:`last_correction_frame`)."""
        return self.state.last_correction

    @property
    def last_factor(self) -> gtsam.NonlinearFactor | None:
        return self.state.last_factor

    @property
    def last_correction_frame(self) -> int:
        return self.state.last_correction_frame

    @property
    def current_estimate(self) -> np.ndarray:
        """(4, 4) the latest frame's pose as known now (the causal estimate)."""
        return np.array(self.state.online[-1])

    # --- the run, as its steps ---------------------------------------------------------

    def run(self, on_keyframe=None, stop=None) -> RunResult:
        """Run over the sequence. ``on_keyframe(record)`` hears about each keyframe as soon as
        it is done (a results writer appends it); ``stop()`` is asked before each frame and,
        when it says so, the run ends there with what it has (``RunResult.partial``).
        numpy's BLAS works with ``config.library_threads`` threads meanwhile."""
        t_start = time.perf_counter()
        self.start()
        with library_threads(self.config.library_threads):
            result = self._run_frames(on_keyframe, stop)
        result.wall_time_s = time.perf_counter() - t_start
        return result

    def _run_frames(self, on_keyframe, stop) -> RunResult:
        n = len(self.sequence) if self.config.max_frames is None else min(len(self.sequence), self.config.max_frames)
        done, partial = n, False
        worker = CorrectionWorker(self.field, self.config) if self.overlaps() else None
        self.worker = worker  # a caller's stop hook may watch it
        # A third thread on two cores: when the second thread is what the run waits for, the
        # reader would only slow it down (FrameReader.hold_back), and reading here costs nothing.
        self.frames.read_ahead(self.config.read_ahead, n)
        try:
            for i in progress_bar(range(n), desc="run", unit="frame", disable=not self.config.progress):
                if stop is not None and stop():
                    done, partial = i, True
                    break
                self.step(i, worker, on_keyframe)
            if worker is not None:
                self.land_pending(worker, on_keyframe)
        finally:
            if worker is not None:
                worker.close()
            self.worker = None
            self.frames.close()
        result = self.result(max(done, 1))
        result.partial = partial
        return result

    def step(self, i: int, worker: CorrectionWorker | None = None, on_keyframe=None) -> None:
        """Frame i (after frames 0..i-1; :meth:`start` first): its odometry, and when it is a
        keyframe, its node, its correction and the solve. ``run`` is this over the sequence;
        :class:`nap3d_graph.run.live.DriftCorrector` calls it a frame at a time. With a
        ``worker`` the keyframe is measured on it while the run goes on
        (:mod:`nap3d_graph.run.overlapped`)."""
        state = self.state
        state.last_correction = state.last_factor = None  # what this frame's step measures
        if worker is not None:
            self._overlapped(worker).step(state, i, on_keyframe)
            return
        frame = self.predict(i, self.frames.for_odometry(i))
        if self.is_keyframe(i, frame, idle=False):
            self.add_keyframe(i)  # its node and motion factor: the prediction
            frame = self.frames.for_keyframe(i, frame, needed=self.field is not None)
            self._correct_keyframe(i, frame)  # measured, gated, added, solved
            tell(on_keyframe, self.finish_keyframe())
        state.online.append(state.motion.causal_pose())

    def overlaps(self) -> bool:
        """Whether keyframes are measured on a worker thread (``config.overlap``, a field, and a
        motion model that allows it); after :meth:`start`."""
        return bool(self.config.overlap) and self.field is not None and self.state.motion.allows_overlap

    def land_pending(self, worker: CorrectionWorker, on_keyframe=None) -> None:
        """The measurement still in flight, if any, waited for and put in the graph (the end of
        an overlapped run)."""
        self._overlapped(worker).land_pending(self.state, on_keyframe)

    def _overlapped(self, worker: CorrectionWorker) -> OverlappedSteps:
        """The overlapped steps of this run with ``worker`` (made once per worker)."""
        if self._overlap is None or self._overlap.worker is not worker:
            self._overlap = OverlappedSteps(self, worker, self.frames, self.selector, self.jobs, self.config,
                                            self.sequence)
        return self._overlap

    # --- a frame's steps (the inline path here; nap3d_graph.run.overlapped the other) -------

    def predict(self, i: int, frame):
        """Frame i's odometry step (the motion model's prediction of its pose); returns ``frame``."""
        if i > 0:
            t = float(self.sequence.timestamps[i])
            self.state.motion.frame(i, frame, t, t - float(self.sequence.timestamps[i - 1]))
        return frame

    def is_keyframe(self, i: int, frame, idle: bool) -> bool:
        """Whether frame i is a keyframe (``idle``: an overlapped run's worker has nothing in flight)."""
        motion = self.state.motion
        return self.selector.is_keyframe(i, frame, self.state.last_keyframe, motion.doubted, motion.since_keyframe(),
                                         idle)

    def add_keyframe(self, i: int) -> None:
        """Frame i becomes a keyframe: its pose enters iSAM2 with its motion factor (that is
        the prediction), and its record is pending (``state.pending_record``) until it is measured."""
        state = self.state
        j = len(state.keyframe_indices)
        state.keyframe_indices.append(i)
        entry = state.motion.add_keyframe(j, i, float(self.sequence.timestamps[i]))
        state.graph.enter(entry)
        state.T_world_kf_pred = entry.T_world_kf_pred
        if entry.interval is not None:
            state.stream.add_interval(i, entry.interval)
        why, sharp, waited = self.selector.take()
        trained = bool(self._trained[i]) if i < len(self._trained) else False  # a live run's frames: unknown
        state.pending_record = KeyframeRecord(i, float(self.sequence.timestamps[i]), X(j), trained_frame=trained,
                                              why=why, sharpness=sharp, postponed=waited)
        state.update_graph()

    def placing(self) -> bool:
        """Whether the next keyframe goes to finding the run in its map, not to a correction."""
        return self.recovery.placing()

    def place_keyframe(self, i: int, frame) -> None:
        """The pending keyframe i relocalised in the map, or confirming where it was found."""
        self.recovery.place_keyframe(self.state, self.state.pending(), i, frame)

    def _correct_keyframe(self, i: int, frame) -> None:
        """Measure the pending keyframe's correction and give it to the graph, now; then the
        motion model hears whether it landed, and adds its own notes of the interval."""
        state = self.state
        record = state.pending()
        if self.placing():
            self.place_keyframe(i, frame)
        elif (job := self.jobs.job(state, record, i, frame)) is not None:
            correction = measure_keyframe(job, self.field, self.config)
            self.apply_correction(record, i, correction, job.T_field_cam_render, frame)
        if notes := state.motion.interval_notes():
            record.reason = f"{record.reason}; {notes}" if record.reason else notes
        state.motion.after_correction(i, frame, record.accepted)

    def apply_correction(self, record: KeyframeRecord, i: int, correction: Correction, T_field_cam_render,
                         frame, latest: bool = True) -> None:
        """Keyframe i's measured ``correction`` through the gate; when it enters the graph, the
        solve; then, for the ``latest`` keyframe, a recovery in the map if the run is lost."""
        if self.corrections.apply(self.state, record, i, correction, T_field_cam_render) is not None:
            # Two iSAM2 steps: a correction can move the pose a long way from its linearisation.
            self.state.update_graph(extra_step=True, record=record)
        if latest:
            self.recovery.recover_if_lost(self.state, record, i, frame)

    def keyframe_estimated(self) -> None:
        """The motion model hears the latest keyframe's estimate as the graph has it now."""
        state = self.state
        j = len(state.keyframe_indices) - 1
        state.motion.keyframe_estimated(state.graph, j, float(self.sequence.timestamps[state.keyframe_indices[j]]))

    def finish_keyframe(self) -> KeyframeRecord | None:
        """The latest keyframe is done: the motion model hears its estimate, its record is kept
        and returned (None when it was already handed on)."""
        state = self.state
        self.keyframe_estimated()
        record, state.pending_record = state.pending_record, None
        if record is not None:
            state.records.append(record)
        return record

    def _retire(self, cut: int) -> None:
        """Keyframes before ``cut`` left the bounded graph: the frames now final go to ``on_retire``."""
        if self.on_retire is not None and (segment := retired_segment(self.state, self.sequence, cut)) is not None:
            self.on_retire(segment)

    # --- start and result ------------------------------------------------------------------

    def start(self) -> None:
        """A fresh graph and state, before frame 0 (:meth:`run` starts itself)."""
        self._overlap = None
        config, stamps = self.config, self.sequence.timestamps
        # A live run (DriftCorrector) starts before its first frame: no stamp yet.
        motion = motion_model(self.odometry, config, float(stamps[0]) if len(stamps) else 0.0)
        anchor = motion.anchor_prior()
        anchored = config.use_anchor or anchor is not None
        self._trained = trained_frames(self.field, self.sequence)
        self.selector = KeyframeSelector(config)
        self.frames = FrameReader(self.sequence, motion, self.selector)
        self.jobs = KeyframeJobs(self.field, config, self.odometry, stamps, self.frames)
        timing = self.jobs.timing()
        settings = self._placement_settings or PlacementSettings(confirm_travel_m=config.placement_travel_m)
        self._placement = None if self.relocaliser is None else MapPlacement(
            self.relocaliser, settings, placed=not self._starts_unplaced)
        self.state = RunState(motion, KeyframeGraph(config, anchored), anchored, MeasurementStream(),
                              DepthScaleTracker(timing.depth_scale if timing is not None else 1.0, config),
                              IntrinsicsModelTracker.for_run(config), self._placement,
                              motion.T_world_cam_odom[0], retire=self._retire)
        self.corrections = CorrectionGate(config, self.correction_hook)
        self.recovery = MapRecovery(self._placement, self.field, config, self.jobs)
        self._recoveries = self.recovery.recoveries
        if config.use_anchor:  # the field's frame in the odometry's world, to be estimated
            anchor = (anchor_prior_factor(M(0), np.eye(4), config.anchor_rot_sigma_rad,
                                          config.anchor_trans_sigma_m), np.eye(4))
        if anchor is not None:
            self.state.graph.add_anchor(*anchor)

    def result(self, n: int) -> RunResult:
        """The run over its first ``n`` frames as it stands: the final solve, every frame's
        pose (``run`` returns this at its end)."""
        state = self.state
        motion, graph, keyframe_indices = state.motion, state.graph, state.keyframe_indices
        first = state.online.start  # frames before it were retired (on_retire)
        T_world_cam_gt = ground_truth_reader(self.sequence, first, n)
        stamps = np.asarray(self.sequence.timestamps[first:n], dtype=float)
        if not len(keyframe_indices):  # stopped before the first keyframe: odometry is all there is
            T_world_cam_odom = np.stack(motion.T_world_cam_odom[:n])
            return RunResult(stamps, T_world_cam_odom, T_world_cam_odom, T_world_cam_gt, [], [], T_world_cam_online=T_world_cam_odom)
        accepted = {r.frame_index for r in state.records if r.accepted}
        estimate = graph.final_estimate(accepted)
        frozen = graph.frozen
        T_world_kf_by_frame = {idx: frozen[j] if j in frozen else pose3_to_T(estimate.atPose3(X(j)))
                               for j, idx in keyframe_indices.items()}
        T_world_cam_est = motion.smoothed(estimate, T_world_kf_by_frame, keyframe_indices, stamps)
        T_online = motion.causal(state.online, stamps)
        T_map = pose3_to_T(estimate.atPose3(M(0))) if self.config.use_anchor else None
        result = RunResult(stamps, T_world_cam_est, np.stack(motion.T_world_cam_odom[:n]), T_world_cam_gt,
                           list(state.records), list(keyframe_indices), T_map, T_world_cam_online=T_online,
                           gnc_outliers=list(graph.gnc_outliers), gnc_recovered=list(graph.gnc_recovered),
                           depth_scale=state.depth_scale.scale, interval_odometry=dict(state.stream.interval_odometry),
                           corrections=dict(state.stream.corrections), increments=list(motion.increments[:n]),
                           first_frame=first)
        motion.finish(estimate, graph, accepted, keyframe_indices, result)
        if self._placement is not None:
            result.placement = self._placement.summary()
        return result


def trained_frames(field, sequence) -> np.ndarray:
    """(N,) bool: which frames of ``sequence`` ``field`` was trained on (none without a field)."""
    return frames_seen_in_training(field, sequence) if field is not None else np.zeros(len(sequence), dtype=bool)
