"""Open-loop runs through a ``Robot``: apply a torque sequence, record what the robot reports.

Sample k of the recording is the command u_k written before SYNC k (held until SYNC k+1) and
the drives', encoder's and IMU's readings at SYNC k, so a run of N torques gives N+1 samples
(the last command repeats), the layout of ``otbot_hw.simulation.runs.simulated_recording``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from otbot_hw.recording import (TOPIC_COMMAND, TOPIC_EVENTS, TOPIC_IMU, TOPIC_JOINTS, TOPIC_TRUTH, Recording,
                                RecordingWriter)
from otbot_hw.robot import Fault, Robot


@dataclass
class BusRun:
    """Result of ``run_torques``: the recording (also streamed to disk when a path was given),
    per-sample saturation flags (N+1, 3), the faults that stopped the run (empty when it completed)."""

    recording: Recording
    saturated: np.ndarray
    faults: tuple[Fault, ...] = ()
    completed: bool = True
    extra: dict = field(default_factory=dict)


def run_torques(robot: Robot, torques: np.ndarray, period: float, path: str | Path | None = None,
                metadata: dict | None = None, truth=None, progress: Callable[[str], None] | None = None) -> BusRun:
    """Enable ``robot``, apply ``torques`` (N, 3) N m one per control period, record, quick-stop.

    ``truth``: a ``sim.plant.TruthLog`` of a simulated plant, recorded as ground truth;
    ``progress(msg)`` is called about every second of robot time. Stops at the first fault (the
    robot has already reacted: drives stopped); the recording then ends with the last sample
    before the fault and an ``/otbot/events`` fault event per fault.
    """
    torques = np.asarray(torques, dtype=float)
    n = len(torques)
    has_imu = getattr(robot, "imu", None) is not None
    topics = ([TOPIC_JOINTS] + ([TOPIC_IMU] if has_imu else []) + ([TOPIC_TRUTH] if truth is not None else [])
              + [TOPIC_EVENTS])
    meta = {"source": "bus", "sample_period": period, **(metadata or {})}
    writer = RecordingWriter(path, meta, topics=topics) if path is not None else None
    rows: dict[str, list] = {k: [] for k in ("t", "u", "pos", "vel", "acc", "gyro")}
    sat = []
    faults: tuple[Fault, ...] = ()
    every = max(1, int(round(1.0 / period)))
    try:
        robot.enable()
        for k in range(n + 1):
            u = torques[min(k, n - 1)] if n else np.zeros(3)
            cmd = robot.write(u)
            s = robot.read()
            if s.faults:
                faults = s.faults
                if writer is not None:
                    for f in faults:
                        writer.write_event(max(0.0, s.t), "fault", str(f), device=f.device, node=f.node,
                                           fault=f.kind, code=f.code)
                break
            msg = {TOPIC_COMMAND: {"t": s.t, "torque": cmd.commanded.tolist()},
                   TOPIC_JOINTS: {"t": s.t, "position": s.joint_pos.tolist(), "velocity": s.joint_vel.tolist()}}
            if has_imu:
                acc = s.imu_accel if s.imu_accel is not None else np.full(3, np.nan)
                gyro = s.imu_gyro if s.imu_gyro is not None else np.full(3, np.nan)
                msg[TOPIC_IMU] = {"t": s.t, "accel": acc.tolist(), "gyro": gyro.tolist()}
                rows["acc"].append(acc)
                rows["gyro"].append(gyro)
            if truth is not None:
                x = truth.x[k]
                msg[TOPIC_TRUTH] = {"t": s.t, "q": x[:6].tolist(), "qd": x[6:].tolist(), "force": truth.f[k].tolist()}
            if writer is not None:
                writer.write_sample(msg)
            rows["t"].append(s.t)
            rows["u"].append(cmd.commanded)
            rows["pos"].append(s.joint_pos)
            rows["vel"].append(s.joint_vel)
            sat.append(cmd.saturated)
            if progress and k % every == 0 and k:
                progress(f"t = {s.t:.2f} s of {n * period:.2f} s, phi = "
                         + ", ".join(f"{v:.3f}" for v in s.joint_pos) + " rad")
        if not faults:
            robot.quick_stop()
    finally:
        if writer is not None:
            writer.close()
    m = len(rows["t"])
    rec = Recording(t=np.array(rows["t"]), torque=np.array(rows["u"]).reshape(m, 3),
                    joint_pos=np.array(rows["pos"]).reshape(m, 3), joint_vel=np.array(rows["vel"]).reshape(m, 3),
                    metadata=meta)
    if has_imu:
        rec.imu_accel = np.array(rows["acc"]).reshape(m, 3)
        rec.imu_gyro = np.array(rows["gyro"]).reshape(m, 3)
    if truth is not None:
        rec.truth_q = np.array(truth.x[:m])[:, :6].reshape(m, 6)
        rec.truth_qd = np.array(truth.x[:m])[:, 6:].reshape(m, 6)
        rec.truth_force = np.array(truth.f[:m]).reshape(m, 2)
    return BusRun(recording=rec, saturated=np.array(sat).reshape(m, 3), faults=faults, completed=not faults)
