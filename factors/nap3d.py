"""Factors from one NAP3D pose correction.

A NAP3D correction (:class:`~nap3d_graph.results.Alignment` or
:class:`~nap3d_graph.results.Correction`) measures the camera pose *in the radiance
field's frame*, with a 6x6 covariance of that pose in GTSAM's tangent order and frame
(right perturbation, ``[rot, trans]``, body frame). Two ways to put it in a graph:

* :func:`nap3d_prior_factor`: the field's frame *is* the odometry world frame, so the
  corrected pose is a ``PriorFactorPose3`` on ``X(k)``. Its error is
  ``Logmap(T_measured^-1 @ T_world_cam)``, a right perturbation of the measured pose,
  so the NAP3D covariance is its noise model unchanged.
* :func:`nap3d_anchor_factor`: the field's frame ("map" frame M) is only approximately the
  world frame; an anchor node ``M(0)`` holds ``T_world_map`` and the correction becomes
  ``BetweenFactorPose3(M(0), X(k), T_map_cam_measured)``. ``between(T_world_map,
  T_world_cam) = T_map_cam``, and its error is again a right perturbation of the measured
  ``T_map_cam``, so the same covariance applies.
"""

from __future__ import annotations

import logging
from typing import Optional, Union

import gtsam
import numpy as np

from nap3d_graph.conventions import T_to_pose3, rigid_transform_problem
from nap3d_graph.results import Alignment, Correction

from .noise import noise_model, validate_covariance

__all__ = [
    "corrected_pose_and_covariance",
    "nap3d_prior_factor",
    "nap3d_anchor_factor",
    "anchor_prior_factor",
]

logger = logging.getLogger(__name__)

PoseLike = Union[np.ndarray, gtsam.Pose3]
NAP3DResult = Union[Alignment, Correction]

# Weak by default: the anchor prior only fixes the gauge until NAP3D factors arrive; the
# field's frame is expected within a metre and ~20 degrees of the world frame.
DEFAULT_ANCHOR_ROT_SIGMA_RAD = 0.35
DEFAULT_ANCHOR_TRANS_SIGMA_M = 1.0


def _as_T(pose: PoseLike, name: str) -> np.ndarray:
    """A ``gtsam.Pose3`` or 4x4 array -> finite (4, 4) float array."""
    if isinstance(pose, gtsam.Pose3):
        return np.asarray(pose.matrix(), dtype=float)
    T = np.asarray(pose, dtype=float)
    problem = rigid_transform_problem(T, tolerance=1e-6)
    if problem:
        raise ValueError(f"{name} must be a rigid 4x4 transform or gtsam.Pose3: {problem}")
    return T


def corrected_pose_and_covariance(T_world_cam_est: Optional[PoseLike],
                                  result: NAP3DResult) -> tuple[np.ndarray, np.ndarray]:
    """The measured camera pose and its covariance from a NAP3D result.

    Args:
        T_world_cam_est: (4, 4) pose the field rendered at (field frame <- camera, OpenCV
            camera). Needed for an ``Alignment``; ignored (may be ``None``) for a
            ``Correction``, which carries its own corrected pose.
        result: a successful ``Alignment`` or ``Correction``.

    Returns:
        ``(T_field_cam_measured (4, 4), covariance (6, 6))``, covariance symmetrised,
        GTSAM order and frame.

    Raises:
        ValueError: the result failed, or its pose/covariance is not finite, or the
            covariance is not positive definite.
        TypeError: ``result`` is neither an ``Alignment`` nor a ``Correction``.
    """
    if isinstance(result, Correction):
        if not result.success:
            raise ValueError(f"NAP3D correction failed: {result.reason or 'no reason given'}")
        T_meas = _as_T(result.T_world_cam_corrected, "Correction.T_world_cam_corrected")
    elif isinstance(result, Alignment):
        if not result.success:
            raise ValueError(f"NAP3D alignment failed: {result.reason or 'no reason given'}")
        if T_world_cam_est is None:
            raise ValueError("an Alignment needs T_world_cam_est (the pose the field rendered at)")
        T_meas = result.corrected_pose(_as_T(T_world_cam_est, "T_world_cam_est"))
        if not np.all(np.isfinite(T_meas)):
            raise ValueError("NAP3D alignment gives a non-finite corrected pose")
    else:
        raise TypeError(f"expected an Alignment or a Correction, got {type(result).__name__}")
    covariance = validate_covariance(result.covariance, name="NAP3D covariance")
    return T_meas, covariance


