#!/usr/bin/env python3
"""Your own RGB-D images, your own iSAM2 loop, NAP3D corrections gated before they enter it.

Nothing here comes from the simulator: frames are read with OpenCV from a folder (the TUM
layout of the real fr1/xyz slice in tests/data; point ``--data`` at yours), the map is a splat
field built from every other frame (``nap3d-graph train-field`` does the same from the
command line), and the other frames run through a plain GTSAM iSAM2 loop: an odometry
between factor per frame (here the motion capture's increments with a bias added, so it
drifts), and at each frame the NAP3D correction as a robust prior, added only when
``chi2_gate_isam2`` accepts it against iSAM2's current marginal.

    python examples/your_frames_in_your_isam2.py [--data FOLDER]
"""

import argparse
import dataclasses
from pathlib import Path

import cv2
import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from nap3d_graph import Intrinsics, RGBDFrame, correct_pose
from nap3d_graph.conventions import exp_se3, inv_T, pose_error, tum_to_T
from nap3d_graph.factors import chi2_gate_isam2, nap3d_prior_factor, odometry_factor, pose_prior_factor

DATA = Path(__file__).resolve().parents[1] / "tests" / "data" / "tum" / "rgbd_dataset_freiburg1_xyz"
CAMERA = Intrinsics(517.3, 516.5, 318.6, 255.3, 640, 480)  # your camera (fr1's published pinhole)
FIELD_ERROR = np.diag([0.01**2] * 3 + [0.015**2] * 3)  # rad, m (GTSAM order): the map's own error


def read_list(path: Path) -> list[tuple[float, Path]]:
    rows = [line.split() for line in path.read_text().splitlines() if line.strip() and not line.startswith("#")]
    return [(float(t), path.parent / name) for t, name in rows]


def read_frames(folder: Path) -> list[RGBDFrame]:
    """Colour and depth paired by line (the lists of your recorder), depth 5000 per metre."""
    frames = []
    for (t, rgb_path), (_, depth_path) in zip(read_list(folder / "rgb.txt"), read_list(folder / "depth.txt")):
        rgb = cv2.cvtColor(cv2.imread(str(rgb_path)), cv2.COLOR_BGR2RGB)
        depth_m = cv2.imread(str(depth_path), cv2.IMREAD_UNCHANGED).astype(np.float32) / 5000.0
        frames.append(RGBDFrame(rgb, depth_m, CAMERA, t))
    return frames


def read_poses(folder: Path, stamps) -> np.ndarray:
    """Your poses for the frames (here the motion capture's, nearest in time)."""
    rows = np.array([[float(v) for v in line.split()] for line in (folder / "groundtruth.txt").read_text().splitlines()
                     if line.strip() and not line.startswith("#")])
    nearest = [int(np.argmin(np.abs(rows[:, 0] - t))) for t in stamps]
    return tum_to_T(rows[nearest, 1:8])


def build_map(folder: Path):
    """A splat map from frames 0, 2, 4, ... (``every=2``): the others are left to correct."""
    from nap3d_graph.datasets import TumSequence
    from nap3d_graph.fields.build import build_field

    sequence = TumSequence(folder, undistort=False, intrinsics=CAMERA)
    field, _ = build_field(sequence, "splat", every=2, timing=None, eval_frames=0, measure_error=False,
                           progress=False)
    return field


def main(data: Path = DATA) -> dict:
    frames = read_frames(data)
    T_world_cam_gt = read_poses(data, [f.timestamp for f in frames])
    field = build_map(data)
    run = list(range(1, len(frames), 2))  # frames the map was not built from
    isam = gtsam.ISAM2()
    bias = exp_se3([0.0, 0.004, 0.0, 0.004, 0.0, 0.002])  # the odometry's drift per frame
    T_odom = T_world_cam_gt[run[0]]
    results = {"accepted": 0, "refused": 0}
    for k, i in enumerate(run):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if k == 0:
            graph.add(pose_prior_factor(X(0), T_odom, rot_sigma_rad=0.01, trans_sigma_m=0.02))  # where it starts
        else:
            step = inv_T(T_world_cam_gt[run[k - 1]]) @ T_world_cam_gt[i] @ bias
            T_odom = T_odom @ step
            graph.add(odometry_factor(X(k - 1), X(k), step, np.diag([3e-3**2] * 3 + [5e-3**2] * 3)))
        estimate_now = T_odom if k == 0 else isam.calculateEstimatePose3(X(k - 1)).matrix() @ step
        values.insert(X(k), gtsam.Pose3(estimate_now))
        isam.update(graph, values)
        # NAP3D at the pose iSAM2 predicts now, gated against its marginal before it enters.
        correction = correct_pose(frames[i], field, isam.calculateEstimatePose3(X(k)), iterations=2)
        if correction.success:
            # The map's own error, which the alignment's covariance (matches only) does not
            # know: a map of six frames is centimetres off. train-field measures it for its
            # fields (FIELD.report.json, field_error) and runs add it the same way.
            widened = dataclasses.replace(correction, covariance=correction.covariance + FIELD_ERROR)
            factor = nap3d_prior_factor(X(k), None, widened, robust="huber")
            gate = chi2_gate_isam2(factor, isam)
            if gate.accepted:
                accepted = gtsam.NonlinearFactorGraph()
                accepted.add(factor)
                isam.update(accepted, gtsam.Values())
                results["accepted"] += 1
            else:
                results["refused"] += 1
            print(f"frame {i}: {correction.num_inliers} inliers, gate d2 {gate.d2:.1f} "
                  f"{'accepted' if gate.accepted else 'refused: ' + gate.reason}")
        else:
            results["refused"] += 1
            print(f"frame {i}: no correction ({correction.reason})")
    last = len(run) - 1
    results["odometry_error_m"] = pose_error(T_odom, T_world_cam_gt[run[last]])[0]
    results["estimate_error_m"] = pose_error(isam.calculateEstimatePose3(X(last)).matrix(), T_world_cam_gt[run[last]])[0]
    print(f"last frame: odometry {results['odometry_error_m'] * 1000:.1f} mm off, with NAP3D "
          f"{results['estimate_error_m'] * 1000:.1f} mm off ({results['accepted']} corrections accepted)")
    return results


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DATA, help="a folder with rgb.txt, depth.txt, groundtruth.txt")
    main(parser.parse_args().data)
