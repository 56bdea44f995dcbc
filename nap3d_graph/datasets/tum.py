"""TUM RGB-D benchmark I/O: sequences, file lists, association and trajectory files.

A TUM sequence folder (as TUM publishes it) holds ``rgb.txt`` and ``depth.txt`` (lines
``timestamp filename``), the ``rgb/`` and ``depth/`` PNGs (depth uint16, 5000 per metre,
0 = missing) and, optionally, ``groundtruth.txt`` (``timestamp tx ty tz qx qy qz qw``,
the pose ``T_world_cam`` of the colour camera's optical centre).

Why not evo for everything: evo reads and writes trajectories well (our files are checked
against its reader), but it has no image-list reader, its ``associate_trajectories`` pairs
trajectories rather than image lists, and it cannot interpolate ground truth to the image
timestamps. TUM's own ``associate.py`` is a script, not an importable package, so its
greedy association is re-implemented here (vectorised candidate search), next to the
optimal one-to-one association that is the default.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from nap3d_graph.errors import DatasetError
from nap3d_graph.textfiles import data_lines, parse_float
from nap3d_graph.trajectory import read_tum_trajectory

from ..camera import CameraError, Intrinsics, RGBDFrame
from ..trajectory import GT_MAX_GAP_S, interpolate_poses
from .association import ASSOCIATION_METHODS, GroundTruthLookup, associate, pair_streams
from .depth_unit import checked_depth_scale
from .frames import frame_index, parse_frame_range
from .identity import fingerprint_files

__all__ = [
    "TumSequence",
    "read_file_list",
    "file_order_stamps",
    "tum_intrinsics_for",
    "TUM_DEPTH_SCALE",
    "depth_scale_of",
]

logger = logging.getLogger(__name__)

#: TUM depth PNGs store z-depth in units of 1/5000 m.
TUM_DEPTH_SCALE = 5000.0

# TUM's published colour-camera calibrations (https://cvg.cit.tum.de/data/datasets/rgbd-dataset
# "file formats" page). Depth is registered to colour by the driver, so one camera serves both.
_TUM_CAMERAS = {
    "freiburg1": Intrinsics(517.3, 516.5, 318.6, 255.3, 640, 480,
                            (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    "freiburg2": Intrinsics(520.9, 521.0, 325.1, 249.7, 640, 480,
                            (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    "freiburg3": Intrinsics(535.4, 539.2, 320.1, 247.6, 640, 480),
}
_TUM_DEFAULT_CAMERA = Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)


# --- text files ---------------------------------------------------------------------------


def read_file_list(path) -> tuple[np.ndarray, list[str]]:
    """Read a TUM ``rgb.txt`` / ``depth.txt``: lines ``timestamp filename``, ``#`` comments.

    Returns ``(timestamps (N,) float seconds, filenames list of N str)`` in file order; the
    file names are relative to the sequence folder as written in the file.
    """
    path = Path(path)
    stamps, names = [], []
    for number, fields in data_lines(path):
        if len(fields) < 2:
            raise DatasetError(f"{path}:{number}: expected 'timestamp filename', got {' '.join(fields)!r}")
        stamps.append(parse_float(path, number, fields[0]))
        names.append(" ".join(fields[1:]))
    return np.asarray(stamps, dtype=float), names


#: ``stamps=`` of :class:`TumSequence`: the lists' stamps as written (refused when they go
#: backwards), or the frames in file order with stamps derived from that order.
STAMPS_OPTIONS = ("as-written", "file-order")


_FILE_ORDER_HINT = "pass `stamps='file-order'` to keep the frames in file order with stamps derived from it"


def _backwards_problem(path: Path, stamps: np.ndarray) -> str | None:
    """What is wrong when some stamps are smaller than the one before them (file order)."""
    back = np.flatnonzero(np.diff(stamps) < 0) + 1
    if not back.size:
        return None
    first = int(back[0])
    return (f"{path}: stamps go backwards at {back.size} of {len(stamps)} lines (first at data line {first + 1}: "
            f"{stamps[first - 1]:.6f} then {stamps[first]:.6f})")


def _per_frame_intervals(stamps: np.ndarray) -> bool:
    """Stamps that are each frame's interval since the last (a script restarting its clock
    every frame): all positive, below a second, and they do not grow over the list (their
    spread is under their median)."""
    return bool(len(stamps) >= 3 and np.all(stamps > 0) and stamps.max() < 1.0
                and np.ptp(stamps) < np.median(stamps))


#: Frame rates no RGB-D camera has: stamps implying a rate outside these (Hz) are not a clock.
PLAUSIBLE_RATE_HZ = (5.0, 120.0)


def implausible_rate(path, stamps: np.ndarray) -> str | None:
    """A warning when a list's stamps imply a frame rate (its median forward step) no RGB-D
    camera has (outside :data:`PLAUSIBLE_RATE_HZ`): a script that wrote something else than a
    clock (each frame's processing time, a counter), whose every derived velocity (rolling
    shutter, depth instant, motion prior) would be off by the same factor. None when plausible."""
    steps = np.diff(np.asarray(stamps, dtype=float))
    steps = steps[steps > 0]
    if not steps.size:
        return None
    rate = 1.0 / float(np.median(steps))
    low, high = PLAUSIBLE_RATE_HZ
    if low <= rate <= high:
        return None
    return (f"{path}: its stamps imply {rate:.1f} frames a second, which no RGB-D camera delivers (outside "
            f"{low:g}-{high:g} Hz): if they are not a clock, give the camera's rate (`fps`, e.g. 30); a recording thinned "
            "on purpose can ignore this")


def fps_stamps(rgb_list: Path, depth_list: Path, rgb_count: int, depth_count: int, fps: float) -> np.ndarray:
    """Stamps ``i / fps`` for the lists' lines in file order (the camera's rate given, the
    lists' stamps not a clock), one colour and one depth image per line; a one-line error when
    the two lists do not have a line for every frame."""
    if not fps > 0:
        raise DatasetError(f"{rgb_list.parent}: `fps` must be a positive frame rate, got {fps}")
    if rgb_count != depth_count:
        raise DatasetError(f"{rgb_list.parent}: with `fps` each line of {rgb_list.name} and {depth_list.name} is one "
                           f"frame, but they list {rgb_count} and {depth_count} images")
    return np.arange(rgb_count, dtype=float) / float(fps)


def file_order_stamps(path, stamps: np.ndarray) -> np.ndarray:
    """Strictly increasing stamps for a list's lines in file order. Stamps that never go
    backwards are returned as they are; per-frame intervals (:func:`_per_frame_intervals`)
    become their running sum; otherwise the first stamp, then one median positive step (of
    the stamps as written) per line. A warning says how many went backwards."""
    stamps = np.asarray(stamps, dtype=float)
    problem = _backwards_problem(Path(path), stamps)
    if problem is None:
        return stamps
    if _per_frame_intervals(stamps):
        logger.warning("%s; they look like per-frame intervals (they never grow: %.6f to %.6f s): keeping the frames in "
                       "file order with stamps from their running sum", problem, stamps.min(), stamps.max())
        return np.cumsum(stamps)
    steps = np.diff(stamps)
    positive = steps[steps > 0]
    if not positive.size:
        raise DatasetError(f"{path}: no two consecutive stamps increase; cannot derive a frame rate from them")
    step = float(np.median(positive))
    logger.warning("%s; keeping the frames in file order with stamps from %.6f s every %.6f s (the median forward "
                   "step)", problem, stamps[0], step)
    return stamps[0] + np.arange(len(stamps)) * step


# --- intrinsics -----------------------------------------------------------------------------


def tum_intrinsics_for(name: str) -> Intrinsics | None:
    """TUM's published (raw, distorted) intrinsics for a sequence name with ``freiburgN``."""
    name = name.lower()
    for key, intrinsics in _TUM_CAMERAS.items():
        if key in name:
            return intrinsics
    return None


