"""RealSense files at the sensor level: read every frame of a recording, write one offline.

pyrealsense2 is imported here and only here, lazily: it needs the system's libusb-1.0, and a
missing library is one clear :class:`DatasetError`, not a traceback at import.

Reading (:func:`read_recording`) opens the file's sensors directly with real time off:
``rs.pipeline`` playback drops and duplicates frames, the sensor level returns every one.
Playback is paused while the sensors start (a sensor started late loses its first frames
without a word) and every frame is ``keep()``-ed (holding frames without it exhausts the
frame pool and the file silently stops early).

Writing (:class:`RecordingWriter`) goes through a ``software_device`` and ``rs.recorder``
(pyrealsense2 2.59 writes rosbag2 ``.db3`` only): depth z16 with its depth units, colour
rgb8, accel and gyro as ``motion_xyz32f``, the depth-to-colour extrinsics; every frame is
injected in timestamp order across streams. Not stored by the format, whatever is injected:
the IMU's extrinsics (recordings keep extrinsics of video streams only).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from nap3d_graph.errors import DatasetError

__all__ = ["import_pyrealsense2", "RawRecording", "read_recording", "RecordingWriter", "StreamIntrinsics"]

LIBUSB_HINT = "install the system library libusb-1.0 (Debian/Ubuntu: apt-get install libusb-1.0-0)"


def import_pyrealsense2():
    """``pyrealsense2``, or a one-line :class:`DatasetError` that says what to install."""
    try:
        import pyrealsense2 as rs
    except ImportError as exc:
        if "libusb" in str(exc):
            raise DatasetError(f"pyrealsense2 cannot load: {LIBUSB_HINT}") from None
        raise DatasetError(f"pyrealsense2 is not installed ({exc}); pip install pyrealsense2") from None
    return rs


@dataclass(frozen=True)
class StreamIntrinsics:
    """A video stream's pinhole model as RealSense reports it (pixels; ``coeffs`` and
    ``model`` as librealsense names them)."""

    width: int
    height: int
    fx: float
    fy: float
    ppx: float
    ppy: float
    model: str = "none"
    coeffs: tuple = (0.0, 0.0, 0.0, 0.0, 0.0)


@dataclass
class RawRecording:
    """Every frame of a recording, sorted by time (stamps in seconds, the recording's clock).

    depth: (stamps (D,), frame numbers (D,), list of (H, W) uint16); colour: the same with
    (H, W, 3) uint8 RGB; accel / gyro: (stamps (M,), (M, 3) float32 samples);
    depth_units: metres per depth unit; T_colour_depth (4, 4) or None; stereo_baseline_m: the
    depth camera's stereo baseline (m) where the file records it.
    arrival: ``{"depth": (D,), "colour": (C,)}`` each frame's arrival on the host (librealsense's
    ``time_of_arrival``, seconds, the recording computer's system clock; NaN where the file has
    none), in the order of the stamps above: the one clock the streams share when their own
    stamps are each sensor's hardware clock. fps: ``{"depth": ..., "colour": ...}`` nominal rates.
    """

    depth: tuple
    colour: tuple
    accel: tuple
    gyro: tuple
    depth_intrinsics: StreamIntrinsics | None
    colour_intrinsics: StreamIntrinsics | None
    depth_units: float
    T_colour_depth: np.ndarray | None
    info: dict = field(default_factory=dict)
    arrival: dict = field(default_factory=dict)
    fps: dict = field(default_factory=dict)
    stereo_baseline_m: float | None = None


def _intrinsics(profile) -> StreamIntrinsics:
    i = profile.as_video_stream_profile().get_intrinsics()
    return StreamIntrinsics(i.width, i.height, i.fx, i.fy, i.ppx, i.ppy, str(i.model).split(".")[-1],
                            tuple(float(c) for c in i.coeffs))


def _T_from_extrinsics(e) -> np.ndarray:
    """librealsense extrinsics ``p_to = R p_from + t`` (rotation column-major) as a 4x4."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(e.rotation, dtype=float).reshape(3, 3).T
    T[:3, 3] = np.asarray(e.translation, dtype=float)
    return T


