"""Odometry sources for the drift-correction pipeline, behind one small interface.

Each source gives, frame by frame, the increment ``T_prev_cur`` (4x4, previous camera <-
current camera) with its 6x6 covariance (GTSAM order, right perturbation), and the pose it
starts from. A failed increment (VO with too few matches) falls back to the constant
velocity model with a large covariance, so the run continues.

* :class:`RecordedOdometry`: poses a source already has (the simulator's ``odometry.txt``).
* :class:`NoisyGroundTruthOdometry`: seeded noise injected on ground-truth increments (with
  the slowly wandering bias of :class:`~nap3d_graph.sims.sensors.OdometryNoise`).
* :class:`VisualOdometry`: frame-to-frame RGB-D odometry with the same SIFT matcher and 3D-3D
  alignment as NAP3D (the previous frame plays the rendered view).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from .alignment import AlignConfig, align_views
from .camera import RenderedView, RGBDFrame
from .conventions import inv_T

__all__ = ["Increment", "RecordedOdometry", "NoisyGroundTruthOdometry", "VisualOdometry", "make_odometry"]

log = logging.getLogger(__name__)


@dataclass
class Increment:
    """``T_prev_cur`` (4, 4) and its covariance (6, 6); ``ok`` False when it was guessed."""

    T_prev_cur: np.ndarray
    covariance: np.ndarray
    ok: bool = True
    reason: str = ""


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
    bias, and a heading bias about gravity; see :class:`~nap3d_graph.sims.sensors.OdometryNoise`)."""

    name = "noisy"

    def __init__(self, T_world_cam_gt: np.ndarray, stamps: np.ndarray, rot_sigma_rad: float = 2e-3,
                 trans_sigma_m: float = 2e-3, bias=(0.0, 0.0, 0.004, 0.01, 0.0, 0.0), bias_walk: float = 1e-3,
                 heading_bias_rad_s: float = 0.004, seed: int = 0):
        from nap3d_graph.sims.sensors import OdometryNoise, drifting_odometry

        noise = OdometryNoise(rot_sigma_rad=rot_sigma_rad, trans_sigma_m=trans_sigma_m, bias_init=tuple(bias),
                              bias_walk=bias_walk, heading_bias_rad_s=heading_bias_rad_s)
        T_odom, _ = drifting_odometry(np.asarray(T_world_cam_gt), np.asarray(stamps), noise,
                                      np.random.default_rng(seed))
        super().__init__(T_odom, rot_sigma_rad, trans_sigma_m)


