"""What an alignment must reach to be believed: one rule for the survey's loops
(:mod:`.loops`) and for relocalisation (:mod:`.relocalise`), each with its own thresholds."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Verification", "worst_sigmas", "depth_disagreement", "DEPTH_DISAGREEMENT_BAD"]


def worst_sigmas(covariance: np.ndarray) -> tuple[float, float]:
    """``(sigma_m, sigma_deg)``: the largest standard deviation of a (6, 6) pose covariance's
    translation block and of its rotation block (GTSAM order: rotation first), in metres
    and degrees; inf or NaN where the covariance is."""
    cov = np.asarray(covariance, dtype=float)
    sigma_m = float(np.sqrt(np.max(np.linalg.eigvalsh(cov[3:, 3:]))))
    sigma_deg = float(np.degrees(np.sqrt(np.max(np.linalg.eigvalsh(cov[:3, :3])))))
    return sigma_m, sigma_deg


#: A view whose depth disagrees with the field's render over more than this share of the frame is
#: not of the place the render is (a doorway where a twin room has a wall; chosen on the tests' floor).
DEPTH_DISAGREEMENT_BAD = 0.08


def depth_disagreement(depth_m: np.ndarray, rendered_depth_m: np.ndarray, opacity: np.ndarray,
                       tolerance_m: float = 0.25, tolerance_fraction: float = 0.1) -> float:
    """The share of a frame (H, W: the sensor's depth, the field's depth and opacity rendered at
    the pose under test, metres) where both have depth and they differ by more than
    ``tolerance_m`` or ``tolerance_fraction`` of the depth, whichever is larger: features can
    align on the walls and furniture two look-alike rooms share while a doorway one of them has
    and the other does not stays out of the matches; the depth of the whole view does not.
    NaN when no pixel has both."""
    real = np.asarray(depth_m, dtype=float)
    rendered = np.asarray(rendered_depth_m, dtype=float)
    both = np.isfinite(real) & (real > 0) & np.isfinite(rendered) & (rendered > 0) & (np.asarray(opacity) > 0.5)
    if not both.any():
        return float("nan")
    gap = np.abs(real[both] - rendered[both])
    return float(np.mean(gap > np.maximum(tolerance_m, tolerance_fraction * real[both])))


@dataclass(frozen=True)
class Verification:
    """An alignment is verified when it has at least ``min_inliers`` inliers and its
    covariance's worst sigmas (:func:`worst_sigmas`) are within ``max_sigma_m`` metres and
    ``max_sigma_deg`` degrees."""

    min_inliers: int
    max_sigma_m: float
    max_sigma_deg: float

    def refusal(self, inliers: int, sigma_m: float, sigma_deg: float) -> str:
        """Why an alignment is not verified, in a few words; "" when it is (a NaN sigma is
        never verified)."""
        if inliers < self.min_inliers:
            return f"{inliers} inliers < {self.min_inliers}"
        if not sigma_m <= self.max_sigma_m:
            return f"translation sigma {sigma_m * 100:.1f} cm > {self.max_sigma_m * 100:.1f} cm"
        if not sigma_deg <= self.max_sigma_deg:
            return f"rotation sigma {sigma_deg:.2f} deg > {self.max_sigma_deg} deg"
        return ""
