"""Does the depth sensor agree with the images? A figure the survey gives without ground truth.

Every verified match the survey's keyframes saw from two viewpoints far enough apart is
triangulated from its two pixels and the adjusted keyframe poses, and the depth the sensor
measured at each pixel is compared with it. A structured-light or stereo depth camera is
``f b / (d + offset)``: a wrong disparity offset reads far depth long and near depth short, a
wrong baseline scales it all, a wrong focal length or registration bends it. The comparison
is binned by the measured depth, and a line ``1/z_images = slope / z_depth + intercept`` is
fitted through the bins' medians (the measured depth is the precise axis, so the
triangulation's noise does not flatten the line).

The survey's metre is the depth's (the images alone have no scale), so a depth that is only
scaled shows as a slope the bundle adjustment has absorbed: what the figure can tell is the
depth's *shape* against the images, bin by bin. ``benchmarks/survey_floor.py`` undoes the
fitted line on real maps and measures what it does to the survey (little: see
``docs/mapping.md``), so ``map`` reports it and does not apply it.
"""

from __future__ import annotations

import numpy as np

from nap3d_graph.camera import Intrinsics

__all__ = ["triangulated_depths", "depth_against_images", "MIN_PARALLAX_DEG", "MIN_PER_BIN", "DEPTH_SHAPE_BAD",
           "DEPTH_OFFSET_BAD_PER_M"]

#: Matches triangulated: the two rays at least this far apart (degrees); narrower ones
#: triangulate too loosely to compare a depth with.
MIN_PARALLAX_DEG = 8.0
#: Observations per depth bin at least (and at least three bins).
MIN_PER_BIN = 50
#: A bin whose measured depth differs from the images' by more than this share (after the
#: median bin is taken as the metre): more than twice the depth error Kinect v1 and
#: RealSense D400 cameras are specified to (about 2% at 2 m).
DEPTH_SHAPE_BAD = 0.05
#: A fitted disparity offset beyond this (1/m): the depth off by this share per metre of
#: depth, three times those cameras' specified error at 2 m. A survey that saw a narrow range
#: of depths has bins too close together to show an offset, while the line still measures it.
DEPTH_OFFSET_BAD_PER_M = 0.03
#: The bins' span in inverse depth against the observations' scatter in it, at least, for the
#: fitted offset to be measured (see :func:`depth_against_images`).
SPAN_OVER_NOISE = 10.0


def triangulated_depths(pairs: list, T_map_key: np.ndarray, intrinsics: Intrinsics,
                        min_parallax_deg: float = MIN_PARALLAX_DEG) -> tuple[np.ndarray, np.ndarray]:
    """``(z_depth, z_images)`` (M,) metres: the measured depth of both observations of every
    match in ``pairs`` (:class:`~.bundle.PairMatches`, pixels in ``intrinsics``) whose rays
    from keyframes ``T_map_key`` (K, 4, 4, map <- camera) are ``min_parallax_deg`` apart,
    and its depth triangulated from the two pixels (the two rays' closest points)."""
    K = intrinsics

    def rays(uv: np.ndarray) -> np.ndarray:  # camera rays with z = 1: a ray's length factor is its depth
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        return np.c_[(uv[:, 0] - K.cx) / K.fx, (uv[:, 1] - K.cy) / K.fy, np.ones(len(uv))]

    measured, images = [np.empty(0)], [np.empty(0)]
    for p in pairs:
        if len(p.uv_a) == 0:
            continue
        Ta, Tb = T_map_key[p.a], T_map_key[p.b]
        ra, rb = rays(p.uv_a) @ Ta[:3, :3].T, rays(p.uv_b) @ Tb[:3, :3].T
        # depths s, t with a's centre + s ra closest to b's centre + t rb (least squares)
        cos = np.einsum("mi,mi->m", ra, rb) / (np.linalg.norm(ra, axis=1) * np.linalg.norm(rb, axis=1))
        wide = np.degrees(np.arccos(np.clip(np.nan_to_num(cos, nan=1.0), -1.0, 1.0))) >= min_parallax_deg
        A = np.stack([ra[wide], -rb[wide]], axis=2)  # (W, 3, 2); wide rays are never parallel
        st = np.full((len(ra), 2), np.nan)
        rhs = np.broadcast_to(Tb[:3, 3] - Ta[:3, 3], (int(wide.sum()), 3))
        st[wide] = np.linalg.solve(np.einsum("mij,mik->mjk", A, A), np.einsum("mij,mi->mj", A, rhs)[..., None])[..., 0]
        z_a, z_b = np.asarray(p.z_a, dtype=float), np.asarray(p.z_b, dtype=float)
        with np.errstate(invalid="ignore"):
            keep = (wide & (st[:, 0] > 0.2) & (st[:, 1] > 0.2) & (z_a > 0) & (z_b > 0) & np.isfinite(z_a)
                    & np.isfinite(z_b))
        measured += [z_a[keep], z_b[keep]]
        images += [st[keep, 0], st[keep, 1]]
    return np.concatenate(measured), np.concatenate(images)


