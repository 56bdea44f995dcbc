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

On a CPU the algorithm runs compiled, a loop per ray (:mod:`.grid_kernels`, numba: 4x faster
than the batched torch operations, which stay the path on a GPU and without numba).

Why hand-written: no maintained package renders a voxel radiance field on a CPU without a
CUDA extension (nerfacc, tiny-cuda-nn, Plenoxels' svox2 and DVGO's kernels all need CUDA).
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from .base import FieldError
from .checkpoint import load_state, meta_json, save_state
from .grid_render import DENSITY_SHIFT, GridRenderer, RenderConfig

__all__ = [
    "GridField",
    "CHECKPOINT_FORMAT",
    "CHECKPOINT_VERSION",
    "default_device",
    "trilinear_corners",
]

log = logging.getLogger(__name__)

CHECKPOINT_FORMAT = "nap3d-graph grid field"
#: Bumped whenever the meaning of a stored tensor changes; older files are refused.
CHECKPOINT_VERSION = 1
#: Raw density above which a coarse cell counts as occupied (sigma ~ 0.018 per voxel).
_OCCUPIED_RAW = DENSITY_SHIFT - 4.0


def default_device() -> torch.device:
    """CUDA when torch sees a GPU, otherwise the CPU; every code path runs on both."""
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


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


class GridField(GridRenderer):
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
        self._numpy: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

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
        self._numpy = None

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

    def _numpy_grids(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """CPU numpy views for the compiled renderer: raw density (nz, ny, nx) float32,
        occupancy (cz, cy, cx) bool, raw colour (mz, my, mx, 3) float32. Cached until
        :meth:`mark_changed`."""
        if self._numpy is None:
            def view(t: torch.Tensor) -> np.ndarray:
                return np.ascontiguousarray(t.detach().cpu().numpy())
            if self.color.device.type == "cpu":
                self.color_channels_last()
            # Colour channel-last: a pixel's three channels share a cache line.
            self._numpy = (view(self.density[0, 0]), view(self.occupancy()), view(self.color[0].permute(1, 2, 3, 0)))
        return self._numpy

    def color_channels_last(self) -> torch.Tensor:
        """The colour grid stored channel-last, (mz, my, mx, 3), and returned as that tensor;
        ``color`` stays its (1, 3, mz, my, mx) view. What the compiled renderer and the trainer
        read: one copy of the colour (most of a grid's memory) instead of one per layout."""
        last = self.color[0].permute(1, 2, 3, 0)
        if not last.is_contiguous():
            last = last.contiguous()
            self.color = last.permute(3, 0, 1, 2).unsqueeze(0)
        return last

    # --- checkpoints --------------------------------------------------------------------------

    def state_dict(self) -> dict:
        """Everything needed to render, as tensors and plain values (no pickled code)."""
        return {
            "format": CHECKPOINT_FORMAT,
            "version": CHECKPOINT_VERSION,
            "density_raw": self.density[0, 0].detach().cpu().contiguous(),
            # Saved as the channel-last storage it renders from, seen as (3, mz, my, mx): the file's
            # shape is the same for every reader, and loading it needs no second copy of the colour.
            "color_raw": self.color_channels_last().detach().cpu().permute(3, 0, 1, 2),
            "grid_min_m": torch.as_tensor(self.grid_min, dtype=torch.float64),
            "voxel_size_m": float(self.voxel_size),
            "color_voxel_size_m": float(self.color_voxel_size),
            "density_shift": float(DENSITY_SHIFT),
            "conventions": "units=metres; depth=z-depth; camera=OpenCV (x right, y down, z forward); "
                           "poses=T_world_cam; grid tensors indexed [z, y, x]; "
                           "sigma_per_m=softplus(raw-shift)/voxel; rgb=sigmoid(raw)",
            "render_config": json.dumps(asdict(self.render_config)),
            "meta": meta_json(self.meta),
        }

    def save(self, path) -> Path:
        """Write the checkpoint (``torch.save`` of :meth:`state_dict`, atomically); returns the path."""
        return save_state(self.state_dict(), path)

    @classmethod
    def from_state_dict(cls, state: dict, device=None, source: str = "checkpoint", scan: bool = True) -> "GridField":
        """The field of a :meth:`state_dict`; :class:`FieldError` on a foreign, wrong-version or
        malformed one, and (``scan``) on non-finite weights."""
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
        if scan and not (_all_finite(density) and _all_finite(color)):
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


def _all_finite(tensor: torch.Tensor, chunk: int = 1 << 22) -> bool:
    """Whether every value is finite, checked a chunk at a time: ``torch.isfinite`` of a whole
    grid makes temporaries as large as the grid (a run's memory peaked at reading a submap)."""
    # In its storage's order (a channel-last colour grid too): a view, never a copy of the grid.
    in_storage = tensor.permute(sorted(range(tensor.ndim), key=lambda d: -tensor.stride(d)))
    flat = in_storage.reshape(-1)
    return all(bool(torch.isfinite(part).all()) for part in flat.split(chunk))
