"""NAP3D: 3D-3D alignment of a rendered view to a real RGB-D frame.

Pipeline for one (real frame, rendered view) pair:

1. Feature matches (``matching.py``): the paper's SIFT with Lowe's ratio test (exact search
   by default, FLANN as an option, both deterministic), or XFeat's learned features.
2. Back-projection: rendered keypoints with the rendered z-depth and the view's intrinsics
   give ``x_i`` (rendered camera); real keypoints with the sensor depth and the frame's
   intrinsics give ``y_i`` (real camera). Pairs with missing depth, depth outside the valid
   range or low opacity are dropped.
3. RANSAC over minimal 3-point Kabsch hypotheses, vectorised over hypotheses, scored by the
   paper's anisotropic residual ``r^2 = |e_xy|^2/s_xy^2 + e_z^2/s_z^2`` in the real camera,
   ``s_z`` growing with depth like the sensor's noise; adaptive iteration count; the
   consensus is refit by opacity-weighted Umeyama until the inlier set settles.
4. ``method="plain"`` stops there (the paper's variant). ``method="refined"`` (default)
   then solves weighted least squares over each inlier's reprojection (pixels, in the real
   image) and depth residuals under their noise models, with Huber weights and per-group
   variance factors, so it uses the precise real keypoint position and the depth alike.
5. The 6x6 covariance of ``T_world_cam_true`` comes from the Gauss-Newton Hessian at the
   solution, scaled by the residual variance.

The stages live beside this module in ``nap3d_graph.nap3d``: ``config`` (settings),
``matching``, ``correspondences`` (back-projection, noise sigmas), ``ransac`` (rigid fits,
RANSAC) and ``refine`` (least squares and covariance); this module runs them for one pair
(``align_views``) and ``correct`` re-renders and iterates (``correct_pose``).
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace

import numpy as np

from ..camera import Intrinsics, RenderedView, RGBDFrame, backproject, project
from ..conventions import make_T
from ..results import Alignment
from .config import AlignConfig
from .correspondences import Correspondences, build_correspondences, noise_sigmas, subset
from .matching import Features, detect_features, match_features, refine_matches_subpixel
from .ransac import anisotropic_residual_sq, ransac_procrustes, ransac_scale
from .refine import consensus_cost, plain_covariance, refine_pose
from .rolling_shutter import RowMotion, to_mid_readout

__all__ = ["align_views", "align_correspondences", "prepare_correspondences", "view_features",
           "choose_intrinsics_model", "covariance_inflation", "inflate_rotation", "viewpoint_change_px"]

log = logging.getLogger(__name__)


# --- public API -----------------------------------------------------------------------------------


def align_correspondences(corr: Correspondences, intrinsics: Intrinsics, config: AlignConfig | None = None,
                          timings: dict | None = None) -> Alignment:
    """NAP3D on ready-made correspondences (rendered ``x``, real ``y``). Never raises.

    With ``estimate_intrinsics="auto"`` both camera models are fitted and the self-calibrated
    one is kept only when it explains the correspondences clearly better
    (:func:`choose_intrinsics_model`).
    """
    config = config or AlignConfig()
    if config.estimate_intrinsics == "auto" and config.method == "refined":
        fixed = align_correspondences(corr, intrinsics, replace(config, estimate_intrinsics=False), timings)
        calibrated = align_correspondences(corr, intrinsics, replace(config, estimate_intrinsics=True), {})
        return choose_intrinsics_model(corr, intrinsics, fixed, calibrated, config)
    timings = {} if timings is None else timings
    method = f"nap3d-{config.method}"
    n = len(corr)
    if corr.reason:
        return Alignment.failure(corr.reason, corr.num_matches, method=method, timings_s=timings)
    if n < config.min_matches:
        return Alignment.failure(f"too few matches with valid depth ({n} < {config.min_matches})",
                                 corr.num_matches, method=method, timings_s=timings)
    s_xy, s_z = noise_sigmas(corr, intrinsics, config)
    t0 = time.perf_counter()
    scale, scale_sigma = _depth_scale(corr, s_xy, s_z, config)
    if config.rescale_depth and np.isfinite(scale) and abs(scale - 1.0) > config.scale_tolerance:
        # The real depth's metre is not the field's: fit the pose to the rescaled points. When
        # that fit fails (a scale measured on a frame that matches badly), the fit as measured:
        # keeping it measured 15.4 -> 13.2 mm on a pose refinement, dropping it 14.0 mm.
        plain = replace(config, rescale_depth=False)
        again = align_correspondences(replace(corr, y=corr.y / scale), intrinsics, plain, timings)
        if again.success:
            residual = again.diagnostics.get("depth_scale", float("nan"))
            again.diagnostics["depth_scale"] = scale * residual if np.isfinite(residual) else scale
            return again
        config = plain
        t0 = time.perf_counter()
    weights = corr.opacity if config.opacity_weighting else np.ones(n)
    ransac = ransac_procrustes(corr.x, corr.y, weights, s_xy, s_z, config)
    timings["ransac"] = time.perf_counter() - t0
    if not ransac.success:
        return Alignment.failure(ransac.reason, corr.num_matches, method=method, timings_s=timings)
    inliers = ransac.inliers
    if inliers.sum() < config.min_inliers:
        return Alignment.failure(f"too few inliers ({int(inliers.sum())} < {config.min_inliers})",
                                 corr.num_matches, int(inliers.sum()), method=method, timings_s=timings)
    t0 = time.perf_counter()
    R, t = ransac.R, ransac.t
    diagnostics: dict = {}
    K_refined = intrinsics
    if config.method == "plain":
        cov = plain_covariance(R, t, corr.x[inliers], corr.y[inliers], weights[inliers], s_xy[inliers],
                               s_z[inliers]) * covariance_inflation(R, t, corr.y[inliers], intrinsics, config,
                                                                    plain=True)
        cov = inflate_rotation(cov, config.plain_rotation_inflation)
    else:
        refined = refine_pose(R, t, subset(corr, inliers), intrinsics, config, return_intrinsics=True)
        if refined is None:
            return Alignment.failure("degenerate geometry (singular refinement)", corr.num_matches,
                                     int(inliers.sum()), method=method, timings_s=timings)
        R, t, cov, _, K_refined, diagnostics = refined
        # The refined pose (and intrinsics) may admit points RANSAC's cruder estimate
        # rejected, or the reverse: re-select the inliers once and refine again.
        for _ in range(4 if config.estimate_intrinsics is True else 1):
            y = backproject(corr.uv_real, corr.y[:, 2], K_refined) if config.estimate_intrinsics is True else corr.y
            new_inliers = anisotropic_residual_sq(R, t, corr.x, y, 1 / s_xy**2, 1 / s_z**2) < config.inlier_chi2
            if new_inliers.sum() < config.min_inliers or np.array_equal(new_inliers, inliers):
                break
            again = refine_pose(R, t, subset(corr, new_inliers), intrinsics, config, return_intrinsics=True)
            if again is None:
                break
            inliers = new_inliers
            R, t, cov, _, K_refined, diagnostics = again
        cov = cov * covariance_inflation(R, t, corr.y[inliers], intrinsics, config)
        cov = inflate_rotation(cov, config.rotation_inflation, config.cross_covariance_scale)
    timings["refine"] = time.perf_counter() - t0
    if not np.all(np.isfinite(cov)) or np.min(np.linalg.eigvalsh(cov)) <= 0:
        return Alignment.failure("degenerate geometry (covariance not positive definite)", corr.num_matches,
                                 int(inliers.sum()), method=method, timings_s=timings)
    e = corr.x[inliers] @ R.T + t - corr.y[inliers]
    # The paper's Procrustes also gives a scale: the real depth's metre against the field's.
    diagnostics = dict(diagnostics)
    diagnostics["depth_scale"], diagnostics["depth_scale_sigma"] = scale, scale_sigma
    # The inlier matches' pixels, for display: the rendered keypoint is its 3D point projected.
    diagnostics["inlier_uv_real"] = corr.uv_real[inliers]
    diagnostics["inlier_uv_render"] = project(corr.x[inliers], intrinsics)[0]
    return Alignment(
        T_real_rendered=make_T(R, t),
        covariance=cov,
        num_matches=corr.num_matches,
        num_inliers=int(inliers.sum()),
        inlier_rmse_m=float(np.sqrt(np.mean(np.sum(e**2, axis=1)))),
        success=True,
        method=method,
        timings_s=timings,
        inlier_mask=inliers,
        diagnostics={**diagnostics, "intrinsics": K_refined.to_dict()} if config.estimate_intrinsics is True else diagnostics,
    )


def _depth_scale(corr: Correspondences, s_xy: np.ndarray, s_z: np.ndarray, config: AlignConfig) -> tuple[float, float]:
    """The real depth's scale against the field's and its sigma (similarity RANSAC)."""
    if not config.estimate_scale:
        return float("nan"), float("inf")
    return ransac_scale(corr.x, corr.y, s_xy, s_z, config)[:2]


def viewpoint_change_px(R: np.ndarray, t: np.ndarray, y_inliers: np.ndarray, intrinsics: Intrinsics) -> float:
    """Apparent motion (pixels) between the rendered and the real view: the correction's
    translation over the inliers' median depth plus its rotation angle, times the focal length."""
    angle = float(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))
    depth = max(float(np.median(y_inliers[:, 2])), 1e-3)
    return 0.5 * (intrinsics.fx + intrinsics.fy) * (float(np.linalg.norm(t)) / depth + angle)


