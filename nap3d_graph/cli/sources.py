"""What ``run`` and ``compare`` share: the data source, field, odometry and keyframe options,
and turning them into a ready :class:`~nap3d_graph.run.pipeline.Pipeline`."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nap3d_graph.cache import default_cache_dir
from nap3d_graph.conventions import inv_T
from nap3d_graph.datasets import is_rosbag, is_sevenscenes_folder, open_sequence, source_of
from nap3d_graph.datasets.depth_timing import resolve_capture_timing
from nap3d_graph.datasets.posed import reframed
from nap3d_graph.datasets.realsense import capture_live
from nap3d_graph.fields import resolve_field
from nap3d_graph.mapping.folder import load_map_info
from nap3d_graph.mapping.start import map_relocaliser as relocaliser_of
from nap3d_graph.motion.imu import ImuConfig, estimate_gravity, gravity_angle_deg
from nap3d_graph.motion.odometry import DenseVisualOdometry, VisualOdometry, make_odometry
from nap3d_graph.nap3d.config import AlignConfig
from nap3d_graph.nap3d.keyframe import readout_of
from nap3d_graph.nap3d.matching import choose_matcher
from nap3d_graph.run.default import embedded_default_inputs
from nap3d_graph.run.imu import ImuOdometry
from nap3d_graph.run.pipeline import Pipeline
from nap3d_graph.run.settings import LAND_WITHIN_FRAME_SHARE, SettingsError

from .binding import add_options, settings_from_args
from .common import UsageError, parse_pose, parse_size, warn_depth_units, warn_trained_frames
from .run_options import SOURCE_OPTIONS

__all__ = ["add_source_arguments", "prepare", "Prepared"]


def warn_guessed_camera(sequence) -> None:
    """Print a warning when a TUM-layout folder's camera is TUM's default, a guess."""
    import sys

    if getattr(sequence, "intrinsics_source", None) == "default":
        K = sequence.intrinsics
        print(f"warning: {sequence.path} has no intrinsics.json and no freiburg1/2/3 in its name: using TUM's "
              f"default camera (fx={K.fx:g}, fy={K.fy:g}, cx={K.cx:g}, cy={K.cy:g}), a guess; write your camera to "
              "intrinsics.json in the folder (fx, fy, cx, cy, width, height)", file=sys.stderr)


def land_within_s(value: float | str, sequence) -> float:
    """``--land-within`` in seconds: as given, or ('frame') :data:`LAND_WITHIN_FRAME_SHARE`
    of the sequence's median frame period."""
    if value != "frame":
        return float(value)
    stamps = np.asarray(sequence.timestamps, dtype=float)
    if stamps.size < 2:
        raise UsageError("--land-within frame needs at least two frames to find the camera's rate")
    return LAND_WITHIN_FRAME_SHARE * float(np.median(np.diff(stamps)))


def live_defaults(args, odom_kind: str) -> None:
    """Resolve ``--overlap`` and ``--keyframe-when-idle`` left at their defaults: a run fed at
    its camera's rate (``run --pace``) takes the live settings (overlapped, a keyframe whenever
    the second thread is idle; ``--land-within frame`` follows from ``_land_within_default``),
    any other run is inline. The IMU path never overlaps."""
    paced = getattr(args, "pace", None) is not None
    if args.overlap is None:
        args.overlap = paced and odom_kind != "imu"
    if args.keyframe_when_idle is None:
        args.keyframe_when_idle = 1 if args.overlap and paced else 0


def _land_within_default(args) -> float | str:
    """``--land-within`` as given, else 'frame' for an overlapped run fed at its camera's
    rate (``run --pace``: waiting costs nothing while the next frame has not come), else 0."""
    if args.land_within is not None:
        return args.land_within
    return "frame" if args.overlap and getattr(args, "pace", None) else 0.0


def add_source_arguments(p) -> None:
    """The source, field, odometry and keyframe options of a drift-correction run (bound to
    the run's settings tree: :data:`~nap3d_graph.cli.run_options.SOURCE_OPTIONS`)."""
    add_options(p, SOURCE_OPTIONS)


