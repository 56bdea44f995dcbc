"""The hand-written maths of the NAP3D refinement: Jacobians against finite differences,
the perturbation convention against GTSAM, and the covariance against Monte-Carlo scatter
on synthetic correspondences whose noise is exactly the model's."""

import gtsam
import numpy as np
import pytest
from scipy.stats import chi2

from nap3d_graph.camera import Intrinsics, backproject, project
from nap3d_graph.conventions import T_to_pose3, exp_se3, inv_T, log_se3, make_T, pose3_to_T
from nap3d_graph.nap3d.config import AlignConfig
from nap3d_graph.nap3d.correspondences import Correspondences
from nap3d_graph.nap3d.refine import (
    _intrinsics_jacobian,
    _with_intrinsics_delta,
    consensus_cost,
    point_jacobian,
    refine_pose,
    reprojection_terms,
    stack_rows,
)

K = Intrinsics(262.5, 260.0, 159.5, 121.0, 320, 240)


def _points(rng, n):
    return np.c_[rng.uniform(-1.5, 1.5, n), rng.uniform(-1.0, 1.0, n), rng.uniform(1.0, 4.0, n)]


def _moved(T, x, delta):
    """Points x (rendered camera) in the real camera after the right perturbation ``delta`` of
    the corrected pose, i.e. T_real_rendered <- Exp(-delta) T_real_rendered."""
    T_new = exp_se3(-np.asarray(delta)) @ T
    return x @ T_new[:3, :3].T + T_new[:3, 3]


def test_point_and_reprojection_jacobians_match_finite_differences():
    rng = np.random.default_rng(0)
    x = _points(rng, 20)
    T = exp_se3([0.05, -0.03, 0.02, 0.1, -0.05, 0.08])
    p = x @ T[:3, :3].T + T[:3, 3]
    J_point = point_jacobian(p)
    res0, J_pix = reprojection_terms(p, np.zeros((20, 2)), K)
    eps = 1e-6
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps
        p_plus, p_minus = _moved(T, x, d), _moved(T, x, -d)
        numeric_point = (p_plus - p_minus) / (2 * eps)
        np.testing.assert_allclose(J_point[:, :, k], numeric_point, atol=1e-7)
        r_plus, _ = reprojection_terms(p_plus, np.zeros((20, 2)), K)
        r_minus, _ = reprojection_terms(p_minus, np.zeros((20, 2)), K)
        np.testing.assert_allclose(J_pix[:, :, k], (r_plus - r_minus) / (2 * eps), rtol=1e-5, atol=1e-5)
    # The residual itself is the projection minus the keypoint.
    uv, _ = project(p, K)
    np.testing.assert_allclose(res0, uv, atol=1e-9)


def test_intrinsics_jacobian_matches_finite_differences():
    rng = np.random.default_rng(1)
    p = _points(rng, 15)
    J = _intrinsics_jacobian(p)
    eps = 1e-5
    for k in range(4):
        d = np.zeros(4)
        d[k] = eps
        r_plus, _ = reprojection_terms(p, np.zeros((15, 2)), _with_intrinsics_delta(K, d))
        r_minus, _ = reprojection_terms(p, np.zeros((15, 2)), _with_intrinsics_delta(K, -d))
        np.testing.assert_allclose(J[:, :, k], (r_plus - r_minus) / (2 * eps), rtol=1e-6, atol=1e-8)


def test_perturbation_is_gtsams_right_perturbation():
    """The refinement's delta moves T_world_cam_true exactly as GTSAM's Pose3.retract does, so
    its covariance is what a PriorFactorPose3 on the corrected pose expects."""
    T_world_cam_est = exp_se3([0.2, -0.1, 0.4, 1.0, 2.0, 0.5])
    T_real_rendered = exp_se3([0.03, 0.01, -0.02, 0.05, -0.02, 0.01])
    delta = np.array([0.01, -0.02, 0.005, 0.03, 0.01, -0.02])
    ours = T_world_cam_est @ inv_T(exp_se3(-delta) @ T_real_rendered)
    T_true = T_world_cam_est @ inv_T(T_real_rendered)
    theirs = pose3_to_T(T_to_pose3(T_true).retract(delta))
    np.testing.assert_allclose(ours, theirs, atol=1e-12)
    np.testing.assert_allclose(log_se3(inv_T(T_true) @ ours), delta, atol=1e-12)
    np.testing.assert_allclose(gtsam.Pose3.Logmap(T_to_pose3(T_true).between(T_to_pose3(ours))), delta, atol=1e-12)


def test_stacked_rows_whiten_the_correlated_pixel_and_depth_noise():
    """A pixel error moves the depth read through the depth gradient g: the 3x3 covariance of
    one correspondence has that correlation, and its inverse whitens samples drawn from it."""
    rng = np.random.default_rng(2)
    g = np.array([[0.004, -0.002]])
    var_px, var_z = 2 * 0.7**2, 0.003**2
    samples = []
    for _ in range(20000):
        n_uv = rng.normal(size=2) * np.sqrt(var_px)
        samples.append(np.r_[n_uv, g[0] @ n_uv + rng.normal() * np.sqrt(var_z)])
    samples = np.array(samples)
    r, _, W = stack_rows(samples[:, :2], np.zeros((len(samples), 2, 6)), samples[:, 2], np.zeros((len(samples), 6)),
                          np.repeat(g, len(samples), 0), var_px, np.full(len(samples), var_z), True, True)
    whitened = np.einsum("ni,nij,nj->n", r, W, r)
    assert np.mean(whitened) == pytest.approx(3.0, rel=0.03)


