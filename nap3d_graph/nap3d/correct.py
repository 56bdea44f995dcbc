"""One NAP3D pose correction: render at the believed pose, align, re-render until it settles.

Re-rendering at the corrected pose makes the second alignment compare two views from almost
the same viewpoint, where SIFT's viewpoint-dependent localisation bias cancels; that is why
iterating is both more accurate and gives a more honest covariance than one round.
"""

from __future__ import annotations

import logging
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from ..camera import Intrinsics, RenderedView, RGBDFrame
from ..conventions import as_T, inv_T, log_se3, rigid_transform_problem
from ..results import Alignment, Correction
from .align import align_views, view_features
from .config import AlignConfig
from .matching import Features, detect_features
from .rolling_shutter import RowMotion

__all__ = ["correct_pose", "render_safely", "resize_frame", "at_width", "at_render_size", "real_features", "PreparedView",
           "prepare_view", "prepare_view_beside"]

log = logging.getLogger(__name__)


def render_safely(field, T_world_cam: np.ndarray, intrinsics: Intrinsics):
    """``field.render`` that turns a failure into ``(None, reason)`` instead of raising."""
    try:
        view = field.render(T_world_cam, intrinsics)
    except Exception as exc:  # a field is user code: any failure skips this correction
        log.warning("field render failed: %s", exc)
        return None, f"render failed: {exc}"
    if not np.any(view.opacity > 0.5):
        return None, "low opacity: the field does not cover this view"
    return view, ""


@dataclass(frozen=True)
class PreparedView:
    """A render made before its frame arrived, with its features: ``T_world_cam`` (4, 4) where
    it was rendered, ``view`` (RenderedView), ``features`` (:func:`view_features`),
    ``intrinsics`` (its camera), ``seconds`` (render and detection)."""

    T_world_cam: np.ndarray
    view: RenderedView
    features: Features
    intrinsics: Intrinsics
    seconds: float


def prepare_view(field, T_world_cam: np.ndarray, intrinsics: Intrinsics, config: AlignConfig | None = None
                 ) -> PreparedView | None:
    """Render at ``T_world_cam`` and detect the view's features, ahead of the frame that will
    be aligned to it (a run's next keyframe at its predicted pose); None when the field does
    not render there."""
    t0 = time.perf_counter()
    view, _ = render_safely(field, np.asarray(T_world_cam, dtype=float), intrinsics)
    if view is None:
        return None
    features = view_features(view, config or AlignConfig())
    return PreparedView(np.array(T_world_cam, dtype=float), view, features, intrinsics, time.perf_counter() - t0)


def prepare_view_beside(field, T_world_cam: np.ndarray, intrinsics: Intrinsics, config: AlignConfig | None = None):
    """:func:`prepare_view` on the side thread that otherwise detects the real frame's features
    (a future): for a caller that has those features already and other work to do meanwhile."""
    return _detector().submit(prepare_view, field, T_world_cam, intrinsics, config)


def correct_pose(
    frame: RGBDFrame,
    field,
    T_world_cam_est,
    iterations: int = 4,
    config: AlignConfig | None = None,
    render_intrinsics: Intrinsics | None = None,
    stop_mahalanobis: float = 0.3,
    prepared: PreparedView | None = None,
    feats_real: Features | None = None,
    motion: RowMotion | None = None,
) -> Correction:
    """Correct ``T_world_cam_est`` (world <- camera, OpenCV; a (4, 4) array or a
    ``gtsam.Pose3``, as a GTSAM loop has it) of ``frame`` with ``field``.

    Renders at the estimate, aligns with :func:`align_views`, and re-renders at the
    corrected pose, up to ``iterations`` rounds in all. It stops early once a round's update
    is small against that round's own uncertainty (Mahalanobis distance below
    ``stop_mahalanobis``): then the last alignment compared two views from practically the
    same viewpoint, and its covariance is honest. ``render_intrinsics`` (default: the
    frame's) sets the rendering camera; a frame at another resolution is resized to it.
    ``prepared``: a render made ahead near the estimate (:func:`prepare_view`, with the same
    camera): the first round aligns to it instead of rendering, measuring the pose from where
    it was rendered. ``feats_real``: the frame's features at the render size, when already
    detected (:func:`real_features`). ``motion``: the camera's twist while its rolling shutter
    read the frame (:class:`~nap3d_graph.nap3d.rolling_shutter.RowMotion`), or None. Never
    raises on bad data: ``success=False`` and ``reason`` say why.
    """
    T_est = as_T(T_world_cam_est)  # a 4x4 array or a gtsam.Pose3
    problem = rigid_transform_problem(T_est, tolerance=1e-5)
    if problem:
        failed = Alignment.failure(f"T_world_cam_est is not a rigid transform: {problem}")
        T_keep = T_est if T_est.shape == (4, 4) else np.eye(4)
        return Correction(T_keep, T_keep.copy(), np.full((6, 6), np.inf), failed, 0, False, failed.reason, {})
    intrinsics = render_intrinsics or frame.intrinsics
    if prepared is not None and prepared.intrinsics.shape != intrinsics.shape:
        prepared = None  # rendered for another camera: render afresh
    # The real frame is the same every round: resize it and detect its features once.
    rounds = _Rounds(field, at_render_size(frame, intrinsics), intrinsics, config or AlignConfig(), motion, feats_real)
    T_current = rounds.run(T_est, iterations, stop_mahalanobis, prepared)
    alignment, shown = rounds.alignment, rounds.shown
    views = {"real_rgb": rounds.real.rgb, "render_rgb": None if shown is None else shown.rgb,
             **{k: alignment.diagnostics[k] for k in ("inlier_uv_real", "inlier_uv_render") if k in alignment.diagnostics}}
    if not alignment.success:
        return Correction(T_est, T_est.copy(), np.full((6, 6), np.inf), alignment, rounds.done, False,
                          alignment.reason, rounds.timings, views)
    return Correction(T_est, T_current, alignment.covariance, alignment, rounds.done, True, "", rounds.timings, views)


