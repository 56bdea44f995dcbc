"""A view field: the survey's own sharpest RGB-D frames, re-projected into the asked view.

Fused fields (the grid's colour voxels, the splats' footprints) average the survey's images
over a few millimetres and several views; a trained map whose texture is blurred by a few
pixels costs a feature matcher most of its correct matches (fr1/desk: 13-14 dB held out).
This field keeps the pixels themselves, as image-based renderers do:

Building it (``build_view_field``):

1. every training frame's sharpness (variance of the Laplacian) is measured; frames are taken
   sharpest first, and a frame is kept as a *view* unless a kept view already sees nearly
   the same thing (camera within ``min_spacing_m`` and viewing centre within
   ``min_spacing_m``, see :func:`view_gap_m`), so the map holds the sharp frames of each
   stretch, not the motion-blurred ones;
2. each view's depth is moved from its capture pose to its colour's (the capture timing),
   scaled (the depth scale) and resampled into the view's colour camera at the stored size
   (``width`` x ``height``) by a z-buffered forward splat; its colour is resampled by area.

Rendering (``render``): the ``views_per_render`` views nearest the asked pose (camera centre
plus viewing centre, within ``max_angle_deg`` of its optical axis) are forward-splatted into
it, the nearest first: each pixel keeps the first view's surface unless a later view puts a
surface clearly in front of it (an occluder the first view did not see), and takes a later
view's where the earlier ones left a hole. A splatted pixel far behind its neighbours is a
background point seen through a crack in a nearer surface and is dropped; one-pixel holes
surrounded by the same surface are filled from their neighbours. Opacity is 1 where a view
put a surface, 0 elsewhere. Where no view's depth landed (the depth camera sees less than the
colour camera; dark and far surfaces), the colour comes from the nearest views through the
homography of the plane each looks at, with no depth and no opacity (``fill_background``):
an approximate background instead of black, whose edges would be false features.

The field's world frame is that of the training poses; the training frames render as
themselves (the training-view PSNR is not a figure of merit for this field: held-out
frames are).
"""

from __future__ import annotations

import copy
import json
import logging
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import cv2
import numpy as np
import torch

from nap3d_graph.camera import Intrinsics, RenderedView, backproject_depth, colour_coverage, warp_depth
from nap3d_graph.camera import sharpness as image_sharpness
from nap3d_graph.conventions import inv_T
from nap3d_graph.progress import progress_bar
from nap3d_graph.torch_threads import torch_threads

from .base import FieldError
from .checkpoint import check_state, load_state, meta_json, save_state
from .gap_error import sigmas_at_gap, view_gap_m
from .splat import capture_poses

__all__ = ["ViewFieldConfig", "ViewField", "build_view_field", "VIEW_FORMAT", "VIEW_VERSION"]

log = logging.getLogger(__name__)

VIEW_FORMAT = "nap3d-graph view field"
VIEW_VERSION = 1

#: Depth of a pixel no point landed on, in splat buffers (finite, so filters can take minima).
FAR = 1.0e6


@dataclass(frozen=True)
class ViewFieldConfig:
    """Settings of a view field (defaults for room-sized scenes seen by an RGB-D camera,
    rendered at 320x240, the pipeline's size)."""

    width: int = 320
    height: int = 240
    min_spacing_m: float = 0.04
    views_per_render: int = 3
    max_angle_deg: float = 45.0
    min_depth_m: float = 0.2
    max_depth_m: float = 4.5
    crack_rel: float = 0.05
    occluder_rel: float = 0.05
    near_m: float = 0.05
    fill_background: bool = True
    threads: int | None = 1

    def to_dict(self) -> dict:
        return asdict(self)


