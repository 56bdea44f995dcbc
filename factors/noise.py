"""The one place where GTSAM noise models are built.

Every 6x6 covariance, sigma vector and information matrix in this project is in GTSAM's
Pose3 tangent order ``[rotation(3), translation(3)]`` with the right perturbation
``T @ Exp(xi)`` (translation part in the body frame). That is exactly what the noise model
of a ``PriorFactorPose3`` / ``BetweenFactorPose3`` means, so a covariance from NAP3D or from
odometry goes into :func:`noise_model` unchanged.

Robust kernels wrap a Gaussian *base* model. GTSAM's ``noiseModel.Robust`` weighs the whole
whitened error vector by its *norm* (block reweighting), so for a 6-dof pose factor the
threshold is compared with the norm of six whitened components, whose typical value under
pure Gaussian noise is already sqrt(6) ~ 2.4. The scalar textbook thresholds (Huber 1.345)
would down-weight nearly every inlier to about half its information. The defaults here are
thresholds on that norm for 6-dof factors:

* ``"huber"``: ``k = sqrt(chi2.ppf(0.95, 6)) = 3.548``: 95 % of Gaussian inliers keep their
  full weight (quadratic inside ``k``, linear outside).
* ``"cauchy"``: ``k = 6.293``, the scalar pair's ratio (2.3849 / 1.345) applied to Huber's.
  (GTSAM's own examples sometimes use 0.1, which down-weights every inlier and so throws away
  most of the information the covariance carries.)

Gating and covariance recovery need the Gaussian inside a robust model, never the robust
model itself (its ``error()`` and ``whitenedError()`` are re-weighted): use
:func:`base_gaussian`.
"""

from __future__ import annotations

import logging
from typing import Optional, Union

import gtsam
import numpy as np

__all__ = [
    "ROBUST_KERNELS",
    "DEFAULT_ROBUST_THRESHOLDS",
    "validate_covariance",
    "noise_model",
    "robustify",
    "base_gaussian",
]

logger = logging.getLogger(__name__)

ArrayLike = Union[float, np.ndarray, "list[float]"]

#: Robust kernels :func:`noise_model` accepts (``None`` means plain Gaussian).
ROBUST_KERNELS = ("huber", "cauchy")

#: Default kernel thresholds on the whitened error norm of a 6-dof factor; see the module docstring.
DEFAULT_ROBUST_THRESHOLDS = {"huber": 3.548, "cauchy": 6.293}

# A covariance whose smallest eigenvalue is below this fraction of its largest one is
# numerically singular: its information matrix would be garbage, so refuse it.
_MAX_CONDITION_NUMBER = 1e14
# Relative tolerance on asymmetry: covariances computed as inv(J^T J) are symmetric only
# up to rounding, so a little asymmetry is expected and is removed by symmetrising.
_SYMMETRY_RTOL = 1e-6


def validate_covariance(covariance: np.ndarray, dim: int = 6, name: str = "covariance") -> np.ndarray:
    """Check a covariance and return its symmetrised copy.

    Args:
        covariance: (dim, dim) covariance, GTSAM tangent order.
        dim: expected dimension (6 for a Pose3).
        name: what to call it in error messages.

    Returns:
        (dim, dim) float array, ``(C + C^T) / 2``.

    Raises:
        ValueError: wrong shape, non-finite entries, asymmetric beyond rounding, not
            positive definite or numerically singular. The message says which.
    """
    C = np.asarray(covariance, dtype=float)
    if C.shape != (dim, dim):
        raise ValueError(f"{name} must have shape ({dim}, {dim}), got {C.shape}")
    if not np.all(np.isfinite(C)):
        raise ValueError(f"{name} has non-finite entries (NaN or inf): {C.tolist()}")
    scale = float(np.max(np.abs(C)))
    asym = float(np.max(np.abs(C - C.T)))
    if asym > _SYMMETRY_RTOL * max(scale, np.finfo(float).tiny):
        raise ValueError(f"{name} is not symmetric: max |C - C^T| = {asym:.3g} "
                         f"(max |C| = {scale:.3g})")
    C = 0.5 * (C + C.T)
    eig = np.linalg.eigvalsh(C)
    if eig[0] <= 0.0:
        raise ValueError(f"{name} is not positive definite: smallest eigenvalue {eig[0]:.3g}")
    if eig[-1] > _MAX_CONDITION_NUMBER * eig[0]:
        raise ValueError(f"{name} is numerically singular: eigenvalues span "
                         f"[{eig[0]:.3g}, {eig[-1]:.3g}]")
    return C


