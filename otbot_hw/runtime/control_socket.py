"""The daemon's control interface: a Unix socket speaking the JSON lines of ``control_protocol``.

Threads and hand-over to the loop (the server never blocks the control loop):

* one I/O thread (``otbot-control``) runs a ``selectors`` loop: accepts, reads, frames lines,
  parses, validates, checks authorization and writes replies, all non-blocking;
* one dispatch thread (``otbot-dispatch``) calls the handler, one request at a time in arrival
  order: the handler is lock-protected by construction (never called concurrently with itself),
  so a slow command (loading a CSV, planning) delays other commands but never the I/O or the loop;
* ``estop`` is the exception: it is called on the I/O thread the moment it is parsed, even while
  the dispatch thread is busy, so the handler's ``estop`` must be quick and thread-safe (set a
  flag the loop reads every cycle);
* to act on the loop thread, the handler puts work into a ``LoopMailbox`` (a thread-safe queue
  the loop drains once per cycle with ``service()``, never waiting) and waits for its result.

Authorization: the kernel's peer credentials (SO_PEERCRED: pid, uid, gid; SO_PEERGROUPS: the
supplementary groups), read once per connection, against ``daemon.socket.allowed_users`` /
``allowed_groups``; ``status`` is open to every peer. The socket file is created mode 0660; a
live daemon on the same path (probed by connecting) makes ``ControlServer`` refuse to start, a
stale socket file is removed. There is no network listener.
"""
from __future__ import annotations

import errno
import grp
import itertools
import json
import logging
import math
import os
import pwd
import queue
import selectors
import socket
import stat
import struct
import threading
import time
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Protocol

from otbot_hw.runtime.control_protocol import (
    COMMANDS, OPEN_COMMANDS, ArgumentLimits, CommandRefused, ProtocolError, Request, check_status,
    encode_reply, encode_request, parse_request)
from otbot_hw.runtime.daemon_config import ControlSocketConfig

log = logging.getLogger(__name__)

SOCKET_MODE = 0o660
SO_PEERGROUPS = getattr(socket, "SO_PEERGROUPS", 59)  # Linux >= 4.13
MAX_IN_FLIGHT = 8              # requests of one connection waiting for the handler
MAX_OUTPUT = 1 << 20           # bytes of unread replies before a client is dropped


class SocketInUse(RuntimeError):
    """Another live daemon answers on the socket path, or the path is not a socket."""


class DaemonUnreachable(ConnectionError):
    """No daemon answers at the socket path (client side)."""


class ControlError(RuntimeError):
    """The daemon answered with an error reply: ``code`` (``ERROR_CODES``) and message."""

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code


@dataclass(frozen=True)
class Peer:
    """The connected process as the kernel reports it: pid, uid, gid, supplementary groups."""

    pid: int
    uid: int
    gid: int
    groups: tuple[int, ...] = ()

    def __str__(self) -> str:
        return f"pid {self.pid} uid {self.uid} gid {self.gid}"


def peer_credentials(conn: socket.socket) -> Peer:
    pid, uid, gid = struct.unpack("3i", conn.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, 12))
    try:
        raw = conn.getsockopt(socket.SOL_SOCKET, SO_PEERGROUPS, 4 * 1024)
        groups = struct.unpack(f"{len(raw) // 4}I", raw)
    except OSError:  # older kernel or more than 1024 groups: the user database's list
        try:
            groups = tuple(os.getgrouplist(pwd.getpwuid(uid).pw_name, gid))
        except KeyError:
            groups = ()
    return Peer(pid=pid, uid=uid, gid=gid, groups=tuple(groups))


class Authorizer:
    """Who may send commands beyond ``OPEN_COMMANDS``: users and groups by name or numeric id.
    Names are looked up when a peer connects (a user added later is recognized); names that do
    not exist match nobody. Nobody is implied, root included."""

    def __init__(self, users=(), groups=()):
        self.users = tuple(users)
        self.groups = tuple(groups)

    def _ids(self, entries, lookup) -> set[int]:
        out = set()
        for e in entries:
            if isinstance(e, int):
                out.add(e)
            else:
                try:
                    out.add(lookup(e))
                except KeyError:
                    pass
        return out

    def allows(self, peer: Peer) -> bool:
        if peer.uid in self._ids(self.users, lambda n: pwd.getpwnam(n).pw_uid):
            return True
        gids = self._ids(self.groups, lambda n: grp.getgrnam(n).gr_gid)
        return bool(gids & ({peer.gid} | set(peer.groups)))


