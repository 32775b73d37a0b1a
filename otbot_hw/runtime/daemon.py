"""The on-robot daemon: the one loop runner, run indefinitely in real time, commanded over the
control socket, recorded, shown live in Foxglove and watched by systemd (``otbot daemon``,
``docs/daemon.md``).

Threads: the loop runs on the thread that calls ``Daemon.serve`` (the main thread in ``otbot
daemon``); the control server's I/O and dispatch threads call this class's command methods
(``CommandHandler``). Every change of mode runs on the loop thread, between two cycles, handed
over through the ``LoopMailbox``; ``estop`` alone acts from the I/O thread, through the runner's
thread-safe ``trip`` (it wakes the loop's real-time wait, which quick-stops before anything else).

Modes (``MODES``) and what moves between them:

=========  =====================================================================================
idle       drives unpowered (start, ``disable``, every fault). ``enable`` (fault-free) -> hold.
hold       computed-torque hold of a pose (``StopTrajectory``: from the motion it takes over, the
           velocity decays within the acceleration limits, then the pose is held). ``hold``/``stop``
           from any powered mode, the end of a track or an excitation, the velocity deadman.
track      a scenario (moved rigidly to start where the robot is held) or a trajectory CSV (ground
           frame; it must start within ``START_TOLERANCE`` of the held pose). Only from hold, at rest.
velocity   a commanded twist (``TwistReference``: bumpless, within the acceleration limits) from hold
           or velocity; no new command within ``daemon.velocity.deadman`` -> ramp to zero and hold.
excite     a torque sequence (recording or CSV) played open loop, from hold at rest; then hold.
=========  =====================================================================================

Every new controller continues the reference acting when it takes over (same pose and velocity
at the same instant), so a change of mode is bumpless. Any fault — the supervisor's checks, the
drives', encoder's and IMU's own, the estimator's, an ``estop``, a recording that fails (disk full,
file too large, I/O error), a control-socket thread that dies — quick-stops the drives, latches
with its cause and leaves the daemon in idle; the loop keeps reading, estimating, recording and
publishing; ``reset`` clears it (faults still present come back), then ``enable``. A dead control
socket also stops the systemd watchdog ping (systemd restarts the daemon: nobody could estop it).

Overruns (a period longer than ``safety.overrun_factor`` periods): while the robot moves (track,
velocity, excite, or a hold still ramping to rest) more than ``safety.max_consecutive_overruns`` in
a row are a fault; at rest (idle, or a hold that has reached its pose) they are a warning, counted
in ``status`` (``overrun_warnings``) and logged once per streak.
"""
from __future__ import annotations

import gc
import logging
import math
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
from otbot_hw.control.trajectories import PlacedTrajectory, StopTrajectory, TrajectoryError
from otbot_hw.json_output import json_safe
from otbot_hw.motors import MOTORS
from otbot_hw.recording import RecordingError
from otbot_hw.robot import Robot, RobotError
from otbot_hw.runtime.control_protocol import ArgumentLimits, CommandRefused, ProtocolError
from otbot_hw.runtime.control_socket import ControlServer, LoopMailbox, Peer
from otbot_hw.runtime.controllers import OpenLoopTorques, TrackingController, TwistReference
from otbot_hw.runtime.daemon_config import DaemonConfig
from otbot_hw.runtime.feedback import EkfFeedback
from otbot_hw.runtime.loop import LoopRunner
from otbot_hw.runtime.session_recording import SessionRecording, os_error_text
from otbot_hw.runtime.supervisor import SafetyConfig, Supervisor, Violation
from otbot_hw.runtime.systemd import Notifier, Watchdog

log = logging.getLogger(__name__)

