"""Cutting a long survey into submaps (:mod:`nap3d_graph.fields.submaps` says why and what a
submap is): by space, along the survey's principal direction, in slabs of equal frame count,
each training on its slab and ``overlap_m`` beyond."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from nap3d_graph.camera import backproject_depth
from nap3d_graph.conventions import transform_points
from nap3d_graph.fields.submaps import Submap, SubmapSettings
from nap3d_graph.progress import progress_bar

__all__ = ["plan_submaps", "level_frame", "with_viewing_frames"]

#: Every this many rows and columns of a depth image count where a frame looked (a 320 x 240
#: frame: 300 points).
VIEW_STRIDE = 16


def level_frame(T_map_cam: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """(3, 3) ``R_grid_map``: a frame whose ``y`` is the floor's down and ``x`` runs along ``axis``
    (3,), for a submap's grid. T_map_cam (N, 4, 4) its cameras. Down is the direction most
    orthogonal to every camera's ``x`` axis (a robot's or a hand's camera keeps its rows level
    while it pans and tilts), signed like the cameras' own ``y`` (OpenCV: down); ``x`` is ``axis``
    made level (the cameras' first level principal direction when ``axis`` is near vertical)."""
    R = np.asarray(T_map_cam, dtype=float)[:, :3, :3]
    x_cams = R[:, :, 0]
    down = np.linalg.eigh(x_cams.T @ x_cams)[1][:, 0]
    if float(down @ R[:, :, 1].sum(axis=0)) < 0:
        down = -down
    along = np.asarray(axis, dtype=float) - (np.asarray(axis, dtype=float) @ down) * down
    if np.linalg.norm(along) < 0.3:
        p = np.asarray(T_map_cam, dtype=float)[:, :3, 3]
        p = p - p.mean(axis=0)
        p = p - np.outer(p @ down, down)
        along = np.linalg.svd(p, full_matrices=False)[2][0] if len(p) > 1 else np.cross(down, [0.0, 0.0, 1.0])
        along = along - (along @ down) * down
    x = along / np.linalg.norm(along)
    z = np.cross(x, down)
    return np.stack([x, down, z])


def _shorter_cores(cuts: list[float], lo: float, hi: float, max_length_m: float) -> list[float]:
    """``cuts`` (increasing, metres along the axis) with every core between the survey's ends
    ``lo`` and ``hi`` longer than ``max_length_m`` cut into equal parts."""
    ends = [lo, *cuts, hi]
    out: list[float] = []
    for k, (a, b) in enumerate(zip(ends[:-1], ends[1:])):
        n = math.ceil((b - a) / max_length_m)
        out.extend(float(a + (b - a) * i / n) for i in range(1, n))
        if k < len(cuts):
            out.append(cuts[k])
    return out


def plan_submaps(T_map_cam: np.ndarray, settings: SubmapSettings | None = None) -> list[Submap]:
    """The submaps of a survey posed at ``T_map_cam`` (N, 4, 4; NaN where a frame has no pose):
    the posed cameras ordered along their principal direction (the map's frame is the first
    camera's, so no axis of it is known to be level or long) and cut into slabs of equal count,
    ``ceil(frames / max_frames)`` of them, a slab longer than ``max_length_m`` cut again into
    equal lengths, each taking the frames within ``overlap_m`` of its slab too, and trains in a
    level frame along the floor (:func:`level_frame`); one submap of every posed frame, in the
    map's frame, when there are no more than ``max_frames``."""
    s = settings or SubmapSettings()
    T = np.asarray(T_map_cam, dtype=float)
    posed = np.flatnonzero(np.all(np.isfinite(T.reshape(len(T), -1)), axis=1))
    p = T[posed, :3, 3]
    axis = np.array([1.0, 0.0, 0.0])
    if len(p) > 1:
        axis = np.linalg.svd(p - p.mean(axis=0), full_matrices=False)[2][0]
    if len(posed) <= s.max_frames:
        return [Submap(0, axis, np.array([-np.inf, np.inf]), posed)]
    along = p @ axis
    order = np.argsort(along, kind="stable")
    slabs = np.array_split(order, math.ceil(len(posed) / s.max_frames))
    # Cut halfway between neighbouring slabs: every point of the floor has one core.
    cuts = [(along[a[-1]] + along[b[0]]) / 2 for a, b in zip(slabs[:-1], slabs[1:])]
    edges = [-np.inf, *_shorter_cores(cuts, float(along.min()), float(along.max()), s.max_length_m), np.inf]
    submaps, lo = [], edges[0]
    for hi in edges[1:]:
        near = (along >= lo - s.overlap_m) & (along <= hi + s.overlap_m)
        if not near.any():  # a stretch of a long core no camera stood in: part of the next one
            continue
        submaps.append(Submap(len(submaps), axis, np.array([lo, hi]), posed[near],
                              R_grid_map=level_frame(T[posed[near]], axis)))
        lo = hi
    return submaps


def with_viewing_frames(submaps: list[Submap], sequence, T_map_cam: np.ndarray, settings: SubmapSettings,
                        progress: bool = False) -> list[Submap]:
    """``submaps`` (cut by :func:`plan_submaps`), each with the survey frames whose camera stood
    outside it but whose depth saw into its core: at least ``settings.viewing_share`` of a frame's
    sampled depth points (every ``VIEW_STRIDE``-th pixel, at ``T_map_cam`` (N, 4, 4)), the
    ``settings.viewing_frames`` that saw most of it (:class:`~nap3d_graph.fields.submaps.SubmapSettings`
    says why). ``sequence``: the survey, read once for its depth. A map of one submap, or
    ``viewing_frames`` 0, is returned as it is."""
    if len(submaps) < 2 or settings.viewing_frames == 0:
        return submaps
    along = _depth_along(sequence, T_map_cam, submaps[0].axis, progress)
    out = []
    for s in submaps:
        own = set(int(i) for i in s.frames)
        share = {i: float(np.mean((a >= s.core[0]) & (a < s.core[1]))) for i, a in along.items()
                 if i not in own and a.size}
        seen = sorted((i for i, v in share.items() if v >= settings.viewing_share), key=lambda i: -share[i])
        extra = np.asarray(seen[: settings.viewing_frames], dtype=int)
        out.append(replace(s, frames=np.union1d(s.frames, extra).astype(int)))
    return out


def _depth_along(sequence, T_map_cam: np.ndarray, axis: np.ndarray, progress: bool) -> dict[int, np.ndarray]:
    """Each posed frame's sampled depth points, as metres along ``axis`` (3,) in the map's frame."""
    T = np.asarray(T_map_cam, dtype=float)
    posed = np.flatnonzero(np.all(np.isfinite(T.reshape(len(T), -1)), axis=1))
    along = {}
    for i in progress_bar(posed, desc="where frames looked", unit="frame", disable=not progress, leave=False):
        frame = sequence[int(i)]
        p_cam, _ = backproject_depth(np.nan_to_num(frame.depth_m), frame.intrinsics, VIEW_STRIDE)
        along[int(i)] = transform_points(T[i], p_cam) @ axis
    return along
