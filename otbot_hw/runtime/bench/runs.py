"""The bench's runs on the robot (``BenchRuns``): each a supervised run through the loop runner (the
``safety:`` section tightened to the experiment limits and the step's fixture, torques clipped to the
experiment's), recorded with the bench's metadata; before each, the communication watchdogs that tripped
while the bench was idle are reset. ``warm_up`` compiles what the runs call before a bus opens.
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from otbot_hw.experiment_limits import ExperimentLimits
from otbot_hw.motors import MotorLimits
from otbot_hw.params import OtbotParams
from otbot_hw.robot import Robot, RobotError
from otbot_hw.robot import SimulatedRobot as SimulatedBackEnd
from otbot_hw.runtime.bench.excitation import ExcitationController, brake_gains, predicted_margins
from otbot_hw.runtime.bench.session import SessionFolder
from otbot_hw.runtime.bench.steps import BENCH_STEPS, BenchAbort, BenchSettings, SimulatedRobot
from otbot_hw.runtime.loop import LoopResult, LoopRunner
from otbot_hw.runtime.supervisor import SafetyConfig, Supervisor
from otbot_hw.sensors import NoiseModel

#: EMCY codes of the drives' communication watchdogs (CiA 301): SYNC timeout, life guard / heartbeat
WATCHDOG_CODES = (0x8100, 0x8130)


@dataclass
class BenchRuns:
    """The runs of one bench invocation on the opened ``robot``: ``run`` (``timing``: where the runs' wall
    time and robot time add up), ``meta`` (a run's recording metadata, from ``metadata``), ``idle_resets``
    (the communication faults reset between runs, each a list of fault dicts)."""

    robot: Robot
    s: BenchSettings
    session: SessionFolder
    timing: Any
    realtime: bool = False
    say: Callable[[str], None] = lambda m: None
    sim: SimulatedRobot | None = None
    metadata: dict = field(default_factory=dict)
    idle_resets: list = field(default_factory=list)

    def __post_init__(self):
        self.period = float(self.robot.period)
        self.torque_limits = MotorLimits(np.minimum(np.asarray(self.s.motor_limits.max_torque, dtype=float),
                                                    self.s.limits.torque))

    def meta(self, step: str, kind: str, attempt: int, fixture: str, extra: dict | None = None) -> dict:
        meta = {**self.metadata, "sample_period": self.period, "fixture": fixture, "noise": self.s.noise.to_dict(),
                "bench": {"session": str(self.session.path), "step": step, "attempt": attempt, "run": kind,
                          "excitation": self.s.excitation}}
        if self.sim is not None:
            params = (self.robot.simulated_params if isinstance(self.robot, SimulatedBackEnd)
                      else (self.sim.loaded if BENCH_STEPS[step].loaded else self.sim.unloaded))
            meta["params"] = params.to_dict()
            if self.sim.effects:
                meta["effects"] = self.sim.effects
        meta.update(extra or {})
        return meta

    def clear_idle_watchdogs(self) -> None:
        """Between runs nothing commands torque (the drives are quick-stopped) and the bus rests while
        the bench computes or waits for the operator. Wall-clock watchdogs may trip meanwhile: the
        drives' watch of the master's heartbeat (or of SYNC, where configured) on a loaded host, said
        by EMCY; in lockstep a node's heartbeat or TPDO, or the simulated IMU (it publishes on SYNC)
        looks late. One SYNC shows them; such communication faults alone are then reset (and counted
        in the result): a node or an IMU that is really gone faults again at once and fails the run's
        drive or IMU check, as does any other fault, which is never reset."""
        try:
            self.robot.read()  # one SYNC: what went wrong while idle shows now (e.g. the IMU stream's watchdog)
        except RobotError:
            pass  # the bus is gone: the run's enable says so
        faults = self.robot.faults
        if faults and all(_communication(f) for f in faults):
            self.say("[bench] communication watchdogs tripped while the bench was idle ("
                     + "; ".join(sorted({f"{f.device}: {f.kind}" + (f" 0x{f.code:04X}" if f.code else "")
                                         for f in faults})) + "): reset")
            self.idle_resets.append([f.to_dict() for f in faults])
            self.robot.fault_reset()

    def run(self, controller, cycles: int, fixture: str | None, path: Path, meta: dict,
             feedback=None) -> LoopResult:
        # the EKF serves the speed and free-area checks here; it may gate out the encoders for a while at
        # a hard torque step (seen on some platform-to-chassis angles), which its std then shows: the
        # std checks stay, the share of rejected innovations (a tracking loop's health check) does not
        safety = dataclasses.replace(self.s.safety.within(self.s.limits, fixture or "stand"),
                                     max_rejected_fraction=None)
        sup = Supervisor(self.torque_limits, safety, self.period, realtime=self.realtime)
        runner = LoopRunner(self.robot, controller, sup, feedback, path=path, metadata=meta, realtime=self.realtime)
        t0 = time.perf_counter()
        try:
            self.clear_idle_watchdogs()
            res = runner.run(cycles)
        except RobotError as exc:  # the bus failed underneath (not a latched fault)
            raise BenchAbort(meta["bench"]["step"], f"the robot stopped answering: {exc}") from None
        self.timing.runs += time.perf_counter() - t0
        self.timing.robot_time += res.stats.robot_time
        return res


def _communication(f) -> bool:
    """A fault of the bus's wall-clock watchdogs (not of a drive's power stage or its sensors)."""
    if f.kind == "emcy":
        return f.code in WATCHDOG_CODES
    if f.kind == "imu":
        return "no valid IMU sentence" in f.meaning or "no IMU sample within" in f.meaning
    return f.kind in ("heartbeat", "stale")


def warm_up(params: OtbotParams, period: float) -> None:
    """Compile what the bench's runs call (the EKF's kernels, the supervisor, the brake's and the
    predicted motion's model functions) before a bus opens: numba compiles at the first call and holds
    the interpreter meanwhile (seconds on a cold cache), which on a live bus starves the heartbeat
    threads (as ``runtime.tracking.warm_up`` does for tracking)."""
    from otbot_hw.identification.experiments import PAPER_EXPERIMENTS
    from otbot_hw.runtime.backends import DirectBackend
    from otbot_hw.runtime.feedback import EkfFeedback

    with DirectBackend(rate=1.0 / period, noise=NoiseModel.paper()).open(params) as robot:
        ctrl = ExcitationController(np.zeros((3, 3)), period, brake_gains(params, "floor", period), 1.0, 3)
        sup = Supervisor(MotorLimits(np.full(3, 1e9)), SafetyConfig(max_travel=10.0), period)
        LoopRunner(robot, ctrl, sup, EkfFeedback(params, period, np.zeros(3))).run(6)
    predicted_margins(PAPER_EXPERIMENTS["wheel"], params, ExperimentLimits(), None, None)
