"""Where the colour camera sits relative to the depth camera, estimated from posed RGB-D data.

Some recordings do not register depth to colour (7-Scenes: Kinect v1 depth and colour
cameras a few centimetres apart, poses tracked for the depth camera, and only the depth
camera's focal length published). NAP3D back-projects each real keypoint with the depth at
that pixel, and a field built from such frames puts colour on the wrong surfaces, so the
colour camera must be known: its pinhole intrinsics and ``T_colour_depth``.

Estimate: colour keypoints matched between frames a fraction of a second apart are given
the depth their ray meets in the first frame's depth image (through the extrinsics), moved
with the depth camera's poses into the second frame's colour camera, and projected; a
robust least squares over the colour focal length and principal point minimises the
reprojection error.

The offset between the two cameras is *not* estimated: it stays what the caller gives
(identity by default). Measured on a simulated Kinect (colour 25 mm beside depth, exact
poses): with the offset free, the fit stopped wherever it started along a valley in which
the offset trades against the principal point (the median reprojection error at the true
offset is 0.27 px, at zero 0.35 px, the fits landed at 0.34-1.0 px from starts at -40..40
mm); on real 7-Scenes poses, whose own errors move the reprojections by pixels, it landed on
unphysical offsets (28 mm along the axis). For surfaces 1-3 m away a 25 mm offset shifts
the colour by 2-6 px, nearly uniformly: the principal point absorbs most of it, and what
remains is a misregistration at depth edges. The rotation between the two cameras is taken
as identity for the same reason (to first order a principal-point shift).

Why not OpenCV's stereo calibration: it needs a calibration target seen by both cameras,
and datasets ship without one.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from ..camera import Intrinsics, project, warp_depth
from ..conventions import inv_T, pose_error, transform_points
from ..nap3d.matching import detect_features, match_features

__all__ = ["DepthColourRegistration", "estimate_registration", "register_depth_to_colour"]

log = logging.getLogger(__name__)


@dataclass
class DepthColourRegistration:
    """The colour camera relative to the depth camera.

    colour: the colour camera's pinhole intrinsics. T_colour_depth (4, 4): maps depth-camera
    points into the colour camera. residual_px: median reprojection error of the matched
    keypoints at this registration (NaN when not estimated); start_residual_px: the same at
    the nominal registration the estimate started from; matches: how many keypoints it used.
    """

    colour: Intrinsics
    T_colour_depth: np.ndarray = field(default_factory=lambda: np.eye(4))
    residual_px: float = float("nan")
    start_residual_px: float = float("nan")
    matches: int = 0

    def to_dict(self) -> dict:
        return {"colour": self.colour.to_dict(), "T_colour_depth": np.asarray(self.T_colour_depth).tolist(),
                "residual_px": self.residual_px, "start_residual_px": self.start_residual_px,
                "matches": self.matches}

    @classmethod
    def from_dict(cls, d: dict) -> "DepthColourRegistration":
        T = np.asarray(d.get("T_colour_depth", np.eye(4)), dtype=float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"T_colour_depth must be a finite 4x4 matrix, got {T.shape}")
        return cls(Intrinsics.from_dict(d["colour"]), T, float(d.get("residual_px", float("nan"))),
                   float(d.get("start_residual_px", float("nan"))), int(d.get("matches", 0)))

    def describe(self) -> str:
        t_mm = np.asarray(self.T_colour_depth)[:3, 3] * 1000
        return (f"colour camera f={self.colour.fx:.1f} px, centre ({self.colour.cx:.1f}, {self.colour.cy:.1f}), "
                f"{t_mm[0]:+.1f} {t_mm[1]:+.1f} {t_mm[2]:+.1f} mm from the depth camera (as given); matched keypoints "
                f"reproject to {self.residual_px:.2f} px median (nominal {self.start_residual_px:.2f} px)")


def register_depth_to_colour(depth_m: np.ndarray, depth_intrinsics: Intrinsics,
                             registration: DepthColourRegistration) -> np.ndarray:
    """A depth image (H, W) of the depth camera seen from the colour camera: float32 metres
    on the colour camera's pixel grid, 0 where nothing was seen (z-buffered, no depth
    interpolated across edges; see :func:`nap3d_graph.camera.warp_depth`)."""
    if np.allclose(registration.T_colour_depth, np.eye(4)) and registration.colour == depth_intrinsics:
        return np.nan_to_num(np.asarray(depth_m, dtype=np.float32), nan=0.0)
    return warp_depth(depth_m, depth_intrinsics, registration.T_colour_depth,
                      dst_intrinsics=registration.colour, iterations=3)


# --- the estimate ----------------------------------------------------------------------------


def _params_to_registration(p: np.ndarray, template: Intrinsics, T_colour_depth: np.ndarray) -> DepthColourRegistration:
    """[f, cx, cy] (pixels) as a registration (fx = fy) with the given extrinsics."""
    f, cx, cy = p[:3]
    colour = Intrinsics(float(f), float(f), float(cx), float(cy), template.width, template.height)
    return DepthColourRegistration(colour, np.asarray(T_colour_depth, dtype=float))


def _bilinear_valid(depth: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Depth (N,) at sub-pixel ``uv`` (N, 2), NaN outside the image, in holes, or where the
    four neighbours straddle a depth edge (more than 3% apart)."""
    h, w = depth.shape
    u, v = uv[:, 0], uv[:, 1]
    inside = np.isfinite(u) & np.isfinite(v) & (u >= 0) & (v >= 0) & (u <= w - 1.001) & (v <= h - 1.001)
    u0 = np.where(inside, np.floor(np.nan_to_num(u)), 0).astype(np.int64)
    v0 = np.where(inside, np.floor(np.nan_to_num(v)), 0).astype(np.int64)
    a, b = np.nan_to_num(u) - u0, np.nan_to_num(v) - v0
    d00, d01, d10, d11 = depth[v0, u0], depth[v0, u0 + 1], depth[v0 + 1, u0], depth[v0 + 1, u0 + 1]
    lo = np.minimum(np.minimum(d00, d01), np.minimum(d10, d11))
    hi = np.maximum(np.maximum(d00, d01), np.maximum(d10, d11))
    z = (d00 * (1 - a) + d01 * a) * (1 - b) + (d10 * (1 - a) + d11 * a) * b
    return np.where(inside & (lo > 0) & (hi - lo < 0.03 * hi), z, np.nan)


