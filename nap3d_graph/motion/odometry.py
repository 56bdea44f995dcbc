"""Odometry sources for the drift-correction pipeline, behind one small interface.

Each source gives, frame by frame, the increment ``T_prev_cur`` (4x4, previous camera <-
current camera) with its 6x6 covariance (GTSAM order, right perturbation), and the pose it
starts from. A failed increment (VO with too few matches) falls back to the constant
velocity model with a large covariance, so the run continues; the feature odometry first tries
the depths alone (:mod:`.depth_step`: a blank wall still says how far away it is).

* :class:`RecordedOdometry`: poses a source already has (the simulator's ``odometry.txt``).
* :class:`NoisyGroundTruthOdometry`: seeded noise injected on ground-truth increments (with
  the slowly wandering bias of :class:`~nap3d_graph.sims.sensors.OdometryNoise`).
* :class:`VisualOdometry`: frame-to-frame RGB-D odometry with the same SIFT matcher and 3D-3D
  alignment as NAP3D (the previous frame plays the rendered view).
"""

from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from nap3d_graph.sims.sensors import OdometryNoise, drifting_odometry

from ..camera import Intrinsics, RenderedView, RGBDFrame, backproject_depth, project
from ..conventions import exp_se3, inv_T, log_se3
from ..nap3d.align import align_views
from ..nap3d.config import AlignConfig
from ..nap3d.correct import at_width, real_features
from ..nap3d.matching import Features
from ..trajectory import interpolate_poses
from .depth_step import depth_step

__all__ = ["Increment", "RecordedOdometry", "NoisyGroundTruthOdometry", "VisualOdometry", "make_odometry",
           "bridge_pose_gaps"]

log = logging.getLogger(__name__)

#: Measured steps whose mean translation a depth step holds as its heading (half a second at 10 Hz).
STEADY_STEPS = 5


@dataclass
class Increment:
    """``T_prev_cur`` (4, 4) and its covariance (6, 6); ``ok`` False when it was guessed;
    ``timings_s``: seconds per stage of the step (the visual odometries say where it went);
    ``frame_noise`` (6, 6): the part of ``covariance`` that is its two frames' own registration
    noise, which a chain of steps cancels inside (:class:`~.interval.IntervalCovariance`;
    None: none known, the whole covariance adds up step by step)."""

    T_prev_cur: np.ndarray
    covariance: np.ndarray
    ok: bool = True
    reason: str = ""
    timings_s: dict = field(default_factory=dict)
    frame_noise: np.ndarray | None = None


def _diag_cov(rot_sigma_rad: float, trans_sigma_m: float) -> np.ndarray:
    return np.diag([rot_sigma_rad**2] * 3 + [trans_sigma_m**2] * 3)


class RecordedOdometry:
    """Increments between consecutive poses of a recorded odometry trajectory (N, 4, 4)."""

    name = "recorded"

    def __init__(self, T_world_cam_odom: np.ndarray, rot_sigma_rad: float = 2e-3, trans_sigma_m: float = 2e-3):
        self.T_world_cam_odom = np.asarray(T_world_cam_odom, dtype=float)
        self.covariance = _diag_cov(rot_sigma_rad, trans_sigma_m)

    def initial_pose(self) -> np.ndarray:
        return self.T_world_cam_odom[0].copy()

    def increment(self, i: int, frame: RGBDFrame | None = None) -> Increment:
        return Increment(inv_T(self.T_world_cam_odom[i - 1]) @ self.T_world_cam_odom[i], self.covariance)


