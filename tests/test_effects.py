"""Extended model (otbot_hw.model.effects): reduces to the paper's model, and each effect obeys its physics."""
import numpy as np
import pytest

from otbot_hw.model import compiled
from otbot_hw.model import effect_physics as phys
from otbot_hw.model import effects as fx
from otbot_hw.model import sensor_model
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
    s = sensor_model.sensor_outputs(tr, p, eff)
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
    s = sensor_model.sensor_outputs(tr, params, eff)
    assert np.all(s["joint_pos"][1:, :2] > tr.x[1:, 3:5])
    # creep k_slip times the torque passed to the ground: the command less the motor's friction and the
    # torque that accelerates the wheel itself (I_a times its rolling acceleration)
    acc = phys.ext_accelerations(tr.x[-1], np.array([3.0, 3.0, 0.0]), np.zeros(2), eff, params.as_array(),
                                 compiled.FLOOR)
    expected = 0.05 * (3.0 - params.b_w * tr.x[-1, 9] - params.I_a * acc[3])
    assert s["joint_vel"][-1, 0] - tr.x[-1, 9] == pytest.approx(expected, rel=1e-9)
    assert abs(params.I_a * acc[3]) > 1e-3  # the inertia term is there to be checked


def test_imu_sensor_effects(params):
    n = 5
    alpha, ad, add = np.full(n, 0.3), np.full(n, 2.0), np.full(n, 1.0)
    xdd, ydd = np.zeros(n), np.zeros(n)
    eff = fx.effect_vector({"d_x": 0.1, "b_ay": 0.05})
    acc, gyro = sensor_model.imu_from_motion(alpha, ad, xdd, ydd, add, eff)
    assert acc[0, 0] == pytest.approx(-4.0 * 0.1)  # centripetal
    assert acc[0, 1] == pytest.approx(1.0 * 0.1 + 0.05)  # tangential + bias
    eff = fx.effect_vector({"g_x": 0.2})
    acc, _ = sensor_model.imu_from_motion(np.zeros(n), np.zeros(n), xdd, ydd, np.zeros(n), eff)
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


def test_each_motor_saturates_at_its_own_limit():
    eff = fx.effect_vector({"u_max_r": 3.0, "u_max_p": 1.5})
    assert np.allclose(phys.actuated_torque(np.array([5.0, -7.0, -2.0]), eff), [3.0, -7.0, -1.5])
    tied = fx.ExtendedModel.paper(nominal_params()).with_values({"u_max": 2.0})
    assert tied.get("u_max") == 2.0 and np.allclose(tied.eff[[fx.U_MAX_R, fx.U_MAX_L, fx.U_MAX_P]], 2.0)


def nominal_params():
    from otbot_hw.params import nominal

    return nominal()


@pytest.mark.parametrize("tau_tr", [0.5, 2.0, 2.9, 3.5, 8.0, -6.0, 0.0])
def test_traction_limited_slip_solves_the_wheel_balance(tau_tr):
    """sigma solves tau_tr - b sigma = T y / sqrt(1 + y^2), y = sigma / (k T); the ground torque never exceeds
    T; below the limit the wheel creeps k tau, above it spins up until viscous friction takes the excess."""
    k, T, b = 0.02, 3.0, 0.18
    eff = fx.effect_vector({"k_slip": k, "t_trac": T})
    sigma, tg = phys.slip_state(tau_tr, b, eff)
    y = sigma / (k * T)
    assert tau_tr - b * sigma == pytest.approx(T * y / np.sqrt(1 + y * y), abs=1e-9)
    assert tg == pytest.approx(tau_tr - b * sigma, abs=1e-9) and abs(tg) <= T
    if abs(tg) < 0.999 * T:
        u = tg / T
        assert sigma == pytest.approx(k * T * u / np.sqrt(1 - u * u), rel=1e-7, abs=1e-12)  # on the traction curve
    if abs(tau_tr) < 0.2 * T:
        assert sigma == pytest.approx(k * tau_tr, rel=0.03)  # linear creep
    if abs(tau_tr) > 2 * T:
        assert sigma == pytest.approx((tau_tr - np.sign(tau_tr) * T) / b, rel=0.01)
    # no traction limit: the linear creep law
    assert phys.slip_state(tau_tr, b, fx.effect_vector({"k_slip": k})) == pytest.approx((k * tau_tr, tau_tr))


