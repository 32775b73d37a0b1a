"""The loop runner: read -> estimate -> supervise -> record -> control -> limit -> write, at a fixed period,
over any ``otbot_hw.robot.Robot`` (there is one loop in the project).

Cycle k (``LoopRunner.cycle``)::

    s_k = robot.read()                    # sensors at t_k; u_k (written last cycle) acts on [t_k, t_k+1)
    e_k = feedback.step(s_k, u_k-1)       # EKF or ground truth (EstimatorFault -> fault)
    supervisor.check(s_k, e_k, r_k)       # rates, speed, workspace, tracking error, estimator, overruns
    record sample k                       # u_k, joints, IMU, e_k, reference r_k of u_k, truth, events
    c = controller.update(t_k+1, (e_k, u_k), s_k)   # the command for [t_k+1, t_k+2) and its reference
    u_k+1 = supervisor.limit(c.u)         # motor limits, saturation reported
    robot.write(u_k+1)

``start()`` enables the robot and writes u_0 (the controller asked without feedback). Any fault
(the robot's own, the estimator's, a supervisor violation) is latched, the robot is quick-stopped
through ``robot.quick_stop()``, a ``fault`` event is recorded and the run ends with
``LoopResult.completed = False``; the recording (streamed with ``RecordingWriter``, flushed at the
fault) holds every sample up to and including the one that showed the fault. At the end of a run
the robot is quick-stopped too (zero torque, drives in QUICK STOP ACTIVE).

Timing: ``realtime=True`` paces the reads at the period against the wall clock (a real bus);
otherwise cycles run back to back (lockstep simulation, faster than real time). Either way the
loop measures each cycle's wall-clock period and compute time, jitter and overruns
(``LoopStats``), and reports robot time next to wall time.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from otbot_hw.control.computed_torque import TaskState
from otbot_hw.recording import (TOPIC_COMMAND, TOPIC_ESTIMATE, TOPIC_EVENTS, TOPIC_IMU, TOPIC_JOINTS,
                                TOPIC_REFERENCE, TOPIC_TRUTH, Recording, RecordingWriter)
from otbot_hw.robot import Robot, RobotError, Snapshot
from otbot_hw.runtime.controllers import ControlStep, Controller, Feedback, Reference
from otbot_hw.runtime.feedback import FeedbackUnavailable, StateEstimate
from otbot_hw.runtime.supervisor import Supervisor, Violation


@dataclass
class LoopStats:
    """Timing of a run. Robot time (s, what the robot's clock advanced) next to wall time (s); per
    cycle the wall-clock period between reads (p50/p99/max, s), the jitter (rms of period minus the
    nominal period, s; meaningful when paced in real time), the compute time from the read's return
    to the write's (p50/p99/max, s) and the overruns (cycles whose period exceeded the overrun
    factor times the nominal period; only a fault in real-time loops)."""

    period: float
    realtime: bool
    cycles: int = 0
    robot_time: float = 0.0
    wall_time: float = 0.0
    period_p50: float = math.nan
    period_p99: float = math.nan
    period_max: float = math.nan
    jitter_rms: float = math.nan
    compute_p50: float = math.nan
    compute_p99: float = math.nan
    compute_max: float = math.nan
    overruns: int = 0

    @property
    def realtime_factor(self) -> float:
        """Robot seconds per wall second."""
        return self.robot_time / self.wall_time if self.wall_time > 0 else math.nan

    def to_dict(self) -> dict:
        d = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in self.__dict__.items()}
        rf = self.realtime_factor
        d["realtime_factor"] = rf if math.isfinite(rf) else None
        return d


@dataclass
class LoopResult:
    """A finished run: the recording (every sample, also streamed to disk when a path was given),
    ``completed`` (False when a fault stopped it), the latched ``fault``, timing ``stats``, the
    supervisor's saturation episodes, and per sample the controller's request before limiting
    ``requested`` (N, 3) N m and the law's parts ``u_traj``, ``u_corr`` (NaN where not a CTC)."""

    recording: Recording
    completed: bool
    stats: LoopStats
    fault: Violation | None = None
    saturation: list = field(default_factory=list)
    requested: np.ndarray | None = None
    u_traj: np.ndarray | None = None
    u_corr: np.ndarray | None = None
    feedback: str | None = None
    robot_faults: tuple = ()


