"""What every subcommand shares: the one-line usage error, the arguments several commands add
(their argparse settings in :mod:`nap3d_graph.arguments`), and checks of output paths made
*before* any work starts."""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

from nap3d_graph.arguments import (
    DEPTH_SCALE_OPTION,
    FPS_OPTION,
    STAMPS_OPTION,
    TOPICS_OPTION,
    frames_option,
    matcher_option,
)
from nap3d_graph.conventions import tum_to_T
from nap3d_graph.datasets import DatasetError, read_tum_trajectory
from nap3d_graph.datasets.depth_unit import inspect_depth_unit
from nap3d_graph.fields import frames_seen_in_training
from nap3d_graph.run.settings import SettingsError, render_size

__all__ = ["SETTING_FLAGS", "in_flags", "UsageError", "Parser", "PartialOutput", "PARTIAL_MARKER", "add_frames_argument", "add_topics_argument", "warn_trained_frames", "warn_depth_units", "add_unit_arguments", "StopOnSignal", "parse_pose",
           "writable_dir", "writable_file_parent", "empty_or_new_dir"]


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


def add_matcher_argument(parser, default: str = "sift") -> None:
    parser.add_argument("--matcher", default=default, **matcher_option(default))


def add_topics_argument(parser) -> None:
    """``--topics``: which topics and tf frames of a ROS bag to read."""
    parser.add_argument("--topics", default=None, **TOPICS_OPTION)


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
