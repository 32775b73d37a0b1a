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
import sys
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
from otbot_hw.runtime.control_peers import Authorizer, Peer
from otbot_hw.runtime.control_socket import ControlServer
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


# -- the daemon on the simulated robot: judged from the simulated drives' own state -------------------
@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    from test_daemon import RELAXED, SimDaemon

    # many estops in a row on a shared machine: 20 periods for the drives to confirm a quick stop
    # before the master escalates to NMT STOP (the escalation is not under test here)
    d = SimDaemon(tmp_path_factory.mktemp("fz"), replace={
        **RELAXED, "reaction_timeout: {value: 2, unit: periods}": "reaction_timeout: {value: 20, unit: periods}"})
    os.chmod(d.folder, 0o755)
    os.chmod(d.sock, 0o666)  # the status-only peer (uid nobody) may connect; it is in no allowed group
    yield d
    if d.thread.is_alive():
        d.daemon.request_stop("end of tests")
        d.thread.join(30)


def _enabled_and_held(sim) -> None:
    sim.to_hold_at_rest()
    assert _wait(lambda: sim.drive_states() == [ENABLED] * 3, 2)


#: what a status-only peer may do on one connection
_ACTION = st.one_of(
    st.tuples(st.just("line"), st.sampled_from(PAYLOADS)),
    st.tuples(st.just("line"), st.binary(max_size=300)),
    st.tuples(st.just("line"), st.sampled_from([b'{"id": 1, "cmd": "estop"}', b'{"id": 1, "cmd": "shutdown"}',
                                                b'{"id": 1, "cmd": "status"}', b'{"id": 1, "cmd": "enable"}'])),
    st.tuples(st.just("partial"), st.binary(min_size=1, max_size=100)),   # a line never finished, kept open
    st.tuples(st.just("silent"), st.integers(1, 40)),                    # connections that send nothing, kept
    st.tuples(st.just("half_close"), st.sampled_from(PAYLOADS[:6] + [b'{"id": 2, "cmd": "status"}'])),
    st.tuples(st.just("big"), st.just(65537)),                           # 64 KiB + 1 without a newline
    st.tuples(st.just("burst"), st.integers(1, 300)),                    # connect and close in a loop
    st.tuples(st.just("flood"), st.integers(1, 40)),                     # status requests never read
)


def _hostile(actions):
    def script(path):
        keep, seen = [], []

        def conn():
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            s.settimeout(2)
            s.connect(str(path))
            return s
        for kind, arg in actions:
            try:
                if kind == "line":
                    s = conn()
                    s.sendall(arg.replace(b"\n", b" ") + b"\n")
                    keep.append(s)
                elif kind == "partial":
                    s = conn()
                    s.sendall(arg.replace(b"\n", b" "))
                    keep.append(s)
                elif kind == "silent":
                    keep += [conn() for _ in range(arg)]
                elif kind == "half_close":
                    s = conn()
                    s.sendall(arg + b"\n")
                    s.shutdown(socket.SHUT_WR)
                    seen.append(len(s.recv(65536)) > 0)
                    s.close()
                elif kind == "big":
                    s = conn()
                    with contextlib.suppress(OSError):
                        s.sendall(b"x" * arg)
                    keep.append(s)
                elif kind == "burst":
                    for _ in range(arg):
                        conn().close()
                elif kind == "flood":
                    s = conn()
                    with contextlib.suppress(OSError):
                        s.sendall(b'{"id": 1, "cmd": "status"}\n' * arg)
                    keep.append(s)
            except OSError as exc:  # refused (busy) or closed by the server: that is its right
                seen.append(type(exc).__name__)
        return seen, keep
    return script


@pytest.mark.skipif(not ROOT, reason="needs root to run the status-only peer as another user")
@settings(max_examples=8, deadline=None, suppress_health_check=list(HealthCheck))
@given(actions=st.lists(_ACTION, min_size=1, max_size=6))
def test_fuzzed_status_only_peer_then_an_allowed_estop_stops_the_drives_within_100_ms(sim, actions):
    _enabled_and_held(sim)
    d = sim.daemon
    cycles0 = d.runner.cycles
    _, (dt, reply) = as_peer(sim.sock, NOBODY, NOGROUP, [], _hostile(actions), hold=lambda: estop_time(sim.sock))
    assert reply["latched"] is True
    assert dt <= 0.1, f"estop answered after {dt * 1e3:.1f} ms"
    assert _wait(lambda: ENABLED not in sim.drive_states(), 1), sim.drive_states()
    assert d.server.alive and d.server.counters["internal_errors"] == 0
    assert d.runner.fault is not None and d.runner.fault.kind == "estop"
    assert _wait(lambda: d.runner.cycles > cycles0 + 5, 2)                 # the loop runs on
    assert sim.ctl("reset")["mode"] == "idle"


