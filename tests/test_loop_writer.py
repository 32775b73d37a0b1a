"""``otbot_hw.runtime.loop_recording.BackgroundWriter``: the loop's recording written by a thread of its own
keeps every sample and event in order, flushes and closes when asked, and hands the writer's
exceptions back to the loop."""
from __future__ import annotations

import threading

import pytest

from otbot_hw.runtime.loop_recording import BackgroundWriter


class _Writer:
    """Keeps each call with the thread that made it."""

    path = "x-000.mcap"

    def __init__(self, fail_at: int | None = None):
        self.calls = []
        self.fail_at = fail_at

    def _log(self, *call):
        self.calls.append((threading.current_thread().name, *call))

    def write_sample(self, m):
        t = m["t"] if "t" in m else m["/otbot/command"]["t"]
        if self.fail_at is not None and t == self.fail_at:
            raise ValueError(f"sample at {t} refused")
        self._log("sample", t)

    def write_event(self, t, kind, text, **extra):
        self._log("event", t, kind)

    def flush(self):
        self._log("flush")

    def close(self):
        self._log("close")


def test_order_flush_close_in_the_writer_thread():
    w = _Writer()
    bw = BackgroundWriter(w)
    expected = []
    for k in range(500):
        bw.write_sample({"t": k})
        expected.append(("sample", k))
        if k % 97 == 0:
            bw.write_event(k, "mode", "x")
            expected.append(("event", k, "mode"))
        if k % 10 == 0:
            bw.wake()
    bw.flush()  # returns once all of the above is written and flushed
    assert [c[1:] for c in w.calls] == expected + [("flush",)]
    assert {c[0] for c in w.calls} == {"recording-writer"}
    assert bw.path == "x-000.mcap"  # the writer's own attributes
    bw.write_sample({"t": 500})
    bw.close()
    assert [c[1:] for c in w.calls[-2:]] == [("sample", 500), ("close",)]
    assert not bw._thread.is_alive()


def test_a_writer_error_reaches_the_loop():
    w = _Writer(fail_at=3)
    bw = BackgroundWriter(w)
    for k in range(6):
        bw.write_sample({"t": k})
    with pytest.raises(ValueError, match="sample at 3 refused"):
        bw.flush()
    assert [c[2] for c in w.calls if c[1] == "sample"] == [0, 1, 2, 4, 5]
    bw.close()


def test_a_full_queue_waits_for_the_writer():
    w = _Writer()
    gate = threading.Event()
    original = w.write_sample

    def slow(m):
        gate.wait(5)
        original(m)

    w.write_sample = slow
    bw = BackgroundWriter(w, max_queue=10)
    for k in range(10):
        bw.write_sample({"t": k})
    blocked = threading.Thread(target=lambda: bw.write_sample({"t": 10}))
    blocked.start()
    blocked.join(0.3)
    assert blocked.is_alive()  # the 11th sample waits: the queue holds at most max_queue
    gate.set()
    blocked.join(5)
    assert not blocked.is_alive()
    bw.close()
    assert [c[2] for c in w.calls if c[1] == "sample"] == list(range(11))


def test_a_realtime_loop_writes_each_sample_after_its_command_in_file_order():
    """``record_after_write`` (a real-time loop's default): the sample of a cycle reaches the writer
    after that cycle's ``robot.write`` — not between read and write — and before any event of the
    cycle, so the file holds what inline writing gave; nothing is left pending at close."""
    import numpy as np

    from otbot_hw.motors import load_motor_limits
    from otbot_hw.params import nominal
    from otbot_hw.runtime import LoopRunner, OpenLoopTorques, SafetyConfig, Supervisor
    from sim.direct import DirectSimRobot

    log = []
    limits = load_motor_limits()
    robot = DirectSimRobot(nominal(), period=0.01, imu_rate=None, limits=limits)
    real_write = robot.write
    robot.write = lambda u: (log.append(("write",)), real_write(u))[1]
    w = _Writer()
    w._log = lambda *call: log.append(call)
    u = np.array([[0.0, 0.0, 50.0]])  # beyond the pivot's limit: saturation events mid-cycle
    sup = Supervisor(limits, SafetyConfig(), 0.01, realtime=False)
    runner = LoopRunner(robot, OpenLoopTorques(u, 0.01), sup, realtime=False, keep_samples=False,
                        recorder=lambda meta, topics: w, record_after_write=True)
    runner.run(6)
    kinds = [c[0] for c in log]
    samples = [i for i, k in enumerate(kinds) if k == "sample"]
    writes = [i for i, k in enumerate(kinds) if k == "write"]
    assert len(samples) == 6 and kinds[-1] == "close"
    for k, i in enumerate(samples[:-1]):  # cycle k's sample after cycle k's command (write k + 1)
        assert writes[k] < writes[k + 1] < i
    ts = [c[1] for c in log if c[0] in ("sample", "event")]
    assert ts == sorted(ts)  # events after the sample of their time, as inline
    assert "event" in kinds and runner._pending_sample is None


def test_the_overrun_event_goes_out_after_the_cycles_command_and_sample():
    """The overrun event said at the start of a streak (between the read and the write) reaches the
    writer after that cycle's command and sample — never between a read and its write — in time
    order with the samples and the other events, and nothing is left behind."""
    import time

    import numpy as np

    from otbot_hw.motors import load_motor_limits
    from otbot_hw.params import nominal
    from otbot_hw.runtime import LoopRunner, OpenLoopTorques, SafetyConfig, Supervisor
    from sim.direct import DirectSimRobot

    log = []
    limits = load_motor_limits()
    robot = DirectSimRobot(nominal(), period=0.01, imu_rate=None, limits=limits)
    real_read, real_write = robot.read, robot.write
    n_reads = [0]

    def read():
        n_reads[0] += 1
        if n_reads[0] in (5, 9):  # two overrun streaks of one cycle each
            time.sleep(0.03)
        log.append(("read",))
        return real_read()

    robot.read = read
    robot.write = lambda u: (log.append(("write",)), real_write(u))[1]
    w = _Writer()
    w._log = lambda *call: log.append(call)
    sup = Supervisor(limits, SafetyConfig(overrun_factor=1.5, max_consecutive_overruns=5), 0.01, realtime=True)
    runner = LoopRunner(robot, OpenLoopTorques(np.zeros((1, 3)), 0.01), sup, realtime=True, keep_samples=False,
                        recorder=lambda meta, topics: w, record_after_write=True)
    res = runner.run(12)
    assert res.completed and res.stats.overruns >= 2
    kinds = [c[0] for c in log]
    overruns = [c for c in log if c[0] == "event" and c[2] == "overrun"]
    assert len(overruns) == sum(1 for e in runner.events if e["kind"] == "overrun") >= 2
    for ev in overruns:  # after its cycle's command and sample, not between the read and the write
        k = log.index(ev)
        i = max(j for j in range(k) if kinds[j] == "read")
        assert kinds[i:k] == ["read", "write", "sample"] and log[k - 1] == ("sample", ev[1])
    ts = [c[1] for c in log if c[0] in ("sample", "event")]
    assert ts == sorted(ts) and runner._deferred_events == [] and kinds[-1] == "close"
