"""The simulated robot in process gives the same bits as before its speed work (issue 19).

``tests/data/direct_reference.npz`` holds ``sim.direct.DirectSimRobot``'s outputs on 1500 samples of four
effect settings (paper model; drive and sensor effects; friction forces; slip with a current lag and an
IMU latency), with limits, quantization, noise, a pivot force, a quick stop, and parameters and effects
changed mid-run, as main at 31ef067 computed them (``tests/data/make_direct_reference.py``)."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

DATA = Path(__file__).parent / "data"


def _reference():
    sys.path.insert(0, str(DATA))
    try:
        import make_direct_reference as ref
    finally:
        sys.path.remove(str(DATA))
    return ref


REF = _reference()


@pytest.mark.parametrize("setting", list(REF.SETTINGS))
def test_direct_robot_outputs_are_bit_identical_to_the_reference(setting):
    d = np.load(DATA / "direct_reference.npz")
    out = REF.run(setting)
    # the run does reach the paths it is meant to: saturation, the quick stop's refused writes, the IMU
    assert np.nansum(out["saturated"]) > 10 and np.isnan(out["commanded"][750]).all()
    assert np.isfinite(out["accel"]).all(axis=1).sum() >= 140
    for c in REF.CHANNELS:
        rows = d[f"{setting}/{c}/rows"]
        assert np.array_equal(out[c][::50], rows, equal_nan=True), \
            f"{c}: max difference {np.nanmax(np.abs(out[c][::50] - rows)):.3g}"
        assert REF.digest(out[c]) == str(d[f"{setting}/{c}/digest"]), f"{c}: digest differs"
