"""What a drift-correction run holds between its frames: :class:`RunState`.

The motion model, the keyframe graph, the logs of keyframes, records and causal poses, the
keyframe being measured and the latest correction: one object, made by
:meth:`~nap3d_graph.run.pipeline.Pipeline.start`. ``Pipeline.step`` hands it to one part at a
time (the keyframe jobs, the correction gate, the map recovery, the overlapped steps), for the
length of that part's call; no part keeps it, and none holds the pipeline.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import gtsam
import numpy as np

from nap3d_graph.conventions import inv_T
from nap3d_graph.mapping.start import MapPlacement
from nap3d_graph.results import Correction
from nap3d_graph.run.graph import KeyframeGraph
from nap3d_graph.run.history import FrameLog
from nap3d_graph.run.intrinsics_model import IntrinsicsModelTracker
from nap3d_graph.run.keyframe import DepthScaleTracker
from nap3d_graph.run.motion import MotionModel
from nap3d_graph.run.records import KeyframeRecord
from nap3d_graph.run.stream import MeasurementStream

__all__ = ["RunState"]


@dataclass
class RunState:
    """A run's state between frames.

    motion: the motion model (odometry poses, increments, the causal pose).
    graph: the keyframe graph (iSAM2); ``anchored``: it estimates the field's frame ``M(0)``.
    stream: what was measured (intervals, corrections) for the estimators.
    depth_scale / intrinsics_model: the depth-scale and camera-model trackers.
    placement: where the run is in a map (None: no map, or a given start).
    T_world_kf_pred: (4, 4) the latest keyframe's prediction, world frame.
    keyframe_indices / records / online: frame of each keyframe, each keyframe's record (in the
        order they were done), each frame's causal pose; with a bounded graph the oldest leave.
    pending_record: the keyframe being measured (None between keyframes).
    last_correction / last_factor / last_correction_frame: the latest correction, its factor
        when it entered the graph, and its keyframe's frame (a live caller reads them).
    retire: ``f(cut)`` when a bounded graph's window moved: keyframes before ``cut`` left it.
    """

    motion: MotionModel
    graph: KeyframeGraph
    anchored: bool
    stream: MeasurementStream
    depth_scale: DepthScaleTracker
    intrinsics_model: IntrinsicsModelTracker
    placement: MapPlacement | None
    T_world_kf_pred: np.ndarray
    retire: Callable[[int], None] | None = None
    keyframe_indices: FrameLog[int] = field(default_factory=FrameLog)
    records: FrameLog[KeyframeRecord] = field(default_factory=FrameLog)
    online: FrameLog[np.ndarray] = field(default_factory=FrameLog)
    pending_record: KeyframeRecord | None = None
    last_correction: Correction | None = None
    last_factor: gtsam.NonlinearFactor | None = None
    last_correction_frame: int = -1

    @property
    def placed(self) -> bool:
        """Whether the poses are in the field's (map's) frame: always, unless the run started
        from anywhere in a map and has not been placed yet."""
        return self.placement is None or self.placement.placed

    @property
    def last_keyframe(self) -> int | None:
        """The latest keyframe's frame (None before the first)."""
        return self.keyframe_indices[-1] if self.keyframe_indices else None

    def pending(self) -> KeyframeRecord:
        """The record of the keyframe being measured."""
        if self.pending_record is None:
            raise RuntimeError("no keyframe is pending: add_keyframe comes first")
        return self.pending_record

    def in_field_frame(self, T_world_cam: np.ndarray) -> np.ndarray:
        """(4, 4) a world pose in the field's frame (the anchor's estimate taken out)."""
        return inv_T(self.graph.anchor()) @ T_world_cam if self.anchored else T_world_cam

    def update_graph(self, extra_step: bool = False, record: KeyframeRecord | None = None) -> None:
        """An iSAM2 step (two with ``extra_step``); with a bounded graph, what left its window
        is forgotten (and handed to ``retire``). The time goes to ``record``'s timings (the
        pending keyframe's when not given)."""
        t0 = time.perf_counter()
        self.graph.update(extra_step)
        # Until the run is placed in the map its graph holds every keyframe (it will be moved whole).
        cut = self.graph.bound(len(self.keyframe_indices)) if self.placed else None
        if cut is not None:  # the window moved: the stream forgets what left it
            self.stream.forget_before(self.keyframe_indices[cut])
            if self.retire is not None:
                self.retire(cut)
        record = record or self.pending_record
        if record is not None:
            record.timings_s["isam"] = round(record.timings_s.get("isam", 0.0) + time.perf_counter() - t0, 5)

    def reframe(self, T_map_run: np.ndarray) -> None:
        """Move the run so far from its provisional frame into the map's by ``T_map_run``
        (4, 4): the odometry, the causal poses, the prediction and the graph (which drops its
        provisional first-pose prior: a relocalisation then holds the gauge)."""
        T = np.asarray(T_map_run, dtype=float)
        self.motion.reframe(T)
        self.online = self.online.mapped(lambda T_run_cam: T @ T_run_cam)
        self.T_world_kf_pred = T @ self.T_world_kf_pred
        self.graph = self.graph.reframed(T)
