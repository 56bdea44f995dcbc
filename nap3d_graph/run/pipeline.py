"""The drift-correction run: drifting odometry in an iSAM2 graph, NAP3D corrections as factors.

Graph: one ``Pose3`` node ``X(k)`` per keyframe (``T_world_cam``, OpenCV camera), a prior on
``X(0)``, odometry ``BetweenFactorPose3`` between consecutive keyframes (the frame-to-frame
increments composed, covariance propagated), and at each keyframe the NAP3D correction as a
robust ``PriorFactorPose3`` (or, with a map anchor, a between factor from ``M(0)``, the
field's frame in the world). Each keyframe first enters iSAM2 with its odometry factor
alone (the prediction); a correction then enters only if it passes the chi-square gate
against that prediction: the joint marginal covariance of the factor's variables (the pose,
and the anchor when there is one) carried through the factor's Jacobians, plus the
correction's own covariance. Other frames are chained from a keyframe (``trajectory``).

``Pipeline.run()`` reads as its steps; no failed correction stops a run or reaches the graph.
"""

from __future__ import annotations

import logging
import time

import gtsam
import numpy as np
from gtsam.symbol_shorthand import M, X

from nap3d_graph.camera import Intrinsics
from nap3d_graph.conventions import T_to_pose3, compose_covariance, inv_T, pose3_to_T, pose_error
from nap3d_graph.factors import (
    anchor_prior_factor,
    chi2_gate_isam2,
    nap3d_anchor_factor,
    nap3d_prior_factor,
    odometry_factor,
    pose_prior_factor,
)
from nap3d_graph.results import Correction
from nap3d_graph.run.config import PipelineConfig, with_field_error
from nap3d_graph.run.keyframe import CorrectionWorker, DepthScaleTracker, KeyframeJob, measure_keyframe
from nap3d_graph.run.records import KeyframeRecord, RunResult
from nap3d_graph.run.solve import gnc_solve, isam2_params, rebuilt_isam2
from nap3d_graph.run.trajectory import chain_from_nearest_keyframe

__all__ = ["Pipeline"]

log = logging.getLogger(__name__)