def _colour_ray_depth(pair: "_Pair", K_depth: Intrinsics, reg: DepthColourRegistration,
                      uv: np.ndarray) -> np.ndarray:
    """Colour-camera points (N, 3) where colour pixels ``uv`` (N, 2) meet the surface of the
    depth image: fixed-point steps along each ray, looking the depth up where the current
    point projects into the depth camera. NaN rows where it leaves the image or hits a hole."""
    K = reg.colour
    rays = np.stack([(uv[:, 0] - K.cx) / K.fx, (uv[:, 1] - K.cy) / K.fy, np.ones(len(uv))], axis=1)
    T_depth_colour = inv_T(reg.T_colour_depth)
    z = np.full(len(uv), pair.start_depth_m)
    for _ in range(4):
        p_depth = transform_points(T_depth_colour, rays * z[:, None])
        uv_d, z_d = project(p_depth, K_depth)
        looked = _bilinear_valid(pair.depth_a, uv_d)
        # Move along the ray by the depth disagreement along the depth camera's axis.
        with np.errstate(invalid="ignore", divide="ignore"):
            z = z * looked / z_d
    return rays * z[:, None]


@dataclass
class _Pair:
    """Two frames' matched keypoints, the first frame's depth (and the median depth the ray
    search starts from, computed once rather than at every residual evaluation) and the depth
    camera's poses."""

    depth_a: np.ndarray
    T_world_depth_a: np.ndarray
    T_world_depth_b: np.ndarray
    uv_a: np.ndarray
    uv_b: np.ndarray

    def __post_init__(self) -> None:
        valid = self.depth_a > 0
        self.start_depth_m = float(np.median(self.depth_a[valid])) if np.any(valid) else 1.0


