"""The diagnosis's speed-ups change no number (issue 20 item 6): the initial state of a model next to one
whose initial rates were fitted, decided at rest with the reused rate sensitivity, equals the full fit's."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from otbot_hw.diagnose import simulated_run as SR
from otbot_hw.diagnose.data import from_recording
from otbot_hw.model.effects import ExtendedModel
from otbot_hw.params import nominal
from otbot_hw.simulation.concealed import concealed_recording

P = nominal()


def _counting(monkeypatch):
    calls = [0]
    plain = SR.simulate_outputs

    def counted(*a, **k):
        calls[0] += 1
        return plain(*a, **k)

    monkeypatch.setattr(SR, "simulate_outputs", counted)
    return calls


@pytest.mark.parametrize("moving", [False, True])
def test_reused_rate_sensitivity_gives_the_full_fits_initial_state(monkeypatch, moving):
    """Near models (a Jacobian column, a small fitter step) of a record starting at rest take the shortcut
    (one head simulation instead of four) and get the full fit's x0; a far model, or a record starting in
    motion, gets the full fit."""
    d = from_recording(concealed_recording(P, {"c_w": 0.1}, "multisine", 2.0, seed=7), "run")
    if moving:
        d = d.segment(60, len(d))  # cut where the robot moves
    m = ExtendedModel.paper(P).with_values({"c_w": 0.1})
    x0 = SR.initial_state(d, m)  # fits the rates under m: its sensitivity is kept
    assert np.any(x0[6:] != 0.0) == moving
    calls = _counting(monkeypatch)
    for name, rel in (("b_w", 1e-6), ("I_p", -1e-6), ("c_w", 3e-4), ("b_p", 0.5)):
        near = m.with_values({name: m.get(name) * (1 + rel)})
        before = calls[0]
        got = SR._fitted_start(d, near)
        sims = calls[0] - before
        fresh = SR._fitted_start(dataclasses.replace(d), near)  # a copy with an empty memo: the full fit
        assert np.array_equal(got, fresh), (name, got, fresh)
        assert sims == (1 if abs(rel) < SR.NEAR_MODEL and not moving else 4), (name, sims)
