"""A dense voxel-grid radiance field in plain torch, and its fast renderer.

The field stores, at the vertices of a regular grid over the scene's bounds, a raw density
(one channel) and raw colour features (three channels). Both are interpolated trilinearly with
``torch.nn.functional.grid_sample`` *before* their activations (DVGO's "post-activation"):
density ``sigma = softplus(raw - DENSITY_SHIFT) / voxel_size`` (per metre) and colour
``rgb = sigmoid(raw)``. Interpolating before the activation lets a surface sit anywhere inside
a voxel with a sharp density edge, which is what sub-centimetre depth from a 3 cm grid needs.
A zero raw density is near-transparent (``softplus(-10)`` ~ 5e-5 per voxel), so a new field
is empty and points outside the grid (zero padding) are empty too.

World frame: whatever frame the training poses live in (``T_world_cam``, OpenCV camera).
Grid axes are the world axes; ``grid_sample``'s (x, y, z) coordinates address the tensor's
(W, H, D) dimensions, so the density tensor is indexed ``[z, y, x]``.

Rendering (``render``) is hierarchical because a CPU cannot afford hundreds of trilinear
samples per pixel (``grid_sample`` does ~15 M coherent samples/s on 2 cores):

1. level 0, a sparse lattice of ~5k pixels, marches: a coarse occupancy grid (the largest raw
   density over 2x2x2 voxels, a conservative bound, read with cheap nearest lookups one voxel
   apart) finds the first cell that could hold a surface, and the trilinear density is
   sampled every 1/3 voxel in a window from there (again further on if it was not opaque);
2. each finer lattice level (the stride halves down to 1) starts from the four bracketing
   coarse pixels: where they agree (a smooth surface) a few samples in one window spanning
   their depths suffice; at depth edges the ray marches from the nearest of them; a window
   that finds no surface falls back to the full march. At the last level, cells whose
   corners are opaque and nearly planar interpolate inverse depth (exact on planes);
3. the depth is the median termination depth (where transmittance crosses 0.5), refined with
   a few extra samples inside the crossing interval; colour is looked up once, at that point.

Why hand-written: no maintained package renders a voxel radiance field on a CPU without a
CUDA extension (nerfacc, tiny-cuda-nn, Plenoxels' svox2 and DVGO's kernels all need CUDA).
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from nap3d_graph.camera import Intrinsics, RenderedView

from .base import FieldError
from .checkpoint import load_state

__all__ = [
    "GridField",
    "RenderConfig",
    "CHECKPOINT_FORMAT",
    "CHECKPOINT_VERSION",
    "DENSITY_SHIFT",
    "default_device",
    "pixel_directions",
    "trilinear_corners",
    "torch_threads",
]

log = logging.getLogger(__name__)

CHECKPOINT_FORMAT = "nap3d-graph grid field"
#: Bumped whenever the meaning of a stored tensor changes; older files are refused.
CHECKPOINT_VERSION = 1
#: Raw density 0 maps to a near-transparent softplus(-DENSITY_SHIFT).
DENSITY_SHIFT = 10.0
#: Raw density above which a coarse cell counts as occupied (sigma ~ 0.018 per voxel).
_OCCUPIED_RAW = DENSITY_SHIFT - 4.0
_LN2 = math.log(2.0)


@contextlib.contextmanager
def torch_threads(count: int | None):
    """Run a block with ``torch.set_num_threads(count)`` and restore the old setting after.

    Why: on a small CPU, and on any CPU other processes also use, torch's OpenMP threads spin
    while they wait for each other; one thread measured 15x faster than two per training step
    on this project's 2-core machine under load, and no slower when it was idle.
    ``None`` leaves torch's setting alone.
    """
    if count is None or count == torch.get_num_threads():
        yield
        return
    previous = torch.get_num_threads()
    torch.set_num_threads(int(count))
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def default_device() -> torch.device:
    """CUDA when torch sees a GPU, otherwise the CPU; every code path runs on both."""
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


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
    smooth_max_twist_m. threads: torch CPU threads while rendering (see :func:`torch_threads`;
    None keeps torch's setting).
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


def trilinear_corners(points_local: torch.Tensor, shape_xyz: tuple[int, int, int], voxel_size: float):
    """The 8 grid vertices around each point and their trilinear weights.

    points_local (N, 3) metres relative to the grid's first vertex; points outside the grid
    are clamped onto its faces. Returns ``idx`` (N, 8) int64 flat vertex indices into a
    ``[z, y, x]``-ordered grid and ``w`` (N, 8) weights summing to 1, corner order
    ``(dz, dy, dx)`` -- the same interpolation as ``grid_sample(align_corners=True)``.
    """
    nx, ny, nz = shape_xyz
    device = points_local.device
    # Clamp just inside the last cell so floor() never selects a cell past the grid.
    hi = torch.tensor([nx - 1, ny - 1, nz - 1], dtype=torch.float32, device=device) - 1e-4
    q = torch.clamp(points_local * (1.0 / voxel_size), min=torch.zeros_like(hi), max=hi)
    i0 = q.floor()
    frac = q - i0
    i0 = i0.long()
    base = i0[:, 0] + i0[:, 1] * nx + i0[:, 2] * (nx * ny)
    offsets = torch.tensor([dz * nx * ny + dy * nx + dx for dz in (0, 1) for dy in (0, 1) for dx in (0, 1)],
                           device=device)
    idx = base[:, None] + offsets
    pair = torch.stack([1.0 - frac, frac], dim=2)  # (N, 3, 2): weights of the low and high vertex
    w = ((pair[:, 2, :, None] * pair[:, 1, None, :])[:, :, :, None] * pair[:, 0, None, None, :]).reshape(-1, 8)
    return idx, w


def _lattice(n: int, stride: int) -> torch.Tensor:
    """Pixel coordinates 0, stride, 2 stride, ... plus the last one, so it brackets all."""
    coords = list(range(0, n, stride))
    if coords[-1] != n - 1:
        coords.append(n - 1)
    return torch.tensor(coords, dtype=torch.long)


class GridField:
    """Dense voxel grids of raw density and colour; satisfies the field protocol.

    density_raw: (nz, ny, nx) float32 tensor at ``voxel_size`` spacing; color_raw:
    (3, mz, my, mx) float32 tensor at ``color_voxel_size`` spacing (finer than the density
    grid by default: texture needs more detail than geometry, and colour is looked up only
    near surfaces). Both grids start at ``grid_min``, the world position (3,) of vertex
    [0, 0, 0], metres. ``meta`` is a JSON-serialisable dict kept in the checkpoint (training
    config, data source, report summary).
    """

    name = "grid"

    def __init__(
        self,
        density_raw: torch.Tensor,
        color_raw: torch.Tensor,
        grid_min,
        voxel_size: float,
        meta: dict | None = None,
        render_config: RenderConfig | None = None,
        color_voxel_size: float | None = None,
    ):
        density_raw = torch.as_tensor(density_raw, dtype=torch.float32)
        color_raw = torch.as_tensor(color_raw, dtype=torch.float32)
        if density_raw.ndim != 3 or color_raw.ndim != 4 or color_raw.shape[0] != 3:
            raise FieldError(
                f"grid field needs density (nz, ny, nx) and colour (3, mz, my, mx), got "
                f"{tuple(density_raw.shape)} and {tuple(color_raw.shape)}"
            )
        if min(density_raw.shape) < 2 or min(color_raw.shape[1:]) < 2:
            raise FieldError(f"grid field needs at least 2 vertices per axis, got {tuple(density_raw.shape)}")
        color_voxel_size = float(voxel_size if color_voxel_size is None else color_voxel_size)
        if not (voxel_size > 0 and color_voxel_size > 0):
            raise FieldError(f"voxel sizes must be positive, got {voxel_size} and {color_voxel_size}")
        self.density = density_raw.reshape(1, 1, *density_raw.shape)
        self.color = color_raw.reshape(1, *color_raw.shape)
        self.grid_min = np.asarray(grid_min, dtype=np.float64).reshape(3)
        self.voxel_size = float(voxel_size)
        self.color_voxel_size = color_voxel_size
        self.meta = dict(meta or {})
        self.render_config = render_config or RenderConfig()
        self._occupancy: torch.Tensor | None = None

    # --- geometry -------------------------------------------------------------------------

    @property
    def device(self) -> torch.device:
        return self.density.device

    @property
    def shape_xyz(self) -> tuple[int, int, int]:
        """Density vertex counts along world x, y, z."""
        nz, ny, nx = self.density.shape[2:]
        return (nx, ny, nz)

    @property
    def color_shape_xyz(self) -> tuple[int, int, int]:
        """Colour vertex counts along world x, y, z."""
        mz, my, mx = self.color.shape[2:]
        return (mx, my, mz)

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) world box ``[min, max]`` in metres covered by the grid's vertices."""
        extent = (np.asarray(self.shape_xyz, dtype=np.float64) - 1.0) * self.voxel_size
        return np.stack([self.grid_min, self.grid_min + extent])

    @staticmethod
    def _counts(extent: np.ndarray, voxel_size: float) -> tuple[int, int, int]:
        counts = np.maximum(np.ceil(np.asarray(extent) / voxel_size - 1e-9).astype(int) + 1, 2)
        return tuple(int(c) for c in counts)

    @classmethod
    def empty(cls, bounds, voxel_size: float, device=None, meta: dict | None = None,
              color_voxel_size: float | None = None) -> "GridField":
        """A near-transparent grey field whose grids cover ``bounds`` (2, 3): density at
        ``voxel_size``, colour at ``color_voxel_size`` (default: the same)."""
        bounds = np.asarray(bounds, dtype=np.float64).reshape(2, 3)
        if not np.all(bounds[1] > bounds[0]):
            raise FieldError(f"empty bounds {bounds.tolist()}")
        if not (voxel_size > 0 and (color_voxel_size is None or color_voxel_size > 0)):
            raise FieldError(f"voxel sizes must be positive, got {voxel_size} and {color_voxel_size}")
        color_voxel_size = voxel_size if color_voxel_size is None else color_voxel_size
        nx, ny, nz = cls._counts(bounds[1] - bounds[0], voxel_size)
        extent = (np.array([nx, ny, nz]) - 1.0) * voxel_size
        mx, my, mz = cls._counts(extent, color_voxel_size)
        if max(nx * ny * nz, 3 * mx * my * mz) > 400_000_000:
            raise FieldError(f"a {nx}x{ny}x{nz} grid (colour {mx}x{my}x{mz}) is too large; use larger voxels")
        device = device or default_device()
        return cls(
            torch.zeros((nz, ny, nx), device=device),
            torch.zeros((3, mz, my, mx), device=device),
            bounds[0],
            voxel_size,
            meta,
            color_voxel_size=color_voxel_size,
        )

    def to(self, device) -> "GridField":
        """This field on another device (a new object; tensors are copied)."""
        return GridField(self.density[0, 0].to(device), self.color[0].to(device), self.grid_min,
                         self.voxel_size, self.meta, self.render_config, self.color_voxel_size)

    def resampled(self, voxel_size: float, color_voxel_size: float | None = None) -> "GridField":
        """The same field on grids of other voxel sizes (coarse-to-fine training).

        Raw values are interpolated trilinearly at the new vertices, which keeps the
        interpolated raw field (and so every rendered ray) nearly unchanged.
        """
        target = GridField.empty(self.bounds, voxel_size, device=self.device, color_voxel_size=color_voxel_size)

        def vertices(shape_xyz, spacing):
            nx, ny, nz = shape_xyz
            axes = [torch.arange(n, device=self.device, dtype=torch.float32) * spacing for n in (nx, ny, nz)]
            zz, yy, xx = torch.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
            return torch.stack([xx, yy, zz], dim=-1).reshape(1, nz, ny, nx, 3)

        with torch.no_grad():
            grid = self._local_to_grid(vertices(target.shape_xyz, voxel_size), self.shape_xyz, self.voxel_size)
            target.density = F.grid_sample(self.density, grid, align_corners=True, padding_mode="border")
            grid = self._local_to_grid(vertices(target.color_shape_xyz, target.color_voxel_size),
                                       self.color_shape_xyz, self.color_voxel_size)
            target.color = F.grid_sample(self.color, grid, align_corners=True, padding_mode="border")
        target.meta = dict(self.meta)
        return target

    def mark_changed(self) -> None:
        """Drop caches derived from the weights (call after editing or training them)."""
        self._occupancy = None

    # --- sampling -------------------------------------------------------------------------

    def _local_to_grid(self, points_local: torch.Tensor, shape_xyz=None, spacing: float | None = None) -> torch.Tensor:
        """Points relative to ``grid_min`` (..., 3) -> grid_sample coordinates in [-1, 1] of a
        grid with ``shape_xyz`` vertices at ``spacing`` (default: the density grid)."""
        shape_xyz = self.shape_xyz if shape_xyz is None else shape_xyz
        spacing = self.voxel_size if spacing is None else spacing
        extent = (torch.tensor(shape_xyz, dtype=torch.float32, device=points_local.device) - 1.0) * spacing
        return points_local * (2.0 / extent) - 1.0

    def world_to_local(self, points_world) -> torch.Tensor:
        """World points (..., 3) to float32 coordinates relative to ``grid_min``.

        Rays are built relative to ``grid_min`` in float64 first so float32 keeps
        sub-millimetre precision far from the world origin.
        """
        p = torch.as_tensor(points_world, dtype=torch.float64, device=self.device)
        return (p - torch.as_tensor(self.grid_min, device=self.device)).to(torch.float32)

    def raw_density_local(self, points_local: torch.Tensor) -> torch.Tensor:
        """Raw (pre-activation) density at local points (..., 3) -> (...)."""
        shape = points_local.shape[:-1]
        grid = self._local_to_grid(points_local.reshape(1, -1, 1, 1, 3))
        return F.grid_sample(self.density, grid, align_corners=True).reshape(shape)

    def sigma_from_raw(self, raw: torch.Tensor) -> torch.Tensor:
        """Density per metre from raw values."""
        return F.softplus(raw - DENSITY_SHIFT) / self.voxel_size

    def rgb_local(self, points_local: torch.Tensor) -> torch.Tensor:
        """Colour in [0, 1] at local points (..., 3) -> (..., 3)."""
        shape = points_local.shape[:-1]
        grid = self._local_to_grid(points_local.reshape(1, -1, 1, 1, 3), self.color_shape_xyz, self.color_voxel_size)
        raw = F.grid_sample(self.color, grid, align_corners=True).reshape(3, -1).T
        return torch.sigmoid(raw).reshape(*shape, 3)

    def occupancy(self) -> torch.Tensor:
        """Coarse occupancy (cz, cy, cx) bool: cell c covers vertices [2c, 2c + 2] per axis and
        is True when the largest raw density there could make the interpolated density
        noticeable. Cached until :meth:`mark_changed`."""
        if self._occupancy is None:
            d = self.density
            pad = [0, d.shape[4] % 2 == 0, 0, d.shape[3] % 2 == 0, 0, d.shape[2] % 2 == 0]
            padded = F.pad(d, [int(p) for p in pad], value=-1e4)
            pooled = F.max_pool3d(padded, kernel_size=3, stride=2)
            self._occupancy = (pooled[0, 0] > _OCCUPIED_RAW).contiguous()
        return self._occupancy

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
        rgb8 = (rgb.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()
        return RenderedView(
            rgb=rgb8,
            depth_m=depth.cpu().numpy().astype(np.float32),
            opacity=opacity.clamp(0, 1).cpu().numpy().astype(np.float32),
            intrinsics=intrinsics,
            extras={"render_stats": stats},
        )

    def _camera_rays(self, T_world_cam: np.ndarray, intrinsics: Intrinsics):
        R = torch.as_tensor(T_world_cam[:3, :3], dtype=torch.float32, device=self.device)
        origin = self.world_to_local(T_world_cam[:3, 3])
        dirs = pixel_directions(intrinsics, self.device) @ R.T  # (H, W, 3), unit camera z
        return origin, dirs

    def _render_image(self, T_world_cam: np.ndarray, intrinsics: Intrinsics):
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
        stats = {"level0_stride": stride, "marched": 0, "windowed": 0, "interpolated": 0, "fallback": 0}

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

    # --- checkpoints --------------------------------------------------------------------------

    def state_dict(self) -> dict:
        """Everything needed to render, as tensors and plain values (no pickled code)."""
        return {
            "format": CHECKPOINT_FORMAT,
            "version": CHECKPOINT_VERSION,
            "density_raw": self.density[0, 0].detach().cpu().contiguous(),
            "color_raw": self.color[0].detach().cpu().contiguous(),
            "grid_min_m": torch.as_tensor(self.grid_min, dtype=torch.float64),
            "voxel_size_m": float(self.voxel_size),
            "color_voxel_size_m": float(self.color_voxel_size),
            "density_shift": float(DENSITY_SHIFT),
            "conventions": "units=metres; depth=z-depth; camera=OpenCV (x right, y down, z forward); "
                           "poses=T_world_cam; grid tensors indexed [z, y, x]; "
                           "sigma_per_m=softplus(raw-shift)/voxel; rgb=sigmoid(raw)",
            "render_config": json.dumps(asdict(self.render_config)),
            "meta": json.dumps(self.meta, default=_json_default),
        }

    def save(self, path) -> Path:
        """Write the checkpoint (``torch.save`` of :meth:`state_dict`); returns the path."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp")
        torch.save(self.state_dict(), tmp)
        tmp.replace(path)  # never leave a half-written checkpoint under the real name
        return path

    @classmethod
    def from_state_dict(cls, state: dict, device=None, source: str = "checkpoint") -> "GridField":
        if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
            raise FieldError(f"{source}: not a nap3d-graph grid field checkpoint")
        version = state.get("version")
        if version != CHECKPOINT_VERSION:
            raise FieldError(
                f"{source}: grid field checkpoint version {version!r}, but this nap3d-graph reads "
                f"version {CHECKPOINT_VERSION}; retrain it with `nap3d-graph train-field`"
            )
        missing = [k for k in ("density_raw", "color_raw", "grid_min_m", "voxel_size_m", "density_shift") if k not in state]
        if missing:
            raise FieldError(f"{source}: checkpoint lacks {', '.join(missing)}")
        if float(state["density_shift"]) != DENSITY_SHIFT:
            raise FieldError(f"{source}: density shift {state['density_shift']} != {DENSITY_SHIFT}")
        density, color = state["density_raw"], state["color_raw"]
        if not (isinstance(density, torch.Tensor) and isinstance(color, torch.Tensor)):
            raise FieldError(f"{source}: density_raw and color_raw must be tensors")
        if not (torch.isfinite(density).all() and torch.isfinite(color).all()):
            raise FieldError(f"{source}: checkpoint holds non-finite weights")
        try:
            meta = json.loads(state.get("meta", "{}"))
            render_config = RenderConfig(**json.loads(state.get("render_config", "{}")))
        except (TypeError, ValueError) as exc:
            raise FieldError(f"{source}: unreadable checkpoint metadata ({exc})") from None
        device = device or default_device()
        if density.ndim != 3 or color.ndim != 4 or color.shape[0] != 3:
            raise FieldError(f"{source}: density/colour grids have shapes {tuple(density.shape)} and {tuple(color.shape)}")
        return cls(density.to(device), color.to(device), state["grid_min_m"].numpy(),
                   float(state["voxel_size_m"]), meta, render_config,
                   float(state.get("color_voxel_size_m", state["voxel_size_m"])))

    @classmethod
    def load(cls, path, device=None) -> "GridField":
        """Open a checkpoint written by :meth:`save` (``torch.load(weights_only=True)``: tensors
        and plain values only, never pickled code). Raises :class:`FieldError` on a missing,
        corrupt, foreign or wrong-version file."""
        path = Path(path)
        state = load_state(path)
        return cls.from_state_dict(state, device=device, source=str(path))

    def __repr__(self) -> str:
        nx, ny, nz = self.shape_xyz
        return (f"GridField({nx}x{ny}x{nz} vertices, voxel {self.voxel_size * 100:.1f} cm, colour voxel "
                f"{self.color_voxel_size * 100:.1f} cm, device={self.device})")


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


def _json_default(value):
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"cannot store {type(value).__name__} in checkpoint metadata")


def _median_depth(t, dt, tau, n, field: GridField, origin, dirs, refine: int, tau0=None):
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
