"""``benchmarks/machine_tail.py``: the fixed work's times are per period and scale with its size; the
ratio is p99 over p50 of the same numbers; bad arguments are one line and exit 2."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(BENCH))
import machine_tail  # noqa: E402


def test_one_timing_per_period_and_ordered_percentiles():
    row = machine_tail.tail(rate=400.0, seconds=0.25, iterations=500)
    assert row["samples"] == 100
    assert 0 < row["cpu_p50_us"] <= row["cpu_p99_us"] <= row["cpu_max_us"]
    assert 0 < row["wall_p50_us"] <= row["wall_p99_us"] <= row["wall_max_us"]
    assert row["cpu_p99_over_p50"] == pytest.approx(row["cpu_p99_us"] / row["cpu_p50_us"])
    assert row["cpu_p99_over_p50"] >= 1.0


def test_paced_repetitions_take_the_periods_they_are_given():
    import time

    t0 = time.monotonic()
    machine_tail.tail(rate=200.0, seconds=0.2, iterations=10)
    assert time.monotonic() - t0 >= 0.19  # 40 periods of 5 ms: slept, not run back to back
    t0 = time.monotonic()
    machine_tail.tail(rate=200.0, seconds=0.2, iterations=10, paced=False)
    assert time.monotonic() - t0 < 0.15


def test_the_work_scales_with_its_size():
    small = machine_tail.tail(rate=1000.0, seconds=0.1, iterations=500, paced=False)
    big = machine_tail.tail(rate=1000.0, seconds=0.1, iterations=4000, paced=False)
    assert big["cpu_p50_us"] > 2.5 * small["cpu_p50_us"]  # 8x the turns


def test_json_row():
    out = subprocess.run([sys.executable, str(BENCH / "machine_tail.py"), "--rate", "500", "--seconds", "0.1",
                          "--iterations", "100", "--json"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    row = json.loads(out.stdout)
    assert row["samples"] == 50 and row["paced"] is True and row["cpus"] is None


@pytest.mark.parametrize("args, names", [
    (["--rate", "0"], "--rate"),
    (["--rate", "nan"], "--rate"),
    (["--rate", "-800"], "--rate"),
    (["--seconds", "inf"], "--seconds"),
    (["--iterations", "-1"], "--iterations"),
    (["--iterations", "1.5"], "--iterations"),
    (["--fifo", "0"], "--fifo"),
    (["--fifo", "100"], "--fifo"),
    (["--cpus", "4096"], "--cpus"),
    (["--cpus", "one"], "--cpus"),
])
def test_bad_arguments_are_one_line_exit_2(args, names):
    out = subprocess.run([sys.executable, str(BENCH / "machine_tail.py"), "--seconds", "0.01", *args],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2
    last = out.stderr.strip().splitlines()[-1]
    assert names in last and "Traceback" not in out.stderr
