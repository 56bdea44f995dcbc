"""What measuring one keyframe needs, gathered from a run as it stands
(:class:`~nap3d_graph.nap3d.keyframe.KeyframeJob`): the frame, where to render the field, the
camera's motion, the capture timing and the depth scale the run believes."""

from __future__ import annotations

import numpy as np

from nap3d_graph.camera import Intrinsics
from nap3d_graph.datasets.depth_timing import CaptureTiming, resolve_capture_timing
from nap3d_graph.nap3d.keyframe import KeyframeJob
from nap3d_graph.run.frames import FrameReader
from nap3d_graph.run.records import KeyframeRecord
from nap3d_graph.run.state import RunState

__all__ = ["KeyframeJobs"]


class KeyframeJobs:
    """Makes each keyframe's :class:`~nap3d_graph.nap3d.keyframe.KeyframeJob` of a run with
    ``field``, ``config`` (a :class:`~nap3d_graph.run.config.PipelineConfig`), ``odometry`` and
    frame ``timestamps`` (s), from the run's state as it is when asked
    (:class:`~nap3d_graph.run.state.RunState`). ``frames``: the run's frame reader (why the
    last frame could not be read is what a keyframe without a frame records)."""

    def __init__(self, field, config, odometry, timestamps, frames: FrameReader):
        self.field, self.config, self.odometry = field, config, odometry
        self.timestamps, self.frames = timestamps, frames
        self._timing = resolve_capture_timing(field, given=config.timing, compensate=config.compensate_timing)[0]

    def timing(self) -> CaptureTiming | None:
        """The capture timing the run compensates: the config's, else the field's (None: off)."""
        return self._timing

    def render_intrinsics(self, intrinsics: Intrinsics) -> Intrinsics:
        """The render's camera: the frame's (``intrinsics``) at the configured render size."""
        w, h = self.config.render_width, self.config.render_height
        if w is None or h is None or (w, h) == (intrinsics.width, intrinsics.height):
            return intrinsics
        return intrinsics.scaled(w, h)

    def shares_features(self, intrinsics: Intrinsics) -> bool:
        """Whether the feature odometry detects, for a frame of camera ``intrinsics``, the
        features its correction would (so they need not be detected ahead)."""
        shares = getattr(self.odometry, "shares_features", None)
        return shares is not None and shares(self.render_intrinsics(intrinsics), self.config.align)

    def job(self, state: RunState, record: KeyframeRecord, i: int, frame,
            T_field_cam_render: np.ndarray | None = None) -> KeyframeJob | None:
        """What measuring keyframe i needs, or None (the reason put in ``record``) when it
        cannot be; rendered at the run's prediction, or at ``T_field_cam_render`` (4, 4, the
        field's frame) when given."""
        if self.field is None:
            record.reason = "no field"
            return None
        if frame is None:
            record.reason = f"frame unreadable: {self.frames.error}"
            return None
        if T_field_cam_render is None:
            T_field_cam_render = state.in_field_frame(state.T_world_kf_pred)
        render_intrinsics = self.render_intrinsics(frame.intrinsics)
        return KeyframeJob(i, frame, T_field_cam_render, self.velocity(state, i), self.timing(),
                           state.depth_scale.scale, render_intrinsics,
                           feats_real=self._odometry_features(i, render_intrinsics),
                           fit_intrinsics=state.intrinsics_model.fits_both(i))

    def velocity(self, state: RunState, i: int) -> np.ndarray | None:
        """Body twist per second (GTSAM order) of the camera at frame i, by the motion model."""
        t = float(self.timestamps[i])
        dt = t - float(self.timestamps[i - 1]) if i >= 1 else 0.0
        return state.motion.twist(i, t, dt)

    def _odometry_features(self, i: int, render_intrinsics: Intrinsics):
        """``(features, 0.0)``: frame i's features as the feature odometry detected them, when
        they are what its correction would detect (``--odom vo --vo-width`` at the render's
        width); else None."""
        features_of = getattr(self.odometry, "features_of", None)
        features = features_of(i, render_intrinsics, self.config.align) if features_of is not None else None
        return None if features is None else (features, 0.0)