class CommandHandler(Protocol):
    """What the daemon implements; the server calls one method per validated request with the
    checked arguments and the peer, and replies with the returned JSON object. A method raises
    ``CommandRefused`` to refuse in the current state; any other exception is an ``internal``
    error (logged). ``status`` must satisfy ``control_protocol.STATUS_REQUIRED``. ``estop`` is
    called from the I/O thread (see the module docstring); every other method from the dispatch
    thread, one at a time. A method may call ``ControlServer.close()`` (``shutdown`` does): the
    requests already queued are still carried out and every reply, its own included, goes out.
    A method may raise ``ProtocolError`` (e.g. ``bad_request`` for a file that does not parse): the
    reply carries its code."""

    def status(self, *, peer: Peer) -> dict: ...
    def enable(self, *, peer: Peer) -> dict: ...
    def disable(self, *, peer: Peer) -> dict: ...
    def hold(self, *, peer: Peer) -> dict: ...
    def track(self, *, target: str, kind: str, peer: Peer) -> dict: ...
    def velocity(self, *, vx: float, vy: float, wz: float, peer: Peer) -> dict: ...
    def excite(self, *, path: str, peer: Peer) -> dict: ...
    def stop(self, *, peer: Peer) -> dict: ...
    def estop(self, *, peer: Peer) -> dict: ...
    def reset(self, *, peer: Peer) -> dict: ...
    def record(self, *, action: str, peer: Peer) -> dict: ...
    def shutdown(self, *, peer: Peer) -> dict: ...


class LoopMailbox:
    """Work for the loop thread: other threads ``call(fn)`` (blocking, with a timeout) or
    ``submit(fn)`` (a Future); the loop calls ``service()`` once per cycle, which runs what is
    queued on the loop thread without ever waiting. A call the loop has not picked up within
    the timeout raises ``TimeoutError`` and is dropped (it never runs late)."""

    def __init__(self, max_per_cycle: int = 4):
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self.max_per_cycle = max_per_cycle

    def submit(self, fn: Callable[[], Any]) -> Future:
        fut: Future = Future()
        self._queue.put((fn, fut))
        return fut

    def call(self, fn: Callable[[], Any], timeout: float = 1.0) -> Any:
        fut = self.submit(fn)
        try:
            return fut.result(timeout)
        except TimeoutError:
            if fut.cancel():
                raise TimeoutError(f"the control loop did not take the command within {timeout:g} s") from None
            return fut.result()  # picked up just now: wait for it

    def service(self) -> int:
        """Run up to ``max_per_cycle`` queued calls on the calling (loop) thread; returns how many."""
        n = 0
        while n < self.max_per_cycle:
            try:
                fn, fut = self._queue.get_nowait()
            except queue.Empty:
                break
            if not fut.set_running_or_notify_cancel():
                continue
            n += 1
            try:
                fut.set_result(fn())
            except BaseException as exc:  # handed back to the caller's thread
                fut.set_exception(exc)
        return n


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


def bind_control_socket(path: Path, backlog: int = 64) -> tuple[socket.socket, os.stat_result]:
    """A listening socket at ``path``, mode 0660, created safely: refuse if a live daemon answers
    there or the path is not a socket; remove a stale socket. The socket is bound under a
    temporary name, given its mode, and linked into place (``link`` fails if the name has been
    taken meanwhile), so clients never see a socket with the wrong mode or half set up."""
    path = Path(path)
    if not path.parent.is_dir():
        path.parent.mkdir(mode=0o750, parents=True, exist_ok=True)
    try:
        st = path.lstat()
    except FileNotFoundError:
        st = None
    if st is not None:
        if not stat.S_ISSOCK(st.st_mode):
            raise SocketInUse(f"{path} exists and is not a socket: refusing to replace it")
        if probe_socket(path):
            raise SocketInUse(f"another daemon is running on {path}")
        log.warning("removing stale control socket %s", path)
        path.unlink(missing_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}")
    tmp.unlink(missing_ok=True)
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        sock.bind(str(tmp))
        os.chmod(tmp, SOCKET_MODE)
        sock.listen(backlog)
        try:
            os.link(tmp, path)
        except FileExistsError:
            raise SocketInUse(f"another daemon created {path} while this one was starting") from None
        finally:
            tmp.unlink(missing_ok=True)
    except BaseException:
        sock.close()
        raise
    sock.setblocking(False)
    return sock, path.lstat()