def test_ten_thousand_connections_leave_the_daemons_loop_and_estop_unaffected(sim):
    _enabled_and_held(sim)
    d = sim.daemon
    cycles0 = d.runner.cycles
    # the flood comes from another process, as a hostile client would (in this process, its thread would
    # also compete with the daemon's threads for the interpreter lock: not what happens on the robot)
    flood = ("import contextlib, socket, sys\n"
             "for i in range(10_000):\n"
             "    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)\n"
             "    s.connect(sys.argv[1])\n"
             "    if i % 2:\n"
             "        with contextlib.suppress(OSError):  # refused as busy: the server's right\n"
             "            s.sendall(b'{\"id\": 1, \"cmd\": \"status\"}\\n')\n"
             "    s.close()\n")
    subprocess.run([sys.executable, "-c", flood, str(sim.sock)], check=True, timeout=120)
    assert d.runner.fault is None and sim.drive_states() == [ENABLED] * 3 and d.runner.cycles > cycles0
    dt, reply = estop_time(sim.sock)
    print(f"estop after 10^4 connections: answered in {dt * 1e3:.1f} ms")
    assert reply["latched"] is True and dt <= 0.1, dt
    assert _wait(lambda: ENABLED not in sim.drive_states(), 1)
    assert d.server.alive and d.server.counters["internal_errors"] == 0
    assert sim.ctl("reset")["mode"] == "idle"


def _fill(folder: Path) -> Path:
    """Fill the file system of ``folder`` to the last byte."""
    filler = folder / "filler"
    with open(filler, "wb", buffering=0) as f:
        with contextlib.suppress(OSError):
            while True:
                f.write(b"\0" * 65536)
        with contextlib.suppress(OSError):
            while True:
                f.write(b"\0" * 512)
    return filler


@contextlib.contextmanager
def _full_disk_or_enospc(sim, monkeypatch):
    """A tmpfs of 4 MiB as the daemon's recording folder, filled (root); where none can be mounted,
    the session's writer raises ENOSPC. Yields a function that frees the space."""
    from otbot_hw.recording import RecordingWriter

    rec = sim.daemon.settings.record_dir
    mnt = rec.parent / "full"
    mnt.mkdir()
    mounted = ROOT and subprocess.run(["mount", "-t", "tmpfs", "-o", "size=4m", "tmpfs", str(mnt)],
                                      capture_output=True).returncode == 0
    try:
        if mounted:
            sim.ctl("record", action="stop")
            monkeypatch.setattr(sim.daemon.settings, "record_dir", mnt)
            sim.ctl("record", action="start")
            filler = _fill(mnt)
            yield lambda: filler.unlink()
        else:
            full = {"on": True}
            real = RecordingWriter.flush

            def flush(self):
                if full["on"]:
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
                real(self)
            monkeypatch.setattr(RecordingWriter, "flush", flush)
            yield lambda: full.update(on=False)
    finally:
        if mounted:
            with contextlib.suppress(ControlError):
                sim.ctl("record", action="stop")
            subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


def test_a_full_recording_disk_is_a_latched_fault_the_loop_and_socket_stay_up(sim, monkeypatch):
    _enabled_and_held(sim)
    d = sim.daemon
    with _full_disk_or_enospc(sim, monkeypatch) as free:
        path = d.runner.recording.path
        assert _wait(lambda: d.runner.fault is not None, 5), "no fault after the disk filled"
        f = d.runner.fault
        assert f.kind == "recording" and str(path) in f.text and "No space left on device" in f.text, f
        assert _wait(lambda: ENABLED not in sim.drive_states(), 1)            # quick-stopped
        st1 = sim.ctl("status")
        assert st1["faults"][0]["kind"] == "recording" and st1["recording"]["error"]
        assert _wait(lambda: sim.ctl("status")["loop"]["cycles"] > st1["loop"]["cycles"] + 20, 3)  # loop runs
        with pytest.raises(ControlError, match="No space left"):
            sim.ctl("record", action="start")                                 # still full: refused, said why
        free()
        assert sim.ctl("reset")["mode"] == "idle"
        rec = sim.ctl("record", action="start")["recording"]
        assert rec["error"] is None and rec["path"] != str(path)
        assert _wait(lambda: sim.ctl("status")["recording"]["samples"] > 10, 3)
    assert d.server.alive and sim.thread.is_alive()


