"""The kinematics written once and shared by Python and compiled callers: the entries give the paper's
matrices, the model state of a pose and twist is admissible, the EKF builds it with the true pivot angle,
and the one angle wrap."""
import math

import numpy as np
import pytest

from otbot_hw.estimation import kernels
from otbot_hw.estimation.ekf import EP, N_STATE, PoseEKF
from otbot_hw.model import compiled
from otbot_hw.model.angles import wrap_angle
from otbot_hw.model.kinematics import (constraint_jacobian, forward_kinematics_matrix, inverse_kinematics_matrix,
                                       inverse_kinematics_matrix_dot, model_state_into)
from otbot_hw.params import nominal

P = nominal()


@pytest.mark.parametrize("th", [-2.5, -0.3, 0.0, 1.1, 3.0])
def test_the_entries_give_inverse_matrices_and_the_derivative(th):
    q = np.array([0.3, -0.2, th + 0.4, 1.0, -2.0, 0.4])
    fik, iik = forward_kinematics_matrix(q, P), inverse_kinematics_matrix(q, P)
    np.testing.assert_allclose(fik @ iik, np.eye(3), atol=1e-12)
    qd = np.array([0.1, 0.2, 0.7, 0.0, 0.0, -0.5])
    h = 1e-6
    num = (inverse_kinematics_matrix(q + h * qd, P) - inverse_kinematics_matrix(q - h * qd, P)) / (2 * h)
    np.testing.assert_allclose(inverse_kinematics_matrix_dot(q, qd, P), num, atol=1e-7)


def test_the_model_state_of_a_pose_and_twist_is_admissible_in_python_and_compiled():
    rng = np.random.default_rng(1)
    for _ in range(20):
        pose, twist, phi_p = rng.uniform(-3, 3, 3), rng.uniform(-1, 1, 3), rng.uniform(-3, 3)
        py = np.empty(12)
        model_state_into(*pose, *twist, phi_p, P.l1, P.l2, P.r, py)
        x = np.concatenate([pose, twist])
        x = np.concatenate([x, np.zeros(N_STATE - 6)])
        cc = np.empty(12)
        kernels.model_state(x, phi_p, P.as_array(), cc)  # compiled, e_p = 0
        np.testing.assert_allclose(cc, py, atol=1e-15)
        assert py[5] == phi_p and np.all(py[6:9] == twist)
        np.testing.assert_allclose(constraint_jacobian(py[:6], P) @ py[6:], 0.0, atol=1e-12)


def test_the_ekf_evaluates_the_model_at_the_true_pivot_angle():
    """e_p = reading - true angle, so the model's pivot angle is the reading less e_p, in the compiled
    yaw-acceleration kernel and in the dynamic-model prediction alike (they once differed)."""
    ekf = PoseEKF(P, 0.01)
    ekf.initialize(0.0, (0.0, 0.0, 0.3), np.array([0.0, 0.0, 0.5]), twist=(0.4, -0.2, 0.6))
    ekf.kf.x[EP] = 0.01
    reading = ekf._phi_p  # the pivot reading (floored to whole counts)
    u = np.array([2.0, -1.0, 0.5])
    got = ekf._model_acceleration(ekf.kf.x, u)
    xs = np.empty(12)
    model_state_into(0.0, 0.0, 0.3, 0.4, -0.2, 0.6, reading - 0.01, P.l1, P.l2, P.r, xs)
    want = compiled.accelerations(xs, u, np.zeros(2), np.zeros(6), P.as_array())[:3]
    np.testing.assert_allclose(got, want, atol=1e-12)
    xs_reading = xs.copy()
    model_state_into(0.0, 0.0, 0.3, 0.4, -0.2, 0.6, reading, P.l1, P.l2, P.r, xs_reading)
    assert np.abs(compiled.accelerations(xs_reading, u, np.zeros(2), np.zeros(6), P.as_array())[:3] - got).max() > 1e-6
    # the compiled kernel with the measured acceleration equal to the model's: the model's alpha_dd
    assert kernels.yaw_acceleration(ekf.kf.x, reading, u, want[0], want[1], P.as_array()) == pytest.approx(want[2],
                                                                                                        abs=1e-9)


def test_one_angle_wrap_into_minus_pi_to_pi():
    assert wrap_angle(math.pi) == -math.pi and wrap_angle(-math.pi) == -math.pi
    assert wrap_angle(3 * math.pi + 0.1) == pytest.approx(-math.pi + 0.1)
    a = np.array([-7.0, -math.pi, 0.0, math.pi, 7.0])
    w = wrap_angle(a)
    assert np.all((w >= -math.pi) & (w < math.pi))
    np.testing.assert_allclose(np.cos(w), np.cos(a), atol=1e-12)
    np.testing.assert_allclose(np.sin(w), np.sin(a), atol=1e-12)
