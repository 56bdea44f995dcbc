"""From matched pixels to 3D correspondences: depth lookup, back-projection, noise sigmas.

Rendered keypoints with the rendered z-depth and the view's intrinsics give ``x_i``
(rendered camera); real keypoints with the sensor depth and the frame's intrinsics give
``y_i`` (real camera). Pairs with missing depth, depth outside the valid range or low
opacity are dropped.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..camera import Intrinsics, RenderedView, RGBDFrame, backproject, valid_depth_mask
from .config import AlignConfig
from .matching import Matches

__all__ = ["Correspondences", "build_correspondences", "sample_depth", "depth_gradient", "noise_sigmas",
           "subset"]


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
        reason += _depth_unit_hint(z_real, config)
    x = backproject(matches.uv_b[keep], z_rend[keep], view.intrinsics)
    y = backproject(matches.uv_a[keep], z_real[keep], real.intrinsics)
    grad = depth_gradient(view.depth_m, matches.uv_b[keep])
    return Correspondences(x, y, matches.uv_a[keep], opacity[keep], len(matches), reason, grad)


def _depth_unit_hint(z_real: np.ndarray, config: AlignConfig) -> str:
    """A hint when the real depth is valid but far out of range: the unit looks wrong."""
    z = z_real[np.isfinite(z_real) & (z_real > 0)]
    if z.size < 3:
        return ""
    median = float(np.median(z))
    if median > 50.0 * config.max_depth_m / 10.0 and median > 100:
        return (f" (the real depth's median is {median:.0f}: it looks like millimetres; depth_m must be in metres, "
                "e.g. divide by 1000)")
    if median < config.min_depth_m:
        return f" (the real depth's median is {median:.4f} m: is its unit or scale wrong?)"
    return ""


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


def noise_sigmas(corr: Correspondences, intrinsics: Intrinsics, config: AlignConfig):
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


def subset(corr: Correspondences, mask: np.ndarray) -> Correspondences:
    grad = None if corr.depth_grad is None else corr.depth_grad[mask]
    return replace(corr, x=corr.x[mask], y=corr.y[mask], uv_real=corr.uv_real[mask], opacity=corr.opacity[mask],
                   depth_grad=grad)
