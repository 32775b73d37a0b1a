"""Where the diagnosis's nested fits start: a held delay (IMU latency) inside a sample interval, chosen by a
scan, and no fit for an effect whose parameters are already free beside it. The family study's misses these
close: a PRBS IMU latency of 12.5 ms fitted 20.0 ms (its catalog start, on the model's jump at two sample
periods), and a wheel slip "found" beside a traction limit that has the same k_slip."""
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from otbot_hw.diagnose import catalog as cat
from otbot_hw.diagnose import rules
from otbot_hw.diagnose import select
from otbot_hw.diagnose.data import from_recording
from otbot_hw.model.effects import ExtendedModel, effect_vector
from otbot_hw.params import nominal
from otbot_hw.simulation.concealed import concealed_recording

P = nominal()


@settings(max_examples=200, deadline=None)
@given(st.lists(st.sampled_from([0.001, 0.002, 0.004, 0.005, 0.01, 0.0125]), min_size=1, max_size=3, unique=True),
       st.floats(0.0, 0.05), st.floats(0.001, 0.1))
def test_mid_interval_delays_sit_inside_a_sample_interval_of_every_period(periods, lo, width):
    periods = sorted(periods)
    hi = lo + width
    got = select.mid_interval_delays(periods, lo, hi)
    dt = periods[0]
    for v in got:
        assert lo < v < hi
        for q in periods:  # never on (or within a quarter of the finest period of) a jump of any recording
            assert abs(v / q - round(v / q)) * q >= 0.25 * dt - 1e-12
    if len(periods) == 1:  # one recording rate: every interval inside (lo, hi) has its middle
        assert len(got) == sum(lo < (k + 0.5) * dt < hi for k in range(int(hi / dt) + 2))
    coarse = select.mid_interval_delays(periods, lo, hi, spacing=0.008)
    assert set(coarse) <= set(got) and (not got or coarse[0] == got[0])
    assert all(b - a >= 0.008 - 1e-12 for a, b in zip(coarse, coarse[1:]))


@pytest.mark.parametrize("truth", [0.0125, 0.025])
def test_an_imu_latency_fit_starts_in_the_sample_interval_of_the_true_latency(truth):
    """Torque steps at 100 Hz: the start is the mid-interval delay the simulation fits best, not the catalog's
    20 ms (a whole number of periods, where the readings jump and a finite-difference slope means nothing)."""
    rec = from_recording(concealed_recording(P, {"d_imu": truth}, "steps", 4.0, dt=0.01, seed=3), "steps")
    search = select._Search([rec], [], None, [], lambda m: None, True)
    e = search.by_name["imu_latency"]
    assert e.held_delays == ("d_imu",)
    start = search._better_start(e, ExtendedModel(P, effect_vector()), {"d_imu": 0.02})
    k = np.floor(truth / rec.dt)
    assert k * rec.dt < start["d_imu"] < (k + 1) * rec.dt, start
    assert start["d_imu"] / rec.dt % 1.0 == pytest.approx(0.5)


def test_an_effect_whose_parameters_are_already_fitted_is_no_candidate(monkeypatch):
    """Wheel slip beside a traction limit: k_slip is free in both, so the "nested fit" would only continue the
    traction limit's fit and its BIC gain would read as a second effect."""
    def must_not_fit(*a, **kw):
        raise AssertionError("fitted an effect that adds no parameter")

    monkeypatch.setattr(select, "refit", must_not_fit)
    search = select._Search([SimpleNamespace(fixture="floor")], [], None, [], lambda m: None, True)
    on = SimpleNamespace(names=["m_c", "k_slip", "t_trac"], model=None)
    c = search.nested("wheel_slip", on, (0.0, 0.0, 0.0), {"k_slip": 0.01})
    assert not rules.has_evidence(c) and not rules.fitting_evidence(c) and c not in search.tried
    assert set(cat.CATALOG[[e.name for e in cat.CATALOG].index("wheel_slip")].parameters) <= set(on.names)
