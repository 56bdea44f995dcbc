"""Microsoft 7-Scenes RGB-D sequences (and anything written in their layout).

A sequence folder (``seq-01/``, ``seq-02/``... in the release) holds, per frame k (its number
in six digits: ``frame-000042`` for k = 42), ``frame-000042.color.png`` (or ``.jpg``),
``frame-000042.depth.png`` (uint16 millimetres; 0 or 65535 missing) and
``frame-000042.pose.txt`` (4x4 camera-to-world, metres, tracked for
the *depth* camera by KinectFusion). Frame k was captured at k / 30 s. A
``camera-intrinsics.txt`` (3x3) beside the frames or in the scene folder gives the depth
camera; without one the dataset's nominal fx = fy = 585, centre (320, 240) is used.

Depth is not registered to colour, and the colour camera's calibration is not published.
By default (``registration="nominal"``) the colour camera is the Kinect v1's nominal one
(525 px, centre at the image's centre, no offset from the depth camera: the value commonly
used with this dataset), and each frame's depth is warped into it, so frames and ground truth
are the colour camera's, as for every other source here. ``registration="images"`` estimates
the focal length and principal point from the recording itself instead
(:mod:`~nap3d_graph.datasets.registration`, cached per recording). On the redkitchen copy in
this project's shared data that estimate lands at f = 547 px, outside the range Kinect v1
colour cameras calibrate to (517-535 px for the three TUM calibrated), and the surveys made with it close fewer
loops and agree worse with their own depth than those made with the nominal camera: why the
nominal camera is the default (``benchmarks/map_registration.py``, figures on the results page).
"""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from nap3d_graph.cache import default_cache_dir
from nap3d_graph.errors import DatasetError

from ..camera import Intrinsics, RGBDFrame
from .association import GroundTruthLookup
from .depth_timing import frame_pairs
from .depth_unit import checked_depth_scale
from .frames import frame_index, parse_frame_range
from .identity import fingerprint_files
from .registration import DepthColourRegistration, depth_chain, estimate_registration, register_depth_to_colour

__all__ = ["SevenScenesSequence", "NOMINAL_DEPTH_CAMERA", "NOMINAL_COLOUR_CAMERA", "SEVENSCENES_FPS",
           "is_sevenscenes_folder", "write_sevenscenes_frame"]

log = logging.getLogger(__name__)

#: Kinect v1 at 640x480: the depth camera 7-Scenes publishes, and the colour camera commonly used.
NOMINAL_DEPTH_CAMERA = Intrinsics(585.0, 585.0, 320.0, 240.0, 640, 480)
NOMINAL_COLOUR_CAMERA = Intrinsics(525.0, 525.0, 320.0, 240.0, 640, 480)
SEVENSCENES_FPS = 30.0
#: Depth PNGs: millimetres; 65535 (and 0) mean no measurement.
DEPTH_PER_METRE = 1000.0
DEPTH_MISSING = 65535

_FRAME = re.compile(r"^frame-(\d+)\.pose\.txt$")
_REGISTRATION_VERSION = 3  # 2: poses projected onto rigid transforms; 3: posed by the depth images


def is_sevenscenes_folder(path) -> bool:
    """A 7-Scenes sequence folder (``frame-*.pose.txt``) or a scene folder of sequence
    folders (``seq-01/``, ``seq-02/``...)."""
    path = Path(path)
    if not path.is_dir():
        return False
    if next(path.glob("frame-*.pose.txt"), None) is not None:
        return True
    return any(next(seq.glob("frame-*.pose.txt"), None) is not None for seq in path.glob("seq-*") if seq.is_dir())


