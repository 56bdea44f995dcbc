"""Compiled rasteriser of a splat field's visible splats (numba).

:meth:`~nap3d_graph.fields.splat.SplatField.render` was torch tensor operations grouped by
footprint size: a 320x240 render of fr1/desk's half map took 0.33 s on one thread, three
quarters of a relocalisation attempt. This loops over the splats and their footprints once
per pass instead (the same two passes, the same arithmetic in float32), so nothing is
gathered or scattered through index tensors. The sums add up in another order than the
torch version's, so a render differs from it by float32 rounding only.

Frames and units: ``z_m`` (N,) the splats' depth in the camera (metres, > near), ``u_px`` /
``v_px`` (N,) their projected centres (pixel centres at integer coordinates, OpenCV),
``radius_px`` (N,) their footprint radius, ``colors`` (N, 3) linear RGB in [0, 1],
``confidence`` (N,) their fusion weight.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["rasterise_splats"]


@njit(cache=True, nogil=True)
def rasterise_splats(z_m: np.ndarray, u_px: np.ndarray, v_px: np.ndarray, radius_px: np.ndarray,
                     colors: np.ndarray, confidence: np.ndarray, width: int, height: int,
                     blend_tolerance_rel: float, blend_tolerance_m: float, opacity_gain: float):
    """``(rgb (H*W, 3), depth_m (H*W,), opacity (H*W,))`` float32: pass 1 finds the nearest
    splat depth at each pixel within the footprints (a Gaussian of sigma = radius / 2, cut at
    the radius); pass 2 blends, at each pixel, the splats of that front surface (within
    ``blend_tolerance_rel`` of its depth plus ``blend_tolerance_m``), colour and depth weighted
    by footprint times confidence; opacity is ``1 - exp(-opacity_gain * footprint sum)`` and
    the colour is premultiplied by it. Depth 0 where nothing is seen."""
    n_pixels = width * height
    zbuf = np.full(n_pixels, np.float32(np.inf), dtype=np.float32)
    n = z_m.shape[0]
    for i in range(n):  # pass 1: the front surface
        ui, vi = np.rint(u_px[i]), np.rint(v_px[i])
        du, dv = u_px[i] - ui, v_px[i] - vi
        r2 = radius_px[i] * radius_px[i]
        reach = int(math.ceil(radius_px[i]))
        for dy in range(-reach, reach + 1):
            py = int(vi) + dy
            if py < 0 or py >= height:
                continue
            for dx in range(-reach, reach + 1):
                px = int(ui) + dx
                if px < 0 or px >= width:
                    continue
                d2 = (dx - du) ** 2 + (dy - dv) ** 2
                if d2 <= r2:
                    k = py * width + px
                    if z_m[i] < zbuf[k]:
                        zbuf[k] = z_m[i]
    weight = np.zeros(n_pixels, dtype=np.float32)
    footprint = np.zeros(n_pixels, dtype=np.float32)
    depth = np.zeros(n_pixels, dtype=np.float32)
    rgb = np.zeros((n_pixels, 3), dtype=np.float32)
    for i in range(n):  # pass 2: blend the front surface's splats
        ui, vi = np.rint(u_px[i]), np.rint(v_px[i])
        du, dv = u_px[i] - ui, v_px[i] - vi
        r2 = radius_px[i] * radius_px[i]
        inv_two_sigma2 = np.float32(2.0) / r2
        reach = int(math.ceil(radius_px[i]))
        for dy in range(-reach, reach + 1):
            py = int(vi) + dy
            if py < 0 or py >= height:
                continue
            for dx in range(-reach, reach + 1):
                px = int(ui) + dx
                if px < 0 or px >= width:
                    continue
                d2 = (dx - du) ** 2 + (dy - dv) ** 2
                if d2 > r2:
                    continue
                k = py * width + px
                if z_m[i] > zbuf[k] * (1.0 + blend_tolerance_rel) + blend_tolerance_m:
                    continue
                g = np.float32(math.exp(-d2 * inv_two_sigma2))
                wgt = g * confidence[i]
                weight[k] += wgt
                footprint[k] += g
                depth[k] += wgt * z_m[i]
                for c in range(3):
                    rgb[k, c] += wgt * colors[i, c]
    opacity = np.empty(n_pixels, dtype=np.float32)
    for k in range(n_pixels):
        if weight[k] > 0:
            depth[k] /= weight[k]
            for c in range(3):
                rgb[k, c] /= weight[k]
        opacity[k] = 1.0 - math.exp(-opacity_gain * footprint[k])
        for c in range(3):
            rgb[k, c] *= opacity[k]
    return rgb, depth, opacity
