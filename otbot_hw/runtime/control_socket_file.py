"""The control socket's file: its path checked, the socket bound safely (mode 0660, linked into place),
a live daemon on the same path detected (by connecting) and refused, a stale socket file removed. The
daemon never creates the folder (systemd's ``RuntimeDirectory=`` does). There is no network listener.
"""
from __future__ import annotations

import errno
import itertools
import logging
import os
import socket
import stat
from pathlib import Path

from otbot_hw.folders import require_folder

log = logging.getLogger(__name__)

SOCKET_MODE = 0o660


class ControlSocketError(RuntimeError):
    """The control socket cannot be set up (its folder is missing or not writable, the path is too
    long for AF_UNIX, ...); the message names the path and what to do. Bad input: exit 2."""


class SocketInUse(ControlSocketError):
    """Another live daemon answers on the socket path, or the path is not a socket."""



def probe_socket(path: Path, timeout: float = 0.5) -> bool:
    """Whether a process accepts connections on the Unix socket ``path``."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(timeout)
    try:
        s.connect(str(path))
        return True
    except (ConnectionRefusedError, FileNotFoundError):
        return False
    except PermissionError:
        raise SocketInUse(f"{path} belongs to someone this process may not connect to: "
                          f"refusing to replace it") from None
    except OSError as exc:
        if exc.errno == errno.EAGAIN:  # backlog full: someone is listening
            return True
        raise
    finally:
        s.close()


#: bytes of an AF_UNIX socket path, its terminating NUL included (``sun_path`` on Linux)
SUN_PATH_MAX = 108


def check_socket_path(path: Path) -> None:
    """ControlSocketError unless a socket can be created at ``path``: its folder exists (the daemon
    never creates it: systemd's ``RuntimeDirectory=`` does), is a folder this process may write, and
    the path fits AF_UNIX's 107 bytes."""
    path = Path(path)
    n = len(os.fsencode(str(path)))
    if n >= SUN_PATH_MAX:
        raise ControlSocketError(f"control socket path {path} is {n} bytes; a Unix socket path has at most "
                                 f"{SUN_PATH_MAX - 1} (choose a shorter --socket or daemon.socket.path)")
    folder = f"control socket folder {path.parent}"
    require_folder(path.parent, ControlSocketError, f"{folder} does not exist (the daemon does not create it: create "
                   f"it, or let systemd's RuntimeDirectory= do it, or choose --socket)", f"{folder} is not a folder",
                   f"{folder} is not writable by this user (uid {os.geteuid()}): choose --socket or fix its owner/mode")


def _tmp_name(path: Path) -> Path:
    """A name beside ``path`` no longer than it (so it fits AF_UNIX whenever ``path`` does), unique
    to this process and call."""
    tag = f"{os.getpid():x}{next(_TMP_COUNTER):x}{os.urandom(4).hex()}"
    width = max(len(path.name), 8)
    return path.with_name(("." + tag)[:width])


_TMP_COUNTER = itertools.count()


def bind_control_socket(path: Path, backlog: int = 64) -> tuple[socket.socket, os.stat_result]:
    """A listening socket at ``path``, mode 0660, created safely: refuse if a live daemon answers
    there or the path is not a socket; remove a stale socket. The socket is bound under a
    temporary name, given its mode, and linked into place (``link`` fails if the name has been
    taken meanwhile), so clients never see a socket with the wrong mode or half set up. The folder
    must exist (``check_socket_path``); every failure is a ``ControlSocketError`` naming the path."""
    path = Path(path)
    check_socket_path(path)
    try:
        st = path.lstat()
    except FileNotFoundError:
        st = None
    except OSError as exc:
        raise ControlSocketError(f"control socket {path}: {exc.strerror}") from None
    if st is not None:
        if stat.S_ISDIR(st.st_mode):
            raise SocketInUse(f"{path} is a folder, not a socket: refusing to replace it")
        if not stat.S_ISSOCK(st.st_mode):
            raise SocketInUse(f"{path} exists and is not a socket: refusing to replace it")
        if probe_socket(path):
            raise SocketInUse(f"another daemon is running on {path}")
        log.warning("removing stale control socket %s", path)
        try:
            path.unlink(missing_ok=True)
        except OSError as exc:
            raise ControlSocketError(f"cannot remove the stale control socket {path}: {exc.strerror}") from None
    tmp = _tmp_name(path)
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        tmp.unlink(missing_ok=True)
        sock.bind(str(tmp))
        os.chmod(tmp, SOCKET_MODE)
        sock.listen(backlog)
        try:
            os.link(tmp, path)
        except FileExistsError:
            raise SocketInUse(f"another daemon created {path} while this one was starting") from None
        finally:
            tmp.unlink(missing_ok=True)
    except OSError as exc:
        sock.close()
        raise ControlSocketError(f"cannot create the control socket {path}: {exc.strerror or exc}") from None
    except BaseException:
        sock.close()
        raise
    sock.setblocking(False)
    return sock, path.lstat()

