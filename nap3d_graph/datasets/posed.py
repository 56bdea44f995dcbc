"""A sequence seen through other poses than its ground truth: the one wrapper for it.

Training a field reads a sequence's ``T_world_cam_gt`` (and ``ground_truth_at`` for the
capture timing): :class:`PosedSequence` gives other poses there (a map's own, a second
ground truth), so the field is built exactly as for a recording with ground truth, without
one. :func:`reframed` moves a sequence's ground truth into a map's frame (for evaluation in
that frame); :class:`~nap3d_graph.fields.pose_refinement.PoseCorrectedSequence` is the
training poses corrected frame by frame.
"""

from __future__ import annotations

import numpy as np

from ..trajectory import interpolate_poses

__all__ = ["PosedSequence", "ReframedSequence", "reframed"]


class PosedSequence:
    """``base`` with ``T_world_cam_gt`` replaced by ``T_world_cam`` (N, 4, 4; NaN where a
    frame has no pose), and ``pose_source`` saying where the poses came from. Frames,
    stamps, intrinsics and the recording's identity are the base's."""

    def __init__(self, base, T_world_cam: np.ndarray, pose_source: str, T_new_old: np.ndarray | None = None):
        T_world_cam = np.asarray(T_world_cam, dtype=float)
        if T_world_cam.shape != (len(base), 4, 4):
            raise ValueError(f"poses must be ({len(base)}, 4, 4), got {T_world_cam.shape}")
        self._base = base
        self.T_world_cam_gt = T_world_cam
        self.pose_source = pose_source
        # Reframed ground truth (T_new_old set): interpolate the base's own raw ground truth and
        # move it, so capture-timing estimates see the same samples as before.
        self._T_new_old = None if T_new_old is None else np.asarray(T_new_old, dtype=float)

    def __getattr__(self, name):
        if name.startswith("__"):
            raise AttributeError(name)
        return getattr(self._base, name)

    def __len__(self) -> int:
        return len(self._base)

    def __getitem__(self, i: int):
        return self._base[i]

    @property
    def base(self):
        return self._base

    def ground_truth_at(self, stamps) -> np.ndarray | None:
        """The poses (M, 4, 4) at any times (M,): the base's ground truth moved into the new
        frame, or the map's poses interpolated (NaN outside them)."""
        stamps = np.asarray(stamps, dtype=float)
        if self._T_new_old is not None:
            raw = self._base.ground_truth_at(stamps) if hasattr(self._base, "ground_truth_at") else None
            return None if raw is None else self._T_new_old @ raw
        posed = np.all(np.isfinite(self.T_world_cam_gt), axis=(1, 2))
        if posed.sum() < 2:
            return None
        # Frames are a fraction of a second apart; a dropped stretch is not bridged.
        return interpolate_poses(np.asarray(self._base.timestamps, dtype=float)[posed], self.T_world_cam_gt[posed],
                                 stamps, max_gap=0.5)

    def __repr__(self) -> str:
        return f"PosedSequence({self._base!r}, poses from {self.pose_source})"


class ReframedSequence(PosedSequence):
    """``base`` with its ground truth moved by ``T_new_old`` (4, 4), read from the base only
    when asked for (a run on a map reads no ground truth before its results are written)."""

    def __init__(self, base, T_new_old: np.ndarray, pose_source: str):
        self._base = base
        self.pose_source = pose_source
        self._T_new_old = np.asarray(T_new_old, dtype=float)

    @property
    def T_world_cam_gt(self):
        T_old = self._base.T_world_cam_gt
        return None if T_old is None else self._T_new_old @ np.asarray(T_old, dtype=float)


def reframed(sequence, T_new_old: np.ndarray, pose_source: str):
    """``sequence`` with its ground truth moved by ``T_new_old`` (4, 4): ``T_new_cam =
    T_new_old @ T_old_cam`` (None stays None), read from ``sequence`` only when used."""
    return ReframedSequence(sequence, T_new_old, pose_source)
