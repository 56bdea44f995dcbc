"""Intel RealSense (D435i / D455) recordings and live cameras as a sequence of RGBD frames.

:class:`RealSenseRecording` reads a ``.bag`` / ``.db3`` file at the sensor level (every frame;
:mod:`.realsense_io`), pairs each colour frame with its depth frame, registers the depth into
the colour camera with the file's intrinsics and depth-to-colour extrinsics
(:func:`~nap3d_graph.camera.warp_depth`: sub-pixel, where ``cv2.registerDepth``'s rounding to
the nearest pixel leaves millimetres of error on slanted surfaces), and gives what :class:`~nap3d_graph.datasets.TumSequence` gives:
``len``, ``seq[i] -> RGBDFrame`` (colour-camera depth in metres), ``timestamps`` (the colour
frames' stamps, seconds, the recording's clock), ``intrinsics``, ``T_world_cam_gt`` (from a
TUM file of poses, or None), plus ``imu`` (accel resampled at the gyro's stamps) and
``imu_config`` (noise, gravity and the camera-IMU extrinsics, which recordings do not store:
from a YAML file, by default ``<recording>.yaml`` beside it, else D435i values).

Pairing: by the frames' own stamps within ``max_difference``; when those pair fewer than half
of the colour frames and the file has every frame's arrival time (librealsense's
``time_of_arrival``), the sensors stamp in clocks of their own (a D435 recorded without global
time) and the frames are paired by arrival instead, within half a frame period.
``pairing_clock`` says which ("sensor" or "arrival"; logged once), ``depth_clock_offset`` (s)
what was added to the depth stamps to put them on the colour clock.

:func:`capture_live` records a connected camera (depth, colour, accel, gyro) to a ``.bag``
for a given time; the run then reads that recording like any other.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from nap3d_graph.camera import Intrinsics, RGBDFrame, warp_depth
from nap3d_graph.conventions import T_to_tum, tum_to_T
from nap3d_graph.errors import DatasetError
from nap3d_graph.motion.imu import ImuConfig
from nap3d_graph.trajectory import read_tum_trajectory

from ..trajectory import interpolate_poses
from .association import GroundTruthLookup, associate
from .frames import parse_frame_range
from .identity import fingerprint_files
from .realsense_io import import_pyrealsense2, read_recording

__all__ = ["RealSenseRecording", "RealSenseConfig", "capture_live", "D435I_T_DEPTH_IMU"]

log = logging.getLogger(__name__)

#: The D435i IMU in its depth (left infrared) camera: librealsense's CAD extrinsics (the IMU
#: samples arrive already rotated into the depth camera's axes, so no rotation).
D435I_T_DEPTH_IMU = np.array([[1.0, 0.0, 0.0, 0.00552], [0.0, 1.0, 0.0, -0.0051], [0.0, 0.0, 1.0, -0.01174],
                              [0.0, 0.0, 0.0, 1.0]])


@dataclass
class RealSenseConfig:
    """What a recording does not store. ``T_depth_imu`` (4, 4): the IMU frame in the depth
    camera's; noise densities as :class:`~nap3d_graph.motion.imu.ImuConfig` (BMI055, as the D435i's
    and D455's); ``max_difference``: how far (s) a depth frame may be from its colour frame;
    ``simulated``: the recording was written by the simulator (``simulate --realsense``)."""

    T_depth_imu: np.ndarray = field(default_factory=lambda: D435I_T_DEPTH_IMU.copy())
    accel_noise_density: float = 2.0e-3
    gyro_noise_density: float = 2.4e-4
    accel_bias_rw: float = 1.0e-4
    gyro_bias_rw: float = 2.0e-6
    gravity: float = 9.81
    max_difference: float = 0.02
    simulated: bool = False  # written by simulate --realsense

    @classmethod
    def load(cls, path) -> "RealSenseConfig":
        """From a YAML file (keys as the fields; ``T_depth_imu`` as ``[tx, ty, tz, qx, qy, qz, qw]``)."""
        import yaml


        path = Path(path)
        try:
            data = yaml.safe_load(path.read_text()) or {}
        except (OSError, yaml.YAMLError) as exc:
            raise DatasetError(f"{path}: not a readable YAML file ({exc})") from None
        if not isinstance(data, dict):
            raise DatasetError(f"{path}: expected a mapping of settings")
        unknown = set(data) - set(cls.__dataclass_fields__)
        if unknown:
            raise DatasetError(f"{path}: unknown settings {sorted(unknown)}")
        if "T_depth_imu" in data:
            pose = np.asarray(data["T_depth_imu"], dtype=float).reshape(-1)
            if pose.shape != (7,):
                raise DatasetError(f"{path}: T_depth_imu needs 7 numbers (tx ty tz qx qy qz qw)")
            data["T_depth_imu"] = tum_to_T(pose)
        return cls(**data)

    def save(self, path) -> Path:
        import yaml


        values = {k: getattr(self, k) for k in self.__dataclass_fields__}
        values["T_depth_imu"] = [round(float(v), 9) for v in T_to_tum(self.T_depth_imu)]
        header = "# nap3d-graph RealSense settings: what a recording does not store\n"
        Path(path).write_text(header + yaml.safe_dump(values, sort_keys=False))
        return Path(path)

    def imu_config(self, T_colour_depth: np.ndarray):
        """The :class:`~nap3d_graph.motion.imu.ImuConfig` of the colour camera (the frames' camera)."""
        return ImuConfig(self.accel_noise_density, self.gyro_noise_density, self.accel_bias_rw, self.gyro_bias_rw,
                         self.gravity, T_cam_imu=np.asarray(T_colour_depth) @ self.T_depth_imu)


class RealSenseRecording(GroundTruthLookup):
    """A RealSense recording as a sequence (see the module docstring).

    path: ``.bag`` / ``.db3``. groundtruth: a TUM file of camera poses (colour camera,
    OpenCV axes) for the recording's frames, or None. frames: ``START:STOP`` as in
    :func:`~nap3d_graph.datasets.frames.parse_frame_range`. config: a
    :class:`RealSenseConfig` (default: ``<path>.yaml`` when it exists, else D435i values).
    Holds the recording's frames in memory (about 1.5 MB per 640x480 pair).
    """

    #: Frames may be read on another thread (a replay reads ahead: nap3d_graph.run.read_ahead).
    reads_concurrently = True

    def __init__(self, path, groundtruth=None, frames: str | None = None, config: RealSenseConfig | None = None):
        self.path = Path(path)
        self.name = self.path.stem
        sidecar = self.path.with_suffix(".yaml")
        self.config = config or (RealSenseConfig.load(sidecar) if sidecar.is_file() else RealSenseConfig())
        raw = read_recording(self.path)
        if raw.colour_intrinsics is None or not len(raw.colour[0]):
            raise DatasetError(f"{self.path}: no colour stream in this recording")
        if raw.depth_intrinsics is None or not len(raw.depth[0]):
            raise DatasetError(f"{self.path}: no depth stream in this recording")
        self.raw = raw
        self.T_colour_depth = raw.T_colour_depth if raw.T_colour_depth is not None else np.eye(4)
        if raw.T_colour_depth is None:
            log.warning("%s: no depth-to-colour extrinsics in the file; taking the cameras as co-located", self.path)
        self.intrinsics = self._intrinsics(raw.colour_intrinsics)
        self.depth_intrinsics = self._intrinsics(raw.depth_intrinsics)
        # The device's depth unit, as the file stores it (a D435: 0.001 m).
        self.depth_units_per_m = 1.0 / float(raw.depth_units)
        self.depth_scale_source = "the recording's depth units"
        self.stereo_baseline_m = raw.stereo_baseline_m  # the depth noise model's baseline (map's bundle)
        self._pair(raw)
        self.imu = self._imu(raw)
        self.imu_config = self.config.imu_config(self.T_colour_depth)
        self.simulated = bool(self.config.simulated)
        self.T_world_cam_gt = None
        self._gt_raw = None
        if groundtruth is not None:
            self._attach_ground_truth(Path(groundtruth))
        self.frame_range = parse_frame_range(frames, len(self.timestamps))
        self._select(*self.frame_range)

    @property
    def recording_id(self) -> str:
        """Content fingerprint of the recording file (the same for any ``frames`` range)."""
        return fingerprint_files([self.path])

    @staticmethod
    def _intrinsics(K):
        if any(abs(c) > 1e-9 for c in K.coeffs) and K.model not in ("none",):
            log.warning("stream distortion model %s %s is ignored (D400 colour and depth streams report none)",
                        K.model, K.coeffs)
        return Intrinsics(K.fx, K.fy, K.ppx, K.ppy, K.width, K.height)

    def _pair(self, raw) -> None:
        """Pair colour with depth frames: by the frames' own (sensor) stamps, or, when those are
        not on one clock, by their arrival on the host (see :meth:`_pair_by_arrival`). Sets
        ``pairing_clock`` ("sensor" or "arrival") and ``depth_clock_offset`` (s, added to the
        depth stamps to put them on the colour stream's clock; 0 when paired by sensor)."""
        c_stamps, d_stamps = raw.colour[0], raw.depth[0]
        tolerance = self.config.max_difference
        pairs = associate(c_stamps, d_stamps, tolerance)
        self.pairing_clock, self.depth_clock_offset = "sensor", 0.0
        # A file whose depth and colour sensors stamp in their own hardware clocks (a D435's
        # recording: colour 360713.5 ms, depth 360815.1 ms for frames 54 ms apart on arrival)
        # pairs few or none of its frames by those stamps; the host's arrival times are one clock.
        if len(pairs) < len(c_stamps) / 2:
            by_arrival = self._pair_by_arrival(raw)
            if by_arrival is not None and len(by_arrival[0]) > len(pairs):
                pairs, tolerance, self.depth_clock_offset = by_arrival
                self.pairing_clock = "arrival"
        if not len(pairs):
            raise DatasetError(f"{self.path}: no depth frame within {self.config.max_difference * 1000:.0f} ms of "
                               "any colour frame (by the frames' own stamps or by their arrival times)")
        if self.pairing_clock == "arrival":
            log.warning("%s: the depth and colour frames' own stamps are not on one clock (each sensor's hardware "
                        "clock: %d of %d colour frames have a depth frame within %.0f ms by them); paired by "
                        "arrival time instead (%d pairs within %.0f ms), depth stamps moved onto the colour clock by "
                        "%+.1f ms", self.path, len(associate(c_stamps, d_stamps, self.config.max_difference)),
                        len(c_stamps), self.config.max_difference * 1000, len(pairs), tolerance * 1000,
                        self.depth_clock_offset * 1000)
        else:
            log.info("%s: depth and colour paired by the frames' own (sensor) stamps", self.path)
        lost = len(c_stamps) - len(pairs)
        if lost:
            log.warning("%s: %d of %d colour frames have no depth frame within %.0f ms and are left out", self.path,
                        lost, len(c_stamps), tolerance * 1000)
        self._colour_index, self._depth_index = pairs[:, 0], pairs[:, 1]
        self.timestamps = c_stamps[self._colour_index]
        self.depth_timestamps = d_stamps[self._depth_index] + self.depth_clock_offset
        self.rgb_line_index = None

    def _pair_by_arrival(self, raw):
        """``(pairs, tolerance, depth_clock_offset)`` pairing by the frames' arrival times, or
        None when the file has no arrival time for every frame.

        Arrival on the host carries the USB transfer's delay and jitter, so the tolerance is
        half the slower stream's frame period (at least ``max_difference``): each colour frame
        gets at most its nearest depth frame. The depth stamps' offset onto the colour clock is
        the difference of the two streams' median (arrival - own stamp): a depth frame stamped
        d arrived about when a colour frame stamped d + offset did."""
        c_arrival, d_arrival = raw.arrival.get("colour"), raw.arrival.get("depth")
        if c_arrival is None or d_arrival is None or len(c_arrival) != len(raw.colour[0]) \
                or len(d_arrival) != len(raw.depth[0]) or not len(c_arrival) or not len(d_arrival) \
                or not (np.all(np.isfinite(c_arrival)) and np.all(np.isfinite(d_arrival))):
            return None
        rates = [raw.fps[k] for k in ("colour", "depth") if raw.fps.get(k, 0) > 0]
        if not rates:  # no nominal rate: from the stamps
            steps = [np.median(np.diff(s)) for s in (raw.colour[0], raw.depth[0]) if len(s) > 1]
            rates = [1.0 / step for step in steps if step > 0]
        tolerance = max(self.config.max_difference, 0.5 / min(rates)) if rates else self.config.max_difference
        pairs = associate(c_arrival, d_arrival, tolerance)
        offset = float(np.median(d_arrival - raw.depth[0]) - np.median(c_arrival - raw.colour[0]))
        return pairs, tolerance, offset

    def _imu(self, raw) -> dict | None:
        (a_t, a_xyz), (g_t, g_xyz) = raw.accel, raw.gyro
        if len(a_t) < 2 or len(g_t) < 2:
            return None
        # The accelerometer and the gyroscope run at their own rates: resample the
        # accelerometer (the slower, smoother one on D400) at the gyroscope's stamps.
        inside = (g_t >= a_t[0]) & (g_t <= a_t[-1])
        accel = np.column_stack([np.interp(g_t[inside], a_t, a_xyz[:, k]) for k in range(3)])
        return {"stamps": g_t[inside], "accel": accel, "gyro": g_xyz[inside].astype(float)}

    def _attach_ground_truth(self, gt_path: Path) -> None:
        if not gt_path.is_file():
            raise DatasetError(f"{gt_path}: no such ground-truth file")
        stamps, T = read_tum_trajectory(gt_path)
        self._gt_raw = (stamps, T)
        self.T_world_cam_gt = interpolate_poses(stamps, T, self.timestamps)
        if not np.any(np.all(np.isfinite(self.T_world_cam_gt), axis=(1, 2))):
            raise DatasetError(f"{gt_path}: its poses cover none of the recording's frames (times "
                               f"{stamps.min():.3f}-{stamps.max():.3f} s, frames {self.timestamps[0]:.3f}-"
                               f"{self.timestamps[-1]:.3f} s)")

    def _select(self, start: int, stop: int) -> None:
        self.timestamps = self.timestamps[start:stop]
        self.depth_timestamps = self.depth_timestamps[start:stop]
        self._colour_index = self._colour_index[start:stop]
        self._depth_index = self._depth_index[start:stop]
        if self.T_world_cam_gt is not None:
            self.T_world_cam_gt = self.T_world_cam_gt[start:stop]

    def __len__(self) -> int:
        return len(self.timestamps)

    def raw_depth(self, i: int) -> np.ndarray:
        """Frame i's depth as the device stored it: (H, W) uint16 in the depth camera,
        ``depth_units_per_m`` per metre, 0 = missing."""
        return np.asarray(self.raw.depth[2][self._depth_index[i]])

    def registered_depth(self, i: int) -> np.ndarray:
        """Frame i's depth (H, W) float32 metres in the colour camera (0 where none)."""
        depth_m = self.raw.depth[2][self._depth_index[i]].astype(np.float32) * np.float32(self.raw.depth_units)
        return warp_depth(depth_m, self.depth_intrinsics, self.T_colour_depth, dst_intrinsics=self.intrinsics,
                          iterations=3)

    def __getitem__(self, index):
        import operator


        i = operator.index(index)
        if i < 0:
            i += len(self)
        if not 0 <= i < len(self):
            raise IndexError(f"frame index {index} out of range for {len(self)} frames of {self.name}")
        rgb = self.raw.colour[2][self._colour_index[i]]
        return RGBDFrame(rgb, self.registered_depth(i), self.intrinsics, float(self.timestamps[i]),
                         float(self.depth_timestamps[i]))

    def __iter__(self):
        for i in range(len(self)):
            yield self[i]

    def __repr__(self) -> str:
        return (f"RealSenseRecording({str(self.path)!r}, frames={len(self)}, imu={self.imu is not None}, "
                f"ground_truth={self.T_world_cam_gt is not None})")


def capture_live(out_path, seconds: float, width: int = 640, height: int = 480, fps: int = 30) -> Path:
    """Record ``seconds`` of a connected camera (depth, colour, accel, gyro) to ``out_path``
    (``.bag``); a clear :class:`DatasetError` when no camera is connected."""
    import time


    rs = import_pyrealsense2()
    if len(rs.context().query_devices()) == 0:
        raise DatasetError("no RealSense camera connected (check the USB 3 cable, or read a recording instead)")
    out = Path(out_path)
    if out.suffix.lower() != ".bag":
        raise DatasetError(f"{out}: a live capture is recorded as a .bag file")
    config = rs.config()
    config.enable_stream(rs.stream.depth, width, height, rs.format.z16, fps)
    config.enable_stream(rs.stream.color, width, height, rs.format.rgb8, fps)
    config.enable_stream(rs.stream.accel)
    config.enable_stream(rs.stream.gyro)
    config.enable_record_to_file(str(out))
    pipeline = rs.pipeline()
    try:
        pipeline.start(config)
    except RuntimeError as exc:
        raise DatasetError(f"the RealSense camera cannot stream depth, colour and IMU ({exc})") from None
    try:
        started = time.monotonic()
        while time.monotonic() - started < seconds:
            pipeline.wait_for_frames()
    finally:
        pipeline.stop()
    return out
