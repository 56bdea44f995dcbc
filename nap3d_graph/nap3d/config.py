"""Settings of one NAP3D alignment (noise models, RANSAC, refinement)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..camera import DEPTH_SIGMA_Z2_PER_M
from .matching import MATCHERS, NN_SEARCHES

#: XFeat's covariance inflation over SIFT's (refined and the paper's plain estimator).
XFEAT_INFLATION = 1.46
XFEAT_PLAIN_INFLATION = 1.74

__all__ = ["AlignConfig", "MATCHER_NOISE", "FROM_MATCHER"]

#: A noise setting left to the matcher's own value (``MATCHER_NOISE``).
FROM_MATCHER = math.nan

_SIFT_NOISE = {
    "keypoint_sigma_px": 0.7,
    "covariance_inflation": 1.2485, "covariance_inflation_per_px": 0.0097, "covariance_inflation_per_octave": 0.2569,
    "plain_covariance_inflation": 1.2637, "plain_covariance_inflation_per_px": 0.0081,
    "plain_covariance_inflation_per_octave": 0.0829,
    "rotation_inflation": 1.0, "plain_rotation_inflation": 1.0, "cross_covariance_scale": 1.0,
}

#: Each matcher's keypoint noise and covariance inflation (see ``AlignConfig``), fitted on the
#: simulator's calibration rooms 21 and 22 only. XFeat localises a keypoint to a pixel (its
#: detector works on 8x8 cells), SIFT to a fraction of one: between a real frame and the exact
#: render, the matched pixels disagree by 0.49 px RMS with SIFT and 1.68 px with XFeat (320x240,
#: 24 frames). Its keypoint sigma stays SIFT's all the same: the refinement estimates each
#: residual group's variance, so the sigma mostly sets RANSAC's inlier threshold, and the
#: measured 2.4 px let in worse inliers (pose NEES 16 -> 20). The residuals still under-state
#: XFeat's error, more in rotation than in translation (block NEES 6.5 and 4.4 against 3 with
#: SIFT's inflation, ``benchmarks/covariance.py --rooms 21 22 --trials 40 --configs pipeline
#: --matcher xfeat``): its inflation is SIFT's times one factor for the translation and another
#: on top for the rotation block (``rotation_inflation``), which puts both blocks at 3.0 on the
#: calibration rooms, and the pose NEES at 8.6 (refined): the refinement's covariance couples
#: rotation and translation errors much more than XFeat's errors are coupled (its pose NEES
#: falls to 4.3 with the cross terms at 0.8 of their value). The refined covariance keeps the
#: two blocks uncorrelated (``cross_covariance_scale`` 0), which puts the pose NEES at 6.0 on
#: the calibration rooms. The plain estimator keeps its cross terms and a common factor of 1.2
#: over its block fit (blocks 2.5, pose 7.7). LighterGlue pairs the same keypoints.
MATCHER_NOISE: dict[str, dict[str, float]] = {
    "sift": _SIFT_NOISE,
    "xfeat": {"keypoint_sigma_px": 0.7,
              **{k: v * XFEAT_INFLATION for k, v in _SIFT_NOISE.items() if k.startswith("covariance")},
              **{k: v * XFEAT_PLAIN_INFLATION for k, v in _SIFT_NOISE.items() if k.startswith("plain_cov")},
              "rotation_inflation": 1.5, "plain_rotation_inflation": 1.79, "cross_covariance_scale": 0.0},
}
MATCHER_NOISE["xfeat-lighterglue"] = MATCHER_NOISE["xfeat"]


@dataclass(frozen=True)
class AlignConfig:
    """Settings of one alignment. Noise sigmas describe the *real* sensor and the field.

    opacity_weighting: weigh each correspondence by the field's opacity at its rendered pixel
        in the Procrustes fits (the paper's choice; False: all alike, for comparison).
    estimate_scale, rescale_depth, scale_tolerance: the real depth's scale against the
        field's is measured by a RANSAC over similarity transforms (the paper's Procrustes
        has a scale) and reported (``diagnostics["depth_scale"]`` and its sigma), so a
        caller can refuse a frame whose scale disagrees, or rescale its depth and align
        again (the pipeline does both). With ``rescale_depth`` the real points are rescaled
        here before the rigid fit when the scale differs from 1 by more than
        ``scale_tolerance``; off by default, because a wrong focal length also looks like a
        scale to a similarity fit.
    matcher: what finds and pairs the pixels: "sift" (the paper's SIFT with Lowe's ratio
        test), "xfeat" (XFeat, mutual nearest neighbours) or "xfeat-lighterglue" (XFeat
        matched by LighterGlue); see ``matching.py``.
    subpixel: move each match's real pixel to where the rendered keypoint's patch fits best
        (Lucas-Kanade, ``matching.refine_matches_subpixel``) before the back-projection.
    nn_search: SIFT's nearest-neighbour search, "exact" (brute-force 2-NN, default) or "flann"
        (single kd-tree); both are deterministic (see ``matching.py`` for why FLANN's
        randomised trees are not used).
    keypoint_sigma_px: localisation noise of one SIFT keypoint (pixels).
    depth_sigma_floor_m + depth_sigma_z2_per_m * z^2: the real depth noise at z-depth z.
    render_depth_sigma_m: error of the field's depth (0.5 cm for a well-trained field).
    inlier_chi2: RANSAC threshold on r^2 (3 dof; 11.34 is chi2(3) at 99%).
    covariance: "hessian" (Gauss-Newton Hessian with estimated variance factors) or
        "sandwich" (heteroscedasticity-consistent; for diagnostics).
    estimate_intrinsics: True: also estimate the real camera's fx, fy, cx, cy in the refinement
        (self-calibration against the field's exact 3D points: the depth residuals fix the
        pose, the pixels the intrinsics), with a prior of ``intrinsics_focal_sigma``
        (relative) and ``intrinsics_principal_sigma_px``. For cameras whose calibration
        drifted (the paper's intrinsics noise); the pose covariance then includes the
        intrinsics' uncertainty. "auto": fit both and keep the self-calibrated solution
        only when the data call for it: its truncated cost over *all* correspondences (the
        same noise model for both) must be lower by ``auto_intrinsics_min_gain``, a
        likelihood-ratio test for four extra parameters (18.5 = chi2(4) at 99.9%), *and* it
        must explain ``auto_intrinsics_min_consensus`` times as many correspondences. The
        second test is what real data need: between two real fr1/xyz frames (one camera,
        so the intrinsics are right by construction) the extra parameters absorb unmodelled
        errors, lower the cost by 17-140 and move cy by 12 px and the rotation by up to 1
        deg, but explain at most 3% more correspondences; a wrong calibration (the
        paper's MILD shift upwards) leaves the fixed model 1.3 to 12 times fewer.
    covariance_inflation, covariance_inflation_per_px, covariance_inflation_per_octave: the
        refined covariance is multiplied by ``covariance_inflation + covariance_inflation_per_px
        * v + covariance_inflation_per_octave * log2(width / 320)``: ``v`` is the viewpoint
        change between the two views in pixels of apparent motion (``f (|t| / z + angle)``,
        ``z`` the inliers' median depth), ``width`` the real image's (at least 320). Why:
        residuals cannot show the part of SIFT's localisation error that the real and the
        rendered keypoint share (the same texture seen from elsewhere and resampled), and
        that part grows with the viewpoint change and, in pixels, with the resolution.
        Fitted to the NEES of one render-align round on simulated rooms 21 and 22 only
        (exact field, Kinect-like sensor noise; 320x240 and 640x480; the estimate +-3 mm /
        0.15 deg to +-10 cm / 5 deg off; 120-160 trials per level): without it the NEES was
        1.25-1.5 times the chi2(6) mean at 320x240 and 1.45-2.2 at 640x480; with it
        0.92-1.08 at every level (per 3-dof block 0.84-1.12). Rendered at exactly the real
        pose (never the case in use) it is 0.72: conservative there. The rooms the tests (11)
        and the benchmarks (31-35) use never entered it.
    plain_covariance_inflation, plain_covariance_inflation_per_px,
    plain_covariance_inflation_per_octave: the same for the plain (paper's) estimator's
        sandwich covariance: 1.25-1.9 times the chi2(6) mean without it on the same trials,
        0.93-1.06 with it.
        rotation_inflation, plain_rotation_inflation: a further factor on the rotation block only
        (1 for SIFT), for matchers whose residuals under-state the rotation more than the
        translation.
    cross_covariance_scale: the refined covariance's rotation-translation cross terms are
        multiplied by it (1 for SIFT; 0 for XFeat, whose errors are far less coupled than its
        residuals say). Every noise field left unset (``FROM_MATCHER``, NaN; None is taken
        as unset too) takes its matcher's value from ``MATCHER_NOISE``.
    """

    method: str = "refined"
    matcher: str = "sift"
    nn_search: str = "exact"
    subpixel: bool = False
    opacity_weighting: bool = True
    estimate_scale: bool = True
    rescale_depth: bool = False
    scale_tolerance: float = 0.004
    ratio: float = 0.8
    mutual: bool = False
    max_features: int = 0
    min_matches: int = 8
    min_inliers: int = 8
    min_opacity: float = 0.5
    min_depth_m: float = 0.1
    max_depth_m: float = 10.0
    keypoint_sigma_px: float = FROM_MATCHER
    depth_sigma_floor_m: float = 0.002
    depth_sigma_z2_per_m: float = DEPTH_SIGMA_Z2_PER_M
    render_depth_sigma_m: float = 0.005
    inlier_chi2: float = 11.34
    ransac_confidence: float = 0.999
    ransac_max_iterations: int = 2000
    ransac_batch: int = 128
    min_sample_side_m: float = 0.03
    min_sample_sine: float = 0.1
    refine_iterations: int = 8
    huber_k: float = 2.5
    covariance: str = "hessian"
    covariance_inflation: float = FROM_MATCHER
    covariance_inflation_per_px: float = FROM_MATCHER
    covariance_inflation_per_octave: float = FROM_MATCHER
    plain_covariance_inflation: float = FROM_MATCHER
    plain_covariance_inflation_per_px: float = FROM_MATCHER
    plain_covariance_inflation_per_octave: float = FROM_MATCHER
    rotation_inflation: float = FROM_MATCHER
    cross_covariance_scale: float = FROM_MATCHER
    plain_rotation_inflation: float = FROM_MATCHER
    estimate_intrinsics: bool | str = "auto"
    auto_intrinsics_min_gain: float = 18.5
    auto_intrinsics_min_consensus: float = 1.2
    intrinsics_focal_sigma: float = 0.05
    intrinsics_principal_sigma_px: float = 10.0
    seed: int = 0

    def __post_init__(self) -> None:
        if self.method not in ("refined", "plain"):
            raise ValueError(f"AlignConfig.method must be 'refined' or 'plain', got {self.method!r}")
        if self.matcher not in MATCHERS:
            raise ValueError(f"AlignConfig.matcher must be one of {', '.join(MATCHERS)}, got {self.matcher!r}")
        if self.nn_search not in NN_SEARCHES:
            raise ValueError(f"AlignConfig.nn_search must be 'exact' or 'flann', got {self.nn_search!r}")
        # The matcher's own noise model wherever the caller left a value unset.
        for name, value in MATCHER_NOISE[self.matcher].items():
            if getattr(self, name) is None or math.isnan(getattr(self, name)):
                object.__setattr__(self, name, value)
        if self.min_inliers < 3 or self.min_matches < 3:
            raise ValueError("min_matches and min_inliers must be at least 3")
