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
  exceeds ``color_weight_eps``; one torch thread (see ``nap3d_graph.torch_threads``);
* colour on a grid 1.5x finer than density: texture needs more detail than geometry;
* a learning rate that decays with the *time* budget (the budget is minutes, not steps).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace
from typing import Callable, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from nap3d_graph.datasets.depth_timing import CaptureTiming
from nap3d_graph.fields.grid import CHECKPOINT_VERSION, GridField, default_device, trilinear_corners
from nap3d_graph.fields.grid_render import DENSITY_SHIFT
from nap3d_graph.progress import progress_bar
from nap3d_graph.torch_threads import torch_threads

from .base import FieldError
from .evaluation import evaluate_field, oracle_for, psnr
from .lazy_adam import LazyAdam
from .train_config import TrainConfig
from .training_data import TrainingRays, ray_poses, scene_bounds_from_depth, splat_init, split_posed_frames

__all__ = ["train_field"]

log = logging.getLogger(__name__)


# --- frames, rays and bounds ------------------------------------------------------------------


class _Trainer:
    """One optimisation stage on one grid: sampling, losses and lazy Adam."""

    def __init__(self, field: GridField, rays: TrainingRays, config: TrainConfig, generator: torch.Generator):
        self.field = field
        self.rays = rays
        self.config = config
        self.generator = generator
        self.device = field.device
        # Channels-last tables: a vertex's values are one contiguous row. On a CPU the colour
        # table is the field's own storage (the compiled renderer reads that layout too); on a
        # GPU a working copy written back by sync_field (its renderer samples channel-first).
        self.density_table = field.density.view(-1, 1)
        self.shared_color = field.device.type == "cpu"
        self.color_table = (field.color_channels_last().view(-1, 3) if self.shared_color
                            else field.color.view(3, -1).T.contiguous())
        self.density_adam = LazyAdam(self.density_table, config.lr_density)
        self.color_adam = LazyAdam(self.color_table, config.lr_color)
        self.lr_scale = 1.0
        k = rays.intrinsics
        self.K = (k.fx, k.fy, k.cx, k.cy, k.width, k.height)
        self.t_local = torch.as_tensor(rays.t_world_cam - field.grid_min, dtype=torch.float32, device=self.device)
        self.box_hi = (torch.tensor(field.shape_xyz, dtype=torch.float32, device=self.device) - 1) * field.voxel_size

    def set_lr_scale(self, scale: float) -> None:
        self.lr_scale = scale

    def sync_field(self) -> GridField:
        """The field with the colour table written back (on a GPU; on a CPU it is the field's
        own storage), told its grids changed."""
        if not self.shared_color:
            self.field.color.view(3, -1).copy_(self.color_table.T)
        self.field.mark_changed()
        return self.field

    def sample_batch(self):
        """Rays of ``rays_per_step // patch**2`` random square pixel patches of random training
        frames (neighbouring rays touch the same voxels, which keeps the grid lookups in cache),
        without the pixels that have no depth. Returns ray origins (N, 3) in the grid's frame,
        directions (N, 3) with unit camera z, depths (N,), colours (N, 3) in [0, 1] and whether
        each colour is data (N,) bool (see ``TrainingRays.coverage``; None: all are)."""
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
        has_colour = None if rays.coverage is None else rays.coverage[v.long(), u.long()]
        return origins, dirs, z, target, has_colour

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
        origins, dirs, z, target, has_colour = self.sample_batch()
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
        # Every ray trains the geometry; only those whose pixel holds colour data the colour.
        if has_colour is None:
            rgb_loss = F.mse_loss(color, target)
        else:
            rgb_loss = F.mse_loss(color[has_colour], target[has_colour]) if bool(has_colour.any()) else color.sum() * 0.0
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
    timing: CaptureTiming | None = None,
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
    held_out = _held_out(sequence, config, held_idx, eval_sequence, eval_indices, oracle, timing)
    started = time.perf_counter()
    rays = TrainingRays.from_sequence(sequence, train_idx, config, device, progress=progress, timing=timing)
    bounds = scene_bounds_from_depth(rays.depth.cpu().numpy(), ray_poses(rays),
                                     rays.intrinsics, margin_m=config.bounds_margin_m, slab_m=config.slab_m)
    load_seconds = time.perf_counter() - started
    log.info("training on %d frames (%d rays with depth), bounds %s", len(train_idx), rays.num_valid,
             bounds.round(2).tolist())
    field = _initial_field(bounds, rays, config, device)
    loop = _TrainingLoop(config, rays, generator, held_out, snapshot_seconds, callback)
    field = loop.run(field, progress)
    field.meta = _field_meta(sequence, config, train_idx, loop)
    evaluation = held_out.evaluate(field) if len(held_out.indices) else None
    report = {
        "field": repr(field),
        "voxel_size_m": field.voxel_size,
        "color_voxel_size_m": field.color_voxel_size,
        "bounds_m": field.bounds.tolist(),
        "device": str(device),
        "torch_threads": config.threads if config.threads is not None else torch.get_num_threads(),
        "train_frames": len(train_idx),
        "train_rays_with_depth": int(rays.num_valid),
        "steps": loop.steps,
        "train_seconds": round(loop.train_seconds, 2),
        "load_seconds": round(load_seconds, 2),
        "final_train_psnr_db": round(loop.last_psnr, 2),
        "final_train_depth_err_m": round(loop.last_depth, 5),
        "held_out": evaluation,
        "snapshots": loop.snapshot_reports,
        "history": loop.history,
        "config": config.to_dict(),
    }
    return field, report


