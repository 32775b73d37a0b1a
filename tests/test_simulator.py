"""Simulator checks: energy balance, constraint invariants, fast vs reference, fixtures, stepping."""
import numpy as np
import pytest

from otbot_hw.model import dynamics as dyn
from otbot_hw.model import kinematics as kin
from otbot_hw.params import nominal
from otbot_hw.simulation.simulator import ForceSchedule, PivotForce, Stepper, simulate

DT = 0.01


def varied_torques(n: int, dt: float = DT, seed: int = 3) -> np.ndarray:
    """Time-varying torques (N m): sinusoids of different frequencies plus a random walk."""
    t = np.arange(n) * dt
    rng = np.random.default_rng(seed)
    walk = np.cumsum(rng.normal(scale=0.3, size=(n, 3)), axis=0)
    base = np.column_stack([6 * np.sin(2.1 * t), -8 * np.cos(1.3 * t) + 2, 5 * np.sin(3.7 * t + 0.4)])
    return base + np.clip(walk, -4, 4)


SCHEDULE = ForceSchedule([PivotForce(0.3, 0.6, 40.0, -25.0), PivotForce(1.1, 0.5, -30.0, 35.0)])


# --- energy balance ---------------------------------------------------------

def simpson_weights(sub: int) -> np.ndarray:
    w = np.ones(sub + 1)
    w[1:-1:2], w[2:-1:2] = 4, 2
    return w / 3


def test_kinetic_energy_change_equals_work_of_torques_friction_and_pivot_force(params):
    """T(t_k) - T(0) = integral of u.phi_dot - b_w(phi_r_dot^2 + phi_l_dot^2) - b_p phi_p_dot^2 + f.(x_dot, y_dot).

    T is summed body by body (independent of M). The run uses time-varying torques,
    a pivot force schedule and an off-centre platform and chassis; it is sampled
    ``sub`` times per ZOH interval (commands repeated: the same held input) and each
    power term is integrated by Simpson's rule interval by interval, where it is smooth.
    """
    sub, n = 10, 200
    Uk = varied_torques(n)
    Uk[:, 2] *= 3  # make the pivot do real work too
    Fk = SCHEDULE.sample(np.arange(n) * DT)
    traj = simulate(params, np.repeat(Uk, sub, axis=0), DT / sub, forces=np.repeat(Fk, sub, axis=0))
    T = np.array([dyn.kinetic_energy(q, qd, params) for q, qd in zip(traj.q, traj.qd)])
    idx = np.arange(n)[:, None] * sub + np.arange(sub + 1)[None, :]  # fine samples of interval k
    qd = traj.qd[idx]  # (n, sub + 1, 6)
    power = {
        "torque": np.einsum("kj,kij->ki", Uk, qd[..., 3:6]),
        "wheel friction": -params.b_w * (qd[..., 3] ** 2 + qd[..., 4] ** 2),
        "pivot friction": -params.b_p * qd[..., 5] ** 2,
        "pivot force": np.einsum("kj,kij->ki", Fk, qd[..., :2]),
    }
    w = simpson_weights(sub) * (DT / sub)
    work = {name: np.cumsum(pw @ w) for name, pw in power.items()}  # J, at t_1 .. t_n
    dT = T[sub::sub] - T[0]
    residual = np.abs(dT - sum(work.values())).max()
    smallest = min(np.abs(v).max() for v in work.values())
    assert smallest > 0.5, {k: np.abs(v).max() for k, v in work.items()}  # every term does real work
    assert residual < 1e-6 * smallest, residual
    # the check has teeth: a sign error in any one term breaks the balance by far more
    for name, v in work.items():
        assert np.abs(dT - (sum(work.values()) - 2 * v)).max() > 1e4 * residual, name


def test_no_friction_no_input_conserves_energy(params):
    """Without torques, friction or forces the kinetic energy stays constant while the robot moves."""
    p = params.replace(b_w=0.0, b_p=0.0)
    rng = np.random.default_rng(7)
    q0 = rng.uniform(-1, 1, 6)
    x0 = np.concatenate([q0, kin.admissible_velocity(q0, np.array([4.0, -2.0, 3.0]), p)])
    traj = simulate(p, np.zeros((300, 3)), DT, x0=x0)
    T = np.array([dyn.kinetic_energy(q, qd, p) for q, qd in zip(traj.q, traj.qd)])
    assert np.ptp(traj.q[:, 2]) > 1.0  # it really turns
    assert np.abs(T - T[0]).max() < 1e-9 * T[0]


# --- constraints ------------------------------------------------------------

