"""The ``Robot`` interface: the one seam every loop talks through (python-can's ``BusABC`` idea).

Back ends: ``drivers.robot.CanopenRobot`` (the real robot, or the simulated plant behind virtual
CAN / slcan) and ``sim.direct.DirectSimRobot`` (the model stepped in-process with sensor noise, no
bus). The loop runner (``otbot_hw.runtime``) knows only this module.

The common work is done here once (python-can's ``BusABC``: public ``send`` checks, the interface's
``_send`` does the rest): ``Robot.write`` checks the torques, clamps them to ``max_torque`` and builds
the ``Command``; a back end implements ``_apply`` (take the clamped torques, return what the drives
will produce). What only a simulated robot can do (the ground truth, its plant, an operator at the
bench) is declared by the ``SimulatedRobot`` sub-interface: callers test ``isinstance``, never probe
attributes.

One control cycle::

    robot.write(u)        # torques (N m); applied from the next sample instant on
    s = robot.read()      # one synchronous sample of every sensor

so the torque written before a ``read()`` is held from that sample to the next one, and the
snapshot returned by that ``read()`` holds the joints at the same instant: sample k of a run is
(u_k held on [t_k, t_k+1), sensors at t_k), the recording convention of ``otbot_hw.recording``.
A controller that computes u_k from the sensors at t_k therefore acts one period later, as on
the real bus.
"""
from __future__ import annotations

import abc
import math
import time
from dataclasses import dataclass, field

import numpy as np

#: ``Command.saturated`` when no limit cut the request (shared, read-only: most cycles)
_NO_SATURATION = np.zeros(3, bool)
_NO_SATURATION.flags.writeable = False
_NOT_SATURATED = [False, False, False]

#: Kinds of fault, by where they were detected.
FAULT_KINDS = ("emcy", "statusword", "heartbeat", "stale", "nmt", "boot", "config", "imu", "bus")


@dataclass(frozen=True)
class Fault:
    """One fault: ``device`` (joint or encoder name), CANopen ``node`` ID (None for the IMU),
    ``kind`` (one of ``FAULT_KINDS``), error ``code`` (or None), ``meaning``, host ``time`` (monotonic s)."""

    device: str
    node: int | None
    kind: str
    meaning: str
    code: int | None = None
    time: float = field(default_factory=time.monotonic)

    def __str__(self) -> str:
        where = f"{self.device} (node {self.node})" if self.node is not None else self.device
        code = f" 0x{self.code:04X}" if self.code is not None else ""
        return f"{where}: {self.kind}{code}: {self.meaning}"

    def to_dict(self) -> dict:
        return {"device": self.device, "node": self.node, "kind": self.kind, "code": self.code,
                "meaning": self.meaning}



class RobotError(RuntimeError):
    """A robot operation failed (boot, configuration, enabling, I/O); ``faults`` says why."""

    def __init__(self, message: str, faults: tuple[Fault, ...] = ()):
        super().__init__(message)
        self.faults = tuple(faults)


class RobotFault(RobotError):
    """The robot is in a fault state: torques cannot be applied until the fault is reset."""


@dataclass(frozen=True, init=False)
class Snapshot:
    """Everything read at one SYNC.

    t: s since the drives were enabled (cycle * period); cycle: SYNC count since enabling;
    host_time: host monotonic time of the SYNC (s); joint_pos (3,) rad and joint_vel (3,) rad/s
    for (phi_r, phi_l, phi_p); joint_torque (3,) N m as the drives report it; imu_accel (3,) m/s^2
    and imu_gyro (3,) rad/s in the platform frame B'' (None without IMU), imu_time its host
    reception time; drive_states: CiA 402 state names; faults: active faults.
    """

    t: float
    cycle: int
    host_time: float
    joint_pos: np.ndarray
    joint_vel: np.ndarray
    joint_torque: np.ndarray
    imu_accel: np.ndarray | None = None
    imu_gyro: np.ndarray | None = None
    imu_time: float | None = None
    drive_states: tuple[str, ...] = ()
    faults: tuple[Fault, ...] = ()

    def __init__(self, t, cycle, host_time, joint_pos, joint_vel, joint_torque, imu_accel=None, imu_gyro=None,
                 imu_time=None, drive_states=(), faults=()):
        # one per cycle on every back end: the fields written straight into the instance's dict (the
        # frozen dataclass's generated __init__ sets each through object.__setattr__, 2.1 against 0.6 us)
        d = self.__dict__
        d["t"], d["cycle"], d["host_time"] = t, cycle, host_time
        d["joint_pos"], d["joint_vel"], d["joint_torque"] = joint_pos, joint_vel, joint_torque
        d["imu_accel"], d["imu_gyro"], d["imu_time"] = imu_accel, imu_gyro, imu_time
        d["drive_states"], d["faults"] = drive_states, faults


