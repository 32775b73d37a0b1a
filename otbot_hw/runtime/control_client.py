"""The client side of the daemon's control socket (``otbot ctl``): stdlib and ``control_protocol``
only, so that a command-line call starts in a few tens of milliseconds (the velocity deadman is
0.5 s). The server is ``control_socket``.
"""
from __future__ import annotations

import errno
import itertools
import json
import os
import socket
import stat
import time
from pathlib import Path
from typing import Any

from otbot_hw.runtime.control_protocol import encode_request


SOCKET_NAME = "control.sock"


def default_runtime_dir(environ: dict | None = None) -> Path:
    """The daemon's runtime directory: ``$RUNTIME_DIRECTORY`` (systemd's ``RuntimeDirectory=``; the
    first of a colon-separated list), else ``$XDG_RUNTIME_DIR/otbot``, else ``/run/otbot``."""
    env = os.environ if environ is None else environ
    if env.get("RUNTIME_DIRECTORY"):
        return Path(env["RUNTIME_DIRECTORY"].split(":")[0])
    if env.get("XDG_RUNTIME_DIR"):
        return Path(env["XDG_RUNTIME_DIR"]) / "otbot"
    return Path("/run/otbot")


def default_socket_path(environ: dict | None = None) -> Path:
    """Where the daemon creates its control socket when the configuration names none."""
    return default_runtime_dir(environ) / SOCKET_NAME


def socket_candidates(environ: dict | None = None) -> list[Path]:
    """Where a client looks for the daemon's socket when told nowhere: the service's runtime
    directory when the client runs inside it, the system daemon's ``/run/otbot``, then a user's
    daemon under ``$XDG_RUNTIME_DIR`` (a client's environment is not the daemon's)."""
    env = os.environ if environ is None else environ
    out = [default_runtime_dir({"RUNTIME_DIRECTORY": env["RUNTIME_DIRECTORY"]})] if env.get("RUNTIME_DIRECTORY") else []
    out.append(default_runtime_dir({}))
    if env.get("XDG_RUNTIME_DIR"):
        out.append(default_runtime_dir({"XDG_RUNTIME_DIR": env["XDG_RUNTIME_DIR"]}))
    return [d / SOCKET_NAME for d in out]


class DaemonUnreachable(ConnectionError):
    """No daemon answers at the socket path (client side)."""


class ControlError(RuntimeError):
    """The daemon answered with an error reply: ``code`` (``ERROR_CODES``) and message."""

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code


def describe_non_socket(path: Path) -> str | None:
    """What ``path`` is when it exists and is not a socket ("a regular file", "a folder", ...), else None."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return None
    if stat.S_ISSOCK(mode):
        return None
    for test, what in ((stat.S_ISDIR, "a folder"), (stat.S_ISREG, "a regular file"), (stat.S_ISFIFO, "a FIFO"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device")):
        if test(mode):
            return what
    return "not a socket"


def _stale(line: bytes, rid: int) -> bool:
    """Whether ``line`` is a reply to an earlier request of this connection (an int id below ``rid``)."""
    try:
        rep = json.loads(line)
    except ValueError:
        return False
    old = rep.get("id") if isinstance(rep, dict) else None
    return isinstance(old, int) and not isinstance(old, bool) and old < rid


class ControlClient:
    """A connection to the daemon (``otbot ctl``); ``request`` sends one command and returns its
    result, raising ``ControlError`` for an error reply and ``DaemonUnreachable`` when no daemon
    answers (within ``timeout`` s)."""

    def __init__(self, path: Path, timeout: float = 5.0):
        self.path = Path(path)
        self.timeout = timeout
        self._ids = itertools.count(1)
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._sock.settimeout(timeout)
        try:
            self._connect(time.monotonic() + timeout)
        except FileNotFoundError:
            self._sock.close()
            raise DaemonUnreachable(f"no daemon at {self.path} (no such socket)") from None
        except ConnectionRefusedError:
            self._sock.close()
            what = describe_non_socket(self.path)
            if what is not None:
                raise DaemonUnreachable(f"{self.path} is {what}, not a daemon's control socket") from None
            raise DaemonUnreachable(f"no daemon at {self.path} (connection refused: stale socket)") from None
        except PermissionError:
            self._sock.close()
            raise DaemonUnreachable(f"no permission to connect to {self.path} (join the daemon's group)") from None
        except OSError as exc:
            self._sock.close()
            what = describe_non_socket(self.path)
            if what is not None:
                raise DaemonUnreachable(f"{self.path} is {what}, not a daemon's control socket") from None
            if exc.errno == errno.EAGAIN:
                raise DaemonUnreachable(f"the daemon at {self.path} is not accepting connections (backlog full)") from None
            raise DaemonUnreachable(f"cannot connect to {self.path}: {exc.strerror or exc}") from None
        self._file = self._sock.makefile("rb")

    def _connect(self, deadline: float) -> None:
        """Connect; a full listen backlog (EAGAIN: someone floods the daemon with connections, which
        it accepts as fast as it can) is retried until ``deadline`` rather than given up at once."""
        while True:
            try:
                self._sock.connect(str(self.path))
                return
            except BlockingIOError:
                if time.monotonic() >= deadline:
                    raise
                time.sleep(0.002)

    def request(self, cmd: str, args: dict | None = None) -> Any:
        rid = next(self._ids)
        lost: OSError | None = None
        try:
            self._sock.sendall(encode_request(rid, cmd, args))
        except socket.timeout:
            raise DaemonUnreachable(f"the daemon at {self.path} did not answer within {self.timeout:g} s") from None
        except OSError as exc:  # closed by the daemon: it may have said why before closing
            lost = exc
        while True:
            try:
                line = self._file.readline()
            except socket.timeout:
                raise DaemonUnreachable(f"the daemon at {self.path} did not answer within {self.timeout:g} s") from None
            except OSError as exc:
                line, lost = b"", lost or exc
            if not _stale(line, rid):  # the reply to an earlier request cut short (Ctrl-C): skipped
                break
        if not line:
            why = f": {lost.strerror or lost}" if lost else ""
            raise DaemonUnreachable(f"the daemon at {self.path} closed the connection{why}")
        try:
            reply = json.loads(line)
        except json.JSONDecodeError:
            raise ControlError("internal", f"the daemon's reply is not JSON: {line[:80]!r}") from None
        if isinstance(reply, dict) and reply.get("id") is None and not reply.get("ok", True):
            pass  # an error about the connection itself (busy, too large): reported below
        elif not isinstance(reply, dict) or reply.get("id") != rid:
            raise ControlError("internal", f"unexpected reply {line[:80]!r} to request {rid}")
        if not reply.get("ok"):
            err = reply.get("error") or {}
            raise ControlError(str(err.get("code", "internal")), str(err.get("message", "error")))
        return reply.get("result")

    def close(self) -> None:
        self._file.close()
        self._sock.close()

    def __enter__(self) -> "ControlClient":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


__all__ = ["ControlClient", "ControlError", "DaemonUnreachable", "describe_non_socket", "default_runtime_dir",
           "default_socket_path", "socket_candidates", "SOCKET_NAME"]
