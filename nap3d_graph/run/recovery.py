"""A run in a map finding where it is: at its start (it began anywhere in the map, in a
provisional frame) and again when it is lost (keyframes refused in a row).

:class:`MapRecovery` drives a run's :class:`~nap3d_graph.mapping.start.MapPlacement`: each
keyframe while the run is not placed (or while a recovery waits) relocalises in the map or
confirms the pending candidate; a confirmed candidate enters the graph past the gate, which
would compare it with the prediction that is lost, and at the start everything so far moves
into the map's frame with it.
"""

from __future__ import annotations

import logging

import numpy as np

from nap3d_graph.conventions import pose_error
from nap3d_graph.mapping.start import MapPlacement, Measured
from nap3d_graph.nap3d.keyframe import measure_keyframe
from nap3d_graph.results import Alignment, Correction
from nap3d_graph.run.jobs import KeyframeJobs
from nap3d_graph.run.records import KeyframeRecord
from nap3d_graph.run.state import RunState

__all__ = ["MapRecovery"]

log = logging.getLogger(__name__)


class MapRecovery:
    """Placement and recovery of a run in the map of ``placement`` (None: the run has no map;
    nothing to do), measuring with ``field`` and ``jobs`` (the run's
    :class:`~nap3d_graph.run.jobs.KeyframeJobs`) as ``config`` says; each call takes the run's
    state (:class:`~nap3d_graph.run.state.RunState`: its graph, motion model, causal poses and
    prediction) for its length. ``recoveries``: each relocalisation tried after refusals, and
    each recovery (metrics.json's record)."""

    def __init__(self, placement: MapPlacement | None, field, config, jobs: KeyframeJobs):
        self.placement, self.field, self.config, self.jobs = placement, field, config, jobs
        self.recoveries: list[dict] = []
        self.refused_in_a_row = 0

    def placing(self) -> bool:
        """Whether this keyframe goes to the placement rather than to a correction: the run is
        not placed yet, or a recovery waits for its confirmation."""
        return self.placement is not None and (not self.placement.placed or self.placement.candidate is not None)

    def recover_if_lost(self, state: RunState, record: KeyframeRecord, i: int, frame) -> None:
        """After ``relocalise_after`` keyframes refused in a row (the estimate drifted off the
        map, or the odometry lost track), relocalise keyframe i in the map: a verified
        relocalisation becomes a candidate that the next keyframes confirm
        (:meth:`place_keyframe`)."""
        self.refused_in_a_row = 0 if record.accepted else self.refused_in_a_row + 1
        after, placement = self.config.relocalise_after, self.placement
        if (placement is None or frame is None or not after or self.refused_in_a_row < after
                or state.anchored):
            return
        found = placement.propose(i, record.key, frame, state.T_world_kf_pred, self.jobs.velocity(state, i))
        entry = {"frame": int(i), "step": "relocalise", "refused_in_a_row": self.refused_in_a_row,
                 "found": found is not None, "seconds": placement.events[-1]["seconds"]}
        if found is None:  # tried again at the next keyframe
            entry["reason"] = placement.events[-1].get("reason", "")
        else:
            self.refused_in_a_row = 0
            if placement.settings.confirmations == 0:
                self._place(state, record, i)
        self.recoveries.append(entry)

    def place_keyframe(self, state: RunState, record: KeyframeRecord, i: int, frame) -> None:
        """Keyframe i while the run is not placed in the map (or a recovery waits): it confirms
        the pending candidate (rendered where the candidate puts it), or relocalises afresh.
        Nothing enters the graph until a candidate is confirmed."""
        placement = self.placement
        assert placement is not None
        if frame is None or self.field is None:
            record.reason = "no frame to relocalise" if frame is None else "no field"
            return
        if placement.candidate is not None and self._confirm(state, record, i, frame, lost=placement.placed):
            return
        found = placement.propose(i, record.key, frame, state.T_world_kf_pred, self.jobs.velocity(state, i))
        if found is not None and placement.settings.confirmations == 0:
            self._place(state, record, i)
            return
        record.reason = ("not yet placed in the map: relocalised, to be confirmed by the next keyframe" if found
                         else f"not yet placed in the map: {placement.events[-1].get('reason', 'not found')}")

    def _confirm(self, state: RunState, record: KeyframeRecord, i: int, frame, lost: bool) -> bool:
        """Keyframe i measured where the pending candidate puts it: True when that settles the
        keyframe (confirmed and placed, agreeing so far, not measured while the candidate waits,
        refuted while recovering, or not measurable), False when the candidate was refuted and the run relocalises afresh.
        ``lost``: a recovery, not the start."""
        placement = self.placement
        assert placement is not None
        T_map_cam_pred = placement.predicted(state.T_world_kf_pred)
        job = self.jobs.job(state, record, i, frame, T_field_cam_render=T_map_cam_pred)
        if job is None:
            return True
        correction = measure_keyframe(job, self.field, self.config)
        record.matches, record.inliers, record.iterations = (correction.num_matches, correction.num_inliers,
                                                             correction.iterations)
        verdict = placement.confirm(i, record.key, correction, T_map_cam_pred, frame)
        if verdict == "confirmed":
            self._place(state, record, i)
        elif verdict == "agrees":
            record.reason = "relocalised in the map: confirming (agrees so far)"
        elif verdict == "unmeasured":
            record.reason = f"relocalised in the map: confirming ({placement.events[-1]['reason']})"
        elif lost:  # refuted while recovering: back to counting refusals
            record.reason = f"recovery refuted: {placement.events[-1].get('reason', '')}"
        else:
            return False
        return True

    def _place(self, state: RunState, record: KeyframeRecord, i: int) -> None:
        """The pending candidate is confirmed at keyframe i: at the start, everything so far
        moves into the map's frame (:meth:`RunState.reframe`); then the relocalisation and each
        confirming correction enter the graph past the gate, and at the start what was measured
        before and agrees with them (:meth:`_add_earlier`)."""
        placement = self.placement
        assert placement is not None
        first = not placement.placed
        cand = placement.accept(i)
        if first:
            state.reframe(cand.T_map_run)
        found = cand.found
        relocalised = _measured_pose(found.T_map_cam, found.covariance, int(found.inliers))
        T_pred = state.T_world_kf_pred
        for frame_index, key, correction in [(cand.frame, cand.key, relocalised), *cand.confirmed]:
            if not state.graph.has(key) and key != record.key:
                continue  # left a bounded graph meanwhile
            try:
                state.graph.add_past_gate(key, correction, frame_index)
            except ValueError as exc:  # a covariance GTSAM cannot use: that one stays out
                log.warning("frame %d: relocalisation not usable (%s)", frame_index, exc)
        state.update_graph(extra_step=True, record=record)
        if first and self._add_earlier(state, i, placement.earlier(cand)):
            state.update_graph(extra_step=True, record=record)
        last = cand.confirmed[-1][2] if cand.confirmed else relocalised
        record.correction_m, record.correction_deg = pose_error(last.T_world_cam_corrected, T_pred)
        record.accepted = True
        record.reason = ""
        state.last_correction, state.last_correction_frame = last, i
        if first:
            log.warning("frame %d: %s", i, placement.describe())
        else:
            self._recovered(i, cand, found, T_pred, state.graph.pose(record.key))
        self.refused_in_a_row = 0

    def _add_earlier(self, state: RunState, i: int, earlier: list[Measured]) -> int:
        """The keyframes measured before the start's placement at keyframe i (``earlier``:
        relocalisations, ambiguous ones too, and corrections of dropped candidates) enter the
        graph as corrections do, through the gate against the placed graph: of each keyframe's
        measured poses the one nearest where the graph puts it, when within ``max_jump_m`` (a
        look-alike room's answer is metres away and stays out altogether). Without them the
        poses before the placement hang on the odometry from the placed keyframe alone.
        Returns how many keyframes were added."""
        placement, graph = self.placement, state.graph
        assert placement is not None
        if not earlier:
            return 0
        nearest: dict[int, tuple[float, Measured, np.ndarray]] = {}
        for m in earlier:
            if not graph.has(m.key):
                continue
            p_est = graph.pose(m.key)[:3, 3]
            jump_m, T = min(((float(np.linalg.norm(T[:3, 3] - p_est)), T) for T in m.T_map_cams), key=lambda o: o[0])
            if jump_m <= placement.settings.max_jump_m and jump_m < nearest.get(m.key, (np.inf,))[0]:
                nearest[m.key] = (jump_m, m, T)
        added = [m.frame for _, m, T in nearest.values()
                 if graph.gated_correction(m.key, _measured_pose(T, m.covariance, m.inliers), m.frame)[0] is not None]
        placement.note_earlier(i, sorted(added), len({m.key for m in earlier}))
        return len(added)

    def _recovered(self, i: int, cand, found, T_pred: np.ndarray, T_now: np.ndarray) -> None:
        """Record and say a recovery confirmed at keyframe i (the estimate jumped from
        ``T_pred`` to ``T_now``, both (4, 4))."""
        jump_m, jump_deg = pose_error(T_now, T_pred)
        self.recoveries.append({"frame": int(i), "step": "recovered", "recovered_from_frame": cand.frame,
                                "jump_m": round(jump_m, 4), "jump_deg": round(jump_deg, 3),
                                "keyframe": int(found.keyframe), "inliers": int(found.inliers), "success": True})
        log.warning("frame %d: recovered in the map (relocalised at frame %d, confirmed); the estimate jumped "
                    "%.2f m / %.1f deg", i, cand.frame, jump_m, jump_deg)


def _measured_pose(T_map_cam: np.ndarray, covariance: np.ndarray, inliers: int) -> Correction:
    """A pose found in the map (a relocalisation, (4, 4) ``T_map_cam`` with its (6, 6)
    ``covariance``) as the correction the graph takes."""
    alignment = Alignment(success=True, num_inliers=inliers, covariance=covariance)
    return Correction(T_map_cam, T_map_cam, covariance, alignment, 1, True, "", {})
