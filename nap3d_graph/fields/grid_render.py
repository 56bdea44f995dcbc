"""The rendering half of :class:`~nap3d_graph.fields.grid.GridField` (a mixin over its
tensors): the hierarchical ray marcher its module describes, and the brute-force reference
renderer it is tested against."""

from __future__ import annotations

import functools
import logging
import math
import time
import types
from dataclasses import dataclass

import numpy as np
import torch

from nap3d_graph.camera import Intrinsics, RenderedView
from nap3d_graph.torch_threads import torch_threads

from .base import FieldError

log = logging.getLogger(__name__)

#: Raw density 0 maps to a near-transparent softplus(-DENSITY_SHIFT) (see grid.py).
DENSITY_SHIFT = 10.0

__all__ = ["DENSITY_SHIFT", "GridRenderer", "RenderConfig", "pixel_directions"]

_LN2 = math.log(2.0)


@dataclass(frozen=True)
class RenderConfig:
    """Knobs of the hierarchical renderer (defaults tuned for 3 cm grids on a CPU).

    coarse_rays: at most this many rays march at level 0 (the lattice stride is the
    smallest power of two that keeps under it). march_step_vox: sample spacing of a march
    window, in voxels; window_voxels: its length; max_march_windows: how many windows a ray
    tries before it gives up. window_samples: samples per pixel at the finer levels;
    window_margin_m: how far beyond the neighbours' depths that window reaches; edge_gap_m:
    neighbour depth spread above which the pixel marches instead. refine_samples: extra
    samples inside the interval where transmittance crosses 0.5. min_opacity: a window result
    below this falls back to the full march. near_m: rays start this far from the camera.
    interpolate_below_stride: levels at or below this stride interpolate smooth cells
    (0: never); a cell is smooth when its corners' opacity >= smooth_min_opacity, their depth
    spread < smooth_max_spread_m and the twist of their inverse depth, in metres, is below
    smooth_max_twist_m. empty_cell_opacity: a finer-level pixel whose four corners' opacities
    are all below this sees a hole (unseen space, an open doorway) and does not march: it takes
    their opacity, bilinearly, and the most opaque corner's depth (on fr1/desk's field a fifth
    of the render's time went into marching through such holes, where the reference renderer
    finds no more surface either); 0 marches every cell. threads: torch CPU threads while
    rendering (see :func:`torch_threads`; None keeps torch's setting). backend: "auto" renders on a CPU with the compiled kernels of
    :mod:`~nap3d_graph.fields.grid_kernels` when numba is installed (the same algorithm, a loop
    per ray instead of batches of tensors) and with torch otherwise and on a GPU; "torch"
    always takes the torch path.
    """

    coarse_rays: int = 5000
    march_step_vox: float = 1.0 / 3.0
    window_voxels: float = 8.0
    max_march_windows: int = 6
    window_samples: int = 8
    window_margin_m: float = 0.03
    edge_gap_m: float = 0.08
    refine_samples: int = 4
    min_opacity: float = 0.5
    near_m: float = 0.05
    interpolate_below_stride: int = 1
    smooth_min_opacity: float = 0.99
    smooth_max_spread_m: float = 0.05
    smooth_max_twist_m: float = 0.002
    threads: int | None = 1
    backend: str = "auto"
    empty_cell_opacity: float = 0.02

    def __post_init__(self):
        if self.backend not in ("auto", "torch"):
            raise FieldError(f"render backend must be 'auto' or 'torch', got {self.backend!r}")


def pixel_directions(intrinsics: Intrinsics, device=None) -> torch.Tensor:
    """Camera-frame ray directions with unit z, (H, W, 3) float32, OpenCV frame.

    With z = 1 the ray parameter ``t`` is the z-depth itself.
    """
    v, u = torch.meshgrid(
        torch.arange(intrinsics.height, dtype=torch.float32, device=device),
        torch.arange(intrinsics.width, dtype=torch.float32, device=device),
        indexing="ij",
    )
    return torch.stack(
        [(u - intrinsics.cx) / intrinsics.fx, (v - intrinsics.cy) / intrinsics.fy, torch.ones_like(u)], dim=-1
    )


def _lattice(n: int, stride: int) -> torch.Tensor:
    """Pixel coordinates 0, stride, 2 stride, ... plus the last one, so it brackets all."""
    coords = list(range(0, n, stride))
    if coords[-1] != n - 1:
        coords.append(n - 1)
    return torch.tensor(coords, dtype=torch.long)


