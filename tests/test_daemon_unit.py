"""The systemd unit (config/otbot-daemon.service): what the issue asks of it, hardening that would
break CAN or serial kept out, systemd's own verifier, and agreement with the daemon's defaults."""
from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from otbot_hw.runtime.daemon_config import DaemonConfig, default_socket_path, load_daemon_config

ROOT = Path(__file__).resolve().parents[1]
UNIT = ROOT / "config" / "otbot-daemon.service"


def directives() -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    text = UNIT.read_text().replace("\\\n", " ")
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith(("#", "[")):
            continue
        k, _, v = line.partition("=")
        out.setdefault(k.strip(), []).append(v.strip())
    return out


def test_unit_asks_for_notify_watchdog_restart_and_an_unprivileged_user():
    d = directives()
    assert d["Type"] == ["notify"] and d["Restart"] == ["on-failure"]
    assert d["WatchdogSec"] and d["WatchdogSec"][0].endswith("s")
    assert d["User"] == ["otbot"] and d["Group"] == ["otbot"]
    assert "dialout" in d["SupplementaryGroups"][0].split()
    assert d["RuntimeDirectory"] == ["otbot"] and d["KillSignal"] == ["SIGTERM"]
    # the daemon's default socket under systemd is where the unit's RuntimeDirectory puts it
    assert default_socket_path({"RUNTIME_DIRECTORY": "/run/otbot"}) == Path("/run/otbot/control.sock")
    assert "--record-dir /var/lib/otbot/recordings" in d["ExecStart"][0]
    assert "otbot/recordings" in d["StateDirectory"][0].split()


def test_hardening_keeps_can_and_serial_working():
    d = directives()
    assert d.get("PrivateDevices", ["no"]) == ["no"]          # would hide /dev/ttyUSB*
    assert d.get("PrivateNetwork", ["no"]) == ["no"]          # CAN interfaces are in the host namespace
    assert d.get("MemoryDenyWriteExecute", ["no"]) == ["no"]  # numba's JIT writes machine code
    assert "AF_CAN" in d["RestrictAddressFamilies"][0].split()
    assert {"char-ttyUSB rw", "char-ttyACM rw"} <= set(d["DeviceAllow"])
    assert d["NoNewPrivileges"] == ["yes"] and d["ProtectSystem"] == ["strict"]


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_systemd_accepts_the_unit(tmp_path):
    # the same unit with an ExecStart that exists here (the verifier checks the binary)
    text = UNIT.read_text().replace("ExecStart=/opt/otbot-hw/.venv/bin/otbot", "ExecStart=/bin/true")
    (tmp_path / "otbot-daemon.service").write_text(text)
    p = subprocess.run(["systemd-analyze", "verify", str(tmp_path / "otbot-daemon.service")],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 0 and "otbot-daemon.service" not in p.stderr, p.stderr


def test_config_file_daemon_section_is_the_documented_default():
    assert load_daemon_config(ROOT / "config" / "robot.yaml") == DaemonConfig()
