"""otbot diagnose on concealed effects: finds, names and sizes the hidden effect; adds nothing when there is none;
rejects bad input. Short recordings (5 s multisine + 2 s stand fitting, 5 s tracking held out) keep this fast."""
import json

import numpy as np
import pytest

from otbot_hw.cli import main
from otbot_hw.diagnose.data import DiagnosisInputError, from_recording
from otbot_hw.diagnose.diagnosis import diagnose
from otbot_hw.params import nominal
from otbot_hw.recording import write_recording
from otbot_hw.simulation.concealed import concealed_recording

P = nominal()


def _sets(values, seed=7, stand=False, duration=5.0):
    fit = [from_recording(concealed_recording(P, values, "multisine", duration, seed=seed), "multisine")]
    if stand:
        fit.append(from_recording(concealed_recording(P, values, "stand", 1.5, seed=seed + 1), "stand"))
    held = [from_recording(concealed_recording(P, values, "tracking", duration, seed=seed + 2), "tracking")]
    return fit, held


def _check_found(result, name, truth):
    assert result["model_adequate"], result["verdict"]
    assert [e["name"] for e in result["effects"]] == [name], result["verdict"]
    assert result["effects"][0]["significance"]["matters"] is True
    got = result["effects"][0]["parameters"]
    for k, v in truth.items():
        assert got[k]["value"] == pytest.approx(v, rel=0.2), (k, got[k])
        assert got[k]["std"] is not None and got[k]["std"] < 0.2 * abs(v)
    before = result["fit_before"]["heldout"]
    after = result["fit_after"]["heldout"]
    gain = [after[c]["fit_percent"] - before[c]["fit_percent"] for c in before]
    assert max(gain) > 2.0 and min(gain) > -1.0, (before, after)
    assert result["ambiguous"] == []
    assert name in result["verdict"] or result["effects"][0]["title"] in result["verdict"]
    # the recording that revealed it is one the Fisher criterion says can reveal it
    assert result["identifiability"][name]["identifiable"]


def test_coulomb_wheel_friction_absorbed_in_b_w_is_found():
    truth = {"c_w": 0.3}
    fit, held = _sets(truth, stand=True)
    r = diagnose(fit, P, held)
    # concealed: the nominal fit inflated b_w to absorb it, and still fits the fitting data plausibly
    assert r["nominal_shift"]["b_w"]["before"] > 1.2 * P.b_w
    assert min(v["fit_percent"] for v in r["fit_before"]["fitting"].values()) > 60
    _check_found(r, "coulomb_wheels", truth)
    assert r["nominal_shift"]["b_w"]["after"] == pytest.approx(P.b_w, rel=0.1)
    assert any(w["kind"] == "torque" for w in r["located"])


@pytest.mark.parametrize("name,truth", [
    ("imu_bias", {"b_ax": 0.06, "b_ay": 0.04, "b_gz": -0.01}),
    ("gain_right", {"k_r": -0.1}),
    ("floor_slope", {"g_x": 0.04, "g_y": 0.03}),
])
def test_concealed_effect_is_found_named_and_sized(name, truth):
    fit, held = _sets(truth, seed=11)
    r = diagnose(fit, P, held)
    _check_found(r, name, truth)


@pytest.mark.parametrize("seed", [5, 6, 8])
def test_negative_control_adds_nothing(seed):
    fit, held = _sets({}, seed=seed, duration=4.0)
    r = diagnose(fit, P, held)
    assert r["model_adequate"] and r["detected_small"] == []
    assert r["effects"] == [] and r["ambiguous"] == []
    assert r["verdict"].startswith("No missing physics found")
    for ch, v in r["fit_after"]["fitting"].items():
        assert v["fit_percent"] == r["fit_before"]["fitting"][ch]["fit_percent"]


def _rec(tmp_path, **changes):
    rec = concealed_recording(P, {}, "multisine", 1.0, seed=1)
    for k, v in changes.items():
        setattr(rec, k, v)
    path = tmp_path / "bad.mcap"
    write_recording(path, rec)
    return rec, path