@dataclass
class _HeldOut:
    """The frames a field is evaluated on (``indices`` of ``sequence``) and the oracle that
    scores them, with the capture ``timing`` training used."""

    sequence: object
    indices: np.ndarray
    oracle: object
    timing: object = None

    def evaluate(self, field) -> dict:
        return evaluate_field(field, self.sequence, self.indices, self.oracle, timing=self.timing)


def _held_out(sequence, config: TrainConfig, held_idx, eval_sequence, eval_indices, oracle, timing) -> _HeldOut:
    """The training sequence's held-out frames, or ``eval_indices`` of ``eval_sequence``
    (evenly spread ones where not given), with their oracle."""
    if eval_sequence is None:
        eval_sequence, eval_indices = sequence, (held_idx if eval_indices is None else eval_indices)
        oracle = oracle if oracle is not None else oracle_for(sequence)
    else:
        if eval_indices is None:
            n = len(eval_sequence)
            eval_indices = np.unique(np.round(np.linspace(0, n - 1, min(config.eval_frames, n))).astype(int))
        oracle = oracle if oracle is not None else oracle_for(eval_sequence)
    return _HeldOut(eval_sequence, eval_indices, oracle, timing)


def _initial_field(bounds: np.ndarray, rays: TrainingRays, config: TrainConfig, device) -> GridField:
    """The empty grid of the first stage over ``bounds`` ((2, 3) metres), initialised from the
    depth images when ``config.init_from_depth``."""
    voxel = _stages(config)[0][0]
    field = GridField.empty(bounds, voxel, device=device, color_voxel_size=voxel / config.color_voxel_ratio)
    if config.init_from_depth:
        started_init = time.perf_counter()
        splat_init(field, rays, config)
        log.info("initialised the grid from the depth images in %.1f s", time.perf_counter() - started_init)
    return field


