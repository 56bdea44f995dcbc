"""A sequence written as a ROS bag in TUM's own bag layout (ROS 1 ``.bag`` or a ROS 2 folder).

Topics (as TUM publishes its RGB-D bags): ``/camera/rgb/image_color`` (``Image`` rgb8, or
``CompressedImage`` PNG on ``/camera/rgb/image_color/compressed``), ``/camera/depth/image``
(``Image`` 32FC1 metres or 16UC1 millimetres), ``/camera/rgb/camera_info`` and
``/camera/depth/camera_info``, ``/imu`` (when the sequence has one; in the camera's frame) and
``/tf``: the ground truth as ``world -> kinect`` at each ground-truth sample, with the camera's
optical frame mounted on ``kinect`` by a fixed transform (on ``/tf_static`` in ROS 2). Stamps
are the sequence's; every message's bag time is its header stamp.

It makes test and benchmark bags from folders (the reader must give back the same frames)
and lets a user try the bag source on a TUM folder they have.
"""

from __future__ import annotations

import heapq
from pathlib import Path

import cv2
import numpy as np

from nap3d_graph.conventions import inv_T
from nap3d_graph.errors import DatasetError

from .rosbag_msgs import camera_info_msg, header, image_msg, make_typestore, stamp_ns, transform_msg

__all__ = ["write_sequence_bag", "T_KINECT_OPTICAL", "CAMERA_FRAME"]

CAMERA_FRAME = "openni_rgb_optical_frame"
#: Where the optical frame sits on the ``kinect`` body frame (x forward, z up, as ROS bodies
#: are): optical z along body x, optical x along body -y, plus a small offset.
T_KINECT_OPTICAL = np.array([[0.0, 0.0, 1.0, 0.02], [-1.0, 0.0, 0.0, -0.045], [0.0, -1.0, 0.0, 0.01],
                             [0.0, 0.0, 0.0, 1.0]])


class _Bag:
    """A rosbags writer of either ROS version, with the connections it needs."""

    def __init__(self, out: Path, ros: int, storage: str):
        self.ros, self.store = ros, make_typestore(ros)
        if ros == 1:
            from rosbags.rosbag1 import Writer

            self.writer = Writer(out)
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer

            self.writer = Writer(out, version=9, storage_plugin=StoragePlugin[storage.upper()])
        self.writer.open()
        self.connections: dict[str, object] = {}

    def write(self, topic: str, msgtype: str, msg, t_s: float) -> None:
        if topic not in self.connections:
            self.connections[topic] = self.writer.add_connection(topic, msgtype, typestore=self.store)
        data = (self.store.serialize_ros1 if self.ros == 1 else self.store.serialize_cdr)(msg, msgtype)
        self.writer.write(self.connections[topic], stamp_ns(t_s), data)

    def close(self) -> None:
        self.writer.close()


def _imu_msg(store, t_s: float, accel, gyro, seq: int):
    types = store.types
    vec = types["geometry_msgs/msg/Vector3"]
    return types["sensor_msgs/msg/Imu"](
        header=header(store, t_s, CAMERA_FRAME, seq), orientation=types["geometry_msgs/msg/Quaternion"](x=0, y=0, z=0, w=1),
        orientation_covariance=np.r_[-1.0, np.zeros(8)], angular_velocity=vec(x=gyro[0], y=gyro[1], z=gyro[2]),
        angular_velocity_covariance=np.zeros(9), linear_acceleration=vec(x=accel[0], y=accel[1], z=accel[2]),
        linear_acceleration_covariance=np.zeros(9))


