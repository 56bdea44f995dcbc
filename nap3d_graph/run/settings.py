"""A drift-correction run's settings as one tree: :class:`RunSettings`.

Sections: ``source`` (what is read), ``odometry`` (the motion between keyframes),
``keyframes`` (when a correction is measured), ``alignment`` (how: the field, the matcher,
NAP3D's settings), ``graph`` (how a correction enters iSAM2), ``threads`` (what runs beside
the odometry) and ``output`` (what is written). ``run`` writes the tree to ``config.yaml``
(under ``settings``) and ``run --config`` reads it back: :meth:`RunSettings.to_dict` and
:meth:`RunSettings.from_dict` round-trip exactly, by construction (every field is plain
YAML data: numbers, strings, booleans, None, lists and mappings).

Each setting is declared once (:func:`~nap3d_graph.arguments.setting`): its name, type,
default and, when the command line sets it, its flag, how argparse reads it and its help; the
command line's options are generated from the fields (:func:`~nap3d_graph.arguments.flagged`).
A setting the pipeline takes is declared by its :class:`~nap3d_graph.run.config.PipelineConfig`
field, which says where it sits in the tree (``tree``: section and name); each section adds
those fields after its own (``pipeline`` metadata: the field they set), and
:meth:`RunSettings.pipeline_config` builds the ``PipelineConfig`` from them. A setting
without a flag is set in ``config.yaml``.
"""

from __future__ import annotations

import argparse
import dataclasses
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from nap3d_graph.arguments import (
    DEPTH_SCALE_OPTION,
    FPS_OPTION,
    RUN_MATCHER,
    STAMPS_OPTION,
    TOPICS_OPTION,
    frames_option,
    gravity,
    land_within,
    matcher_option,
    non_negative_int,
    positive_float,
    positive_int,
    setting,
)
from nap3d_graph.datasets import SOURCES
from nap3d_graph.nap3d.config import AlignConfig

from .config import PipelineConfig
from .default import DEFAULT_TRAIN_STEPS

__all__ = ["RunSettings", "SettingsTree", "SettingsError", "SECTIONS", "pipeline_name", "LAND_WITHIN_FRAME_SHARE"]

T = TypeVar("T")

#: ``--land-within frame``: this share of the camera's frame period (the rest of the step:
#: the graph update and handing the pose over).
LAND_WITHIN_FRAME_SHARE = 0.9

class SettingsError(ValueError):
    """A settings tree that cannot be read: an unknown section or setting, or a value of the
    wrong kind (one line, naming the setting)."""


def _with_pipeline_fields(section: str) -> Callable[[type[T]], type[T]]:
    """Class decorator: the settings section ``cls`` (a dataclass) with, after its own fields,
    each :class:`PipelineConfig` field that declares it sits in ``section`` (its ``tree``
    metadata: the setting's name there), with that field's type, default and flag, bound to it
    (``pipeline`` metadata). A run setting the pipeline takes is declared once, in
    ``PipelineConfig``."""

    def with_fields(cls: type[T]) -> type[T]:
        own = [(f.name, f.type, _copied(f)) for f in dataclasses.fields(cls)]  # type: ignore[arg-type]
        bound = [(f.metadata["tree"][1], f.type,
                  dataclasses.field(default=f.default, metadata={**f.metadata, "pipeline": f.name}))
                 for f in dataclasses.fields(PipelineConfig) if f.metadata.get("tree", ("",))[0] == section]
        made = dataclasses.make_dataclass(cls.__name__, own + bound)
        made.__doc__, made.__module__, made.__qualname__ = cls.__doc__, cls.__module__, cls.__qualname__
        return made

    return with_fields


def _copied(f: dataclasses.Field) -> Any:
    """A new field with ``f``'s default (or factory) and metadata."""
    if f.default_factory is not dataclasses.MISSING:
        return dataclasses.field(default_factory=f.default_factory, metadata=f.metadata)
    return dataclasses.field(default=f.default, metadata=f.metadata)


def pipeline_name(f: dataclasses.Field) -> str | None:
    """The ``PipelineConfig`` field a settings field sets (None: resolved by the run)."""
    return f.metadata.get("pipeline")


