"""The diagnosis on recordings from the independent simulator (benchmarks/diagnose_independent.py):
its own 9x9 dynamics, nearly hard friction sign (tanh(w / 0.005 rad/s)), own sensor model and plain mcap
writer, no truth topic. Small fast version of that benchmark: pivot Coulomb friction (the case the tool's
smoothed sign got wrong when it was 0.2 rad/s wide) and the negative control, one seed pair each."""
import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def independent():
    spec = importlib.util.spec_from_file_location("diagnose_independent", ROOT / "benchmarks" / "diagnose_independent.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _case(mod, label):
    return next(c for c in mod.CASES if c[0] == label)


def test_sharp_pivot_coulomb_friction_is_named_alone_and_sized(independent):
    r = independent.run_case(_case(independent, "coulomb_pivot"), rep=0)
    assert r["named"] == ["coulomb_pivot"] and r["ambiguous"] == [], r["verdict"]
    assert abs(r["rel_error"]["c_p"]) < 0.05, r["estimate"]
    assert r["heldout_after"] > r["heldout_before"] + 20 and r["heldout_after"] > 90


def test_independent_negative_control_adds_nothing(independent):
    r = independent.run_case(_case(independent, "none"), rep=0)
    assert r["named"] == [] and r["ambiguous"] == [] and r["estimate"] == {}
    assert r["verdict"].startswith("No missing physics found")
