"""The diagnosis's selection rules, pinned at their thresholds: each test sits just inside and just
outside one rule, so changing a threshold (or flipping a comparison) fails it. Rules: screening bar
(SCREEN_DBIC, LATER_ROUND_FACTOR), shortlist size and fraction (MAX_CANDIDATES, SHORTLIST_FRACTION),
acceptance by evidence (ACCEPT_DBIC, its sign, held-out, residual correlation), ambiguity margin
(AMBIGUOUS_DBIC), physical significance (TORQUE_FRACTION, HEADING_DRIFT, Z_MIN, ...), model adequacy
(noise ratios, bounds, plausible refits). Pure functions on small inputs: fast."""
import numpy as np
import pytest

from otbot_hw.diagnose import adequacy
from otbot_hw.diagnose import rules as sel
from otbot_hw.diagnose import significance as sig
from otbot_hw.diagnose.data import DiagnosisData
from otbot_hw.model.effects import ExtendedModel
from otbot_hw.params import nominal

P = nominal()


def test_screening_bar_admits_gains_beyond_it_only():
    assert sel.shortlist({"a": -10.5, "b": -9.5}, {}, 0) == ["a"]
    assert sel.shortlist({}, {"a": -9.5}, 0) == []
    # later rounds need LATER_ROUND_FACTOR times the evidence
    assert sel.shortlist({"a": -49.0, "b": -51.0}, {}, 1) == ["b"]
    assert sel.shortlist({"a": -49.0}, {"c": -52.0}, 2) == ["c"]


def test_shortlist_keeps_the_best_three_within_a_tenth_of_the_best_gain():
    eq = {"a": -1000.0, "b": -99.0, "c": -101.0}
    assert sel.shortlist(eq, {}, 0) == ["a", "c"]
    many = {"a": -500.0, "b": -400.0, "c": -300.0, "d": -200.0}
    assert sel.shortlist(many, {}, 0) == ["a", "b", "c"]
    # the two screenings are merged without repeats, equation screening first
    assert sel.shortlist({"a": -100.0}, {"x": -50.0, "a": -60.0}, 0) == ["a", "x"]


def _cand(dbic, kappa=1.0, dholdout=-1.0, name="e", significance=None):
    return sel.Candidate(name, None, dbic, dbic, dholdout, float("nan"), kappa=kappa,
                         significance=significance or {})


def test_acceptance_needs_bic_evidence_in_effective_samples_and_no_worse_held_out():
    assert sel.has_evidence(_cand(-10.5))
    assert not sel.has_evidence(_cand(-9.5))
    assert not sel.has_evidence(_cand(+50.0))
    assert not sel.has_evidence(_cand(-50.0, dholdout=+0.5))  # predicts the held-out runs worse
    assert sel.has_evidence(_cand(-50.0, dholdout=float("nan")))  # no held-out runs
    # correlated residuals (kappa = N / N_eff) deflate the evidence
    assert sel.has_evidence(_cand(-21.0, kappa=2.0)) and not sel.has_evidence(_cand(-19.0, kappa=2.0))


def test_ambiguity_margin_in_effective_samples():
    best = _cand(-1000.0, name="best")
    near, far = _cand(-990.5, name="near"), _cand(-989.5, name="far")
    assert [c.effect for c in sel.ambiguous_group(best, [near, far])] == ["best", "near"]
    wide = _cand(-1000.0, kappa=3.0, name="best")
    assert [c.effect for c in sel.ambiguous_group(wide, [_cand(-971.0, name="x"), _cand(-969.0, name="y")])] \
        == ["best", "x"]


def _recording(u_rms=2.0, w_rms=3.0, n=400):
    """Commands and encoder rates with the given RMS (sine waves), no IMU."""
    t = np.arange(n) * 0.01
    s = np.sqrt(2) * np.sin(2 * np.pi * 0.5 * t)
    u = np.column_stack([u_rms * s, u_rms * s, u_rms * s])
    w = np.column_stack([w_rms * s, w_rms * s, w_rms * s])
    return DiagnosisData("synthetic", t, 0.01, u, np.cumsum(w, 0) * 0.01, w, None, None, "floor")


