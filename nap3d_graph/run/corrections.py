"""The graph half of a keyframe's correction: the depth-scale check, the chi-square gate
against the prediction, the factor (the run then solves); and a warning while the run goes when
corrections keep failing for one reason (:class:`~nap3d_graph.run.refusals.RefusalWatch`)."""

from __future__ import annotations

import time

import gtsam

from nap3d_graph.conventions import pose_error
from nap3d_graph.results import Correction
from nap3d_graph.run.records import KeyframeRecord
from nap3d_graph.run.refusals import RefusalWatch
from nap3d_graph.run.state import RunState

__all__ = ["CorrectionGate"]


class CorrectionGate:
    """Puts measured corrections into a run's graph (:class:`~nap3d_graph.run.state.RunState`:
    its graph, depth-scale and camera-model trackers and measurement stream), each checked by
    ``config`` (a :class:`~nap3d_graph.run.config.PipelineConfig`) and passed through
    ``correction_hook`` (``f(frame_index, Correction) -> Correction`` or None); the latest one is
    left in the state's ``last_correction`` / ``last_factor`` for a live caller."""

    def __init__(self, config, correction_hook=None):
        self.config, self.correction_hook = config, correction_hook
        self.refusals = RefusalWatch()

    def apply(self, state: RunState, record: KeyframeRecord, i: int, correction: Correction,
              T_field_cam_render) -> gtsam.NonlinearFactor | None:
        """Keyframe i's ``correction`` (measured against a render at ``T_field_cam_render``)
        gated; returns its factor when it passed and was added to the graph (the caller then
        solves), else None; ``record`` says what became of it."""
        factor = self._gate_and_add(state, record, i, correction, T_field_cam_render)
        self.refusals.observe(record)
        return factor

    def _checked(self, state: RunState, record: KeyframeRecord, i: int, correction: Correction) -> Correction:
        """The correction after the depth-scale check and the hook, kept in the stream."""
        record.intrinsics_model = state.intrinsics_model.observe(i, correction)
        if correction.success and self.config.depth_scale_check:
            correction = state.depth_scale.check(correction, record)
        if correction.success:
            state.stream.add_correction(i, correction.T_world_cam_corrected, correction.covariance)
        if self.correction_hook is not None:
            correction = self.correction_hook(i, correction)
        state.last_correction, state.last_factor = correction, None
        state.last_correction_frame = i  # which keyframe last_correction is (an observer checks)
        record.timings_s.update({k: round(v, 4) for k, v in correction.timings_s.items()})
        record.matches, record.inliers, record.iterations = (correction.num_matches, correction.num_inliers,
                                                             correction.iterations)
        return correction

    def _gate_and_add(self, state: RunState, record: KeyframeRecord, i: int, correction: Correction,
                      T_field_cam_render) -> gtsam.NonlinearFactor | None:
        correction = self._checked(state, record, i, correction)
        if not correction.success:
            record.reason = correction.reason
            return None
        record.correction_m, record.correction_deg = pose_error(correction.T_world_cam_corrected, T_field_cam_render)
        if not state.graph.has(record.key):
            record.reason = "keyframe left the graph window before its correction landed"
            return None
        t0 = time.perf_counter()
        factor, gate = state.graph.gated_correction(record.key, correction, i)
        record.timings_s["gate"] = round(time.perf_counter() - t0, 5)
        record.gate_d2 = gate.d2 if gate is not None else float("nan")
        if factor is None:
            # Gated out against a prediction that may itself be wrong: the final solve weighs it
            # again with everything else (KeyframeGraph.final_estimate).
            record.reason = gate.reason if gate is not None else "invalid covariance"
            return None
        state.last_factor = factor
        record.accepted = True
        return factor
