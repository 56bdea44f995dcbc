"""A simulated recording seen in another world frame, as a field's mapping may leave it, or
with a field that covers only part of it.

The simulator's world is z-up. A field built by COLMAP or nerfstudio has whatever frame its
mapping gave it (a y-down room, say). :class:`SequenceInFrame` gives a sequence's ground truth
in a frame F (``T_F_W`` (4, 4): simulator world -> F); :class:`FieldInFrame` renders a field of
the simulator's world from poses in F. The frames, depth and IMU samples (camera frame) are
unchanged, so the pair is the same recording mapped into F. :class:`PartlyMappedField` is a
field whose survey covered only the start of a walk: the views then leave it.
"""

from __future__ import annotations

import numpy as np

from nap3d_graph.camera import RenderedView
from nap3d_graph.conventions import inv_T

__all__ = ["SequenceInFrame", "FieldInFrame", "PartlyMappedField"]


class SequenceInFrame:
    """``sequence`` with its ground truth (``T_world_cam_gt``, ``ground_truth_at``) in frame F;
    everything else is the sequence's own."""

    def __init__(self, sequence, T_F_W: np.ndarray):
        self._sequence = sequence
        self.T_F_W = np.asarray(T_F_W, dtype=float)
        self.T_world_cam_gt = self.T_F_W @ np.asarray(sequence.T_world_cam_gt)

    def __getattr__(self, name):
        return getattr(self._sequence, name)

    def __len__(self) -> int:
        return len(self._sequence)

    def __getitem__(self, i):
        return self._sequence[i]

    def ground_truth_at(self, stamps):
        return self.T_F_W @ self._sequence.ground_truth_at(stamps)


class FieldInFrame:
    """``field`` (of the simulator's world) rendered from camera poses ``T_F_cam`` in frame F."""

    def __init__(self, field, T_F_W: np.ndarray):
        self._field, self.T_W_F = field, inv_T(np.asarray(T_F_W, dtype=float))
        self.name, self.bounds = f"{getattr(field, 'name', 'field')} (in another frame)", None

    def render(self, T_F_cam, intrinsics):
        return self._field.render(self.T_W_F @ T_F_cam, intrinsics)


class PartlyMappedField:
    """The exact field of ``sequence``'s room, but empty (no opacity) farther than ``radius``
    (m) from where its first ``mapped`` frames went (their ground-truth positions)."""

    def __init__(self, sequence, mapped: int, radius: float = 0.05):
        self._field, self.name, self.bounds = sequence.oracle_field(), "start of the walk", None
        self._positions, self._radius = np.asarray(sequence.T_world_cam_gt)[:mapped, :3, 3], radius

    def render(self, T_world_cam, intrinsics):
        view = self._field.render(T_world_cam, intrinsics)
        if np.min(np.linalg.norm(self._positions - T_world_cam[:3, 3], axis=1)) > self._radius:
            return RenderedView(view.rgb, view.depth_m, np.zeros_like(view.opacity), view.intrinsics)
        return view
