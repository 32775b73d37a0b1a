"""One sensor model: the sample-by-sample sensors of a stepped simulation (what the direct and bus
simulated robots record) equal the batch sensor outputs of the same run (what identification and the
diagnosis predict), to 1e-12, for every effect of the catalog, with and without a current-loop lag and
an IMU latency."""
import numpy as np
import pytest

from otbot_hw.model import effects as fx
from otbot_hw.model.sensor_model import sensor_outputs
from otbot_hw.params import nominal
from otbot_hw.simulation.sensing import StepperSensors
from otbot_hw.simulation.simulator import make_stepper, simulate_extended

P = nominal()
#: a value for each effect that makes it act on the chosen commands (geometry with the caster drag)
VALUES = {"c_r": 0.3, "c_l": 0.2, "c_p": 0.3, "s_w": 0.2, "v_s": 0.3, "c_rr": 0.02, "f_cst": 8.0, "k_slip": 0.02,
          "g_x": 0.2, "g_y": -0.1, "c_air": 5.0, "k_r": 0.1, "k_l": -0.1, "k_p": 0.05, "u_max_r": 4.0,
          "u_max_l": 4.0, "u_max_p": 3.0, "T_i": 0.02, "db_w": 0.05, "dr_r": 0.03, "dr_l": -0.03, "t_trac": 2.0,
          "b_ax": 0.1, "b_ay": -0.1, "b_gz": 0.02, "d_x": 0.05, "d_y": -0.04, "psi": 0.1, "d_imu": 0.015,
          "e_r": 0.02, "e_l": -0.02, "n_cst": 2.0, "x_c1": 0.15, "y_c1": 0.1, "x_c2": 0.15, "y_c2": -0.1,
          "x_c3": 0.0, "y_c3": 0.0, "x_c4": 0.0, "y_c4": 0.0, "kn_trac": 1.0,
          # laws beyond the catalog (diagnose/discover.py writes them)
          "c_lin": 12.0, "dz_r": 1.0, "dz_l": 0.5, "dz_p": 0.8, "ts_r": 3.0, "ts_l": 4.0, "ts_p": 2.0,
          "cog_r": 0.3, "cog_l": -0.2, "cog_p": 0.4, "cogn_r": 4.0, "cogn_l": 2.0, "cogn_p": 6.0,
          "cogph_r": 0.5, "cogph_l": -1.0, "cogph_p": 2.0}
WITH = {"v_s": {"s_w": 0.2}, "kn_trac": {"k_slip": 0.02, "t_trac": 2.0}, "n_cst": {"f_cst": 8.0}, "x_c1": {"f_cst": 8.0}, "y_c1": {"f_cst": 8.0},
        "x_c2": {"f_cst": 8.0, "n_cst": 2.0}, "y_c2": {"f_cst": 8.0, "n_cst": 2.0},
        **{f"cog_{j}": {f"cogn_{j}": 3.0} for j in "rlp"}, **{f"cogn_{j}": {f"cog_{j}": 0.3} for j in "rlp"},
        **{f"cogph_{j}": {f"cog_{j}": 0.3, f"cogn_{j}": 3.0} for j in "rlp"}}
CASES = [n for n in fx.EFFECT_PARAM_NAMES if not (n[1:3] == "_c" and n[3:] in ("3", "4"))]


def _stepped(model, U, dt, fixture="floor"):
    """Sensors read sample by sample, the way ``sim.direct.DirectSimRobot`` does: at x_k with u_k acting,
    then one step."""
    st = make_stepper(model, dt, fixture=fixture)
    sens = StepperSensors(st, dt)
    out = {k: [] for k in ("joint_pos", "joint_vel", "imu_accel", "imu_gyro")}
    zero = np.zeros(2)
    for k in range(len(U) + 1):
        u = U[min(k, len(U) - 1)]
        a, g = sens.imu(st.t, u, zero)
        pos, vel = sens.joints(u)
        for name, v in zip(out, (pos, vel, a, g)):
            out[name].append(np.array(v, dtype=float))
        if k < len(U):
            st.step(u, zero)
    return {k: np.array(v) for k, v in out.items()}


def _commands(n_hold=6, n=12, seed=0):
    rng = np.random.default_rng(seed)
    return np.repeat(rng.uniform(-7, 7, (n, 3)), n_hold, axis=0)


@pytest.mark.parametrize("name", CASES)
@pytest.mark.parametrize("lag", [0.0, 0.02])
@pytest.mark.parametrize("latency", [0.0, 0.015])
def test_stepper_sensors_equal_batch_sensor_outputs_for_every_effect(name, lag, latency):
    values = dict(WITH.get(name, {}))
    values[name] = VALUES[name]
    values.setdefault("T_i", lag)
    values.setdefault("d_imu", latency)
    model = fx.ExtendedModel.paper(P).with_values(values).checked()
    U, dt = _commands(), 0.01
    got = _stepped(model, U, dt)
    tr = simulate_extended(model.params, model.eff, U, dt)
    want = sensor_outputs(tr, model.params, model.eff)
    for ch in got:
        np.testing.assert_allclose(got[ch], want[ch], rtol=0, atol=1e-12, err_msg=f"{name}: {ch}")


@pytest.mark.parametrize("fixture", ["stand", "locked"])
def test_stepper_sensors_equal_batch_sensor_outputs_off_the_floor(fixture):
    model = fx.ExtendedModel.paper(P).with_values({"c_r": 0.2, "g_x": 0.2, "d_imu": 0.015, "psi": 0.1, "e_l": 0.02})
    U, dt = _commands(), 0.01
    got = _stepped(model, U, dt, fixture)
    tr = simulate_extended(model.params, model.eff, U, dt, fixture=fixture)
    want = sensor_outputs(tr, model.params, model.eff)
    for ch in got:
        np.testing.assert_allclose(got[ch], want[ch], rtol=0, atol=1e-12, err_msg=f"{fixture}: {ch}")


@pytest.mark.parametrize("name", CASES)
def test_the_integrators_paper_shortcut_never_drops_an_effect(name):
    """``ext_rk4_into`` takes the paper model's RK4 when ``forces_active`` says no effect adds a force:
    with and without per-sample outputs (the full extended RK4) the trajectory is the same for every
    effect entry, so an effect missing from ``forces_active`` cannot be silently dropped."""
    from otbot_hw.model.fixtures import fixture_code
    from otbot_hw.simulation.integrators import ext_rk4_into

    values = dict(WITH.get(name, {}))
    values[name] = VALUES[name]
    model = fx.ExtendedModel.paper(P).with_values(values).checked()
    U, dt = _commands(), 0.01
    n = len(U)
    x0 = np.zeros(12)
    x0[9:12] = (0.5, -0.3, 0.4)  # moving, so rate-dependent laws act from the start
    F, prm, code = np.zeros((n, 2)), model.params.as_array(), fixture_code("floor")
    out = []
    for rows in (0, n + 1):  # 0 rows: the shortcut is allowed; n + 1: the full RK4 with its outputs
        X, TAU, S = np.empty((n + 1, 12)), np.empty((n + 1, 3)), np.zeros((n + 1, 2))
        ext_rk4_into(x0, U[0].copy(), U, F, dt, 4, prm, model.eff, code, X, TAU, S,
                     np.empty((rows, 6)), np.empty((rows, 2)))
        out.append(X)
    np.testing.assert_allclose(out[0], out[1], rtol=0, atol=1e-12, err_msg=name)
