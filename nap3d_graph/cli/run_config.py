"""``run --config config.yaml``: a run reproduced from the configuration another run wrote.

Every run writes ``config.yaml`` (:mod:`nap3d_graph.run.output`): the options it was given,
the pipeline's and the alignment's settings as they were resolved. Reading it back sets each
option the file knows, unless the command line gives that option (a flag given wins over the
file, even when it gives the option's default); settings with no flag (the depth-scale
check's tolerance, the alignment's noise model...) are carried into the run's configuration
as they were. ``_TOP`` and ``_PIPELINE`` are the one table between the file's keys and the
options.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from .common import UsageError

__all__ = ["apply_run_config", "load_config_file", "load_run_config", "set_unless_given"]

#: config.yaml key -> run option (argparse dest).
_TOP = {"traj": "traj", "data": "data", "frames": "frames", "field": "field", "odometry": "odom",
        "odom_rot_sigma_rad": "odom_rot_sigma", "odom_trans_sigma_m": "odom_trans_sigma", "seed": "seed",
        "pace": "pace", "vo_width": "vo_width", "topics": "topics", "groundtruth": "groundtruth",
        "imu_noise": "imu_noise", "imu_extrinsics": "imu_extrinsics", "realsense_config": "realsense_config"}
#: Options whose values are paths.
_PATHS = {"data", "groundtruth", "realsense_config"}
_PIPELINE = {"keyframe_every": "keyframe_every", "keyframe_distance_m": "keyframe_distance",
             "keyframe_angle_deg": "keyframe_angle", "keyframe_window": "keyframe_window",
             "keyframe_on_doubt": "keyframe_on_doubt", "keyframe_when_idle": "keyframe_when_idle", "correction_iterations": "iterations", "gate_p": "gate_p",
             "field_sigma_m": "field_sigma", "overlap": "overlap", "render_ahead": "render_ahead",
             "land_within_s": "land_within", "rolling_shutter_s": "rolling_shutter",
             "max_frames": "max_frames", "graph_window": "graph_window",
             "use_anchor": "anchor"}
#: Pipeline settings a run resolves for itself each time (not carried over).
_RESOLVED = {"timing", "progress", "align"}


def load_config_file(path: Path, section: str, command: str) -> dict:
    """The mapping a ``command``'s ``config.yaml`` holds, which must have a ``section``
    mapping (one-line errors for a bad file)."""
    import yaml

    try:
        config = yaml.safe_load(Path(path).read_text())
    except FileNotFoundError:
        raise UsageError(f"--config {path}: file not found") from None
    except (OSError, yaml.YAMLError) as exc:
        raise UsageError(f"--config {path}: not a readable YAML file ({str(exc).splitlines()[0]})") from None
    if not isinstance(config, dict) or not isinstance(config.get(section), dict):
        raise UsageError(f"--config {path}: not a {command}'s config.yaml (no '{section}' section)")
    return config


def load_run_config(path: Path) -> dict:
    """The mapping a run's ``config.yaml`` holds (one-line errors for a bad file)."""
    return load_config_file(path, "pipeline", "run")


def _given(args, parser) -> set[str]:
    """The options the command line gave (``args.given``, set by the CLI's ``main``); without
    it, those whose value differs from the default."""
    given = getattr(args, "given", None)
    if given is not None:
        return set(given)
    return {dest for dest, value in vars(args).items() if value != parser.get_default(dest)}


def set_unless_given(args, parser, values: dict) -> None:
    """Set each option of ``values`` the command line did not give (flags win)."""
    given = _given(args, parser)
    for dest, value in values.items():
        if hasattr(args, dest) and dest not in given:
            setattr(args, dest, value)


def apply_run_config(args, parser, path: Path) -> None:
    """Set ``args`` from the run configuration at ``path`` where the command line left an
    option at its default; the file's other pipeline and alignment settings go to
    ``args.pipeline_overrides`` and ``args.align_overrides``."""
    config = load_run_config(path)
    pipeline = config.get("pipeline") or {}
    values = {dest: config[key] for key, dest in _TOP.items() if key in config}
    values.update({dest: pipeline[key] for key, dest in _PIPELINE.items() if key in pipeline})
    for dest in _PATHS & set(values):
        if values[dest] is not None:
            values[dest] = Path(values[dest])
    if "render_width" in pipeline and pipeline.get("render_width"):
        values["render_size"] = f"{pipeline['render_width']}x{pipeline['render_height']}"
    if "compensate_timing" in pipeline:
        values["timing"] = "auto" if pipeline["compensate_timing"] else "none"
    if config.get("initial_pose") is not None:
        from nap3d_graph.conventions import T_to_tum

        values["initial_pose"] = " ".join(f"{v:.12g}" for v in T_to_tum(np.asarray(config["initial_pose"])[None])[0])
    if (config.get("align") or {}).get("matcher"):
        values["matcher"] = config["align"]["matcher"]
    imu = config.get("imu") or {}
    if imu.get("gravity_world") is not None:
        values["gravity"] = tuple(float(v) for v in imu["gravity_world"])
    elif imu.get("gravity") is not None:
        values["gravity"] = float(imu["gravity"])
    if imu.get("fallback_odometry") is not None:
        values["fallback_odom"] = imu["fallback_odometry"]
    set_unless_given(args, parser, values)
    mapped = set(_PIPELINE) | {"render_width", "render_height", "compensate_timing"} | _RESOLVED
    # A setting named as an option the command line gave is the flag's, not the file's.
    given = _given(args, parser)
    args.pipeline_overrides = {k: v for k, v in pipeline.items() if k not in mapped and k not in given}
    args.align_overrides = {k: v for k, v in (config.get("align") or {}).items() if k != "matcher"}


def with_overrides(config, overrides: dict | None):
    """``config`` (a dataclass) with the fields of ``overrides`` it has replaced."""
    if not overrides:
        return config
    names = {f.name for f in dataclasses.fields(config)}
    return dataclasses.replace(config, **{k: v for k, v in overrides.items() if k in names})
