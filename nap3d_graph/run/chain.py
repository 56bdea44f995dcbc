"""Whole trajectories from keyframe poses and the odometry's frame-to-frame increments."""

from __future__ import annotations

import numpy as np

from nap3d_graph.conventions import inv_T

__all__ = ["chain_from_nearest_keyframe"]


def chain_from_nearest_keyframe(T_world_kf_by_frame: dict[int, np.ndarray], increments: list[np.ndarray], n: int) -> np.ndarray:
    """Every frame's pose (n, 4, 4): keyframes (``{frame: T_world_cam}``) as given, the others
    chained from the nearest keyframe with the increments (``increments[i]`` = T_prev_cur of
    frame i), forwards or backwards."""
    kf = np.array(sorted(T_world_kf_by_frame))
    T = np.empty((n, 4, 4))
    for i in range(n):
        k = int(kf[np.argmin(np.abs(kf - i))])
        pose = T_world_kf_by_frame[k]
        if i > k:
            for m in range(k + 1, i + 1):
                pose = pose @ increments[m]
        elif i < k:
            for m in range(k, i, -1):
                pose = pose @ inv_T(increments[m])
        T[i] = pose
    return T