def _small_messages(bag: _Bag, sequence):
    """(t, order, topic, msgtype, msg) of the tf and IMU messages, in time order."""
    store, out = bag.store, []
    tf_type = "tf2_msgs/msg/TFMessage"
    TF = store.types[tf_type]
    raw = getattr(sequence, "ground_truth_samples", None)
    if raw is not None:
        stamps, T_world_cam = raw
        T_world_kinect = T_world_cam @ inv_T(T_KINECT_OPTICAL)
        for k, (t, T) in enumerate(zip(stamps, T_world_kinect)):
            if np.all(np.isfinite(T)):
                out.append((float(t), 0, "/tf", tf_type, TF(transforms=[transform_msg(store, T, t, "world", "kinect", k)])))
        mount = TF(transforms=[transform_msg(store, T_KINECT_OPTICAL, float(stamps[0]), "kinect", CAMERA_FRAME)])
        out.append((float(stamps[0]), -1, "/tf_static" if bag.ros == 2 else "/tf", tf_type, mount))
    imu = getattr(sequence, "imu", None)
    if imu is not None:
        for k, (t, a, w) in enumerate(zip(imu["stamps"], imu["accel"], imu["gyro"])):
            out.append((float(t), 1, "/imu", "sensor_msgs/msg/Imu", _imu_msg(store, float(t), a, w, k)))
    out.sort(key=lambda m: (m[0], m[1]))
    return out


def _frame_messages(bag: _Bag, sequence, depth_encoding: str, compressed: bool):
    """(t, order, topic, msgtype, msg) of each frame's images and camera infos, in frame order."""
    store = bag.store
    for i in range(len(sequence)):
        frame = sequence[i]
        t_c, t_d = frame.timestamp, frame.depth_timestamp if frame.depth_timestamp is not None else frame.timestamp
        if compressed:
            ok, png = cv2.imencode(".png", cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR))
            colour = store.types["sensor_msgs/msg/CompressedImage"](header=header(store, t_c, CAMERA_FRAME, i),
                                                                    format="rgb8; png compressed bgr8", data=png.reshape(-1))
            yield t_c, 2, "/camera/rgb/image_color/compressed", "sensor_msgs/msg/CompressedImage", colour
        else:
            yield t_c, 2, "/camera/rgb/image_color", "sensor_msgs/msg/Image", image_msg(store, t_c, CAMERA_FRAME,
                                                                                       frame.rgb, "rgb8", i)
        yield t_c, 3, "/camera/rgb/camera_info", "sensor_msgs/msg/CameraInfo", camera_info_msg(store, t_c, CAMERA_FRAME,
                                                                                             frame.intrinsics, i)
        if depth_encoding == "32FC1":
            depth = frame.depth_m.astype(np.float32)
        else:
            depth = np.round(np.clip(frame.depth_m, 0, 65.535) * 1000.0).astype(np.uint16)
        yield t_d, 2, "/camera/depth/image", "sensor_msgs/msg/Image", image_msg(store, t_d, CAMERA_FRAME, depth,
                                                                             depth_encoding, i)
        yield t_d, 3, "/camera/depth/camera_info", "sensor_msgs/msg/CameraInfo", camera_info_msg(
            store, t_d, CAMERA_FRAME, frame.intrinsics, i)


def write_sequence_bag(sequence, out, ros: int = 1, depth_encoding: str = "32FC1", compressed: bool = False,
                       storage: str = "sqlite3") -> Path:
    """Write ``sequence`` (any of the project's sequences) to ``out``: a ``.bag`` file for
    ``ros=1``, a bag folder for ``ros=2`` (``storage``: ``sqlite3`` or ``mcap``).

    depth_encoding: ``32FC1`` (metres, exact) or ``16UC1`` (millimetres, rounded).
    compressed: colour as PNG ``CompressedImage`` (lossless) instead of raw rgb8.
    """
    out = Path(out)
    if ros not in (1, 2):
        raise DatasetError(f"ros must be 1 or 2, got {ros}")
    if depth_encoding not in ("32FC1", "16UC1"):
        raise DatasetError(f"depth_encoding must be 32FC1 or 16UC1, got {depth_encoding!r}")
    if out.exists():
        raise DatasetError(f"{out}: exists already; a bag is never overwritten")
    bag = _Bag(out, ros, storage)
    try:
        # Bags are read back in time order: merge the frames' messages with tf and IMU by stamp.
        merged = heapq.merge(_small_messages(bag, sequence), _frame_messages(bag, sequence, depth_encoding, compressed),
                             key=lambda m: (m[0], m[1]))
        for t, _, topic, msgtype, msg in merged:
            bag.write(topic, msgtype, msg, t)
    finally:
        bag.close()
    return out
