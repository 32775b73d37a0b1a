"""The daemon's command handlers: what the control socket's requests do (``CommandHandler`` of
``otbot_hw.runtime.control_protocol``), on the control server's threads.

Slow, fallible work (planning a scenario, reading a trajectory or torque file) is done here, off
the loop; the switch itself is handed to the loop thread through the ``LoopMailbox`` and runs there
between two cycles (``otbot_hw.runtime.daemon_modes``). ``estop`` alone acts from the I/O thread,
through the runner's thread-safe ``trip``; ``status`` reads what the loop last published (replaced,
never mutated, by the loop).
"""
from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any, Callable

from otbot_hw.control.trajectories import TrajectoryError
from otbot_hw.json_output import json_safe
from otbot_hw.motors import MOTORS
from otbot_hw.runtime.control_protocol import CommandRefused, ProtocolError
from otbot_hw.runtime.control_peers import Peer
from otbot_hw.runtime.supervisor import Violation

log = logging.getLogger("otbot_hw.runtime.daemon")

#: How long a command waits for the loop to pick it up (s); after that it is dropped, never late.
LOOP_PICKUP_TIMEOUT = 2.0


class DaemonCommands:
    """The ``CommandHandler`` of a ``Daemon`` (``daemon``: its runner, mode machine, mailbox,
    recording sessions and settings)."""

    def __init__(self, daemon):
        self.daemon = daemon

    def _loop_call(self, fn: Callable[[], Any]) -> Any:
        d = self.daemon
        if d.runner is None:
            raise CommandRefused("the daemon is still starting (booting the drives)")
        if d.stopping:
            raise CommandRefused("the daemon is stopping")
        try:
            return d.mailbox.call(fn, timeout=LOOP_PICKUP_TIMEOUT)
        except TimeoutError as exc:
            raise RuntimeError(str(exc)) from None

    def status(self, *, peer: Peer) -> dict:
        d = self.daemon
        r = d.runner
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
        mode = d.mode if r is None or r.fault is None else "idle"  # the loop goes idle at its next step
        out = {"mode": mode, "mode_text": d.modes.mode_text, "t": r.t if r is not None else None,
               "faults": faults,
               "drive_states": dict(zip(MOTORS, s.drive_states)) if s is not None else {},
               "loop": r.timing() if r is not None else None,
               "pose": None, "tracking_error": None,
               "recording": r.recording.status() if r is not None and r.recording is not None else None,
               "overrun_warnings": d.overrun_warnings,
               "payload": d.payload_status(),
               "telemetry": d.telemetry.status() if d.telemetry is not None else None,
               "scheduling": None if d.scheduling is None else {**d.scheduling,
                                                                 "operator_shares": d.operator_share.count}}
        if est is not None:
            out["pose"] = {"x": float(est.pose[0]), "y": float(est.pose[1]), "alpha": float(est.pose[2]),
                           "std": [float(v) for v in est.std[:3]],
                           "twist": [float(v) for v in est.twist]}
            if ref is not None and d.mode in ("hold", "track", "velocity"):
                from otbot_hw.runtime.telemetry import wrap_angle

                out["tracking_error"] = {"x": float(ref.p[0] - est.pose[0]), "y": float(ref.p[1] - est.pose[1]),
                                         "alpha": wrap_angle(float(ref.p[2] - est.pose[2]))}
        return json_safe(out)

    def enable(self, *, peer: Peer) -> dict:
        d = self.daemon
        return self._loop_call(lambda: d.modes.enable(peer, lambda: d.on_fault(d.runner.fault)))

    def disable(self, *, peer: Peer) -> dict:
        return self._loop_call(lambda: self.daemon.modes.disable(peer))

    def hold(self, *, peer: Peer) -> dict:
        return self._loop_call(lambda: self.daemon.modes.hold(peer, "hold"))

    def stop(self, *, peer: Peer) -> dict:
        return self._loop_call(lambda: self.daemon.modes.hold(peer, "stop"))

    def track(self, *, target: str, kind: str, peer: Peer) -> dict:
        from otbot_hw.control.scenarios import build_spec, csv_spec

        d = self.daemon
        try:  # slow work (planning, reading a file) here, off the loop
            spec = build_spec(target, d.params, d.settings.limits) if kind == "scenario" else csv_spec(target)
        except TrajectoryError as exc:
            raise ProtocolError("bad_request", f"track: {exc}") from None
        name = target if kind == "scenario" else Path(target).name
        return self._loop_call(lambda: d.modes.track(spec.reference, name, kind, peer))

    def velocity(self, *, vx: float, vy: float, wz: float, peer: Peer) -> dict:
        return self._loop_call(lambda: self.daemon.modes.command_twist((vx, vy, wz), peer))

    def excite(self, *, path: str, peer: Peer) -> dict:
        from otbot_hw.runtime.openloop import TorqueSequenceError, load_torque_sequence

        try:
            times, torques = load_torque_sequence(path)
        except TorqueSequenceError as exc:
            raise ProtocolError("bad_request", f"excite: {exc}") from None
        return self._loop_call(lambda: self.daemon.modes.excite_torques(times, torques, path, peer))

    def estop(self, *, peer: Peer) -> dict:
        """On the I/O thread: trip the loop (quick stop before anything else, fault latched) and
        wait briefly (at most 5 periods, 0.2 s) for it to confirm."""
        d = self.daemon
        r = d.runner
        v = Violation("estop", r.t if r is not None else 0.0, f"emergency stop by {peer}")
        log.warning("estop by %s", peer)
        if r is None:
            d.pending_trip = v
            return {"latched": True, "stopped": False, "note": "the daemon is starting: applied when the loop starts"}
        r.trip(v)
        end = time.monotonic() + min(0.2, 5 * r.period)
        while (r.fault is None or d.seen_fault is not r.fault) and time.monotonic() < end:
            time.sleep(0.0005)  # until the loop has stopped the drives and gone idle
        return {"latched": True, "stopped": r.fault is not None and not r.armed,
                "fault": str(r.fault) if r.fault is not None else None}

    def reset(self, *, peer: Peer) -> dict:
        return self._loop_call(lambda: self.daemon.reset_faults(peer))

    def record(self, *, action: str, peer: Peer) -> dict:
        return self._loop_call(lambda: self.daemon.recordings.command(action, peer))

    def shutdown(self, *, peer: Peer) -> dict:
        d = self.daemon
        log.warning("shutdown by %s", peer)
        d.request_stop(f"shutdown by {peer}")
        d.server.close()
        return {"stopping": True}
