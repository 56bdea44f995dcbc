"""The refinement that makes the survey's keyframes agree: a bundle adjustment over every
verified match.

Each verified pair (consecutive keyframes and accepted loops) leaves its inlier pixel pairs.
Pixels that are the same keypoint of one keyframe chain matches across pairs into tracks (a
union-find over (keyframe, keypoint pixel)); a track seen twice in one keyframe is ambiguous
and dropped. Every track becomes a 3D landmark, every observation a GTSAM
``GenericStereoFactor3D``: the RGB-D frame as a virtual stereo camera (the right pixel
``u - f b / z``, as ORB-SLAM's RGB-D mode does), so the pixel residuals carry the
multi-view geometry and the disparity carries the depth (the metric scale) with the sensor's
noise that ORB-SLAM2 gives it (:class:`BundleSettings`). Huber-robust; the gauge is the
first keyframe, held by a prior.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from nap3d_graph.camera import DEPTH_SIGMA_Z2_PER_M, Intrinsics
from nap3d_graph.conventions import T_to_pose3, pose3_to_T

__all__ = ["PairMatches", "BundleSettings", "tracks_of", "bundle_adjust"]

log = logging.getLogger(__name__)


@dataclass
class PairMatches:
    """Inlier matches of keyframe positions ``a`` and ``b``: pixels ``uv_a``, ``uv_b`` (M, 2)
    and their depths ``z_a``, ``z_b`` (M,) metres."""

    a: int
    b: int
    uv_a: np.ndarray
    uv_b: np.ndarray
    z_a: np.ndarray
    z_b: np.ndarray


@dataclass(frozen=True)
class BundleSettings:
    """pixel_sigma: a keypoint's position noise (px) to start with; baseline_m: the depth
    sensor's baseline (Kinect v1's projector is 7.5 cm from its camera) and
    ``disparity_to_pixel``: the disparity's noise in units of the pixels', so the depth's
    sigma is ``disparity_to_pixel z^2 sigma_px / (f b)``. ORB-SLAM2's RGB-D model takes 1 (the
    virtual right keypoint as uncertain as the left: 2.6 cm at 1 m with 1 px on a Kinect); the
    sensor's own noise model says 1.4 mm. Neither is what the Kinect's depth agrees to across
    views: it is distorted across the image, so the more the adjustment follows it the more
    the survey takes the depth's shape. Measured (``benchmarks/map_bundle.py``): against
    fr1/desk's motion capture, the one reference independent of both the images and the depth,
    the survey's ATE falls from 2.43 cm (0.1) through 2.29 (1) to 2.00 (10) and 1.94 (30); on
    redkitchen against the SfM pseudo ground truth (built from the images) 3.73 -> 2.82 ->
    1.55 -> 1.99, while against KinectFusion's (built from the depth) it rises 2.83 -> 5.54.
    Default 10: the depth sets the scale and little else (26 cm at 1 m);
    huber_k: the robust kernel's threshold (whitened);
    min_track: keyframes a landmark must be seen in; iterations: LM's limit; vce_rounds:
    rounds of estimating the pixels' noise from the residuals (:func:`bundle_adjust`)."""

    pixel_sigma: float = 1.0
    baseline_m: float = 0.075
    disparity_to_pixel: float = 10.0
    huber_k: float = 1.345
    min_track: int = 2
    iterations: int = 50
    vce_rounds: int = 1


def tracks_of(pairs: list[PairMatches]) -> list[list[tuple[int, float, float, float]]]:
    """Tracks: lists of observations ``(keyframe, u, v, z)``, at most one per keyframe, seen
    in at least two keyframes."""
    parent: dict = {}
    obs: dict = {}

    def key(k: int, u: float, v: float):
        return (k, int(round(u * 64)), int(round(v * 64)))  # the same keypoint, to 1/64 px

    def find(x):
        root = x
        while parent[root] != root:
            root = parent[root]
        while parent[x] != root:  # path compression
            parent[x], x = root, parent[x]
        return root

    for p in pairs:
        for (ua, va), (ub, vb), za, zb in zip(p.uv_a, p.uv_b, p.z_a, p.z_b):
            ka, kb = key(p.a, ua, va), key(p.b, ub, vb)
            for k, u, v, z in ((ka, ua, va, za), (kb, ub, vb, zb)):
                if k not in parent:
                    parent[k] = k
                    obs[k] = (k[0], float(u), float(v), float(z))
            ra, rb = find(ka), find(kb)
            if ra != rb:
                parent[ra] = rb
    groups: dict = {}
    for k in parent:
        groups.setdefault(find(k), []).append(obs[k])
    tracks = []
    for members in groups.values():
        frames = [m[0] for m in members]
        if len(set(frames)) == len(frames) and len(frames) >= 2:
            tracks.append(sorted(members))
    return tracks