class _Rounds:
    """The render-and-align rounds of one :func:`correct_pose`: ``alignment`` the kept one,
    ``shown`` the render it compared, ``done`` how many rounds ran, ``timings`` (seconds) what
    they cost. ``real``: the frame at the render's size."""

    def __init__(self, field, real: RGBDFrame, intrinsics: Intrinsics, config: AlignConfig, motion, feats_real):
        self.field, self.real, self.intrinsics, self.config, self.motion = field, real, intrinsics, config, motion
        self.timings = {"render": 0.0, "align": 0.0}
        self.alignment = Alignment.failure("not run")
        self.shown = None
        self.done = 0
        self.feats_real = feats_real
        # The real frame's features while the first render is made: the two do not depend on each
        # other, and OpenCV and torch both release the GIL, so the second core takes one of them.
        self.detecting = _detector().submit(_timed_detect, real.rgb, config) if feats_real is None else None

    def run(self, T_est: np.ndarray, iterations: int, stop_mahalanobis: float, prepared) -> np.ndarray:
        """Up to ``iterations`` rounds from ``T_est`` (4, 4); returns the last corrected pose."""
        T_current = T_est
        for self.done in range(1, max(1, iterations) + 1):
            T_current, view, feats_view, reason = self._view(T_current, prepared if self.done == 1 else None)
            if self.detecting is not None:
                self.feats_real, self.timings["detect"] = self.detecting.result()
                self.detecting = None
            if view is None:
                self.alignment = Alignment.failure(reason)
                break
            step = self._align(view, feats_view)
            if not step.success:
                # A failed re-render round keeps the previous round's good result.
                if not self.alignment.success:
                    self.alignment, self.shown = step, view
                break
            self.alignment, self.shown = step, view
            T_next = step.corrected_pose(T_current)
            update = log_se3(inv_T(T_current) @ T_next)
            T_current = T_next
            if float(update @ np.linalg.solve(step.covariance, update)) < stop_mahalanobis**2:
                break
        return T_current

    def _view(self, T_current: np.ndarray, prepared):
        """``(T_world_cam, view, features or None, reason)``: the render a round aligns to,
        made ahead (``prepared``: aligned to from where it was made) or rendered now."""
        if prepared is not None:
            self.timings["render_ahead"] = prepared.seconds
            return prepared.T_world_cam, prepared.view, prepared.features, ""
        t0 = time.perf_counter()
        view, reason = render_safely(self.field, T_current, self.intrinsics)
        self.timings["render"] += time.perf_counter() - t0
        return T_current, view, None, reason

    def _align(self, view, feats_view):
        """One round's alignment of the real frame to ``view``, its stage timings added up."""
        t0 = time.perf_counter()
        step = align_views(self.real, view, self.config, feats_real=self.feats_real, feats_view=feats_view,
                           motion=self.motion)
        self.timings["align"] += time.perf_counter() - t0
        for key, value in step.timings_s.items():
            self.timings[key] = self.timings.get(key, 0.0) + value
        return step


def at_render_size(frame: RGBDFrame, intrinsics: Intrinsics) -> RGBDFrame:
    """The frame resized to the render's camera (as it is when the sizes agree)."""
    if intrinsics.shape != frame.intrinsics.shape:
        return resize_frame(frame, intrinsics.width, intrinsics.height)
    return frame


def real_features(frame: RGBDFrame, intrinsics: Intrinsics, config: AlignConfig | None = None
                  ) -> tuple[Features, float]:
    """``(features, seconds)``: the real frame's features as :func:`correct_pose` detects them
    (at the render's size), for a caller that detects them before the correction starts."""
    return _timed_detect(at_render_size(frame, intrinsics).rgb, config or AlignConfig())


def _timed_detect(rgb: np.ndarray, config: AlignConfig):
    t0 = time.perf_counter()
    return detect_features(rgb, config.max_features, matcher=config.matcher), time.perf_counter() - t0


_DETECTOR: tuple[int, ThreadPoolExecutor] | None = None


def _detector() -> ThreadPoolExecutor:
    """One thread for the real frame's features, per process (a forked child gets its own: an
    executor's thread does not survive a fork)."""
    global _DETECTOR
    if _DETECTOR is None or _DETECTOR[0] != os.getpid():
        _DETECTOR = (os.getpid(), ThreadPoolExecutor(max_workers=1, thread_name_prefix="nap3d-detect"))
    return _DETECTOR[1]


def at_width(frame: RGBDFrame, width: int | None) -> RGBDFrame:
    """The frame scaled down to ``width`` pixels, its aspect kept (as it is when it is no wider,
    or when ``width`` is None)."""
    K = frame.intrinsics
    if width is None or K.width <= width:
        return frame
    return resize_frame(frame, width, int(round(K.height * width / K.width)))


def resize_frame(frame: RGBDFrame, width: int, height: int) -> RGBDFrame:
    """The frame at another resolution (area for colour, nearest for depth)."""
    import cv2

    rgb = cv2.resize(frame.rgb, (width, height), interpolation=cv2.INTER_AREA)
    depth = cv2.resize(frame.depth_m, (width, height), interpolation=cv2.INTER_NEAREST)
    return RGBDFrame(rgb, depth, frame.intrinsics.scaled(width, height), frame.timestamp, frame.depth_timestamp)
