"""Online payload adaptation (otbot_hw.estimation.payload, runtime.payload_adapter.PayloadAdapter): the
linear-in-parameters form, recovery of a known payload, step-change detection, bounds refusal, the
bumpless switch, the recording topic and the configuration's bad input."""
from __future__ import annotations

import numpy as np
import pytest

from otbot_hw.control.computed_torque import ComputedTorqueController
from otbot_hw.control.task_model import task_space_matrices
from otbot_hw.estimation.payload import (PAYLOAD_NAMES, AdaptationConfig, PayloadEstimator, bounds_violation,
                                         payload_from_theta, regressor_sample, theta_from_payload)
from otbot_hw.params import ParameterError, nominal
from otbot_hw.simulation.simulator import Stepper, rest_state

LOAD = (60.0, 0.15, -0.10, 1.0)
PERIOD = 0.01


def truth_vec(p):
    return np.array([p.m_p, p.I_p, p.x_F, p.y_F])


def test_torques_are_linear_in_the_platform_parameters():
    """u = u_rest + Y theta reproduces the full task-space model for random states and payloads."""
    rng = np.random.default_rng(3)
    for _ in range(20):
        p = nominal().with_load(rng.uniform(0, 200), *rng.uniform(-0.3, 0.3, 2), rng.uniform(0, 3))
        a, ph = rng.uniform(-3, 3, 2)
        pd, pdd, out = rng.normal(size=3), rng.normal(size=3), np.empty(15)
        Mb, Cb = np.empty((3, 3)), np.empty((3, 3))
        task_space_matrices(a, ph, pd, p.as_array(), Mb, Cb)
        u = Mb @ pdd + Cb @ pd
        regressor_sample(a, ph, pd, pdd, u, nominal().as_array(), out)  # the file knows no load
        theta = theta_from_payload(p.m_p, p.I_p, p.x_F, p.y_F)
        assert np.allclose(out[12:], out[:12].reshape(3, 4) @ theta, atol=1e-9)
        assert np.allclose(payload_from_theta(theta)[0], truth_vec(p))


def excite(plant_of_t, seconds: float, seed: int = 0, twist_noise: float = 0.0):
    """(t, x, u_prev) samples of the paper's model under multisine torques that drive and turn the
    platform; ``plant_of_t(t)``: the plant's parameters at time t (a load step)."""
    rng = np.random.default_rng(seed)
    st = Stepper(plant_of_t(0.0), PERIOD, rest_state(np.zeros(3)))
    f = rng.uniform(0.2, 1.5, (3, 3))
    ph = rng.uniform(0, 2 * np.pi, (3, 3))
    amp = np.array([12.0, 12.0, 6.0])
    u_prev = np.zeros(3)
    out = [(0.0, st.x.copy(), u_prev)]
    current = plant_of_t(0.0)
    for k in range(int(round(seconds / PERIOD))):
        t = k * PERIOD
        if plant_of_t(t) is not current:
            current = plant_of_t(t)
            st.set_params(current)
        u = amp * np.sum(np.sin(2 * np.pi * f * t + ph), axis=1) / 3.0
        x = st.step(u).copy()
        if twist_noise:
            x[6:9] += rng.normal(0, twist_noise, 3)
        out.append((t + PERIOD, x, u))
    return out


def feed(est: PayloadEstimator, samples):
    changes = []
    for t, x, u in samples:
        if est.observe(t, x[2], x[5], x[6:9], u):
            changes.append(t)
    return changes


@pytest.mark.parametrize("noise", [0.0, 2e-3])
def test_a_known_payload_is_recovered_within_its_reported_std(noise):
    """20 s of excitation with the file unaware of a 60 kg off-centre load: every parameter within 3 reported
    std of the truth, and the std small enough to matter (kg, m)."""
    plant = nominal().with_load(*LOAD)
    est = PayloadEstimator(nominal(), AdaptationConfig(), PERIOD)
    feed(est, excite(lambda t: plant, 20.0, twist_noise=noise))
    e = est.estimate()
    err = (e.value - truth_vec(plant)) / e.std
    assert np.all(np.abs(err) < 3.0), dict(zip(PAYLOAD_NAMES, err))
    assert e.std[0] < 1.0 and e.std[2] < 0.01 and e.std[3] < 0.01
    assert all(e.confident[n] for n in ("m_p", "x_F", "y_F"))