def _sig(name, values, std=None):
    std = std or {k: abs(v) / 100 + 1e-12 for k, v in values.items()}
    return sig.significance(name, values, std, ExtendedModel.paper(P), [_recording()])


def test_torque_effects_matter_from_one_percent_of_the_command():
    # RMS command 2 N m: the limit is 0.02 N m
    assert _sig("coulomb_pivot", {"c_p": 0.021})["matters"]
    assert not _sig("coulomb_pivot", {"c_p": 0.019})["matters"]
    assert _sig("gain_left", {"k_l": -0.0105})["matters"]
    assert not _sig("gain_left", {"k_l": -0.0095})["matters"]


def test_gyro_bias_matters_by_heading_drift_not_by_fit_percent():
    s = _sig("imu_bias", {"b_ax": 0.0, "b_ay": 0.0, "b_gz": 0.0059}, {"b_ax": 1e-3, "b_ay": 1e-3, "b_gz": 3e-4})
    assert s["matters"] and "20° of heading per minute" in s["statement"] and "5.9 ± 0.3 mrad/s" in s["statement"]
    per_min = np.deg2rad(1.0) / 60.0  # rad/s: 1 degree of heading per minute
    zero = {"b_ax": 0.0, "b_ay": 0.0}
    assert _sig("imu_bias", {**zero, "b_gz": 1.05 * per_min})["matters"]
    assert not _sig("imu_bias", {**zero, "b_gz": 0.95 * per_min})["matters"]
    acc = 2 * 0.05 / 10.0 ** 2  # m/s^2: 5 cm of position in 10 s
    assert _sig("imu_bias", {"b_ax": 1.05 * acc, "b_ay": 0.0, "b_gz": 0.0})["matters"]
    assert not _sig("imu_bias", {"b_ax": 0.95 * acc, "b_ay": 0.0, "b_gz": 0.0})["matters"]


@pytest.mark.parametrize("name,param,limit", [
    ("imu_misalignment", "psi", np.deg2rad(0.2)), ("imu_latency", "d_imu", 1e-3), ("current_lag", "T_i", 1e-3)])
def test_geometry_and_delay_effects_matter_from_their_thresholds(name, param, limit):
    assert _sig(name, {param: 1.05 * limit})["matters"]
    assert not _sig(name, {param: 0.95 * limit})["matters"]


def test_scale_lever_and_radius_thresholds():
    f = 0.002  # 0.2 % of the distance
    assert _sig("encoder_scale", {"e_r": 1.05 * f, "e_l": 0.0})["matters"]
    assert not _sig("encoder_scale", {"e_r": 0.95 * f, "e_l": 0.0})["matters"]
    assert _sig("wheel_radii", {"dr_r": 1.05 * f, "dr_l": 0.0})["matters"]
    assert not _sig("wheel_radii", {"dr_r": 0.95 * f, "dr_l": 0.0})["matters"]
    d = 0.01  # m
    assert _sig("imu_lever_arm", {"d_x": 1.05 * d, "d_y": 0.0})["matters"]
    assert not _sig("imu_lever_arm", {"d_x": 0.95 * d, "d_y": 0.0})["matters"]


def test_an_effect_within_its_own_uncertainty_does_not_matter():
    big = 0.5  # N m: far above the torque threshold
    assert _sig("coulomb_pivot", {"c_p": big}, {"c_p": big / 1.9})["matters"] is False  # 1.9 sigma
    assert _sig("coulomb_pivot", {"c_p": big}, {"c_p": big / 2.1})["matters"] is True


def _clean_residuals(rng, n, channels=6, scale=1.0):
    """Residuals of a right model: white noise (times ``scale``) over the noise level the diagnosis measures
    from the same series (MAD of second differences)."""
    from otbot_hw.diagnose.data import mad_sigma

    out = {}
    for j in range(channels):
        y = scale * rng.standard_normal(n)
        out[("r", f"c{j}")] = y / mad_sigma(y / scale)
    return out