class NoisyGroundTruthOdometry(RecordedOdometry):
    """Ground-truth increments with seeded noise (white per frame, a wandering camera-frame
    bias, and a heading bias about gravity; see :class:`~nap3d_graph.sims.sensors.OdometryNoise`).

    Frames without ground truth (outside the motion capture or in its gaps; all-NaN rows of
    ``T_world_cam_gt``) do not stop the odometry: the truth is bridged across them
    (interpolated inside a gap, constant velocity beyond either end, see
    :func:`bridge_pose_gaps`), and every increment that touches such a frame is marked as a
    guess (``ok`` False) with the large fallback covariance, as visual odometry does when a
    step fails. ``num_bridged`` says how many frames were bridged.
    """

    name = "noisy"

    def __init__(self, T_world_cam_gt: np.ndarray, stamps: np.ndarray, rot_sigma_rad: float = 2e-3,
                 trans_sigma_m: float = 2e-3, bias=(0.0, 0.0, 0.004, 0.01, 0.0, 0.0), bias_walk: float = 1e-3,
                 heading_bias_rad_s: float = 0.004, seed: int = 0, fallback_rot_sigma_rad: float = 0.05,
                 fallback_trans_sigma_m: float = 0.05):
        T_world_cam_bridged, self.bridged = bridge_pose_gaps(np.asarray(stamps, dtype=float),
                                                             np.asarray(T_world_cam_gt, dtype=float))
        noise = OdometryNoise(rot_sigma_rad=rot_sigma_rad, trans_sigma_m=trans_sigma_m, bias_init=tuple(bias),
                              bias_walk=bias_walk, heading_bias_rad_s=heading_bias_rad_s)
        T_odom, _ = drifting_odometry(T_world_cam_bridged, np.asarray(stamps), noise, np.random.default_rng(seed))
        super().__init__(T_odom, rot_sigma_rad, trans_sigma_m)
        self._fallback_cov = _diag_cov(fallback_rot_sigma_rad, fallback_trans_sigma_m)

    @property
    def num_bridged(self) -> int:
        return int(self.bridged.sum())

    def increment(self, i: int, frame: RGBDFrame | None = None) -> Increment:
        inc = super().increment(i, frame)
        if self.bridged[i] or self.bridged[i - 1]:
            return Increment(inc.T_prev_cur, self._fallback_cov, False, "no ground truth to inject noise on")
        return inc