@pytest.mark.parametrize("start", ["rest", "moving"])
def test_constraints_hold_over_ten_seconds(params, start):
    """J(q) q_dot = 0 and the holonomic constraint hold to 1e-8 over 10 s of varied torques."""
    x0 = None
    if start == "moving":
        q0 = np.array([0.4, -1.2, 0.7, 3.0, -2.0, 1.1])
        x0 = np.concatenate([q0, kin.admissible_velocity(q0, np.array([5.0, 2.0, -3.0]), params)])
    traj = simulate(params, varied_torques(1000), DT, x0=x0)
    jq = max(np.abs(kin.constraint_jacobian(q, params) @ qd).max() for q, qd in zip(traj.q, traj.qd))
    hol = max(abs(kin.holonomic_constraint(q, traj.q[0], params)) for q in traj.q)
    assert np.hypot(*traj.q[-1, :2] - traj.q[0, :2]) > 0.5  # the robot went somewhere
    assert jq <= 1e-8
    assert hol <= 1e-8


# --- fast vs reference ------------------------------------------------------

def test_fast_matches_reference_on_chassis_experiment():
    p = nominal()
    U = np.tile([6.0, -10.0, 6.0], (300, 1))
    fast = simulate(p, U, DT)
    ref = simulate(p, U, DT, method="reference")
    assert np.abs(fast.x - ref.x).max() <= 1e-8
    assert np.abs(ref.q[-1, :2]).max() > 0.1  # nontrivial motion


def test_fast_matches_reference_with_force_schedule(params):
    U = varied_torques(150)
    fast = simulate(params, U, DT, forces=SCHEDULE)
    ref = simulate(params, U, DT, forces=SCHEDULE, method="reference")
    free = simulate(params, U, DT)
    assert np.abs(free.x - fast.x).max() > 1e-2  # the force matters
    assert np.abs(fast.x - ref.x).max() <= 1e-8


@pytest.mark.parametrize("fixture", ["stand", "locked"])
def test_fast_matches_reference_on_fixtures(params, fixture):
    U = varied_torques(150)
    fast = simulate(params, U, DT, fixture=fixture)
    ref = simulate(params, U, DT, fixture=fixture, method="reference")
    assert np.abs(fast.x - ref.x).max() <= 1e-8


# --- fixtures against closed-form solutions ---------------------------------

def test_locked_fixture_is_first_order_pivot_response(params):
    """Locked wheels: (I_p + m_p|PF|^2) w' = tau_p - b_p w, so w(t) = tau/b_p (1 - exp(-b_p t / I))."""
    tau = 3.0
    traj = simulate(params, np.tile([5.0, -5.0, tau], (200, 1)), DT, fixture="locked")
    inertia = params.I_p + params.m_p * (params.x_F ** 2 + params.y_F ** 2)
    w = tau / params.b_p * (1 - np.exp(-params.b_p * traj.t / inertia))
    assert np.allclose(traj.qd[:, 5], w, rtol=0, atol=1e-9)
    assert np.array_equal(traj.qd[:, 5], traj.qd[:, 2])  # alpha follows phi_p
    assert np.all(traj.x[:, [0, 1, 3, 4, 6, 7, 9, 10]] == 0)  # chassis and wheels do not move


def test_stand_fixture_wheels_spin_freely(params):
    """On the stand each wheel is I_a w' = tau - b_w w with time constant I_a / b_w."""
    traj = simulate(params, np.tile([0.5, -0.2, 0.0], (100, 1)), DT, fixture="stand")
    tc = params.I_a / params.b_w
    for j, tau in ((3, 0.5), (4, -0.2)):
        w = tau / params.b_w * (1 - np.exp(-traj.t / tc))
        assert np.allclose(traj.qd[:, j], w, rtol=0, atol=1e-8)
    assert np.all(traj.q[:, :2] == 0)


# --- ZOH semantics, stepping and input checks --------------------------------

def test_zoh_command_takes_effect_in_its_own_interval(params):
    """u_k acts on [t_k, t_k+1): a torque first applied at k = 5 leaves x_0..x_5 at rest."""
    U = np.zeros((10, 3))
    U[5:] = [4.0, 4.0, 0.0]
    traj = simulate(params, U, DT)
    assert np.all(traj.x[:6] == 0)
    assert np.abs(traj.qd[6, 3]) > 0.01


def test_force_schedule_is_sampled_at_interval_starts():
    s = ForceSchedule([PivotForce(0.05, 0.03, 2.0, -1.0), PivotForce(0.06, 0.1, 1.0, 0.0)])
    t = np.arange(10) * DT
    F = s.sample(t)
    assert np.array_equal(F[4], [0, 0]) and np.array_equal(F[5], [2, -1])
    assert np.array_equal(F[6], [3, -1]) and np.array_equal(F[7], [3, -1])
    assert np.array_equal(F[8], [1, 0])


def test_stepper_reproduces_batch_simulation(params):
    U = varied_torques(50)
    F = SCHEDULE.sample(np.arange(50) * DT)
    batch = simulate(params, U, DT, forces=F)
    st = Stepper(params, DT)
    for k in range(50):
        st.step(U[k], F[k])
    assert np.array_equal(st.x, batch.x[-1])
    assert st.t == pytest.approx(0.5)


