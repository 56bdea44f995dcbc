"""IMU factor builders: preintegration and CombinedImuFactor on closed-form cases."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from factor_helpers import G
from gtsam.symbol_shorthand import B, V, X

from nap3d_graph.factors import imu_factor, imu_params, preintegrate

# --- IMU -------------------------------------------------------------------------------


@pytest.fixture
def params():
    return imu_params(accel_noise_density=0.01, gyro_noise_density=0.001,
                      accel_bias_rw=1e-4, gyro_bias_rw=1e-5, gravity=G)


def uniform_samples(rate_hz: float, duration_s: float, accel, gyro):
    stamps = np.arange(0.0, duration_s + 1e-9, 1.0 / rate_hz)
    n = len(stamps)
    return stamps, np.tile(np.asarray(accel, float), (n, 1)), np.tile(np.asarray(gyro, float), (n, 1))


def test_imu_at_rest_predicts_no_motion(params):
    stamps, acc, gyr = uniform_samples(200, 1.0, [0, 0, G], [0, 0, 0])
    pim = preintegrate(params, None, stamps, acc, gyr, 0.0, 1.0)
    assert pim.deltaTij() == pytest.approx(1.0, abs=1e-12)
    state = pim.predict(gtsam.NavState(gtsam.Pose3(), np.zeros(3)), gtsam.imuBias.ConstantBias())
    np.testing.assert_allclose(state.pose().matrix(), np.eye(4), atol=1e-9)
    np.testing.assert_allclose(state.velocity(), np.zeros(3), atol=1e-9)


def test_imu_constant_yaw_rate_gives_yaw(params):
    w = 0.7
    stamps, acc, gyr = uniform_samples(100, 1.0, [0, 0, G], [0, 0, w])
    pim = preintegrate(params, None, stamps, acc, gyr, 0.0, 1.0)
    np.testing.assert_allclose(pim.deltaRij().matrix(), gtsam.Rot3.Yaw(w).matrix(), atol=1e-12)
    assert pim.deltaRij().yaw() == pytest.approx(w, abs=1e-12)


def test_preintegrate_cuts_partial_first_and_last_intervals(params):
    stamps = np.arange(11) * 0.1
    gyro = np.zeros((11, 3))
    gyro[:, 2] = np.arange(11)  # sample k reads k rad/s of yaw
    acc = np.tile([0, 0, G], (11, 1))
    pim = preintegrate(params, None, stamps, acc, gyro, 0.05, 0.35)
    assert pim.deltaTij() == pytest.approx(0.30, abs=1e-12)
    # [0.05, 0.1) sample 0, [0.1, 0.2) sample 1, [0.2, 0.3) sample 2, [0.3, 0.35) sample 3
    assert pim.deltaRij().yaw() == pytest.approx(0.05 * 0 + 0.1 * 1 + 0.1 * 2 + 0.05 * 3, abs=1e-12)
    # Consecutive keyframe intervals add up: no time lost or counted twice.
    a = preintegrate(params, None, stamps, acc, gyro, 0.05, 0.23).deltaRij().yaw()
    b = preintegrate(params, None, stamps, acc, gyro, 0.23, 0.35).deltaRij().yaw()
    assert a + b == pytest.approx(0.45, abs=1e-12)
    with pytest.raises(ValueError, match="t_end > t_start"):
        preintegrate(params, None, stamps, acc, gyro, 0.3, 0.3)
    with pytest.raises(ValueError, match="shape"):
        preintegrate(params, None, stamps, acc[:, :2], gyro, 0.0, 0.3)
    acc_nan = acc.copy()
    acc_nan[2] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        preintegrate(params, None, stamps, acc_nan, gyro, 0.0, 0.3)
    preintegrate(params, None, stamps, acc_nan, gyro, 0.5, 0.7)  # NaN outside the interval is fine


def test_combined_imu_factor_zero_error_at_true_states(params):
    # Constant world acceleration, constant tilted attitude, non-zero velocity and bias:
    # the accelerometer reads R^T (a + g_up) + b_a, which is constant, so ZOH is exact.
    R0 = gtsam.Rot3.Ypr(0.4, -0.1, 0.2)
    p0, v0, a_world = np.array([1.0, 2.0, 0.5]), np.array([0.3, -0.2, 0.1]), np.array([0.5, -0.2, 0.1])
    bias = gtsam.imuBias.ConstantBias(np.array([0.02, -0.01, 0.03]), np.array([0.001, 0.002, -0.001]))
    T = 1.0
    f_body = R0.matrix().T @ (a_world + np.array([0, 0, G])) + bias.accelerometer()
    stamps, acc, gyr = uniform_samples(200, T, f_body, bias.gyroscope())
    pim = preintegrate(params, bias, stamps, acc, gyr, 0.0, T)
    factor = imu_factor(X(0), V(0), X(1), V(1), B(0), B(1), pim)
    assert isinstance(factor, gtsam.CombinedImuFactor)
    v = gtsam.Values()
    v.insert(X(0), gtsam.Pose3(R0, p0))
    v.insert(V(0), v0)
    v.insert(X(1), gtsam.Pose3(R0, p0 + v0 * T + 0.5 * a_world * T ** 2))
    v.insert(V(1), v0 + a_world * T)
    v.insert(B(0), bias)
    v.insert(B(1), bias)
    error = factor.unwhitenedError(v)
    assert error.shape == (15,)
    np.testing.assert_allclose(error, np.zeros(15), atol=1e-9)
    # A wrong end position is seen by the factor.
    v.update(X(1), gtsam.Pose3(R0, p0 + v0 * T + 0.5 * a_world * T ** 2 + np.array([0.1, 0, 0])))
    assert np.linalg.norm(factor.unwhitenedError(v)) > 0.05


def test_imu_params_validate():
    with pytest.raises(ValueError, match="gyro_noise_density"):
        imu_params(0.01, -1.0, 1e-4, 1e-5)
    p = imu_params(0.02, 0.003, 1e-4, 1e-5, gravity=9.8)
    np.testing.assert_allclose(p.n_gravity, [0, 0, -9.8])
    np.testing.assert_allclose(p.getAccelerometerCovariance(), 0.02 ** 2 * np.eye(3))
    np.testing.assert_allclose(p.getGyroscopeCovariance(), 0.003 ** 2 * np.eye(3))
