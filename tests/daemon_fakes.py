"""A recording ``CommandHandler`` for the control-socket and ``otbot ctl`` tests."""
from __future__ import annotations

import threading
import time

from otbot_hw.runtime.control_protocol import CommandRefused


class FakeHandler:
    """Records every call (command, arguments, peer, thread name); ``status`` returns a full report.
    ``slow`` maps a command to seconds to sleep; ``refuse`` a command to a refusal message."""

    def __init__(self, slow: dict | None = None, refuse: dict | None = None):
        self.calls: list[tuple[str, dict, object, str]] = []
        self.lock = threading.Lock()
        self.slow = dict(slow or {})
        self.refuse = dict(refuse or {})
        self.mode = "idle"
        self.faults: list[dict] = []

    def _record(self, cmd: str, peer, **args) -> dict:
        with self.lock:
            self.calls.append((cmd, args, peer, threading.current_thread().name))
        if cmd in self.slow:
            time.sleep(self.slow[cmd])
        if cmd in self.refuse:
            raise CommandRefused(self.refuse[cmd])
        return {"accepted": cmd, **args}

    def commands(self) -> list[str]:
        with self.lock:
            return [c[0] for c in self.calls]

    def status(self, *, peer):
        self._record("status", peer)
        return {
            "mode": self.mode, "faults": list(self.faults),
            "drive_states": {"right_wheel": "OPERATION ENABLED", "left_wheel": "OPERATION ENABLED",
                             "pivot": "OPERATION ENABLED"},
            "loop": {"rate": 250.0, "period": {"target": 0.004, "p50": 0.004, "p99": 0.00412},
                     "jitter": {"p99": 0.00012, "max": 0.0003}, "overruns": 0, "cycles": 12345},
            "pose": {"x": 1.25, "y": -0.5, "alpha": 0.1, "std": [0.002, 0.003, 0.001]},
            "tracking_error": {"x": 0.004, "y": -0.001, "alpha": 0.002},
            "recording": {"path": "/var/lib/otbot/recordings/s-000.mcap", "samples": 100, "bytes": 4096},
        }

    def enable(self, *, peer): return self._record("enable", peer)
    def disable(self, *, peer): return self._record("disable", peer)
    def hold(self, *, peer): return self._record("hold", peer)
    def track(self, *, target, kind, peer): return self._record("track", peer, target=target, kind=kind)
    def velocity(self, *, vx, vy, wz, peer): return self._record("velocity", peer, vx=vx, vy=vy, wz=wz)
    def excite(self, *, path, peer): return self._record("excite", peer, path=path)
    def stop(self, *, peer): return self._record("stop", peer)
    def estop(self, *, peer): return self._record("estop", peer)
    def reset(self, *, peer): return self._record("reset", peer)
    def record(self, *, action, peer): return self._record("record", peer, action=action)
    def shutdown(self, *, peer): return self._record("shutdown", peer)