def _intrinsics_source(folder: Path, intrinsics) -> str:
    """Where a sequence's camera came from: "argument", "intrinsics.json", "freiburgN" (TUM's
    published calibration by the folder's name) or "default" (TUM's default camera: a guess)."""
    if intrinsics is not None:
        return "argument"
    if (folder / "intrinsics.json").is_file():
        return "intrinsics.json"
    name = folder.name.lower()
    return next((key for key in _TUM_CAMERAS if key in name), "default")


def _resolve_intrinsics(folder: Path, intrinsics) -> Intrinsics:
    """Explicit argument, else ``intrinsics.json``, else TUM's camera from the name, else default."""
    if intrinsics is not None:
        if isinstance(intrinsics, dict):
            try:
                return Intrinsics.from_dict(intrinsics)
            except (CameraError, TypeError, ValueError) as exc:
                raise DatasetError(f"{folder}: invalid intrinsics argument ({exc})") from None
        if not isinstance(intrinsics, Intrinsics):
            raise DatasetError(
                f"{folder}: intrinsics must be an Intrinsics or its dict, got {type(intrinsics).__name__}"
            )
        return intrinsics
    json_path = folder / "intrinsics.json"
    if json_path.is_file():
        try:
            return Intrinsics.from_dict(json.loads(json_path.read_text()))
        except (CameraError, TypeError, ValueError, AttributeError, OSError) as exc:
            message = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise DatasetError(f"{json_path}: invalid intrinsics ({message})") from None
    from_name = tum_intrinsics_for(folder.name)
    if from_name is not None:
        return from_name
    logger.warning(
        "%s: no intrinsics given, no intrinsics.json and no freiburg1/2/3 in the name; "
        "using TUM's default camera (fx=fy=525, cx=319.5, cy=239.5)", folder
    )
    return _TUM_DEFAULT_CAMERA


