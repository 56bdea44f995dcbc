"""Result objects of one alignment and one pose correction.

A registration result carries what a factor needs (as small_gicp's does): the transform,
whether it succeeded, the inlier count and a 6x6 covariance in GTSAM's tangent order
``[rotation, translation]`` (right perturbation, body frame).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .conventions import inv_T

__all__ = ["Alignment", "Correction"]


@dataclass
class Alignment:
    """Rigid alignment of a rendered view to a real frame.

    T_real_rendered: (4, 4) maps points in the rendered camera into the real camera
        (``y = R x + t``), so ``T_world_cam_true = T_world_cam_est @ inv(T_real_rendered)``.
    covariance: (6, 6) covariance of the corrected pose ``T_world_cam_true`` in GTSAM's
        tangent order and frame (right perturbation of the corrected camera pose).
    success: False when any stage failed; ``reason`` then says why and the transform is
        the identity, the covariance infinite.
    """

    T_real_rendered: np.ndarray = field(default_factory=lambda: np.eye(4))
    covariance: np.ndarray = field(default_factory=lambda: np.full((6, 6), np.inf))
    num_matches: int = 0
    num_inliers: int = 0
    inlier_rmse_m: float = float("nan")
    success: bool = False
    reason: str = ""
    method: str = ""
    timings_s: dict = field(default_factory=dict)
    inlier_mask: np.ndarray | None = None
    diagnostics: dict = field(default_factory=dict)

    @classmethod
    def failure(cls, reason: str, num_matches: int = 0, num_inliers: int = 0, method: str = "",
                timings_s: dict | None = None) -> "Alignment":
        return cls(num_matches=num_matches, num_inliers=num_inliers, success=False,
                   reason=reason, method=method, timings_s=dict(timings_s or {}))

    def corrected_pose(self, T_world_cam_est: np.ndarray) -> np.ndarray:
        """``T_world_cam_true = T_world_cam_est @ inv(T_real_rendered)``."""
        return np.asarray(T_world_cam_est, dtype=float) @ inv_T(self.T_real_rendered)


@dataclass
class Correction:
    """One NAP3D pose correction: render at the estimate, align, optionally re-render.

    T_world_cam_corrected: (4, 4) corrected camera pose (world <- camera, OpenCV camera).
    covariance: (6, 6) of that pose, GTSAM order and frame.
    iterations: how many render-align rounds ran.
    views: what the last round compared, for display (``run --viz``): ``real_rgb`` and
        ``render_rgb`` (H, W, 3) uint8 at the render's resolution, and on success the inlier
        matches' pixels ``inlier_uv_real`` / ``inlier_uv_render`` (K, 2).
    """

    T_world_cam_est: np.ndarray
    T_world_cam_corrected: np.ndarray
    covariance: np.ndarray
    alignment: Alignment
    iterations: int = 0
    success: bool = False
    reason: str = ""
    timings_s: dict = field(default_factory=dict)
    views: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def num_inliers(self) -> int:
        return self.alignment.num_inliers

    @property
    def num_matches(self) -> int:
        return self.alignment.num_matches
