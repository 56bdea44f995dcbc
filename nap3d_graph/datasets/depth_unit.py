"""Is the depth in metres? Checked on a few posed frames before any work, not after a field.

A depth unit mistake scales every depth by one factor (TUM-layout PNGs holding millimetres
read at TUM's 5000 per metre are 5x short). The frames' median depth cannot always tell
(0.3 m is a plausible depth), but the recording's poses can: moved by the poses' metric
translation, one frame's depth lands on another's only at the right scale. For each candidate
scale the check moves frame pairs with enough baseline into each other and takes the median
relative disagreement ``|s d_b - z_ab(s)| / (s d_b)`` (relative, because a sensor's depth noise
grows with depth, so no scale is favoured for shrinking the numbers). At the right scale it
is the sensor's noise (about 1%); at a wrong one it is a good part of the parallax the motion
causes. Scale is unobservable from the camera alone (odometry from that depth scales with
it), so the check needs the recording's poses: ground truth or the poses given to
``train-field``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ..conventions import inv_T
from ..errors import DatasetError
from .depth_timing import depth_seen_from

__all__ = ["DepthUnitCheck", "check_depth_unit", "UNIT_MISTAKES", "checked_depth_scale", "DepthUnitLook",
           "inspect_depth_unit", "KINECT_STEP_PER_M", "NEAREST_SEEN_M", "FURTHEST_MEDIAN_M"]

log = logging.getLogger(__name__)

#: The scales a unit mistake multiplies the true depth by, and what each mistake is.
UNIT_MISTAKES = {
    5.0: "millimetres read at TUM's 5000 per metre (x5 = 5000/1000)",
    0.2: "TUM's 1/5000 m read as millimetres (x0.2 = 1000/5000)",
    1000.0: "millimetres read as metres (x1000)",
    0.001: "metres read as millimetres (x0.001)",
}


@dataclass(frozen=True)
class DepthUnitCheck:
    """The outcome: ``scale`` multiplies the depth as read to agree across views best (1.0:
    it is in metres); ``disagreement`` maps each tried scale to its median relative
    disagreement; ``pairs`` the frame pairs compared; ``mistake`` what the wrong scale means
    (None when the depth is in metres)."""

    scale: float
    disagreement: dict
    pairs: int
    mistake: str | None

    def message(self) -> str:
        """One line: what the depth looks like and the evidence."""
        right, as_read = self.disagreement[self.scale], self.disagreement[1.0]
        return (f"the depth looks like {self.mistake}: the views agree when it is multiplied by {self.scale:g} "
                f"({100 * right:.1f}% median disagreement over {self.pairs} frame pairs, against {100 * as_read:.1f}% "
                "as read)")


def _relative_disagreement(depth_a, depth_b, K, T_b_a: np.ndarray, scale: float, stride: int) -> float:
    """Median ``|s d_b - z| / (s d_b)`` over pixels of ``a`` that land on valid depth in ``b``."""
    measured, z = depth_seen_from(depth_a, depth_b, K, T_b_a, stride, scale)
    valid = (measured > 0) & (z > 0)
    if valid.sum() < 50:
        return float("nan")
    return float(np.median(np.abs(measured[valid] - z[valid]) / measured[valid]))


def _pairs_with_baseline(T_world_cam: np.ndarray, count: int, baseline_m: tuple[float, float],
                         max_angle_deg: float) -> list[tuple[int, int]]:
    """Up to ``count`` frame pairs, spread over the recording, whose cameras are
    ``baseline_m`` apart and turned less than ``max_angle_deg`` (they see the same surfaces)."""
    posed = np.flatnonzero(np.all(np.isfinite(T_world_cam), axis=(1, 2)))
    pairs = []
    for i in posed[np.linspace(0, len(posed) - 1, min(len(posed), 4 * count)).round().astype(int)]:
        for j in posed[posed > i]:
            T_ij = inv_T(T_world_cam[i]) @ T_world_cam[j]
            distance = float(np.linalg.norm(T_ij[:3, 3]))
            angle = float(np.degrees(np.arccos(np.clip((np.trace(T_ij[:3, :3]) - 1) / 2, -1, 1))))
            if distance > baseline_m[1] or angle > max_angle_deg:
                break
            if distance >= baseline_m[0]:
                pairs.append((int(i), int(j)))
                break
        if len(pairs) >= count:
            break
    return pairs


def check_depth_unit(sequence, pairs: int = 12, baseline_m: tuple[float, float] = (0.08, 0.6),
                     max_angle_deg: float = 25.0, stride: int = 8) -> DepthUnitCheck | None:
    """Which unit scale makes ``sequence``'s depth agree across its posed frames (see the
    module docstring); None when it has no poses or too little baseline to tell."""
    T_world_cam = getattr(sequence, "T_world_cam_gt", None)
    if T_world_cam is None:
        return None
    chosen = _pairs_with_baseline(np.asarray(T_world_cam, dtype=float), pairs, baseline_m, max_angle_deg)
    if len(chosen) < 3:
        log.info("depth unit: %d frame pairs with %.2f-%.2f m baseline, too few to check", len(chosen), *baseline_m)
        return None
    K = sequence.intrinsics
    depths = {}
    for i in sorted({k for pair in chosen for k in pair}):
        try:
            depths[i] = np.nan_to_num(np.asarray(sequence[i].depth_m, dtype=float), nan=0.0)
        except (DatasetError, OSError):
            continue
    chosen = [(i, j) for i, j in chosen if i in depths and j in depths]
    scores = {}
    for scale in (1.0, *UNIT_MISTAKES):
        values = [_relative_disagreement(depths[i], depths[j], K, inv_T(T_world_cam[j]) @ T_world_cam[i], scale,
                                         stride) for i, j in chosen]
        values = [v for v in values if np.isfinite(v)]
        scores[scale] = float(np.median(values)) if len(values) >= 3 else float("nan")
    if not np.isfinite(scores[1.0]):
        return None
    best = min((s for s in scores if np.isfinite(scores[s])), key=scores.__getitem__)
    # A mistake only when the other scale agrees clearly better: noise moves the figures a little.
    mistaken = best != 1.0 and scores[best] < 0.6 * scores[1.0]
    result = DepthUnitCheck(best if mistaken else 1.0, scores, len(chosen), UNIT_MISTAKES[best] if mistaken else None)
    log.info("depth unit: %s", {f"x{s:g}": round(v, 4) for s, v in scores.items()})
    return result


# --- without poses: the depth's own range and steps -----------------------------------------

#: Kinect v1's depth step: depth comes from disparity in 1/8 px at a ~580 px focal length over a
#: 7.5 cm baseline, so representable depths ``z`` lie ``z**2 / (8 * 580 * 0.075)`` apart
#: (per metre of z**2). TUM RGB-D, 7-Scenes, NYU and most public RGB-D recordings are Kinect
#: v1's; their stored values keep these steps whatever unit they are written in.
KINECT_STEP_PER_M = 1.0 / (8 * 580.0 * 0.075)

#: Nearer than an RGB-D camera measures: a D435 sees from about 0.2 m (0.28 m at 1280x720), a
#: Kinect v1 from 0.5 m. A survey with a tenth of its depth nearer is read in the wrong unit.
NEAREST_SEEN_M = 0.2

#: The units recordings are written in (units per metre): millimetres, TUM's 1/5000 m.
COMMON_UNITS = (1000.0, 5000.0)

#: A median depth beyond this is further than RGB-D cameras measure a room (a Kinect to ~4.5 m,
#: a D435 to ~6-10 m, noisily).
FURTHEST_MEDIAN_M = 10.0

#: Steps resolved: only where the stored unit is finer than the sensor's step (3 units or more
#: between neighbouring values) do the values show the sensor's steps.
_RESOLVED_STEP_UNITS = 3


def checked_depth_scale(value, where: str) -> float:
    """A depth scale (stored units per metre) as a float, or a one-line :class:`DatasetError`:
    finite and at least 1 (a value below 1 is metres per unit, a RealSense's way of saying it:
    its 0.001 is 1000 here)."""
    try:
        scale = float(value)
    except (TypeError, ValueError):
        raise DatasetError(f"{where}: `depth_scale` must be a number (depth units per metre), got {value!r}") from None
    if not np.isfinite(scale) or scale <= 0:
        raise DatasetError(f"{where}: `depth_scale` must be a finite number > 0 (depth units per metre), got {value!r}")
    if scale < 1:
        raise DatasetError(f"{where}: `depth_scale` is depth units per metre (TUM 5000, millimetres 1000); {scale:g} "
                           f"looks like metres per unit (a RealSense's depth scale): write {1 / scale:g}")
    return scale


def kinect_units_per_m(raw: np.ndarray) -> float | None:
    """The units per metre at which ``raw`` (stored depth values, 0 and 65535 = missing)
    shows Kinect v1's depth steps (:data:`KINECT_STEP_PER_M`): with ``r`` a stored value and
    ``g`` the gap to the next smaller one present, ``units = KINECT_STEP_PER_M * r**2 / g``
    (median). None when the steps are not resolved (a unit coarser than the sensor's steps,
    or depth that was filtered or resampled)."""
    values = np.unique(raw[(raw > 0) & (raw < 65535)])
    if values.size < 50:
        return None
    gaps, upper = np.diff(values.astype(float)), values[1:].astype(float)
    if np.median(gaps) < _RESOLVED_STEP_UNITS:
        return None
    return float(KINECT_STEP_PER_M * np.median(upper ** 2 / gaps))


@dataclass(frozen=True)
class DepthUnitLook:
    """What a few frames' depth looks like, without poses: ``median_m`` and ``near_m`` the
    median and 10th percentile of their valid depth as read (metres); ``units_per_m`` the unit the source reads (None when it does not say);
    ``kinect_units_per_m`` the unit at which the stored values show Kinect v1's steps, per
    frame inspected (None where they do not); ``warnings`` what looks wrong, one line each;
    ``mixed`` a one-line refusal when the frames are in different units (else None)."""

    median_m: float
    near_m: float
    units_per_m: float | None
    kinect_units_per_m: tuple
    warnings: tuple
    mixed: str | None


def _near(a: float, b: float, tolerance: float = 0.15) -> bool:
    return abs(a / b - 1.0) <= tolerance


def _kinect_warning(implied: float, used: float, source: str) -> str | None:
    """The line for stored values whose Kinect steps say ``implied`` units per metre when
    ``used`` is read (None when they agree)."""
    if _near(implied, used):
        return None
    implied = next((u for u in COMMON_UNITS if _near(implied, u)), implied)
    factor = used / implied
    return (f"the depth's steps are a Kinect v1's at {implied:.0f} units per metre, but it is read at {used:g} "
            f"({source}): every depth would be x{1 / factor:.3g} ({'too near' if factor > 1 else 'too far'}); "
            f"declare depth_scale {implied:.0f} (intrinsics.json or --depth-scale) if the data is a Kinect's")


def _range_warning(median_m: float, near_m: float, units_per_m: float | None) -> str | None:
    """The line for depth no RGB-D camera's survey has (None when plausible): ``near_m`` is the
    frames' 10th percentile of valid depth, ``median_m`` their median."""
    read = "" if units_per_m is None else f" (read at {units_per_m:g} units per metre)"
    if near_m < NEAREST_SEEN_M:
        hint = ("; millimetres read at TUM's 5000 per metre are 5x too near: declare depth_scale 1000 (intrinsics.json "
                "or --depth-scale)" if units_per_m == 5000 else "")
        return (f"a tenth of the frames' depth is nearer than {NEAREST_SEEN_M} m (10th percentile {near_m:.3g} m, median "
                f"{median_m:.3g} m{read}): nearer than an RGB-D camera sees (a D435 from ~{NEAREST_SEEN_M} m, a Kinect "
                f"from 0.5 m){hint}")
    if median_m > FURTHEST_MEDIAN_M:
        hint = ("; TUM's 1/5000 m read as millimetres is 5x too far: declare depth_scale 5000" if units_per_m == 1000
                else "")
        return (f"the frames' median depth is {median_m:.3g} m{read}: further than an RGB-D camera measures a room"
                f"{hint}")
    return None


