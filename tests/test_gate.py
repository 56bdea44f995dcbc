"""Chi-square gates of new factors: base Gaussian, innovation covariance, statistics."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
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

from factor_helpers import random_covariance, vals


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
    assert 2 * robust.error(v) < 0.05 * expected  # what a naive gate would have used
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
