"""Model invariants: each test checks a property, not the formula typed twice."""
import numpy as np
import pytest

from otbot_hw.model import dynamics as dyn
from otbot_hw.model import kinematics as kin
from otbot_hw.model import task_space as ts
from otbot_hw.model import compiled


def random_state(rng, p):
    q = rng.uniform(-3, 3, size=6)
    qd = kin.admissible_velocity(q, rng.normal(scale=3.0, size=3), p)
    return q, qd


def test_mass_matrix_symmetric_positive_definite(params, rng):
    for _ in range(20):
        q, _ = random_state(rng, params)
        M = dyn.mass_matrix(q, params)
        assert np.allclose(M, M.T, atol=0)
        assert np.linalg.eigvalsh(M).min() > 0


def test_mass_matrix_is_hessian_of_body_kinetic_energy(params, rng):
    """T is quadratic in q_dot, so the Hessian from finite differences is exact up to rounding."""
    q, qd = random_state(rng, params)
    h = 1e-3
    H = np.zeros((6, 6))
    E = np.eye(6) * h
    T = lambda v: dyn.kinetic_energy(q, v, params)
    for i in range(6):
        for j in range(6):
            H[i, j] = (T(qd + E[i] + E[j]) - T(qd + E[i] - E[j]) - T(qd - E[i] + E[j]) + T(qd - E[i] - E[j])) / (4 * h * h)
    assert np.allclose(H, dyn.mass_matrix(q, params), atol=1e-6)


def test_coriolis_matches_christoffel_construction(params, rng):
    q, qd = random_state(rng, params)
    h = 1e-6
    dM = np.zeros((6, 6, 6))  # dM[k] = dM/dq_k
    for k in range(6):
        e = np.zeros(6)
        e[k] = h
        dM[k] = (dyn.mass_matrix(q + e, params) - dyn.mass_matrix(q - e, params)) / (2 * h)
    C = np.zeros((6, 6))
    for i in range(6):
        for j in range(6):
            C[i, j] = 0.5 * sum((dM[k][i, j] + dM[j][i, k] - dM[i][k, j]) * qd[k] for k in range(6))
    assert np.allclose(C, dyn.coriolis_matrix(q, qd, params), atol=1e-6)


def test_delta_annihilates_constraints_and_selects_torques(params, rng):
    q, _ = random_state(rng, params)
    D = ts.delta_matrix(q, params)
    assert np.abs(kin.constraint_jacobian(q, params) @ D).max() < 1e-14
    assert np.allclose(D.T @ dyn.actuation_matrix(), np.eye(3), atol=0)


def test_kinematic_matrices_inverse_and_determinant(params, rng):
    for _ in range(10):
        q, _ = random_state(rng, params)
        F = kin.forward_kinematics_matrix(q, params)
        assert np.allclose(kin.inverse_kinematics_matrix(q, params) @ F, np.eye(3), atol=1e-13)
        assert np.linalg.det(F) == pytest.approx(-params.l1 * params.r ** 2 / (2 * params.l2), rel=1e-12)


def test_jacobian_dot_is_time_derivative(params, rng):
    q, qd = random_state(rng, params)
    h = 1e-6
    num = (kin.constraint_jacobian(q + h * qd, params) - kin.constraint_jacobian(q - h * qd, params)) / (2 * h)
    assert np.allclose(num, kin.constraint_jacobian_dot(q, qd, params), atol=1e-8)
    num = (kin.inverse_kinematics_matrix(q + h * qd, params) - kin.inverse_kinematics_matrix(q - h * qd, params)) / (2 * h)
    assert np.allclose(num, kin.inverse_kinematics_matrix_dot(q, qd, params), atol=1e-7)


def test_conventional_and_multiplier_free_forward_dynamics_agree(params, rng):
    for _ in range(50):
        q, qd = random_state(rng, params)
        u = rng.normal(scale=10, size=3)
        f = rng.normal(scale=50, size=2)
        a9, _ = dyn.forward_dynamics_conventional(q, qd, u, params, f)
        a6 = dyn.forward_dynamics(q, qd, u, params, f)
        ac = compiled.accelerations(np.concatenate([q, qd]), u, f, np.zeros(6), params.as_array())
        assert np.abs(a9 - a6).max() < 1e-10
        assert np.abs(ac - a6).max() < 1e-10
        # the accelerations satisfy the acceleration constraint
        assert np.abs(kin.constraint_jacobian(q, params) @ a6 + kin.constraint_jacobian_dot(q, qd, params) @ qd).max() < 1e-10


def test_inverse_of_forward_is_identity(params, rng):
    for _ in range(20):
        q, qd = random_state(rng, params)
        u = rng.normal(scale=10, size=3)
        f = rng.normal(scale=50, size=2)
        qdd = dyn.forward_dynamics(q, qd, u, params, f)
        assert np.allclose(dyn.inverse_dynamics(q, qd, qdd, params, f), u, atol=1e-9)
        u2, lam = dyn.inverse_dynamics_conventional(q, qd, qdd, params, f)
        assert np.allclose(u2, u, atol=1e-9)
        _, lam9 = dyn.forward_dynamics_conventional(q, qd, u, params, f)
        assert np.allclose(lam, lam9, atol=1e-8)


def test_task_space_model_reproduces_torques(params, rng):
    q, qd = random_state(rng, params)
    u = rng.normal(scale=10, size=3)
    qdd = dyn.forward_dynamics(q, qd, u, params)
    Mbar, Cbar = ts.task_space_model(q, qd, params)
    assert np.allclose(Mbar @ qdd[:3] + Cbar @ qd[:3], u, atol=1e-9)
