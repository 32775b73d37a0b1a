"""Beyond the catalog: sparse regression of the residual torques (otbot_hw/diagnose/discover.py)."""
import importlib
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent


def test_stlsq_keeps_the_true_terms_and_drops_the_rest():
    from otbot_hw.diagnose.discover import _stlsq

    rng = np.random.default_rng(0)
    A = rng.standard_normal((2000, 8))
    y = 0.7 * A[:, 1] - 0.3 * A[:, 5] + 0.5 * rng.standard_normal(2000)
    coef, std, active = _stlsq(A, y, 4.0)
    assert list(np.nonzero(active)[0]) == [1, 5]
    assert abs(coef[1] - 0.7) < 4 * std[1] and abs(coef[5] + 0.3) < 4 * std[5]


@pytest.fixture(scope="module")
def ir():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    return importlib.import_module("independent_robot")


def test_cogging_on_one_wheel_is_discovered_with_held_out_improvement(ir, tmp_path):
    """Cogging 0.3 N m sin(4 phi_r) on the right wheel (not in the catalog) on the independent robot: the
    regression names sin(4 phi_r) on that wheel with about its size, and the held-out right-wheel torque
    residual shrinks by more than half. (Linear platform drag and a pivot dead zone are not yet named
    reliably: docs/diagnose.md.)"""
    from otbot_hw.diagnose.data import load
    from otbot_hw.diagnose.discover import discover
    from otbot_hw.diagnose.refit import refit
    from otbot_hw.diagnose.select import free_nominal
    from otbot_hw.model.effects import ExtendedModel
    from otbot_hw.params import nominal

    world = ir.World(cogging=(0.3, 4))
    for kind, seed in (("piecewise", 31), ("smooth", 32)):
        ir.record(tmp_path / f"{kind}.mcap", world, kind, seed)
    fit, hold = load([tmp_path / "piecewise.mcap"]), load([tmp_path / "smooth.mcap"])
    base = refit(fit, ExtendedModel.paper(nominal()), free_nominal(fit))
    r = discover(fit, hold, base.model)
    cog = [t for t in r["terms"] if t["term"] == "sin(4 phi_r)"]
    assert cog and 0.2 < cog[0]["value"] < 0.4 and cog[0]["joint"] == "r", r["terms"]
    assert r["heldout"]["r"]["after_rms"] < 0.5 * r["heldout"]["r"]["before_rms"], r["heldout"]
