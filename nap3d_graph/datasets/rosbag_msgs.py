"""ROS messages to arrays and back, for ROS 1 and ROS 2 alike (``rosbags`` message objects).

The two ROS versions differ in small ways a reader and a writer both meet: ROS 1 headers
carry a ``seq``, ROS 1 ``CameraInfo`` spells its matrices ``K D`` where ROS 2 has ``k d``,
ROS 1 bags name tf's message ``tf/tfMessage`` or ``tf2_msgs/TFMessage``. Images are decoded
here (``sensor_msgs/Image`` by encoding, ``CompressedImage`` with OpenCV) because rosbags
gives raw bytes and the image helper package (``rosbags-image``) is not a dependency.

Times: a stamp is float seconds (``sec + nanosec * 1e-9``, as TUM's files and the rest of
the project count); poses are ``T_parent_child`` (4, 4), the child frame in the parent's.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from nap3d_graph.conventions import T_to_tum, tum_to_T
from nap3d_graph.errors import DatasetError

__all__ = [
    "COLOUR_ENCODINGS",
    "DEPTH_ENCODINGS",
    "stamp_s",
    "stamp_parts",
    "stamp_ns",
    "decode_colour",
    "decode_depth_m",
    "camera_info_arrays",
    "transform_to_T",
    "pose_to_T",
    "make_typestore",
    "header",
    "transform_msg",
    "pose_msg",
    "image_msg",
    "camera_info_msg",
]

#: sensor_msgs/Image colour encodings read: their channels and OpenCV's conversion to RGB.
COLOUR_ENCODINGS = {"rgb8": (3, None), "bgr8": (3, cv2.COLOR_BGR2RGB), "rgba8": (4, cv2.COLOR_RGBA2RGB),
                    "bgra8": (4, cv2.COLOR_BGRA2RGB), "mono8": (1, cv2.COLOR_GRAY2RGB)}
#: sensor_msgs/Image depth encodings read, and their unit in metres (16-bit: millimetres,
#: as OpenNI and RealSense drivers publish; 32-bit float: metres, NaN where none).
DEPTH_ENCODINGS = {"16UC1": 1e-3, "mono16": 1e-3, "32FC1": 1.0}


# --- stamps ---------------------------------------------------------------------------------


def stamp_s(stamp) -> float:
    """A ``builtin_interfaces/Time`` as float seconds."""
    return float(stamp.sec) + float(stamp.nanosec) * 1e-9


def stamp_parts(t_s: float) -> tuple[int, int]:
    """``(sec, nanosec)`` of float seconds (rounded to the nanosecond; ``t - sec`` is exact in
    floating point, so nothing is lost beyond the stamp's own precision)."""
    sec = math.floor(t_s)
    nanosec = int(round((t_s - sec) * 1e9))
    if nanosec >= 1_000_000_000:
        sec, nanosec = sec + 1, nanosec - 1_000_000_000
    return int(sec), nanosec


def stamp_ns(t_s: float) -> int:
    """Float seconds as integer nanoseconds (a bag's message time)."""
    sec, nanosec = stamp_parts(t_s)
    return sec * 1_000_000_000 + nanosec


# --- images ---------------------------------------------------------------------------------


def _pixels(msg, dtype, channels: int, topic: str) -> np.ndarray:
    """The (H, W[, C]) array of a sensor_msgs/Image, honouring its row stride and byte order."""
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    item = np.dtype(dtype).itemsize
    data = np.asarray(msg.data, dtype=np.uint8)
    if h <= 0 or w <= 0 or step < w * channels * item or data.size < h * step:
        raise DatasetError(f"{topic}: image of {w}x{h} (step {step}) holds {data.size} bytes: truncated or corrupt")
    rows = data[: h * step].reshape(h, step)[:, : w * channels * item]
    order = ">" if msg.is_bigendian else "<"
    pixels = np.ascontiguousarray(rows).view(np.dtype(dtype).newbyteorder(order) if item > 1 else dtype)
    pixels = pixels.astype(np.dtype(dtype).newbyteorder("="), copy=False)
    return pixels.reshape(h, w, channels) if channels > 1 else pixels.reshape(h, w)


def _is_compressed(msg) -> bool:
    return hasattr(msg, "format") and not hasattr(msg, "encoding")


def decode_colour(msg, topic: str) -> np.ndarray:
    """(H, W, 3) uint8 RGB from a sensor_msgs/Image (rgb8, bgr8, rgba8, bgra8, mono8) or a
    CompressedImage (JPEG, PNG)."""
    if _is_compressed(msg):
        image = cv2.imdecode(np.asarray(msg.data, dtype=np.uint8), cv2.IMREAD_COLOR)
        if image is None:
            raise DatasetError(f"{topic}: compressed image ({msg.format!r}) cannot be decoded")
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    encoding = str(msg.encoding)
    if encoding not in COLOUR_ENCODINGS:
        raise DatasetError(f"{topic}: colour encoding {encoding!r} is not read (known: {', '.join(COLOUR_ENCODINGS)})")
    channels, conversion = COLOUR_ENCODINGS[encoding]
    pixels = _pixels(msg, np.uint8, channels, topic)
    return pixels.copy() if conversion is None else cv2.cvtColor(pixels, conversion)


def decode_depth_m(msg, topic: str) -> np.ndarray:
    """(H, W) float32 depth in metres (0 where none) from a sensor_msgs/Image (16UC1 / mono16
    in millimetres, 32FC1 in metres) or a CompressedImage in image_transport's
    ``compressedDepth`` format of 16UC1."""
    if _is_compressed(msg):
        fmt = str(msg.format)
        if "compresseddepth" not in fmt.lower().replace(" ", "") or not fmt.startswith("16UC1"):
            raise DatasetError(f"{topic}: compressed depth format {fmt!r} is not read (known: '16UC1; "
                               "compressedDepth png' and the raw encodings 16UC1, 32FC1)")
        # compressed_depth_image_transport puts a 12-byte configuration header before the PNG.
        raw = cv2.imdecode(np.asarray(msg.data, dtype=np.uint8)[12:], cv2.IMREAD_UNCHANGED)
        if raw is None or raw.dtype != np.uint16:
            raise DatasetError(f"{topic}: compressedDepth image cannot be decoded")
        return raw.astype(np.float32) * np.float32(1e-3)
    encoding = str(msg.encoding)
    if encoding not in DEPTH_ENCODINGS:
        raise DatasetError(f"{topic}: depth encoding {encoding!r} is not read (known: {', '.join(DEPTH_ENCODINGS)})")
    if encoding == "32FC1":
        depth = _pixels(msg, np.float32, 1, topic).copy()
        depth[~np.isfinite(depth) | (depth < 0)] = 0.0
        return depth
    return _pixels(msg, np.uint16, 1, topic).astype(np.float32) * np.float32(DEPTH_ENCODINGS[encoding])


def camera_info_arrays(msg) -> tuple[np.ndarray, tuple[float, ...], str, int, int]:
    """``(K (3, 3), distortion, model, width, height)`` of a sensor_msgs/CameraInfo."""
    K = np.asarray(msg.k if hasattr(msg, "k") else msg.K, dtype=float).reshape(3, 3)
    D = np.asarray(msg.d if hasattr(msg, "d") else msg.D, dtype=float).reshape(-1)
    return K, tuple(float(d) for d in D), str(msg.distortion_model), int(msg.width), int(msg.height)


# --- poses ----------------------------------------------------------------------------------


def _T(translation, rotation) -> np.ndarray:
    q = [rotation.x, rotation.y, rotation.z, rotation.w]
    if np.linalg.norm(q) < 1e-9:
        raise DatasetError("a transform in the bag has a zero quaternion")
    return tum_to_T(np.array([translation.x, translation.y, translation.z, *q], dtype=float))


def transform_to_T(transform) -> np.ndarray:
    """(4, 4) of a geometry_msgs/Transform."""
    return _T(transform.translation, transform.rotation)


def pose_to_T(msg) -> tuple[np.ndarray, str, str]:
    """``(T_parent_child, parent frame, child frame)`` of a pose message: PoseStamped,
    PoseWithCovarianceStamped, TransformStamped or nav_msgs/Odometry (child: its
    ``child_frame_id``, else '')."""
    parent = str(msg.header.frame_id)
    if hasattr(msg, "transform"):
        return transform_to_T(msg.transform), parent, str(msg.child_frame_id)
    pose = msg.pose
    if hasattr(pose, "pose"):  # with covariance, and Odometry's
        pose = pose.pose
    return _T(pose.position, pose.orientation), parent, str(getattr(msg, "child_frame_id", ""))


# --- building messages (the writers) --------------------------------------------------------

_TF_MSG = "geometry_msgs/TransformStamped[] transforms"


def make_typestore(ros: int):
    """The message types of a ROS 1 (noetic) or ROS 2 (humble) bag, with tf2's TFMessage."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros == 1 else Stores.ROS2_HUMBLE)
    if "tf2_msgs/msg/TFMessage" not in store.types:
        store.register(get_types_from_msg(_TF_MSG, "tf2_msgs/msg/TFMessage"))
    return store


def header(store, t_s: float, frame_id: str, seq: int = 0):
    """A std_msgs/Header at float seconds ``t_s`` (ROS 1's with its ``seq``)."""
    Header, Time = store.types["std_msgs/msg/Header"], store.types["builtin_interfaces/msg/Time"]
    sec, nanosec = stamp_parts(t_s)
    if "seq" in Header.__dataclass_fields__:
        return Header(seq=seq, stamp=Time(sec=sec, nanosec=nanosec), frame_id=frame_id)
    return Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=frame_id)


def _geometry(store, T: np.ndarray):
    """(translation Vector3, rotation Quaternion, position Point) of a (4, 4) pose."""
    tx, ty, tz, qx, qy, qz, qw = (float(v) for v in T_to_tum(np.asarray(T, dtype=float)[None])[0])
    types = store.types
    rotation = types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw)
    return (types["geometry_msgs/msg/Vector3"](x=tx, y=ty, z=tz), rotation,
            types["geometry_msgs/msg/Point"](x=tx, y=ty, z=tz))