@dataclass
class Prepared:
    """A run ready to go: ``pipeline()`` is it; ``config`` its configuration as the pipeline
    resolved it (the field's error included); ``record`` is its config.yaml."""

    sequence: object
    field: object
    odometry: object
    config: object
    record: dict
    name: str
    runner: object

    def pipeline(self):
        return self.runner


def _say_readout(config, field_obj) -> float:
    """The rolling-shutter readout (s) the run compensates, said in one line when it did not come
    from the command line."""
    readout_s = readout_of(config, resolve_capture_timing(field_obj, given=config.timing,
                                                          compensate=config.compensate_timing)[0])
    if readout_s > 0 and config.rolling_shutter_s is None:
        print(f"rolling shutter: colour rows read over {readout_s * 1000:.0f} ms (estimated with the capture timing); "
              "each keyframe is aligned as of its middle row (--rolling-shutter 0: a global shutter)")
    return readout_s


def _timing(args, field_obj, sequence):
    """The capture timing a run is given beyond its field's: the one estimated from the
    sequence's ground truth when the field records none (None: off, no field, nothing known,
    the field's own, which the pipeline takes itself, or a map's field: a run on a map reads
    no ground truth)."""
    if field_obj is None:
        return None
    if (getattr(field_obj, "meta", None) or {}).get("map") is not None:
        return None  # a run on a map reads no ground truth: the map's field has the survey's timing, or none is known
    timing, source = resolve_capture_timing(field_obj, sequence, compensate=args.timing == "auto")
    if source != "estimated":
        return None
    print(f"capture timing estimated from this sequence's ground truth (the field records none): depth "
          f"{timing.depth_offset_s * 1000:+.0f} ms from its stamp, colour {timing.colour_offset_s * 1000:+.0f} ms")
    return timing


def imu_config(args, base=None):
    """The IMU's noise, gravity and extrinsics from the options, over ``base`` (a recording's
    own :class:`~nap3d_graph.motion.imu.ImuConfig`; default: the simulator's)."""
    import dataclasses


    magnitude = args.gravity if isinstance(args.gravity, float) else 9.81
    vector = tuple(float(v) for v in args.gravity) if isinstance(args.gravity, (list, tuple)) else None
    if vector is not None:
        magnitude = float(np.linalg.norm(vector))
    config = (dataclasses.replace(base, gravity=magnitude, gravity_world=vector) if base is not None
              else ImuConfig(gravity=magnitude, gravity_world=vector))
    if args.imu_noise is not None:
        try:
            values = [float(v) for v in args.imu_noise.replace(",", " ").split()]
        except ValueError:
            values = []
        if len(values) != 4 or not all(v > 0 for v in values):
            raise UsageError(f"--imu-noise needs 4 positive numbers (accel, gyro, accel walk, gyro walk), "
                             f"got {args.imu_noise!r}")
        config.accel_noise_density, config.gyro_noise_density, config.accel_bias_rw, config.gyro_bias_rw = values
    if args.imu_extrinsics is not None:
        config.T_cam_imu = parse_pose(args.imu_extrinsics, None)
    return config


def _inputs(args):
    """(sequence folder, field, field description, run name) from the arguments."""
    if args.data is None:
        if args.traj != "sim":
            raise UsageError(f"--traj {args.traj} needs --data PATH" + (" (a .bag/.db3 recording, or live)"
                                                                       if args.traj == "realsense" else ""))
        cache = args.cache or default_cache_dir()
        data, field_obj, field_path, _ = embedded_default_inputs(cache, args.train_steps, progress=True, say=print)
        if args.field not in (None, "default"):
            field_obj = resolve_field(args.field, open_sequence(data))
            field_path = args.field
        return data, field_obj, str(field_path), "default"
    if args.field is None:
        raise UsageError("--data needs --field (a checkpoint, 'oracle' for simulated data, or 'none')")

    if args.traj == "rosbag":
        if not args.data.exists():
            raise UsageError(f"--traj rosbag: {args.data}: no such bag file or folder")
        if not is_rosbag(args.data):
            raise UsageError(f"--traj rosbag needs a ROS 1 .bag (not a RealSense recording) or a ROS 2 bag folder "
                             f"(with metadata.yaml), got {args.data}")
        return args.data, None, args.field, args.traj
    if is_rosbag(args.data):
        raise UsageError(f"{args.data} is a ROS bag: use --traj rosbag")
    if args.traj == "realsense":
        return _realsense_data(args), None, args.field, args.traj
    if args.data.suffix.lower() in (".bag", ".db3"):
        raise UsageError(f"{args.data} is a RealSense recording: use --traj realsense")

    if args.traj == "7scenes" and args.data.is_dir() and not is_sevenscenes_folder(args.data):
        raise UsageError(f"{args.data} is not a 7-Scenes folder (no frame-000000.pose.txt-like files, no "
                         "seq-01/-like folders)")
    return args.data, None, args.field, args.traj


