"""The extended model (paper dynamics + catalog effects) outside the diagnosis: model files written by
``otbot diagnose --out``, simulation (``otbot simulate``, the one ``Stepper``) and control (feedforward
compensation in ``ComputedTorqueController``, ``otbot track --params/--plant-params``)."""
import json

import numpy as np
import pytest

from otbot_hw.cli import main
from otbot_hw.runtime.tracking import track_reference
from otbot_hw.control.computed_torque import ComputedTorqueController
from otbot_hw.control.task_model import reference_state, task_space
from otbot_hw.control.trajectories import corridor
from otbot_hw.model import compiled
from otbot_hw.model import effect_physics as phys
from otbot_hw.model import effects as fx
from otbot_hw.model.kinematics import inverse_kinematics_matrix
from otbot_hw.params import DEFAULT_PARAMS_FILE, OtbotParams, ParameterError, nominal
from otbot_hw.simulation.simulator import Stepper, make_stepper, simulate, simulate_extended

P = nominal()
PHYSICS = {"c_w": 0.3, "c_p": 0.2, "s_w": 0.1, "v_s": 0.4, "c_rr": 0.01, "f_cst": 3.0, "g_x": 0.05, "g_y": -0.03,
           "c_air": 10.0, "db_w": 0.03, "dr_r": 0.02, "dr_l": -0.01, "k_r": -0.1, "k_l": 0.05, "k_p": 0.08}


def test_model_file_round_trips_and_paper_commands_refuse_it(tmp_path):
    m = fx.ExtendedModel.paper(P.replace(b_w=0.2)).with_values({"c_w": 0.3, "g_x": 0.02, "T_i": 0.01})
    path = tmp_path / "model.yaml"
    m.save(path, header="test", effect_std={"c_w": 0.01, "g_x": 0.002})
    back = fx.ExtendedModel.load(path)
    assert back.params == m.params and np.array_equal(back.eff, m.eff)
    text = path.read_text()
    assert "effects:" in text and "std: 0.01" in text
    with pytest.raises(ParameterError, match="section 'effects' holds extended-model terms"):
        OtbotParams.load(path)
    assert fx.ExtendedModel.load(None).active_effects() == {}  # config/otbot.yaml: the paper's model


@pytest.mark.parametrize("entry,message", [
    ("gremlins: {value: 1.0, unit: N m}", "unknown effect parameter 'effects.gremlins'"),
    ("c_p: {value: 0.1, unit: N}", "'effects.c_p' unit must be 'N m'"),
    ("c_p: {value: -0.1, unit: N m}", "outside its physical range"),
    ("c_p: {value: .nan, unit: N m}", "must be a finite number"),
    ("c_p: {value: 0.1, unit: N m, std: -1}", "'effects.c_p.std' must be a number >= 0"),
    ("c_p: 0.1", "must be a mapping with 'value' and 'unit'"),
])
def test_bad_effect_entries_are_rejected_naming_the_key(tmp_path, capsys, entry, message):
    path = tmp_path / "bad.yaml"
    path.write_text(DEFAULT_PARAMS_FILE.read_text() + "effects:\n  " + entry + "\n")
    with pytest.raises(ParameterError, match=message):
        fx.ExtendedModel.load(path)
    assert main(["simulate", "--params", str(path), "--duration", "0.1"]) == 2
    assert "effects." in capsys.readouterr().err


def test_effects_enter_the_task_space_model_as_delta_transpose_gen_and_are_compensated_exactly():
    """ext_accelerations == M_bar^-1 (u + Delta^T gen - C_bar p_dot), and the compensated command makes the
    extended model accelerate exactly like the paper model under the law's torque (dr = 0)."""
    rng = np.random.default_rng(3)
    prm = P.as_array()
    eff = fx.ExtendedModel.paper(P).with_values({k: v for k, v in PHYSICS.items() if not k.startswith("dr")}).eff
    eff_dr = fx.ExtendedModel.paper(P).with_values(PHYSICS).eff
    for _ in range(20):
        p, pd, phi = rng.uniform(-1, 1, 3), rng.uniform(-0.5, 0.5, 3), rng.uniform(-3, 3)
        x = reference_state(p, pd, phi, prm)
        q = np.array([*p, 0.0, 0.0, phi])
        assert np.allclose(x[9:], inverse_kinematics_matrix(q, P) @ pd, atol=1e-12)
        u = rng.uniform(-3, 3, 3)
        Mb, Cb = task_space(p[2], phi, pd, prm)
        acc = phys.ext_accelerations(x, u, np.zeros(2), eff, prm, compiled.FLOOR)
        gen_u = phys.effect_joint_torque(x, u, eff, prm, compiled.FLOOR)
        assert np.allclose(acc[:3], np.linalg.solve(Mb, u + gen_u - Cb @ pd), atol=1e-10)
        want = np.linalg.solve(Mb, u - Cb @ pd)
        cmd = phys.compensated_command(x, u, eff, prm, compiled.FLOOR)
        got = phys.ext_accelerations(x, phys.actuated_torque(cmd, eff), np.zeros(2), eff, prm, compiled.FLOOR)
        assert np.allclose(got[:3], want, atol=1e-10)
        # a radius asymmetry also changes the wheels' inertia, which is not compensated: small, not zero
        cmd = phys.compensated_command(x, u, eff_dr, prm, compiled.FLOOR)
        got = phys.ext_accelerations(x, phys.actuated_torque(cmd, eff_dr), np.zeros(2), eff_dr, prm, compiled.FLOOR)
        assert np.abs(got[:3] - want).max() < 0.05 * (np.abs(want).max() + 1.0)


