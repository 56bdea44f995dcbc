"""A splat field: surface splats fused from the RGB-D frames themselves, rasterised on the CPU.

The extension the NAP3D paper names, 3D Gaussians initialised from the RGB-D points, in its
simplest form that runs on two CPU cores: isotropic Gaussian splats on a regular fusion grid,
no gradient training. Building it:

1. every training frame's depth (scaled by the estimated depth scale, pixels next to depth
   jumps dropped: a Kinect's flying pixels) is back-projected with the pose *at the depth's
   capture time*, and each point takes its colour from the colour image at the pose *at the
   colour's capture time* (on a moving Kinect the two are ~30 ms apart: 1 cm at 0.4 m/s);
2. points are fused per voxel (``voxel_size_m``): a weighted mean position (weights
   ``1/sigma(z)^2`` of the sensor's depth noise) and colour; voxels seen by fewer than
   ``min_views`` frames are dropped (noise, flying pixels, moving things);
3. each frame's exposure and white balance are estimated as a per-channel affine map onto
   the fused colours and removed, and the colours fused again (``exposure_rounds``); a
   frame's colours count with the square of its sharpness (variance of the Laplacian,
   relative to the median frame), so motion-blurred frames blur the texture less.

Rendering (``render``): splats in front of the camera are projected; their footprints (a
Gaussian of ``splat_radius_vox`` voxels) are z-buffered, and the splats within
``blend_tolerance`` of the nearest one at a pixel are blended (colour and z-depth, weighted
by footprint and confidence), so the depth of a surface is the mean of its splats, not the
nearest noisy one. Opacity is ``1 - exp(-opacity_gain * sum of footprints)``: 1 on a covered
surface, falling to 0 in holes and beyond what the survey saw.

Why hand-written: gsplat and the reference Gaussian-splatting rasteriser need CUDA; Open3D
(TSDF fusion and raycasting on the CPU) is a 200 MB dependency for what is here ~150 lines of
numpy and torch.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

import numpy as np
import torch

from nap3d_graph.camera import DEPTH_SIGMA_Z2_PER_M, Intrinsics, RenderedView, colour_coverage
from nap3d_graph.camera import sharpness as image_sharpness
from nap3d_graph.conventions import inv_T
from nap3d_graph.progress import progress_bar
from nap3d_graph.torch_threads import torch_threads

from .base import FieldError
from .checkpoint import check_state, load_state, meta_json, save_state

__all__ = ["SplatConfig", "SplatField", "build_splat_field", "capture_poses", "SPLAT_FORMAT", "SPLAT_VERSION"]

log = logging.getLogger(__name__)

SPLAT_FORMAT = "nap3d-graph splat field"
SPLAT_VERSION = 1


@dataclass(frozen=True)
class SplatConfig:
    """Settings of building and rendering a splat field (defaults for room-sized scenes seen
    from 0.5-4 m by an RGB-D camera, rendered at 320x240).

    ``voxel_size_m`` None: 1.5 times the spacing of the back-projected points at the frames'
    median depth (6 mm for a 640x480 Kinect at 1.2 m, stride 2), at least 4 mm.
    """

    voxel_size_m: float | None = None
    stride: int = 2
    min_depth_m: float = 0.2
    max_depth_m: float = 4.5
    edge_rel_jump: float = 0.04
    min_views: int = 2
    depth_sigma_floor_m: float = 0.002
    depth_sigma_z2_per_m: float = DEPTH_SIGMA_Z2_PER_M
    exposure_rounds: int = 2
    splat_radius_vox: float = 1.3
    max_footprint_px: float = 2.5
    blend_tolerance_m: float = 0.02
    blend_tolerance_rel: float = 0.015
    opacity_gain: float = 2.0
    near_m: float = 0.05
    threads: int | None = 1

    def to_dict(self) -> dict:
        return asdict(self)


class SplatField:
    """Fused surface splats behind the field protocol.

    points: (N, 3) float32 world positions (m); colors: (N, 3) float32 in [0, 1]; weights:
    (N,) float32 confidence (fused ``1/sigma^2``, normalised to mean 1); views: (N,) int32
    number of frames that saw each splat. ``meta``: JSON-serialisable provenance.
    """

    name = "splat"

    def __init__(self, points, colors, weights, views, voxel_size_m: float, config: SplatConfig | None = None,
                 meta: dict | None = None):
        self.points = torch.as_tensor(np.asarray(points, dtype=np.float32))
        self.colors = torch.as_tensor(np.asarray(colors, dtype=np.float32))
        self.weights = torch.as_tensor(np.asarray(weights, dtype=np.float32))
        self.views = torch.as_tensor(np.asarray(views, dtype=np.int32))
        n = self.points.shape[0]
        if self.points.shape != (n, 3) or self.colors.shape != (n, 3) or self.weights.shape != (n,):
            raise FieldError(f"splat field needs points (N, 3), colours (N, 3), weights (N,); got "
                             f"{tuple(self.points.shape)}, {tuple(self.colors.shape)}, {tuple(self.weights.shape)}")
        if n == 0:
            raise FieldError("a splat field needs at least one splat")
        self.voxel_size = float(voxel_size_m)
        self.config = config or SplatConfig(voxel_size_m=voxel_size_m)
        self.meta = dict(meta or {})

    @property
    def bounds(self) -> np.ndarray:
        p = self.points.numpy()
        return np.stack([p.min(axis=0), p.max(axis=0)]).astype(np.float64)

    def __len__(self) -> int:
        return int(self.points.shape[0])

    def __repr__(self) -> str:
        return f"SplatField({len(self)} splats, voxel {self.voxel_size * 1000:.1f} mm)"

    # --- rendering ----------------------------------------------------------------------------

    def render(self, T_world_cam: np.ndarray, intrinsics: Intrinsics) -> RenderedView:
        """RGB, z-depth (m, 0 where nothing is seen) and opacity at ``T_world_cam`` (4x4,
        world <- OpenCV camera)."""
        T_world_cam = np.asarray(T_world_cam, dtype=np.float64)
        if T_world_cam.shape != (4, 4) or not np.all(np.isfinite(T_world_cam)):
            raise FieldError(f"T_world_cam must be a finite 4x4 matrix, got shape {T_world_cam.shape}")
        intrinsics = intrinsics.without_distortion()
        with torch.no_grad(), torch_threads(self.config.threads):
            rgb, depth, opacity = self._rasterise(T_world_cam, intrinsics)
        return RenderedView(rgb=(rgb.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).numpy(),
                            depth_m=depth.numpy().astype(np.float32),
                            opacity=opacity.clamp(0, 1).numpy().astype(np.float32), intrinsics=intrinsics)

    def _visible(self, T_world_cam: np.ndarray, K: Intrinsics):
        """Splats in front of the camera and near the image: ``(z_m, u_px, v_px, index)``
        numpy arrays (:func:`~.splat_kernel.visible_splats`)."""
        from .splat_kernel import visible_splats

        T_cam_world = inv_T(T_world_cam)
        margin = int(np.ceil(self.config.max_footprint_px)) + 1
        return visible_splats(self.points.numpy(), T_cam_world[:3, :3].astype(np.float32),
                              T_cam_world[:3, 3].astype(np.float32), K.fx, K.fy, K.cx, K.cy, K.width, K.height,
                              float(self.config.near_m), margin)

    def _rasterise(self, T_world_cam: np.ndarray, K: Intrinsics):
        """The visible splats rasterised by :func:`~.splat_kernel.rasterise_splats`:
        ``(rgb (H, W, 3), depth (H, W), opacity (H, W))`` float32 tensors."""
        from .splat_kernel import rasterise_splats

        cfg = self.config
        h, w = K.height, K.width
        z, u, v, idx = self._visible(T_world_cam, K)
        if z.size == 0:
            return torch.zeros((h, w, 3)), torch.zeros((h, w)), torch.zeros((h, w))
        reach = np.float32(0.5 * (K.fx + K.fy) * cfg.splat_radius_vox * self.voxel_size)
        radius_px = np.clip(reach / z, np.float32(0.5), np.float32(cfg.max_footprint_px))
        rgb, depth, opacity = rasterise_splats(
            z, u, v, radius_px, self.colors.numpy()[idx], self.weights.numpy()[idx],
            w, h, cfg.blend_tolerance_rel, cfg.blend_tolerance_m, cfg.opacity_gain)
        return (torch.from_numpy(rgb).reshape(h, w, 3), torch.from_numpy(depth).reshape(h, w),
                torch.from_numpy(opacity).reshape(h, w))

    # --- checkpoints --------------------------------------------------------------------------

    def state_dict(self) -> dict:
        return {"format": SPLAT_FORMAT, "version": SPLAT_VERSION, "points": self.points.contiguous(),
                "colors": self.colors.contiguous(), "weights": self.weights.contiguous(),
                "views": self.views.contiguous(), "voxel_size_m": self.voxel_size,
                "config": json.dumps(self.config.to_dict()),
                "conventions": "units=metres; points in the world frame of the training poses (T_world_cam); "
                               "colours linear in [0, 1] after exposure normalisation",
                "meta": meta_json(self.meta)}

    def save(self, path) -> Path:
        """Write the checkpoint (:meth:`state_dict`, atomically); returns the path."""
        return save_state(self.state_dict(), path)

    @classmethod
    def from_state_dict(cls, state: dict, source: str = "checkpoint") -> "SplatField":
        check_state(state, source, "splat field", SPLAT_FORMAT, SPLAT_VERSION,
                    ("points", "colors", "weights", "views", "voxel_size_m"))
        if not all(torch.isfinite(state[k]).all() for k in ("points", "colors", "weights")):
            raise FieldError(f"{source}: checkpoint holds non-finite splats")
        try:
            stored = json.loads(state.get("config", "{}"))
            known = {f.name for f in fields(SplatConfig)}
            config = SplatConfig(**{k: v for k, v in stored.items() if k in known})
            meta = json.loads(state.get("meta", "{}"))
        except (TypeError, ValueError) as exc:
            raise FieldError(f"{source}: unreadable checkpoint metadata ({exc})") from None
        return cls(state["points"].numpy(), state["colors"].numpy(), state["weights"].numpy(),
                   state["views"].numpy(), float(state["voxel_size_m"]), config, meta)

    @classmethod
    def load(cls, path) -> "SplatField":
        path = Path(path)
        return cls.from_state_dict(load_state(path), source=str(path))



# --- building ------------------------------------------------------------------------------------


def _edge_free(depth: np.ndarray, rel_jump: float) -> np.ndarray:
    """True where no 4-neighbour's depth differs by more than ``rel_jump`` x depth."""
    d = depth
    ok = d > 0
    jump = np.zeros_like(d, dtype=bool)
    for shifted in (np.roll(d, 1, 0), np.roll(d, -1, 0), np.roll(d, 1, 1), np.roll(d, -1, 1)):
        jump |= (shifted > 0) & (np.abs(shifted - d) > rel_jump * d)
        jump |= shifted <= 0  # next to a hole: the sensor's edge pixels are the least reliable
    ok &= ~jump
    ok[0, :] = ok[-1, :] = ok[:, 0] = ok[:, -1] = False
    return ok


