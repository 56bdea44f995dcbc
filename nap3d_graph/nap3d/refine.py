"""Refinement of a NAP3D pose over every inlier's pixel and depth residuals, and its covariance.

Parameterisation: with ``T_true = T_world_cam_est @ inv(T_real_rendered)`` and the GTSAM
right perturbation ``T_true <- T_true @ Exp(delta)``, a point ``p`` in the real camera moves
to ``Exp(-delta) p ~ p + [p]x omega - v``, so ``dp/ddelta = [[p]x, -I]``: the covariance of
``delta`` is directly the covariance GTSAM's Pose3 prior expects (rotation first, body frame).
"""

from __future__ import annotations

import numpy as np
from scipy.stats import chi2

from ..camera import Intrinsics
from ..conventions import exp_se3, make_T, skew
from .config import AlignConfig
from .correspondences import Correspondences

__all__ = ["refine_pose", "plain_covariance", "consensus_cost", "point_jacobian", "reprojection_terms", "stack_rows", "information_matrices",
           "variance_factors"]


# --- refinement and covariance -------------------------------------------------------------------


def point_jacobian(p: np.ndarray) -> np.ndarray:
    """d p / d delta (N, 3, 6) for the right perturbation of the real camera pose."""
    J = np.zeros((len(p), 3, 6))
    J[:, :, :3] = skew(p)
    J[:, :, 3:] = -np.eye(3)
    return J


def reprojection_terms(p: np.ndarray, uv: np.ndarray, K: Intrinsics):
    """Residuals (N, 2) pixels and Jacobians (N, 2, 6) of projecting p into the real image."""
    z = p[:, 2]
    res = np.stack([K.fx * p[:, 0] / z + K.cx - uv[:, 0], K.fy * p[:, 1] / z + K.cy - uv[:, 1]], axis=1)
    Jproj = np.zeros((len(p), 2, 3))
    Jproj[:, 0, 0] = K.fx / z
    Jproj[:, 0, 2] = -K.fx * p[:, 0] / z**2
    Jproj[:, 1, 1] = K.fy / z
    Jproj[:, 1, 2] = -K.fy * p[:, 1] / z**2
    return res, Jproj @ point_jacobian(p)


def _huber_weights(r_norm: np.ndarray, k: float) -> np.ndarray:
    return np.where(r_norm <= k, 1.0, k / np.maximum(r_norm, 1e-12))


def _intrinsics_jacobian(p: np.ndarray) -> np.ndarray:
    """d pixel / d (fx, fy, cx, cy), (N, 2, 4)."""
    J = np.zeros((len(p), 2, 4))
    J[:, 0, 0] = p[:, 0] / p[:, 2]
    J[:, 1, 1] = p[:, 1] / p[:, 2]
    J[:, 0, 2] = 1.0
    J[:, 1, 3] = 1.0
    return J


def _with_intrinsics_delta(K: Intrinsics, d: np.ndarray) -> Intrinsics:
    return Intrinsics(K.fx + d[0], K.fy + d[1], K.cx + d[2], K.cy + d[3], K.width, K.height)


