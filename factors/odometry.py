"""Odometry (relative pose) and plain pose-prior factors."""

from __future__ import annotations

import logging
from typing import Optional, Union

import gtsam
import numpy as np

from nap3d_graph.conventions import T_to_pose3

from .noise import noise_model

__all__ = ["odometry_factor", "pose_prior_factor"]

logger = logging.getLogger(__name__)

PoseLike = Union[np.ndarray, gtsam.Pose3]
SigmaLike = Union[float, np.ndarray]


def _as_pose3(pose: PoseLike) -> gtsam.Pose3:
    return pose if isinstance(pose, gtsam.Pose3) else T_to_pose3(pose)


def _noise(covariance: Optional[np.ndarray], rot_sigma_rad: Optional[SigmaLike],
           trans_sigma_m: Optional[SigmaLike], robust: Optional[str],
           robust_threshold: Optional[float]) -> gtsam.noiseModel.Base:
    # noise_model() rejects "both" and "neither", so the caller's mistake gets one message.
    return noise_model(covariance=covariance, rot_sigma_rad=rot_sigma_rad,
                       trans_sigma_m=trans_sigma_m, robust=robust,
                       robust_threshold=robust_threshold)


def odometry_factor(key_i: int, key_j: int, T_i_j: PoseLike,
                    covariance: Optional[np.ndarray] = None, *,
                    rot_sigma_rad: Optional[SigmaLike] = None,
                    trans_sigma_m: Optional[SigmaLike] = None,
                    robust: Optional[str] = None,
                    robust_threshold: Optional[float] = None) -> gtsam.BetweenFactorPose3:
    """``BetweenFactorPose3(key_i, key_j, T_i_j)``: measured motion from pose i to pose j.

    Args:
        key_i, key_j: pose keys (variables ``T_world_cam_i``, ``T_world_cam_j``).
        T_i_j: (4, 4) or ``Pose3``, ``inv(T_world_cam_i) @ T_world_cam_j`` as measured
            (pose j expressed in camera frame i).
        covariance: (6, 6) of ``T_i_j``, GTSAM order (right perturbation, frame j); or
        rot_sigma_rad, trans_sigma_m: sigmas (scalar or (3,)) instead of a covariance.
        robust, robust_threshold: optional kernel (see :func:`noise_model`); odometry is
            usually trusted, hence no kernel by default.
    """
    noise = _noise(covariance, rot_sigma_rad, trans_sigma_m, robust, robust_threshold)
    return gtsam.BetweenFactorPose3(key_i, key_j, _as_pose3(T_i_j), noise)


def pose_prior_factor(key: int, T_world_cam: PoseLike,
                      covariance: Optional[np.ndarray] = None, *,
                      rot_sigma_rad: Optional[SigmaLike] = None,
                      trans_sigma_m: Optional[SigmaLike] = None,
                      robust: Optional[str] = None,
                      robust_threshold: Optional[float] = None) -> gtsam.PriorFactorPose3:
    """``PriorFactorPose3(key, T_world_cam)``, e.g. the start pose ``X(0)``.

    Args:
        key: pose key.
        T_world_cam: (4, 4) or ``Pose3``.
        covariance / rot_sigma_rad, trans_sigma_m / robust: as in :func:`odometry_factor`.
    """
    noise = _noise(covariance, rot_sigma_rad, trans_sigma_m, robust, robust_threshold)
    return gtsam.PriorFactorPose3(key, _as_pose3(T_world_cam), noise)
