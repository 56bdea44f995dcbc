"""What a grid field is trained on: the split of a sequence into training and held-out
frames, the rays of the training frames (colour and depth each at their capture instant's
pose), the scene bounds their depth covers, and the field initialised from their points."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING, Sequence

import numpy as np
import torch

from nap3d_graph.camera import Intrinsics, backproject_depth, colour_coverage, valid_depth_mask, warp_depth
from nap3d_graph.conventions import inv_T, transform_points
from nap3d_graph.datasets.depth_timing import CaptureTiming
from nap3d_graph.fields.grid import GridField, trilinear_corners
from nap3d_graph.fields.grid_render import pixel_directions
from nap3d_graph.progress import progress_bar

from .base import FieldError

if TYPE_CHECKING:
    from .train_config import TrainConfig

__all__ = ["TrainingRays", "outside_slab", "ray_poses", "split_frames", "split_posed_frames", "scene_bounds_from_depth", "splat_init"]

log = logging.getLogger(__name__)


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
        raise FieldError(f"`every` must be at least 1, got {every}")
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
    have a usable depth; coverage: (H, W) bool, the pixels whose colour is data (None: all;
    an undistorting reader's black corners are not, :func:`~nap3d_graph.camera.colour_coverage`):
    elsewhere a pixel's depth trains the geometry and its colour nothing.
    """

    rgb: torch.Tensor
    depth: torch.Tensor
    R_world_cam: torch.Tensor
    t_world_cam: np.ndarray
    num_valid: int
    intrinsics: Intrinsics
    coverage: torch.Tensor | None = None

    @classmethod
    def from_sequence(cls, sequence, indices: Sequence[int], config: TrainConfig, device,
                      progress: bool = False, timing: CaptureTiming | None = None) -> "TrainingRays":
        """Frames ``indices`` as training rays. With ``timing`` (``depth_offset_s``,
        ``colour_offset_s``, ``depth_scale``: see :mod:`nap3d_graph.datasets.depth_timing`)
        each frame's depth is scaled and moved from the pose at its capture time to the pose
        at the colour's, so both images of a ray see the same instant."""
        timing = CaptureTiming.of(timing)
        poses = _poses_of(sequence)
        T_colour = T_depth = poses[np.asarray(indices, dtype=int)]
        if timing is not None and getattr(sequence, "ground_truth_at", None) is not None:
            idx = np.asarray(indices, dtype=int)
            T_colour = sequence.ground_truth_at(np.asarray(sequence.timestamps)[idx] + timing.colour_offset_s)
            T_depth = sequence.ground_truth_at(np.asarray(sequence.depth_timestamps)[idx] + timing.depth_offset_s)
            bad = ~(np.all(np.isfinite(T_colour), axis=(1, 2)) & np.all(np.isfinite(T_depth), axis=(1, 2)))
            T_colour = np.where(bad[:, None, None], poses[idx], T_colour)
            T_depth = np.where(bad[:, None, None], poses[idx], T_depth)
        intrinsics = sequence.intrinsics.without_distortion()
        h, w = intrinsics.height, intrinsics.width
        coverage = colour_coverage(sequence)
        rgb = np.empty((len(indices), h, w, 3), dtype=np.uint8)
        depth = np.empty((len(indices), h, w), dtype=np.float32)
        for k, i in enumerate(progress_bar(indices, desc="load frames", unit="frame", disable=not progress, leave=False)):
            frame = sequence[int(i)]
            if frame.rgb.shape[:2] != (h, w):
                raise FieldError(f"frame {i} is {frame.rgb.shape[1]}x{frame.rgb.shape[0]}, "
                                 f"the sequence's intrinsics say {w}x{h}")
            rgb[k] = frame.rgb
            d = np.nan_to_num(frame.depth_m, nan=0.0)
            if timing is not None:
                d = warp_depth(d, intrinsics, inv_T(T_colour[k]) @ T_depth[k], timing.depth_scale)
            d[~valid_depth_mask(d, config.min_depth_m, config.max_depth_m)] = 0.0
            if config.slab_m is not None:
                d[outside_slab(d, intrinsics, T_colour[k], config.slab_m)] = 0.0
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
            coverage=None if coverage is None else torch.from_numpy(coverage.copy()).to(device),
        )

    @property
    def num_frames(self) -> int:
        return self.rgb.shape[0]


