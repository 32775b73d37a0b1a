"""``benchmarks/diagnose_same.py``, the check that a speed-up changes no diagnosis: it ignores timings, and
flags a changed verdict, a changed effect list and a value off by more than 1e-6 relative."""
from __future__ import annotations

import importlib
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _same():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    return importlib.import_module("diagnose_same")


def test_the_check_ignores_timings_and_flags_verdicts_effects_and_values():
    same = _same()
    r = {"model_adequate": False, "elapsed_s": 3.0, "cpu_s": 5.0,
         "effects": [{"name": "caster_drag", "parameters": {"f_cst": {"value": 6.0, "std": 0.07}}}],
         "discovered": {"laws": [{"law": "linear drag", "refit": {"c_lin": {"value": 15.1}}}], "regression_s": 0.2}}
    a = same._strip(r)
    assert "elapsed_s" not in a and "regression_s" not in a["discovered"]
    timing = {**r, "elapsed_s": 9.0, "cpu_s": 1.0}
    assert same.diff(a, same._strip(timing)) == []
    close = {**r, "effects": [{"name": "caster_drag", "parameters": {"f_cst": {"value": 6.0 * (1 + 1e-8), "std": 0.07}}}]}
    assert same.diff(a, same._strip(close)) == []
    off = {**r, "effects": [{"name": "caster_drag", "parameters": {"f_cst": {"value": 6.0 * (1 + 1e-5), "std": 0.07}}}]}
    assert any("f_cst.value" in d for d in same.diff(a, same._strip(off)))
    assert same.diff(a, same._strip({**r, "model_adequate": True}))
    assert same.diff(a, same._strip({**r, "effects": []}))
    renamed = {**r, "effects": [{"name": "air_drag", "parameters": {"f_cst": {"value": 6.0, "std": 0.07}}}]}
    assert same.diff(a, same._strip(renamed))
