"""Fault injection into the simulated robot, for tests and commissioning drills.

``--inject KIND@SECONDS[:DEVICE]`` (``otbot run --bus sim``, ``otbot plant``): at the first SYNC
whose plant time (s since all drives were enabled) reaches SECONDS, the plant itself does KIND, so
the injection does not depend on which loop drives the robot:

=============  ================================================================================
drive-silent   the drive (default ``left_wheel``) drops off the bus: sends nothing, hears nothing
emcy           the drive sends an EMCY (0x4310, excess drive temperature) and keeps running
fault-bit      the drive goes to FAULT (0x603F = 0x2310, over-current) without sending an EMCY
imu-loss       the IMU's serial line is cut (its pseudo-terminal closes)
imu-error      the IMU sends ``$VNERR,12`` (insufficient baud rate) while streaming
bus-off        the simulated bus stops carrying frames, both ways
plant-kill     the plant process kills itself with SIGKILL (the plant must be its own process)
=============  ================================================================================

``reaction`` summarizes what followed, judged from the simulated drives' own state.
"""
from __future__ import annotations

import math
import os
import signal
import time
from dataclasses import dataclass

KINDS = ("drive-silent", "emcy", "fault-bit", "imu-loss", "imu-error", "bus-off", "plant-kill")
DRIVES = ("right_wheel", "left_wheel", "pivot")
DEFAULT_DEVICE = "left_wheel"
EMCY_CODE = 0x4310  # excess drive temperature: a warning, the drive keeps running
FAULT_CODE = 0x2310  # continuous over-current
VNERR_CODE = 12  # insufficient baud rate


@dataclass(frozen=True)
class Injection:
    """``kind`` at plant time ``at`` (s) on ``device`` (the drive, for the drive kinds)."""

    kind: str
    at: float
    device: str = DEFAULT_DEVICE

    @classmethod
    def parse(cls, text: str) -> "Injection":
        """'KIND@SECONDS[:DEVICE]'; ValueError with a one-line reason."""
        head, _, device = str(text).partition(":")
        kind, at_sign, when = head.partition("@")
        if not at_sign:
            raise ValueError(f"--inject must be KIND@SECONDS (KIND one of {', '.join(KINDS)}), got {text!r}")
        if kind not in KINDS:
            raise ValueError(f"--inject: unknown fault kind {kind!r} (one of {', '.join(KINDS)})")
        try:
            at = float(when)
        except ValueError:
            raise ValueError(f"--inject: {when!r} is not a time in seconds") from None
        if not (math.isfinite(at) and at >= 0):
            raise ValueError(f"--inject: the time must be a finite number of seconds >= 0, got {when!r}")
        device = device or DEFAULT_DEVICE
        if device not in DRIVES:
            raise ValueError(f"--inject: device must be one of {', '.join(DRIVES)}, got {device!r}")
        return cls(kind, at, device)

    def __str__(self) -> str:
        return f"{self.kind}@{self.at:g}" + (f":{self.device}" if self.device != DEFAULT_DEVICE else "")


class Injector:
    """Fires ``injection`` from inside the plant's SYNC handler (``on_sync``); ``fired_t`` is the
    plant time it fired at (None before), ``fired_wall`` the host monotonic time."""

    def __init__(self, injection: Injection, own_process: bool = False):
        self.injection = injection
        self.own_process = own_process
        self.fired_t: float | None = None
        self.fired_wall: float | None = None

    def check(self, plant) -> None:
        """Refuse, before the run, an injection this plant cannot do (ValueError)."""
        kind = self.injection.kind
        if kind.startswith("imu") and plant.imu is None:
            raise ValueError(f"--inject {kind}: the simulated robot has no IMU")
        if kind == "bus-off" and plant.bus_gate is None:
            raise ValueError("--inject bus-off: this plant's bus cannot be cut")
        if kind == "plant-kill" and not self.own_process:
            raise ValueError("--inject plant-kill needs the plant as its own process")

    def on_sync(self, plant) -> None:
        if self.fired_t is not None or not plant.started or plant.t < self.injection.at - 1e-9:
            return
        self.fired_t = plant.t
        self.fired_wall = time.monotonic()
        kind = self.injection.kind
        drive = next(d for d in plant.drives if d.name == self.injection.device)
        if kind == "drive-silent":
            drive.go_silent()
        elif kind == "emcy":
            drive.send_emcy(EMCY_CODE)
        elif kind == "fault-bit":
            drive.inject_fault(FAULT_CODE, emcy=False)
        elif kind == "imu-loss":
            plant.imu.disconnect()
        elif kind == "imu-error":
            plant.imu.report_error(VNERR_CODE)
        elif kind == "bus-off":
            plant.bus_gate.cut()
        elif kind == "plant-kill":
            os.kill(os.getpid(), signal.SIGKILL)

    def to_dict(self) -> dict:
        return {"kind": self.injection.kind, "device": self.injection.device, "at": self.injection.at,
                "t": self.fired_t, "wall": self.fired_wall}


def reaction(injection: Injection, injected_t: float | None, robot, plant_report: dict | None,
             period: float) -> dict:
    """The ``reaction`` block: when the fault was injected (plant time, s), detected by the master
    (``robot``: its first fault), and when every simulated drive's own state showed zero torque
    and not OPERATION ENABLED (null if never, or unknown because the plant is gone), with each
    drive's CiA 402 state after the run (``plant_report``: ``Plant.report()``).

    Times are plant time (s since the drives were enabled) on the SYNC grid both sides count; what
    happens between SYNCs (EMCY, watchdogs) adds the wall time since the last SYNC. Without a
    plant report, the master's own cycle count stands in for the plant's."""
    start = (plant_report or {}).get("start_sync")
    if start is not None:
        times = [(s - start) * period for s in robot.fault_syncs().values()]
    else:
        times = list(robot.fault_times().values())
    after = [t for t in times if injected_t is None or t >= injected_t - 1e-9]
    detected = min(after) if after else None
    drives = (plant_report or {}).get("drives") or []
    stops = {d["name"]: d["stopped_t"] for d in drives}
    all_stopped = max(stops.values()) if stops and all(v is not None for v in stops.values()) else None
    # The drives still on the bus (all but a silent one) are what the master's reaction must stop.
    healthy = {k: v for k, v in stops.items() if not (injection.kind == "drive-silent" and k == injection.device)}
    healthy_stopped = max(healthy.values()) if healthy and all(v is not None for v in healthy.values()) else None
    out = {"kind": injection.kind, "device": injection.device if injection.kind in
           ("drive-silent", "emcy", "fault-bit") else None,
           "injected_s": injected_t, "detected_s": detected, "all_stopped_s": all_stopped,
           "healthy_stopped_s": healthy_stopped,
           "drive_states_after": {d["name"]: d["state"] for d in drives} if drives else None,
           "drive_stopped_s": stops or None, "period": period}
    if detected is not None and injected_t is not None:
        out["detection_periods"] = (detected - injected_t) / period
    if detected is not None and healthy_stopped is not None:
        out["stop_periods"] = (healthy_stopped - detected) / period
    if plant_report is None:
        out["note"] = "the plant process is gone: the drives' state after the run is unknown"
    return out