@_with_pipeline_fields("source")
@dataclass
class SourceSettings:
    """What is read. ``traj``: sim, tum, realsense, 7scenes, rosbag or auto (the source the
    data's path says; sim without data); ``data``: the folder, recording or bag (None with
    sim: the embedded default); ``frames``: START:STOP (indices or fractions);
    ``depth_scale``: a folder's depth units per metre (None: intrinsics.json's, else the
    format's); ``stamps``: a TUM-layout folder's stamps as-written or file-order; ``fps``: its camera's rate when its stamps are not a clock; ``topics``: a ROS bag's KEY=TOPIC pairs; ``groundtruth`` /
    ``realsense_config`` / ``record`` / ``seconds``: a RealSense recording's ground truth,
    IMU settings, live capture file and length; ``initial_pose``: 'auto' (found in a map) or
    'tx ty tz qx qy qz qw' in the field's frame, ``initial_pose_file`` its TUM file;
    ``max_frames``: stop after this many; ``pace``: feed the frames at this multiple of the
    camera's rate (None: as fast as they come); ``cache`` / ``train_steps``: the embedded
    default's cache folder and field budget."""

    traj: str = setting("auto", "--traj", choices=("auto", *SOURCES),
        help="the data source (default auto: the one --data's path says, a simulator's folder, a TUM-layout or "
             "7-Scenes folder, a RealSense or ROS bag; sim without --data): sim (a folder from 'nap3d-graph "
             "simulate'), tum (a TUM RGB-D folder), realsense (a .bag/.db3 recording, or 'live': a connected "
             "camera) or 7scenes (a 7-Scenes sequence folder: depth is warped into its colour camera, whose "
             "focal length and centre are estimated from the data), or rosbag (a ROS 1 .bag or a ROS 2 bag "
             "folder: colour, depth, camera info, IMU and ground truth from /tf or a pose topic; see --topics)")
    data: str | None = setting(None, "--data", type=Path,
        help="the sequence folder, or for realsense a recording or 'live', or for rosbag the .bag file or ROS 2 "
             "bag folder; omit (with --traj sim) for the embedded default")
    frames: str | None = setting(None, "--frames", **frames_option("the run (a field should not have been trained on them)"))
    depth_scale: float | None = setting(None, "--depth-scale", **DEPTH_SCALE_OPTION)
    stamps: str | None = setting(None, "--stamps", **STAMPS_OPTION)
    fps: float | None = setting(None, "--fps", **FPS_OPTION)
    topics: str | None = setting(None, "--topics", **TOPICS_OPTION)
    groundtruth: str | None = setting(None, "--groundtruth", type=Path, metavar="TUM_FILE",
        help="realsense: camera poses of the recording's frames, for ATE/RPE (without it the results report "
             "correction statistics)")
    realsense_config: str | None = setting(None, "--realsense-config", type=Path, metavar="YAML",
        help="realsense: IMU extrinsics (T_depth_imu) and noise, which recordings do not store (default: "
             "RECORDING.yaml beside the file if there is one, else D435i values)")
    record: str | None = setting(None, "--record", type=Path, metavar="FILE.bag",
        help="realsense live: keep what the camera streamed in this file (default: a temporary file)")
    seconds: float = setting(30.0, "--seconds", type=positive_float,
        help="realsense live: how long to capture before correcting (default %(default)g)")
    initial_pose: str | None = setting(None, "--initial-pose", metavar="auto|'tx ty tz qx qy qz qw'",
        help="where the camera starts in the field's frame, for --odom vo / dense. auto: found in the map (the "
             "map's keyframes most like the first frame, the field rendered there, NAP3D aligned and verified; a"
             " clear error when none verifies); the default with a map from 'nap3d-graph map' (its frame is not "
             "the ground truth's). Otherwise the default is the ground truth's first pose, and with --field none"
             " and no ground truth the identity")
    initial_pose_file: str | None = setting(None, "--initial-pose-file", type=Path, metavar="TUM_FILE",
        help="the same from the first line of a TUM trajectory file")
    pace: float | None = setting(None, "--pace", only_run=True, type=positive_float, nargs="?", const=1.0, metavar="SPEED",
        help="feed the frames as the camera delivered them (SPEED times its rate; default 1): the causal "
             "trajectory is then the one a robot riding along would have had, which for --overlap depends on the"
             " camera's rate, not on how fast a replay goes. Takes the live settings unless told otherwise "
             "(--overlap --land-within frame --keyframe-when-idle 1; --no-overlap runs inline). metrics.json "
             "records how late the run took the frames")
    cache: str | None = setting(None, "--cache", type=Path,
        help="cache of the embedded default's data and field (default $NAP3D_GRAPH_CACHE or "
             "~/.cache/nap3d-graph)")
    train_steps: int = setting(DEFAULT_TRAIN_STEPS, "--train-steps", type=positive_int,
        help="field training budget of the embedded default, in steps (default %(default)s, about two minutes on"
             " two cores)")


