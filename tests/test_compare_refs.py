"""benchmarks/compare_refs.py: the numbers it reads from a benchmark's output, the "moved" rule, bad input."""
from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "compare_refs.py"


def _module():
    spec = importlib.util.spec_from_file_location("compare_refs", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_numbers_are_read_from_json_leaves_strings_and_printed_tables():
    cr = _module()
    flat = cr.flatten({"a": {"b": [1, 2.5]}, "t": "4.95 s wall (165 us per cycle)", "ok": True, "n": None})
    assert flat == {"a.b[0]": 1.0, "a.b[1]": 2.5, "t#0": 4.95, "t#1": 165.0}
    text = "| seed | ours (s) | plain (s) |\n|---|---|---|\n| 0 | 0.182 | 18.6 |\nSweep: 40 s wall, 50 ms\n"
    nums = cr.text_numbers(text)
    assert nums["0#0"] == 0.182 and nums["0#1"] == 18.6
    assert nums["Sweep:#0"] == 40.0 and nums["Sweep:#1"] == 50.0


def test_moved_only_beyond_the_spread_of_the_repeats_and_the_minimum_change():
    cr = _module()
    runs = {"b": {"before": [{"x": 10.0, "y": 10.0, "z": 1.0}, {"x": 11.0, "y": 10.2, "z": 1.0}],
                  "after": [{"x": 10.5, "y": 13.0, "z": 1.01}, {"x": 10.8, "y": 13.1, "z": 1.01}]}}
    rows = {r["key"]: r for r in cr.summarize(runs)["b"]}
    assert not rows["x"]["moved"]  # inside the before range
    assert rows["y"]["moved"] and abs(rows["y"]["ratio"] - 13.05 / 10.1) < 1e-12
    assert not rows["z"]["moved"]  # deterministic, but a 1 % change is below --min-change
    assert cr.summarize(runs, min_change=0.0)["b"][2]["moved"]


def test_bad_arguments_exit_2_with_one_line(tmp_path):
    bad = tmp_path / "saved.json"
    bad.write_text(json.dumps({"nothing": 1}))
    for args in (["--before", str(tmp_path)], ["--before", str(ROOT), "--only", "nosuch"], ["--load", str(bad)],
                 ["--before", str(ROOT), "--keys", "("]):
        out = subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=60)
        assert out.returncode == 2, (args, out.stderr)
        assert "Traceback" not in out.stderr and len(out.stderr.strip().splitlines()) == 1, out.stderr
