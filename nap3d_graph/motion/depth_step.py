"""A step measured from depth alone, for when the colour has nothing to match.

A camera that faces a blank wall (a corridor's end, a painted door, a dark cupboard) gives the
visual odometry no features, and its fallback, constant velocity, carries the camera on at the
last speed while the real one slows, turns or stops: a walk that ends facing a wall was placed
metres through it. The wall's depth still says how far away it is and how the camera is tilted
to it (three of the six directions of a step; a floor or a corner in view says more).

:func:`depth_step` aligns the current frame's depth to the previous frame's, point to plane
(projective association, Gauss-Newton on the right perturbation), with the constant-velocity
guess as a prior: where the depth constrains the step it wins, where it cannot (sliding along
a plane, turning about its normal) the guess holds, and the covariance says which is which.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..camera import Intrinsics, backproject_depth, project, valid_depth_mask
from ..conventions import exp_se3, log_se3

__all__ = ["DepthStep", "depth_step", "heading_prior"]

#: Depth noise of one point in the alignment (m): a structured-light or stereo camera's at 1-2 m.
DEPTH_SIGMA_M = 0.01
#: Points whose depths differ by more than this share of their depth per pixel between them
#: share no plane (an object's edge): no normal there.
EDGE_JUMP = 0.05
#: Normals from points this many pixels apart: one pixel apart, a z^2 sensor's noise at 1.5 m
#: (3 mm against 6 mm between the points) turns them by tens of degrees.
NORMAL_REACH_PX = 4
#: A step farther from the guess than this (Mahalanobis squared under the guess's covariance,
#: chi-square 6 dof at 99.9%) is not taken: the depths may have settled in a wrong minimum.
MAX_GUESS_D2 = 22.46
#: The residuals of nearby points are not independent (the sensor's errors come in patches): the
#: alignment's information is that of this many independent points, however many it used.
INDEPENDENT_POINTS = 100


@dataclass
class DepthStep:
    """``T_prev_cur`` (4, 4) and its covariance (6, 6, GTSAM order, right perturbation);
    ``points``: how many depth points the last iteration associated; ``residual_m``: their
    median point-to-plane distance."""

    T_prev_cur: np.ndarray
    covariance: np.ndarray
    points: int
    residual_m: float


def heading_prior(T_prev_cur_guess: np.ndarray, speed_m: float | None = None, rot_sigma_rad: float = 0.05,
                  along_sigma_m: float = 0.05, heading_sigma_rad: float = np.radians(10.0),
                  floor_sigma_m: float = 1e-3) -> np.ndarray:
    """The constant-velocity guess's covariance (6, 6, GTSAM order, right perturbation) for
    :func:`depth_step`: the camera keeps its heading (the guessed step's direction, within
    ``heading_sigma_rad`` of it at ``speed_m`` a step, ``floor_sigma_m`` at least; the guess's
    own speed by default), the depth says how fast (``along_sigma_m`` along it).

    Why anisotropic: a camera walking up to a wall slows down, and the wall's depth sees the
    slowing only along its normal; an isotropic guess would keep the rest of the step at the old
    speed (a camera tilted down towards a wall sinks through the floor). Why at the step's speed:
    ten degrees off a 12 cm step is 2 cm, off a 5 mm step 1 mm. A camera that was still has no
    heading: then ``along_sigma_m`` every way.
    """
    t = np.asarray(T_prev_cur_guess, dtype=float)[:3, 3]
    speed = float(np.linalg.norm(t))
    cov = np.zeros((6, 6))
    cov[:3, :3] = np.eye(3) * rot_sigma_rad**2
    if speed < floor_sigma_m:  # no heading to keep
        cov[3:, 3:] = np.eye(3) * along_sigma_m**2
        return cov
    # The perturbation's translation is in the current camera: the step's direction seen from there.
    heading = T_prev_cur_guess[:3, :3].T @ t / speed
    along = np.outer(heading, heading)
    across_sigma_m = max(floor_sigma_m, np.tan(heading_sigma_rad) * (speed if speed_m is None else speed_m))
    cov[3:, 3:] = along * along_sigma_m**2 + (np.eye(3) - along) * across_sigma_m**2
    return cov


def _normals(points: np.ndarray, reach: int = NORMAL_REACH_PX) -> np.ndarray:
    """Unit normals (H, W, 3) of a grid of camera points (H, W, 3), facing the camera, from the
    differences between the points ``reach`` pixels either side; NaN where a neighbour is
    missing or across a depth edge (``EDGE_JUMP`` of the depth per pixel of reach)."""
    k = int(reach)
    du = points[k:-k, 2 * k:] - points[k:-k, : -2 * k]
    dv = points[2 * k:, k:-k] - points[: -2 * k, k:-k]
    n = np.full_like(points, np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        cross = np.cross(du, dv)
        cross /= np.linalg.norm(cross, axis=2, keepdims=True)
        jump = 2 * k * EDGE_JUMP * points[k:-k, k:-k, 2]
        edge = (np.abs(du[..., 2]) > jump) | (np.abs(dv[..., 2]) > jump)
        cross[edge] = np.nan
        # Face the camera, so a residual's sign means in front of or behind the surface.
        flip = np.einsum("hwc,hwc->hw", cross, points[k:-k, k:-k]) > 0
    cross[flip] *= -1
    n[k:-k, k:-k] = cross
    return n


def _grid_points(depth_m: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """Every pixel's camera point (H, W, 3), NaN where the depth is invalid."""
    h, w = depth_m.shape
    v, u = np.mgrid[0:h, 0:w]
    z = np.where(valid_depth_mask(depth_m), depth_m, np.nan)
    return np.stack([(u - intrinsics.cx) / intrinsics.fx * z, (v - intrinsics.cy) / intrinsics.fy * z, z], axis=2)


