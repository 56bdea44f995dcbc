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
"""

from __future__ import annotations

import logging
import time

import gtsam
import numpy as np
from gtsam.symbol_shorthand import M, X

from nap3d_graph.camera import Intrinsics
from nap3d_graph.conventions import inv_T, pose3_to_T, pose_error
from nap3d_graph.datasets.depth_timing import CaptureTiming, resolve_capture_timing
from nap3d_graph.datasets.protocol import FrameSource
from nap3d_graph.factors import anchor_prior_factor
from nap3d_graph.mapping.start import MapPlacement, PlacementSettings
from nap3d_graph.results import Alignment, Correction
from nap3d_graph.run.chain import chain_from_nearest_keyframe
from nap3d_graph.run.config import PipelineConfig, with_field_error
from nap3d_graph.run.graph import KeyframeGraph
from nap3d_graph.run.history import FrameLog
from nap3d_graph.run.imu import ImuMotion, ImuOdometry
from nap3d_graph.run.intrinsics_model import IntrinsicsModelTracker
from nap3d_graph.run.keyframe import CorrectionWorker, DepthScaleTracker, KeyframeJob, measure_keyframe
from nap3d_graph.run.library_threads import library_threads
from nap3d_graph.run.motion import MotionModel, OdometryMotion
from nap3d_graph.run.overlapped import OverlappedSteps
from nap3d_graph.run.read_ahead import FrameReadAhead, reads_concurrently
from nap3d_graph.run.records import KeyframeRecord, RunResult
from nap3d_graph.run.selection import KeyframeSelector

__all__ = ["Pipeline", "motion_model", "motion_kind"]

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

    def __init__(self, sequence: FrameSource, field, odometry, config: PipelineConfig | None = None,
                 correction_hook=None, on_retire=None):
        self.sequence = sequence
        # What frames are read from: the sequence, or a FrameReadAhead over it while run() goes.
        self._frames: FrameSource | FrameReadAhead = sequence
        self._waits_for_worker = False  # the latest keyframe had to wait for the one in flight
        self.on_retire = on_retire
        self.worker: CorrectionWorker | None = None  # an overlapped run's, while it runs
        self._overlap: OverlappedSteps | None = None  # its steps (nap3d_graph.run.overlapped)
        self.field = field
        self.odometry = odometry
        # The field's own error, as it measured it when it was built, unless told otherwise.
        self.config = with_field_error(config or PipelineConfig(), field)
        self.correction_hook = correction_hook
        # A map's relocaliser (nap3d_graph.mapping.relocalise.Relocaliser), set by whoever has the
        # map: after config.relocalise_after keyframes refused in a row, the frame is found in the
        # map afresh and enters as a correction past the gate (the prediction it would be gated
        # against is what went wrong). Each recovery is listed in ``recoveries``.
        self.relocaliser = None
        self.recoveries: list[dict] = []
        self._refused_in_a_row = 0
        # Placing the run in the map (nap3d_graph.mapping.start): None when the start is given;
        # set by start_in_map for a run that starts from anywhere in a map.
        self._placement_settings: PlacementSettings | None = None
        self._starts_unplaced = False
        self.placement: MapPlacement | None = None
        motion = motion_kind(odometry)
        if self.config.use_anchor and motion.estimates_field_frame:
            raise ValueError("`use_anchor` does not apply with `odometry='imu'`: the IMU path estimates the field's frame's "
                             "tilt (its gravity) itself")
        if self.config.graph_window and (self.config.use_anchor or not motion.allows_graph_window):
            raise ValueError("graph_window (a bounded graph) does not apply with the map anchor or the IMU path")

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

    @property
    def placed(self) -> bool:
        """Whether the run's poses are in the field's (map's) frame: always, unless it started
        from anywhere in a map and has not been placed yet."""
        return self.placement is None or self.placement.placed

    def _motion(self) -> MotionModel:
        stamps = self.sequence.timestamps
        # A live run (DriftCorrector) starts before its first frame: no stamp yet.
        return motion_model(self.odometry, self.config, float(stamps[0]) if len(stamps) else 0.0)

    # --- the run, as its steps ---------------------------------------------------------

    def run(self, on_keyframe=None, stop=None) -> RunResult:
        """Run over the sequence. ``on_keyframe(record)`` hears about each keyframe as soon as
        it is done (a results writer appends it); ``stop()`` is asked before each frame and,
        when it says so, the run ends there with what it has (``RunResult.partial``).
        numpy's BLAS works with ``config.library_threads`` threads meanwhile."""
        t_start = time.perf_counter()
        self._start()
        with library_threads(self.config.library_threads):
            result = self._run_frames(on_keyframe, stop)
        result.wall_time_s = time.perf_counter() - t_start
        return result

    def _run_frames(self, on_keyframe, stop) -> RunResult:
        from nap3d_graph.progress import progress_bar

        n = len(self.sequence) if self.config.max_frames is None else min(len(self.sequence), self.config.max_frames)
        done, partial = n, False
        worker = CorrectionWorker(self.field, self.config) if self.overlaps() else None
        self.worker = worker  # a caller's stop hook may watch it
        # Only a run that reads every frame reads ahead (one that moves with recorded or IMU
        # odometry reads its keyframes alone).
        reads_all = self.motion.needs_frames or self.selector.reads_every_frame
        if self.config.read_ahead and reads_all and reads_concurrently(self.sequence):
            # A third thread on two cores: when the second thread is what the run waits for, the
            # reader would only slow it down, and reading here costs nothing (the run would wait).
            self._frames = FrameReadAhead(self.sequence, self.config.read_ahead, n,
                                          wanted=lambda: not self._waits_for_worker)
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
            if isinstance(self._frames, FrameReadAhead):
                self._frames.close()
            self._frames = self.sequence
        result = self._finish(max(done, 1))
        result.partial = partial
        return result

    def start(self) -> None:
        """A fresh graph and state, before frame 0 (``run`` starts itself)."""
        self._start()

    def result(self, n: int) -> RunResult:
        """The run over its first ``n`` frames as it stands: the final solve, every frame's
        pose (``run`` returns this at its end)."""
        return self._finish(n)

    def step(self, i: int, worker: CorrectionWorker | None = None, on_keyframe=None) -> None:
        """Frame i (after frames 0..i-1; ``_start`` first): its odometry, and when it is a
        keyframe, its node, its correction and the solve. ``run`` is this over the sequence;
        :class:`nap3d_graph.run.live.DriftCorrector` calls it a frame at a time. With a
        ``worker`` the keyframe is measured on it while the run goes on
        (:mod:`nap3d_graph.run.overlapped`)."""
        if worker is not None:
            self._overlapped(worker).step(i, on_keyframe)
            return
        frame = self._predict(i, self._frame_for_odometry(i))
        if self._is_keyframe(i, frame, idle=False):
            self._add_keyframe(i)  # its node and motion factor: the prediction
            frame = self._keyframe_frame(i, frame)
            self._correct_keyframe(i, frame)  # measured, gated, added, solved
            self._report(self._finish_keyframe(), on_keyframe)
        self._online.append(self.motion.causal_pose())

    def _overlapped(self, worker: CorrectionWorker) -> OverlappedSteps:
        """The overlapped steps of this run with ``worker`` (made once per worker)."""
        if self._overlap is None or self._overlap.worker is not worker:
            self._overlap = OverlappedSteps(self, worker)
        return self._overlap

    def _frame_for_odometry(self, i: int):
        """Frame i when the motion model or the keyframe selection reads every frame, else None
        (a run on recorded or IMU odometry reads its keyframes alone)."""
        return self._read_frame(i) if self.motion.needs_frames or self.selector.reads_every_frame else None

    def _predict(self, i: int, frame):
        """Frame i's odometry step (the motion model's prediction of its pose); returns ``frame``."""
        if i > 0:
            t = float(self.sequence.timestamps[i])
            self.motion.frame(i, frame, t, t - float(self.sequence.timestamps[i - 1]))
        return frame

    def _is_keyframe(self, i: int, frame, idle: bool) -> bool:
        """Whether frame i is a keyframe (``idle``: an overlapped run's worker has nothing in flight)."""
        last = self.keyframe_indices[-1] if self.keyframe_indices else None
        return self.selector.is_keyframe(i, frame, last, self.motion.doubted, self.motion.since_keyframe(), idle)

    def _keyframe_frame(self, i: int, frame):
        """The keyframe's image: read now if the odometry did not (without a field a keyframe
        needs none)."""
        if frame is None and self.field is not None:
            return self._read_frame(i)
        return frame

    @staticmethod
    def _report(record: KeyframeRecord | None, on_keyframe) -> None:
        """Tell ``on_keyframe`` about a finished keyframe."""
        if on_keyframe is not None and record is not None:
            on_keyframe(record)

    @property
    def current_estimate(self) -> np.ndarray:
        """(4, 4) the latest frame's pose as known now (the causal estimate)."""
        return np.array(self._online[-1])

    # --- steps -----------------------------------------------------------------------------

    def _start(self) -> None:
        self._frames, self._waits_for_worker = self.sequence, False  # as in __init__, for a new run
        self._overlap = None
        self.motion = self._motion()
        anchor = self.motion.anchor_prior()
        self.anchored = self.config.use_anchor or anchor is not None
        self.graph = KeyframeGraph(self.config, self.anchored)
        # Indexed by keyframe number (records: in the order they were done); with on_retire
        # the oldest are dropped (FrameLog), like the motion model's per-frame lists.
        self.keyframe_indices: FrameLog[int] = FrameLog()
        self.records: FrameLog[KeyframeRecord] = FrameLog()
        self.T_world_kf_pred = self.motion.T_world_cam_odom[0]
        self._pending_record: KeyframeRecord | None = None
        self._frame_intrinsics: Intrinsics | None = None  # the last frame read's camera (a render made ahead uses it)
        self._online: FrameLog[np.ndarray] = FrameLog()  # each frame's pose as known at that frame (causal)
        # The latest keyframe's correction and factor (a live caller reads them).
        self.last_correction: Correction | None = None
        self.last_factor: gtsam.NonlinearFactor | None = None
        self._streak: tuple[str | None, int] = (None, 0)  # the current run of refusals for one reason
        self.last_correction_frame = -1
        self._trained = self._trained_timestamps()
        self.placement = None if self.relocaliser is None else MapPlacement(
            self.relocaliser, self._placement_settings, placed=not self._starts_unplaced)
        self.recoveries, self._refused_in_a_row = [], 0
        self.selector = KeyframeSelector(self.config)
        timing = self._timing()
        self.depth_scale = DepthScaleTracker(timing.depth_scale if timing is not None else 1.0, self.config)
        self.intrinsics_model = IntrinsicsModelTracker.for_run(self.config)
        # The measurement stream, for estimators compared on the same inputs
        # (nap3d_graph.estimators): each keyframe interval's odometry as its factor has it,
        # and every successful correction (gated out or not) with its covariance.
        self.interval_odometry: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.measured_corrections: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        if self.config.use_anchor:  # the field's frame in the odometry's world, to be estimated
            anchor = (anchor_prior_factor(M(0), np.eye(4), self.config.anchor_rot_sigma_rad,
                                          self.config.anchor_trans_sigma_m), np.eye(4))
        if anchor is not None:
            self.graph.add_anchor(*anchor)

    def _read_frame(self, i: int):
        """Frame i, or None when it cannot be read (the reason is logged and recorded)."""
        from nap3d_graph.datasets import DatasetError

        try:
            frame = self._frames[i]
        except (DatasetError, OSError) as exc:
            log.warning("frame %d unreadable: %s", i, exc)
            self._frame_error = str(exc)
            return None
        if i == 0:
            self.motion.prime(frame)
        self._frame_intrinsics = frame.intrinsics
        return frame

    def _keyframe_record(self, i: int, key: int, **extra) -> KeyframeRecord:
        """The record of keyframe i (why it is one, its sharpness); starts the next interval."""
        why, sharp, waited = self.selector.take()
        trained = bool(self._trained[i]) if i < len(self._trained) else False  # a live run's frames: unknown
        return KeyframeRecord(i, float(self.sequence.timestamps[i]), key, trained_frame=trained,
                              why=why, sharpness=sharp, postponed=waited, **extra)

    def _add_keyframe(self, i: int) -> None:
        """The keyframe's pose enters iSAM2 with its motion factor: that is the prediction."""
        j = len(self.keyframe_indices)
        self.keyframe_indices.append(i)
        entry = self.motion.add_keyframe(j, i, float(self.sequence.timestamps[i]))
        self.graph.enter(entry)
        self.T_world_kf_pred = entry.T_world_kf_pred
        if entry.interval is not None:
            self.interval_odometry[i] = entry.interval
        self._pending_record = self._keyframe_record(i, X(j))
        self._update_isam()

    def _correct_keyframe(self, i: int, frame) -> None:
        """Measure the pending keyframe's correction and give it to the graph, now; then the
        motion model hears whether it landed, and adds its own notes of the interval."""
        record = self._pending()
        if self._placing():
            self._place_keyframe(record, i, frame)
        elif (job := self._job(i, frame)) is not None:
            self._apply_correction(record, i, measure_keyframe(job, self.field, self.config), job.T_field_cam_render)
            self._recover_if_lost(record, i, frame)
        if notes := self.motion.interval_notes():
            record.reason = f"{record.reason}; {notes}" if record.reason else notes
        self.motion.after_correction(i, frame, record.accepted)

    def _pending(self) -> KeyframeRecord:
        """The record of the keyframe being measured (between ``_add_keyframe`` and
        ``_finish_keyframe`` / ``_launch``)."""
        if self._pending_record is None:
            raise RuntimeError("no keyframe is pending: _add_keyframe comes first")
        return self._pending_record

    def _job(self, i: int, frame, T_field_cam_render: np.ndarray | None = None) -> KeyframeJob | None:
        """What measuring keyframe i needs, or None (the reason recorded) when it cannot be;
        rendered at its prediction, or at ``T_field_cam_render`` (4, 4) when given."""
        record = self._pending()
        if self.field is None:
            record.reason = "no field"
            return None
        if frame is None:
            record.reason = f"frame unreadable: {getattr(self, '_frame_error', 'unknown error')}"
            return None
        if T_field_cam_render is not None:
            pass
        elif self.anchored:
            T_field_cam_render = inv_T(self.graph.anchor()) @ self.T_world_kf_pred  # the field's frame
        else:
            T_field_cam_render = self.T_world_kf_pred
        render_intrinsics = self._render_intrinsics(frame.intrinsics)
        return KeyframeJob(i, frame, T_field_cam_render, self._velocity(i), self._timing(), self.depth_scale.scale,
                           render_intrinsics, feats_real=self._odometry_features(i, render_intrinsics),
                           fit_intrinsics=self.intrinsics_model.fits_both(i))

    def _odometry_features(self, i: int, render_intrinsics: Intrinsics):
        """``(features, 0.0)``: frame i's features as the feature odometry detected them, when they
        are what its correction would detect (``--odom vo --vo-width`` at the render's width);
        else None."""
        features_of = getattr(self.odometry, "features_of", None)
        features = features_of(i, render_intrinsics, self.config.align) if features_of is not None else None
        return None if features is None else (features, 0.0)

    def _odometry_shares_features(self, intrinsics: Intrinsics) -> bool:
        shares = getattr(self.odometry, "shares_features", None)
        return shares is not None and shares(self._render_intrinsics(intrinsics), self.config.align)

    def _due_by_count(self, i: int) -> bool:
        """Frame i is due to be a keyframe by ``keyframe_every`` alone (what can be known before
        its odometry; the other reasons a keyframe is taken cannot)."""
        return len(self.keyframe_indices) > 0 and i - self.keyframe_indices[-1] >= self.config.keyframe_every

    def _apply_correction(self, record: KeyframeRecord, i: int, correction: Correction, T_field_cam_render) -> None:
        """The graph half (:meth:`_gate_and_add`), and a warning while the run goes when
        corrections keep failing for one reason."""
        self._gate_and_add(record, i, correction, T_field_cam_render)
        self._watch_refusals(record)

    def _latest_key(self) -> int:
        """The graph key of the latest keyframe."""
        return X(len(self.keyframe_indices) - 1)

    def _placing(self) -> bool:
        """Whether this keyframe goes to the map placement (:mod:`nap3d_graph.mapping.start`)
        rather than to a correction: the run is not placed yet, or a recovery waits for its
        confirmation."""
        return self.placement is not None and (not self.placement.placed or self.placement.candidate is not None)

    def _recover_if_lost(self, record: KeyframeRecord, i: int, frame) -> None:
        """After ``relocalise_after`` keyframes refused in a row (the estimate drifted off the
        map, or the odometry lost track), relocalise this frame in the map: a verified
        relocalisation becomes a candidate that the next keyframes confirm
        (:meth:`_place_keyframe`), then enters without the gate, which would compare it with
        the prediction that is lost."""
        self._refused_in_a_row = 0 if record.accepted else self._refused_in_a_row + 1
        after = self.config.relocalise_after
        if (self.placement is None or frame is None or not after or self._refused_in_a_row < after
                or self.anchored):
            return
        found = self.placement.propose(i, record.key, frame, self.T_world_kf_pred)
        entry = {"frame": int(i), "step": "relocalise", "refused_in_a_row": self._refused_in_a_row,
                 "found": found is not None,
                 "seconds": self.placement.events[-1]["seconds"]}
        if found is None:  # tried again at the next keyframe
            entry["reason"] = self.placement.events[-1].get("reason", "")
        else:
            self._refused_in_a_row = 0
            if self.placement.settings.confirmations == 0:
                self._place(record, i)
        self.recoveries.append(entry)

    def _place_keyframe(self, record: KeyframeRecord, i: int, frame) -> None:
        """Keyframe i while the run is not placed in the map (or a recovery waits): it confirms
        the pending candidate (rendered where the candidate puts it), or relocalises afresh.
        Nothing enters the graph until a candidate is confirmed; then :meth:`_place`."""
        placement = self.placement
        assert placement is not None
        lost = placement.placed  # a recovery, not the start
        if frame is None or self.field is None:
            record.reason = "no frame to relocalise" if frame is None else "no field"
            return
        if placement.candidate is not None:
            T_map_cam_pred = placement.predicted(self.T_world_kf_pred)
            job = self._job(i, frame, T_field_cam_render=T_map_cam_pred)
            if job is None:
                return
            correction = measure_keyframe(job, self.field, self.config)
            record.matches, record.inliers, record.iterations = (correction.num_matches, correction.num_inliers,
                                                                 correction.iterations)
            verdict = placement.confirm(i, record.key, correction, T_map_cam_pred)
            if verdict == "confirmed":
                self._place(record, i)
                return
            if verdict == "agrees":
                record.reason = "relocalised in the map: confirming (agrees so far)"
                return
            if lost:  # refuted while recovering: back to counting refusals
                record.reason = f"recovery refuted: {placement.events[-1].get('reason', '')}"
                return
        found = placement.propose(i, record.key, frame, self.T_world_kf_pred)
        if found is not None and placement.settings.confirmations == 0:
            self._place(record, i)
            return
        record.reason = ("not yet placed in the map: relocalised, to be confirmed by the next keyframe" if found
                         else f"not yet placed in the map: {placement.events[-1].get('reason', 'not found')}")

    def _place(self, record: KeyframeRecord, i: int) -> None:
        """The pending candidate is confirmed at keyframe i: at the start, everything so far
        moves into the map's frame (:meth:`_reframe`); then the relocalisation and each
        confirming correction enter the graph past the gate."""
        placement = self.placement
        assert placement is not None
        first = not placement.placed
        cand = placement.accept(i)
        if first:
            self._reframe(cand.T_map_run)
        found = cand.found
        alignment = Alignment(success=True, num_inliers=int(found.inliers), covariance=found.covariance)
        relocalised = Correction(found.T_map_cam, found.T_map_cam, found.covariance, alignment, 1, True, "", {})
        T_pred = self.T_world_kf_pred
        for frame_index, key, correction in [(cand.frame, cand.key, relocalised), *cand.confirmed]:
            if not self.graph.has(key) and key != record.key:
                continue  # left a bounded graph meanwhile
            try:
                self.graph.add_past_gate(key, correction, frame_index)
            except ValueError as exc:  # a covariance GTSAM cannot use: that one stays out
                log.warning("frame %d: relocalisation not usable (%s)", frame_index, exc)
        self._update_isam(extra_step=True, record=record)
        last = cand.confirmed[-1][2] if cand.confirmed else relocalised
        record.correction_m, record.correction_deg = pose_error(last.T_world_cam_corrected, T_pred)
        record.accepted = True
        record.reason = ""
        self.last_correction, self.last_correction_frame = last, i
        if first:
            log.warning("frame %d: %s", i, placement.describe())
        else:
            jump_m, jump_deg = pose_error(self.graph.pose(record.key), T_pred)
            entry = {"frame": int(i), "step": "recovered", "recovered_from_frame": cand.frame, "jump_m": round(jump_m, 4),
                     "jump_deg": round(jump_deg, 3), "keyframe": int(found.keyframe), "inliers": int(found.inliers),
                     "success": True}
            self.recoveries.append(entry)
            log.warning("frame %d: recovered in the map (relocalised at frame %d, confirmed); the estimate jumped "
                        "%.2f m / %.1f deg", i, cand.frame, jump_m, jump_deg)
        self._refused_in_a_row = 0

    def _reframe(self, T_map_run: np.ndarray) -> None:
        """Move the run so far from its provisional frame into the map's by ``T_map_run``
        (4, 4): the odometry, the causal poses, the prediction and the graph (which drops its
        provisional first-pose prior: the relocalisation now holds the gauge)."""
        T = np.asarray(T_map_run, dtype=float)
        self.motion.reframe(T)
        self._online = self._online.mapped(lambda T_run_cam: T @ T_run_cam)
        self.T_world_kf_pred = T @ self.T_world_kf_pred
        self.graph = self.graph.reframed(T)

    #: Consecutive keyframes refused for one reason before the run says so.
    REFUSAL_STREAK = 5

    def _watch_refusals(self, record: KeyframeRecord) -> None:
        """Warn (once per streak) when the last REFUSAL_STREAK keyframes were all refused for
        the same reason: the run then goes on on its odometry alone, and the user should know
        it now, not from the summary."""
        from nap3d_graph.run.output import refusal_hint_for
        from nap3d_graph.run.records import refusal_kind

        if record.accepted:
            self._streak = (None, 0)
            return
        kind = refusal_kind(record.reason)
        previous, count = self._streak
        count = count + 1 if kind == previous else 1
        self._streak = (kind, count)
        if count == self.REFUSAL_STREAK:
            log.warning("the last %d keyframes (to frame %d) were all refused for '%s' (the last: %s); the run goes "
                        "on on its odometry alone until corrections land again. %s", count, record.frame_index, kind,
                        record.reason, refusal_hint_for(kind))

    def _gate_and_add(self, record: KeyframeRecord, i: int, correction: Correction, T_field_cam_render) -> None:
        """The graph half: depth-scale check, gate, factor (see the module docstring)."""
        record.intrinsics_model = self.intrinsics_model.observe(i, correction)
        if correction.success and self.config.depth_scale_check:
            correction = self.depth_scale.check(correction, record)
        if correction.success:
            self.measured_corrections[i] = (np.array(correction.T_world_cam_corrected), np.array(correction.covariance))
        if self.correction_hook is not None:
            correction = self.correction_hook(i, correction)
        self.last_correction, self.last_factor = correction, None
        self.last_correction_frame = i  # which keyframe last_correction is (an observer checks)
        record.timings_s.update({k: round(v, 4) for k, v in correction.timings_s.items()})
        record.matches, record.inliers, record.iterations = (correction.num_matches, correction.num_inliers,
                                                             correction.iterations)
        if not correction.success:
            record.reason = correction.reason
            return
        record.correction_m, record.correction_deg = pose_error(correction.T_world_cam_corrected, T_field_cam_render)
        if not self.graph.has(record.key):
            record.reason = "keyframe left the graph window before its correction landed"
            return
        t0 = time.perf_counter()
        factor, gate = self.graph.gated_correction(record.key, correction, i)
        record.timings_s["gate"] = round(time.perf_counter() - t0, 5)
        record.gate_d2 = gate.d2 if gate is not None else float("nan")
        if factor is None:
            # Gated out against a prediction that may itself be wrong: the final solve weighs it
            # again with everything else (KeyframeGraph.final_estimate).
            record.reason = gate.reason if gate is not None else "invalid covariance"
            return
        self.last_factor = factor
        record.accepted = True
        # Two iSAM2 steps: a correction can move the pose a long way from its linearisation.
        self._update_isam(extra_step=True, record=record)

    def overlaps(self) -> bool:
        """Whether keyframes are measured on a worker thread (``config.overlap``, a field, and a
        motion model that allows it); after :meth:`start`."""
        return bool(self.config.overlap) and self.field is not None and self.motion.allows_overlap

    def land_pending(self, worker: CorrectionWorker, on_keyframe=None) -> None:
        """The measurement still in flight, if any, waited for and put in the graph (the end of
        an overlapped run)."""
        self._overlapped(worker).land_pending(on_keyframe)

    def _timing(self) -> CaptureTiming | None:
        """The capture timing the run compensates: the config's, else the field's (None: off)."""
        return resolve_capture_timing(self.field, given=self.config.timing, compensate=self.config.compensate_timing)[0]

    def _velocity(self, i: int) -> np.ndarray | None:
        """Body twist per second (GTSAM order) of the camera at frame i, by the motion model."""
        t = float(self.sequence.timestamps[i])
        dt = t - float(self.sequence.timestamps[i - 1]) if i >= 1 else 0.0
        return self.motion.twist(i, t, dt)

    def _update_isam(self, extra_step: bool = False, record: KeyframeRecord | None = None) -> None:
        t0 = time.perf_counter()
        self.graph.update(extra_step)
        # Until the run is placed in the map its graph holds every keyframe (it will be moved whole).
        cut = self.graph.bound(len(self.keyframe_indices)) if self.placed else None
        if cut is not None:  # the window moved: the stream forgets what left it
            oldest_frame = self.keyframe_indices[cut]
            for kept in (self.interval_odometry, self.measured_corrections):
                for frame in [frame for frame in kept if frame < oldest_frame]:
                    del kept[frame]
            if self.on_retire is not None:
                self._retire(cut)
        record = record or self._pending_record
        if record is not None:
            record.timings_s["isam"] = round(record.timings_s.get("isam", 0.0) + time.perf_counter() - t0, 5)

    def _retire(self, cut: int) -> None:
        """Keyframes before ``cut`` have left the graph with their poses fixed: the frames before
        the last of them have their final smoothed poses (each is chained from a fixed
        keyframe). Hand them to ``on_retire`` and forget them; the last fixed keyframe stays, the
        frames after it are chained from it at the end."""
        first, last_fixed = self._online.start, self.keyframe_indices[cut - 1]
        if last_fixed <= first:
            return
        fixed = {idx: self.graph.frozen[j] for j, idx in self.keyframe_indices.items() if j < cut}
        T_world_cam_est = chain_from_nearest_keyframe(fixed, self.motion.increments, last_fixed, start=first)
        stamps = np.asarray(self.sequence.timestamps[first:last_fixed], dtype=float)
        keyframes_gone = self.keyframe_indices.drop_before(self.keyframe_indices.first(lambda idx: idx >= last_fixed))
        records_gone = self.records.drop_before(self.records.first(lambda r: r.frame_index >= last_fixed))
        for j in [j for j in self.graph.frozen if j < self.keyframe_indices.start]:
            del self.graph.frozen[j]
        segment = RunResult(stamps, T_world_cam_est, np.stack(self.motion.T_world_cam_odom.drop_before(last_fixed)),
                            self._ground_truth(first, last_fixed), records_gone, keyframes_gone,
                            T_world_cam_online=np.stack(self._online.drop_before(last_fixed)),
                            increments=self.motion.increments.drop_before(last_fixed), first_frame=first)
        self.on_retire(segment)

    def _finish_keyframe(self) -> KeyframeRecord | None:
        j = len(self.keyframe_indices) - 1
        self.motion.keyframe_estimated(self.graph, j, float(self.sequence.timestamps[self.keyframe_indices[j]]))
        record, self._pending_record = self._pending_record, None
        if record is not None:
            self.records.append(record)
        return record

    def _trained_timestamps(self) -> np.ndarray:
        from nap3d_graph.fields import frames_seen_in_training

        return frames_seen_in_training(self.field, self.sequence) if self.field is not None else \
            np.zeros(len(self.sequence), dtype=bool)

    def _ground_truth(self, start: int, stop: int):
        """A function reading the sequence's ground truth of frames ``start:stop`` (None when
        it has none) when a result is asked for it, not before: the run never sees it."""
        sequence = self.sequence

        def read():
            T = sequence.T_world_cam_gt
            return None if T is None else np.asarray(T[start:stop])

        return read

    def _finish(self, n: int) -> RunResult:
        first = self._online.start  # frames before it were retired (on_retire)
        T_world_cam_gt = self._ground_truth(first, n)
        stamps = np.asarray(self.sequence.timestamps[first:n], dtype=float)
        if not len(self.keyframe_indices):  # stopped before the first keyframe: odometry is all there is
            T_world_cam_odom = np.stack(self.motion.T_world_cam_odom[:n])
            return RunResult(stamps, T_world_cam_odom, T_world_cam_odom, T_world_cam_gt, [], [], T_world_cam_online=T_world_cam_odom)
        accepted = {r.frame_index for r in self.records if r.accepted}
        estimate = self.graph.final_estimate(accepted)
        frozen = self.graph.frozen
        T_world_kf_by_frame = {idx: frozen[j] if j in frozen else pose3_to_T(estimate.atPose3(X(j)))
                               for j, idx in self.keyframe_indices.items()}
        T_world_cam_est = self.motion.smoothed(estimate, T_world_kf_by_frame, self.keyframe_indices, stamps)
        T_online = self.motion.causal(self._online, stamps)
        T_map = pose3_to_T(estimate.atPose3(M(0))) if self.config.use_anchor else None
        result = RunResult(stamps, T_world_cam_est, np.stack(self.motion.T_world_cam_odom[:n]), T_world_cam_gt,
                           list(self.records), list(self.keyframe_indices), T_map, T_world_cam_online=T_online,
                           gnc_outliers=list(self.graph.gnc_outliers), gnc_recovered=list(self.graph.gnc_recovered),
                           depth_scale=self.depth_scale.scale, interval_odometry=dict(self.interval_odometry),
                           corrections=dict(self.measured_corrections), increments=list(self.motion.increments[:n]),
                           first_frame=first)
        self.motion.finish(estimate, self.graph, accepted, self.keyframe_indices, result)
        if self.placement is not None:
            result.placement = self.placement.summary()
        return result

    # --- helpers -----------------------------------------------------------------------------

    def _render_intrinsics(self, intrinsics: Intrinsics) -> Intrinsics:
        """The render's camera: the frame's (``intrinsics``) at the configured render size."""
        w, h = self.config.render_width, self.config.render_height
        if w is None or h is None or (w, h) == (intrinsics.width, intrinsics.height):
            return intrinsics
        return intrinsics.scaled(w, h)
