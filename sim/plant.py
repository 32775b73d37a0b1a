"""The simulated Otbot behind a CAN bus: the dynamic model in lockstep with the SYNC.

``Plant`` puts three ``SimulatedDrive`` s and the ``SimulatedEncoder`` (CANopen slaves on
canopen's ``LocalNode``) on a ``canopen.Network`` and subscribes to SYNC. On every SYNC:

1. each slave applies the synchronous RPDOs received since the previous SYNC (controlword,
   target torque) and runs its CiA 402 state machine;
2. the joint torques u_k the drives now produce (zero unless OPERATION ENABLED) and the
   external pivot force f_k are taken;
3. the IMU sentence for the state x_k (with u_k, f_k) is published, noise from
   ``otbot_hw.sensors`` added, rotated into the sensor frame by the inverse mounting rotation;
4. the drives and the encoder sample x_k and send their TPDOs;
5. the model advances one control period, x_k+1 = Stepper.step(u_k, f_k) (zero-order hold).

The plant's clock starts (t = 0) at the first SYNC after all three drives reached OPERATION
ENABLED; before that the robot stands still at x0. The run is deterministic: it depends on the
SYNC count only, never on wall time, and runs as fast as the master sends SYNCs.

The drives' own watchdogs (master heartbeat, SYNC loss, RPDO deadline) run on wall time in a
thread of the plant (``check_watchdogs``); an ``Injector`` (``sim.injection``) fires its fault
from inside the SYNC handler, at plant time. ``report()`` gives each drive's CiA 402 state and
the bus time at which it stopped producing torque: plant time at SYNCs, plus the wall time elapsed
since the last SYNC for what happens between SYNCs (watchdogs, NMT).

Transports: ``VirtualPlant`` (python-can ``virtual`` interface, same process), ``serve``
(a plant in its own process behind an slcan adapter emulated on a pseudo-terminal, or on a
socketcan interface; ``PlantProcess`` starts one and asks it for its ``report()``).

The operator channel: what a person at the bench does to the robot (change the fixture, fix or
remove a load) is ``Plant.operator("fixture stand")`` in this process, and the same line on the
standard input of ``serve`` (``otbot plant``), which answers each with one JSON line
(``OPERATOR_HELP``; the bench procedure's ``--yes`` uses it on the simulated robot).
"""
from __future__ import annotations

import gc
import json
import os
import subprocess
import sys
import threading
import time
import uuid
from contextlib import contextmanager
from dataclasses import dataclass, field

import logging

import can
import canopen
import numpy as np

from drivers.config import LOCKSTEP_HEARTBEAT, LOCKSTEP_SDO_TIMEOUT, LOCKSTEP_TIMEOUT, RobotConfig
from drivers.robot import STANDARD_FRAMES_ONLY, CanopenRobot, imu_due
from otbot_hw.params import OtbotParams, nominal, parse_load
from otbot_hw.robot import SimulatedRobot
from otbot_hw.sensors import NoiseModel
from otbot_hw.simulation.sensing import StepperSensors
from otbot_hw.simulation.simulator import ForceSchedule, make_stepper
from sim.canopen_slaves import SimulatedDrive, SimulatedEncoder
from sim.lockstep import ImuLockstep, LockstepCanopenRobot
from sim.injection import Injection, Injector


log = logging.getLogger(__name__)


class GatedBus(can.BusABC):
    """A python-can bus that can be cut (``cut()``): from then on it carries no frame either way,
    as a CAN controller gone bus-off or a pulled connector."""

    def __init__(self, inner: can.BusABC):
        self.inner = inner
        self.is_cut = False
        super().__init__(channel=getattr(inner, "channel_info", "gated"))
        self.channel_info = f"gated {getattr(inner, 'channel_info', inner)}"

    def cut(self) -> None:
        self.is_cut = True

    def send(self, msg: can.Message, timeout=None) -> None:
        if not self.is_cut:
            self.inner.send(msg, timeout)

    def _recv_internal(self, timeout):
        msg = self.inner.recv(timeout)
        return (None if self.is_cut else msg), False

    def shutdown(self) -> None:
        super().shutdown()
        self.inner.shutdown()