def _associate(q_prev: np.ndarray, grid: np.ndarray, normals: np.ndarray, intrinsics: Intrinsics):
    """For points in the previous camera (N, 3): the previous frame's point and normal at the
    pixel each projects to, and which of them have both (N,) bool."""
    uv, z = project(q_prev, intrinsics)
    h, w = grid.shape[:2]
    with np.errstate(invalid="ignore"):
        u, v = np.rint(uv[:, 0]), np.rint(uv[:, 1])
        inside = (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    u, v = u[inside].astype(int), v[inside].astype(int)
    s, n = np.full_like(q_prev, np.nan), np.full_like(q_prev, np.nan)
    s[inside], n[inside] = grid[v, u], normals[v, u]
    return s, n, np.isfinite(s).all(axis=1) & np.isfinite(n).all(axis=1)


def depth_step(prev_depth_m: np.ndarray, prev_intrinsics: Intrinsics, cur_depth_m: np.ndarray,
               cur_intrinsics: Intrinsics, T_prev_cur_guess: np.ndarray, stride: int = 4, iterations: int = 30,
               max_residual_m: float = 0.05, start_residual_m: float = 0.4, min_points: int = 200,
               max_median_residual_m: float = 0.01) -> DepthStep | None:
    """The step from the previous frame's camera to the current one's by their depths alone.

    prev_depth_m, cur_depth_m: z-depth images (H, W) in metres (NaN or 0 where missing) with
    their intrinsics; T_prev_cur_guess (4, 4): the constant-velocity guess, the prior's mean
    (:func:`heading_prior`, its heading held at the speed the depth finds); every
    ``stride``-th pixel of the current frame is aligned. Points farther than
    ``start_residual_m`` from the previous frame's surface are left out at first (the guess can
    be off by a walking step), the bound halving each iteration down to ``max_residual_m``.
    None when the depths do not agree on a step (fewer than ``min_points`` associated within
    ``max_residual_m``, or a median residual over ``max_median_residual_m``) or find one farther
    from the guess than the guess's covariance allows (``MAX_GUESS_D2``).
    """
    cur_points, _ = backproject_depth(cur_depth_m, cur_intrinsics, stride)
    if len(cur_points) < min_points:
        return None
    grid = _grid_points(np.asarray(prev_depth_m, dtype=float), prev_intrinsics)
    normals = _normals(grid)
    T_guess = np.asarray(T_prev_cur_guess, dtype=float)
    T_guess_inv = np.linalg.inv(T_guess)
    direction = T_guess[:3, 3] / max(float(np.linalg.norm(T_guess[:3, 3])), 1e-9)

    def prior_info(T: np.ndarray) -> np.ndarray:  # the heading held at the speed T has along it
        return np.linalg.inv(heading_prior(T_guess, abs(float(T[:3, 3] @ direction))))

    T = T_guess.copy()
    for k in range(iterations):
        bound = max(max_residual_m, start_residual_m / 2**k)
        J, r = _linearise(T, cur_points, grid, normals, prev_intrinsics, bound)
        if len(r) < min_points:
            return None
        prior = prior_info(T)
        offset = log_se3(T_guess_inv @ T)  # from the guess: the prior's residual
        weight = _point_weight(len(r))
        dxi = -np.linalg.solve(weight * J.T @ J + prior, weight * J.T @ r + prior @ offset)
        T = T @ exp_se3(dxi)
        if bound == max_residual_m and np.linalg.norm(dxi[:3]) < 1e-5 and np.linalg.norm(dxi[3:]) < 1e-5:
            break
    J, r = _linearise(T, cur_points, grid, normals, prev_intrinsics, max_residual_m)
    median = float(np.median(np.abs(r))) if len(r) else np.inf
    if len(r) < min_points or median > max_median_residual_m:
        return None
    offset = log_se3(T_guess_inv @ T)
    if float(offset @ prior_info(T) @ offset) > MAX_GUESS_D2:
        # Farther from the guess than the guess's own doubt: at a fast swing the guess is wrong
        # and the depths settle in a wrong minimum as tightly as in the right one.
        return None
    return DepthStep(T, np.linalg.inv(_point_weight(len(r)) * J.T @ J + prior_info(T)), len(r), median)


def _point_weight(points: int) -> float:
    """The information of one point's residual (1/m^2), shared so that ``points`` of them say
    no more than ``INDEPENDENT_POINTS`` would. In the solve as in the covariance: thousands of
    points taken as independent would outweigh the guess even where their only say is their
    noise (a plane's weak slope along itself)."""
    return min(1.0, INDEPENDENT_POINTS / max(points, 1)) / DEPTH_SIGMA_M**2


def _linearise(T_prev_cur: np.ndarray, cur_points: np.ndarray, grid: np.ndarray, normals: np.ndarray,
               intrinsics: Intrinsics, max_residual_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Point-to-plane residuals (M,) of the associated points within ``max_residual_m`` and
    their Jacobians (M, 6) with respect to ``T_prev_cur @ Exp(xi)``, ``xi = [omega, v]``."""
    R, t = T_prev_cur[:3, :3], T_prev_cur[:3, 3]
    q = cur_points @ R.T + t
    s, n, ok = _associate(q, grid, normals, intrinsics)
    r = np.einsum("ij,ij->i", n[ok], q[ok] - s[ok])
    keep = np.abs(r) <= max_residual_m
    p, m = cur_points[ok][keep], n[ok][keep] @ R  # m = R^T n: the normal in the current camera
    # d(n . q) / d omega = (p x m), d / d v = m (q = R (p + omega x p + v) + t).
    return np.hstack([np.cross(p, m), m]), r[keep]