@_with_pipeline_fields("odometry")
@dataclass
class OdometrySettings:
    """The motion between keyframes. ``kind``: recorded, noisy, vo, dense or imu (None: the
    data's own, resolved by the run); ``rot_sigma_rad`` / ``trans_sigma_m``: per-frame noise
    (injected by noisy; the odometry factors' sigmas); ``seed``: of the injected noise;
    ``vo_width``: vo's frame width in pixels (None: as read); ``imu_noise`` /
    ``imu_extrinsics`` / ``gravity`` / ``fallback``: the IMU's noise densities, T_cam_imu,
    gravity ('check', 'auto', a magnitude or [gx, gy, gz] m/s^2) and the frame odometry it
    falls back on; ``drift_*``: the odometry's bias-like drift (see ``PipelineConfig``)."""

    kind: str | None = setting(None, "--odom", choices=("recorded", "noisy", "vo", "dense", "imu"),
        help="motion between keyframes: recorded (the sequence's odometry.txt; default for sim), noisy (noise "
             "injected on ground-truth increments; default for tum), vo (frame-to-frame RGB-D odometry with "
             "NAP3D's matcher), dense (OpenCV's dense RGB-D odometry at 320 px wide: the camera's rate, about "
             "the same drift on fr1/desk) or imu (the sequence's IMU preintegrated into CombinedImuFactors; "
             "biases estimated; default for a realsense recording with an IMU)")
    rot_sigma_rad: float = setting(2e-3, "--odom-rot-sigma", type=positive_float,
        help="per-frame rotation noise of the odometry, rad (injected with --odom noisy, and the odometry "
             "factors' sigma); default %(default)g")
    trans_sigma_m: float = setting(2e-3, "--odom-trans-sigma", type=positive_float,
        help="per-frame translation noise of the odometry, m; default %(default)g")
    seed: int = setting(0, "--seed", type=int,
        help="seed of injected odometry noise (default %(default)s)")
    vo_width: int | None = setting(None, "--vo-width", type=positive_int, metavar="PX",
        help="--odom vo: detect and align each frame resized to PX pixels wide (default: as read). At the "
             "render's width (320 by default) each keyframe's correction reuses the features the odometry "
             "detected: a higher frame rate, the odometry alone drifting more (measured against the frames as "
             "read in docs/results.md, 'Feature odometry at the render's width'). --pace with --odom vo takes "
             "the render's width unless told")
    imu_noise: str | None = setting(None, "--imu-noise", metavar="'AN GN AW GW'",
        help="IMU noise densities: accel m/s^2/sqrt(Hz), gyro rad/s/sqrt(Hz), accel bias walk m/s^3/sqrt(Hz), "
             "gyro bias walk rad/s^2/sqrt(Hz) (default: the simulator's, 2e-3 2.4e-4 1e-4 2e-6)")
    imu_extrinsics: str | None = setting(None, "--imu-extrinsics", metavar="'tx ty tz qx qy qz qw'",
        help="T_cam_imu: the IMU frame in the camera frame (default identity, as simulated)")
    gravity: str | float | list[float] = setting("check", "--gravity", type=gravity, metavar="check|auto|G|'gx gy gz'",
        help="--odom imu: gravity in the field's frame as the run's graph starts it; the graph then refines its "
             "tilt (a few degrees; the EKFs of compare keep it as given). 'check' (default): z-up (-9.81 m/s^2 "
             "along z), unless the accelerometer over the first 0.5 s, with the starting pose, puts it more than"
             " 10 deg away (a field's frame from COLMAP or nerfstudio, a y-down room): then the accelerometer's "
             "direction, said on the terminal. 'auto': always the accelerometer's direction. A magnitude "
             "(m/s^2): z-up, only warned about. Or the vector in m/s^2")
    fallback: str = setting("dense", "--fallback-odom", choices=("dense", "vo", "none"),
        help="--odom imu: the frame odometry the run falls back on between keyframes after 3 keyframes refused "
             "in a row (the views left the field, say: the IMU alone then drifts by metres within seconds), "
             "until a correction lands again (default %(default)s; none: the IMU alone)")


