"""PnP-RANSAC baseline (the paper's 2D-3D comparison) on the same matches as NAP3D.

3D points come from the rendered depth (rendered camera), 2D points are the real
keypoints; ``cv2.solvePnPRansac`` then ``cv2.solvePnPRefineLM`` on its inliers. The result is
an :class:`Alignment` like NAP3D's, with the covariance from the reprojection Hessian.

``estimate_intrinsics`` gives PnP the same help the self-calibrating NAP3D has: after the LM
step, the pose *and* the real camera's fx, fy, cx, cy are refined on the reprojection
residuals under the same prior (``"auto"``: kept only when the data support it, by the same
test as NAP3D's, :func:`~nap3d_graph.nap3d.align.choose_intrinsics_model`, on pixels only;
True: kept at every frame, the PnP at its best where the given calibration is wrong).
Evaluation K compares each NAP3D variant with the PnP that had the same help, and the
self-calibrating NAP3D also with the PnP that always calibrates.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace

import numpy as np

from ..camera import Intrinsics, RenderedView, RGBDFrame
from ..conventions import make_T
from ..nap3d.align import prepare_correspondences
from ..nap3d.config import AlignConfig
from ..nap3d.correspondences import Correspondences, subset
from ..nap3d.refine import consensus_cost, refine_pose
from ..results import Alignment

__all__ = ["PnPConfig", "pnp_align", "pnp_from_correspondences"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PnPConfig:
    reprojection_error_px: float = 3.0
    iterations: int = 1000
    confidence: float = 0.999
    min_inliers: int = 8


def pnp_from_correspondences(corr: Correspondences, intrinsics: Intrinsics, config: PnPConfig | None = None,
                             align_config: AlignConfig | None = None, timings: dict | None = None,
                             estimate_intrinsics: bool | str = False) -> Alignment:
    """PnP-RANSAC with the rendered 3D points ``corr.x`` and real pixels ``corr.uv_real``.

    ``estimate_intrinsics``: False (the paper's baseline, method ``"pnp-ransac"``), True
    (also refine the real camera's intrinsics at every call, ``"pnp-calibrated"``; its
    diagnostics' ``intrinsics_model`` is ``"calibrated"``, or ``"fixed (the calibration
    failed)"`` where the joint refinement was singular) or ``"auto"`` (``"pnp-selfcal"``:
    calibrated only when the data call for it, see the module docstring).
    """
    import cv2

    config = config or PnPConfig()
    align_config = align_config or AlignConfig()
    timings = {} if timings is None else timings
    method = {False: "pnp-ransac", True: "pnp-calibrated"}.get(estimate_intrinsics, "pnp-selfcal")
    n = len(corr)
    if n < max(4, config.min_inliers):
        return Alignment.failure(f"too few matches with valid depth ({n})", corr.num_matches, method=method,
                                 timings_s=timings)
    t0 = time.perf_counter()
    cv2.setRNGSeed(align_config.seed)  # OpenCV's RANSAC sampling: reproducible runs
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(
        corr.x.astype(np.float64), corr.uv_real.astype(np.float64), intrinsics.K, None,
        iterationsCount=config.iterations, reprojectionError=config.reprojection_error_px,
        confidence=config.confidence, flags=cv2.SOLVEPNP_EPNP)
    if not ok or inliers is None or len(inliers) < config.min_inliers:
        found = 0 if inliers is None else len(inliers)
        return Alignment.failure(f"too few inliers ({found})", corr.num_matches, found, method=method,
                                 timings_s=timings)
    mask = np.zeros(n, bool)
    mask[inliers.ravel()] = True
    rvec, tvec = cv2.solvePnPRefineLM(corr.x[mask], corr.uv_real[mask], intrinsics.K, None, rvec, tvec)
    R = cv2.Rodrigues(rvec)[0]
    t = tvec.ravel()
    timings["pnp"] = time.perf_counter() - t0
    # Covariance from the reprojection residuals only (what PnP uses), same parameterisation.
    fixed_config = replace(align_config, estimate_intrinsics=False)
    refined = refine_pose(R, t, subset(corr, mask), intrinsics, fixed_config, use_depth=False)
    cov = refined[2] if refined is not None else np.full((6, 6), np.inf)
    fixed = _pnp_alignment(corr, R, t, cov, mask, method, timings)
    if estimate_intrinsics is False:
        return fixed
    calibrated = _pnp_with_intrinsics(corr, intrinsics, R, t, mask, config, align_config, method, timings)
    if calibrated is None:
        fixed.diagnostics["intrinsics_model"] = "fixed (the calibration failed)"
        return fixed
    if estimate_intrinsics is True:
        calibrated.diagnostics["intrinsics_model"] = "calibrated"
        return calibrated
    return _choose_pnp_model(corr, intrinsics, fixed, calibrated, align_config)


def _pnp_alignment(corr, R, t, cov, mask, method, timings, diagnostics=None) -> Alignment:
    e = corr.x[mask] @ R.T + t - corr.y[mask]
    return Alignment(T_real_rendered=make_T(R, t), covariance=cov, num_matches=corr.num_matches,
                     num_inliers=int(mask.sum()), inlier_rmse_m=float(np.sqrt(np.mean(np.sum(e**2, axis=1)))),
                     success=True, method=method, timings_s=timings, inlier_mask=mask,
                     diagnostics=diagnostics or {})


def _pnp_with_intrinsics(corr, intrinsics, R, t, mask, config, align_config, method, timings):
    """Pose and intrinsics refined together on the reprojection residuals, inliers
    re-selected under the refined camera until they settle; None if singular."""
    calib_config = replace(align_config, estimate_intrinsics=True)
    result = None
    for _ in range(4):
        refined = refine_pose(R, t, subset(corr, mask), intrinsics, calib_config, use_depth=False,
                              return_intrinsics=True)
        if refined is None:
            break
        R, t, cov, _, K_refined, diagnostics = refined
        result = (R, t, cov, mask, K_refined, diagnostics)
        p = corr.x @ R.T + t
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.stack([K_refined.fx * p[:, 0] / p[:, 2] + K_refined.cx, K_refined.fy * p[:, 1] / p[:, 2] + K_refined.cy], 1)
        new_mask = (p[:, 2] > 0) & (np.linalg.norm(uv - corr.uv_real, axis=1) < config.reprojection_error_px)
        if new_mask.sum() < config.min_inliers or np.array_equal(new_mask, mask):
            break
        mask = new_mask
    if result is None:
        return None
    R, t, cov, mask, K_refined, diagnostics = result
    return _pnp_alignment(corr, R, t, cov, mask, method, timings,
                          {**diagnostics, "intrinsics": K_refined.to_dict()})


def _choose_pnp_model(corr, intrinsics, fixed: Alignment, calibrated: Alignment, align_config: AlignConfig):
    """NAP3D's test on the pixels only: the cost over all correspondences must drop by the
    likelihood-ratio margin and the consensus grow by the same factor."""
    K_calibrated = Intrinsics.from_dict(calibrated.diagnostics["intrinsics"])
    scale = max(calibrated.diagnostics.get("pixel_variance_factor", 1.0), 1.0)
    cost_f, n_f = consensus_cost(fixed.T_real_rendered[:3, :3], fixed.T_real_rendered[:3, 3], corr, intrinsics,
                                 align_config, scale, use_depth=False)
    cost_c, n_c = consensus_cost(calibrated.T_real_rendered[:3, :3], calibrated.T_real_rendered[:3, 3], corr,
                                 K_calibrated, align_config, scale, use_depth=False)
    supported = cost_f - cost_c > align_config.auto_intrinsics_min_gain and \
        n_c >= align_config.auto_intrinsics_min_consensus * n_f
    chosen = calibrated if supported else fixed
    chosen.diagnostics.update({"intrinsics_model": "calibrated" if supported else "fixed",
                               "intrinsics_cost_gain": float(cost_f - cost_c), "consensus_fixed": n_f,
                               "consensus_calibrated": n_c})
    return chosen


def pnp_align(real: RGBDFrame, view: RenderedView, config: PnPConfig | None = None,
              align_config: AlignConfig | None = None, estimate_intrinsics: bool | str = False) -> Alignment:
    """PnP-RANSAC between a real frame and a rendered view (same matching as NAP3D)."""
    timings: dict = {}
    try:
        corr, reason = prepare_correspondences(real, view, align_config, timings)
        if corr is None:
            return Alignment.failure(reason, method="pnp-ransac", timings_s=timings)
        return pnp_from_correspondences(corr, real.intrinsics, config, align_config, timings, estimate_intrinsics)
    except (ValueError, np.linalg.LinAlgError, Exception) as exc:  # cv2.error is not a ValueError
        log.warning("PnP failed: %s", exc)
        return Alignment.failure(f"numerical failure: {exc}", method="pnp-ransac", timings_s=timings)
