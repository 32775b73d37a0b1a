"""Back ends behind the ``Robot`` seam, chosen by name (python-can's "interface by configuration" idea).

=============  ======================================================================================
name           robot
=============  ======================================================================================
``sim``        ``sim.direct.DirectSimRobot``: the model stepped in this process, no bus, lockstep
``bus sim``    ``sim.bus_robot.SimulatedBusRobot``: the CANopen drivers over python-can's virtual bus to
               the simulated drives/encoder/IMU (``sim.plant.Plant``) in this process, lockstep
``bus config`` ``drivers.robot.CanopenRobot`` on the configured bus (the real robot, or an
               ``otbot plant`` process), paced in real time with the drives' watchdogs as
               configured; ``lockstep``: ``sim.lockstep.LockstepCanopenRobot``
=============  ======================================================================================

``make_backend(name, config, options)`` builds one from the registry ``BACKENDS`` (the command line
picks by name, never by branching on it); each says what its recordings come from (``source()``,
built by ``otbot_hw.recording.source_metadata``).

The two simulated back ends take the robot to simulate (``OtbotParams`` or an ``ExtendedModel``
with effects), its start state and pivot forces per run, and know the ground truth. Only this
package and ``otbot_hw.cli`` import ``sim`` and ``drivers`` (``tests/test_layering.py``).
"""
from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass, field

from otbot_hw.motors import MotorLimits
from otbot_hw.recording import source_metadata
from otbot_hw.sensors import NoiseModel


def encoder_resolution(config) -> tuple[float, float, float]:
    """Counts per joint revolution of (phi_r, phi_l, phi_p) in a hardware configuration
    (``drivers.config.RobotConfig``): motor counts times gear for the wheels; the pivot from the
    CiA 406 encoder's 0x6001 (its EDS default) times its gear, or from the pivot drive."""
    wheels = [d.counts_per_rev * d.gear_ratio for d in config.drives]
    enc = config.pivot_encoder
    if enc.source == "encoder":
        import canopen

        od = canopen.import_od(str(enc.eds), enc.node_id)
        pivot = float(od[0x6001].default) * enc.gear_ratio
    else:
        pivot = wheels[2]
    return (wheels[0], wheels[1], pivot)


@dataclass
class DirectBackend:
    """``sim``: ``DirectSimRobot`` at ``rate`` Hz with ``noise``/``seed``, IMU at ``imu_rate`` Hz
    (None: no IMU), encoder resolution ``encoder_counts`` (counts per joint revolution) and
    ``rate_step`` (rad/s) (None: exact), motor ``limits`` (None: no clamp) and torque resolution ``torque_step`` N m (None: exact). ``ideal()``: exact sensors,
    no noise (model studies, the control benchmarks)."""

    rate: float = 1000.0
    noise: NoiseModel | None = None
    seed: int | None = 0
    imu_rate: float | None = 100.0
    encoder_counts: tuple | None = None
    rate_step: tuple | None = None
    limits: MotorLimits | None = None
    torque_step: float | None = None
    name: str = "sim"
    realtime: bool = False
    has_truth: bool = True
    simulated = True  # the robot is simulated (class constants, not fields)
    bus = False  # behind the CANopen drivers

    @classmethod
    def from_config(cls, config, rate: float, noise: NoiseModel | None = None, seed: int | None = 0,
                    with_imu: bool = True) -> "DirectBackend":
        """The direct back end with the sensors and drives of a hardware configuration: encoder
        resolution (angles from the drives' motor encoders and the pivot encoder, rates from the drives'
        0x606C unit), IMU rate, motor limits, the drives' torque resolution (one per-mille of rated torque)."""
        return cls(rate=rate, noise=noise, seed=seed,
                   imu_rate=float(config.imu.rate_hz) if (with_imu and config.imu is not None) else None,
                   encoder_counts=encoder_resolution(config),
                   rate_step=tuple(d.rad_s_per_velocity_unit for d in config.drives), limits=config.limits,
                   torque_step=min(d.joint_torque_per_permille for d in config.drives))

    @property
    def period(self) -> float:
        return 1.0 / self.rate

    @contextmanager
    def open(self, plant, x0=None, forces=None, fixture: str = "floor"):
        from sim.direct import DirectSimRobot

        robot = DirectSimRobot(plant, period=1.0 / self.rate, x0=x0, fixture=fixture, noise=self.noise,
                               seed=self.seed, imu_rate=self.imu_rate, encoder_counts=self.encoder_counts,
                               rate_step=self.rate_step, limits=self.limits, torque_step=self.torque_step, forces=forces)
        try:
            yield robot
        finally:
            robot.close()

    def describe(self) -> dict:
        return {"mode": self.name, "rate": self.rate, "imu_rate": self.imu_rate,
                "encoder_counts": list(self.encoder_counts) if self.encoder_counts else None,
                "torque_step": self.torque_step}


def source(backend) -> dict:
    """The metadata ``source`` of a back end's recordings (``otbot_hw.recording.source_metadata``)."""
    return source_metadata(simulated=backend.simulated, bus=backend.bus)


class _ConfiguredRate:
    """The control rate (Hz) and period (s) of the hardware configuration's bus."""

    @property
    def rate(self) -> float:
        return self.config.bus.control_rate

    @property
    def period(self) -> float:
        return self.config.bus.period