@_with_pipeline_fields("keyframes")
@dataclass
class KeyframeSettings:
    """When a correction is measured (see ``PipelineConfig``'s ``keyframe_*``);
    ``when_idle`` None: 1 for an overlapped paced run, else 0 (resolved by the run)."""

    when_idle: int | None = setting(None, "--keyframe-when-idle", type=non_negative_int, metavar="N",
        help="with --overlap: also a keyframe at any frame N or more after the last while the second thread is "
             "idle, so corrections come as often as it can measure them (--keyframe-every is then the longest "
             "interval; which frames are keyframes depends on the machine's speed, or with run --pace on the "
             "camera's rate). Default: 1 for an overlapped run --pace (the live settings), else 0: off")


@_with_pipeline_fields("alignment")
@dataclass
class AlignmentSettings:
    """How a keyframe is measured. ``field``: 'oracle', a checkpoint, a nerfstudio config,
    a map folder or 'none' (None with the embedded default: its own); ``matcher``: sift, xfeat,
    xfeat-lighterglue or auto; ``iterations``: render-align rounds; ``render_size``: 'WxH';
    ``timing``: 'auto' (move the depth to the colour's capture instant) or 'none';
    ``rolling_shutter_s``, ``field_sigma_*``, ``depth_scale_*``, ``intrinsics_check_every``:
    see ``PipelineConfig``; ``nap3d``: NAP3D's own settings
    (:class:`~nap3d_graph.nap3d.config.AlignConfig` field -> value) where they differ from its
    defaults, the matcher excepted."""

    field: str | None = setting(None, "--field",
        help="'oracle' (the exact simulated room of --data), a field checkpoint (.pt, from 'nap3d-graph "
             "train-field'), a nerfstudio config.yml, or 'none' (odometry only)")
    matcher: str = setting("auto", "--matcher", **matcher_option(RUN_MATCHER))
    render_size: str = setting("320x240", "--render-size",
        help="WxH the field renders at (default %(default)s)")
    timing: str = setting("auto", "--timing", choices=("auto", "none"),
        help="auto: move each keyframe's depth to its colour's capture instant with the capture timing the field"
             " records, or, for a field that records none (the oracle, nerfstudio), the timing estimated from "
             "this sequence's ground truth; none: take the stamps as they are")
    nap3d: dict[str, Any] = dataclasses.field(default_factory=dict)


@_with_pipeline_fields("graph")
@dataclass
class GraphSettings:
    """How a correction enters iSAM2 (see ``PipelineConfig``): the chi-square gate, the
    window of keyframes kept, the map anchor, the robust loss, the priors, the final GNC
    solve, how many refused keyframes in a row call for relocalising in a map and how far a
    run started anywhere in a map travels confirming its placement."""



@_with_pipeline_fields("threads")
@dataclass
class ThreadSettings:
    """What runs beside the odometry (see ``PipelineConfig``). ``overlap`` None: on for a
    paced run, else off; ``land_within`` None: 'frame' for an overlapped paced run, else 0;
    'frame' waits 0.9 of the camera's frame period (both resolved by the run)."""

    overlap: bool | None = setting(None, "--overlap", action=argparse.BooleanOptionalAction,
        help="measure each keyframe's correction on a second thread while the odometry goes on; it enters the "
             "graph when ready (faster on two cores; not bit-for-bit repeatable; not with --odom imu). Default: "
             "on for run --pace (frames fed as the camera delivers them: with the live settings, --land-within "
             "frame and --keyframe-when-idle 1, as accurate as inline and more often corrected), off for a "
             "replay that goes as fast as it can (inline is repeatable there, and an overlapped run's causal "
             "trajectory would depend on the machine's speed)")
    land_within: float | str | None = setting(None, "--land-within", type=land_within, metavar="S|frame",
        help="with --overlap: wait up to S seconds after a frame arrives for the correction in flight, "
             "so one that is done by then lands at that frame and not a later one; 'frame' waits "
             f"{LAND_WITHIN_FRAME_SHARE:g} of the camera's frame period (only while a live run would idle "
             "for the next frame; with run --pace, as a live camera feeds it). Default: 'frame' for run "
             "--overlap --pace (the run would idle then anyway), else 0: never wait")