def bridge_pose_gaps(stamps: np.ndarray, T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Poses (N, 4, 4) with every non-finite one replaced by a guess, and which were (N,) bool.

    Inside a gap the pose is interpolated in time between its valid neighbours (linear
    translation, SLERP rotation); before the first or after the last valid pose it continues
    at the constant velocity of the two nearest valid poses (held still when there is only
    one). Raises ``ValueError`` when no pose is valid.
    """
    T_world_cam = np.array(T_world_cam, dtype=float)
    missing = ~np.all(np.isfinite(T_world_cam), axis=(1, 2))
    valid = np.flatnonzero(~missing)
    if valid.size == 0:
        raise ValueError("no frame has a ground-truth pose")
    if not missing.any():
        return T_world_cam, missing
    inside = missing & (np.arange(len(stamps)) > valid[0]) & (np.arange(len(stamps)) < valid[-1])
    if inside.any():
        T_world_cam[inside] = interpolate_poses(stamps[valid], T_world_cam[valid], stamps[inside], max_gap=np.inf)
    for end, (a, b) in ((np.arange(valid[0]), valid[:2]), (np.arange(valid[-1] + 1, len(stamps)), valid[-2:][::-1])):
        if end.size == 0:
            continue
        T_anchor = T_world_cam[a]
        velocity = np.zeros(6)
        if a != b and stamps[a] != stamps[b]:  # twist per second, body frame of the end pose
            velocity = log_se3(inv_T(T_world_cam[b]) @ T_anchor) / (stamps[a] - stamps[b])
        for k in end:
            T_world_cam[k] = T_anchor @ exp_se3(velocity * (stamps[k] - stamps[a]))
    return T_world_cam, missing


class VisualOdometry:
    """Frame-to-frame RGB-D odometry: NAP3D's matcher and alignment between frame i-1 (as
    the 'rendered' view, opaque where its depth is valid) and frame i.

    Its covariance says when a step is doubtful, so a graph trusts the corrections there
    instead: the alignment's own covariance is inflated when it rests on few inliers
    (``(min_good_inliers / inliers)^2``), and a step that disagrees with the constant-velocity
    prediction from the previous one gets at least that disagreement as its sigma (a hand-held
    camera does not change speed by a metre per second in one frame; a wrong match does).
    A step without features to match (a blank wall) is measured by the depths alone where they
    agree, the constant-velocity guess holding what they cannot see (``depth_fallback``,
    :mod:`.depth_step`); else it is that guess with a large covariance. A step on fewer than
    ``min_good_inliers`` inliers has its translation fused with that depth step's, its
    covariance kept (:meth:`_with_depth`).

    ``width``: detect and align each frame resized to this many pixels wide (area for colour,
    nearest for depth; None: as read). At the keyframe render's size (320) a keyframe's
    correction reuses the features the odometry detected (:meth:`features_of`). On fr1/desk's
    second half the steps took 33 / 56 ms (SIFT / XFeat) instead of 90 / 159 ms at 640 and
    whole runs went 2.5x / 2.3x as fast; the odometry alone drifted more (10.2 / 14.5 against
    7.9 / 7.4 cm ATE), the corrected trajectories ended at 2.15 / 2.13 against 2.24 / 2.11 cm
    and their causal ones 4-14% worse (``benchmarks/results/vo_width_*.json``).
    """

    name = "vo"
    needs_frames = True

    def __init__(self, initial_pose: np.ndarray | None = None, config: AlignConfig | None = None,
                 fallback_rot_sigma_rad: float = 0.05, fallback_trans_sigma_m: float = 0.05,
                 min_good_inliers: int = 60, reuse_features: bool = True, width: int | None = None,
                 depth_fallback: bool = True):
        if width is not None and int(width) < 16:
            raise ValueError(f"the odometry's width must be at least 16 pixels, got {width}")
        self._initial = np.eye(4) if initial_pose is None else np.asarray(initial_pose, dtype=float)
        self.config = config or AlignConfig(min_opacity=0.5)
        self.width = None if width is None else int(width)
        self._previous: RGBDFrame | None = None
        # The previous frame's features (detected when it was the current frame), which serve
        # it again as the view: detected once per frame, not twice.
        self._previous_features: Features | None = None
        # (frame index, the current frame's features): what a keyframe's correction can reuse.
        self._latest: tuple[int, Features] | None = None
        self._last_good = np.eye(4)
        self._fallback_cov = _diag_cov(fallback_rot_sigma_rad, fallback_trans_sigma_m)
        self.min_good_inliers = int(min_good_inliers)
        self.reuse_features = bool(reuse_features)
        self.depth_fallback = bool(depth_fallback)
        # The last measured steps' translations in the odometry's own frame, and the previous
        # camera's rotation in it: the walker's heading is held there, not in the camera, which
        # turns its head while the walker walks on.
        self._recent_steps: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=STEADY_STEPS)
        self._R_odom_prev = np.eye(3)

    def initial_pose(self) -> np.ndarray:
        return self._initial.copy()

    def prime(self, frame: RGBDFrame) -> None:
        """Give the first frame (the pipeline calls this before any increment)."""
        self._previous, self._previous_features, self._latest = self._sized(frame), None, None
        self._R_odom_prev = np.eye(3)

    def _sized(self, frame: RGBDFrame | None) -> RGBDFrame | None:
        """The frame at the odometry's width (as it is without one, or when it is narrower)."""
        return None if frame is None else at_width(frame, self.width)

    def shares_features(self, intrinsics: Intrinsics, config: AlignConfig) -> bool:
        """Whether the features this odometry detects on a frame are those a correction rendered
        with ``intrinsics`` and aligned with ``config`` detects on it: the same size, matcher and
        cap on their number."""
        return (self.width is not None and self.width == intrinsics.width
                and self.config.matcher == config.matcher and self.config.max_features == config.max_features)

    def features_of(self, i: int, intrinsics: Intrinsics, config: AlignConfig) -> Features | None:
        """Frame i's features as detected by its step (when it was the latest frame), if they are
        what a correction at ``intrinsics`` with ``config`` would detect (:meth:`shares_features`);
        else None."""
        if self._latest is None or self._latest[0] != i or not self.shares_features(intrinsics, config):
            return None
        previous = self._previous
        if previous is None or previous.intrinsics.shape != intrinsics.shape:
            return None
        return self._latest[1]

    def increment(self, i: int, frame: RGBDFrame | None = None) -> Increment:
        frame = self._sized(frame)
        if frame is None or self._previous is None:
            # An unreadable frame: guess with constant velocity, restart from the next one.
            self._previous, self._previous_features, self._latest = frame, None, None
            return self._stepped(Increment(self._last_good.copy(), self._fallback_cov, False, "no frame"))
        prev, prev_features = self._previous, self._previous_features
        opacity = np.isfinite(prev.depth_m) & (prev.depth_m > 0)
        view = RenderedView(prev.rgb, np.nan_to_num(prev.depth_m), opacity.astype(np.float32), prev.intrinsics)
        features, detect_s = real_features(frame, frame.intrinsics, self.config)
        view_features = None
        if prev_features is not None and self._features_reusable():
            view_features = prev_features.where(opacity >= self.config.min_opacity)
        self._previous, self._previous_features, self._latest = frame, features, (i, features)
        a = align_views(frame, view, self.config, feats_real=features, feats_view=view_features)
        timings = dict(a.timings_s)
        timings["detect"] = timings.get("detect", 0.0) + detect_s
        if not a.success:
            return self._stepped(self._without_features(i, prev, frame, a.reason, timings))
        # T_real_rendered maps frame i-1's camera into frame i's: T_cur_prev.
        T_features = inv_T(a.T_real_rendered)
        cov_features, frame_noise = self._step_covariance(a, T_features)
        T_prev_cur, covariance = T_features, cov_features
        if self.depth_fallback and a.num_inliers < self.min_good_inliers:
            T_prev_cur, covariance = self._with_depth(prev, frame, T_features, cov_features, timings)
        # The guesses (constant velocity, the walker's heading) are held from what the features
        # measured: a fused step's unseen part is the guess's own, and feeding it back would lock
        # in whatever heading the guess had.
        self._last_good = T_features
        R = self._R_odom_prev
        self._recent_steps.append((R @ T_features[:3, 3], np.linalg.inv(R @ cov_features[3:, 3:] @ R.T)))
        return self._stepped(Increment(T_prev_cur, covariance, timings_s=timings, frame_noise=frame_noise))

    def _stepped(self, increment: Increment) -> Increment:
        """``increment``, after turning the previous camera's rotation in the odometry's frame by it."""
        self._R_odom_prev = self._R_odom_prev @ increment.T_prev_cur[:3, :3]
        return increment

    def _without_features(self, i: int, prev: RGBDFrame, frame: RGBDFrame, reason: str, timings: dict) -> Increment:
        """A step the features could not measure: by the depths alone where they agree
        (:func:`~.depth_step.depth_step`, the constant-velocity guess holding what they cannot
        see), else the guess. Either way ``ok`` is False: part of the step is guessed."""
        step = self._depth_step(prev, frame, timings) if self.depth_fallback else None
        if step is None:
            log.info("VO failed at frame %d (%s); constant-velocity guess", i, reason)
            return Increment(self._last_good.copy(), self._fallback_cov, False, reason, timings)
        log.info("VO failed at frame %d (%s); stepped by depth alone (%d points, median %.1f mm)", i, reason,
                 step.points, step.residual_m * 1000)
        # The guess stays the last step the features measured: a depth step's unseen directions
        # are that guess already, and chaining them would let their noise wander step by step.
        return Increment(step.T_prev_cur, step.covariance, False, f"{reason}; stepped by depth alone", timings)

    def _depth_step(self, prev: RGBDFrame, frame: RGBDFrame, timings: dict):
        """The step from ``prev`` to ``frame`` by their depths under the constant-velocity guess
        (:func:`~.depth_step.depth_step`; None where they do not agree), timed into ``timings``."""
        t0 = time.perf_counter()
        step = depth_step(prev.depth_m, prev.intrinsics, frame.depth_m, frame.intrinsics, self._steady_guess())
        timings["depth_step"] = time.perf_counter() - t0
        return step

    def _with_depth(self, prev: RGBDFrame, frame: RGBDFrame, T_prev_cur: np.ndarray, covariance: np.ndarray,
                    timings: dict) -> tuple[np.ndarray, np.ndarray]:
        """A step the features measured on few inliers (``T_prev_cur`` (4, 4), its (6, 6)
        covariance) with its translation fused with the depths' own measurement of it
        (:func:`~.depth_step.depth_step` under the constant-velocity guess), each weighted by its
        information; the step keeps the features' covariance. Why: as the colour runs out (a
        blank wall coming into view) the last steps rest on a handful of matches and are off by
        centimetres (6.7 cm on a 5.4 cm step on a simulated floor's end wall) with a covariance
        that says so; nothing later corrects them, and the depths measure the distance to the
        wall to millimetres. On fr1/desk (15 Hz, the
        odometry alone, from the first pose) 4 / 16 steps of its halves were fused: ATE 7.9 ->
        4.2 / 5.6 -> 4.7 cm, SE(3)-aligned 2.8 -> 2.7 / 2.0 -> 2.2 cm; the kitchen's 500 frames
        have no step so weak. Why the features' covariance: the depth step's own (a hundred
        independent points at 1 cm) is far tighter than its errors on the tests' small fast
        surveys, and a map's pose graph that trusted it bent its loops to it (a survey across a
        loss of the camera 2.9 cm off instead of under 1); the fused mean is the better guess
        where nothing else measures the step, and where loops or corrections do, they move it."""
        step = self._depth_step(prev, frame, timings)
        if step is None:
            return T_prev_cur, covariance
        # The rotation stays the features': on fr1/desk's fast half the depth steps' tilts were
        # 2 deg off where the features' were 1 deg (its depth is not the colour's instant).
        info_features, info_depth = np.linalg.inv(covariance[3:, 3:]), np.linalg.inv(step.covariance[3:, 3:])
        fused = np.linalg.inv(info_features + info_depth)
        T = T_prev_cur.copy()
        T[:3, 3] = fused @ (info_features @ T_prev_cur[:3, 3] + info_depth @ step.T_prev_cur[:3, 3])
        return T, covariance

    def _steady_guess(self) -> np.ndarray:
        """The constant-velocity guess with the mean translation of the last few measured steps
        (``T_prev_cur`` (4, 4)): one step's direction is as noisy as its few inliers at a blank
        wall, and a depth step keeps it for every step until features return. The mean is taken
        in the odometry's frame and seen from the previous camera: a walker keeps walking the
        same way while the camera sweeps left and right (held in the camera, the heading would
        turn with every sweep of the head)."""
        T = self._last_good.copy()
        if self._recent_steps:
            # Weighted by their information: the last steps before the features run out rest on
            # a few inliers, and their covariance says so.
            info = sum(w for _, w in self._recent_steps)
            t_odom = np.linalg.solve(info, sum(w @ t for t, w in self._recent_steps))
            T[:3, 3] = self._R_odom_prev.T @ t_odom
        return T

    def _features_reusable(self) -> bool:
        """A frame's features serve it masked as the view (``reuse_features``): always for
        XFeat (masked after detection), for SIFT only without a cap on their number (a capped
        SIFT keeps the strongest among the masked ones)."""
        return self.reuse_features and (self.config.matcher != "sift" or self.config.max_features == 0)

    def _step_covariance(self, alignment, T_prev_cur: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The step's covariance (6, 6) and the part of it taken as its frames' own noise: the
        disagreement with constant velocity. Why that part: on real recordings the alignment's
        own covariance is far too small (NEES 200-700 over single steps of fr1/desk and the
        kitchen, against 6); what the steps get wrong is mostly each frame's registration (its
        depth against its colour, a rolling shutter), which jerks a step against the previous
        one and cancels along a chain."""
        cov = alignment.covariance * max(1.0, (self.min_good_inliers / max(alignment.num_inliers, 1)) ** 2)
        surprise = log_se3(inv_T(self._last_good) @ T_prev_cur)  # against constant velocity
        frame_noise = np.diag(surprise**2)
        return cov + frame_noise, frame_noise


class DenseVisualOdometry:
    """Frame-to-frame dense RGB-D odometry at the camera's rate: OpenCV's ``cv2.Odometry``
    (``OdometryType_RGB_DEPTH``, photometric + ICP terms over an image pyramid, as DVO) on the
    frames resized to at most ``max_width`` pixels wide.

    On fr1/desk's second half it drifted about as much as the SIFT odometry
    (:class:`VisualOdometry`): 8.1 against 7.9 cm ATE of the odometry alone, at 22 ms per
    pair on 320x240 against 204 ms (``benchmarks/results/vo_fr1_desk.json``). It reports no covariance of its
    own: each step gets ``rot_sigma_rad`` / ``trans_sigma_m``, plus, as the SIFT odometry, its
    disagreement with the constant-velocity prediction. A dense solve can land in a wrong
    minimum without saying so (in the simulator about one step in a hundred moved 10-20 cm
    the wrong way), so each step is checked against the depth: the previous frame's depth,
    moved by the step, must agree with the new frame's (median difference) about as well as
    when moved by the constant-velocity guess (5 mm slack: at slow motion the guess is as
    good), and within ``max_depth_residual_m``. A
    step that fails, diverges or disagrees falls back to constant velocity with a large
    covariance.
    """

    name = "dense"
    needs_frames = True

    def __init__(self, initial_pose: np.ndarray | None = None, max_width: int = 320, rot_sigma_rad: float = 4e-3,
                 trans_sigma_m: float = 4e-3, fallback_rot_sigma_rad: float = 0.05,
                 fallback_trans_sigma_m: float = 0.05, max_step_m: float = 0.3, max_depth_residual_m: float = 0.03):
        self._initial = np.eye(4) if initial_pose is None else np.asarray(initial_pose, dtype=float)
        self.max_width = int(max_width)
        self._step_cov = _diag_cov(rot_sigma_rad, trans_sigma_m)
        self._fallback_cov = _diag_cov(fallback_rot_sigma_rad, fallback_trans_sigma_m)
        self.max_step_m = float(max_step_m)
        self.max_depth_residual_m = float(max_depth_residual_m)
        self._previous = None
        self._odometry = None
        self._last_good = np.eye(4)

    def initial_pose(self) -> np.ndarray:
        return self._initial.copy()

    def _frame(self, frame: RGBDFrame):
        import cv2

        K = frame.intrinsics
        rgb, depth = frame.rgb, np.nan_to_num(frame.depth_m).astype(np.float32)
        if K.width > self.max_width:
            width, height = self.max_width, int(round(K.height * self.max_width / K.width))
            K = K.scaled(width, height)
            rgb = cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA)
            depth = cv2.resize(depth, (width, height), interpolation=cv2.INTER_NEAREST)  # never blend across edges
        if self._odometry is None:
            settings = cv2.OdometrySettings()
            settings.setCameraMatrix(K.K.astype(np.float32))
            self._odometry = cv2.Odometry(cv2.OdometryType_RGB_DEPTH, settings, cv2.OdometryAlgoType_COMMON)
        return cv2.OdometryFrame(depth, cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)), depth, K

    @staticmethod
    def _depth_residual(prev, cur, T_cur_prev: np.ndarray, stride: int = 4) -> float:
        """Median |z| difference (m) between the previous depth moved by ``T_cur_prev`` and
        the current depth where it lands (inf when almost nothing lands)."""
        (_, depth_prev, K), (_, depth_cur, _) = prev, cur
        points, _ = backproject_depth(depth_prev, K, stride)
        uv, z = project(points @ T_cur_prev[:3, :3].T + T_cur_prev[:3, 3], K)
        with np.errstate(invalid="ignore"):
            u, v = np.rint(uv[:, 0]), np.rint(uv[:, 1])
            inside = (z > 0) & (u >= 0) & (u < K.width) & (v >= 0) & (v < K.height)
        z_cur = depth_cur[v[inside].astype(int), u[inside].astype(int)]
        valid = z_cur > 0
        if valid.sum() < 0.1 * max(len(points), 1):
            return float("inf")
        return float(np.median(np.abs(z[inside][valid] - z_cur[valid])))

    def prime(self, frame: RGBDFrame) -> None:
        """Give the first frame (the pipeline calls this before any increment)."""
        self._previous = self._frame(frame)

    def increment(self, i: int, frame: RGBDFrame | None = None) -> Increment:
        import cv2


        if frame is None or self._previous is None:
            self._previous = None if frame is None else self._frame(frame)
            return Increment(self._last_good.copy(), self._fallback_cov, False, "no frame")
        clock = time.perf_counter()
        timings: dict[str, float] = {}

        def lap(stage: str) -> None:
            nonlocal clock
            now = time.perf_counter()
            timings[stage] = now - clock
            clock = now

        prev, cur = self._previous, self._frame(frame)
        self._previous = cur
        lap("resize")
        try:
            self._odometry.prepareFrames(prev[0], cur[0])
            lap("pyramid")
            ok, T_cur_prev = self._odometry.compute(prev[0], cur[0], np.eye(4))
            lap("solve")
        except cv2.error as exc:
            ok, reason = False, f"cv2.Odometry failed: {str(exc).splitlines()[0]}"
        else:
            reason = "dense odometry did not converge"
        if ok and np.all(np.isfinite(T_cur_prev)):
            T_cur_prev = np.asarray(T_cur_prev, dtype=float)
            T_prev_cur = inv_T(T_cur_prev)
            residual = self._depth_residual(prev, cur, T_cur_prev)
            guess = self._depth_residual(prev, cur, inv_T(self._last_good))
            lap("check")
            if np.linalg.norm(T_prev_cur[:3, 3]) > self.max_step_m:
                reason = f"dense odometry step of {np.linalg.norm(T_prev_cur[:3, 3]):.2f} m (diverged)"
            elif residual > self.max_depth_residual_m or residual > guess + 0.005:
                reason = (f"dense odometry step disagrees with the depth ({residual * 1000:.0f} mm median, "
                          f"constant velocity {guess * 1000:.0f} mm)")
            else:
                surprise = log_se3(inv_T(self._last_good) @ T_prev_cur)  # against constant velocity
                self._last_good = T_prev_cur
                return Increment(T_prev_cur, self._step_cov + np.diag(surprise**2), timings_s=timings)
        log.info("dense VO failed at frame %d (%s); constant-velocity guess", i, reason)
        return Increment(self._last_good.copy(), self._fallback_cov, False, reason, timings)


def make_odometry(kind: str, sequence, seed: int = 0, rot_sigma_rad: float = 2e-3, trans_sigma_m: float = 2e-3,
                  initial_pose: np.ndarray | None = None, matcher: str | None = None, vo_width: int | None = None):
    """The odometry a run uses: ``recorded`` (the sequence's own drifting odometry, as the
    simulator writes it), ``noisy`` (noise injected on ground-truth increments), ``vo`` (SIFT
    frame-to-frame) or ``dense`` (:class:`DenseVisualOdometry`, at the camera's rate).

    ``matcher``: the feature matcher of ``vo`` (default ``AlignConfig``'s); ``vo_width``: the
    width ``vo`` works at (:class:`VisualOdometry`'s ``width``; None: the frames' own).
    ``initial_pose`` (4, 4): where the camera starts in the field's frame, for ``vo`` (default
    the ground truth's first pose; required without one). Raises ``ValueError`` (one line,
    saying what to use instead) when the sequence cannot give that odometry."""
    if kind not in ("vo", "dense") and initial_pose is not None:
        raise ValueError(f"`initial_pose` is for `odometry='vo'` / `odometry='dense'`; `odometry='{kind}'` starts where its "
                         "poses start")
    if kind != "vo" and vo_width is not None:
        raise ValueError(f"`vo_width` is for `odometry='vo'`, not `odometry='{kind}'`")
    if kind == "recorded":
        T_odom = getattr(sequence, "T_world_cam_odom", None)
        if T_odom is None:
            raise ValueError(f"{sequence.path}: no recorded odometry (odometry.txt) in a TUM folder; use `odometry='noisy'` "
                             "or `odometry='vo'`")
        return RecordedOdometry(T_odom, rot_sigma_rad, trans_sigma_m)
    if kind == "noisy":
        if sequence.T_world_cam_gt is None:
            raise ValueError(f"{sequence.path}: `odometry='noisy'` needs ground truth (groundtruth.txt); use `odometry='vo'`")
        odometry = NoisyGroundTruthOdometry(sequence.T_world_cam_gt, sequence.timestamps, rot_sigma_rad,
                                            trans_sigma_m, seed=seed)
        if odometry.num_bridged:
            log.warning("%s: %d of %d frames have no ground truth; --odom noisy carries the odometry across them "
                        "on interpolated (or constant-velocity) motion with a large covariance", sequence.path,
                        odometry.num_bridged, len(sequence.timestamps))
        return odometry
    if kind in ("vo", "dense"):
        start = initial_pose
        if start is None and sequence.T_world_cam_gt is not None and np.all(np.isfinite(sequence.T_world_cam_gt[0])):
            start = sequence.T_world_cam_gt[0]
        if start is None:
            raise ValueError(f"{sequence.path}: `odometry='{kind}'` needs to know where the camera starts in the field's frame: "
                             "give `initial_pose='tx ty tz qx qy qz qw'` or `initial_pose_file` (the sequence has no "
                             "ground truth at its first frame)")
        if kind == "dense":
            return DenseVisualOdometry(start)
        config = AlignConfig(min_opacity=0.5) if matcher is None else AlignConfig(min_opacity=0.5, matcher=matcher)
        return VisualOdometry(start, config, width=vo_width)
    raise ValueError(f"unknown odometry {kind!r}; use recorded, noisy, vo or dense")
