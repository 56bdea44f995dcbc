"""When was a depth image taken, and how long is its metre? Both from the data itself.

A field trained with posed RGB-D frames inherits every error of those poses. On TUM's Kinect,
depth is stamped some 12-20 ms before colour, and its capture time relative to the
motion-capture clock is off by tens of milliseconds more; at 0.4 m/s, 20 ms is 8 mm of
smeared geometry. The depth scale can be off by a few percent too (TUM publishes a 1.035
correction for its freiburg1 camera). Both are estimated here by a multi-view criterion:
the depth of frame i, back-projected and moved with the ground-truth poses into frame j,
must agree with frame j's own depth. The median disagreement over pixel pairs (frames about
0.3-0.8 s apart) is minimised over a time offset added to the depth stamps.

The depth scale is *not* estimated by default: this criterion hardly depends on it and is
biased towards compressing depth (a shorter metre shrinks every disagreement in mm). On
simulated rooms whose true scale is 1 it returned 0.955-1.005, and 0.95 (the edge of its
search) for a true 0.966; a field trained at such a scale is centimetres off at 3 m. A run
measures the sensor's scale against the field instead (a similarity fit on each
correction's inliers, calibrated on the fly: ``PipelineConfig.depth_scale_check``). Pass
``scales`` to search it here anyway.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field

import numpy as np

from nap3d_graph.errors import DatasetError
from nap3d_graph.nap3d.matching import detect_features, match_features

from ..camera import backproject_depth, project
from ..conventions import inv_T, transform_points

__all__ = ["CaptureTiming", "ColourTiming", "DepthTiming", "estimate_colour_timing", "depth_agreement_mm", "frame_pairs",
           "depth_seen_from", "estimate_depth_timing", "estimate_timing", "multiview_agreement_mm",
           "resolve_capture_timing"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CaptureTiming:
    """When a recording's colour and depth were captured, against their stamps, and its depth's
    scale: what a run moves each keyframe's depth by (to its colour's instant) and what a field
    is built with. ``depth_offset_s`` / ``colour_offset_s``: add to the depth / colour stamps to
    get the capture instants on the ground truth's clock; ``depth_scale``: multiply the sensor's
    depth by it. The agreement figures (mm) say how well the frames agree with it
    (``agreement_mm``), at the depth stamps as they are and at the colour stamps, over
    ``pairs`` frame pairs. ``readout_s``: the colour camera's rolling shutter, first row to
    last (``colour_offset_s`` is then its middle row's; 0: a global shutter), with the median
    reprojection error of matched keypoints at this timing and at the best global-shutter one
    (``colour_error_px``, ``global_shutter_error_px``). Stored as a dict (a field's
    ``meta["timing"]``, reports, config files): :meth:`to_dict` and :meth:`of`; one stored
    before the readout was estimated reads as a global shutter."""

    depth_offset_s: float = 0.0
    colour_offset_s: float = 0.0
    depth_scale: float = 1.0
    agreement_mm: float = float("nan")
    agreement_at_depth_stamps_mm: float = float("nan")
    agreement_at_colour_stamps_mm: float = float("nan")
    pairs: int = 0
    readout_s: float = 0.0
    colour_error_px: float = float("nan")
    global_shutter_error_px: float = float("nan")

    def to_dict(self) -> dict:
        return {k: (float(v) if isinstance(v, (float, np.floating)) else int(v)) for k, v in asdict(self).items()}

    @classmethod
    def of(cls, value: "CaptureTiming | dict | None") -> "CaptureTiming | None":
        """``value`` as a CaptureTiming: a dict as stored (unknown keys ignored, missing ones at
        their defaults), a CaptureTiming as it is, None (or an empty dict) as None."""
        if value is None or isinstance(value, CaptureTiming):
            return value
        if not value:
            return None
        known = {f for f in cls.__dataclass_fields__}
        return cls(**{k: v for k, v in dict(value).items() if k in known})


@dataclass
class DepthTiming:
    """Depth capture offset and scale of a posed RGB-D sequence.

    offset_s: add to the depth stamps to get the instant the depth was captured on the
        ground truth's clock. scale: multiply the sensor's depth by it. agreement_mm: median
        disagreement of depth between frame pairs at the estimate; at_depth_stamps_mm and
        at_colour_stamps_mm: the same with poses at the depth stamps (scale 1) and at the
        colour stamps (what a trainer that ignores the stamps uses).
    """

    offset_s: float = 0.0
    scale: float = 1.0
    agreement_mm: float = float("nan")
    at_depth_stamps_mm: float = float("nan")
    at_colour_stamps_mm: float = float("nan")
    pairs: int = 0
    search: list = field(default_factory=list)

    def to_dict(self) -> dict:
        return asdict(self)


def depth_seen_from(depth_a: np.ndarray, depth_b: np.ndarray, intrinsics, T_b_a: np.ndarray, stride: int = 4,
                    scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Frame ``a``'s depth (every ``stride``-th pixel) moved into frame ``b`` by ``T_b_a``:
    ``(measured, z)`` (N,) each, for the points that land inside ``b``'s image: ``b``'s own depth
    at the pixel (0 where it has none) and the moved point's depth; both depths x ``scale``."""
    points_a, _ = backproject_depth(np.asarray(depth_a) * scale, intrinsics, stride)
    uv, z = project(transform_points(T_b_a, points_a), intrinsics)
    with np.errstate(invalid="ignore"):
        u, v = np.rint(uv[:, 0]), np.rint(uv[:, 1])
        inside = (u >= 0) & (u < intrinsics.width) & (v >= 0) & (v < intrinsics.height)
    return np.asarray(depth_b)[v[inside].astype(int), u[inside].astype(int)] * scale, z[inside]


def depth_agreement_mm(depth_a: np.ndarray, depth_b: np.ndarray, intrinsics, T_world_a: np.ndarray,
                       T_world_b: np.ndarray, stride: int = 4, scale: float = 1.0,
                       max_diff_m: float = 0.05) -> tuple[float, int]:
    """Median |z_b - z(a moved into b)| (mm) over pixels valid in both and within
    ``max_diff_m`` (the same surface), and how many; depths multiplied by ``scale``."""
    measured, z = depth_seen_from(depth_a, depth_b, intrinsics, inv_T(T_world_b) @ T_world_a, stride, scale)
    diff = measured - z
    same = (measured > 0) & (np.abs(diff) < max_diff_m)
    if not same.any():
        return float("nan"), 0
    return 1000.0 * float(np.median(np.abs(diff[same]))), int(same.sum())


def frame_pairs(timestamps: np.ndarray, count: int = 30, gap_s: tuple[float, float] = (0.33, 0.83)) -> list:
    """``count`` frame pairs ``(i, j)`` spread over the sequence, ``j`` the first frame at least
    a gap after ``i``, the gaps cycling through ``gap_s``: far enough apart that a time or
    scale error shows, near enough that they see the same surfaces."""
    t = np.asarray(timestamps, dtype=float)
    gaps = np.linspace(gap_s[0], gap_s[1], 4)
    pairs = []
    starts = np.linspace(0, max(len(t) - 2, 0), count).round().astype(int)
    for k, i in enumerate(starts):
        j = int(np.searchsorted(t, t[i] + gaps[k % len(gaps)]))
        if j < len(t) and (i, j) not in pairs:
            pairs.append((int(i), j))
    return pairs


def _pairs_agreement_mm(chosen, depths: dict, K, T_world: np.ndarray, needed: list, stride: int,
                        scale: float) -> float:
    """Median depth disagreement (mm) over frame pairs ``chosen`` with frames ``needed`` posed
    at ``T_world`` (len(needed), 4, 4); NaN when no pair could be compared."""
    pose = dict(zip(needed, T_world))
    values = [depth_agreement_mm(depths[i], depths[j], K, pose[i], pose[j], stride, scale)[0]
              for i, j in chosen if np.all(np.isfinite(pose[i])) and np.all(np.isfinite(pose[j]))]
    values = [v for v in values if np.isfinite(v)]
    return float(np.median(values)) if values else float("nan")


def multiview_agreement_mm(sequence, offset_s: float = 0.0, pairs: int = 30,
                           gap_s: tuple[float, float] = (0.33, 0.83), stride: int = 4) -> float:
    """Median disagreement (mm) of depth between frame pairs of ``sequence`` placed with its
    poses at the depth stamps + ``offset_s``: how self-consistent its poses and depth are
    (what refining training poses should lower)."""
    chosen = frame_pairs(sequence.timestamps, pairs, gap_s)
    needed = sorted({i for pair in chosen for i in pair})
    depths = {i: np.nan_to_num(sequence[i].depth_m, nan=0.0) for i in needed}
    T = sequence.ground_truth_at(np.asarray(sequence.depth_timestamps)[needed] + offset_s)
    return _pairs_agreement_mm(chosen, depths, sequence.intrinsics, T, needed, stride, 1.0)


def estimate_depth_timing(sequence, pairs: int = 30, gap_s: tuple[float, float] = (0.33, 0.83),
                          offsets_s: np.ndarray | None = None, scales: np.ndarray | None = None,
                          stride: int = 4) -> DepthTiming:
    """Estimate the depth capture offset and scale of ``sequence`` (needs ground truth,
    ``depth_timestamps`` and ``ground_truth_at``; see the module docstring).

    A coarse search over ``offsets_s`` (default -60 to +40 ms in 5 ms) at scale 1, then over
    ``scales`` (default: 1 only, see the module docstring) at the best offset, then a 1 ms
    refinement of the offset at the best scale.
    """
    if getattr(sequence, "ground_truth_at", None) is None or sequence.T_world_cam_gt is None:
        raise DatasetError("estimating the depth timing needs ground-truth poses")
    chosen = frame_pairs(sequence.timestamps, pairs, gap_s)
    if len(chosen) < 3:
        raise DatasetError(f"too few frames ({len(sequence)}) to estimate the depth timing")
    needed = sorted({i for pair in chosen for i in pair})
    depths = {i: np.nan_to_num(sequence[i].depth_m, nan=0.0) for i in needed}
    K = sequence.intrinsics
    search = []

    def score(offset: float, scale: float, at_colour: bool = False) -> float:
        stamps = sequence.timestamps if at_colour else sequence.depth_timestamps + offset
        result = _pairs_agreement_mm(chosen, depths, K, sequence.ground_truth_at(stamps[needed]), needed, stride, scale)
        result = result if np.isfinite(result) else float("inf")
        search.append([round(offset, 4), round(scale, 4), result])
        return result

    offsets = np.arange(-0.06, 0.0401, 0.005) if offsets_s is None else np.asarray(offsets_s, dtype=float)
    scales = np.array([1.0]) if scales is None else np.asarray(scales, dtype=float)
    at_depth = score(0.0, 1.0)
    at_colour = score(0.0, 1.0, at_colour=True)
    best_offset = min(offsets, key=lambda o: score(float(o), 1.0))
    # (one scale, the default: nothing to search, its score at best_offset is known)
    best_scale = scales[0] if len(scales) == 1 else min(scales, key=lambda s: score(float(best_offset), float(s)))
    fine = np.arange(best_offset - 0.005, best_offset + 0.0051, 0.001)
    best_offset = min(fine, key=lambda o: score(float(o), float(best_scale)))
    agreement = score(float(best_offset), float(best_scale))
    log.info("depth timing: offset %+.1f ms, scale %.4f: %.2f mm (depth stamps %.2f mm, colour stamps %.2f mm)",
             1000 * best_offset, best_scale, agreement, at_depth, at_colour)
    return DepthTiming(float(best_offset), float(best_scale), agreement, at_depth, at_colour, len(chosen), search)


def _bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    h, w = image.shape
    u = np.clip(uv[:, 0], 0, w - 1.001)
    v = np.clip(uv[:, 1], 0, h - 1.001)
    u0, v0 = np.floor(u).astype(int), np.floor(v).astype(int)
    du, dv = u - u0, v - v0
    return (image[v0, u0] * (1 - du) * (1 - dv) + image[v0, u0 + 1] * du * (1 - dv)
            + image[v0 + 1, u0] * (1 - du) * dv + image[v0 + 1, u0 + 1] * du * dv)


def _depth_along_rays(depth: np.ndarray, K, uv: np.ndarray, T_depth_colour: np.ndarray) -> np.ndarray:
    """z-depth (colour camera) where the rays of colour pixels ``uv`` (N, 2) meet the surface a
    depth image saw from another pose (``T_depth_colour`` (4, 4), or (N, 4, 4) one per pixel,
    maps colour-camera points into the depth camera): a few fixed-point steps, looking the
    depth up where the current point projects into the depth image. NaN where it leaves the
    image or hits a hole."""
    z = _bilinear(depth, uv)
    rays = np.stack([(uv[:, 0] - K.cx) / K.fx, (uv[:, 1] - K.cy) / K.fy, np.ones(len(uv))], axis=1)
    T = np.broadcast_to(T_depth_colour, (len(uv), 4, 4))
    for _ in range(3):
        p_depth = np.einsum("nij,nj->ni", T[:, :3, :3], rays * z[:, None]) + T[:, :3, 3]
        uv_d, z_d = project(p_depth, K)
        looked = _bilinear(depth, np.nan_to_num(uv_d))
        ok = np.all(np.isfinite(uv_d), axis=1) & (looked > 0) & (z_d > 0)
        # Move along the ray by the depth disagreement, measured along the depth camera's axis.
        z = np.where(ok, z * looked / np.where(ok, z_d, 1.0), np.nan)
    return z


#: A rolling-shutter readout is adopted only when it brings the matched keypoints closer (by 3%
#: of the median reprojection error) than a global shutter at its own best offset, and lies
#: inside the searched range: on a global-shutter camera the search's minimum is noise.
READOUT_MIN_GAIN = 0.03
READOUT_SEARCH_S = (0.0, 0.06)


@dataclass
class ColourTiming:
    """When a recording's colour rows were captured: ``offset_s`` to add to a colour stamp to get
    its middle row's instant on the ground truth's clock, ``readout_s`` from its first row to
    its last (0: a global shutter, or none the data could tell); ``error_px`` the median
    reprojection error of matched keypoints there, ``global_error_px`` the best a global
    shutter gave; ``search``: ``[[offset, readout, median px], ...]``."""

    offset_s: float
    readout_s: float
    error_px: float
    global_error_px: float
    search: list = field(default_factory=list)


class _MatchedPairs:
    """The keypoints of colour frame pairs matched once, their depth frames, and the
    reprojection error (px) of frame i's keypoints in frame j for a colour timing."""

    def __init__(self, sequence, timing: DepthTiming, pairs: int, gap_s: tuple[float, float]):
        self.sequence = sequence
        chosen = frame_pairs(sequence.timestamps, pairs, gap_s)
        needed = sorted({i for pair in chosen for i in pair})
        frames = {i: sequence[i] for i in needed}
        features = {i: detect_features(frames[i].rgb, 1500) for i in needed}
        self.depth = {i: np.nan_to_num(frames[i].depth_m, nan=0.0) * timing.scale for i in needed}
        self.T_world_depth = dict(zip(needed, sequence.ground_truth_at(
            np.asarray(sequence.depth_timestamps)[needed] + timing.offset_s)))
        self.matched = []
        for i, j in chosen:
            m = match_features(features[i], features[j], ratio=0.7)
            if len(m) >= 20 and np.all(np.isfinite(self.T_world_depth[i])):
                self.matched.append((i, j, m))

    def errors_px(self, offset_s: float, readout_s: float) -> np.ndarray:
        """Reprojection errors (px) of every matched keypoint of frame i in frame j, each pixel
        placed with the ground truth at its own row's instant: stamp + ``offset_s`` +
        ``readout_s`` * (row / height - 1/2)."""
        K, t = self.sequence.intrinsics, np.asarray(self.sequence.timestamps, dtype=float)
        stamps = [t[k] + offset_s + readout_s * (uv[:, 1] / K.height - 0.5)
                  for i, j, m in self.matched for k, uv in ((i, m.uv_a), (j, m.uv_b))]
        if not stamps:
            return np.zeros(0)
        # One interpolation for every keypoint of every pair: the interpolator is built per call.
        poses = np.split(self.sequence.ground_truth_at(np.concatenate(stamps)),
                         np.cumsum([len(s) for s in stamps])[:-1])
        errors = []
        for (i, j, m), T_i, T_j in zip(self.matched, poses[0::2], poses[1::2]):
            if not (np.all(np.isfinite(T_i)) and np.all(np.isfinite(T_j))):
                continue
            z = _depth_along_rays(self.depth[i], K, m.uv_a, inv_T(self.T_world_depth[i]) @ T_i)
            ok = np.isfinite(z) & (z > 0)
            rays = np.stack([(m.uv_a[ok, 0] - K.cx) / K.fx, (m.uv_a[ok, 1] - K.cy) / K.fy, np.ones(ok.sum())], 1)
            world = np.einsum("nij,nj->ni", T_i[ok, :3, :3], rays * z[ok, None]) + T_i[ok, :3, 3]
            T_j_cam = inv_T(T_j[ok])
            uv_j, _ = project(np.einsum("nij,nj->ni", T_j_cam[:, :3, :3], world) + T_j_cam[:, :3, 3], K)
            errors.append(np.linalg.norm(uv_j - m.uv_b[ok], axis=1))
        values = np.concatenate(errors) if errors else np.zeros(0)
        return values[np.isfinite(values)]


def estimate_colour_timing(sequence, timing: DepthTiming, pairs: int = 30, gap_s: tuple[float, float] = (0.2, 0.5),
                           offsets_s: np.ndarray | None = None, readouts_s: np.ndarray | None = None) -> ColourTiming:
    """The colour stamps' offset and the rolling shutter's readout, from matched keypoints.

    For frame pairs, SIFT keypoints of colour image i are matched with image j; each is given
    the depth its ray meets in depth image i (placed with the depth ``timing``), moved with the
    ground truth at its own row's instant in each image, and projected into image j. The
    timing that brings them closest to their matches (median pixel distance) is returned.
    Offset first (``offsets_s``, default -50 to +30 ms in 5 ms, then 1 ms) with a global
    shutter, then offset and readout together (``readouts_s``, default 0-60 ms in 5 ms, offsets
    within 6 ms in 2 ms; then both in 1 ms). A rolling shutter tilts the error with the row, so the two are told
    apart; the readout is kept only when it helps (:data:`READOUT_MIN_GAIN`).
    """
    pairs_ = _MatchedPairs(sequence, timing, pairs, gap_s)
    search = []

    def score(offset: float, readout: float) -> float:
        values = pairs_.errors_px(offset, readout)
        result = float(np.median(values)) if values.size >= 50 else float("inf")
        search.append([round(offset, 4), round(readout, 4), result])
        return result

    def best_offset(candidates, readout: float) -> float:
        return float(min(candidates, key=lambda o: score(float(o), readout)))

    offsets = np.arange(-0.05, 0.0301, 0.005) if offsets_s is None else np.asarray(offsets_s, dtype=float)
    offset = best_offset(offsets, 0.0)
    offset = best_offset(np.arange(offset - 0.005, offset + 0.0051, 0.001), 0.0)
    global_error = score(offset, 0.0)
    if not np.isfinite(global_error):
        raise DatasetError("too few matched keypoints with depth and ground truth to estimate the colour timing")
    # The two trade against each other (a later offset and a longer readout move the top rows
    # alike), so the readout is searched on a grid of both around the global shutter's offset.
    readouts = np.arange(READOUT_SEARCH_S[0], READOUT_SEARCH_S[1] + 1e-4, 0.005) if readouts_s is None \
        else np.asarray(readouts_s, dtype=float)
    grid = [(float(o), float(r)) for o in np.arange(offset - 0.006, offset + 0.0061, 0.002) for r in readouts]
    rs_offset, readout = min(grid, key=lambda g: score(*g))
    fine = [(float(o), float(r)) for o in np.arange(rs_offset - 0.002, rs_offset + 0.0021, 0.001)
            for r in np.arange(max(readout - 0.004, 0.0), readout + 0.0041, 0.001)]
    rs_offset, readout = min(fine, key=lambda g: score(*g))
    error = score(rs_offset, readout)
    inside = readout < READOUT_SEARCH_S[1] - 0.002
    if not (error < (1.0 - READOUT_MIN_GAIN) * global_error and inside):
        log.info("colour timing: offset %+.1f ms, global shutter (%.3f px; a %.0f ms readout gave %.3f px)",
                 1000 * offset, global_error, 1000 * readout, error)
        return ColourTiming(offset, 0.0, global_error, global_error, search)
    log.info("colour timing: offset %+.1f ms, rolling shutter read in %.0f ms (%.3f px; global shutter %.3f px)",
             1000 * rs_offset, 1000 * readout, error, global_error)
    return ColourTiming(rs_offset, readout, error, global_error, search)


def estimate_timing(sequence) -> CaptureTiming | None:
    """The capture timing of a sequence with depth stamps and ground truth (see
    :mod:`nap3d_graph.datasets.depth_timing`), or None when it cannot be estimated (no ground
    truth, too few frames) or the data cannot tell it."""
    if getattr(sequence, "ground_truth_at", None) is None or getattr(sequence, "depth_timestamps", None) is None:
        return None
    try:
        depth = estimate_depth_timing(sequence)
    except DatasetError as exc:
        log.warning("depth timing not estimated (%s); using the stamps as they are", exc)
        return None
    unclear = _unclear_timing(depth)
    if unclear:
        log.warning("capture timing not compensated: %s; using the stamps as they are", unclear)
        return None
    try:
        colour = estimate_colour_timing(sequence, depth)
    except DatasetError as exc:
        log.warning("colour timing not estimated (%s); using the stamps as they are", exc)
        return None
    return CaptureTiming(depth.offset_s, colour.offset_s, depth.scale, depth.agreement_mm, depth.at_depth_stamps_mm,
                         depth.at_colour_stamps_mm, depth.pairs, colour.readout_s, colour.error_px,
                         colour.global_error_px)


#: An estimated depth offset is used only when it makes the frames agree better than (by 2%)
#: the depth stamps as they are, and lies inside the searched range: on a
#: short recording (12 frames, 9 pairs) the search's minimum is noise, and a wrong offset warps
#: every keyframe's depth the wrong way (measured: ATE 1.63 instead of 0.60 cm).
TIMING_MIN_GAIN = 0.02
TIMING_SEARCH_S = (-0.06, 0.04)


def _unclear_timing(depth) -> str:
    """Why an estimated capture timing is not to be trusted ('' when it is)."""
    plain = depth.at_depth_stamps_mm  # what a run without the timing uses: depth at its own stamp
    if not depth.agreement_mm < (1.0 - TIMING_MIN_GAIN) * plain:
        return (f"the best depth offset ({depth.offset_s * 1000:+.0f} ms) makes the frames agree to "
                f"{depth.agreement_mm:.1f} mm, no better than the depth stamps as they are ({plain:.1f} mm)")
    if not TIMING_SEARCH_S[0] + 0.002 < depth.offset_s < TIMING_SEARCH_S[1] - 0.002:
        return f"the best depth offset ({depth.offset_s * 1000:+.0f} ms) is at the edge of the searched range"
    return ""


def resolve_capture_timing(field=None, sequence=None, given=None, compensate: bool = True
                           ) -> tuple[CaptureTiming | None, str]:
    """The capture timing to compensate, and where it came from, in this order: ``"off"``
    (``compensate`` False: None), ``"given"`` (``given``, e.g. a run's ``config.timing``),
    ``"field"`` (what ``field`` recorded when it was built), ``"estimated"`` (from
    ``sequence``'s ground truth: :func:`estimate_timing`), ``"none"`` (nothing known: None).
    The one resolver a run, Evaluation K, the peers and the study share."""
    if not compensate:
        return None, "off"
    if given is not None:
        return CaptureTiming.of(given), "given"
    recorded = CaptureTiming.of((getattr(field, "meta", None) or {}).get("timing"))
    if recorded is not None:
        return recorded, "field"
    if sequence is not None:
        estimated = estimate_timing(sequence)
        if estimated is not None:
            return estimated, "estimated"
    return None, "none"
