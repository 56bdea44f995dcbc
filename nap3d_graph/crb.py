"""The physical limit of one correction: the Cramer-Rao bound of its 6-DoF pose.

Under the refinement's noise model (:func:`~nap3d_graph.nap3d.refine.refine_pose`: each
correspondence measures the real keypoint's pixel with variance ``2 s_px^2`` per axis and
its depth with the sensor's ``(s0 + k z^2)^2`` plus the rendered depth's, correlated through
the rendered depth's gradient), the Fisher information of the correction is
``F = sum_i J_i^T Sigma_i^-1 J_i`` with ``J_i`` the derivative of ``[u, v, z]`` of ``R x_i + t``
with respect to the corrected pose, evaluated at the *true* pose. Any unbiased estimator's
covariance is at least ``F^-1``: a method's error against ``sqrt(trace)`` of its blocks says
how far from the limit the matches allow it is.
"""

from __future__ import annotations

import numpy as np

from .camera import Intrinsics
from .nap3d.config import AlignConfig
from .nap3d.correspondences import Correspondences
from .nap3d.refine import point_jacobian, reprojection_terms, stack_rows, variance_factors

__all__ = ["cramer_rao_bound", "bound_sigmas"]


def cramer_rao_bound(T_real_rendered_true: np.ndarray, corr: Correspondences, intrinsics: Intrinsics,
                     config: AlignConfig | None = None, noise: str = "nominal") -> np.ndarray:
    """The bound (6, 6) on the covariance of the corrected camera pose (GTSAM order
    ``[rotation, translation]``, right perturbation, as every correction's covariance) from
    the correspondences ``corr`` (rendered points ``x``, real depths ``y[:, 2]``; pass the true
    inliers) at the true ``T_real_rendered`` (4, 4). Infinite where the matches do not
    constrain the pose.

    ``noise``: ``"nominal"`` takes the noise model's variances as they are; ``"measured"``
    scales the pixel and the depth variance by the mean square of these matches' residuals
    at the true pose (which *are* their noise), as the refinement's variance factors do at
    its estimate: the bound for the noise these matches actually carry.
    """
    config = config or AlignConfig()
    T = np.asarray(T_real_rendered_true, dtype=float)
    p = corr.x @ T[:3, :3].T + T[:3, 3]
    if len(p) < 3 or np.any(p[:, 2] <= 1e-6):
        return np.full((6, 6), np.inf)
    z = p[:, 2]
    grad = np.zeros((len(p), 2)) if corr.depth_grad is None else corr.depth_grad
    edge = ~np.all(np.isfinite(grad), axis=1)
    grad = np.where(edge[:, None], 0.0, grad)
    var_px = 2.0 * config.keypoint_sigma_px**2
    var_z = (config.depth_sigma_floor_m + config.depth_sigma_z2_per_m * z**2) ** 2 + config.render_depth_sigma_m**2
    var_z = np.where(edge, 1.0, var_z)
    r_px, J_px = reprojection_terms(p, corr.uv_real, intrinsics)
    J_z = point_jacobian(p)[:, 2, :]
    if noise == "measured":
        r_z = z - corr.y[:, 2]
        scale_px, scale_z = variance_factors(r_px, r_z, grad, np.ones(len(p)), var_px, var_z, True, True)
        var_px, var_z = var_px * scale_px, var_z * scale_z
    elif noise != "nominal":
        raise ValueError(f"noise must be 'nominal' or 'measured', got {noise!r}")
    _, J, W = stack_rows(r_px, J_px, z - z, J_z, grad, var_px, var_z, True, True)
    fisher = np.einsum("nri,nrs,nsj->ij", J, W, J)
    try:
        bound = np.linalg.inv(fisher)
    except np.linalg.LinAlgError:
        return np.full((6, 6), np.inf)
    return 0.5 * (bound + bound.T)


def bound_sigmas(bound: np.ndarray) -> tuple[float, float]:
    """``(rotation rad, translation m)``: the root of the trace of each 3x3 block, the
    smallest RMS error an unbiased estimator can have in each."""
    return float(np.sqrt(np.trace(bound[:3, :3]))), float(np.sqrt(np.trace(bound[3:, 3:])))
