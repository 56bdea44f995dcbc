"""NAP3D: 3D-3D alignment of a rendered view to a real RGB-D frame.

Pipeline for one (real frame, rendered view) pair:

1. SIFT + FLANN matches (``matching.py``).
2. Back-projection: rendered keypoints with the rendered z-depth and the view's intrinsics
   give ``x_i`` (rendered camera); real keypoints with the sensor depth and the frame's
   intrinsics give ``y_i`` (real camera). Pairs with missing depth, depth outside the valid
   range or low opacity are dropped.
3. RANSAC over minimal 3-point Kabsch hypotheses, vectorised over hypotheses, scored by the
   paper's anisotropic residual ``r^2 = |e_xy|^2/s_xy^2 + e_z^2/s_z^2`` in the real camera,
   ``s_z`` growing with depth like the sensor's noise; adaptive iteration count; the
   consensus is refit by opacity-weighted Umeyama until the inlier set settles.
4. ``method="plain"`` stops there (the paper's variant). ``method="refined"`` (default)
   then solves weighted least squares over each inlier's reprojection (pixels, in the real
   image) and depth residuals under their noise models, with Huber weights and per-group
   variance factors, so it uses the precise real keypoint position and the depth alike.
5. The 6x6 covariance of ``T_world_cam_true`` comes from the Gauss-Newton Hessian at the
   solution, scaled by the residual variance.

Parameterisation: with ``T_true = T_world_cam_est @ inv(T_real_rendered)`` and the GTSAM
right perturbation ``T_true <- T_true @ Exp(delta)``, a point ``p`` in the real camera moves
to ``Exp(-delta) p ~ p + [p]x omega - v``, so ``dp/ddelta = [[p]x, -I]``: the covariance of
``delta`` is directly the covariance GTSAM's Pose3 prior expects (rotation first, body frame).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace

import numpy as np

from .camera import Intrinsics, RenderedView, RGBDFrame, backproject, valid_depth_mask
from .conventions import exp_se3, make_T
from .matching import Features, Matches, detect_features, match_features
from .results import Alignment

__all__ = [
    "AlignConfig",
    "align_views",
    "align_correspondences",
    "prepare_correspondences",
    "view_features",
    "Correspondences",
    "build_correspondences",
    "sample_depth",
    "weighted_umeyama",
    "kabsch_batch",
    "triad_batch",
    "anisotropic_residual_sq",
    "ransac_procrustes",
    "RansacResult",
    "refine_pose",
    "skew",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class AlignConfig:
    """Settings of one alignment. Noise sigmas describe the *real* sensor and the field.

    keypoint_sigma_px: localisation noise of one SIFT keypoint (pixels).
    depth_sigma_floor_m + depth_sigma_z2_per_m * z^2: the real depth noise at z-depth z.
    render_depth_sigma_m: error of the field's depth (0.5 cm for a well-trained field).
    inlier_chi2: RANSAC threshold on r^2 (3 dof; 11.34 is chi2(3) at 99%).
    covariance: "hessian" (Gauss-Newton Hessian with estimated variance factors) or
        "sandwich" (heteroscedasticity-consistent; for diagnostics).
    estimate_intrinsics: True: also estimate the real camera's fx, fy, cx, cy in the refinement
        (self-calibration against the field's exact 3D points: the depth residuals fix the
        pose, the pixels the intrinsics), with a prior of ``intrinsics_focal_sigma``
        (relative) and ``intrinsics_principal_sigma_px``. For cameras whose calibration
        drifted (the paper's intrinsics noise); the pose covariance then includes the
        intrinsics' uncertainty. "auto": fit both and keep the self-calibrated solution
        only when the data call for it (see :func:`align_correspondences`).
    covariance_inflation: multiplies the refined covariance. Residuals cannot show the
        part of SIFT's localisation error that the real and the rendered keypoint share, so
        the Hessian alone is ~20% optimistic in NEES; 1.2 was calibrated on simulated rooms
        21 and 22 (NEES 7.16 and 7.01 before, chi2(6) mean 6), never on the hold-out room
        the tests and evaluations use.
    """

    method: str = "refined"
    ratio: float = 0.8
    mutual: bool = False
    max_features: int = 0
    min_matches: int = 8
    min_inliers: int = 8
    min_opacity: float = 0.5
    min_depth_m: float = 0.1
    max_depth_m: float = 10.0
    keypoint_sigma_px: float = 0.7
    depth_sigma_floor_m: float = 0.002
    depth_sigma_z2_per_m: float = 1.4e-3
    render_depth_sigma_m: float = 0.005
    inlier_chi2: float = 11.34
    ransac_confidence: float = 0.999
    ransac_max_iterations: int = 2000
    ransac_batch: int = 128
    min_sample_side_m: float = 0.03
    min_sample_sine: float = 0.1
    refine_iterations: int = 8
    huber_k: float = 2.5
    covariance: str = "hessian"
    covariance_inflation: float = 1.2
    estimate_intrinsics: bool | str = "auto"
    auto_intrinsics_ratio: float = 1.5
    intrinsics_focal_sigma: float = 0.05
    intrinsics_principal_sigma_px: float = 10.0
    seed: int = 0

    def __post_init__(self) -> None:
        if self.method not in ("refined", "plain"):
            raise ValueError(f"AlignConfig.method must be 'refined' or 'plain', got {self.method!r}")
        if self.min_inliers < 3 or self.min_matches < 3:
            raise ValueError("min_matches and min_inliers must be at least 3")


# --- geometry helpers ----------------------------------------------------------------------


def skew(p: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrices (..., 3, 3) of vectors (..., 3): ``skew(a) @ b = a x b``."""
    p = np.asarray(p, dtype=float)
    S = np.zeros(p.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -p[..., 2], p[..., 1]
    S[..., 1, 0], S[..., 1, 2] = p[..., 2], -p[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -p[..., 1], p[..., 0]
    return S


def weighted_umeyama(x: np.ndarray, y: np.ndarray, weights: np.ndarray | None = None):
    """Rigid ``(R, t)`` minimising ``sum_i w_i |R x_i + t - y_i|^2`` (no scale).

    x, y: (N, 3); weights (N,) >= 0. Rotation from the SVD of the weighted cross-covariance,
    with the reflection fix (det R = +1).
    """
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    w = np.ones(len(x)) if weights is None else np.asarray(weights, dtype=float)
    w = w / w.sum()
    cx, cy = w @ x, w @ y
    H = (x - cx).T @ ((y - cy) * w[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return R, cy - R @ cx


def kabsch_batch(x: np.ndarray, y: np.ndarray):
    """Unweighted Kabsch for K point sets at once: x, y (K, M, 3) -> R (K, 3, 3), t (K, 3)."""
    cx, cy = x.mean(axis=1), y.mean(axis=1)
    H = np.einsum("kni,knj->kij", x - cx[:, None], y - cy[:, None])
    U, _, Vt = np.linalg.svd(H)
    V = np.swapaxes(Vt, 1, 2)
    d = np.sign(np.linalg.det(V @ np.swapaxes(U, 1, 2)))
    d[d == 0] = 1.0
    V[:, :, 2] *= d[:, None]
    R = V @ np.swapaxes(U, 1, 2)
    t = cy - np.einsum("kij,kj->ki", R, cx)
    return R, t


def triad_batch(x: np.ndarray, y: np.ndarray):
    """Rigid transforms from K minimal 3-point samples at once (the triad method).

    x, y: (K, 3, 3) samples -> R (K, 3, 3), t (K, 3). Each sample's triangle spans an
    orthonormal frame in both sets; the rotation maps one frame onto the other and the
    translation the centroids. Exact for noise-free points, no SVD per hypothesis, so
    hundreds of hypotheses cost well under a millisecond; the consensus refit is the
    weighted Umeyama/SVD solution.
    """

    def frames(p: np.ndarray) -> np.ndarray:
        a = p[:, 1] - p[:, 0]
        normal = np.cross(a, p[:, 2] - p[:, 0])
        a = a / np.linalg.norm(a, axis=1, keepdims=True)
        normal = normal / np.linalg.norm(normal, axis=1, keepdims=True)
        return np.stack([a, np.cross(normal, a), normal], axis=2)

    R = frames(y) @ np.swapaxes(frames(x), 1, 2)
    t = y.mean(axis=1) - np.einsum("kij,kj->ki", R, x.mean(axis=1))
    return R, t


def anisotropic_residual_sq(R: np.ndarray, t: np.ndarray, x: np.ndarray, y: np.ndarray,
                            inv_sxy2: np.ndarray, inv_sz2: np.ndarray) -> np.ndarray:
    """The paper's ``r_i^2`` for one (R (3,3), t) or K stacked hypotheses (K,3,3), (K,3).

    x, y: (N, 3) rendered / real camera points; inv_sxy2, inv_sz2: (N,) inverse variances.
    Returns (N,) or (K, N).
    """
    if R.ndim == 2:
        e = x @ R.T + t - y
        return (e[:, 0] ** 2 + e[:, 1] ** 2) * inv_sxy2 + e[:, 2] ** 2 * inv_sz2
    # One (3K, 3) x (3, N) product instead of K small ones, then in-place float32 arithmetic:
    # scoring hypotheses needs no more precision and halves the memory traffic.
    k = len(R)
    e = (R.reshape(-1, 3).astype(np.float32) @ x.T.astype(np.float32)).reshape(k, 3, -1)
    e += t.astype(np.float32)[:, :, None]
    e -= y.T.astype(np.float32)[None]
    np.square(e, out=e)
    out = e[:, 0]
    out += e[:, 1]
    out *= inv_sxy2.astype(np.float32)
    e[:, 2] *= inv_sz2.astype(np.float32)
    out += e[:, 2]
    return out


def sample_depth(depth_m: np.ndarray, uv: np.ndarray, max_rel_jump: float = 0.03) -> np.ndarray:
    """Depth (N,) at sub-pixel keypoints ``uv`` (N, 2); NaN where missing.

    Where the four neighbours are valid and agree within ``max_rel_jump``, the lookup is
    bilinear in *inverse* depth (exact on planes); across an edge it falls back to the
    nearest pixel so foreground and background are never mixed.
    """
    depth = np.asarray(depth_m, dtype=np.float64)
    h, w = depth.shape
    uv = np.asarray(uv, dtype=float)
    out = np.full(len(uv), np.nan)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
    if not inside.any():
        return out
    u, v = uv[inside, 0], uv[inside, 1]
    u0 = np.clip(np.floor(u).astype(int), 0, w - 2)
    v0 = np.clip(np.floor(v).astype(int), 0, h - 2)
    du, dv = u - u0, v - v0
    corners = np.stack([depth[v0, u0], depth[v0, u0 + 1], depth[v0 + 1, u0], depth[v0 + 1, u0 + 1]], axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        ok = np.all(np.isfinite(corners) & (corners > 0), axis=1)
        spread = (corners.max(axis=1) - corners.min(axis=1)) / corners.min(axis=1)
        smooth = ok & (spread <= max_rel_jump)
        inv = 1.0 / corners
        weights = np.stack([(1 - du) * (1 - dv), du * (1 - dv), (1 - du) * dv, du * dv], axis=1)
        bilinear = 1.0 / np.sum(inv * weights, axis=1)
    nearest = depth[np.clip(np.round(v).astype(int), 0, h - 1), np.clip(np.round(u).astype(int), 0, w - 1)]
    nearest = np.where(np.isfinite(nearest) & (nearest > 0), nearest, np.nan)
    out[inside] = np.where(smooth, bilinear, nearest)
    return out


# --- correspondences -------------------------------------------------------------------------


@dataclass(frozen=True)
class Correspondences:
    """Matched 3D points and what the refinement needs about them.

    x: (N, 3) rendered camera; y: (N, 3) real camera; uv_real: (N, 2) real keypoints;
    opacity: (N,) field opacity at the rendered keypoint; depth_grad: (N, 2) gradient of the
    rendered z-depth at the rendered keypoint in metres per pixel (d/du, d/dv): how much a
    keypoint's position error moves its depth, so the refinement can whiten the correlated
    reprojection and depth residuals of one correspondence.
    """

    x: np.ndarray
    y: np.ndarray
    uv_real: np.ndarray
    opacity: np.ndarray
    num_matches: int
    reason: str = ""
    depth_grad: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.x)


def build_correspondences(real: RGBDFrame, view: RenderedView, matches: Matches,
                          config: AlignConfig) -> Correspondences:
    """Back-project matched pixels (``uv_a`` real, ``uv_b`` rendered) and drop invalid pairs.

    ``reason`` is set when no pair survives (no valid depth, low opacity).
    """
    z_real = sample_depth(real.depth_m, matches.uv_a)
    z_rend = sample_depth(view.depth_m, matches.uv_b)
    h, w = view.opacity.shape
    ij = np.clip(np.round(matches.uv_b).astype(int), [0, 0], [w - 1, h - 1]) if len(matches) else np.zeros((0, 2), int)
    opacity = view.opacity[ij[:, 1], ij[:, 0]].astype(float)
    depth_ok = valid_depth_mask(z_real, config.min_depth_m, config.max_depth_m) & valid_depth_mask(
        z_rend, config.min_depth_m, config.max_depth_m)
    opaque = opacity >= config.min_opacity
    keep = depth_ok & opaque
    reason = ""
    if len(matches) and not keep.any():
        reason = "no valid depth at the matches" if not depth_ok.any() else "low opacity at the matches"
    x = backproject(matches.uv_b[keep], z_rend[keep], view.intrinsics)
    y = backproject(matches.uv_a[keep], z_real[keep], real.intrinsics)
    grad = depth_gradient(view.depth_m, matches.uv_b[keep])
    return Correspondences(x, y, matches.uv_a[keep], opacity[keep], len(matches), reason, grad)


def depth_gradient(depth_m: np.ndarray, uv: np.ndarray, max_rel_jump: float = 0.02) -> np.ndarray:
    """Central-difference z-depth gradient (N, 2) in m/px at pixels ``uv`` (N, 2).

    NaN across a depth edge or next to a hole: there the depth at the keypoint is not a
    smooth function of its position, and the refinement drops that depth residual's weight.
    """
    depth = np.asarray(depth_m, dtype=np.float64)
    h, w = depth.shape
    u = np.clip(np.round(uv[:, 0]).astype(int), 1, w - 2)
    v = np.clip(np.round(uv[:, 1]).astype(int), 1, h - 2)
    left, right, up, down, centre = depth[v, u - 1], depth[v, u + 1], depth[v - 1, u], depth[v + 1, u], depth[v, u]
    grad = np.stack([(right - left) / 2.0, (down - up) / 2.0], axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        neighbours = np.stack([left, right, up, down], axis=1)
        ok = np.all(np.isfinite(neighbours) & (neighbours > 0), axis=1) & (centre > 0)
        ok &= np.max(np.abs(neighbours - centre[:, None]), axis=1) <= max_rel_jump * centre
    grad[~ok] = np.nan
    return grad


def _noise_sigmas(corr: Correspondences, intrinsics: Intrinsics, config: AlignConfig):
    """Per-correspondence lateral and depth sigmas (N,) of the 3D residual, real camera."""
    z = corr.y[:, 2]
    f = 0.5 * (intrinsics.fx + intrinsics.fy)
    # Both keypoints are localised with sigma_px; each shifts its point laterally by z*s/f.
    s_xy = np.sqrt(2.0) * config.keypoint_sigma_px * z / f
    if config.estimate_intrinsics is True:
        # Intrinsics still to be estimated: their prior uncertainty moves the real point
        # sideways too, more the farther it is from the principal point.
        off_axis_px = np.hypot(corr.uv_real[:, 0] - intrinsics.cx, corr.uv_real[:, 1] - intrinsics.cy)
        s_calib_px = np.hypot(config.intrinsics_focal_sigma * off_axis_px, config.intrinsics_principal_sigma_px)
        s_xy = np.hypot(s_xy, s_calib_px * z / f)
    s_z = np.sqrt((config.depth_sigma_floor_m + config.depth_sigma_z2_per_m * z**2) ** 2
                  + config.render_depth_sigma_m**2)
    return s_xy, s_z


# --- RANSAC ------------------------------------------------------------------------------------


@dataclass
class RansacResult:
    R: np.ndarray
    t: np.ndarray
    inliers: np.ndarray
    iterations: int
    reason: str = ""

    @property
    def success(self) -> bool:
        return not self.reason


def _degenerate(samples_x: np.ndarray, min_side_m: float, min_sine: float) -> np.ndarray:
    """True for 3-point samples (K, 3, 3) that are too small or nearly collinear."""
    a = samples_x[:, 1] - samples_x[:, 0]
    b = samples_x[:, 2] - samples_x[:, 0]
    c = samples_x[:, 2] - samples_x[:, 1]
    sides = np.stack([np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1), np.linalg.norm(c, axis=1)], axis=1)
    area2 = np.linalg.norm(np.cross(a, b), axis=1)
    # sine of the smallest angle ~ twice the area over the product of the two longest sides
    longest = np.sort(sides, axis=1)
    sine = area2 / np.maximum(longest[:, 1] * longest[:, 2], 1e-12)
    return (sides.min(axis=1) < min_side_m) | (sine < min_sine)


def ransac_procrustes(x: np.ndarray, y: np.ndarray, weights: np.ndarray, s_xy: np.ndarray, s_z: np.ndarray,
                      config: AlignConfig | None = None, rng: np.random.Generator | None = None) -> RansacResult:
    """RANSAC over minimal 3-point hypotheses with the anisotropic residual, then the
    opacity-weighted Umeyama refit of the consensus until its inlier set settles.

    x, y: (N, 3) rendered / real camera points; weights (N,) opacity; s_xy, s_z (N,) sigmas.
    """
    config = config or AlignConfig()
    rng = rng if rng is not None else np.random.default_rng(config.seed)
    n = len(x)
    if n < 3:
        return RansacResult(np.eye(3), np.zeros(3), np.zeros(n, bool), 0, "too few matches")
    inv_sxy2, inv_sz2 = 1.0 / s_xy**2, 1.0 / s_z**2
    thr = config.inlier_chi2
    best_cost, best = np.inf, None
    needed, done, any_valid = config.ransac_max_iterations, 0, False
    while done < min(needed, config.ransac_max_iterations):
        k = config.ransac_batch
        # Three distinct indices per hypothesis.
        idx = np.argsort(rng.random((k, n)), axis=1)[:, :3] if n < 64 else _three_distinct(rng, k, n)
        done += k
        sx, sy = x[idx], y[idx]
        ok = ~_degenerate(sx, config.min_sample_side_m, config.min_sample_sine)
        if not ok.any():
            continue
        any_valid = True
        with np.errstate(invalid="ignore", divide="ignore"):
            R, t = triad_batch(sx[ok], sy[ok])
        finite = np.all(np.isfinite(R), axis=(1, 2)) & np.all(np.isfinite(t), axis=1)
        if not finite.all():  # a sample degenerate on the real side
            R, t = R[finite], t[finite]
            if len(R) == 0:
                continue
        if n > 4 * _PREVIEW_POINTS:
            # Preemptive scoring: rank all hypotheses on a random preview of the points and
            # score only the best tenth on all of them.
            preview = rng.choice(n, _PREVIEW_POINTS, replace=False)
            r2p = anisotropic_residual_sq(R, t, x[preview], y[preview], inv_sxy2[preview], inv_sz2[preview])
            keep = np.argsort(np.minimum(r2p, thr).sum(axis=1))[: max(8, len(R) // 10)]
            R, t = R[keep], t[keep]
        r2 = anisotropic_residual_sq(R, t, x, y, inv_sxy2, inv_sz2)
        # MSAC: inliers cost their residual, outliers the threshold; lower is better.
        cost = np.minimum(r2, thr).sum(axis=1)
        j = int(np.argmin(cost))
        if cost[j] < best_cost:
            best_cost, best = cost[j], (R[j], t[j])
            inlier_ratio = np.mean(r2[j] < thr)
            needed = _iterations_needed(inlier_ratio, config.ransac_confidence)
    if not any_valid or best is None:
        return RansacResult(np.eye(3), np.zeros(3), np.zeros(n, bool), done, "degenerate geometry")
    R, t = best
    inliers = anisotropic_residual_sq(R, t, x, y, inv_sxy2, inv_sz2) < thr
    for _ in range(10):  # local optimisation: refit on the consensus until it settles
        if inliers.sum() < 3:
            break
        R, t = weighted_umeyama(x[inliers], y[inliers], weights[inliers])
        new = anisotropic_residual_sq(R, t, x, y, inv_sxy2, inv_sz2) < thr
        if np.array_equal(new, inliers):
            break
        inliers = new
    return RansacResult(R, t, inliers, done)


_PREVIEW_POINTS = 64


def _three_distinct(rng: np.random.Generator, k: int, n: int) -> np.ndarray:
    i = rng.integers(0, n, k)
    j = (i + rng.integers(1, n, k)) % n
    m = rng.integers(0, n - 2, k)
    # Map m into [0, n) skipping i and j.
    lo, hi = np.minimum(i, j), np.maximum(i, j)
    m = m + (m >= lo)
    m = m + (m >= hi)
    return np.stack([i, j, m], axis=1)


def _iterations_needed(inlier_ratio: float, confidence: float) -> int:
    w3 = inlier_ratio**3
    if w3 <= 0 or confidence >= 1.0:
        return 10**9
    if w3 >= 1:
        return 1
    return int(np.ceil(np.log(1 - confidence) / np.log(1 - w3)))


# --- refinement and covariance -------------------------------------------------------------------


def _point_jacobian(p: np.ndarray) -> np.ndarray:
    """d p / d delta (N, 3, 6) for the right perturbation of the real camera pose."""
    J = np.zeros((len(p), 3, 6))
    J[:, :, :3] = skew(p)
    J[:, :, 3:] = -np.eye(3)
    return J


def _reprojection_terms(p: np.ndarray, uv: np.ndarray, K: Intrinsics):
    """Residuals (N, 2) pixels and Jacobians (N, 2, 6) of projecting p into the real image."""
    z = p[:, 2]
    res = np.stack([K.fx * p[:, 0] / z + K.cx - uv[:, 0], K.fy * p[:, 1] / z + K.cy - uv[:, 1]], axis=1)
    Jproj = np.zeros((len(p), 2, 3))
    Jproj[:, 0, 0] = K.fx / z
    Jproj[:, 0, 2] = -K.fx * p[:, 0] / z**2
    Jproj[:, 1, 1] = K.fy / z
    Jproj[:, 1, 2] = -K.fy * p[:, 1] / z**2
    return res, Jproj @ _point_jacobian(p)


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
    for iteration in range(config.refine_iterations + 2):
        p = x @ T[:3, :3].T + T[:3, 3]
        if np.any(p[:, 2] <= 1e-6):
            return None
        r_px, J_px = _reprojection_terms(p, uv, _with_intrinsics_delta(intrinsics, d_K))
        r_z = p[:, 2] - z_real
        J_z = _point_jacobian(p)[:, 2, :]
        if calibrate:
            J_px = np.concatenate([J_px, _intrinsics_jacobian(p)], axis=2)
            J_z = np.concatenate([J_z, np.zeros((n, 4))], axis=1)
        r, J, W = _stack_rows(r_px, J_px, r_z, J_z, grad, var_px0 * scale_px, var_z0 * scale_z,
                              use_reprojection, use_depth)
        norm_sq = np.einsum("ni,nij,nj->n", r, W, r)
        rob = _huber_weights(np.sqrt(norm_sq / rows), config.huber_k)
        H = np.einsum("n,nri,nrs,nsj->ij", rob, J, W, J)
        g = np.einsum("n,nri,nrs,ns->i", rob, J, W, r)
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
            scale_px, scale_z = _variance_factors(r_px, r_z, grad, rob, var_px0, var_z0, use_reprojection,
                                                  use_depth)
        elif iteration > 3 and np.linalg.norm(delta) < 1e-10:
            break
    cov = _covariance(H)[:6, :6]  # the pose block: intrinsics, if estimated, marginalised
    if config.covariance == "sandwich":
        # Heteroscedasticity-consistent (HC1) sandwich: the spread of each correspondence's
        # actual residual, not only the model's, enters the covariance.
        score = rob[:, None] * np.einsum("nri,nrs,ns->ni", J, W, r)
        B = score.T @ score * n / max(n - 6, 1)
        full = _covariance(H)
        cov = (full @ B @ full)[:6, :6]
        cov = 0.5 * (cov + cov.T)
    if return_intrinsics:
        diagnostics = {"pixel_variance_factor": float(scale_px), "depth_variance_factor": float(scale_z)}
        return T[:3, :3], T[:3, 3], cov, np.sqrt(norm_sq), _with_intrinsics_delta(intrinsics, d_K), diagnostics
    return T[:3, :3], T[:3, 3], cov, np.sqrt(norm_sq)


def _stack_rows(r_px, J_px, r_z, J_z, grad, var_px, var_z, use_reprojection, use_depth):
    """Residuals (N, m), Jacobians (N, m, 6) and information matrices (N, m, m) per
    correspondence, m = 3 (pixels + depth), 2 (pixels) or 1 (depth)."""
    n = len(r_z)
    if use_reprojection and use_depth:
        C = np.zeros((n, 3, 3))
        C[:, 0, 0] = C[:, 1, 1] = var_px
        C[:, :2, 2] = C[:, 2, :2] = var_px * grad
        C[:, 2, 2] = var_px * np.sum(grad**2, axis=1) + var_z
        return np.concatenate([r_px, r_z[:, None]], 1), np.concatenate([J_px, J_z[:, None]], 1), np.linalg.inv(C)
    if use_reprojection:
        W = np.broadcast_to(np.eye(2) / var_px, (n, 2, 2))
        return r_px, J_px, W
    var = var_px * np.sum(grad**2, axis=1) + var_z
    return r_z[:, None], J_z[:, None], (1.0 / var)[:, None, None]


def _variance_factors(r_px, r_z, grad, rob, var_px0, var_z0, use_reprojection, use_depth):
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


def _plain_covariance(R, t, x, y, weights) -> np.ndarray:
    """Covariance of the weighted Procrustes solution from its isotropic 3D residuals."""
    p = x @ R.T + t
    e = p - y
    J = _point_jacobian(p)
    w = weights / weights.mean()
    H = np.einsum("n,nri,nrj->ij", w, J, J)
    dof = max(3 * len(x) - 6, 1)
    sigma2 = float(np.sum(w * np.sum(e**2, axis=1)) / dof)
    return _covariance(H / max(sigma2, 1e-12))


# --- public API -----------------------------------------------------------------------------------


def align_correspondences(corr: Correspondences, intrinsics: Intrinsics, config: AlignConfig | None = None,
                          timings: dict | None = None) -> Alignment:
    """NAP3D on ready-made correspondences (rendered ``x``, real ``y``). Never raises.

    With ``estimate_intrinsics="auto"`` both models are fitted and the self-calibrated one
    is kept only when it explains the pixels much better (the pixel variance factor drops by
    more than ``auto_intrinsics_ratio``): with a good calibration, four extra parameters
    barely move it; with a drifted one, the fixed model's pixel residuals are several times
    the keypoint noise.
    """
    config = config or AlignConfig()
    if config.estimate_intrinsics == "auto" and config.method == "refined":
        fixed = align_correspondences(corr, intrinsics, replace(config, estimate_intrinsics=False), timings)
        calibrated = align_correspondences(corr, intrinsics, replace(config, estimate_intrinsics=True), {})
        if not calibrated.success:
            return fixed
        if not fixed.success:
            return calibrated
        ratio = fixed.diagnostics["pixel_variance_factor"] / max(calibrated.diagnostics["pixel_variance_factor"],
                                                                 1e-12)
        chosen = calibrated if ratio > config.auto_intrinsics_ratio else fixed
        chosen.diagnostics["intrinsics_ratio"] = float(ratio)
        return chosen
    timings = {} if timings is None else timings
    method = f"nap3d-{config.method}"
    n = len(corr)
    if corr.reason:
        return Alignment.failure(corr.reason, corr.num_matches, method=method, timings_s=timings)
    if n < config.min_matches:
        return Alignment.failure(f"too few matches with valid depth ({n} < {config.min_matches})",
                                 corr.num_matches, method=method, timings_s=timings)
    s_xy, s_z = _noise_sigmas(corr, intrinsics, config)
    t0 = time.perf_counter()
    ransac = ransac_procrustes(corr.x, corr.y, corr.opacity, s_xy, s_z, config)
    timings["ransac"] = time.perf_counter() - t0
    if not ransac.success:
        return Alignment.failure(ransac.reason, corr.num_matches, method=method, timings_s=timings)
    inliers = ransac.inliers
    if inliers.sum() < config.min_inliers:
        return Alignment.failure(f"too few inliers ({int(inliers.sum())} < {config.min_inliers})",
                                 corr.num_matches, int(inliers.sum()), method=method, timings_s=timings)
    t0 = time.perf_counter()
    R, t = ransac.R, ransac.t
    diagnostics: dict = {}
    K_refined = intrinsics
    if config.method == "plain":
        cov = _plain_covariance(R, t, corr.x[inliers], corr.y[inliers], corr.opacity[inliers])
    else:
        refined = refine_pose(R, t, _subset(corr, inliers), intrinsics, config, return_intrinsics=True)
        if refined is None:
            return Alignment.failure("degenerate geometry (singular refinement)", corr.num_matches,
                                     int(inliers.sum()), method=method, timings_s=timings)
        R, t, cov, _, K_refined, diagnostics = refined
        # The refined pose (and intrinsics) may admit points RANSAC's cruder estimate
        # rejected, or the reverse: re-select the inliers once and refine again.
        for _ in range(4 if config.estimate_intrinsics is True else 1):
            y = backproject(corr.uv_real, corr.y[:, 2], K_refined) if config.estimate_intrinsics is True else corr.y
            new_inliers = anisotropic_residual_sq(R, t, corr.x, y, 1 / s_xy**2, 1 / s_z**2) < config.inlier_chi2
            if new_inliers.sum() < config.min_inliers or np.array_equal(new_inliers, inliers):
                break
            again = refine_pose(R, t, _subset(corr, new_inliers), intrinsics, config, return_intrinsics=True)
            if again is None:
                break
            inliers = new_inliers
            R, t, cov, _, K_refined, diagnostics = again
        cov = cov * config.covariance_inflation
    timings["refine"] = time.perf_counter() - t0
    if not np.all(np.isfinite(cov)) or np.min(np.linalg.eigvalsh(cov)) <= 0:
        return Alignment.failure("degenerate geometry (covariance not positive definite)", corr.num_matches,
                                 int(inliers.sum()), method=method, timings_s=timings)
    e = corr.x[inliers] @ R.T + t - corr.y[inliers]
    return Alignment(
        T_real_rendered=make_T(R, t),
        covariance=cov,
        num_matches=corr.num_matches,
        num_inliers=int(inliers.sum()),
        inlier_rmse_m=float(np.sqrt(np.mean(np.sum(e**2, axis=1)))),
        success=True,
        method=method,
        timings_s=timings,
        inlier_mask=inliers,
        diagnostics={**diagnostics, "intrinsics": K_refined.to_dict()} if config.estimate_intrinsics is True else diagnostics,
    )


def _subset(corr: Correspondences, mask: np.ndarray) -> Correspondences:
    grad = None if corr.depth_grad is None else corr.depth_grad[mask]
    return replace(corr, x=corr.x[mask], y=corr.y[mask], uv_real=corr.uv_real[mask], opacity=corr.opacity[mask],
                   depth_grad=grad)


def prepare_correspondences(real: RGBDFrame, view: RenderedView, config: AlignConfig | None = None,
                            timings: dict | None = None, feats_real: Features | None = None,
                            feats_view: Features | None = None) -> tuple[Correspondences | None, str]:
    """SIFT + FLANN + back-projection for one pair: ``(correspondences, "")`` or
    ``(None, reason)``. NAP3D and the PnP baseline both start from this, so an evaluation
    compares them on the very same matches. Features already computed for an image can be
    passed in (``feats_real``, ``feats_view``) to skip detecting them again."""
    config = config or AlignConfig()
    timings = {} if timings is None else timings
    t0 = time.perf_counter()
    if feats_real is None:
        feats_real = detect_features(real.rgb, config.max_features)
    if feats_view is None:
        feats_view = view_features(view, config)
    timings["sift"] = time.perf_counter() - t0
    if len(feats_real) < 3:
        return None, "no keypoints in the real image"
    if len(feats_view) < 3:
        return None, "no keypoints in the rendered view"
    t0 = time.perf_counter()
    matches = match_features(feats_real, feats_view, ratio=config.ratio, mutual=config.mutual)
    timings["flann"] = time.perf_counter() - t0
    if len(matches) < config.min_matches:
        return None, f"too few matches ({len(matches)} < {config.min_matches})"
    corr = build_correspondences(real, view, matches, config)
    if corr.reason:
        return None, corr.reason
    return corr, ""


def view_features(view: RenderedView, config: AlignConfig | None = None) -> Features:
    """SIFT on a rendered view, only where the field is opaque."""
    config = config or AlignConfig()
    return detect_features(view.rgb, config.max_features, mask=view.opacity >= config.min_opacity)


def align_views(real: RGBDFrame, view: RenderedView, config: AlignConfig | None = None) -> Alignment:
    """NAP3D between a real RGB-D frame and the view a field rendered at the believed pose.

    Returns an :class:`Alignment` whose ``T_real_rendered`` maps rendered-camera points into
    the real camera; ``success=False`` with a ``reason`` on bad data. Never raises on data.
    """
    config = config or AlignConfig()
    method = f"nap3d-{config.method}"
    timings: dict = {}
    try:
        corr, reason = prepare_correspondences(real, view, config, timings)
        if corr is None:
            return Alignment.failure(reason, method=method, timings_s=timings)
        return align_correspondences(corr, real.intrinsics, config, timings)
    except (ValueError, np.linalg.LinAlgError) as exc:  # numerical trouble is a failed alignment, not a crash
        log.warning("alignment failed: %s", exc)
        return Alignment.failure(f"numerical failure: {exc}", method=method, timings_s=timings)
