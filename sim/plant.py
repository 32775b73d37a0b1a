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

Around it: ``sim.bus_robot`` (the master's side in this process: ``VirtualPlant`` on python-can's
``virtual`` interface, ``SimulatedBusRobot``, ``simulated_robot``), ``sim.plant_process`` (a plant in its
own process behind an slcan adapter emulated on a pseudo-terminal, or on socketcan: ``serve``,
``PlantProcess``).

The operator channel: what a person at the bench does to the robot (change the fixture, fix or
remove a load) is ``Plant.operator("fixture stand")`` in this process, and the same line on the
standard input of ``serve`` (``otbot plant``), which answers each with one JSON line
(``OPERATOR_HELP``; the bench procedure's ``--yes`` uses it on the simulated robot).
"""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field

import can
import canopen
import numpy as np

from drivers.config import RobotConfig
from drivers.robot import imu_due
from otbot_hw.params import OtbotParams, nominal, parse_load
from otbot_hw.sensors import NoiseModel
from otbot_hw.simulation.sensing import StepperSensors
from otbot_hw.simulation.simulator import ForceSchedule, make_stepper
from sim.canopen_slaves.drive import SimulatedDrive
from sim.canopen_slaves.encoder import SimulatedEncoder
from sim.injection import Injector

log = logging.getLogger(__name__)

#: the operator channel's commands (``Plant.operator``)
OPERATOR_COMMANDS = ("fixture", "load", "unload", "status")
OPERATOR_HELP = "fixture floor|stand|locked, load KG@X,Y[,I], unload, status"


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
        #: the state (12,) and pivot force (2,) N at the latest SYNC, set before its TPDOs go out and
        #: never changed after (``SimulatedBusRobot.truth``/``truth_force`` read them without the
        #: lock); None until a SYNC after a set-up
        self.sync_x: np.ndarray | None = None
        self.sync_f: np.ndarray | None = None
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
        self.sync_x = self.sync_f = None  # the robot was moved: the truth is the new stepper's until the next SYNC
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

    def _send_frames(self, frames: list) -> None:
        """Put this SYNC's TPDOs ((COB-ID, data), in order) on the bus: at once where the bus takes
        several frames in one call (``sim.bus_robot.SimVirtualBus.send_many``: the master's receive
        thread woken once, not per frame), else one ``send_message`` each."""
        send_many = getattr(self.network.bus, "send_many", None)
        if send_many is not None and frames:
            send_many([can.Message(arbitration_id=cob, data=data, is_extended_id=cob > 0x7FF) for cob, data in frames])
            return
        for cob, data in frames:
            self.network.send_message(cob, data)

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
        self.sync_x, self.sync_f = x, f
        if self.imu is not None and imu_due(sync_index, self.period, self.imu_rate):
            acc, gyro = self.imu_reading(x, u, f)
            self.imu.publish(self.mounting.T @ acc, self.mounting.T @ gyro)
        elif self.imu is not None and self.sensors.latency > 0:
            self.sensors.imu(self.t, u, f)  # keeps the history the IMU latency interpolates in
        pos, vel = self.sensors.joints(u)
        rate_noise = self.noise.enc_rate * self.rng.standard_normal(3) if self.noise.enc_rate else np.zeros(3)
        angle_noise = self.noise.enc_angle * self.rng.standard_normal(3) if self.noise.enc_angle else np.zeros(3)
        frames: list = []
        for j, d in enumerate(self.drives):
            d.sample(pos[j] + angle_noise[j], vel[j] + rate_noise[j])
            d.send_tpdos(frames)
        if self.encoder is not None:
            self.encoder.sample(pos[2] + angle_noise[2])
            self.encoder.send_tpdos(frames)
        self._send_frames(frames)
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