@dataclass
class BusSimBackend(_ConfiguredRate):
    """``bus sim``: the drivers over virtual CAN to the simulated plant in this process, at the
    configuration's control rate (``config.bus.control_rate``)."""

    config: object  # drivers.config.RobotConfig
    noise: NoiseModel | None = None
    seed: int | None = 0
    with_imu: bool = True
    inject: object = None  # sim.injection.Injection: a fault the plant injects at its time
    process: bool = False  # the plant as its own process over slcan (no ground truth then)
    name: str = "bus sim"
    realtime: bool = False
    has_truth: bool = True
    simulated = True
    bus = True
    plant: object = field(default=None, init=False, repr=False)  # the last opened plant (its report after close)

    def __post_init__(self):
        if self.process:
            self.has_truth = False

    @contextmanager
    def open(self, plant, x0=None, forces=None, fixture: str = "floor"):
        from sim.bus_robot import simulated_robot

        kw = {"params": plant, "x0": x0, "forces": forces, "fixture": fixture, "noise": self.noise or NoiseModel(),
              "seed": self.seed}
        if self.process:  # a plant process takes the nominal robot, its fixture, noise and seed only
            for key in ("params", "x0", "forces"):
                if kw[key] is not None:
                    raise ValueError(f"a simulated robot in its own process cannot take {key}")
                del kw[key]
        with simulated_robot(self.config, with_imu=self.with_imu, inject=self.inject, process=self.process,
                             **kw) as (robot, sim_plant):
            self.plant = sim_plant
            yield robot

    def describe(self) -> dict:
        b = self.config.bus
        return {"mode": self.name, "interface": "virtual", "rate": b.control_rate, "bitrate": b.bitrate}


@dataclass
class BusConfigBackend(_ConfiguredRate):
    """``bus config``: ``CanopenRobot`` on the configured bus and IMU port (``imu_port`` overrides
    it); ``lockstep``: the other end is a simulated plant (``sim.lockstep.LockstepCanopenRobot``:
    SYNCs back to back, each SYNC's TPDOs and IMU sample awaited, no period-based drive watchdogs)
    instead of a real robot paced in real time. Every run that is not lockstep is paced by the loop
    runner (the one clock, handed down to the driver) with the drives' watchdogs as the configuration
    says (0x1006, 0x1400:05 armed by default), each SYNC's TPDOs awaited within the period. ``paced``
    is that fact (``not lockstep``)."""

    config: object  # drivers.config.RobotConfig
    imu_port: str | None = None
    lockstep: bool = False
    with_imu: bool = True
    name: str = "bus config"
    has_truth: bool = False
    simulated = False  # the robot that is there (a plant process in lockstep included)
    bus = True

    @property
    def realtime(self) -> bool:
        return not self.lockstep

    @property
    def paced(self) -> bool:
        """Whether the loop paces the bus in real time (``not lockstep``); it arms nothing itself."""
        return not self.lockstep

    @contextmanager
    def open(self, plant=None, x0=None, forces=None, fixture: str = "floor"):
        from drivers.config import LOCKSTEP_SDO_TIMEOUT, LOCKSTEP_TIMEOUT
        from drivers.robot import CanopenRobot, open_imu
        from sim.lockstep import LockstepCanopenRobot

        if plant is not None or forces is not None:
            raise ValueError("the configured bus runs the robot that is there: no plant parameters or forces")
        config = self.config
        imu = open_imu(config.imu, port=self.imu_port) if (self.with_imu and config.imu is not None) else None
        if self.lockstep:  # lockstep is the simulated plant's property (sim.lockstep): it answers in its own time
            robot = LockstepCanopenRobot(config, imu=imu, lockstep_timeout=LOCKSTEP_TIMEOUT,
                                         sdo_timeout=LOCKSTEP_SDO_TIMEOUT)
        else:  # the real driver: the drives' watchdogs as configured, paced by the loop's clock
            robot = CanopenRobot(config, imu=imu)
        with robot:
            robot.open()
            yield robot

    def describe(self) -> dict:
        b = self.config.bus
        return {"mode": self.name, "interface": b.interface, "channel": b.channel, "rate": b.control_rate,
                "bitrate": b.bitrate, "lockstep": self.lockstep, "paced": self.paced}


@dataclass(frozen=True)
class BackendOptions:
    """What a command line chooses for any back end; each takes the part it uses. ``rate`` Hz (None:
    the configuration's control rate; the direct robot's default 1 kHz), ``noise``/``seed`` and
    ``with_imu`` (simulated sensors), ``imu_port`` and ``lockstep`` (the configured bus), ``inject``
    and ``process`` (the simulated bus: a fault to inject, the plant as its own process)."""

    rate: float | None = None
    noise: NoiseModel | None = None
    seed: int | None = 0
    with_imu: bool = True
    imu_port: str | None = None
    lockstep: bool = False
    inject: object = None
    process: bool = False


def _direct(config, o: BackendOptions) -> DirectBackend:
    return DirectBackend.from_config(config, o.rate or 1000.0, o.noise, o.seed, o.with_imu)


def _bus_sim(config, o: BackendOptions) -> BusSimBackend:
    return BusSimBackend(config, o.noise, o.seed, o.with_imu, inject=o.inject, process=o.process)


def _bus_config(config, o: BackendOptions) -> BusConfigBackend:
    return BusConfigBackend(config, o.imu_port, o.lockstep, o.with_imu)


#: The back ends by name: name -> factory(config, BackendOptions).
BACKENDS = {"sim": _direct, "bus sim": _bus_sim, "bus config": _bus_config}


def make_backend(name: str, config, options: BackendOptions | None = None):
    """The back end ``name`` (a key of ``BACKENDS``) for the hardware configuration ``config``
    (``drivers.config.RobotConfig``); ValueError for an unknown name."""
    try:
        factory = BACKENDS[name]
    except KeyError:
        raise ValueError(f"unknown back end {name!r} (known: {', '.join(BACKENDS)})") from None
    return factory(config, options or BackendOptions())
