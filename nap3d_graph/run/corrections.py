"""The graph half of a keyframe's correction: the depth-scale check, the chi-square gate
against the prediction, the factor, the solve; and a warning while the run goes when
corrections keep failing for one reason (:class:`~nap3d_graph.run.refusals.RefusalWatch`)."""

from __future__ import annotations

import time

from nap3d_graph.conventions import pose_error
from nap3d_graph.results import Correction
from nap3d_graph.run.records import KeyframeRecord
from nap3d_graph.run.refusals import RefusalWatch

__all__ = ["CorrectionGate"]


class CorrectionGate:
    """Puts measured corrections into ``run``'s graph (a
    :class:`~nap3d_graph.run.pipeline.Pipeline`: its graph, depth-scale and camera-model
    trackers, measurement stream and ``correction_hook``); the latest one is left in
    ``run.last_correction`` / ``run.last_factor`` for a live caller."""

    def __init__(self, run):
        self.run = run
        self.refusals = RefusalWatch()

    def apply(self, record: KeyframeRecord, i: int, correction: Correction, T_field_cam_render) -> None:
        """Keyframe i's ``correction`` (measured against a render at ``T_field_cam_render``)
        gated and, when it passes, added and solved; ``record`` says what became of it."""
        self._gate_and_add(record, i, correction, T_field_cam_render)
        self.refusals.observe(record)

    def _checked(self, record: KeyframeRecord, i: int, correction: Correction) -> Correction:
        """The correction after the depth-scale check and the hook, kept in the stream."""
        run = self.run
        record.intrinsics_model = run.intrinsics_model.observe(i, correction)
        if correction.success and run.config.depth_scale_check:
            correction = run.depth_scale.check(correction, record)
        if correction.success:
            run.stream.add_correction(i, correction.T_world_cam_corrected, correction.covariance)
        if run.correction_hook is not None:
            correction = run.correction_hook(i, correction)
        run.last_correction, run.last_factor = correction, None
        run.last_correction_frame = i  # which keyframe last_correction is (an observer checks)
        record.timings_s.update({k: round(v, 4) for k, v in correction.timings_s.items()})
        record.matches, record.inliers, record.iterations = (correction.num_matches, correction.num_inliers,
                                                             correction.iterations)
        return correction

    def _gate_and_add(self, record: KeyframeRecord, i: int, correction: Correction, T_field_cam_render) -> None:
        run = self.run
        correction = self._checked(record, i, correction)
        if not correction.success:
            record.reason = correction.reason
            return
        record.correction_m, record.correction_deg = pose_error(correction.T_world_cam_corrected, T_field_cam_render)
        if not run.graph.has(record.key):
            record.reason = "keyframe left the graph window before its correction landed"
            return
        t0 = time.perf_counter()
        factor, gate = run.graph.gated_correction(record.key, correction, i)
        record.timings_s["gate"] = round(time.perf_counter() - t0, 5)
        record.gate_d2 = gate.d2 if gate is not None else float("nan")
        if factor is None:
            # Gated out against a prediction that may itself be wrong: the final solve weighs it
            # again with everything else (KeyframeGraph.final_estimate).
            record.reason = gate.reason if gate is not None else "invalid covariance"
            return
        run.last_factor = factor
        record.accepted = True
        # Two iSAM2 steps: a correction can move the pose a long way from its linearisation.
        run.update_graph(extra_step=True, record=record)
