"""Every reader gives what the Sequence protocol says (datasets.protocol), so the run, the field
builders and the evaluations can read any source without probing it."""

import numpy as np
import pytest

from nap3d_graph.datasets import (
    RealSenseRecording,
    RosbagSequence,
    Sequence,
    SevenScenesSequence,
    SimSequence,
    TumSequence,
)
from nap3d_graph.datasets.protocol import SEQUENCE_ATTRIBUTES


@pytest.fixture(scope="module")
def readers(sim_walk, tum_path, tmp_path_factory):
    from nap3d_graph.datasets.realsense_sim import write_realsense_recording
    from nap3d_graph.datasets.rosbag_write import write_sequence_bag
    from nap3d_graph.datasets.sevenscenes_sim import simulate_sevenscenes

    root = tmp_path_factory.mktemp("readers")
    walk = sim_walk(8)
    return {
        "tum": (TumSequence(tum_path), False),
        "sim": (SimSequence(walk), True),
        "7scenes": (SevenScenesSequence(simulate_sevenscenes(root / "kitchen", frames=6), cache_dir=False), False),
        "realsense": (RealSenseRecording(write_realsense_recording(walk, root / "walk.db3"),
                                         groundtruth=walk / "groundtruth.txt"), True),
        "rosbag": (RosbagSequence(write_sequence_bag(SimSequence(walk), root / "walk.bag")), False),
    }


@pytest.mark.parametrize("source", ["tum", "sim", "7scenes", "realsense", "rosbag"])
def test_every_reader_is_a_sequence(readers, source):
    sequence, simulated = readers[source]
    assert isinstance(sequence, Sequence)
    missing = [name for name in SEQUENCE_ATTRIBUTES if not hasattr(sequence, name)]
    assert missing == [], missing
    n = len(sequence)
    assert n >= 2 and sequence.timestamps.shape == (n,) and np.asarray(sequence.depth_timestamps).shape == (n,)
    assert sequence.T_world_cam_gt is None or np.asarray(sequence.T_world_cam_gt).shape == (n, 4, 4)
    assert isinstance(sequence.recording_id, str) and sequence.recording_id
    assert sequence.simulated is simulated  # a bag written from the simulator does not say so: a camera's
    start, stop = sequence.frame_range
    assert stop - start == n
    frame = sequence[0]
    assert frame.rgb.shape[:2] == (sequence.intrinsics.height, sequence.intrinsics.width)