@dataclass
class OutputSettings:
    """What is written: the results root, a ROS bag of the trajectories, a rerun recording."""

    out: str = setting("results", "--out", only_run=True, type=Path,
        help="results root (default ./%(default)s)")
    write_bag: str | None = setting(None, "--write-bag", only_run=True, type=Path, metavar="OUT.bag|OUT_DIR",
        help="also write the trajectories as a ROS bag in the input's time, to play next to the input in RViz: "
             "causal, smoothed and odometry poses (PoseStamped), paths (nav_msgs/Path) and /tf from the world to"
             " the corrected camera. A .bag path is a ROS 1 bag, any other a ROS 2 bag folder (MCAP when it ends"
             " in .mcap)")
    viz: str | None = setting(None, "--viz", only_run=True, metavar="RUN.rrd|spawn",
        help="also record the run for the rerun viewer (extra 'viz': rerun-sdk): trajectories, each keyframe's "
             "image, render and inlier matches, the corrections' covariance ellipsoids, accepted or refused with"
             " the reason, on one timeline. RUN.rrd: a file to open with 'rerun RUN.rrd'; spawn: open the viewer"
             " now (needs a display)")


#: Section name -> its dataclass, in the order config.yaml lists them.
SECTIONS: dict[str, type] = {"source": SourceSettings, "odometry": OdometrySettings, "keyframes": KeyframeSettings,
                             "alignment": AlignmentSettings, "graph": GraphSettings, "threads": ThreadSettings,
                             "output": OutputSettings}


class SettingsTree:
    """A tree of dataclass sections (``SECTIONS``: name -> class) of plain values: its dump
    (:meth:`to_dict`) and load (:meth:`from_dict`) round-trip exactly."""

    SECTIONS: typing.ClassVar[dict[str, type]] = {}

    def to_dict(self) -> dict:
        """``{section: {setting: value}}``, plain YAML data (tuples as lists)."""
        return {name: {k: _plain(v) for k, v in dataclasses.asdict(getattr(self, name)).items()}
                for name in self.SECTIONS}

    @classmethod
    def from_dict(cls, data: dict):
        """The tree ``to_dict`` wrote (sections or settings left out keep their defaults);
        :class:`SettingsError` names an unknown section or setting, or a value of the wrong
        kind."""
        if not isinstance(data, dict):
            raise SettingsError(f"settings must be a mapping of sections, got {type(data).__name__}")
        unknown = sorted(set(data) - set(cls.SECTIONS))
        if unknown:
            raise SettingsError(f"unknown settings section {unknown[0]!r} (sections: {', '.join(cls.SECTIONS)})")
        sections = {}
        for name, kind in cls.SECTIONS.items():
            values = data.get(name) or {}
            if not isinstance(values, dict):
                raise SettingsError(f"settings section {name!r} must be a mapping, got {type(values).__name__}")
            sections[name] = _section(name, kind, values)
        return cls(**sections)

    def get(self, path: str) -> Any:
        """The value at ``'section.setting'``."""
        section, name = path.split(".")
        return getattr(getattr(self, section), name)

    def replace(self, values: dict[str, Any]):
        """A copy with ``{'section.setting': value}`` set (each checked as ``from_dict`` checks)."""
        tree = self.to_dict()
        for path, value in values.items():
            section, name = path.split(".")
            tree[section][name] = _plain(value)
        return type(self).from_dict(tree)


def _plain(value):
    """``value`` as YAML data: tuples as lists."""
    return [_plain(v) for v in value] if isinstance(value, (tuple, list)) else value


