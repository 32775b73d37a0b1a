"""The on-robot daemon: the one loop runner, run indefinitely in real time, commanded over the
control socket, recorded, shown live in Foxglove and watched by systemd (``otbot daemon``,
``docs/daemon.md``).

Threads: the loop runs on the thread that calls ``Daemon.serve`` (the main thread in ``otbot
daemon``); the control server's I/O and dispatch threads call the command handlers
(``daemon_commands.DaemonCommands``, a ``CommandHandler``). Every change of mode runs on the loop thread, between two cycles, handed
over through the ``LoopMailbox``; ``estop`` alone acts from the I/O thread, through the runner's
thread-safe ``trip`` (it wakes the loop's real-time wait, which quick-stops before anything else).

Parts (each its own module): the mode machine, a registry of controllers switched only between
two cycles (``daemon_modes``: idle, hold, track, velocity, excite; ``MODES``); the command handlers
the control server calls (``daemon_commands``); the recording sessions (``daemon_sessions``). This
module holds the life cycle (boot, loop, stop), the per-cycle supervision (faults, overruns, the
systemd watchdog, the control server's health) and telemetry.

A change of mode is bumpless (``daemon_modes``). Any fault — the supervisor's checks, the
drives', encoder's and IMU's own, the estimator's, an ``estop``, a recording that fails (disk full,
file too large, I/O error), a control-socket thread that dies — quick-stops the drives, latches
with its cause and leaves the daemon in idle; the loop keeps reading, estimating, recording and
publishing; ``reset`` clears it (faults still present come back), then ``enable``. A dead control
socket also stops the systemd watchdog ping (systemd restarts the daemon: nobody could estop it).

Overruns (a period longer than ``safety.overrun_factor`` periods): while the robot moves (track,
velocity, excite, or a hold still ramping to rest) more than ``safety.max_consecutive_overruns`` in
a row are a fault; at rest (idle, or a hold that has reached its pose) they are a warning, counted
in ``status`` (``overrun_warnings``) and logged once per streak. A loop that fills its core still
leaves the operator's threads their share (``scheduling.OperatorShare``).
"""
from __future__ import annotations

import gc
import logging
import os
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, ContextManager

import numpy as np

from otbot_hw.control.computed_torque import ComputedTorqueController
from otbot_hw.control.gains import gains_from_tstab
from otbot_hw.control.trajectories import StopTrajectory
from otbot_hw.json_output import json_safe
from otbot_hw.model.constants import GRAVITY
from otbot_hw.recording import source_metadata
from otbot_hw.robot import Robot
from otbot_hw.runtime import scheduling
from otbot_hw.runtime.control_protocol import ArgumentLimits
from otbot_hw.runtime.control_peers import Peer
from otbot_hw.runtime.control_socket import ControlServer
from otbot_hw.runtime.loop_mailbox import LoopMailbox
from otbot_hw.runtime.controllers import TrackingController
from otbot_hw.runtime.daemon_commands import LOOP_PICKUP_TIMEOUT, DaemonCommands  # noqa: F401 (re-exported)
from otbot_hw.runtime.daemon_config import DaemonConfig
from otbot_hw.runtime.daemon_modes import MODES, REST_SPEED, REST_TURN, START_TOLERANCE, ModeMachine  # noqa: F401
from otbot_hw.runtime.daemon_sessions import DaemonRecordings
from otbot_hw.runtime.feedback import EkfFeedback
from otbot_hw.runtime.loop import LoopRunner
from otbot_hw.runtime.loop_trace import from_env as loop_trace_from_env
from otbot_hw.runtime.supervisor import SafetyConfig, Supervisor, Violation
from otbot_hw.runtime.systemd import Notifier, Watchdog

log = logging.getLogger(__name__)
#: s: how long the loop thread may wait for the interpreter lock held by another thread (Python's
#: default is 5 ms: longer than the jitter the loop is allowed).
GIL_SWITCH_INTERVAL = 0.0002