class ViewField:
    """Posed RGB-D views behind the field protocol.

    rgb: (V, H, W, 3) uint8; depth_m: (V, H, W) float32 z-depth in each view's colour camera
    (0 = none); T_world_cam: (V, 4, 4) float64 colour-camera poses (world <- camera);
    intrinsics: the views' pinhole camera (H x W); meta: JSON-serialisable provenance;
    coverage: (H, W) bool, the pixels of the views' images that hold data (an undistorted
    camera's black corners do not, see :func:`~nap3d_graph.camera.colour_coverage`), None
    for all.
    """

    name = "views"

    def __init__(self, rgb, depth_m, T_world_cam, intrinsics: Intrinsics, config: ViewFieldConfig | None = None,
                 meta: dict | None = None, coverage: np.ndarray | None = None):
        self.rgb = np.ascontiguousarray(rgb, dtype=np.uint8)
        self.depth_m = np.ascontiguousarray(depth_m, dtype=np.float32)
        self.T_world_cam = np.asarray(T_world_cam, dtype=np.float64)
        v = self.rgb.shape[0] if self.rgb.ndim == 4 else -1
        h, w = intrinsics.height, intrinsics.width
        if (v < 1 or self.rgb.shape != (v, h, w, 3) or self.depth_m.shape != (v, h, w)
                or self.T_world_cam.shape != (v, 4, 4)):
            raise FieldError(f"a view field needs rgb (V, {h}, {w}, 3), depth (V, {h}, {w}) and poses (V, 4, 4) "
                             f"with V >= 1; got {self.rgb.shape}, {self.depth_m.shape}, {self.T_world_cam.shape}")
        if not np.all(np.isfinite(self.T_world_cam)) or not np.all(np.isfinite(self.depth_m)):
            raise FieldError("a view field's poses and depths must be finite")
        if coverage is not None and np.shape(coverage) != (h, w):
            raise FieldError(f"a view field's coverage must be ({h}, {w}), got {np.shape(coverage)}")
        self.coverage = None if coverage is None else np.array(coverage, dtype=bool)  # own, writable copy
        self.intrinsics = intrinsics.without_distortion()
        self.config = config or ViewFieldConfig(width=w, height=h)
        self.meta = dict(meta or {})
        self._points: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}
        self._hidden: np.ndarray | None = None  # views left out (hiding_near), (V,) bool
        depth_med = [float(np.median(d[d > 0])) if np.any(d > 0) else 1.0 for d in self.depth_m]
        self._look_depth_m = np.asarray(depth_med)

    def __len__(self) -> int:
        return int(self.rgb.shape[0])

    def __repr__(self) -> str:
        return f"ViewField({len(self)} views, {self.intrinsics.width}x{self.intrinsics.height})"

    @property
    def bounds(self) -> np.ndarray:
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        for j in range(len(self)):
            p, _ = backproject_depth(self.depth_m[j], self.intrinsics)  # not cached: a render needs few views
            if len(p):
                world = p @ self.T_world_cam[j, :3, :3].T + self.T_world_cam[j, :3, 3]
                lo, hi = np.minimum(lo, world.min(0)), np.maximum(hi, world.max(0))
        return np.stack([lo, hi])

    # --- rendering ----------------------------------------------------------------------------

    def _gaps(self, T_world_cam: np.ndarray) -> np.ndarray:
        """(V,) :func:`view_gap_m` of each view from ``T_world_cam``; inf for views beyond
        ``max_angle_deg`` of its optical axis and for hidden ones."""
        gap = view_gap_m(self.T_world_cam, self._look_depth_m, T_world_cam)
        axes = self.T_world_cam[:, :3, 2]
        cos = axes @ np.asarray(T_world_cam)[:3, 2]
        gap[cos < np.cos(np.radians(self.config.max_angle_deg))] = np.inf
        if self._hidden is not None:
            gap[self._hidden] = np.inf
        return gap

    def nearest_views(self, T_world_cam: np.ndarray, count: int | None = None) -> np.ndarray:
        """Indices of the views that best see what a camera at ``T_world_cam`` sees, best
        first: smallest camera-centre plus viewing-centre distance, within ``max_angle_deg``."""
        count = count or self.config.views_per_render
        gap = self._gaps(T_world_cam)
        order = np.argsort(gap, kind="stable")[:count]
        return order[np.isfinite(gap[order])]

    def nearest_gap_m(self, T_world_cam: np.ndarray) -> float:
        """How far (:func:`view_gap_m`, metres) the nearest view sees from ``T_world_cam``
        (inf when none looks its way)."""
        return float(self._gaps(T_world_cam).min())

    def hiding_near(self, T_world_cam: np.ndarray, radius_m: float) -> "ViewField":
        """This field without the views within ``radius_m`` of ``T_world_cam`` (they share
        the data): how it renders a viewpoint it saw from no nearer than that."""
        other = copy.copy(self)
        hidden = view_gap_m(self.T_world_cam, self._look_depth_m, T_world_cam) < radius_m
        other._hidden = hidden if self._hidden is None else (hidden | self._hidden)
        return other

    def only_views(self, indices) -> "ViewField":
        """This field with every view but ``indices`` (view numbers) hidden (they share the
        data): rendered at one kept view's own pose it gives that frame as it was stored, so a
        frame can be aligned to each training view alone."""
        keep = np.zeros(len(self), dtype=bool)
        keep[np.asarray(indices, dtype=int)] = True
        other = copy.copy(self)
        other._hidden = ~keep if self._hidden is None else (~keep | self._hidden)
        return other

    @property
    def has_error_by_view(self) -> bool:
        """Whether the field measured how its error grows away from its views
        (``meta["field_error"]["by_view"]``, see :meth:`error_sigmas_at`)."""
        return bool(((self.meta.get("field_error") or {}).get("by_view") or {}).get("gap_m"))

    def error_sigmas_at(self, T_world_cam: np.ndarray) -> tuple[float, float] | None:
        """``(sigma_m, sigma_rad)`` of the field's error at ``T_world_cam``, from the error
        measured with the views near held-out frames hidden (``meta["field_error"]["by_view"]``:
        sigmas at increasing gaps to the nearest view), interpolated at this pose's gap and
        extended linearly beyond the largest measured one; None without that measurement."""
        if not self.has_error_by_view:
            return None
        return sigmas_at_gap(self.meta["field_error"]["by_view"], self.nearest_gap_m(T_world_cam))

    def render(self, T_world_cam: np.ndarray, intrinsics: Intrinsics) -> RenderedView:
        """RGB, z-depth (m, 0 where no view sees) and opacity at ``T_world_cam`` (4x4,
        world <- OpenCV camera). Above the stored size the render is made at the stored size
        and enlarged (no texture is invented)."""
        T_world_cam = np.asarray(T_world_cam, dtype=np.float64)
        if T_world_cam.shape != (4, 4) or not np.all(np.isfinite(T_world_cam)):
            raise FieldError(f"T_world_cam must be a finite 4x4 matrix, got shape {T_world_cam.shape}")
        intrinsics = intrinsics.without_distortion()
        K = intrinsics
        if intrinsics.width > self.intrinsics.width or intrinsics.height > self.intrinsics.height:
            ratio = min(self.intrinsics.width / intrinsics.width, self.intrinsics.height / intrinsics.height)
            K = intrinsics.scaled(max(1, int(round(intrinsics.width * ratio))),
                                  max(1, int(round(intrinsics.height * ratio))))
        with torch.no_grad(), torch_threads(self.config.threads):
            rgb, depth = self._composite(T_world_cam, K)
        if K is not intrinsics:
            size = (intrinsics.width, intrinsics.height)
            rgb = cv2.resize(rgb, size, interpolation=cv2.INTER_LINEAR)
            depth = cv2.resize(depth, size, interpolation=cv2.INTER_NEAREST)
        return RenderedView(rgb=rgb, depth_m=depth, opacity=(depth > 0).astype(np.float32), intrinsics=intrinsics)

    def _view_points(self, j: int) -> tuple[torch.Tensor, torch.Tensor]:
        """View ``j``'s valid pixels as camera points (N, 3) float32 and colours (N, 3) uint8
        (cached: a run renders near the same views again and again)."""
        if j not in self._points:
            points, uv = backproject_depth(self.depth_m[j], self.intrinsics)
            uv = uv.astype(np.int64)
            colours = self.rgb[j][uv[:, 1], uv[:, 0]]
            self._points[j] = (torch.from_numpy(points.astype(np.float32)), torch.from_numpy(colours))
        return self._points[j]

    def _splat_all(self, views: np.ndarray, T_cam_world: np.ndarray, K: Intrinsics):
        """``views`` (best first) forward-splatted together into camera ``K`` at
        ``T_cam_world``: depth (H, W) (``FAR`` where nothing lands) and colour (H, W, 3).

        One z-buffer for all: each point lands on its nearest pixel and competes with the
        depth ``z (1 + occluder_rel * rank)``, rank the view's place in ``views``: a pixel
        keeps the best view's surface unless a later view's is clearly in front of it (an
        occluder the best view did not see), and takes a later view's where the earlier left
        a hole."""
        h, w = K.height, K.width
        us, vs, zs, keys, colours = [], [], [], [], []
        for rank, j in enumerate(views):
            points, rgb = self._view_points(int(j))
            T = T_cam_world @ self.T_world_cam[j]
            p = points @ torch.as_tensor(T[:3, :3].T, dtype=torch.float32) + torch.as_tensor(T[:3, 3],
                                                                                           dtype=torch.float32)
            front = p[:, 2] > self.config.near_m
            p = p[front]
            z = p[:, 2]
            us.append(torch.round(K.fx * p[:, 0] / z + K.cx).long())
            vs.append(torch.round(K.fy * p[:, 1] / z + K.cy).long())
            zs.append(z)
            keys.append(z * (1.0 + self.config.occluder_rel * rank))
            colours.append(rgb[front])
        if not zs:
            return np.full((h, w), FAR, np.float32), np.zeros((h, w, 3), np.uint8)
        u, v, z, key, colour = (torch.cat(x) for x in (us, vs, zs, keys, colours))
        ok = ((u >= 0) & (u < w) & (v >= 0) & (v < h)).nonzero()[:, 0]
        pix, z, key = v[ok] * w + u[ok], z[ok], key[ok]
        best = torch.full((h * w,), float("inf"))
        best.scatter_reduce_(0, pix, key, reduce="amin")
        winner = (key <= best[pix]).nonzero()[:, 0]
        depth = torch.full((h * w,), FAR)
        rgb = torch.zeros((h * w, 3), dtype=torch.uint8)
        depth[pix[winner]] = z[winner]
        rgb[pix[winner]] = colour[ok[winner]]
        return depth.numpy().reshape(h, w), rgb.numpy().reshape(h, w, 3)

    def _composite(self, T_world_cam: np.ndarray, K: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
        views = self.nearest_views(T_world_cam)
        z, rgb = self._splat_all(views, inv_T(T_world_cam), K)
        z = _drop_cracks(z, self.config.crack_rel)
        depth = np.where(z < FAR, z, 0.0).astype(np.float32)
        rgb[depth <= 0] = 0
        # Twice: a surface seen nearer than its view was spreads its pixels apart, and the
        # gaps between them (one pixel wide, sometimes two) close in two passes.
        for _ in range(2):
            depth, rgb = _fill_pinholes(depth, rgb, self.config.crack_rel)
        if self.config.fill_background:
            rgb = self._fill_background(rgb, depth <= 0, views, T_world_cam, K)
        return rgb, depth

    def _fill_background(self, rgb: np.ndarray, hole: np.ndarray, views: np.ndarray, T_world_cam: np.ndarray,
                         K: Intrinsics) -> np.ndarray:
        """``rgb`` (H, W, 3) with its ``hole`` pixels (H, W) bool (no view's depth landed
        there) coloured from the views (best first) through the homography of the plane each
        view looks at (its median depth, facing it): an approximate background, with no depth,
        instead of black. The depth camera sees less than the colour camera (fr1/desk: 11-22%
        of a render has no depth), and a black region's edges are strong, false features."""
        hole = hole.copy()
        if not hole.any():
            return rgb
        out = rgb.copy()
        size = (K.width, K.height)
        K_asked, K_view_inv = K.K, np.linalg.inv(self.intrinsics.K)
        T_cam_world = inv_T(T_world_cam)
        # Where a view's image holds data (the same for every view): only those pixels are warped.
        has_data = np.ones(self.rgb.shape[1:3], np.uint8) if self.coverage is None else self.coverage.astype(np.uint8)
        for j in views:
            T_cam_view = T_cam_world @ self.T_world_cam[j]
            # Plane n.X = d in the view's camera (n = +z, d its median depth): X_cam = (R + t n^T / d) X_view.
            H = K_asked @ (T_cam_view[:3, :3] + np.outer(T_cam_view[:3, 3], [0.0, 0.0, 1.0 / self._look_depth_m[j]])) \
                @ K_view_inv
            warped = cv2.warpPerspective(self.rgb[j], H, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
            inside = cv2.warpPerspective(has_data, H, size, flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT) > 0
            take = hole & inside
            out[take] = warped[take]
            hole &= ~take
            if not hole.any():
                break
        return out

    # --- checkpoints --------------------------------------------------------------------------

    def state_dict(self) -> dict:
        return {"format": VIEW_FORMAT, "version": VIEW_VERSION, "rgb": torch.from_numpy(self.rgb),
                "depth_m": torch.from_numpy(self.depth_m), "T_world_cam": torch.from_numpy(self.T_world_cam),
                "intrinsics": json.dumps(self.intrinsics.to_dict()), "config": json.dumps(self.config.to_dict()),
                "conventions": "units=metres; T_world_cam: world <- OpenCV colour camera at the colour's capture "
                               "instant; depth_m: z-depth in that camera, 0 = none; rgb: the frame's own colours",
                "meta": meta_json(self.meta),
                **({} if self.coverage is None else {"coverage": torch.from_numpy(self.coverage)})}

    def save(self, path) -> Path:
        """Write the checkpoint (:meth:`state_dict`, atomically); returns the path."""
        return save_state(self.state_dict(), path)

    @classmethod
    def from_state_dict(cls, state: dict, source: str = "checkpoint") -> "ViewField":
        check_state(state, source, "view field", VIEW_FORMAT, VIEW_VERSION, ("rgb", "depth_m", "T_world_cam", "intrinsics"))
        try:
            intrinsics = Intrinsics.from_dict(json.loads(state["intrinsics"]))
            stored = json.loads(state.get("config", "{}"))
            known = {f.name for f in fields(ViewFieldConfig)}
            config = ViewFieldConfig(**{k: v for k, v in stored.items() if k in known})
            meta = json.loads(state.get("meta", "{}"))
        except (TypeError, ValueError, KeyError) as exc:
            raise FieldError(f"{source}: unreadable checkpoint metadata ({exc})") from None
        coverage = state.get("coverage")
        return cls(state["rgb"].numpy(), state["depth_m"].numpy(), state["T_world_cam"].numpy(), intrinsics,
                   config, meta, None if coverage is None else coverage.numpy())

    @classmethod
    def load(cls, path) -> "ViewField":
        path = Path(path)
        return cls.from_state_dict(load_state(path), source=str(path))


def _drop_cracks(z: np.ndarray, rel: float) -> np.ndarray:
    """A splatted depth (H, W) (``FAR`` = nothing) without the background points seen
    through cracks in a nearer surface: a pixel more than ``rel`` behind the nearest of its
    3x3 neighbours, when at least 6 of the 8 are that near (a crack has the nearer surface on
    both sides; a pixel beside a depth edge has it on one, and stays), is set to ``FAR``."""
    z = z.astype(np.float32)
    near = cv2.erode(z, np.ones((3, 3), np.uint8))
    front = (z <= near * (1.0 + rel)).astype(np.float32)
    count = cv2.filter2D(front, -1, np.ones((3, 3), np.float32), borderType=cv2.BORDER_CONSTANT)
    out = z.copy()
    out[(front == 0) & (count >= 6)] = FAR
    return out


def _fill_pinholes(depth: np.ndarray, rgb: np.ndarray, rel: float) -> tuple[np.ndarray, np.ndarray]:
    """Holes (depth 0) with at least 4 of their 8 neighbours on one surface (within ``rel``
    of their mean) take the neighbours' mean depth and colour: the splat's cracks, not
    what no view saw."""
    seen = (depth > 0).astype(np.float32)
    box = np.ones((3, 3), np.float32)
    count = cv2.filter2D(seen, -1, box, borderType=cv2.BORDER_CONSTANT)
    hole = (depth <= 0) & (count >= 4)
    if not hole.any():
        return depth, rgb
    dsum = cv2.filter2D(depth, -1, box, borderType=cv2.BORDER_CONSTANT)
    d2sum = cv2.filter2D(depth * depth, -1, box, borderType=cv2.BORDER_CONSTANT)
    mean = dsum / np.maximum(count, 1)
    spread = np.sqrt(np.maximum(d2sum / np.maximum(count, 1) - mean**2, 0.0))
    hole &= spread <= rel * mean
    csum = cv2.filter2D(rgb.astype(np.float32) * seen[..., None], -1, box, borderType=cv2.BORDER_CONSTANT)
    depth = depth.copy()
    rgb = rgb.copy()
    depth[hole] = mean[hole]
    rgb[hole] = np.clip(csum[hole] / count[hole][:, None] + 0.5, 0, 255).astype(np.uint8)
    return depth, rgb


# --- building ------------------------------------------------------------------------------------


def build_view_field(sequence, indices, config: ViewFieldConfig | None = None, depth_offset_s: float = 0.0,
                     colour_offset_s: float = 0.0, depth_scale: float = 1.0, progress: bool = False):
    """The sharp, spread-out views among frames ``indices`` of a posed ``sequence`` as a
    :class:`ViewField`; returns ``(field, report)``.

    Depth is placed with the ground truth at ``depth_timestamps + depth_offset_s`` and scaled
    by ``depth_scale``, colour at ``timestamps + colour_offset_s`` (see
    :mod:`nap3d_graph.datasets.depth_timing`); a sequence with poses at its frame stamps only
    uses them for both.
    """
    config = config or ViewFieldConfig()
    indices = np.asarray(indices, dtype=int)
    if indices.size == 0:
        raise FieldError("no frames to build a view field from")
    if getattr(sequence, "T_world_cam_gt", None) is None:
        raise FieldError("building a view field needs posed frames, but the sequence has no ground-truth poses")
    started = time.perf_counter()
    T_depth, T_colour = capture_poses(sequence, indices, depth_offset_s, colour_offset_s)
    posed = np.all(np.isfinite(T_depth), axis=(1, 2)) & np.all(np.isfinite(T_colour), axis=(1, 2))
    K_full = sequence.intrinsics.without_distortion()
    K = K_full.scaled(min(config.width, K_full.width), min(config.height, K_full.height))
    sharp = np.full(len(indices), -1.0)
    for k in progress_bar(np.flatnonzero(posed), desc="rate frames", unit="frame", disable=not progress, leave=False):
        sharp[k] = image_sharpness(sequence[int(indices[k])].rgb)
    if not posed.any():
        raise FieldError("no training frame has a finite pose")
    look_m = float(np.median(_median_depths(sequence, indices[np.flatnonzero(posed)])))
    chosen = _choose_views(T_colour, sharp, posed, look_m, config.min_spacing_m)
    coverage = colour_coverage(sequence, (K.width, K.height))
    rgb = np.empty((len(chosen), K.height, K.width, 3), np.uint8)
    depth = np.empty((len(chosen), K.height, K.width), np.float32)
    for n, k in enumerate(progress_bar(chosen, desc="store views", unit="view", disable=not progress, leave=False)):
        frame = sequence[int(indices[k])]
        rgb[n] = cv2.resize(frame.rgb, (K.width, K.height), interpolation=cv2.INTER_AREA)
        d = warp_depth(np.nan_to_num(frame.depth_m, nan=0.0), K_full, inv_T(T_colour[k]) @ T_depth[k],
                       depth_scale, dst_intrinsics=K)
        d[(d < config.min_depth_m) | (d > config.max_depth_m)] = 0.0
        if coverage is not None:
            d[~coverage] = 0.0  # no colour there: the black corners must not be warped into other views
        depth[n] = d
    field = ViewField(rgb, depth, T_colour[chosen], K, config, coverage=coverage)
    report = {"views": int(len(chosen)), "frames_rated": int(posed.sum()), "look_depth_m": round(look_m, 4),
              "view_frames": [int(indices[k]) for k in chosen],
              "sharpness_kept_median": float(np.median(sharp[chosen])),
              "sharpness_all_median": float(np.median(sharp[posed])),
              "build_seconds": round(time.perf_counter() - started, 2)}
    log.info("view field: %d views of %d frames in %.1f s", len(chosen), int(posed.sum()), report["build_seconds"])
    return field, report


def _choose_views(T_colour: np.ndarray, sharp: np.ndarray, posed: np.ndarray, look: float,
                  min_spacing_m: float) -> np.ndarray:
    """Positions into the frames of the kept views, in frame order: sharpest first, each kept
    unless a kept view sees from within ``min_spacing_m`` (:func:`view_gap_m` with the
    viewing centres ``look`` metres ahead)."""
    kept: list[int] = []
    for k in np.argsort(-sharp, kind="stable"):
        if not posed[k]:
            continue
        if kept:
            gap = view_gap_m(T_colour[kept], np.full(len(kept), look), T_colour[k])
            if gap.min() < min_spacing_m:
                continue
        kept.append(int(k))
    return np.sort(np.asarray(kept, dtype=int))


def _median_depths(sequence, indices) -> np.ndarray:
    """Median sensor depths of up to 5 frames spread over ``indices`` (1 m when none has one)."""
    picks = np.asarray(indices)[np.linspace(0, len(indices) - 1, min(5, len(indices))).round().astype(int)]
    values = []
    for i in picks:
        d = np.nan_to_num(sequence[int(i)].depth_m, nan=0.0)
        if np.any(d > 0):
            values.append(float(np.median(d[d > 0])))
    return np.asarray(values or [1.0])