class _Columns:
    """Per-sample rows kept in memory (to build the ``Recording`` and the run's summaries)."""

    NAMES = ("t", "torque", "requested", "u_traj", "u_corr", "pos", "vel", "acc", "gyro", "truth", "force", "pose",
             "twist", "std", "bias", "ref_p", "ref_pd", "ref_pdd")

    def __init__(self):
        for n in self.NAMES:
            setattr(self, n, [])


_NAN3 = np.full(3, np.nan)
_ZERO2 = np.zeros(2)
_NO_REFERENCE = Reference(_NAN3, _NAN3, _NAN3)


class LoopRunner:
    """The loop over ``robot`` with ``controller``, ``feedback`` (``EkfFeedback``, ``TruthFeedback`` or
    None for open loop) and ``supervisor``.

    ``path``: MCAP recording to stream (None: in memory only); ``metadata``: extra recording metadata;
    ``realtime``: pace against the wall clock; ``progress(text)``: called about every
    ``progress_every`` s of robot time; ``stop_at_end``: quick-stop after the last cycle;
    ``record_reference``: record ``/otbot/reference`` (NaN while no controller gives one); default:
    when the first command comes with a reference.

    Between ``start()`` and ``close()`` a caller may drive the cycles itself (``cycle()``, a daemon)
    and swap the controller between them (``set_controller``); ``result()`` then gives what ran.
    """

    def __init__(self, robot: Robot, controller: Controller, supervisor: Supervisor, feedback=None,
                 path: str | Path | None = None, metadata: dict | None = None, realtime: bool = False,
                 progress: Callable[[str], None] | None = None, progress_every: float = 1.0,
                 stop_at_end: bool = True, record_reference: bool | None = None):
        self.robot = robot
        self.controller = controller
        self.supervisor = supervisor
        self.feedback = feedback
        self.path = Path(path) if path is not None else None
        self.metadata = dict(metadata or {})
        self.realtime = realtime
        self.progress = progress
        self.progress_every = progress_every
        self.stop_at_end = stop_at_end
        self.record_reference = record_reference
        self.period = float(robot.period)
        self.stats = LoopStats(self.period, realtime)
        self.writer: RecordingWriter | None = None
        self.events: list[dict] = []
        self.fault: Violation | None = None
        self.robot_faults: tuple = ()
        self._cols = _Columns()
        self._k = 0
        self._held: ControlStep | None = None
        self._u_held = np.zeros(3)
        self._u_prev = None
        self._last_est: StateEstimate | None = None
        self._has_truth = None
        self._has_imu = robot.has_imu
        self._truth_force = getattr(robot, "truth_force", None)  # simulated robots: the pivot force
        self._periods: list[float] = []
        self._compute: list[float] = []
        self._t_last_read = None
        self._t_next = None
        self._t_wall0 = None
        self._next_progress = progress_every
        self._total = None
        self._user_saturation = supervisor.limiter.on_saturation
        supervisor.limiter.on_saturation = self._on_saturation

    # -- lifecycle ---------------------------------------------------------------------------------
    def start(self) -> None:
        """Enable the robot and write the first command (asked without feedback)."""
        self._t_wall0 = time.perf_counter()
        try:
            self.robot.enable()
        except RobotError as exc:
            self._fail(Violation("robot", 0.0, f"enabling failed: {exc}"), stop=True)
            return
        self._command(0.0, None, None)
        self.event(0.0, "mode", f"start: {type(self.controller).__name__}"
                                + (f", feedback {self.feedback.name}" if self.feedback is not None else ""))

    def set_controller(self, controller: Controller, mode: str | None = None) -> None:
        """Swap the controller between two cycles (bumpless: the next command is the new one's)."""
        self.controller = controller
        t = self._cols.t[-1] if self._cols.t else 0.0
        self.event(t, "mode", mode or f"controller: {type(controller).__name__}")

    def run(self, cycles: int) -> LoopResult:
        """``start()``, ``cycles`` cycles (one sample each), then stop; returns the result."""
        if cycles < 1:
            raise ValueError(f"a run needs at least one cycle, got {cycles}")
        self._total = cycles
        try:
            self.start()
            while self.fault is None and self._k < cycles:
                self.cycle(last=self._k == cycles - 1)
            if self.fault is None and self.stop_at_end:
                self._quick_stop()
                self.event(self._cols.t[-1] if self._cols.t else 0.0, "mode", "stopped: end of run (quick stop)")
        except BaseException:
            self._quick_stop()
            raise
        finally:
            self.close()
        return self.result()

    def cycle(self, last: bool = False) -> bool:
        """One cycle (see the module docstring); ``last``: record the sample but write no new command.
        Returns False once a fault has stopped the loop."""
        if self.fault is not None:
            return False
        if self.realtime:
            now = time.perf_counter()
            self._t_next = now if self._t_next is None else max(self._t_next + self.period, now)
            delay = self._t_next - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
        try:
            s = self.robot.read()
        except RobotError as exc:
            self._fail(Violation("robot", self._cols.t[-1] if self._cols.t else 0.0, f"read failed: {exc}"))
            return False
        t_read = time.perf_counter()
        wall_period = None if self._t_last_read is None else t_read - self._t_last_read
        self._t_last_read = t_read
        if wall_period is not None:
            self._periods.append(wall_period)
        if self._has_truth is None:
            self._has_truth = self.robot.truth() is not None
        fault = None
        if s.faults:
            self.robot_faults = tuple(s.faults)
            fault = Violation("robot", s.t, "; ".join(map(str, s.faults)))
        est = None
        if self.feedback is not None and fault is None:
            try:
                est = (self.feedback.start(s, self.robot) if self._k == 0
                       else self.feedback.step(s, self.robot, self._u_prev))
            except self.feedback.faults as exc:
                fault = Violation("estimator_fault", s.t, str(exc) or type(exc).__name__)
            except FeedbackUnavailable as exc:
                fault = Violation("feedback", s.t, str(exc))
        if est is None and fault is not None:
            est = self._last_est
        self._last_est = est
        ref = self._held.reference if self._held is not None else None
        if fault is None:
            fault = self.supervisor.check(s.t, s.joint_vel, est, ref, wall_period)
        else:
            fault = self.supervisor.latch(fault)
        self._record(s, est, ref)
        if fault is not None:
            self._fail(fault)
            return False
        self._k += 1
        if self.progress is not None and s.t >= self._next_progress:
            self._next_progress += self.progress_every
            self.progress(self._progress_text(s, est))
        if not last:
            fb = None
            if est is not None:
                fb = Feedback(s.t, TaskState(est.pose, est.twist, est.phi_p), self._u_held, self.period)
            self._command(s.t + self.period, fb, s)
            self._compute.append(time.perf_counter() - t_read)
        return self.fault is None

    def _command(self, t: float, fb: Feedback | None, s: Snapshot | None) -> None:
        step = self.controller.update(t, fb, s)
        u, _ = self.supervisor.limit(t, step.u)
        if self.supervisor.fault is not None:
            self._fail(self.supervisor.fault)
            return
        try:
            cmd = self.robot.write(u)
        except RobotError as exc:
            self._fail(Violation("robot", t, f"write failed: {exc}"))
            return
        self._u_prev = self._u_held
        self._u_held = cmd.commanded
        self._held = step

    # -- recording ---------------------------------------------------------------------------------
    def _open_writer(self, est, ref) -> None:
        topics = [TOPIC_JOINTS, TOPIC_EVENTS]
        if self._has_imu:
            topics.append(TOPIC_IMU)
        if self._has_truth:
            topics.append(TOPIC_TRUTH)
        if est is not None:
            topics.append(TOPIC_ESTIMATE)
        if self.record_reference or (self.record_reference is None and ref is not None):
            topics.append(TOPIC_REFERENCE)
        self._topics = set(topics)
        meta = {"source": "loop", "sample_period": self.period, "realtime": self.realtime, **self.metadata}
        if self._has_imu and getattr(self.robot, "imu_rate", None):
            meta.setdefault("imu_rate", float(self.robot.imu_rate))
        if self.feedback is not None:
            meta.setdefault("feedback", self.feedback.name)
        self.metadata = meta
        if self.path is not None:
            self.writer = RecordingWriter(self.path, meta, topics=topics)
            for ev in self.events:
                self.writer.write_event(ev["t"], ev["kind"], ev["text"])

    def _record(self, s: Snapshot, est: StateEstimate | None, ref) -> None:
        c = self._cols
        if not c.t:
            self._open_writer(est, ref)
        held = self._held
        c.t.append(s.t)
        c.torque.append(self._u_held)
        c.requested.append(held.u if held is not None else self._u_held)
        c.u_traj.append(held.u_traj if held is not None and held.u_traj is not None else _NAN3)
        c.u_corr.append(held.u_corr if held is not None and held.u_corr is not None else _NAN3)
        c.pos.append(s.joint_pos)
        c.vel.append(s.joint_vel)
        acc = s.imu_accel if s.imu_accel is not None else _NAN3
        gyro = s.imu_gyro if s.imu_gyro is not None else _NAN3
        c.acc.append(acc)
        c.gyro.append(gyro)
        truth = self.robot.truth() if self._has_truth else None
        if self._has_truth:
            c.truth.append(truth)
            c.force.append(self._truth_force() if self._truth_force is not None else _ZERO2)
        if TOPIC_ESTIMATE in self._topics:
            e = est if est is not None else self._last_est
            c.pose.append(e.pose)
            c.twist.append(e.twist)
            c.std.append(e.std)
            c.bias.append(e.gyro_bias)
        if TOPIC_REFERENCE in self._topics:
            r = ref if ref is not None else _NO_REFERENCE  # e.g. open loop before a tracking controller
            c.ref_p.append(r.p)
            c.ref_pd.append(r.pd)
            c.ref_pdd.append(r.pdd)
        if self.writer is None:
            return
        t = s.t
        msg: dict[str, Any] = {TOPIC_COMMAND: {"t": t, "torque": self._u_held.tolist()},
                               TOPIC_JOINTS: {"t": t, "position": s.joint_pos.tolist(),
                                              "velocity": s.joint_vel.tolist()}}
        if self._has_imu:
            msg[TOPIC_IMU] = {"t": t, "accel": acc.tolist(), "gyro": gyro.tolist()}
        if truth is not None:
            msg[TOPIC_TRUTH] = {"t": t, "q": truth[:6].tolist(), "qd": truth[6:].tolist(),
                                "force": c.force[-1].tolist()}
        if TOPIC_ESTIMATE in self._topics:
            msg[TOPIC_ESTIMATE] = {"t": t, "pose": c.pose[-1].tolist(), "twist": c.twist[-1].tolist(),
                                   "std": c.std[-1].tolist(), "gyro_bias": float(c.bias[-1])}
        if TOPIC_REFERENCE in self._topics:
            msg[TOPIC_REFERENCE] = {"t": t, "p": c.ref_p[-1].tolist(), "pd": c.ref_pd[-1].tolist(),
                                    "pdd": c.ref_pdd[-1].tolist()}
        self.writer.write_sample(msg)

    def event(self, t: float, kind: str, text: str) -> None:
        """Record a sparse ``/otbot/events`` message (mode, fault, saturation, note)."""
        self.events.append({"t": float(t), "kind": kind, "text": text})
        if self.writer is not None:
            self.writer.write_event(t, kind, text)

    def _on_saturation(self, ep) -> None:
        self.event(ep.t_start, "saturation", f"{ep.motor} clamped to {ep.limit:g} N m (requested {ep.peak_request:.2f} N m)")
        if self._user_saturation is not None:
            self._user_saturation(ep)

    # -- faults and stopping -----------------------------------------------------------------------
    def _quick_stop(self) -> str | None:
        try:
            self.robot.quick_stop()
        except Exception as exc:  # the bus may be gone: say so, keep the fault
            return f"quick stop failed: {exc}"
        return None

    def _fail(self, v: Violation, stop: bool = True) -> None:
        self.supervisor.latch(v)
        self.fault = self.supervisor.fault
        note = self._quick_stop() if stop else None
        t = max(v.t, self._cols.t[-1]) if self._cols.t else v.t
        self.event(t, "fault", str(self.fault) + (f" ({note})" if note else ""))
        if self.writer is not None:
            self.writer.flush()

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None

    def _progress_text(self, s: Snapshot, est) -> str:
        total = f" of {(self._total - 1) * self.period:.1f}" if self._total else ""
        pos = f", pose ({est.pose[0]:.3f}, {est.pose[1]:.3f}) m, {est.pose[2]:.3f} rad" if est is not None else ""
        return f"t = {s.t:.1f}{total} s{pos}"

    # -- result ------------------------------------------------------------------------------------
    def result(self) -> LoopResult:
        c = self._cols
        n = len(c.t)
        st = self.stats
        st.cycles = n
        st.wall_time = time.perf_counter() - self._t_wall0 if self._t_wall0 is not None else 0.0
        st.robot_time = (c.t[-1] - c.t[0] + self.period) if n else 0.0
        if self._periods:
            p = np.asarray(self._periods)
            st.period_p50, st.period_p99, st.period_max = (float(v) for v in np.percentile(p, [50, 99, 100]))
            st.jitter_rms = float(np.sqrt(np.mean((p - self.period) ** 2)))
            st.overruns = int(np.sum(p > self.supervisor.config.overrun_factor * self.period))
        if self._compute:
            q = np.asarray(self._compute)
            st.compute_p50, st.compute_p99, st.compute_max = (float(v) for v in np.percentile(q, [50, 99, 100]))

        def arr(rows, w):
            return np.array(rows, dtype=float).reshape(n, w)

        rec = Recording(t=np.array(c.t, dtype=float), torque=arr(c.torque, 3), joint_pos=arr(c.pos, 3),
                        joint_vel=arr(c.vel, 3), metadata=dict(self.metadata), events=list(self.events))
        if self._has_imu:
            rec.imu_accel, rec.imu_gyro = arr(c.acc, 3), arr(c.gyro, 3)
        if c.truth:
            x = arr(c.truth, 12)
            rec.truth_q, rec.truth_qd = x[:, :6].copy(), x[:, 6:].copy()
            rec.truth_force = arr(c.force, 2)
        if c.pose:
            rec.estimate_pose, rec.estimate_twist = arr(c.pose, 3), arr(c.twist, 3)
            rec.estimate_std, rec.estimate_gyro_bias = arr(c.std, 6), np.array(c.bias, dtype=float)
        if c.ref_p:
            rec.reference_p, rec.reference_pd, rec.reference_pdd = arr(c.ref_p, 3), arr(c.ref_pd, 3), arr(c.ref_pdd, 3)
        return LoopResult(recording=rec, completed=self.fault is None, stats=st, fault=self.fault,
                          saturation=self.supervisor.limiter.report(), requested=arr(c.requested, 3),
                          u_traj=arr(c.u_traj, 3), u_corr=arr(c.u_corr, 3),
                          feedback=self.feedback.name if self.feedback is not None else None,
                          robot_faults=self.robot_faults)
