"""Issue 22, "the daemon's first minutes": every start-up failure is one line naming what is wrong,
exit 2, no traceback, nothing created and no robot touched (a start-up table); ``--bus sim`` allows
the invoking user and ``--allow-user`` adds users without a copy of the configuration; ``otbot ctl``
starts without the runtime (it imports the protocol and client only), names a regular file or a
folder given as ``--socket`` for what it is, does not double its error prefix, and ``velocity --hold``
streams at 5 Hz until Ctrl-C, then stops."""
from __future__ import annotations

import json
import os
import pwd
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from daemon_fakes import FakeHandler
from otbot_hw.runtime.control_protocol import ArgumentLimits
from otbot_hw.runtime.control_socket import ControlServer
from otbot_hw.runtime.daemon_config import ControlSocketConfig

ROOT = os.geteuid() == 0
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def short_dir():
    d = Path(tempfile.mkdtemp(prefix="ots"))  # short: AF_UNIX paths are limited to 107 bytes
    yield d
    subprocess.run(["umount", "-l", str(d / "ro")], capture_output=True) if ROOT else None
    import shutil
    shutil.rmtree(d, ignore_errors=True)


def _read_only_folder(d: Path) -> Path:
    ro = d / "ro"
    ro.mkdir()
    if ROOT:  # root writes anywhere a mode allows nothing: a read-only file system is what stops it
        if subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=64k", "tmpfs", str(ro)],
                          capture_output=True).returncode != 0:
            pytest.skip("cannot mount a read-only tmpfs")
    else:
        os.chmod(ro, 0o555)
    return ro


def _taken_port():
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    s.bind(("127.0.0.1", 0))
    s.listen(1)
    return s, s.getsockname()[1]


#: (name, set-up(dir) -> (extra arguments, cleanup), words the one line must contain)
def _table():
    def socket_in(folder_fn, name="control.sock"):
        def setup(d):
            return ["--socket", str(folder_fn(d) / name)], None
        return setup

    def long_path(d):
        deep = d / ("x" * 60)
        deep.mkdir()
        return ["--socket", str(deep / ("s" * 60 + ".sock"))], None

    def port_taken(d):
        s, port = _taken_port()
        return ["--telemetry", f"127.0.0.1:{port}"], s.close

    def second_daemon(d):
        server = ControlServer(FakeHandler(), ControlSocketConfig(), ArgumentLimits(), path=d / "control.sock").start()
        return [], server.close

    def cpu_missing(d):
        from otbot_hw.runtime.daemon_process import local_config

        cpu = max(os.sched_getaffinity(0)) + 1
        return ["--config", str(local_config(d / "cfg", replace={"cpus: null": f"cpus: [0, {cpu}]"}))], None

    return [
        ("a CPU this process may not use", cpu_missing, ["daemon.scheduling.cpus", "not available", "may run on"]),
        ("socket folder missing", socket_in(lambda d: d / "nope"), ["control socket folder", "does not exist",
                                                                    "RuntimeDirectory="]),
        ("socket folder unwritable", socket_in(_read_only_folder), ["control socket folder", "not writable"]),
        ("socket path over the AF_UNIX limit", long_path, ["bytes", "at most 107"]),
        ("socket path is a folder", lambda d: (["--socket", str(d)], None), ["is a folder"]),
        ("telemetry port taken", port_taken, ["telemetry port", "is taken", "--no-telemetry"]),
        ("telemetry address not local", lambda d: (["--telemetry", "192.0.2.1:0"], None),
         ["192.0.2.1", "not an address of this machine"]),
        ("telemetry host unknown", lambda d: (["--telemetry", "no-such-host.invalid:0"], None),
         ["telemetry host", "unknown"]),
        ("second daemon on the same socket", second_daemon, ["another daemon is running on"]),
        ("recording folder missing", lambda d: (["--record-dir", str(d / "rec" / "deeper")], None),
         ["--record-dir", "does not exist", "StateDirectory="]),
        ("recording folder unwritable", lambda d: (["--record-dir", str(_read_only_folder(d))], None),
         ["--record-dir", "can write"]),
        ("unknown --allow-user", lambda d: (["--allow-user", "no-such-user-xyz"], None),
         ["--allow-user", "no such user"]),
    ]


@pytest.mark.parametrize("name, setup, words", _table(), ids=[row[0] for row in _table()])
def test_daemon_start_up_failures_are_one_line_exit_2_and_touch_nothing(name, setup, words, short_dir, otbot_cli):
    rec = short_dir / "rec"
    rec.mkdir()
    extra, cleanup = setup(short_dir)
    before = sorted(p.name for p in short_dir.rglob("*"))
    argv = ["daemon", "--bus", "sim", "--socket", str(short_dir / "control.sock"), "--record-dir", str(rec),
            "--no-telemetry", *extra]
    if "--telemetry" in extra:
        argv.remove("--no-telemetry")
    try:
        rc, out, err = otbot_cli(argv)
        after = sorted(p.name for p in short_dir.rglob("*"))
    finally:
        if cleanup is not None:
            cleanup()
    lines = err.strip().splitlines()
    assert rc == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith("otbot daemon: error: ")
    for w in words:
        assert w in lines[0], (w, lines[0])
    assert after == before, "the daemon created something"                 # no folder, no socket, no recording