def detected_source(args) -> str:
    """``--traj`` as given, or for ``auto`` the source ``--data``'s path says (a RealSense
    recording for 'live', sim without data)."""
    if args.traj != "auto":
        return args.traj
    if args.data is None:
        return "sim"
    if str(args.data) == "live":
        return "realsense"
    if not args.data.exists():
        raise UsageError(f"--data {args.data}: no such file or folder")
    return source_of(args.data)


def _realsense_data(args) -> Path:
    """The recording to read: the file given, or a capture of the connected camera."""
    if str(args.data) != "live":
        if args.data.suffix.lower() not in (".bag", ".db3"):
            raise UsageError(f"--traj realsense needs a .bag or .db3 recording (or 'live'), got {args.data}")
        return args.data
    import tempfile


    out = args.record or Path(tempfile.mkdtemp(prefix="nap3d_live_")) / "live.bag"
    print(f"capturing {args.seconds:.0f} s from the RealSense camera into {out} ...")
    return capture_live(out, args.seconds)


def _odometry(args, sequence, initial_pose):
    """``(kind, odometry)``: the motion source the options and the data call for (the run's
    motion model follows from it: an IMU's preintegration, or a frame odometry's increments)."""
    if args.odom:
        odom_kind = args.odom
    elif args.traj == "realsense" or (getattr(sequence, "T_world_cam_odom", None) is None
                                      and sequence.T_world_cam_gt is None):
        # A recording without ground truth to draw noise on: its own motion source, its IMU or its frames.
        odom_kind = "imu" if getattr(sequence, "imu", None) is not None else "vo"
    else:
        odom_kind = "recorded" if getattr(sequence, "T_world_cam_odom", None) is not None else "noisy"
    if getattr(args, "vo_width", None) is not None and odom_kind != "vo":  # a chosen odometry, too
        raise UsageError(f"--vo-width is for --odom vo, not --odom {odom_kind}")
    try:
        if odom_kind == "imu":
            config = imu_config(args, getattr(sequence, "imu_config", None))
            odometry = ImuOdometry.from_sequence(sequence, config, initial_pose)
            config = _checked_gravity(args, odometry)
            odometry = ImuOdometry.from_sequence(sequence, config, initial_pose)
            odometry.fallback = _fallback_odometry(getattr(args, "fallback_odom", "dense"), args.matcher)
            return odom_kind, odometry
        if odom_kind == "vo" and getattr(args, "vo_width", None) is None and getattr(args, "pace", None) is not None:
            # Fed as a live camera: the feature odometry at the render's width, its features shared
            # with the corrections (on fr1/desk SIFT keeps up with 15 Hz so, not at 640).
            args.vo_width = parse_size(args.render_size)[0]
            print(f"--odom vo fed at the camera's rate: frames resized to {args.vo_width} px wide, their features "
                  "shared with the corrections (--vo-width sets it)")
        odometry = make_odometry(odom_kind, sequence, args.seed, args.odom_rot_sigma, args.odom_trans_sigma,
                                 initial_pose=initial_pose, matcher=args.matcher,
                                 vo_width=getattr(args, "vo_width", None))
        return odom_kind, odometry
    except ValueError as exc:  # the data cannot give that odometry: say which and what to use
        raise UsageError(str(exc)) from None


def chosen_matcher(name: str, sequence) -> str:
    """The matcher for this data (``--matcher auto``: said on the terminal, with why)."""
    chosen, why = choose_matcher(name, sequence)
    if chosen != name:
        print(f"matcher: {chosen} ({why}; --matcher sets it)")
    return chosen