def _synthetic_correspondences(rng, T_real_rendered, config, n=80):
    """Correspondences with exactly the model's noise: keypoint noise on both images, real
    depth noise sigma(z), rendered depth noise; a fronto-parallel depth (no gradient)."""
    x_true = _points(rng, n)
    y_true = x_true @ T_real_rendered[:3, :3].T + T_real_rendered[:3, 3]
    keep = y_true[:, 2] > 0.5
    x_true, y_true = x_true[keep], y_true[keep]
    uv_rend, _ = project(x_true, K)
    uv_rend = uv_rend + rng.normal(size=uv_rend.shape) * config.keypoint_sigma_px
    z_rend = x_true[:, 2] + rng.normal(size=len(x_true)) * config.render_depth_sigma_m
    x = backproject(uv_rend, z_rend, K)
    uv_real, _ = project(y_true, K)
    uv_real = uv_real + rng.normal(size=uv_real.shape) * config.keypoint_sigma_px
    z = y_true[:, 2]
    z_real = z + rng.normal(size=len(z)) * (config.depth_sigma_floor_m + config.depth_sigma_z2_per_m * z**2)
    y = backproject(uv_real, z_real, K)
    return Correspondences(x, y, uv_real, np.ones(len(x)), len(x), "", np.zeros((len(x), 2)))


def test_refined_covariance_matches_monte_carlo_scatter():
    """NEES of refine_pose over 300 synthetic problems: inside chi2's 95% band for the
    6-dof pose and for each 3-dof block (rotation, translation)."""
    rng = np.random.default_rng(3)
    config = AlignConfig(estimate_intrinsics=False)
    nees6, nees_rot, nees_trans = [], [], []
    for _ in range(300):
        T_rr = exp_se3(np.r_[rng.normal(size=3) * 0.03, rng.normal(size=3) * 0.05])
        corr = _synthetic_correspondences(rng, T_rr, config)
        start = exp_se3(rng.normal(size=6) * 0.002) @ T_rr
        R, t, cov, _ = refine_pose(start[:3, :3], start[:3, 3], corr, K, config)
        # Error of the corrected pose T_world_cam_est inv(T_rr_estimated) against the true one
        # T_world_cam_est inv(T_rr), as a right perturbation: log(T_rr_estimated inv(T_rr)).
        e = log_se3(make_T(R, t) @ inv_T(T_rr))
        nees6.append(e @ np.linalg.solve(cov, e))
        nees_rot.append(e[:3] @ np.linalg.solve(cov[:3, :3], e[:3]))
        nees_trans.append(e[3:] @ np.linalg.solve(cov[3:, 3:], e[3:]))
    n = len(nees6)
    for values, dof in ((nees6, 6), (nees_rot, 3), (nees_trans, 3)):
        lo, hi = chi2.ppf([0.025, 0.975], dof * n) / n
        assert lo <= np.mean(values) <= hi, (dof, np.mean(values), lo, hi)


def test_consensus_cost_prefers_the_true_model():
    rng = np.random.default_rng(4)
    config = AlignConfig()
    T_rr = exp_se3([0.02, 0.01, 0.0, 0.04, 0.0, 0.02])
    corr = _synthetic_correspondences(rng, T_rr, config, n=200)
    cost_true, inliers_true = consensus_cost(T_rr[:3, :3], T_rr[:3, 3], corr, K, config)
    wrong = exp_se3([0.0, 0.0, 0.0, 0.05, 0.0, 0.0]) @ T_rr  # 5 cm sideways
    cost_wrong, inliers_wrong = consensus_cost(wrong[:3, :3], wrong[:3, 3], corr, K, config)
    assert inliers_true > 0.97 * len(corr) and cost_true < 3.5 * len(corr)  # chi2(3): mean 3
    assert inliers_wrong < 0.5 * inliers_true and cost_wrong > 2 * cost_true


def test_plain_procrustes_covariance_matches_monte_carlo_scatter():
    """The paper's estimator (weighted Procrustes, every coordinate weighed alike) under the
    anisotropic noise: its sandwich covariance is honest for the pose and per block."""
    from nap3d_graph.nap3d.correspondences import noise_sigmas
    from nap3d_graph.nap3d.ransac import weighted_umeyama
    from nap3d_graph.nap3d.refine import plain_covariance

    rng = np.random.default_rng(5)
    config = AlignConfig(method="plain")
    nees6, nees_rot, nees_trans = [], [], []
    for _ in range(300):
        T_rr = exp_se3(np.r_[rng.normal(size=3) * 0.03, rng.normal(size=3) * 0.05])
        corr = _synthetic_correspondences(rng, T_rr, config)
        R, t = weighted_umeyama(corr.x, corr.y, corr.opacity)
        s_xy, s_z = noise_sigmas(corr, K, config)
        cov = plain_covariance(R, t, corr.x, corr.y, corr.opacity, s_xy, s_z)
        e = log_se3(make_T(R, t) @ inv_T(T_rr))
        nees6.append(e @ np.linalg.solve(cov, e))
        nees_rot.append(e[:3] @ np.linalg.solve(cov[:3, :3], e[:3]))
        nees_trans.append(e[3:] @ np.linalg.solve(cov[3:, 3:], e[3:]))
    n = len(nees6)
    for values, dof in ((nees6, 6), (nees_rot, 3), (nees_trans, 3)):
        lo, hi = chi2.ppf([0.025, 0.975], dof * n) / n
        assert lo <= np.mean(values) <= hi, (dof, np.mean(values), lo, hi)