def _sample_colour(rgb01: np.ndarray, uv: np.ndarray) -> np.ndarray:
    h, w, _ = rgb01.shape
    u = np.clip(uv[:, 0], 0, w - 1.001)
    v = np.clip(uv[:, 1], 0, h - 1.001)
    u0, v0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    du, dv = (u - u0)[:, None], (v - v0)[:, None]
    return (rgb01[v0, u0] * (1 - du) * (1 - dv) + rgb01[v0, u0 + 1] * du * (1 - dv)
            + rgb01[v0 + 1, u0] * (1 - du) * dv + rgb01[v0 + 1, u0 + 1] * du * dv)


def _frame_points(frame, T_world_depth: np.ndarray, T_world_colour: np.ndarray, scale: float,
                  config: SplatConfig, coverage: np.ndarray | None = None):
    """World points (M, 3), colours (M, 3) in [0, 1], weights (M,) and whether each has a
    colour (M,) bool of one frame: a point whose colour lands where the image holds no data
    (outside ``coverage`` (H, W) bool, see :func:`~nap3d_graph.camera.colour_coverage`; None:
    it holds data everywhere) keeps its geometry, with colour 0 and no colour."""
    K = frame.intrinsics
    depth = np.nan_to_num(frame.depth_m.astype(np.float64), nan=0.0) * scale
    depth[(depth < config.min_depth_m) | (depth > config.max_depth_m)] = 0.0
    ok = _edge_free(depth, config.edge_rel_jump)
    v, u = np.mgrid[0:depth.shape[0]:config.stride, 0:depth.shape[1]:config.stride]
    keep = ok[v, u]
    u, v, z = u[keep].astype(np.float64), v[keep].astype(np.float64), depth[v[keep], u[keep]]
    p_depth = np.stack([(u - K.cx) / K.fx * z, (v - K.cy) / K.fy * z, z], axis=1)
    world = p_depth @ T_world_depth[:3, :3].T + T_world_depth[:3, 3]
    # Colour from the colour image at *its* capture pose.
    T_colour_world = inv_T(T_world_colour)
    p_colour = world @ T_colour_world[:3, :3].T + T_colour_world[:3, 3]
    zc = p_colour[:, 2]
    uc = K.fx * p_colour[:, 0] / zc + K.cx
    vc = K.fy * p_colour[:, 1] / zc + K.cy
    inside = (zc > 0) & (uc >= 0) & (uc < K.width - 1) & (vc >= 0) & (vc < K.height - 1)
    colours = _sample_colour(frame.rgb.astype(np.float32) / 255.0, np.stack([uc, vc], 1)[inside])
    has_colour = np.ones(len(colours), bool)
    if coverage is not None:
        # All four pixels of the bilinear sample must hold data.
        iu, iv = uc[inside].astype(int), vc[inside].astype(int)
        has_colour = coverage[iv, iu] & coverage[iv + 1, iu + 1] & coverage[iv, iu + 1] & coverage[iv + 1, iu]
        colours[~has_colour] = 0.0
    sigma = config.depth_sigma_floor_m + config.depth_sigma_z2_per_m * z[inside] ** 2
    return world[inside].astype(np.float32), colours.astype(np.float32), (1.0 / sigma**2).astype(np.float32), \
        has_colour


