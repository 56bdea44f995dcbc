"""GTSAM factor builders for the NAP3D drift-correction graph.

Installed as ``nap3d_graph.factors``. Conventions (DESIGN.md): Pose3 tangent order
``[rotation(3), translation(3)]``, right perturbation, body frame; every noise model is
built by :func:`noise_model`; gating uses the unwhitened error under the base Gaussian.

Keys follow ``gtsam.symbol_shorthand``: X poses, V velocities, B IMU biases, M map anchor.
"""

from .gate import (
    GateResult,
    chi2_gate,
    chi2_gate_isam2,
    chi2_gate_with_marginal,
    chi2_threshold,
    error_jacobian,
    factor_error_and_covariance,
    mahalanobis_sq,
)
from .imu import imu_factor, imu_params, imu_pieces, integrate_pieces, preintegrate
from .nap3d import (
    anchor_prior_factor,
    corrected_pose_and_covariance,
    nap3d_anchor_factor,
    nap3d_prior_factor,
)
from .noise import (
    DEFAULT_ROBUST_THRESHOLDS,
    ROBUST_KERNELS,
    base_gaussian,
    noise_model,
    robustify,
    validate_covariance,
)
from .odometry import odometry_factor, pose_prior_factor

__all__ = [
    "noise_model",
    "base_gaussian",
    "robustify",
    "validate_covariance",
    "ROBUST_KERNELS",
    "DEFAULT_ROBUST_THRESHOLDS",
    "nap3d_prior_factor",
    "nap3d_anchor_factor",
    "anchor_prior_factor",
    "corrected_pose_and_covariance",
    "odometry_factor",
    "pose_prior_factor",
    "imu_params",
    "imu_pieces",
    "integrate_pieces",
    "imu_factor",
    "preintegrate",
    "GateResult",
    "mahalanobis_sq",
    "factor_error_and_covariance",
    "chi2_threshold",
    "chi2_gate",
    "chi2_gate_with_marginal",
    "chi2_gate_isam2",
    "error_jacobian",
]
