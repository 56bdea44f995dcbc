#!/usr/bin/env python3
"""The NAP3D factor in your own GTSAM graph, nothing else of the pipeline.

A plain odometry chain X(0) .. X(N) (prior on X(0), between factors), drifting; at the last
pose a field (here the simulator's exact oracle room) corrects the pose with
``correct_pose``, and ``nap3d_prior_factor`` turns the correction into a robust prior with
the alignment's covariance. Levenberg-Marquardt then pulls the chain back.

    python examples/nap3d_factor_in_your_graph.py
"""

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from nap3d_graph import correct_pose
from nap3d_graph.conventions import exp_se3, inv_T, pose_error
from nap3d_graph.factors import nap3d_prior_factor, odometry_factor, pose_prior_factor
from nap3d_graph.sims.scene import OracleField, make_scene
from nap3d_graph.sims.sensors import sensor_frame
from nap3d_graph.sims.sequence import default_intrinsics
from nap3d_graph.sims.trajectories import make_trajectory


def main() -> dict:
    rng = np.random.default_rng(0)
    scene = make_scene(0)
    field = OracleField(scene)  # or nap3d_graph.load_field("room.pt")
    K = default_intrinsics(320, 240)
    trajectory = make_trajectory("traverse", scene, rng, duration_s=10.0)
    T_world_cam_gt = trajectory.poses(np.linspace(0.0, 10.0, 11))  # ground-truth T_world_cam, 1 Hz

    # Your odometry: true increments with a small yaw and forward bias (it drifts).
    graph, initial = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(pose_prior_factor(X(0), T_world_cam_gt[0], rot_sigma_rad=1e-3, trans_sigma_m=1e-3))
    T_odom = T_world_cam_gt[0]
    initial.insert(X(0), gtsam.Pose3(T_odom))
    odom_cov = np.diag([2e-3**2] * 3 + [2e-2**2] * 3)
    for k in range(1, len(T_world_cam_gt)):
        T_k1_k = inv_T(T_world_cam_gt[k - 1]) @ T_world_cam_gt[k] @ exp_se3([0, 0.0, 0.02, 0.03, 0.0, 0.0])
        graph.add(odometry_factor(X(k - 1), X(k), T_k1_k, odom_cov))
        T_odom = T_odom @ T_k1_k
        initial.insert(X(k), gtsam.Pose3(T_odom))
    last = len(T_world_cam_gt) - 1
    print(f"odometry at X({last}): {pose_error(T_odom, T_world_cam_gt[last])[0] * 100:.1f} cm off")

    # The camera's RGB-D frame at the last pose, corrected against the field.
    frame = sensor_frame(scene, T_world_cam_gt[last], K, rng)
    correction = correct_pose(frame, field, T_odom)
    print(f"NAP3D: {correction.num_inliers} inliers in {correction.iterations} rounds, "
          f"{pose_error(correction.T_world_cam_corrected, T_world_cam_gt[last])[0] * 1000:.1f} mm off, "
          f"sigma_t = {np.sqrt(np.diag(correction.covariance)[3:]).round(4)} m")
    graph.add(nap3d_prior_factor(X(last), None, correction, robust="huber"))

    estimate = gtsam.LevenbergMarquardtOptimizer(graph, initial).optimize()
    errors = {}
    for k in (last // 2, last):
        errors[k] = pose_error(estimate.atPose3(X(k)).matrix(), T_world_cam_gt[k])[0]
        print(f"after optimisation X({k}): {errors[k] * 100:.2f} cm off")
    return {"odometry_error_m": pose_error(T_odom, T_world_cam_gt[last])[0], "optimised_error_m": errors}


if __name__ == "__main__":
    main()