def _voxels(keys, frame_of):
    """``(inverse, n, views)``: each point's voxel among the ``n`` occupied ones, and how many
    frames see each voxel. The same for every exposure round: computed once."""
    unique, inverse = np.unique(keys, return_inverse=True)
    n = len(unique)
    frames = frame_of.max() + 1
    views = np.bincount(np.unique(inverse.astype(np.int64) * frames + frame_of) // frames, minlength=n)
    return inverse, n, views


def _fuse(inverse, n, frame_of, points, colours, weights, colour_weights, gains, offsets):
    """Weighted means per voxel (``inverse``, ``n``: :func:`_voxels`); returns (mean points,
    colours, weight sums)."""
    corrected = np.clip(colours * gains[frame_of] + offsets[frame_of], 0.0, 1.0)
    wsum = np.bincount(inverse, weights=weights, minlength=n)
    csum = np.maximum(np.bincount(inverse, weights=colour_weights, minlength=n), 1e-12)
    mean_p = np.stack([np.bincount(inverse, weights=weights * points[:, k], minlength=n) for k in range(3)], 1)
    mean_c = np.stack([np.bincount(inverse, weights=colour_weights * corrected[:, k], minlength=n) for k in range(3)],
                      1) * (wsum / csum)[:, None]
    return mean_p / wsum[:, None], mean_c / wsum[:, None], wsum


def _exposure_fit(frame_of, colours, target, weights, frames: int):
    """Per frame and channel, the affine map ``a c + b`` of its colours onto the fused ones
    (weighted least squares, from per-frame sums: one pass over the points, not one a frame)."""
    gains = np.ones((frames, 3), np.float64)
    offsets = np.zeros((frames, 3), np.float64)
    counts = np.bincount(frame_of, minlength=frames)
    sw = np.bincount(frame_of, weights=weights, minlength=frames)
    for k in range(3):
        x, y = colours[:, k].astype(np.float64), target[:, k].astype(np.float64)
        sx, sy = (np.bincount(frame_of, weights=weights * v, minlength=frames) for v in (x, y))
        sxx, sxy = (np.bincount(frame_of, weights=weights * x * v, minlength=frames) for v in (x, y))
        det = sw * sxx - sx * sx
        solvable = (counts >= 100) & (det > 1e-12 * np.maximum(sw * sxx, 1e-300))
        a = np.divide(sw * sxy - sx * sy, det, out=np.ones(frames), where=solvable)
        b = np.divide(sy - a * sx, sw, out=np.zeros(frames), where=solvable)
        gains[solvable, k], offsets[solvable, k] = a[solvable], b[solvable]
    # Keep the overall exposure where it was: the mean map is the identity.
    gains /= gains.mean(axis=0, keepdims=True)
    offsets -= offsets.mean(axis=0, keepdims=True)
    return gains, offsets


def build_splat_field(sequence, indices, config: SplatConfig | None = None, depth_offset_s: float = 0.0,
                      colour_offset_s: float = 0.0, depth_scale: float = 1.0, progress: bool = False):
    """Fuse frames ``indices`` of a posed ``sequence`` into a :class:`SplatField`.

    Depth is placed with the ground truth at ``depth_timestamps + depth_offset_s`` and scaled
    by ``depth_scale``; colour is looked up with the ground truth at ``timestamps +
    colour_offset_s`` (see :mod:`nap3d_graph.datasets.depth_timing`). A sequence without
    ``ground_truth_at`` (poses at the frame stamps only) uses its poses for both. Returns
    ``(field, report)``.
    """
    config = config or SplatConfig()
    indices = np.asarray(indices, dtype=int)
    if indices.size == 0:
        raise FieldError("no frames to build a splat field from")
    poses = getattr(sequence, "T_world_cam_gt", None)
    if poses is None:
        raise FieldError("building a splat field needs posed frames, but the sequence has no ground-truth poses")
    started = time.perf_counter()
    T_depth, T_colour = capture_poses(sequence, indices, depth_offset_s, colour_offset_s)
    frame_of, points, colours, weights, has_colour, sharpness, n_frames = _frames_points(
        sequence, indices, T_depth, T_colour, depth_scale, config, progress)
    colour_weights = weights * (sharpness / np.median(sharpness))[frame_of] ** 2 * has_colour
    voxel = config.voxel_size_m or _auto_voxel(sequence, config)
    config = replace(config, voxel_size_m=voxel)
    keys = _voxel_keys(points, voxel)
    gains, offsets = np.ones((len(indices), 3)), np.zeros((len(indices), 3))
    inverse, n_voxels, views = _voxels(keys, frame_of)
    for _ in range(max(config.exposure_rounds, 0) + 1):
        mean_p, mean_c, wsum = _fuse(inverse, n_voxels, frame_of, points, colours, weights, colour_weights, gains,
                                     offsets)
        if _ == config.exposure_rounds:
            break
        gains, offsets = _exposure_fit(frame_of, colours, mean_c[inverse], weights * has_colour, len(indices))
    # A voxel only ever seen where the images hold no colour data has no colour: not a splat.
    coloured = np.bincount(inverse, weights=has_colour.astype(np.float64), minlength=len(views)) > 0
    keep = (views >= config.min_views) & coloured
    if not keep.any():
        raise FieldError(f"no voxel was seen by {config.min_views} frames; use more or overlapping frames")
    confidence = wsum[keep] / wsum[keep].mean()
    field = SplatField(mean_p[keep], np.clip(mean_c[keep], 0, 1), confidence, views[keep], voxel, config)
    report = {"splats": int(keep.sum()), "voxel_size_m": voxel, "voxels_seen_once_or_too_few_views": int((~keep).sum()),
              "points_fused": int(len(points)), "frames": n_frames,
              "exposure_gain_range": [float(gains.min()), float(gains.max())],
              "build_seconds": round(time.perf_counter() - started, 2)}
    log.info("splat field: %d splats from %d points of %d frames in %.1f s", report["splats"], len(points),
             n_frames, report["build_seconds"])
    return field, report


def _frames_points(sequence, indices, T_depth, T_colour, depth_scale: float, config: SplatConfig, progress: bool):
    """Every posed frame's back-projected points, concatenated: ``(frame_of (P,) position in
    ``indices``, points (P, 3) world metres, colours (P, 3), weights (P,) float64, has_colour
    (P,), sharpness (len(indices),) of each frame, frames used)``."""
    chunks, sharpness = [], np.ones(len(indices))
    coverage = colour_coverage(sequence)
    for k, i in enumerate(progress_bar(indices, desc="fuse frames", unit="frame", disable=not progress, leave=False)):
        if not (np.all(np.isfinite(T_depth[k])) and np.all(np.isfinite(T_colour[k]))):
            continue
        frame = sequence[int(i)]
        # Full resolution; the small offset keeps a featureless frame's weight above zero.
        sharpness[k] = image_sharpness(frame.rgb, width=None) + 1e-6
        points, colours, weights, has_colour = _frame_points(frame, T_depth[k], T_colour[k], depth_scale, config,
                                                             coverage)
        chunks.append((np.full(len(points), k, np.int64), points, colours, weights, has_colour))
    if not chunks:
        raise FieldError("no training frame has a usable depth pixel")
    frame_of, points, colours, weights, has_colour = (np.concatenate([c[j] for c in chunks]) for j in range(5))
    return frame_of, points, colours, weights.astype(np.float64), has_colour, sharpness, len(chunks)


def _voxel_keys(points: np.ndarray, voxel: float) -> np.ndarray:
    """(P,) int64: one key per voxel of edge ``voxel`` metres that ``points`` (P, 3) fall in."""
    cell = np.floor(points / voxel).astype(np.int64)
    cell -= cell.min(axis=0)
    span = cell.max(axis=0) + 1
    return (cell[:, 2] * span[1] + cell[:, 1]) * span[0] + cell[:, 0]


def _auto_voxel(sequence, config: SplatConfig) -> float:
    """1.5 x the spacing of neighbouring back-projected points at the median sensor depth."""
    K = sequence.intrinsics
    depth = float(np.median(_depth_sample(sequence)))
    return max(0.004, 1.5 * depth * config.stride / (0.5 * (K.fx + K.fy)))


def _depth_sample(sequence) -> np.ndarray:
    values = []
    for i in np.linspace(0, len(sequence) - 1, min(5, len(sequence))).round().astype(int):
        d = np.nan_to_num(sequence[int(i)].depth_m, nan=0.0)
        values.append(d[d > 0][::50])
    values = np.concatenate(values) if values else np.zeros(0)
    return values if values.size else np.array([1.0])


def capture_poses(sequence, indices, depth_offset_s: float, colour_offset_s: float):
    """Poses of each frame's depth and colour at their capture times (N, 4, 4) each."""
    at = getattr(sequence, "ground_truth_at", None)
    if at is None or getattr(sequence, "depth_timestamps", None) is None:
        poses = np.asarray(sequence.T_world_cam_gt)[indices]
        return poses, poses
    T_depth = at(np.asarray(sequence.depth_timestamps)[indices] + depth_offset_s)
    T_colour = at(np.asarray(sequence.timestamps)[indices] + colour_offset_s)
    if T_depth is None:
        poses = np.asarray(sequence.T_world_cam_gt)[indices]
        return poses, poses
    return T_depth, T_colour
