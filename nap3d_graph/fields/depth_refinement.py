"""Training poses made consistent with the depth they saw: dense depth alignment between
neighbouring training frames and a pose graph that holds them to their input poses.

Motion capture places each frame to about a centimetre, but at the wrong instant for a
rolling-shutter, motion-blurred Kinect the same surface seen by two frames half a second
apart lands 6 mm apart (median; fr1/desk at the best global timing), and in fast turns
centimetres apart. Depth alignment measures the motion between two overlapping frames far
better than that: each pair's first depth is moved into the second frame's input pose
(:func:`~nap3d_graph.camera.warp_depth`), OpenCV's ICP (``cv2.Odometry``, depth only, over an
image pyramid) measures what remains, and the pair's relative pose is corrected by it. A GTSAM
graph then weighs every training frame's input pose (a prior: what the caller knows of its
poses) against the pairs' relative poses (robust between factors), so the frames agree with
each other where their depths overlap while the whole set stays where the input put it (the
priors hold the gauge: the field stays in the recording's ground-truth frame).

Poses are the depth's capture instant's (``timing.depth_offset_s``); the correction of each
frame is a body-frame ``D`` (refined pose = input pose @ D), applied to the frame's colour
instant as well (:class:`~nap3d_graph.fields.pose_refinement.PoseCorrectedSequence`).

This is the self-consistent map of the map-then-align refinement
(:mod:`~nap3d_graph.fields.pose_refinement`) without a map: the depth frames themselves are
the model each frame is aligned to.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from nap3d_graph.datasets.depth_timing import CaptureTiming
from nap3d_graph.factors import odometry_factor, pose_prior_factor
from nap3d_graph.progress import progress_bar

from ..camera import Intrinsics, backproject_depth, warp_depth
from ..conventions import T_to_pose3, inv_T, pose3_to_T, pose_error, rigid_transform_problem

__all__ = ["DepthRefinementConfig", "refine_poses_by_depth"]

log = logging.getLogger(__name__)


@dataclass
class DepthRefinementConfig:
    """neighbours: each training frame is aligned to the ones this many training frames later.
    width: the depth images' width for the alignment (pixels; height in proportion).
    input_sigma_m / input_sigma_rad: the input poses' own error per axis (what the caller knows
    of its motion capture or tracker). pair_sigma_m / pair_sigma_rad: an aligned pair's relative
    pose error per axis. max_pair_m / max_pair_deg: an alignment that moves the pair farther
    than this from its input is refused (ICP slid away). rounds: align and solve again from
    the refined poses. A pair's covariance is what its geometry constrains (point-to-plane:
    a flat wall leaves the motion along it free), from the destination's surface normals with
    ``point_sigma_m`` per point and ``independent_points`` (the depth's errors are correlated
    over a frame, so thousands of pixels are worth far fewer independent measurements), plus
    ``pair_sigma_*`` as a floor."""

    neighbours: tuple[int, ...] = (1, 2, 4, 8)
    width: int = 320
    input_sigma_m: float = 0.01
    input_sigma_rad: float = 0.0087
    pair_sigma_m: float = 0.002
    pair_sigma_rad: float = 0.0017
    point_sigma_m: float = 0.004
    independent_points: int = 50
    max_pair_m: float = 0.08
    max_pair_deg: float = 6.0
    rounds: int = 2

    def to_dict(self) -> dict:
        from dataclasses import asdict

        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}


class _PairAligner:
    """Depth-only ICP between two depth images of one camera (cv2.Odometry)."""

    def __init__(self, intrinsics: Intrinsics):
        import cv2

        settings = cv2.OdometrySettings()
        settings.setCameraMatrix(intrinsics.K.astype(np.float32))
        self._odometry = cv2.Odometry(cv2.OdometryType_DEPTH, settings, cv2.OdometryAlgoType_COMMON)
        self.intrinsics = intrinsics

    def residual(self, depth_src: np.ndarray, depth_dst: np.ndarray, T_dst_src: np.ndarray) -> np.ndarray | None:
        """``D`` (4, 4) such that ``D @ T_dst_src`` maps the source camera's points onto the
        destination's surfaces (None when the alignment fails): the source depth is first moved
        by ``T_dst_src``, so ICP only measures what that motion got wrong."""
        import cv2

        warped = warp_depth(depth_src, self.intrinsics, T_dst_src).astype(np.float32)
        if np.count_nonzero(warped) < 0.05 * warped.size:
            return None
        src, dst = cv2.OdometryFrame(warped), cv2.OdometryFrame(depth_dst)
        try:
            self._odometry.prepareFrames(src, dst)
            ok, Rt = self._odometry.compute(src, dst)
        except cv2.error as exc:
            log.debug("depth alignment failed: %s", str(exc).splitlines()[0])
            return None
        Rt = np.asarray(Rt, dtype=float)
        # A failed solve can hand back anything: keep only a rigid transform.
        return Rt if ok and Rt.shape == (4, 4) and not rigid_transform_problem(Rt, tolerance=1e-4) else None


def _small_depths(sequence, frames: np.ndarray, width: int, scale: float) -> tuple[dict, Intrinsics]:
    import cv2

    K = sequence.intrinsics
    small = K.scaled(width, int(round(K.height * width / K.width))) if K.width > width else K
    depths = {}
    for i in frames:
        depth = np.nan_to_num(sequence[int(i)].depth_m, nan=0.0).astype(np.float32) * np.float32(scale)
        if small is not K:  # nearest: never blend depth across an edge
            depth = cv2.resize(depth, (small.width, small.height), interpolation=cv2.INTER_NEAREST)
        depths[int(i)] = depth
    return depths, small


def _surface_normals(depth: np.ndarray, intrinsics: Intrinsics, stride: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Points (M, 3) and unit normals (M, 3) of a depth image (camera frame), every
    ``stride``-th pixel where the surface is continuous (central differences; depth jumps of
    more than 5% left out)."""
    h, w = depth.shape
    points, _ = backproject_depth(depth, intrinsics, 1)  # every valid pixel, row-major
    grid = np.full((h, w, 3), np.nan)
    valid = depth > 0
    grid[valid] = points
    du = grid[1:-1, 2:] - grid[1:-1, :-2]
    dv = grid[2:, 1:-1] - grid[:-2, 1:-1]
    normal = np.cross(du, dv)
    centre = grid[1:-1, 1:-1]
    z = depth[1:-1, 1:-1]
    smooth = (np.abs(depth[1:-1, 2:] - depth[1:-1, :-2]) < 0.05 * z) & (np.abs(depth[2:, 1:-1] - depth[:-2, 1:-1]) < 0.05 * z)
    keep = np.zeros_like(z, dtype=bool)
    keep[::stride, ::stride] = True
    keep &= smooth & np.all(np.isfinite(normal), axis=2) & (z > 0)
    n = normal[keep]
    length = np.linalg.norm(n, axis=1)
    ok = length > 0
    return centre[keep][ok], n[ok] / length[ok, None]


