"""The daemon's mode machine: which controller drives the loop, switched only between two cycles.

Every method here runs on the loop thread (the control socket's requests reach it through the
``LoopMailbox``; see ``otbot_hw.runtime.daemon``), so a switch happens at a cycle boundary: the
loop runner's ``set_controller`` takes the new controller for the next cycle.

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
at the same instant), so a change of mode is bumpless.
"""
from __future__ import annotations

import logging
import math
import time
from typing import Callable

import numpy as np

from otbot_hw.control.trajectories import PlacedTrajectory, StopTrajectory
from otbot_hw.robot import RobotError
from otbot_hw.runtime.control_protocol import CommandRefused
from otbot_hw.runtime.control_peers import Peer
from otbot_hw.runtime.controllers import OpenLoopTorques, TrackingController, TwistReference

log = logging.getLogger("otbot_hw.runtime.daemon")

MODES = ("idle", "hold", "track", "velocity", "excite")
#: The robot is at rest (track, excite and disable need it): estimated speed below REST_SPEED
#: (m/s) and turn rate below REST_TURN (rad/s), and the hold's own ramp finished.
REST_SPEED = 0.01
REST_TURN = 0.02
#: A trajectory CSV (ground frame) must start this close to the held pose: m, rad.
START_TOLERANCE = (0.05, 0.05)