def covariance_inflation(R: np.ndarray, t: np.ndarray, y_inliers: np.ndarray, intrinsics: Intrinsics,
                         config: AlignConfig, plain: bool = False) -> float:
    """The factor a covariance is multiplied by: it grows with the viewpoint change between
    the rendered and the real view, see :class:`AlignConfig` for the measurement behind it."""
    v = viewpoint_change_px(R, t, y_inliers, intrinsics)
    octaves = max(0.0, float(np.log2(intrinsics.width / 320.0)))
    if plain:
        return (config.plain_covariance_inflation + config.plain_covariance_inflation_per_px * v
                + config.plain_covariance_inflation_per_octave * octaves)
    return (config.covariance_inflation + config.covariance_inflation_per_px * v
            + config.covariance_inflation_per_octave * octaves)


def inflate_rotation(covariance: np.ndarray, factor: float, cross_scale: float = 1.0) -> np.ndarray:
    """``covariance`` (6, 6, GTSAM order) with its rotation block times ``factor`` (the cross
    terms times its square root, so the correlation is kept) and then the rotation-translation
    cross terms times ``cross_scale`` (1 keeps them; 0 leaves the two blocks uncorrelated)."""
    if factor == 1.0 and cross_scale == 1.0:
        return covariance
    d = np.array([np.sqrt(factor)] * 3 + [1.0] * 3)
    shaped = covariance * np.outer(d, d)
    shaped[:3, 3:] *= cross_scale
    shaped[3:, :3] *= cross_scale
    return shaped