class VisualOdometry:
    """Frame-to-frame RGB-D odometry: NAP3D's matcher and alignment between frame i-1 (as
    the 'rendered' view, opaque where its depth is valid) and frame i.

    Its covariance says when a step is doubtful, so a graph trusts the corrections there
    instead: the alignment's own covariance is inflated when it rests on few inliers
    (``(min_good_inliers / inliers)^2``), and a step that disagrees with the constant-velocity
    prediction from the previous one gets at least that disagreement as its sigma (a hand-held
    camera does not change speed by a metre per second in one frame; a wrong match does).
    A failed step falls back to constant velocity with a large covariance.
    """

    name = "vo"

    def __init__(self, initial_pose: np.ndarray | None = None, config: AlignConfig | None = None,
                 fallback_rot_sigma_rad: float = 0.05, fallback_trans_sigma_m: float = 0.05,
                 min_good_inliers: int = 60):
        self._initial = np.eye(4) if initial_pose is None else np.asarray(initial_pose, dtype=float)
        self.config = config or AlignConfig(min_opacity=0.5)
        self._previous: RGBDFrame | None = None
        self._last_good = np.eye(4)
        self._fallback_cov = _diag_cov(fallback_rot_sigma_rad, fallback_trans_sigma_m)
        self.min_good_inliers = int(min_good_inliers)

    def initial_pose(self) -> np.ndarray:
        return self._initial.copy()

    def prime(self, frame: RGBDFrame) -> None:
        """Give the first frame (the pipeline calls this before any increment)."""
        self._previous = frame

    def increment(self, i: int, frame: RGBDFrame | None = None) -> Increment:
        if frame is None or self._previous is None:
            # An unreadable frame: guess with constant velocity, restart from the next one.
            self._previous = frame
            return Increment(self._last_good.copy(), self._fallback_cov, False, "no frame")
        prev = self._previous
        self._previous = frame
        opacity = np.isfinite(prev.depth_m) & (prev.depth_m > 0)
        view = RenderedView(prev.rgb, np.nan_to_num(prev.depth_m), opacity.astype(np.float32), prev.intrinsics)
        a = align_views(frame, view, self.config)
        if not a.success:
            log.info("VO failed at frame %d (%s); constant-velocity guess", i, a.reason)
            return Increment(self._last_good.copy(), self._fallback_cov, False, a.reason)
        # T_real_rendered maps frame i-1's camera into frame i's: T_cur_prev.
        T_prev_cur = inv_T(a.T_real_rendered)
        covariance = self._step_covariance(a, T_prev_cur)
        self._last_good = T_prev_cur
        return Increment(T_prev_cur, covariance)

    def _step_covariance(self, alignment, T_prev_cur: np.ndarray) -> np.ndarray:
        from .conventions import log_se3

        cov = alignment.covariance * max(1.0, (self.min_good_inliers / max(alignment.num_inliers, 1)) ** 2)
        surprise = log_se3(inv_T(self._last_good) @ T_prev_cur)  # against constant velocity
        return cov + np.diag(surprise**2)


def make_odometry(kind: str, sequence, seed: int = 0, rot_sigma_rad: float = 2e-3, trans_sigma_m: float = 2e-3,
                  initial_pose: np.ndarray | None = None):
    """The odometry a run uses: ``recorded`` (the sequence's own drifting odometry, as the
    simulator writes it), ``noisy`` (noise injected on ground-truth increments) or ``vo``.

    ``initial_pose`` (4, 4): where the camera starts in the field's frame, for ``vo`` (default
    the ground truth's first pose; required without one). Raises ``ValueError`` (one line,
    saying what to use instead) when the sequence cannot give that odometry."""
    if kind != "vo" and initial_pose is not None:
        raise ValueError(f"an initial pose is for --odom vo; --odom {kind} starts where its poses start")
    if kind == "recorded":
        T_odom = getattr(sequence, "T_world_cam_odom", None)
        if T_odom is None:
            raise ValueError(f"{sequence.path}: no recorded odometry (odometry.txt) in a TUM folder; use --odom noisy "
                             "or --odom vo")
        return RecordedOdometry(T_odom, rot_sigma_rad, trans_sigma_m)
    if kind == "noisy":
        if sequence.T_world_cam_gt is None:
            raise ValueError(f"{sequence.path}: --odom noisy needs ground truth (groundtruth.txt); use --odom vo")
        missing = int((~np.all(np.isfinite(sequence.T_world_cam_gt), axis=(1, 2))).sum())
        if missing:
            raise ValueError(f"{sequence.path}: --odom noisy injects noise on ground-truth increments, but {missing} "
                             f"frames have no ground truth; use --odom vo (or --frames to skip them)")
        return NoisyGroundTruthOdometry(sequence.T_world_cam_gt, sequence.timestamps, rot_sigma_rad, trans_sigma_m,
                                        seed=seed)
    if kind == "vo":
        start = initial_pose
        if start is None and sequence.T_world_cam_gt is not None and np.all(np.isfinite(sequence.T_world_cam_gt[0])):
            start = sequence.T_world_cam_gt[0]
        if start is None:
            raise ValueError(f"{sequence.path}: --odom vo needs to know where the camera starts in the field's frame: "
                             "give --initial-pose 'tx ty tz qx qy qz qw' or --initial-pose-file (the sequence has no "
                             "ground truth at its first frame)")
        return VisualOdometry(start)
    raise ValueError(f"unknown odometry {kind!r}; use recorded, noisy or vo")