def _open(rs, path: Path):
    if not path.is_file():
        raise DatasetError(f"{path}: no such recording")
    if path.suffix.lower() not in (".bag", ".db3"):
        raise DatasetError(f"{path}: a RealSense recording is a .bag or .db3 file")
    try:
        device = rs.context().load_device(str(path))
    except RuntimeError as exc:
        raise DatasetError(f"{path}: not a readable RealSense recording ({str(exc).splitlines()[0]})") from None
    return device


def read_recording(path, timeout_s: float = 600.0) -> RawRecording:
    """Every depth, colour, accel and gyro frame of a ``.bag`` / ``.db3`` recording."""
    rs = import_pyrealsense2()
    path = Path(path)
    device = _open(rs, path)
    playback = device.as_playback()
    playback.set_real_time(False)
    done = threading.Event()
    playback.set_status_changed_callback(lambda status: done.set() if status == rs.playback_status.stopped else None)
    frames, lock = [], threading.Lock()

    def keep(frame) -> None:
        frame.keep()  # without it the frame pool runs dry and playback stops early, silently
        with lock:
            frames.append(frame)

    sensors = device.query_sensors()
    for sensor in sensors:
        sensor.open(sensor.get_stream_profiles())
    playback.pause()  # start every sensor before the first frame plays
    for sensor in sensors:
        sensor.start(keep)
    playback.resume()
    finished = done.wait(timeout_s)
    for sensor in sensors:
        sensor.stop()
    for sensor in sensors:
        sensor.close()
    if not finished:
        raise DatasetError(f"{path}: playback did not finish within {timeout_s:.0f} s")
    return _collect(rs, device, frames, path)


def _arrival_s(rs, frame) -> float:
    """A frame's ``time_of_arrival`` metadata (host system clock) in seconds, NaN if absent."""
    key = rs.frame_metadata_value.time_of_arrival
    try:
        if frame.supports_frame_metadata(key):
            return float(frame.get_frame_metadata(key)) / 1000.0
    except RuntimeError:
        pass
    return float("nan")


def _collect(rs, device, frames, path: Path) -> RawRecording:
    streams: dict = {"depth": [], "colour": [], "accel": [], "gyro": []}
    names = {rs.stream.depth: "depth", rs.stream.color: "colour", rs.stream.accel: "accel", rs.stream.gyro: "gyro"}
    profiles = {}
    for frame in frames:
        profile = frame.get_profile()
        kind = names.get(profile.stream_type())
        if kind is None:
            continue  # infrared and other streams: not used
        profiles.setdefault(kind, profile)
        stamp = frame.get_timestamp() / 1000.0
        if kind in ("accel", "gyro"):
            d = frame.as_motion_frame().get_motion_data()
            streams[kind].append((stamp, frame.get_frame_number(), np.array([d.x, d.y, d.z], dtype=np.float32)))
        else:
            streams[kind].append((stamp, frame.get_frame_number(), np.asanyarray(frame.get_data()).copy(),
                                  _arrival_s(rs, frame)))
    out, arrival = {}, {}
    for kind, items in streams.items():
        items.sort(key=lambda item: item[0])
        stamps = np.array([item[0] for item in items], dtype=float)
        numbers = np.array([item[1] for item in items], dtype=np.int64)
        data = [item[2] for item in items]
        if kind in ("depth", "colour"):
            out[kind] = (stamps, numbers, data)
            arrival[kind] = np.array([item[3] for item in items], dtype=float)
        else:
            out[kind] = (stamps, np.array(data, dtype=np.float32).reshape(-1, 3))
    fps = {}
    for kind in ("depth", "colour"):
        if kind in profiles:
            try:
                fps[kind] = float(profiles[kind].fps())
            except RuntimeError:
                pass
    T_colour_depth = None
    if "depth" in profiles and "colour" in profiles:
        try:
            T_colour_depth = _T_from_extrinsics(profiles["depth"].get_extrinsics_to(profiles["colour"]))
        except RuntimeError:
            T_colour_depth = None
    try:
        depth_units = float(device.first_depth_sensor().get_depth_scale())
    except RuntimeError:
        depth_units = 0.001
    baseline_m = _stereo_baseline_m(rs, device)
    info = {}
    for key in ("name", "serial_number", "firmware_version"):
        try:
            info[key] = device.get_info(getattr(rs.camera_info, key))
        except RuntimeError:
            pass
    return RawRecording(out["depth"], out["colour"], out["accel"], out["gyro"],
                        _intrinsics(profiles["depth"]) if "depth" in profiles else None,
                        _intrinsics(profiles["colour"]) if "colour" in profiles else None,
                        depth_units, T_colour_depth, info, arrival, fps, baseline_m)


