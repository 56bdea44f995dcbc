"""Chi-square gating of factors before they enter the graph.

The test statistic is the squared Mahalanobis distance of the factor's *unwhitened* error
under its *base Gaussian* model, compared with ``scipy.stats.chi2.ppf(p, dof)``. A robust
model's ``error()`` (and, in GTSAM 4.3, its ``whitenedError()``) is already re-weighted by
the kernel, which shrinks exactly the outliers the gate exists to catch, so it is never
used here.

Two gates, for two situations:

* :func:`chi2_gate` (``S = factor covariance``) treats the current estimate as exact. Right
  when the estimate is much more certain than the measurement (e.g. a pose just
  corrected, or a well-constrained smoother), or as a deliberately strict sanity check.
  Wrong after long drift: the estimate's own uncertainty has grown, a *correct* NAP3D
  correction is then far from the estimate in the factor's metric, and the gate rejects
  the very correction that is needed most.
* :func:`chi2_gate_with_marginal` (``S = factor covariance + J P J^T``, the innovation
  covariance as in an EKF's NIS test) accounts for the estimate's marginal covariance
  ``P`` (e.g. ``isam2.marginalCovariance(X(k))``). Right for a prior-type correction of a
  drifting estimate. For a pose prior, the error is ``Logmap(z^-1 x)`` and its Jacobian
  w.r.t. the right perturbation of ``x`` is ``J = Jr^-1(error) ~ I`` for small errors;
  pass ``jacobian`` when the error is large or the factor is not a plain prior.

* :func:`chi2_gate_isam2` does the latter for any factor of Pose3 variables already in an
  iSAM2 problem: the *joint* marginal covariance of all the factor's variables, and the
  error's Jacobian w.r.t. each of them (numerical, on GTSAM's retract), so a factor between
  a map anchor ``M(0)`` and a pose ``X(k)`` sees the anchor's uncertainty carried into the
  camera frame through the adjoint and the anchor-pose correlation, not added as if both
  lived in one frame.

No gate raises on NaN: a non-finite error or covariance is rejected with a reason.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Optional

import gtsam
import numpy as np
from scipy.stats import chi2

from .noise import base_gaussian

__all__ = [
    "GateResult",
    "mahalanobis_sq",
    "factor_error_and_covariance",
    "chi2_threshold",
    "chi2_gate",
    "chi2_gate_with_marginal",
    "chi2_gate_isam2",
    "error_jacobian",
]

logger = logging.getLogger(__name__)

DEFAULT_GATE_P = 0.997


@dataclass(frozen=True)
class GateResult:
    """Outcome of a chi-square gate.

    accepted: True when ``d2 <= threshold``.
    d2: squared Mahalanobis distance (NaN when it could not be computed).
    threshold: ``chi2.ppf(p, dof)``.
    reason: empty when accepted; otherwise why it was rejected (for corrections.csv).
    """

    accepted: bool
    d2: float
    threshold: float
    reason: str = ""


def chi2_threshold(p: float, dof: int) -> float:
    """``scipy.stats.chi2.ppf(p, dof)``, validating ``0 < p < 1`` and ``dof >= 1``."""
    if not 0.0 < p < 1.0:
        raise ValueError(f"gate probability p must be in (0, 1), got {p}")
    if int(dof) != dof or dof < 1:
        raise ValueError(f"dof must be a positive integer, got {dof}")
    return float(chi2.ppf(p, int(dof)))


def factor_error_and_covariance(factor: gtsam.NonlinearFactor,
                                values: gtsam.Values) -> tuple[np.ndarray, np.ndarray]:
    """Unwhitened error (m,) of ``factor`` at ``values`` and its base Gaussian covariance (m, m).

    For a Pose3 factor the error is a tangent vector ``[rot, trans]`` (GTSAM order), e.g.
    ``Logmap(measured^-1 @ x)`` for a prior. Raises ``TypeError`` if the factor has no
    noise model (not a ``NoiseModelFactor``).
    """
    if not (hasattr(factor, "unwhitenedError") and hasattr(factor, "noiseModel")):
        raise TypeError(f"{type(factor).__name__} is not a NoiseModelFactor")
    error = np.asarray(factor.unwhitenedError(values), dtype=np.float64).reshape(-1)
    return error, np.asarray(base_gaussian(factor.noiseModel()).covariance(), dtype=float)


def mahalanobis_sq(factor: gtsam.NonlinearFactor, values: gtsam.Values) -> float:
    """Squared Mahalanobis distance ``e^T Sigma^-1 e`` of a factor at ``values``.

    ``e`` is ``factor.unwhitenedError(values)`` and ``Sigma`` the covariance of the base
    Gaussian (inside any robust kernel). Computed as ``|whiten(e)|^2`` with the base
    model's square-root information, which equals ``e^T information e`` without forming
    an inverse. Returns NaN for a non-finite error; never raises on NaN.

    Raises:
        TypeError: ``factor`` is not a ``NoiseModelFactor`` or has no Gaussian base model.
    """
    if not (hasattr(factor, "unwhitenedError") and hasattr(factor, "noiseModel")):
        raise TypeError(f"{type(factor).__name__} is not a NoiseModelFactor")
    base = base_gaussian(factor.noiseModel())
    error = np.asarray(factor.unwhitenedError(values), dtype=np.float64).reshape(-1)
    if not np.all(np.isfinite(error)):
        return float("nan")
    return float(np.sum(np.square(base.whiten(error))))


def _decide(d2: float, threshold: float, what: str) -> GateResult:
    if not np.isfinite(d2):
        return GateResult(False, float("nan"), threshold, f"{what}: non-finite error or covariance")
    if d2 > threshold:
        return GateResult(False, d2, threshold,
                          f"{what}: chi-square gate d2={d2:.4g} > {threshold:.4g}")
    return GateResult(True, d2, threshold, "")


def chi2_gate(factor: gtsam.NonlinearFactor, values: gtsam.Values,
              p: float = DEFAULT_GATE_P, dof: Optional[int] = 6) -> GateResult:
    """Gate a factor against the current estimate, taking the estimate as exact.

    Args:
        factor: a ``NoiseModelFactor`` (robust or not; its base Gaussian is used).
        values: estimate holding every key of the factor.
        p: acceptance probability of a correct factor (0.997: ~3 sigma).
        dof: chi-square degrees of freedom; ``None`` takes ``factor.dim()``.

    Returns:
        :class:`GateResult`; rejected with a reason on NaN, never raises on NaN.
    """
    dof = factor.dim() if dof is None else dof
    if dof != factor.dim():
        logger.warning("chi2_gate: dof=%s but the factor's error has dimension %d", dof, factor.dim())
    threshold = chi2_threshold(p, dof)
    return _decide(mahalanobis_sq(factor, values), threshold, "factor")


def chi2_gate_with_marginal(factor_error_xi: np.ndarray, factor_cov: np.ndarray,
                            estimate_cov: Optional[np.ndarray] = None,
                            p: float = DEFAULT_GATE_P, dof: int = 6, *,
                            jacobian: Optional[np.ndarray] = None) -> GateResult:
    """Gate with the innovation covariance ``S = factor_cov + J estimate_cov J^T``.

    Args:
        factor_error_xi: (m,) unwhitened factor error at the current estimate (GTSAM order),
            e.g. from :func:`factor_error_and_covariance`.
        factor_cov: (m, m) covariance of the factor's base Gaussian.
        estimate_cov: (n, n) marginal covariance of the estimate the error depends on
            (e.g. ``isam2.marginalCovariance(X(k))``, right perturbation, GTSAM order), or
            ``None`` to ignore it (then this equals :func:`chi2_gate`).
        p, dof: as in :func:`chi2_gate`.
        jacobian: (m, n) derivative of the error w.r.t. the estimate's perturbation;
            ``None`` means identity (a pose prior with a small error).

    Returns:
        :class:`GateResult`; a non-finite or non-positive-definite ``S`` is rejected with a
        reason, never raised.

    Raises:
        ValueError: inconsistent shapes (a programming error, not a data error).
    """
    xi = np.asarray(factor_error_xi, dtype=float).reshape(-1)
    m = xi.shape[0]
    R = np.asarray(factor_cov, dtype=float)
    if R.shape != (m, m):
        raise ValueError(f"factor_cov must have shape ({m}, {m}), got {R.shape}")
    S = R.copy()
    if estimate_cov is not None:
        P = np.asarray(estimate_cov, dtype=float)
        J = np.eye(m) if jacobian is None else np.asarray(jacobian, dtype=float)
        if P.ndim != 2 or P.shape[0] != P.shape[1] or J.shape != (m, P.shape[0]):
            raise ValueError(f"estimate_cov {P.shape} and jacobian {J.shape} do not fit an "
                             f"error of dimension {m}")
        S = S + J @ P @ J.T
    threshold = chi2_threshold(p, dof)
    if not (np.all(np.isfinite(xi)) and np.all(np.isfinite(S))):
        return _decide(float("nan"), threshold, "innovation")
    try:
        # Cholesky both checks positive definiteness and gives a stable solve.
        L = np.linalg.cholesky(0.5 * (S + S.T))
    except np.linalg.LinAlgError:
        return GateResult(False, float("nan"), threshold,
                          "innovation: covariance is not positive definite")
    w = np.linalg.solve(L, xi)
    return _decide(float(w @ w), threshold, "innovation")


def error_jacobian(factor: gtsam.NoiseModelFactor, values: gtsam.Values, step: float = 1e-6) -> np.ndarray:
    """Jacobian (m, 6 * len(keys)) of ``factor.unwhitenedError`` w.r.t. the right
    perturbation (GTSAM retract) of each of its Pose3 variables, in ``factor.keys()`` order.

    Central differences: exact to ~1e-8 for the Pose3 priors and between factors used here,
    and valid for any factor of Pose3 variables (a user's own included).
    """
    keys = list(factor.keys())
    e0 = np.asarray(factor.unwhitenedError(values), dtype=np.float64).reshape(-1)
    J = np.zeros((e0.size, 6 * len(keys)))
    for j, key in enumerate(keys):
        pose = values.atPose3(key)
        for k in range(6):
            d = np.zeros(6)
            d[k] = step
            errors = []
            for sign in (1.0, -1.0):
                moved = gtsam.Values(values)
                moved.update(key, pose.retract(sign * d))
                errors.append(np.asarray(factor.unwhitenedError(moved), dtype=np.float64).reshape(-1))
            J[:, 6 * j + k] = (errors[0] - errors[1]) / (2 * step)
    return J


def chi2_gate_isam2(factor: gtsam.NoiseModelFactor, isam: gtsam.ISAM2, p: float = DEFAULT_GATE_P,
                    dof: Optional[int] = 6) -> GateResult:
    """Gate a factor on Pose3 variables that iSAM2 already holds, before adding it.

    ``S = Sigma_factor + J P J^T`` with ``P`` the joint marginal covariance of the factor's
    variables (``isam.jointMarginalCovariance``) and ``J`` the error's Jacobian at iSAM2's
    current estimate (:func:`error_jacobian`); ``d2 = e^T S^-1 e`` against
    ``chi2.ppf(p, dof)``. Rejected with a reason (never raised) on NaN or a singular ``S``.
    """
    keys = list(factor.keys())
    values = gtsam.Values()
    for key in keys:
        values.insert(key, isam.calculateEstimatePose3(key))
    xi, factor_cov = factor_error_and_covariance(factor, values)
    if len(keys) == 1:
        P = np.asarray(isam.marginalCovariance(keys[0]))
    else:
        joint = isam.jointMarginalCovariance(gtsam.KeyVector(keys))
        P = np.block([[np.asarray(joint.at(a, b)) for b in keys] for a in keys])
    J = error_jacobian(factor, values)
    return chi2_gate_with_marginal(xi, factor_cov, P, p=p, dof=factor.dim() if dof is None else dof, jacobian=J)