def test_without_excitation_the_file_values_stay():
    """60 s at rest with a noisy twist (0.3 mm/s, 0.3 mrad/s white at 100 Hz): nothing is learnt, the estimate stays the file's and is not confident. Without the excitation gate the noise in
    the differenced accelerations (errors in variables) drags the mass away."""
    rng = np.random.default_rng(5)
    samples = [(k * PERIOD, np.zeros(12), np.zeros(3)) for k in range(6000)]
    for _, x, _ in samples:
        x[6:9] = rng.normal(0, 3e-4, 3)
    est = PayloadEstimator(nominal(), AdaptationConfig(), PERIOD)
    feed(est, samples)
    e = est.estimate()
    assert np.allclose(e.value, truth_vec(nominal())) and est.updates == 0
    assert not any(e.confident.values())
    ungated = PayloadEstimator(nominal(), AdaptationConfig(min_accel=1e-9, min_alpha_accel=1e-9), PERIOD)
    feed(ungated, samples)
    assert abs(ungated.estimate().value[0] - nominal().m_p) > 5.0


def test_a_load_step_is_detected_and_re_estimated():
    """The box is put on after 15 s: no alarm before, an alarm within 2 s after, and the new payload is
    recovered; taking it off again is detected too."""
    bare, loaded = nominal(), nominal().with_load(*LOAD)
    est = PayloadEstimator(bare, AdaptationConfig(), PERIOD)
    changes = feed(est, excite(lambda t: loaded if 15.0 <= t < 35.0 else bare, 50.0, seed=1))
    assert len(changes) == 2, changes
    assert 15.0 < changes[0] < 17.0 and 35.0 < changes[1] < 37.0
    e = est.estimate()
    assert abs(e.value[0] - bare.m_p) < 3 * e.std[0] + 1e-9


def test_bounds():
    assert bounds_violation([80, 2, 0.1, 0.0], [1, 1, 0.01, 0.01], 300, 0.5) is None
    assert "not positive" in bounds_violation([-20, 2, 0.1, 0.0], [1, 1, 0.01, 0.01], 300, 0.5)
    assert "max_mass" in bounds_violation([400, 2, 0.1, 0.0], [1, 1, 0.01, 0.01], 300, 0.5)
    assert "radius" in bounds_violation([80, 2, 0.6, 0.2], [1, 1, 0.01, 0.01], 300, 0.5)
    assert bounds_violation([80, 2, 0.52, 0.0], [1, 1, 0.01, 0.01], 300, 0.5) is None  # within 3 std


def _run(plant, config, seconds=8.0, path=None):
    from otbot_hw.control.gains import gains_from_tstab
    from otbot_hw.control.scenarios import build_spec
    from otbot_hw.motors import load_motor_limits
    from otbot_hw.runtime.backends import DirectBackend
    from otbot_hw.runtime.tracking import track_reference

    limits = load_motor_limits()
    spec = build_spec("corridor-smooth", nominal(), limits)
    backend = DirectBackend(rate=1.0 / PERIOD, imu_rate=None)
    law = ComputedTorqueController(nominal(), gains_from_tstab(3.0))
    return track_reference(spec.reference, law, plant, limits, backend, "truth", x0=spec.x0, duration=seconds,
                           adapt=config, path=path, metadata={"test": "payload"}), spec


def test_an_estimate_outside_the_bounds_faults_and_restores_the_file():
    """A robot heavier than daemon.adaptation.max_mass: a latched payload fault that says why; the law is
    back on the file's platform parameters."""
    run, _ = _run(nominal().with_load(*LOAD), AdaptationConfig(enabled=True, max_mass=50.0), seconds=4.0)
    assert not run.completed
    f = run.loop.fault
    assert f.kind == "payload" and "max_mass 50 kg" in f.text and "file's platform parameters restored" in f.text
    law = run.adapter.law
    assert law.params.m_p == nominal().m_p and law.prm[7] == nominal().m_p
    assert run.adapter.state == "fault"


