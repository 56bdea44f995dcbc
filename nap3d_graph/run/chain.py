"""Whole trajectories from keyframe poses and the odometry's frame-to-frame increments."""

from __future__ import annotations

import numpy as np

from nap3d_graph.conventions import inv_T

__all__ = ["chain_from_nearest_keyframe"]


def chain_from_nearest_keyframe(T_world_kf_by_frame: dict[int, np.ndarray], increments, n: int,
                                start: int = 0) -> np.ndarray:
    """The poses (n - start, 4, 4) of frames ``start..n-1``: keyframes (``{frame:
    T_world_cam}``) as given, the others chained from the nearest keyframe with the
    increments (``increments[i]`` = T_prev_cur of frame i, indexed by frame), forwards or
    backwards."""
    kf = np.array(sorted(T_world_kf_by_frame))
    T = np.empty((n - start, 4, 4))
    for i in range(start, n):
        k = int(kf[np.argmin(np.abs(kf - i))])
        pose = T_world_kf_by_frame[k]
        if i > k:
            for m in range(k + 1, i + 1):
                pose = pose @ increments[m]
        elif i < k:
            for m in range(k, i, -1):
                pose = pose @ inv_T(increments[m])
        T[i - start] = pose
    return T