def _residuals(p: np.ndarray, pairs: list[_Pair], K_depth: Intrinsics, template: Intrinsics,
               T_colour_depth: np.ndarray) -> np.ndarray:
    reg = _params_to_registration(p, template, T_colour_depth)
    out = []
    for pair in pairs:
        points_a = _colour_ray_depth(pair, K_depth, reg, pair.uv_a)
        T_cb_ca = reg.T_colour_depth @ inv_T(pair.T_world_depth_b) @ pair.T_world_depth_a @ inv_T(reg.T_colour_depth)
        uv_b, _ = project(transform_points(T_cb_ca, points_a), reg.colour)
        out.append((uv_b - pair.uv_b).ravel())
    return np.concatenate(out)  # NaN where a keypoint found no depth


def estimate_registration(frames_a, frames_b, T_world_depth_a, T_world_depth_b, depth_intrinsics: Intrinsics,
                          nominal: DepthColourRegistration, max_features: int = 1500,
                          min_matches: int = 200) -> DepthColourRegistration:
    """The colour camera's intrinsics (the offset from the depth camera given), from frame pairs.

    frames_a, frames_b: lists of ``(rgb (H, W, 3) uint8, depth_m (H, W) float metres of the
    depth camera)`` for the two frames of each pair; T_world_depth_a / _b: (P, 4, 4) the depth
    camera's poses. ``nominal``: where the fit starts, and the extrinsics it keeps (and what it
    returns, with its residual, when too few keypoints match). Pairs should be 0.2-1 s apart on a hand-held camera.
    """
    pairs = []
    for (rgb_a, depth_a), (rgb_b, _), T_a, T_b in zip(frames_a, frames_b, T_world_depth_a, T_world_depth_b):
        if not (np.all(np.isfinite(T_a)) and np.all(np.isfinite(T_b))):
            continue
        m = match_features(detect_features(rgb_a, max_features), detect_features(rgb_b, max_features), ratio=0.7)
        if len(m) >= 10:
            depth = np.nan_to_num(np.asarray(depth_a, dtype=np.float64), nan=0.0)
            pairs.append(_Pair(depth, np.asarray(T_a, float), np.asarray(T_b, float), m.uv_a, m.uv_b))
    count = sum(len(p.uv_a) for p in pairs)
    template, T_cd = nominal.colour, np.asarray(nominal.T_colour_depth, dtype=float)
    p0 = np.array([template.fx, template.cx, template.cy])
    start = _median_error(_residuals(p0, pairs, depth_intrinsics, template, T_cd)) if pairs else float("nan")
    if count < min_matches:
        log.warning("depth-to-colour registration: only %d matched keypoints (need %d); keeping the nominal one",
                    count, min_matches)
        return DepthColourRegistration(nominal.colour, T_cd, start, start, count)
    p = p0
    for _ in range(3):
        p = _fit_inliers(p, pairs, depth_intrinsics, template, T_cd)
    result = _params_to_registration(p, template, T_cd)
    result.residual_px = _median_error(_residuals(p, pairs, depth_intrinsics, template, T_cd))
    result.start_residual_px, result.matches = start, count
    log.info("depth-to-colour registration: %s", result.describe())
    return result


