"""ROS bags: a simulated sequence written as ROS 1 and ROS 2 bags reads back as the folder's
frames, runs to the folder's trajectory, and bad bags are refused in one line."""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from nap3d_graph.datasets import DatasetError, RosbagSequence, SimSequence, open_sequence, read_tum_trajectory
from nap3d_graph.datasets.rosbag import BagTopics, is_rosbag
from nap3d_graph.datasets.rosbag_write import write_sequence_bag
from nap3d_graph.sims.sequence import SimConfig, simulate_sequence

FRAMES, WIDTH, HEIGHT = 16, 160, 120

BAGS = {  # name: (ROS version, depth encoding, compressed colour, ROS 2 storage)
    "ros1.bag": (1, "32FC1", False, "sqlite3"),
    "ros1_mm_png.bag": (1, "16UC1", True, "sqlite3"),
    "ros2_sqlite": (2, "32FC1", True, "sqlite3"),
    "ros2_mcap_mm": (2, "16UC1", False, "mcap"),
}


@pytest.fixture(scope="module")
def sim_dir(tmp_path_factory):
    return simulate_sequence(tmp_path_factory.mktemp("sim") / "room",
                             SimConfig(frames=FRAMES, width=WIDTH, height=HEIGHT, seed=5))


@pytest.fixture(scope="module")
def bags(sim_dir, tmp_path_factory):
    root = tmp_path_factory.mktemp("bags")
    sequence = SimSequence(sim_dir)
    return {name: write_sequence_bag(sequence, root / name, ros=ros, depth_encoding=enc, compressed=comp,
                                     storage=storage)
            for name, (ros, enc, comp, storage) in BAGS.items()}


