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

Transports: ``VirtualPlant`` (python-can ``virtual`` interface, same process), ``serve``
(a plant in its own process behind an slcan adapter emulated on a pseudo-terminal, or on a
socketcan interface).

The operator channel: what a person at the bench does to the robot (change the fixture, fix or
remove a load) is ``Plant.operator("fixture stand")`` in this process, and the same line on the
standard input of ``serve`` (``otbot plant``), which answers each with one JSON line
(``OPERATOR_HELP``; the bench procedure's ``--yes`` uses it on the simulated robot).
"""
from __future__ import annotations

import json
import sys
import threading
import uuid
from contextlib import contextmanager
from dataclasses import dataclass, field

import can
import canopen
import numpy as np

from drivers.config import RobotConfig
from drivers.robot import STANDARD_FRAMES_ONLY, CanopenRobot, imu_due
from otbot_hw.params import OtbotParams, nominal
from otbot_hw.sensors import NoiseModel
from otbot_hw.simulation.sensing import StepperSensors
from otbot_hw.simulation.simulator import ForceSchedule, make_stepper
from sim.canopen_slaves import SimulatedDrive, SimulatedEncoder


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
                 position_offsets=(0, 0, 0), supported_modes: int | None = None):
        self.config = config
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
        self._warm_up()
        for n in self.nodes:
            n.reset_listeners.append(self._on_node_reset)
        network.subscribe(0x80, self._on_sync)

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
                    self._set_up(load=parse_load(args[0]))
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
        for n in self.nodes:
            n.stop()

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
            for n in self.nodes:
                n.latch()
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


OPERATOR_COMMANDS = ("fixture", "load", "unload", "status")
OPERATOR_HELP = "fixture floor|stand|locked, load KG@X,Y[,I], unload, status"


def parse_load(text: str) -> tuple[float, float, float, float]:
    """'KG@X,Y[,I]' -> (mass kg, x m, y m, own inertia kg m^2); ValueError naming what is wrong."""
    kg, sep, pos = text.partition("@")
    parts = pos.split(",")
    try:
        vals = [float(kg), *(float(v) for v in parts)]
    except ValueError:
        vals = []
    if not sep or len(parts) not in (2, 3) or len(vals) != len(parts) + 1 or not all(np.isfinite(vals)):
        raise ValueError(f"a load looks like KG@X,Y or KG@X,Y,I (finite numbers), got {text!r}")
    if vals[0] < 0 or (len(vals) == 4 and vals[3] < 0):
        raise ValueError(f"load mass and inertia must be >= 0, got {text!r}")
    return vals[0], vals[1], vals[2], vals[3] if len(vals) == 4 else 0.0


class VirtualPlant:
    """A ``Plant`` on python-can's ``virtual`` interface (channel ``config.bus.channel``), in-process.

    Use as a context manager; the master opens its own virtual bus on the same channel.
    """

    def __init__(self, config: RobotConfig, **plant_kwargs):
        self.bus = can.Bus(interface="virtual", channel=config.bus.channel)
        self.network = canopen.Network(self.bus)
        self.network.NOTIFIER_CYCLE = 0.1
        self.network.connect()
        self.bus.set_filters(STANDARD_FRAMES_ONLY)
        self.plant = Plant(self.network, config, **plant_kwargs)
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


class SimulatedBusRobot(CanopenRobot):
    """``CanopenRobot`` talking to a ``Plant`` in this process: everything goes over the bus as with a
    real robot; only ``truth()`` looks behind it, at the plant's state at the last read's SYNC."""

    def __init__(self, plant: Plant, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.plant = plant

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
def simulated_robot(config: RobotConfig, with_imu: bool = True, imu_pair=None, tpdo_timeout: float | None = 1.0,
                    heartbeat_consumer: float | None = 1.0, **plant_kwargs):
    """A ``CanopenRobot`` (opened: booted, configured, PDOs running) talking over python-can's
    ``virtual`` bus to a ``Plant`` in this process, with the simulated IMU on a pseudo-terminal.

    Yields (robot, plant). The virtual channel is made unique, so runs never hear each other.
    ``tpdo_timeout`` and ``heartbeat_consumer`` (s) replace the configured ones: the run is in
    lockstep, so nothing real-time is at stake and a busy machine must not trip the watchdogs;
    None keeps the configuration's values (fault tests).
    """
    from dataclasses import replace

    config = config.replace_bus(interface="virtual", channel=f"otbot-sim-{uuid.uuid4().hex[:12]}")
    if tpdo_timeout is not None:
        config = config.replace_bus(tpdo_timeout=max(tpdo_timeout, config.bus.tpdo_timeout))
    if heartbeat_consumer is not None:
        config = replace(config, drives=tuple(replace(d, heartbeat_consumer=max(heartbeat_consumer, d.heartbeat_consumer))
                                              for d in config.drives),
                         pivot_encoder=replace(config.pivot_encoder, heartbeat_consumer=max(
                             heartbeat_consumer, config.pivot_encoder.heartbeat_consumer)))
    pub = drv = None
    if with_imu and config.imu is not None:
        pub, drv = imu_pair if imu_pair is not None else open_sim_imu(config)
    vp = VirtualPlant(config, imu=pub, **plant_kwargs)
    robot = SimulatedBusRobot(vp.plant, config, bus=can.Bus(interface="virtual", channel=config.bus.channel), imu=drv,
                              imu_lockstep=True)
    try:
        robot.open()
        yield robot, vp.plant
    finally:
        robot.close()
        vp.close()
        if pub is not None and hasattr(pub, "close"):
            pub.close()


def serve(config: RobotConfig, transport: str = "slcan", channel: str | None = None, with_imu: bool = True,
          out=None, **plant_kwargs) -> None:
    """Run a plant in this process until stdin closes: ``transport`` "slcan" (adapter emulated on a
    new pseudo-terminal) or "socketcan" (``channel``, default vcan0). Prints one JSON line with
    ``can_interface``, ``can_channel`` and ``imu_port`` for the master."""
    out = out or sys.stdout
    if transport == "slcan":
        from sim.slcan_adapter import SlcanAdapterBus

        bus = SlcanAdapterBus()
        info = {"can_interface": "slcan", "can_channel": bus.port}
    elif transport == "socketcan":
        bus = can.Bus(interface="socketcan", channel=channel or "vcan0")
        info = {"can_interface": "socketcan", "can_channel": channel or "vcan0"}
    else:
        raise ValueError(f"unknown transport {transport!r} (slcan, socketcan)")
    imu = None
    if with_imu and config.imu is not None:
        from sim.imu import SimulatedIMU

        imu = SimulatedIMU(output=config.imu.output, rate_hz=int(config.imu.rate_hz), mounting=config.imu.mounting)
    info["imu_port"] = imu.port if imu is not None else None
    network = canopen.Network(bus)
    network.NOTIFIER_CYCLE = 0.1
    network.connect()
    bus.set_filters(STANDARD_FRAMES_ONLY)
    plant = Plant(network, config, imu=imu, **plant_kwargs)
    plant.power_on()
    out.write(json.dumps(info) + "\n")
    out.flush()
    try:
        for line in sys.stdin:  # operator commands, one per line, until the parent closes our stdin
            if line.strip():
                out.write(json.dumps(plant.operator(line)) + "\n")
                out.flush()
    except KeyboardInterrupt:
        pass
    finally:
        plant.stop()
        network.disconnect()
        if imu is not None and hasattr(imu, "close"):
            imu.close()