def refine_pose(R: np.ndarray, t: np.ndarray, corr: Correspondences, intrinsics: Intrinsics,
                config: AlignConfig, use_depth: bool = True, use_reprojection: bool = True,
                return_intrinsics: bool = False):
    """Weighted Gauss-Newton over reprojection (px) and depth (m) residuals of each inlier.

    Each correspondence contributes ``r = [pi(p) - uv_real, p_z - z_real]`` with a 3x3
    covariance: the two keypoints' localisation noise ``2 s_px^2`` on the pixels, and on the
    depth the sensor/field depth noise plus the same pixel noise carried through the depth
    gradient ``g`` (so the rows are correlated: ``cov(r_uv, r_z) = 2 s_px^2 g``). Huber
    weights guard against remaining outliers; variance factors for the pixel and the depth
    noise are estimated from the residuals. Starts from ``(R, t)`` = T_real_rendered; returns
    the refined ``(R, t)``, the 6x6 covariance of the corrected camera pose (GTSAM order,
    right perturbation) and the per-correspondence normalised residual norms (N,), or None
    when the problem is singular. With ``config.estimate_intrinsics`` the real camera's
    intrinsics are refined too (returned last when ``return_intrinsics``).
    """
    x, uv = corr.x, corr.uv_real
    n = len(x)
    z_real = corr.y[:, 2]
    grad = np.zeros((n, 2)) if corr.depth_grad is None else corr.depth_grad
    var_px0 = 2.0 * config.keypoint_sigma_px**2
    var_z0 = (config.depth_sigma_floor_m + config.depth_sigma_z2_per_m * z_real**2) ** 2 + config.render_depth_sigma_m**2
    # At a depth edge the linearised depth model does not hold: keep the pixel residuals and
    # give the depth residual a (1 m)^2 variance, i.e. no say.
    edge = ~np.all(np.isfinite(grad), axis=1)
    grad = np.where(edge[:, None], 0.0, grad)
    var_z0 = np.where(edge, 1.0, var_z0)
    scale_px, scale_z = 1.0, 1.0  # variance factors, estimated from the residuals
    T = make_T(R, t)
    H = np.full((6, 6), np.nan)
    norm_sq = np.zeros(n)
    rows = int(use_reprojection) * 2 + int(use_depth)
    calibrate = config.estimate_intrinsics is True and use_reprojection
    d_K = np.zeros(4)  # fx, fy, cx, cy corrections (pixels)
    f_mean = 0.5 * (intrinsics.fx + intrinsics.fy)
    K_prior_info = 1.0 / np.array([config.intrinsics_focal_sigma * f_mean] * 2
                                  + [config.intrinsics_principal_sigma_px] * 2) ** 2
    information = None  # ((scale_px, scale_z), W) for the current variance factors
    for iteration in range(config.refine_iterations + 2):
        p = x @ T[:3, :3].T + T[:3, 3]
        if np.any(p[:, 2] <= 1e-6):
            return None
        r_px, J_px = reprojection_terms(p, uv, _with_intrinsics_delta(intrinsics, d_K))
        r_z = p[:, 2] - z_real
        J_z = point_jacobian(p)[:, 2, :]
        if calibrate:
            J_px = np.concatenate([J_px, _intrinsics_jacobian(p)], axis=2)
            J_z = np.concatenate([J_z, np.zeros((n, 4))], axis=1)
        if information is None or information[0] != (scale_px, scale_z):
            # The information matrices change only with the variance factors (twice per
            # refinement): inverting N 3x3 covariances every iteration was a quarter of it.
            information = ((scale_px, scale_z), information_matrices(grad, var_px0 * scale_px, var_z0 * scale_z,
                                                                     use_reprojection, use_depth))
        r, J, W = stack_rows(r_px, J_px, r_z, J_z, grad, var_px0 * scale_px, var_z0 * scale_z,
                             use_reprojection, use_depth, W=information[1])
        Wr = _apply(W, r)
        norm_sq = np.sum(r * Wr, axis=1)
        rob = _huber_weights(np.sqrt(norm_sq / rows), config.huber_k)
        H, g = _normal_equations(rob, J, W, Wr)
        if calibrate:  # the prior keeps the intrinsics near their given values
            H[6:, 6:] += np.diag(K_prior_info)
            g[6:] += K_prior_info * d_K
        try:
            step = -np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            return None
        delta = step[:6]
        if calibrate:
            d_K = d_K + step[6:]
        # T_true <- T_true Exp(delta)  <=>  T_real_rendered <- Exp(-delta) T_real_rendered
        T = exp_se3(-delta) @ T
        if iteration in (1, 3):
            scale_px, scale_z = variance_factors(r_px, r_z, grad, rob, var_px0, var_z0, use_reprojection,
                                                  use_depth)
        elif iteration > 3 and np.linalg.norm(delta) < 1e-10:
            break
    cov = _covariance(H)[:6, :6]  # the pose block: intrinsics, if estimated, marginalised
    if config.covariance == "sandwich":
        # Heteroscedasticity-consistent (HC1) sandwich: the spread of each correspondence's
        # actual residual, not only the model's, enters the covariance.
        score = rob[:, None] * np.matmul(np.swapaxes(J, 1, 2), Wr[:, :, None])[:, :, 0]
        B = score.T @ score * n / max(n - 6, 1)
        full = _covariance(H)
        cov = (full @ B @ full)[:6, :6]
        cov = 0.5 * (cov + cov.T)
    if return_intrinsics:
        diagnostics = {"pixel_variance_factor": float(scale_px), "depth_variance_factor": float(scale_z)}
        return T[:3, :3], T[:3, 3], cov, np.sqrt(norm_sq), _with_intrinsics_delta(intrinsics, d_K), diagnostics
    return T[:3, :3], T[:3, 3], cov, np.sqrt(norm_sq)