def _pair_covariance(depth_dst: np.ndarray, intrinsics: Intrinsics, config: DepthRefinementConfig) -> np.ndarray:
    """(6, 6) covariance (GTSAM order, destination camera frame) of a point-to-plane
    alignment onto ``depth_dst``: each surface point constrains the motion along its normal
    (Jacobian ``[p x n, n]``); see :class:`DepthRefinementConfig`."""
    p, n = _surface_normals(depth_dst, intrinsics)
    floor = np.diag([config.pair_sigma_rad**2] * 3 + [config.pair_sigma_m**2] * 3)
    if len(p) < 6:
        return floor + np.diag([1.0] * 3 + [1.0] * 3)  # no geometry: no say
    J = np.concatenate([np.cross(p, n), n], axis=1)
    information = (J.T @ J) / len(p) * config.independent_points / config.point_sigma_m**2
    try:
        return np.linalg.inv(information + 1e-9 * np.eye(6)) + floor
    except np.linalg.LinAlgError:
        return floor + np.eye(6)


def _measure_pairs(frames, T_world, depths, covariances, aligner, config, progress) -> tuple[list, int]:
    """``[(a, b, T_a_b measured, covariance)]`` for each neighbour pair whose alignment held
    (``covariances``: each frame's as a pair's destination), and how many pairs were tried."""
    pairs, tried = [], 0
    for a in progress_bar(range(len(frames)), desc="align depth pairs", unit="frame", disable=not progress):
        for k in config.neighbours:
            b = a + k
            if b >= len(frames):
                continue
            tried += 1
            T_b_a = inv_T(T_world[b]) @ T_world[a]
            D = aligner.residual(depths[int(frames[a])], depths[int(frames[b])], T_b_a)
            if D is None:
                continue
            moved_m, turned_deg = pose_error(D, np.eye(4))
            if moved_m > config.max_pair_m or turned_deg > config.max_pair_deg:
                continue
            pairs.append((a, b, inv_T(D @ T_b_a), covariances[int(frames[b])]))
    return pairs, tried


