"""What a drift-correction run is told: :class:`PipelineConfig` (what it gives back is in
:mod:`nap3d_graph.run.records`)."""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field

import numpy as np

from nap3d_graph.arguments import (
    auto_or_non_negative,
    non_negative_float,
    non_negative_int,
    positive_int,
    probability,
    setting,
)
from nap3d_graph.conventions import pose_error
from nap3d_graph.datasets.depth_timing import CaptureTiming
from nap3d_graph.fields.base import field_sigmas
from nap3d_graph.fields.gap_error import error_sigmas_at, has_error_by_view
from nap3d_graph.nap3d.config import AlignConfig
from nap3d_graph.nap3d.keyframe import MeasureSettings

__all__ = ["PipelineConfig", "with_field_error"]

@dataclass
class PipelineConfig:
    """Settings of one run. A field the run's settings tree holds says where (``tree``: its
    section and name in :class:`~nap3d_graph.run.settings.RunSettings` and ``config.yaml``) and,
    when the command line sets it, its flag and help (:func:`~nap3d_graph.arguments.setting`):
    declared here once.

    keyframe_every: a keyframe every N frames; keyframe_distance_m / keyframe_angle_deg
        (when > 0) also make one once the odometry moved that far since the last.
    keyframe_window: when a keyframe is due, take it at the first frame of the next
        ``keyframe_window`` frames that is sharp (variance of the Laplacian at least
        ``keyframe_sharpness_fraction`` of the median of the frames since the last
        keyframe), the last of them if none is: a motion-blurred frame gives the matcher
        little to hold on to (0 or 1: the due frame, as it comes). Causal: no frame is
        waited for beyond the window.
    keyframe_on_doubt: also take a keyframe at the frame after the odometry guessed a step
        (visual odometry lost track: fast, blurred motion), so a jump is corrected at once.
    keyframe_when_idle: with ``overlap``, N > 0 also takes a keyframe at any frame at least
        N after the last one while the worker has no measurement in flight: the second core
        measures as often as it can keep up, and ``keyframe_every`` is the longest interval
        (which waits for the worker if need be). 0 (the default): keyframes by count,
        distance and angle only. Which frames are keyframes then depends on the machine's
        speed (with ``run --pace``, on the camera's rate).
    correction_iterations: render-align rounds per correction (see ``correct_pose``).
    render_width, render_height: the field renders at this size (None: the frame's).
    gate_p: chi-square gate probability (6 dof) of a correction against the prediction.
    use_anchor: estimate the field's frame in the world (``M(0)``) instead of assuming it is
        the world frame.
    odom_drift_fraction, odom_drift_rad_per_m, odom_drift_rad_per_rad: odometry drift that
        the per-frame sigmas cannot describe (scale and heading biases), as sigmas growing with
        the distance travelled and the angle turned between keyframes (3% of the distance,
        1 deg per metre and 3% of the angle by default: a typical visual odometry). They
        keep the gate from rejecting exactly the corrections a biased odometry needs.
    odom_drift_m_per_s, odom_drift_rad_per_s: drift that grows with *time*, moving or not
        (a velocity or gyro bias integrates while the robot stands still), as sigmas per
        second between keyframes (1 cm/s and 0.2 deg/s by default: the simulator's odometry
        bias). Added to the distance terms.
    compensate_timing: when the field records the sensor's capture timing (a real recording's
        depth captured ~30 ms before its colour) and the frame has a depth stamp, move each
        keyframe's depth to the colour's capture instant with the odometry's velocity, and
        the corrected pose back to the frame's stamp, before it enters the graph.
    rolling_shutter_s: the real colour camera's rolling-shutter readout, first row to last
        (seconds; 0: a global shutter). With the odometry's velocity at the keyframe, each
        matched real point is moved to the middle row's instant before the alignment
        (:mod:`nap3d_graph.nap3d.rolling_shutter`). None, the default: the readout the
        capture timing records (``CaptureTiming.readout_s``, estimated by ``train-field`` from
        the recording's ground truth; 0 without one). A CMOS camera at its highest frame rate
        reads for up to a frame period (fr1/desk's Kinect colour camera: 24 ms estimated).
    timing: the sensor's capture timing (``depth_offset_s``, ``colour_offset_s``,
        ``depth_scale``) when the field does not record it (the oracle of a simulated room,
        a nerfstudio model): e.g. :func:`nap3d_graph.datasets.depth_timing.estimate_timing` of any
        recording of the same camera with ground truth.
    final_gnc: the written trajectory is solved by GTSAM's graduated non-convexity (TLS) over
        the NAP3D factors, with the odometry and the priors known inliers: a wrong
        correction that passed the gate (the prediction was uncertain just then) is found
        by its disagreement with the corrections and the odometry around it and weighed
        out (``gnc_p``: each factor's chi-square inlier probability).
    field_sigma_m, field_sigma_rad, field_sigma_depth_m: the field's own geometric error,
        added to every correction's covariance (translation ``field_sigma_m`` per axis,
        rotation ``field_sigma_rad`` per axis, or ``field_sigma_m / field_sigma_depth_m`` rad
        when that is None): a correction measures the pose in the field's geometry, and a
        trained field's is centimetres off where the alignment's covariance, which knows only
        the matches, says millimetres. None (the default): what the field measured of itself
        when it was built (``meta["field_error"]``, see
        :mod:`nap3d_graph.fields.field_error`; 0 for a field that records none, such as the
        exact oracle); :func:`with_field_error` resolves it. 0 adds nothing.
    field_error_by_view: set by :func:`with_field_error` when the field's error comes from
        the field and the field also measured how it grows away from what it saw (a view
        field's own ``error_sigmas_at``, or a grid's or splat field's model from
        ``train-field --error-growth``: :mod:`nap3d_graph.fields.error_growth`; larger the
        farther the asked pose is from its nearest view): each correction then adds the
        field's error at its own render pose, with the resolved sigmas as the floor.
    depth_scale_check, depth_scale_tolerance, depth_scale_sigmas, depth_scale_window: every
        correction also measures the real depth's scale against the field's (a similarity
        fit on its inliers). A running estimate (median of the last ``depth_scale_window``
        frames' scales) is applied to each keyframe's depth, so a sensor whose every depth
        is a few percent off is calibrated on the fly; a frame whose scale still differs
        from it by more than ``depth_scale_tolerance`` and ``depth_scale_sigmas`` of its
        sigma is a failed correction (its depth or its match is wrong).
    intrinsics_check_every: where the alignment fits the self-calibrated camera model beside
        the given one (``AlignConfig.estimate_intrinsics="auto"``), the run stops fitting it once
        the given intrinsics won this many keyframes in a row, and fits both again every this
        many keyframes (a win for the self-calibrated model resumes fitting both at every
        keyframe); 0: both at every keyframe. The camera does not change during a run, and
        the second fit is 10-20% of a keyframe's measurement with XFeat
        (:mod:`~nap3d_graph.run.intrinsics_model`).
    overlap: measure each keyframe's correction on a worker thread while the odometry goes
        on (the second core); the correction enters the graph, at its keyframe, at the first
        frame after it is ready, and a new keyframe waits for the one in flight. The causal
        trajectory then holds each frame's pose as it was known at that frame. Results depend
        on when a correction finishes, so an overlapped run is not bit-for-bit repeatable.
        The IMU path does not overlap.
    detect_ahead: with ``overlap``, when a frame due to be a keyframe (``keyframe_every``)
        arrives, the worker detects its features while the run computes its odometry; the
        keyframe's measurement then starts at its render (the features are the same: nothing
        changes but when its correction lands).
    render_ahead, render_ahead_m, render_ahead_deg: with ``overlap``, also render ahead: while
        the worker is idle and the next frame is due to be a keyframe, it renders at that
        frame's one-step guess (the last frame's pose, one more step of the same motion) and
        detects the render's features, so the keyframe's measurement starts at the matching.
        The keyframe aligns to that render when it was made within ``render_ahead_m`` /
        ``render_ahead_deg`` of its own prediction, else renders afresh. Off by default: on
        fr1/desk at 15 Hz the guess is up to 3 deg off in fast turns, and the corrections
        measured from it were worse (median 16.7 against 14.7 mm); it lands them a frame
        sooner (``benchmarks/realtime_desk.py``). At 30 Hz the guess is four times closer.
    land_within_s: with ``overlap``, how long after a frame's step starts (the frame arrived)
        the run may wait for the correction in flight before it gives that frame's pose: a
        correction done by then lands at that frame instead of a later one. 0 (the default)
        never waits. The camera's frame period less the odometry's time waits only while the
        run would sit idle for the next frame anyway, so it never falls behind the camera.
    read_ahead: frames a replay reads ahead on a background thread while the run works on
        the current one (:mod:`nap3d_graph.run.read_ahead`; 0: read each frame when its step
        comes). Only for sequences whose frames can be read from another thread; the frames
        are the same either way.
    library_threads: the threads numpy's BLAS (OpenBLAS) works with while the run goes
        (:mod:`nap3d_graph.run.library_threads`; None: as it comes, every core). The run's
        own threads are its parallelism, and OpenBLAS's idle threads spin: on two cores an
        fr1/desk run with XFeat went 1.1x as fast inline with it on one thread, 1.2x
        overlapped. OpenCV's pool is left as it is. Same results either way.
    graph_window: keyframes kept in iSAM2 (0: all, the default). With N > 0, once more than
        1.5 N keyframes are in the graph the oldest are marginalised down to N (iSAM2's
        ``marginalizeLeaves``: their information stays as a linear prior on the window's
        first keyframe) and their poses are fixed at their estimate then, so a long run's
        graph, its updates and its final solve stay bounded; corrections that land later
        no longer move those poses. Not with the map anchor or the IMU path.
    """

    keyframe_every: int = setting(5, "--keyframe-every", tree=("keyframes", "every"), type=positive_int,
        help="a keyframe (and a correction) every N frames (default %(default)s)")
    keyframe_distance_m: float = setting(0.0, "--keyframe-distance", tree=("keyframes", "distance_m"), type=non_negative_float,
        help="also a keyframe after this many metres of odometry (0: off)")
    keyframe_angle_deg: float = setting(0.0, "--keyframe-angle", tree=("keyframes", "angle_deg"), type=non_negative_float,
        help="also a keyframe after this many degrees of rotation (0: off)")
    keyframe_window: int = setting(0, "--keyframe-window", tree=("keyframes", "window"), type=non_negative_int, metavar="N",
        help="a due keyframe is taken at the first sharp frame (variance of the Laplacian at least 0.8 of the "
             "median since the last keyframe) among the next N, the last of them if none is: motion blur starves"
             " the matcher (0 or 1: the due frame; default %(default)s)")
    keyframe_sharpness_fraction: float = setting(0.8, tree=("keyframes", "sharpness_fraction"))
    keyframe_on_doubt: bool = setting(False, "--keyframe-on-doubt", tree=("keyframes", "on_doubt"), action=argparse.BooleanOptionalAction,
        help="also a keyframe right after the odometry guessed a step (visual odometry lost track), so the jump "
             "is corrected at once")
    keyframe_when_idle: int = 0
    correction_iterations: int = setting(MeasureSettings.correction_iterations, "--iterations", tree=("alignment", "iterations"), type=positive_int,
        help="render-align rounds per correction (default %(default)s; 2 re-renders at the corrected pose: a "
             "little more accurate, twice the time)")
    render_width: int | None = 320
    render_height: int | None = 240
    robust: str | None = setting("huber", tree=("graph", "robust"))
    gate_p: float = setting(0.997, "--gate-p", tree=("graph", "gate_p"), type=probability,
        help="chi-square gate probability, in (0, 1) (default %(default)g)")
    use_anchor: bool = setting(False, "--anchor", tree=("graph", "anchor"), only_run=True, action="store_true",
        help="estimate the field's frame in the world (map anchor M(0)) instead of assuming it is the odometry's"
             " world frame")
    anchor_rot_sigma_rad: float = setting(0.1, tree=("graph", "anchor_rot_sigma_rad"))
    anchor_trans_sigma_m: float = setting(0.5, tree=("graph", "anchor_trans_sigma_m"))
    prior_rot_sigma_rad: float = setting(1e-3, tree=("graph", "prior_rot_sigma_rad"))
    prior_trans_sigma_m: float = setting(1e-3, tree=("graph", "prior_trans_sigma_m"))
    relinearize_threshold: float = setting(1e-3, tree=("graph", "relinearize_threshold"))
    compensate_timing: bool = True
    rolling_shutter_s: float | None = setting(MeasureSettings.rolling_shutter_s, "--rolling-shutter", tree=("alignment", "rolling_shutter_s"), type=auto_or_non_negative, metavar="S|auto",
        help="the colour camera's rolling-shutter readout, first row to last, in seconds: each keyframe's "
             "matched points are moved along the odometry's velocity to the middle row's instant before the "
             "alignment. Default auto: the readout train-field estimated from the recording's ground truth with "
             "its capture timing (fr1/desk's Kinect: 24 ms; 0, a global shutter, where the data showed none or "
             "the field records no timing); 0: a global shutter")
    timing: CaptureTiming | dict | None = None
    final_gnc: bool = setting(True, tree=("graph", "final_gnc"))
    gnc_p: float = setting(0.997, tree=("graph", "gnc_p"))
    depth_scale_check: bool = setting(MeasureSettings.depth_scale_check, tree=("alignment", "depth_scale_check"))
    depth_scale_tolerance: float = setting(0.02, tree=("alignment", "depth_scale_tolerance"))
    depth_scale_sigmas: float = setting(4.0, tree=("alignment", "depth_scale_sigmas"))
    depth_scale_window: int = setting(15, tree=("alignment", "depth_scale_window"))
    intrinsics_check_every: int = setting(5, tree=("alignment", "intrinsics_check_every"))
    odom_drift_fraction: float = setting(0.03, tree=("odometry", "drift_fraction"))
    odom_drift_rad_per_m: float = setting(0.0175, tree=("odometry", "drift_rad_per_m"))
    odom_drift_rad_per_rad: float = setting(0.03, tree=("odometry", "drift_rad_per_rad"))
    odom_drift_m_per_s: float = setting(0.01, tree=("odometry", "drift_m_per_s"))
    odom_drift_rad_per_s: float = setting(0.0035, tree=("odometry", "drift_rad_per_s"))
    field_sigma_m: float | None = setting(None, "--field-sigma", tree=("alignment", "field_sigma_m"), type=auto_or_non_negative, metavar="M|auto",
        help="the field's own geometric error in metres, added to every correction's covariance (rotation: M / 2"
             " m per radian). Default auto: what the field measured of itself when train-field built it (0 for "
             "the exact oracle and fields that record none); 0: take the field as exact")
    field_sigma_rad: float | None = setting(None, tree=("alignment", "field_sigma_rad"))
    field_sigma_depth_m: float = setting(2.0, tree=("alignment", "field_sigma_depth_m"))
    field_error_by_view: bool = False
    overlap: bool = False
    detect_ahead: bool = setting(True, tree=("threads", "detect_ahead"))
    render_ahead: bool = setting(False, "--render-ahead", tree=("threads", "render_ahead"), action="store_true",
        help="with --overlap: render the next keyframe at its one-step guessed pose while the second thread is "
             "idle, so its correction lands sooner (for slow fields or fast cameras; its corrections can be "
             "slightly worse where the motion turns fast)")
    render_ahead_m: float = setting(MeasureSettings.render_ahead_m, tree=("threads", "render_ahead_m"))
    render_ahead_deg: float = setting(MeasureSettings.render_ahead_deg, tree=("threads", "render_ahead_deg"))
    land_within_s: float = 0.0
    read_ahead: int = setting(2, tree=("threads", "read_ahead"))
    library_threads: int | None = setting(1, tree=("threads", "library_threads"))
    graph_window: int = setting(0, "--graph-window", tree=("graph", "window"), type=non_negative_int, metavar="N",
        help="keep the last N keyframes in iSAM2 (>= 3), marginalising older ones and fixing their poses, so a "
             "long run's graph and its updates stay bounded (default %(default)s: every keyframe, the whole "
             "trajectory smoothed at the end; not with --odom imu or --anchor)")
    max_frames: int | None = setting(None, "--max-frames", tree=("source", "max_frames"), type=positive_int,
        help="stop after this many frames")
    progress: bool = False
    relocalise_after: int = setting(3, tree=("graph", "relocalise_after"))
    #: A run started anywhere in a map is placed once the keyframes that confirm its
    #: relocalisation span this much of its own travel (metres; :class:`~nap3d_graph.mapping.start.PlacementSettings`).
    placement_travel_m: float = setting(1.0, tree=("graph", "placement_travel_m"))
    align: AlignConfig = field(default_factory=AlignConfig)

    def __post_init__(self) -> None:
        if self.graph_window and self.graph_window < 3:
            raise ValueError(f"graph_window must be 0 (all keyframes) or >= 3, got {self.graph_window}")
        if self.keyframe_every < 1:
            raise ValueError(f"keyframe_every must be >= 1, got {self.keyframe_every}")
        if self.keyframe_window < 0 or not 0 < self.keyframe_sharpness_fraction <= 1:
            raise ValueError(f"keyframe_window must be >= 0 and keyframe_sharpness_fraction in (0, 1], got "
                             f"{self.keyframe_window}, {self.keyframe_sharpness_fraction}")
        for name in ("field_sigma_m", "field_sigma_rad"):
            value = getattr(self, name)
            if value is not None and not value >= 0:
                raise ValueError(f"{name} must be >= 0 or None, got {value}")
        if self.keyframe_when_idle < 0 or (self.keyframe_when_idle and not self.overlap):
            raise ValueError(f"keyframe_when_idle must be >= 0 and needs overlap (the worker it waits to be idle), "
                             f"got {self.keyframe_when_idle} with overlap={self.overlap}")
        if self.library_threads is not None and self.library_threads < 1:
            raise ValueError(f"library_threads must be >= 1 or None (BLAS's pool as it comes), got {self.library_threads}")
        if self.intrinsics_check_every < 0:
            raise ValueError(f"intrinsics_check_every must be >= 0 keyframes (0: both models at every keyframe), "
                             f"got {self.intrinsics_check_every}")
        if self.read_ahead < 0:
            raise ValueError(f"read_ahead must be >= 0 frames, got {self.read_ahead}")
        if self.rolling_shutter_s is not None and not (np.isfinite(self.rolling_shutter_s)
                                                       and 0 <= self.rolling_shutter_s <= 1):
            raise ValueError(f"rolling_shutter_s must be a readout time in [0, 1] seconds or None (the capture "
                             f"timing's), got {self.rolling_shutter_s}")
        if not self.land_within_s >= 0:
            raise ValueError(f"land_within_s must be >= 0 seconds, got {self.land_within_s}")
        if not self.field_sigma_depth_m > 0:
            raise ValueError(f"field_sigma_depth_m must be > 0, got {self.field_sigma_depth_m}")

    def field_covariance(self, field=None, T_field_cam: np.ndarray | None = None) -> np.ndarray | None:
        """The field's error as a 6x6 covariance (GTSAM order), or None when it adds nothing;
        with ``field_error_by_view``, the ``field``'s own at the render pose ``T_field_cam``
        where it is larger than the resolved sigmas."""
        s_t = self.field_sigma_m or 0.0
        s_r = self.field_sigma_rad if self.field_sigma_rad is not None else s_t / self.field_sigma_depth_m
        local = None
        if self.field_error_by_view and field is not None and T_field_cam is not None:
            local = error_sigmas_at(field, T_field_cam)
        if local is not None:
            s_t, s_r = max(s_t, local[0]), max(s_r, local[1])
        if s_t <= 0 and s_r <= 0:
            return None
        return np.diag([s_r**2] * 3 + [s_t**2] * 3)

    def drift_covariance(self, T_prev_cur: np.ndarray, dt_s: float) -> np.ndarray:
        """Diagonal covariance (6, 6) of the odometry's bias-like drift over one keyframe
        interval: sigmas growing with the distance, the angle and the time (``dt_s`` seconds)."""
        distance_m, angle_deg = pose_error(T_prev_cur, np.eye(4))
        rot = self.odom_drift_rad_per_m * distance_m + self.odom_drift_rad_per_rad * np.radians(angle_deg)
        trans = self.odom_drift_fraction * distance_m
        rot_var = rot**2 + (self.odom_drift_rad_per_s * dt_s) ** 2
        trans_var = trans**2 + (self.odom_drift_m_per_s * dt_s) ** 2
        return np.diag([rot_var] * 3 + [trans_var] * 3)


def with_field_error(config: PipelineConfig, field) -> PipelineConfig:
    """``config`` with ``field_sigma_m`` / ``field_sigma_rad`` resolved: as given, or (None)
    what ``field`` measured of itself when it was built (zeros when it records nothing)."""
    import dataclasses

    if config.field_sigma_m is not None:
        return config

    sigma_m, sigma_rad = field_sigmas(field) if field is not None else (0.0, 0.0)
    rad = config.field_sigma_rad if config.field_sigma_rad is not None else sigma_rad

    by_view = field is not None and has_error_by_view(field)
    return dataclasses.replace(config, field_sigma_m=sigma_m, field_sigma_rad=rad, field_error_by_view=by_view)
