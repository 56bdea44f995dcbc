"""The ROS bag source on real data: fr1/desk as a folder, as a ROS 1 bag and as a ROS 2 bag.

Writes TUM fr1/desk (the shared 15 Hz copy) as a ROS 1 ``.bag`` in TUM's own layout (rgb8
colour, 32FC1 depth, ground truth on /tf through a camera mount) and as a ROS 2 MCAP folder
(PNG-compressed colour, 16UC1 millimetre depth, as ROS 2 drivers publish), then:

- reads every frame of each source and times it (frames per second, opening included);
- checks the bag frames against the folder's (colour bit-exact; depth exact for 32FC1, within
  half a millimetre for 16UC1) and the ground truth through tf;
- runs ``nap3d-graph run --odom vo`` on the second half of each with the same splat field
  (built on the folder's first half) and compares the trajectories and ATE;
- writes the run's ``--write-bag`` output and reads it back against estimate.txt, and its
  ``--viz`` rerun recording, read back with rerun's reader (entries per keyframe).

Writes ``benchmarks/results/rosbag_fr1_desk.json``.

    python benchmarks/rosbag_desk.py [--data ../shared/data/tum/rgbd_dataset_freiburg1_desk]
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
from provenance import write_result

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "tum" / "rgbd_dataset_freiburg1_desk"


def _read_all(sequence) -> tuple[float, list]:
    t0 = time.perf_counter()
    frames = [sequence[i] for i in range(len(sequence))]
    return time.perf_counter() - t0, frames


def _run(data: Path, traj: str, field: Path, out: Path, extra=()) -> dict:
    from nap3d_graph.cli import main

    # SIFT, as when these figures were measured: the benchmark compares sources, not matchers.
    code = main(["run", "--traj", traj, "--data", str(data), "--frames", "0.5:1", "--field", str(field), "--odom",
                 "vo", "--matcher", "sift", "--out", str(out), *extra])
    if code != 0:
        raise SystemExit(f"run on {data} failed ({code})")
    metrics = json.loads((out / "latest" / "metrics.json").read_text())
    return {"ate_cm": metrics["estimate"]["ate_m"]["rmse"] * 100, "causal_ate_cm":
            metrics["estimate_online"]["ate_m"]["rmse"] * 100, "odometry_ate_cm":
            metrics["odometry"]["ate_m"]["rmse"] * 100, "accepted": metrics["corrections_accepted"],
            "keyframes": metrics["keyframes"], "estimate": str(out / "latest" / "estimate.txt")}


def _bag_poses(path: Path, topic: str) -> tuple[np.ndarray, np.ndarray]:
    from rosbags.highlevel import AnyReader

    from nap3d_graph.conventions import tum_to_T

    stamps, rows = [], []
    with AnyReader([path]) as reader:
        connections = [c for c in reader.connections if c.topic == topic]
        for connection, _, raw in reader.messages(connections=connections):
            msg = reader.deserialize(raw, connection.msgtype)
            p, q = msg.pose.position, msg.pose.orientation
            stamps.append(msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9)
            rows.append([p.x, p.y, p.z, q.x, q.y, q.z, q.w])
    return np.array(stamps), tum_to_T(np.array(rows))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=DEFAULT_DATA)
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/rosbag_fr1_desk.json"))
    args = p.parse_args()

    from nap3d_graph.datasets import RosbagSequence, TumSequence, read_tum_trajectory
    from nap3d_graph.datasets.rosbag_write import write_sequence_bag
    from nap3d_graph.fields.build import build_field

    folder = TumSequence(args.data)
    result: dict = {"benchmark": "rosbag_fr1_desk", "data": str(args.data), "frames": len(folder),
                    "machine": {"cpus": __import__("os").cpu_count(), "python": platform.python_version()},
                    "sources": {}}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        bags = {"ros1_32FC1_rgb8": write_sequence_bag(folder, tmp / "desk.bag", ros=1, depth_encoding="32FC1"),
                "ros2_mcap_16UC1_png": write_sequence_bag(folder, tmp / "desk_ros2", ros=2, depth_encoding="16UC1",
                                                          compressed=True, storage="mcap")}
        folder_s, folder_frames = _read_all(TumSequence(args.data))
        result["sources"]["folder"] = {"read_frames_per_s": len(folder) / folder_s}
        for name, path in bags.items():
            t0 = time.perf_counter()
            bag = RosbagSequence(path)
            open_s = time.perf_counter() - t0
            read_s, frames = _read_all(bag)
            size = path.stat().st_size if path.is_file() else sum(f.stat().st_size for f in path.iterdir())
            rgb_exact = all(np.array_equal(a.rgb, b.rgb) for a, b in zip(frames, folder_frames))
            depth_err = max(float(np.abs(a.depth_m - b.depth_m).max()) for a, b in zip(frames, folder_frames))
            gt_err = float(np.nanmax(np.abs(bag.T_world_cam_gt[:, :3, 3] - folder.T_world_cam_gt[:, :3, 3])))
            result["sources"][name] = {"bag_mb": round(size / 1e6, 1), "open_s": open_s,
                                       "read_frames_per_s": len(bag) / read_s,
                                       "read_frames_per_s_with_open": len(bag) / (read_s + open_s),
                                       "frames": len(bag), "colour_bit_exact": rgb_exact,
                                       "depth_max_abs_error_mm": depth_err * 1000,
                                       "ground_truth_max_abs_error_m": gt_err}
            del frames
        del folder_frames
        field = build_field(TumSequence(args.data, frames="0:0.5"), "splat", progress=False)[0]
        field_path = tmp / "desk_splat.pt"
        field.save(field_path)
        runs = {"folder": _run(args.data, "tum", field_path, tmp / "run_folder")}
        for name, path in bags.items():
            extra = ("--write-bag", str(tmp / f"{name}_out.bag"), "--viz", str(tmp / f"{name}.rrd")) \
                if name.startswith("ros1") else ()
            runs[name] = _run(path, "rosbag", field_path, tmp / f"run_{name}", extra)
        want = read_tum_trajectory(runs["folder"]["estimate"])
        for name in bags:
            got = read_tum_trajectory(runs[name]["estimate"])
            runs[name]["max_pose_difference_to_folder_m"] = float(np.abs(got[1][:, :3, 3] - want[1][:, :3, 3]).max())
        ros1 = "ros1_32FC1_rgb8"
        stamps, poses = _bag_poses(tmp / f"{ros1}_out.bag", "/nap3d/smoothed/pose")
        got = read_tum_trajectory(runs[ros1]["estimate"])
        runs[ros1]["written_bag_max_pose_difference_to_estimate_m"] = float(np.abs(poses[:, :3, 3] - got[1][:, :3, 3]).max())
        runs[ros1]["written_bag_stamps_equal"] = bool(np.allclose(stamps, got[0], atol=1e-6))
        from nap3d_graph.run.viz import keyframe_entries

        entries = keyframe_entries(tmp / f"{ros1}.rrd")
        runs[ros1]["rerun_recording"] = {"mb": round((tmp / f"{ros1}.rrd").stat().st_size / 1e6, 1),
                                         "status_entries": entries.get("/keyframes/status", 0),
                                         "render_entries": entries.get("/keyframes/render", 0),
                                         "accepted_ellipsoids": sum(p.startswith("/world/corrections/accepted/")
                                                                    for p in entries)}
        for run in runs.values():
            run.pop("estimate")
        result["runs"] = runs
    write_result(args.out, result, args)
    for name, source in result["sources"].items():
        print(f"{name}: {source['read_frames_per_s']:.0f} frame/s" + (
            f" ({source['bag_mb']} MB, opened in {source['open_s']:.1f} s, colour exact {source['colour_bit_exact']}, "
            f"depth within {source['depth_max_abs_error_mm']:.2f} mm)" if name != "folder" else ""))
    for name, run in runs.items():
        print(f"run on {name}: ATE {run['ate_cm']:.2f} cm (causal {run['causal_ate_cm']:.2f}, odometry "
              f"{run['odometry_ate_cm']:.2f}), {run['accepted']}/{run['keyframes']} accepted"
              + (f", {run['max_pose_difference_to_folder_m'] * 1000:.3f} mm from the folder's"
                 if "max_pose_difference_to_folder_m" in run else ""))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