def _fallback_odometry(kind: str, matcher: str | None):
    """The frame odometry an IMU run falls back on (None for 'none')."""
    if kind == "none":
        return None
    if kind == "dense":
        return DenseVisualOdometry()
    return VisualOdometry(config=AlignConfig(min_opacity=0.5) if matcher is None else
                          AlignConfig(min_opacity=0.5, matcher=matcher))


def _checked_gravity(args, odometry):
    """The IMU config with gravity estimated (``--gravity auto``, or ``check`` when the
    accelerometer at the start disagrees with z-up by more than 10 degrees), or as given
    (warned about in that case)."""
    import dataclasses
    import sys


    config = odometry.stream.config
    try:
        measured, spread = estimate_gravity(odometry.stream, odometry.T_world_cam0, config.gravity)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    angle = gravity_angle_deg(measured, config.gravity_vector())
    if args.gravity == "auto" or (args.gravity == "check" and angle > 10.0):
        from_z = gravity_angle_deg(measured, np.array([0.0, 0.0, -1.0]))
        print(f"gravity from the accelerometer over the first 0.5 s: ({measured[0]:.2f}, {measured[1]:.2f}, "
              f"{measured[2]:.2f}) m/s^2 in the field's frame, {from_z:.1f} deg from -z (samples' spread "
              f"{spread:.2f} m/s^2); the graph refines its tilt")
        return dataclasses.replace(config, gravity_world=tuple(float(v) for v in measured))
    if angle > 10.0:
        print(f"warning: the accelerometer at the start puts gravity {angle:.0f} deg from the one assumed "
              f"({config.gravity_vector().round(2).tolist()} m/s^2 in the field's frame): is the field's frame not "
              "z-up? --gravity auto estimates it from the data, --gravity 'gx gy gz' sets it", file=sys.stderr)
    return config


#: The odometries that read the recording's ground truth, and what they read of it: refused on a map.
GROUND_TRUTH_ODOMETRY = {
    "noisy": "its motion is the ground truth with noise added",
    "recorded": "without --initial-pose (its start in the map's frame) it starts at the ground truth's first pose",
    "imu": "it starts from the ground truth's pose and velocity",
}


def _start_in_map(args, sequence, field_obj, initial_pose, auto_start: bool):
    """``(sequence, initial_pose, record)``: with a map from ``nap3d-graph map`` the run's
    world is the map's, so the sequence's ground truth is moved into it through the *survey's*
    alignment (survey_ate.json; none where the survey had no ground truth) and the start is
    found in the map (``--initial-pose auto``, the default there). With ``--field none`` and
    nothing to start from, the odometry starts at the identity."""

    import numpy as np


    map_dir = (getattr(field_obj, "meta", None) or {}).get("map")
    record: dict = {}
    if map_dir is not None:
        given_start = initial_pose is not None or args.initial_pose_file is not None
        if args.odom in GROUND_TRUTH_ODOMETRY and not (args.odom == "recorded" and given_start):
            raise UsageError(f"--odom {args.odom} on a map: {GROUND_TRUTH_ODOMETRY[args.odom]}, which a run on a map "
                             "made without ground truth must not read; use --odom vo or dense (the start is found in "
                             "the map)")
        info = load_map_info(map_dir)
        T_gt_map = (info.get("survey_ate") or {}).get("T_gt_map")
        record["map"] = str(map_dir)
        if args.odom is None:  # the map's world is the camera's own: so is the run's motion, by default
            args.odom = "vo"
        # The run's ground truth, if it has one, is read only once its results are written: here
        # it is only told which frame it will be scored in.
        if T_gt_map is None:
            record["ground_truth_frame"] = "unknown (per-run alignment only)"
        else:
            sequence = reframed(sequence, inv_T(np.asarray(T_gt_map)), "ground truth in the map's frame")
            record["ground_truth_frame"] = "moved into the map's frame by the survey's own alignment"
            if info.get("recording_id") not in (None, getattr(sequence, "recording_id", None)):
                print("note: this recording is not the map's survey; its ground truth, if any, is taken to share "
                      "the survey's frame (as a dataset's recordings of one place do)")
        if initial_pose is None and args.initial_pose_file is None and args.odom in (None, "vo", "dense"):
            auto_start = True
    if auto_start:
        if field_obj is None:
            raise UsageError("--initial-pose auto finds the start in a map: give --field MAP_DIR")
        if map_dir is None:
            raise UsageError("--initial-pose auto needs a map from 'nap3d-graph map' (--field MAP_DIR): a field "
                             "checkpoint alone holds no keyframes to retrieve from")
        if args.odom in ("noisy", "recorded", "imu"):
            raise UsageError(f"--initial-pose auto is for --odom vo / dense (--odom {args.odom} starts where its poses do)")
        if args.odom is None:
            args.odom = "vo"
        print("start: anywhere in the map: the odometry runs in its own frame (its first camera) until the map "
              "recognises a keyframe and the next keyframe confirms it; then the whole run moves into the map's frame")
        record["initial_pose"] = "found in the map (see placement)"
        record["start_anywhere"] = True
        return sequence, np.eye(4), record
    if (field_obj is None and initial_pose is None and args.initial_pose_file is None
            and args.odom in (None, "vo", "dense") and _no_start(sequence)):
        print("start: the identity (odometry only, no field and no ground truth to place it in)")
        return sequence, np.eye(4), record
    return sequence, initial_pose, record