def depth_scale_of(folder: Path, depth_scale=None) -> tuple[float, str]:
    """``(units per metre, where it came from)`` of a TUM-layout folder's depth PNGs: the
    argument ("argument"), else ``intrinsics.json``'s ``depth_scale`` ("intrinsics.json"), else
    TUM's 5000 ("TUM default")."""
    if depth_scale is not None:
        return checked_depth_scale(depth_scale, str(folder)), "argument"
    json_path = folder / "intrinsics.json"
    if json_path.is_file():
        try:
            declared = json.loads(json_path.read_text())
        except (ValueError, OSError):
            declared = None  # _resolve_intrinsics says what is wrong with the file
        if isinstance(declared, dict) and declared.get("depth_scale") is not None:
            return checked_depth_scale(declared["depth_scale"], str(json_path)), "intrinsics.json"
    return TUM_DEPTH_SCALE, "TUM default"


def _png_size(path: Path) -> tuple[int, int] | None:
    """A PNG's (width, height) from its header; None for another format or an unreadable file
    (such a frame is said when it is read)."""
    try:
        with open(path, "rb") as f:
            head = f.read(24)
    except OSError:
        return None
    if len(head) < 24 or head[:8] != b"\x89PNG\r\n\x1a\n":
        return None
    return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")


# --- sequence -------------------------------------------------------------------------------


