"""Estimators compared on one measurement stream (``nap3d-graph compare``).

One module each: :mod:`.odometry_only` (the baseline), :mod:`.eskf` (filterpy error-state
EKF, odometry or IMU process model), :mod:`.navstate_ekf` (GTSAM's ``NavStateImuEKF``, IMU
path), :mod:`.graph` (iSAM2 causal and final; batch Levenberg-Marquardt). The interface is
in :mod:`.base`; ``examples/own_estimator.py`` plugs a user's own one in.
"""

from __future__ import annotations

import numpy as np

from .base import Estimator, EstimatorResult, MeasurementStream, run_estimator, stream_from_run
from .eskf import ErrorStateEKF, ImuErrorStateEKF
from .graph import BatchLM, GraphModel, Isam2Estimator
from .navstate_ekf import NavStateEKF
from .odometry_only import OdometryOnly

__all__ = ["Estimator", "EstimatorResult", "MeasurementStream", "run_estimator", "stream_from_run",
           "OdometryOnly", "ErrorStateEKF", "ImuErrorStateEKF", "NavStateEKF", "Isam2Estimator", "BatchLM",
           "GraphModel", "default_estimators"]


def default_estimators(stream: MeasurementStream) -> list:
    """Every estimator that applies to ``stream``, the baseline first."""
    if stream.imu is None:
        return [OdometryOnly(), ErrorStateEKF(), Isam2Estimator(), BatchLM()]
    out = [OdometryOnly(), ImuErrorStateEKF()]
    if np.allclose(np.asarray(stream.imu.config.T_cam_imu, float), np.eye(4)):
        out.append(NavStateEKF())
    return out + [Isam2Estimator(), BatchLM()]
