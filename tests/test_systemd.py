"""sd_notify datagrams received on real sockets bound by the test (path and abstract), and the
loop-driven watchdog: pings at half of WATCHDOG_USEC while cycles meet their deadlines, none while
they miss or while the loop is stuck."""
from __future__ import annotations

import os
import shutil
import socket
import tempfile
import threading
import time
from pathlib import Path

import pytest

from otbot_hw.runtime.systemd import Notifier, Watchdog, notify_address, watchdog_interval


@pytest.fixture(params=["path", "abstract"])
def listener(request):
    """(NOTIFY_SOCKET value, bound datagram socket) like systemd's."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.settimeout(2)
    d = Path(tempfile.mkdtemp(prefix="otbn"))
    if request.param == "path":
        value = str(d / "notify")
        s.bind(value)
    else:
        value = f"@otbot-test-{os.getpid()}-{id(s)}"
        s.bind(b"\0" + value[1:].encode())
    yield value, s
    s.close()
    shutil.rmtree(d, ignore_errors=True)


def received(s: socket.socket, wait: float = 0.05) -> list[str]:
    out = []
    s.settimeout(wait)
    try:
        while True:
            out.append(s.recv(4096).decode())
    except socket.timeout:
        pass
    s.settimeout(2)
    return out


def test_notifications_arrive_as_systemd_reads_them(listener, monkeypatch):
    value, s = listener
    monkeypatch.setenv("NOTIFY_SOCKET", value)
    n = Notifier()
    assert n.enabled
    assert n.ready(status="idle, drives booted")
    assert n.status("mode track corridor")
    assert n.watchdog()
    assert n.extend_timeout(2.5)
    assert n.stopping()
    assert received(s) == ["READY=1\nSTATUS=idle, drives booted", "STATUS=mode track corridor", "WATCHDOG=1",
                           "EXTEND_TIMEOUT_USEC=2500000", "STOPPING=1"]
    with pytest.raises(ValueError, match="one line"):
        n.status("two\nlines")
    n.close()


def test_without_systemd_nothing_is_sent_and_nothing_fails(tmp_path):
    n = Notifier(environ={})
    assert not n.enabled and not n.ready() and not n.watchdog()
    assert Notifier(environ={"NOTIFY_SOCKET": "vsock:2:1234"}).enabled is False
    # systemd's socket gone: counted, never raised into the loop
    gone = Notifier(environ={"NOTIFY_SOCKET": str(tmp_path / "nobody")})
    assert gone.enabled and gone.ready() is False and gone.errors == 1


def test_addresses_and_watchdog_interval():
    assert notify_address("@sd/notify") == b"\0sd/notify"
    assert notify_address("/run/systemd/notify") == "/run/systemd/notify"
    assert notify_address(None) is None and notify_address("") is None
    assert watchdog_interval({"WATCHDOG_USEC": "3000000"}) == 1.5
    assert watchdog_interval({"WATCHDOG_USEC": "3000000", "WATCHDOG_PID": str(os.getpid())}) == 1.5
    assert watchdog_interval({"WATCHDOG_USEC": "3000000", "WATCHDOG_PID": str(os.getpid() + 1)}) is None
    assert watchdog_interval({}) is None and watchdog_interval({"WATCHDOG_USEC": "x"}) is None
    assert watchdog_interval({"WATCHDOG_USEC": "0"}) is None


def test_watchdog_pings_only_while_the_loop_meets_its_deadlines(listener):
    value, s = listener
    env = {"NOTIFY_SOCKET": value, "WATCHDOG_USEC": "200000"}  # WatchdogSec=0.2 s -> ping every 0.1 s
    wd = Watchdog(Notifier(environ=env), environ=env)
    assert wd.enabled and wd.interval == 0.1
    period = 0.004
    pings, got = [], []
    for k in range(400):
        t = k * period
        if 250 <= k < 375:                     # 1 s of good cycles, 0.5 s of missed deadlines, recovered
            wd.cycle_missed(t)
        elif wd.cycle_ok(t):
            pings.append(t)
            got += received(s, 0.001)          # systemd reads as they come (its queue holds 10)
    gaps = [b - a for a, b in zip(pings, pings[1:])]
    assert 10 <= sum(p < 1.0 for p in pings) <= 11
    assert all(g <= 0.1 + period + 1e-9 for g in gaps[:9])  # while healthy: never longer than the interval
    assert not any(1.0 <= p < 1.5 for p in pings)             # while missing: silence, systemd will act
    assert pings[-1] == pytest.approx(1.5)                     # first good cycle after: ping at once
    assert (wd.ok, wd.missed, wd.pings) == (275, 125, len(pings))
    assert got == ["WATCHDOG=1"] * len(pings) and received(s) == []


def test_watchdog_in_real_time_goes_silent_when_the_loop_stalls(listener):
    value, s = listener
    env = {"NOTIFY_SOCKET": value, "WATCHDOG_USEC": "100000"}  # ping every 50 ms
    wd = Watchdog(Notifier(environ=env), environ=env)
    stamps = []
    wanted = 4

    def loop():
        """Cycles every 4 ms on the wall clock until ``wanted`` pings went out (a loaded machine
        only makes the cycles fewer, never the pings faster); 10 s at most."""
        end = time.monotonic() + 10
        while len(stamps) < wanted and time.monotonic() < end:
            now = time.monotonic()
            if wd.cycle_ok(now):
                stamps.append(now)  # the time the watchdog judged, not when this thread ran again
            time.sleep(0.004)

    th = threading.Thread(target=loop)
    th.start()
    th.join()
    assert len(stamps) == wanted, f"{len(stamps)} pings in 10 s of good cycles"
    assert all(b - a >= 0.05 for a, b in zip(stamps, stamps[1:]))  # never faster than the interval
    s.setblocking(False)  # a datagram is queued when sent: what the loop sent is there now
    sent = []
    while True:
        try:
            sent.append(s.recv(4096).decode())
        except BlockingIOError:
            break
    assert sent == ["WATCHDOG=1"] * wanted
    # the loop is stuck: nobody calls cycle_ok, nothing pings on its own (systemd will act)
    assert received(s, 0.2) == []
    assert wd.pings == wanted


def test_a_full_notify_queue_is_retried_per_interval_not_per_cycle(listener):
    value, s = listener  # bound but never read: the kernel queue (10 datagrams) fills up
    env = {"NOTIFY_SOCKET": value, "WATCHDOG_USEC": "1000000"}
    n = Notifier(environ=env)
    wd = Watchdog(n, environ=env)
    for k in range(5000):  # 20 s at 250 Hz, ping due every 0.5 s
        wd.cycle_ok(k * 0.004)
    assert wd.pings + n.errors == 40 and n.errors >= 20  # 40 attempts, one per interval; most failed