MODES = ("idle", "hold", "track", "velocity", "excite")
#: The robot is at rest (track, excite and disable need it): estimated speed below REST_SPEED
#: (m/s) and turn rate below REST_TURN (rad/s), and the hold's own ramp finished.
REST_SPEED = 0.01
REST_TURN = 0.02
#: A trajectory CSV (ground frame) must start this close to the held pose: m, rad.
START_TOLERANCE = (0.05, 0.05)
#: How long a command waits for the loop to pick it up (s); after that it is dropped, never late.
LOOP_PICKUP_TIMEOUT = 2.0
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
        self.server = ControlServer(self, settings.daemon.socket, ArgumentLimits(vel.max_linear, vel.max_angular,
                                                                               SCENARIOS),
                                    path=settings.socket_path)
        self.notifier = notifier or Notifier()
        self.watchdog = watchdog or Watchdog(self.notifier)
        self.telemetry = None
        self.runner: LoopRunner | None = None
        self.robot: Robot | None = None
        self.mode = "starting"
        self.mode_text = "starting"
        self.stop_reason: str | None = None
        self._stop = threading.Event()
        self._pending_trip: Violation | None = None
        self._seen_fault: Violation | None = None
        self._fault_texts: tuple[str, ...] = ()
        self._velocity: TwistReference | None = None
        self._last_velocity = 0.0
        self._tracking: TrackingController | None = None
        self._excite: tuple[OpenLoopTorques, float] | None = None
        self._holding: TrackingController | None = None
        self.sessions: list[str] = []
        self.problems: list[str] = []
        self.faults_seen = 0
        self.overrun_warnings = 0
        self._overrun_streak = False
        self._recording_error: str | None = None
        self._t_start = None
        self._next_server_check = 0.0
        self.server.on_failure = self._server_failed

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
        rec_cfg = s.daemon.recording

        def recorder(meta: dict, topics: list):
            try:
                sess = SessionRecording(s.record_dir, meta, topics, rate=1.0 / period,
                                        rotate_size=rec_cfg.rotate_size, rotate_time=rec_cfg.rotate_time,
                                        flush_interval=rec_cfg.flush_interval, format=rec_cfg.format,
                                        on_error=self._recording_failed)
            except (RecordingError, OSError) as exc:  # the folder gone, the disk full at the first file
                self._recording_failed(str(exc) if isinstance(exc, RecordingError)
                                       else f"recording in {s.record_dir}: cannot start: {os_error_text(exc)}")
                return None
            self.sessions.append(sess.session_id)
            return sess

        sup = Supervisor(s.limits, s.safety, period, realtime=True)
        meta = {"source": "otbot daemon", "params": self.params.to_dict(), **(s.metadata or {})}
        self.runner = runner = LoopRunner(
            robot, None, sup, self._new_feedback(s.start_pose, period), metadata=meta, realtime=True,
            stop_at_end=False, record_reference=True, keep_samples=False, continue_after_fault=True,
            recorder=recorder if s.record_dir is not None else None)
        adapter = self._new_adapter(period)
        if adapter is not None:  # its estimate on /otbot/payload, its events and bounds fault through the loop
            runner.payload = adapter
            adapter.on_fault, adapter.on_event = runner.trip, runner.event
        runner.start(enable=False)
        runner.cycle()
        gc.freeze()  # what booting the drives created, too (no collection: that would stall the bus)
        if self._pending_trip is not None:
            runner.trip(self._pending_trip)
        self._set_mode("idle", "idle: drives booted, not powered", notify=False)
        self.notifier.ready(self._status_line())
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
        z, g = np.zeros(3), np.array([0.0, 0.0, 9.81])
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
        from otbot_hw.runtime.controllers import PayloadAdapter

        self.law.adapter = PayloadAdapter(self.law, cfg, period)
        return self.law.adapter

    def _new_feedback(self, pose, period: float) -> EkfFeedback:
        """The pose EKF, starting at ``pose`` (x, y m, alpha rad)."""
        return EkfFeedback(self.params, period, pose, self.settings.estimator)

    # -- every cycle (loop thread) -----------------------------------------------------------
    def _after_cycle(self) -> None:
        r = self.runner
        if r.fault is not self._seen_fault:
            self._on_fault(r.fault)
        self.mailbox.service()
        mode = self.mode
        if mode == "velocity" and time.monotonic() - self._last_velocity > self.settings.daemon.velocity.deadman:
            self._ramp_to_hold(f"deadman: no velocity command for {self.settings.daemon.velocity.deadman:g} s")
        elif mode == "track" and self._tracking.finished(r.t + r.period):
            self._holding, self._tracking = self._tracking, None  # it rests at its end: a hold
            self._set_mode("hold", "hold: track finished")
        elif mode == "excite":
            ctrl, end = self._excite
            if ctrl.origin is not None and r.t + r.period >= ctrl.origin + end:
                self._ramp_to_hold("excitation finished")
        period = r.last_period
        now = time.monotonic()
        sup = r.supervisor
        # the overrun rule (module docstring): a fault only while moving
        sup.realtime = self._moving(r)
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
        if now >= self._next_server_check:  # a server thread that died without saying so
            self._next_server_check = now + 0.25
            if not self.server.alive and not self._stop.is_set() and self.server.failure is None:
                self._server_failed("control socket server stopped")
        if self.telemetry is not None and r.last_snapshot is not None:
            from otbot_hw.runtime.telemetry import TelemetrySample

            ref = r.last_reference
            self.telemetry.publish(TelemetrySample.from_cycle(
                r.last_snapshot, r.last_command if r.armed else None, r.last_estimate,
                ref.p if ref is not None else None, self.mode, self._fault_texts), now)

    def _moving(self, r: LoopRunner) -> bool:
        """Whether the robot is meant to move: track, velocity, excite, or a hold still ramping."""
        mode = self.mode
        if mode in ("track", "velocity", "excite"):
            return True
        if mode == "hold":
            h = self._holding
            return h is None or not h.finished(r.t + r.period)
        return False

    def _recording_failed(self, text: str) -> None:
        """The session recording failed (disk full, file too large, I/O error): a latched fault
        naming the file and the error; the drives quick-stop at the next cycle, the loop and the
        socket stay up. Any thread."""
        self._recording_error = text
        v = Violation("recording", self.runner.t if self.runner is not None else 0.0, text)
        if self.runner is None:
            self._pending_trip = self._pending_trip or v
        else:
            self.runner.trip(v)

    def _server_failed(self, text: str) -> None:
        """The control socket's server died: nobody can estop through it any more. Quick stop and
        latch a fault, tell systemd, and stop the watchdog ping so systemd restarts the daemon.
        Any thread."""
        log.critical("%s: quick stop, fault latched, systemd watchdog ping stopped", text)
        self.watchdog.stop(text)
        v = Violation("control_socket", self.runner.t if self.runner is not None else 0.0,
                      f"{text}: restart the daemon (systemd does, its watchdog no longer pinged)")
        if self.runner is None:
            self._pending_trip = self._pending_trip or v
        else:
            self.runner.trip(v)
        try:
            self.notifier.status(f"FAULT: {text}; watchdog ping stopped")
        except Exception:  # noqa: BLE001
            pass

    def _on_fault(self, fault: Violation | None) -> None:
        self._seen_fault = fault
        if fault is None:
            self._fault_texts = ()
            return
        self.faults_seen += 1
        self._fault_texts = (str(fault),)
        log.error("fault: %s", fault)
        self._velocity = self._tracking = self._excite = None
        self._set_mode("idle", f"idle: fault: {fault}")

    def _set_mode(self, mode: str, text: str, event: bool = True, notify: bool = True) -> None:
        self.mode, self.mode_text = mode, text
        if event:
            self.runner.event(self.runner.t, "mode", text)
        if notify:
            self.notifier.status(self._status_line())
        log.info("mode %s", text)

    def _status_line(self) -> str:
        r = self.runner
        fault = f"; FAULT {r.fault.kind}: {r.fault.text}" if r is not None and r.fault is not None else ""
        return (self.mode_text + fault).replace("\n", " ")[:200]

    # -- mode changes (loop thread) ----------------------------------------------------------
    def _refuse_if_faulted(self) -> None:
        r = self.runner
        if r.fault is not None:
            raise CommandRefused(f"robot is faulted ({r.fault}): reset first")
        if r.last_snapshot is not None and r.last_snapshot.faults:
            raise CommandRefused("robot reports faults (" + "; ".join(map(str, r.last_snapshot.faults))
                                 + "): reset first")

    def _estimate(self):
        est = self.runner.last_estimate
        if est is None:
            raise CommandRefused("no pose estimate yet: the loop has not read the robot")
        return est

    def _at_rest(self) -> bool:
        est = self._estimate()
        held = self._holding is not None and self._holding.finished(self.runner.t + self.runner.period)
        return (held and math.hypot(est.twist[0], est.twist[1]) <= REST_SPEED
                and abs(est.twist[2]) <= REST_TURN)

    def _require_hold_at_rest(self, what: str) -> None:
        self._refuse_if_faulted()
        if self.mode == "idle":
            raise CommandRefused(f"{what}: the drives are not powered: enable first")
        if self.mode != "hold":
            raise CommandRefused(f"{what}: the robot is in {self.mode}: stop first")
        if not self._at_rest():
            est = self._estimate()
            raise CommandRefused(f"{what}: the robot is not at rest yet (speed {math.hypot(*est.twist[:2]):.3f} m/s, "
                                 f"turn {est.twist[2]:.3f} rad/s): wait for the hold")

    def _hold(self, p0, v0, origin: float | None):
        """A hold controller (``StopTrajectory`` from p0 moving at v0, its time 0 at ``origin``) and
        its trajectory; it becomes the one the rest checks refer to."""
        vel = self.settings.daemon.velocity
        traj = StopTrajectory(p0, v0, vel.max_acceleration, vel.max_angular_acceleration)
        ctrl = TrackingController(self.law, traj, self.runner.period, origin=origin)
        self._holding, self._velocity, self._tracking, self._excite = ctrl, None, None, None
        return ctrl, traj

    def _ramp_to_hold(self, reason: str) -> dict:
        """Hold, continuing the acting reference (or, open loop, the estimated motion)."""
        r = self.runner
        rs = r.reference_state()
        if rs is not None:
            origin, ref = rs
            p0, v0 = ref.p, ref.pd
        else:
            est = self._estimate()
            origin, p0, v0 = est.t, est.pose, est.twist
        ctrl, traj = self._hold(p0, v0, origin)
        text = f"hold: {reason}" + (f" (ramp to rest over {traj.stop_time:.2f} s)" if traj.stop_time > 0 else "")
        r.set_controller(ctrl, text)
        self._set_mode("hold", text, event=False)
        return {"mode": "hold", "rest_pose": traj.rest.tolist(), "ramp_s": traj.stop_time}

    def _do_enable(self, peer: Peer) -> dict:
        self._refuse_if_faulted()
        if self.mode != "idle":
            raise CommandRefused(f"already enabled (mode {self.mode})")
        est = self._estimate()
        ctrl, traj = self._hold(est.pose, est.twist, est.t)
        text = f"hold: enabled by {peer}"
        try:
            self.runner.enable(ctrl, text)
        except RobotError as exc:
            self._on_fault(self.runner.fault)
            raise CommandRefused(f"enabling failed: {exc}") from None
        self._set_mode("hold", text, event=False)
        return {"mode": "hold", "pose": traj.rest.tolist()}

    def _do_disable(self, peer: Peer) -> dict:
        if self.mode == "idle":
            return {"mode": "idle"}
        if self.mode != "hold":
            raise CommandRefused(f"disable: the robot is in {self.mode}: stop first (or estop)")
        if not self._at_rest():
            raise CommandRefused("disable: the robot is not at rest yet: wait for the hold (or estop)")
        text = f"idle: disabled by {peer}"
        self._holding = None
        self.runner.disable(text)
        self._set_mode("idle", text, event=False)
        return {"mode": "idle"}

    def _do_hold(self, peer: Peer, what: str) -> dict:
        self._refuse_if_faulted()
        if self.mode == "idle":
            if what == "stop":
                return {"mode": "idle"}
            raise CommandRefused("hold: the drives are not powered: enable first")
        if self.mode == "hold":
            return {"mode": "hold"}
        return self._ramp_to_hold(f"{what} by {peer}")

    def _do_track(self, reference, name: str, kind: str, peer: Peer) -> dict:
        self._require_hold_at_rest("track")
        _, here = self.runner.reference_state()
        if kind == "scenario":
            reference = PlacedTrajectory(reference, here.p)
        else:
            start = reference.sample(np.zeros(1))[0][0]
            d, da = float(np.hypot(*(start[:2] - here.p[:2]))), abs(float(start[2] - here.p[2]))
            if d > START_TOLERANCE[0] or da > START_TOLERANCE[1]:
                raise CommandRefused(f"track: {name} starts at ({start[0]:.3f}, {start[1]:.3f}) m, {start[2]:.3f} rad, "
                                     f"{d:.3f} m and {da:.3f} rad from the held pose ({here.p[0]:.3f}, "
                                     f"{here.p[1]:.3f}) m, {here.p[2]:.3f} rad (tolerance {START_TOLERANCE[0]:g} m, "
                                     f"{START_TOLERANCE[1]:g} rad): drive there first")
        ctrl = TrackingController(self.law, reference, self.runner.period)
        text = f"track: {name} by {peer} ({reference.duration:.1f} s)"
        self.runner.set_controller(ctrl, text)
        self._tracking, self._holding = ctrl, None
        self._set_mode("track", text, event=False)
        return {"mode": "track", "target": name, "duration_s": reference.duration,
                "start": here.p.tolist()}

    def _do_velocity(self, twist, peer: Peer) -> dict:
        self._refuse_if_faulted()
        self._last_velocity = time.monotonic()
        if self.mode == "velocity":
            self._velocity.command(twist)
            return {"mode": "velocity", "twist": list(twist)}
        if self.mode == "idle":
            raise CommandRefused("velocity: the drives are not powered: enable first")
        if self.mode != "hold":
            raise CommandRefused(f"velocity: the robot is in {self.mode}: stop first")
        origin, ref = self.runner.reference_state()
        vel = self.settings.daemon.velocity
        tw = TwistReference(ref.p, ref.pd, self.runner.period, vel.max_acceleration, vel.max_angular_acceleration)
        tw.command(twist)
        ctrl = TrackingController(self.law, tw, self.runner.period, origin=origin)
        text = f"velocity: by {peer}"
        self.runner.set_controller(ctrl, text)
        self._velocity, self._holding = tw, None
        self._set_mode("velocity", text, event=False)
        return {"mode": "velocity", "twist": list(twist)}

    def _do_excite(self, times, torques, path: str, peer: Peer) -> dict:
        self._require_hold_at_rest("excite")
        last = float(np.median(np.diff(times))) if len(times) > 1 else self.runner.period
        ctrl = OpenLoopTorques(torques, times=times)
        end = float(times[-1]) + last
        text = f"excite: {path} by {peer} ({len(times)} rows, {end:.2f} s)"
        self.runner.set_controller(ctrl, text)
        self._excite, self._holding = (ctrl, end), None
        self._set_mode("excite", text, event=False)
        return {"mode": "excite", "rows": len(times), "duration_s": end}

    def _do_reset(self, peer: Peer) -> dict:
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
        self._seen_fault = None
        self._fault_texts = ()
        self._set_mode("idle", f"idle: reset by {peer} (was {was})")
        return {"mode": "idle", "cleared": was}

    def _do_record(self, action: str, peer: Peer) -> dict:
        r = self.runner
        if r.recorder is None:
            raise CommandRefused("record: this daemon records nowhere (no recording folder)")
        failed = r.recording is not None and getattr(r.recording, "error", None) is not None
        if action == "stop":
            w = r.stop_recording()
            if w is None:
                raise CommandRefused("record stop: not recording")
            log.info("recording %s stopped by %s", w.session_id, peer)
            return {"recording": w.status()}
        if failed:  # a session that failed (disk full): closed, a new one may start
            r.stop_recording()
        if r.recording is not None:
            raise CommandRefused(f"record start: already recording ({r.recording.path})")
        self._recording_error = None
        w = r.start_recording()
        if w is None and self._recording_error is not None:
            raise CommandRefused(f"record start: {self._recording_error}")
        r.event(r.t, "mode", self.mode_text)
        return {"recording": w.status() if w is not None else None}

    def _loop_call(self, fn: Callable[[], Any]) -> Any:
        if self.runner is None:
            raise CommandRefused("the daemon is still starting (booting the drives)")
        if self._stop.is_set():
            raise CommandRefused("the daemon is stopping")
        try:
            return self.mailbox.call(fn, timeout=LOOP_PICKUP_TIMEOUT)
        except TimeoutError as exc:
            raise RuntimeError(str(exc)) from None

    # -- CommandHandler (control server threads) ----------------------------------------------
    def status(self, *, peer: Peer) -> dict:
        r = self.runner
        s = r.last_snapshot if r is not None else None
        est = r.last_estimate if r is not None else None
        ref = r.last_reference if r is not None else None
        faults: list = []
        if r is not None and r.fault is not None:
            v = r.fault
            faults.append({"device": "supervisor", "node": None, "kind": v.kind, "code": None, "meaning": v.text,
                           "t": v.t})
        if s is not None:
            faults += [f.to_dict() for f in s.faults]
        mode = self.mode if r is None or r.fault is None else "idle"  # the loop goes idle at its next step
        out = {"mode": mode, "mode_text": self.mode_text, "t": r.t if r is not None else None,
               "faults": faults,
               "drive_states": dict(zip(MOTORS, s.drive_states)) if s is not None else {},
               "loop": r.timing() if r is not None else None,
               "pose": None, "tracking_error": None,
               "recording": r.recording.status() if r is not None and r.recording is not None else None,
               "overrun_warnings": self.overrun_warnings,
               "payload": self._payload_status(),
               "telemetry": self.telemetry.status() if self.telemetry is not None else None}
        if est is not None:
            out["pose"] = {"x": float(est.pose[0]), "y": float(est.pose[1]), "alpha": float(est.pose[2]),
                           "std": [float(v) for v in est.std[:3]],
                           "twist": [float(v) for v in est.twist]}
            if ref is not None and self.mode in ("hold", "track", "velocity"):
                from otbot_hw.runtime.telemetry import wrap_angle

                out["tracking_error"] = {"x": float(ref.p[0] - est.pose[0]), "y": float(ref.p[1] - est.pose[1]),
                                         "alpha": wrap_angle(float(ref.p[2] - est.pose[2]))}
        return json_safe(out)

    def _payload_status(self) -> dict | None:
        """Online payload adaptation: {estimate: {m_p, I_p, x_F, y_F: {value, std, confident}}, state,
        converged_s, switched_s (robot time, s), changes, law, fault}; None when disabled."""
        a = getattr(self.law, "adapter", None)
        if a is None:
            return None
        return {"estimate": a.payload_estimate(), **a.summary()}

    def enable(self, *, peer: Peer) -> dict:
        return self._loop_call(lambda: self._do_enable(peer))

    def disable(self, *, peer: Peer) -> dict:
        return self._loop_call(lambda: self._do_disable(peer))

    def hold(self, *, peer: Peer) -> dict:
        return self._loop_call(lambda: self._do_hold(peer, "hold"))

    def stop(self, *, peer: Peer) -> dict:
        return self._loop_call(lambda: self._do_hold(peer, "stop"))

    def track(self, *, target: str, kind: str, peer: Peer) -> dict:
        from otbot_hw.control.scenarios import build_spec, csv_spec

        try:  # slow work (planning, reading a file) here, off the loop
            spec = build_spec(target, self.params, self.settings.limits) if kind == "scenario" else csv_spec(target)
        except TrajectoryError as exc:
            raise ProtocolError("bad_request", f"track: {exc}") from None
        name = target if kind == "scenario" else Path(target).name
        return self._loop_call(lambda: self._do_track(spec.reference, name, kind, peer))

    def velocity(self, *, vx: float, vy: float, wz: float, peer: Peer) -> dict:
        return self._loop_call(lambda: self._do_velocity((vx, vy, wz), peer))

    def excite(self, *, path: str, peer: Peer) -> dict:
        from otbot_hw.runtime.openloop import TorqueSequenceError, load_torque_sequence

        try:
            times, torques = load_torque_sequence(path)
        except TorqueSequenceError as exc:
            raise ProtocolError("bad_request", f"excite: {exc}") from None
        return self._loop_call(lambda: self._do_excite(times, torques, path, peer))

    def estop(self, *, peer: Peer) -> dict:
        """On the I/O thread: trip the loop (quick stop before anything else, fault latched) and
        wait briefly (at most 5 periods, 0.2 s) for it to confirm."""
        r = self.runner
        v = Violation("estop", r.t if r is not None else 0.0, f"emergency stop by {peer}")
        log.warning("estop by %s", peer)
        if r is None:
            self._pending_trip = v
            return {"latched": True, "stopped": False, "note": "the daemon is starting: applied when the loop starts"}
        r.trip(v)
        end = time.monotonic() + min(0.2, 5 * r.period)
        while (r.fault is None or self._seen_fault is not r.fault) and time.monotonic() < end:
            time.sleep(0.0005)  # until the loop has stopped the drives and gone idle
        return {"latched": True, "stopped": r.fault is not None and not r.armed,
                "fault": str(r.fault) if r.fault is not None else None}

    def reset(self, *, peer: Peer) -> dict:
        return self._loop_call(lambda: self._do_reset(peer))

    def record(self, *, action: str, peer: Peer) -> dict:
        return self._loop_call(lambda: self._do_record(action, peer))

    def shutdown(self, *, peer: Peer) -> dict:
        log.warning("shutdown by %s", peer)
        self.request_stop(f"shutdown by {peer}")
        self.server.close()
        return {"stopping": True}

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
                        "wall_s": wall, "cpu_s": cpu, "pid": os.getpid(), "problems": self.problems})


def _probe_feedback(period: float):
    from otbot_hw.control.computed_torque import TaskState
    from otbot_hw.runtime.controllers import Feedback

    z = np.zeros(3)
    return Feedback(0.0, TaskState(z, z, 0.0), z, period)