class GridRenderer:
    """Rendering for :class:`~nap3d_graph.fields.grid.GridField` (see the module docstring)."""

    # --- rendering --------------------------------------------------------------------------

    def render(self, T_world_cam: np.ndarray, intrinsics: Intrinsics) -> RenderedView:
        """RGB (uint8), z-depth (metres, 0 where nothing is hit) and opacity seen by an OpenCV
        pinhole camera at ``T_world_cam`` (4x4, world <- camera)."""
        T_world_cam = np.asarray(T_world_cam, dtype=np.float64)
        if T_world_cam.shape != (4, 4) or not np.all(np.isfinite(T_world_cam)):
            raise FieldError(f"T_world_cam must be a finite 4x4 matrix, got shape {T_world_cam.shape}")
        intrinsics = intrinsics.without_distortion()
        with torch.no_grad(), torch_threads(self.render_config.threads if self.device.type == "cpu" else None):
            rgb, depth, opacity, stats = self._render_image(T_world_cam, intrinsics)
        return RenderedView(
            rgb=_rgb_uint8(rgb.cpu().numpy()),
            depth_m=np.asarray(depth.cpu().numpy(), dtype=np.float32),
            opacity=np.clip(np.asarray(opacity.cpu().numpy(), dtype=np.float32), 0.0, 1.0),
            intrinsics=intrinsics,
            extras={"render_stats": stats},
        )

    def _camera_rays(self, T_world_cam: np.ndarray, intrinsics: Intrinsics):
        R = torch.as_tensor(T_world_cam[:3, :3], dtype=torch.float32, device=self.device)
        origin = self.world_to_local(T_world_cam[:3, 3])
        dirs = pixel_directions(intrinsics, self.device) @ R.T  # (H, W, 3), unit camera z
        return origin, dirs

    def _render_image(self, T_world_cam: np.ndarray, intrinsics: Intrinsics):
        """(rgb (H, W, 3), depth (H, W), opacity (H, W), stats) as tensors, compiled or torch."""
        kernels = _compiled_kernels() if (self.device.type == "cpu" and self.render_config.backend == "auto") else None
        if kernels is not None:
            return self._render_image_compiled(kernels, T_world_cam, intrinsics)
        return self._render_image_torch(T_world_cam, intrinsics)

    def _render_image_compiled(self, kernels, T_world_cam: np.ndarray, intrinsics: Intrinsics):
        """The hierarchical render by :mod:`~nap3d_graph.fields.grid_kernels` (CPU)."""
        cfg = self.render_config
        started = time.perf_counter()
        h, w = intrinsics.height, intrinsics.width
        stride = 1
        while (h * w) / float(stride * stride) > cfg.coarse_rays:
            stride *= 2
        density, occupancy, color = self._numpy_grids()
        origin = self.world_to_local(T_world_cam[:3, 3]).numpy().astype(np.float64)
        R = np.ascontiguousarray(T_world_cam[:3, :3], dtype=np.float64)
        params = np.array([cfg.near_m, cfg.march_step_vox, cfg.window_voxels, cfg.max_march_windows,
                           cfg.window_samples, cfg.window_margin_m, cfg.edge_gap_m, cfg.refine_samples,
                           cfg.min_opacity, cfg.interpolate_below_stride, cfg.smooth_min_opacity,
                           cfg.smooth_max_spread_m, cfg.smooth_max_twist_m, cfg.empty_cell_opacity],
                          dtype=np.float64)
        counts = np.zeros(5, dtype=np.int64)
        K = (float(intrinsics.fx), float(intrinsics.fy), float(intrinsics.cx), float(intrinsics.cy))
        depth, opacity = kernels.render_depth(density, occupancy, origin, R, *K, h, w, stride, self.voxel_size,
                                              DENSITY_SHIFT, params, counts)
        levels_s = time.perf_counter() - started
        rgb = kernels.shade(color, self.color_voxel_size, origin, R, *K, depth, opacity, 1e-3)
        stats = {"level0_stride": stride, "marched": int(counts[0]), "windowed": int(counts[1]),
                 "interpolated": int(counts[2]), "fallback": int(counts[3]), "empty": int(counts[4]),
                 "backend": "compiled",
                 "t_levels": levels_s, "seconds": time.perf_counter() - started}
        return torch.from_numpy(rgb), torch.from_numpy(depth), torch.from_numpy(opacity), stats

    def _render_image_torch(self, T_world_cam: np.ndarray, intrinsics: Intrinsics):
        """The hierarchical render in batched torch operations (any device)."""
        cfg = self.render_config
        started = time.perf_counter()
        h, w = intrinsics.height, intrinsics.width
        origin, dirs = self._camera_rays(T_world_cam, intrinsics)
        depth = torch.zeros((h, w), device=self.device)
        opacity = torch.zeros((h, w), device=self.device)
        known = torch.zeros((h, w), dtype=torch.bool, device=self.device)
        stride = 1
        while (h * w) / float(stride * stride) > cfg.coarse_rays:
            stride *= 2
        stats = {"level0_stride": stride, "marched": 0, "windowed": 0, "interpolated": 0, "fallback": 0,
                 "empty": 0, "backend": "torch"}

        # Level 0: full march on a sparse lattice.
        us, vs = _lattice(w, stride).to(self.device), _lattice(h, stride).to(self.device)
        vv, uu = torch.meshgrid(vs, us, indexing="ij")
        z, a = self._march(origin, dirs[vv, uu].reshape(-1, 3))
        depth[vv, uu] = z.reshape(vv.shape)
        opacity[vv, uu] = a.reshape(vv.shape)
        known[vv, uu] = True
        stats["marched"] += vv.numel()
        stats["t_level0"] = time.perf_counter() - started

        # Finer levels: windows around the depths of the bracketing coarse pixels.
        while stride > 1:
            fine = stride // 2
            us_f, vs_f = _lattice(w, fine).to(self.device), _lattice(h, fine).to(self.device)
            vv, uu = torch.meshgrid(vs_f, us_f, indexing="ij")
            new = ~known[vv, uu]
            vv, uu = vv[new], uu[new]
            iu = torch.searchsorted(us, uu, right=True) - 1
            iv = torch.searchsorted(vs, vv, right=True) - 1
            u0, v0 = us[iu], vs[iv]
            u1 = us[torch.clamp(iu + (us[iu] != uu).long(), max=len(us) - 1)]
            v1 = vs[torch.clamp(iv + (vs[iv] != vv).long(), max=len(vs) - 1)]
            corners_z = torch.stack([depth[v0, u0], depth[v0, u1], depth[v1, u0], depth[v1, u1]], dim=1)
            corners_a = torch.stack([opacity[v0, u0], opacity[v0, u1], opacity[v1, u0], opacity[v1, u1]], dim=1)
            z = torch.zeros(vv.shape[0], device=self.device)
            a = torch.zeros(vv.shape[0], device=self.device)
            todo = torch.ones(vv.shape[0], dtype=torch.bool, device=self.device)
            if fine <= cfg.interpolate_below_stride:
                # Smooth, opaque neighbourhoods: interpolate inverse depth (exact on planes).
                smooth = _smooth_cells(corners_z, corners_a, cfg)
                if bool(smooth.any()):
                    wu = _fraction(uu, u0, u1)[smooth]
                    wv = _fraction(vv, v0, v1)[smooth]
                    bilinear = torch.stack([(1 - wu) * (1 - wv), wu * (1 - wv), (1 - wu) * wv, wu * wv], dim=1)
                    z[smooth] = 1.0 / (bilinear / corners_z[smooth]).sum(dim=1)
                    a[smooth] = (bilinear * corners_a[smooth]).sum(dim=1)
                    todo = ~smooth
                    stats["interpolated"] += int(smooth.sum())
            # Smooth cells: one window spanning the corners' depths. Depth edges (or corners
            # without a surface): march, from just before the nearest corner's surface.
            ok = corners_a >= cfg.min_opacity
            big = torch.full_like(corners_z, 1e9)
            z_near = torch.where(ok, corners_z, big).amin(dim=1)
            z_far = torch.where(ok, corners_z, -big).amax(dim=1)
            windowed = todo & ok.any(dim=1) & ((z_far - z_near) <= cfg.edge_gap_m)
            sel = windowed.nonzero()[:, 0]
            zs, as_ = self._window(origin, dirs[vv[sel], uu[sel]], z_near[sel], z_far[sel])
            z[sel], a[sel] = zs, as_
            stats["windowed"] += int(sel.numel())
            march = (todo & ~windowed) | (windowed & (a < cfg.min_opacity))
            if cfg.empty_cell_opacity > 0:
                # No corner saw even a faint surface: a hole, where a march finds none either
                # (silhouettes, with a partly opaque corner, still march).
                empty = todo & (corners_a < cfg.empty_cell_opacity).all(dim=1)
                if bool(empty.any()):
                    wu = _fraction(uu, u0, u1)[empty]
                    wv = _fraction(vv, v0, v1)[empty]
                    bilinear = torch.stack([(1 - wu) * (1 - wv), wu * (1 - wv), (1 - wu) * wv, wu * wv], dim=1)
                    a[empty] = (bilinear * corners_a[empty]).sum(dim=1)
                    z[empty] = corners_z[empty].gather(1, corners_a[empty].argmax(dim=1, keepdim=True))[:, 0]
                    march = march & ~empty
                    stats["empty"] += int(empty.sum())
            rows = march.nonzero()[:, 0]
            if rows.numel():
                start = torch.where(ok[rows].any(dim=1), z_near[rows] - cfg.window_margin_m,
                                    torch.zeros_like(z_near[rows]))
                # A window that found nothing starts over from the camera.
                start = torch.where(windowed[rows], torch.zeros_like(start), start)
                z[rows], a[rows] = self._march(origin, dirs[vv[rows], uu[rows]], t_start=start)
                stats["fallback"] += int(rows.numel())
            depth[vv, uu] = z
            opacity[vv, uu] = a
            known[vv, uu] = True
            us, vs, stride = us_f, vs_f, fine

        stats["t_levels"] = time.perf_counter() - started
        hit = opacity > 1e-3
        points = origin + dirs * depth[..., None]
        rgb = torch.zeros((h, w, 3), device=self.device)
        if bool(hit.any()):
            rgb[hit] = self.rgb_local(points[hit]) * opacity[hit][:, None]
        depth = torch.where(hit, depth, torch.zeros_like(depth))
        stats["seconds"] = time.perf_counter() - started
        return rgb, depth, opacity, stats

    # --- ray kernels (all rays have unit camera-z directions, so t is z-depth) ---------------

    def _box_range(self, origin: torch.Tensor, dirs: torch.Tensor, near: float) -> tuple[torch.Tensor, torch.Tensor]:
        """Entry and exit ``t`` of rays through the grid box (local frame)."""
        hi = (torch.tensor(self.shape_xyz, dtype=torch.float32, device=self.device) - 1.0) * self.voxel_size
        safe = torch.where(dirs.abs() < 1e-9, torch.full_like(dirs, 1e-9), dirs)
        t0 = (0.0 - origin) / safe
        t1 = (hi - origin) / safe
        t_in = torch.minimum(t0, t1).amax(dim=-1).clamp(min=near)
        t_out = torch.maximum(t0, t1).amin(dim=-1)
        return t_in, t_out

    def _march(self, origin: torch.Tensor, dirs: torch.Tensor, t_start: torch.Tensor | None = None,
               chunk: int = 32768):
        """:meth:`_march_chunk` over chunks of rays, so temporaries stay small."""
        if dirs.shape[0] <= chunk:
            return self._march_chunk(origin, dirs, t_start)
        parts = [self._march_chunk(origin, dirs[i : i + chunk], None if t_start is None else t_start[i : i + chunk])
                 for i in range(0, dirs.shape[0], chunk)]
        return torch.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts])

    def _march_chunk(self, origin: torch.Tensor, dirs: torch.Tensor, t_start: torch.Tensor | None = None):
        """Full march of rays (N, 3) from ``t_start`` (N,) (default: the camera or the grid's
        entry): median depth (N,) and opacity (N,).

        Repeats: find the first occupied coarse cell from the current start (cheap nearest
        lookups, one per voxel), then sample the trilinear density finely in a window from
        just before it; rays whose transmittance has not crossed 0.5 go on from the window's
        end, carrying their optical depth.
        """
        cfg = self.render_config
        n = dirs.shape[0]
        depth = torch.zeros(n, device=self.device)
        opacity = torch.zeros(n, device=self.device)
        if n == 0:
            return depth, opacity
        norms = dirs.norm(dim=-1)
        t_in, t_end = self._box_range(origin, dirs, cfg.near_m)
        t_start = t_in if t_start is None else torch.maximum(t_in, t_start)
        step = self.voxel_size / norms  # one voxel of metric length, in t (z-depth) units
        tau0 = torch.zeros(n, device=self.device)
        active = torch.arange(n, device=self.device)
        fine = max(2, int(round(cfg.window_voxels / cfg.march_step_vox)))
        for _ in range(cfg.max_march_windows):
            if active.numel() == 0:
                break
            t_hit, found = self._first_occupied(origin, dirs[active], t_start[active], t_end[active], step[active])
            active, t_hit = active[found], t_hit[found]
            if active.numel() == 0:
                break
            a0 = t_hit - 1.5 * step[active]
            length = cfg.window_voxels * step[active]
            k = (torch.arange(fine, device=self.device, dtype=torch.float32) + 0.5) / fine
            t = a0[:, None] + length[:, None] * k[None, :]
            dt = (length / fine)[:, None].expand_as(t)
            d = dirs[active]
            inside = t < t_end[active, None]
            points = origin + t[..., None] * d[:, None, :]
            sigma = self.sigma_from_raw(self.raw_density_local(points)) * inside
            tau = sigma * dt * norms[active, None]
            z, a = _median_depth(t, dt, tau, active.numel(), self, origin, d, refine=cfg.refine_samples,
                                 tau0=tau0[active])
            depth[active] = z
            opacity[active] = a
            tau0[active] = tau0[active] + tau.sum(dim=1)
            go_on = a < 0.5
            t_start[active] = a0 + length
            active = active[go_on]
        return depth, opacity

    def _first_occupied(self, origin, dirs, t_start, t_end, step, chunk_steps: int = 48):
        """First ``t`` at or after ``t_start`` (N,) where the ray (N, 3) is in an occupied
        coarse cell, sampling every ``step`` (N,); ``found`` is False for rays that leave
        the grid first."""
        n = dirs.shape[0]
        occ = self.occupancy().reshape(-1)
        cz, cy, cx = self.occupancy().shape
        inv_cell = 1.0 / (2.0 * self.voxel_size)
        t_hit = torch.zeros(n, device=self.device)
        found = torch.zeros(n, dtype=torch.bool, device=self.device)
        pending = torch.arange(n, device=self.device)
        k = torch.arange(chunk_steps, device=self.device, dtype=torch.float32)
        start = t_start.clone()
        while pending.numel() > 0:
            t = start[pending, None] + (k[None, :] + 0.5) * step[pending, None]  # (P, K)
            cell = ((origin + t[..., None] * dirs[pending, None, :]) * inv_cell).floor_()
            cell_x = cell[..., 0].clamp_(0, cx - 1)
            cell_y = cell[..., 1].clamp_(0, cy - 1)
            cell_z = cell[..., 2].clamp_(0, cz - 1)
            flat = ((cell_z * cy + cell_y) * cx + cell_x).long()
            hit = occ[flat] & (t < t_end[pending, None])
            any_hit = hit.any(dim=1)
            first = hit.float().argmax(dim=1)
            rows = pending[any_hit]
            t_hit[rows] = t[any_hit, first[any_hit]]
            found[rows] = True
            start[pending] = start[pending] + chunk_steps * step[pending]
            pending = pending[~any_hit & (start[pending] < t_end[pending])]
        return t_hit, found

    def _window(self, origin: torch.Tensor, dirs: torch.Tensor, z_lo: torch.Tensor, z_hi: torch.Tensor):
        """Depth and opacity of rays (N, 3) whose surface lies in ``[z_lo, z_hi]`` (N,), give or
        take the window margin: a few samples there, then the crossing refined."""
        cfg = self.render_config
        n = dirs.shape[0]
        if n == 0:
            empty = torch.zeros(0, device=self.device)
            return empty, empty
        a0 = z_lo - cfg.window_margin_m
        length = (z_hi + cfg.window_margin_m) - a0
        k = (torch.arange(cfg.window_samples, device=self.device, dtype=torch.float32) + 0.5) / cfg.window_samples
        t = a0[:, None] + length[:, None] * k[None, :]
        dt = (length / cfg.window_samples)[:, None].expand_as(t)
        norms = dirs.norm(dim=-1)
        t_in, t_out = self._box_range(origin, dirs, cfg.near_m)
        inside = (t > t_in[:, None]) & (t < t_out[:, None])
        points = origin + t[..., None] * dirs[:, None, :]
        sigma = self.sigma_from_raw(self.raw_density_local(points)) * inside
        tau = sigma * dt * norms[:, None]
        return _median_depth(t, dt, tau, n, self, origin, dirs, refine=cfg.refine_samples)

    # --- reference renderer (slow, exact enough to check the fast one) ------------------------

    def render_reference(self, T_world_cam: np.ndarray, intrinsics: Intrinsics, step_vox: float = 0.1,
                         chunk: int = 2048) -> RenderedView:
        """Plain volume rendering with uniform samples every ``step_vox`` voxels: slow, used to
        check the hierarchical renderer. Depth is the median termination depth."""
        T_world_cam = np.asarray(T_world_cam, dtype=np.float64)
        intrinsics = intrinsics.without_distortion()
        with torch.no_grad(), torch_threads(self.render_config.threads if self.device.type == "cpu" else None):
            origin, dirs = self._camera_rays(T_world_cam, intrinsics)
            flat = dirs.reshape(-1, 3)
            z_out, a_out, rgb_out = [], [], []
            for start in range(0, flat.shape[0], chunk):
                d = flat[start : start + chunk]
                norms = d.norm(dim=-1)
                t_in, t_out = self._box_range(origin, d, self.render_config.near_m)
                dt = step_vox * self.voxel_size / norms
                steps = int(torch.clamp(((t_out - t_in) / dt).max(), min=1).ceil())
                k = torch.arange(steps, device=self.device, dtype=torch.float32)
                t = t_in[:, None] + (k[None, :] + 0.5) * dt[:, None]
                points = origin + t[..., None] * d[:, None, :]
                sigma = self.sigma_from_raw(self.raw_density_local(points)) * (t < t_out[:, None])
                tau = sigma * (dt * norms)[:, None]
                trans = torch.exp(-torch.cumsum(tau, dim=1))
                weights = torch.cat([torch.ones_like(trans[:, :1]), trans[:, :-1]], dim=1) - trans
                rgb_out.append((weights[..., None] * self.rgb_local(points)).sum(dim=1))
                z, a = _median_depth(t, dt[:, None].expand_as(t), tau, d.shape[0], self, origin, d, refine=0)
                z_out.append(z)
                a_out.append(a)
            h, w = intrinsics.height, intrinsics.width
            rgb = torch.cat(rgb_out).reshape(h, w, 3)
            depth = torch.cat(z_out).reshape(h, w)
            opacity = torch.cat(a_out).reshape(h, w)
        return RenderedView(
            rgb=(rgb.clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu().numpy(),
            depth_m=torch.where(opacity > 1e-3, depth, torch.zeros_like(depth)).cpu().numpy(),
            opacity=opacity.clamp(0, 1).cpu().numpy(),
            intrinsics=intrinsics,
        )


@functools.lru_cache(maxsize=1)
def _compiled_kernels():
    """The kernels of :mod:`~nap3d_graph.fields.grid_kernels` (``render_depth``, ``shade``), or
    None (logged once) without numba. The names are imported, not the module through the
    package (``from . import``), which would make the package and this module import each other."""
    try:
        from .grid_kernels import render_depth, shade
    except ImportError as exc:
        log.warning("numba is not installed (%s): the grid field renders with torch on the CPU, several times "
                    "slower; `pip install numba` (in the \"full\" extra) for the compiled renderer", exc)
        return None
    return types.SimpleNamespace(render_depth=render_depth, shade=shade)


def _rgb_uint8(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 of colours in [0, 1] (float32): clipped, times 255, rounded half up, in
    place on one float32 copy (the same values torch's clamp/mul/add/cast gave, in a tenth of
    its time with one thread)."""
    out = np.clip(np.asarray(rgb, dtype=np.float32), 0.0, 1.0)
    out *= np.float32(255.0)
    out += np.float32(0.5)
    return out.astype(np.uint8)


def _fraction(x: torch.Tensor, x0: torch.Tensor, x1: torch.Tensor) -> torch.Tensor:
    """Position of ``x`` between lattice neighbours ``x0 <= x <= x1`` in [0, 1] (0 when equal)."""
    span = (x1 - x0).float()
    return torch.where(span > 0, (x - x0).float() / span.clamp(min=1.0), torch.zeros_like(span))


def _smooth_cells(corners_z: torch.Tensor, corners_a: torch.Tensor, cfg: RenderConfig) -> torch.Tensor:
    """Cells whose four corner pixels (N, 4) all see an opaque surface at nearly the same,
    nearly planar depth: inverse depth is bilinear in the pixel coordinates on a plane, so
    interpolating it there is exact up to curvature over a couple of pixels."""
    opaque = (corners_a >= cfg.smooth_min_opacity).all(dim=1) & (corners_z > 0).all(dim=1)
    spread = corners_z.amax(dim=1) - corners_z.amin(dim=1)
    inv = 1.0 / corners_z.clamp(min=1e-3)
    # Twist of the bilinear patch of inverse depth; zero on any plane (in metres at this depth).
    twist = (inv[:, 0] + inv[:, 3] - inv[:, 1] - inv[:, 2]).abs() * corners_z.mean(dim=1) ** 2
    return opaque & (spread < cfg.smooth_max_spread_m) & (twist < cfg.smooth_max_twist_m)


def _median_depth(t, dt, tau, n, field: GridRenderer, origin, dirs, refine: int, tau0=None):
    """Median termination depth and opacity from samples.

    t, dt, tau: (N, S) sample positions (z-depth), their interval lengths (in t) and optical
    depths, sorted along each ray; a sample stands for ``[t - dt/2, t + dt/2]``. The depth is
    where the optical depth reaches ln 2 (transmittance 0.5); ``refine`` extra density samples
    inside that interval place it more precisely. Rays that never reach transmittance 0.5 get
    their expected depth (weights normalised). ``tau0`` (N,): optical depth already
    accumulated before the first sample.
    """
    cum = torch.cumsum(tau, dim=1)
    if tau0 is not None:
        cum = cum + tau0[:, None]
    total = cum[:, -1] if cum.shape[1] else (tau0 if tau0 is not None else torch.zeros(n, device=t.device))
    opacity = 1.0 - torch.exp(-total)
    crossed = total >= _LN2
    idx = torch.searchsorted(cum, torch.full((n, 1), _LN2, device=t.device)).clamp(max=max(t.shape[1] - 1, 0))
    t_i = t.gather(1, idx)[:, 0]
    dt_i = dt.gather(1, idx)[:, 0]
    tau_i = tau.gather(1, idx)[:, 0]
    before = (cum.gather(1, idx)[:, 0] - tau_i)
    start = t_i - 0.5 * dt_i
    # Piecewise-constant density inside the interval: exact crossing of that model.
    frac = ((_LN2 - before) / tau_i.clamp(min=1e-12)).clamp(0, 1)
    z = start + frac * dt_i
    if refine > 0 and bool(crossed.any()):
        sel = crossed.nonzero()[:, 0]
        k = (torch.arange(refine, device=t.device, dtype=torch.float32) + 0.5) / refine
        sub_dt = dt_i[sel] / refine
        ts = start[sel, None] + k[None, :] * dt_i[sel, None]
        d = dirs[sel]
        points = origin + ts[..., None] * d[:, None, :]
        norms = d.norm(dim=-1)
        sub_tau = field.sigma_from_raw(field.raw_density_local(points)) * (sub_dt * norms)[:, None]
        sub_cum = before[sel, None] + torch.cumsum(sub_tau, dim=1)
        j = torch.searchsorted(sub_cum, torch.full((len(sel), 1), _LN2, device=t.device)).clamp(max=refine - 1)
        tau_j = sub_tau.gather(1, j)[:, 0]
        before_j = sub_cum.gather(1, j)[:, 0] - tau_j
        frac_j = ((_LN2 - before_j) / tau_j.clamp(min=1e-12)).clamp(0, 1)
        z_ref = start[sel] + (j[:, 0].float() + frac_j) * sub_dt
        # Only where the refined samples confirm the crossing inside the interval.
        ok = sub_cum[:, -1] >= _LN2
        z[sel] = torch.where(ok, z_ref, z[sel])
    trans_before = torch.exp(-(cum - tau))
    weights = trans_before * (1.0 - torch.exp(-tau))
    expected = (weights * t).sum(dim=1) / weights.sum(dim=1).clamp(min=1e-12)
    z = torch.where(crossed, z, expected)
    return z, opacity