class ModeMachine:
    """The daemon's modes over one ``LoopRunner`` (``runner``, set once the loop starts): ``law`` the
    computed-torque law every tracking controller uses, ``velocity`` the ``daemon.velocity`` section
    (acceleration limits, deadman), ``notify(status_line)`` told every change (systemd STATUS).

    The controllers of the modes (the registry): ``holding`` (hold; also what the rest checks refer
    to), ``tracking``, ``twist`` (velocity), ``excite`` (open-loop torques and their end, s) — at most
    one acting; a switch replaces the runner's controller."""

    def __init__(self, law, velocity, notify: Callable[[str], None]):
        self.law = law
        self.velocity = velocity
        self.notify = notify
        self.runner = None
        self.mode = "starting"
        self.mode_text = "starting"
        self.twist: TwistReference | None = None
        self.last_twist = 0.0  # monotonic s of the last velocity command (the deadman's start)
        self.tracking: TrackingController | None = None
        self.excite: tuple[OpenLoopTorques, float] | None = None
        self.holding: TrackingController | None = None

    # -- bookkeeping ---------------------------------------------------------------------------
    def set_mode(self, mode: str, text: str, event: bool = True, notify: bool = True) -> None:
        self.mode, self.mode_text = mode, text
        if event:
            self.runner.event(self.runner.t, "mode", text)
        if notify:
            self.notify(self.status_line())
        log.info("mode %s", text)

    def status_line(self) -> str:
        r = self.runner
        fault = f"; FAULT {r.fault.kind}: {r.fault.text}" if r is not None and r.fault is not None else ""
        return (self.mode_text + fault).replace("\n", " ")[:200]

    def fault(self, text: str) -> None:
        """A fault latched: every controller dropped, idle (the runner has stopped the drives)."""
        self.twist = self.tracking = self.excite = None
        self.set_mode("idle", f"idle: fault: {text}")

    # -- every cycle ----------------------------------------------------------------------------
    def end_of_cycle(self) -> None:
        """What ends a mode by itself: the velocity deadman, a finished track or excitation."""
        r = self.runner
        mode = self.mode
        if mode == "velocity" and time.monotonic() - self.last_twist > self.velocity.deadman:
            self.ramp_to_hold(f"deadman: no velocity command for {self.velocity.deadman:g} s")
        elif mode == "track" and self.tracking.finished(r.t + r.period):
            self.holding, self.tracking = self.tracking, None  # it rests at its end: a hold
            self.set_mode("hold", "hold: track finished")
        elif mode == "excite":
            ctrl, end = self.excite
            if ctrl.origin is not None and r.t + r.period >= ctrl.origin + end:
                self.ramp_to_hold("excitation finished")

    def moving(self) -> bool:
        """Whether the robot is meant to move: track, velocity, excite, or a hold still ramping from a
        speed above rest (``REST_SPEED``, ``REST_TURN``). A hold that starts from rest -- ``enable``'s,
        ramping from the estimate's noise-level twist for a few ms -- is standing."""
        mode = self.mode
        if mode in ("track", "velocity", "excite"):
            return True
        if mode == "hold":
            h = self.holding
            r = self.runner
            if h is None:
                return True
            if h.finished(r.t + r.period):
                return False
            v0 = getattr(h.reference, "v0", None)  # the StopTrajectory's start twist (m/s, rad/s)
            return bool(v0 is None or math.hypot(v0[0], v0[1]) > REST_SPEED or abs(v0[2]) > REST_TURN)
        return False

    # -- checks -----------------------------------------------------------------------------------
    def refuse_if_faulted(self) -> None:
        r = self.runner
        if r.fault is not None:
            raise CommandRefused(f"robot is faulted ({r.fault}): reset first")
        if r.last_snapshot is not None and r.last_snapshot.faults:
            raise CommandRefused("robot reports faults (" + "; ".join(map(str, r.last_snapshot.faults))
                                 + "): reset first")

    def estimate(self):
        est = self.runner.last_estimate
        if est is None:
            raise CommandRefused("no pose estimate yet: the loop has not read the robot")
        return est

    def at_rest(self) -> bool:
        est = self.estimate()
        held = self.holding is not None and self.holding.finished(self.runner.t + self.runner.period)
        return (held and math.hypot(est.twist[0], est.twist[1]) <= REST_SPEED
                and abs(est.twist[2]) <= REST_TURN)

    def require_hold_at_rest(self, what: str) -> None:
        self.refuse_if_faulted()
        if self.mode == "idle":
            raise CommandRefused(f"{what}: the drives are not powered: enable first")
        if self.mode != "hold":
            raise CommandRefused(f"{what}: the robot is in {self.mode}: stop first")
        if not self.at_rest():
            est = self.estimate()
            raise CommandRefused(f"{what}: the robot is not at rest yet (speed {math.hypot(*est.twist[:2]):.3f} m/s, "
                                 f"turn {est.twist[2]:.3f} rad/s): wait for the hold")

    # -- switches ---------------------------------------------------------------------------------
    def _hold(self, p0, v0, origin: float | None):
        """A hold controller (``StopTrajectory`` from p0 moving at v0, its time 0 at ``origin``) and
        its trajectory; it becomes the one the rest checks refer to."""
        vel = self.velocity
        traj = StopTrajectory(p0, v0, vel.max_acceleration, vel.max_angular_acceleration)
        ctrl = TrackingController(self.law, traj, self.runner.period, origin=origin)
        self.holding, self.twist, self.tracking, self.excite = ctrl, None, None, None
        return ctrl, traj

    def ramp_to_hold(self, reason: str) -> dict:
        """Hold, continuing the acting reference (or, open loop, the estimated motion)."""
        r = self.runner
        rs = r.reference_state()
        if rs is not None:
            origin, ref = rs
            p0, v0 = ref.p, ref.pd
        else:
            est = self.estimate()
            origin, p0, v0 = est.t, est.pose, est.twist
        ctrl, traj = self._hold(p0, v0, origin)
        text = f"hold: {reason}" + (f" (ramp to rest over {traj.stop_time:.2f} s)" if traj.stop_time > 0 else "")
        r.set_controller(ctrl, text)
        self.set_mode("hold", text, event=False)
        return {"mode": "hold", "rest_pose": traj.rest.tolist(), "ramp_s": traj.stop_time}

    def enable(self, peer: Peer, on_failure: Callable[[], None]) -> dict:
        """idle -> hold of the estimated pose; ``on_failure`` when the drives refuse (a fault latched)."""
        self.refuse_if_faulted()
        if self.mode != "idle":
            raise CommandRefused(f"already enabled (mode {self.mode})")
        est = self.estimate()
        ctrl, traj = self._hold(est.pose, est.twist, est.t)
        text = f"hold: enabled by {peer}"
        try:
            self.runner.enable(ctrl, text)
        except RobotError as exc:
            on_failure()
            raise CommandRefused(f"enabling failed: {exc}") from None
        self.set_mode("hold", text, event=False)
        return {"mode": "hold", "pose": traj.rest.tolist()}

    def disable(self, peer: Peer) -> dict:
        if self.mode == "idle":
            return {"mode": "idle"}
        if self.mode != "hold":
            raise CommandRefused(f"disable: the robot is in {self.mode}: stop first (or estop)")
        if not self.at_rest():
            raise CommandRefused("disable: the robot is not at rest yet: wait for the hold (or estop)")
        text = f"idle: disabled by {peer}"
        self.holding = None
        self.runner.disable(text)
        self.set_mode("idle", text, event=False)
        return {"mode": "idle"}

    def hold(self, peer: Peer, what: str) -> dict:
        self.refuse_if_faulted()
        if self.mode == "idle":
            if what == "stop":
                return {"mode": "idle"}
            raise CommandRefused("hold: the drives are not powered: enable first")
        if self.mode == "hold":
            return {"mode": "hold"}
        return self.ramp_to_hold(f"{what} by {peer}")

    def track(self, reference, name: str, kind: str, peer: Peer) -> dict:
        self.require_hold_at_rest("track")
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
        self.tracking, self.holding = ctrl, None
        self.set_mode("track", text, event=False)
        return {"mode": "track", "target": name, "duration_s": reference.duration,
                "start": here.p.tolist()}

    def command_twist(self, twist, peer: Peer) -> dict:
        self.refuse_if_faulted()
        self.last_twist = time.monotonic()
        if self.mode == "velocity":
            self.twist.command(twist)
            return {"mode": "velocity", "twist": list(twist)}
        if self.mode == "idle":
            raise CommandRefused("velocity: the drives are not powered: enable first")
        if self.mode != "hold":
            raise CommandRefused(f"velocity: the robot is in {self.mode}: stop first")
        origin, ref = self.runner.reference_state()
        vel = self.velocity
        tw = TwistReference(ref.p, ref.pd, self.runner.period, vel.max_acceleration, vel.max_angular_acceleration)
        tw.command(twist)
        ctrl = TrackingController(self.law, tw, self.runner.period, origin=origin)
        text = f"velocity: by {peer}"
        self.runner.set_controller(ctrl, text)
        self.twist, self.holding = tw, None
        self.set_mode("velocity", text, event=False)
        return {"mode": "velocity", "twist": list(twist)}

    def excite_torques(self, times, torques, path: str, peer: Peer) -> dict:
        self.require_hold_at_rest("excite")
        last = float(np.median(np.diff(times))) if len(times) > 1 else self.runner.period
        ctrl = OpenLoopTorques(torques, times=times)
        end = float(times[-1]) + last
        text = f"excite: {path} by {peer} ({len(times)} rows, {end:.2f} s)"
        self.runner.set_controller(ctrl, text)
        self.excite, self.holding = (ctrl, end), None
        self.set_mode("excite", text, event=False)
        return {"mode": "excite", "rows": len(times), "duration_s": end}