def outside_slab(depth_m: np.ndarray, intrinsics: Intrinsics, T_world_cam: np.ndarray, slab_m: tuple) -> np.ndarray:
    """(H, W) bool: the pixels of ``depth_m`` (H, W, z-depth metres) whose point, at
    ``T_world_cam`` (4, 4), lies outside ``slab_m`` (``(ax, ay, az, from_m, to_m)``, world frame;
    a None end is open). Pixels without depth are not outside."""
    a = np.asarray(slab_m[:3], dtype=float)
    lo = -np.inf if slab_m[3] is None else float(slab_m[3])
    hi = np.inf if slab_m[4] is None else float(slab_m[4])
    h, w = depth_m.shape
    v, u = np.mgrid[0:h, 0:w]
    # a . (R p_cam + t) with p_cam = z ((u - cx) / fx, (v - cy) / fy, 1): linear in each pixel's z.
    a_cam = np.asarray(T_world_cam, dtype=float)[:3, :3].T @ a
    per_z = a_cam[0] * (u - intrinsics.cx) / intrinsics.fx + a_cam[1] * (v - intrinsics.cy) / intrinsics.fy + a_cam[2]
    along = depth_m * per_z + float(a @ np.asarray(T_world_cam, dtype=float)[:3, 3])
    return (depth_m > 0) & ((along < lo) | (along > hi))


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


def ray_poses(rays: TrainingRays) -> np.ndarray:
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


#: Depth beyond this (metres) does not set a field's bounds: past an RGB-D camera's useful range
#: (Kinect v1 and RealSense D400 up to about 4-8 m), and on a floor of rooms in a row it is the
#: view through a line of doorways, which would stretch one room's grid down the whole floor.
BOUNDS_MAX_DEPTH_M = 8.0


def scene_bounds_from_depth(depth_m: np.ndarray, T_world_cam: np.ndarray, intrinsics: Intrinsics,
                            margin_m: float = 0.15, stride: int = 4, percentile: float = 0.02,
                            max_depth_m: float = BOUNDS_MAX_DEPTH_M, slab_m: tuple | None = None) -> np.ndarray:
    """World box (2, 3) that holds what the depth images see and the cameras.

    depth_m (F, H, W) z-depth metres (0 = missing); T_world_cam (F, 4, 4). Points are
    back-projected on every ``stride``-th pixel up to ``max_depth_m``; the box spans their
    ``percentile`` to ``100 - percentile`` percentiles per axis (stray far returns do not blow it
    up), grown by ``margin_m`` so windows behind the farthest surfaces still fit. With ``slab_m``
    (:func:`outside_slab`'s) only the cameras inside the slab: one that stood rooms away and
    looked into it (a submap's viewing frame) would stretch the box down the floor; its rays
    enter the box from outside.
    """
    depth_m = np.asarray(depth_m)
    chunks = []
    for k in range(depth_m.shape[0]):
        p_cam, _ = backproject_depth(depth_m[k], intrinsics, stride)
        p_cam = p_cam[p_cam[:, 2] <= max_depth_m]
        chunks.append(transform_points(T_world_cam[k], p_cam))
    points = np.concatenate(chunks) if chunks else np.zeros((0, 3))
    if len(points) < 10:
        raise FieldError("too few valid depth pixels to find the scene's bounds")
    lo = np.percentile(points, percentile, axis=0)
    hi = np.percentile(points, 100.0 - percentile, axis=0)
    cams = T_world_cam[:, :3, 3]
    if slab_m is not None:
        along = cams @ np.asarray(slab_m[:3], dtype=float)
        lo_m = -np.inf if slab_m[3] is None else float(slab_m[3])
        hi_m = np.inf if slab_m[4] is None else float(slab_m[4])
        cams = cams[(along >= lo_m) & (along <= hi_m)]
    if len(cams):
        lo, hi = np.minimum(lo, cams.min(axis=0)), np.maximum(hi, cams.max(axis=0))
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
        if rays.coverage is not None:  # no colour where the image holds no data
            wts = wts * rays.coverage[v, u].reshape(-1)[ok, None]
        color_weight.index_add_(0, idx.reshape(-1), wts.reshape(-1))
        color_sum.index_add_(1, idx.reshape(-1), (rgb.T[:, :, None] * wts[None]).reshape(3, -1))
    seen = color_weight > 0
    mean_rgb = (color_sum[:, seen] / color_weight[seen]).clamp(0.02, 0.98)
    field.density.view(-1)[weight_sum >= config.init_min_weight] = config.init_density_raw
    field.color.view(3, -1)[:, seen] = torch.log(mean_rgb / (1.0 - mean_rgb))
    field.mark_changed()
    return field
