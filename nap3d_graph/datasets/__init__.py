"""Data sources: one module per format, each giving sequences of ``RGBDFrame``.

``SOURCES`` maps a source name (as the CLI's ``--traj`` uses it) to its sequence class:
``"tum"`` any TUM RGB-D folder, ``"sim"`` a folder written by ``nap3d-graph simulate``,
``"realsense"`` a RealSense ``.bag`` / ``.db3`` recording (pyrealsense2 is imported only when
one is read), ``"7scenes"`` a Microsoft 7-Scenes sequence (or scene) folder, ``"rosbag"`` a
ROS 1 ``.bag`` or a ROS 2 bag folder (read with ``rosbags``).
"""

from __future__ import annotations

from nap3d_graph.datasets.protocol import Sequence
from nap3d_graph.datasets.tum import TumSequence
from nap3d_graph.errors import DatasetError
from nap3d_graph.trajectory import Trajectory, read_tum_trajectory, write_tum_trajectory

from .realsense import RealSenseConfig, RealSenseRecording
from .rosbag import BagTopics, RosbagSequence, is_rosbag
from .sevenscenes import SevenScenesSequence, is_sevenscenes_folder
from .sim import SimSequence

__all__ = [
    "Sequence",
    "Trajectory",
    "SOURCES",
    "source_of",
    "open_sequence",
    "DatasetError",
    "TumSequence",
    "SimSequence",
    "RealSenseRecording",
    "RealSenseConfig",
    "SevenScenesSequence",
    "is_sevenscenes_folder",
    "RosbagSequence",
    "BagTopics",
    "is_rosbag",
    "read_tum_trajectory",
    "write_tum_trajectory",
]

SOURCES: dict[str, type] = {"tum": TumSequence, "sim": SimSequence, "realsense": RealSenseRecording,
                            "7scenes": SevenScenesSequence, "rosbag": RosbagSequence}

RECORDING_SUFFIXES = (".bag", ".db3")


def source_of(path) -> str:
    """The source (a key of ``SOURCES``) a path is read as: "rosbag" for a ROS bag (a ROS 2
    folder, or a ``.bag`` whose topics are not a RealSense recording's), "realsense" for a
    RealSense ``.bag`` / ``.db3``, "sim" for a folder with a simulator's ``scene.json``,
    "7scenes" for a 7-Scenes folder, "tum" for any other folder."""
    from pathlib import Path

    path = Path(path)
    if is_rosbag(path):
        return "rosbag"
    if path.suffix.lower() in RECORDING_SUFFIXES:
        return "realsense"
    if (path / "scene.json").exists():
        return "sim"
    if is_sevenscenes_folder(path) and not (path / "rgb.txt").exists():
        return "7scenes"
    return "tum"


def open_sequence(path, groundtruth=None, realsense_config=None, topics=None, depth_scale=None, stamps=None,
                  fps=None, **kwargs):
    """A sequence as the right class: :class:`RosbagSequence` for a ROS bag (a ROS 2 bag
    folder, or a ``.bag`` whose topics are not a RealSense recording's; ``topics``: its
    :class:`BagTopics` or their ``key=value`` text), :class:`RealSenseRecording` for a RealSense
    ``.bag`` / ``.db3`` file (``groundtruth``: a TUM file of its poses; ``realsense_config``: a
    YAML of what the file does not store), :class:`SimSequence` for a folder with a
    simulator's ``scene.json``, :class:`SevenScenesSequence` for a 7-Scenes folder
    (``frame-*.pose.txt`` or sequence folders ``seq-01/``...), :class:`TumSequence` for any
    other folder (its own groundtruth.txt). ``depth_scale`` (depth units per metre) is for
    folders of depth PNGs (TUM layout, 7-Scenes); ``stamps`` (``"as-written"`` or
    ``"file-order"``) and ``fps`` (the camera's rate, for lists whose stamps are not a clock:
    stamps ``i / fps`` in file order) for TUM-layout folders: a recording carries its own units
    and clock."""
    from pathlib import Path

    path = Path(path)
    source = source_of(path)
    if depth_scale is not None:
        if source not in ("tum", "sim", "7scenes"):
            raise DatasetError(f"{path}: `depth_scale` is for folders of depth PNGs (TUM layout, 7-Scenes); a "
                               f"{source} recording carries its own depth units")
        kwargs["depth_scale"] = depth_scale
    if stamps is not None:
        if source not in ("tum", "sim"):
            raise DatasetError(f"{path}: `stamps` is for TUM-layout folders (rgb.txt, depth.txt); a {source} "
                               "source's frames carry their own stamps")
        kwargs["stamps"] = stamps
    if fps is not None:
        if source != "tum":
            raise DatasetError(f"{path}: `fps` is for TUM-layout folders whose stamps are not a clock; a {source} "
                               "source's frames carry their own stamps")
        kwargs["fps"] = fps
    if source == "rosbag":
        if groundtruth is not None or realsense_config is not None:
            raise DatasetError(f"{path}: a ROS bag's ground truth comes from its /tf or a pose topic (`topics=gt=...`), "
                               "not `groundtruth` / `realsense_config`")
        return RosbagSequence(path, topics=topics, frames=kwargs.get("frames"))
    if topics:
        raise DatasetError(f"{path}: `topics` is for ROS bags (a .bag file or a ROS 2 bag folder)")
    if source == "realsense":
        config = None if realsense_config is None else RealSenseConfig.load(realsense_config)
        return RealSenseRecording(path, groundtruth=groundtruth, frames=kwargs.get("frames"), config=config)
    if groundtruth is not None or realsense_config is not None:
        raise DatasetError(f"{path}: `groundtruth` / `realsense_config` are for RealSense recordings (.bag, .db3); "
                           "a TUM folder's own groundtruth.txt is read")
    return SOURCES[source](path, **kwargs)
