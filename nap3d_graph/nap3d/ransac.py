"""Rigid fits and RANSAC for 3D-3D correspondences.

Weighted Umeyama (SVD with the reflection fix), batched minimal-sample solvers, the paper's
anisotropic residual ``r^2 = |e_xy|^2/s_xy^2 + e_z^2/s_z^2`` in the real camera, and
RANSAC over 3-point hypotheses (vectorised over hypotheses, preemptive scoring, adaptive
iteration count, consensus refit until the inlier set settles).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import AlignConfig

__all__ = ["weighted_umeyama", "similarity_scale", "similarity_batch", "ransac_scale", "kabsch_batch", "triad_batch", "anisotropic_residual_sq",
           "RansacResult", "ransac_procrustes"]


# --- geometry helpers ----------------------------------------------------------------------


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


def similarity_scale(x: np.ndarray, y: np.ndarray, weights: np.ndarray | None = None) -> tuple[float, float]:
    """Scale ``s`` of the weighted similarity ``y = s R x + t`` (Umeyama 1991) and its sigma.

    The paper's Procrustes gives scale as well as rotation and translation: between rendered
    points ``x`` and real points ``y`` (N, 3) it is the ratio of the real depth's metre to
    the field's (a depth sensor a few percent off; a wrong match set). The sigma is the
    residual's RMS per coordinate over the points' spread (``sqrt(sum w |x - x_bar|^2)``).
    """
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    w = np.ones(len(x)) if weights is None else np.asarray(weights, dtype=float)
    w = w / w.sum()
    cx, cy = w @ x, w @ y
    xc, yc = x - cx, y - cy
    var_x = float(w @ np.sum(xc**2, axis=1))
    if var_x <= 0:
        return float("nan"), float("inf")
    H = xc.T @ (yc * w[:, None])
    U, S, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    D = np.diag([1.0, 1.0, d])
    scale = float(np.trace(np.diag(S) @ D) / var_x)
    R = Vt.T @ D @ U.T
    residual = yc - scale * xc @ R.T
    rms = float(np.sqrt(w @ np.sum(residual**2, axis=1) / 3.0))
    return scale, rms / np.sqrt(var_x * len(x))


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


def similarity_batch(x: np.ndarray, y: np.ndarray):
    """Umeyama similarity for K point sets at once: x, y (K, M, 3) -> scale (K,), R (K, 3, 3),
    t (K, 3) with ``y = s R x + t``."""
    cx, cy = x.mean(axis=1), y.mean(axis=1)
    xc, yc = x - cx[:, None], y - cy[:, None]
    H = np.einsum("kni,knj->kij", xc, yc)
    U, S, Vt = np.linalg.svd(H)
    V = np.swapaxes(Vt, 1, 2)
    d = np.sign(np.linalg.det(V @ np.swapaxes(U, 1, 2)))
    d[d == 0] = 1.0
    V[:, :, 2] *= d[:, None]
    R = V @ np.swapaxes(U, 1, 2)
    var_x = np.einsum("kni,kni->k", xc, xc)
    scale = (S[:, 0] + S[:, 1] + d * S[:, 2]) / np.maximum(var_x, 1e-12)
    t = cy - scale[:, None] * np.einsum("kij,kj->ki", R, cx)
    return scale, R, t


def ransac_scale(x: np.ndarray, y: np.ndarray, s_xy: np.ndarray, s_z: np.ndarray, config: AlignConfig | None = None,
                 rng: np.random.Generator | None = None) -> tuple[float, float, np.ndarray]:
    """The scale of the real points against the rendered ones, by RANSAC over similarity
    hypotheses (``y = s R x + t``) with the paper's anisotropic residual.

    A rigid RANSAC cannot see a depth scale error: it keeps the points of one depth band,
    where the scale looks like a translation along the axis, and rejects the rest. Returns
    ``(scale, sigma, inliers)``; ``(1.0, inf, none)`` when there is no consensus.
    """
    config = config or AlignConfig()
    rng = rng if rng is not None else np.random.default_rng(config.seed + 1)
    n = len(x)
    if n < 4:
        return 1.0, float("inf"), np.zeros(n, bool)
    inv_sxy2, inv_sz2 = 1.0 / s_xy**2, 1.0 / s_z**2
    thr = config.inlier_chi2
    best_cost, best = np.inf, None
    for _ in range(max(1, config.ransac_max_iterations // (4 * config.ransac_batch))):
        idx = _three_distinct(rng, config.ransac_batch, n) if n >= 64 else \
            np.argsort(rng.random((config.ransac_batch, n)), axis=1)[:, :3]
        sx, sy = x[idx], y[idx]
        ok = ~_degenerate(sx, config.min_sample_side_m, config.min_sample_sine)
        if not ok.any():
            continue
        with np.errstate(invalid="ignore", divide="ignore"):
            scale, R, t = similarity_batch(sx[ok], sy[ok])
        good = np.isfinite(scale) & (scale > 0.5) & (scale < 2.0)
        if not good.any():
            continue
        r2 = anisotropic_residual_sq(R[good] * scale[good, None, None], t[good], x, y, inv_sxy2, inv_sz2)
        cost = np.minimum(r2, thr).sum(axis=1)
        j = int(np.argmin(cost))
        if cost[j] < best_cost:
            best_cost, best = cost[j], (scale[good][j], R[good][j], t[good][j])
    if best is None:
        return 1.0, float("inf"), np.zeros(n, bool)
    scale, R, t = best
    inliers = anisotropic_residual_sq(R * scale, t, x, y, inv_sxy2, inv_sz2) < thr
    for _ in range(5):  # refit on the consensus until it settles
        if inliers.sum() < 4:
            break
        scale, sigma = similarity_scale(x[inliers], y[inliers])
        R, t = weighted_umeyama(x[inliers] * scale, y[inliers])
        new = anisotropic_residual_sq(R * scale, t, x, y, inv_sxy2, inv_sz2) < thr
        if np.array_equal(new, inliers):
            break
        inliers = new
    if inliers.sum() < 4:
        return 1.0, float("inf"), inliers
    scale, sigma = similarity_scale(x[inliers], y[inliers])
    return float(scale), float(sigma), inliers

