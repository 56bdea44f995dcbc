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

__all__ = ["DepthUnitCheck", "check_depth_unit", "UNIT_MISTAKES"]

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
