"""Handing a bounded run's final frames over (``Pipeline(on_retire=...)``) so that a long
run's memory stays flat."""

from __future__ import annotations

import numpy as np

from nap3d_graph.run.chain import chain_from_nearest_keyframe
from nap3d_graph.run.records import RunResult, ground_truth_reader
from nap3d_graph.run.state import RunState

__all__ = ["retired_segment"]


def retired_segment(run: RunState, sequence, cut: int) -> RunResult | None:
    """Keyframes before ``cut`` have left the run's graph with their poses fixed: the frames
    before the last of them have their final smoothed poses (each is chained from a fixed
    keyframe). Returns them as a :class:`RunResult` segment (``first_frame`` says where it
    starts) and drops them from the run (None when there is nothing to hand over); the last
    fixed keyframe stays, the frames after it are chained from it at the end.

    run: the run's state (its ``online``, ``keyframe_indices``, ``records``, ``graph`` and
        ``motion``); sequence: the run's frames (their stamps and ground truth).
    """
    first, last_fixed = run.online.start, run.keyframe_indices[cut - 1]
    if last_fixed <= first:
        return None
    frozen = run.graph.frozen
    fixed = {idx: frozen[j] for j, idx in run.keyframe_indices.items() if j < cut}
    T_world_cam_est = chain_from_nearest_keyframe(fixed, run.motion.increments, last_fixed, start=first)
    stamps = np.asarray(sequence.timestamps[first:last_fixed], dtype=float)
    keyframes_gone = run.keyframe_indices.drop_before(run.keyframe_indices.first(lambda idx: idx >= last_fixed))
    records_gone = run.records.drop_before(run.records.first(lambda r: r.frame_index >= last_fixed))
    for j in [j for j in frozen if j < run.keyframe_indices.start]:
        del frozen[j]
    return RunResult(stamps, T_world_cam_est, np.stack(run.motion.T_world_cam_odom.drop_before(last_fixed)),
                     ground_truth_reader(sequence, first, last_fixed), records_gone, keyframes_gone,
                     T_world_cam_online=np.stack(run.online.drop_before(last_fixed)),
                     increments=run.motion.increments.drop_before(last_fixed), first_frame=first)