def test_adequacy_test_keeps_its_size_on_white_noise_at_every_length():
    """The size is what the test says: over 300 clean diagnoses of 6 channels each (1 s at 100 Hz to 60 s
    at 100 Hz), at most 2 % are judged inadequate at ALPHA = 1 % (binomial: 3 expected at most)."""
    rng = np.random.default_rng(7)
    for n in (100, 1000, 6000):
        bad = sum(bool(adequacy.failed(adequacy.residual_tests(_clean_residuals(rng, n), adequacy.EXCESS_FITTING,
                                                               "fitting"))) for _ in range(100))
        assert bad <= 2, (n, bad)
    # at the tolerated excess itself the size still holds (the hypothesis is "excess <= EXCESS")
    edge = [_clean_residuals(rng, 3000, scale=np.sqrt(1 + adequacy.EXCESS_FITTING)) for _ in range(100)]
    assert sum(bool(adequacy.failed(adequacy.residual_tests(r, adequacy.EXCESS_FITTING, "fitting"))) for r in edge) <= 2
    # ... and with no excess tolerated the same residuals are rejected
    assert all(adequacy.failed(adequacy.residual_tests(r, 0.0, "fitting")) for r in edge[:5])


def test_adequacy_test_finds_a_misfit_and_where_it_sits():
    rng = np.random.default_rng(8)
    res = _clean_residuals(rng, 4000)
    res[("r", "c2")] = res[("r", "c2")] * np.sqrt(1.6)  # 60 % unexplained variance on one channel
    bad = adequacy.failed(adequacy.residual_tests(res, adequacy.EXCESS_FITTING, "fitting"))
    assert {b["channel"] for b in bad} == {"c2"}
    res = _clean_residuals(rng, 4000)
    res[("r", "c4")][:1000] += 1.5  # a misfit in the first quarter only (a wrong initial state)
    bad = adequacy.failed(adequacy.residual_tests(res, adequacy.EXCESS_FITTING, "fitting"))
    assert {b["channel"] for b in bad} == {"c4"} and [0, 1000] in [b["samples"] for b in bad]
    assert all(b["noise_ratio"] > b["limit"] for b in bad)


def test_noise_level_of_a_quantized_reading_is_its_step():
    from otbot_hw.diagnose.data import resolution

    y = np.round(np.linspace(0, 0.05, 500) / 1e-3) * 1e-3  # a slow reading in 1e-3 steps, no noise above a step
    assert resolution(y) == pytest.approx(1e-3)
    assert resolution(np.random.default_rng(0).standard_normal(500)) == 0.0


def test_adequacy_bounds_and_plausible_refits():
    # on a bound: within 1e-3 of the range (gains: -0.5 .. 0.5)
    assert [b["parameter"] for b in adequacy.on_bound({"k_r": -0.4995, "k_l": -0.498})] == ["k_r"]
    assert adequacy.on_bound({"c_p": 0.0}) == []  # zero friction: absent, not clipped
    # the chassis mass may move 30 % from the file, a centre-of-mass coordinate 0.1 m
    assert adequacy.implausible_shifts({"m_c": P.m_c * 1.29}, P) == []
    assert [m["parameter"] for m in adequacy.implausible_shifts({"m_c": P.m_c * 1.31}, P)] == ["m_c"]
    assert adequacy.implausible_shifts({"x_B": P.x_B + 0.098}, P) == []
    assert len(adequacy.implausible_shifts({"x_B": P.x_B - 0.102}, P)) == 1


def test_shortlist_alternates_between_the_screenings_up_to_max_nested():
    eq = {"a": -900.0, "b": -800.0, "c": -700.0}
    sim = {"a": -500.0, "x": -400.0, "y": -300.0}
    assert sel.shortlist(eq, sim, 0) == ["a", "b", "x", "c"][:sel.MAX_NESTED]