def _serve(path: Path, **cfg):
    cfg = {"allowed_users": (), "allowed_groups": (), **cfg}
    return ControlServer(FakeHandler(), ControlSocketConfig(**cfg), ArgumentLimits(), path=path).start()


def test_bus_sim_allows_the_invoking_user_and_allow_user_needs_no_copy_of_the_configuration(tmp_path):
    from otbot_hw.cli import build_parser
    from otbot_hw.cli.daemon import prepare

    (tmp_path / "rec").mkdir()
    me = pwd.getpwuid(os.getuid()).pw_name
    common = ["--socket", str(tmp_path / "c.sock"), "--record-dir", str(tmp_path / "rec"), "--no-telemetry"]
    d, _ = prepare(build_parser().parse_args(["daemon", "--bus", "sim", *common]))
    assert os.getuid() in d.server.config.allowed_users                       # the shipped config, unchanged
    d, _ = prepare(build_parser().parse_args(["daemon", "--bus", "config", *common]))
    assert d.server.config.allowed_users == ()                               # the real bus keeps the safe default
    d, _ = prepare(build_parser().parse_args(["daemon", "--bus", "config", "--allow-user", me,
                                              "--allow-user", "0", *common]))
    assert d.server.authorizer.allows(type("P", (), {"uid": os.getuid(), "gid": -1, "groups": ()})())
    assert set(d.server.config.allowed_users) == {os.getuid(), 0}


def test_refusal_names_the_key_and_the_option(tmp_path, otbot_cli):
    server = _serve(tmp_path / "c.sock")
    try:
        rc, out, err = otbot_cli(["ctl", "--socket", str(server.path), "enable"])
    finally:
        server.close()
    assert rc == 1 and "daemon.socket.allowed_users" in err and "--allow-user" in err


def test_ctl_names_a_regular_file_or_a_folder_given_as_socket(tmp_path, otbot_cli):
    f = tmp_path / "notes.txt"
    f.write_text("x")
    for path, what in ((f, "is a regular file"), (tmp_path, "is a folder")):
        rc, out, err = otbot_cli(["ctl", "--socket", str(path), "status"])
        assert rc == 1 and what in err and "stale" not in err, err
        assert len(err.strip().splitlines()) == 1


def test_ctl_error_prefix_is_not_doubled(tmp_path, otbot_cli):
    server = _serve(tmp_path / "c.sock", allowed_users=(os.getuid(),))
    try:
        rc, out, err = otbot_cli(["ctl", "--socket", str(server.path), "track", str(tmp_path / "missing.csv")])
    finally:
        server.close()
    assert rc == 2 and err.count("track:") == 1 and err.startswith("otbot ctl track: error: /"), err


def test_ctl_imports_the_protocol_only():
    code = ("import sys; from otbot_hw.cli import main\n"
            "rc = None\n"
            "try:\n    main(['ctl', '--socket', '/nonexistent/s.sock', 'status'])\n"
            "except SystemExit as e:\n    rc = e.code\n"
            "heavy = sorted(m for m in ('numpy', 'scipy', 'numba', 'canopen', 'can', 'otbot_hw.runtime.loop', "
            "'otbot_hw.params', 'otbot_hw.runtime.control_socket') if m in sys.modules)\n"
            "print(rc, heavy)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=60)
    assert out.stdout.strip() == "1 []", (out.stdout, out.stderr[-1000:])


def test_ctl_velocity_hold_streams_at_5_hz_until_ctrl_c_then_stops(tmp_path):
    h = FakeHandler()
    server = ControlServer(h, ControlSocketConfig(allowed_users=(os.getuid(),), allowed_groups=()),
                           ArgumentLimits(max_linear=0.5, max_angular=1.0), path=tmp_path / "c.sock").start()
    try:
        p = subprocess.Popen([sys.executable, "-m", "otbot_hw", "ctl", "--socket", str(server.path), "--json",
                              "velocity", "0.1", "0", "0", "--hold"], cwd=REPO, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
        end = time.monotonic() + 20
        while h.commands().count("velocity") < 4 and time.monotonic() < end:
            time.sleep(0.05)
        t0, n0 = time.monotonic(), h.commands().count("velocity")
        time.sleep(1.0)
        rate = (h.commands().count("velocity") - n0) / (time.monotonic() - t0)
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=20)
    finally:
        server.close()
    assert p.returncode == 0, err
    assert 3.0 <= rate <= 7.0, rate                                        # 5 Hz: within the 0.5 s deadman
    assert h.commands()[-1] == "stop"                                      # Ctrl-C ramps to rest
    res = json.loads(out.strip().splitlines()[-1])
    assert res["stopped"] is True and res["velocity_commands"] == h.commands().count("velocity")