def test_bad_input_is_rejected_with_a_clear_message(tmp_path, capsys):
    rec = concealed_recording(P, {}, "multisine", 1.0, seed=1)
    t = rec.t.copy()
    t[40:] += 0.05
    rec_gap = concealed_recording(P, {}, "multisine", 1.0, seed=1)
    rec_gap.t = t
    rec_gap.metadata.pop("sample_period")
    with pytest.raises(DiagnosisInputError, match="gap or uneven sampling at sample 40"):
        from_recording(rec_gap, "gap")
    u = rec.torque.copy()
    u[10, 1] = np.nan
    rec.torque = u
    with pytest.raises(DiagnosisInputError, match="torque is NaN or inf at sample 10"):
        from_recording(rec, "nan")
    rec = concealed_recording(P, {}, "multisine", 1.0, seed=1)
    rec.metadata["sample_period"] = 0.02
    with pytest.raises(DiagnosisInputError, match="disagrees with the median time step"):
        from_recording(rec, "meta")
    rec = concealed_recording(P, {}, "multisine", 1.0, seed=1)
    rec.metadata["fixture"] = "ceiling"
    with pytest.raises(DiagnosisInputError, match="fixture 'ceiling' is unknown"):
        from_recording(rec, "fixture")
    rec = concealed_recording(P, {}, "multisine", 1.0, seed=1)
    rec.joint_pos = rec.joint_vel = None
    rec.truth_q = None
    with pytest.raises(DiagnosisInputError, match="no /otbot/joints"):
        from_recording(rec, "nojoints")
    # a NaN in one IMU channel: the channel is dropped with the reason, the rest is used
    rec = concealed_recording(P, {}, "multisine", 1.0, seed=1)
    a = rec.imu_accel.copy()
    a[5, 1] = np.nan
    rec.imu_accel = a
    d = from_recording(rec, "imu")
    assert "a_y" in d.unusable and "NaN" in d.unusable["a_y"]
    assert "a_y" not in d.channels() and "a_x" in d.channels()
    from otbot_hw.diagnose.residuals import imu_residual, torque_residual
    from otbot_hw.diagnose.simulated_run import simulation_residual
    from otbot_hw.model.effects import ExtendedModel
    m = ExtendedModel.paper(P)
    ir = imu_residual(d, m)
    assert np.all(np.isnan(ir[:, 1])) and np.all(np.isfinite(ir[:, [0, 2]]))
    assert np.all(np.isfinite(torque_residual(d, m)))
    assert set(simulation_residual(d, m)) == set(d.channels())
    # the CLI: exit 2 with the reason, nothing on stdout
    _, path = _rec(tmp_path, torque=np.where(np.arange(101)[:, None] == 3, np.nan, rec.torque))
    assert main(["diagnose", str(path), "--json"]) == 2
    err = capsys.readouterr()
    assert "torque is NaN" in err.err and err.out == ""
    assert main(["diagnose", str(tmp_path / "missing.mcap")]) == 2
    assert main(["diagnose"]) == 2
    assert main(["diagnose", "--demo", "--demo-effect", "gremlins"]) == 2


def test_truth_is_never_read(tmp_path):
    """The diagnosis keeps only commands, encoders, IMU, sample period and fixture."""
    rec = concealed_recording(P, {"c_w": 0.3}, "multisine", 1.0, seed=1, effect_name="coulomb_wheels")
    d = from_recording(rec, "x")
    assert not any("truth" in k for k in vars(d))
    assert "coulomb" not in json.dumps({k: str(v) for k, v in vars(d).items()})


