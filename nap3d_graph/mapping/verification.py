"""What an alignment must reach to be believed: one rule for the survey's loops
(:mod:`.loops`) and for relocalisation (:mod:`.relocalise`), each with its own thresholds."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Verification", "worst_sigmas"]


def worst_sigmas(covariance: np.ndarray) -> tuple[float, float]:
    """``(sigma_m, sigma_deg)``: the largest standard deviation of a (6, 6) pose covariance's
    translation block and of its rotation block (GTSAM order: rotation first), in metres
    and degrees; inf or NaN where the covariance is."""
    cov = np.asarray(covariance, dtype=float)
    sigma_m = float(np.sqrt(np.max(np.linalg.eigvalsh(cov[3:, 3:]))))
    sigma_deg = float(np.degrees(np.sqrt(np.max(np.linalg.eigvalsh(cov[:3, :3])))))
    return sigma_m, sigma_deg


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
