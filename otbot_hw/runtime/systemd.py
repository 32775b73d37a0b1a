"""systemd's notification protocol (sd_notify(3)) and a loop-driven watchdog.

``Notifier`` sends ``READY=1``, ``STATUS=...``, ``WATCHDOG=1``, ``STOPPING=1`` datagrams to
``$NOTIFY_SOCKET`` (a path, or an abstract socket written with a leading ``@``); without it (not
started by systemd with ``Type=notify``) every call does nothing. Written on the socket module:
the protocol is one ``AF_UNIX`` datagram of ``KEY=VALUE`` lines, sd_notify(3) documents it as
stable for reimplementation, the bindings (systemd-python, cysystemd) need libsystemd headers
to build, and the small pure one (sdnotify) is unmaintained, swallows every error and does not
read ``$WATCHDOG_USEC``: wrapping it would be as long as this.

``Watchdog`` pings only while the loop says it meets its deadlines: the loop calls
``cycle_ok(now)`` after a cycle that met its deadline and ``cycle_missed(now)`` after one that did
not. A ping (``WATCHDOG=1``) is sent from ``cycle_ok`` at most every ``interval`` s (half of
``$WATCHDOG_USEC``); a missed cycle never pings, so a loop that is stuck, or that misses every
deadline for longer than ``WatchdogSec``, is killed and restarted by systemd. Single overruns do
not starve the watchdog (the supervisor latches them as a fault instead). ``stop(reason)`` ends the
pings for good: the daemon calls it when a part nobody can do without (the control socket, through
which estop comes) has died, so that systemd restarts it.
"""
from __future__ import annotations

import errno
import os
import socket
import time


def notify_address(value: str | None) -> str | bytes | None:
    """The ``sendto`` address of ``$NOTIFY_SOCKET``: a filesystem path, or the abstract name
    (``@name`` -> ``b"\\0name"``); None when unset or of a kind this module does not speak (vsock)."""
    if not value:
        return None
    if value.startswith("@"):
        return b"\0" + value[1:].encode()
    if value.startswith("/"):
        return value
    return None


def watchdog_interval(environ: dict | None = None) -> float | None:
    """Seconds between pings: half of ``$WATCHDOG_USEC``, if it is set for this process
    (``$WATCHDOG_PID`` absent or equal to our pid); None when systemd expects no pings."""
    env = os.environ if environ is None else environ
    usec, pid = env.get("WATCHDOG_USEC"), env.get("WATCHDOG_PID")
    if not usec:
        return None
    try:
        if pid and int(pid) != os.getpid():
            return None
        us = int(usec)
    except ValueError:
        return None
    return us / 2e6 if us > 0 else None


class Notifier:
    """Talks to systemd through ``$NOTIFY_SOCKET`` (or ``address``); ``enabled`` says whether
    anyone listens. Sending never raises: a notification that cannot be sent is counted in
    ``errors`` (systemd gone is no reason to stop the robot's loop)."""

    def __init__(self, address: str | bytes | None = ..., environ: dict | None = None):
        env = os.environ if environ is None else environ
        self.address = notify_address(env.get("NOTIFY_SOCKET")) if address is ... else address
        self.errors = 0
        self._sock: socket.socket | None = None
        if self.address is not None:
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._sock.setblocking(False)

    @property
    def enabled(self) -> bool:
        return self._sock is not None

    def notify(self, **fields: str | int) -> bool:
        """Send ``KEY=VALUE`` lines in one datagram (keys upper case, values without newlines)."""
        if self._sock is None:
            return False
        lines = []
        for k, v in fields.items():
            v = str(v)
            if "\n" in v:
                raise ValueError(f"sd_notify value of {k} must be one line, got {v!r}")
            lines.append(f"{k.upper()}={v}")
        try:
            self._sock.sendto("\n".join(lines).encode(), self.address)
            return True
        except OSError as exc:
            if exc.errno not in (errno.EAGAIN, errno.ECONNREFUSED, errno.ENOENT, errno.EPERM, errno.EACCES):
                raise
            self.errors += 1
            return False

    def ready(self, status: str | None = None) -> bool:
        """``READY=1`` (after the drives are booted), with an optional status line."""
        return self.notify(READY=1, **({"STATUS": status} if status else {}))

    def status(self, text: str) -> bool:
        """``STATUS=...``: the one line ``systemctl status`` shows (e.g. the mode)."""
        return self.notify(STATUS=text)

    def watchdog(self) -> bool:
        return self.notify(WATCHDOG=1)

    def stopping(self, status: str | None = None) -> bool:
        return self.notify(STOPPING=1, **({"STATUS": status} if status else {}))

    def extend_timeout(self, seconds: float) -> bool:
        """``EXTEND_TIMEOUT_USEC``: more time for a slow start (drive boot) or stop."""
        return self.notify(EXTEND_TIMEOUT_USEC=int(seconds * 1e6))

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None


class Watchdog:
    """Pings ``notifier`` every ``interval`` s (default: ``watchdog_interval()``) while the loop
    reports met deadlines. ``now``: the loop's monotonic time in s. ``pings``, ``ok`` and
    ``missed`` count what happened; ``enabled`` is False when systemd wants no pings."""

    def __init__(self, notifier: Notifier, interval: float | None = ..., environ: dict | None = None):
        self.notifier = notifier
        self.interval = watchdog_interval(environ) if interval is ... else interval
        self.last_ping: float | None = None
        self.pings = self.ok = self.missed = 0
        #: why the pings were stopped for good (``stop``), or None
        self.stopped: str | None = None

    def stop(self, reason: str) -> None:
        """No more pings, whatever the loop reports (systemd kills and restarts the process after
        ``WatchdogSec``)."""
        if self.stopped is None:
            self.stopped = reason

    @property
    def enabled(self) -> bool:
        return self.interval is not None and self.notifier.enabled

    def cycle_ok(self, now: float | None = None) -> bool:
        """A cycle met its deadline; pings if ``interval`` has passed since the last ping.
        Returns whether it pinged. Costs one comparison when no ping is due."""
        self.ok += 1
        if not self.enabled or self.stopped is not None:
            return False
        now = time.monotonic() if now is None else now
        if self.last_ping is not None and now - self.last_ping < self.interval:
            return False
        self.last_ping = now  # also after a failed send: retry next interval, not every cycle
        if self.notifier.watchdog():
            self.pings += 1
            return True
        return False

    def cycle_missed(self, now: float | None = None) -> None:
        """A cycle missed its deadline: no ping for it."""
        self.missed += 1