@dataclass
class TruthLog:
    """Ground truth of the plant per started SYNC: t (s), x (12,), u (3,) N m, f (2,) N."""

    t: list = field(default_factory=list)
    x: list = field(default_factory=list)
    u: list = field(default_factory=list)
    f: list = field(default_factory=list)


class Plant:
    """The simulated robot on ``network`` (a connected ``canopen.Network``).

    ``params``: the robot to simulate, ``OtbotParams`` (the paper's model) or an ``ExtendedModel``
    (a parameter or diagnosed-model file with ``effects``: the extended model is stepped and its
    sensor effects appear in the encoder and IMU samples); default the nominal parameters.
    ``imu``: an object with ``publish(accel_sensor (3,), gyro_sensor (3,))`` (``sim.imu.SimulatedIMU``)
    or None; ``noise``: sensor noise (IMU accel/gyro sigma; joint angle and rate sigma added before
    the drives and the encoder quantize); ``position_offsets``: each drive's 0x6064 at phi = 0 (counts).
    """

    #: the load an operator fixed on the platform ({mass, x, y, inertia}), and the robot without it
    load: dict | None = None
    unloaded_model = None

    def __init__(self, network: canopen.Network, config: RobotConfig, params=None,
                 fixture: str = "floor", forces: ForceSchedule | None = None, x0: np.ndarray | None = None,
                 noise: NoiseModel | None = None, seed: int | None = 0, imu=None,
                 position_offsets=(0, 0, 0), supported_modes: int | None = None, injector: Injector | None = None,
                 bus_gate=None):
        self.config = config
        self.network = network
        self.model = params if params is not None else nominal()
        self.params: OtbotParams = getattr(self.model, "params", self.model)
        self.period = config.bus.period
        self.drives = [SimulatedDrive(network, dc, off, supported_modes)
                       for dc, off in zip(config.drives, position_offsets)]
        self.encoder = (SimulatedEncoder(network, config.pivot_encoder)
                        if config.pivot_encoder.source == "encoder" else None)
        self.nodes = [*self.drives, *([self.encoder] if self.encoder else [])]
        self.stepper = make_stepper(self.model, self.period, x0, fixture)
        self.sensors = StepperSensors(self.stepper, self.period)
        self.fixture = fixture
        self.forces = forces
        self.noise = noise or NoiseModel()
        self.rng = np.random.default_rng(seed)
        self.imu = imu
        self.mounting = config.imu.mounting if config.imu is not None else np.eye(3)
        self.imu_rate = float(config.imu.rate_hz) if config.imu is not None else 1.0 / self.period
        self.started = False
        self.k = 0
        self.syncs = 0
        self.malformed_sync = 0
        self.truth = TruthLog()
        self.lock = threading.Lock()
        self.bus_gate = bus_gate
        self.injector = injector
        self._sync_index = -1  # index of the last SYNC since the nodes' last reset (the master's boot)
        self._sync_wall = time.monotonic()
        self._in_sync = False
        self.start_sync: int | None = None  # index of the SYNC at which the plant time is 0
        self._warm_up()
        for n in self.nodes:
            n.reset_listeners.append(self._on_node_reset)
        for d in self.drives:
            d.clock = self.sync_stamp
        if injector is not None:
            injector.check(self)
        network.subscribe(0x80, self._on_sync)
        self._stop = threading.Event()
        self._watchdogs = threading.Thread(target=self._watch, name="drive-watchdogs", daemon=True)
        self._watchdogs.start()

    def sync_stamp(self) -> float:
        """The bus clock, in SYNCs: the index of the current SYNC inside the SYNC handler; between
        SYNCs, that of the last one plus the wall time elapsed since it, in periods. The master
        counts the same SYNCs from its boot (``CanopenRobot.fault_syncs``)."""
        if self._in_sync:
            return float(self._sync_index)
        return self._sync_index + (time.monotonic() - self._sync_wall) / self.period

    def to_time(self, stamp: float | None) -> float | None:
        """Plant time (s) of a ``sync_stamp`` (None before the plant started)."""
        if stamp is None or self.start_sync is None:
            return None
        return (stamp - self.start_sync) * self.period

    def _watch(self) -> None:
        """The drives' wall-clock watchdogs, checked every tenth of the shortest one (0.5..10 ms)."""
        while not self._stop.is_set():
            times = [t for d in self.drives for t in d.watchdog_times()]
            step = min(0.01, max(0.0005, min(times) / 10)) if times else 0.01
            if self._stop.wait(step):
                return
            now = time.monotonic()
            for d in self.drives:
                try:
                    d.check_watchdogs(now)
                except Exception:  # noqa: BLE001 - a watchdog must not take the plant down
                    log.exception("%s: watchdog check failed", d.name)

    def report(self) -> dict:
        """Each drive's own state: CiA 402 state, applied torque (per-mille), NMT state, when it
        stopped producing torque (bus time s and host monotonic s; None while it produces torque),
        the aborts its watchdogs triggered; plant time; the injection, if any."""
        drives = [{"name": d.name, "node": d.node_id, "state": d.state, "torque_permille": d.applied_permille(),
                   "nmt": d.node.nmt.state, "silent": d.silent,
                   "stopped_t": self.to_time(d.stopped_since[0]) if d.stopped_since else None,
                   "stopped_wall": d.stopped_since[1] if d.stopped_since else None,
                   "aborts": [[code, why, self.to_time(t)] for code, why, t in d.aborts]} for d in self.drives]
        return {"t": self.t, "syncs": self.syncs, "started": self.started, "start_sync": self.start_sync,
                "drives": drives, "injection": self.injector.to_dict() if self.injector is not None else None}

    @property
    def injected_t(self) -> float | None:
        """Plant time (s) at which the injector fired (None without one, or before it fired)."""
        return self.injector.fired_t if self.injector is not None else None

    def all_stopped(self) -> bool:
        return all(d.stopped_since is not None for d in self.drives)

    def wait_all_stopped(self, timeout: float) -> bool:
        """Wait up to ``timeout`` s (wall) for every drive to stop producing torque by itself."""
        end = time.monotonic() + timeout
        while not self.all_stopped():
            if time.monotonic() > end:
                return False
            time.sleep(0.002)
        return True

    def longest_watchdog(self) -> float:
        """The longest watchdog time (s) the master configured into any drive (0 if none)."""
        return max([t for d in self.drives for t in d.watchdog_times()] or [0.0])

    def _on_node_reset(self, node, application: bool) -> None:
        """A master (re)starting resets the nodes before its first SYNC: count SYNCs from there, so
        the IMU's output ticks line up with the master's (``drivers.robot.imu_due``)."""
        with self.lock:
            self.syncs = 0

    def _warm_up(self) -> None:
        """Compile (or load from numba's cache) the model functions now, not inside the first SYNC."""
        st = make_stepper(self.model, self.period, self.stepper.x, self.fixture)
        probe = StepperSensors(st, self.period)
        probe.imu(0.0, np.zeros(3), np.zeros(2))
        probe.joints(np.zeros(3))
        st.step(np.zeros(3))

    @property
    def t(self) -> float:
        """Plant time, s (0 at the first SYNC with all drives enabled)."""
        return self.k * self.period

    # -- the operator channel: what a person at the bench does to the robot --------------------------
    def operator(self, command: str) -> dict:
        """Do what an operator at the bench would: ``command`` is one line (``OPERATOR_COMMANDS``):

        * ``fixture floor|stand|locked``: put the robot on the floor, on the stand (chassis held,
          wheels free) or lock its wheels;
        * ``load KG@X,Y[,I]``: fix a load of KG kg at (X, Y) m in the platform frame (own inertia
          I kg m^2) on the platform (replacing any load); ``unload``: take it off;
        * ``status``: report the fixture, the load and the robot's parameters.

        A person handles the robot at rest: every change stops it (joint rates zero; the joint
        angles, what the encoders count, are kept). Returns a JSON-ready reply (``error`` for a
        command it does not know or cannot do); thread-safe against the SYNC handler."""
        words = command.split()
        if not words:
            return {"error": "empty operator command (" + OPERATOR_HELP + ")"}
        verb, args = words[0], words[1:]
        with self.lock:
            try:
                if verb == "fixture" and len(args) == 1:
                    self._set_up(fixture=args[0])
                elif verb == "load" and len(args) == 1:
                    self._set_up(load=parse_load(args[0]))  # ValueError says what is wrong
                elif verb == "unload" and not args:
                    self._set_up(load=None)
                elif verb != "status" or args:
                    return {"error": f"unknown operator command {command.strip()!r} ({OPERATOR_HELP})"}
            except ValueError as exc:
                return {"error": f"{command.strip()}: {exc}"}
            return {"fixture": self.fixture, "load": self.load, "params": self.params.to_dict()}

    def _set_up(self, fixture: str | None = None, load="keep") -> None:
        """Rebuild the stepper for a new fixture and/or load (None: no load), the robot at rest."""
        from otbot_hw.model.fixtures import FIXTURES
        from otbot_hw.params import ParameterError

        fixture = self.fixture if fixture is None else fixture
        if fixture not in FIXTURES:
            raise ValueError(f"unknown fixture {fixture!r} (known: {', '.join(FIXTURES)})")
        if self.unloaded_model is None:
            self.unloaded_model = self.model
        if load != "keep":
            base = self.unloaded_model
            try:
                params = getattr(base, "params", base).with_load(*load) if load else getattr(base, "params", base)
            except ParameterError as exc:
                raise ValueError(str(exc)) from None
            self.model = type(base)(params, base.eff) if hasattr(base, "eff") else params
            self.params = params
            self.load = dict(zip(("mass", "x", "y", "inertia"), load)) if load else None
        old = self.stepper
        x0 = old.x.copy()
        x0[6:] = 0.0  # handled by a person: at rest
        st = make_stepper(self.model, self.period, x0, fixture)
        for attr in ("slip", "tau"):  # the extended model's wheel slip (encoder offset) and drive torque
            if hasattr(old, attr) and hasattr(st, attr):
                setattr(st, attr, getattr(old, attr) * (0.0 if attr == "tau" else 1.0))
        st.t = old.t
        self.stepper = st
        self.sensors = StepperSensors(st, self.period)
        self.fixture = fixture

    def power_on(self) -> None:
        """Boot every slave (boot-up message, PRE-OPERATIONAL, heartbeat)."""
        for n in self.nodes:
            n.boot()

    def stop(self) -> None:
        self._stop.set()
        for n in self.nodes:
            n.stop()

    def detach(self) -> None:
        """Leave the network for good (``serve``'s restart puts a new plant in its place)."""
        self.stop()
        try:
            self.network.unsubscribe(0x80, self._on_sync)
        except (KeyError, ValueError):
            pass
        for n in self.nodes:
            n.detach()

    def imu_reading(self, x: np.ndarray, u: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """IMU specific force (3,) m/s^2 and rate (3,) rad/s in B'' (the extended model's IMU frame) with
        noise, at the current state x of the stepper under u, f (``otbot_hw.simulation.sensing``)."""
        acc, gyro = self.sensors.imu(self.t, u, f)
        acc = acc + self.noise.accel * self.rng.standard_normal(3)
        gyro = gyro + self.noise.gyro * self.rng.standard_normal(3)
        return acc, gyro

    def _on_sync(self, can_id: int, data: bytes, timestamp: float) -> None:
        if len(data) > 1:
            self.malformed_sync += 1
            return
        with self.lock:
            sync_index = self.syncs
            self.syncs += 1
            self._sync_index = sync_index
            self._sync_wall = time.monotonic()
            self._in_sync = True
            try:
                self._step(sync_index)
            finally:
                self._in_sync = False

    def _step(self, sync_index: int) -> None:
        """One SYNC (lock held): latch, inject, torques, IMU, TPDOs, model step."""
        for n in self.nodes:
            n.latch()
        if self.injector is not None:
            self.injector.on_sync(self)
        u = np.array([d.joint_torque() for d in self.drives])
        x = self.stepper.x.copy()
        f = self.forces.at(self.t + 1e-9) if (self.forces is not None and self.started) else np.zeros(2)
        if self.imu is not None and imu_due(sync_index, self.period, self.imu_rate):
            acc, gyro = self.imu_reading(x, u, f)
            self.imu.publish(self.mounting.T @ acc, self.mounting.T @ gyro)
        elif self.imu is not None and self.sensors.latency > 0:
            self.sensors.imu(self.t, u, f)  # keeps the history the IMU latency interpolates in
        pos, vel = self.sensors.joints(u)
        rate_noise = self.noise.enc_rate * self.rng.standard_normal(3) if self.noise.enc_rate else np.zeros(3)
        angle_noise = self.noise.enc_angle * self.rng.standard_normal(3) if self.noise.enc_angle else np.zeros(3)
        for j, d in enumerate(self.drives):
            d.sample(pos[j] + angle_noise[j], vel[j] + rate_noise[j])
            d.send_tpdos()
        if self.encoder is not None:
            self.encoder.sample(pos[2] + angle_noise[2])
            self.encoder.send_tpdos()
        if self.started:
            self.truth.t.append(self.t)
            self.truth.x.append(x)
            self.truth.u.append(u)
            self.truth.f.append(f)
            self.stepper.step(u, f)
            self.k += 1
        elif all(d.state == "OPERATION ENABLED" for d in self.drives):
            self.started = True
            self.start_sync = sync_index + 1


OPERATOR_COMMANDS = ("fixture", "load", "unload", "status")
OPERATOR_HELP = "fixture floor|stand|locked, load KG@X,Y[,I], unload, status"


class VirtualPlant:
    """A ``Plant`` on python-can's ``virtual`` interface (channel ``config.bus.channel``), in-process,
    behind a ``GatedBus`` (the ``bus-off`` injection cuts it).

    Use as a context manager; the master opens its own virtual bus on the same channel.
    """

    def __init__(self, config: RobotConfig, **plant_kwargs):
        self.bus = GatedBus(can.Bus(interface="virtual", channel=config.bus.channel))
        self.network = canopen.Network(self.bus)
        self.network.NOTIFIER_CYCLE = 0.1
        self.network.connect()
        self.bus.set_filters(STANDARD_FRAMES_ONLY)
        try:
            self.plant = Plant(self.network, config, bus_gate=self.bus, **plant_kwargs)
        except Exception:
            self.network.disconnect()
            raise
        self.plant.power_on()

    def close(self) -> None:
        self.plant.stop()
        self.network.disconnect()

    def __enter__(self) -> Plant:
        return self.plant

    def __exit__(self, *exc) -> None:
        self.close()


def open_sim_imu(config: RobotConfig):
    """(publisher, driver): the simulated IMU on a pseudo-terminal and the VectorNav driver that
    opens it by path and configures it with register writes, as it would a real sensor."""
    from drivers.robot import open_imu
    from sim.imu import SimulatedIMU

    pub = SimulatedIMU(output=config.imu.output, rate_hz=int(config.imu.rate_hz), mounting=config.imu.mounting)
    try:
        drv = open_imu(config.imu, port=pub.port, configure=True)
    except Exception:
        pub.close()
        raise
    return pub, drv


class SimulatedBusRobot(ImuLockstep, CanopenRobot, SimulatedRobot):
    """``CanopenRobot`` talking to a ``Plant`` in this process, in lockstep with its IMU unless
    ``imu_lockstep=False`` (``sim.lockstep``): everything goes over the bus as with a real robot; only
    the ``SimulatedRobot`` part looks behind it: ``truth()`` (the plant's state at the last read's
    SYNC), the pivot force, the parameters simulated now and the plant's operator channel."""

    has_operator = True

    def __init__(self, plant: Plant, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.plant = plant

    @property
    def simulated_params(self):
        return self.plant.params

    def operator(self, command: str) -> dict:
        return self.plant.operator(command)

    def truth(self) -> np.ndarray | None:
        with self.plant.lock:  # the SYNC handler holds it until the state of that SYNC is logged
            if self.plant.truth.x:
                return np.array(self.plant.truth.x[-1])
            return self.plant.stepper.x.copy()

    def truth_force(self) -> np.ndarray:
        """External pivot force (2,) N, ground frame, held from the last read's SYNC on."""
        with self.plant.lock:
            return np.array(self.plant.truth.f[-1], dtype=float) if self.plant.truth.f else np.zeros(2)




@contextmanager
def simulated_robot(config: RobotConfig, with_imu: bool = True, imu_pair=None, tpdo_timeout: float | None = None,
                    heartbeat_consumer: float | None = LOCKSTEP_HEARTBEAT, inject: Injection | str | None = None,
                    process: bool = False, realtime: bool = False, **plant_kwargs):
    """A ``CanopenRobot`` (opened: booted, configured, PDOs running) talking over python-can's
    ``virtual`` bus to a ``Plant`` in this process, with the simulated IMU on a pseudo-terminal;
    with ``process``, to a plant in its own process (``otbot plant``) over slcan on a pty.

    Yields (robot, plant) (``plant``: the ``Plant``, or the ``PlantProcess``). The virtual channel
    is made unique, so runs never hear each other. ``tpdo_timeout``: the lockstep wait for the
    TPDOs of a SYNC (s, default ``LOCKSTEP_TIMEOUT``); ``heartbeat_consumer`` (s): the heartbeat
    consumer times of both sides are at least this (None keeps the configuration's: fault tests);
    ``inject``: a fault for the plant to inject (``sim.injection``); ``realtime``: pace SYNCs at
    the control period with the configured watchdogs (no relaxing). On exit, after ``robot.close()``,
    with an injection the drives are given their longest watchdog time to stop by themselves, and
    ``plant.after`` holds the plant's ``report()``.
    """
    if isinstance(inject, str):
        inject = Injection.parse(inject)
    if heartbeat_consumer is not None and not realtime:
        config = config.relaxed(heartbeat_consumer)
    lockstep_timeout = tpdo_timeout if tpdo_timeout is not None else LOCKSTEP_TIMEOUT
    if process:
        with PlantProcess(config, inject=inject, with_imu=with_imu, **plant_kwargs) as pp:
            robot = pp.robot(config, with_imu=with_imu, realtime=realtime, lockstep_timeout=lockstep_timeout)
            try:
                robot.open()
                yield robot, pp
            finally:
                robot.close()
                pp.after = pp.report(wait_stopped=inject is not None)
        return
    config = config.replace_bus(interface="virtual", channel=f"otbot-sim-{uuid.uuid4().hex[:12]}")
    pub = drv = None
    if with_imu and config.imu is not None:
        pub, drv = imu_pair if imu_pair is not None else open_sim_imu(config)
    injector = Injector(inject) if inject is not None else None
    try:
        vp = VirtualPlant(config, imu=pub, injector=injector, **plant_kwargs)
    except Exception:
        if pub is not None and imu_pair is None:
            pub.close()
            drv.close()
        raise
    master_bus = can.Bus(interface="virtual", channel=config.bus.channel)
    try:
        robot = SimulatedBusRobot(vp.plant, config, bus=master_bus, imu=drv, imu_lockstep=not realtime,
                                  realtime=realtime, lockstep_timeout=lockstep_timeout,
                                  sdo_timeout=LOCKSTEP_SDO_TIMEOUT)
    except Exception:
        master_bus.shutdown()
        vp.close()
        if pub is not None:
            pub.close()
            drv.close()
        raise
    if realtime:  # wall-clock watchdogs on both sides of one process: no full collection of a large
        gc.collect()  # heap in the middle of the run (as otbot plant and the daemon do; 20-185 ms
        gc.freeze()   # pauses measured without, longer than a heartbeat consumer's slack)
    try:
        robot.open()
        yield robot, vp.plant
    finally:
        robot.close()
        if injector is not None and injector.fired_t is not None:
            vp.plant.wait_all_stopped(vp.plant.longest_watchdog() + 0.2)
        vp.plant.after = vp.plant.report()
        vp.close()
        if pub is not None and hasattr(pub, "close"):
            pub.close()
        if realtime:
            gc.unfreeze()


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
