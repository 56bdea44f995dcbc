"""A drift-correction run's settings as one tree: :class:`RunSettings`.

Sections: ``source`` (what is read), ``odometry`` (the motion between keyframes),
``keyframes`` (when a correction is measured), ``alignment`` (how: the field, the matcher,
NAP3D's settings), ``graph`` (how a correction enters iSAM2), ``threads`` (what runs beside
the odometry) and ``output`` (what is written). ``run`` writes the tree to ``config.yaml``
(under ``settings``) and ``run --config`` reads it back: :meth:`RunSettings.to_dict` and
:meth:`RunSettings.from_dict` round-trip exactly, by construction (every field is plain
YAML data: numbers, strings, booleans, None, lists and mappings).

A field that sets a :class:`~nap3d_graph.run.config.PipelineConfig` field names it in its
metadata (``pipeline``) and takes that field's default, so the tree and the library's
config cannot disagree on a default; :meth:`RunSettings.pipeline_config` builds the
``PipelineConfig`` from them. The command line binds its flags to the tree's fields in one
table (``nap3d_graph.cli.run_options``).
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass
from typing import Any

from nap3d_graph.nap3d.config import AlignConfig

from .config import PipelineConfig
from .default import DEFAULT_TRAIN_STEPS

__all__ = ["RunSettings", "SettingsTree", "SettingsError", "SECTIONS", "pipeline_name"]

_PIPELINE_DEFAULTS = {f.name: f.default for f in dataclasses.fields(PipelineConfig)
                      if f.default is not dataclasses.MISSING}


class SettingsError(ValueError):
    """A settings tree that cannot be read: an unknown section or setting, or a value of the
    wrong kind (one line, naming the setting)."""


def _pipe(name: str) -> Any:
    """A field bound to ``PipelineConfig.<name>``, with its default."""
    return dataclasses.field(default=_PIPELINE_DEFAULTS[name], metadata={"pipeline": name})


def pipeline_name(f: dataclasses.Field) -> str | None:
    """The ``PipelineConfig`` field a settings field sets (None: resolved by the run)."""
    return f.metadata.get("pipeline")


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

    traj: str = "auto"
    data: str | None = None
    frames: str | None = None
    depth_scale: float | None = None
    stamps: str | None = None
    fps: float | None = None
    topics: str | None = None
    groundtruth: str | None = None
    realsense_config: str | None = None
    record: str | None = None
    seconds: float = 30.0
    initial_pose: str | None = None
    initial_pose_file: str | None = None
    max_frames: int | None = _pipe("max_frames")
    pace: float | None = None
    cache: str | None = None
    train_steps: int = DEFAULT_TRAIN_STEPS


@dataclass
class OdometrySettings:
    """The motion between keyframes. ``kind``: recorded, noisy, vo, dense or imu (None: the
    data's own, resolved by the run); ``rot_sigma_rad`` / ``trans_sigma_m``: per-frame noise
    (injected by noisy; the odometry factors' sigmas); ``seed``: of the injected noise;
    ``vo_width``: vo's frame width in pixels (None: as read); ``imu_noise`` /
    ``imu_extrinsics`` / ``gravity`` / ``fallback``: the IMU's noise densities, T_cam_imu,
    gravity ('check', 'auto', a magnitude or [gx, gy, gz] m/s^2) and the frame odometry it
    falls back on; ``drift_*``: the odometry's bias-like drift (see ``PipelineConfig``)."""

    kind: str | None = None
    rot_sigma_rad: float = 2e-3
    trans_sigma_m: float = 2e-3
    seed: int = 0
    vo_width: int | None = None
    imu_noise: str | None = None
    imu_extrinsics: str | None = None
    gravity: str | float | list[float] = "check"
    fallback: str = "dense"
    drift_fraction: float = _pipe("odom_drift_fraction")
    drift_rad_per_m: float = _pipe("odom_drift_rad_per_m")
    drift_rad_per_rad: float = _pipe("odom_drift_rad_per_rad")
    drift_m_per_s: float = _pipe("odom_drift_m_per_s")
    drift_rad_per_s: float = _pipe("odom_drift_rad_per_s")


@dataclass
class KeyframeSettings:
    """When a correction is measured (see ``PipelineConfig``'s ``keyframe_*``);
    ``when_idle`` None: 1 for an overlapped paced run, else 0 (resolved by the run)."""

    every: int = _pipe("keyframe_every")
    distance_m: float = _pipe("keyframe_distance_m")
    angle_deg: float = _pipe("keyframe_angle_deg")
    window: int = _pipe("keyframe_window")
    sharpness_fraction: float = _pipe("keyframe_sharpness_fraction")
    on_doubt: bool = _pipe("keyframe_on_doubt")
    when_idle: int | None = None


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

    field: str | None = None
    matcher: str = "auto"
    iterations: int = _pipe("correction_iterations")
    render_size: str = "320x240"
    timing: str = "auto"
    rolling_shutter_s: float | None = _pipe("rolling_shutter_s")
    field_sigma_m: float | None = _pipe("field_sigma_m")
    field_sigma_rad: float | None = _pipe("field_sigma_rad")
    field_sigma_depth_m: float = _pipe("field_sigma_depth_m")
    depth_scale_check: bool = _pipe("depth_scale_check")
    depth_scale_tolerance: float = _pipe("depth_scale_tolerance")
    depth_scale_sigmas: float = _pipe("depth_scale_sigmas")
    depth_scale_window: int = _pipe("depth_scale_window")
    intrinsics_check_every: int = _pipe("intrinsics_check_every")
    nap3d: dict[str, Any] = dataclasses.field(default_factory=dict)


@dataclass
class GraphSettings:
    """How a correction enters iSAM2 (see ``PipelineConfig``): the chi-square gate, the
    window of keyframes kept, the map anchor, the robust loss, the priors, the final GNC
    solve, how many refused keyframes in a row call for relocalising in a map and how far a
    run started anywhere in a map travels confirming its placement."""

    gate_p: float = _pipe("gate_p")
    window: int = _pipe("graph_window")
    anchor: bool = _pipe("use_anchor")
    robust: str | None = _pipe("robust")
    anchor_rot_sigma_rad: float = _pipe("anchor_rot_sigma_rad")
    anchor_trans_sigma_m: float = _pipe("anchor_trans_sigma_m")
    prior_rot_sigma_rad: float = _pipe("prior_rot_sigma_rad")
    prior_trans_sigma_m: float = _pipe("prior_trans_sigma_m")
    relinearize_threshold: float = _pipe("relinearize_threshold")
    final_gnc: bool = _pipe("final_gnc")
    gnc_p: float = _pipe("gnc_p")
    relocalise_after: int = _pipe("relocalise_after")
    placement_travel_m: float = _pipe("placement_travel_m")


@dataclass
class ThreadSettings:
    """What runs beside the odometry (see ``PipelineConfig``). ``overlap`` None: on for a
    paced run, else off; ``land_within`` None: 'frame' for an overlapped paced run, else 0;
    'frame' waits 0.9 of the camera's frame period (both resolved by the run)."""

    overlap: bool | None = None
    render_ahead: bool = _pipe("render_ahead")
    render_ahead_m: float = _pipe("render_ahead_m")
    render_ahead_deg: float = _pipe("render_ahead_deg")
    land_within: float | str | None = None
    detect_ahead: bool = _pipe("detect_ahead")
    read_ahead: int = _pipe("read_ahead")
    library_threads: int | None = _pipe("library_threads")


@dataclass
class OutputSettings:
    """What is written: the results root, a ROS bag of the trajectories, a rerun recording."""

    out: str = "results"
    write_bag: str | None = None
    viz: str | None = None


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
        source, odometry, graph, threads = self.source, self.odometry, self.graph, self.threads
        kind, overlap = odometry.kind, threads.overlap
        problems = (
            (source.traj not in ("realsense", "auto") and bool(source.groundtruth or source.realsense_config
                                                               or source.record),
             "--groundtruth, --realsense-config and --record are for --traj realsense"),
            (bool(source.topics) and source.traj not in ("rosbag", "auto"), "--topics is for --traj rosbag"),
            (source.initial_pose == "auto" and source.initial_pose_file is not None,
             "give --initial-pose auto or --initial-pose-file, not both"),
            (odometry.vo_width is not None and kind not in (None, "vo"), f"--vo-width is for --odom vo, not --odom {kind}"),
            (threads.render_ahead and overlap is False,
             "--render-ahead works ahead on the second thread: it needs --overlap"),
            (bool(self.keyframes.when_idle) and overlap is False,
             "--keyframe-when-idle takes keyframes while the second thread is idle: it needs --overlap"),
            (bool(threads.land_within) and overlap is False,
             "--land-within waits for the second thread's correction: it needs --overlap"),
            (bool(overlap) and kind == "imu",
             "--overlap does not apply to --odom imu (the IMU keyframe state follows each correction)"),
            (bool(graph.window) and (kind == "imu" or graph.anchor), "--graph-window does not apply to --odom imu or --anchor"),
            (bool(graph.window) and graph.window < 3,
             f"--graph-window must be 0 (every keyframe) or at least 3, got {graph.window}"),
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
