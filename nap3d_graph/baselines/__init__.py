"""NAP3D's peers behind one interface: every method corrects the same real frame against the
same rendered view and returns an :class:`~nap3d_graph.results.Alignment`
(``T_real_rendered``, covariance where the method has one, success, reason, timings).

:data:`PEERS` names them; :func:`run_peers` runs a selection on one frame. The three NAP3D
variants and PnP-RANSAC share one set of SIFT matches (as Evaluation K does), so they
differ only in what they do with them.
"""

from __future__ import annotations

import time

import numpy as np

from nap3d_graph import correct_pose

from ..camera import RenderedView, RGBDFrame
from ..conventions import inv_T
from ..nap3d.align import align_correspondences, prepare_correspondences
from ..nap3d.config import AlignConfig
from ..results import Alignment
from .dense_rgbd import DenseRgbdConfig, dense_rgbd_align
from .gicp import GicpConfig, gicp_align
from .photometric import PhotometricConfig, photometric_align
from .pnp import pnp_from_correspondences

__all__ = ["PEERS", "run_peers", "gicp_align", "GicpConfig", "dense_rgbd_align", "DenseRgbdConfig",
           "photometric_align", "PhotometricConfig"]

#: name -> what it is
PEERS = {
    "nap3d-plain": "the paper's NAP3D: RANSAC with the anisotropic residual + opacity-weighted Procrustes",
    "nap3d-refined": "NAP3D refined over every inlier's pixel and depth residuals (the project's default)",
    "nap3d-iter": "correct_pose: refined NAP3D, re-rendered at the corrected pose (up to 3 rounds)",
    "pnp-ransac": "PnP-RANSAC + LM on the same matches (rendered 3D, real 2D)",
    "gicp": "dense generalized ICP between the rendered and the real depth (small_gicp)",
    "dense-rgbd": "dense direct RGB-D alignment (OpenCV cv2.Odometry RGB_DEPTH, as DVO)",
    "photometric": "iNeRF: the pose refined by Adam on the colour error through the differentiable grid field",
}


def run_peers(real: RGBDFrame, view: RenderedView, methods=tuple(PEERS), field=None,
              T_world_cam_est: np.ndarray | None = None, align_config=None) -> tuple[dict[str, Alignment], object]:
    """Every method of ``methods`` on one frame: ``({name: Alignment}, correspondences)``
    (the shared feature correspondences, or None when matching failed). ``nap3d-iter`` and
    ``photometric`` need ``field`` and ``T_world_cam_est`` (they re-render; the photometric
    peer needs a differentiable :class:`~nap3d_graph.fields.grid.GridField`)."""
    from dataclasses import replace

    unknown = set(methods) - set(PEERS)
    if unknown:
        raise ValueError(f"unknown method(s) {sorted(unknown)}; choose from {list(PEERS)}")
    align_config = align_config or AlignConfig()
    out: dict[str, Alignment] = {}
    timings: dict = {}
    t0 = time.perf_counter()
    corr, reason = prepare_correspondences(real, view, align_config, timings)
    shared_s = time.perf_counter() - t0  # features + matching, charged to every feature method
    feature_methods = {
        "nap3d-plain": lambda: align_correspondences(corr, real.intrinsics, replace(align_config, method="plain"), {}),
        "nap3d-refined": lambda: align_correspondences(corr, real.intrinsics, align_config, {}),
        "pnp-ransac": lambda: pnp_from_correspondences(corr, real.intrinsics, None, align_config, {}),
    }
    for name in methods:
        t0 = time.perf_counter()
        if name in feature_methods:
            result = Alignment.failure(reason, method=name) if corr is None else _safe(feature_methods[name], name)
            result.timings_s["total"] = shared_s + time.perf_counter() - t0
        elif name == "nap3d-iter":
            result = _iterated(real, field, T_world_cam_est, align_config)
            result.timings_s["total"] = time.perf_counter() - t0
        elif name == "photometric":
            result = (Alignment.failure("the photometric peer needs the field and the believed pose", method=name)
                      if field is None or T_world_cam_est is None
                      else _safe(lambda: photometric_align(real, view, field, T_world_cam_est), name))
            result.timings_s["total"] = time.perf_counter() - t0
        else:
            run = gicp_align if name == "gicp" else dense_rgbd_align
            result = _safe(lambda: run(real, view), name)
            result.timings_s["total"] = time.perf_counter() - t0
        result.method = name
        out[name] = result
    return out, corr


def _safe(fn, name: str) -> Alignment:
    import cv2

    try:
        return fn()
    except (ValueError, np.linalg.LinAlgError, cv2.error) as exc:
        return Alignment.failure(f"numerical failure: {exc}", method=name)


def _iterated(real, field, T_world_cam_est, align_config) -> Alignment:
    """``correct_pose`` as an alignment against the view at ``T_world_cam_est``."""
    if field is None or T_world_cam_est is None:
        return Alignment.failure("nap3d-iter needs the field and the believed pose", method="nap3d-iter")
    c = correct_pose(real, field, T_world_cam_est, iterations=3, config=align_config)
    if not c.success:
        return Alignment.failure(c.reason, method="nap3d-iter")
    a = c.alignment
    return Alignment(T_real_rendered=inv_T(c.T_world_cam_corrected) @ np.asarray(T_world_cam_est, dtype=float),
                     covariance=c.covariance, num_matches=a.num_matches, num_inliers=a.num_inliers,
                     inlier_rmse_m=a.inlier_rmse_m, success=True, method="nap3d-iter",
                     diagnostics={"rounds": c.iterations})
