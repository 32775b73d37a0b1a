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

Timing: the loop owns the clock (``otbot_hw.clock``) and hands it to the robot, whose own
multi-cycle sequences (a driver's enable, fault reaction) tick it too. Real time or not is the back
end's declaration (``Robot.lockstep``; a caller's ``realtime`` overrides it): real time paces the
reads at the period against the wall clock (``Pacer``: a real bus); otherwise cycles run back to
back (``Unpaced``: lockstep simulation, faster than real time). Either way the
loop measures each cycle's wall-clock period (between the snapshots' host times, i.e. the SYNCs)
and compute time, jitter and overruns (``LoopStats``), and reports robot time next to wall time.

Running indefinitely (the daemon): ``keep_samples=False`` keeps nothing per sample in memory (the
recording is streamed, timing goes into fixed-size histograms); ``continue_after_fault=True`` keeps
reading, estimating and recording after a fault (no commands) until ``reset()``. A robot whose clock
restarts (``CanopenRobot`` counts from ``enable()``) is continued: the loop's time never goes back.

The runner's parts, each in a module of its own (mixed into ``LoopRunner``; this module keeps the
cycle — read → estimate → supervise → record → control → limit → write — and the pacing):

* ``loop_timing``    — ``LoopStats``, ``TimingHistogram``, overrun accounting, the loop's clock;
* ``loop_recording`` — topics, metadata, the writer, ``start_recording``/``stop_recording``,
  ``event()``, ``BackgroundWriter``, the samples kept in memory;
* ``loop_power``     — ``start``/``enable``/``disable``/``power_down``/``trip``/``reset``, the
  quick stop and the fault latch.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from otbot_hw.clock import clock_for, paced
from otbot_hw.control.computed_torque import TaskState
from otbot_hw.recording import Recording
from otbot_hw.robot import Robot, RobotError, SimulatedRobot, Snapshot
from otbot_hw.runtime.controllers import ControlStep, Controller, Feedback, Reference
from otbot_hw.runtime.feedback import FeedbackUnavailable, StateEstimate
from otbot_hw.runtime.loop_power import LoopPower
from otbot_hw.runtime.loop_recording import BackgroundWriter, LoopRecording
from otbot_hw.runtime.loop_timing import LoopStats, LoopTiming
from otbot_hw.runtime.supervisor import Supervisor, Violation

__all__ = ["LoopResult", "LoopRunner", "LoopStats"]


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


_ZERO3 = np.zeros(3)


