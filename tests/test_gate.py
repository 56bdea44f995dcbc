"""Chi-square gates of new factors: base Gaussian, innovation covariance, statistics."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from factor_helpers import random_covariance, vals
from gtsam.symbol_shorthand import X
from scipy.stats import chi2

from nap3d_graph.factors import (
    GateResult,
    chi2_gate,
    chi2_gate_with_marginal,
    factor_error_and_covariance,
    mahalanobis_sq,
    noise_model,
)

# --- gate ------------------------------------------------------------------------------


def prior_at_identity(C: np.ndarray, robust=None) -> gtsam.PriorFactorPose3:
    return gtsam.PriorFactorPose3(X(0), gtsam.Pose3(), noise_model(covariance=C, robust=robust))


def test_gate_accepts_correct_and_rejects_wrong_factor():
    C = np.diag([np.radians(0.5)] * 3 + [0.01] * 3) ** 2
    factor = prior_at_identity(C, robust="huber")
    ok = chi2_gate(factor, vals((X(0), gtsam.Pose3.Expmap(np.array([0.005, 0, 0, 0.01, -0.01, 0])))))
    assert isinstance(ok, GateResult)
    assert ok.accepted and ok.reason == ""
    assert ok.threshold == pytest.approx(chi2.ppf(0.997, 6))
    wrong = chi2_gate(factor, vals((X(0), gtsam.Pose3(gtsam.Rot3(), np.array([0.5, 0, 0])))))
    assert not wrong.accepted
    assert wrong.d2 == pytest.approx((0.5 / 0.01) ** 2, rel=1e-9)  # reported, not clipped
    assert "d2=2500" in wrong.reason


def test_gate_uses_base_gaussian_not_robust_error():
    rng = np.random.default_rng(5)
    C = random_covariance(rng)
    x = gtsam.Pose3.Expmap(np.array([0.02, -0.01, 0.03, 0.2, -0.1, 0.3]))  # a gross outlier
    v = vals((X(0), x))
    robust, gauss = prior_at_identity(C, "cauchy"), prior_at_identity(C)
    e = gtsam.Pose3.Logmap(x)
    expected = e @ np.linalg.solve(C, e)
    assert mahalanobis_sq(gauss, v) == pytest.approx(expected, rel=1e-9)
    assert mahalanobis_sq(robust, v) == pytest.approx(expected, rel=1e-9)
    assert 2 * robust.error(v) < 0.15 * expected  # what a naive gate would have used
    assert chi2_gate(robust, v).d2 == pytest.approx(expected, rel=1e-9)
    xi, cov = factor_error_and_covariance(robust, v)
    np.testing.assert_allclose(xi, e, atol=1e-12)
    np.testing.assert_allclose(cov, C, rtol=1e-9, atol=1e-18)


def test_gate_rejection_rate_matches_chi2():
    rng = np.random.default_rng(6)
    C = random_covariance(rng)
    factor = prior_at_identity(C, robust="huber")
    draws = rng.multivariate_normal(np.zeros(6), C, size=2000)
    rejected = np.mean([not chi2_gate(factor, vals((X(0), gtsam.Pose3.Expmap(xi))), p=0.95).accepted
                        for xi in draws])
    assert abs(rejected - 0.05) < 0.015, rejected
    # The innovation gate with S = R + P has the same rate on errors drawn from R + P.
    P = random_covariance(rng, 0.02, 0.1)
    draws = rng.multivariate_normal(np.zeros(6), C + P, size=2000)
    rejected = np.mean([not chi2_gate_with_marginal(xi, C, P, p=0.95).accepted for xi in draws])
    assert abs(rejected - 0.05) < 0.015, rejected


def test_gate_with_marginal_accepts_correction_of_drifted_estimate():
    C = np.diag([np.radians(0.5)] * 3 + [0.01] * 3) ** 2
    P = np.diag([np.radians(2.0)] * 3 + [0.3] * 3) ** 2  # drifted: 30 cm uncertain
    factor = prior_at_identity(C)
    v = vals((X(0), gtsam.Pose3(gtsam.Rot3(), np.array([0.4, 0.0, 0.0]))))
    assert not chi2_gate(factor, v).accepted
    xi, cov = factor_error_and_covariance(factor, v)
    with_marginal = chi2_gate_with_marginal(xi, cov, P)
    assert with_marginal.accepted, with_marginal
    assert with_marginal.d2 == pytest.approx(0.4 ** 2 / (0.01 ** 2 + 0.3 ** 2), rel=1e-6)
    # Without an estimate covariance it is the plain gate.
    assert chi2_gate_with_marginal(xi, cov, None).d2 == pytest.approx(chi2_gate(factor, v).d2, rel=1e-9)
    # An explicit Jacobian is used as J P J^T.
    J = 2.0 * np.eye(6)
    assert chi2_gate_with_marginal(xi, cov, P, jacobian=J).d2 == pytest.approx(
        0.4 ** 2 / (0.01 ** 2 + 4 * 0.3 ** 2), rel=1e-6)


def test_gate_never_raises_on_nan():
    C = np.eye(6) * 1e-4
    nan_prior = gtsam.PriorFactorPose3(X(0), gtsam.Pose3(gtsam.Rot3(), np.array([np.nan, 0, 0])),
                                       noise_model(covariance=C, robust="huber"))
    result = chi2_gate(nan_prior, vals((X(0), gtsam.Pose3())))
    assert not result.accepted and np.isnan(result.d2) and "non-finite" in result.reason
    result = chi2_gate_with_marginal(np.array([np.nan] + [0.0] * 5), C, C)
    assert not result.accepted and "non-finite" in result.reason
    result = chi2_gate_with_marginal(np.zeros(6), C, np.full((6, 6), np.nan))
    assert not result.accepted and "non-finite" in result.reason
    result = chi2_gate_with_marginal(np.ones(6), -C, None)
    assert not result.accepted and "positive definite" in result.reason


def _anchor_trial(rng, P_M, P_X, R, T_world_cam_true):
    """One map-anchor problem: the field's frame M drawn from its prior, the pose X from its
    prior, a correct NAP3D measurement of T_map_cam; iSAM2 holds the two priors."""
    from gtsam.symbol_shorthand import M

    from nap3d_graph.conventions import T_to_pose3, exp_se3, inv_T
    from nap3d_graph.factors import anchor_prior_factor, pose_prior_factor

    T_world_map = exp_se3(rng.multivariate_normal(np.zeros(6), P_M))
    T_world_cam_prior = T_world_cam_true @ exp_se3(rng.multivariate_normal(np.zeros(6), P_X))
    measured = inv_T(T_world_map) @ T_world_cam_true @ exp_se3(rng.multivariate_normal(np.zeros(6), R))
    isam = gtsam.ISAM2()
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(anchor_prior_factor(M(0), np.eye(4), np.sqrt(P_M[0, 0]), np.sqrt(P_M[3, 3])))
    graph.add(pose_prior_factor(X(0), T_world_cam_prior, rot_sigma_rad=np.sqrt(P_X[0, 0]),
                                trans_sigma_m=np.sqrt(P_X[3, 3])))
    values.insert(M(0), gtsam.Pose3())
    values.insert(X(0), T_to_pose3(T_world_cam_prior))
    isam.update(graph, values)
    factor = gtsam.BetweenFactorPose3(M(0), X(0), T_to_pose3(measured), noise_model(covariance=R))
    return isam, factor


def test_anchor_gate_passes_good_corrections_at_the_expected_rate():
    """With a map anchor whose rotation is uncertain (0.1 rad) and a camera 4 m from the map's
    origin, a correct correction's innovation includes the anchor's rotation carried to the
    camera by the lever arm (~0.4 m). The joint-marginal gate accepts correct corrections at
    its 99.7% rate; adding the anchor's covariance to the pose's as if both lived in one
    frame (what the pipeline did) rejects most of them."""
    from nap3d_graph.conventions import exp_se3
    from nap3d_graph.factors import chi2_gate_isam2

    rng = np.random.default_rng(11)
    P_M = np.diag([0.1**2] * 3 + [0.02**2] * 3)
    P_X = np.diag([0.01**2] * 3 + [0.05**2] * 3)
    R = np.diag([0.003**2] * 3 + [0.005**2] * 3)
    T_world_cam = exp_se3([0.3, -0.5, 1.2, 3.0, 2.5, 1.0])  # 4 m from the map's origin
    accepted, mixed_frames_accepted, trials = 0, 0, 400
    threshold = chi2.ppf(0.997, 6)
    for _ in range(trials):
        isam, factor = _anchor_trial(rng, P_M, P_X, R, T_world_cam)
        gate = chi2_gate_isam2(factor, isam, p=0.997)
        accepted += gate.accepted
        values = isam.calculateEstimate()
        xi, cov = factor_error_and_covariance(factor, values)
        S_mixed = cov + np.asarray(isam.marginalCovariance(X(0))) + np.asarray(isam.marginalCovariance(gtsam.symbol("m", 0)))
        mixed_frames_accepted += xi @ np.linalg.solve(S_mixed, xi) <= threshold
    # Binomial: 400 trials at 0.997 expect 1.2 rejections; 6 or more has probability < 0.2%.
    assert accepted >= trials - 5, accepted
    assert mixed_frames_accepted < 0.7 * trials, mixed_frames_accepted


def test_gate_isam2_on_a_prior_matches_the_marginal_gate():
    from nap3d_graph.factors import chi2_gate_isam2, error_jacobian

    rng = np.random.default_rng(12)
    C = random_covariance(rng)
    isam = gtsam.ISAM2()
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(), noise_model(covariance=4 * C)))
    values.insert(X(0), gtsam.Pose3())
    isam.update(graph, values)
    z = gtsam.Pose3.Expmap(np.array([0.01, 0.0, -0.01, 0.02, 0.01, 0.0]))
    factor = gtsam.PriorFactorPose3(X(0), z, noise_model(covariance=C))
    gate = chi2_gate_isam2(factor, isam)
    xi, cov = factor_error_and_covariance(factor, vals((X(0), gtsam.Pose3())))
    J = error_jacobian(factor, vals((X(0), gtsam.Pose3())))
    reference = chi2_gate_with_marginal(xi, cov, 4 * C, jacobian=J)
    assert gate.d2 == pytest.approx(reference.d2, rel=1e-9)
    # The prior's Jacobian is Jr^-1 of its error: close to the identity for a small error.
    np.testing.assert_allclose(J, gtsam.Pose3.LogmapDerivative(z.inverse()), atol=1e-6)