class TumSequence(GroundTruthLookup):
    """A TUM RGB-D sequence folder, frames loaded lazily.

    Colour frames are paired one-to-one with depth frames within ``max_difference`` seconds
    (after adding ``offset`` to the depth stamps; ``"auto"``, the default, estimates the
    depth stream's typical lead with :func:`estimate_stream_offset`): ``association="optimal"`` (default) keeps
    the most pairs with the least total time difference, ``"greedy"`` is TUM's
    ``associate.py`` (see :func:`associate`). Ground truth, when ``groundtruth.txt`` exists,
    is interpolated to each colour timestamp; frames it cannot cover keep a NaN pose
    (``has_gt``).

    Images: with ``undistort`` (default) and a camera with distortion, colour is remapped to
    the pinhole camera ``intrinsics`` (same fx fy cx cy, no distortion). Depth is delivered
    as stored unless ``undistort_depth``: TUM's depth is registered to colour by the Kinect
    driver with a pinhole model, and on fr1/xyz raw depth re-projects onto the other frames
    with the ground-truth poses better than depth remapped with the colour distortion
    (5.4 vs 6.3 mm median over frame pairs 30 apart); TUM also advises not to undistort
    it. Depth values are never interpolated (nearest neighbour when remapped).

    Attributes: ``timestamps`` (N,) colour stamps, ``depth_timestamps`` (N,),
    ``T_world_cam_gt`` (N, 4, 4) at the colour stamps, or None, ``rgb_paths`` /
    ``depth_paths`` (N Paths), ``intrinsics`` (of the delivered images: undistorted pinhole
    when ``undistort`` and the camera has distortion), ``raw_intrinsics`` (as resolved,
    possibly with distortion), ``path``, ``name``, ``has_gt`` (N,), ``rgb_line_index`` (N,)
    (each frame's line among rgb.txt's data lines), ``undistort``,
    ``undistort_depth``, ``association``, ``offset``, ``frame_range`` ``(start, stop)``,
    ``recording_id`` (a content fingerprint of the whole recording).

    ``frames``: ``START:STOP`` keeps part of the associated frames (indices, or fractions
    such as ``0:0.5`` for the first half; see :func:`parse_frame_range`).

    ``stamps``: ``"as-written"`` (default) uses the lists' stamps and refuses a list whose
    stamps go backwards (a one-line :class:`DatasetError` naming the file and how many lines);
    ``"file-order"`` keeps such a list's frames in file order and replaces its stamps with
    strictly increasing ones at its median forward step (a warning says how many went
    backwards; a list whose stamps never go backwards is kept as written). Attribute
    ``stamps_mode``.

    ``depth_scale``: the depth PNGs' units per metre (TUM 5000, a RealSense or 7-Scenes' millimetres
    1000); default ``intrinsics.json``'s ``depth_scale``, else TUM's 5000. Attributes
    ``depth_units_per_m`` and ``depth_scale_source``; :meth:`raw_depth` gives a frame's depth
    as stored.

    On the Kinect, depth is stamped 12-20 ms before colour; for geometric checks with depth,
    interpolate the ground truth at ``depth_timestamps`` (:func:`interpolate_poses`): on
    fr1/xyz that takes neighbouring frames' depth agreement from 3.2 to 2.4 mm.
    """

    #: Frames may be read on another thread (a replay reads ahead: nap3d_graph.run.read_ahead).
    reads_concurrently = True

    def __init__(
        self,
        path,
        intrinsics=None,
        max_difference: float = 0.02,
        undistort: bool = True,
        undistort_depth: bool = False,
        association: str = "optimal",
        offset: float | str = "auto",
        frames: str | None = None,
        stamps: str = "as-written",
        depth_scale: float | None = None,
        fps: float | None = None,
    ):
        self.path = Path(path)
        self._check_arguments(stamps, association)
        self.fps = None if fps is None else float(fps)
        self.name = self.path.name
        self.max_difference = float(max_difference)
        self.association = association
        self.offset = offset
        self._resolve_camera(intrinsics, undistort, undistort_depth, depth_scale)
        rgb_list, depth_list, (rgb_stamps, rgb_names), (depth_stamps, depth_names) = self._read_lists()
        pairs = self._associate(rgb_list, depth_list, rgb_stamps, depth_stamps)
        self._keep_pairs(pairs, rgb_list, depth_list, rgb_stamps, rgb_names, depth_stamps, depth_names)
        self.T_world_cam_gt = None
        self._gt_raw: tuple[np.ndarray, np.ndarray] | None = None
        self._attach_ground_truth(self.path / "groundtruth.txt")
        self.frame_range = parse_frame_range(frames, len(self.timestamps))
        self._select(*self.frame_range)
        self._check_images_exist()
        self._check_image_sizes()

    def _check_arguments(self, stamps: str, association: str) -> None:
        """One-line errors for a folder that is not there or options it cannot take."""
        if not self.path.is_dir():
            raise DatasetError(f"{self.path}: sequence folder not found")
        if stamps not in STAMPS_OPTIONS:
            raise DatasetError(f"{self.path}: stamps must be one of {STAMPS_OPTIONS}, got {stamps!r}")
        self.stamps_mode = stamps
        if association not in ASSOCIATION_METHODS:
            raise DatasetError(f"{self.path}: association must be one of {ASSOCIATION_METHODS}, got {association!r}")

    def _resolve_camera(self, intrinsics, undistort: bool, undistort_depth: bool, depth_scale: float | None) -> None:
        """The camera (as resolved and as delivered), whether images are undistorted, and the
        depth's unit."""
        self.raw_intrinsics = _resolve_intrinsics(self.path, intrinsics)
        self.intrinsics_source = _intrinsics_source(self.path, intrinsics)
        self.depth_units_per_m, self.depth_scale_source = depth_scale_of(self.path, depth_scale)
        has_distortion = any(d != 0.0 for d in self.raw_intrinsics.distortion)
        self.undistort = bool(undistort) and has_distortion
        # Depth PNGs are registered to colour by the Kinect driver (OpenNI, factory pinhole
        # model): they are already close to an undistorted image, and TUM advises against
        # undistorting them. Measured on fr1/xyz, raw depth agrees better with the ground
        # truth than depth remapped with the colour distortion (see undistort_depth).
        self.undistort_depth = self.undistort and bool(undistort_depth)
        if self.undistort or not has_distortion:
            self.intrinsics = self.raw_intrinsics.without_distortion()
        else:
            self.intrinsics = self.raw_intrinsics  # raw images: say so with the distortion
        self._maps: tuple[np.ndarray, np.ndarray] | None = None

    def _read_lists(self):
        """``(rgb.txt, depth.txt, (rgb stamps, names), (depth stamps, names))``, the stamps as
        ``stamps_mode`` says (refused when they go backwards, or kept in file order)."""
        if (self.path / "PARTIAL.txt").is_file():
            raise DatasetError(f"{self.path}: the command that wrote this folder did not finish (PARTIAL.txt); "
                               "redo it with `force`, or remove the folder")
        rgb_list, depth_list = self.path / "rgb.txt", self.path / "depth.txt"
        for listed in (rgb_list, depth_list):
            if not listed.is_file():
                raise DatasetError(f"{listed}: file not found")
        rgb_stamps, rgb_names = read_file_list(rgb_list)
        depth_stamps, depth_names = read_file_list(depth_list)
        if self.fps is not None:  # the camera's rate given: the lists' stamps are not a clock
            rgb_stamps = depth_stamps = fps_stamps(rgb_list, depth_list, len(rgb_names), len(depth_names), self.fps)
            if (self.path / "groundtruth.txt").is_file():
                logger.warning("%s: stamps from `fps` (%g Hz) start at 0 s; groundtruth.txt keeps its own stamps, so "
                               "it pairs with the frames only if it was written on the same clock", self.path, self.fps)
            return rgb_list, depth_list, (rgb_stamps, rgb_names), (depth_stamps, depth_names)
        # Stamps that go backwards (a recording script's badly formatted fractions) would be
        # re-sorted by the association and written out of order downstream: refuse them, or
        # keep the file order when asked.
        if self.stamps_mode == "as-written":
            problems = [_backwards_problem(listed, listed_stamps)
                        for listed, listed_stamps in ((rgb_list, rgb_stamps), (depth_list, depth_stamps))]
            if any(problems):
                raise DatasetError("; ".join(p for p in problems if p) + "; " + _FILE_ORDER_HINT)
        else:
            rgb_stamps = file_order_stamps(rgb_list, rgb_stamps)
            depth_stamps = file_order_stamps(depth_list, depth_stamps)
        warning = implausible_rate(rgb_list, rgb_stamps)
        if warning:
            logger.warning(warning)
        return rgb_list, depth_list, (rgb_stamps, rgb_names), (depth_stamps, depth_names)

    def _associate(self, rgb_list: Path, depth_list: Path, rgb_stamps: np.ndarray, depth_stamps: np.ndarray
                   ) -> np.ndarray:
        """(M, 2) indices of the colour and depth entries paired (``offset`` estimated when
        'auto'); a one-line error when none pair."""
        if self.offset == "auto":
            self.offset, pairs = pair_streams(rgb_stamps, depth_stamps, self.max_difference, self.association)
        else:
            self.offset = float(self.offset)
            pairs = associate(rgb_stamps, depth_stamps, self.max_difference, self.offset, self.association)
        if len(pairs) == 0:
            raise DatasetError(
                f"{depth_list}: no depth timestamp within {self.max_difference} s of any in {rgb_list.name}"
            )
        logger.info(
            "%s: %d rgb, %d depth frames, %d associated within %.3f s",
            self.name, len(rgb_stamps), len(depth_stamps), len(pairs), self.max_difference,
        )
        return pairs

    def _keep_pairs(self, pairs: np.ndarray, rgb_list: Path, depth_list: Path, rgb_stamps, rgb_names, depth_stamps,
                    depth_names) -> None:
        """The associated frames' stamps, paths and line indices, and what identifies the recording."""
        self.timestamps = rgb_stamps[pairs[:, 0]]
        self.depth_timestamps = depth_stamps[pairs[:, 1]]
        # Each frame's line among rgb.txt's data lines: what a run reports as its frame index,
        # so a row of corrections.csv names the same image whatever association dropped.
        self.rgb_line_index = pairs[:, 0].astype(int)
        self.rgb_paths = [self.path / rgb_names[i] for i in pairs[:, 0]]
        # What identifies the recording whatever frames are selected (recording_id).
        self._identity_files = [rgb_list, depth_list, self.path / "groundtruth.txt",
                                self.path / rgb_names[0], self.path / rgb_names[-1]]
        self._recording_id: str | None = None
        self.depth_paths = [self.path / depth_names[j] for j in pairs[:, 1]]

    def _check_images_exist(self) -> None:
        """A listed image that is gone does not make the whole sequence unusable: say so now,
        and raise (naming the file) only when that frame is read, so a run can skip it."""
        self.missing_images = [p for p in (*self.rgb_paths, *self.depth_paths) if not p.is_file()]
        if len(self.missing_images) == len(self.rgb_paths) + len(self.depth_paths):
            raise DatasetError(f"{self.path}: none of the listed images exist (first: {self.missing_images[0]})")
        if self.missing_images:
            logger.warning("%s: %d listed image(s) not found, e.g. %s; those frames will fail to load",
                           self.name, len(self.missing_images), self.missing_images[0])

    def _check_image_sizes(self) -> None:
        """One line, before any frame is read, for a folder whose images are not all of one size
        (two recordings mixed), whose depth is not the colour's size (not registered to
        colour), or whose images are not the size the camera says. PNG headers only: cheap."""
        sizes = {}
        for kind, paths in (("colour", self.rgb_paths), ("depth", self.depth_paths)):
            found = {}
            for path in paths:
                size = _png_size(path)
                if size is not None:
                    found.setdefault(size, path)
            if len(found) > 1:
                (a, first), (b, other) = list(found.items())[:2]
                raise DatasetError(f"{self.path}: the {kind} images are of {len(found)} sizes ({first.name} is "
                                   f"{a[0]}x{a[1]}, {other.name} {b[0]}x{b[1]}): does the folder mix recordings?")
            sizes[kind] = next(iter(found), None)
        colour, depth = sizes["colour"], sizes["depth"]
        if colour and depth and colour != depth:
            raise DatasetError(f"{self.path}: depth is {depth[0]}x{depth[1]}, colour {colour[0]}x{colour[1]}: the depth "
                               "is not registered to colour (record it aligned to colour, e.g. librealsense's "
                               "rs.align, or read the .bag itself)")
        K = self.raw_intrinsics
        if colour and colour != (K.width, K.height):
            source = ("TUM's default camera, a guess" if self.intrinsics_source == "default"
                      else self.intrinsics_source)
            raise DatasetError(f"{self.path}: the images are {colour[0]}x{colour[1]} but the camera ({source}) is "
                               f"{K.width}x{K.height}: give its intrinsics.json")

    def _select(self, start: int, stop: int) -> None:
        """Keep frames ``start:stop`` of the associated frames (``frames=`` of the constructor)."""
        if (start, stop) == (0, len(self.timestamps)):
            return
        self.timestamps = self.timestamps[start:stop]
        self.depth_timestamps = self.depth_timestamps[start:stop]
        self.rgb_line_index = self.rgb_line_index[start:stop]
        self.rgb_paths = self.rgb_paths[start:stop]
        self.depth_paths = self.depth_paths[start:stop]
        if self.T_world_cam_gt is not None:
            self.T_world_cam_gt = self.T_world_cam_gt[start:stop]

    def _attach_ground_truth(self, gt_path: Path) -> None:
        """Ground truth interpolated at the colour stamps. Frames it does not cover (before or
        after it, or in a gap) stay in the sequence with a NaN pose: they have no error, not
        no pose; ``has_gt`` says which, and a warning says how many."""
        if not gt_path.is_file():
            return
        stamps_gt, T_world_cam_gt = read_tum_trajectory(gt_path)
        self._gt_raw = (stamps_gt, T_world_cam_gt)
        try:
            T = interpolate_poses(stamps_gt, T_world_cam_gt, self.timestamps)
        except DatasetError as exc:
            raise DatasetError(f"{gt_path}: {exc}") from None
        keep = np.all(np.isfinite(T), axis=(1, 2))
        if not np.any(keep):
            raise DatasetError(f"{gt_path}: ground truth covers none of the {len(keep)} frames")
        missing = np.flatnonzero(~keep)
        if missing.size:
            logger.warning(
                "%s: %d of %d frames have no ground truth (outside it or in its gaps > %.2f s), e.g. frames %s; "
                "they are still run, without an error figure",
                self.name, missing.size, len(keep), GT_MAX_GAP_S, ", ".join(str(int(i)) for i in missing[:5]),
            )
        self.T_world_cam_gt = T

    @property
    def recording_id(self) -> str:
        """Content fingerprint of the whole recording (lists, ground truth, first and last
        colour image): the same for any ``frames`` range, different for another recording
        with the same stamps (see :mod:`nap3d_graph.datasets.identity`)."""
        if self._recording_id is None:
            self._recording_id = fingerprint_files(self._identity_files)
        return self._recording_id

    def __len__(self) -> int:
        return len(self.timestamps)

    def __getitem__(self, index) -> RGBDFrame:
        i = frame_index(index, len(self), self.name)
        rgb = self._read_rgb(self.rgb_paths[i])
        depth_m = self._read_depth(self.depth_paths[i])
        return RGBDFrame(rgb, depth_m, self.intrinsics, float(self.timestamps[i]), float(self.depth_timestamps[i]))

    def __iter__(self) -> Iterator[RGBDFrame]:
        for i in range(len(self)):
            yield self[i]

    def __repr__(self) -> str:
        return (
            f"TumSequence({str(self.path)!r}, frames={len(self)}, "
            f"ground_truth={self.T_world_cam_gt is not None}, undistort={self.undistort})"
        )

    # --- image reading ---

    def _check_size(self, path: Path, image: np.ndarray) -> None:
        if image.shape[:2] != self.raw_intrinsics.shape:
            raise DatasetError(
                f"{path}: image is {image.shape[1]}x{image.shape[0]} but the intrinsics say "
                f"{self.raw_intrinsics.width}x{self.raw_intrinsics.height}"
            )

    def _undistort_maps(self) -> tuple[np.ndarray, np.ndarray]:
        if self._maps is None:
            self._maps = self.raw_intrinsics.undistortion_maps()
        return self._maps

    def _read_rgb(self, path: Path) -> np.ndarray:
        if not path.is_file():
            raise DatasetError(f"{path}: listed image file not found")
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise DatasetError(f"{path}: cannot read colour image (missing or corrupt)")
        self._check_size(path, bgr)
        if self.undistort:
            map_x, map_y = self._undistort_maps()
            bgr = cv2.remap(bgr, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)

    def raw_depth(self, index) -> np.ndarray:
        """Frame ``index``'s depth PNG as stored: (H, W) uint16, ``depth_units_per_m`` per metre,
        0 = missing (not undistorted)."""
        return self._read_raw_depth(self.depth_paths[frame_index(index, len(self), self.name)])

    def _read_raw_depth(self, path: Path) -> np.ndarray:
        if not path.is_file():
            raise DatasetError(f"{path}: listed image file not found")
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise DatasetError(f"{path}: cannot read depth image (missing or corrupt)")
        if raw.dtype != np.uint16 or raw.ndim != 2:
            raise DatasetError(
                f"{path}: depth must be a single-channel uint16 PNG, got {raw.dtype} with shape {raw.shape}"
            )
        self._check_size(path, raw)
        return raw

    def _read_depth(self, path: Path) -> np.ndarray:
        raw = self._read_raw_depth(path)
        if self.undistort_depth:
            map_x, map_y = self._undistort_maps()
            # Nearest neighbour: interpolating across a depth edge would invent surfaces.
            raw = cv2.remap(
                raw, map_x, map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0
            )
        return raw.astype(np.float32) / np.float32(self.depth_units_per_m)
