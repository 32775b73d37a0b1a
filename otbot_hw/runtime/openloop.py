"""Open-loop experiments through the loop runner: a torque sequence applied, everything recorded.

``run_torques`` is what ``otbot run``, the bus part of ``otbot demo`` and identification experiments
use: N torque rows, one per period, give N + 1 samples (the last command repeats), the layout of
``otbot_hw.simulation.runs.simulated_recording``; the supervisor clamps to the motor limits (reported)
and watches the joint rates; the robot is quick-stopped at the end or at the first fault.
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from otbot_hw.motors import MotorLimits
from otbot_hw.robot import Robot
from otbot_hw.runtime.controllers import OpenLoopTorques
from otbot_hw.runtime.loop import LoopResult, LoopRunner
from otbot_hw.runtime.supervisor import SafetyConfig, Supervisor


def run_torques(robot: Robot, torques, limits: MotorLimits | None = None, safety: SafetyConfig | None = None,
                path: str | Path | None = None, metadata: dict | None = None, realtime: bool = False,
                progress: Callable[[str], None] | None = None, feedback=None) -> LoopResult:
    """Enable ``robot``, apply ``torques`` (N, 3) N m one per period, record N + 1 samples, quick-stop.

    ``limits``: motor limits of the supervisor (default: none); ``safety``: its checks (default
    ``SafetyConfig()``); ``path``: MCAP recording; ``realtime``: pace against the wall clock (a real
    bus); ``progress(text)``: about every second of robot time; ``feedback``: an estimator to run
    alongside (recorded on ``/otbot/estimate``), None for none."""
    torques = np.asarray(torques, dtype=float).reshape(-1, 3)
    period = robot.period
    sup = Supervisor(limits if limits is not None else MotorLimits(np.full(3, np.inf)), safety, period,
                     realtime=realtime)
    meta = {"sample_period": period, **(metadata or {})}
    runner = LoopRunner(robot, OpenLoopTorques(torques, period), sup, feedback, path=path, metadata=meta,
                        realtime=realtime, progress=progress)
    return runner.run(len(torques) + 1)


def saturated_samples(res: LoopResult, limits: MotorLimits | None) -> np.ndarray:
    """Per sample (N,) whether a motor limit cut the requested torque."""
    if limits is None or res.requested is None:
        return np.zeros(len(res.recording), bool)
    return np.any(np.abs(res.requested) > np.asarray(limits.max_torque) + 1e-12, axis=1)