@dataclass
class DaemonSettings:
    """What the daemon runs with. ``model``: the controller's ``OtbotParams`` or ``ExtendedModel``
    (effects compensated); ``limits``: motor ``MotorLimits``; ``safety``: the supervisor's
    ``SafetyConfig``; ``estimator``: the EKF's ``EstimatorConfig``; ``daemon``: the ``daemon:``
    section; ``record_dir`` (None: no recording); ``telemetry``: (host, port) or None;
    ``start_pose`` (x, y m, alpha rad): where the robot stands at start (defines the frame B);
    ``t_stab`` (s): the controller's stabilization time; ``metadata``: added to every recording."""

    model: Any
    limits: Any
    safety: SafetyConfig
    estimator: Any
    daemon: DaemonConfig
    socket_path: Path | None = None
    record_dir: Path | None = None
    telemetry: tuple[str, int] | None = None
    start_pose: tuple[float, float, float] = (0.0, 0.0, 0.0)
    t_stab: float = 3.0
    metadata: dict | None = None


class Daemon:
    """The daemon (see the module docstring). ``serve(open_robot)`` binds the control socket
    (refusing if another daemon holds it), opens the robot (``open_robot()``: a context manager
    yielding an opened ``Robot``), notifies systemd (READY=1 once the drives are booted), runs the
    loop until ``request_stop`` (SIGTERM, SIGINT, ``shutdown``), then quick-stops, disables and
    closes the recording; returns a summary."""

    def __init__(self, settings: DaemonSettings, notifier: Notifier | None = None,
                 watchdog: Watchdog | None = None, period: float = 0.01):
        from otbot_hw.control.scenarios import SCENARIOS

        self.settings = settings
        self._period_hint = float(period)  # the loop period the robot will have (s), for the warm-up
        self.params = getattr(settings.model, "params", settings.model)
        self.law = ComputedTorqueController(settings.model, gains_from_tstab(settings.t_stab))
        vel = settings.daemon.velocity
        self.mailbox = LoopMailbox()
        self.server = ControlServer(DaemonCommands(self), settings.daemon.socket,
                                    ArgumentLimits(vel.max_linear, vel.max_angular, SCENARIOS),
                                    path=settings.socket_path)
        self.notifier = notifier or Notifier()
        self.watchdog = watchdog or Watchdog(self.notifier)
        self.modes = ModeMachine(self.law, vel, self.notifier.status)
        self.recordings = DaemonRecordings(self)
        self.telemetry = None
        self.scheduling: dict | None = None  # what serve() did: cpus, policy, the loop's and operator's priority
        self.runner: LoopRunner | None = None
        self.robot: Robot | None = None
        self.stop_reason: str | None = None
        self._stop = threading.Event()
        self.pending_trip: Violation | None = None  # a trip before the loop runs (estop, failure at start)
        self.seen_fault: Violation | None = None  # the runner's fault this daemon has reacted to
        self._fault_texts: tuple[str, ...] = ()
        self.problems: list[str] = []
        self.faults_seen = 0
        self.overrun_warnings = 0
        self._overrun_streak = False
        self.operator_share = scheduling.OperatorShare()  # active once serve() lowered the operator's threads
        self._t_start = None
        self._next_server_check = 0.0
        self.server.on_failure = self._server_failed

    @property
    def mode(self) -> str:
        """The current mode (``daemon_modes.MODES``, or "starting")."""
        return self.modes.mode

    @mode.setter
    def mode(self, value: str) -> None:
        self.modes.mode = value

    @property
    def sessions(self) -> list[str]:
        return self.recordings.sessions

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def _at_rest(self) -> bool:
        return self.modes.at_rest()

    # -- life cycle ------------------------------------------------------------------------
    def request_stop(self, reason: str) -> None:
        """End the loop (any thread, signal handlers included): quick stop, disable, exit."""
        if self.stop_reason is None:
            self.stop_reason = reason
        self._stop.set()
        if self.runner is not None:
            self.runner.wake.set()

    def serve(self, open_robot: Callable[[], ContextManager[Robot]]) -> dict:
        """Run the daemon (on the calling thread) until ``request_stop``; returns the summary."""
        from otbot_hw.runtime.telemetry import TelemetryServer

        s = self.settings
        self._t_start = (time.monotonic(), time.process_time())
        sched = s.daemon.scheduling
        if sched.cpus is not None:  # before any thread starts: they inherit it (pin() moves the others)
            scheduling.pin(scheduling.check_cpus(sched.cpus))
        before = scheduling.tasks()
        self.server.start()  # SocketInUse: another daemon runs here; nothing else touched yet
        switch = sys.getswitchinterval()
        # A thread waiting for the interpreter lock asks the holder to let go after this interval:
        # 5 ms by default, i.e. a loop waking while a command thread builds a reply could start its
        # cycle up to 5 ms late. The loop's threads wait on I/O almost all the time, so a short
        # interval costs little.
        sys.setswitchinterval(GIL_SWITCH_INTERVAL)
        try:
            if s.telemetry is not None:
                host, port = s.telemetry
                self.telemetry = TelemetryServer(host, port, s.daemon.telemetry.rate, limits=s.limits.max_torque,
                                                 l1=self.params.l1)
            # the operator's threads (control socket's dispatch, telemetry and its server's workers) below the loop's
            # ... but the control socket's I/O thread, where estop acts the moment it is parsed
            io = self.server.io_thread_id
            self.scheduling = {**scheduling.lower_operators(scheduling.tasks() - before - {io},
                                                            sched.operator_threads_below), "estop_thread": io}
            self.operator_share.active = self.scheduling["operator_priority"] < self.scheduling["priority"]
            self._warm_up(self._period_hint)
            with open_robot() as robot:
                self.robot = robot
                self._run(robot)
        finally:
            for what, step in (("systemd", lambda: self.notifier.stopping(f"stopping: {self.stop_reason or 'error'}")),
                               ("control socket", self.server.close),
                               ("telemetry", lambda: self.telemetry is not None and self.telemetry.close())):
                try:
                    step()
                except Exception as exc:  # noqa: BLE001 - a stop path says what failed, never raises
                    self.problems.append(f"closing {what} failed: {type(exc).__name__}: {exc}")
            sys.setswitchinterval(switch)
        return self.summary()

    def _run(self, robot: Robot) -> None:
        s = self.settings
        period = robot.period
        sup = Supervisor(s.limits, s.safety, period, realtime=True)
        meta = {**source_metadata(program="otbot daemon"), "params": self.params.to_dict(), **(s.metadata or {})}
        self.runner = runner = LoopRunner(
            robot, None, sup, self._new_feedback(s.start_pose, period), metadata=meta, realtime=True,
            stop_at_end=False, record_reference=True, keep_samples=False, continue_after_fault=True,
            recorder=self.recordings.recorder(period))
        self.modes.runner = runner
        adapter = self._new_adapter(period)
        if adapter is not None:  # its estimate on /otbot/payload, its events and bounds fault through the loop
            runner.payload = adapter
            adapter.on_fault, adapter.on_event = runner.trip, runner.event
        trace = loop_trace_from_env(period, sup.config.overrun_factor)  # a measurement aid, off by default
        if trace is not None:
            trace.install(self, robot, runner)
        runner.start(enable=False)
        runner.cycle()
        gc.freeze()  # what booting the drives created, too (no collection: that would stall the bus)
        if self.pending_trip is not None:
            runner.trip(self.pending_trip)
        self.modes.set_mode("idle", "idle: drives booted, not powered", notify=False)
        self.notifier.ready(self.modes.status_line())
        log.info("ready: %s Hz, socket %s", 1.0 / period, self.server.path)
        try:
            while not self._stop.is_set():
                runner.cycle()
                self._after_cycle()
        finally:
            self.problems += runner.power_down(f"idle: stopped ({self.stop_reason or 'error'})")
            self.mode = "idle"
            try:
                runner.close()
            except Exception as exc:  # noqa: BLE001 - the recording's close: said, never raised
                self.problems.append(f"closing the recording failed: {type(exc).__name__}: {exc}")
            if trace is not None:
                try:
                    trace.close()
                except Exception as exc:  # noqa: BLE001 - a measurement aid never fails the daemon
                    self.problems.append(f"writing the loop trace failed: {type(exc).__name__}: {exc}")

    def _warm_up(self, period: float) -> None:
        """Before the robot is opened: everything the first cycles run once — the EKF's compiled
        kernels, the law and its prediction, the recording and telemetry libraries — then a full
        collection and the heap frozen out of the garbage collector. Loading compiled code or
        collecting the whole heap holds the interpreter for 0.1-1 s: in a cycle it is an overrun;
        once the drives are booted it starves the master's heartbeat thread, and the drives stop."""
        import foxglove.messages  # noqa: F401 - imported by the first telemetry publish
        import mcap.writer  # noqa: F401 - imported by the first recording

        from otbot_hw.robot import Snapshot

        fb = self._new_feedback(self.settings.start_pose, period)
        z, g = np.zeros(3), np.array([0.0, 0.0, GRAVITY])
        for k in range(3):
            snap = Snapshot(t=k * period, cycle=k, host_time=0.0, joint_pos=z, joint_vel=z, joint_torque=z,
                            imu_accel=g, imu_gyro=z, imu_time=float(k))
            est = fb.start(snap, None) if k == 0 else fb.step(snap, None, z)
        TrackingController(self.law, StopTrajectory(est.pose), period).update(period, _probe_feedback(period), snap)
        self._new_adapter(period)
        gc.collect()
        gc.freeze()

    def _new_adapter(self, period: float):
        """Online payload adaptation (``daemon.adaptation``; None when disabled), on the law from now on."""
        cfg = self.settings.daemon.adaptation
        if cfg is None or not cfg.enabled:
            return None
        from otbot_hw.runtime.payload_adapter import PayloadAdapter

        self.law.adapter = PayloadAdapter(self.law, cfg, period)
        return self.law.adapter

    def _new_feedback(self, pose, period: float) -> EkfFeedback:
        """The pose EKF, starting at ``pose`` (x, y m, alpha rad)."""
        return EkfFeedback(self.params, period, pose, self.settings.estimator)

    # -- every cycle (loop thread) -----------------------------------------------------------
    def _after_cycle(self) -> None:
        r = self.runner
        if r.fault is not self.seen_fault:
            self.on_fault(r.fault)
        self.mailbox.service()
        self.modes.end_of_cycle()
        period = r.last_period
        now = time.monotonic()
        sup = r.supervisor
        # the overrun rule (module docstring): a fault only while moving
        sup.realtime = self.modes.moving()
        if period is None or period <= sup.config.overrun_factor * r.period:
            self.watchdog.cycle_ok(now)
            self._overrun_streak = False
        else:
            self.watchdog.cycle_missed(now)
            if not sup.realtime:
                self.overrun_warnings += 1
                if not self._overrun_streak:
                    log.warning("overrun at rest (%s): period %.2f ms (target %.2f ms); %d so far, a warning "
                                "(a fault only while moving)", self.mode, period * 1e3, r.period * 1e3,
                                self.overrun_warnings)
                self._overrun_streak = True
        self.operator_share.after_cycle(r.clock, now)
        if now >= self._next_server_check:  # a server thread that died without saying so
            self._next_server_check = now + 0.25
            if not self.server.alive and not self._stop.is_set() and self.server.failure is None:
                self._server_failed("control socket server stopped")
        if self.telemetry is not None and r.last_snapshot is not None:  # queued; encoded on its own thread
            ref = r.last_reference
            self.telemetry.publish_cycle(r.last_snapshot, r.last_command if r.armed else None, r.last_estimate,
                                         ref.p if ref is not None else None, self.mode, self._fault_texts, now)

    def _server_failed(self, text: str) -> None:
        """The control socket's server died: nobody can estop through it any more. Quick stop and
        latch a fault, tell systemd, and stop the watchdog ping so systemd restarts the daemon.
        Any thread."""
        log.critical("%s: quick stop, fault latched, systemd watchdog ping stopped", text)
        self.watchdog.stop(text)
        v = Violation("control_socket", self.runner.t if self.runner is not None else 0.0,
                      f"{text}: restart the daemon (systemd does, its watchdog no longer pinged)")
        if self.runner is None:
            self.pending_trip = self.pending_trip or v
        else:
            self.runner.trip(v)
        try:
            self.notifier.status(f"FAULT: {text}; watchdog ping stopped")
        except Exception:  # noqa: BLE001
            pass

    def on_fault(self, fault: Violation | None) -> None:
        """The runner latched ``fault`` (None: it was cleared): counted, logged, the modes to idle."""
        self.seen_fault = fault
        if fault is None:
            self._fault_texts = ()
            return
        self.faults_seen += 1
        self._fault_texts = (str(fault),)
        log.error("fault: %s", fault)
        self.modes.fault(str(fault))

    def reset_faults(self, peer: Peer) -> dict:
        """``reset`` (loop thread): clear the latched fault (a new EKF after an estimator fault)."""
        r = self.runner
        if r.fault is None and not (r.last_snapshot is not None and r.last_snapshot.faults):
            return {"mode": self.mode, "faults": []}
        feedback = None
        if r.fault is not None and r.fault.kind in ("estimator", "estimator_fault", "feedback"):
            est = r.last_estimate
            pose = est.pose if est is not None and np.all(np.isfinite(est.pose)) else self.settings.start_pose
            feedback = self._new_feedback(pose, r.period)
        was = str(r.fault) if r.fault is not None else "robot faults"
        adapter = getattr(self.law, "adapter", None)
        if adapter is not None and r.fault is not None and r.fault.kind == "payload":
            adapter.reset()  # the file's platform parameters (already restored), adaptation starts over
        r.reset(feedback)
        self.seen_fault = None
        self._fault_texts = ()
        self.modes.set_mode("idle", f"idle: reset by {peer} (was {was})")
        return {"mode": "idle", "cleared": was}

    def payload_status(self) -> dict | None:
        """Online payload adaptation: {estimate: {m_p, I_p, x_F, y_F: {value, std, confident}}, state,
        converged_s, switched_s (robot time, s), changes, law, fault}; None when disabled."""
        a = getattr(self.law, "adapter", None)
        if a is None:
            return None
        return {"estimate": a.payload_estimate(), **a.summary()}

    # -- summary -----------------------------------------------------------------------------
    def summary(self) -> dict:
        r = self.runner
        wall = cpu = None
        if self._t_start is not None:
            wall = time.monotonic() - self._t_start[0]
            cpu = time.process_time() - self._t_start[1]
        return json_safe({"stopped": self.stop_reason, "mode": self.mode, "loop": r.timing() if r is not None else None,
                        "fault": r.fault.to_dict() if r is not None and r.fault is not None else None,
                        "faults_seen": self.faults_seen, "sessions": self.sessions,
                        "recording_dir": str(self.settings.record_dir) if self.settings.record_dir else None,
                        "wall_s": wall, "cpu_s": cpu, "pid": os.getpid(), "scheduling": self.scheduling,
                        "problems": self.problems})


def _probe_feedback(period: float):
    from otbot_hw.control.computed_torque import TaskState
    from otbot_hw.runtime.controllers import Feedback

    z = np.zeros(3)
    return Feedback(0.0, TaskState(z, z, 0.0), z, period)