def test_look_alikes_on_floor_data_are_reported_ambiguous_with_the_separating_experiment():
    """Floor-only data cannot tell motor Coulomb friction from rolling resistance (same torque
    signature): the tool says so instead of guessing, and names the stand experiment."""
    fit, held = _sets({"c_w": 0.3}, seed=3)
    r = diagnose(fit, P, held)
    assert r["effects"] == []
    assert len(r["ambiguous"]) == 1
    names = {c["name"] for c in r["ambiguous"][0]["candidates"]}
    assert {"coulomb_wheels", "rolling_resistance"} <= names
    assert "stand" in r["ambiguous"][0]["experiment"]
    cw = next(c for c in r["ambiguous"][0]["candidates"] if c["name"] == "coulomb_wheels")
    assert cw["parameters"]["c_w"]["value"] == pytest.approx(0.3, rel=0.2)
    assert "cannot tell apart" in r["verdict"]


def test_refit_seam_recovers_known_parameters_with_honest_std():
    """The seam alone: wheel inertia and friction from a stand run, started 30 % off."""
    from otbot_hw.diagnose.refit import refit
    from otbot_hw.model.effects import ExtendedModel

    d = from_recording(concealed_recording(P, {}, "stand", 3.0, seed=4), "stand")
    start = ExtendedModel.paper(P.replace(I_a=P.I_a * 1.3, b_w=P.b_w * 0.7))
    fit = refit([d], start, ["I_a", "b_w"])
    for n in ("I_a", "b_w"):
        true = getattr(P, n)
        assert abs(fit.values[n] - true) < 4 * fit.std[n] + 1e-3 * true, (n, fit.values[n], fit.std[n])
        assert fit.std[n] < 0.05 * true


def test_extended_model_serves_the_shared_fitter_interface():
    """ExtendedPredictionModel: a batch of parameter rows predicts what the diagnosis simulates; a tied
    parameter sets its members; the seam's per-channel RSS is that of the fitted model's residuals."""
    from otbot_hw.diagnose.prediction import ExtendedPredictionModel, diagnosis_experiments
    from otbot_hw.diagnose.refit import channel_sigmas, refit, weighted_residuals
    from otbot_hw.diagnose.simulated_run import simulate_outputs
    from otbot_hw.model.effects import ExtendedModel

    d = from_recording(concealed_recording(P, {"c_w": 0.2}, "stand", 2.0, seed=3), "stand")
    base = ExtendedModel.paper(P)
    pm = ExtendedPredictionModel(base, tied=["c_w"])
    (e,) = diagnosis_experiments([d], base, channel_sigmas([d]))
    assert e.channels == ("w_r", "w_l", "w_p", "a_x", "a_y", "omega_z")
    rows = np.repeat(pm.vector()[None], 2, axis=0)
    rows[1, pm.names.index("c_w")] = 0.2
    y = pm.predict(rows, e)
    assert y.shape == (2, len(d), 6)
    for row, m in zip(y, (base, base.with_values({"c_r": 0.2, "c_l": 0.2}))):
        sim = simulate_outputs(d, m)
        assert np.array_equal(row[:, 0], sim["w_r"]) and np.array_equal(row[:, 5], sim["g_z"])
    assert np.max(np.abs(y[1, :, :2] - y[0, :, :2])) > 0.05  # friction slows both wheels
    fit = refit([d], base, ["c_w"])
    assert fit.values["c_w"] == pytest.approx(0.2, rel=0.05) and fit.std["c_w"] < 0.01
    res = weighted_residuals([d], fit.model, fit.sigma)
    assert set(res) == set(fit.rss)
    for k, r in res.items():
        assert fit.rss[k] == pytest.approx(float(r @ r), rel=1e-9) and fit.n_samples[k] == len(r)


def test_regime_tags_come_from_the_measured_signals():
    from otbot_hw.diagnose.locate import regimes
    from otbot_hw.diagnose.residuals import joint_rates

    d = from_recording(concealed_recording(P, {}, "steps", 3.0, seed=2), "steps")
    vel, _ = joint_rates(d)
    speed = np.full(len(d), 1.0)
    turn = np.zeros(len(d))
    assert "torque step" in regimes(d, 45, 60, speed, turn, vel)  # a step every 0.5 s (sample 50)
    assert "torque step" not in regimes(d, 55, 95, speed, turn, vel)
    still = np.zeros_like(vel)
    assert "standstill" in regimes(d, 55, 95, speed, turn, still)
    assert "high turn rate" in regimes(d, 55, 95, speed, np.full(len(d), 1.0), vel)


