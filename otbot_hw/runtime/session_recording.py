"""A recording session that spans files: the daemon records all day, in the project's format
(``otbot_hw.recording``), rotating by size or by time.

Files are ``<dir>/<session>-<index>.mcap`` (index 000, 001, ...); each is a complete recording
of its own (metadata, channels, samples), with ``session`` metadata {id, index, previous file,
rate} so the pieces can be found and put back in order. Sample times run on across the files of
a session (the loop's time), so concatenating them gives the whole session. The latest event of
each kind in ``carry_kinds`` (the mode) is repeated at the start of the next file, so every
file says what the robot was doing.

Durability: ``RecordingWriter`` flushes every ``rate * flush_interval`` samples and this class
also flushes when ``flush_interval`` s of sample time have passed since the last flush (a slower
loop), so a process killed at any instant loses at most ``flush_interval`` (<= 1 s) of samples;
events are flushed as they are written. Files closed by rotation or ``close()`` are complete;
the one open at a crash loads as a truncated recording (``read_recording``).

Failures: a write, flush, rotation or close that fails in the operating system (ENOSPC disk full,
EFBIG file too large / ``ulimit -f``, EIO) never raises into the loop. The session stops recording
(``error`` says which file and what failed, e.g. "recording /var/lib/otbot/recordings/x-000.mcap:
write failed: [Errno 28] No space left on device"), closes what it can, and calls ``on_error(text)``
once: the daemon latches that as a fault and quick-stops. Later calls do nothing.

``format="ros2"`` writes each file as a ROS 2 bag folder ``<dir>/<session>-<index>/`` instead
(``otbot_hw.ros2.writer.BagWriter``: the same flushing; a cut bag imports up to the crash with
``otbot import --allow-truncated``).
"""
from __future__ import annotations

import errno
import logging
import math
import os
import time
from pathlib import Path
from typing import Any, Callable, Iterable

from otbot_hw.recording import TOPIC_COMMAND, TOPIC_EVENTS, RecordingError, RecordingWriter

log = logging.getLogger(__name__)


def os_error_text(exc: OSError) -> str:
    """``[Errno 28] No space left on device (ENOSPC)``: the number, the words and the symbol."""
    name = errno.errorcode.get(exc.errno or 0)
    return f"[Errno {exc.errno}] {exc.strerror or exc}" + (f" ({name})" if name else "")


def new_session_id() -> str:
    """UTC start time and pid, e.g. ``20260510T143000Z-1234``: sorts by time, unique per process."""
    return time.strftime("%Y%m%dT%H%M%SZ", time.gmtime()) + f"-{os.getpid()}"