def test_the_switch_is_bumpless_and_the_tracking_improves(tmp_path):
    """Adapting, the torque has no step at the switch (largest change per period within the first 3 s no
    larger than the law's own changes; an instant switch is a step), the estimate is the truth within 3 std,
    and the smooth corridor's error after the switch is a fraction of the file's. The recording carries
    /otbot/payload."""
    from otbot_hw.recording import read_recording

    plant = nominal().with_load(*LOAD)
    cfg = AdaptationConfig(enabled=True)
    path = tmp_path / "a.mcap"
    run, _ = _run(plant, cfg, path=path)
    assert run.completed
    ad = run.adapter.summary()
    assert ad["switched_s"] is not None and ad["converged_s"] is not None
    pe = run.adapter.payload_estimate()
    for i, n in enumerate(("m_p", "x_F", "y_F")):
        assert abs(pe[n]["value"] - truth_vec(plant)[[0, 2, 3]][i]) < 3 * pe[n]["std"] + 1e-6, n

    def steps_near_switch(r):
        origin = r.loop.recording.t[len(r.loop.recording.t) - len(r.t)]
        k = int(np.searchsorted(r.t, r.adapter.switched_s - origin))
        assert k > 40
        du = np.abs(np.diff(r.u_cmd, axis=0)).max(axis=1)
        return du[k - 40:k - 2].max(), du[k - 2:k + 60].max()

    before, at = steps_near_switch(run)
    assert at <= 2.0 * before + 0.05
    instant, _ = _run(plant, cfg.with_(ramp=PERIOD / 10))
    b2, a2 = steps_near_switch(instant)
    assert a2 > 3.0 * max(b2, at)  # the test can tell a step
    bare, _ = _run(plant, None)
    m = run.t > 4.0
    e_ad = np.abs(run.e_p[m, :2]).max()
    e_file = np.abs(bare.e_p[m, :2]).max()
    assert e_ad < 0.2 * e_file
    rec = read_recording(path)
    assert rec.payload_value is not None and rec.payload_value.shape == (len(rec.t), 4)
    assert np.allclose(rec.payload_used[0], truth_vec(nominal()))
    assert abs(rec.payload_used[-1, 0] - plant.m_p) < 1.0


def test_adaptation_config_bad_input(tmp_path):
    AdaptationConfig.from_section({"enabled": True, "max_mass": {"value": 200, "unit": "kg"}})
    with pytest.raises(ParameterError, match="unknown key"):
        AdaptationConfig.from_section({"max_mas": {"value": 200, "unit": "kg"}})
    with pytest.raises(ParameterError, match="max_mass"):
        AdaptationConfig.from_section({"max_mass": {"value": -1, "unit": "kg"}})
    with pytest.raises(ParameterError, match="unit"):
        AdaptationConfig.from_section({"ramp": {"value": 1, "unit": "ms"}})
    with pytest.raises(ParameterError, match="enabled"):
        AdaptationConfig.from_section({"enabled": "yes"})


def test_the_law_swap_hook_changes_the_torque():
    law = ComputedTorqueController(nominal())
    z = np.zeros(3)
    u0 = law.update_fast(z, z, 0.0, z, z, np.array([0.5, 0.0, 0.0]))[0].copy()
    law.set_platform(*truth_vec(nominal().with_load(*LOAD)))
    u1 = law.update_fast(z, z, 0.0, z, z, np.array([0.5, 0.0, 0.0]))[0].copy()
    assert law.params.m_p == pytest.approx(nominal().m_p + 60)
    assert not np.allclose(u0, u1)