class LoopRunner(LoopTiming, LoopRecording, LoopPower):
    """The loop over ``robot`` with ``controller``, ``feedback`` (``EkfFeedback``, ``TruthFeedback`` or
    None for open loop) and ``supervisor``.

    ``path``: MCAP recording to stream (None: in memory only); ``metadata``: extra recording metadata;
    ``realtime``: pace against the wall clock (None: as the robot declares, ``otbot_hw.clock.paced``);
    ``progress(text)``: called about every ``progress_every`` s of robot time; ``stop_at_end``: quick-stop after the last cycle;
    ``record_reference``: record ``/otbot/reference`` (NaN while no controller gives one); default:
    when the first command comes with a reference.

    Between ``start()`` and ``close()`` a caller may drive the cycles itself (``cycle()``, a daemon)
    and swap the controller between them (``set_controller``); ``result()`` then gives what ran.
    ``keep_samples``, ``continue_after_fault``, ``recorder``: see the module docstring.
    """

    def __init__(self, robot: Robot, controller: Controller | None, supervisor: Supervisor, feedback=None,
                 path: str | Path | None = None, metadata: dict | None = None, realtime: bool | None = None,
                 progress: Callable[[str], None] | None = None, progress_every: float = 1.0,
                 stop_at_end: bool = True, record_reference: bool | None = None, keep_samples: bool = True,
                 continue_after_fault: bool = False, recorder: Callable[[dict, list], Any] | None = None,
                 record_in_background: bool = False, record_after_write: bool | None = None):
        self.robot = robot
        self.controller = controller
        self.supervisor = supervisor
        self.feedback = feedback
        self.metadata = dict(metadata or {})
        self.realtime = paced(robot, realtime)
        self.progress = progress
        self.progress_every = progress_every
        self.stop_at_end = stop_at_end
        self.period = float(robot.period)
        self.keep_samples = keep_samples
        self.continue_after_fault = continue_after_fault
        self._init_timing()
        self._init_recording(Path(path) if path is not None else None, recorder, record_reference,
                             record_in_background, record_after_write)
        self._init_power()
        self._k = 0
        self._held: ControlStep | None = None
        self._u_held = np.zeros(3)
        self._u_prev = None
        self._last_est: StateEstimate | None = None
        self._has_truth = None
        self._has_imu = robot.has_imu
        self._truth_force = robot.truth_force if isinstance(robot, SimulatedRobot) else None  # the pivot force
        self._t_last_read = None  # host time of the last read (s; None: the next period is not a loop period)
        # the one clock: this loop's cycles and the robot's own multi-cycle sequences tick it
        self.clock = clock_for(self.period, self.realtime)
        robot.use_clock(self.clock)
        self._next_progress = progress_every
        self._total = None
        self._user_saturation = supervisor.limiter.on_saturation
        supervisor.limiter.on_saturation = self._on_saturation
        # the last cycle, for telemetry and status (read by other threads; replaced, never mutated)
        self.last_snapshot: Snapshot | None = None
        self.last_estimate: StateEstimate | None = None
        self.last_command = None  # otbot_hw.robot.Command
        self.last_reference: Reference | None = None
        self._feedback_started = False
        self.payload = None  # a payload adapter (``message(t)``): recorded on /otbot/payload when set before the first sample

    # -- the cycle ---------------------------------------------------------------------------------
    def set_controller(self, controller: Controller | None, mode: str | None = None) -> None:
        """Swap the controller between two cycles (bumpless: the next command is the new one's)."""
        self.controller = controller
        self.event(self.t, "mode", mode or f"controller: {type(controller).__name__}")

    def reference_state(self):
        """(t, Reference) of the command acting now — where a new controller continues from —
        or None when the acting command has no reference (open loop, unpowered)."""
        held = self._held
        if held is None or held.reference is None:
            return None
        return self.t + self.period, held.reference

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
                self.event(self.t, "mode", "stopped: end of run (quick stop)")
        except BaseException:
            self._quick_stop()
            raise
        finally:
            self.close()
        return self.result()

    def cycle(self, last: bool = False) -> bool:
        """One cycle (see the module docstring); ``last``: record the sample but write no new command.
        Returns False once a fault has stopped the loop (with ``continue_after_fault`` the cycles go on
        reading and recording; commands wait for ``reset()`` and ``enable()``)."""
        ok = self._cycle(last)
        if self._pending_sample is not None:  # the command is out: the sample's turn
            self._write_pending()
        w = self.writer
        if w is not None and w.__class__ is BackgroundWriter:  # the command is out: the writer's turn
            w.wake()
        return ok

    def _cycle(self, last: bool) -> bool:
        if self.fault is not None and not self.continue_after_fault:
            return False
        self._take_trip()
        if self.realtime:
            self.clock.wait(self.wake)  # a trip wakes it
            if self._take_trip() and not self.continue_after_fault:
                return False
        t_ask = time.perf_counter()
        try:
            s = self.robot.read()
        except RobotError as exc:
            if self.fault is None:
                self._fail(Violation("robot", self.t, f"read failed: {exc}"))
            return False
        t_read = time.perf_counter()
        self.read_hist.add(t_read - t_ask)
        s = self._loop_time(s)
        host = s.host_time if s.host_time is not None and math.isfinite(s.host_time) else t_read
        wall_period = None if self._t_last_read is None else host - self._t_last_read
        self._t_last_read = host
        if wall_period is not None:
            self._timing(wall_period)
        if self._has_truth is None:
            self._has_truth = self.robot.truth() is not None
        faulted = self.fault is not None
        fault = None
        if s.faults and not faulted:
            self.robot_faults = tuple(s.faults)
            fault = Violation("robot", s.t, "; ".join(map(str, s.faults)))
        est = None
        if self.feedback is not None and fault is None:
            try:
                if not self._feedback_started:
                    est = self.feedback.start(s, self.robot)
                    self._feedback_started = True
                else:
                    est = self.feedback.step(s, self.robot, self._u_prev if self._u_prev is not None else _ZERO3)
            except self.feedback.faults as exc:
                if not faulted:
                    fault = Violation("estimator_fault", s.t, str(exc) or type(exc).__name__)
            except FeedbackUnavailable as exc:
                if not faulted:
                    fault = Violation("feedback", s.t, str(exc))
        if est is None and (fault is not None or faulted):
            est = self._last_est
        self._last_est = est
        ref = self._held.reference if (self._held is not None and self.armed) else None
        if faulted:
            fault = None
        elif fault is None:
            fault = self.supervisor.check(s.t, s.joint_vel, est, ref, wall_period)
        else:
            fault = self.supervisor.latch(fault)
        self.last_snapshot, self.last_estimate, self.last_reference = s, est, ref
        self._record(s, est, ref)
        self.cycles += 1
        if fault is not None:
            self._fail(fault)
            return False
        if faulted:
            return False
        self._k += 1
        if self.progress is not None and s.t >= self._next_progress:
            self._next_progress += self.progress_every
            self.progress(self._progress_text(s, est))
        if not last and self.armed and self.controller is not None:
            fb = None
            if est is not None:
                fb = Feedback(s.t, TaskState(est.pose, est.twist, est.phi_p), self._u_held, self.period)
            if not self._take_trip():
                self._command(s.t + self.period, fb, s)
            t_done = time.perf_counter() - t_read
            self.compute_hist.add(t_done)
            if self.keep_samples:
                self._compute.append(t_done)
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
        self.last_command = cmd
        self._u_prev = self._u_held
        self._u_held = cmd.commanded
        self._held = step

    def _progress_text(self, s: Snapshot, est) -> str:
        total = f" of {(self._total - 1) * self.period:.1f}" if self._total else ""
        pos = f", pose ({est.pose[0]:.3f}, {est.pose[1]:.3f}) m, {est.pose[2]:.3f} rad" if est is not None else ""
        return f"t = {s.t:.1f}{total} s{pos}"

    # -- result ------------------------------------------------------------------------------------
    def result(self) -> LoopResult:
        """What ran. Without ``keep_samples`` the recording is empty (it went to the writer) and the
        timing comes from the histograms (percentiles to their 10 us bins)."""
        c = self._cols
        n = len(c.t)
        st = self._final_stats(c.t)
        rec = self._recording_result()

        def arr(rows, w):
            return np.array(rows, dtype=float).reshape(n, w)

        return LoopResult(recording=rec, completed=self.fault is None, stats=st, fault=self.fault,
                          saturation=self.supervisor.limiter.report(), requested=arr(c.requested, 3),
                          u_traj=arr(c.u_traj, 3), u_corr=arr(c.u_corr, 3),
                          feedback=self.feedback.name if self.feedback is not None else None,
                          robot_faults=self.robot_faults)
