"""The shortcuts that keep every diagnosis under 10 s of CPU (issue 20 item 6) keep what they stand in for:
the RK4 step off the floor and with a friction sign, the initial rates of a Jacobian column from its centre's rate sensitivity, the
centre of a finite-difference batch, a diverged simulation read without overflow, and the check that a speed-up
changes no conclusion (``benchmarks/diagnose_same.py --conclusions``)."""
from __future__ import annotations

import importlib
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from otbot_hw.diagnose import simulated_run as SR
from otbot_hw.diagnose.data import from_recording
from otbot_hw.diagnose.prediction import ExtendedPredictionModel
from otbot_hw.diagnose.refit import channel_sigmas, weighted_residuals
from otbot_hw.model.effects import ExtendedModel
from otbot_hw.params import nominal
from otbot_hw.simulation.concealed import concealed_recording

ROOT = Path(__file__).resolve().parent.parent
P = nominal()


@pytest.fixture(scope="module")
def stand():
    return from_recording(concealed_recording(P, {}, "stand", 2.0, seed=3), "stand")


@pytest.fixture(scope="module")
def floor():
    return from_recording(concealed_recording(P, {}, "multisine", 3.0, seed=4), "multisine")


@pytest.mark.parametrize("vals", [{}, {"T_i": 0.005}, {"k_r": 0.1}])
def test_off_the_floor_the_coarser_step_is_within_a_hundredth_of_the_noise(stand, vals):
    """Without a friction sign the stand is simulated at 5 ms (was the default's 0.5 ms, kept with friction)."""
    m = ExtendedModel.paper(P).with_values(vals)
    sub = SR.diagnosis_substeps(stand.dt, stand.fixture, m.eff)
    assert sub < SR.default_substeps(stand.dt, "stand")
    x0 = SR.initial_state(stand, m)
    fine = SR.simulate_outputs(stand, m, x0, substeps=64, cached=False)
    got = SR.simulate_outputs(stand, m, x0, cached=False)
    for ch in stand.channels():
        assert np.max(np.abs(got[ch] - fine[ch])) < 0.01 * stand.noise_sigma(ch), ch


@pytest.mark.parametrize("rec,vals", [("stand", {"c_w": 0.002}), ("stand", {"c_w": 0.3}), ("floor", {"c_w": 0.002}),
                                      ("floor", {"c_w": 0.3}), ("floor", {"c_rr": 0.0005, "c_p": 0.05})])
def test_with_a_friction_sign_the_step_follows_its_level_and_stays_accurate(request, rec, vals):
    """A small friction level (a candidate's start) runs at a coarser step than the simulator's default, a large
    one at the default's (which keeps the stiffest sign stable); both within 0.1 sigma of 64 steps per sample."""
    d = request.getfixturevalue(rec)
    m = ExtendedModel.paper(P).with_values(vals)
    sub, default = SR.diagnosis_substeps(d.dt, d.fixture, m.eff, m.params), SR.default_substeps(d.dt, d.fixture)
    if max(vals.values()) >= 0.3:
        assert 0.9 * default <= sub <= default
    else:
        assert sub < default
    x0 = SR.initial_state(d, m)
    fine = SR.simulate_outputs(d, m, x0, substeps=64, cached=False)
    got = SR.simulate_outputs(d, m, x0, cached=False)
    for ch in d.channels():
        assert np.max(np.abs(got[ch] - fine[ch])) < 0.1 * d.noise_sigma(ch), ch


def test_a_jacobian_column_takes_its_centres_rate_sensitivity_and_lands_where_its_own_fit_does(floor):
    """A column next to the centre (a relative step of 1e-6, as the fitter's) gets the initial state its own
    rate fit gives, to far below the fitted rates' std (sigma / sqrt(n_head) ~ 1e-3 rad/s), from one head
    simulation instead of four; a model far from the centre is not a column and is fitted on its own."""
    centre = ExtendedModel.paper(P).with_values({"k_slip": 0.02})
    calls = []
    orig = SR._simulate_outputs

    def counted(data, model, x0, sub):
        calls.append(len(data))
        return orig(data, model, x0, sub)

    SR.initial_state(floor, centre)
    for name in ("m_c", "k_slip", "b_w"):
        col = centre.with_values({name: centre.get(name) * (1 + 1e-6)})
        own = SR._fitted_start(floor, col)[0]
        SR._SIM_CACHE.clear()
        calls.clear()
        try:
            SR._simulate_outputs = counted
            got = SR.initial_state(floor, col, rates_from=centre)
        finally:
            SR._simulate_outputs = orig
        assert len(calls) == 1, name  # the head at rest only: the sensitivity is the centre's
        assert np.allclose(got[:6], own[:6], atol=1e-12) and np.allclose(got[6:], own[6:], atol=1e-6), name


def test_the_centre_of_a_finite_difference_batch_is_found_and_nothing_else_is_one():
    pm = ExtendedPredictionModel(ExtendedModel.paper(P))
    th = pm.vector()
    i, j, k = (pm.names.index(n) for n in ("m_c", "b_w", "k_slip"))
    rows = np.repeat(th[None], 3, axis=0)
    rows[0, i] += 1e-6 * th[i]
    rows[1, j] += 1e-6 * th[j]
    rows[2, k] += 1e-8
    c = pm._centre(rows)
    assert c is not None and np.array_equal(pm.vector(c), th)
    trial = rows.copy()
    trial[0, j] += 0.1 * th[j]  # a row that moved two entries, one far: not a Jacobian
    assert pm._centre(trial) is None
    assert pm._centre(rows[:2]) is None  # two rows: the centre is ambiguous


def test_a_diverged_simulation_reads_as_failed_without_overflow(floor, monkeypatch):
    m = ExtendedModel.paper(P)
    huge = {ch: np.full(len(floor), 1e200) for ch in floor.channels()}
    monkeypatch.setattr("otbot_hw.diagnose.refit.simulate_outputs", lambda d, model, x0=None: huge)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = weighted_residuals([floor], m, channel_sigmas([floor]))
        total = sum(float(v @ v) for v in res.values())
    assert all(np.all(v == 1e6) for v in res.values()) and np.isfinite(total)


def test_the_same_conclusions_check_flags_what_a_diagnosis_concludes_and_lists_what_moved():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    same = importlib.import_module("diagnose_same")

    def result(adequate=True, f_cst=6.0, effects=("caster_drag",), withheld=()):
        par = {"f_cst": {"value": f_cst, "std": 0.1}}
        return {"model_adequate": adequate, "effects": [{"name": e, "parameters": par} for e in effects],
                "ambiguous": [], "withheld": [{"name": w, "parameters": par} for w in withheld],
                "detected_small": [], "discovered": None}

    a = result()
    assert same.diff_conclusions(a, result()) == ([], [])
    bad, moved = same.diff_conclusions(a, result(f_cst=6.6))  # +10 %: the same conclusion, listed as moved
    assert bad == [] and len(moved) == 1 and "f_cst" in moved[0]
    assert same.diff_conclusions(a, result(f_cst=7.5))[0]  # +25 %: beyond the study's 20 % rule
    assert same.diff_conclusions(a, result(adequate=False))[0]
    assert same.diff_conclusions(a, result(effects=()))[0]
    assert same.diff_conclusions(result(adequate=False, effects=(), withheld=("gain_pivot",)),
                                 result(adequate=False, effects=()))[0]