def test_the_traction_knee_default_is_the_magic_formula_and_stays_last_in_the_effect_vector():
    """kn_trac absent/0 takes the closed form T y / sqrt(1 + y^2) (the curve before the knee parameter, bit for
    bit); the general form tanh(asinh y) agrees with it; kn_trac is the last entry (no saved index moves), not
    a discovered law, and bounded."""
    from otbot_hw.model import effect_catalog as ec
    from otbot_hw.model import slip_law

    assert ec.EFFECT_PARAM_NAMES[-1] == "kn_trac" and ec.KN_TRAC == ec.N_EFFECT - 1
    assert ec.EFFECT_INDEX["t_trac"] == ec.T_TRAC == 21 and ec.EFFECT_INDEX["cogph_p"] == ec.KN_TRAC - 1
    assert "kn_trac" not in ec.DISCOVERED_PARAMS and "cogph_p" in ec.DISCOVERED_PARAMS
    assert fx.effect_vector()[ec.KN_TRAC] == 0.0
    for bad in (-3.5, 5.01):
        with pytest.raises(ValueError, match="kn_trac"):
            fx.effect_vector({"kn_trac": bad})
    k, T = 0.02, 3.0
    for s in (-3.0, -0.05, 0.0, 0.01, 0.06, 0.5, 40.0):
        y = s / (k * T)
        assert slip_law.traction_curve(s, k, T) == T * y / np.sqrt(1.0 + y * y)  # exact: the closed form
        assert slip_law._knee(s, k, T, 1e-300)[0] == pytest.approx(T * y / np.sqrt(1.0 + y * y), rel=1e-13,
                                                                  abs=1e-300)  # the general form


@pytest.mark.parametrize("kn", [-2.0, 0.5, 1.0, 1.7, 3.0])
@pytest.mark.parametrize("tau_tr", [0.3, 2.5, 2.95, 8.0, -6.0])
def test_every_traction_knee_keeps_the_creep_slope_and_the_limit(kn, tau_tr):
    """sigma solves the wheel balance on the curve T tanh(h(y)); |tau_g| <= T; the creep slope is k whatever the
    knee (small torques creep k tau); far above the limit the excess goes to viscous friction; the curve's
    slope is the one Newton uses; kn = 1 is T tanh y and kn = 3 the hard clip, exactly."""
    from otbot_hw.model import slip_law

    k, T, b = 0.02, 3.0, 0.18
    eff = fx.effect_vector({"k_slip": k, "t_trac": T, "kn_trac": kn})
    sigma, tg = phys.slip_state(tau_tr, b, eff)
    assert tau_tr - b * sigma == pytest.approx(slip_law.traction_curve(sigma, k, T, kn), abs=1e-9)
    assert tg == pytest.approx(tau_tr - b * sigma, abs=1e-9) and abs(tg) <= T
    if abs(tau_tr) < 0.15 * T:
        assert sigma == pytest.approx(k * tau_tr, rel=0.05)
    if abs(tau_tr) > 2 * T:
        assert sigma == pytest.approx((tau_tr - np.sign(tau_tr) * T) / b, rel=0.05)
    s = np.linspace(-0.3, 0.3, 3001)
    curve = np.array([slip_law.traction_curve(x, k, T, kn) for x in s])
    slope = np.array([slip_law._knee(x, k, T, kn)[1] for x in s])
    smooth = np.abs(np.abs(s / (k * T)) - 1.0) > 0.01  # (the clip's kink)
    assert np.allclose(np.gradient(curve, s)[1:-1][smooth[1:-1]], slope[1:-1][smooth[1:-1]], rtol=2e-2, atol=0.2)
    assert slope[1500] == pytest.approx(1.0 / k)  # creep slope at zero slip
    assert np.all(np.abs(curve) <= T) and abs(curve[-1]) > 0.85 * T
    if kn == 1.0:
        assert np.allclose(curve, T * np.tanh(s / (k * T)), rtol=1e-12, atol=1e-12)
    if kn == 3.0:
        assert np.allclose(curve, T * np.clip(s / (k * T), -1, 1), rtol=1e-9, atol=1e-9)