def choose_intrinsics_model(corr: Correspondences, intrinsics: Intrinsics, fixed: Alignment,
                            calibrated: Alignment, config: AlignConfig) -> Alignment:
    """The fixed-intrinsics or the self-calibrated alignment, whichever the data support.

    Both are scored on *every* correspondence, not on their own inlier sets: with a badly
    wrong calibration RANSAC under the given intrinsics finds only a handful of consistent
    points, and a fit to those few looks as good as any (comparing each model's residuals on
    its own inliers picked it, and a 7-deg error, in Evaluation K's HARSH cells). The cost is
    the truncated whitened residual (:func:`~nap3d_graph.nap3d.refine.consensus_cost`) under
    one noise model, the self-calibrated fit's estimated variance factors (at least the
    nominal noise), so the comparison is a likelihood-ratio test: four extra parameters
    must lower the cost by ``config.auto_intrinsics_min_gain``; and they must explain
    ``config.auto_intrinsics_min_consensus`` times as many correspondences (see
    :class:`AlignConfig` for why real data need that too).
    """
    if not calibrated.success:
        return fixed
    if not fixed.success:
        calibrated.diagnostics["intrinsics_model"] = "calibrated (the fixed model failed)"
        return calibrated
    K_calibrated = Intrinsics.from_dict(calibrated.diagnostics["intrinsics"])
    scale_px = max(calibrated.diagnostics.get("pixel_variance_factor", 1.0), 1.0)
    scale_z = max(calibrated.diagnostics.get("depth_variance_factor", 1.0), 1.0)
    cost_fixed, inliers_fixed = consensus_cost(fixed.T_real_rendered[:3, :3], fixed.T_real_rendered[:3, 3], corr,
                                               intrinsics, config, scale_px, scale_z)
    cost_cal, inliers_cal = consensus_cost(calibrated.T_real_rendered[:3, :3], calibrated.T_real_rendered[:3, 3],
                                           corr, K_calibrated, config, scale_px, scale_z)
    gain = cost_fixed - cost_cal
    supported = gain > config.auto_intrinsics_min_gain and \
        inliers_cal >= config.auto_intrinsics_min_consensus * inliers_fixed
    chosen = calibrated if supported else fixed
    chosen.diagnostics.update({
        "intrinsics_model": "calibrated" if chosen is calibrated else "fixed",
        "intrinsics_cost_gain": float(gain),
        "consensus_fixed": inliers_fixed,
        "consensus_calibrated": inliers_cal,
    })
    return chosen