def _noise(sigma_px: float, sigma_d: float, huber_k: float):
    """The stereo observation's noise: pixels ``sigma_px``, disparity ``sigma_d`` (uR = uL - d,
    so the two horizontal pixels share uL's noise), Huber-robust."""
    import gtsam

    cov = np.array([[sigma_px**2, sigma_px**2, 0.0], [sigma_px**2, sigma_px**2 + sigma_d**2, 0.0],
                    [0.0, 0.0, sigma_px**2]])
    return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(huber_k),
                                          gtsam.noiseModel.Gaussian.Covariance(cov))


def _robust_sigma(residuals: np.ndarray) -> float:
    """1.4826 x the median absolute residual: a standard deviation that outliers do not move."""
    return float(1.4826 * np.median(np.abs(residuals)))


def bundle_adjust(T_map_key: np.ndarray, pairs: list[PairMatches], intrinsics: Intrinsics,
                  settings: BundleSettings | None = None) -> tuple[np.ndarray, dict]:
    """Refined keyframe poses (K, 4, 4) and a report (landmarks, observations, the pixel noise
    estimated from the residuals and the disparity's beside it, pose changes). Solved with the
    starting sigma, then again ``vce_rounds`` times with the pixels' robust residual spread as
    their sigma (the disparity's following it)."""
    import gtsam
    from gtsam.symbol_shorthand import L, X

    settings = settings or BundleSettings()
    tracks = [t for t in tracks_of(pairs) if len(t) >= settings.min_track]
    if not tracks:
        return T_map_key.copy(), {"landmarks": 0, "reason": "no track seen in two keyframes"}
    K = intrinsics
    calibration = gtsam.Cal3_S2Stereo(K.fx, K.fy, 0.0, K.cx, K.cy, settings.baseline_m)
    fb = K.fx * settings.baseline_m
    sigma_px = settings.pixel_sigma
    sigma_d = sigma_px * settings.disparity_to_pixel
    measured = []
    values = gtsam.Values()
    for k, T in enumerate(T_map_key):
        values.insert(X(k), T_to_pose3(T))
    for t, track in enumerate(tracks):
        k0, u0, v0, z0 = track[0]
        p_cam = np.array([(u0 - K.cx) * z0 / K.fx, (v0 - K.cy) * z0 / K.fy, z0])
        values.insert(L(t), T_map_key[k0][:3, :3] @ p_cam + T_map_key[k0][:3, 3])
        measured.extend((k, t, u, u - fb / z, v) for k, u, v, z in track)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(settings.iterations)
    history = []
    result = values
    for _ in range(settings.vce_rounds + 1):
        noise = _noise(sigma_px, sigma_d, settings.huber_k)
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.PriorFactorPose3(X(0), T_to_pose3(T_map_key[0]), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
        for k, t, u, ur, v in measured:
            graph.add(gtsam.GenericStereoFactor3D(gtsam.StereoPoint2(u, ur, v), noise, X(k), L(t), calibration))
        try:
            result = gtsam.LevenbergMarquardtOptimizer(graph, result, params).optimize()
        except RuntimeError as exc:  # a cheirality failure or an indeterminate system: keep the graph's poses
            log.warning("bundle adjustment failed (%s): the pose graph's poses are kept", exc)
            return T_map_key.copy(), {"landmarks": len(tracks), "observations": len(measured), "reason": str(exc)}
        pixel, disparity = _residuals(result, measured, calibration)
        history.append({"sigma_px": sigma_px, "sigma_disparity_px": sigma_d,
                        "residual_px": _robust_sigma(pixel), "residual_disparity_px": _robust_sigma(disparity)})
        sigma_px = max(_robust_sigma(pixel), 0.05)
        sigma_d = sigma_px * settings.disparity_to_pixel
    T_out = np.stack([pose3_to_T(result.atPose3(X(k))) for k in range(len(T_map_key))])
    moved = np.linalg.norm(T_out[:, :3, 3] - T_map_key[:, :3, 3], axis=1)
    report = {"landmarks": len(tracks), "observations": len(measured), "noise_rounds": history,
              "depth_sigma_at_1m_mm": history[-1]["sigma_disparity_px"] / fb * 1000,
              "sensor_model_depth_sigma_at_1m_mm": DEPTH_SIGMA_Z2_PER_M * 1000,
              "median_keyframe_move_mm": float(np.median(moved) * 1000),
              "max_keyframe_move_mm": float(moved.max() * 1000), "settings": settings.__dict__}
    return T_out, report


def _residuals(values, measured, calibration) -> tuple[np.ndarray, np.ndarray]:
    """Pixel residuals (2M,) and disparity residuals (M,) of every observation at ``values``."""
    import gtsam
    from gtsam.symbol_shorthand import L, X

    pixel, disparity = [], []
    for k, t, u, ur, v in measured:
        try:
            p = gtsam.StereoCamera(values.atPose3(X(k)), calibration).project(values.atPoint3(L(t)))
        except RuntimeError:  # behind the camera
            continue
        pixel += [u - p.uL(), v - p.v()]
        disparity.append((u - ur) - (p.uL() - p.uR()))
    return np.asarray(pixel), np.asarray(disparity)
