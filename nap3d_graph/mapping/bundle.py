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

A rolling-shutter colour camera (the Kinect's, a D435's) read each keyframe's rows one after
another while it moved: a keypoint on a lower row was seen later, from elsewhere, than the
keyframe's pose says. Given each keyframe's body twist, every observation is moved to its
keyframe's middle row (:mod:`nap3d_graph.nap3d.rolling_shutter`) before the adjustment. The
readout time is the recording's own: solved at each readout of a grid and kept where the
pixels agree best (no ground truth; a global-shutter camera's is 0).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from nap3d_graph.camera import DEPTH_SIGMA_Z2_PER_M, Intrinsics, backproject, project
from nap3d_graph.conventions import T_to_pose3, inv_T, pose3_to_T
from nap3d_graph.nap3d.rolling_shutter import exp_apply

from .pose_graph import Edge, between_factor

__all__ = ["PairMatches", "BundleSettings", "tracks_of", "bundle_adjust", "keyframe_twists", "pair_reprojection_px"]

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
    the survey takes the depth's shape. Measured by ``benchmarks/map_bundle.py`` (the results
    page tables it): against fr1/desk's motion capture, the one reference independent of both
    the images and the depth, the survey's ATE falls as the weight goes from 0.1 to 30, with the
    rolling shutter undone or not; on redkitchen the SfM pseudo ground truth (built from the
    images) also prefers the higher weights, while KinectFusion's (built from the depth) does
    not. Default 10: the depth sets the scale and little else (26 cm at 1 m);
    huber_k: the robust kernel's threshold (whitened);
    min_track: keyframes a landmark must be seen in; iterations: LM's limit; vce_rounds:
    rounds of estimating the pixels' noise from the residuals (:func:`bundle_adjust`);
    admit_factor: a loop the pose graph turned away is let into the adjustment when its own
    matches agree with the adjusted poses (:func:`pair_reprojection_px`) within this many
    times the kept loops' median (0: never);
    readout_s: the colour camera's rolling shutter, seconds from its first row to its last (0:
    a global shutter; None: estimated, the adjustment solved at each of ``readout_grid_s``
    and at the parabola's vertex through the best three, and the readout whose pixels agree
    best kept; ``docs/mapping.md``, "The rolling shutter")."""

    pixel_sigma: float = 1.0
    baseline_m: float = 0.075
    disparity_to_pixel: float = 10.0
    huber_k: float = 1.345
    min_track: int = 2
    iterations: int = 50
    vce_rounds: int = 1
    admit_factor: float = 3.0
    readout_s: float | None = None
    readout_grid_s: tuple[float, ...] = (0.0, 0.01, 0.02, 0.03, 0.04)


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


def keyframe_twists(T_odom_cam: np.ndarray, stamps_s: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """Each keyframe's body twist per second (K, 6) (GTSAM order ``[omega, v]``, camera frame)
    from the survey's odometry (N, 4, 4) over its neighbours (frames ``key - 1`` and
    ``key + 1``, one side at either end) and the frames' stamps (N,) seconds. Only relative
    motion is used, so the odometry's drift does not enter. Zero where it cannot be told."""
    import gtsam

    n = len(T_odom_cam)
    twists = np.zeros((len(keys), 6))
    for row, key in enumerate(np.asarray(keys, dtype=int)):
        a, b = max(key - 1, 0), min(key + 1, n - 1)
        dt = float(stamps_s[b] - stamps_s[a])
        if b == a or not dt > 0 or not (np.all(np.isfinite(T_odom_cam[a])) and np.all(np.isfinite(T_odom_cam[b]))):
            continue
        twists[row] = gtsam.Pose3.Logmap(T_to_pose3(inv_T(T_odom_cam[a]) @ T_odom_cam[b])) / dt
    return twists


def _mid_readout_points(k: np.ndarray, uv: np.ndarray, z: np.ndarray, twists: np.ndarray | None,
                        readout_s: float, intrinsics: Intrinsics) -> np.ndarray:
    """Keypoints ``uv`` (N, 2) with depths ``z`` (N,) of keyframes ``k`` (N,) as camera points
    (N, 3) at their keyframe's middle row, moved along ``twists`` (K, 6) per second over
    ``readout_s`` (first row to last); as read without twists or with a global shutter."""
    points = backproject(uv, z, intrinsics)
    if twists is None or readout_s == 0.0 or len(points) == 0:
        return points
    dt = (np.asarray(uv, dtype=float)[:, 1] / float(intrinsics.height) - 0.5) * readout_s
    return exp_apply(twists[k] * dt[:, None], points)


def _at_mid_readout(measured: list, twists: np.ndarray, readout_s: float, intrinsics: Intrinsics,
                    baseline_m: float) -> list:
    """The stereo observations ``(k, t, uL, uR, v)`` moved from their rows' instants to their
    keyframes' middle row (``twists`` (K, 6) per second, ``readout_s`` first row to last)."""
    if readout_s == 0.0 or not measured:
        return measured
    fb = intrinsics.fx * baseline_m
    obs = np.asarray([m[2:] for m in measured], dtype=float)  # (M, 3): uL, uR, v
    k = np.asarray([m[0] for m in measured], dtype=int)
    points = _mid_readout_points(k, obs[:, [0, 2]], fb / (obs[:, 0] - obs[:, 1]), twists, readout_s, intrinsics)
    uv, z = project(points, intrinsics)
    return [(m[0], m[1], float(ui), float(ui - fb / zi), float(vi)) for m, (ui, vi), zi in zip(measured, uv, z)]