@pytest.mark.parametrize("kwargs, match", [
    ({"torques": np.array([[1.0, np.nan, 0.0]])}, "NaN"),
    ({"torques": np.zeros((3, 2))}, "shape"),
    ({"dt": -0.01}, "sample period"),
    ({"dt": 0.0}, "sample period"),
    ({"x0": np.zeros(11)}, "initial state"),
    ({"fixture": "ceiling"}, "unknown fixture"),
    ({"method": "euler"}, "unknown method"),
    ({"forces": np.full((1, 2), np.inf)}, "pivot forces"),
])
def test_simulate_rejects_bad_input(params, kwargs, match):
    args = {"torques": np.zeros((1, 3)), "dt": DT, **kwargs}
    with pytest.raises(ValueError, match=match):
        simulate(params, **args)


# --- the compiled model's extra generalized force hook ----------------------------

def test_compiled_extra_generalized_force_matches_augmented_system(params):
    """compiled.accelerations with ``gen`` solves M q_dd + C q_d + J^T lambda = E u + E_f q_d + Q_p + gen."""
    from otbot_hw.model import compiled
    from otbot_hw.model.fixtures import fixture_code, held_chassis_accelerations

    rng = np.random.default_rng(21)
    for _ in range(20):
        q = rng.uniform(-3, 3, 6)
        qd = kin.admissible_velocity(q, rng.normal(scale=3.0, size=3), params)
        u, f, gen = rng.normal(scale=5, size=3), rng.normal(scale=20, size=2), rng.normal(scale=5, size=6)
        J = kin.constraint_jacobian(q, params)
        A = np.zeros((9, 9))
        A[:6, :6], A[:6, 6:], A[6:, :6] = dyn.mass_matrix(q, params), J.T, J
        rhs = np.concatenate([
            dyn.actuation_matrix() @ u + (dyn.friction_matrix(params) - dyn.coriolis_matrix(q, qd, params)) @ qd
            + dyn.pivot_force_generalized(f) + gen,
            -kin.constraint_jacobian_dot(q, qd, params) @ qd])
        expect = np.linalg.solve(A, rhs)[:6]
        x = np.concatenate([q, qd])
        got = compiled.accelerations(x, u, f, gen, params.as_array())
        assert np.abs(got - expect).max() < 1e-10
        for fixture in ("stand", "locked"):
            got = compiled.derivative(x, u, f, gen, params.as_array(), fixture_code(fixture))[6:]
            assert np.abs(got - held_chassis_accelerations(qd, u, params, fixture, gen)).max() < 1e-12


def test_chunked_integration_is_bit_identical_to_one_call():
    """``simulate`` integrates in chunks (Ctrl-C and progress between them): the same numbers bit for bit
    as one compiled call over every interval, whatever the chunk size, with the progress counted."""
    from otbot_hw.simulation.integrators import rk4_zoh
    from otbot_hw.simulation.simulator import default_substeps

    p = nominal()
    rng = np.random.default_rng(3)
    U = rng.uniform(-8, 8, (257, 3))
    F = rng.uniform(-5, 5, (257, 2))
    one = rk4_zoh(np.zeros(12), U, F, 0.01, default_substeps(0.01), p.as_array(), 0)
    for chunk in (1, 7, 100, 256, 257, 1000):
        seen = []
        traj = simulate(p, U, 0.01, forces=F, chunk=chunk, progress=lambda d, n: seen.append((d, n)))
        assert np.array_equal(traj.x, one), chunk
        assert seen[-1] == (257, 257) and len(seen) == -(-257 // chunk)


@pytest.mark.parametrize("effects", [{"k_slip": 0.02}, {"k_slip": 0.02, "c_r": 0.3, "T_i": 0.01}])
def test_chunked_extended_integration_is_bit_identical_to_one_call(effects):
    """``simulate_extended`` in chunks (without a current lag; with one it makes one call): the states,
    delivered torques, slip angles, accelerations and slip rates of one compiled call, bit for bit."""
    from otbot_hw.model.effect_catalog import EFFECT_INDEX, effect_vector
    from otbot_hw.simulation.integrators import ext_rk4_zoh_samples
    from otbot_hw.simulation.simulator import default_substeps, simulate_extended

    p = nominal()
    eff = effect_vector()
    for name, value in effects.items():
        eff[EFFECT_INDEX[name]] = value
    rng = np.random.default_rng(4)
    U = rng.uniform(-10, 10, (203, 3))
    F = rng.uniform(-5, 5, (203, 2))
    one = ext_rk4_zoh_samples(np.zeros(12), np.zeros(3), U, F, 0.01, default_substeps(0.01), p.as_array(), eff, 0)
    assert np.abs(one[2]).max() > 0  # the wheels slipped: the slip sum goes on across chunks
    for chunk in (1, 10, 202, 203, 500):
        seen = []
        traj = simulate_extended(p, eff, U, 0.01, forces=F, chunk=chunk, progress=lambda d, n: seen.append(d))
        for got, want in zip((traj.x, traj.tau, traj.slip, traj.qdd, traj.slip_rate), one):
            assert np.array_equal(got, want), chunk
        assert not seen or seen[-1] == 203