@dataclass
class RunSettings(SettingsTree):
    """Everything a run is told, by section (each a dataclass of plain values)."""

    SECTIONS = SECTIONS

    source: SourceSettings = dataclasses.field(default_factory=SourceSettings)
    odometry: OdometrySettings = dataclasses.field(default_factory=OdometrySettings)
    keyframes: KeyframeSettings = dataclasses.field(default_factory=KeyframeSettings)
    alignment: AlignmentSettings = dataclasses.field(default_factory=AlignmentSettings)
    graph: GraphSettings = dataclasses.field(default_factory=GraphSettings)
    threads: ThreadSettings = dataclasses.field(default_factory=ThreadSettings)
    output: OutputSettings = dataclasses.field(default_factory=OutputSettings)

    def validate(self) -> None:
        """Every combination of settings a run cannot honour, in one place: a one-line
        :class:`SettingsError` for the first found (named by the command line's flags). What
        the run resolves later (the odometry's kind, whether it overlaps) is checked once
        known: a None there passes, so a tree is validated before and again after it."""
        source, odometry, threads = self.source, self.odometry, self.threads
        kind, overlap, window = odometry.kind, threads.overlap, self.get("graph.window")
        problems = (
            (source.traj not in ("realsense", "auto") and bool(source.groundtruth or source.realsense_config
                                                               or source.record),
             "--groundtruth, --realsense-config and --record are for --traj realsense"),
            (bool(source.topics) and source.traj not in ("rosbag", "auto"), "--topics is for --traj rosbag"),
            (source.initial_pose == "auto" and source.initial_pose_file is not None,
             "give --initial-pose auto or --initial-pose-file, not both"),
            (odometry.vo_width is not None and kind not in (None, "vo"), f"--vo-width is for --odom vo, not --odom {kind}"),
            (self.get("threads.render_ahead") and overlap is False,
             "--render-ahead works ahead on the second thread: it needs --overlap"),
            (bool(self.keyframes.when_idle) and overlap is False,
             "--keyframe-when-idle takes keyframes while the second thread is idle: it needs --overlap"),
            (bool(threads.land_within) and overlap is False,
             "--land-within waits for the second thread's correction: it needs --overlap"),
            (bool(overlap) and kind == "imu",
             "--overlap does not apply to --odom imu (the IMU keyframe state follows each correction)"),
            (bool(window) and (kind == "imu" or self.get("graph.anchor")),
             "--graph-window does not apply to --odom imu or --anchor"),
            (bool(window) and window < 3, f"--graph-window must be 0 (every keyframe) or at least 3, got {window}"),
        )
        for problem, message in problems:
            if problem:
                raise SettingsError(message)

    def pipeline_config(self, *, land_within_s: float, overlap: bool, keyframe_when_idle: int, timing=None,
                        progress: bool = True) -> PipelineConfig:
        """The :class:`PipelineConfig` these settings make: every field bound to one
        (``pipeline`` metadata) as it is; the render size, the timing switch and NAP3D's
        settings converted; the settings the run resolves given (``land_within_s`` seconds,
        ``overlap``, ``keyframe_when_idle``, ``timing``: a capture timing beyond the field's)."""
        values: dict[str, Any] = {}
        for name in SECTIONS:
            section = getattr(self, name)
            for f in dataclasses.fields(section):
                target = pipeline_name(f)
                if target is not None:
                    values[target] = getattr(section, f.name)
        width, height = render_size(self.alignment.render_size)
        align = AlignConfig(**{**self.alignment.nap3d, "matcher": self.alignment.matcher})
        return PipelineConfig(**values, render_width=width, render_height=height,
                              compensate_timing=self.alignment.timing == "auto", timing=timing,
                              land_within_s=land_within_s, overlap=overlap, keyframe_when_idle=keyframe_when_idle,
                              progress=progress, align=align)


def render_size(text: str) -> tuple[int, int]:
    """'WxH' -> (W, H) pixels (SettingsError for anything else)."""
    try:
        width, height = (int(v) for v in str(text).lower().split("x"))
    except ValueError:
        raise SettingsError(f"render size must be WxH (e.g. 320x240), got {text!r}") from None
    if width <= 0 or height <= 0:
        raise SettingsError(f"render size must be positive, got {text!r}")
    return width, height


def _section(name: str, kind: type, values: dict):
    """The section ``kind`` from ``values``, each checked against its field's type."""
    hints = typing.get_type_hints(kind)
    known = {f.name for f in dataclasses.fields(kind)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise SettingsError(f"unknown setting {name}.{unknown[0]} (in {name}: {', '.join(sorted(known))})")
    checked = {key: _checked(f"{name}.{key}", hints[key], value) for key, value in values.items()}
    return kind(**checked)


def _checked(path: str, hint, value):
    """``value`` as the type ``hint`` wants it (an int where a float goes becomes a float);
    SettingsError when it is of another kind."""
    options = typing.get_args(hint) if isinstance(hint, types.UnionType) else (hint,)
    for option in options:
        origin = typing.get_origin(option) or option
        if option is type(None) and value is None:
            return None
        if origin is bool and isinstance(value, bool):
            return value
        if origin is int and isinstance(value, int) and not isinstance(value, bool):
            return value
        if origin is float and isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        if origin is str and isinstance(value, str):
            return value
        if origin is list and isinstance(value, (list, tuple)) and all(
                isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
            return [float(v) for v in value]
        if origin is tuple and isinstance(value, (list, tuple)) and all(isinstance(v, str) for v in value):
            return tuple(value)
        if origin is dict and isinstance(value, dict):
            return dict(value)
    wanted = " or ".join("None" if o is type(None) else getattr(typing.get_origin(o) or o, "__name__", str(o))
                         for o in options)
    raise SettingsError(f"setting {path} must be {wanted}, got {value!r}")