def test_cli_writes_report_and_strict_json(tmp_path, capsys):
    path = tmp_path / "run.mcap"
    write_recording(path, concealed_recording(P, {}, "multisine", 3.0, seed=9))
    rc = main(["diagnose", str(path), "--report", str(tmp_path / "rep"), "--json"])
    out = capsys.readouterr().out
    assert rc == 0
    r = json.loads(out)
    assert r["effects"] == [] and "No missing physics" in r["verdict"]
    assert (tmp_path / "rep" / "diagnosis.json").exists()
    assert all(p.endswith(".png") and (tmp_path / "rep" / p.split("/")[-1]).exists() for p in r["plots"])
    assert set(r["fit_before"]["fitting"]) == {"w_r", "w_l", "w_p", "a_x", "a_y", "g_z"}


def test_fleet_runs_on_the_shared_executor_serial_and_dask(tmp_path, capsys):
    """--each on a Dask cluster gives the same diagnoses, in the given order, as in this process;
    an unreadable recording is reported and the others go on."""
    from distributed import LocalCluster

    from otbot_hw.diagnose.fleet import diagnose_each
    from otbot_hw.identification.executors import SerialExecutor

    paths = []
    for i, values in enumerate(({"b_ax": 0.06, "b_ay": 0.04, "b_gz": -0.01}, {})):
        paths.append(tmp_path / f"run{i}.mcap")
        write_recording(paths[-1], concealed_recording(P, values, "multisine", 3.0, seed=20 + i))
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(b"not an mcap file")
    paths.insert(1, broken)
    serial = diagnose_each(paths, P, executor=SerialExecutor())
    assert [r["recording"] for r in serial] == [str(p) for p in paths]
    assert "error" in serial[1] and "broken.mcap" in serial[1]["error"]
    assert [e["name"] for e in serial[0]["effects"]] == ["imu_bias"] and serial[2]["effects"] == []
    with LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None) as cluster:
        rc = main(["diagnose", *map(str, paths), "--each", "--scheduler", cluster.scheduler_address, "--json"])
    assert rc == 0
    runs = json.loads(capsys.readouterr().out)["runs"]
    assert [r["recording"] for r in runs] == [str(p) for p in paths]
    assert runs[1]["error"] == serial[1]["error"]
    for a, b in ((runs[0], serial[0]), (runs[2], serial[2])):
        assert a["verdict"] == b["verdict"] and a["effects"] == b["effects"]
    # bad executor arguments: exit 2, nothing on stdout
    for argv in (["--each", "--workers", "0"], ["--scheduler", cluster.scheduler_address],
                 ["--each", "--workers", "2", "--scheduler", "tcp://127.0.0.1:1"]):
        assert main(["diagnose", str(paths[0]), *argv]) == 2
        cap = capsys.readouterr()
        assert cap.out == "" and "--" in cap.err


def _write(tmp_path, name, values, kind, duration, seed, params=P):
    path = tmp_path / name
    write_recording(path, concealed_recording(params, values, kind, duration, seed=seed))
    return path