class SessionRecording:
    """Streams samples and events into rotating files; the same calls as ``RecordingWriter``
    (``write_sample``, ``write_event``, ``flush``, ``close``), so the loop's recorder can write
    into either. ``rate`` Hz: the loop rate (sets the flush period in samples); ``rotate_size``
    bytes and ``rotate_time`` s (of sample time) per file; ``flush_interval`` s (<= 1);
    ``on_error(text)``: called once when the recording fails (see the module docstring). The folder
    must exist: a session never creates it (systemd's ``StateDirectory=`` does)."""

    def __init__(self, directory: str | Path, metadata: dict[str, Any], topics: Iterable[str] = (), *,
                 rate: float, rotate_size: int = 512 * 2 ** 20, rotate_time: float = 3600.0,
                 flush_interval: float = 1.0, session_id: str | None = None,
                 carry_kinds: tuple[str, ...] = ("mode",), on_error: Callable[[str], None] | None = None,
                 format: str = "otbot"):
        if not (math.isfinite(rate) and rate > 0):
            raise ValueError(f"rate must be a number of Hz > 0, got {rate}")
        if not 0 < flush_interval <= 1.0:
            raise ValueError(f"flush_interval must be in (0, 1] s, got {flush_interval}")
        if format not in ("otbot", "ros2"):
            raise ValueError(f"format must be otbot or ros2, got {format!r}")
        self.format = format
        if not (rotate_size > 0 and rotate_time > 0):
            raise ValueError(f"rotate_size and rotate_time must be > 0, got {rotate_size}, {rotate_time}")
        self.directory = Path(directory)
        if not self.directory.is_dir():
            raise RecordingError(f"{self.directory}: the recording folder does not exist (a session does not create it)")
        self.on_error = on_error
        #: None while recording works; else the sentence that says which file failed and how
        self.error: str | None = None
        self.metadata = dict(metadata)
        self.topics = tuple(dict.fromkeys([*topics, TOPIC_EVENTS]))
        self.rate = float(rate)
        self.rotate_size = int(rotate_size)
        self.rotate_time = float(rotate_time)
        self.flush_interval = float(flush_interval)
        self.flush_every = max(1, int(self.rate * self.flush_interval))
        if session_id is None:  # a session started within the same second as another one: .2, .3, ...
            base = session_id = new_session_id()
            n = 1
            while any((self.directory / f"{session_id}-000{ext}").exists() for ext in (".mcap", "")):
                n += 1
                session_id = f"{base}.{n}"
        self.session_id = session_id
        self.carry_kinds = tuple(carry_kinds)
        self.files: list[Path] = []
        self.samples = 0
        self._carried: dict[str, tuple[str, dict]] = {}
        self._writer: RecordingWriter | None = None
        self._file_t0: float | None = None
        self._flushed_t: float | None = None
        self._size = 0
        self._closed = False
        self._carry_pending = False
        self._open_next()

    # -- files -------------------------------------------------------------------------------
    @property
    def path(self) -> Path:
        """The file being written."""
        return self.files[-1]

    def _open_next(self) -> None:
        index = len(self.files)
        path = self.directory / (f"{self.session_id}-{index:03d}" + (".mcap" if self.format == "otbot" else ""))
        if path.exists():
            raise RecordingError(f"{path}: already exists; a session never overwrites a recording")
        meta = {**self.metadata, "session": {"id": self.session_id, "index": index, "rate": self.rate,
                                             "previous": self.files[-1].name if self.files else None}}
        try:
            if self.format == "ros2":
                from otbot_hw.ros2.writer import BagWriter

                self._writer = BagWriter(path, meta, self.topics, flush_every=self.flush_every, has_force=False)
            else:
                self._writer = RecordingWriter(path, meta, self.topics, flush_every=self.flush_every)
        except OSError as exc:
            raise RecordingError(f"recording {path}: cannot write: {os_error_text(exc)}") from None
        self.files.append(path)
        self._file_t0 = None
        self._size = 0

    def _failed(self, what: str, exc: BaseException) -> None:
        """Stop recording after an operating-system failure: close quietly, say so once."""
        if self.error is not None:
            return
        where = self.files[-1] if self.files else self.directory
        detail = os_error_text(exc) if isinstance(exc, OSError) else str(exc)
        self.error = f"recording {where}: {what} failed: {detail}"
        log.error("%s", self.error)
        w, self._writer = self._writer, None
        if w is not None:
            try:
                w.close()
            except (OSError, ValueError):
                pass  # the disk is still full: the file stays a truncated recording
        if self.on_error is not None:
            self.on_error(self.error)

    def rotate(self, t: float | None = None) -> Path | None:
        """Close the current file and start the next one now; carried events are repeated at
        ``t`` (s; default: the next sample's time). Returns the new file's path (None once failed)."""
        if self.error is not None:
            return None
        try:
            return self._rotate(t)
        except (OSError, RecordingError) as exc:
            self._failed("rotation", exc)
            return None

    def _rotate(self, t: float | None = None) -> Path:
        self._writer.close()
        self._open_next()
        if t is not None:
            self._carry(t)
        else:
            self._carry_pending = True
        return self.path

    def _carry(self, t: float) -> None:
        self._carry_pending = False
        for kind, (text, extra) in self._carried.items():
            self._writer.write_event(t, kind, text, **extra)

    # -- the RecordingWriter calls -----------------------------------------------------------
    def write_sample(self, messages: dict[str, dict[str, Any]]) -> None:
        """One sample (``RecordingWriter.write_sample``); rotates first when the current file has
        reached ``rotate_size`` bytes or spans ``rotate_time`` s."""
        if self.error is not None:
            return
        try:
            self._write_sample(messages)
        except (OSError, RecordingError) as exc:
            self._failed("write", exc)

    def _write_sample(self, messages: dict[str, dict[str, Any]]) -> None:
        t = float(messages[TOPIC_COMMAND]["t"])
        if self._file_t0 is not None and (t - self._file_t0 >= self.rotate_time or self._size >= self.rotate_size):
            self._rotate(t)
        w = self._writer
        w.write_sample(messages)
        self.samples += 1
        if self._file_t0 is None:
            self._file_t0 = t
            self._flushed_t = t
        if self._carry_pending:
            self._carry(t)
        if w.samples % self.flush_every == 0:  # RecordingWriter has just flushed
            self._flushed_t = t
            self._size = self._writer.path.stat().st_size
        elif t - self._flushed_t >= self.flush_interval:
            w.flush()
            self._flushed_t = t
            self._size = self._writer.path.stat().st_size

    def write_event(self, t: float, kind: str, text: str, **extra: Any) -> None:
        """A sparse event (``RecordingWriter.write_event``; flushed at once)."""
        if self.error is not None:
            return
        try:
            self._writer.write_event(t, kind, text, **extra)
        except OSError as exc:
            self._failed("write", exc)
            return
        if kind in self.carry_kinds:
            self._carried[kind] = (text, extra)

    def flush(self) -> None:
        if self.error is not None:
            return
        try:
            self._writer.flush()
        except OSError as exc:
            self._failed("flush", exc)

    def close(self) -> None:
        """Finish the current file (summary and footer). Safe to call twice; never raises an
        operating-system error (a failed close is reported like a failed write)."""
        if not self._closed:
            self._closed = True
            if self.error is None:
                try:
                    self._writer.close()
                except OSError as exc:
                    self._failed("close", exc)

    def status(self) -> dict:
        """For the daemon's ``status``: session id, current file (a bag folder with ``ros2``), its index and
        size (bytes), total samples."""
        try:
            size = (self._writer.path if self._writer is not None else self.path).stat().st_size
        except OSError:
            size = None
        return {"session": self.session_id, "path": str(self.path), "index": len(self.files) - 1,
                "files": len(self.files), "samples": self.samples, "bytes": size, "closed": self._closed,
                "error": self.error}

    def __enter__(self) -> "SessionRecording":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
