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
loop measures each cycle's wall-clock period (between the snapshots' host times, i.e. the SYNCs)
and compute time, jitter and overruns (``LoopStats``), and reports robot time next to wall time.

Running indefinitely (the daemon): ``keep_samples=False`` keeps nothing per sample in memory (the
recording is streamed, timing goes into fixed-size histograms, ``TimingHistogram``);
``start(enable=False)`` starts with the drives unpowered and ``enable()``/``disable()`` power them
between cycles (only armed cycles write commands); ``continue_after_fault=True`` keeps reading,
estimating and recording after a fault (no commands) until ``reset()``; ``trip(violation)`` is a
fault raised from another thread (an operator's estop), acted on at once — it also wakes the
real-time wait; ``recorder(metadata, topics)`` makes the writer (a ``SessionRecording``) and
``start_recording``/``stop_recording`` open and close it between cycles. In a real-time loop each
sample is written once the cycle's command is out (``record_after_write``: the JSON and MCAP
encoding and the file I/O no longer sit between the read and the write; the file order is
unchanged, a pending sample goes out before any event, flush or close); ``record_in_background``
writes in a thread of its own instead (``BackgroundWriter``; measured in docs/performance.md: it
costs the process more CPU than it takes off the loop). A robot whose clock
restarts (``CanopenRobot`` counts from ``enable()``) is continued: the loop's time never goes back.
"""
from __future__ import annotations

import math
import threading
from collections import deque
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from otbot_hw.control.computed_torque import TaskState
from otbot_hw.recording import (TOPIC_COMMAND, TOPIC_ESTIMATE, TOPIC_EVENTS, TOPIC_IMU, TOPIC_JOINTS,
                                TOPIC_PAYLOAD, TOPIC_REFERENCE, TOPIC_TRUTH, Recording, RecordingWriter,
                                source_metadata)
from otbot_hw.robot import Robot, RobotError, SimulatedRobot, Snapshot
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


class TimingHistogram:
    """Durations (s) counted in ``resolution``-wide bins up to ``span`` (longer ones in the last bin,
    their maximum kept): percentiles of a loop that runs all day in fixed memory, O(1) per cycle."""

    def __init__(self, resolution: float = 1e-5, span: float = 1.0):
        self.resolution = float(resolution)
        self.bins = [0] * (int(span / resolution) + 1)
        self.count = 0
        self.max = 0.0
        self.total = 0.0
        self.total_sq = 0.0

    def add(self, value: float) -> None:
        i = int(value / self.resolution)
        bins = self.bins
        bins[i if i < len(bins) else -1] += 1
        self.count += 1
        self.total += value
        self.total_sq += value * value
        if value > self.max:
            self.max = value

    def percentiles(self, qs) -> list[float]:
        """Upper bin edges at the percentiles ``qs`` (0..100); NaN while empty."""
        if not self.count:
            return [math.nan for _ in qs]
        counts = np.cumsum(np.asarray(self.bins))  # a copy: safe against the loop adding meanwhile
        n = counts[-1]
        out = []
        for q in qs:
            i = int(np.searchsorted(counts, max(1, math.ceil(q / 100.0 * n))))
            out.append(min((i + 1) * self.resolution, self.max) if i < len(self.bins) - 1 else self.max)
        return out


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


class BackgroundWriter:
    """A recording writer (``RecordingWriter``, ``SessionRecording``) fed from the loop thread and
    written by a thread of its own: ``write_sample``/``write_event`` only queue (in order, O(1));
    the JSON encoding, MCAP framing, file writes and flushes run in the ``recording-writer`` thread,
    which drains the queue when ``wake()`` is called — the loop calls it once its cycle has written
    its command, so the writer holds the interpreter while the loop waits for the next period, not
    in the middle of its compute — at the latest every ``interval`` s, and at once when
    ``flush()``/``close()`` ask.
    ``flush()`` and ``close()`` return once everything queued before them is written (and flushed);
    more than ``max_queue`` waiting samples (a stalled disk) make ``write_sample`` wait for the
    writer, as writing in the loop did. An exception the writer raises is re-raised by the next call
    from the loop. Other attributes (``path``, ``error``, ``status()``, ...) are the writer's."""

    def __init__(self, writer, interval: float = 0.1, max_queue: int = 10000):
        self.writer = writer
        self.interval = float(interval)
        self.max_queue = int(max_queue)
        self._q: deque = deque()
        self._cv = threading.Condition()
        self._go = threading.Event()
        self._done = 0  # items written so far
        self._queued = 0  # items queued so far
        self._failure: BaseException | None = None
        self._closing = False
        self._thread = threading.Thread(target=self._run, name="recording-writer", daemon=True)
        self._thread.start()

    def wake(self) -> None:
        """Let the writer write what is queued (the loop's cycle is done)."""
        self._go.set()

    def __getattr__(self, name):
        return getattr(self.__dict__["writer"], name)

    def write_sample(self, messages: dict) -> None:
        self._check()
        self._q.append((0, messages))
        self._queued += 1
        if len(self._q) > self.max_queue:
            self._wait(self._queued - self.max_queue // 2)

    def write_event(self, t: float, kind: str, text: str, **extra) -> None:
        self._check()
        self._q.append((1, (t, kind, text, extra)))
        self._queued += 1

    def flush(self) -> None:
        """Everything queued so far written and flushed to the file (waits for the writer)."""
        self._check()
        self._q.append((2, None))
        self._queued += 1
        self._wait(self._queued)
        self._check()

    def close(self) -> None:
        """Write what is queued, close the writer and end the thread."""
        self._q.append((3, None))
        self._queued += 1
        self._closing = True
        self._go.set()
        self._thread.join()
        self._check()

    def _check(self) -> None:
        if self._failure is not None:
            exc, self._failure = self._failure, None
            raise exc

    def _wait(self, n: int) -> None:
        self._go.set()
        with self._cv:
            while self._done < n and self._thread.is_alive():
                self._cv.wait(0.1)

    def _run(self) -> None:
        w, q = self.writer, self._q
        while True:
            if not self._closing:
                self._go.wait(self.interval)
                self._go.clear()
            while q:
                what, item = q.popleft()
                try:
                    if what == 0:
                        w.write_sample(item)
                    elif what == 1:
                        t, kind, text, extra = item
                        w.write_event(t, kind, text, **extra)
                    elif what == 2:
                        w.flush()
                    else:
                        w.close()
                except BaseException as exc:  # noqa: BLE001 - handed to the loop thread
                    if self._failure is None:
                        self._failure = exc
                self._done += 1
                if what >= 2:
                    with self._cv:
                        self._cv.notify_all()
                    if what == 3:
                        return
            if self._done >= self._queued - self.max_queue // 2:
                with self._cv:
                    self._cv.notify_all()


_NAN3 = np.full(3, np.nan)
_ZERO3 = np.zeros(3)
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
    ``keep_samples``, ``continue_after_fault``, ``recorder``: see the module docstring.
    """

    def __init__(self, robot: Robot, controller: Controller | None, supervisor: Supervisor, feedback=None,
                 path: str | Path | None = None, metadata: dict | None = None, realtime: bool = False,
                 progress: Callable[[str], None] | None = None, progress_every: float = 1.0,
                 stop_at_end: bool = True, record_reference: bool | None = None, keep_samples: bool = True,
                 continue_after_fault: bool = False, recorder: Callable[[dict, list], Any] | None = None,
                 record_in_background: bool = False, record_after_write: bool | None = None):
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
        self._truth_force = robot.truth_force if isinstance(robot, SimulatedRobot) else None  # the pivot force
        self._periods: list[float] = []
        self._compute: list[float] = []
        self._t_last_read = None
        self._t_next = None
        self._t_wall0 = None
        self._next_progress = progress_every
        self._total = None
        self._user_saturation = supervisor.limiter.on_saturation
        supervisor.limiter.on_saturation = self._on_saturation
        self.keep_samples = keep_samples
        self.continue_after_fault = continue_after_fault
        self.recorder = recorder
        self.record_in_background = bool(record_in_background)
        # a sample written after the cycle's command (default: a real-time loop with a recorder)
        self.record_after_write = (recorder is not None and realtime) if record_after_write is None \
            else bool(record_after_write)
        self._pending_sample: dict | None = None
        self.armed = False  # the drives are powered and commands are written
        self.period_hist = TimingHistogram()
        self.jitter_hist = TimingHistogram()
        self.compute_hist = TimingHistogram()
        self.read_hist = TimingHistogram()
        self._overrunning = False
        self.cycles = 0
        self.overruns = 0
        self.last_period: float | None = None
        # the last cycle, for telemetry and status (read by other threads; replaced, never mutated)
        self.last_snapshot: Snapshot | None = None
        self.last_estimate: StateEstimate | None = None
        self.last_command = None  # otbot_hw.robot.Command
        self.last_reference: Reference | None = None
        self._trip: Violation | None = None
        self._trip_lock = threading.Lock()
        self.wake = threading.Event()
        self._t_offset = 0.0
        self._t_prev_raw = None
        self._t_prev = None
        self._topics: set = set()
        self._topic_list: list = []
        self._feedback_started = False
        self.payload = None  # a payload adapter (``message(t)``): recorded on /otbot/payload when set before the first sample
        if not keep_samples:  # the recent events only (they are in the recording)
            self.events = deque(maxlen=1000)

    # -- lifecycle ---------------------------------------------------------------------------------
    def start(self, enable: bool = True) -> None:
        """Enable the robot and write the first command (asked without feedback); with ``enable``
        False the loop starts with the drives unpowered (``enable()`` later)."""
        self._t_wall0 = time.perf_counter()
        if not enable:
            self.event(0.0, "mode", "start: drives disabled"
                                    + (f", feedback {self.feedback.name}" if self.feedback is not None else ""))
            return
        try:
            self.robot.enable()
        except RobotError as exc:
            self._fail(Violation("robot", 0.0, f"enabling failed: {exc}"), stop=True)
            return
        self.armed = True
        self._command(0.0, None, None)
        self.event(0.0, "mode", f"start: {type(self.controller).__name__}"
                                + (f", feedback {self.feedback.name}" if self.feedback is not None else ""))

    @property
    def t(self) -> float:
        """The loop's time (s): that of the last sample (0 before the first)."""
        return self._t_prev if self._t_prev is not None else 0.0

    def set_controller(self, controller: Controller | None, mode: str | None = None) -> None:
        """Swap the controller between two cycles (bumpless: the next command is the new one's)."""
        self.controller = controller
        self.event(self.t, "mode", mode or f"controller: {type(controller).__name__}")

    def enable(self, controller: Controller, mode: str | None = None) -> None:
        """Between cycles: power the drives (``robot.enable()``, a few bus cycles) and hand the next
        command to ``controller``. A failure is latched as a fault (quick stop) and re-raised."""
        if self.fault is not None:
            raise RobotError(f"cannot enable while faulted: {self.fault}")
        try:
            self.robot.enable()
        except RobotError as exc:
            self._fail(Violation("robot", self.t, f"enabling failed: {exc}"))
            raise
        self._interrupted()
        self._no_torque()
        self.armed = True
        self._held = None
        self.set_controller(controller, mode)

    def disable(self, mode: str = "disabled") -> None:
        """Between cycles: remove motor power (``robot.disable()``); no commands until ``enable``."""
        try:
            self._unpowered(self.robot.disable)
        finally:
            self.event(self.t, "mode", mode)

    def _unpowered(self, operation: Callable[[], None]) -> None:
        """A drive operation between cycles after which nothing is commanded (it runs bus cycles of
        its own: the next period is not a loop period)."""
        self.armed = False
        self._held = None
        self._no_torque()
        try:
            operation()
        finally:
            self._interrupted()

    def power_down(self, text: str) -> list[str]:
        """Between cycles, when the loop ends for good: quick stop (if the drives are powered), then
        disable; recorded as a mode event. Never raises: returns what could not be done."""
        problems = []
        if self.armed:
            self.armed = False
            note = self._quick_stop()
            if note:
                problems.append(note)
        try:
            self.robot.disable()
        except Exception as exc:  # noqa: BLE001 - the bus may be gone: say so
            problems.append(f"disable failed: {exc}")
        self._held = None
        self._no_torque()
        self.event(self.t, "mode", text + (f" ({'; '.join(problems)})" if problems else ""))
        return problems

    def trip(self, v: Violation) -> None:
        """A fault from another thread (e.g. an estop): quick stop and latch at once — before the next
        read, and before any command not yet written. Thread-safe; wakes a real-time wait."""
        with self._trip_lock:
            if self._trip is None:
                self._trip = v
        self.wake.set()

    def _take_trip(self) -> bool:
        """Act on a pending ``trip``; returns whether the loop is (now) faulted."""
        if self._trip is not None:
            with self._trip_lock:
                v, self._trip = self._trip, None
            if v is not None:
                self._fail(v)
        return self.fault is not None

    def reset(self, feedback=None) -> None:
        """Clear the latched fault (``robot.fault_reset()``, the supervisor's latch); the drives stay
        unpowered. ``feedback``: a new state source (an estimator that faulted starts again)."""
        self._unpowered(self.robot.fault_reset)
        self.supervisor.reset()
        self.fault = None
        self.robot_faults = ()
        if feedback is not None:
            self.feedback = feedback
            self._feedback_started = False
        self.event(self.t, "mode", "reset")

    def pause(self) -> None:
        """The caller held the loop up on purpose (a warm-up): the next period is not a loop period."""
        self._interrupted()

    def _no_torque(self) -> None:
        """The drives produce no torque from now on: what is recorded as commanded and what the
        estimator is told acted."""
        self._u_held = self._u_prev = np.zeros(3)

    def _interrupted(self) -> None:
        """A drive operation ran bus cycles of its own: the next period is not a loop period."""
        self._t_last_read = None
        self._t_next = None

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

    def _write_pending(self) -> None:
        msg, self._pending_sample = self._pending_sample, None
        if msg is not None and self.writer is not None:
            self.writer.write_sample(msg)

    def _cycle(self, last: bool) -> bool:
        if self.fault is not None and not self.continue_after_fault:
            return False
        self._take_trip()
        if self.realtime:
            now = time.perf_counter()
            self._t_next = now if self._t_next is None else max(self._t_next + self.period, now)
            delay = self._t_next - time.perf_counter()
            if delay > 0:
                self.wake.wait(delay)
                self.wake.clear()
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

    def _loop_time(self, s: Snapshot) -> Snapshot:
        """The snapshot on the loop's clock: a robot clock that restarts (at ``enable()``) is
        continued one period after the last sample."""
        raw = s.t
        if self._t_prev_raw is not None and raw + self._t_offset <= self._t_prev + 1e-9 * self.period:
            self._t_offset = self._t_prev + self.period - raw
        self._t_prev_raw = raw
        t = raw + self._t_offset
        self._t_prev = t
        return s if self._t_offset == 0.0 else replace(s, t=t)

    def _timing(self, wall_period: float) -> None:
        self.last_period = wall_period
        self.period_hist.add(wall_period)
        self.jitter_hist.add(abs(wall_period - self.period))
        if wall_period > self.supervisor.config.overrun_factor * self.period:
            self.overruns += 1
            if not self._overrunning and self.realtime and not self.keep_samples:  # a streak starts: say when
                self.event(self.t, "overrun", f"period {wall_period * 1e3:.2f} ms (target {self.period * 1e3:.2f} ms)")
            self._overrunning = True
        else:
            self._overrunning = False
        if self.keep_samples:
            self._periods.append(wall_period)

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

    def timing(self) -> dict:
        """Timing so far (any thread): rate (Hz), period {target, p50, p99, max}, jitter (|period -
        target|) {p50, p99, max}, compute {p50, p99} (read's return to write's), read {p50, p99}
        (``robot.read()``: SYNC to every TPDO and the IMU) (s), overruns, cycles."""
        p50, p99 = self.period_hist.percentiles((50, 99))
        j50, j99 = self.jitter_hist.percentiles((50, 99))
        c50, c99 = self.compute_hist.percentiles((50, 99))
        r50, r99 = self.read_hist.percentiles((50, 99))
        f = lambda v: None if not math.isfinite(v) else float(v)  # noqa: E731
        return {"rate": 1.0 / self.period, "period": {"target": self.period, "p50": f(p50), "p99": f(p99),
                                                      "max": f(self.period_hist.max) if self.period_hist.count else None},
                "jitter": {"p50": f(j50), "p99": f(j99),
                           "max": f(self.jitter_hist.max) if self.jitter_hist.count else None},
                "compute": {"p50": f(c50), "p99": f(c99)}, "read": {"p50": f(r50), "p99": f(r99)},
                "overruns": self.overruns, "cycles": self.cycles}

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
        if self.payload is not None:
            topics.append(TOPIC_PAYLOAD)
        self._topics = set(topics)
        self._topic_list = topics
        meta = {**source_metadata(program="loop"), "sample_period": self.period, "realtime": self.realtime,
                **self.metadata}
        if self._has_imu and self.robot.imu_rate:
            meta.setdefault("imu_rate", float(self.robot.imu_rate))
        if self.feedback is not None:
            meta.setdefault("feedback", self.feedback.name)
        self.metadata = meta
        if self.path is not None:
            self.writer = RecordingWriter(self.path, meta, topics=topics)
        elif self.recorder is not None:
            self.writer = self._background(self.recorder(meta, topics))
        if self.writer is not None:
            for ev in self.events:
                self.writer.write_event(ev["t"], ev["kind"], ev["text"])

    def _background(self, writer):
        """The recorder's writer, written from its own thread when ``record_in_background``."""
        if writer is None or not self.record_in_background:
            return writer
        return BackgroundWriter(writer)

    @property
    def recording(self):
        """The writer samples go to (None: not recording)."""
        return self.writer

    def start_recording(self):
        """Between cycles: open a new recording with ``recorder`` (the same topics and metadata);
        returns the writer. Before the first sample the recording opens with it anyway."""
        if self.recorder is None:
            raise RuntimeError("this loop has no recorder")
        if self.writer is not None:
            raise RuntimeError("already recording")
        if not self._topics:
            return None
        self.writer = self._background(self.recorder(self.metadata, self._topic_list))
        return self.writer

    def stop_recording(self):
        """Between cycles: close the current recording (complete, with its summary); returns it."""
        self._write_pending()
        w, self.writer = self.writer, None
        if w is not None:
            w.close()
        return w

    def _record(self, s: Snapshot, est: StateEstimate | None, ref) -> None:
        if not self._topics:
            self._open_writer(est, ref)
        held = self._held
        acc = s.imu_accel if s.imu_accel is not None else _NAN3
        gyro = s.imu_gyro if s.imu_gyro is not None else _NAN3
        truth = self.robot.truth() if self._has_truth else None
        force = (self._truth_force() if self._truth_force is not None else _ZERO2) if self._has_truth else None
        e = est if est is not None else self._last_est
        r = ref if ref is not None else _NO_REFERENCE  # e.g. open loop before a tracking controller
        if self.keep_samples:
            c = self._cols
            c.t.append(s.t)
            c.torque.append(self._u_held)
            c.requested.append(held.u if held is not None else self._u_held)
            c.u_traj.append(held.u_traj if held is not None and held.u_traj is not None else _NAN3)
            c.u_corr.append(held.u_corr if held is not None and held.u_corr is not None else _NAN3)
            c.pos.append(s.joint_pos)
            c.vel.append(s.joint_vel)
            c.acc.append(acc)
            c.gyro.append(gyro)
            if self._has_truth:
                c.truth.append(truth)
                c.force.append(force)
            if TOPIC_ESTIMATE in self._topics:
                c.pose.append(e.pose)
                c.twist.append(e.twist)
                c.std.append(e.std)
                c.bias.append(e.gyro_bias)
            if TOPIC_REFERENCE in self._topics:
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
            msg[TOPIC_TRUTH] = {"t": t, "q": truth[:6].tolist(), "qd": truth[6:].tolist(), "force": force.tolist()}
        if TOPIC_ESTIMATE in self._topics:
            msg[TOPIC_ESTIMATE] = {"t": t, "pose": e.pose.tolist(), "twist": e.twist.tolist(),
                                   "std": e.std.tolist(), "gyro_bias": float(e.gyro_bias)}
        if TOPIC_REFERENCE in self._topics:
            msg[TOPIC_REFERENCE] = {"t": t, "p": r.p.tolist(), "pd": r.pd.tolist(), "pdd": r.pdd.tolist()}
        if TOPIC_PAYLOAD in self._topics:
            msg[TOPIC_PAYLOAD] = self.payload.message(t)
        if self.record_after_write:
            self._pending_sample = msg
        else:
            self.writer.write_sample(msg)

    def event(self, t: float, kind: str, text: str) -> None:
        """Record a sparse ``/otbot/events`` message (mode, fault, saturation, note)."""
        self.events.append({"t": float(t), "kind": kind, "text": text})
        if self.writer is not None:
            if self._pending_sample is not None:  # the sample of this cycle first, as it happened
                self._write_pending()
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
        self.armed = False
        note = self._quick_stop() if stop else None
        if self.continue_after_fault:  # the cycles go on: they record (and estimate with) no torque
            self._no_torque()
        self._interrupted()
        t = max(v.t, self.t)
        self.event(t, "fault", str(self.fault) + (f" ({note})" if note else ""))
        if self.writer is not None:
            self._write_pending()
            self.writer.flush()

    def close(self) -> None:
        if self.writer is not None:
            self._write_pending()
            self.writer.close()
            self.writer = None

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
        st = self.stats
        st.cycles = n
        st.wall_time = time.perf_counter() - self._t_wall0 if self._t_wall0 is not None else 0.0
        st.robot_time = (c.t[-1] - c.t[0] + self.period) if n else 0.0
        if not self.keep_samples:
            st.cycles = self.cycles
            st.robot_time = self.cycles * self.period
            if self.period_hist.count:
                st.period_p50, st.period_p99 = self.period_hist.percentiles((50, 99))
                st.period_max = self.period_hist.max
                st.jitter_rms = math.sqrt(self.jitter_hist.total_sq / self.jitter_hist.count)
                st.overruns = self.overruns
            if self.compute_hist.count:
                st.compute_p50, st.compute_p99 = self.compute_hist.percentiles((50, 99))
                st.compute_max = self.compute_hist.max
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