def test_a_second_effect_beside_the_first_needs_its_own_evidence_and_no_worse_held_out():
    first = _cand(-5000.0, dholdout=-3000.0)
    assert sel.pair_adds(_cand(-5010.5, dholdout=-3000.0), first)
    assert not sel.pair_adds(_cand(-5009.5, dholdout=-3000.0), first)
    assert not sel.pair_adds(_cand(-6000.0, dholdout=-2999.0), first)  # predicts the held-out runs worse
    assert sel.pair_adds(_cand(-5021.0, kappa=2.0, dholdout=-3100.0), first)
    assert not sel.pair_adds(_cand(-5019.0, kappa=2.0, dholdout=-3100.0), first)
    assert sel.fitting_evidence(_cand(-10.5, dholdout=+100.0)) and not sel.fitting_evidence(_cand(-9.5))


def test_white_residuals_end_the_search():
    assert sel.white(_cand(-100.0, kappa=1.19)) and not sel.white(_cand(-100.0, kappa=1.21))


def test_a_candidate_that_only_adds_a_parameter_is_not_a_look_alike():
    slip = sel.Candidate("wheel_slip", None, -1000.0, -1000.0, -1.0, 0.0, parameters=("k_slip",))
    limit = sel.Candidate("traction_limit", None, -1001.0, -1001.0, -1.0, 0.0, parameters=("k_slip", "t_trac"))
    enc = sel.Candidate("encoder_scale", None, -995.0, -995.0, -1.0, 0.0, parameters=("e_r", "e_l"))
    assert [c.effect for c in sel.ambiguous_group(limit, [slip, enc])] == ["wheel_slip", "encoder_scale"]
    assert [c.effect for c in sel.ambiguous_group(slip, [limit])] == ["wheel_slip"]


def test_a_parameter_on_its_bound_is_not_identifiable_only_when_its_std_says_the_data_do_not_determine_it():
    from otbot_hw.diagnose import identifiability as ident

    on = adequacy.on_bound({"I_c": 1e-9, "k_r": -0.5})
    assert [b["parameter"] for b in on] == ["I_c", "k_r"]
    files = {"I_c": P.I_c}
    # std 0.99 kg m^2 (a 1 s run under one constant torque): the file's 1.3 is within 3 std of the bound
    loose = ident.undetermined_on_bound(on, {"I_c": 0.99, "k_r": 1.0}, files)
    assert [u["parameter"] for u in loose] == ["I_c"] and "otbot identify chassis" in loose[0]["record"]
    assert ident.undetermined_on_bound(on, {"I_c": float("nan")}, files)[0]["std"] is None
    # determined (std 0.1): on the bound is evidence of a wrong model; an effect parameter never qualifies
    assert ident.undetermined_on_bound(on, {"I_c": P.I_c / ident.BOUND_SIGMAS - 0.01, "k_r": 1.0}, files) == []


def test_an_effect_is_identifiable_when_its_signature_beats_the_evidence_it_would_need():
    from otbot_hw.diagnose import identifiability as ident

    need = ident.needed_chi2(1, 1000)
    assert need == pytest.approx(sel.ACCEPT_DBIC + np.log(1000))
    out = ident.effect_identifiability({"a": (need * 1.01, 1, 1000, {"c_w": 0.15}),
                                        "b": (need / 4, 1, 1000, {"c_w": 0.15})})
    assert out["a"]["identifiable"] and not out["b"]["identifiable"]
    assert out["b"]["revealable_factor"] == pytest.approx(2.0)  # chi2 grows with the square of the size
    missing = ident.not_identifiable_effects(out, set(), {"b": "B"})
    assert [m["name"] for m in missing] == ["b"] and missing[0]["record"]
    assert ident.not_identifiable_effects(out, {"b"}, {}) == []  # found: evidently revealed
    from otbot_hw.diagnose.catalog import CATALOG
    assert {e.name for e in CATALOG} == set(ident.EFFECT_RECORD)


