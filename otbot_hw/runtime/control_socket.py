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

Its parts: ``control_peers`` (peer credentials and who may command), ``control_socket_file``
(the socket file: path checks, safe bind, a live daemon refused, a stale socket removed),
``loop_mailbox`` (``LoopMailbox``), the wire format in ``control_protocol``. This module is the
server: connections, line framing, admission, dispatch.

Length: ``ControlServer`` is one state machine (the I/O thread's connections, their buffers, slots and
timeouts); its methods share those invariants, and spreading them over modules would hide them.
"""
from __future__ import annotations

import itertools
import json
import logging
import math
import queue
import select
import selectors
import socket
import threading
import time
from pathlib import Path
from typing import Callable, Protocol

from otbot_hw.runtime.control_peers import Authorizer, Peer, peer_credentials
from otbot_hw.runtime.control_protocol import (
    OPEN_COMMANDS, ArgumentLimits, CommandRefused, ProtocolError, Request, check_command, check_status,
    decode_request, encode_reply, validate_args)
from otbot_hw.runtime.control_socket_file import bind_control_socket
from otbot_hw.runtime.daemon_config import ControlSocketConfig

log = logging.getLogger(__name__)

MAX_IN_FLIGHT = 8              # requests of one connection waiting for the handler
MAX_OUTPUT = 1 << 20           # bytes of unread replies before a client is dropped


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



class _Connection:
    __slots__ = ("sock", "peer", "allowed", "inbuf", "outbuf", "started", "in_flight", "closing", "eof",
                 "opened", "active")

    def __init__(self, sock: socket.socket, peer: Peer, allowed: bool, now: float):
        self.sock, self.peer, self.allowed = sock, peer, allowed
        self.inbuf = bytearray()
        self.outbuf = bytearray()
        self.started: float | None = None  # monotonic time the pending partial line began
        self.in_flight = 0
        self.closing = False               # close once outbuf is written
        self.eof = False                   # the peer closed its write side: reply, then close
        self.opened = now                  # monotonic time of accept (eviction: oldest first)
        self.active = now                  # last byte received or reply sent (idle timeout)


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
        reserved = min(config.reserved_clients, config.max_clients - 1)
        #: connections a status-only peer may take; the rest are kept for allowed peers
        self.status_only_limit = max(1, config.max_clients - max(reserved, 0))
        #: called once (from the failing thread) with a sentence if a server thread dies of a bug
        #: while serving: the daemon then quick-stops, latches a fault and stops its watchdog ping
        self.on_failure: Callable[[str], None] | None = None
        self.failure: str | None = None
        #: what the server has seen; ``polls`` counts wake-ups of the I/O thread (about 2/s when idle)
        self.counters = {"connections": 0, "requests": 0, "errors": 0, "refused_clients": 0, "polls": 0,
                         "evicted": 0, "idle_closed": 0, "internal_errors": 0}

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

    @property
    def io_thread_id(self) -> int | None:
        """Kernel thread id of the I/O thread (where ``estop`` acts; None before ``start``)."""
        return self._threads[0].native_id if self._threads else None

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

    @property
    def alive(self) -> bool:
        """Serving: started, not closing, and both threads running."""
        return (bool(self._threads) and not self._stop.is_set()
                and all(t.is_alive() for t in self._threads))

    def _failed(self, what: str) -> None:
        """A server thread is dying of a bug while serving: say so once, to the log and ``on_failure``."""
        if self._stop.is_set() or self.failure is not None:
            return
        self.failure = f"control socket {what} thread failed"
        log.critical("%s", self.failure)
        if self.on_failure is not None:
            try:
                self.on_failure(self.failure)
            except Exception:  # noqa: BLE001 - the callback must not hide the failure
                log.exception("control socket failure callback failed")

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
                        self._serve(key.data, events)
                self._deliver_replies()
                self._expire(time.monotonic())
        except BaseException:  # a bug here must not take the daemon down silently
            log.exception("control socket I/O thread failed")
            self._failed("I/O")
        finally:
            for cid in list(self._conns):
                self._drop(cid)
            self._sel.close()
            if self._listener is not None:
                self._listener.close()
            self._remove_socket_file()
            self._wake_r.close()

    def _serve(self, cid: int, events: int) -> None:
        """One connection's events, inside its error boundary: whatever a request does, a bug it
        triggers costs that connection an ``internal`` error reply and its close, never the server."""
        conn = self._conns.get(cid)
        if conn is None:
            return
        try:
            if events & selectors.EVENT_READ:
                self._read(cid, conn)
            if events & selectors.EVENT_WRITE and cid in self._conns:
                self._flush(cid, conn)
        except Exception as exc:  # noqa: BLE001 - the per-connection error boundary
            self.counters["internal_errors"] += 1
            log.exception("control socket: request from %s failed", conn.peer)
            if cid in self._conns:
                try:
                    conn.inbuf.clear()
                    self._error(cid, conn, None, "internal", f"the server failed on this connection's "
                                                             f"request ({type(exc).__name__}); closing it", close=True)
                except Exception:  # noqa: BLE001
                    self._drop(cid)

    def _accept(self) -> None:
        while True:
            try:
                sock, _ = self._listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:  # EMFILE and friends: keep serving the others
                log.warning("accept failed: %s", exc)
                return
            try:
                sock.setblocking(False)
                peer = peer_credentials(sock)
                allowed = self.authorizer.allows(peer)
            except Exception as exc:  # noqa: BLE001 - credentials unreadable or the user database failing
                log.warning("dropping a connection whose credentials cannot be checked: %s", exc)
                sock.close()
                continue
            now = time.monotonic()
            cid = next(self._ids)
            conn = _Connection(sock, peer, allowed, now)
            self._conns[cid] = conn
            self._sel.register(sock, selectors.EVENT_READ, cid)
            self.counters["connections"] += 1
            self._admit(cid, conn)

    def _admit(self, cid: int, conn: _Connection) -> None:
        """Keep the connection if there is room for its kind of peer. A status-only peer may hold
        ``status_only_limit`` connections in all; an allowed peer that finds every slot taken evicts
        the oldest status-only connection, so an emergency stop always finds a way in."""
        live = [c for c in self._conns.values() if not c.closing]
        if len(live) > self.config.max_clients or (not conn.allowed and len(live) > self.status_only_limit):
            self._reap(cid)  # clients that have gone already (a burst accepted at once) hold no slot
            live = [c for c in self._conns.values() if not c.closing]
        busy = None
        if len(live) > self.config.max_clients:
            victims = sorted(((c.opened, k) for k, c in self._conns.items()
                              if not c.allowed and not c.closing and k != cid))
            if conn.allowed and victims:
                k = victims[0][1]
                victim = self._conns[k]
                self.counters["evicted"] += 1
                log.warning("evicting the oldest status-only connection (%s) for %s", victim.peer, conn.peer)
                self._error(k, victim, None, "busy", f"closed to make room for an allowed user "
                                                     f"(limit {self.config.max_clients} clients)", close=True)
            else:
                busy = f"too many clients (limit {self.config.max_clients})"
        elif not conn.allowed and sum(1 for c in live if not c.allowed) > self.status_only_limit:
            busy = (f"too many status-only clients (limit {self.status_only_limit}; "
                    f"{self.config.max_clients - self.status_only_limit} kept for allowed users)")
        if busy is not None:
            self.counters["refused_clients"] += 1
            self._send(cid, conn, encode_reply(None, error=("busy", busy)), close=True)

    def _reap(self, keep: int) -> None:
        """Read every other connection once now (not waiting for its turn in the selector), so those
        whose peer has already closed are dropped before a newcomer is refused for want of room."""
        for k, c in list(self._conns.items()):
            if k != keep and k in self._conns and not (c.closing or c.eof):
                self._serve(k, selectors.EVENT_READ)
        poll = select.poll()
        gone = {c.sock.fileno(): k for k, c in self._conns.items() if k != keep and c.eof}
        for fd in gone:
            poll.register(fd, select.POLLHUP)
        for fd, ev in poll.poll(0):  # POLLHUP: closed for good, not just half-closed (SHUT_WR)
            if ev & (select.POLLHUP | select.POLLERR):
                self._drop(gone[fd])  # its pending replies would go nowhere

    def _read(self, cid: int, conn: _Connection) -> None:
        if conn.closing or conn.eof:
            return
        try:
            data = conn.sock.recv(65536)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:  # reset by the peer: nobody to answer
            self._drop(cid)
            return
        conn.active = time.monotonic()
        if not data:
            self._end_of_input(cid, conn)
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

    def _end_of_input(self, cid: int, conn: _Connection) -> None:
        """The peer closed its write side (``shutdown(SHUT_WR)``, as ``socat`` does after its
        request, or a full close): a last line without its newline is still a request; the replies
        of everything it sent go out, then the connection closes."""
        conn.eof = True
        line = bytes(conn.inbuf).rstrip(b"\r")
        conn.inbuf.clear()
        conn.started = None
        if line.strip() and not conn.closing:
            self._request(cid, conn, line)
        if cid in self._conns:
            self._flush(cid, conn)

    def _request(self, cid: int, conn: _Connection, line: bytes) -> None:
        """Decode (bounded numbers), read the command name, check authorization, then validate the
        arguments: a peer that may not send a command never has its arguments looked at."""
        self.counters["requests"] += 1
        try:
            rid, name, args = decode_request(line)
            cmd = check_command(rid, name)
            if cmd not in OPEN_COMMANDS and not conn.allowed:
                log.warning("refused %s from %s: not an allowed user or group", cmd, conn.peer)
                self._error(cid, conn, rid, "forbidden",
                            f"{cmd}: {conn.peer} may not command the robot (allow it with daemon.socket.allowed_users "
                            f"or allowed_groups in the daemon's configuration, or `otbot daemon --allow-user NAME`); "
                            f"only {', '.join(sorted(OPEN_COMMANDS))} is open")
                return
            try:
                req = Request(id=rid, cmd=cmd, args=validate_args(cmd, args, self.limits))
            except ProtocolError as exc:
                exc.request_id = rid
                raise
        except ProtocolError as exc:
            self._error(cid, conn, exc.request_id, exc.code, str(exc))
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
                conn.active = time.monotonic()
        except (BlockingIOError, InterruptedError):
            pass
        except OSError:  # peer gone: its replies go nowhere, nothing else changes
            self._drop(cid)
            return
        if not conn.outbuf and (conn.closing or (conn.eof and conn.in_flight == 0)):
            self._drop(cid)
            return
        self._interest(cid, conn)

    def _interest(self, cid: int, conn: _Connection) -> None:
        """Read while serving, write while replies are pending; no reading from a connection
        being closed, half-closed by its peer, or once the server is closing (so it never spins on
        unread sockets)."""
        reading = not (self._stop.is_set() or conn.closing or conn.eof)
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
        cfg = self.config
        for cid, conn in list(self._conns.items()):
            if cid not in self._conns or conn.closing:
                continue
            if conn.started is not None and now - conn.started > cfg.request_timeout:
                conn.inbuf.clear()
                conn.started = None
                self._error(cid, conn, None, "timeout", f"request line not completed within "
                                                        f"{cfg.request_timeout:g} s", close=True)
            elif conn.in_flight == 0 and not conn.outbuf and now - conn.active > cfg.idle_timeout:
                self.counters["idle_closed"] += 1
                self._error(cid, conn, None, "timeout", f"idle for {cfg.idle_timeout:g} s: closed", close=True)

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
                try:
                    self._send(cid, conn, data)
                except Exception:  # noqa: BLE001 - that connection's problem only
                    log.exception("control socket: reply to %s failed", conn.peer)
                    self._drop(cid)

    # -- dispatch thread ---------------------------------------------------------------------
    def _dispatch_loop(self) -> None:
        try:
            while True:
                item = self._dispatch.get()
                if item is None:
                    self._replies.put(None)
                    self._wake()
                    return
                cid, req, peer = item
                if cid not in self._conns and req.cmd == "status":
                    continue  # its client has left: a flood of abandoned requests costs nothing
                self._replies.put((cid, self._call(req, peer)))
                self._wake()
        except BaseException:
            log.exception("control socket dispatch thread failed")
            self._failed("dispatch")
            raise

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
        except Exception as exc:  # noqa: BLE001 - the handler's failure is this request's, not the server's
            log.exception("%s failed", req.cmd)
            return encode_reply(req.id, error=("internal", f"{req.cmd} failed: {type(exc).__name__}: {str(exc)[:200]}"))