class _Connection:
    __slots__ = ("sock", "peer", "allowed", "inbuf", "outbuf", "started", "in_flight", "closing")

    def __init__(self, sock: socket.socket, peer: Peer, allowed: bool):
        self.sock, self.peer, self.allowed = sock, peer, allowed
        self.inbuf = bytearray()
        self.outbuf = bytearray()
        self.started: float | None = None  # monotonic time the pending partial line began
        self.in_flight = 0
        self.closing = False               # close once outbuf is written


class ControlServer:
    """Serve ``handler`` (a ``CommandHandler``) on the control socket; ``start()`` binds (raising
    ``SocketInUse``) and starts the threads, ``close()`` stops them and removes the socket file."""

    def __init__(self, handler: CommandHandler, config: ControlSocketConfig = ControlSocketConfig(),
                 limits: ArgumentLimits = ArgumentLimits(), path: Path | None = None):
        self.handler = handler
        self.config = config
        self.limits = limits
        self.path = Path(path) if path is not None else config.socket_path()
        self.authorizer = Authorizer(config.allowed_users, config.allowed_groups)
        self._sel = selectors.DefaultSelector()
        self._conns: dict[int, _Connection] = {}
        self._ids = itertools.count()
        self._dispatch: queue.SimpleQueue = queue.SimpleQueue()
        self._replies: queue.SimpleQueue = queue.SimpleQueue()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._stop = threading.Event()
        self._dispatch_done = False
        self._deadline = math.inf
        self._threads: list[threading.Thread] = []
        self._listener: socket.socket | None = None
        self._inode: tuple[int, int] | None = None
        #: what the server has seen; ``polls`` counts wake-ups of the I/O thread (about 2/s when idle)
        self.counters = {"connections": 0, "requests": 0, "errors": 0, "refused_clients": 0, "polls": 0}

    # -- life cycle --------------------------------------------------------------------------
    def start(self) -> "ControlServer":
        self._listener, st = bind_control_socket(self.path)
        self._inode = (st.st_dev, st.st_ino)
        self._sel.register(self._listener, selectors.EVENT_READ, "listen")
        self._sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        self._threads = [threading.Thread(target=self._io_loop, name="otbot-control", daemon=True),
                         threading.Thread(target=self._dispatch_loop, name="otbot-dispatch", daemon=True)]
        for t in self._threads:
            t.start()
        log.info("control socket %s", self.path)
        return self

    def close(self, timeout: float = 2.0) -> None:
        """Stop serving and remove the socket file (only if it is still ours). New connections and
        requests are no longer taken; requests already queued are carried out and their replies
        sent (within ``timeout`` s), so a handler may call this, e.g. from ``shutdown``, and its
        own reply still goes out. It does not wait for the thread it is called from."""
        if self._stop.is_set():
            return
        self._stop.set()
        self._deadline = time.monotonic() + timeout
        self._dispatch.put(None)  # after everything queued
        self._wake()
        if threading.current_thread() in self._threads:
            return  # called by the handler: the threads finish once its reply is out
        for t in self._threads:
            t.join(timeout + 0.5)

    def _remove_socket_file(self) -> None:
        try:
            st = self.path.lstat()
            if (st.st_dev, st.st_ino) == self._inode:
                self.path.unlink()
        except FileNotFoundError:
            pass

    def __enter__(self) -> "ControlServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def _wake(self) -> None:
        try:
            self._wake_w.send(b"\0")
        except (BlockingIOError, OSError):
            pass  # already woken

    # -- I/O thread ------------------------------------------------------------------------
    def _io_loop(self) -> None:
        try:
            while not self._finished():
                self.counters["polls"] += 1
                for key, events in self._sel.select(timeout=0.5):
                    if key.data == "listen":
                        self._accept()
                    elif key.data == "wake":
                        try:
                            while self._wake_r.recv(4096):
                                pass
                        except BlockingIOError:
                            pass
                    else:
                        conn = self._conns.get(key.data)
                        if conn is None:
                            continue
                        if events & selectors.EVENT_READ:
                            self._read(key.data, conn)
                        if events & selectors.EVENT_WRITE and key.data in self._conns:
                            self._flush(key.data, conn)
                self._deliver_replies()
                self._expire(time.monotonic())
        except Exception:  # pragma: no cover - a bug here must not take the daemon down silently
            log.exception("control socket I/O thread failed")
        finally:
            for cid in list(self._conns):
                self._drop(cid)
            self._sel.close()
            if self._listener is not None:
                self._listener.close()
            self._remove_socket_file()
            self._wake_r.close()

    def _accept(self) -> None:
        while True:
            try:
                sock, _ = self._listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:  # EMFILE and friends: keep serving the others
                log.warning("accept failed: %s", exc)
                return
            sock.setblocking(False)
            try:
                peer = peer_credentials(sock)
            except OSError:
                sock.close()
                continue
            cid = next(self._ids)
            conn = _Connection(sock, peer, self.authorizer.allows(peer))
            self._conns[cid] = conn
            self._sel.register(sock, selectors.EVENT_READ, cid)
            self.counters["connections"] += 1
            if len(self._conns) > self.config.max_clients:
                self.counters["refused_clients"] += 1
                self._send(cid, conn, encode_reply(None, error=(
                    "busy", f"too many clients (limit {self.config.max_clients})")), close=True)

    def _read(self, cid: int, conn: _Connection) -> None:
        if conn.closing:
            return
        try:
            data = conn.sock.recv(65536)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""
        if not data:  # peer closed (maybe mid-request): forget its partial line, nothing dispatched
            self._drop(cid)
            return
        conn.inbuf += data
        limit = self.config.max_request
        completed = False
        while not conn.closing:
            nl = conn.inbuf.find(b"\n", 0, limit + 1)
            if nl < 0:
                if len(conn.inbuf) > limit:
                    self._error(cid, conn, None, "too_large",
                                f"request line longer than {limit} bytes", close=True)
                    conn.inbuf.clear()
                break
            line = bytes(conn.inbuf[:nl]).rstrip(b"\r")
            del conn.inbuf[:nl + 1]
            completed = True
            if line.strip():
                self._request(cid, conn, line)
        if not conn.inbuf:
            conn.started = None
        elif completed or conn.started is None:  # a new partial line starts its clock
            conn.started = time.monotonic()

    def _request(self, cid: int, conn: _Connection, line: bytes) -> None:
        self.counters["requests"] += 1
        try:
            req = parse_request(line, self.limits)
        except ProtocolError as exc:
            self._error(cid, conn, exc.request_id, exc.code, str(exc))
            return
        if req.cmd not in OPEN_COMMANDS and not conn.allowed:
            log.warning("refused %s from %s: not an allowed user or group", req.cmd, conn.peer)
            self._error(cid, conn, req.id, "forbidden",
                        f"{req.cmd}: {conn.peer} may not command the robot (daemon.socket.allowed_users/"
                        f"allowed_groups); only {', '.join(sorted(OPEN_COMMANDS))} is open")
            return
        if req.cmd == "estop":  # now, on this thread: never queued behind a slow command
            self._send(cid, conn, self._call(req, conn.peer))
            return
        if conn.in_flight >= MAX_IN_FLIGHT:
            self._error(cid, conn, req.id, "busy", f"more than {MAX_IN_FLIGHT} requests in flight")
            return
        conn.in_flight += 1
        self._dispatch.put((cid, req, conn.peer))

    def _error(self, cid, conn, rid, code, message, close=False) -> None:
        self.counters["errors"] += 1
        self._send(cid, conn, encode_reply(rid, error=(code, message)), close=close)

    def _send(self, cid: int, conn: _Connection, data: bytes, close: bool = False) -> None:
        conn.outbuf += data
        conn.closing = conn.closing or close
        if len(conn.outbuf) > MAX_OUTPUT:
            log.warning("dropping %s: %d bytes of replies unread", conn.peer, len(conn.outbuf))
            self._drop(cid)
            return
        self._flush(cid, conn)

    def _flush(self, cid: int, conn: _Connection) -> None:
        try:
            while conn.outbuf:
                n = conn.sock.send(conn.outbuf)
                del conn.outbuf[:n]
        except (BlockingIOError, InterruptedError):
            pass
        except OSError:  # peer gone: its replies go nowhere, nothing else changes
            self._drop(cid)
            return
        if not conn.outbuf and conn.closing:
            self._drop(cid)
            return
        self._interest(cid, conn)

    def _interest(self, cid: int, conn: _Connection) -> None:
        """Read while serving, write while replies are pending; no reading from a connection
        being closed or once the server is closing (so it never spins on unread sockets)."""
        reading = not (self._stop.is_set() or conn.closing)
        want = (selectors.EVENT_READ if reading else 0) | (selectors.EVENT_WRITE if conn.outbuf else 0)
        registered = self._registered(conn)
        if want and registered:
            self._sel.modify(conn.sock, want, cid)
        elif want:
            self._sel.register(conn.sock, want, cid)
        elif registered:
            self._sel.unregister(conn.sock)

    def _registered(self, conn: _Connection) -> bool:
        try:
            self._sel.get_key(conn.sock)
            return True
        except KeyError:
            return False

    def _drop(self, cid: int) -> None:
        conn = self._conns.pop(cid, None)
        if conn is not None:
            try:
                self._sel.unregister(conn.sock)
            except (KeyError, ValueError):
                pass
            conn.sock.close()

    def _expire(self, now: float) -> None:
        for cid, conn in list(self._conns.items()):
            if conn.started is not None and now - conn.started > self.config.request_timeout:
                self._error(cid, conn, None, "timeout", f"request line not completed within "
                                                        f"{self.config.request_timeout:g} s", close=True)
                conn.inbuf.clear()
                conn.started = None

    def _finished(self) -> bool:
        """Closing, and every queued reply is written (or the close timeout has passed)."""
        if not self._stop.is_set():
            return False
        if self._listener is not None and self._listener.fileno() >= 0:
            self._sel.unregister(self._listener)
            self._listener.close()  # no new connections: clients now get "connection refused"
            for cid, conn in list(self._conns.items()):
                self._interest(cid, conn)
        pending = any(c.outbuf for c in self._conns.values())
        return (self._dispatch_done and not pending) or time.monotonic() > self._deadline

    def _deliver_replies(self) -> None:
        while True:
            try:
                item = self._replies.get_nowait()
            except queue.Empty:
                return
            if item is None:  # the dispatch thread has finished
                self._dispatch_done = True
                continue
            cid, data = item
            conn = self._conns.get(cid)
            if conn is not None:  # a client that left before its reply: the reply is dropped
                conn.in_flight -= 1
                self._send(cid, conn, data)

    # -- dispatch thread ---------------------------------------------------------------------
    def _dispatch_loop(self) -> None:
        while True:
            item = self._dispatch.get()
            if item is None:
                self._replies.put(None)
                self._wake()
                return
            cid, req, peer = item
            self._replies.put((cid, self._call(req, peer)))
            self._wake()

    def _call(self, req: Request, peer: Peer) -> bytes:
        log.info("%s %s from %s", req.cmd, json.dumps(req.args), peer)
        try:
            result = getattr(self.handler, req.cmd)(**req.args, peer=peer)
            if req.cmd == "status":
                check_status(result)
            return encode_reply(req.id, result)
        except CommandRefused as exc:
            return encode_reply(req.id, error=("refused", str(exc)))
        except ProtocolError as exc:  # an argument found bad on closer look (a file that does not parse)
            return encode_reply(req.id, error=(exc.code, str(exc)))
        except Exception as exc:
            log.exception("%s failed", req.cmd)
            return encode_reply(req.id, error=("internal", f"{req.cmd} failed: {type(exc).__name__}: {exc}"))


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
            self._sock.connect(str(self.path))
        except FileNotFoundError:
            self._sock.close()
            raise DaemonUnreachable(f"no daemon at {self.path} (no such socket)") from None
        except ConnectionRefusedError:
            self._sock.close()
            raise DaemonUnreachable(f"no daemon at {self.path} (connection refused: stale socket)") from None
        except PermissionError:
            self._sock.close()
            raise DaemonUnreachable(f"no permission to connect to {self.path} (join the daemon's group)") from None
        except OSError as exc:
            self._sock.close()
            raise DaemonUnreachable(f"cannot connect to {self.path}: {exc.strerror or exc}") from None
        self._file = self._sock.makefile("rb")

    def request(self, cmd: str, args: dict | None = None) -> Any:
        rid = next(self._ids)
        lost: OSError | None = None
        try:
            self._sock.sendall(encode_request(rid, cmd, args))
        except socket.timeout:
            raise DaemonUnreachable(f"the daemon at {self.path} did not answer within {self.timeout:g} s") from None
        except OSError as exc:  # closed by the daemon: it may have said why before closing
            lost = exc
        try:
            line = self._file.readline()
        except socket.timeout:
            raise DaemonUnreachable(f"the daemon at {self.path} did not answer within {self.timeout:g} s") from None
        except OSError as exc:
            line, lost = b"", lost or exc
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


__all__ = ["ControlServer", "ControlClient", "CommandHandler", "LoopMailbox", "Peer", "Authorizer",
           "SocketInUse", "DaemonUnreachable", "ControlError", "bind_control_socket", "probe_socket",
           "peer_credentials", "COMMANDS"]