def depth_against_images(pairs: list, T_map_key: np.ndarray, intrinsics: Intrinsics) -> dict:
    """The measured depth against the images' triangulation (module docstring):
    ``observations``; ``bins`` ``[[median z_depth m, z_depth / z_images], ...]`` nearest
    first, each ratio divided by the median bin's (the depth's metre kept); ``worst`` the
    largest ``|ratio - 1|`` of them; ``median_depth_m``; the fitted ``slope`` and ``intercept_per_m`` (the
    disparity offset: the depth reads ``intercept_per_m`` x its depth too long); ``bad``
    when ``worst`` is beyond :data:`DEPTH_SHAPE_BAD` or the offset beyond
    :data:`DEPTH_OFFSET_BAD_PER_M` where ``offset_measurable`` (the bins span
    :data:`SPAN_OVER_NOISE` times the observations' scatter and the offset's resampled
    ``intercept_sigma_per_m`` is small against its line); ``scatter_at_1m_mm``: the depth's
    scatter about the images near 1 m. ``reason`` instead when too few matches were seen from
    far enough apart."""
    z_depth, z_images = triangulated_depths(pairs, T_map_key, intrinsics)
    keep = np.isfinite(z_depth) & np.isfinite(z_images)
    z_depth, z_images = z_depth[keep], z_images[keep]
    n_bins = min(10, len(z_depth) // MIN_PER_BIN)
    if n_bins < 3:
        return {"observations": int(len(z_depth)),
                "reason": f"{len(z_depth)} observations of matches seen {MIN_PARALLAX_DEG:g} deg apart or more "
                          f"(at least {3 * MIN_PER_BIN} needed)"}
    x_arr, y_arr = _bins(1.0 / z_depth, 1.0 / z_images, n_bins)
    if np.ptp(x_arr) < 1e-3 * np.median(x_arr):  # one wall at one distance: no line through one point
        return {"observations": int(len(z_depth)), "reason": "every match at the same depth"}
    slope, intercept = np.polyfit(x_arr, y_arr, 1)
    sigma = _intercept_sigma(z_depth, z_images, n_bins)
    # An offset is measurable when the survey's depths span enough to tell it from none: the
    # bins' span in inverse depth at least SPAN_OVER_NOISE times the observations' own scatter
    # (else the bins sort the noise, not the depth, and the line tilts by itself: a desk 6 cm
    # deep fits an offset of tenths per metre from none), and its 2-sigma at most half the line.
    inverse_scatter = _inverse_scatter(1.0 / z_depth, 1.0 / z_images, n_bins)
    measurable = bool(np.ptp(x_arr) >= SPAN_OVER_NOISE * inverse_scatter
                      and 2.0 * sigma <= DEPTH_OFFSET_BAD_PER_M / 2.0)
    ratio = y_arr / x_arr  # z_depth / z_images per bin
    ratio = ratio / np.median(ratio)
    worst = float(np.max(np.abs(ratio - 1.0)))
    return {"observations": int(len(z_depth)), "slope": float(slope), "intercept_per_m": float(intercept),
            "intercept_sigma_per_m": sigma, "offset_measurable": measurable,
            "median_depth_m": float(np.median(z_depth)), "scatter_at_1m_mm": _scatter_at_1m_mm(z_depth, z_images),
            "bins": [[round(float(1.0 / a), 3), round(float(r), 4)] for a, r in zip(x_arr, ratio)],
            "worst": worst,
            "bad": bool(worst > DEPTH_SHAPE_BAD or (measurable and abs(intercept) > DEPTH_OFFSET_BAD_PER_M))}


def _bins(inv_depth: np.ndarray, inv_images: np.ndarray, n_bins: int) -> tuple[np.ndarray, np.ndarray]:
    """The bins' medians of the inverse depths ``(x, y)``, nearest bin first."""
    order = np.argsort(-inv_depth)  # nearest first (the largest inverse depth)
    chunks = np.array_split(order, n_bins)
    return (np.array([np.median(inv_depth[c]) for c in chunks]), np.array([np.median(inv_images[c]) for c in chunks]))


def _inverse_scatter(inv_depth: np.ndarray, inv_images: np.ndarray, n_bins: int) -> float:
    """The observations' scatter in inverse depth (1/m): the robust sigma of the depth's inverse
    against the images' (their common scale taken out), about each bin's median, so an offset's
    slow trend across the bins is not counted as scatter. Binned by the images' depth: binned by
    the measured depth, each bin would hold the observations whose noise is alike and hide it."""
    gap = inv_depth - np.median(inv_depth / inv_images) * inv_images
    order = np.argsort(-inv_images)
    spread = np.concatenate([gap[c] - np.median(gap[c]) for c in np.array_split(order, n_bins)])
    return 1.4826 * float(np.median(np.abs(spread)))


def _intercept_sigma(z_depth: np.ndarray, z_images: np.ndarray, n_bins: int, draws: int = 200) -> float:
    """The fitted offset's standard deviation (1/m), by resampling the observations (a fixed
    seed: the same map reports the same figure)."""
    rng = np.random.default_rng(0)
    fits = []
    for _ in range(draws):
        pick = rng.integers(0, len(z_depth), len(z_depth))
        x, y = _bins(1.0 / z_depth[pick], 1.0 / z_images[pick], n_bins)
        if np.ptp(x) > 0:
            fits.append(np.polyfit(x, y, 1)[1])
    return float(np.std(fits)) if len(fits) > 1 else float("inf")


def _scatter_at_1m_mm(z_depth: np.ndarray, z_images: np.ndarray) -> float | None:
    """How far the measured depth scatters about the images' triangulation (robust sigma of
    their difference) for observations within 0.25 m of 1 m, in mm; an upper bound of the
    sensor's noise there (the triangulation's own noise is in it). None with under 20 there."""
    near = np.abs(z_depth - 1.0) <= 0.25
    if near.sum() < 20:
        return None
    ratio = z_depth[near] / z_images[near]
    ratio = ratio / np.median(z_depth / z_images)  # the depth's metre kept, as the bins do
    return float(1.4826 * np.median(np.abs(ratio - np.median(ratio))) * 1000.0)
