"""Extended model (otbot_hw.model.effects): reduces to the paper's model, and each effect obeys its physics."""
import numpy as np
import pytest

from otbot_hw.model import compiled
from otbot_hw.model import effects as fx
from otbot_hw.model.dynamics import kinetic_energy
from otbot_hw.simulation.simulator import simulate, simulate_extended


def _torques(n=400, dt=0.01, seed=3):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * dt
    return np.column_stack([3 * np.sin(2 * np.pi * 0.4 * t + rng.uniform(0, 6)),
                            3 * np.sin(2 * np.pi * 0.3 * t + rng.uniform(0, 6)),
                            2 * np.sin(2 * np.pi * 0.7 * t)])


def test_zero_effects_is_the_papers_model(params):
    U = _torques()
    ext = simulate_extended(params, fx.effect_vector(), U, 0.01)
    ref = simulate(params, U, 0.01)
    assert np.max(np.abs(ext.x - ref.x)) < 1e-12
    # sample accelerations equal the compiled model's
    acc = np.array([compiled.accelerations(ref.x[k], ref.u[k], np.zeros(2), np.zeros(6), params.as_array())
                    for k in range(len(ref.t))])
    assert np.max(np.abs(ext.qdd - acc)) < 1e-9


def test_slope_conserves_energy_without_friction(params):
    """On a slope with no friction, kinetic + potential energy stays constant under zero torque."""
    p = params.replace(b_w=0.0, b_p=0.0)
    g = np.array([0.3, -0.2])
    eff = fx.effect_vector({"g_x": g[0], "g_y": g[1]})
    x0 = np.zeros(12)
    x0[6:] = fx_admissible(p, np.array([2.0, -1.0, 0.5]))
    tr = simulate_extended(p, eff, np.zeros((300, 3)), 0.01, x0=x0)

    def energy(x):
        q, qd = x[:6], x[6:]
        th, a = q[2] - q[5], q[2]
        b = q[:2] + np.array([np.cos(th) * p.x_B - np.sin(th) * p.y_B, np.sin(th) * p.x_B + np.cos(th) * p.y_B])
        f = q[:2] + np.array([np.cos(a) * p.x_F - np.sin(a) * p.y_F, np.sin(a) * p.x_F + np.cos(a) * p.y_F])
        return kinetic_energy(q, qd, p) - p.m_c * g @ b - p.m_p * g @ f

    e = np.array([energy(x) for x in tr.x])
    assert np.ptp(e) < 1e-6 * (1 + abs(e[0]))
    assert np.ptp([kinetic_energy(x[:6], x[6:], p) for x in tr.x]) > 1e-2  # the slope did work


def fx_admissible(p, phid):
    from otbot_hw.model.kinematics import admissible_velocity
    return admissible_velocity(np.zeros(6), phid, p)


def test_coulomb_friction_dissipates_power_c_times_speed(params):
    """Wheel Coulomb friction on the stand: I_a w_dot = tau - b w - c tanh(w / SIGN_RATE_WHEEL)."""
    eff = fx.effect_vector({"c_r": 0.4})
    tr = simulate_extended(params, eff, np.tile([1.0, 1.0, 0.0], (100, 1)), 0.01, fixture="stand")
    w_r, w_l = tr.x[-1, 9], tr.x[-1, 10]
    # steady state: tau = b w + c sgn w
    assert w_l == pytest.approx(1.0 / params.b_w, rel=1e-3)
    assert w_r == pytest.approx((1.0 - 0.4) / params.b_w, rel=1e-3)


def test_gain_saturation_and_lag_shape_the_delivered_torque(params):
    U = np.tile([10.0, -2.0, 4.0], (50, 1))
    eff = fx.ExtendedModel.paper(params).with_values({"k_r": -0.1, "u_max": 8.0, "T_i": 0.03}).eff
    tr = simulate_extended(params, eff, U, 0.01, fixture="stand")
    assert tr.tau[-1] == pytest.approx([8.0, -2.0, 4.0], abs=1e-4)  # 9 N m clipped to 8
    assert tr.tau[3, 2] == pytest.approx(4.0 * (1 - np.exp(-0.03 / 0.03)), rel=1e-9)