def test_the_one_stepper_matches_the_batch_integrators_of_both_models():
    m = fx.ExtendedModel.paper(P).with_values({"c_w": 0.3, "T_i": 0.02, "k_p": -0.1, "g_x": 0.05})
    U = np.random.default_rng(0).uniform(-4, 4, (200, 3))
    tr = simulate_extended(m.params, m.eff, U, 0.01)
    st = make_stepper(m, 0.01)
    for u in U:
        st.step(u)
    assert np.abs(st.x - tr.x[-1]).max() < 1e-12
    assert np.allclose(st.tau, tr.tau[-1], atol=1e-12)
    for plant in (P, fx.ExtendedModel.paper(P)):  # the paper's model: the same stepper with every effect at zero
        st = make_stepper(plant, 0.01)
        assert type(st) is Stepper
        for u in U:
            st.step(u)
        assert np.abs(st.x - simulate(P, U, 0.01).x[-1]).max() < 1e-12


def test_controller_with_the_extended_model_cancels_the_effects_in_closed_loop():
    """Plant with wheel/pivot Coulomb friction, a slope and a weak right motor: the paper-model controller
    leaves millimetre errors (PD, no integral); the controller that knows the effects removes them."""
    plant = fx.ExtendedModel.paper(P).with_values({"c_w": 0.4, "c_p": 0.3, "g_x": 0.05, "k_r": -0.1})
    ref = corridor(smoothing=1.0)
    naive = track_reference(ref, ComputedTorqueController(P), plant, rate_hz=500.0, duration=8.0)
    aware = track_reference(ref, ComputedTorqueController(plant), plant, rate_hz=500.0, duration=8.0)
    e_naive = np.abs(naive.e_p[:, :2]).max()
    e_aware = np.abs(aware.e_p[:, :2]).max()
    assert e_naive > 1e-3
    assert e_aware < 0.05 * e_naive
    assert ComputedTorqueController(plant).compensates == plant.active_effects()
    assert ComputedTorqueController(P).compensates == {}


def test_diagnosed_model_file_feeds_simulate_and_track(tmp_path, capsys):
    """otbot diagnose --demo --out writes the refit model with the found effect and its std; otbot simulate and
    otbot track load it."""
    out = tmp_path / "diagnosed.yaml"
    assert main(["diagnose", "--demo", "--demo-dir", str(tmp_path / "demo"), "--out", str(out), "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert [e["name"] for e in r["effects"]] == ["coulomb_wheels"] and r["model_file"] == str(out)
    m = fx.ExtendedModel.load(out)
    assert m.get("c_w") == pytest.approx(r["effects"][0]["parameters"]["c_w"]["value"])
    assert m.params.b_w == pytest.approx(r["nominal_shift"]["b_w"]["after"])
    assert "std" in out.read_text().split("effects:")[1]
    assert main(["simulate", "--params", str(out), "--duration", "0.5", "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["effects"]["c_r"] == pytest.approx(m.get("c_w")) and s["max_constraint_residual"] < 1e-8
    assert main(["track", "corridor-smooth", "--sim", "--feedback", "truth", "--no-robustness", "--params", str(out),
                 "--rate", "250", "--json"]) == 0
    t = json.loads(capsys.readouterr().out)
    assert t["compensated_effects"]["c_r"] == pytest.approx(m.get("c_w"))
    assert max(t["max_abs_error"][k] for k in ("x", "y")) < 1e-3