def test_saturated_traction_limits_the_body_and_races_the_encoders(params):
    U = np.tile([8.0, 8.0, 0.0], (60, 1))
    lim = fx.effect_vector({"k_slip": 0.02, "t_trac": 3.0})
    tr = simulate_extended(params, lim, U, 0.01)
    free = simulate_extended(params, fx.effect_vector({"k_slip": 0.02}), U, 0.01)
    assert np.max(np.abs(tr.qdd[:, 0])) < 0.45 * np.max(np.abs(free.qdd[:, 0]))  # ~3 of 8 N m reach the ground
    s = sensor_model.sensor_outputs(tr, params, lim)
    assert np.all(s["joint_vel"][10:, :2] > tr.x[10:, 9:11] + 5.0)  # the wheels spin far ahead of rolling


def test_caster_drag_dissipates_exactly_its_contact_power(params):
    """Q . q_dot of the caster forces = -sum f_j |v_j|^2 / sqrt(|v_j|^2 + w^2) at the contact points, wherever
    the casters are; two casters symmetric about the chassis axis give no turning moment in straight driving."""
    rng = np.random.default_rng(4)
    casters = {"n_cst": 2, "x_c1": 0.35, "y_c1": 0.12, "x_c2": -0.4, "y_c2": -0.05, "f_cst": 6.0}
    eff = fx.effect_vector(casters)
    prm = params.as_array()
    for _ in range(5):
        x = np.zeros(12)
        x[:6] = rng.normal(size=6)
        x[6:] = fx_admissible_state(params, x[:6], rng.normal(size=3))
        gen = phys.effect_force(x, np.zeros(3), eff, prm, compiled.FLOOR)
        th, thd = x[2] - x[5], x[8] - x[11]
        power = 0.0
        width = max(fx.WIDTH_MIN_CASTER, fx.WIDTH_PER_N_CASTER * 6.0)
        for cx, cy in ((0.35, 0.12), (-0.4, -0.05)):
            r = np.array([np.cos(th) * cx - np.sin(th) * cy, np.sin(th) * cx + np.cos(th) * cy])
            v = x[6:8] + thd * np.array([-r[1], r[0]])
            power -= 3.0 * (v @ v) / np.sqrt(v @ v + width ** 2)
        assert gen @ x[6:] == pytest.approx(power, rel=1e-9)
    sym = fx.effect_vector({"n_cst": 2, "x_c1": 0.35, "y_c1": 0.12, "x_c2": 0.35, "y_c2": -0.12, "f_cst": 6.0})
    x = np.zeros(12)
    x[6:] = fx_admissible_state(params, np.zeros(6), np.array([2.0, 2.0, 0.0]))  # straight, no pivot motion
    gen = phys.effect_force(x, np.zeros(3), sym, prm, compiled.FLOOR)
    assert abs(gen[2]) < 1e-12 and gen[0] == pytest.approx(-6.0, rel=1e-3)


def fx_admissible_state(p, q, phid):
    from otbot_hw.model.kinematics import admissible_velocity
    return admissible_velocity(q, phid, p)


@pytest.mark.parametrize("c,fixture", [(0.3, "stand"), (2.0, "stand"), (0.3, "floor"), (2.0, "floor")])
def test_friction_sign_narrow_in_proportion_and_stable(params, c, fixture):
    """The sign width follows the friction level (0.3 N m: 0.0075 rad/s at a wheel) and RK4 at the default
    step stays stable at every level: a wheel coasting down under Coulomb friction comes to rest and stays
    within one width of zero, without chatter."""
    eff = fx.effect_vector({"c_r": c, "c_l": c, "c_p": c})
    assert phys.sign_width(0, eff, params.as_array()) == pytest.approx(max(0.002, 0.025 * c))
    assert phys.sign_width(2, eff, params.as_array()) == pytest.approx(max(0.001, 0.005 * c))
    x0 = np.zeros(12)
    x0[6:] = fx_admissible_state(params, np.zeros(6), np.array([0.5, -0.4, 0.1])) if fixture == "floor" \
        else np.array([0, 0, 0.1, 0.5, -0.4, 0.1])
    tr = simulate_extended(params, eff, np.zeros((600, 3)), 0.01, x0=x0, fixture=fixture)
    w = tr.x[-100:, 9:12]
    assert np.all(np.isfinite(tr.x))
    assert np.max(np.abs(w[:, :2])) <= phys.sign_width(0, eff, params.as_array())
    assert np.max(np.abs(w[:, 2])) <= phys.sign_width(2, eff, params.as_array())