def test_wrong_parameter_file_gives_model_inadequate_and_exit_1_not_a_finding(tmp_path, capsys):
    """The file claims a 15 kg platform load that the robot does not carry (the diagnosis takes m_p, x_F,
    y_F as known): no effect is named, the platform parameters are suspected, exit code 1."""
    fit = _write(tmp_path, "fit.mcap", {}, "multisine", 4.0, 31)
    held = _write(tmp_path, "held.mcap", {}, "tracking", 4.0, 32)
    wrong = tmp_path / "wrong.yaml"
    P.with_load(15.0, 0.12, 0.05, 0.2).save(wrong)
    with pytest.raises(SystemExit) as exc:
        main(["diagnose", str(fit), "--holdout", str(held), "--params", str(wrong), "--json",
              "--out", str(tmp_path / "model.yaml")])
    assert exc.value.code == 1
    cap = capsys.readouterr()
    r = json.loads(cap.out)
    assert r["model_adequate"] is False and r["effects"] == [] and r["ambiguous"] == []
    assert {"m_p", "x_F", "y_F"} <= set(r["suspect_parameters"])
    assert r["adequacy"]["channels"] or r["adequacy"]["moved"] or r["adequacy"]["on_bound"]
    assert r["verdict"].startswith("Model inadequate") and "step 3" in r["verdict"]
    assert "model inadequate" in cap.err and not (tmp_path / "model.yaml").exists()
    # the right file: the same recordings are adequate and nothing is named
    r = diagnose(from_recording_path(fit), P, from_recording_path(held))
    assert r["model_adequate"] is True and r["effects"] == [] and r["suspect_parameters"] == []


def from_recording_path(path):
    from otbot_hw.diagnose.data import load

    return load([path])


