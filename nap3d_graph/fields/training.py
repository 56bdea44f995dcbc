"""Train a :class:`~nap3d_graph.fields.grid.GridField` from any posed RGB-D sequence, and
evaluate a field on held-out frames.

Any sequence works that has ``len(seq)``, ``seq[i] -> RGBDFrame``, ``seq.T_world_cam_gt``
(N, 4, 4) and ``seq.intrinsics``: a TUM folder, a simulated room, a RealSense recording.

What makes a grid converge in minutes on a CPU (a prototype's findings, then ours):

* depth-guided sampling: per ray a few stratified free-space samples between the camera and
  the measured depth, and most samples in a window around it (its half-width follows the
  sensor's ``sigma(z) = k z^2`` noise, at least a few centimetres);
* losses: RGB L2 against a *random background colour* per ray (so a see-through surface
  costs colour error, which drives opacity to 1 in a closed room), a DS-NeRF-like
  ``(1 - weight inside the depth window)^2``, URF-like terms on the weight that lands in
  free space and on the spread of the termination distribution around the measured depth,
  and a small ``|1 - opacity|``;
* a start from the depth images (:func:`splat_init`): back-projected points splatted into
  the grid give an opaque shell around the observed surfaces and their mean colour, so the
  optimiser refines instead of building surfaces from nothing (which a grid does slowly, and
  which filled free space with haze in the prototype);
* sparse work per step: patches of neighbouring rays (cache-friendly lookups), trilinear
  interpolation by explicit gathers, gradients scattered by hand and a lazy Adam that updates
  only the touched vertices (:class:`_LazyAdam`) -- a dense optimiser and ``grid_sample``'s
  backward cost O(grid) per step, most of a CPU step; colour only where a sample's weight
  exceeds ``color_weight_eps``; one torch thread (see ``grid.torch_threads``);
* colour on a grid 1.5x finer than density: texture needs more detail than geometry;
* a learning rate that decays with the *time* budget (the budget is minutes, not steps).
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, replace
from typing import Callable, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from nap3d_graph.camera import Intrinsics, backproject_depth, valid_depth_mask
from nap3d_graph.conventions import transform_points

from .base import FieldError
from .evaluation import evaluate_field, oracle_for, psnr
from .grid import (CHECKPOINT_VERSION, DENSITY_SHIFT, GridField, default_device, pixel_directions, torch_threads,
                   trilinear_corners)

__all__ = [
    "TrainConfig",
    "TrainingRays",
    "train_field",
    "split_frames",
    "split_posed_frames",
    "splat_init",
    "scene_bounds_from_depth",
]

log = logging.getLogger(__name__)


@dataclass
class TrainConfig:
    """Training settings; every field has a default that works for a room-sized scene.

    Geometry: ``voxel_size_m`` (density grid; colour is ``color_voxel_ratio`` times finer),
    ``coarse_voxel_size_m`` (an optional first stage on a coarser grid, for
    ``coarse_fraction`` of the budget; off by default since ``init_from_depth`` starts the
    grid from the back-projected depth). Budget: ``minutes`` of optimisation
    (loading and evaluation not counted), or ``max_steps`` if set. Frames: every ``every``-th
    frame is used for training; ``eval_frames`` held-out frames are evaluated.
    Sampling: ``rays_per_step``, ``free_samples`` and ``window_samples`` per ray; the window
    half-width is ``max(window_min_m, window_sigmas * depth_sigma_z2 * z^2)``.
    ``threads``: torch CPU threads during training (1: see ``grid.torch_threads``; None keeps
    torch's setting).
    """

    voxel_size_m: float = 0.03
    color_voxel_ratio: float = 1.5
    coarse_voxel_size_m: float | None = None
    coarse_fraction: float = 0.2
    minutes: float = 5.0
    max_steps: int | None = None
    every: int = 1
    eval_frames: int = 8
    seed: int = 0
    rays_per_step: int = 4096
    patch_size: int = 8
    free_samples: int = 8
    window_samples: int = 16
    window_min_m: float = 0.04
    window_sigmas: float = 3.0
    depth_sigma_z2: float = 1.4e-3
    min_depth_m: float = 0.1
    max_depth_m: float = 8.0
    bounds_margin_m: float = 0.15
    lr_density: float = 1.0
    lr_color: float = 0.1
    lr_final_ratio: float = 0.1
    weight_rgb: float = 1.0
    weight_window: float = 1.0
    weight_near: float = 5.0
    weight_empty: float = 1.0
    weight_opacity: float = 0.01
    color_weight_eps: float = 2e-3
    init_from_depth: bool = True
    init_density_raw: float = 14.0
    init_min_weight: float = 1.0
    init_stride: int = 2
    device: str | None = None
    threads: int | None = 1

    def to_dict(self) -> dict:
        return asdict(self)


# --- frames, rays and bounds ------------------------------------------------------------------


def split_frames(num_frames: int, every: int = 1, eval_frames: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Training and held-out frame indices.

    Training uses frames ``0, every, 2 every, ...``; held out are ``eval_frames`` frames
    spread evenly over the rest. With ``every == 1`` every tenth frame (offset 5) is held out
    of training first, so there always is something to evaluate on.
    """
    if num_frames < 2:
        raise FieldError(f"need at least 2 frames to train and evaluate, got {num_frames}")
    every = int(every)
    if every < 1:
        raise FieldError(f"--every must be at least 1, got {every}")
    all_idx = np.arange(num_frames)
    if every == 1:
        held = all_idx[(all_idx % 10) == 5] if num_frames > 5 else all_idx[-1:]
        train = np.setdiff1d(all_idx, held)
    else:
        train = all_idx[::every]
        held = np.setdiff1d(all_idx, train)
    if len(train) == 0:
        raise FieldError("no training frames left")
    if eval_frames > 0 and len(held) > eval_frames:
        held = held[np.round(np.linspace(0, len(held) - 1, eval_frames)).astype(int)]
    return train, held[: max(eval_frames, 0)] if eval_frames > 0 else held[:0]


@dataclass
class TrainingRays:
    """Every training pixel with a valid depth, kept compact on the training device.

    rgb (F, H, W, 3) uint8; depth (F, H, W) float32 z-depth metres (0 = missing);
    R_world_cam (F, 3, 3) float32; t_world_cam (F, 3) float64; num_valid: how many pixels
    have a usable depth.
    """

    rgb: torch.Tensor
    depth: torch.Tensor
    R_world_cam: torch.Tensor
    t_world_cam: np.ndarray
    num_valid: int
    intrinsics: Intrinsics

    @classmethod
    def from_sequence(cls, sequence, indices: Sequence[int], config: TrainConfig, device,
                      progress: bool = False, timing: dict | None = None) -> "TrainingRays":
        """Frames ``indices`` as training rays. With ``timing`` (``depth_offset_s``,
        ``colour_offset_s``, ``depth_scale``: see :mod:`nap3d_graph.datasets.depth_timing`)
        each frame's depth is scaled and moved from the pose at its capture time to the pose
        at the colour's, so both images of a ray see the same instant."""
        from tqdm import tqdm

        from nap3d_graph.camera import warp_depth
        from nap3d_graph.conventions import inv_T

        poses = _poses_of(sequence)
        T_colour = T_depth = poses[np.asarray(indices, dtype=int)]
        if timing is not None and getattr(sequence, "ground_truth_at", None) is not None:
            idx = np.asarray(indices, dtype=int)
            T_colour = sequence.ground_truth_at(np.asarray(sequence.timestamps)[idx] + timing["colour_offset_s"])
            T_depth = sequence.ground_truth_at(np.asarray(sequence.depth_timestamps)[idx] + timing["depth_offset_s"])
            bad = ~(np.all(np.isfinite(T_colour), axis=(1, 2)) & np.all(np.isfinite(T_depth), axis=(1, 2)))
            T_colour = np.where(bad[:, None, None], poses[idx], T_colour)
            T_depth = np.where(bad[:, None, None], poses[idx], T_depth)
        intrinsics = sequence.intrinsics.without_distortion()
        h, w = intrinsics.height, intrinsics.width
        rgb = np.empty((len(indices), h, w, 3), dtype=np.uint8)
        depth = np.empty((len(indices), h, w), dtype=np.float32)
        for k, i in enumerate(tqdm(indices, desc="load frames", unit="frame", disable=not progress, leave=False)):
            frame = sequence[int(i)]
            if frame.rgb.shape[:2] != (h, w):
                raise FieldError(f"frame {i} is {frame.rgb.shape[1]}x{frame.rgb.shape[0]}, "
                                 f"the sequence's intrinsics say {w}x{h}")
            rgb[k] = frame.rgb
            d = np.nan_to_num(frame.depth_m, nan=0.0)
            if timing is not None:
                d = warp_depth(d, intrinsics, inv_T(T_colour[k]) @ T_depth[k], timing.get("depth_scale", 1.0))
            d[~valid_depth_mask(d, config.min_depth_m, config.max_depth_m)] = 0.0
            depth[k] = d
        T = np.asarray(T_colour)
        num_valid = int(np.count_nonzero(depth))
        if num_valid == 0:
            raise FieldError("no training frame has a valid depth pixel")
        return cls(
            rgb=torch.from_numpy(rgb).to(device),
            depth=torch.from_numpy(depth).to(device),
            R_world_cam=torch.as_tensor(T[:, :3, :3], dtype=torch.float32, device=device),
            t_world_cam=T[:, :3, 3].copy(),
            num_valid=num_valid,
            intrinsics=intrinsics,
        )

    @property
    def num_frames(self) -> int:
        return self.rgb.shape[0]


def split_posed_frames(sequence, every: int = 1, eval_frames: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """:func:`split_frames` over the frames that have a ground-truth pose (the others cannot
    train or evaluate a field); indices into ``sequence``."""
    poses = getattr(sequence, "T_world_cam_gt", None)
    if poses is None:
        raise FieldError("training a field needs posed frames, but the sequence has no ground-truth poses")
    posed = np.flatnonzero(np.all(np.isfinite(np.asarray(poses)), axis=(1, 2)))
    if posed.size < 2:
        raise FieldError(f"need at least 2 frames with a ground-truth pose, got {posed.size}")
    train, held = split_frames(len(posed), every, eval_frames)
    return posed[train], posed[held]


def _ray_poses(rays: TrainingRays) -> np.ndarray:
    T = np.tile(np.eye(4), (rays.num_frames, 1, 1))
    T[:, :3, :3] = rays.R_world_cam.cpu().numpy()
    T[:, :3, 3] = rays.t_world_cam
    return T


def _poses_of(sequence) -> np.ndarray:
    poses = getattr(sequence, "T_world_cam_gt", None)
    if poses is None:
        raise FieldError("training a field needs posed frames, but the sequence has no ground-truth poses")
    poses = np.asarray(poses, dtype=np.float64)
    if poses.shape != (len(sequence), 4, 4):
        raise FieldError(f"sequence poses must be (N, 4, 4) with N = {len(sequence)}, got {poses.shape}")
    return poses


def scene_bounds_from_depth(depth_m: np.ndarray, T_world_cam: np.ndarray, intrinsics: Intrinsics,
                            margin_m: float = 0.15, stride: int = 4, percentile: float = 0.02) -> np.ndarray:
    """World box (2, 3) that holds what the depth images see and the cameras.

    depth_m (F, H, W) z-depth metres (0 = missing); T_world_cam (F, 4, 4). Points are
    back-projected on every ``stride``-th pixel; the box spans their ``percentile`` to
    ``100 - percentile`` percentiles per axis (stray far returns do not blow it up), grown by
    ``margin_m`` so windows behind the farthest surfaces still fit.
    """
    depth_m = np.asarray(depth_m)
    chunks = []
    for k in range(depth_m.shape[0]):
        p_cam, _ = backproject_depth(depth_m[k], intrinsics, stride)
        chunks.append(transform_points(T_world_cam[k], p_cam))
    points = np.concatenate(chunks) if chunks else np.zeros((0, 3))
    if len(points) < 10:
        raise FieldError("too few valid depth pixels to find the scene's bounds")
    lo = np.percentile(points, percentile, axis=0)
    hi = np.percentile(points, 100.0 - percentile, axis=0)
    cams = T_world_cam[:, :3, 3]
    lo = np.minimum(lo, cams.min(axis=0))
    hi = np.maximum(hi, cams.max(axis=0))
    return np.stack([lo - margin_m, hi + margin_m])


# --- the training step ---------------------------------------------------------------------------


def splat_init(field: GridField, rays: TrainingRays, config: TrainConfig) -> GridField:
    """Start the field from the depth images instead of from nothing.

    Every ``init_stride``-th pixel of every training frame is back-projected and splatted
    trilinearly into the grid: vertices with enough splat weight get a raw density that is
    already opaque (a shell about one voxel thick around the observed surfaces, which the
    free-space and window losses then carve to its sub-voxel place), and every splatted vertex
    gets the weighted mean colour of its points. Training then refines instead of building
    surfaces from scratch, which is what a voxel grid on a CPU struggles with.
    """
    h, w = rays.intrinsics.height, rays.intrinsics.width
    stride = max(1, int(config.init_stride))
    v, u = torch.meshgrid(torch.arange(0, h, stride, device=field.device), torch.arange(0, w, stride, device=field.device),
                          indexing="ij")
    d_cam = pixel_directions(rays.intrinsics, field.device)[::stride, ::stride].reshape(-1, 3)
    weight_sum = torch.zeros(field.density.numel(), device=field.device)
    color_weight = torch.zeros(field.color[0, 0].numel(), device=field.device)
    color_sum = torch.zeros(3, field.color[0, 0].numel(), device=field.device)
    t_local = torch.as_tensor(rays.t_world_cam - field.grid_min, dtype=torch.float32, device=field.device)
    for k in range(rays.num_frames):
        z = rays.depth[k, v, u].reshape(-1)
        ok = z > 0
        if not bool(ok.any()):
            continue
        points = (d_cam[ok] * z[ok, None]) @ rays.R_world_cam[k].T + t_local[k]
        idx, wts = trilinear_corners(points, field.shape_xyz, field.voxel_size)
        weight_sum.index_add_(0, idx.reshape(-1), wts.reshape(-1))
        idx, wts = trilinear_corners(points, field.color_shape_xyz, field.color_voxel_size)
        rgb = rays.rgb[k, v, u].reshape(-1, 3)[ok].float() / 255.0
        color_weight.index_add_(0, idx.reshape(-1), wts.reshape(-1))
        color_sum.index_add_(1, idx.reshape(-1), (rgb.T[:, :, None] * wts[None]).reshape(3, -1))
    seen = color_weight > 0
    mean_rgb = (color_sum[:, seen] / color_weight[seen]).clamp(0.02, 0.98)
    field.density.view(-1)[weight_sum >= config.init_min_weight] = config.init_density_raw
    field.color.view(3, -1)[:, seen] = torch.log(mean_rgb / (1.0 - mean_rgb))
    field.mark_changed()
    return field


class _LazyAdam:
    """Adam on the rows of a (V, C) grid table that a step touched ("lazy" Adam).

    Why not ``torch.optim.Adam``: a step touches a few percent of the grid's vertices, but a
    dense optimiser (and ``grid_sample``'s backward, which zero-fills a gradient the size of
    the grid) costs O(grid) per step -- most of a CPU step's time on a 3 cm room grid.
    Gradients are scattered here with ``index_add_`` and only touched rows are updated, so a
    step costs O(samples). Bias correction uses the global step, as ``torch.optim.SparseAdam``.
    Rows are vertices, so a (V, C) channels-last table keeps each update contiguous.
    """

    def __init__(self, table: torch.Tensor, lr: float, betas=(0.9, 0.99), eps: float = 1e-8):
        self.table = table  # (V, C), updated in place
        self.lr = lr
        self.beta1, self.beta2 = betas
        self.eps = eps
        self.grad = torch.zeros_like(table)
        self.m = torch.zeros_like(table)
        self.v = torch.zeros_like(table)
        self.touched = torch.zeros(table.shape[0], dtype=torch.bool, device=table.device)
        self.steps = 0

    def accumulate(self, idx: torch.Tensor, contrib: torch.Tensor) -> None:
        """Add gradient ``contrib`` (K, C) at vertex indices ``idx`` (K,)."""
        self.grad.index_add_(0, idx, contrib)
        self.touched[idx] = True

    def step(self, lr_scale: float = 1.0) -> None:
        rows = self.touched.nonzero()[:, 0]
        if rows.numel() == 0:
            return
        self.touched[rows] = False
        self.steps += 1
        g = self.grad[rows]
        self.grad[rows] = 0.0
        m = self.m[rows].mul_(self.beta1).add_(g, alpha=1.0 - self.beta1)
        v = self.v[rows].mul_(self.beta2).addcmul_(g, g, value=1.0 - self.beta2)
        self.m[rows] = m
        self.v[rows] = v
        bc1 = 1.0 - self.beta1 ** self.steps
        bc2 = 1.0 - self.beta2 ** self.steps
        update = (m / bc1).div_((v / bc2).sqrt_().add_(self.eps))
        self.table.index_add_(0, rows, update, alpha=-(self.lr * lr_scale))


class _Trainer:
    """One optimisation stage on one grid: sampling, losses and lazy Adam."""

    def __init__(self, field: GridField, rays: TrainingRays, config: TrainConfig, generator: torch.Generator):
        self.field = field
        self.rays = rays
        self.config = config
        self.generator = generator
        self.device = field.device
        # Channels-last working copies: a vertex's values are one contiguous row.
        self.density_table = field.density.view(-1, 1)
        self.color_table = field.color.view(3, -1).T.contiguous()
        self.density_adam = _LazyAdam(self.density_table, config.lr_density)
        self.color_adam = _LazyAdam(self.color_table, config.lr_color)
        self.lr_scale = 1.0
        k = rays.intrinsics
        self.K = (k.fx, k.fy, k.cx, k.cy, k.width, k.height)
        self.t_local = torch.as_tensor(rays.t_world_cam - field.grid_min, dtype=torch.float32, device=self.device)
        self.box_hi = (torch.tensor(field.shape_xyz, dtype=torch.float32, device=self.device) - 1) * field.voxel_size

    def set_lr_scale(self, scale: float) -> None:
        self.lr_scale = scale

    def sync_field(self) -> GridField:
        """Write the channels-last colour back into the field (density is shared) and return it."""
        self.field.color.view(3, -1).copy_(self.color_table.T)
        self.field.mark_changed()
        return self.field

    def sample_batch(self):
        """Rays of ``rays_per_step // patch**2`` random square pixel patches of random training
        frames (neighbouring rays touch the same voxels, which keeps the grid lookups in cache),
        without the pixels that have no depth."""
        cfg, rays = self.config, self.rays
        fx, fy, cx, cy, w, h = self.K
        p = max(1, min(cfg.patch_size, w, h))
        n_patches = max(1, cfg.rays_per_step // (p * p))
        frame = torch.randint(rays.num_frames, (n_patches, 1), generator=self.generator, device=self.device)
        u0 = torch.randint(w - p + 1, (n_patches, 1), generator=self.generator, device=self.device)
        v0 = torch.randint(h - p + 1, (n_patches, 1), generator=self.generator, device=self.device)
        offset = torch.arange(p, device=self.device)
        u = (u0 + offset.repeat(p)[None, :]).reshape(-1)
        v = (v0 + offset.repeat_interleave(p)[None, :]).reshape(-1)
        frame = frame.expand(-1, p * p).reshape(-1)
        flat = (frame * h + v) * w + u
        z = rays.depth.reshape(-1)[flat]
        ok = z > 0
        flat, frame, u, v, z = flat[ok], frame[ok], u[ok].float(), v[ok].float(), z[ok]
        d_cam = torch.stack([(u - cx) / fx, (v - cy) / fy, torch.ones_like(u)], dim=-1)
        dirs = torch.einsum("nij,nj->ni", rays.R_world_cam[frame], d_cam)
        origins = self.t_local[frame]
        target = rays.rgb.reshape(-1, 3)[flat].float() / 255.0
        return origins, dirs, z, target

    def sample_t(self, origins, dirs, z):
        """Stratified free-space samples, then window samples around the measured depth."""
        cfg = self.config
        n = z.shape[0]
        half = torch.clamp(cfg.window_sigmas * cfg.depth_sigma_z2 * z * z, min=cfg.window_min_m)
        safe = torch.where(dirs.abs() < 1e-9, torch.full_like(dirs, 1e-9), dirs)
        t0, t1 = (0.0 - origins) / safe, (self.box_hi - origins) / safe
        t_near = torch.minimum(t0, t1).amax(dim=-1).clamp(min=0.05)
        win_start = z - half
        t_near = torch.minimum(t_near, win_start)
        jitter_free = torch.rand((n, cfg.free_samples), generator=self.generator, device=self.device)
        jitter_win = torch.rand((n, cfg.window_samples), generator=self.generator, device=self.device)
        k_free = torch.arange(cfg.free_samples, device=self.device, dtype=torch.float32)
        k_win = torch.arange(cfg.window_samples, device=self.device, dtype=torch.float32)
        free_len = (win_start - t_near)[:, None]
        t_free = t_near[:, None] + free_len * (k_free + jitter_free) / cfg.free_samples
        t_win = win_start[:, None] + (2 * half)[:, None] * (k_win + jitter_win) / cfg.window_samples
        t = torch.cat([t_free, t_win], dim=1)
        last = (2 * half / cfg.window_samples)[:, None]
        dt = torch.cat([t[:, 1:] - t[:, :-1], last], dim=1)
        return t, dt

    def step(self):
        cfg, fld = self.config, self.field
        origins, dirs, z, target = self.sample_batch()
        t, dt = self.sample_t(origins, dirs, z)
        n, s = t.shape
        norms = dirs.norm(dim=-1, keepdim=True)
        points = (origins[:, None, :] + t[..., None] * dirs[:, None, :]).reshape(-1, 3)
        # Autograd runs over per-sample values only; grid gradients are scattered by hand.
        idx, w = trilinear_corners(points, fld.shape_xyz, fld.voxel_size)
        raw = (self.density_table[:, 0].take(idx) * w).sum(dim=1).reshape(n, s).requires_grad_(True)
        sigma = F.softplus(raw - DENSITY_SHIFT) / fld.voxel_size
        tau = sigma * dt * norms
        cum = torch.cumsum(tau, dim=1)
        trans = torch.exp(-(cum - tau))
        weights = trans * (1.0 - torch.exp(-tau))
        opacity = weights.sum(dim=1)

        # Colour only where a sample matters (most are free space or behind the surface); the
        # kept weights are rescaled to the ray's opacity so dropping the rest adds no bias.
        keep = (weights.detach() > cfg.color_weight_eps).reshape(-1).nonzero()[:, 0]
        idx_c, w_c = trilinear_corners(points[keep], fld.color_shape_xyz, fld.color_voxel_size)
        color_raw = torch.bmm(w_c[:, None, :], self.color_table[idx_c])[:, 0].requires_grad_(True)
        ray_of = keep // s
        kept_w = weights.reshape(-1)[keep]
        kept_sum = torch.zeros_like(opacity).index_add(0, ray_of, kept_w.detach())
        rescale = (opacity.detach() / kept_sum.clamp(min=1e-8))[ray_of]
        color = torch.zeros_like(target).index_add(0, ray_of, (kept_w * rescale)[:, None] * torch.sigmoid(color_raw))
        background = torch.rand(target.shape, generator=self.generator, device=self.device)
        color = color + (1.0 - opacity)[:, None] * background

        nf = cfg.free_samples
        window_mass = weights[:, nf:].sum(dim=1)
        spread = (weights[:, nf:] * (t[:, nf:] - z[:, None]).abs()).sum(dim=1) * norms[:, 0]
        free_mass = weights[:, :nf].sum(dim=1)
        rgb_loss = F.mse_loss(color, target)
        loss = (cfg.weight_rgb * rgb_loss
                + cfg.weight_window * ((1.0 - window_mass) ** 2).mean()
                + cfg.weight_empty * free_mass.mean()
                + cfg.weight_near * spread.mean()
                + cfg.weight_opacity * (1.0 - opacity).abs().mean())
        loss.backward()
        with torch.no_grad():
            self.density_adam.accumulate(idx.reshape(-1), (raw.grad.reshape(-1, 1) * w).reshape(-1, 1))
            self.color_adam.accumulate(idx_c.reshape(-1), (w_c[:, :, None] * color_raw.grad[:, None, :]).reshape(-1, 3))
            self.density_adam.step(self.lr_scale)
            self.color_adam.step(self.lr_scale)
            depth = (weights * t).sum(dim=1) / opacity.clamp(min=1e-6)
            depth_err = (depth - z).abs().median()
        return float(rgb_loss.detach()), float(depth_err)


# --- the whole run -------------------------------------------------------------------------------


def train_field(
    sequence,
    config: TrainConfig | None = None,
    *,
    minutes: float | None = None,
    every: int | None = None,
    seed: int | None = None,
    progress: bool = True,
    eval_sequence=None,
    eval_indices: Sequence[int] | None = None,
    oracle=None,
    snapshot_seconds: Sequence[float] = (),
    callback: Callable[[dict], None] | None = None,
    timing: dict | None = None,
) -> tuple[GridField, dict]:
    """Train a grid field on a posed RGB-D ``sequence``; returns ``(field, report)``.

    ``minutes``, ``every`` and ``seed`` override the config's. Held-out evaluation runs on
    ``eval_sequence`` (frames ``eval_indices``, default: evenly spread) when given, else on
    frames of ``sequence`` kept out of training (see :func:`split_frames`). Depth errors are
    measured against ``oracle`` (default: the sequence's simulator oracle if it has one). The
    report also holds an evaluation at each of ``snapshot_seconds`` of training (the clock
    pauses meanwhile). ``callback`` gets a small dict every few steps (progress hooks).
    ``timing``: a real recording's depth / colour capture offsets and depth scale, applied to
    the training frames and the evaluation (see :class:`TrainingRays`).
    """
    config = replace(config or TrainConfig())
    if minutes is not None:
        config.minutes = float(minutes)
    if every is not None:
        config.every = int(every)
    if seed is not None:
        config.seed = int(seed)
    if not config.minutes > 0 and not config.max_steps:
        raise FieldError(f"the training budget must be positive, got {config.minutes} minutes")
    device = torch.device(config.device) if config.device else default_device()
    with torch_threads(config.threads if device.type == "cpu" else None):
        return _train(sequence, config, device, progress, eval_sequence, eval_indices, oracle,
                      snapshot_seconds, callback, timing)


def _train(sequence, config: TrainConfig, device, progress, eval_sequence, eval_indices, oracle,
           snapshot_seconds, callback, timing=None) -> tuple[GridField, dict]:
    generator = torch.Generator(device=device).manual_seed(config.seed)

    train_idx, held_idx = split_posed_frames(sequence, config.every, config.eval_frames)
    if eval_sequence is None:
        eval_sequence, eval_indices = sequence, (held_idx if eval_indices is None else eval_indices)
        oracle = oracle if oracle is not None else oracle_for(sequence)
    else:
        if eval_indices is None:
            n = len(eval_sequence)
            eval_indices = np.unique(np.round(np.linspace(0, n - 1, min(config.eval_frames, n))).astype(int))
        oracle = oracle if oracle is not None else oracle_for(eval_sequence)

    started = time.perf_counter()
    rays = TrainingRays.from_sequence(sequence, train_idx, config, device, progress=progress, timing=timing)
    bounds = scene_bounds_from_depth(rays.depth.cpu().numpy(), _ray_poses(rays),
                                     rays.intrinsics, margin_m=config.bounds_margin_m)
    load_seconds = time.perf_counter() - started
    log.info("training on %d frames (%d rays with depth), bounds %s", len(train_idx), rays.num_valid, bounds.round(2).tolist())

    stages = _stages(config)
    field = GridField.empty(bounds, stages[0][0], device=device,
                            color_voxel_size=stages[0][0] / config.color_voxel_ratio)
    if config.init_from_depth:
        started_init = time.perf_counter()
        splat_init(field, rays, config)
        log.info("initialised the grid from the depth images in %.1f s", time.perf_counter() - started_init)
    budget_s = config.minutes * 60.0
    snapshots = sorted(float(s) for s in snapshot_seconds if 0 < float(s) < budget_s)
    snapshot_reports = []
    history = []
    train_seconds = 0.0
    steps = 0
    last_psnr, last_depth = float("nan"), float("nan")

    from tqdm import tqdm

    bar = tqdm(total=round(budget_s) if not config.max_steps else config.max_steps,
               desc="train field", unit="s" if not config.max_steps else "step", disable=not progress,
               bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt} {unit} [{elapsed}<{remaining}{postfix}]")
    trainer = None
    stage_index = -1
    try:
        while True:
            fraction = (steps / config.max_steps) if config.max_steps else (train_seconds / budget_s)
            if fraction >= 1.0:
                break
            wanted = _stage_at(stages, fraction)
            if wanted != stage_index:
                if stage_index >= 0:
                    voxel = stages[wanted][0]
                    field = trainer.sync_field().resampled(voxel, voxel / config.color_voxel_ratio)
                stage_index = wanted
                trainer = _Trainer(field, rays, config, generator)
            trainer.set_lr_scale(config.lr_final_ratio ** fraction)
            tick = time.perf_counter()
            rgb_mse, depth_err = trainer.step()
            train_seconds += time.perf_counter() - tick
            steps += 1
            last_psnr, last_depth = psnr(rgb_mse), depth_err
            if steps % 20 == 0:
                history.append({"step": steps, "seconds": round(train_seconds, 2), "train_psnr_db": round(last_psnr, 2),
                                "train_depth_err_m": round(last_depth, 5)})
                bar.set_postfix_str(f"PSNR {last_psnr:.1f} dB, depth err {last_depth * 100:.2f} cm, step {steps}")
                bar.n = steps if config.max_steps else min(round(train_seconds), bar.total)
                bar.refresh()
                if callback is not None:
                    callback(history[-1])
            if snapshots and train_seconds >= snapshots[0]:
                snapshots.pop(0)
                view_field = _frozen(trainer.sync_field())
                snap = evaluate_field(view_field, eval_sequence, eval_indices, oracle, timing=timing)
                snap.pop("per_frame", None)
                snapshot_reports.append({"train_seconds": round(train_seconds, 2), "steps": steps, **snap})
    finally:
        bar.close()

    field = _frozen(trainer.sync_field() if trainer is not None else field)
    field.meta = {
        "trained_by": "nap3d-graph train-field",
        "checkpoint_version": CHECKPOINT_VERSION,
        "train_config": config.to_dict(),
        "source": str(getattr(sequence, "path", type(sequence).__name__)),
        "train_frames": [int(i) for i in train_idx],
        # Colour stamps of the frames trained on: runs and evaluations warn when they use one.
        "train_timestamps": [float(sequence.timestamps[int(i)]) for i in train_idx]
        if hasattr(sequence, "timestamps") else [],
        "steps": steps,
        "train_seconds": round(train_seconds, 2),
    }
    evaluation = evaluate_field(field, eval_sequence, eval_indices, oracle, timing=timing) if len(eval_indices) else None
    report = {
        "field": repr(field),
        "voxel_size_m": field.voxel_size,
        "color_voxel_size_m": field.color_voxel_size,
        "bounds_m": field.bounds.tolist(),
        "device": str(device),
        "torch_threads": config.threads if config.threads is not None else torch.get_num_threads(),
        "train_frames": len(train_idx),
        "train_rays_with_depth": int(rays.num_valid),
        "steps": steps,
        "train_seconds": round(train_seconds, 2),
        "load_seconds": round(load_seconds, 2),
        "final_train_psnr_db": round(last_psnr, 2),
        "final_train_depth_err_m": round(last_depth, 5),
        "held_out": evaluation,
        "snapshots": snapshot_reports,
        "history": history,
        "config": config.to_dict(),
    }
    return field, report


def _stages(config: TrainConfig) -> list[tuple[float, float]]:
    """(voxel size, budget fraction at which the stage starts)."""
    if config.coarse_voxel_size_m and config.coarse_voxel_size_m > config.voxel_size_m and config.coarse_fraction > 0:
        return [(config.coarse_voxel_size_m, 0.0), (config.voxel_size_m, config.coarse_fraction)]
    return [(config.voxel_size_m, 0.0)]


def _stage_at(stages, fraction: float) -> int:
    index = 0
    for k, (_, start) in enumerate(stages):
        if fraction >= start:
            index = k
    return index


def _frozen(field: GridField) -> GridField:
    """A detached copy of the field for rendering (training keeps its own tensors)."""
    out = GridField(field.density[0, 0].detach().clone(), field.color[0].detach().clone(), field.grid_min,
                    field.voxel_size, field.meta, field.render_config, field.color_voxel_size)
    return out
