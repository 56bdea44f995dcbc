"""A keyframe interval's covariance from its odometry steps (issue 62's too-cautious gate):
frame registration noise cancels inside a chain, the walk adds up."""

import numpy as np

from nap3d_graph.conventions import compose_covariance, exp_se3, inv_T, log_se3
from nap3d_graph.datasets.tum import TumSequence
from nap3d_graph.motion.interval import IntervalCovariance
from nap3d_graph.motion.odometry import VisualOdometry

STEP = np.array([0.02, -0.01, 0.015, 0.03, 0.005, -0.01])  # a hand-held step: ~1 deg, 3 cm
FRAME_SIGMA = np.array([4e-3] * 3 + [3e-3] * 3)  # each frame's own registration error
WALK_SIGMA = np.array([1e-3] * 3 + [1e-3] * 3)  # what each step adds that nothing cancels


def _simulated_chains(rng, steps: int, trials: int) -> tuple[np.ndarray, np.ndarray]:
    """(trials, 6) errors of chains of ``steps`` measured steps against the true chain (right
    perturbation), each frame registered with its own error and each step with a walk error;
    and the true steps (steps, 4, 4)."""
    T_step = exp_se3(STEP)
    errors = np.empty((trials, 6))
    for t in range(trials):
        frame_err = [exp_se3(rng.normal(0.0, FRAME_SIGMA)) for _ in range(steps + 1)]
        T_meas = np.eye(4)
        for k in range(steps):
            # frame k+1 seen from frame k, each frame off by its own error, plus the step's walk
            measured = inv_T(frame_err[k]) @ T_step @ frame_err[k + 1] @ exp_se3(rng.normal(0.0, WALK_SIGMA))
            T_meas = T_meas @ measured
        T_true = np.linalg.matrix_power(T_step, steps)
        errors[t] = log_se3(inv_T(T_true) @ T_meas)
    return errors, np.repeat(T_step[None], steps, axis=0)


def _nees(errors: np.ndarray, cov: np.ndarray) -> float:
    return float(np.mean(np.einsum("ti,ij,tj->t", errors, np.linalg.inv(cov), errors)))


def test_frame_noise_cancels_inside_a_chain_and_the_walk_adds_up():
    rng = np.random.default_rng(0)
    frame_noise = 2.0 * np.diag(FRAME_SIGMA**2)  # a step's two frames, half each
    step_cov = frame_noise + np.diag(WALK_SIGMA**2)
    for steps in (1, 5):
        errors, T_steps = _simulated_chains(rng, steps, 3000)
        interval, independent = IntervalCovariance(), np.zeros((6, 6))
        for T in T_steps:
            interval.add(T, step_cov, frame_noise)
            independent = compose_covariance(independent, T, step_cov)
        # Consistent: the mean NEES of 6 dof is 6 (3000 draws: within a few percent).
        assert 5.5 < _nees(errors, interval.value) < 6.5, steps
        if steps == 1:
            np.testing.assert_allclose(interval.value, step_cov, atol=1e-15)
        else:  # the steps chained as independent count the inner frames' noise twice each
            assert _nees(errors, independent) < 0.5 * 6


def test_an_interval_without_frame_noise_is_the_steps_chained_as_independent():
    interval, independent = IntervalCovariance(), np.zeros((6, 6))
    assert not interval.value.any()
    cov = np.diag([1e-4] * 3 + [4e-4] * 3)
    for k in range(4):
        T = exp_se3(STEP * (k + 1))
        interval.add(T, cov)
        independent = compose_covariance(independent, T, cov)
    np.testing.assert_allclose(interval.value, independent, atol=1e-15)
    interval.reset()
    assert not interval.value.any()


def test_the_feature_odometry_says_which_part_of_its_steps_is_the_frames_own_noise(tum_path):
    seq = TumSequence(tum_path)
    odometry = VisualOdometry(seq.T_world_cam_gt[0], width=160)
    odometry.prime(seq[0])
    for i in range(1, 4):
        inc = odometry.increment(i, seq[i])
        assert inc.ok and inc.frame_noise is not None
        # The frames' noise is part of the step's covariance, never more than all of it.
        assert np.linalg.eigvalsh(inc.covariance - inc.frame_noise).min() > 0
        assert np.count_nonzero(inc.frame_noise - np.diag(np.diag(inc.frame_noise))) == 0
