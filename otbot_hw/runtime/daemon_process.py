"""``otbot daemon`` (and the ``otbot plant`` it drives) as child processes: for the end-to-end tests,
``benchmarks/daemon.py`` and bench scripts that need a daemon they can signal or kill.

``config_copy(folder)`` copies a hardware configuration with its object dictionaries and text
replaced (the tests' one set-up, ``tests/conftest.py``); ``local_config(folder)`` writes a copy of a
hardware configuration that this user may command (``daemon.socket.allowed_users``), with the object
dictionaries beside it and no slcan settle delay; ``DaemonProcess`` starts ``otbot daemon``, waits
until it answers ``status`` and talks to it like ``otbot ctl``; ``plant_bus_args`` puts it on a
``sim.plant_process.PlantProcess``; ``realtime_priority`` gives a process SCHED_FIFO, as the unit's
CPUSchedulingPolicy=fifo would.
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
from otbot_hw.runtime.control_client import ControlClient, ControlError, DaemonUnreachable


def config_copy(folder: Path, replace: dict[str, str] | None = None, source: Path | None = None) -> Path:
    """``folder/robot.yaml``: ``source`` (default config/robot.yaml) with each ``replace`` old -> new
    text substituted (each must occur: ValueError naming it), the EDS files beside ``source`` copied
    beside it (``folder`` is created). Returns the path."""
    source = Path(source) if source is not None else DEFAULT_ROBOT_FILE
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    text = source.read_text()
    for old, new in (replace or {}).items():
        if old not in text:
            raise ValueError(f"{source}: no {old!r} to replace")
        text = text.replace(old, new)
    for eds in source.parent.glob("*.eds"):
        shutil.copy(eds, folder / eds.name)
    out = folder / "robot.yaml"
    out.write_text(text)
    return out


def local_config(folder: Path, source: Path | None = None, replace: dict[str, str] | None = None) -> Path:
    """``folder/robot.yaml``: ``source`` (default config/robot.yaml) with this user allowed to command,
    the slcan adapter's settle delay off, and each ``replace`` old -> new text substituted (each must
    occur); the EDS files are copied beside it (``config_copy``). Returns the path."""
    source = Path(source) if source is not None else DEFAULT_ROBOT_FILE
    text = source.read_text()
    own = {m: f"allowed_users: [{os.getuid()}]" for m in re.findall(r"allowed_users: \[[^\]]*\]", text)}
    if "  options: {}" in text:
        own["  options: {}"] = "  options: {sleep_after_open: 0}"
    out = config_copy(folder, own, source)
    if replace:
        text = out.read_text()
        for old, new in replace.items():
            if old not in text:
                raise ValueError(f"{source}: no {old!r} to replace")
            text = text.replace(old, new)
        out.write_text(text)
    return out


def _cli() -> list[str]:
    return [sys.executable, "-m", "otbot_hw"]


def plant_bus_args(info: dict) -> list[str]:
    """``otbot daemon`` options that put it on a plant process (``sim.plant_process.PlantProcess.info``:
    slcan on a pty, the IMU on another), answering in lockstep (``otbot daemon --lockstep``)."""
    return ["--bus", "config", "--lockstep", "--interface", "slcan", "--channel", info["can_channel"],
            *(["--imu-port", info["imu_port"]] if info.get("imu_port") else ["--no-imu"])]


def realtime_priority(pid: int, priority: int = 50) -> int:
    """Put every thread of process ``pid`` under SCHED_FIFO ``priority`` (what the unit's
    CPUSchedulingPolicy=fifo does from the start); returns how many threads. Needs CAP_SYS_NICE."""
    tasks = [int(t) for t in os.listdir(f"/proc/{pid}/task")]
    for tid in tasks:
        os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
    return len(tasks)


class DaemonProcess:
    """``otbot daemon --json ARGS`` as a child process with its socket at ``socket`` and its log in
    ``log`` (a file path); the ``--record-dir`` folder in ARGS is created first (as systemd's
    ``StateDirectory=`` would). ``priority``: started under SCHED_FIFO at it, as the unit's
    CPUSchedulingPolicy=fifo starts it (needs CAP_SYS_NICE). ``request(cmd, **args)`` sends one
    command; ``terminate()`` sends SIGTERM and returns (exit code, the JSON summary it printed)."""

    def __init__(self, args: list[str], socket: Path, log: Path, env: dict | None = None, ready_timeout: float = 60.0,
                 priority: int | None = None):
        self.socket = Path(socket)
        self.log_path = Path(log)
        if "--record-dir" in args:  # the daemon never creates it (systemd's StateDirectory= would): this helper does
            Path(args[args.index("--record-dir") + 1]).mkdir(parents=True, exist_ok=True)
        self._log = open(self.log_path, "w")
        self.proc = subprocess.Popen([*_cli(), "daemon", "--socket", str(self.socket), "--json", *args],
                                     stdout=subprocess.PIPE, stderr=self._log, text=True,
                                     env={**os.environ, **(env or {})},
                                     preexec_fn=None if priority is None else lambda: os.sched_setscheduler(
                                         0, os.SCHED_FIFO, os.sched_param(priority)))
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