class _TrainingLoop:
    """The optimisation, stage by stage, until its budget (steps, or minutes of training) is
    spent: ``steps``, ``train_seconds``, the last training PSNR and depth error, ``history``
    every 20 steps and ``snapshot_reports`` (the held-out frames at ``snapshot_seconds``)."""

    def __init__(self, config: TrainConfig, rays: TrainingRays, generator, held_out: _HeldOut,
                 snapshot_seconds, callback):
        self.config, self.rays, self.generator, self.held_out, self.callback = (config, rays, generator, held_out,
                                                                               callback)
        self.stages = _stages(config)
        self.budget_s = config.minutes * 60.0
        self.snapshots = sorted(float(s) for s in snapshot_seconds if 0 < float(s) < self.budget_s)
        self.snapshot_reports: list[dict] = []
        self.history: list[dict] = []
        self.train_seconds = 0.0
        self.steps = 0
        self.last_psnr, self.last_depth = float("nan"), float("nan")

    def run(self, field: GridField, progress: bool) -> GridField:
        """Train ``field`` (resampled at each stage); returns it frozen."""
        config = self.config
        bar = progress_bar(total=round(self.budget_s) if not config.max_steps else config.max_steps,
                           desc="train field", unit="s" if not config.max_steps else "step", disable=not progress,
                           bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt} {unit} [{elapsed}<{remaining}{postfix}]")
        trainer = None
        stage_index = -1
        try:
            while (fraction := self._fraction()) < 1.0:
                wanted = _stage_at(self.stages, fraction)
                if wanted != stage_index:
                    if trainer is not None:
                        voxel = self.stages[wanted][0]
                        field = trainer.sync_field().resampled(voxel, voxel / config.color_voxel_ratio)
                    stage_index = wanted
                    trainer = _Trainer(field, self.rays, config, self.generator)
                trainer.set_lr_scale(config.lr_final_ratio ** fraction)
                self._step(trainer, bar)
        finally:
            bar.close()
        return _frozen(trainer.sync_field() if trainer is not None else field)

    def _fraction(self) -> float:
        """How much of the budget is spent (0 to 1)."""
        config = self.config
        return (self.steps / config.max_steps) if config.max_steps else (self.train_seconds / self.budget_s)

    def _step(self, trainer, bar) -> None:
        """One optimisation step; every 20 the history, the bar and the callback; a snapshot
        when one is due."""
        tick = time.perf_counter()
        rgb_mse, depth_err = trainer.step()
        self.train_seconds += time.perf_counter() - tick
        self.steps += 1
        self.last_psnr, self.last_depth = psnr(rgb_mse), depth_err
        if self.steps % 20 == 0:
            self.history.append({"step": self.steps, "seconds": round(self.train_seconds, 2),
                                 "train_psnr_db": round(self.last_psnr, 2),
                                 "train_depth_err_m": round(self.last_depth, 5)})
            bar.set_postfix_str(f"PSNR {self.last_psnr:.1f} dB, depth err {self.last_depth * 100:.2f} cm, "
                                f"step {self.steps}")
            bar.n = self.steps if self.config.max_steps else min(round(self.train_seconds), bar.total)
            bar.refresh()
            if self.callback is not None:
                self.callback(self.history[-1])
        if self.snapshots and self.train_seconds >= self.snapshots[0]:
            self.snapshots.pop(0)
            snap = self.held_out.evaluate(_frozen(trainer.sync_field()))
            snap.pop("per_frame", None)
            self.snapshot_reports.append({"train_seconds": round(self.train_seconds, 2), "steps": self.steps, **snap})


def _field_meta(sequence, config: TrainConfig, train_idx, loop: _TrainingLoop) -> dict:
    """What a trained field's checkpoint records of how it was trained."""
    return {
        "trained_by": "nap3d-graph train-field",
        "checkpoint_version": CHECKPOINT_VERSION,
        "train_config": config.to_dict(),
        "source": str(getattr(sequence, "path", type(sequence).__name__)),
        "train_frames": [int(i) for i in train_idx],
        # Colour stamps of the frames trained on: runs and evaluations warn when they use one.
        "train_timestamps": [float(sequence.timestamps[int(i)]) for i in train_idx]
        if hasattr(sequence, "timestamps") else [],
        "train_recording": getattr(sequence, "recording_id", None),
        "steps": loop.steps,
        "train_seconds": round(loop.train_seconds, 2),
    }


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
