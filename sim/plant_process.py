"""The simulated plant in its own process (``otbot plant``): ``serve`` runs a ``sim.plant.Plant`` behind an
slcan adapter emulated on a pseudo-terminal (or on socketcan) and answers ``report``, operator, ``flood``
and ``restart`` lines on its standard input; ``PlantProcess`` starts one as a child process and gives the
master's lockstep robot for it; ``flood_frames`` / ``send_flood``: random frames on the devices' COB-IDs.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time

import can
import canopen
import numpy as np

from drivers.config import LOCKSTEP_SDO_TIMEOUT, LOCKSTEP_TIMEOUT, RobotConfig
from drivers.robot import STANDARD_FRAMES_ONLY
from otbot_hw.sensors import NoiseModel
from sim.injection import Injection, Injector
from sim.lockstep import LockstepCanopenRobot
from sim.plant import OPERATOR_COMMANDS, OPERATOR_HELP, Plant


def serve(config: RobotConfig, transport: str = "slcan", channel: str | None = None, with_imu: bool = True,
          out=None, inject: Injection | None = None, commands=None, **plant_kwargs) -> None:
    """Run a plant in this process until its command input (default stdin) closes: ``transport``
    "slcan" (adapter emulated on a new pseudo-terminal) or "socketcan" (``channel``, default
    vcan0). Prints one JSON line with ``can_interface``, ``can_channel`` and ``imu_port`` for the
    master; then answers each input line ``report`` with one JSON line (``Plant.report()``).
    ``inject``: a fault the plant injects at its plant time (``plant-kill`` kills this process)."""
    out = out or sys.stdout
    commands = commands if commands is not None else sys.stdin
    if transport == "slcan":
        from sim.slcan_adapter import SlcanAdapterBus

        bus = SlcanAdapterBus()
        info = {"can_interface": "slcan", "can_channel": bus.port}
    elif transport == "socketcan":
        bus = can.Bus(interface="socketcan", channel=channel or "vcan0")
        info = {"can_interface": "socketcan", "can_channel": channel or "vcan0"}
    else:
        raise ValueError(f"unknown transport {transport!r} (slcan, socketcan)")
    gate = bus if hasattr(bus, "cut") else None
    network = canopen.Network(bus)
    network.NOTIFIER_CYCLE = 0.1
    network.connect()
    bus.set_filters(STANDARD_FRAMES_ONLY)
    info["pid"] = os.getpid()
    imu = None

    def new_plant(injection):
        """A fresh plant (new slaves, robot at rest, IMU on a new pty when the last one was cut)."""
        nonlocal imu
        if with_imu and config.imu is not None and (imu is None or imu.closed):
            from sim.imu import SimulatedIMU

            imu = SimulatedIMU(output=config.imu.output, rate_hz=int(config.imu.rate_hz),
                               mounting=config.imu.mounting)
        info["imu_port"] = imu.port if imu is not None else None
        if gate is not None:
            gate.is_cut = False
        injector = Injector(injection, own_process=True) if injection is not None else None
        p = Plant(network, config, imu=imu, injector=injector, bus_gate=gate, **plant_kwargs)
        p.power_on()
        return p

    plant = new_plant(inject)
    out.write(json.dumps(info) + "\n")
    out.flush()
    try:
        for line in commands:  # until the parent closes our input
            words = line.split()
            if not words:
                continue
            if words == ["report"]:
                reply = plant.report()
            elif words[0] in OPERATOR_COMMANDS:
                reply = plant.operator(line)
            elif words[0] == "flood":
                reply = flood_reply(bus, config, words)
            elif words[:1] == ["restart"] and len(words) <= 2:
                plant.detach()
                try:
                    plant = new_plant(Injection.parse(words[1]) if len(words) == 2 else None)
                    reply = dict(info)
                except ValueError as exc:
                    plant = new_plant(None)
                    reply = {"error": str(exc), **info}
            else:
                reply = {"error": f"unknown command {line.strip()!r} (report, flood N SEED, restart [KIND@S], {OPERATOR_HELP})"}
            out.write(json.dumps(reply) + "\n")
            out.flush()
    except KeyboardInterrupt:
        pass
    finally:
        plant.stop()
        network.disconnect()
        if imu is not None and hasattr(imu, "close"):
            imu.close()


#: most frames one ``flood`` line sends
MAX_FLOOD = 100_000


def flood_reply(bus, config: RobotConfig, words: list[str]):
    """The reply to a stdin line ``flood N SEED`` (split into ``words``): the frames sent, or an ``error``
    naming what is wrong (a bad line never ends the plant)."""
    usage = f"flood N SEED: N random frames (0..{MAX_FLOOD}) from the integer seed SEED >= 0"
    if len(words) != 3:
        return {"error": f"{' '.join(words)[:80]!r}: {usage}"}
    try:
        n, seed = int(words[1]), int(words[2])
    except ValueError:
        return {"error": f"{' '.join(words)[:80]!r}: N and SEED must be integers ({usage})"}
    if not 0 <= n <= MAX_FLOOD or seed < 0:
        return {"error": f"{' '.join(words)[:80]!r}: {usage}"}
    return send_flood(bus, flood_frames(config, n, seed))


def device_cob_ids(config: RobotConfig) -> list[int]:
    """The COB-IDs of every CANopen device of ``config`` (CiA 301 predefined connection set):
    EMCY, four TPDOs and RPDOs, SDO both ways, heartbeat."""
    out = []
    for n in config.node_ids():
        out += [0x80 + n, *(0x180 + 0x100 * k + n for k in range(4)), *(0x200 + 0x100 * k + n for k in range(4)),
                0x580 + n, 0x600 + n, 0x700 + n]
    return out


def flood_frames(config: RobotConfig, n: int, seed: int = 0) -> list[can.Message]:
    """``n`` random frames on the devices' COB-IDs: random length 0..8 and data, as a faulty or
    hostile node would send them."""
    rng = np.random.default_rng(seed)
    ids = device_cob_ids(config)
    out = []
    for _ in range(n):
        length = int(rng.integers(0, 9))
        out.append(can.Message(arbitration_id=int(rng.choice(ids)), is_extended_id=False,
                               data=bytes(rng.integers(0, 256, length, dtype=np.uint8))))
    return out


def send_flood(bus, frames) -> int:
    """Send ``frames`` on ``bus`` back to back; returns how many went out."""
    sent = 0
    for m in frames:
        try:
            bus.send(m)
            sent += 1
        except (can.CanError, OSError):
            pass
    return sent


class PlantProcess:
    """``otbot plant`` (slcan on a pty) as a child process: ``info`` (can_channel, imu_port, pid),
    ``report()`` (the plant's own ``Plant.report()``, None once the process is gone), ``kill()``.

    ``config`` is passed on by file (``config.path``) with its control rate; keyword arguments:
    fixture, noise (``NoiseModel``: paper or none), seed."""

    def __init__(self, config: RobotConfig, inject: Injection | None = None, with_imu: bool = True,
                 fixture: str = "floor", noise: NoiseModel | None = None, seed: int = 0, **unsupported):
        if unsupported:
            raise ValueError(f"a plant process cannot take {', '.join(sorted(unsupported))}")
        from otbot_hw.params import nominal

        noise_name = "paper" if noise is not None and noise.to_dict() == NoiseModel.paper().to_dict() else "none"
        if noise is not None and noise_name == "none" and noise.to_dict() != NoiseModel().to_dict():
            raise ValueError("a plant process simulates the paper's noise or none")
        args = [sys.executable, "-m", "otbot_hw", "plant", "--config", str(config.path),
                "--rate", repr(config.bus.control_rate), "--fixture", fixture, "--noise", noise_name,
                "--seed", str(seed)]
        if not with_imu:
            args.append("--no-imu")
        if inject is not None:
            args += ["--inject", f"{inject.kind}@{inject.at!r}:{inject.device}"]
        self.injection = inject
        self.period = config.bus.period
        self.params = nominal()
        self.truth = None
        self.after: dict | None = None
        self.proc = subprocess.Popen(args, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        line = self.proc.stdout.readline()
        try:
            self.info = json.loads(line)
        except ValueError:
            self.close()
            raise RuntimeError(f"the plant process did not start (exit code {self.proc.poll()})") from None
        self._lock = threading.Lock()

    def robot(self, config: RobotConfig, with_imu: bool = True, realtime: bool = False,
              lockstep_timeout: float = LOCKSTEP_TIMEOUT):
        """A ``CanopenRobot`` (not yet opened) on this plant's slcan port and IMU pty, in lockstep
        (``sim.lockstep``) unless ``realtime``."""
        from drivers.robot import open_imu

        cfg = config.replace_bus(interface="slcan", channel=self.info["can_channel"],
                                 options={**config.bus.options, "sleep_after_open": 0})
        imu = None
        if with_imu and config.imu is not None and self.info.get("imu_port"):
            imu = open_imu(config.imu, port=self.info["imu_port"])
        return LockstepCanopenRobot(cfg, imu=imu, imu_lockstep=not realtime, realtime=realtime,
                            lockstep_timeout=lockstep_timeout, sdo_timeout=LOCKSTEP_SDO_TIMEOUT)

    def restart(self, inject: Injection | None = None) -> dict:
        """Replace the plant in the process by a fresh one (new slaves, robot at rest) with the
        fault ``inject``; returns the new ``info`` (the IMU pty changes if the last one was cut)."""
        reply = self._ask("restart" + (f" {inject.kind}@{inject.at!r}:{inject.device}" if inject else ""))
        if not reply or "error" in reply:
            raise RuntimeError(f"plant restart failed: {reply}")
        self.info = reply
        self.injection = inject
        self.after = None
        return reply

    def flood(self, frames: int, seed: int = 0) -> int:
        """Make the plant's side of the bus send ``frames`` random frames on the devices' COB-IDs
        (``flood_frames``); returns how many it sent."""
        return int(self._ask(f"flood {int(frames)} {int(seed)}") or 0)

    @property
    def injected_t(self) -> float | None:
        """Plant time of the injection: for plant-kill the SYNC at which the plant kills itself."""
        if self.injection is None:
            return None
        if self.after is not None and self.after.get("injection") and self.after["injection"]["t"] is not None:
            return self.after["injection"]["t"]
        k = int(np.ceil(self.injection.at / self.period - 1e-9))
        return k * self.period

    def alive(self) -> bool:
        return self.proc.poll() is None

    def report(self, wait_stopped: bool = False, timeout: float = 2.0) -> dict | None:
        """The plant's ``report()``; with ``wait_stopped``, polled until every drive has stopped
        producing torque (at most ``timeout`` s). None once the process is gone."""
        end = time.monotonic() + timeout
        while True:
            rep = self._ask()
            if rep is None or not wait_stopped or time.monotonic() > end:
                return rep
            if all(d["stopped_t"] is not None for d in rep["drives"]):
                return rep
            time.sleep(0.01)

    def _ask(self, command: str = "report"):
        with self._lock:
            if not self.alive():
                return None
            try:
                self.proc.stdin.write(command + "\n")
                self.proc.stdin.flush()
                line = self.proc.stdout.readline()
            except (OSError, ValueError):
                return None
        try:
            return json.loads(line)
        except ValueError:
            return None

    def kill(self) -> None:
        if self.alive():
            self.proc.kill()
        self.proc.wait(timeout=10)

    def close(self) -> int | None:
        """Close its input (it exits) and wait; returns the exit code (negative: killed by a signal)."""
        try:
            self.proc.stdin.close()
        except OSError:
            pass
        try:
            return self.proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            return self.proc.wait(timeout=10)

    def __enter__(self) -> "PlantProcess":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