def _no_start(sequence) -> bool:
    import numpy as np

    gt = sequence.T_world_cam_gt
    return gt is None or not np.all(np.isfinite(np.asarray(gt)[0]))


def map_relocaliser(map_dir, field_obj, sequence, args):
    """A :class:`~nap3d_graph.mapping.relocalise.Relocaliser` of the map, rendering at the
    run's size with the run's matcher."""
    width, height = parse_size(args.render_size)
    K = sequence.intrinsics
    render = K.scaled(width, height) if (K.width, K.height) != (width, height) else K
    return relocaliser_of(map_dir, field_obj, args.matcher, render)


def prepare(args) -> Prepared:
    """Open the sequence and the field, make the odometry and the pipeline's config; the
    settings tree as the run resolved them (its odometry, matcher, overlap...) is
    ``record["settings"]``, what it found beside them ``record["resolved"]``."""
    auto_start, initial_pose = _checked_options(args)
    data, sequence, field_obj, field_desc, name = _open_inputs(args)
    trained_on = _look_at_inputs(args, sequence, field_obj)
    sequence, initial_pose, start_record = _start_in_map(args, sequence, field_obj, initial_pose, auto_start)
    odometry = _resolved_odometry(args, sequence, initial_pose)
    settings = validated_settings(args)  # again, with the odometry and the overlap resolved
    runner, readout_s = _pipeline(args, settings, sequence, field_obj, odometry)
    resolved = _resolved(runner.config, data, sequence, field_desc, trained_on, readout_s, initial_pose, start_record,
                         odometry if args.odom == "imu" else None)
    record = {"settings": settings.to_dict(), "resolved": resolved}
    _give_map(runner, start_record, field_obj, sequence, args)
    return Prepared(sequence, field_obj, odometry, runner.config, record, name, runner)


def validated_settings(args):
    """The run's settings tree from its options, validated (``RunSettings.validate``: every
    flag combination a run cannot honour), or a one-line usage error."""
    try:
        settings = settings_from_args(args)
        settings.validate()
    except SettingsError as exc:
        raise UsageError(str(exc)) from None
    return settings


def _checked_options(args) -> tuple[bool, object]:
    """The source resolved and the options checked before any data is read; ``(auto_start,
    initial_pose)``: whether the start is to be found in a map, else the pose given (or None)."""
    args.traj = detected_source(args)
    validated_settings(args)
    parse_size(args.render_size)  # a one-line error now, not after the data is read
    auto_start = args.initial_pose == "auto"
    return auto_start, None if auto_start else parse_pose(args.initial_pose, args.initial_pose_file)


