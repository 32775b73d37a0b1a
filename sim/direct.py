"""``DirectSimRobot``: the simulated Otbot in this process, no bus (the ``Robot`` seam's mock hardware).

Each ``read()`` is one sample, in lockstep, as fast as the model steps (the ``sim.plant.Plant``
behind the CAN bus does the same thing once per SYNC):

1. the command written before this read (u_k, clamped to the motor limits; zero for a joint whose
   drive is not OPERATION ENABLED) and the external pivot force f_k are taken;
2. the sensors sample the state x_k with u_k acting (``otbot_hw.simulation.sensing``: the paper's
   model, or the extended model with its sensor effects) and the model advances one period under
   (u_k, f_k) (``otbot_hw.simulation.simulator.make_stepper``), both in one compiled call
   (``StepperSensors.sample_and_step``);
3. the seeded noise of ``otbot_hw.sensors.NoiseModel`` is added to the sample and, where configured,
   the encoder angles are floored to whole counts and the rates rounded to whole counts/s; the IMU
   outputs at its own rate (a new sample when a new IMU period starts, ``drivers.robot.imu_due``, the
   bus's schedule).

So u written before read k is held on [t_k, t_k+1), the timing convention of ``otbot_hw.robot`` and
of the bus. The drives are emulated at the level the loop sees them: CiA 402 state names
(SWITCH ON DISABLED, OPERATION ENABLED, QUICK STOP ACTIVE, FAULT), torque only when enabled, a
fault on one drive quick-stops the others (the fault reaction of ``drivers.robot.CanopenRobot``).
The clock starts (t = 0) at ``enable()``; before that the robot stands still at x0.
"""
from __future__ import annotations

import math
import time

import numpy as np

from drivers.robot import imu_due
from otbot_hw.motors import MotorLimits
from otbot_hw.params import nominal
from otbot_hw.robot import Fault, RobotFault, SimulatedRobot, Snapshot
from otbot_hw.sensors import NoiseModel
from otbot_hw.simulation.sensing import StepperSensors
from otbot_hw.simulation.simulator import ForceSchedule, make_stepper

JOINTS = ("right_wheel", "left_wheel", "pivot")
ENABLED = "OPERATION ENABLED"
DISABLED = "SWITCH ON DISABLED"
QUICK_STOP = "QUICK STOP ACTIVE"
FAULT = "FAULT"


