"""Drift correction a frame at a time, for a loop that owns its camera and its odometry.

``DriftCorrector`` is the run of :class:`~nap3d_graph.run.pipeline.Pipeline` without a recorded
sequence: each call to :meth:`DriftCorrector.add_frame` gives one RGB-D frame with its
stamp and the odometry's increment since the previous frame, and returns the pose estimate
now, and, at a keyframe, the NAP3D correction and the GTSAM factor it put in the graph (or
why it did not). The batch run is the same steps over a sequence, so both give the same
trajectory for the same inputs.

    corrector = DriftCorrector(field, T_world_cam_start)
    for rgb, depth_m, stamp, T_prev_cur in camera_and_odometry():
        update = corrector.add_frame(rgb, depth_m, intrinsics, stamp, T_prev_cur)
        use(update.T_world_cam)                  # causal estimate at this frame
    trajectory = corrector.finish()             # the smoothed run (RunResult)

The batch run holds numpy's BLAS pool to ``config.library_threads`` while it goes; a loop
of one's own that wants the same wraps itself in ``with library_threads(1):``
(:mod:`nap3d_graph.run.library_threads`), since the setting is the whole process's.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from nap3d_graph.camera import Intrinsics, RGBDFrame
from nap3d_graph.conventions import as_T, rigid_transform_problem
from nap3d_graph.motion.odometry import Increment
from nap3d_graph.run.config import PipelineConfig
from nap3d_graph.run.history import FrameLog
from nap3d_graph.run.keyframe import CorrectionWorker
from nap3d_graph.run.pipeline import Pipeline
from nap3d_graph.run.records import KeyframeRecord, RunResult

__all__ = ["DriftCorrector", "LiveUpdate"]


@dataclass
class LiveUpdate:
    """What one frame changed. ``T_world_cam`` (4, 4): the estimate at this frame as known now
    (causal). ``keyframe``: this frame is a keyframe. When a correction met the graph during
    this frame: ``record`` (one row of corrections.csv), ``correction`` (the
    :class:`~nap3d_graph.results.Correction`, successful or not) and ``factor`` (the robust
    GTSAM factor that entered the graph, or None when the correction failed or was gated out;
    ``record.reason`` says why). Measured inline that is this keyframe's own; with
    ``PipelineConfig.overlap`` it is the one that landed now, of an earlier keyframe
    (``record.frame_index``). ``placed``: False while a run that starts from anywhere in a
    map has not been found in it (``T_world_cam`` is then in the run's own frame)."""

    T_world_cam: np.ndarray
    keyframe: bool = False
    placed: bool = True
    record: KeyframeRecord | None = None
    correction: object | None = None
    factor: object | None = None


class _LiveFrames:
    """The frames given so far, as the sequence the pipeline reads (the latest two kept; the
    stamps of the frames the run has not retired)."""

    def __init__(self):
        self._stamps: FrameLog[float] = FrameLog()
        self._frames: dict[int, RGBDFrame] = {}
        self.T_world_cam_gt = None
        self.intrinsics: Intrinsics | None = None

    @property
    def timestamps(self) -> FrameLog[float]:
        """Indexed by frame (``[i]``, ``[a:b]``), as a sequence's stamps are."""
        return self._stamps

    def forget_before(self, i: int) -> None:
        self._stamps.drop_before(i)

    def append(self, frame: RGBDFrame) -> int:
        i = len(self._stamps)
        self._stamps.append(float(frame.timestamp))
        self._frames[i] = frame
        self._frames.pop(i - 2, None)
        self.intrinsics = frame.intrinsics
        return i

    def __len__(self) -> int:
        return len(self._stamps)

    def __getitem__(self, i: int) -> RGBDFrame:
        return self._frames[int(i)]


class _GivenOdometry:
    """The caller's odometry: the increment handed in with each frame."""

    needs_frames = False

    def __init__(self, T_world_cam_start: np.ndarray):
        self._start = T_world_cam_start
        self.next: Increment | None = None

    def initial_pose(self) -> np.ndarray:
        return self._start

    def increment(self, i: int, frame) -> Increment:
        inc, self.next = self.next, None
        if inc is None:
            raise RuntimeError("add_frame gives each frame its increment before the run steps")
        return inc


def _rigid(pose, what: str) -> np.ndarray:
    """``pose`` (4x4 or ``gtsam.Pose3``) as a 4x4 array; ValueError naming ``what`` when it is
    not a rigid transform."""
    T = as_T(pose)
    problem = rigid_transform_problem(T, tolerance=1e-5)
    if problem:
        raise ValueError(f"{what} is not a rigid transform: {problem}")
    return T


class DriftCorrector:
    """Odometry and NAP3D corrections in an iSAM2 graph, a frame at a time.

    field: anything with ``render(T_world_cam, intrinsics)`` (:func:`nap3d_graph.load_field`).
    T_world_cam_start (4, 4) or ``gtsam.Pose3``: the first frame's pose in the field's frame;
        None with ``relocaliser``: the start is found in the map (below).
    config: a :class:`PipelineConfig`. With ``overlap`` each keyframe is measured on a worker
        thread and ``add_frame`` returns at once; its correction enters the graph at a later
        frame (that frame's :class:`LiveUpdate` carries it), and :meth:`finish` waits for the
        last one. ``land_within_s`` (say 0.9 of the camera's frame period less your own
        per-frame work) lets ``add_frame`` wait that long after it is called for the
        correction in flight, so one done by then comes with this frame.
    odometry_sigmas: (rad, m) per-frame sigmas of the increments when ``add_frame`` is given
    no covariance.
    on_retire: optional ``f(RunResult)`` for a loop that runs for hours: with a bounded graph
        (``config.graph_window``) the frames whose poses are final are handed to it (write
        them out) and forgotten, so memory stays flat; :meth:`finish` then gives the frames
        after them (see :class:`~nap3d_graph.run.pipeline.Pipeline`).
    relocaliser: a map's :class:`~nap3d_graph.mapping.relocalise.Relocaliser`
        (:func:`nap3d_graph.mapping.start.map_relocaliser`). Without a start pose the run starts
        from anywhere in the map: until a keyframe is found in it and the next confirms it
        (``LiveUpdate.placed``), the poses are in the run's own frame (its first camera), then
        the run moves into the map's. With a start pose it recovers a run lost in the map.
    """

    def __init__(self, field, T_world_cam_start=None, config: PipelineConfig | None = None,
                 odometry_sigmas: tuple[float, float] = (2e-3, 2e-3), on_retire=None, relocaliser=None):
        if T_world_cam_start is None and relocaliser is None:
            raise ValueError("give T_world_cam_start, or a map's relocaliser to find the start in the map")
        T_start = np.eye(4) if T_world_cam_start is None else _rigid(T_world_cam_start, "T_world_cam_start")
        config = dataclasses.replace(config or PipelineConfig(), progress=False)
        self._frames = _LiveFrames()
        self._odometry = _GivenOdometry(T_start)
        self._default_cov = np.diag([odometry_sigmas[0] ** 2] * 3 + [odometry_sigmas[1] ** 2] * 3)
        retire = None
        if on_retire is not None:
            def retire(segment: RunResult) -> None:
                self._frames.forget_before(segment.first_frame + len(segment.timestamps))
                on_retire(segment)
        self.pipeline = Pipeline(self._frames, field, self._odometry, config, on_retire=retire)
        if relocaliser is not None and T_world_cam_start is None:
            self.pipeline.start_in_map(relocaliser)
        elif relocaliser is not None:
            self.pipeline.recover_in_map(relocaliser)
        self.pipeline.start()
        self._worker = CorrectionWorker(field, self.pipeline.config) if self.pipeline.overlaps() else None

    def add_frame(self, rgb: np.ndarray, depth_m: np.ndarray, intrinsics: Intrinsics, stamp: float,
                  T_prev_cur: np.ndarray | None = None, covariance: np.ndarray | None = None) -> LiveUpdate:
        """One frame: RGB (H, W, 3) uint8, z-depth (H, W) metres (0 or NaN missing), its camera,
        its stamp (s, increasing), and the odometry's ``T_prev_cur`` (4, 4) from the previous
        frame's camera to this one's (with its 6x6 covariance, GTSAM order; default from
        ``odometry_sigmas``). The first frame takes no increment. Raises ValueError on a bad
        increment or stamp (the graph is left as it was)."""
        i = len(self._frames)
        if i > 0:
            if T_prev_cur is None:
                raise ValueError("every frame after the first needs the odometry's T_prev_cur")
            T_prev_cur = _rigid(T_prev_cur, "T_prev_cur")
            if not stamp > self._frames.timestamps[-1]:
                raise ValueError(f"stamps must increase: {stamp} after {self._frames.timestamps[-1]}")
            cov = self._default_cov if covariance is None else np.asarray(covariance, dtype=float)
            if cov.shape != (6, 6) or not np.all(np.isfinite(cov)):
                raise ValueError(f"the increment's covariance must be a finite 6x6 matrix, got {cov.shape}")
            self._odometry.next = Increment(T_prev_cur, cov)
        frame = RGBDFrame(rgb, depth_m, intrinsics, float(stamp))  # validates the images
        self._frames.append(frame)
        pipeline = self.pipeline
        records, keyframes = len(pipeline.records), len(pipeline.keyframe_indices)
        pipeline.step(i, self._worker)
        update = LiveUpdate(pipeline.current_estimate, keyframe=len(pipeline.keyframe_indices) > keyframes,
                            placed=pipeline.placed)
        if len(pipeline.records) > records:
            update.record = pipeline.records[-1]
            update.correction, update.factor = pipeline.last_correction, pipeline.last_factor
        return update

    def finish(self) -> RunResult:
        """Every frame's pose so far, smoothed with every correction (a batch solve); with
        ``overlap``, the correction still in flight is waited for first and the worker stops."""
        if self._worker is not None:
            self.pipeline.land_pending(self._worker)
            self._worker.close()
            self._worker = None
        return self.pipeline.result(len(self._frames))
