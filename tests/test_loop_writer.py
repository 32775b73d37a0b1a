"""``otbot_hw.runtime.loop.BackgroundWriter``: the loop's recording written by a thread of its own
keeps every sample and event in order, flushes and closes when asked, and hands the writer's
exceptions back to the loop."""
from __future__ import annotations

import threading

import pytest

from otbot_hw.runtime.loop import BackgroundWriter


class _Writer:
    """Keeps each call with the thread that made it."""

    path = "x-000.mcap"

    def __init__(self, fail_at: int | None = None):
        self.calls = []
        self.fail_at = fail_at

    def _log(self, *call):
        self.calls.append((threading.current_thread().name, *call))

    def write_sample(self, m):
        if self.fail_at is not None and m["t"] == self.fail_at:
            raise ValueError(f"sample at {m['t']} refused")
        self._log("sample", m["t"])

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