class Pipeline:
    """One drift-correction run over a sequence.

    sequence: ``len``, ``seq[i] -> RGBDFrame``, ``timestamps``, ``T_world_cam_gt`` (or None).
    field: anything with ``render(T_world_cam, intrinsics)`` (None: odometry only).
    odometry: an odometry source (``initial_pose()``, ``increment(i, frame)``).
    correction_hook: optional ``f(frame_index, Correction) -> Correction`` applied before the
        gate (tests use it to inject a wrong correction).
    """

    #: Whether this run's graph can be bounded (``PipelineConfig.graph_window``).
    supports_graph_window = True

    def __init__(self, sequence, field, odometry, config: PipelineConfig | None = None, correction_hook=None):
        self.sequence = sequence
        self.field = field
        self.odometry = odometry
        # The field's own error, as it measured it when it was built, unless told otherwise.
        self.config = with_field_error(config or PipelineConfig(), field)
        self.correction_hook = correction_hook
        if self.config.graph_window and (self.config.use_anchor or not self.supports_graph_window):
            raise ValueError("graph_window (a bounded graph) does not apply with the map anchor or the IMU path")

    # --- the run, as its steps ---------------------------------------------------------

    def run(self, on_keyframe=None, stop=None) -> RunResult:
        """Run over the sequence. ``on_keyframe(record)`` hears about each keyframe as soon as
        it is done (a results writer appends it); ``stop()`` is asked before each frame and,
        when it says so, the run ends there with what it has (``RunResult.partial``)."""
        from tqdm import tqdm

        t_start = time.perf_counter()
        self._start()
        n = len(self.sequence) if self.config.max_frames is None else min(len(self.sequence), self.config.max_frames)
        done, partial = n, False
        worker = CorrectionWorker(self.field, self.config) if self._overlapping() else None
        try:
            for i in tqdm(range(n), desc="run", unit="frame", disable=not self.config.progress):
                if stop is not None and stop():
                    done, partial = i, True
                    break
                self.step(i, worker, on_keyframe)
            if worker is not None and worker.busy:
                self._land(worker, on_keyframe)
        finally:
            if worker is not None:
                worker.close()
        result = self._finish(max(done, 1))
        result.partial = partial
        result.wall_time_s = time.perf_counter() - t_start
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
        :class:`nap3d_graph.run.live.DriftCorrector` calls it a frame at a time."""
        frame = self._read_frame(i) if self._odometry_needs_frames() or self._wants_sharpness(i) else None
        if i > 0:
            self._propagate_odometry(i, frame)
        keyframe = self._is_keyframe(i, frame)
        if worker is not None and (worker.ready() or (worker.busy and keyframe)):
            self._land(worker, on_keyframe)  # a late correction enters the graph now
        if keyframe:
            self._add_keyframe(i)
            if frame is None and self.field is not None:  # without a field a keyframe needs no image
                frame = self._read_frame(i)
            if worker is not None:
                self._launch(worker, i, frame, on_keyframe)
            else:
                self._correct_keyframe(i, frame)
                record = self._finish_keyframe()
                if on_keyframe is not None and record is not None:
                    on_keyframe(record)
        self._online.append(self.T_last_kf_est @ self.T_since_kf)

    @property
    def current_estimate(self) -> np.ndarray:
        """(4, 4) the latest frame's pose as known now (the causal estimate)."""
        return np.array(self._online[-1])

    # --- steps -----------------------------------------------------------------------------

    def _start(self) -> None:
        self.isam = gtsam.ISAM2(isam2_params(self.config.relinearize_threshold))
        self.new_factors = gtsam.NonlinearFactorGraph()
        self.new_values = gtsam.Values()
        # Everything iSAM2 was given, so that it can be rebuilt (see _update_isam).
        self._graph_all = gtsam.NonlinearFactorGraph()
        self._values_all = gtsam.Values()
        self.T_odom = [self.odometry.initial_pose()]
        self.increments: list[np.ndarray] = [np.eye(4)]
        self.T_since_kf = np.eye(4)
        self.cov_since_kf = np.zeros((6, 6))
        self.dt_since_kf = 0.0
        self.keyframe_indices: list[int] = []
        self.records: list[KeyframeRecord] = []
        self.T_last_kf_est: np.ndarray = self.T_odom[0]  # frame 0 is always a keyframe: set there
        self.T_pred = self.T_odom[0]
        self._pending_record: KeyframeRecord | None = None
        self._online: list[np.ndarray] = []  # each frame's pose as known at that frame (causal)
        # The latest keyframe's correction and factor (a live caller reads them).
        self.last_correction: Correction | None = None
        self.last_factor: gtsam.NonlinearFactor | None = None
        self._streak: tuple[str | None, int] = (None, 0)  # the current run of refusals for one reason
        self.last_correction_frame = -1
        self._trained = self._trained_timestamps()
        self._due_since: int | None = None  # the frame a keyframe fell due at, while its window is open
        self._due_why = ""
        self._sharpness_since_kf: list[float] = []
        self._odometry_doubted = False
        self.factor_log: list[tuple[gtsam.NonlinearFactor, bool, int]] = []  # (factor, is NAP3D, keyframe)
        self._frozen: dict[int, np.ndarray] = {}  # keyframes marginalised out of the window: their poses
        self._first_live = 0  # the oldest keyframe still in iSAM2
        timing = self._timing() or {}
        self.depth_scale = DepthScaleTracker(float(timing.get("depth_scale", 1.0)), self.config)
        # The measurement stream, for estimators compared on the same inputs
        # (nap3d_graph.estimators): each keyframe interval's odometry as its factor has it,
        # and every successful correction (gated out or not) with its covariance.
        self.interval_odometry: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.measured_corrections: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        if self._anchored():
            factor, T_world_map0 = self._anchor_prior()
            self._add_factor(factor)
            self.new_values.insert(M(0), T_to_pose3(T_world_map0))

    def _anchored(self) -> bool:
        """Whether the graph has the field's frame as a variable ``M(0)`` (``T_world_map``):
        the NAP3D corrections then tie a pose to it (``--anchor``; the IMU path's gravity frame)."""
        return self.config.use_anchor

    def _anchor_prior(self):
        """The prior on ``M(0)`` and its starting value (4, 4): the field's frame is the world,
        up to the anchor's sigmas."""
        return anchor_prior_factor(M(0), np.eye(4), self.config.anchor_rot_sigma_rad,
                                   self.config.anchor_trans_sigma_m), np.eye(4)

    def _odometry_needs_frames(self) -> bool:
        return bool(getattr(self.odometry, "needs_frames", False))

    def _read_frame(self, i: int):
        """Frame i, or None when it cannot be read (the reason is logged and recorded)."""
        from nap3d_graph.datasets import DatasetError

        try:
            frame = self.sequence[i]
        except (DatasetError, OSError) as exc:
            log.warning("frame %d unreadable: %s", i, exc)
            self._frame_error = str(exc)
            return None
        if i == 0 and hasattr(self.odometry, "prime"):
            self.odometry.prime(frame)
        return frame

    def _propagate_odometry(self, i: int, frame) -> None:
        inc = self.odometry.increment(i, frame)
        self._odometry_doubted = self._odometry_doubted or not getattr(inc, "ok", True)
        self.increments.append(inc.T_prev_cur)
        self.T_odom.append(self.T_odom[-1] @ inc.T_prev_cur)
        self.cov_since_kf = compose_covariance(self.cov_since_kf, inc.T_prev_cur, inc.covariance)
        self.T_since_kf = self.T_since_kf @ inc.T_prev_cur
        self.dt_since_kf += float(self.sequence.timestamps[i] - self.sequence.timestamps[i - 1])

    def _keyframe_due(self, i: int) -> str:
        """Why frame i is due to be a keyframe ("" when it is not)."""
        if not self.keyframe_indices:
            return "first" if i == 0 else ""
        if self.config.keyframe_on_doubt and self._odometry_doubted:
            return "doubt"
        last = self.keyframe_indices[-1]
        if i - last >= self.config.keyframe_every:
            return "every"
        moved_m, turned_deg = pose_error(self.T_since_kf, np.eye(4))
        if self.config.keyframe_distance_m > 0 and moved_m >= self.config.keyframe_distance_m:
            return "distance"
        return "angle" if self.config.keyframe_angle_deg > 0 and turned_deg >= self.config.keyframe_angle_deg else ""

    def _wants_sharpness(self, i: int) -> bool:
        """Whether frame i must be read for its sharpness: with a keyframe window, every frame
        is (the frames since the last keyframe are the reference a due one is judged by)."""
        return self.config.keyframe_window > 1

    def _is_keyframe(self, i: int, frame=None) -> bool:
        """Frame i is a keyframe: it is due (``_keyframe_due``) and, with a keyframe window,
        sharp enough or the window's last frame. Records why on ``self._keyframe_why``."""
        if self._due_since is None:
            why = self._keyframe_due(i)
            if not why:
                self._note_sharpness(frame)
                return False
            self._due_since, self._due_why = i, why
        sharpness = self._note_sharpness(frame)
        waited = i - self._due_since
        window = self.config.keyframe_window
        if window > 1 and waited < window - 1 and self._due_why != "first":
            recent = self._sharpness_since_kf[:-1]
            reference = float(np.median(recent)) if recent else sharpness
            if not sharpness >= self.config.keyframe_sharpness_fraction * reference:
                return False  # blurred: a sharper one may follow within the window
        self._keyframe_why = (self._due_why, sharpness, waited)
        self._due_since = None
        return True

    def _keyframe_record(self, i: int, key: int, **extra) -> KeyframeRecord:
        """The record of keyframe i (why it is one, its sharpness); starts the next interval."""
        why, sharp, waited = getattr(self, "_keyframe_why", ("first", float("nan"), 0))
        self._sharpness_since_kf = []
        self._odometry_doubted = False
        trained = bool(self._trained[i]) if i < len(self._trained) else False  # a live run's frames: unknown
        return KeyframeRecord(i, float(self.sequence.timestamps[i]), key, trained_frame=trained,
                              why=why, sharpness=sharp, postponed=waited, **extra)

    def _note_sharpness(self, frame) -> float:
        """The frame's sharpness (NaN without a frame or a window), kept for the reference."""
        if frame is None or self.config.keyframe_window <= 1:
            return float("nan")
        from nap3d_graph.camera import sharpness

        value = sharpness(frame.rgb)
        self._sharpness_since_kf.append(value)
        return value

    def _add_keyframe(self, i: int) -> None:
        """The keyframe's pose enters iSAM2 with its odometry factor: that is the prediction."""
        j = len(self.keyframe_indices)
        self.keyframe_indices.append(i)
        if j == 0:
            T0 = self.T_odom[0]
            self._add_factor(pose_prior_factor(X(0), T0, rot_sigma_rad=self.config.prior_rot_sigma_rad,
                                               trans_sigma_m=self.config.prior_trans_sigma_m))
            self.new_values.insert(X(0), T_to_pose3(T0))
            self.T_pred = T0
        else:
            cov = self.cov_since_kf + self.config.drift_covariance(self.T_since_kf, self.dt_since_kf)
            self._add_factor(odometry_factor(X(j - 1), X(j), self.T_since_kf, cov))
            self.interval_odometry[i] = (self.T_since_kf.copy(), cov.copy())
            self.T_pred = self.T_last_kf_est @ self.T_since_kf
            self.new_values.insert(X(j), T_to_pose3(self.T_pred))
        self.T_since_kf = np.eye(4)
        self.cov_since_kf = np.zeros((6, 6))
        self.dt_since_kf = 0.0
        self._pending_record = self._keyframe_record(i, X(j))
        self._update_isam()

    def _correct_keyframe(self, i: int, frame) -> None:
        """Measure the pending keyframe's correction and give it to the graph, now."""
        job = self._job(i, frame)
        if job is not None:
            self._apply_correction(self._pending(), i, measure_keyframe(job, self.field, self.config), job.T_render)

    def _pending(self) -> KeyframeRecord:
        """The record of the keyframe being measured (between ``_add_keyframe`` and
        ``_finish_keyframe`` / ``_launch``)."""
        if self._pending_record is None:
            raise RuntimeError("no keyframe is pending: _add_keyframe comes first")
        return self._pending_record

    def _job(self, i: int, frame) -> KeyframeJob | None:
        """What measuring keyframe i needs, or None (the reason recorded) when it cannot be."""
        record = self._pending()
        if self.field is None:
            record.reason = "no field"
            return None
        if frame is None:
            record.reason = f"frame unreadable: {getattr(self, '_frame_error', 'unknown error')}"
            return None
        T_render = self.T_pred
        if self._anchored():
            T_render = inv_T(self._anchor_estimate()) @ self.T_pred  # the field's frame
        return KeyframeJob(i, frame, T_render, self._velocity(i), self._timing(), self.depth_scale.scale,
                           self._render_intrinsics(frame))

    def _launch(self, worker: CorrectionWorker, i: int, frame, on_keyframe) -> None:
        """Overlapped run: hand keyframe i's measurement to the worker and go on; until it
        lands, the keyframe is known by its prediction."""
        record, job = self._pending(), self._job(i, frame)
        self._pending_record = None
        self.T_last_kf_est = pose3_to_T(self.isam.calculateEstimatePose3(record.key))
        if job is None:  # nothing to measure: the keyframe is done (its reason recorded)
            self.records.append(record)
            if on_keyframe is not None:
                on_keyframe(record)
            return
        worker.submit((record, job.T_render), job)

    def _land(self, worker: CorrectionWorker, on_keyframe) -> None:
        """Overlapped run: the measurement in flight (waited for if need be) enters the graph
        at its keyframe, and the latest keyframe's estimate is refreshed."""
        (record, T_render), correction, waited_s = worker.take()
        self._apply_correction(record, record.frame_index, correction, T_render)
        record.timings_s["wait"] = round(waited_s, 5)
        record.timings_s["landed_frame"] = len(self.T_odom) - 1
        self.T_last_kf_est = pose3_to_T(self.isam.calculateEstimatePose3(X(len(self.keyframe_indices) - 1)))
        self.records.append(record)
        if on_keyframe is not None:
            on_keyframe(record)

    def _apply_correction(self, record: KeyframeRecord, i: int, correction: Correction, T_render) -> None:
        """The graph half (:meth:`_gate_and_add`), and a warning while the run goes when
        corrections keep failing for one reason."""
        self._gate_and_add(record, i, correction, T_render)
        self._watch_refusals(record)

    #: Consecutive keyframes refused for one reason before the run says so.
    REFUSAL_STREAK = 5

    def _watch_refusals(self, record: KeyframeRecord) -> None:
        """Warn (once per streak) when the last REFUSAL_STREAK keyframes were all refused for
        the same reason: the run then goes on on its odometry alone, and the user should know
        it now, not from the summary."""
        from nap3d_graph.run.output import refusal_hint_for, refusal_kind

        if record.accepted:
            self._streak = (None, 0)
            return
        kind = refusal_kind(record.reason)
        previous, count = self._streak
        count = count + 1 if kind == previous else 1
        self._streak = (kind, count)
        if count == self.REFUSAL_STREAK:
            log.warning("the last %d keyframes (to frame %d) were all refused for '%s'; the run goes on on its "
                        "odometry alone until corrections land again. %s", count, record.frame_index, kind,
                        refusal_hint_for(kind))

    def _gate_and_add(self, record: KeyframeRecord, i: int, correction: Correction, T_render) -> None:
        """The graph half: depth-scale check, gate, factor (see the module docstring)."""
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
        record.correction_m, record.correction_deg = pose_error(correction.T_world_cam_corrected, T_render)
        if not self.isam.valueExists(record.key):
            record.reason = "keyframe left the graph window before its correction landed"
            return
        t0 = time.perf_counter()
        factor, gate = self._gated_factor(record.key, correction)
        record.timings_s["gate"] = round(time.perf_counter() - t0, 5)
        record.gate_d2 = gate.d2 if gate is not None else float("nan")
        if factor is None:
            record.reason = gate.reason if gate is not None else "invalid covariance"
            if gate is not None:
                # Gated out against a prediction that may itself be wrong: the final solve
                # weighs it again with everything else (see _gnc_solve).
                self.factor_log.append((self._gaussian_twin(record.key, correction), True, i))
            return
        self.new_factors.add(factor)
        self.last_factor = factor
        self.factor_log.append((self._gaussian_twin(record.key, correction), True, i))
        record.accepted = True
        # Two iSAM2 steps: a correction can move the pose a long way from its linearisation.
        self._update_isam(extra_step=True, record=record)

    def _overlapping(self) -> bool:
        return bool(self.config.overlap) and self.field is not None

    def _timing(self) -> dict | None:
        if not self.config.compensate_timing:
            return None
        if self.config.timing is not None:
            return self.config.timing
        return (getattr(self.field, "meta", None) or {}).get("timing")

    def _velocity(self, i: int) -> np.ndarray | None:
        """Body twist per second (GTSAM order) of the odometry's last step before frame i."""
        from nap3d_graph.conventions import log_se3

        if i < 1:
            return None
        dt = float(self.sequence.timestamps[i] - self.sequence.timestamps[i - 1])
        return log_se3(self.increments[i]) / dt if dt > 0 else None

    def _add_factor(self, factor) -> None:
        self.new_factors.add(factor)
        self.factor_log.append((factor, False, -1))

    def _gaussian_twin(self, key: int, correction: Correction):
        """The NAP3D factor without its robust kernel, for the final GNC solve."""
        if self._anchored():
            return nap3d_anchor_factor(key, M(0), None, correction, robust=None)
        return nap3d_prior_factor(key, None, correction, robust=None)

    def _gated_factor(self, key: int, correction: Correction):
        """The NAP3D factor and its gate result; ``(None, gate)`` when gated out.

        The gate is the innovation test against iSAM2's prediction: the joint marginal of
        the factor's variables through its Jacobians (``chi2_gate_isam2``)."""
        try:
            if self._anchored():
                factor = nap3d_anchor_factor(key, M(0), None, correction, robust=self.config.robust)
            else:
                factor = nap3d_prior_factor(key, None, correction, robust=self.config.robust)
        except ValueError as exc:  # a covariance GTSAM cannot use: skip, never corrupt the graph
            log.warning("correction at %s not usable: %s", gtsam.DefaultKeyFormatter(key), exc)
            return None, None
        gate = chi2_gate_isam2(factor, self.isam, p=self.config.gate_p)
        return (factor if gate.accepted else None), gate

    def _update_isam(self, extra_step: bool = False, record: KeyframeRecord | None = None) -> None:
        t0 = time.perf_counter()
        self._graph_all.push_back(self.new_factors)
        self._values_all.insert(self.new_values)
        try:
            self.isam.update(self.new_factors, self.new_values)
            if extra_step:
                self.isam.update()
        except RuntimeError as exc:  # gtsam's IndeterminateSystemException, thrown mid-update
            self._rebuild_isam(str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__)
        # Fresh containers every update: iSAM2 keeps what it was given.
        self.new_factors = gtsam.NonlinearFactorGraph()
        self.new_values = gtsam.Values()
        self._bound_graph()
        record = record or self._pending_record
        if record is not None:
            record.timings_s["isam"] = round(record.timings_s.get("isam", 0.0) + time.perf_counter() - t0, 5)

    def _bound_graph(self) -> None:
        """With ``graph_window`` N: once more than 1.5 N keyframes are live, marginalise the
        oldest down to N and fix their poses (see :class:`PipelineConfig`). What is kept for a
        rebuild and for the final solve becomes iSAM2's own factors, the marginal included; the
        final solve is then Levenberg-Marquardt on them (GNC takes no marginal)."""
        window = self.config.graph_window
        n = len(self.keyframe_indices)
        if not window or n - self._first_live <= window + window // 2:
            return
        cut = n - window
        # Poses about to be fixed: relinearise everything first (iSAM2 relinearises lazily, past
        # a threshold, and the final solve will not polish these any more), then solve fully.
        try:
            self.isam.update(force_relinearize=True)
            self.isam.update(force_relinearize=True)
        except RuntimeError as exc:
            log.debug("relinearisation before the window moved failed (%s)", exc)
            return
        best = self.isam.calculateBestEstimate()
        frozen = {j: pose3_to_T(best.atPose3(X(j))) for j in range(self._first_live, cut)}
        leaving = gtsam.KeyList()
        for j in frozen:
            leaving.push_back(X(j))
        try:
            self.isam.marginalizeLeaves(leaving)
        except RuntimeError as exc:  # not leaves of the Bayes tree: keep them, try again later
            log.debug("keyframes %d-%d not marginalised yet (%s)", self._first_live, cut - 1, exc)
            return
        self._frozen.update(frozen)
        self._first_live = cut
        gone = {X(j) for j in frozen}
        self.factor_log = [entry for entry in self.factor_log if not gone & set(entry[0].keys())]
        factors = self.isam.getFactorsUnsafe()  # marginalised factors leave empty slots
        self._graph_all = gtsam.NonlinearFactorGraph()
        for k in range(factors.size()):
            if (factor := factors.at(k)) is not None:
                self._graph_all.add(factor)
        self._values_all = self.isam.calculateEstimate()
        oldest_frame = self.keyframe_indices[cut]
        for kept in (self.interval_odometry, self.measured_corrections):
            for i in [i for i in kept if i < oldest_frame]:
                del kept[i]

    def _rebuild_isam(self, why: str) -> None:
        """After a failed iSAM2 update (its state is then undefined): a fresh iSAM2 from
        everything it was given (:func:`~nap3d_graph.run.solve.rebuilt_isam2`)."""
        log.warning("iSAM2 update failed (%s); rebuilding it from the %d factors so far", why, self._graph_all.size())
        self.isam = rebuilt_isam2(self.isam, self._graph_all, self._values_all, self.config.relinearize_threshold)
        self.isam_rebuilds = getattr(self, "isam_rebuilds", 0) + 1

    def _finish_keyframe(self) -> KeyframeRecord | None:
        key = X(len(self.keyframe_indices) - 1)
        self.T_last_kf_est = pose3_to_T(self.isam.calculateEstimatePose3(key))
        record, self._pending_record = self._pending_record, None
        if record is not None:
            self.records.append(record)
        return record

    def _trained_timestamps(self) -> np.ndarray:
        from nap3d_graph.fields import frames_seen_in_training

        return frames_seen_in_training(self.field, self.sequence) if self.field is not None else \
            np.zeros(len(self.sequence), dtype=bool)

    def _finish(self, n: int) -> RunResult:
        T_gt = None if self.sequence.T_world_cam_gt is None else np.asarray(self.sequence.T_world_cam_gt[:n])
        stamps = np.asarray(self.sequence.timestamps[:n], dtype=float)
        if not self.keyframe_indices:  # stopped before the first keyframe: odometry is all there is
            T_odom = np.stack(self.T_odom[:n])
            return RunResult(stamps, T_odom, T_odom, T_gt, [], [], T_world_cam_online=T_odom)
        estimate = self._final_estimate()
        T_kf = {idx: self._frozen[j] if j in self._frozen else pose3_to_T(estimate.atPose3(X(j)))
                for j, idx in enumerate(self.keyframe_indices)}
        T_est = self._chain_between_keyframes(T_kf, n)
        T_online = self._chain_forward(n)
        T_map = pose3_to_T(estimate.atPose3(M(0))) if self.config.use_anchor else None
        return RunResult(stamps, T_est, np.stack(self.T_odom[:n]), T_gt, self.records, list(self.keyframe_indices), T_map,
                         T_world_cam_online=T_online, gnc_outliers=list(getattr(self, "gnc_outliers", [])),
                         gnc_recovered=list(getattr(self, "gnc_recovered", [])), depth_scale=self.depth_scale.scale,
                         interval_odometry=dict(self.interval_odometry), corrections=dict(self.measured_corrections),
                         increments=list(self.increments[:n]))

    # --- helpers -----------------------------------------------------------------------------

    def _final_estimate(self) -> gtsam.Values:
        """iSAM2's estimate polished by a batch Levenberg-Marquardt on the same factors: iSAM2
        relinearises lazily (every few updates, past a threshold), the written trajectory
        should be the converged optimum."""
        estimate = self.isam.calculateEstimate()
        nap3d = [k for k, (_, is_nap3d, _) in enumerate(self.factor_log) if is_nap3d]
        try:
            # GNC needs every factor with a noise model; a window's marginal has none (the window's
            # own robust factors then decide, with Levenberg-Marquardt).
            if self.config.final_gnc and nap3d and not self._frozen:
                return self._gnc_solve(estimate, nap3d)
            return gtsam.LevenbergMarquardtOptimizer(self._graph_all, estimate).optimize()
        except RuntimeError as exc:  # keep iSAM2's answer rather than lose the run
            log.warning("final batch optimisation failed (%s); writing the iSAM2 estimate", exc)
            return estimate

    def _gnc_solve(self, estimate: gtsam.Values, nap3d: list[int]) -> gtsam.Values:
        """Graduated non-convexity (TLS) over every NAP3D correction, those the gate accepted
        and those it refused (the prediction it judged them by may have been wrong: after a
        wrong correction slipped in, the good ones that follow disagree with it); the odometry
        and the priors are known inliers. Accepted corrections it weighs out are recorded in
        ``RunResult.gnc_outliers``, refused ones it takes back in ``gnc_recovered``."""
        result, weights = gnc_solve([f for f, _, _ in self.factor_log], estimate, nap3d, self.config.gnc_p)
        accepted = {r.frame_index for r in self.records if r.accepted}
        self.gnc_outliers = [self.factor_log[k][2] for k in nap3d if weights[k] < 0.5
                             and self.factor_log[k][2] in accepted]
        self.gnc_recovered = [self.factor_log[k][2] for k in nap3d if weights[k] >= 0.5
                              and self.factor_log[k][2] not in accepted]
        if self.gnc_outliers or self.gnc_recovered:
            log.info("final solve: %d accepted corrections weighed out (frames %s), %d refused ones taken back "
                     "(frames %s)", len(self.gnc_outliers), self.gnc_outliers[:10], len(self.gnc_recovered),
                     self.gnc_recovered[:10])
        return result

    def _chain_between_keyframes(self, T_kf: dict[int, np.ndarray], n: int) -> np.ndarray:
        """Every frame's pose from the keyframes' (the IMU path predicts with the IMU instead)."""
        return chain_from_nearest_keyframe(T_kf, self.increments, n)

    def _chain_forward(self, n: int) -> np.ndarray:
        """The causal poses (n, 4, 4): each frame's as the run knew it at that frame (the latest
        keyframe's estimate then, chained with the odometry since)."""
        return np.stack(self._online[:n])

    def _render_intrinsics(self, frame) -> Intrinsics:
        w, h = self.config.render_width, self.config.render_height
        if w is None or h is None or (w, h) == (frame.intrinsics.width, frame.intrinsics.height):
            return frame.intrinsics
        return frame.intrinsics.scaled(w, h)

    def _anchor_estimate(self) -> np.ndarray:
        if self.isam.valueExists(M(0)):
            return pose3_to_T(self.isam.calculateEstimatePose3(M(0)))
        return np.eye(4)