class DirectSimRobot(SimulatedRobot):
    """The model stepped in-process behind the ``Robot`` interface.

    ``plant``: ``OtbotParams`` (the paper's model) or ``ExtendedModel`` (with effects; default: nominal
    parameters); ``period`` s per sample; ``x0`` (12,) initial state (rolling-angle coordinates for an
    extended model); ``fixture`` floor, stand or locked; ``noise`` and ``seed``: sensor noise;
    ``imu_rate`` Hz (None: no IMU); ``encoder_counts``: counts per joint revolution (3,) the angles
    are floored to (None: exact); ``rate_step``: resolution (3,) rad/s the rates are rounded to (None:
    exact); ``limits``: motor torque limits (None: no clamp);
    ``torque_step`` N m: the drives' torque resolution (None: exact); ``forces``: pivot forces.
    It is its own ``plant`` (``SimulatedRobot``); no operator channel. Lockstep: nothing runs in real
    time (``Robot.lockstep``).
    """

    lockstep = True

    def __init__(self, plant=None, period: float = 0.001, x0=None, fixture: str = "floor",
                 noise: NoiseModel | None = None, seed: int | None = 0, imu_rate: float | None = 100.0,
                 encoder_counts=None, rate_step=None, limits: MotorLimits | None = None,
                 torque_step: float | None = None, forces: ForceSchedule | None = None):
        if not (period > 0 and math.isfinite(period)):
            raise ValueError(f"period must be > 0 s, got {period}")
        if imu_rate is not None and not imu_rate > 0:
            raise ValueError(f"imu_rate must be > 0 Hz or None, got {imu_rate}")
        plant = plant if plant is not None else nominal()
        self.model = plant
        self.params = getattr(plant, "params", plant)
        self.period = float(period)
        self.fixture = fixture
        self.stepper = make_stepper(plant, self.period, x0, fixture)
        self.sensors = StepperSensors(self.stepper, self.period)
        self.noise = noise or NoiseModel()
        self.rng = np.random.default_rng(seed)
        self.imu_rate = None if imu_rate is None else float(imu_rate)
        self.counts = None if encoder_counts is None else np.asarray(encoder_counts, dtype=float).reshape(3)
        self.rate_step = None if rate_step is None else np.asarray(rate_step, dtype=float).reshape(3)
        self.limits = limits
        self.max_torque = None if limits is None else tuple(float(v) for v in limits.max_torque)
        self.torque_step = torque_step
        self.torque_quantum = (torque_step,) * 3 if torque_step else None
        self.forces = forces
        self.states = [DISABLED] * 3
        self._faults: list[Fault] = []
        self._u = np.zeros(3)
        self._cycle = 0          # samples since enable()
        self._plant_k = 0        # model steps since the first enable (plant time = k * period)
        self._started = False
        self._truth: np.ndarray | None = None
        self._truth_f = np.zeros(2)
        self._imu_last = None
        self._zero_f = np.zeros(2)

    # -- the cycle ---------------------------------------------------------------------------------
    @property
    def has_imu(self) -> bool:
        return self.imu_rate is not None

    @property
    def t_plant(self) -> float:
        """Model time, s since the first ``enable()``."""
        return self._plant_k * self.period

    def applied_torque(self) -> np.ndarray:
        """Torques (3,) N m the drives produce now: the command on enabled drives, zero elsewhere."""
        if self._all_enabled:
            return self._u
        return np.array([u if s == ENABLED else 0.0 for u, s in zip(self._u.tolist(), self.states)])

    @property
    def states(self) -> list[str]:
        """CiA 402 state name of each drive (right wheel, left wheel, pivot)."""
        return list(self._states)

    @states.setter
    def states(self, value) -> None:
        self._states = tuple(value)
        self._all_enabled = all(s == ENABLED for s in self._states)

    def read(self) -> Snapshot:
        u = self._u if self._all_enabled else self.applied_torque()
        t_model = self._plant_k * self.period  # t_plant
        f = self.forces.at(t_model + 1e-9) if (self.forces is not None and self._started) else self._zero_f
        noise = self.noise
        acc = gyro = imu_t = None
        want_imu = self.imu_rate is not None and imu_due(self._cycle, self.period, self.imu_rate)
        x_k = self.stepper.x  # the stepper replaces x at a step, never changes it in place
        if self._started:  # the sensors at x_k and the step to x_k+1 under (u_k, f_k): one compiled call
            pos, vel, a, g = self.sensors.sample_and_step(t_model, u, f, want_imu)
        else:
            a, g = self.sensors.imu(t_model, u, f) if (want_imu or self.sensors.latency > 0) else (None, None)
            pos, vel = self.sensors.joints(u)
        if want_imu:
            if noise.accel:
                a = a + noise.accel * self.rng.standard_normal(3)
            if noise.gyro:
                g = g + noise.gyro * self.rng.standard_normal(3)
            self._imu_last = (a, g, self._cycle * self.period)
        if self._imu_last is not None:
            acc, gyro, imu_t = self._imu_last
        if noise.enc_rate:
            vel = vel + noise.enc_rate * self.rng.standard_normal(3)
        if noise.enc_angle:
            pos = pos + noise.enc_angle * self.rng.standard_normal(3)
        if self.counts is not None:
            step = 2 * np.pi / self.counts
            pos = np.floor(pos / step + 1e-9) * step
        if self.rate_step is not None:
            vel = np.round(vel / self.rate_step) * self.rate_step
        self._truth = x_k
        self._truth_f = f
        snap = Snapshot(t=self._cycle * self.period, cycle=self._cycle, host_time=time.monotonic(), joint_pos=pos,
                        joint_vel=vel, joint_torque=u.copy(), imu_accel=acc, imu_gyro=gyro, imu_time=imu_t,
                        drive_states=self._states, faults=tuple(self._faults))
        if self._started:
            self._plant_k += 1
            self._cycle += 1
        return snap

    def _apply(self, torques: list[float]) -> np.ndarray:
        if self._faults or not self._all_enabled:
            self._refuse_unless_writable(self._faults, self._all_enabled)
        cmd = np.array(torques, dtype=float)
        if self.torque_step:
            cmd = np.round(cmd / self.torque_step) * self.torque_step
        self._u = cmd
        return cmd.copy()

    @property
    def plant(self) -> "DirectSimRobot":
        """The simulated hardware: this robot steps the model itself."""
        return self

    @property
    def simulated_params(self):
        return self.params

    def truth(self) -> np.ndarray | None:
        return None if self._truth is None else self._truth.copy()

    def truth_force(self) -> np.ndarray:
        """External pivot force (2,) N, ground frame, held from the last read's sample on."""
        return np.array(self._truth_f, dtype=float)

    # -- drive states ------------------------------------------------------------------------------
    def enable(self) -> None:
        if self._faults:
            raise RobotFault("cannot enable while faulted: " + "; ".join(map(str, self._faults)), tuple(self._faults))
        self._u = np.zeros(3)
        self.states = [ENABLED] * 3
        self._started = True
        self._cycle = 0

    def disable(self) -> None:
        self._u = np.zeros(3)
        self.states = [FAULT if s == FAULT else DISABLED for s in self.states]

    def quick_stop(self) -> None:
        self._u = np.zeros(3)
        self.states = [QUICK_STOP if s == ENABLED else s for s in self.states]

    def fault_reset(self) -> None:
        self._faults.clear()
        self.states = [DISABLED if s == FAULT else s for s in self.states]

    @property
    def faults(self) -> tuple[Fault, ...]:
        return tuple(self._faults)

    def inject_fault(self, joint: int, code: int = 0x2310, meaning: str = "over-current (injected)") -> None:
        """A drive error on ``joint`` (0 right wheel, 1 left, 2 pivot): that drive goes to FAULT, the
        others quick-stop (zero torque), as the bus robot's fault reaction does."""
        self._faults.append(Fault(JOINTS[joint], joint + 1, "emcy", meaning, code))
        self.states = [FAULT if i == joint else (QUICK_STOP if s == ENABLED else s) for i, s in enumerate(self.states)]