def consensus_cost(R: np.ndarray, t: np.ndarray, corr: Correspondences, intrinsics: Intrinsics,
                   config: AlignConfig, scale_px: float = 1.0, scale_z: float = 1.0,
                   use_depth: bool = True) -> tuple[float, int]:
    """Truncated (MSAC) cost of a pose and camera model over *all* correspondences.

    Each correspondence's whitened residual ``r^2`` (reprojection into the real image with
    ``intrinsics``, plus the depth residual unless ``use_depth`` is False, under the same
    noise model as :func:`refine_pose`, variances times ``scale_px`` / ``scale_z``) costs
    ``min(r^2, config.inlier_chi2)``. Comparing two models on the same correspondences and
    the same noise says which explains more of them better; returns ``(cost, inliers)``.
    """
    p = corr.x @ R.T + t
    n = len(p)
    if n == 0 or np.any(p[:, 2] <= 1e-6):
        return float("inf"), 0
    grad = np.zeros((n, 2)) if corr.depth_grad is None else corr.depth_grad
    z_real = corr.y[:, 2]
    var_z0 = (config.depth_sigma_floor_m + config.depth_sigma_z2_per_m * z_real**2) ** 2 + config.render_depth_sigma_m**2
    edge = ~np.all(np.isfinite(grad), axis=1)
    grad = np.where(edge[:, None], 0.0, grad)
    var_z0 = np.where(edge, 1.0, var_z0)
    r_px, J_px = reprojection_terms(p, corr.uv_real, intrinsics)
    r_z = p[:, 2] - z_real
    J_z = point_jacobian(p)[:, 2, :]
    var_px = 2.0 * config.keypoint_sigma_px**2 * scale_px
    r, _, W = stack_rows(r_px, J_px, r_z, J_z, grad, var_px, var_z0 * scale_z, True, use_depth)
    r2 = np.sum(r * _apply(W, r), axis=1)
    # The same tail probability as the 3-row threshold, for 2 rows when the depth is left out.
    threshold = config.inlier_chi2 if use_depth else float(chi2.ppf(chi2.cdf(config.inlier_chi2, 3), 2))
    return float(np.sum(np.minimum(r2, threshold))), int(np.sum(r2 < threshold))


def _apply(W: np.ndarray, r: np.ndarray) -> np.ndarray:
    """(N, m) ``W[n] @ r[n]`` for information matrices W (N, m, m) and residuals r (N, m)."""
    return np.matmul(W, r[:, :, None])[:, :, 0]