def test_a_nested_fit_whose_simulation_diverges_is_no_candidate_not_a_crash(monkeypatch):
    """The wheel-slip run under one constant torque of the family study: a look-alike's trial point made the
    simulation diverge (NaN in the Jacobian's SVD) and the diagnosis crashed."""
    from types import SimpleNamespace

    from otbot_hw.diagnose import select

    def diverges(*args, **kw):
        raise ValueError("array must not contain infs or NaNs")

    monkeypatch.setattr(select, "refit", diverges)
    monkeypatch.setattr(select._Search, "_better_start", lambda self, e, model, guess: guess)  # not under test
    search = select._Search([SimpleNamespace(fixture="floor")], [], None, [], lambda m: None, True)
    base = SimpleNamespace(names=["m_c"], model=None)
    c = search.nested("traction_limit", base, (0.0, 0.0, 0.0), {"k_slip": 0.01, "t_trac": 2.0})
    assert not sel.has_evidence(c) and not sel.fitting_evidence(c) and c not in search.tried
    assert len(sel.ambiguous_group(_cand(-100.0), [c])) == 1  # no look-alike of anything


def test_a_held_out_run_beyond_the_fitting_runs_range_is_told_apart_and_saturation_above_the_commands():
    from types import SimpleNamespace

    from otbot_hw.diagnose import identifiability as ident
    from otbot_hw.diagnose.catalog import applicable

    def rec(u_top, w_top):
        u = np.outer(np.linspace(-1, 1, 50), u_top)
        return SimpleNamespace(u=u, measured=lambda ch: np.linspace(-w_top, w_top, 50) if ch.startswith("w_") else None)

    fit = [rec([3.0, 3.0, 2.0], 5.0)]
    assert ident.outside_range(fit, rec([3.05, 3.0, 2.0], 5.0)) == []  # within 2 % of the span
    beyond = ident.outside_range(fit, rec([4.0, 3.0, 2.0], 5.0))
    assert len(beyond) == 2 and beyond[0].startswith("u_r up to 4")  # up and down
    assert any(b.startswith("w_p") for b in ident.outside_range(fit, rec([3.0, 3.0, 2.0], 6.0)))
    sat = ident.saturation_not_identifiable(fit, applicable({"floor"}), {"saturation_right"})
    assert {s["name"] for s in sat} == {"torque_saturation", "saturation_left", "saturation_pivot"}
    assert "(2 N m)" in next(s["why"] for s in sat if s["name"] == "saturation_pivot")


def test_a_parameter_on_its_bound_is_undetermined_when_held_at_the_files_value_the_fit_is_barely_worse(monkeypatch):
    """The likelihood-ratio form of the bound rule: I_c on its bound with std 0.33 kg m^2 (the file's 1.3 is
    4 std away, linearized at the bound) is not evidence of a wrong model when refitting with I_c held at 1.3
    costs less than BOUND_SIGMAS^2 of chi2 (a traction limit under closed-loop torques: 7.3); it is when the
    rise is larger."""
    from types import SimpleNamespace

    from otbot_hw.diagnose import identifiability as ident

    model = ExtendedModel.paper(P)
    final = SimpleNamespace(names=["m_c", "I_c"], values={"m_c": 100.0, "I_c": 1e-9}, std={"m_c": 2.0, "I_c": 0.33},
                            model=model, rss={("fit", "a_x"): 1000.0, ("fit", "g_z"): 232.0})
    on = adequacy.on_bound(final.values)
    assert ident.undetermined_on_bound(on, final.std, {"I_c": P.I_c}) == []  # the std alone: determined
    seen = []

    def held_fit(rise):
        def fake(recordings, m, names, **kw):
            seen.append((m.get("I_c"), list(names)))
            return SimpleNamespace(rss={("fit", "a_x"): 1000.0 + rise, ("fit", "g_z"): 232.0})
        return fake

    monkeypatch.setattr(adequacy, "refit", held_fit(7.3))
    u = adequacy._profile_undetermined([], final, on[0], P.I_c)
    assert u["parameter"] == "I_c" and u["chi2_rise"] == pytest.approx(7.3) and "otbot identify chassis" in u["record"]
    assert seen == [(pytest.approx(P.I_c), ["m_c"])]  # held at the file's value, the others refit
    monkeypatch.setattr(adequacy, "refit", held_fit(12.0))
    assert adequacy._profile_undetermined([], final, on[0], P.I_c) is None
