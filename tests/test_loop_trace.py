"""The loop's stall trace (``otbot_hw.runtime.loop_trace``) and the timing histogram's percentiles."""
from __future__ import annotations

import json
import types

import numpy as np
import pytest

from otbot_hw.runtime import loop_trace
from otbot_hw.runtime.loop_timing import TimingHistogram


def test_histogram_percentiles_match_numpy_within_a_bin():
    rng = np.random.default_rng(3)
    v = np.concatenate([rng.uniform(0.0015, 0.0025, 5000), rng.uniform(0.003, 0.02, 50), [1.7]])  # one beyond span
    h = TimingHistogram()
    for x in v:
        h.add(float(x))
    p50, p99, p100 = h.percentiles((50, 99, 100))
    for got, q in ((p50, 50), (p99, 99)):
        want = np.percentile(v, q, method="inverted_cdf")
        assert want <= got <= want + h.resolution + 1e-12
    assert p100 == pytest.approx(1.7)  # the last bin keeps its maximum
    assert h.count == len(v) and sum(h.bins) == len(v)
    assert TimingHistogram().percentiles((50,))[0] != TimingHistogram().percentiles((50,))[0]  # NaN while empty


class _Runner:
    def __init__(self):
        self.feedback = types.SimpleNamespace(step=lambda *a: "est")
        self.supervisor = types.SimpleNamespace(check=lambda *a: None)
        self.clock = types.SimpleNamespace(wait=lambda *a: 0.0)
        self.periods = []

    def _timing(self, p):
        self.periods.append(p)

    def _record(self, *a):
        return None


def test_trace_off_without_the_variable(monkeypatch):
    monkeypatch.delenv(loop_trace.ENV, raising=False)
    assert loop_trace.from_env(0.002, 1.5) is None


def test_trace_keeps_each_overrun_with_its_parts(tmp_path, monkeypatch):
    out = tmp_path / "trace.json"
    monkeypatch.setenv(loop_trace.ENV, str(out))
    tr = loop_trace.from_env(0.002, 1.5)
    runner = _Runner()
    robot = types.SimpleNamespace(read=lambda: "snap", write=lambda u: u)
    daemon = types.SimpleNamespace(mailbox=types.SimpleNamespace(service=lambda: None), telemetry=None)
    tr.install(daemon, robot, runner)
    assert robot.read() == "snap" and robot.write(3) == 3  # wrapped, same results
    for p in (0.002, 0.002, 0.0031, 0.002, 0.0029):  # 1.5 periods = 3 ms: one overrun
        robot.read()
        runner._timing(p)
        runner.feedback.step()
    assert runner.periods == [0.002, 0.002, 0.0031, 0.002, 0.0029]  # the loop's own accounting still sees all
    tr.close()
    d = json.loads(out.read_text())
    assert d["cycles"] == 5 and len(d["stalls"]) == 1
    st = d["stalls"][0]
    assert st["period"] == pytest.approx(0.0031)
    names = {e[0] for e in st["events"]}
    assert {"read", "EKF step"} <= names
    assert any(t["policy"] in ("OTHER", "FIFO", "RR") for t in d["threads_end"])