def inspect_depth_unit(sequence, frames: int = 5) -> DepthUnitLook | None:
    """Look at ``frames`` frames spread over ``sequence`` (no poses needed): their median depth
    against what RGB-D cameras see, and, where the source keeps its stored values
    (``raw_depth(i)`` and ``depth_units_per_m``), whether those show Kinect v1's depth steps at
    another unit than the one read. None when no frame could be read."""
    used = getattr(sequence, "depth_units_per_m", None)
    raw_of = getattr(sequence, "raw_depth", None) if used is not None else None
    source = getattr(sequence, "depth_scale_source", "the source's")
    medians, nears, implied = [], [], []
    for i in np.linspace(0, len(sequence) - 1, min(frames, len(sequence))).round().astype(int):
        try:
            if raw_of is not None:
                raw = np.asarray(raw_of(int(i)))
                valid = raw[(raw > 0) & (raw < 65535)].astype(float) / used
                implied.append(kinect_units_per_m(raw))
            else:
                depth = np.asarray(sequence[int(i)].depth_m, dtype=float)
                valid = depth[np.isfinite(depth) & (depth > 0)]
        except (DatasetError, OSError):
            continue
        if valid.size:
            medians.append(float(np.median(valid)))
            nears.append(float(np.percentile(valid, 10)))
    if not medians:
        return None
    median_m, near_m = float(np.median(medians)), float(np.median(nears))
    seen = [u for u in implied if u is not None]
    mixed = None
    if len(seen) >= 2 and not _near(max(seen), min(seen), 0.3):
        mixed = (f"{getattr(sequence, 'path', 'the sequence')}: the depth images are in different units (their Kinect "
                 f"steps say {min(seen):.0f} to {max(seen):.0f} units per metre over {len(seen)} frames): convert them "
                 "to one unit")
    lines = [_range_warning(median_m, near_m, used)]
    if seen and mixed is None:
        lines.append(_kinect_warning(float(np.median(seen)), float(used), str(source)))
    return DepthUnitLook(median_m, near_m, used, tuple(implied), tuple(line for line in lines if line), mixed)