def _sigma3(value: ArrayLike, name: str) -> np.ndarray:
    """A scalar or 3-vector of standard deviations -> positive finite (3,) array."""
    s = np.asarray(value, dtype=float)
    if s.ndim == 0:
        s = np.full(3, float(s))
    if s.shape != (3,):
        raise ValueError(f"{name} must be a scalar or a 3-vector, got shape {s.shape}")
    if not np.all(np.isfinite(s)) or np.any(s <= 0.0):
        raise ValueError(f"{name} must be finite and > 0, got {s.tolist()}")
    return s


def robustify(base: gtsam.noiseModel.Base, robust: Optional[str],
              robust_threshold: Optional[float] = None) -> gtsam.noiseModel.Base:
    """Wrap ``base`` in a robust kernel (``"huber"``, ``"cauchy"``) or return it (``None``).

    ``robust_threshold`` is on the whitened error norm; ``None`` takes
    :data:`DEFAULT_ROBUST_THRESHOLDS` (for 6-dof factors).
    """
    if robust is None:
        if robust_threshold is not None:
            raise ValueError("robust_threshold given without a robust kernel")
        return base
    kernel = str(robust).lower()
    if kernel not in ROBUST_KERNELS:
        raise ValueError(f"unknown robust kernel {robust!r}; expected one of {ROBUST_KERNELS} or None")
    k = DEFAULT_ROBUST_THRESHOLDS[kernel] if robust_threshold is None else float(robust_threshold)
    if not np.isfinite(k) or k <= 0.0:
        raise ValueError(f"robust_threshold must be finite and > 0, got {robust_threshold}")
    estimator: gtsam.noiseModel.mEstimator.Base
    if kernel == "huber":
        estimator = gtsam.noiseModel.mEstimator.Huber.Create(k)
    else:
        estimator = gtsam.noiseModel.mEstimator.Cauchy.Create(k)
    return gtsam.noiseModel.Robust.Create(estimator, base)


def noise_model(*, rot_sigma_rad: Optional[ArrayLike] = None,
                trans_sigma_m: Optional[ArrayLike] = None,
                covariance: Optional[np.ndarray] = None,
                robust: Optional[str] = None,
                robust_threshold: Optional[float] = None) -> gtsam.noiseModel.Base:
    """Build a 6-dof Pose3 noise model from sigmas *or* a covariance.

    Args:
        rot_sigma_rad: rotation standard deviation(s), scalar or (3,), radians, body frame.
        trans_sigma_m: translation standard deviation(s), scalar or (3,), metres, body frame.
        covariance: (6, 6) covariance in GTSAM order ``[rot, trans]``; validated
            (finite, symmetric, positive definite) and symmetrised.
        robust: ``None``, ``"huber"`` or ``"cauchy"``.
        robust_threshold: kernel threshold on the whitened error norm; default per kernel
            (module docstring).

    Returns:
        ``noiseModel.Diagonal`` (sigmas) or ``noiseModel.Gaussian`` (covariance), wrapped in
        ``noiseModel.Robust`` when ``robust`` is given.

    Raises:
        ValueError: both or neither of (sigmas, covariance) given, or invalid values.
    """
    has_sigmas = rot_sigma_rad is not None or trans_sigma_m is not None
    if has_sigmas and covariance is not None:
        raise ValueError("give either rot_sigma_rad/trans_sigma_m or covariance, not both")
    if covariance is not None:
        base = gtsam.noiseModel.Gaussian.Covariance(validate_covariance(covariance))
    elif rot_sigma_rad is not None and trans_sigma_m is not None:
        sigmas = np.concatenate([_sigma3(rot_sigma_rad, "rot_sigma_rad"),
                                 _sigma3(trans_sigma_m, "trans_sigma_m")])
        base = gtsam.noiseModel.Diagonal.Sigmas(sigmas)
    else:
        raise ValueError("noise_model needs both rot_sigma_rad and trans_sigma_m, or covariance")
    return robustify(base, robust, robust_threshold)


def base_gaussian(noise: gtsam.noiseModel.Base) -> gtsam.noiseModel.Gaussian:
    """The Gaussian inside a ``Robust`` model, or ``noise`` itself if it is Gaussian.

    ``Diagonal``, ``Isotropic`` and ``Unit`` are Gaussians too. Raises ``TypeError`` for
    anything else (there is no base Gaussian to gate or report covariances with).
    """
    model = noise
    # Robust models could in principle be nested; unwrap until a Gaussian appears.
    while isinstance(model, gtsam.noiseModel.Robust):
        model = model.noise()
    if not isinstance(model, gtsam.noiseModel.Gaussian):
        raise TypeError(f"no Gaussian base model in {type(noise).__name__}")
    return model
