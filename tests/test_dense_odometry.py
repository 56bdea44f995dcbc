"""Dense RGB-D odometry (--odom dense) on real TUM frames."""

import numpy as np

from nap3d_graph.conventions import inv_T, pose_error
from nap3d_graph.datasets import TumSequence
from nap3d_graph.motion.odometry import DenseVisualOdometry, make_odometry


def _step_errors(seq, odometry):
    odometry.prime(seq[0])
    errors, fallbacks = [], 0
    for i in range(1, len(seq)):
        inc = odometry.increment(i, seq[i])
        fallbacks += not inc.ok
        truth = inv_T(seq.T_world_cam_gt[i - 1]) @ seq.T_world_cam_gt[i]
        errors.append(pose_error(inc.T_prev_cur, truth)[0])
    return np.array(errors), fallbacks


def test_dense_odometry_follows_real_frames(tum_path):
    seq = TumSequence(tum_path)
    dense, fallbacks = _step_errors(seq, make_odometry("dense", seq))
    sift, _ = _step_errors(seq, make_odometry("vo", seq))
    # fr1/xyz moves about 12 mm between these frames: each step within a few millimetres,
    # no worse than the SIFT odometry at the median.
    assert fallbacks == 0 and np.median(dense) < 0.0035 and dense.max() < 0.006, dense
    assert np.median(dense) <= np.median(sift) + 0.0005


def test_a_step_the_depth_contradicts_falls_back_to_constant_velocity(tum_path):
    seq = TumSequence(tum_path)
    odometry = DenseVisualOdometry(seq.T_world_cam_gt[0])
    odometry.prime(seq[0])
    assert odometry.increment(1, seq[1]).ok
    # A frame whose depth is the previous one pushed 20 cm back: no rigid motion of a few
    # centimetres explains it, and the step is refused, not chained.
    far = seq[2].with_depth(seq[2].depth_m + np.float32(0.2))
    inc = odometry.increment(2, far)
    assert not inc.ok and inc.reason
    assert np.trace(inc.covariance) > 10 * np.trace(odometry._step_cov)


def test_the_depth_check_tells_a_right_step_from_a_wrong_one(tum_path):
    from nap3d_graph.conventions import exp_se3

    seq = TumSequence(tum_path)
    odometry = DenseVisualOdometry()
    prev, cur = odometry._frame(seq[3]), odometry._frame(seq[4])
    T_cur_prev = inv_T(seq.T_world_cam_gt[4]) @ seq.T_world_cam_gt[3]
    right = odometry._depth_residual(prev, cur, T_cur_prev)
    wrong = odometry._depth_residual(prev, cur, exp_se3([0, 0, 0, 0.0, 0.0, 0.08]) @ T_cur_prev)
    assert right < 0.01 and wrong > 0.05 > odometry.max_depth_residual_m, (right, wrong)