def _solve(T_in: np.ndarray, T_start: np.ndarray, pairs: list, config: DepthRefinementConfig) -> np.ndarray:
    """The poses (N, 4, 4) that best agree with the input priors and the measured pairs."""
    import gtsam
    from gtsam.symbol_shorthand import X



    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for a, T in enumerate(T_in):
        graph.add(pose_prior_factor(X(a), T, rot_sigma_rad=config.input_sigma_rad, trans_sigma_m=config.input_sigma_m))
        values.insert(X(a), T_to_pose3(T_start[a]))
    for a, b, T_a_b, covariance in pairs:
        graph.add(odometry_factor(X(a), X(b), T_a_b, covariance, robust="huber"))
    result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    return np.array([pose3_to_T(result.atPose3(X(a))) for a in range(len(T_in))])


def refine_poses_by_depth(sequence, train_idx, timing: CaptureTiming | None = None,
                          config: DepthRefinementConfig | None = None, progress: bool = False):
    """Refined poses of frames ``train_idx`` of a posed ``sequence`` (needs
    ``ground_truth_at`` and ``depth_timestamps``): ``(corrections, report)`` with
    ``corrections`` ``{frame index: D (4, 4)}`` (refined pose = input pose @ D) and a report
    (pairs tried and used per round, median pair and frame corrections)."""
    config = config or DepthRefinementConfig()
    timing = CaptureTiming.of(timing) or CaptureTiming()
    frames = np.asarray(train_idx, dtype=int)
    stamps = np.asarray(sequence.depth_timestamps, dtype=float)[frames] + timing.depth_offset_s
    T_in = np.asarray(sequence.ground_truth_at(stamps), dtype=float)
    known = np.all(np.isfinite(T_in), axis=(1, 2))
    unposed = {int(i): np.eye(4) for i in frames[~known]}  # no pose at their depth's instant: left as they are
    frames, T_in = frames[known], T_in[known]
    if len(frames) < 2:
        return unposed, {"method": "depth", "rounds": [], "reason": "fewer than two posed training frames"}
    depths, small = _small_depths(sequence, frames, config.width, timing.depth_scale)
    aligner = _PairAligner(small)
    # A pair's covariance depends on its destination's surfaces alone: once per frame.
    covariances = {i: _pair_covariance(depth, small, config) for i, depth in depths.items()}
    T_now, rounds = T_in.copy(), []
    for r in range(config.rounds):
        pairs, tried = _measure_pairs(frames, T_now, depths, covariances, aligner, config, progress)
        if not pairs:
            log.warning("depth refinement round %d: no pair aligned; poses left as they are", r + 1)
            break
        T_now = _solve(T_in, T_now, pairs, config)
        pair_moves = np.array([pose_error(T_a_b, inv_T(T_in[a]) @ T_in[b]) for a, b, T_a_b, _ in pairs])
        frame_moves = np.array([pose_error(T_now[a], T_in[a]) for a in range(len(frames))])
        info = {"round": r + 1, "pairs_tried": tried, "pairs_used": len(pairs),
                "median_pair_change_mm": round(float(np.median(pair_moves[:, 0])) * 1000, 3),
                "median_pair_change_deg": round(float(np.median(pair_moves[:, 1])), 4),
                "median_correction_mm": round(float(np.median(frame_moves[:, 0])) * 1000, 3),
                "median_correction_deg": round(float(np.median(frame_moves[:, 1])), 4),
                "mean_correction_mm": round(float(np.linalg.norm(np.mean(
                    [(T_now[a] - T_in[a])[:3, 3] for a in range(len(frames))], axis=0))) * 1000, 3)}
        rounds.append(info)
        log.info("depth refinement round %d: %d of %d pairs aligned, frames moved %.1f mm / %.2f deg (median)",
                 r + 1, len(pairs), tried, info["median_correction_mm"], info["median_correction_deg"])
    corrections = {**unposed, **{int(i): inv_T(T_in[a]) @ T_now[a] for a, i in enumerate(frames)}}
    return corrections, {"method": "depth", "rounds": rounds, "config": config.to_dict()}