def pair_reprojection_px(pair: PairMatches, T_map_key: np.ndarray, intrinsics: Intrinsics,
                         twists: np.ndarray | None = None, readout_s: float = 0.0) -> float:
    """How well a pair's matches agree with keyframe poses ``T_map_key`` (K, 4, 4): the median
    distance (px) from each match in keyframe b to where its keypoint in keyframe a, placed by
    its depth, lands in b (both moved to their middle rows along ``twists`` over
    ``readout_s``). The depth's noise is in it, so kept loops show a few pixels, and a loop
    between places that are not the same tens to hundreds. NaN without matches."""
    if len(pair.z_a) == 0:
        return float("nan")
    n = len(pair.z_a)
    p_a = _mid_readout_points(np.full(n, pair.a), pair.uv_a, pair.z_a, twists, readout_s, intrinsics)
    p_b = _mid_readout_points(np.full(n, pair.b), pair.uv_b, pair.z_b, twists, readout_s, intrinsics)
    T_b_a = inv_T(T_map_key[pair.b]) @ T_map_key[pair.a]
    uv_in_b, z_in_b = project(p_a @ T_b_a[:3, :3].T + T_b_a[:3, 3], intrinsics)
    uv_b, _ = project(p_b, intrinsics)
    distance = np.linalg.norm(uv_in_b - uv_b, axis=1)
    distance[~(z_in_b > 0)] = np.inf  # behind keyframe b: as far off as it gets
    return float(np.median(distance))


def agreeing_pairs(candidates: list[PairMatches], kept: list[PairMatches], T_map_key: np.ndarray,
                   intrinsics: Intrinsics, factor: float, twists: np.ndarray | None = None,
                   readout_s: float = 0.0) -> tuple[np.ndarray, np.ndarray, float]:
    """Which ``candidates`` agree with the poses ``T_map_key`` as well as the ``kept`` pairs
    do: ``(agree (C,) bool, their reprojection px (C,), the gate px)``, the gate ``factor``
    times the kept pairs' median :func:`pair_reprojection_px` (nothing agrees without kept
    pairs or with ``factor`` 0)."""
    px = np.array([pair_reprojection_px(c, T_map_key, intrinsics, twists, readout_s) for c in candidates])
    kept_px = [pair_reprojection_px(k, T_map_key, intrinsics, twists, readout_s) for k in kept]
    kept_px = [v for v in kept_px if np.isfinite(v)]
    if not kept_px or factor <= 0 or not len(candidates):
        return np.zeros(len(candidates), dtype=bool), px, float("nan")
    gate = factor * float(np.median(kept_px))
    return np.isfinite(px) & (px <= gate), px, gate


def bundle_adjust(T_map_key: np.ndarray, pairs: list[PairMatches], intrinsics: Intrinsics,
                  settings: BundleSettings | None = None, twists: np.ndarray | None = None,
                  odometry: Sequence[Edge] = ()) -> tuple[np.ndarray, dict]:
    """Refined keyframe poses (K, 4, 4) and a report (landmarks, observations, the pixel noise
    estimated from the residuals and the disparity's beside it, the rolling shutter's readout
    and its search, pose changes). Solved with the starting sigma, then again ``vce_rounds``
    times with the pixels' robust residual spread as their sigma (the disparity's following
    it). ``twists`` (K, 6): each keyframe's body twist per second
    (:func:`keyframe_twists`); without them the camera is taken as a global shutter.
    ``odometry``: the chain's edges the keyframes' own matches did not measure (kind
    'odometry': the frames between them did), as between factors with their covariances:
    without them a keyframe that sees little (a blank wall, the edge of a loss) is held by a
    few tracks alone and can float far from where its neighbours and its odometry put it."""
    import gtsam
    from gtsam.symbol_shorthand import L, X

    settings = settings or BundleSettings()
    tracks = [t for t in tracks_of(pairs) if len(t) >= settings.min_track]
    if not tracks:
        return T_map_key.copy(), {"landmarks": 0, "reason": "no track seen in two keyframes"}
    K = intrinsics
    calibration = gtsam.Cal3_S2Stereo(K.fx, K.fy, 0.0, K.cx, K.cy, settings.baseline_m)
    fb = K.fx * settings.baseline_m
    values = gtsam.Values()
    for t, track in enumerate(tracks):
        k0, u0, v0, z0 = track[0]
        p_cam = np.array([(u0 - K.cx) * z0 / K.fx, (v0 - K.cy) * z0 / K.fy, z0])
        values.insert(L(t), T_map_key[k0][:3, :3] @ p_cam + T_map_key[k0][:3, 3])
    measured = [(k, t, u, u - fb / z, v) for t, track in enumerate(tracks) for k, u, v, z in track]

    def solve(readout_s: float):
        return _solve(T_map_key, values, _at_mid_readout(measured, twists, readout_s, K, settings.baseline_m)
                      if twists is not None else measured, calibration, settings, odometry)

    search: list = []
    if twists is None or settings.readout_s == 0.0:
        readout, (result, history) = 0.0, solve(0.0)
    elif settings.readout_s is not None:
        readout, (result, history) = float(settings.readout_s), solve(float(settings.readout_s))
    else:
        readout, result, history, search = _readout_search(solve, settings.readout_grid_s)
    if result is None:
        return T_map_key.copy(), {"landmarks": len(tracks), "observations": len(measured), "reason": history}
    T_out = np.stack([pose3_to_T(result.atPose3(X(k))) for k in range(len(T_map_key))])
    moved = np.linalg.norm(T_out[:, :3, 3] - T_map_key[:, :3, 3], axis=1)
    report = {"landmarks": len(tracks), "observations": len(measured), "noise_rounds": history,
              "readout_s": readout, "readout_search": search,
              "depth_sigma_at_1m_mm": history[-1]["sigma_disparity_px"] / fb * 1000,
              "sensor_model_depth_sigma_at_1m_mm": DEPTH_SIGMA_Z2_PER_M * 1000,
              "median_keyframe_move_mm": float(np.median(moved) * 1000),
              "max_keyframe_move_mm": float(moved.max() * 1000), "settings": settings.__dict__}
    return T_out, report


