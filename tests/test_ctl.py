"""``otbot ctl`` end to end against a control server with a recording fake handler: the request
the handler receives, text and --json output, exit codes (0 done, 2 bad input, 1 not done)."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from daemon_fakes import FakeHandler
from otbot_hw.cli import main
from otbot_hw.runtime.control_protocol import ArgumentLimits
from otbot_hw.runtime.control_socket import ControlServer
from otbot_hw.runtime.daemon_config import ControlSocketConfig

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def daemon():
    d = Path(tempfile.mkdtemp(prefix="otb"))
    h = FakeHandler(refuse={"enable": "robot is faulted: reset first"})
    server = ControlServer(h, ControlSocketConfig(allowed_users=(os.getuid(),), allowed_groups=()),
                           ArgumentLimits(max_linear=0.5, max_angular=1.0, scenarios=("corridor",)),
                           path=d / "control.sock").start()
    yield server, h
    server.close()
    shutil.rmtree(d, ignore_errors=True)


def ctl(server, *argv) -> int:
    try:
        return main(["ctl", "--socket", str(server.path), *argv])
    except SystemExit as exc:
        return exc.code


def test_status_text_and_json(daemon, capsys):
    server, h = daemon
    h.faults = [{"device": "pivot", "node": 3, "kind": "emcy", "code": 0x7300, "meaning": "sensor"}]
    assert ctl(server, "status") == 0
    out = capsys.readouterr().out
    assert "mode       idle" in out
    assert "250.0 Hz: period p50 4.000 ms, p99 4.120 ms; jitter p99 0.120 ms" in out and "overruns 0" in out
    assert "x 1.2500 ± 0.0020 m, y -0.5000 ± 0.0030 m, alpha 0.1000 ± 0.0010 rad" in out
    assert "error x 4.0 mm, y -1.0 mm, alpha 2.0 mrad" in out
    assert "pivot (node 3): emcy 0x7300: sensor" in out
    assert "right_wheel OPERATION ENABLED" in out and "s-000.mcap" in out
    for argv in (("status", "--json"), ("--json", "status")):  # --json on either side of the command
        assert ctl(server, *argv) == 0
        s = json.loads(capsys.readouterr().out)
        assert s["mode"] == "idle" and s["faults"][0]["code"] == 0x7300
        assert set(s["drive_states"]) == {"right_wheel", "left_wheel", "pivot"}
    h.faults = []
    assert ctl(server, "status", "--json") == 0
    assert json.loads(capsys.readouterr().out)["faults"] == []


def test_commands_reach_the_daemon_with_units_and_absolute_paths(daemon, capsys, tmp_path, monkeypatch):
    server, h = daemon
    (tmp_path / "traj.csv").write_text("t,x,y,alpha\n0,0,0,0\n")
    (tmp_path / "exc.mcap").write_bytes(b"x")
    monkeypatch.chdir(tmp_path)
    assert ctl(server, "velocity", "-0.25", "0.1", "-0.5") == 0
    assert capsys.readouterr().out.strip() == "velocity: ok (accepted velocity, vx -0.25, vy 0.1, wz -0.5)"
    assert ctl(server, "track", "corridor") == 0
    assert ctl(server, "track", "traj.csv", "--json") == 0
    assert json.loads(capsys.readouterr().out.splitlines()[-1])["target"] == str(tmp_path / "traj.csv")
    assert ctl(server, "excite", "exc.mcap") == 0
    assert ctl(server, "record", "start") == 0
    assert ctl(server, "estop") == 0
    assert [(c[0], c[1]) for c in h.calls] == [
        ("velocity", {"vx": -0.25, "vy": 0.1, "wz": -0.5}), ("track", {"target": "corridor", "kind": "scenario"}),
        ("track", {"target": str(tmp_path / "traj.csv"), "kind": "file"}),
        ("excite", {"path": str(tmp_path / "exc.mcap")}), ("record", {"action": "start"}), ("estop", {})]


def test_exit_codes(daemon, capsys):
    server, h = daemon
    # refused by the daemon's state: not the caller's input -> 1, one line
    assert ctl(server, "enable") == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["otbot ctl: enable refused: robot is faulted: reset first"]
    # the daemon says the request is bad -> 2
    assert ctl(server, "velocity", "0.6", "0", "0") == 2
    assert "exceeds the limit 0.5 m/s" in capsys.readouterr().err
    assert ctl(server, "track", "nowhere/t.csv") == 2
    assert "not an existing file" in capsys.readouterr().err
    # argparse catches what the client can check itself -> 2, the daemon never asked
    assert ctl(server, "velocity", "nan", "0", "0") == 2
    assert ctl(server, "record", "pause") == 2
    assert h.commands() == ["enable"]


def test_no_daemon_is_one_line_and_exit_1(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    p = subprocess.run([sys.executable, "-m", "otbot_hw", "ctl", "--socket", str(tmp_path / "none.sock"), "status"],
                       capture_output=True, text=True, env=env, timeout=60)
    assert p.returncode == 1
    assert p.stderr.strip() == f"otbot ctl: no daemon at {tmp_path / 'none.sock'} (no such socket)"
    assert p.stdout == ""


def test_socket_is_found_where_the_daemon_puts_it(tmp_path, monkeypatch, capsys):
    from otbot_hw.runtime.daemon_config import default_socket_path, socket_candidates

    env = {"RUNTIME_DIRECTORY": "/run/otbot:/run/other", "XDG_RUNTIME_DIR": "/run/user/1000"}
    assert default_socket_path(env) == Path("/run/otbot/control.sock")
    assert default_socket_path({"XDG_RUNTIME_DIR": "/run/user/1000"}) == Path("/run/user/1000/otbot/control.sock")
    assert default_socket_path({}) == Path("/run/otbot/control.sock")
    # a user's shell has XDG_RUNTIME_DIR but the system daemon lives in /run/otbot: both are tried
    assert socket_candidates({"XDG_RUNTIME_DIR": "/run/user/1000"}) == [
        Path("/run/otbot/control.sock"), Path("/run/user/1000/otbot/control.sock")]
    # --config's daemon.socket.path (relative to the file) comes before the defaults
    cfg = tmp_path / "robot.yaml"
    cfg.write_text("daemon:\n  socket:\n    path: run/ctl.sock\n")
    with pytest.raises(SystemExit) as e:
        main(["ctl", "--config", str(cfg), "status"])
    assert e.value.code == 1
    assert capsys.readouterr().err.strip() == f"otbot ctl: no daemon at {tmp_path / 'run' / 'ctl.sock'} (no such socket)"