def transform_msg(store, T_parent_child: np.ndarray, t_s: float, parent: str, child: str, seq: int = 0):
    """A geometry_msgs/TransformStamped."""
    translation, rotation, _ = _geometry(store, T_parent_child)
    transform = store.types["geometry_msgs/msg/Transform"](translation=translation, rotation=rotation)
    return store.types["geometry_msgs/msg/TransformStamped"](header=header(store, t_s, parent, seq),
                                                             child_frame_id=child, transform=transform)


def pose_msg(store, T_parent_child: np.ndarray, t_s: float, parent: str, seq: int = 0):
    """A geometry_msgs/PoseStamped."""
    _, rotation, position = _geometry(store, T_parent_child)
    pose = store.types["geometry_msgs/msg/Pose"](position=position, orientation=rotation)
    return store.types["geometry_msgs/msg/PoseStamped"](header=header(store, t_s, parent, seq), pose=pose)


def image_msg(store, t_s: float, frame_id: str, pixels: np.ndarray, encoding: str, seq: int = 0):
    """A sensor_msgs/Image of (H, W[, C]) pixels in ``encoding`` (rows packed, little-endian)."""
    h, w = pixels.shape[:2]
    data = np.ascontiguousarray(pixels).view(np.uint8).reshape(-1)
    return store.types["sensor_msgs/msg/Image"](header=header(store, t_s, frame_id, seq), height=h, width=w,
                                                encoding=encoding, is_bigendian=0, step=data.size // h, data=data)


def camera_info_msg(store, t_s: float, frame_id: str, intrinsics, seq: int = 0):
    """A sensor_msgs/CameraInfo of a pinhole :class:`~nap3d_graph.camera.Intrinsics` (no distortion)."""
    Info = store.types["sensor_msgs/msg/CameraInfo"]
    K = intrinsics.K.reshape(-1)
    P = np.concatenate([intrinsics.K, np.zeros((3, 1))], axis=1).reshape(-1)
    names = ("D", "K", "R", "P") if "K" in Info.__dataclass_fields__ else ("d", "k", "r", "p")
    values = (np.zeros(5), K, np.eye(3).reshape(-1), P)
    roi = store.types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return Info(header=header(store, t_s, frame_id, seq), height=intrinsics.height, width=intrinsics.width,
                distortion_model="plumb_bob", binning_x=0, binning_y=0, roi=roi,
                **dict(zip(names, values)))