def _normal_equations(rob: np.ndarray, J: np.ndarray, W: np.ndarray, Wr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``H = sum_n rob_n J_n^T W_n J_n`` (k, k) and ``g = sum_n rob_n J_n^T W_n r_n`` (k,) for
    Jacobians J (N, m, k), information W (N, m, m), ``Wr`` = W r (N, m) and weights rob (N,):
    as one matrix product over the stacked rows (BLAS), not an einsum over four operands."""
    J_rob = _weighted_rows(rob, J)
    return J_rob.T @ _rows(np.matmul(W, J)), J_rob.T @ Wr.reshape(-1)


def _rows(M: np.ndarray) -> np.ndarray:
    """(N * m, k) the stacked rows of per-correspondence matrices M (N, m, k)."""
    return M.reshape(-1, M.shape[2])


def _weighted_rows(w: np.ndarray, J: np.ndarray) -> np.ndarray:
    """(N * m, k) the rows of J (N, m, k), each correspondence's scaled by its weight w (N,):
    ``_weighted_rows(w, J).T @ _rows(A)`` is ``sum_n w_n J_n^T A_n`` as one BLAS product."""
    return _rows(J * w[:, None, None])


def stack_rows(r_px, J_px, r_z, J_z, grad, var_px, var_z, use_reprojection, use_depth, W=None):
    """Residuals (N, m), Jacobians (N, m, 6) and information matrices (N, m, m) per
    correspondence, m = 3 (pixels + depth), 2 (pixels) or 1 (depth). ``W``: the information
    matrices when already computed (:func:`information_matrices` of the same arguments)."""
    if W is None:
        W = information_matrices(grad, var_px, var_z, use_reprojection, use_depth)
    if use_reprojection and use_depth:
        return np.concatenate([r_px, r_z[:, None]], 1), np.concatenate([J_px, J_z[:, None]], 1), W
    if use_reprojection:
        return r_px, J_px, W
    return r_z[:, None], J_z[:, None], W


def information_matrices(grad, var_px, var_z, use_reprojection, use_depth) -> np.ndarray:
    """Information matrices (N, m, m) of :func:`stack_rows`' residuals: the pixel noise
    ``var_px`` on both pixel rows, and on the depth row ``var_z`` (N,) plus the pixel noise
    carried through the depth gradient ``grad`` (N, 2), which also correlates the rows."""
    n = len(grad)
    if use_reprojection and use_depth:
        C = np.zeros((n, 3, 3))
        C[:, 0, 0] = C[:, 1, 1] = var_px
        C[:, :2, 2] = C[:, 2, :2] = var_px * grad
        C[:, 2, 2] = var_px * np.sum(grad**2, axis=1) + var_z
        return np.linalg.inv(C)
    if use_reprojection:
        return np.broadcast_to(np.eye(2) / var_px, (n, 2, 2))
    var = var_px * np.sum(grad**2, axis=1) + var_z
    return (1.0 / var)[:, None, None]


def variance_factors(r_px, r_z, grad, rob, var_px0, var_z0, use_reprojection, use_depth):
    """Variance factors (pixel, depth) from the robust-weighted residuals.

    The depth factor uses the depth residual *conditioned* on the pixel residual
    (``r_z - g . r_uv``), whose variance is the depth noise alone. Floored at 0.1^2 so
    noise-free data never yields an infinitely confident factor.
    """
    n = len(r_z)
    rows = 2 * n * use_reprojection + n * use_depth
    redundancy = max(1.0 - 6.0 / max(rows, 7), 0.05)
    f_px = 1.0
    if use_reprojection:
        f_px = np.sum(rob[:, None] * r_px**2) / (var_px0 * 2 * n * redundancy)
    f_z = 1.0
    if use_depth:
        conditional = r_z - np.sum(grad * r_px, axis=1) if use_reprojection else r_z
        smooth = var_z0 < 1.0  # edge points carry a nominal 1 m^2 and say nothing here
        n_z = max(int(smooth.sum()), 1)
        f_z = np.sum((rob * conditional**2 / var_z0)[smooth]) / (n_z * redundancy)
    return max(f_px, 0.01), max(f_z, 0.01)


def _covariance(H: np.ndarray) -> np.ndarray:
    try:
        cov = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return np.full((6, 6), np.inf)
    return 0.5 * (cov + cov.T)


def plain_covariance(R, t, x, y, weights, s_xy, s_z) -> np.ndarray:
    """Covariance (6, 6) of the weighted Procrustes solution (the paper's estimator).

    Procrustes weighs every coordinate of every point alike (``w_i |R x_i + t - y_i|^2``),
    but the noise is anisotropic: lateral ``s_xy`` and depth ``s_z`` per point (N,), the
    depth several times the lateral and acting along the viewing ray (so off-axis it moves
    the point sideways too). The covariance of *that* estimator under *that* noise is the
    sandwich ``H^-1 B H^-1`` with ``H = sum w_i J_i^T J_i`` and
    ``B = sum w_i^2 J_i^T Sigma_i J_i``. The lateral and the along-ray parts of ``Sigma_i``
    get their own variance factors from the residuals: in simulated rooms the lateral one
    is ~0.07 and the depth one ~0.3 of the nominal, and one factor for both left the
    rotation's sigma half its scatter. (An isotropic covariance from the residuals' mean
    square understated the translation by 2-3x in NEES.)
    """
    p = x @ R.T + t
    e = p - y
    J = point_jacobian(p)
    w = np.asarray(weights, dtype=float)
    w = w / w.mean()
    n = len(x)
    ray = y / y[:, 2:3]  # (X/Z, Y/Z, 1): depth noise moves a back-projected point along it
    ray_unit = ray / np.linalg.norm(ray, axis=1, keepdims=True)
    along = np.sum(e * ray_unit, axis=1)
    across_sq = np.sum(e**2, axis=1) - along**2
    redundancy = max(1.0 - 6.0 / max(3 * n, 7), 0.05)
    f_xy = max(float(np.sum(across_sq / (2.0 * s_xy**2)) / (n * redundancy)), 1e-3)
    f_z = max(float(np.sum(along**2 / (s_z**2 * np.sum(ray**2, axis=1))) / (n * redundancy)), 1e-3)
    Sigma = (f_xy * s_xy**2)[:, None, None] * np.diag([1.0, 1.0, 0.0]) + \
        (f_z * s_z**2)[:, None, None] * ray[:, :, None] * ray[:, None, :]
    H = _weighted_rows(w, J).T @ _rows(J)
    B = _weighted_rows(w**2, J).T @ _rows(np.matmul(Sigma, J))
    H_inv = _covariance(H)
    cov = H_inv @ B @ H_inv
    return 0.5 * (cov + cov.T)