def test_truncated_recording_is_diagnosed_on_its_complete_samples(tmp_path, capsys):
    full = _write(tmp_path, "full.mcap", {}, "multisine", 3.0, 33)
    cut = tmp_path / "cut.mcap"
    data = full.read_bytes()
    cut.write_bytes(data[:int(0.7 * len(data))])
    assert main(["diagnose", str(cut), "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    (t,) = r["truncated_recordings"]
    assert t["recording"] == str(cut) and 100 < t["complete_samples"] < 301
    assert f"cut short: diagnosed on its {t['complete_samples']} complete samples" in r["verdict"]
    assert any("cut short" in w for w in r["warnings"])


def test_robot_configuration_gives_caster_and_imu_geometry(tmp_path, capsys):
    from otbot_hw.diagnose.geometry import load_geometry
    from otbot_hw.params import ParameterError

    default = load_geometry()  # config/robot.yaml: positions not configured, so they are fitted
    assert default.casters == () and default.imu_position is None
    good = tmp_path / "robot.yaml"
    good.write_text("casters:\n  - {x: {value: 0.35, unit: m}, y: {value: 0.12, unit: m}}\n"
                    "  - {x: {value: 0.35, unit: m}, y: {value: -0.12, unit: m}}\n"
                    "imu:\n  mounting:\n    position: {x: {value: 0.08, unit: m}, y: {value: -0.04, unit: m}}\n")
    g = load_geometry(good)
    assert g.casters == ((0.35, 0.12), (0.35, -0.12)) and g.imu_position == (0.08, -0.04)
    assert g.effect_values() == {"n_cst": 2.0, "x_c1": 0.35, "y_c1": 0.12, "x_c2": 0.35, "y_c2": -0.12,
                                 "d_x": 0.08, "d_y": -0.04}
    for text, message in (("casters: []", "list of 1 to 4"),
                          ("casters:\n  - {x: {value: 0.3, unit: cm}, y: {value: 0, unit: m}}", "unit must be 'm'"),
                          ("casters:\n  - {x: {value: 3.0, unit: m}, y: {value: 0, unit: m}}", "farther than"),
                          ("imu:\n  mounting:\n    position: {x: {value: 0.1, unit: m}}", "imu.mounting.position")):
        bad = tmp_path / "bad.yaml"
        bad.write_text(text + "\n")
        with pytest.raises(ParameterError, match=message):
            load_geometry(bad)
    fit = _write(tmp_path, "fit.mcap", {}, "multisine", 1.0, 34)
    assert main(["diagnose", str(fit), "--robot", str(tmp_path / "bad.yaml")]) == 2
    assert "imu.mounting.position" in capsys.readouterr().err


# --- the diagnosis's fast paths compute the same numbers as the plain ones ------------------------------------------

def test_fast_paths_give_the_plain_numbers():
    """The speed-ups change no number: (1) the integrator's sample accelerations and slip rates (its first RK4
    stage) equal a re-evaluation of the model at the samples, on every fixture, with slip, traction limit, lag,
    friction, caster drag and unequal radii; (2) x0 from the first two filter windows equals x0 from the whole
    record; (3) a cached simulation equals a fresh one, is read-only and is not served for other commands."""
    import dataclasses

    from otbot_hw.diagnose import residuals as R
    from otbot_hw.diagnose import simulated_run as SR
    from otbot_hw.model import effect_physics as phys
    from otbot_hw.model.effects import ExtendedModel
    from otbot_hw.model.fixtures import fixture_code
    from otbot_hw.simulation import integrators

    rng = np.random.default_rng(3)
    U, F = rng.normal(0, 1.5, (200, 3)), rng.normal(0, 2, (200, 2))
    Ff = np.vstack([F, F[-1:]])
    for vals in ({"k_slip": 0.02, "t_trac": 1.0, "dr_r": 0.02, "T_i": 0.01},
                 {"c_w": 0.3, "c_p": 0.2, "s_w": 0.2, "v_s": 0.4, "f_cst": 4.0, "g_x": 0.1, "u_max_l": 1.0}):
        m = ExtendedModel.paper(P).with_values(vals)
        prm = m.params.as_array()
        for fixture in ("floor", "stand", "locked"):
            c = fixture_code(fixture)
            X, TAU, S, QDD, SD = integrators.ext_rk4_zoh_samples(np.zeros(12), np.full(3, 0.1), U, F, 0.01, 3, prm, m.eff, c)
            for a, b in zip((X, TAU, S), integrators.ext_rk4_zoh(np.zeros(12), np.full(3, 0.1), U, F, 0.01, 3, prm, m.eff, c)):
                assert np.array_equal(a, b)
            assert np.array_equal(QDD, phys.ext_sample_accelerations(X, TAU, Ff, m.eff, prm, c))
            assert np.array_equal(SD, phys.slip_rate_samples(X, TAU, Ff, m.eff, prm, c))
            assert np.any(SD != 0) == ("k_slip" in vals and fixture == "floor")
    d = from_recording(concealed_recording(P, {"k_slip": 0.02}, "multisine", 2.0, seed=4), "slip")
    for vals in ({}, {"k_slip": 0.02, "t_trac": 3.0, "k_l": 0.1, "T_i": 0.01}, {"e_r": 0.05, "dr_l": -0.03}):
        m = ExtendedModel.paper(P).with_values(vals)
        whole = R.estimate_motion(d, m, smooth_rates=False)
        assert np.array_equal(SR.encoder_state(d, m), np.concatenate([whole.q[0], whole.qd[0]]))
    m = ExtendedModel.paper(P).with_values({"c_w": 0.2})
    first = SR.simulate_outputs(d, m)
    again = SR.simulate_outputs(d, m)
    SR._SIM_CACHE.clear()
    fresh = SR.simulate_outputs(d, m)
    assert all(np.array_equal(first[k], fresh[k]) and np.array_equal(again[k], fresh[k]) for k in fresh)
    with pytest.raises(ValueError):
        again["w_r"][0] = 0.0
    other = dataclasses.replace(d, u=d.u * 1.5)
    assert not np.array_equal(SR.simulate_outputs(other, m)["w_r"], fresh["w_r"])


def test_summary_says_n_a_for_a_channel_without_a_fit_percentage(tmp_path, capsys):
    """The locked fixture's accelerometer does not move: no fit percentage (None), the text summary
    printed it with :.1f and crashed (TypeError traceback)."""
    locked = tmp_path / "locked.mcap"
    assert main(["simulate", "--fixture", "locked", "--noise", "none", "--duration", "1", "--out", str(locked)]) == 0
    capsys.readouterr()
    assert main(["diagnose", str(locked)]) == 0
    line = next(ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("fitting fit %:"))
    assert "a_x n/a -> n/a" in line and "w_p 100.0" in line