def write_sevenscenes_frame(folder, index: int, rgb: np.ndarray, depth_m: np.ndarray, T_world_depth: np.ndarray,
                            colour_ext: str = "png") -> None:
    """Write frame ``index`` in the 7-Scenes layout: colour (RGB uint8 (H, W, 3)), depth in
    millimetres (metres (H, W); 0 or NaN missing, rounded to the millimetre) and the depth
    camera's pose ``T_world_depth`` (4, 4)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    stem = folder / f"frame-{index:06d}"
    depth_mm = np.rint(np.nan_to_num(np.asarray(depth_m, dtype=np.float64), nan=0.0) * DEPTH_PER_METRE)
    if not cv2.imwrite(f"{stem}.color.{colour_ext}", cv2.cvtColor(np.asarray(rgb, np.uint8), cv2.COLOR_RGB2BGR)):
        raise DatasetError(f"{stem}.color.{colour_ext}: cannot write")
    cv2.imwrite(f"{stem}.depth.png", np.clip(depth_mm, 0, DEPTH_MISSING - 1).astype(np.uint16))
    np.savetxt(f"{stem}.pose.txt", np.asarray(T_world_depth, dtype=float), fmt="%.18e")


def _read_intrinsics_file(path: Path, width: int, height: int) -> Intrinsics:
    try:
        K = np.loadtxt(path, dtype=float)
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{path}: cannot read a 3x3 camera matrix ({exc})") from None
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise DatasetError(f"{path}: expected a 3x3 camera matrix with positive focal lengths, got {K.tolist()}")
    return Intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], width, height)


def _nearest_rigid(T: np.ndarray, path: Path) -> np.ndarray:
    """The pose with its rotation part projected onto the nearest rotation (SVD). 7-Scenes'
    KinectFusion poses are stored with rounding: |R^T R - I| reaches 2e-4, and increments
    composed from them (``--odom noisy``) drift away from rotations until a check refuses
    them. A matrix far from a rotation is an error, not rounding."""
    U, S, Vt = np.linalg.svd(T[:3, :3])
    if np.max(np.abs(S - 1.0)) > 0.01 or np.linalg.det(U @ Vt) < 0:
        raise DatasetError(f"{path}: the rotation part is not a rotation (singular values {np.round(S, 4).tolist()})")
    if np.any(np.abs(T[3] - [0, 0, 0, 1]) > 1e-6):
        raise DatasetError(f"{path}: the last row of a pose must be 0 0 0 1, got {T[3].tolist()}")
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = U @ Vt, T[:3, 3]
    return out


class SevenScenesSequence(GroundTruthLookup):
    """A 7-Scenes sequence, frames loaded lazily, in the colour camera.

    path: a sequence folder, or a scene folder with one sequence folder ``seq-01/`` (or name it with
    ``sequence``). depth_intrinsics: the depth camera (default: ``camera-intrinsics.txt``,
    else nominal). registration: ``"nominal"`` (the
    Kinect v1's nominal colour camera, see the module's text; reads nothing), ``"images"``
    (``"auto"`` is its older name: estimate the colour camera from the images alone, each
    frame pair's motion by depth-only ICP: no pose file is read; cached in ``cache_dir``),
    ``"poses"`` (the same with each pair's motion from the recording's pose files), ``"none"``
    (treat the depth camera as the colour camera: the images as stored), a
    :class:`DepthColourRegistration` or its dict. frames:
    ``START:STOP`` (see :func:`parse_frame_range`); the registration is always estimated
    on the whole recording, so every part of it is read the same way.

    Attributes: ``timestamps`` (N,) = frame number / 30 s, ``depth_timestamps`` (the same),
    ``T_world_cam_gt`` (N, 4, 4) of the colour camera (NaN where a pose is not finite),
    ``intrinsics`` (colour camera), ``depth_intrinsics``, ``registration``, ``frame_numbers``
    (N,), ``rgb_line_index`` (the frame numbers: what a run reports as frame index),
    ``frame_range``, ``path``, ``name``, ``recording_id``.
    """

    #: Frames may be read on another thread (a replay reads ahead: nap3d_graph.run.read_ahead).
    reads_concurrently = True

    def __init__(self, path, sequence: str | None = None, depth_intrinsics: Intrinsics | None = None,
                 registration="nominal", frames: str | None = None, cache_dir=None, intrinsics=None,
                 depth_scale: float | None = None):
        if intrinsics is not None:
            raise DatasetError(f"{path}: a 7-Scenes sequence takes depth_intrinsics (the colour camera is "
                               "estimated or given through registration)")
        self.path = self._sequence_folder(Path(path), sequence)
        # 7-Scenes stores millimetres; another unit only when declared (a converted copy).
        self.depth_units_per_m = DEPTH_PER_METRE if depth_scale is None else checked_depth_scale(depth_scale,
                                                                                                   str(self.path))
        self.depth_scale_source = "7-Scenes default" if depth_scale is None else "argument"
        in_scene = self.path.name.startswith("seq-")
        self.name = f"{self.path.parent.name}_{self.path.name}" if in_scene else self.path.name
        numbers = sorted(int(m.group(1)) for p in self.path.iterdir() if (m := _FRAME.match(p.name)))
        if not numbers:
            raise DatasetError(f"{self.path}: no frame-<number>.pose.txt files (e.g. frame-000000.pose.txt)")
        self._all_numbers = np.asarray(numbers, dtype=int)
        self._colour_paths = {k: self._colour_path(k) for k in numbers}
        probe = cv2.imread(str(self._colour_paths[numbers[0]]), cv2.IMREAD_COLOR)
        if probe is None:
            raise DatasetError(f"{self._colour_paths[numbers[0]]}: cannot read colour image (missing or corrupt)")
        height, width = probe.shape[:2]
        self.depth_intrinsics = depth_intrinsics or self._depth_camera(width, height)
        self._T_world_depth_all = np.stack([self._read_pose(k) for k in numbers])
        self._recording_id: str | None = None
        self.cache_dir = cache_dir
        self.registration = self._resolve_registration(registration)
        self.intrinsics = self.registration.colour
        self._select_all()
        self.frame_range = parse_frame_range(frames, len(self.timestamps))
        self._select(*self.frame_range)

    # --- layout ---

    @staticmethod
    def _sequence_folder(path: Path, sequence: str | None) -> Path:
        if not path.is_dir():
            raise DatasetError(f"{path}: sequence folder not found")
        if sequence is not None:
            path = path / sequence
            if not path.is_dir():
                raise DatasetError(f"{path}: no such 7-Scenes sequence folder")
            return path
        if next(path.glob("frame-*.pose.txt"), None) is not None:
            return path
        seqs = sorted(p for p in path.glob("seq-*") if p.is_dir())
        if len(seqs) == 1:
            return seqs[0]
        if not seqs:
            raise DatasetError(f"{path}: not a 7-Scenes folder (no frame-000000.pose.txt-like files, no seq-01/-like "
                               "folders)")
        raise DatasetError(f"{path}: holds {len(seqs)} sequences ({', '.join(p.name for p in seqs)}); "
                           "give one folder, e.g. " + str(seqs[0]))

    def _colour_path(self, k: int) -> Path:
        for ext in ("png", "jpg"):
            p = self.path / f"frame-{k:06d}.color.{ext}"
            if p.is_file():
                return p
        raise DatasetError(f"{self.path}: frame-{k:06d} has a pose but no .color.png/.jpg")

    def _depth_camera(self, width: int, height: int) -> Intrinsics:
        for folder in (self.path, self.path.parent):
            p = folder / "camera-intrinsics.txt"
            if p.is_file():
                return _read_intrinsics_file(p, width, height)
        log.info("%s: no camera-intrinsics.txt; using 7-Scenes' nominal depth camera (f=585)", self.path)
        return NOMINAL_DEPTH_CAMERA.scaled(width, height)

    def _read_pose(self, k: int) -> np.ndarray:
        p = self.path / f"frame-{k:06d}.pose.txt"
        try:
            T = np.loadtxt(p, dtype=float)
        except (OSError, ValueError) as exc:
            raise DatasetError(f"{p}: cannot read a 4x4 pose ({exc})") from None
        if T.shape != (4, 4):
            raise DatasetError(f"{p}: expected a 4x4 camera-to-world matrix, got shape {T.shape}")
        if not np.all(np.isfinite(T)):
            return np.full((4, 4), np.nan)  # a tracking loss: the frame stays, without a pose
        return _nearest_rigid(T, p)

    # --- registration ---

    def _resolve_registration(self, registration) -> DepthColourRegistration:
        if isinstance(registration, DepthColourRegistration):
            return registration
        if isinstance(registration, dict):
            try:
                return DepthColourRegistration.from_dict(registration)
            except (KeyError, TypeError, ValueError) as exc:
                raise DatasetError(f"{self.path}: invalid registration ({exc})") from None
        if registration == "none":
            return DepthColourRegistration(self.depth_intrinsics)
        if registration == "nominal":
            return DepthColourRegistration(NOMINAL_COLOUR_CAMERA.scaled(self.depth_intrinsics.width,
                                                                        self.depth_intrinsics.height))
        if registration not in ("images", "auto", "poses"):
            raise DatasetError(f"{self.path}: registration must be 'nominal', 'images', 'poses', 'none', a "
                               f"DepthColourRegistration or its dict, got {registration!r}")
        poses = "recording" if registration == "poses" else "images"
        cache = self._registration_cache(poses)
        if cache is not None and cache.is_file():
            try:
                return DepthColourRegistration.from_dict(json.loads(cache.read_text()))
            except (OSError, KeyError, TypeError, ValueError):
                log.warning("%s: unreadable cached registration; estimating it again", cache)
        result = self.estimate_registration(poses=poses)
        if cache is not None:
            try:
                cache.parent.mkdir(parents=True, exist_ok=True)
                cache.write_text(json.dumps(result.to_dict(), indent=1))
            except OSError as exc:
                log.warning("cannot cache the registration in %s (%s)", cache, exc)
        return result

    def _registration_cache(self, poses: str) -> Path | None:
        if self.cache_dir is False:
            return None

        base = Path(self.cache_dir) if self.cache_dir else default_cache_dir()
        return base / "registration" / f"7scenes_{self.recording_id}_{poses}_v{_REGISTRATION_VERSION}.json"

    def estimate_registration(self, pairs: int = 24, poses: str = "images") -> DepthColourRegistration:
        """The colour camera estimated from ``pairs`` frame pairs 0.3-0.8 s apart spread over
        the whole recording (see :func:`estimate_registration`); logs what it found. ``poses``:
        how each pair's relative motion is known: ``"images"`` (default) from the depth images
        alone (:func:`~nap3d_graph.datasets.registration.depth_chain`: no pose file is read, so
        a map of the recording reads no ground truth), ``"recording"`` from its pose files."""
        if poses not in ("images", "recording"):
            raise DatasetError(f"{self.path}: registration poses must be 'images' or 'recording', got {poses!r}")
        stamps = self._all_numbers / SEVENSCENES_FPS
        chosen = frame_pairs(stamps, pairs, (0.3, 0.8))
        T_a, T_b = self._pair_poses(chosen) if poses == "images" else (
            self._T_world_depth_all[[i for i, _ in chosen]], self._T_world_depth_all[[j for _, j in chosen]])
        needed = sorted({i for pair in chosen for i in pair})
        raw = {i: self._read_raw(int(self._all_numbers[i])) for i in needed}
        nominal = DepthColourRegistration(NOMINAL_COLOUR_CAMERA.scaled(self.depth_intrinsics.width,
                                                                       self.depth_intrinsics.height))
        result = estimate_registration([raw[i] for i, _ in chosen], [raw[j] for _, j in chosen], T_a, T_b,
                                       self.depth_intrinsics, nominal)
        log.warning("%s: depth is not registered to colour; estimated from %d matched keypoints (poses: %s): %s",
                    self.name, result.matches, poses, result.describe())
        return result

    def _pair_poses(self, chosen: list[tuple[int, int]]) -> tuple[np.ndarray, np.ndarray]:
        """(P, 4, 4) twice: each pair's first depth camera at the identity and its second where
        depth-only ICP over the frames between puts it (NaN where ICP failed: the pair is
        skipped)."""
        T_a = np.repeat(np.eye(4)[None], len(chosen), axis=0)
        T_b = np.full((len(chosen), 4, 4), np.nan)
        for p, (i, j) in enumerate(chosen):
            depths = [self._read_raw_depth(int(k)).astype(np.float32) for k in self._all_numbers[i:j + 1]]
            depths = [np.where(d == DEPTH_MISSING, 0, d) / np.float32(self.depth_units_per_m) for d in depths]
            T_b_a = depth_chain(depths, self.depth_intrinsics)
            if T_b_a is not None:
                T_b[p] = np.linalg.inv(T_b_a)
        log.info("%s: %d of %d registration pairs posed by depth-only ICP", self.name,
                 int(np.isfinite(T_b[:, 0, 0]).sum()), len(chosen))
        return T_a, T_b

    # --- frames ---

    def _select_all(self) -> None:
        self.frame_numbers = self._all_numbers.copy()
        self.timestamps = self.frame_numbers / SEVENSCENES_FPS
        self.depth_timestamps = self.timestamps.copy()
        self.rgb_line_index = self.frame_numbers.copy()
        # The colour camera's pose: T_world_colour = T_world_depth @ T_depth_colour.
        T_depth_colour = np.linalg.inv(self.registration.T_colour_depth)
        self.T_world_cam_gt = self._T_world_depth_all @ T_depth_colour
        self._gt_raw = (self.timestamps.copy(), self.T_world_cam_gt.copy())
        missing = int((~self.has_gt).sum())
        if missing:
            log.warning("%s: %d of %d frames have no finite pose; they are still run, without an error figure",
                        self.name, missing, len(self.timestamps))

    def _select(self, start: int, stop: int) -> None:
        for name in ("frame_numbers", "timestamps", "depth_timestamps", "rgb_line_index", "T_world_cam_gt"):
            setattr(self, name, getattr(self, name)[start:stop])

    @property
    def recording_id(self) -> str:
        """Content fingerprint of the whole recording (first and last frames, first pose)."""
        if self._recording_id is None:
            first, last = int(self._all_numbers[0]), int(self._all_numbers[-1])
            self._recording_id = fingerprint_files([
                self._colour_paths[first], self._colour_paths[last], self.path / f"frame-{first:06d}.depth.png",
                self.path / f"frame-{first:06d}.pose.txt", self.path / f"frame-{last:06d}.pose.txt"])
        return self._recording_id

    def raw_depth(self, index) -> np.ndarray:
        """Frame ``index``'s depth PNG as stored, in the depth camera: (H, W) uint16,
        ``depth_units_per_m`` per metre, 0 or 65535 = missing."""
        return self._read_raw_depth(int(self.frame_numbers[frame_index(index, len(self), self.name)]))

    def _read_raw_depth(self, k: int) -> np.ndarray:
        depth_path = self.path / f"frame-{k:06d}.depth.png"
        raw = cv2.imread(str(depth_path), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise DatasetError(f"{depth_path}: cannot read depth image (missing or corrupt)")
        if raw.dtype != np.uint16 or raw.ndim != 2:
            raise DatasetError(f"{depth_path}: depth must be a single-channel uint16 PNG, got {raw.dtype} "
                               f"with shape {raw.shape}")
        if raw.shape != (self.depth_intrinsics.height, self.depth_intrinsics.width):
            raise DatasetError(f"{depth_path}: depth is {raw.shape[1]}x{raw.shape[0]}, the depth camera "
                               f"{self.depth_intrinsics.width}x{self.depth_intrinsics.height}")
        return raw

    def _read_raw(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Frame number k as stored: RGB (H, W, 3) uint8 and the depth camera's depth, metres."""
        colour_path = self._colour_paths[k]
        bgr = cv2.imread(str(colour_path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise DatasetError(f"{colour_path}: cannot read colour image (missing or corrupt)")
        raw = self._read_raw_depth(k)
        depth_m = np.where(raw == DEPTH_MISSING, 0, raw).astype(np.float32) / np.float32(self.depth_units_per_m)
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), depth_m

    def __len__(self) -> int:
        return len(self.timestamps)

    def __getitem__(self, index) -> RGBDFrame:
        i = frame_index(index, len(self), self.name)
        rgb, depth_m = self._read_raw(int(self.frame_numbers[i]))
        if rgb.shape[:2] != (self.intrinsics.height, self.intrinsics.width):
            raise DatasetError(f"{self._colour_paths[int(self.frame_numbers[i])]}: colour is "
                               f"{rgb.shape[1]}x{rgb.shape[0]}, the colour camera {self.intrinsics.width}x"
                               f"{self.intrinsics.height}")
        depth_colour = register_depth_to_colour(depth_m, self.depth_intrinsics, self.registration)
        t = float(self.timestamps[i])
        return RGBDFrame(rgb, depth_colour, self.intrinsics, t, t)

    def __iter__(self) -> Iterator[RGBDFrame]:
        for i in range(len(self)):
            yield self[i]

    def __repr__(self) -> str:
        return f"SevenScenesSequence({str(self.path)!r}, frames={len(self)})"
