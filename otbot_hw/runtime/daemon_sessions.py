"""The daemon's recording sessions: every session a ``SessionRecording`` in ``--record-dir`` (rotating
by size and time, ``daemon.recording``), started with the loop and by ``ctl record start|stop``.

A recording that fails (disk full, file too large, I/O error, the folder gone) is a latched fault
naming the file and the error: the drives quick-stop at the next cycle, the loop and the control
socket stay up, and ``record start`` may begin a new session once the cause is gone.
"""
from __future__ import annotations

import logging

from otbot_hw.recording import RecordingError
from otbot_hw.runtime.control_protocol import CommandRefused
from otbot_hw.runtime.control_peers import Peer
from otbot_hw.runtime.session_recording import SessionRecording, os_error_text
from otbot_hw.runtime.supervisor import Violation

log = logging.getLogger("otbot_hw.runtime.daemon")


class DaemonRecordings:
    """Recording sessions of a ``Daemon`` (``daemon``: its settings, runner and fault hand-over).
    ``sessions``: the id of every session started; ``error``: the last failure's text."""

    def __init__(self, daemon):
        self.daemon = daemon
        self.sessions: list[str] = []
        self.error: str | None = None

    def recorder(self, period: float):
        """The loop runner's ``recorder(meta, topics)`` for a loop of ``period`` s (None: no recording folder)."""
        s = self.daemon.settings
        if s.record_dir is None:
            return None
        cfg = s.daemon.recording

        def start(meta: dict, topics: list):
            try:
                sess = SessionRecording(s.record_dir, meta, topics, rate=1.0 / period,
                                        rotate_size=cfg.rotate_size, rotate_time=cfg.rotate_time,
                                        flush_interval=cfg.flush_interval, format=cfg.format,
                                        on_error=self.failed)
            except (RecordingError, OSError) as exc:  # the folder gone, the disk full at the first file
                self.failed(str(exc) if isinstance(exc, RecordingError)
                            else f"recording in {s.record_dir}: cannot start: {os_error_text(exc)}")
                return None
            self.sessions.append(sess.session_id)
            return sess

        return start

    def failed(self, text: str) -> None:
        """The session recording failed: a latched fault (see the module docstring). Any thread."""
        d = self.daemon
        self.error = text
        v = Violation("recording", d.runner.t if d.runner is not None else 0.0, text)
        if d.runner is None:
            d.pending_trip = d.pending_trip or v
        else:
            d.runner.trip(v)

    def command(self, action: str, peer: Peer) -> dict:
        """``record start|stop`` (loop thread)."""
        r = self.daemon.runner
        if r.recorder is None:
            raise CommandRefused("record: this daemon records nowhere (no recording folder)")
        failed = r.recording is not None and r.recording.error is not None
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
        self.error = None
        w = r.start_recording()
        if w is None and self.error is not None:
            raise CommandRefused(f"record start: {self.error}")
        r.event(r.t, "mode", self.daemon.modes.mode_text)
        return {"recording": w.status() if w is not None else None}