def _stereo_baseline_m(rs, device) -> float | None:
    """The depth camera's stereo baseline (metres) as the file records it (librealsense's
    "Stereo Baseline" option, in millimetres: a D435's ~50 mm), or None where it has none."""
    try:
        sensor = device.first_depth_sensor()
        if not sensor.supports(rs.option.stereo_baseline):
            return None
        baseline_mm = float(sensor.get_option(rs.option.stereo_baseline))
    except (RuntimeError, AttributeError):
        return None
    return baseline_mm / 1000.0 if baseline_mm > 0 else None


def _rs_intrinsics(rs, K: StreamIntrinsics):
    intr = rs.intrinsics()
    intr.width, intr.height, intr.fx, intr.fy, intr.ppx, intr.ppy = K.width, K.height, K.fx, K.fy, K.ppx, K.ppy
    intr.model = rs.distortion.none
    intr.coeffs = [0.0] * 5
    return intr


class RecordingWriter:
    """Write a ``.db3`` recording offline (no camera): ``add_*`` frames in any order, then
    :meth:`close` injects them in timestamp order and finishes the file.

    depth_intrinsics / colour_intrinsics: :class:`StreamIntrinsics` (no distortion);
    depth_units: metres per depth unit; T_colour_depth: (4, 4) depth camera -> colour camera;
    fps: nominal video rate; imu_hz: nominal accel/gyro rate (0: no IMU streams).
    """

    def __init__(self, path, depth_intrinsics: StreamIntrinsics, colour_intrinsics: StreamIntrinsics,
                 depth_units: float = 0.001, T_colour_depth=None, fps: int = 15, imu_hz: int = 200,
                 name: str = "nap3d-graph simulated D435i"):
        self.rs = rs = import_pyrealsense2()
        self.path = Path(path)
        if self.path.suffix.lower() != ".db3":
            raise DatasetError(f"{self.path}: pyrealsense2 writes .db3 recordings only; name the file *.db3")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.depth_units = float(depth_units)
        self.events: list = []
        self.device = rs.software_device()
        self.device.register_info(rs.camera_info.name, name)
        self.device.register_info(rs.camera_info.serial_number, "0")
        stereo = self.device.add_sensor("Stereo Module")
        stereo.add_read_only_option(rs.option.depth_units, self.depth_units)  # the file's depth scale
        rgb = self.device.add_sensor("RGB Camera")
        self.sensors = {"depth": stereo, "colour": rgb}
        self.profiles = {"depth": self._video(stereo, rs.stream.depth, 0, depth_intrinsics, fps, 2, rs.format.z16),
                         "colour": self._video(rgb, rs.stream.color, 1, colour_intrinsics, fps, 3, rs.format.rgb8)}
        if imu_hz:
            motion = self.device.add_sensor("Motion Module")
            for uid, (kind, stream) in enumerate((("accel", rs.stream.accel), ("gyro", rs.stream.gyro)), start=2):
                ms = rs.motion_stream()
                ms.type, ms.index, ms.uid, ms.fps, ms.fmt = stream, 0, uid, imu_hz, rs.format.motion_xyz32f
                ms.intrinsics = rs.motion_device_intrinsic()
                self.profiles[kind] = motion.add_motion_stream(ms, True)
                self.sensors[kind] = motion
        T = np.eye(4) if T_colour_depth is None else np.asarray(T_colour_depth, dtype=float)
        for a, b, T_ab in (("depth", "colour", T), ("colour", "depth", np.linalg.inv(T))):
            e = rs.extrinsics()
            e.rotation = T_ab[:3, :3].T.reshape(-1).tolist()  # column-major, as librealsense stores it
            e.translation = T_ab[:3, 3].tolist()
            self.profiles[a].register_extrinsics_to(self.profiles[b], e)

    def _video(self, sensor, stream, uid, K: StreamIntrinsics, fps, bpp, fmt):
        vs = self.rs.video_stream()
        vs.type, vs.index, vs.uid, vs.width, vs.height = stream, 0, uid, K.width, K.height
        vs.fps, vs.bpp, vs.fmt, vs.intrinsics = fps, bpp, fmt, _rs_intrinsics(self.rs, K)
        return sensor.add_video_stream(vs, True)

    def add_depth(self, stamp_s: float, depth_units: np.ndarray) -> None:
        """A depth image (H, W) uint16 in depth units."""
        self.events.append((float(stamp_s), 0, "depth", np.ascontiguousarray(depth_units, dtype=np.uint16)))

    def add_colour(self, stamp_s: float, rgb: np.ndarray) -> None:
        """A colour image (H, W, 3) uint8 RGB."""
        self.events.append((float(stamp_s), 1, "colour", np.ascontiguousarray(rgb, dtype=np.uint8)))

    def add_imu(self, stamps_s, accel, gyro) -> None:
        """IMU samples: stamps (M,), accel (M, 3) m/s^2, gyro (M, 3) rad/s, in the IMU frame."""
        for t, a, g in zip(np.asarray(stamps_s, float), np.asarray(accel, float), np.asarray(gyro, float)):
            self.events.append((float(t), 2, "accel", a))
            self.events.append((float(t), 3, "gyro", g))

    def close(self) -> Path:
        """Inject every frame in timestamp order and finish the file; returns its path."""
        rs = self.rs
        recorder = rs.recorder(str(self.path), self.device)
        sensors = list({id(s): s for s in self.sensors.values()}.values())
        for sensor in sensors:
            sensor.open([p for k, p in self.profiles.items() if self.sensors[k] is sensor])
            sensor.start(lambda frame: None)  # a stopped sensor drops injected frames
        counts: dict = {}
        for stamp, _, kind, data in sorted(self.events, key=lambda e: (e[0], e[1])):
            number = counts[kind] = counts.get(kind, 0) + 1
            if kind in ("accel", "gyro"):
                self._inject_motion(kind, stamp, number, data)
            else:
                self._inject_video(kind, stamp, number, data)
        for sensor in sensors:
            sensor.stop()
            sensor.close()
        del recorder  # the file is complete only once the recorder is gone
        self.events = []
        return self.path

    def _inject_video(self, kind, stamp, number, data) -> None:
        rs = self.rs
        frame = rs.software_video_frame()
        frame.pixels = data
        frame.bpp = 2 if kind == "depth" else 3
        frame.stride = data.shape[1] * frame.bpp
        frame.timestamp = stamp * 1000.0
        frame.domain = rs.timestamp_domain.hardware_clock
        frame.frame_number = number
        frame.profile = self.profiles[kind].as_video_stream_profile()
        if kind == "depth":
            frame.depth_units = self.depth_units
        self.sensors[kind].on_video_frame(frame)

    def _inject_motion(self, kind, stamp, number, xyz) -> None:
        rs = self.rs
        frame = rs.software_motion_frame()
        v = rs.vector()
        v.x, v.y, v.z = (float(c) for c in xyz)
        frame.data = v
        frame.timestamp = stamp * 1000.0
        frame.domain = rs.timestamp_domain.hardware_clock
        frame.frame_number = number
        frame.profile = self.profiles[kind].as_motion_stream_profile()
        self.sensors[kind].on_motion_frame(frame)
