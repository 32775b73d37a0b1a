"""Issue 18 items 5, 6, 7(b), 7(c), 8 (supplementary group) and its Bad input list: a control socket
no client can take down, and recording failures that are faults, not crashes.

* Against the server with a recording fake handler: the issue's payloads (5000-digit id and
  velocity, a 454-byte vx, a 300-character track path), a 64 KiB + 1 line, a connection that sends
  nothing, a half-closed client (``socat``), 10^4 connections in a loop, a status-only peer holding
  every slot -> error replies or refusals, the server alive, an allowed peer's estop answered.
  Authorization before the arguments are looked at; a peer allowed only through a supplementary
  group. A server thread that dies calls its failure hook.
* Against the in-process daemon on the simulated robot (``--bus sim``), judged from the simulated
  drives' own state: a hypothesis fuzzer drives a status-only peer (another uid, forked) through
  any sequence of lines and connection behaviours, after which an allowed peer's estop is answered
  within 100 ms and takes every drive out of OPERATION ENABLED; a full recording disk (a small
  tmpfs, or a writer raising ENOSPC where none can be mounted) latches a fault naming the file and
  the error, quick-stops, keeps the loop and the socket up, and shutdown does not raise; a dead
  socket server quick-stops, latches and stops the systemd watchdog ping.
"""
from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import socket
import subprocess
import tempfile
import threading
import time
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from daemon_fakes import FakeHandler
from otbot_hw.runtime.control_client import ControlClient, ControlError
from otbot_hw.runtime.control_protocol import ArgumentLimits
from otbot_hw.runtime.control_socket import Authorizer, ControlServer, Peer
from otbot_hw.runtime.daemon_config import ControlSocketConfig

ROOT = os.geteuid() == 0
NOBODY, NOGROUP = 65534, 65534
ENABLED = "OPERATION ENABLED"
LIMITS = ArgumentLimits(max_linear=0.5, max_angular=1.0, scenarios=("corridor",))

#: the payloads of issue 18 item 6, each of which killed the server's I/O thread on 7a43e38
PAYLOADS = [
    b'{"id": ' + b"9" * 5000 + b', "cmd": "status"}',
    b'{"id": 1, "cmd": "velocity", "args": {"vx": ' + b"7" * 5000 + b', "vy": 0, "wz": 0}}',
    b'{"id": 2, "cmd": "velocity", "args": {"vx": 1' + b"0" * 399 + b', "vy": 0, "wz": 0}}',
    b'{"id": 3, "cmd": "velocity", "args": {"vx": 1' + b"0" * 399 + b'.0, "vy": 0, "wz": 0}}',
    b'{"id": 4, "cmd": "velocity", "args": {"vx": 1e399, "vy": -1e400, "wz": 0}}',
    b'{"id": 5, "cmd": "track", "args": {"target": "/' + b"a" * 320 + b'.csv"}}',
    b'{"id": 6, "cmd": "track", "args": {"target": "' + b"/x" * 2100 + b'.csv"}}',
    b'{"id": 7, "cmd": "excite", "args": {"path": "/tmp/\\udcff.csv"}}',
    b'{"id": 8, "cmd": "velocity", "args": {"vx": NaN, "vy": Infinity, "wz": -Infinity}}',
    b'{"id": 9, "cmd": "status", "' + b"k" * 3000 + b'": 1}',
    b'[' * 20000 + b']' * 20000,
]


@pytest.fixture
def sockdir():
    d = Path(tempfile.mkdtemp(prefix="otf"))  # short: AF_UNIX paths are limited to 107 bytes
    os.chmod(d, 0o755)
    yield d
    shutil.rmtree(d, ignore_errors=True)


def serve(sockdir, **cfg):
    cfg = {"allowed_users": (os.getuid(),), "allowed_groups": (), **cfg}
    h = FakeHandler()
    return ControlServer(h, ControlSocketConfig(**cfg), LIMITS, path=sockdir / "control.sock").start(), h


