"""What every reader gives: the :class:`Sequence` protocol (TUM, simulator folders, 7-Scenes,
RealSense recordings, ROS bags). Optional capabilities stay optional and are asked for by name:
``imu`` (IMU samples), ``T_world_cam_odom`` (a recorded odometry), ``oracle_field()`` (the exact
field of a simulated room), ``imu_config``."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from nap3d_graph.camera import Intrinsics, RGBDFrame

__all__ = ["FrameSource", "Sequence", "SEQUENCE_ATTRIBUTES", "GROUND_TRUTH_ACCESSORS"]

#: The attributes every reader sets (a test checks each reader has them).
SEQUENCE_ATTRIBUTES = ("path", "timestamps", "depth_timestamps", "intrinsics", "T_world_cam_gt", "frame_range",
                       "recording_id", "simulated")


class FrameSource(Protocol):
    """What a drift-correction run reads of its frames (a live caller's growing sequence gives
    just this): ``len``, the frames, their ``timestamps`` (N,) and ``T_world_cam_gt`` (or None).
    ``timestamps`` is an array, or anything indexed by frame as one is (``[i]``, ``[a:b]``:
    a live run's :class:`~nap3d_graph.run.history.FrameLog`)."""

    @property
    def timestamps(self) -> Any: ...

    @property
    def T_world_cam_gt(self) -> np.ndarray | None: ...

    def __len__(self) -> int: ...

    def __getitem__(self, i: int) -> RGBDFrame: ...


#: Every attribute through which a reader gives its recording's ground truth (poses, their
#: samples, which frames have one). ``map`` and a run on a map touch none of them before the
#: map's poses and the run's trajectories are written (tests/test_mapping.py watches them all).
GROUND_TRUTH_ACCESSORS = ("T_world_cam_gt", "ground_truth_at", "has_gt", "_gt_raw", "T_world_depth",
                          "_T_world_depth_all", "_gt_from_poses", "_gt_from_tf", "_attach_ground_truth",
                          "ground_truth_samples")


@runtime_checkable

class Sequence(Protocol):
    """An RGB-D recording, frame by frame. ``timestamps`` (N,) colour stamps (s);
    ``depth_timestamps`` (N,) depth stamps (the colour's when the source has none);
    ``T_world_cam_gt`` (N, 4, 4) ground truth at the frames (NaN where none) or None;
    ``frame_range`` the (start, stop) of the source's frames read; ``recording_id`` a content
    fingerprint (which recording a field was built from); ``simulated`` written by the
    simulator."""

    path: Path
    timestamps: np.ndarray
    depth_timestamps: np.ndarray
    intrinsics: Intrinsics
    T_world_cam_gt: np.ndarray | None
    frame_range: tuple[int, int]
    recording_id: str
    simulated: bool

    def __len__(self) -> int: ...

    def __getitem__(self, i: int) -> RGBDFrame: ...

    def ground_truth_at(self, stamps) -> np.ndarray | None: ...