@pytest.mark.parametrize("dr_r,dr_l", [(0.03, -0.03), (0.04, 0.0)])
def test_unequal_wheel_radii_conserve_energy_and_scale_encoders(params, dr_r, dr_l):
    """Unequal radii (opposite changes, or one wheel only): work of the motors on the real wheel angles
    = change of the true kinetic energy (wheel inertia on phi = rho psi), and the encoders read
    phi_i = psi_i / (1 + dr_i)."""
    p = params.replace(b_w=0.0, b_p=0.0)
    eff = fx.effect_vector({"dr_r": dr_r, "dr_l": dr_l})
    U = _torques(300)
    tr = simulate_extended(p, eff, U, 0.01)
    s = fx.sensor_outputs(tr, p, eff)
    assert np.allclose(s["joint_pos"][:, 0], tr.x[:, 3] / (1 + dr_r), rtol=1e-12)
    assert np.allclose(s["joint_pos"][:, 1], tr.x[:, 4] / (1 + dr_l), rtol=1e-12)
    phi = s["joint_pos"]
    work = np.sum(U * np.diff(phi, axis=0))
    rho = np.array([1 / (1 + dr_r), 1 / (1 + dr_l)])

    def true_ke(x):
        return kinetic_energy(x[:6], x[6:], p) + 0.5 * p.I_a * np.sum((rho ** 2 - 1) * x[9:11] ** 2)

    assert true_ke(tr.x[-1]) - true_ke(tr.x[0]) == pytest.approx(work, rel=1e-6)
    # and the paper's model (equal radii) would not balance these encoder readings
    ref = simulate_extended(p, fx.effect_vector(), U, 0.01)
    assert abs(np.sum(U * np.diff(ref.x[:, 3:6], axis=0)) - work) > 1e-3 * abs(work)


def test_slip_makes_encoders_count_more_than_the_wheel_rolls(params):
    eff = fx.effect_vector({"k_slip": 0.05})
    U = np.tile([3.0, 3.0, 0.0], (100, 1))
    tr = simulate_extended(params, eff, U, 0.01)
    ref = simulate(params, U, 0.01)
    assert np.max(np.abs(tr.x - ref.x)) < 1e-12  # the body moves as without slip
    s = fx.sensor_outputs(tr, params, eff)
    assert np.all(s["joint_pos"][1:, :2] > tr.x[1:, 3:5])
    assert s["joint_vel"][-1, 0] - tr.x[-1, 9] == pytest.approx(0.05 * (3.0 - params.b_w * tr.x[-1, 9]), rel=1e-9)


def test_imu_sensor_effects(params):
    n = 5
    alpha, ad, add = np.full(n, 0.3), np.full(n, 2.0), np.full(n, 1.0)
    xdd, ydd = np.zeros(n), np.zeros(n)
    eff = fx.effect_vector({"d_x": 0.1, "b_ay": 0.05})
    acc, gyro = fx.imu_from_motion(alpha, ad, xdd, ydd, add, eff)
    assert acc[0, 0] == pytest.approx(-4.0 * 0.1)  # centripetal
    assert acc[0, 1] == pytest.approx(1.0 * 0.1 + 0.05)  # tangential + bias
    eff = fx.effect_vector({"g_x": 0.2})
    acc, _ = fx.imu_from_motion(np.zeros(n), np.zeros(n), xdd, ydd, np.zeros(n), eff)
    assert acc[0, 0] == pytest.approx(-0.2)  # specific force = a - g


def test_effect_vector_rejects_unknown_names():
    with pytest.raises(ValueError, match="unknown effect parameter"):
        fx.effect_vector({"friction": 1.0})


def test_runs_test_flags_structured_residuals_only():
    from otbot_hw.diagnose.locate import runs_test

    rng = np.random.default_rng(0)
    white = rng.standard_normal(400)
    assert runs_test(white)[1] > 0.01
    drift = np.sin(np.linspace(0, 6, 400)) + 0.1 * rng.standard_normal(400)
    assert runs_test(drift)[1] < 1e-6
