"""ROS bags (ROS 1 ``.bag``; ROS 2 folders of ``.db3`` or ``.mcap``) as a sequence of RGBD frames.

Read with the pure-Python ``rosbags`` package: no ROS install. What is read:

- colour: ``sensor_msgs/Image`` (rgb8, bgr8, rgba8, bgra8, mono8) or ``CompressedImage``;
- depth: ``sensor_msgs/Image`` 16UC1 (millimetres) or 32FC1 (metres), or 16UC1
  ``compressedDepth``; depth in another optical frame than colour (with its own
  ``CameraInfo`` and a tf between the two) is warped into the colour camera;
- ``sensor_msgs/CameraInfo`` of the colour camera (intrinsics; plumb_bob or
  rational_polynomial distortion, which the colour image is undistorted by, as TUM's
  reader does);
- ``sensor_msgs/Imu`` (with its extrinsics in the camera from tf when tf connects them);
- ground truth from ``/tf`` (the colour optical frame in the root of its tf tree, or frames
  named with ``--topics world_frame=...,camera_frame=...``) or from a pose topic
  (``PoseStamped``, ``PoseWithCovarianceStamped``, ``TransformStamped``, ``Odometry``).

Topics are found by type when the bag has one of each (TUM's bags: ``/camera/rgb/image_color``,
``/camera/depth/image``, ``/camera/rgb/camera_info``, ``/imu``, ``/tf``), else chosen with
:class:`BagTopics` (the CLI's ``--topics``). Colour and depth are paired by their header stamps
with TUM's association (:func:`~nap3d_graph.datasets.association.pair_streams`).

Streaming: opening a bag reads its messages once and keeps only stamps, the IMU, tf and the
camera info; a frame's images are read when the frame is asked for, by seeking to its
message's time in the bag, so a bag larger than memory is fine.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from nap3d_graph.camera import CameraError, Intrinsics, RGBDFrame, warp_depth
from nap3d_graph.errors import DatasetError
from nap3d_graph.motion.imu import ImuConfig

from ..trajectory import interpolate_poses
from .association import GroundTruthLookup, pair_streams
from .frames import frame_index, parse_frame_range
from .identity import fingerprint_files
from .rosbag_msgs import camera_info_arrays, decode_colour, decode_depth_m, pose_to_T, stamp_s, transform_to_T
from .tf_tree import TfTree

__all__ = ["RosbagSequence", "BagTopics", "is_rosbag", "bag_topics"]

log = logging.getLogger(__name__)

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
INFO_TYPE = "sensor_msgs/msg/CameraInfo"
IMU_TYPE = "sensor_msgs/msg/Imu"
TF_TYPES = ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")
POSE_TYPES = ("geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/PoseWithCovarianceStamped",
              "geometry_msgs/msg/TransformStamped", "nav_msgs/msg/Odometry")


@dataclass
class BagTopics:
    """Which topics (and tf frames) a bag's frames come from; ``None``: found by type.

    ``gt``: ``/tf`` (the default when the bag has it), a pose topic, or ``none``.
    ``world_frame`` / ``camera_frame``: the tf frames of the ground truth (default: the root
    of the tf tree and the colour images' ``frame_id``).
    """

    rgb: str | None = None
    depth: str | None = None
    camera_info: str | None = None
    depth_info: str | None = None
    imu: str | None = None
    gt: str | None = None
    world_frame: str | None = None
    camera_frame: str | None = None

    @classmethod
    def parse(cls, text: str | None) -> "BagTopics":
        """From ``key=value`` pairs separated by commas: ``rgb=/cam/color,depth=/cam/depth``."""
        if not text:
            return cls()
        known = [f.name for f in fields(cls)]
        values = {}
        for item in text.split(","):
            key, sep, value = item.partition("=")
            key = key.strip().replace("-", "_")
            if not sep or not value.strip():
                raise DatasetError(f"`topics={text}`: expected KEY=TOPIC pairs separated by commas, got {item!r}")
            if key not in known:
                raise DatasetError(f"`topics`: unknown key {key!r} (known: {', '.join(known)})")
            values[key] = value.strip()
        return cls(**values)


def is_rosbag(path) -> bool:
    """A ROS 2 bag folder (``metadata.yaml``), or a ROS 1 ``.bag`` that is not a RealSense
    recording (librealsense writes ROS 1 bags too, with ``/device_0/...`` topics)."""
    path = Path(path)
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    if path.suffix.lower() in (".db3", ".mcap") and (path.parent / "metadata.yaml").is_file():
        return True
    if path.suffix.lower() != ".bag" or not path.is_file():
        return False
    try:
        topics = bag_topics(path)
    except DatasetError:
        return False
    return not any(t.startswith("/device_0/") for t in topics)


def _bag_paths(path: Path) -> list[Path]:
    """What rosbags opens: the .bag file, or the ROS 2 folder (given it or one of its files)."""
    if not path.exists():
        raise DatasetError(f"{path}: no such bag file or folder")
    if path.is_file() and path.suffix.lower() in (".db3", ".mcap"):
        if not (path.parent / "metadata.yaml").is_file():
            raise DatasetError(f"{path}: a ROS 2 storage file without its folder's metadata.yaml (give the bag folder)")
        return [path.parent]
    if path.is_dir() and not (path / "metadata.yaml").is_file():
        raise DatasetError(f"{path}: not a ROS 2 bag folder (no metadata.yaml)")
    if path.is_file() and path.suffix.lower() != ".bag":
        raise DatasetError(f"{path}: not a ROS bag (a ROS 1 .bag file or a ROS 2 bag folder)")
    return [path]


def _open_reader(path: Path):
    """An open ``rosbags.highlevel.AnyReader``; a one-line DatasetError when it cannot be."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    paths = _bag_paths(path)
    try:
        reader = AnyReader(paths, default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except Exception as exc:  # rosbags raises its own error per format; all mean "unreadable"
        raise DatasetError(f"{path}: not a readable ROS bag, or a truncated one ({_first_line(exc)})") from None
    return reader


def _first_line(exc: Exception) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


def bag_topics(path) -> dict[str, str]:
    """``{topic: message type}`` of a bag."""
    reader = _open_reader(Path(path))
    try:
        return {c.topic: c.msgtype for c in reader.connections}
    finally:
        reader.close()


def _listing(topics: dict[str, str]) -> str:
    return ", ".join(f"{t} [{m}]" for t, m in sorted(topics.items())) or "no topics"


def _namespace(topic: str) -> str:
    return topic.rsplit("/", 1)[0]


def choose_topics(path, topics: dict[str, str], given: BagTopics) -> BagTopics:
    """The topics to read: the given ones (checked), the rest found by type and name."""
    chosen = BagTopics(**{f.name: getattr(given, f.name) for f in fields(BagTopics)})
    for key in ("rgb", "depth", "camera_info", "depth_info", "imu"):
        topic = getattr(given, key)
        if topic is not None and topic not in topics:
            raise DatasetError(f"{path}: `topics={key}={topic}`: no such topic (the bag has: {_listing(topics)})")
    images = [t for t, m in topics.items() if m in IMAGE_TYPES]
    if chosen.depth is None:
        chosen.depth = _one(path, [t for t in images if "depth" in t.lower() and t != chosen.rgb], "depth image",
                            "depth", topics)
    if chosen.rgb is None:
        colour = [t for t in images if t != chosen.depth and "depth" not in t.lower()]
        named = [t for t in colour if any(w in t.lower() for w in ("rgb", "color", "colour"))]
        chosen.rgb = _one(path, named if len(colour) > 1 and named else colour, "colour image", "rgb", topics)
    infos = [t for t, m in topics.items() if m == INFO_TYPE]
    if chosen.camera_info is None:
        same = [t for t in infos if _namespace(t) == _namespace(chosen.rgb)]
        chosen.camera_info = _one(path, same or [t for t in infos if "depth" not in t.lower()], "colour camera info",
                                  "camera_info", topics)
    if chosen.depth_info is None:
        chosen.depth_info = next((t for t in infos if _namespace(t) == _namespace(chosen.depth)), None)
    if chosen.imu is None:
        imus = [t for t, m in topics.items() if m == IMU_TYPE]
        chosen.imu = imus[0] if len(imus) == 1 else None
        if len(imus) > 1:
            log.warning("%s: several IMU topics (%s): none read; choose one with --topics imu=TOPIC", path, imus)
    if chosen.gt is None:
        if any(m in TF_TYPES for m in topics.values()):
            chosen.gt = "/tf"
        else:
            poses = [t for t, m in topics.items() if m in POSE_TYPES]
            chosen.gt = poses[0] if len(poses) == 1 else None
    elif chosen.gt not in ("none", "/tf") and chosen.gt not in topics:
        raise DatasetError(f"{path}: `topics=gt={chosen.gt}`: no such topic (the bag has: {_listing(topics)})")
    return chosen


def _one(path, candidates: list[str], what: str, key: str, topics: dict[str, str]) -> str:
    if len(candidates) == 1:
        return candidates[0]
    if not candidates:
        raise DatasetError(f"{path}: no {what} topic (the bag has: {_listing(topics)})")
    raise DatasetError(f"{path}: several {what} topics ({', '.join(sorted(candidates))}): choose one with "
                       f"`topics={key}=TOPIC`")


@dataclass
class _Stream:
    """One image topic's messages: header stamps (s), bag times (ns) and frame id."""

    stamps: list
    log_ns: list
    frame_id: str = ""
    first: object = None


class RosbagSequence(GroundTruthLookup):
    """A ROS bag as a sequence (see the module docstring).

    path: a ROS 1 ``.bag``, a ROS 2 bag folder (or a ``.db3`` / ``.mcap`` file in one).
    topics: :class:`BagTopics` or its ``key=value`` text. frames: ``START:STOP`` as in
    :func:`~nap3d_graph.datasets.frames.parse_frame_range`. max_difference: how far (s) a
    depth image may be from its colour image.

    Gives what :class:`~nap3d_graph.datasets.TumSequence` gives: ``len``, ``seq[i] ->
    RGBDFrame``, ``timestamps`` / ``depth_timestamps`` (header stamps, s), ``intrinsics``,
    ``T_world_cam_gt`` (or None), ``has_gt``, ``ground_truth_at``, ``frame_range``,
    ``recording_id``; and ``imu`` (dict of ``stamps``, ``accel``, ``gyro`` in the IMU frame,
    or None) with ``imu_config``, ``topics`` (the chosen :class:`BagTopics`), ``world_frame``.
    """

    def __init__(self, path, topics: BagTopics | str | None = None, frames: str | None = None,
                 max_difference: float = 0.02, undistort: bool = True):
        self.path = Path(path)
        self.name = self.path.stem if self.path.is_file() else self.path.name
        self.max_difference = float(max_difference)
        given = topics if isinstance(topics, BagTopics) else BagTopics.parse(topics)
        self._lock = threading.Lock()
        self._reader = _open_reader(self.path)
        try:
            available = {c.topic: c.msgtype for c in self._reader.connections}
            self.topics = choose_topics(self.path, available, given)
            self._connections = {c.topic: c for c in self._reader.connections}
            self._index(available)
        except BaseException:
            self.close()
            raise
        self.intrinsics_source = "camera_info"
        self._camera(undistort)
        self._pair()
        self.T_world_cam_gt, self._gt_raw, self.world_frame = None, None, None
        self._attach_ground_truth()
        self._attach_imu()
        self.frame_range = parse_frame_range(frames, len(self.timestamps))
        self._select(*self.frame_range)

    # --- reading the bag once -----------------------------------------------------------

    def _index(self, available: dict[str, str]) -> None:
        """One pass over the bag: image stamps, camera info, IMU samples, tf and poses."""
        t = self.topics
        self._rgb, self._depth = _Stream([], []), _Stream([], [])
        self._info, self._depth_info = None, None
        self._imu_rows, self._imu_frame, self._gyro_missing = [], "", False
        self._tf, self._poses = TfTree(), []
        # tf is read whatever the ground truth: it also places the depth camera and the IMU.
        wanted = {t.rgb, t.depth, t.camera_info, t.depth_info, t.imu} | {
            topic for topic, m in available.items() if m in TF_TYPES}
        if t.gt not in (None, "none", "/tf"):
            wanted.add(t.gt)
        connections = [c for c in self._reader.connections if c.topic in wanted]
        try:
            for connection, log_ns, raw in self._reader.messages(connections=connections):
                self._note(connection, log_ns, self._reader.deserialize(raw, connection.msgtype))
        except DatasetError:
            raise
        except Exception as exc:  # a chunk or record cut short: rosbags' own errors
            raise DatasetError(f"{self.path}: the bag cannot be read to its end, truncated or corrupt "
                               f"({_first_line(exc)})") from None
        for stream, topic in ((self._rgb, t.rgb), (self._depth, t.depth)):
            if not stream.stamps:
                raise DatasetError(f"{self.path}: no messages on {topic} (the bag has: {_listing(available)})")
            order = np.diff(stream.stamps)
            if np.any(order <= 0):
                k = int(np.flatnonzero(order <= 0)[0]) + 1
                raise DatasetError(f"{self.path}: {topic}'s header stamps are out of order at message {k} "
                                   f"({stream.stamps[k - 1]:.6f} then {stream.stamps[k]:.6f} s)")
        if self._info is None:
            raise DatasetError(f"{self.path}: no camera info on {t.camera_info}: the intrinsics are unknown")

    def _note(self, connection, log_ns: int, msg) -> None:
        topic, t = connection.topic, self.topics
        if topic in (t.rgb, t.depth):
            stream = self._rgb if topic == t.rgb else self._depth
            if stream.first is None:  # check the encoding now: one line before any work
                stream.frame_id = str(msg.header.frame_id).lstrip("/")
                stream.first = (decode_colour if topic == t.rgb else decode_depth_m)(msg, f"{self.path}: {topic}").shape[:2]
            stream.stamps.append(stamp_s(msg.header.stamp))
            stream.log_ns.append(int(log_ns))
        elif topic == t.camera_info and self._info is None:
            self._info = msg
        elif topic == t.depth_info and self._depth_info is None:
            self._depth_info = msg
        elif topic == t.imu:
            self._imu_frame = str(msg.header.frame_id)
            # sensor_msgs/Imu: a covariance starting with -1 means "this quantity is not measured"
            # (the Kinect's /imu in TUM's bags is an accelerometer alone).
            self._gyro_missing |= float(msg.angular_velocity_covariance[0]) == -1.0
            a, w = msg.linear_acceleration, msg.angular_velocity
            self._imu_rows.append((stamp_s(msg.header.stamp), a.x, a.y, a.z, w.x, w.y, w.z))
        elif connection.msgtype in TF_TYPES:
            static = topic.endswith("tf_static")
            for tf in msg.transforms:
                self._tf.add(stamp_s(tf.header.stamp), str(tf.header.frame_id), str(tf.child_frame_id),
                             transform_to_T(tf.transform), static=static)
        elif topic == t.gt:
            T, parent, child = pose_to_T(msg)
            self._poses.append((stamp_s(msg.header.stamp), T, parent, child))

    # --- camera and pairing -----------------------------------------------------------------

    def _camera(self, undistort: bool) -> None:
        K, D, model, width, height = camera_info_arrays(self._info)
        if self._rgb.first != (height, width):
            raise DatasetError(f"{self.path}: {self.topics.rgb} images are {self._rgb.first[1]}x{self._rgb.first[0]} "
                               f"but {self.topics.camera_info} says {width}x{height}")
        if any(D) and model not in ("plumb_bob", "rational_polynomial"):
            raise DatasetError(f"{self.path}: distortion model {model!r} of {self.topics.camera_info} is not read "
                               "(plumb_bob, rational_polynomial)")
        try:
            self.raw_intrinsics = Intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], width, height,
                                             D if any(D) else ())
        except CameraError as exc:
            raise DatasetError(f"{self.path}: {self.topics.camera_info}: {exc}") from None
        self.undistort = bool(undistort) and any(D)
        self.intrinsics = self.raw_intrinsics.without_distortion() if self.undistort or not any(D) \
            else self.raw_intrinsics
        self._maps = self.raw_intrinsics.undistortion_maps() if self.undistort else None
        self._depth_warp = self._depth_registration()

    def _depth_registration(self):
        """``(depth intrinsics, T_colour_depth)`` when depth must be warped into the colour
        camera, else None (depth already registered: the same frame, the colour camera's
        intrinsics, or no tf between the two frames)."""
        colour, depth = self._rgb.frame_id, self._depth.frame_id
        # A driver that registers depth to colour publishes the colour camera's intrinsics with
        # it (OpenNI's depth_registered, RealSense's aligned_depth_to_color), whatever frame id
        # it stamps: same camera matrix and size means registered, even across frame ids.
        same_camera = self._depth_info is not None and np.allclose(
            camera_info_arrays(self._depth_info)[0], camera_info_arrays(self._info)[0], atol=0.5) \
            and self._depth.first == self._rgb.first
        if depth == colour or not depth or self._depth_info is None or same_camera or depth not in self._tf.frames \
                or colour not in self._tf.frames:
            if self._depth.first != self._rgb.first:
                raise DatasetError(f"{self.path}: depth images are {self._depth.first[1]}x{self._depth.first[0]}, colour "
                                   f"{self._rgb.first[1]}x{self._rgb.first[0]}, and no depth camera info with a tf "
                                   "between their frames to register them")
            if depth and depth != colour and same_camera:
                log.info("%s: depth (frame %r) has the colour camera's intrinsics: taken as registered to colour",
                         self.path, depth)
            elif depth and depth != colour:
                log.warning("%s: depth frame %r is not the colour frame %r and no depth camera info with a tf between "
                            "them: taking the depth as registered to colour", self.path, depth, colour)
            return None
        T = self._tf.lookup(colour, depth, [self._rgb.stamps[0]])[0]
        if not np.all(np.isfinite(T)):
            raise DatasetError(f"{self.path}: no tf between depth frame {depth!r} and colour frame {colour!r}")
        K, _, _, width, height = camera_info_arrays(self._depth_info)
        return Intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], width, height), T

    def _pair(self) -> None:
        rgb, depth = np.asarray(self._rgb.stamps), np.asarray(self._depth.stamps)
        self.offset, pairs = pair_streams(rgb, depth, self.max_difference)
        if not len(pairs):
            raise DatasetError(f"{self.path}: no depth image within {self.max_difference * 1000:.0f} ms of any colour "
                               f"image ({self.topics.rgb}, {self.topics.depth})")
        lost = len(rgb) - len(pairs)
        if lost:
            log.info("%s: %d of %d colour images have no depth image within %.0f ms and are left out", self.path,
                     lost, len(rgb), self.max_difference * 1000)
        self._colour_index, self._depth_index = pairs[:, 0], pairs[:, 1]
        self.timestamps, self.depth_timestamps = rgb[pairs[:, 0]], depth[pairs[:, 1]]
        self.rgb_line_index = pairs[:, 0].astype(int)  # each frame's message among the colour topic's

    # --- ground truth and IMU ---------------------------------------------------------------

    def _attach_ground_truth(self) -> None:
        """Camera poses from tf or from a pose topic, interpolated at the colour stamps."""
        raw = self._gt_from_tf() if self.topics.gt == "/tf" else self._gt_from_poses() if self._poses else None
        if raw is None:
            return
        self._gt_raw = raw
        self.T_world_cam_gt = interpolate_poses(*raw, self.timestamps)
        if not np.any(self.has_gt):
            log.warning("%s: the ground truth (%s) covers none of the frames: run without it", self.path,
                        self.topics.gt)
            self.T_world_cam_gt, self._gt_raw = None, None

    def _gt_from_tf(self):
        camera = (self.topics.camera_frame or self._rgb.frame_id).lstrip("/")
        if not self._tf or camera not in self._tf.frames:
            if self._tf:
                log.warning("%s: the colour frame %r is not in the tf tree (frames: %s): no ground truth; name it with "
                            "--topics camera_frame=FRAME", self.path, camera, ", ".join(sorted(self._tf.frames)))
            return None
        world = (self.topics.world_frame or self._tf.root(camera)).lstrip("/")
        if world not in self._tf.frames:
            raise DatasetError(f"{self.path}: `topics=world_frame={world}`: no such tf frame (frames: "
                               f"{', '.join(sorted(self._tf.frames))})")
        stamps = self._tf.moving_stamps(world, camera)
        if not len(stamps):
            log.warning("%s: nothing moves between tf frames %r and %r: no ground truth", self.path, world, camera)
            return None
        self.world_frame = world
        return stamps, self._tf.lookup(world, camera, stamps)

    def _gt_from_poses(self):
        """A pose topic's poses, moved to the colour camera by tf when the pose names another frame."""
        stamps = np.array([p[0] for p in self._poses])
        T = np.stack([p[1] for p in self._poses])
        self.world_frame = self._poses[0][2].lstrip("/")
        child, camera = self._poses[0][3].lstrip("/"), (self.topics.camera_frame or self._rgb.frame_id).lstrip("/")
        if child and child != camera and child in self._tf.frames and camera in self._tf.frames:
            T = T @ self._tf.lookup(child, camera, stamps[:1])[0]
        order = np.argsort(stamps, kind="stable")
        return stamps[order], T[order]

    def _attach_imu(self) -> None:
        self.imu, self.imu_config = None, None
        if not self._imu_rows:
            return
        if self._gyro_missing:
            log.info("%s: %s has no gyroscope (covariance -1): no IMU odometry from it", self.path, self.topics.imu)
            return
        rows = np.array(sorted(self._imu_rows))
        keep = np.concatenate([[True], np.diff(rows[:, 0]) > 0])
        rows = rows[keep]
        T_cam_imu = np.eye(4)
        imu_frame, camera = self._imu_frame.lstrip("/"), self._rgb.frame_id
        if imu_frame and imu_frame != camera:
            if imu_frame in self._tf.frames and camera in self._tf.frames:
                T_cam_imu = self._tf.lookup(camera, imu_frame, rows[:1, 0])[0]
            else:
                log.warning("%s: no tf between the IMU frame %r and the camera %r: taking them as one (give "
                            "--imu-extrinsics)", self.path, imu_frame, camera)
        self.imu = {"stamps": rows[:, 0].copy(), "accel": rows[:, 1:4].copy(), "gyro": rows[:, 4:7].copy()}
        self.imu_config = ImuConfig(T_cam_imu=T_cam_imu if np.all(np.isfinite(T_cam_imu)) else np.eye(4))

    # --- frames -------------------------------------------------------------------------

    def _select(self, start: int, stop: int) -> None:
        for name in ("timestamps", "depth_timestamps", "_colour_index", "_depth_index", "rgb_line_index"):
            setattr(self, name, getattr(self, name)[start:stop])
        if self.T_world_cam_gt is not None:
            self.T_world_cam_gt = self.T_world_cam_gt[start:stop]

    def _message(self, topic: str, stream: _Stream, k: int):
        """The k-th message of an image topic, read by seeking to its bag time."""
        connection, log_ns, stamp = self._connections[topic], stream.log_ns[k], stream.stamps[k]
        with self._lock:
            if self._reader is None:
                self._reader = _open_reader(self.path)
                self._connections = {c.topic: c for c in self._reader.connections}
                connection = self._connections[topic]
            try:
                for _, _, raw in self._reader.messages(connections=[connection], start=log_ns, stop=log_ns + 1):
                    msg = self._reader.deserialize(raw, connection.msgtype)
                    if abs(stamp_s(msg.header.stamp) - stamp) < 1e-7:
                        return msg
            except Exception as exc:
                raise DatasetError(f"{self.path}: {topic} message {k} cannot be read ({_first_line(exc)})") from None
        raise DatasetError(f"{self.path}: {topic} message {k} (stamp {stamp:.6f}) is gone from the bag")

    def __len__(self) -> int:
        return len(self.timestamps)

    def __getitem__(self, index):
        import cv2


        i = frame_index(index, len(self), self.name)
        rgb = decode_colour(self._message(self.topics.rgb, self._rgb, int(self._colour_index[i])),
                            f"{self.path}: {self.topics.rgb}")
        depth_m = decode_depth_m(self._message(self.topics.depth, self._depth, int(self._depth_index[i])),
                                 f"{self.path}: {self.topics.depth}")
        if rgb.shape[:2] != self.raw_intrinsics.shape:
            raise DatasetError(f"{self.path}: colour message {int(self._colour_index[i])} is "
                               f"{rgb.shape[1]}x{rgb.shape[0]}, the camera {self.raw_intrinsics.width}x"
                               f"{self.raw_intrinsics.height}")
        if self._maps is not None:
            rgb = cv2.remap(rgb, *self._maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        if self._depth_warp is not None:
            depth_intrinsics, T_colour_depth = self._depth_warp
            depth_m = warp_depth(depth_m, depth_intrinsics, T_colour_depth, dst_intrinsics=self.intrinsics,
                                 iterations=3)
        elif depth_m.shape != rgb.shape[:2]:
            raise DatasetError(f"{self.path}: depth message {int(self._depth_index[i])} is {depth_m.shape[1]}x"
                               f"{depth_m.shape[0]}, colour {rgb.shape[1]}x{rgb.shape[0]}")
        return RGBDFrame(rgb, depth_m, self.intrinsics, float(self.timestamps[i]), float(self.depth_timestamps[i]))

    def __iter__(self):
        for i in range(len(self)):
            yield self[i]

    @property
    def recording_id(self) -> str:
        """Content fingerprint of the bag (the same for any ``frames`` range)."""
        files = [self.path] if self.path.is_file() else sorted(
            p for p in self.path.iterdir() if p.suffix in (".yaml", ".db3", ".mcap"))
        return fingerprint_files(files)

    def close(self) -> None:
        """Close the bag (a later frame read opens it again)."""
        with self._lock:
            if self._reader is not None:
                try:
                    self._reader.close()
                finally:
                    self._reader = None

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass

    def __getstate__(self):  # a pickled sequence (a worker process) reopens the bag when it reads
        state = dict(self.__dict__)
        state["_reader"], state["_lock"] = None, None
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._lock = threading.Lock()

    def __repr__(self) -> str:
        return (f"RosbagSequence({str(self.path)!r}, frames={len(self)}, imu={self.imu is not None}, "
                f"ground_truth={self.T_world_cam_gt is not None})")