def test_track_adapt_refuses_a_bad_adaptation_section(tmp_path, otbot_cli):
    """A bad daemon.adaptation key: one line naming it, exit 2, before anything runs."""
    from otbot_hw.runtime.daemon_process import local_config

    cfg = local_config(tmp_path, replace={"max_mass: {value: 300.0, unit: kg}": "max_mass: {value: 300.0, unit: g}"})
    rc, out, err = otbot_cli(["track", "corridor-smooth", "--sim", "--adapt", "payload", "--config", str(cfg),
                              "--no-robustness", "--json"])
    assert rc == 2 and "daemon.adaptation.max_mass" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1
    rc, out, err = otbot_cli(["track", "corridor-smooth", "--sim", "--adapt", "inertia"])
    assert rc == 2 and "--adapt" in err


def test_track_adapt_payload_json(tmp_path, otbot_cli):
    """otbot track --adapt payload --json: payload_estimate {value, std} near the plant's platform + load and
    adaptation {converged_s, switched_s}; the recording carries /otbot/payload."""
    import json

    from otbot_hw.params import write_yaml
    from otbot_hw.recording import read_recording

    plant = nominal().with_load(*LOAD)
    write_yaml(tmp_path / "plant.yaml", plant.to_dict())
    t = np.linspace(0.0, 6.0, 121)
    s = lambda u: np.clip(u, 0, 1) ** 3 * (10 - 15 * np.clip(u, 0, 1) + 6 * np.clip(u, 0, 1) ** 2)  # noqa: E731
    rows = "\n".join(f"{a:.3f},{s(a / 3):.6f},{s(a / 3 - 1):.6f},0" for a in t)
    (tmp_path / "xy.csv").write_text("t,x,y,alpha\n" + rows + "\n")  # 1 m along x, then 1 m along y
    rc, out, err = otbot_cli(["track", str(tmp_path / "xy.csv"), "--sim", "--rate", "100", "--feedback", "truth",
                              "--plant-params", str(tmp_path / "plant.yaml"), "--adapt", "payload",
                              "--no-robustness", "--out", str(tmp_path / "run.mcap"), "--json"])
    assert rc == 0, err
    r = json.loads(out)
    pe, ad = r["payload_estimate"], r["adaptation"]
    assert set(pe) == {"m_p", "I_p", "x_F", "y_F"} and all({"value", "std"} <= set(v) for v in pe.values())
    assert abs(pe["m_p"]["value"] - plant.m_p) < max(3 * pe["m_p"]["std"], 0.5)
    assert 0 < ad["switched_s"] <= ad["converged_s"] < 6 and ad["fault"] is None
    assert read_recording(tmp_path / "run.mcap").payload_value is not None


def test_a_diagnosed_model_s_compensation_is_not_taken_for_payload():
    """Coulomb friction in plant and model, compensated by the law: the estimator subtracts the compensation
    from the held command, so the mass is the load's (without it: 99 kg for 82)."""
    from otbot_hw.control.gains import gains_from_tstab
    from otbot_hw.control.scenarios import build_spec
    from otbot_hw.model.effects import EFFECT_INDEX, ExtendedModel, effect_vector
    from otbot_hw.motors import load_motor_limits
    from otbot_hw.runtime.backends import DirectBackend
    from otbot_hw.runtime.tracking import track_reference

    eff = np.array(effect_vector(), dtype=float)
    eff[[EFFECT_INDEX["c_r"], EFFECT_INDEX["c_l"], EFFECT_INDEX["c_p"]]] = 0.8, 0.8, 0.5
    limits = load_motor_limits()
    spec = build_spec("corridor-smooth", nominal(), limits)
    law = ComputedTorqueController(ExtendedModel(nominal(), eff), gains_from_tstab(3.0))
    plant = ExtendedModel(nominal().with_load(*LOAD), eff)
    run = track_reference(spec.reference, law, plant, limits, DirectBackend(rate=1.0 / PERIOD, imu_rate=None),
                          "truth", x0=spec.x0, duration=12.0, adapt=AdaptationConfig(enabled=True))
    assert run.completed
    assert abs(run.adapter.payload_estimate()["m_p"]["value"] - plant.params.m_p) < 2.5
