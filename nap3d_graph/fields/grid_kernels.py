"""Compiled CPU kernels of the grid field's hierarchical renderer (numba).

The algorithm is the one :mod:`nap3d_graph.fields.grid` describes and
:mod:`nap3d_graph.fields.grid_render` runs in torch (which stays the path on a GPU): a sparse
lattice of pixels marches through the coarse occupancy grid, finer lattices search a short
window around their neighbours' depths, smooth cells of the last level interpolate inverse
depth, and the depth is the median termination depth. Here each ray is a loop instead of a
batch of tensors: on a CPU the torch version spends most of its time launching small tensor
operations and sampling windows past the surface (measured 117 ms for a 320x240 render of
fr1/desk's field on one core), while a ray that stops where its transmittance is spent costs
a few dozen trilinear lookups. The kernels release the GIL (``nogil``): a run's keyframe
thread renders while its odometry goes on.

Frames and units: points and the ray origin are in the grid's local frame (metres from the
grid's first vertex, world axes); ray directions have unit camera z, so the ray parameter
``t`` is the z-depth in metres. Grids are indexed ``[z, y, x]`` as in
:class:`~nap3d_graph.fields.grid.GridField`; lookups outside them read zero (as
``grid_sample``'s zero padding does).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["render_depth", "shade"]

_LN2 = math.log(2.0)
#: Optical depth past which a window stops sampling (it has crossed): the opacity is then
#: 1 - 6e-6 of the whole window's. Stopping sooner (at 5) saved no measurable time but moved
#: a fifth of the colour values by a level or more against the torch path.
_TAU_DONE = 12.0
#: softplus(x) tabulated every 0.01 over [-15, 20] (linear interpolation is within 4e-6 of it,
#: 1.3e-5 relative): log1p(exp(x)) was a third of a sample's cost.
_SOFTPLUS_LO, _SOFTPLUS_STEP = -15.0, 0.01
_SOFTPLUS = np.log1p(np.exp(np.arange(_SOFTPLUS_LO, 20.0 + 2 * _SOFTPLUS_STEP, _SOFTPLUS_STEP)))


@njit(cache=True, nogil=True, inline="always")
def _raw_at(grid, qx, qy, qz):
    """Trilinear value of ``grid`` (nz, ny, nx) at vertex coordinates (qx, qy, qz); vertices
    outside the grid read 0."""
    nz, ny, nx = grid.shape
    if not (-1.0 < qx < nx and -1.0 < qy < ny and -1.0 < qz < nz):
        return 0.0
    fx, fy, fz = math.floor(qx), math.floor(qy), math.floor(qz)
    ix, iy, iz = int(fx), int(fy), int(fz)
    wx, wy, wz = qx - fx, qy - fy, qz - fz
    if ix >= 0 and iy >= 0 and iz >= 0 and ix + 1 < nx and iy + 1 < ny and iz + 1 < nz:
        c00 = grid[iz, iy, ix] * (1.0 - wx) + grid[iz, iy, ix + 1] * wx
        c01 = grid[iz, iy + 1, ix] * (1.0 - wx) + grid[iz, iy + 1, ix + 1] * wx
        c10 = grid[iz + 1, iy, ix] * (1.0 - wx) + grid[iz + 1, iy, ix + 1] * wx
        c11 = grid[iz + 1, iy + 1, ix] * (1.0 - wx) + grid[iz + 1, iy + 1, ix + 1] * wx
        return (c00 * (1.0 - wy) + c01 * wy) * (1.0 - wz) + (c10 * (1.0 - wy) + c11 * wy) * wz
    return _raw_at_edge(grid, ix, iy, iz, wx, wy, wz)


@njit(cache=True, nogil=True)
def _raw_at_edge(grid, ix, iy, iz, wx, wy, wz):
    """:func:`_raw_at` for a cell that sticks out of the grid (its outside vertices read 0);
    kept out of line so the inlined common case stays small."""
    nz, ny, nx = grid.shape
    total = 0.0
    for dz in range(2):
        z = iz + dz
        if z < 0 or z >= nz:
            continue
        w_z = wz if dz else 1.0 - wz
        for dy in range(2):
            y = iy + dy
            if y < 0 or y >= ny:
                continue
            w_y = wy if dy else 1.0 - wy
            for dx in range(2):
                x = ix + dx
                if x < 0 or x >= nx:
                    continue
                total += grid[z, y, x] * w_z * w_y * (wx if dx else 1.0 - wx)
    return total


@njit(cache=True, nogil=True, inline="always")
def _sigma(density, px, py, pz, inv_voxel, shift):
    """Density per metre at a local point: softplus(raw - shift) / voxel (torch's softplus,
    linear above 20)."""
    x = _raw_at(density, px * inv_voxel, py * inv_voxel, pz * inv_voxel) - shift
    if x > 20.0:
        soft = x
    elif x < _SOFTPLUS_LO:
        soft = math.exp(x)  # log1p(e) = e within 2e-7 relative here
    else:
        p = (x - _SOFTPLUS_LO) * (1.0 / _SOFTPLUS_STEP)
        i = int(p)
        f = p - i
        soft = _SOFTPLUS[i] * (1.0 - f) + _SOFTPLUS[i + 1] * f
    return soft * inv_voxel


@njit(cache=True, nogil=True, inline="always")
def _box_range(o, d, hi, near):
    """Entry and exit ``t`` of a ray through the box [0, hi] (local frame)."""
    t_in = -1e30
    t_out = 1e30
    for k in range(3):
        dk = d[k] if abs(d[k]) >= 1e-9 else 1e-9
        a = (0.0 - o[k]) / dk
        b = (hi[k] - o[k]) / dk
        t_in = max(t_in, min(a, b))
        t_out = min(t_out, max(a, b))
    return max(t_in, near), t_out


@njit(cache=True, nogil=True)
def _samples(density, o, d, norm, a0, length, count, t_lo, t_hi, tau0, refine, inv_voxel, shift):
    """Median termination depth over ``count`` samples in ``[a0, a0 + length]``.

    Samples outside ``(t_lo, t_hi)`` are empty; ``tau0`` is the optical depth already spent
    before ``a0``. Returns (depth, opacity, optical depth at the end, crossed): where the
    transmittance crosses 0.5 the depth is that crossing (piecewise-constant density, then
    ``refine`` extra samples inside the crossing interval where they confirm it); a ray that
    does not cross gets the expected depth of this window's samples.
    """
    dt = length / count
    cum = tau0
    trans = math.exp(-tau0)  # transmittance before the current sample
    w_sum = 0.0
    wt_sum = 0.0
    crossed = False
    z = 0.0
    for k in range(count):
        t = a0 + (k + 0.5) * dt
        tau = 0.0
        if t_lo < t < t_hi:
            tau = _sigma(density, o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2], inv_voxel, shift) * dt * norm
        before = cum
        cum += tau
        if not crossed:
            w = trans * (1.0 - math.exp(-tau))
            trans -= w
            w_sum += w
            wt_sum += w * t
            if cum >= _LN2:
                crossed = True
                start = t - 0.5 * dt
                z = start + min(max((_LN2 - before) / max(tau, 1e-12), 0.0), 1.0) * dt
                if refine > 0:
                    z = _refine(density, o, d, norm, start, dt, before, refine, inv_voxel, shift, z)
        if cum > _TAU_DONE:
            break
    if not crossed:
        z = wt_sum / max(w_sum, 1e-12)
    return z, 1.0 - math.exp(-cum), cum, crossed


@njit(cache=True, nogil=True, inline="always")
def _refine(density, o, d, norm, start, dt, before, refine, inv_voxel, shift, z_coarse):
    """The crossing inside ``[start, start + dt]`` from ``refine`` sub-samples; ``z_coarse``
    where they do not reach optical depth ln 2 (the coarse sample was not confirmed)."""
    sub = dt / refine
    cum = before
    for j in range(refine):
        t = start + (j + 0.5) * sub
        tau = _sigma(density, o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2], inv_voxel, shift) * sub * norm
        if cum + tau >= _LN2:
            return start + (j + min(max((_LN2 - cum) / max(tau, 1e-12), 0.0), 1.0)) * sub
        cum += tau
    return z_coarse


@njit(cache=True, nogil=True)
def _march(density, occ, o, d, t_start, hi, voxel, shift, near, march_step_vox, window_voxels, max_windows,
           refine):
    """Full march of one ray from ``t_start``: find the first occupied coarse cell (lookups one
    voxel apart), sample a window from just before it, go on past it while the transmittance
    stays above 0.5. Returns (depth, opacity); (0, 0) when the ray meets nothing."""
    cz, cy, cx = occ.shape
    norm = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    t_in, t_end = _box_range(o, d, hi, near)
    start = max(t_in, t_start)
    step = voxel / norm
    inv_cell = 1.0 / (2.0 * voxel)
    inv_voxel = 1.0 / voxel
    fine = max(2, int(round(window_voxels / march_step_vox)))
    tau0 = 0.0
    depth = 0.0
    opacity = 0.0
    for _ in range(max_windows):
        t = start + 0.5 * step
        hit = False
        while t < t_end:
            ix = min(max(int(math.floor((o[0] + t * d[0]) * inv_cell)), 0), cx - 1)
            iy = min(max(int(math.floor((o[1] + t * d[1]) * inv_cell)), 0), cy - 1)
            iz = min(max(int(math.floor((o[2] + t * d[2]) * inv_cell)), 0), cz - 1)
            if occ[iz, iy, ix]:
                hit = True
                break
            t += step
        if not hit:
            break
        a0 = t - 1.5 * step
        length = window_voxels * step
        depth, opacity, tau0, crossed = _samples(density, o, d, norm, a0, length, fine, -1e30, t_end, tau0, refine,
                                                 inv_voxel, shift)
        if opacity >= 0.5:
            break
        start = a0 + length
    return depth, opacity


@njit(cache=True, nogil=True)
def _window(density, o, d, z_lo, z_hi, hi, voxel, shift, near, margin, count, refine):
    """Depth and opacity of a ray whose surface lies in ``[z_lo, z_hi]`` give or take
    ``margin``: ``count`` samples there, then the crossing refined."""
    norm = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    t_in, t_out = _box_range(o, d, hi, near)
    a0 = z_lo - margin
    z, a, _, _ = _samples(density, o, d, norm, a0, z_hi + margin - a0, count, t_in, t_out, 0.0, refine,
                          1.0 / voxel, shift)
    return z, a


@njit(cache=True, nogil=True)
def _lattice(n, stride):
    """Pixel coordinates 0, stride, 2 stride, ... plus the last one, so it brackets all."""
    count = (n - 1) // stride + 1
    extra = 1 if (count - 1) * stride != n - 1 else 0
    out = np.empty(count + extra, np.int64)
    for i in range(count):
        out[i] = i * stride
    if extra:
        out[count] = n - 1
    return out


@njit(cache=True, nogil=True)
def _below(coarse, n):
    """For each pixel coordinate 0..n-1, the index of the last coarse coordinate at or before it."""
    out = np.empty(n, np.int64)
    i = 0
    for x in range(n):
        while i + 1 < coarse.shape[0] and coarse[i + 1] <= x:
            i += 1
        out[x] = i
    return out


@njit(cache=True, nogil=True, inline="always")
def _direction(R, fx, fy, cx, cy, u, v, d):
    """World (= grid) direction of pixel (u, v) with unit camera z, written into ``d`` (3,)."""
    x = (u - cx) / fx
    y = (v - cy) / fy
    for k in range(3):
        d[k] = R[k, 0] * x + R[k, 1] * y + R[k, 2]


@njit(cache=True, nogil=True)
def render_depth(density, occ, o, R, fx, fy, cx, cy, height, width, stride, voxel, shift, params, counts):
    """Median depth (H, W) and opacity (H, W) of the density grid seen from origin ``o`` (3,)
    (local frame) with rotation ``R`` (3, 3) (grid <- camera) and pinhole (fx, fy, cx, cy).

    ``stride``: level 0's lattice stride. ``params`` (14,) float64: near_m, march_step_vox,
    window_voxels, max_march_windows, window_samples, window_margin_m, edge_gap_m,
    refine_samples, min_opacity, interpolate_below_stride, smooth_min_opacity,
    smooth_max_spread_m, smooth_max_twist_m, empty_cell_opacity (as in ``RenderConfig``).
    ``counts`` (5,) int64 is incremented by the pixels marched at level 0, windowed,
    interpolated, marched again, and filled as holes.
    """
    near, step_vox, window_vox = params[0], params[1], params[2]
    max_windows, window_samples, margin = int(params[3]), int(params[4]), params[5]
    edge_gap, refine, min_opacity = params[6], int(params[7]), params[8]
    interpolate_below, smooth_opacity, smooth_spread, smooth_twist = int(params[9]), params[10], params[11], params[12]
    empty_opacity = params[13]
    nz, ny, nx = density.shape
    hi = np.array([(nx - 1) * voxel, (ny - 1) * voxel, (nz - 1) * voxel])
    depth = np.zeros((height, width), np.float32)
    opacity = np.zeros((height, width), np.float32)
    known = np.zeros((height, width), np.bool_)
    d = np.empty(3)
    us = _lattice(width, stride)
    vs = _lattice(height, stride)
    for v in vs:
        for u in us:
            _direction(R, fx, fy, cx, cy, u, v, d)
            z, a = _march(density, occ, o, d, 0.0, hi, voxel, shift, near, step_vox, window_vox, max_windows, refine)
            depth[v, u] = z
            opacity[v, u] = a
            known[v, u] = True
            counts[0] += 1
    cz = np.empty(4)
    ca = np.empty(4)
    while stride > 1:
        fine = stride // 2
        us_f = _lattice(width, fine)
        vs_f = _lattice(height, fine)
        iu_of = _below(us, width)
        iv_of = _below(vs, height)
        for v in vs_f:
            iv = iv_of[v]
            v0 = vs[iv]
            v1 = v if v0 == v else vs[min(iv + 1, vs.shape[0] - 1)]
            for u in us_f:
                if known[v, u]:
                    continue
                iu = iu_of[u]
                u0 = us[iu]
                u1 = u if u0 == u else us[min(iu + 1, us.shape[0] - 1)]
                cz[0], cz[1], cz[2], cz[3] = depth[v0, u0], depth[v0, u1], depth[v1, u0], depth[v1, u1]
                ca[0], ca[1], ca[2], ca[3] = opacity[v0, u0], opacity[v0, u1], opacity[v1, u0], opacity[v1, u1]
                if fine <= interpolate_below and _smooth(cz, ca, smooth_opacity, smooth_spread, smooth_twist):
                    wu = (u - u0) / (u1 - u0) if u1 > u0 else 0.0
                    wv = (v - v0) / (v1 - v0) if v1 > v0 else 0.0
                    b0, b1, b2, b3 = (1 - wu) * (1 - wv), wu * (1 - wv), (1 - wu) * wv, wu * wv
                    depth[v, u] = 1.0 / (b0 / cz[0] + b1 / cz[1] + b2 / cz[2] + b3 / cz[3])
                    opacity[v, u] = b0 * ca[0] + b1 * ca[1] + b2 * ca[2] + b3 * ca[3]
                    known[v, u] = True
                    counts[2] += 1
                    continue
                # Smooth cells: one window spanning the corners' depths. Depth edges (or corners
                # without a surface): march, from just before the nearest corner's surface.
                any_ok = False
                z_near = 1e9
                z_far = -1e9
                for k in range(4):
                    if ca[k] >= min_opacity:
                        any_ok = True
                        z_near = min(z_near, cz[k])
                        z_far = max(z_far, cz[k])
                _direction(R, fx, fy, cx, cy, u, v, d)
                windowed = any_ok and (z_far - z_near) <= edge_gap
                z = 0.0
                a = 0.0
                if windowed:
                    z, a = _window(density, o, d, z_near, z_far, hi, voxel, shift, near, margin, window_samples, refine)
                    counts[1] += 1
                if ca[0] < empty_opacity and ca[1] < empty_opacity and ca[2] < empty_opacity and ca[3] < empty_opacity:
                    # A hole: no corner saw even a faint surface. Their opacity, no march.
                    wu = (u - u0) / (u1 - u0) if u1 > u0 else 0.0
                    wv = (v - v0) / (v1 - v0) if v1 > v0 else 0.0
                    a = (1 - wu) * (1 - wv) * ca[0] + wu * (1 - wv) * ca[1] + (1 - wu) * wv * ca[2] + wu * wv * ca[3]
                    z = cz[np.argmax(ca)]
                    counts[4] += 1
                elif not windowed or a < min_opacity:
                    # A window that found nothing starts over from the camera.
                    start = z_near - margin if (any_ok and not windowed) else 0.0
                    z, a = _march(density, occ, o, d, start, hi, voxel, shift, near, step_vox, window_vox,
                                  max_windows, refine)
                    counts[3] += 1
                depth[v, u] = z
                opacity[v, u] = a
                known[v, u] = True
        us, vs, stride = us_f, vs_f, fine
    return depth, opacity


@njit(cache=True, nogil=True, inline="always")
def _smooth(cz, ca, min_opacity, max_spread, max_twist):
    """A cell whose four corners all see an opaque surface at nearly the same, nearly planar
    depth (the twist of the bilinear patch of inverse depth is zero on any plane)."""
    lo = 1e30
    hi = -1e30
    mean = 0.0
    for k in range(4):
        if ca[k] < min_opacity or cz[k] <= 0.0:
            return False
        lo = min(lo, cz[k])
        hi = max(hi, cz[k])
        mean += 0.25 * cz[k]
    if hi - lo >= max_spread:
        return False
    twist = abs(1.0 / max(cz[0], 1e-3) + 1.0 / max(cz[3], 1e-3) - 1.0 / max(cz[1], 1e-3) - 1.0 / max(cz[2], 1e-3))
    return twist * mean * mean < max_twist


@njit(cache=True, nogil=True)
def shade(color, color_voxel, o, R, fx, fy, cx, cy, depth, opacity, min_opacity):
    """Colour (H, W, 3) float32 in [0, 1]: ``sigmoid`` of the raw colour grid (mz, my, mx, 3)
    (channel-last: a lookup's three channels share cache lines) at each pixel's depth point,
    times its opacity; black where opacity <= ``min_opacity``. Also zeroes ``depth`` there
    (in place)."""
    height, width = depth.shape
    mz, my, mx, _ = color.shape
    rgb = np.zeros((height, width, 3), np.float32)
    inv = 1.0 / color_voxel
    d = np.empty(3)
    for v in range(height):
        for u in range(width):
            a = opacity[v, u]
            if not a > min_opacity:
                depth[v, u] = 0.0
                continue
            _direction(R, fx, fy, cx, cy, u, v, d)
            z = depth[v, u]
            qx = (o[0] + z * d[0]) * inv
            qy = (o[1] + z * d[1]) * inv
            qz = (o[2] + z * d[2]) * inv
            if 0.0 <= qx < mx - 1 and 0.0 <= qy < my - 1 and 0.0 <= qz < mz - 1:
                # Inside: one set of corners and weights for the three channels.
                ix, iy, iz = int(qx), int(qy), int(qz)
                wx, wy, wz = qx - ix, qy - iy, qz - iz
                for c in range(3):
                    c00 = color[iz, iy, ix, c] * (1.0 - wx) + color[iz, iy, ix + 1, c] * wx
                    c01 = color[iz, iy + 1, ix, c] * (1.0 - wx) + color[iz, iy + 1, ix + 1, c] * wx
                    c10 = color[iz + 1, iy, ix, c] * (1.0 - wx) + color[iz + 1, iy, ix + 1, c] * wx
                    c11 = color[iz + 1, iy + 1, ix, c] * (1.0 - wx) + color[iz + 1, iy + 1, ix + 1, c] * wx
                    raw = (c00 * (1.0 - wy) + c01 * wy) * (1.0 - wz) + (c10 * (1.0 - wy) + c11 * wy) * wz
                    rgb[v, u, c] = a / (1.0 + math.exp(-raw))
            else:
                for c in range(3):
                    rgb[v, u, c] = a / (1.0 + math.exp(-_raw_at(color[:, :, :, c], qx, qy, qz)))
    return rgb