@pytest.mark.parametrize("name", list(BAGS))
def test_bag_reads_back_the_simulators_frames(name, bags, sim_dir):
    folder, bag = SimSequence(sim_dir), open_sequence(bags[name])
    assert isinstance(bag, RosbagSequence)
    assert bag.topics.depth == "/camera/depth/image" and bag.topics.gt == "/tf"  # found by type, TUM's layout
    assert len(bag) == len(folder) == FRAMES
    np.testing.assert_array_equal(bag.timestamps, folder.timestamps)
    np.testing.assert_array_equal(bag.depth_timestamps, folder.depth_timestamps)
    assert bag.intrinsics == folder.intrinsics
    # The ground truth went through tf as world -> kinect -> optical frame: composed back exactly.
    np.testing.assert_allclose(bag.T_world_cam_gt, folder.T_world_cam_gt, atol=1e-12)
    for key in ("stamps", "accel", "gyro"):
        np.testing.assert_array_equal(bag.imu[key], folder.imu[key])
    np.testing.assert_allclose(bag.imu_config.T_cam_imu, np.eye(4), atol=1e-12)
    for i in (0, FRAMES // 2, FRAMES - 1):
        got, want = bag[i], folder[i]
        np.testing.assert_array_equal(got.rgb, want.rgb)  # raw rgb8 or lossless PNG: bit-exact
        if BAGS[name][1] == "32FC1":
            np.testing.assert_array_equal(got.depth_m, want.depth_m)
        else:  # millimetres: exact to the encoding's quantum
            mm = np.round(want.depth_m.astype(np.float64) * 1000.0)
            np.testing.assert_array_equal(got.depth_m, mm.astype(np.uint16).astype(np.float32) * np.float32(1e-3))
            assert np.abs(got.depth_m - want.depth_m).max() <= 0.5e-3 + 1e-6


def test_frame_range_and_recording_identity(bags):
    whole, half = RosbagSequence(bags["ros1.bag"]), RosbagSequence(bags["ros1.bag"], frames="0.5:1")
    assert len(half) == FRAMES - FRAMES // 2
    np.testing.assert_array_equal(half.timestamps, whole.timestamps[FRAMES // 2:])
    np.testing.assert_array_equal(half[0].rgb, whole[FRAMES // 2].rgb)
    assert half.recording_id == whole.recording_id != RosbagSequence(bags["ros2_sqlite"]).recording_id


class _RepeatedFrame:
    """A sequence of one 320x240 frame repeated at 30 Hz: bags of any length, cheaply."""

    def __init__(self, frame, n: int):
        self.frame, self.n, self.ground_truth_samples, self.imu = frame, n, None, None

    def __len__(self):
        return self.n

    def __getitem__(self, i):
        from nap3d_graph.camera import RGBDFrame

        t = 100.0 + i / 30.0
        return RGBDFrame(self.frame.rgb, self.frame.depth_m, self.frame.intrinsics, t, t - 0.01)


def test_opening_a_bag_streams_it(tmp_path, sim_dir):
    """Opening keeps stamps, not images: a bag five times longer costs what a short one does."""
    import cv2

    from nap3d_graph.camera import RGBDFrame

    small = SimSequence(sim_dir)[0]
    big = RGBDFrame(cv2.resize(small.rgb, (320, 240)), cv2.resize(small.depth_m, (320, 240)),
                    small.intrinsics.scaled(320, 240), 0.0)
    peaks = {}
    for n in (20, 100):
        path = write_sequence_bag(_RepeatedFrame(big, n), tmp_path / f"{n}.bag")
        tracemalloc.start()
        bag = RosbagSequence(path)
        peaks[n] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert len(bag) == n and bag.T_world_cam_gt is None and bag.imu is None
        np.testing.assert_array_equal(bag[n - 1].rgb, big.rgb)
    frame_bytes = big.rgb.nbytes + big.depth_m.nbytes
    # 80 more frames are 43 MB of images: opening holds a chunk and the stamps, not them.
    assert peaks[100] - peaks[20] < 5 * frame_bytes, peaks


def test_run_on_the_bag_gives_the_folders_trajectory(bags, sim_dir):
    """The same frames, ground truth and odometry through the oracle field: the same run."""
    from nap3d_graph.motion.odometry import make_odometry
    from nap3d_graph.run.config import PipelineConfig
    from nap3d_graph.run.pipeline import Pipeline
    from nap3d_graph.sims.scene import OracleField

    folder = SimSequence(sim_dir)
    field = OracleField(folder.scene)
    config = PipelineConfig(keyframe_every=2, render_width=WIDTH, render_height=HEIGHT, progress=False)
    results = {}
    for name, sequence in (("folder", folder), ("bag", RosbagSequence(bags["ros2_sqlite"]))):
        odometry = make_odometry("noisy", sequence, 3, 5e-3, 5e-3)
        results[name] = Pipeline(sequence, field, odometry, config).run()
    a, b = results["folder"], results["bag"]
    np.testing.assert_allclose(b.T_world_cam_estimate, a.T_world_cam_estimate, atol=1e-9)
    assert [k.accepted for k in a.keyframes] == [k.accepted for k in b.keyframes]
    assert sum(k.accepted for k in b.keyframes) >= 3
    gt = folder.T_world_cam_gt[:, :3, 3]
    ate = {k: float(np.sqrt(np.mean(np.sum((T[:, :3, 3] - gt) ** 2, axis=1))))
           for k, T in (("odometry", b.T_world_cam_odometry), ("estimate", b.T_world_cam_estimate))}
    assert ate["estimate"] < 0.5 * ate["odometry"], ate


@pytest.mark.slow
def test_cli_run_on_bags_matches_the_folder_and_writes_a_bag(bags, sim_dir, tmp_path):
    from rosbags.highlevel import AnyReader

    from nap3d_graph.cli import main

    field = tmp_path / "room.pt"
    assert main(["train-field", str(sim_dir), "--model", "splat", "--out", str(field), "--quiet"]) == 0
    common = ["--field", str(field), "--odom", "vo", "--keyframe-every", "3", "--render-size", f"{WIDTH}x{HEIGHT}"]
    assert main(["run", "--traj", "sim", "--data", str(sim_dir), "--out", str(tmp_path / "folder"), *common]) == 0
    want = read_tum_trajectory(tmp_path / "folder" / "latest" / "estimate.txt")
    for name, out_bag in (("ros1.bag", "out.bag"), ("ros2_sqlite", "out_ros2")):
        run_dir = tmp_path / name
        assert main(["run", "--traj", "rosbag", "--data", str(bags[name]), "--out", str(run_dir),
                     "--write-bag", str(tmp_path / out_bag), *common]) == 0
        got = read_tum_trajectory(run_dir / "latest" / "estimate.txt")
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_allclose(got[1], want[1], atol=1e-9)  # the same frames bit for bit: the same run
        # The written bag holds the run's poses, in the input's time.
        with AnyReader([tmp_path / out_bag]) as reader:
            by_topic = {c.topic: c for c in reader.connections}
            stamps, poses = [], []
            for connection, _, raw in reader.messages(connections=[by_topic["/nap3d/smoothed/pose"]]):
                msg = reader.deserialize(raw, connection.msgtype)
                stamps.append(msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9)
                p, q = msg.pose.position, msg.pose.orientation
                poses.append([p.x, p.y, p.z, q.x, q.y, q.z, q.w])
            counts = {c.topic: c.msgcount for c in reader.connections}
        from nap3d_graph.conventions import tum_to_T

        np.testing.assert_allclose(stamps, got[0], atol=1e-6)
        np.testing.assert_allclose(tum_to_T(np.array(poses)), got[1], atol=1e-8)
        assert counts["/nap3d/causal/pose"] == counts["/tf"] == FRAMES
        assert counts["/nap3d/smoothed/path"] == 2


# --- bad input ------------------------------------------------------------------------------


def _rewrite(src: Path, dst: Path, drop=(), edit=None) -> Path:
    """Copy a ROS 1 bag message by message, leaving out topics or editing messages."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag1 import Writer

    from nap3d_graph.datasets.rosbag_msgs import make_typestore

    store = make_typestore(1)
    with AnyReader([src]) as reader, Writer(dst) as writer:
        out = {}
        for k, (connection, t, raw) in enumerate(reader.messages()):
            if connection.topic in drop:
                continue
            if connection.topic not in out:
                out[connection.topic] = writer.add_connection(connection.topic, connection.msgtype, typestore=store)
            if edit is not None:
                msg = reader.deserialize(raw, connection.msgtype)
                msg = edit(connection.topic, k, msg)
                raw = store.serialize_ros1(msg, connection.msgtype)
            writer.write(out[connection.topic], t, raw)
    return dst


def _encoding(topic, k, msg):
    if topic == "/camera/depth/image":
        msg.encoding = "yuv422"
    return msg


def _swap_stamps(topic, k, msg):
    if topic == "/camera/rgb/image_color" and msg.header.seq in (3, 4):
        msg.header.stamp.sec -= 1 if msg.header.seq == 4 else 0
    return msg


BAD = {
    "no depth": (lambda src, dst: _rewrite(src, dst, drop=("/camera/depth/image", "/camera/depth/camera_info")),
                 r"no depth image topic \(the bag has: /camera/rgb/camera_info \[sensor_msgs/msg/CameraInfo\]"),
    "unknown encoding": (lambda src, dst: _rewrite(src, dst, edit=_encoding), r"depth encoding 'yuv422' is not read"),
    "no camera info": (lambda src, dst: _rewrite(src, dst, drop=("/camera/rgb/camera_info", "/camera/depth/camera_info")),
                       r"no colour camera info topic \(the bag has:"),
    "stamps out of order": (lambda src, dst: _rewrite(src, dst, edit=_swap_stamps),
                            r"/camera/rgb/image_color's header stamps are out of order at message 4"),
    "truncated": (lambda src, dst: dst.write_bytes(src.read_bytes()[: src.stat().st_size // 2]) and dst,
                  r"truncated"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_bags_are_refused_in_one_line(case, bags, tmp_path, capsys):
    from nap3d_graph.cli import main

    make, message = BAD[case]
    bad = make(bags["ros1.bag"], tmp_path / "bad.bag")
    with pytest.raises(DatasetError, match=message):
        RosbagSequence(bad)
    out = tmp_path / "results"
    code = main(["run", "--traj", "rosbag", "--data", str(bad), "--field", "none", "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and "bad.bag" in err[0], err
    assert not out.exists() or not any(out.iterdir()), "a refused bag must write nothing"


def test_topics_option_chooses_and_checks(bags):
    bag = RosbagSequence(bags["ros1.bag"], topics="gt=none,imu=/imu")
    assert bag.T_world_cam_gt is None and bag.imu is not None
    with pytest.raises(DatasetError, match="no such topic"):
        RosbagSequence(bags["ros1.bag"], topics="rgb=/camera/nothing")
    with pytest.raises(DatasetError, match="unknown key 'colour'"):
        BagTopics.parse("colour=/x")
    with pytest.raises(DatasetError, match="`topics=world_frame=nowhere`: no such tf frame"):
        RosbagSequence(bags["ros1.bag"], topics="world_frame=nowhere")
    # The optical frame's pose in its body frame ('kinect'), not in the world: the mount, fixed.
    mounted = RosbagSequence(bags["ros1.bag"], topics="world_frame=kinect")
    assert mounted.T_world_cam_gt is None  # nothing moves between them: no ground truth


def test_realsense_bags_are_left_to_the_realsense_reader(tmp_path):
    """librealsense's .bag recordings are ROS 1 bags with /device_0/... topics: not ours."""
    from rosbags.rosbag1 import Writer

    from nap3d_graph.datasets.rosbag_msgs import header, make_typestore

    store = make_typestore(1)
    path = tmp_path / "realsense.bag"
    with Writer(path) as writer:
        connection = writer.add_connection("/device_0/info", "std_msgs/msg/Header", typestore=store)
        writer.write(connection, 1, store.serialize_ros1(header(store, 1e-9, "x"), "std_msgs/msg/Header"))
    assert not is_rosbag(path)
    assert not is_rosbag(tmp_path / "missing.bag")


@pytest.mark.slow
def test_train_field_compare_and_study_read_bags(bags, tmp_path):
    """The other commands that take a recording open a bag by itself (its ground truth from tf)."""
    import json

    from nap3d_graph.cli import main
    from nap3d_graph.fields import load_field

    bag = str(bags["ros2_mcap_mm"])
    field = tmp_path / "bag.pt"
    assert main(["train-field", bag, "--model", "splat", "--out", str(field), "--quiet", "--topics", "gt=/tf"]) == 0
    assert load_field(field).meta["train_recording"] == RosbagSequence(bags["ros2_mcap_mm"]).recording_id
    assert main(["compare", "--traj", "rosbag", "--data", bag, "--field", str(field), "--odom", "noisy",
                 "--out", str(tmp_path / "cmp")]) == 0
    rows = {r["estimator"]: r for r in json.loads((tmp_path / "cmp" / "comparison.json").read_text())["rows"]}
    print("compare on the bag, ATE m:", {k: round(r["ate_rmse_m"], 4) for k, r in rows.items()})
    assert "odometry" in rows and len(rows) >= 3, sorted(rows)
    # The field was trained on this bag: the graph's rows beat its noisy odometry (measured
    # 1.11 against 1.18 cm), and no estimator ends worse than the odometry.
    odometry = rows["odometry"]["ate_rmse_m"]
    assert rows["isam2-final"]["ate_rmse_m"] < 0.97 * odometry and rows["batch-lm"]["ate_rmse_m"] < 0.97 * odometry
    assert all(r["ate_rmse_m"] <= odometry * 1.001 for r in rows.values()), rows
    assert main(["study", bag, "--model", "splat", "--odom", "noisy", "--scenarios", "4", "--out",
                 str(tmp_path / "study")]) == 0
    summary = json.loads((tmp_path / "study" / "summary.json").read_text())
    noisy = summary["runs"]["noisy"]
    # The bag's ground truth (from tf) scores the run: its noisy odometry drifts by millimetres
    # on these few frames (measured 5.3 mm). The tiny field corrects nothing here (no
    # correction accepted), so the estimate is the odometry's: the test is that the bag opens.
    assert 0.001 < noisy["ate_odometry_m"] < 0.05
    assert noisy["ate_estimate_m"] == pytest.approx(noisy["ate_odometry_m"], rel=0.05)


def test_simulate_writes_a_bag_that_runs_with_its_folder_as_field(tmp_path):
    import json

    from nap3d_graph.cli import main

    out, bag = tmp_path / "walk", tmp_path / "walk_ros2"
    assert main(["simulate", str(out), "--count", "12", "--width", "160", "--height", "120", "--rosbag", str(bag)]) == 0
    assert (bag / "metadata.yaml").is_file()  # not a .bag: a ROS 2 folder
    assert main(["run", "--traj", "rosbag", "--data", str(bag), "--field", str(out), "--render-size", "160x120",
                 "--out", str(tmp_path / "r")]) == 0
    metrics = json.loads((tmp_path / "r" / "latest" / "metrics.json").read_text())
    assert metrics["frames"] == 12 and metrics["corrections_accepted"] >= 1
    assert main(["simulate", str(tmp_path / "again"), "--count", "3", "--rosbag", str(bag)]) == 2  # never overwritten


def test_depth_from_a_separate_depth_camera_is_warped_into_colour(sim_dir, tmp_path):
    """An unregistered depth stream (its own camera, 2.5 cm to the side, on tf) reaches the
    colour camera: against the exact depth rendered there, the median error is sub-millimetre."""
    from rosbags.rosbag2 import Writer

    from nap3d_graph.camera import Intrinsics
    from nap3d_graph.datasets.rosbag_msgs import camera_info_msg, image_msg, make_typestore, stamp_ns, transform_msg

    folder = SimSequence(sim_dir)
    colour_K = folder.intrinsics
    depth_K = Intrinsics(140.0, 140.0, 82.0, 58.0, WIDTH, HEIGHT)  # a wider, shifted depth camera
    T_colour_depth = np.eye(4)
    T_colour_depth[0, 3] = 0.025
    store = make_typestore(2)
    types = store.types

    path = tmp_path / "two_cameras"
    frames = (0, 5)
    with Writer(path, version=9) as writer:
        topics = {"/color/image": "sensor_msgs/msg/Image", "/color/camera_info": "sensor_msgs/msg/CameraInfo",
                  "/depth/image": "sensor_msgs/msg/Image", "/depth/camera_info": "sensor_msgs/msg/CameraInfo",
                  "/tf_static": "tf2_msgs/msg/TFMessage"}
        conns = {t: writer.add_connection(t, m, typestore=store) for t, m in topics.items()}

        def put(topic, msg, t):
            writer.write(conns[topic], stamp_ns(t), store.serialize_cdr(msg, topics[topic]))

        t0 = float(folder.timestamps[0])
        mount = transform_msg(store, T_colour_depth, t0, "color_optical", "depth_optical")
        put("/tf_static", types["tf2_msgs/msg/TFMessage"](transforms=[mount]), t0)
        for i in frames:
            t, T = float(folder.timestamps[i]), folder.T_world_cam_gt[i]
            depth = folder.scene.render_depth(T @ T_colour_depth, depth_K).astype(np.float32)
            put("/color/image", image_msg(store, t, "color_optical", folder[i].rgb, "rgb8"), t)
            put("/color/camera_info", camera_info_msg(store, t, "color_optical", colour_K), t)
            put("/depth/image", image_msg(store, t, "depth_optical", depth, "32FC1"), t)
            put("/depth/camera_info", camera_info_msg(store, t, "depth_optical", depth_K), t)
    bag = RosbagSequence(path, topics="gt=none")
    assert len(bag) == len(frames)
    for k, i in enumerate(frames):
        want = folder.scene.render_depth(folder.T_world_cam_gt[i], colour_K)
        got = bag[k].depth_m
        both = (got > 0) & (want > 0)
        assert both.mean() > 0.8  # most of the image is seen by both cameras
        err = np.abs(got[both] - want[both])
        assert np.median(err) < 1e-3 and np.percentile(err, 90) < 5e-3, (np.median(err), np.percentile(err, 90))


def test_sweep_cells_read_bags(bags, tmp_path):
    """A sweep's recording may be a bag: its cells run with --traj rosbag and its --topics."""
    from nap3d_graph.sweep.spec import SweepSpec

    spec = SweepSpec.from_dict({"recordings": [{"data": str(bags["ros2_sqlite"]), "topics": "gt=/tf"}],
                                "field": {"model": "splat"}, "run": {"odom": "noisy"}})
    (task,) = spec.fields()
    (cell,) = spec.cells()
    assert task.argv(tmp_path / "f.pt")[:2] == ["train-field", str(bags["ros2_sqlite"])]
    assert "--topics" in task.argv(tmp_path / "f.pt")
    argv = cell.argv(tmp_path / "f.pt", tmp_path / "run")
    assert argv[1:3] == ["--traj", "rosbag"] and argv[argv.index("--topics") + 1] == "gt=/tf"
    assert argv[argv.index("--frames") + 1] == "0.5:1"
