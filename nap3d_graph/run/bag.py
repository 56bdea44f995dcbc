"""A run's trajectories as a ROS bag, to play next to the input in RViz (``run --write-bag``).

Written in the input's time (each message's header stamp and bag time are the frame's
stamp), with ``rosbags``: a ``.bag`` path is a ROS 1 bag, any other a ROS 2 bag folder
(sqlite3, or MCAP for a path ending in ``.mcap``). Topics:

- ``/nap3d/causal/pose``, ``/nap3d/smoothed/pose``, ``/nap3d/odometry/pose``
  (``geometry_msgs/PoseStamped``, one per frame): the causal estimate (what the robot had
  at each frame), the smoothed one (every correction used) and the odometry alone;
- ``/nap3d/causal/path`` (``nav_msgs/Path``): the causal trajectory so far, at most twice
  a second of input time and at the last frame, so the bag stays small on long runs;
- ``/nap3d/smoothed/path``: the whole smoothed trajectory, at the first and the last frame;
- ``/tf``: ``WORLD -> nap3d_camera`` (causal) and ``WORLD -> nap3d_camera_smoothed`` at each
  frame, WORLD being the input's world frame (a bag's tf root, else ``world``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nap3d_graph.datasets.rosbag_msgs import header, make_typestore, pose_msg, stamp_ns, transform_msg
from nap3d_graph.errors import DatasetError

__all__ = ["write_run_bag", "check_bag_path", "RUN_BAG_TOPICS", "CAUSAL_FRAME", "SMOOTHED_FRAME"]

CAUSAL_FRAME, SMOOTHED_FRAME = "nap3d_camera", "nap3d_camera_smoothed"
RUN_BAG_TOPICS = ("/nap3d/causal/pose", "/nap3d/smoothed/pose", "/nap3d/odometry/pose", "/nap3d/causal/path",
                  "/nap3d/smoothed/path", "/tf")
#: The causal path is re-published at most this often (s of input time).
PATH_PERIOD_S = 0.5


def check_bag_path(path) -> Path:
    """The output path, refused (one line) before a run when it exists or cannot be created."""
    path = Path(path)
    if path.exists():
        raise DatasetError(f"`write_bag={path}`: exists already; a bag is never overwritten")
    if not path.parent.is_dir():
        raise DatasetError(f"`write_bag={path}`: its folder {path.parent} does not exist")
    return path


def _writer(path: Path):
    if path.suffix == ".bag":
        from rosbags.rosbag1 import Writer as Ros1Writer

        return 1, Ros1Writer(path)
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Ros2Writer

    plugin = StoragePlugin.MCAP if path.suffix == ".mcap" else StoragePlugin.SQLITE3
    return 2, Ros2Writer(path, version=9, storage_plugin=plugin)


def _path_msg(store, stamps, T, upto: int, world: str, seq: int):
    poses = [pose_msg(store, T[k], float(stamps[k]), world, k) for k in range(upto + 1)]
    return store.types["nav_msgs/msg/Path"](header=header(store, float(stamps[upto]), world, seq), poses=poses)


def write_run_bag(path, result, world_frame: str = "world") -> Path:
    """Write ``result`` (a :class:`~nap3d_graph.run.config.RunResult`) to ``path``."""
    path = Path(path)
    ros, writer = _writer(path)
    store = make_typestore(ros)
    serialize = store.serialize_ros1 if ros == 1 else store.serialize_cdr
    stamps = np.asarray(result.timestamps, dtype=float)
    smoothed, odometry = result.T_world_cam_estimate, result.T_world_cam_odometry
    causal = result.T_world_cam_online if result.T_world_cam_online is not None else smoothed
    writer.open()
    try:
        connections = {}
        types = {"/tf": "tf2_msgs/msg/TFMessage", "/nap3d/causal/path": "nav_msgs/msg/Path",
                 "/nap3d/smoothed/path": "nav_msgs/msg/Path"}
        for topic in RUN_BAG_TOPICS:
            connections[topic] = writer.add_connection(topic, types.get(topic, "geometry_msgs/msg/PoseStamped"),
                                                       typestore=store)

        def put(topic, msg, t):
            writer.write(connections[topic], stamp_ns(t), serialize(msg, connections[topic].msgtype))

        TF = store.types["tf2_msgs/msg/TFMessage"]
        last_path, n = -np.inf, len(stamps)
        for i, t in enumerate(stamps):
            t = float(t)
            if i == 0:
                put("/nap3d/smoothed/path", _path_msg(store, stamps, smoothed, n - 1, world_frame, 0), t)
            for topic, T in (("/nap3d/causal/pose", causal), ("/nap3d/smoothed/pose", smoothed),
                             ("/nap3d/odometry/pose", odometry)):
                put(topic, pose_msg(store, T[i], t, world_frame, i), t)
            put("/tf", TF(transforms=[transform_msg(store, causal[i], t, world_frame, CAUSAL_FRAME, i),
                                      transform_msg(store, smoothed[i], t, world_frame, SMOOTHED_FRAME, i)]), t)
            if t - last_path >= PATH_PERIOD_S or i == n - 1:
                put("/nap3d/causal/path", _path_msg(store, stamps, causal, i, world_frame, i), t)
                last_path = t
        put("/nap3d/smoothed/path", _path_msg(store, stamps, smoothed, n - 1, world_frame, 1), float(stamps[-1]))
    finally:
        writer.close()
    return path