@dataclass(frozen=True, init=False)
class Command:
    """What ``write`` did: requested (3,) N m, commanded (3,) N m after limit clamping and the
    drives' per-mille quantization, saturated (3,) bool: a limit cut the request."""

    requested: np.ndarray
    commanded: np.ndarray
    saturated: np.ndarray | None = None

    def __init__(self, requested, commanded, saturated=None):
        # one per cycle: written straight into the instance's dict, like ``Snapshot``
        d = self.__dict__
        d["requested"], d["commanded"] = requested, commanded
        d["saturated"] = np.zeros(3, bool) if saturated is None else saturated


class Robot(abc.ABC):
    """A robot with three torque-controlled joints (right wheel, left wheel, pivot) and an IMU.

    ``period`` is the sample (control) period in s: one ``read()`` per period. Back ends set
    ``max_torque`` ((3,) N m the commands are clamped to; None: no clamp), ``torque_quantum`` ((3,) N m,
    the drives' torque resolution, a difference beyond half of it counts as saturation; None: exact),
    ``imu`` / ``imu_rate`` (Hz) when they have an IMU, ``warnings`` (what the devices cannot do that the
    loop would use) and ``close_report`` (what the last ``close()`` could not do).
    """

    period: float
    max_torque: tuple[float, float, float] | None = None
    torque_quantum: tuple[float, float, float] | None = None
    imu = None
    imu_rate: float | None = None
    warnings: tuple[str, ...] | list[str] = ()
    close_report: tuple[str, ...] | list[str] = ()
    #: The clock the back end's own multi-cycle sequences tick (``otbot_hw.clock``; None: it has none)
    clock = None
    #: The back end's timing, declared (ros2_control: the hardware says what it is, the controller manager
    #: owns the clock): True when it advances a simulated plant in lockstep with ``read()`` (nothing runs
    #: in real time: a loop runs its cycles back to back, ``otbot_hw.clock.Unpaced``); False for hardware
    #: or a plant paced in real time (the loop paces it, ``Pacer``). The loop asks it (``clock.paced``)
    #: unless its caller chooses.
    lockstep: bool = False

    def use_clock(self, clock) -> None:
        """The runtime's clock (``otbot_hw.clock``), handed down by the loop that drives this robot:
        the back end's own multi-cycle sequences (a driver's enable, fault reaction) tick it too."""
        self.clock = clock

    @abc.abstractmethod
    def read(self) -> Snapshot:
        """One synchronous sample of all sensors (see the module docstring for timing)."""

    def write(self, torques) -> Command:
        """Command joint torques (tau_r, tau_l, tau_p) N m, clamped to ``max_torque``; applied from the
        next sample on. ValueError for anything but 3 finite numbers; ``RobotFault`` while faulted,
        ``RobotError`` while the drives are not enabled (raised by the back end's ``_apply``)."""
        u = np.asarray(torques, dtype=float).reshape(-1)
        ul = u.tolist()
        if len(ul) != 3 or not all(map(math.isfinite, ul)):
            raise ValueError(f"torques must be 3 finite numbers (tau_r, tau_l, tau_p) N m, got {torques!r}")
        m = self.max_torque
        if m is None:  # plain floats: this runs every cycle
            clamped, sat = ul, _NOT_SATURATED
        else:
            clamped = [min(max(v, -lim), lim) for v, lim in zip(ul, m)]
            sat = [a != b for a, b in zip(clamped, ul)]
        commanded = self._apply(clamped)
        q = self.torque_quantum
        if q is not None:
            sat = [s or abs(c - a) > 0.5 * dq + 1e-12 for s, c, a, dq in zip(sat, commanded.tolist(), clamped, q)]
        return Command(u, commanded, _NO_SATURATION if sat == _NOT_SATURATED else np.array(sat, dtype=bool))

    @abc.abstractmethod
    def _apply(self, torques: list[float]) -> np.ndarray:
        """Stage ``torques`` (3 floats, N m, already checked and clamped) for the next sample; return the
        torques (3,) N m the drives will produce (after their quantization). Refuses with
        ``_refuse_unless_writable`` (faulted or not enabled)."""

    @staticmethod
    def _refuse_unless_writable(faults: tuple[Fault, ...] | list[Fault], enabled: bool,
                                not_enabled: type[RobotError] = RobotError) -> None:
        """The state checks of ``write``, said the same way by every back end."""
        if faults:
            raise RobotFault("robot is faulted: " + "; ".join(map(str, faults)), tuple(faults))
        if not enabled:
            raise not_enabled("drives are not enabled: call enable() first")

    @abc.abstractmethod
    def enable(self) -> None:
        """Bring every drive to OPERATION ENABLED with zero torque."""

    @abc.abstractmethod
    def disable(self) -> None:
        """Remove power from the motors (drives to SWITCH ON DISABLED)."""

    @abc.abstractmethod
    def quick_stop(self) -> None:
        """Quick stop every drive (zero torque, QUICK STOP ACTIVE)."""

    @abc.abstractmethod
    def fault_reset(self) -> None:
        """Reset drive faults and clear the fault list (faults still present come back)."""

    @property
    @abc.abstractmethod
    def faults(self) -> tuple[Fault, ...]:
        """Active faults; while any is active ``write`` raises ``RobotFault``."""

    @property
    def faulted(self) -> bool:
        return bool(self.faults)

    @property
    def has_imu(self) -> bool:
        """Whether ``read()`` delivers IMU samples."""
        return self.imu is not None

    def truth(self) -> np.ndarray | None:
        """Ground-truth state x = (q, q_dot) (12,) at the last ``read()``'s sample instant, where
        the back end knows it (a ``SimulatedRobot``); None on a real robot."""
        return None

    def node_identities(self) -> dict[str, dict]:
        """Each bus node's identity by device name ({node_id, vendor, product, revision, serial}, None
        for what a node does not say); empty for a robot without nodes."""
        return {}

    def close(self) -> list[str]:
        """Release the buses. Never raises: returns what it could not do (empty when all went well)."""
        return []

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class SimulatedRobot(Robot):
    """A robot whose hardware is simulated: what it can do beyond ``Robot`` is declared here.

    ``plant``: the simulated hardware it drives (``sim.plant.Plant`` behind the bus; the direct robot
    is its own plant); ``truth()`` is never None after a ``read()``; ``truth_force()`` the external
    pivot force; ``simulated_params`` the robot simulated now (``OtbotParams``, a load an operator
    fixed included); ``has_operator`` / ``operator(command)``: the operator channel (a person at the
    bench: fixture, load), where the simulated plant has one.
    """

    plant: object
    has_operator: bool = False

    @abc.abstractmethod
    def truth(self) -> np.ndarray | None:
        """Ground-truth state (12,) at the last ``read()``'s sample (None before the first)."""

    @abc.abstractmethod
    def truth_force(self) -> np.ndarray:
        """External pivot force (2,) N, ground frame, held from the last read's sample on."""

    @property
    @abc.abstractmethod
    def simulated_params(self):
        """``OtbotParams`` of the robot simulated now."""

    def operator(self, command: str) -> dict:
        """Do what an operator at the bench would (see ``sim.plant.Plant.operator``); JSON-ready reply,
        ``error`` when this simulated robot has no operator channel."""
        return {"error": "this simulated robot has no operator channel"}


def operator_channel(robot: Robot) -> SimulatedRobot | None:
    """``robot`` when it is a simulated robot with an operator channel, else None."""
    return robot if isinstance(robot, SimulatedRobot) and robot.has_operator else None
