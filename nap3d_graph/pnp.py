"""PnP-RANSAC baseline (the paper's 2D-3D comparison) on the same matches as NAP3D.

3D points come from the rendered depth (rendered camera), 2D points are the real
keypoints; ``cv2.solvePnPRansac`` then ``cv2.solvePnPRefineLM`` on its inliers. The result is
an :class:`Alignment` like NAP3D's, with the covariance from the reprojection Hessian.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from .alignment import AlignConfig, Correspondences, prepare_correspondences, refine_pose
from .correspondences import subset
from .camera import Intrinsics, RenderedView, RGBDFrame
from .conventions import make_T
from .results import Alignment

__all__ = ["PnPConfig", "pnp_align", "pnp_from_correspondences"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PnPConfig:
    reprojection_error_px: float = 3.0
    iterations: int = 1000
    confidence: float = 0.999
    min_inliers: int = 8


def pnp_from_correspondences(corr: Correspondences, intrinsics: Intrinsics, config: PnPConfig | None = None,
                             align_config: AlignConfig | None = None, timings: dict | None = None) -> Alignment:
    """PnP-RANSAC with the rendered 3D points ``corr.x`` and real pixels ``corr.uv_real``."""
    import cv2

    config = config or PnPConfig()
    align_config = align_config or AlignConfig()
    timings = {} if timings is None else timings
    n = len(corr)
    if n < max(4, config.min_inliers):
        return Alignment.failure(f"too few matches with valid depth ({n})", corr.num_matches, method="pnp-ransac",
                                 timings_s=timings)
    t0 = time.perf_counter()
    cv2.setRNGSeed(align_config.seed)  # OpenCV's RANSAC sampling: reproducible runs
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(
        corr.x.astype(np.float64), corr.uv_real.astype(np.float64), intrinsics.K, None,
        iterationsCount=config.iterations, reprojectionError=config.reprojection_error_px,
        confidence=config.confidence, flags=cv2.SOLVEPNP_EPNP)
    if not ok or inliers is None or len(inliers) < config.min_inliers:
        found = 0 if inliers is None else len(inliers)
        return Alignment.failure(f"too few inliers ({found})", corr.num_matches, found, method="pnp-ransac",
                                 timings_s=timings)
    mask = np.zeros(n, bool)
    mask[inliers.ravel()] = True
    rvec, tvec = cv2.solvePnPRefineLM(corr.x[mask], corr.uv_real[mask], intrinsics.K, None, rvec, tvec)
    R = cv2.Rodrigues(rvec)[0]
    t = tvec.ravel()
    timings["pnp"] = time.perf_counter() - t0
    # Covariance from the reprojection residuals only (what PnP uses), same parameterisation.
    refined = refine_pose(R, t, subset(corr, mask), intrinsics, align_config, use_depth=False)
    cov = refined[2] if refined is not None else np.full((6, 6), np.inf)
    e = corr.x[mask] @ R.T + t - corr.y[mask]
    return Alignment(T_real_rendered=make_T(R, t), covariance=cov, num_matches=corr.num_matches,
                     num_inliers=int(mask.sum()), inlier_rmse_m=float(np.sqrt(np.mean(np.sum(e**2, axis=1)))),
                     success=True, method="pnp-ransac", timings_s=timings, inlier_mask=mask)


def pnp_align(real: RGBDFrame, view: RenderedView, config: PnPConfig | None = None,
              align_config: AlignConfig | None = None) -> Alignment:
    """PnP-RANSAC between a real frame and a rendered view (same matching as NAP3D)."""
    timings: dict = {}
    try:
        corr, reason = prepare_correspondences(real, view, align_config, timings)
        if corr is None:
            return Alignment.failure(reason, method="pnp-ransac", timings_s=timings)
        return pnp_from_correspondences(corr, real.intrinsics, config, align_config, timings)
    except (ValueError, np.linalg.LinAlgError, Exception) as exc:  # cv2.error is not a ValueError
        log.warning("PnP failed: %s", exc)
        return Alignment.failure(f"numerical failure: {exc}", method="pnp-ransac", timings_s=timings)
