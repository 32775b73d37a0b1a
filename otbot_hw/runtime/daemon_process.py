"""``otbot daemon`` (and the ``otbot plant`` it drives) as child processes: for the end-to-end tests,
``benchmarks/daemon.py`` and bench scripts that need a daemon they can signal or kill.

``local_config(folder)`` writes a copy of a hardware configuration that this user may command
(``daemon.socket.allowed_users``), with the object dictionaries beside it and no slcan settle delay;
``PlantServer`` starts ``otbot plant`` (slcan on a pseudo-terminal, IMU on another); ``DaemonProcess``
starts ``otbot daemon``, waits until it answers ``status`` and talks to it like ``otbot ctl``. Both
take a command ``prefix`` (``chrt -f 50``: real-time scheduling, as the unit's CPUSchedulingPolicy).
"""
from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

from otbot_hw.motors import DEFAULT_ROBOT_FILE
from otbot_hw.runtime.control_socket import ControlClient, ControlError, DaemonUnreachable


def local_config(folder: Path, source: Path | None = None, replace: dict[str, str] | None = None) -> Path:
    """``folder/robot.yaml``: ``source`` (default config/robot.yaml) with this user allowed to command,
    the slcan adapter's settle delay off, and each ``replace`` old -> new text substituted (each must
    occur); the EDS files are copied beside it. Returns the path."""
    source = Path(source) if source is not None else DEFAULT_ROBOT_FILE
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    text = source.read_text()
    text = re.sub(r"allowed_users: \[[^\]]*\]", f"allowed_users: [{os.getuid()}]", text)
    text = text.replace("  options: {}", "  options: {sleep_after_open: 0}")
    for old, new in (replace or {}).items():
        if old not in text:
            raise ValueError(f"{source}: no {old!r} to replace")
        text = text.replace(old, new)
    for eds in source.parent.glob("*.eds"):
        shutil.copy(eds, folder / eds.name)
    out = folder / "robot.yaml"
    out.write_text(text)
    return out


def _cli(prefix: list[str] | None = None) -> list[str]:
    """The ``otbot`` command of this interpreter, behind ``prefix`` (e.g. ``chrt -f 50``)."""
    return [*(prefix or []), sys.executable, "-m", "otbot_hw"]


class PlantServer:
    """``otbot plant`` (slcan on a pty, IMU on a pty) as a child process: ``info`` has can_channel and
    imu_port; ``close()`` ends it by closing its input."""

    def __init__(self, config: Path, rate: float | None = None, extra: list[str] | None = None, env=None,
                 prefix: list[str] | None = None):
        args = [*_cli(prefix), "plant", "--config", str(config), *(["--rate", repr(rate)] if rate else []), *(extra or [])]
        self.proc = subprocess.Popen(args, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
        line = self.proc.stdout.readline()
        try:
            self.info = json.loads(line)
        except ValueError:
            self.close()
            raise RuntimeError(f"the plant process did not start (exit code {self.proc.poll()})") from None

    def bus_args(self) -> list[str]:
        """``otbot daemon`` options that put it on this plant."""
        return ["--bus", "config", "--interface", "slcan", "--channel", self.info["can_channel"],
                "--imu-port", self.info["imu_port"]]

    def close(self) -> int | None:
        try:
            self.proc.stdin.close()
        except OSError:
            pass
        try:
            return self.proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            return self.proc.wait(timeout=10)

    def __enter__(self) -> "PlantServer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class DaemonProcess:
    """``otbot daemon --json ARGS`` as a child process with its socket at ``socket`` and its log in
    ``log`` (a file path). ``request(cmd, **args)`` sends one command; ``terminate()`` sends SIGTERM
    and returns (exit code, the JSON summary it printed)."""

    def __init__(self, args: list[str], socket: Path, log: Path, env: dict | None = None, ready_timeout: float = 60.0,
                 prefix: list[str] | None = None):
        self.socket = Path(socket)
        self.log_path = Path(log)
        self._log = open(self.log_path, "w")
        self.proc = subprocess.Popen([*_cli(prefix), "daemon", "--socket", str(self.socket), "--json", *args],
                                     stdout=subprocess.PIPE, stderr=self._log, text=True,
                                     env={**os.environ, **(env or {})})
        self.wait_ready(ready_timeout)

    def wait_ready(self, timeout: float) -> dict:
        end = time.monotonic() + timeout
        while True:
            if self.proc.poll() is not None:
                raise RuntimeError(f"the daemon exited with {self.proc.returncode}: {self.log()[-2000:]}")
            try:
                st = self.request("status", timeout=2.0)
                if st["mode"] != "starting":
                    return st
            except (DaemonUnreachable, ControlError):
                pass
            if time.monotonic() > end:
                self.kill()
                raise RuntimeError(f"the daemon did not become ready within {timeout:g} s: {self.log()[-2000:]}")
            time.sleep(0.1)

    def request(self, cmd: str, timeout: float = 10.0, **args):
        with ControlClient(self.socket, timeout=timeout) as c:
            return c.request(cmd, args or None)

    def log(self) -> str:
        self._log.flush()
        return self.log_path.read_text()

    def terminate(self, timeout: float = 30.0, sig: int = signal.SIGTERM) -> tuple[int, dict | None]:
        self.proc.send_signal(sig)
        try:
            out, _ = self.proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.kill()
            raise
        self._log.close()
        try:
            summary = json.loads(out.strip().splitlines()[-1]) if out.strip() else None
        except ValueError:
            summary = None
        return self.proc.returncode, summary

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(timeout=10)
        if not self._log.closed:
            self._log.close()

    @property
    def pid(self) -> int:
        return self.proc.pid
