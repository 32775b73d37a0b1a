"""The daemon's control socket (otbot_hw.runtime.control_socket) against a recording fake handler:
good requests reach the handler with the kernel's peer credentials; malformed, oversized, unknown,
unauthorized or half-sent requests get an error reply (or none) and never reach it; many clients
at once; stale socket vs live daemon; mode 0660; estop is not queued behind a slow command."""
from __future__ import annotations

import json
import os
import pwd
import random
import shutil
import socket
import stat
import tempfile
import threading
import time
from pathlib import Path

import pytest

from daemon_fakes import FakeHandler
from otbot_hw.runtime.control_protocol import ArgumentLimits, ProtocolError, parse_request
from otbot_hw.runtime.control_client import ControlClient, ControlError, DaemonUnreachable
from otbot_hw.runtime.control_socket import ControlServer
from otbot_hw.runtime.control_socket_file import SocketInUse
from otbot_hw.runtime.loop_mailbox import LoopMailbox
from otbot_hw.runtime.daemon_config import ControlSocketConfig, daemon_config_from_dict
from otbot_hw.params import ParameterError

ME = os.getuid()
LIMITS = ArgumentLimits(max_linear=0.5, max_angular=1.0, scenarios=("corridor", "corridor-smooth"))


@pytest.fixture
def sockdir():
    d = Path(tempfile.mkdtemp(prefix="otb"))  # short: AF_UNIX paths are limited to 107 bytes
    yield d
    shutil.rmtree(d, ignore_errors=True)


def serve(sockdir, handler=None, **cfg):
    cfg = {"allowed_users": (ME,), "allowed_groups": (), **cfg}
    handler = handler or FakeHandler()
    server = ControlServer(handler, ControlSocketConfig(**cfg), LIMITS, path=sockdir / "control.sock").start()
    return server, handler


