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

from otbot_hw.clock import paced
from otbot_hw.motors import MotorLimits
from otbot_hw.robot import Robot
from otbot_hw.runtime.controllers import OpenLoopTorques
from otbot_hw.runtime.loop import LoopResult, LoopRunner
from otbot_hw.runtime.supervisor import SafetyConfig, Supervisor


def run_torques(robot: Robot, torques, limits: MotorLimits | None = None, safety: SafetyConfig | None = None,
                path: str | Path | None = None, metadata: dict | None = None, realtime: bool | None = None,
                progress: Callable[[str], None] | None = None, feedback=None) -> LoopResult:
    """Enable ``robot``, apply ``torques`` (N, 3) N m one per period, record N + 1 samples, quick-stop.

    ``limits``: motor limits of the supervisor (default: none); ``safety``: its checks (default
    ``SafetyConfig()``); ``path``: MCAP recording; ``realtime``: pace against the wall clock (None: as the
    robot declares, ``otbot_hw.clock.paced``: a real bus is paced); ``progress(text)``: about every
    second of robot time; ``feedback``: an estimator to run alongside (recorded on ``/otbot/estimate``),
    None for none."""
    torques = np.asarray(torques, dtype=float).reshape(-1, 3)
    period = robot.period
    realtime = paced(robot, realtime)
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


TORQUE_CSV_COLUMNS = ("t", "tau_r", "tau_l", "tau_p")


class TorqueSequenceError(ValueError):
    """A torque sequence file that cannot be played; the message names the file and what is wrong."""


def load_torque_sequence(path) -> tuple[np.ndarray, np.ndarray]:
    """(times (K,) s from 0, torques (K, 3) N m, row k held from times[k]) of a recording (``.mcap``:
    its ``/otbot/command``) or a CSV (header with ``t``, ``tau_r``, ``tau_l``, ``tau_p``; other columns
    ignored; ``#`` comments; the trajectory CSV's reader). Times must increase strictly; every value
    finite."""
    from otbot_hw.recording import RecordingError, read_recording

    path = Path(path)
    if path.suffix.lower() == ".mcap":
        try:
            rec = read_recording(path)
        except RecordingError as exc:
            raise TorqueSequenceError(str(exc)) from None
        t, u = np.asarray(rec.t, float), np.asarray(rec.torque, float)
    else:
        from otbot_hw.control.sampled_trajectory import csv_numbers, csv_table
        from otbot_hw.input_files import read_text

        try:
            text = read_text(path)
        except OSError as exc:
            raise TorqueSequenceError(f"{path}: cannot read a CSV text file: {exc.strerror or exc}") from None
        except UnicodeDecodeError as exc:
            raise TorqueSequenceError(f"{path}: cannot read a CSV text file: {exc}") from None
        header, rows = csv_table(path, text, TORQUE_CSV_COLUMNS, TorqueSequenceError)
        arr = csv_numbers(path, header, rows, TORQUE_CSV_COLUMNS, TorqueSequenceError)
        t, u = arr[:, 0], arr[:, 1:]
    if len(t) < 1:
        raise TorqueSequenceError(f"{path}: no torque rows")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(u))):
        raise TorqueSequenceError(f"{path}: NaN or inf in the times or torques")
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        raise TorqueSequenceError(f"{path}: time does not increase after row {int(bad[0]) + 1} (t = {t[bad[0]]:g} s)")
    return t - t[0], u