def _fit_inliers(p: np.ndarray, pairs: list[_Pair], K_depth: Intrinsics, template: Intrinsics,
                 T_cd: np.ndarray) -> np.ndarray:
    """One round: keep the keypoints that reproject within 3x the median (at least 2 px) at
    ``p``, and fit [f, cx, cy] to them. The set stays fixed within the round (a keypoint that
    loses its depth meanwhile counts zero): letting it change, or scoring lost keypoints
    with a fixed penalty, made the cost favour whichever camera kept the most keypoints
    inside the depth image, 2 px from the truth on a simulated Kinect."""
    from scipy.optimize import least_squares

    errors = np.linalg.norm(_residuals(p, pairs, K_depth, template, T_cd).reshape(-1, 2), axis=1)
    keep = np.isfinite(errors) & (errors < max(3.0 * float(np.nanmedian(errors)), 2.0))
    keep2 = np.repeat(keep, 2)
    scale = np.full(3, template.fx / 100)  # steps of a few pixels: the bilinear depth is rough below that

    def residuals(q: np.ndarray) -> np.ndarray:
        return np.nan_to_num(_residuals(p + q * scale, pairs, K_depth, template, T_cd)[keep2], nan=0.0)

    solution = least_squares(residuals, np.zeros(3), loss="soft_l1", f_scale=1.0, diff_step=2e-2, max_nfev=50)
    return p + solution.x * scale


def _median_error(residuals: np.ndarray) -> float:
    errors = np.linalg.norm(residuals.reshape(-1, 2), axis=1)
    return float(np.median(errors[np.isfinite(errors)])) if np.any(np.isfinite(errors)) else float("nan")


# --- the depth camera's motion from the depth images alone -------------------------------


def depth_icp_step(depth_a_m: np.ndarray, depth_b_m: np.ndarray, K_depth: Intrinsics, width: int = 320,
                   T_b_a_start: np.ndarray | None = None) -> np.ndarray | None:
    """``T_b_a`` (4, 4): the depth camera's motion from frame a to frame b by OpenCV's depth-only
    ICP odometry (``cv2.Odometry``, ``OdometryType_DEPTH``) at ``width`` px; None when it fails.
    Needs no colour camera: what poses a registration estimate when the recording's own
    poses are not to be read."""
    import cv2

    scale = min(1.0, width / depth_a_m.shape[1])
    K = K_depth.scaled(int(round(depth_a_m.shape[1] * scale)), int(round(depth_a_m.shape[0] * scale)))

    def small(depth):
        depth = np.nan_to_num(np.asarray(depth, dtype=np.float32), nan=0.0)
        return cv2.resize(depth, (K.width, K.height), interpolation=cv2.INTER_NEAREST) if scale < 1 else depth

    settings = cv2.OdometrySettings()
    settings.setCameraMatrix(K.K.astype(np.float32))
    odometry = cv2.Odometry(cv2.OdometryType_DEPTH, settings, cv2.OdometryAlgoType_COMMON)
    src, dst = cv2.OdometryFrame(small(depth_a_m)), cv2.OdometryFrame(small(depth_b_m))
    odometry.prepareFrames(src, dst)
    try:
        # A copy: compute() writes its answer into the start it is given.
        ok, T = odometry.compute(src, dst, np.eye(4) if T_b_a_start is None else np.array(T_b_a_start, dtype=float))
    except cv2.error:
        return None
    T = np.asarray(T, dtype=float)
    # compute() gives the source's pose in the destination's frame: a's points into b.
    return T if ok and np.all(np.isfinite(T)) else None


def depth_chain(depths: list[np.ndarray], K_depth: Intrinsics, width: int = 320,
                agree: tuple[float, float] = (0.02, 2.0)) -> np.ndarray | None:
    """``T_last_first`` (4, 4): the depth camera's motion over consecutive depth images
    ``depths`` (metres), by depth-only ICP step by step, then refined directly between the
    first and the last from that start; None when a step fails or the refinement moves
    further than ``agree`` (metres, degrees) from the chain (ICP slid along a surface)."""
    chained = np.eye(4)
    for a, b in zip(depths[:-1], depths[1:]):
        step = depth_icp_step(a, b, K_depth, width)
        if step is None:
            return None
        chained = step @ chained
    refined = depth_icp_step(depths[0], depths[-1], K_depth, width, T_b_a_start=chained)
    if refined is None:
        return None
    moved_m, turned_deg = pose_error(refined, chained)
    return refined if moved_m <= agree[0] and turned_deg <= agree[1] else None