def raw(path, data: bytes, replies: int = 1, timeout: float = 3.0) -> list[dict]:
    """Send bytes, read ``replies`` reply lines (fewer if the server closes)."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(timeout)
    s.connect(str(path))
    s.sendall(data)
    f = s.makefile("rb")
    out = []
    for _ in range(replies):
        line = f.readline()
        if not line:
            break
        out.append(json.loads(line))
    f.close()
    s.close()
    return out


def test_every_command_reaches_the_handler_with_checked_arguments_and_the_peer(sockdir, tmp_path):
    traj = tmp_path / "traj.csv"
    traj.write_text("t,x,y,alpha\n0,0,0,0\n")
    exc = tmp_path / "run.mcap"
    exc.write_bytes(b"x")
    server, h = serve(sockdir)
    try:
        with ControlClient(server.path) as c:
            assert c.request("status")["mode"] == "idle"
            for cmd in ("enable", "disable", "hold", "stop", "estop", "reset", "shutdown"):
                assert c.request(cmd) == {"accepted": cmd}
            assert c.request("track", {"target": "corridor"}) == {"accepted": "track", "target": "corridor",
                                                                  "kind": "scenario"}
            assert c.request("track", {"target": str(traj)})["kind"] == "file"
            assert c.request("velocity", {"vx": 0.3, "vy": -0.2, "wz": -1})["wz"] == -1.0
            assert c.request("excite", {"path": str(exc)})["path"] == str(exc)
            assert c.request("record", {"action": "stop"})["action"] == "stop"
    finally:
        server.close()
    assert h.commands() == ["status", "enable", "disable", "hold", "stop", "estop", "reset", "shutdown",
                            "track", "track", "velocity", "excite", "record"]
    for cmd, _, peer, thread in h.calls:
        assert (peer.pid, peer.uid, peer.gid) == (os.getpid(), os.getuid(), os.getgid())
        assert thread == ("otbot-control" if cmd == "estop" else "otbot-dispatch")
    assert isinstance(h.calls[10][1]["vx"], float)


BAD = [  # (request line, error code, words the message must contain)
    (b"hello", "not_json", "not UTF-8 JSON"),
    (b"\xff\xfe{}", "not_json", "not UTF-8 JSON"),
    (b"[1, 2]", "bad_request", "JSON object"),
    (b'{"cmd": "enable"}', "bad_request", "no 'id'"),
    (b'{"id": true, "cmd": "enable"}', "bad_request", "'id'"),
    (b'{"id": 1.5, "cmd": "enable"}', "bad_request", "'id'"),
    (b'{"id": 1, "cmd": "fly"}', "unknown_command", "fly"),
    (b'{"id": 1, "cmd": 3}', "bad_request", "'cmd'"),
    (b'{"id": 1, "cmd": "enable", "extra": 1}', "bad_request", "extra"),
    (b'{"id": 1, "cmd": "enable", "args": {"force": true}}', "bad_request", "force"),
    (b'{"id": 1, "cmd": "enable", "args": [1]}', "bad_request", "'args'"),
    (b'{"id": 1, "cmd": "velocity", "args": {"vx": 0.1, "vy": 0}}', "bad_request", "wz"),
    (b'{"id": 1, "cmd": "velocity", "args": {"vx": "0.1", "vy": 0, "wz": 0}}', "bad_request", "'vx' must be a number"),
    (b'{"id": 1, "cmd": "velocity", "args": {"vx": true, "vy": 0, "wz": 0}}', "bad_request", "'vx' must be a number"),
    (b'{"id": 1, "cmd": "velocity", "args": {"vx": NaN, "vy": 0, "wz": 0}}', "bad_request", "finite"),
    (b'{"id": 1, "cmd": "velocity", "args": {"vx": 0, "vy": Infinity, "wz": 0}}', "bad_request", "finite"),
    (b'{"id": 1, "cmd": "velocity", "args": {"vx": 0.4, "vy": 0.4, "wz": 0}}', "bad_request", "0.5 m/s"),
    (b'{"id": 1, "cmd": "velocity", "args": {"vx": 0, "vy": 0, "wz": -1.01}}', "bad_request", "1 rad/s"),
    (b'{"id": 1, "cmd": "track", "args": {"target": "square"}}', "bad_request", "neither a scenario"),
    (b'{"id": 1, "cmd": "track", "args": {"target": "/nonexistent/t.csv"}}', "bad_request", "not an existing file"),
    (b'{"id": 1, "cmd": "track", "args": {"target": "/etc/passwd"}}', "bad_request", ".csv"),
    (b'{"id": 1, "cmd": "track", "args": {"target": 5}}', "bad_request", "path"),
    (b'{"id": 1, "cmd": "excite", "args": {"path": "run.mcap"}}', "bad_request", "absolute"),
    (b'{"id": 1, "cmd": "record", "args": {"action": "pause"}}', "bad_request", "start, stop"),
]


def test_malformed_and_unknown_requests_get_an_error_reply_and_change_nothing(sockdir):
    server, h = serve(sockdir)
    try:
        for line, code, words in BAD:
            (reply,) = raw(server.path, line + b"\n")
            assert reply["ok"] is False and reply["error"]["code"] == code, (line, reply)
            assert words in reply["error"]["message"], (line, reply)
            assert set(reply) == {"id", "ok", "error"}
            # the id is echoed whenever it could be read
            assert reply["id"] == (1 if b'"id": 1,' in line else None)
        # all of them on one connection, then a good one: the connection survives bad requests
        replies = raw(server.path, b"\n".join(line for line, _, _ in BAD) + b'\n{"id": "x", "cmd": "status"}\n',
                      replies=len(BAD) + 1)
        assert [r["ok"] for r in replies] == [False] * len(BAD) + [True]
        assert replies[-1]["id"] == "x"
    finally:
        server.close()
    assert h.commands() == ["status"]


def test_oversized_line_is_refused_and_closes_only_that_connection(sockdir):
    server, h = serve(sockdir, max_request=4096)
    try:
        big = b'{"id": 1, "cmd": "enable", "args": {"pad": "' + b"x" * (1 << 20) + b'"}}\n'
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.settimeout(3)
        s.connect(str(server.path))
        try:
            s.sendall(big)
        except (BrokenPipeError, ConnectionResetError):
            pass  # the server closed the connection before the megabyte was through
        reply = json.loads(s.makefile("rb").readline())
        s.close()
        assert reply["error"]["code"] == "too_large" and "4096 bytes" in reply["error"]["message"]
        # a line of exactly the limit is still accepted
        pad = 4096 - len(b'{"id": 2, "cmd": "status", "args": {}}')
        line = b'{"id": 2, "cmd": "status", "args": {}' + b" " * pad + b"}"
        assert len(line) == 4096
        assert raw(server.path, line + b"\n")[0]["ok"]
        with ControlClient(server.path) as c:
            assert c.request("hold") == {"accepted": "hold"}
    finally:
        server.close()
    assert h.commands() == ["status", "hold"]


def test_half_a_request_then_disconnect_harms_nothing(sockdir):
    server, h = serve(sockdir, request_timeout=0.3)
    try:
        for _ in range(20):
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            s.connect(str(server.path))
            s.sendall(b'{"id": 1, "cmd": "ena')
            s.close()
        # a client that stalls mid-line is told and dropped after request_timeout
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.settimeout(3)
        s.connect(str(server.path))
        t0 = time.monotonic()
        s.sendall(b'{"id": 1, "cmd": "enable"')
        reply = json.loads(s.makefile("rb").readline())
        waited = time.monotonic() - t0
        assert reply["error"]["code"] == "timeout" and 0.25 < waited < 1.5
        assert s.recv(10) == b""  # closed
        s.close()
        with ControlClient(server.path) as c:
            assert c.request("status")["mode"] == "idle"
    finally:
        server.close()
    assert h.commands() == ["status"]


def test_fifty_clients_at_once(sockdir):
    server, h = serve(sockdir, max_clients=64)
    results, errors = {}, []
    barrier = threading.Barrier(50)

    def client(i):
        try:
            with ControlClient(server.path) as c:
                barrier.wait(5)
                results[i] = (c.request("status")["mode"], c.request("velocity", {"vx": i / 100, "vy": 0, "wz": 0}))
        except Exception as exc:  # noqa: BLE001 - collected and asserted below
            errors.append(exc)

    threads = [threading.Thread(target=client, args=(i,)) for i in range(50)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10)
    server.close()
    assert not errors
    assert len(results) == 50
    assert all(results[i] == ("idle", {"accepted": "velocity", "vx": i / 100, "vy": 0.0, "wz": 0.0}) for i in range(50))
    assert sorted(c[1]["vx"] for c in h.calls if c[0] == "velocity") == [i / 100 for i in range(50)]


def test_clients_beyond_the_limit_are_told_busy(sockdir):
    server, h = serve(sockdir, max_clients=3)
    held = []
    try:
        for _ in range(3):
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            s.connect(str(server.path))
            held.append(s)
        with pytest.raises(ControlError) as e:
            with ControlClient(server.path, timeout=2) as c:
                c.request("status")
        assert e.value.code == "busy" and "limit 3" in str(e.value)
        held.pop().close()
        time.sleep(0.05)
        with ControlClient(server.path) as c:
            assert c.request("status")["mode"] == "idle"
    finally:
        for s in held:
            s.close()
        server.close()


def test_random_bytes_leave_the_server_running_and_the_handler_untouched(sockdir):
    server, h = serve(sockdir, max_request=8192)
    rng = random.Random(14)
    try:
        def fuzz(seed):
            r = random.Random(seed)
            for _ in range(15):
                s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
                s.settimeout(2)
                s.connect(str(server.path))
                try:
                    for _ in range(r.randint(1, 4)):
                        s.sendall(bytes(r.getrandbits(8) for _ in range(r.randint(1, 3000))))
                    if r.random() < 0.5:
                        s.sendall(b"\n")
                        s.recv(65536)
                except OSError:
                    pass  # the server may close a client that sent an oversized line
                s.close()

        threads = [threading.Thread(target=fuzz, args=(rng.random(),)) for _ in range(6)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(20)
        # structurally plausible garbage too: valid JSON with wrong shapes
        for _ in range(200):
            obj = {"id": rng.choice([1, "a", None, [], {}]), "cmd": rng.choice(["enable", "velocity", "x", 1]),
                   "args": rng.choice([{}, {"vx": rng.uniform(-9, 9)}, {"vx": 1e308, "vy": -1e308, "wz": 0}, None, 3])}
            line = json.dumps(obj).encode()
            try:
                req = parse_request(line, LIMITS)
            except ProtocolError:
                req = None
            (reply,) = raw(server.path, line + b"\n")
            assert reply["ok"] is (req is not None), (obj, reply)
        assert server._threads[0].is_alive() and server._threads[1].is_alive()
        with ControlClient(server.path) as c:
            assert c.request("status")["mode"] == "idle"
    finally:
        server.close()
    valid = [c for c in h.commands() if c != "status"]
    assert all(c == "enable" for c in valid)  # the only command random shapes can validly form


def test_status_is_open_but_commands_need_an_allowed_user_or_group(sockdir):
    me = pwd.getpwuid(ME).pw_name
    for users, groups, allowed in [((ME,), (), True), ((me,), (), True), ((), (os.getgid(),), True),
                                   ((), (), False), ((ME + 1, "no-such-user-xyz"), ("no-such-group-xyz",), False)]:
        server, h = serve(sockdir, allowed_users=users, allowed_groups=groups)
        try:
            with ControlClient(server.path) as c:
                assert c.request("status")["mode"] == "idle"
                for cmd, args in [("enable", None), ("estop", None), ("velocity", {"vx": 0, "vy": 0, "wz": 0})]:
                    if allowed:
                        assert c.request(cmd, args)["accepted"] == cmd
                    else:
                        with pytest.raises(ControlError) as e:
                            c.request(cmd, args)
                        assert e.value.code == "forbidden" and f"uid {ME}" in str(e.value)
        finally:
            server.close()
        assert h.commands() == (["status", "enable", "estop", "velocity"] if allowed else ["status"])


def as_user(uid: int, gid: int, path: Path) -> list:
    """Connect to ``path`` from a forked child running as uid/gid (no supplementary groups) and send
    status then enable; the replies, or ["EACCES"] when the connection is refused by the file mode.
    (A fork, not a new interpreter: the venv's python need not be executable by that user.)"""
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # child: stdlib only, then _exit
        code = 0
        try:
            os.close(r)
            os.setgroups([])
            os.setgid(gid)
            os.setuid(uid)
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            s.settimeout(5)
            try:
                s.connect(str(path))
                f = s.makefile("rb")
                out = []
                for i, cmd in enumerate(("status", "enable")):
                    s.sendall(json.dumps({"id": i, "cmd": cmd}).encode() + b"\n")
                    out.append(json.loads(f.readline()))
            except PermissionError:
                out = ["EACCES"]
            os.write(w, json.dumps(out).encode())
        except BaseException:
            code = 1
        finally:
            os._exit(code)
    os.close(w)
    with os.fdopen(r, "rb") as f:
        data = f.read()
    _, status = os.waitpid(pid, 0)
    assert status == 0 and data, "the child client failed"
    return json.loads(data)


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to run a client as another user")
def test_another_user_reaches_status_only_and_the_socket_mode_keeps_others_out(sockdir):
    nobody = 65534
    server, h = serve(sockdir, allowed_users=(0,), allowed_groups=())
    os.chmod(sockdir, 0o755)
    try:
        st = server.path.stat()
        assert stat.S_ISSOCK(st.st_mode) and stat.S_IMODE(st.st_mode) == 0o660
        # in the socket's group: can connect; status answered, enable forbidden (uid 65534 not allowed)
        status, enable = as_user(nobody, st.st_gid, server.path)
        assert status["ok"] and status["result"]["mode"] == "idle"
        assert enable["error"]["code"] == "forbidden"
        assert f"uid {nobody} gid {st.st_gid}" in enable["error"]["message"]
        # neither owner nor group: the file mode keeps it out
        assert as_user(nobody, nobody, server.path) == ["EACCES"]
    finally:
        server.close()
    assert h.commands() == ["status"]
    assert h.calls[0][2].uid == nobody


def test_stale_socket_is_replaced_live_daemon_is_not(sockdir):
    path = sockdir / "control.sock"
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    stale.bind(str(path))
    stale.close()  # the file stays: a crashed daemon's leftover
    assert path.exists()
    server, _ = serve(sockdir)
    try:
        assert stat.S_IMODE(path.stat().st_mode) == 0o660
        inode = path.stat().st_ino
        with pytest.raises(SocketInUse, match="another daemon is running"):
            ControlServer(FakeHandler(), ControlSocketConfig(), LIMITS, path=path).start()
        assert path.stat().st_ino == inode  # the live daemon keeps its socket
        with ControlClient(path) as c:
            assert c.request("status")["mode"] == "idle"
    finally:
        server.close()
    assert not path.exists()  # removed on close
    path.write_text("not a socket")
    with pytest.raises(SocketInUse, match="not a socket"):
        ControlServer(FakeHandler(), ControlSocketConfig(), LIMITS, path=path).start()
    assert path.read_text() == "not a socket"
    assert sorted(p.name for p in sockdir.iterdir()) == ["control.sock"]  # no temporary left behind


def test_estop_is_not_queued_behind_a_slow_command(sockdir):
    server, h = serve(sockdir, handler=FakeHandler(slow={"track": 1.0}))
    try:
        slow = ControlClient(server.path)
        t = threading.Thread(target=slow.request, args=("track", {"target": "corridor"}))
        t.start()
        time.sleep(0.1)
        with ControlClient(server.path) as c:
            t0 = time.monotonic()
            assert c.request("estop") == {"accepted": "estop"}
            estop_s = time.monotonic() - t0
            t1 = time.monotonic()
            c.request("status")  # queued behind the track command
            status_s = time.monotonic() - t1
        t.join(3)
        slow.close()
    finally:
        server.close()
    assert estop_s < 0.2 and status_s > 0.5
    assert h.commands() == ["track", "estop", "status"]


def test_handler_refusals_and_failures_become_error_replies(sockdir):
    class Broken(FakeHandler):
        def hold(self, *, peer):
            raise ZeroDivisionError("boom")

        def status(self, *, peer):
            return {"mode": "idle", "faults": None, "drive_states": {}}

        def reset(self, *, peer):
            return {"x": float("nan")}

    server, h = serve(sockdir, handler=Broken(refuse={"enable": "robot is faulted: reset first"}))
    try:
        with ControlClient(server.path) as c:
            for cmd, code, words in [("enable", "refused", "reset first"), ("hold", "internal", "boom"),
                                     ("status", "internal", "'faults' as list"), ("reset", "internal", "not JSON")]:
                with pytest.raises(ControlError) as e:
                    c.request(cmd)
                assert e.value.code == code and words in str(e.value)
            assert c.request("stop") == {"accepted": "stop"}
    finally:
        server.close()


def test_no_daemon_is_reported_in_one_sentence(sockdir):
    with pytest.raises(DaemonUnreachable, match="no such socket"):
        ControlClient(sockdir / "none.sock")
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    stale.bind(str(sockdir / "stale.sock"))
    stale.close()
    with pytest.raises(DaemonUnreachable, match="connection refused"):
        ControlClient(sockdir / "stale.sock")


def test_loop_mailbox_runs_work_on_the_loop_thread_without_blocking_it():
    box = LoopMailbox()
    stop = threading.Event()
    cycles = []

    def loop():
        while not stop.is_set():
            t0 = time.perf_counter()
            box.service()
            cycles.append(time.perf_counter() - t0)
            time.sleep(0.004)

    th = threading.Thread(target=loop, name="fake-loop")
    th.start()
    try:
        assert box.call(lambda: threading.current_thread().name) == "fake-loop"
        with pytest.raises(KeyError):
            box.call(lambda: {}["missing"])
    finally:
        stop.set()
        th.join()
    # nobody services: the call times out and never runs afterwards
    ran = []
    with pytest.raises(TimeoutError, match="did not take"):
        box.call(lambda: ran.append(1), timeout=0.05)
    assert box.service() == 0 and ran == []
    assert max(cycles) < 0.002  # service() never waits


def test_daemon_config_errors_name_the_key():
    cfg = daemon_config_from_dict({"socket": {"max_request": {"value": 1, "unit": "MiB"}, "allowed_users": ["ops", 0]}})
    assert cfg.socket.max_request == 2 ** 20 and cfg.socket.allowed_users == ("ops", 0)
    for bad, words in [({"socket": {"max_request": {"value": 64, "unit": "kB"}}}, "daemon.socket.max_request"),
                       ({"socket": {"allowed_groups": "otbot"}}, "daemon.socket.allowed_groups"),
                       ({"socket": {"port": 1}}, "unknown key(s) ['port']"),
                       ({"velocity": {"deadman": {"value": 0, "unit": "s"}}}, "daemon.velocity.deadman"),
                       ({"velocity": {"max_linear": {"value": 1, "unit": "km/h"}}}, "unit must be 'm/s'"),
                       ({"recording": {"flush_interval": {"value": 2, "unit": "s"}}}, "one second"),
                       ({"telemetry": {"port": 70000}}, "daemon.telemetry.port"),
                       ({"telemetry": {"enabled": "yes"}}, "daemon.telemetry.enabled"),
                       ({"sockets": {}}, "unknown key(s) ['sockets']")]:
        with pytest.raises(ParameterError, match=words.replace("[", r"\[").replace("]", r"\]").replace("(", r"\(").replace(")", r"\)")):
            daemon_config_from_dict(bad, "robot.yaml")


def test_a_handler_may_close_the_server_and_its_reply_still_goes_out(sockdir):
    class Closing(FakeHandler):
        server = None

        def shutdown(self, *, peer):
            self._record("shutdown", peer)
            self.server.close()  # from the dispatch thread, as a daemon's shutdown may
            return {"bye": True}

    h = Closing(slow={"hold": 0.3})
    server, _ = serve(sockdir, handler=h)
    h.server = server
    c1 = ControlClient(server.path)
    results = {}
    t = threading.Thread(target=lambda: results.setdefault("hold", c1.request("hold")))
    t.start()
    time.sleep(0.05)
    with ControlClient(server.path) as c2:
        assert c2.request("shutdown") == {"bye": True}  # queued behind hold, answered after it
    t.join(3)
    c1.close()
    assert results["hold"] == {"accepted": "hold"}
    deadline = time.monotonic() + 3
    while server.path.exists() and time.monotonic() < deadline:
        time.sleep(0.01)
    assert not server.path.exists()
    assert not any(th.is_alive() for th in server._threads if th is not threading.current_thread())
    assert h.commands() == ["hold", "shutdown"]


def test_a_client_that_floods_and_never_reads_does_not_make_the_server_spin(sockdir):
    server, h = serve(sockdir, max_request=4096)
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.setblocking(False)
    s.connect(str(server.path))
    try:
        # replies it never reads fill its receive buffer and the server's output queue, then a
        # line too long: the server must close it without reading on (its data stay unread)
        pending = b"x\n" * 6000 + b"y" * 200_000
        deadline = time.monotonic() + 3
        while pending and time.monotonic() < deadline:
            try:
                pending = pending[s.send(pending):]
            except BlockingIOError:
                time.sleep(0.01)
            except (BrokenPipeError, ConnectionResetError):
                break
        seen = -1
        while server.counters["errors"] != seen:  # until the server has answered what it read
            seen = server.counters["errors"]
            time.sleep(0.1)
        s.send(b"more")  # unread data on a connection the server is closing
        polls = server.counters["polls"]
        time.sleep(0.5)
        polls = server.counters["polls"] - polls
        with ControlClient(server.path) as c:
            assert c.request("status")["mode"] == "idle"
    finally:
        s.close()
        server.close()
    # idle, the I/O thread wakes twice a second; spinning on the unread data it would wake thousands of times
    assert seen > 1000 and polls <= 5, f"the I/O thread woke {polls} times in 0.5 s"