def test_a_dead_socket_server_quick_stops_latches_and_stops_the_watchdog_ping(sim, monkeypatch):
    """Last in this module: it kills the shared daemon's socket server."""
    _enabled_and_held(sim)
    d = sim.daemon
    pings = []
    d.watchdog.interval = 0.05
    monkeypatch.setattr(d.watchdog.notifier, "watchdog", lambda: pings.append(time.monotonic()) or True)
    monkeypatch.setattr(type(d.watchdog), "enabled", property(lambda self: True))
    assert _wait(lambda: len(pings) >= 2, 2)
    monkeypatch.setattr(d.server, "_expire", lambda now: 1 / 0)             # a bug in the I/O thread
    assert _wait(lambda: d.runner.fault is not None, 3)
    assert d.runner.fault.kind == "control_socket"
    assert _wait(lambda: ENABLED not in sim.drive_states(), 1)
    assert d.watchdog.stopped is not None
    n = len(pings)
    time.sleep(0.3)
    assert len(pings) == n and sim.thread.is_alive()                        # no ping, the loop runs on
    d.request_stop("end of test")
    sim.thread.join(30)
    assert not sim.thread.is_alive() and sim.summary["stopped"] == "end of test"


SESSION_UNTIL_FULL = """
import errno, json, resource, signal, sys
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)        # `ulimit -f`: EFBIG instead of the signal
if sys.argv[2] != "-":
    resource.setrlimit(resource.RLIMIT_FSIZE, (int(sys.argv[2]), int(sys.argv[2])))
from otbot_hw.recording import TOPIC_COMMAND, TOPIC_JOINTS
from otbot_hw.runtime.session_recording import SessionRecording
errors = []
rec = SessionRecording(sys.argv[1], {}, [TOPIC_JOINTS], rate=100.0, session_id="full", on_error=errors.append)
for k in range(200_000):
    t = k * 0.01
    rec.write_sample({TOPIC_COMMAND: {"t": t, "torque": [0.0] * 3},
                      TOPIC_JOINTS: {"t": t, "position": [0.0] * 3, "velocity": [0.0] * 3}})
    rec.write_event(t, "mode", "hold") if k % 100 == 0 else None
    if errors:
        break
rec.flush(); rec.close(); rec.close()                 # after the failure: no exception, nothing written
print(json.dumps({"errors": errors, "status": rec.status()}))
"""


@pytest.mark.parametrize("limit", ["tmpfs", "ulimit"])
def test_a_session_that_hits_a_full_disk_or_the_file_size_limit_fails_once_and_never_raises(tmp_path, limit):
    folder = tmp_path / "rec"
    folder.mkdir()
    mounted = False
    if limit == "tmpfs":
        if not ROOT or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(folder)],
                                      capture_output=True).returncode != 0:
            pytest.skip("cannot mount a tmpfs here")
        mounted = True
    try:
        out = subprocess.run([sys.executable, "-c", SESSION_UNTIL_FULL, str(folder),
                              "65536" if limit == "ulimit" else "-"],
                             capture_output=True, text=True, timeout=120, cwd=Path(__file__).parents[1])
    finally:
        if mounted:
            subprocess.run(["umount", "-l", str(folder)], capture_output=True)
    assert out.returncode == 0 and "Traceback" not in out.stderr, out.stderr[-2000:]
    res = json.loads(out.stdout.splitlines()[-1])
    (err,) = res["errors"]                                                     # said once
    name = "ENOSPC" if limit == "tmpfs" else "EFBIG"
    assert f"{folder}/full-000.mcap" in err and name in err, err
    assert res["status"]["error"] == err and res["status"]["closed"]
