"""Shared helpers of the factor tests."""

from __future__ import annotations

import gtsam
import numpy as np

from nap3d_graph.conventions import exp_se3, inv_T
from nap3d_graph.factors import base_gaussian
from nap3d_graph.results import Alignment

G = 9.81

def random_covariance(rng: np.random.Generator, rot_sigma: float = 0.005,
                      trans_sigma: float = 0.01) -> np.ndarray:
    """A correlated 6x6 SPD covariance, GTSAM order, ~rot_sigma rad / trans_sigma m."""
    A = rng.normal(size=(6, 6))
    corr = A @ A.T + 6 * np.eye(6)
    d = 1.0 / np.sqrt(np.diag(corr))
    corr = corr * d[:, None] * d[None, :]
    s = np.array([rot_sigma] * 3 + [trans_sigma] * 3)
    return corr * s[:, None] * s[None, :]


def random_T(rng: np.random.Generator, rot_scale: float = 0.5, trans_scale: float = 2.0) -> np.ndarray:
    return exp_se3(np.concatenate([rng.normal(scale=rot_scale, size=3),
                                   rng.normal(scale=trans_scale, size=3)]))


def vals(*items) -> gtsam.Values:
    """``vals((key, Pose3), ...)`` -> Values."""
    v = gtsam.Values()
    for key, value in items:
        v.insert(key, value)
    return v


def unwhitened_jacobian(factor, values: gtsam.Values) -> tuple[list[np.ndarray], np.ndarray]:
    """Jacobians (per key) and error of ``factor`` from its linearisation, unwhitened.

    ``linearize`` returns ``A = R H`` and ``b = -R e`` with ``R`` the square-root
    information of the (Gaussian) noise; undo ``R`` to compare with numerical derivatives.
    """
    A, b = factor.linearize(values).jacobian()
    R = base_gaussian(factor.noiseModel()).R()
    H = np.linalg.solve(R, A)
    e = -np.linalg.solve(R, b)
    dims = [6] * factor.size()
    return np.split(H, np.cumsum(dims)[:-1], axis=1), e


def alignment_for(T_field_cam_est: np.ndarray, T_field_cam_true: np.ndarray,
                  covariance: np.ndarray) -> Alignment:
    """The Alignment NAP3D would return when the field renders at the estimate."""
    # corrected = est @ inv(T_real_rendered) = true  =>  T_real_rendered = inv(true) @ est
    return Alignment(T_real_rendered=inv_T(T_field_cam_true) @ T_field_cam_est,
                     covariance=covariance, num_matches=200, num_inliers=150,
                     inlier_rmse_m=0.01, success=True)