def nap3d_prior_factor(key: int, T_world_cam_est: Optional[PoseLike], result: NAP3DResult,
                       robust: Optional[str] = "huber",
                       robust_threshold: Optional[float] = None) -> gtsam.PriorFactorPose3:
    """``PriorFactorPose3`` on ``key`` at the NAP3D-corrected camera pose.

    Use when the field's frame is the odometry world frame.

    Args:
        key: pose key, e.g. ``X(k)``; the variable is ``T_world_cam`` (4x4, OpenCV camera).
        T_world_cam_est: (4, 4) or ``Pose3``, the estimate the field rendered at
            (``None`` allowed for a ``Correction``).
        result: successful ``Alignment`` (corrected pose
            ``T_world_cam_est @ inv(T_real_rendered)``) or ``Correction``
            (``T_world_cam_corrected``); its (6, 6) covariance, GTSAM order, is the noise.
        robust: ``"huber"`` (default), ``"cauchy"`` or ``None``.
        robust_threshold: kernel threshold in sigmas (default per kernel, see
            :mod:`nap3d_graph.factors.noise`).

    Raises:
        ValueError: failed result or bad covariance (see
            :func:`corrected_pose_and_covariance`).
    """
    T_meas, covariance = corrected_pose_and_covariance(T_world_cam_est, result)
    noise = noise_model(covariance=covariance, robust=robust, robust_threshold=robust_threshold)
    return gtsam.PriorFactorPose3(key, T_to_pose3(T_meas), noise)


def nap3d_anchor_factor(pose_key: int, anchor_key: int, T_world_cam_est: Optional[PoseLike],
                        result: NAP3DResult, robust: Optional[str] = "huber",
                        robust_threshold: Optional[float] = None) -> gtsam.BetweenFactorPose3:
    """``BetweenFactorPose3(anchor_key, pose_key, T_map_cam_measured)``.

    Use when the field's frame M is not exactly the world frame. The anchor variable
    (``M(0)``) is ``T_world_map``, the pose variable ``T_world_cam``; their ``between`` is
    ``T_map_cam``, which is what NAP3D measures.

    Args:
        pose_key: camera pose key ``X(k)`` (variable ``T_world_cam``).
        anchor_key: anchor key ``M(0)`` (variable ``T_world_map``).
        T_world_cam_est: (4, 4) or ``Pose3``: the pose *the field was rendered at*, which
            is a pose in the field's frame M (the pipeline renders with map-frame poses;
            if it has no anchor estimate that is its world estimate taken as a map pose).
            ``None`` allowed for a ``Correction``.
        result: successful ``Alignment`` or ``Correction``; the corrected pose is
            ``T_map_cam_measured`` and its (6, 6) covariance the noise.
        robust, robust_threshold: as in :func:`nap3d_prior_factor`.
    """
    T_map_cam, covariance = corrected_pose_and_covariance(T_world_cam_est, result)
    noise = noise_model(covariance=covariance, robust=robust, robust_threshold=robust_threshold)
    return gtsam.BetweenFactorPose3(anchor_key, pose_key, T_to_pose3(T_map_cam), noise)


def anchor_prior_factor(anchor_key: int, T_world_map_guess: Optional[PoseLike] = None,
                        rot_sigma_rad: float | np.ndarray = DEFAULT_ANCHOR_ROT_SIGMA_RAD,
                        trans_sigma_m: float | np.ndarray = DEFAULT_ANCHOR_TRANS_SIGMA_M,
                        ) -> gtsam.PriorFactorPose3:
    """Weak ``PriorFactorPose3`` on the map anchor ``T_world_map``.

    It keeps the anchor determined before (and between) NAP3D factors; with a few good
    corrections the data dominate it.

    Args:
        anchor_key: ``M(0)``.
        T_world_map_guess: (4, 4) or ``Pose3``; identity when ``None`` (the field was
            trained in world coordinates up to a small error).
        rot_sigma_rad, trans_sigma_m: prior sigmas (scalar or (3,)), body frame of the map.
    """
    T_guess = np.eye(4) if T_world_map_guess is None else _as_T(T_world_map_guess, "T_world_map_guess")
    noise = noise_model(rot_sigma_rad=rot_sigma_rad, trans_sigma_m=trans_sigma_m)
    return gtsam.PriorFactorPose3(anchor_key, T_to_pose3(T_guess), noise)