def prepare_correspondences(real: RGBDFrame, view: RenderedView, config: AlignConfig | None = None,
                            timings: dict | None = None, feats_real: Features | None = None,
                            feats_view: Features | None = None,
                            motion: RowMotion | None = None) -> tuple[Correspondences | None, str]:
    """Features, matches and back-projection for one pair: ``(correspondences, "")`` or
    ``(None, reason)``. NAP3D and the PnP baseline both start from this, so an evaluation
    compares them on the very same matches. Features already computed for an image can be
    passed in (``feats_real``, ``feats_view``) to skip detecting them again. ``motion``: the
    real camera's motion while a rolling shutter read its rows; the real points are moved to
    the middle row's instant (:mod:`~nap3d_graph.nap3d.rolling_shutter`)."""
    config = config or AlignConfig()
    timings = {} if timings is None else timings
    t0 = time.perf_counter()
    if feats_real is None:
        feats_real = detect_features(real.rgb, config.max_features, matcher=config.matcher)
    if feats_view is None:
        feats_view = view_features(view, config)
    timings["detect"] = time.perf_counter() - t0
    if len(feats_real) < 3:
        return None, "no keypoints in the real image"
    if len(feats_view) < 3:
        return None, "no keypoints in the rendered view"
    t0 = time.perf_counter()
    matches = match_features(feats_real, feats_view, ratio=config.ratio, mutual=config.mutual,
                             nn_search=config.nn_search)
    if config.subpixel:
        matches = refine_matches_subpixel(real.rgb, view.rgb, matches)
    timings["match"] = time.perf_counter() - t0
    if len(matches) < config.min_matches:
        return None, f"too few matches ({len(matches)} < {config.min_matches})"
    corr = build_correspondences(real, view, matches, config)
    if corr.reason:
        return None, corr.reason
    if motion is not None:
        corr = to_mid_readout(corr, motion, real.intrinsics)
    return corr, ""


def view_features(view: RenderedView, config: AlignConfig | None = None) -> Features:
    """Features of a rendered view (``config.matcher``'s), only where the field is opaque."""
    config = config or AlignConfig()
    return detect_features(view.rgb, config.max_features, mask=view.opacity >= config.min_opacity,
                           matcher=config.matcher)


def align_views(real: RGBDFrame, view: RenderedView, config: AlignConfig | None = None,
                feats_real: Features | None = None, feats_view: Features | None = None,
                motion: RowMotion | None = None) -> Alignment:
    """NAP3D between a real RGB-D frame and the view a field rendered at the believed pose.

    Returns an :class:`Alignment` whose ``T_real_rendered`` maps rendered-camera points into
    the real camera; ``success=False`` with a ``reason`` on bad data. Never raises on data.
    ``feats_real``, ``feats_view``: the real frame's and the view's features
    (``config.matcher``'s, the view's by :func:`view_features`), when already detected.
    ``motion``: the real camera's twist and its rolling shutter's readout time, to align the
    real points as of the middle row (None: the frame is taken as one instant).
    """
    config = config or AlignConfig()
    method = f"nap3d-{config.method}"
    timings: dict = {}
    try:
        corr, reason = prepare_correspondences(real, view, config, timings, feats_real=feats_real,
                                               feats_view=feats_view, motion=motion)
        if corr is None:
            return Alignment.failure(reason, method=method, timings_s=timings)
        return align_correspondences(corr, real.intrinsics, config, timings)
    except (ValueError, np.linalg.LinAlgError) as exc:  # numerical trouble is a failed alignment, not a crash
        log.warning("alignment failed: %s", exc)
        return Alignment.failure(f"numerical failure: {exc}", method=method, timings_s=timings)
