"""The run's GTSAM solves, apart from the run's bookkeeping: iSAM2's settings, rebuilding an
iSAM2 whose incremental step failed, and the final graduated non-convexity over the NAP3D
corrections."""

from __future__ import annotations

import gtsam
import numpy as np

__all__ = ["isam2_params", "rebuilt_isam2", "gnc_solve"]

#: GTSAM's default: check for relinearisation every 10th update.
RELINEARIZE_SKIP = 10


def isam2_params(relinearize_threshold: float, factorization: str = "CHOLESKY") -> gtsam.ISAM2Params:
    """Millimetre corrections need a fine threshold (GTSAM examples use 0.01, which would leave
    poses linearised a centimetre away from where the corrections put them); checking every
    10th update keeps an update near a millisecond at thousands of poses (the run relinearises
    fully at its end)."""
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(relinearize_threshold)
    params.relinearizeSkip = RELINEARIZE_SKIP
    params.setFactorization(factorization)
    return params


def rebuilt_isam2(failed: gtsam.ISAM2, factors: gtsam.NonlinearFactorGraph, values: gtsam.Values,
                  relinearize_threshold: float) -> gtsam.ISAM2:
    """A fresh iSAM2 holding ``factors`` (everything the failed one was given) at their batch
    solution. iSAM2's incremental elimination can fail on a system that is well posed as a
    whole (seen on the IMU path: a loosely weighted correction at the first keyframe beside
    the bias random walk's ~1e12 information); Levenberg-Marquardt damps what is nearly
    indeterminate, and QR factorisation keeps the new iSAM2 stable where Cholesky was not."""
    initial = gtsam.Values(values)
    try:
        initial.update(failed.calculateEstimate())  # the estimate so far, where it has one
    except RuntimeError:
        pass  # the failed iSAM2 cannot even give its estimate: start from the initial values
    solution = gtsam.LevenbergMarquardtOptimizer(factors, initial).optimize()
    isam = gtsam.ISAM2(isam2_params(relinearize_threshold, "QR"))
    isam.update(factors, solution)
    return isam


def gnc_solve(factors: list, estimate: gtsam.Values, robust: list[int], inlier_p: float) -> tuple[gtsam.Values,
                                                                                                np.ndarray]:
    """Graduated non-convexity (TLS) over ``factors``: those indexed by ``robust`` may be
    outliers, the others (odometry, priors) are known inliers. Returns the solution and each
    factor's final weight (below 0.5: weighed out)."""
    graph = gtsam.NonlinearFactorGraph()
    for factor in factors:
        graph.add(factor)
    params = gtsam.GncLMParams()
    params.setLossType(gtsam.GncLossType.TLS)
    params.setKnownInliers([k for k in range(graph.size()) if k not in set(robust)])
    optimizer = gtsam.GncLMOptimizer(graph, estimate, params)
    optimizer.setInlierCostThresholdsAtProbability(inlier_p)
    result = optimizer.optimize()
    return result, np.asarray(optimizer.getWeights())