def exchange(path: Path, data: bytes, half_close: bool = False, timeout: float = 5.0) -> list[dict]:
    """Send ``data``, optionally shut the write side (as socat does), read reply lines until EOF."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(timeout)
    s.connect(str(path))
    try:
        s.sendall(data)
        if half_close:
            s.shutdown(socket.SHUT_WR)
        f = s.makefile("rb")
        out = []
        while True:
            try:
                line = f.readline()
            except (socket.timeout, ConnectionResetError):
                break
            if not line:
                break
            out.append(json.loads(line))
            if not half_close:
                break
        return out
    finally:
        s.close()


def estop_time(path: Path) -> tuple[float, dict]:
    t0 = time.perf_counter()
    with ControlClient(path, timeout=5.0) as c:
        r = c.request("estop")
    return time.perf_counter() - t0, r


# -- the server against one client at a time ---------------------------------------------------------
def test_the_issues_payloads_get_error_replies_and_the_server_lives_on(sockdir):
    server, h = serve(sockdir)
    try:
        for p in PAYLOADS:
            (reply,) = exchange(server.path, p + b"\n")
            assert reply["ok"] is False and reply["error"]["code"] in ("bad_request", "not_json"), (p[:60], reply)
        assert server.alive and server.counters["internal_errors"] == 0
        assert h.commands() == []                                   # none reached the handler
        assert estop_time(server.path)[1] == {"accepted": "estop"}  # and estop still does
    finally:
        server.close()


def test_a_half_closed_client_gets_its_replies(sockdir):
    server, h = serve(sockdir)
    try:
        two = b'{"id": 1, "cmd": "status"}\n{"id": 2, "cmd": "enable"}\n'
        assert [r["id"] for r in exchange(server.path, two, half_close=True)] == [1, 2]
        # the last line without its newline is a request too
        (r,) = exchange(server.path, b'{"id": "x", "cmd": "status"}', half_close=True)
        assert r["id"] == "x" and r["ok"]
        (r,) = exchange(server.path, PAYLOADS[0], half_close=True)
        assert r["error"]["code"] == "bad_request"
        assert h.commands() == ["status", "enable", "status"]
    finally:
        server.close()


def test_a_line_over_64_KiB_and_a_silent_connection_are_refused_and_closed(sockdir):
    server, h = serve(sockdir, idle_timeout=0.5)
    try:
        (r,) = exchange(server.path, b"{" + b" " * 65536 + b"\n")      # 64 KiB + 1 before the newline
        assert r["error"]["code"] == "too_large"
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.settimeout(5)
        s.connect(str(server.path))
        t0 = time.monotonic()
        (r,) = [json.loads(s.makefile("rb").readline())]               # sends nothing: told, then closed
        assert r["error"]["code"] == "timeout" and "idle" in r["error"]["message"]
        assert 0.4 < time.monotonic() - t0 < 4.0
        assert s.recv(10) == b""
        s.close()
        assert server.counters["idle_closed"] == 1 and h.commands() == []
    finally:
        server.close()


def test_ten_thousand_connections_in_a_loop_leave_estop_answered(sockdir):
    server, h = serve(sockdir)
    try:
        for i in range(10_000):
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            s.connect(str(server.path))
            if i % 3 == 0:
                s.sendall(b'{"id": 1, "cmd": "sta')
            s.close()
        dt, r = estop_time(server.path)
        assert r == {"accepted": "estop"} and server.alive
        assert server.counters["connections"] >= 10_000
    finally:
        server.close()


def test_authorization_comes_before_the_arguments_are_looked_at(sockdir, tmp_path):
    server, h = serve(sockdir, allowed_users=(), allowed_groups=())         # this process: status only
    try:
        for p in (PAYLOADS[4], PAYLOADS[5], PAYLOADS[6], PAYLOADS[8]):   # decodable: refused unread
            (r,) = exchange(server.path, p + b"\n")
            assert r["error"]["code"] == "forbidden", (p[:60], r)
        for p in PAYLOADS[1:3]:                                   # numbers too long to decode at all
            (r,) = exchange(server.path, p + b"\n")
            assert r["error"]["code"] == "bad_request" and "digits" in r["error"]["message"]
        big = b'{"id": 1, "cmd": "track", "args": {"target": "' + str(tmp_path).encode() + b'/nope.csv"}}\n'
        (r,) = exchange(server.path, big)
        assert r["error"]["code"] == "forbidden" and "--allow-user" in r["error"]["message"]
        (r,) = exchange(server.path, b'{"id": 1, "cmd": "velocity", "args": {"vx": 1e399, "vy": 0, "wz": 0}}\n')
        assert r["error"]["code"] == "forbidden"                   # not "must be finite": never validated
    finally:
        server.close()


def test_a_server_thread_that_dies_calls_the_failure_hook(sockdir, monkeypatch):
    server, h = serve(sockdir)
    died = []
    server.on_failure = died.append
    monkeypatch.setattr(server, "_expire", lambda now: 1 / 0)       # a bug outside any connection's boundary
    assert _wait(lambda: died, 3)
    assert "I/O" in died[0] and not server.alive
    server.close()


def _wait(pred, timeout, step=0.01):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(step)
    return bool(pred())


# -- peers of other users (root only: forked children that change their credentials) -------------------
def as_peer(path: Path, uid: int, gid: int, groups: list[int], script, hold=None):
    """Run ``script(path) -> list`` in a forked child with the given credentials; returns its JSON
    result. With ``hold`` (a callable), the child keeps its sockets open while the parent runs
    ``hold()`` and returns (its result, hold's)."""
    r, w = os.pipe()
    go_r, go_w = os.pipe()
    pid = os.fork()
    if pid == 0:  # child: stdlib only, then _exit
        code = 0
        try:
            os.close(r)
            os.close(go_w)
            os.setgroups(groups)
            os.setgid(gid)
            os.setuid(uid)
            out, keep = script(path)
            os.write(w, (json.dumps(out) + "\n").encode())
            os.read(go_r, 1)  # until the parent has done its part
            for s in keep:
                s.close()
        except BaseException as exc:  # noqa: BLE001
            with contextlib.suppress(Exception):
                os.write(w, (json.dumps({"child_error": repr(exc)}) + "\n").encode())
            code = 1
        finally:
            os._exit(code)
    os.close(w)
    os.close(go_r)
    f = os.fdopen(r, "rb")
    try:
        line = f.readline()
        held = hold() if hold is not None else None
    finally:
        os.write(go_w, b"g")
        os.close(go_w)
        _, status = os.waitpid(pid, 0)
        f.close()
    out = json.loads(line) if line else {"child_error": "no output"}
    assert isinstance(out, list), out
    return (out, held) if hold is not None else out


def _codes(path):
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(5)
    s.connect(str(path))
    f = s.makefile("rb")
    out = []
    for i, cmd in enumerate(("status", "enable")):
        s.sendall(json.dumps({"id": i, "cmd": cmd}).encode() + b"\n")
        rep = json.loads(f.readline())
        out.append("ok" if rep["ok"] else rep["error"]["code"])
    return out, [s]


@pytest.mark.skipif(not ROOT, reason="needs root to run a client as another user")
def test_a_peer_allowed_only_through_a_supplementary_group_may_command(sockdir):
    gid_allowed = 4242                                   # neither the peer's uid nor its primary group
    server, h = serve(sockdir, allowed_users=(), allowed_groups=(gid_allowed,))
    os.chmod(server.path, 0o666)
    try:
        assert as_peer(server.path, NOBODY, NOGROUP, [gid_allowed], _codes) == ["ok", "ok"]
        assert as_peer(server.path, NOBODY, NOGROUP, [], _codes) == ["ok", "forbidden"]
        assert as_peer(server.path, NOBODY, NOGROUP, [4243, 4244], _codes) == ["ok", "forbidden"]
    finally:
        server.close()
    peers = [c[2] for c in h.calls if c[0] == "enable"]
    assert len(peers) == 1 and peers[0].gid == NOGROUP and gid_allowed in peers[0].groups
    # the rule itself, on credentials as the kernel gives them
    a = Authorizer((), (gid_allowed,))
    assert a.allows(Peer(1, NOBODY, NOGROUP, (7, gid_allowed))) and not a.allows(Peer(1, NOBODY, NOGROUP, (7,)))


def _hog(n_idle: int):
    def script(path):
        keep, codes = [], []
        for _ in range(n_idle):
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            s.settimeout(2)
            s.connect(str(path))
            keep.append(s)
        time.sleep(0.2)
        for s in keep:  # which of them the server refused at once
            s.setblocking(False)
            try:
                data = s.recv(4096)
                codes.append(json.loads(data.splitlines()[0])["error"]["code"] if data else "closed")
            except BlockingIOError:
                codes.append("open")
        return codes, keep
    return script


@pytest.mark.skipif(not ROOT, reason="needs root to run a client as another user")
def test_a_status_only_peer_holding_every_slot_cannot_block_an_allowed_estop(sockdir):
    server, h = serve(sockdir, allowed_users=(0,), max_clients=8, reserved_clients=2)
    os.chmod(server.path, 0o666)
    try:
        codes, (dt, r) = as_peer(server.path, NOBODY, NOGROUP, [], _hog(12), hold=lambda: estop_time(server.path))
        assert codes.count("open") == 6 and codes.count("busy") == 6     # 8 - 2 reserved for allowed users
        assert r == {"accepted": "estop"}
        # the reserve full of allowed peers too: the next allowed peer evicts the oldest status-only one
        mine = [socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) for _ in range(2)]

        def fill_then_estop():
            for s in mine:
                s.connect(str(server.path))
            return estop_time(server.path)
        codes, (dt, r) = as_peer(server.path, NOBODY, NOGROUP, [], _hog(6), hold=fill_then_estop)
        assert codes == ["open"] * 6 and r == {"accepted": "estop"} and server.counters["evicted"] == 1
        for s in mine:
            s.close()
    finally:
        server.close()