def _open_inputs(args):
    """``(data, sequence, field, field description, run name)``: the recording opened as
    the options say, and the field resolved against it."""
    data, field_obj, field_desc, name = _inputs(args)
    extra = {"groundtruth": args.groundtruth, "realsense_config": args.realsense_config} if args.traj == "realsense" \
        else {"topics": args.topics} if args.traj == "rosbag" else {}
    sequence = open_sequence(data, frames=args.frames, depth_scale=args.depth_scale, stamps=args.stamps, fps=args.fps,
                             **extra)
    if args.data is not None:
        field_obj = resolve_field(args.field, sequence)
    return data, sequence, field_obj, field_desc, name


def _look_at_inputs(args, sequence, field_obj):
    """The warnings a user should see before the run (frames the field was trained on, depth
    units, a guessed camera) and the matcher chosen for the recording; returns the frames the
    field was trained on."""
    trained_on = warn_trained_frames(field_obj, sequence, "frames of this run")
    warn_depth_units(sequence)
    warn_guessed_camera(sequence)
    args.matcher = chosen_matcher(args.matcher, sequence)
    return trained_on


def _resolved_odometry(args, sequence, initial_pose):
    """The run's odometry, its kind and the live settings that follow from it written back
    into the options."""
    odom_kind, odometry = _odometry(args, sequence, initial_pose)
    args.odom = odom_kind
    live_defaults(args, odom_kind)
    return odometry


def _pipeline(args, settings, sequence, field_obj, odometry):
    """``(pipeline, readout_s)``: the run's :class:`~nap3d_graph.run.pipeline.Pipeline` (it
    resolves the field's error, once) and the rolling-shutter readout it compensates, with the
    lines a user reads about both."""
    config = settings.pipeline_config(land_within_s=land_within_s(_land_within_default(args), sequence),
                                      overlap=args.overlap, keyframe_when_idle=args.keyframe_when_idle,
                                      timing=_timing(args, field_obj, sequence))
    runner = Pipeline(sequence, field_obj, odometry, config)
    readout_s = _say_readout(runner.config, field_obj)
    _say_field_error(args, runner.config)
    return runner, readout_s


def _resolved(config, data, sequence, field_desc, trained_on, readout_s: float, initial_pose, start_record,
              imu_odometry) -> dict:
    """What the run found beside its settings (``config.yaml``'s ``resolved``): its data,
    field, readout, start, the pipeline's and aligner's configuration as built and, for
    ``imu_odometry``, the IMU's."""
    resolved = {"data": str(data), "frame_range": list(sequence.frame_range), "field": field_desc,
                "frames_the_field_was_trained_on": trained_on,
                "rolling_shutter_readout_s": round(readout_s, 6),
                "initial_pose": None if initial_pose is None else initial_pose.tolist(),
                "pipeline": {k: (v.to_dict() if hasattr(v, "to_dict") else v) for k, v in vars(config).items()
                             if k != "align"},
                "align": vars(config.align)}
    if start_record:
        resolved["start"] = start_record
    if imu_odometry is not None:
        resolved["imu"] = {**imu_odometry.stream.config.to_dict(),
                           "fallback_odometry": getattr(imu_odometry.fallback, "name", "none")}
    return resolved


def _say_field_error(args, config) -> None:
    """One line on the field's own error added to every correction, unless --field-sigma set it."""
    import numpy as np

    if args.field_sigma is None and (config.field_sigma_m or config.field_sigma_rad):
        growth = (", growing with each correction's distance from the field's views" if config.field_error_by_view
                  else "")
        print(f"field error: {config.field_sigma_m * 1000:.1f} mm, {np.degrees(config.field_sigma_rad or 0):.2f} deg "
              f"(measured by train-field on held-out frames{growth}) added to every correction's covariance; "
              "--field-sigma 0 takes the field as exact")


def _give_map(runner, start_record: dict, field_obj, sequence, args) -> None:
    """A run on a map: the map's relocaliser places it (started anywhere) and recovers it."""
    if start_record.get("start_anywhere"):
        runner.start_in_map(map_relocaliser(start_record["map"], field_obj, sequence, args))
    elif start_record.get("map"):
        # A map's relocaliser: recovers a run lost ``relocalise_after`` keyframes in a row.
        runner.recover_in_map(map_relocaliser(start_record["map"], field_obj, sequence, args))