def _readout_search(solve, grid_s: tuple[float, ...]):
    """``(readout, result, history, search)``: the adjustment solved at each readout of
    ``grid_s`` and at the vertex of the parabola through the best and its two neighbours;
    the one whose pixels agree best (the last round's robust residual) kept. ``search``:
    ``[[readout_s, residual_px], ...]``."""
    solved = {float(readout): solve(float(readout)) for readout in grid_s}
    residual = {r: h[-1]["residual_px"] for r, (result, h) in solved.items() if result is not None}
    if not residual:  # every solve failed: the first one's reason
        return 0.0, None, solved[float(grid_s[0])][1], []
    grid = sorted(residual)
    best = min(grid, key=lambda r: residual[r])
    i = grid.index(best)
    if 0 < i < len(grid) - 1:
        x = np.array(grid[i - 1:i + 2])
        a, b, _ = np.polyfit(x, [residual[r] for r in x], 2)
        if a > 0:
            vertex = float(np.clip(-b / (2 * a), x[0], x[2]))
            if all(abs(vertex - r) > 1e-4 for r in grid):
                result, history = solve(vertex)
                if result is not None:
                    solved[vertex] = (result, history)
                    residual[vertex] = history[-1]["residual_px"]
    best = min(residual, key=lambda r: residual[r])
    search = [[round(r, 4), round(residual[r], 4)] for r in sorted(residual)]
    log.info("rolling shutter: readout %.0f ms (pixel residual %.3f px; global shutter %.3f px)", best * 1000,
             residual[best], residual.get(0.0, float("nan")))
    return best, solved[best][0], solved[best][1], search


def _solve(T_map_key: np.ndarray, landmarks, measured: list, calibration, settings: BundleSettings,
           odometry: Sequence[Edge] = ()):
    """``(values, history)`` of the adjustment over ``measured`` (and the ``odometry`` edges)
    from the keyframes' poses and ``landmarks``; ``(None, reason)`` when GTSAM fails (a
    cheirality failure or an indeterminate system)."""
    import gtsam
    from gtsam.symbol_shorthand import L, X

    values = gtsam.Values(landmarks)
    for k, T in enumerate(T_map_key):
        values.insert(X(k), T_to_pose3(T))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(settings.iterations)
    sigma_px = settings.pixel_sigma
    sigma_d = sigma_px * settings.disparity_to_pixel
    history = []
    result = values
    for _ in range(settings.vce_rounds + 1):
        noise = _noise(sigma_px, sigma_d, settings.huber_k)
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.PriorFactorPose3(X(0), T_to_pose3(T_map_key[0]), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
        for k, t, u, ur, v in measured:
            graph.add(gtsam.GenericStereoFactor3D(gtsam.StereoPoint2(u, ur, v), noise, X(k), L(t), calibration))
        for edge in odometry:
            graph.add(between_factor(edge))
        try:
            result = gtsam.LevenbergMarquardtOptimizer(graph, result, params).optimize()
        except RuntimeError as exc:
            log.warning("bundle adjustment failed (%s): the pose graph's poses are kept", exc)
            return None, str(exc)
        pixel, disparity = _residuals(result, measured, calibration)
        history.append({"sigma_px": sigma_px, "sigma_disparity_px": sigma_d,
                        "residual_px": _robust_sigma(pixel), "residual_disparity_px": _robust_sigma(disparity)})
        sigma_px = max(_robust_sigma(pixel), 0.05)
        sigma_d = sigma_px * settings.disparity_to_pixel
    return result, history


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
