"""Live telemetry: a read-only Foxglove WebSocket server (the ``foxglove-sdk`` package).

Open Foxglove (app or web), "Open connection", Foxglove WebSocket, ``ws://ROBOT:8765`` (through
an SSH tunnel: the server binds 127.0.0.1 by default). Channels, all in SI units:

=====================  ==========================  ==================================================
topic                  schema (encoding)           content
=====================  ==========================  ==================================================
/tf                    foxglove.FrameTransforms    world -> platform (the pose estimate x, y, alpha),
                       (protobuf)                  platform -> chassis (the chassis frame B' at the
                                                   wheel-axis midpoint M, heading alpha - phi_p),
                                                   world -> reference (desired pose, when tracking)
/otbot/joints          otbot.JointState (json)     name, position (rad), velocity (rad/s)
/otbot/torques         otbot.Torques (json)        commanded and limit (N m), ratio, saturated
/otbot/tracking_error  otbot.TrackingError (json)  reference - estimate: x, y (m), alpha (rad), norm (m)
/otbot/estimate        otbot.Estimate (json)       pose, twist, std (sigma of pose and twist), gyro bias
/otbot/status          otbot.Status (json)         mode, faults (list of sentences), drive states
/otbot/log             foxglove.Log (protobuf)     one line per mode change and per new fault
=====================  ==========================  ==================================================

Read-only: no capability is advertised (no client publishing, no services, no parameters), so
the server refuses a client's ``advertise`` and ignores its message data; nothing a client sends
reaches the robot. ``publish(sample)`` (or ``publish_cycle``, from the loop's objects) is called by
the loop once per cycle; it sends at most ``rate`` Hz (a skipped call costs a few comparisons),
except that a changed mode or fault list goes out at once, and the status channel repeats every
second for clients that join later.

Nothing is encoded on the loop's thread: a sample that goes out is copied into one of a fixed set
of preallocated slots and queued; the ``otbot-telemetry`` thread, woken by it, builds the messages
(protobuf, JSON) and hands them to the server. The loop publishes after its write, so that work falls
in the period's idle time (a thread waking at times of its own could take the interpreter, which the
threads share, from the loop in the middle of a cycle). The queue is bounded (``queue_size``): when
the consumer stalls, the loop takes back the oldest queued slot -- that sample is dropped and counted
(``state.dropped``), the loop never waits.
"""
from __future__ import annotations

import collections
import logging
import math
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from otbot_hw.model.angles import wrap_angle  # noqa: F401  (the one angle wrap, [-pi, pi))
from otbot_hw.runtime.telemetry_messages import (  # noqa: F401  (importable from here)
    CHASSIS, JOINT_NAMES, PLATFORM, REFERENCE, WORLD, Slot, TelemetryChannels, chassis_in_platform)
STATUS_REPEAT_S = 1.0
#: Samples the loop may queue for the telemetry thread before the oldest is dropped (1.3 s at 50 Hz).
QUEUE_SIZE = 64

log = logging.getLogger(__name__)

class TelemetryError(RuntimeError):
    """The telemetry server cannot start (port in use, unknown host); the message says which."""


@dataclass(frozen=True)
class TelemetrySample:
    """One loop cycle as telemetry sees it. t: loop time (s); joint_pos (3,) rad, joint_vel (3,)
    rad/s; torque (3,) N m commanded, saturated (3,) bool; pose (3,) x, y (m), alpha (rad), twist
    (3,), std (6,) and gyro_bias (rad/s) of the estimate (None without one); reference (3,) the
    desired pose when tracking; mode; faults (``Fault`` objects or sentences); drive_states
    (CiA 402 state names, joint order)."""

    t: float
    joint_pos: Any
    joint_vel: Any
    torque: Any
    saturated: Any = (False, False, False)
    pose: Any = None
    twist: Any = None
    std: Any = None
    gyro_bias: float | None = None
    reference: Any = None
    mode: str = "idle"
    faults: tuple = ()
    drive_states: tuple = ()

    @classmethod
    def from_cycle(cls, snapshot, command=None, estimate=None, reference=None, mode: str = "idle",
                   faults=None) -> "TelemetrySample":
        """From the loop's ``Snapshot``, ``Command`` (what ``Robot.write`` returned), ``Estimate``
        (``otbot_hw.estimation``) and desired pose (3,), by attribute names only."""
        return cls(t=float(snapshot.t), joint_pos=snapshot.joint_pos, joint_vel=snapshot.joint_vel,
                   torque=command.commanded if command is not None else np.zeros(3),
                   saturated=command.saturated if command is not None else (False,) * 3,
                   pose=getattr(estimate, "pose", None), twist=getattr(estimate, "twist", None),
                   std=getattr(estimate, "std", None), gyro_bias=getattr(estimate, "gyro_bias", None),
                   reference=reference, mode=mode,
                   faults=tuple(snapshot.faults if faults is None else faults),
                   drive_states=tuple(snapshot.drive_states))


def parse_host_port(text: str, default_port: int = 8765) -> tuple[str, int]:
    """``HOST:PORT`` (or ``HOST``, or ``[v6]:PORT``) for ``--telemetry``; ValueError naming the problem."""
    host, port = text, str(default_port)
    if text.startswith("["):
        end = text.find("]")
        if end < 0:
            raise ValueError(f"telemetry address {text!r}: unclosed '['")
        host, rest = text[1:end], text[end + 1:]
        if rest:
            if not rest.startswith(":"):
                raise ValueError(f"telemetry address {text!r}: expected ':PORT' after ']'")
            port = rest[1:]
    elif text.count(":") == 1:
        host, port = text.split(":")
    if not host:
        raise ValueError(f"telemetry address {text!r}: no host")
    if not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"telemetry address {text!r}: port must be 0..65535, got {port!r}")
    return host, int(port)


def check_telemetry_address(host: str, port: int) -> None:
    """TelemetryError (one sentence: what is wrong and what to do) unless a TCP server can listen
    on ``host:port``: the host resolves, is an address of this machine, and the port is free. Port
    0 (any free port) only has its host checked. Run before anything else starts."""
    import errno
    import socket

    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (socket.gaierror, UnicodeError) as exc:
        raise TelemetryError(f"telemetry host {host!r} is unknown ({getattr(exc, 'strerror', None) or exc}): "
                             f"give --telemetry HOST:PORT with an address of this machine, or --no-telemetry") from None
    family, kind, proto, _, addr = infos[0]
    s = socket.socket(family, kind, proto)
    try:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server will: TIME_WAIT is no conflict
        s.bind(addr)
        s.listen(1)
    except OSError as exc:
        if exc.errno == errno.EADDRINUSE:
            raise TelemetryError(f"telemetry port {port} on {host} is taken (another daemon, or a leftover one?): "
                                 f"stop it, or give --telemetry {host}:0 (any free port) or --no-telemetry") from None
        if exc.errno == errno.EADDRNOTAVAIL:
            raise TelemetryError(f"telemetry host {host} is not an address of this machine: give --telemetry "
                                 f"127.0.0.1:{port} (or one of this machine's addresses) or --no-telemetry") from None
        raise TelemetryError(f"cannot serve telemetry on {host}:{port}: {exc.strerror or exc}") from None
    finally:
        s.close()


class _Listener:
    """Counts subscriptions; notes anything a client tries to send (must stay empty)."""

    def __init__(self):
        self.subscriptions = 0
        self.client_messages = 0

    def on_subscribe(self, client, channel) -> None:
        self.subscriptions += 1

    def on_unsubscribe(self, client, channel) -> None:
        self.subscriptions -= 1

    def on_client_advertise(self, client, channel) -> None:  # not reached without ClientPublish
        self.client_messages += 1

    def on_message_data(self, client, client_channel_id, data) -> None:
        self.client_messages += 1


@dataclass
class _State:
    next_due: float = -math.inf
    last_status: float = -math.inf
    mode: str | None = None
    faults: tuple = ()
    drive_states: tuple = ()
    published: int = 0
    skipped: int = 0
    dropped: int = 0   # queued samples the loop took back because the telemetry thread had not sent them
    errors: int = 0    # samples the telemetry thread failed to send
    counts: dict = field(default_factory=dict)


class TelemetryServer:
    """The Foxglove WebSocket server and its channels, on a context of its own (nothing else in
    the process publishes into it). ``limits`` (3,) N m: the motors' torque limits; ``l1`` (m):
    pivot offset (paper Table 3) for the chassis frame; ``port`` 0 picks a free port (``port``
    attribute after start); ``queue_size``: samples queued for the telemetry thread at most."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, rate: float = 50.0, limits=None,
                 l1: float | None = None, name: str = "otbot", queue_size: int = QUEUE_SIZE):
        import foxglove

        if not (math.isfinite(rate) and rate > 0):
            raise ValueError(f"telemetry rate must be > 0 Hz, got {rate}")
        if l1 is None:
            from otbot_hw.params import nominal
            l1 = nominal().l1
        self.rate = float(rate)
        self.period = 1.0 / self.rate
        self.l1 = float(l1)
        self.limits = np.asarray(limits if limits is not None else [np.inf] * 3, float)
        self.context = foxglove.Context()
        self.channels = TelemetryChannels(self.context, self.limits, self.l1)
        self.listener = _Listener()
        try:
            self.server = foxglove.start_server(name=name, host=host, port=port, capabilities=[], services=None,
                                                server_listener=self.listener, context=self.context)
        except RuntimeError as exc:  # FoxgloveError: port in use, unknown host
            raise TelemetryError(f"cannot serve telemetry on {host}:{port}: "
                                 f"{str(exc).removeprefix('FoxgloveError: ')}") from None
        self.host = host
        self.port = self.server.port
        self.state = _State()
        self.queue_size = int(queue_size)
        self._queue: collections.deque = collections.deque()
        self._free = collections.deque(Slot() for _ in range(self.queue_size + 2))
        self._stop = threading.Event()
        self._wake = threading.Event()  # set by each queued sample
        self._idle = threading.Event()  # set while the telemetry thread has nothing in hand
        self._idle.set()
        self._thread = threading.Thread(target=self._run, name="otbot-telemetry", daemon=True)
        self._thread.start()

    # -- the loop's call ---------------------------------------------------------------------
    def publish(self, sample: TelemetrySample, now: float | None = None) -> bool:
        """Called once per loop cycle; ``now`` monotonic s. Returns whether it queued the sample."""
        return self._offer(now, sample.t, sample.joint_pos, sample.joint_vel, sample.torque, sample.saturated,
                           sample.pose, sample.twist, sample.std, sample.gyro_bias, sample.reference, sample.mode,
                           sample.faults, sample.drive_states)

    def publish_cycle(self, snapshot, command=None, estimate=None, reference=None, mode: str = "idle",
                      faults=None, now: float | None = None) -> bool:
        """``publish(TelemetrySample.from_cycle(...))`` without building the sample: the loop's
        ``Snapshot``, ``Command`` (None: unarmed), estimate and desired pose (3,) are read only when
        the sample goes out."""
        if command is not None:
            torque, saturated = command.commanded, command.saturated
        else:
            torque, saturated = _ZERO3, _UNSATURATED
        if estimate is not None:
            pose, twist, std, bias = estimate.pose, estimate.twist, estimate.std, estimate.gyro_bias
        else:
            pose = twist = std = bias = None
        return self._offer(now, snapshot.t, snapshot.joint_pos, snapshot.joint_vel, torque, saturated, pose, twist,
                           std, bias, reference, mode, snapshot.faults if faults is None else faults,
                           snapshot.drive_states)

    def _offer(self, now, t, joint_pos, joint_vel, torque, saturated, pose, twist, std, gyro_bias, reference, mode,
               faults, drive_states) -> bool:
        now = time.monotonic() if now is None else now
        st = self.state
        faults = faults if type(faults) is tuple else tuple(faults)
        drive_states = drive_states if type(drive_states) is tuple else tuple(drive_states)
        changed = mode != st.mode or faults != st.faults or drive_states != st.drive_states
        due = now >= st.next_due - 1e-6
        if not changed and not due:
            st.skipped += 1
            return False
        slot = self._take_slot()
        if slot is None:
            return False
        slot.t, slot.mode, slot.faults, slot.drive_states = float(t), mode, faults, drive_states
        slot.prev_mode, slot.prev_faults, slot.changed, slot.cycle = st.mode, st.faults, changed, due
        slot.status = changed or now - st.last_status >= STATUS_REPEAT_S
        slot.stamp = time.time_ns()
        if due:
            v, has = slot.vec, slot.has
            v[0:3], v[3:6], v[6:9] = joint_pos, joint_vel, torque
            slot.saturated = tuple(saturated)
            for i, (x, lo, hi) in enumerate(((pose, 9, 12), (twist, 12, 15), (std, 15, 21), (gyro_bias, 24, 25),
                                             (reference, 21, 24))):
                has[i] = x is not None
                if x is not None:
                    v[lo:hi] = x
            st.next_due = st.next_due + self.period if now - st.next_due < self.period else now + self.period
            st.published += 1
        if changed:
            st.mode, st.faults, st.drive_states = mode, faults, drive_states
        if slot.status:
            st.last_status = now
        self._queue.append(slot)
        self._wake.set()  # the loop calls this after its write: the encoding runs in the period's idle time
        return True

    def _take_slot(self) -> Slot | None:
        """A free slot, else the oldest queued one (its sample dropped); None when the telemetry thread
        holds them all."""
        try:
            return self._free.pop()
        except IndexError:
            pass
        self.state.dropped += 1
        try:
            return self._queue.popleft()
        except IndexError:
            return None

    # -- the telemetry thread ----------------------------------------------------------------
    def _run(self) -> None:
        while True:
            self._wake.wait(1.0)
            self._wake.clear()
            stopping = self._stop.is_set()
            self._drain()
            if stopping:
                return

    def _drain(self) -> None:
        while True:
            try:
                slot = self._queue.popleft()
            except IndexError:
                return
            self._idle.clear()
            try:
                self._send(slot)
            except Exception as exc:  # noqa: BLE001 -- telemetry never takes the daemon down
                self.state.errors += 1
                if self.state.errors == 1:
                    log.warning("telemetry: a sample could not be sent (%s); counting further ones", exc)
            finally:
                self._free.append(slot)
                self._idle.set()

    def flush(self, timeout: float = 2.0) -> bool:
        """Wait until every queued sample is sent (tests, shutdown); False on timeout."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if not self._queue and self._idle.is_set():
                return True
            time.sleep(0.002)
        return False

    def _send(self, slot: Slot) -> None:
        self.channels.send(slot)

    # -- life cycle --------------------------------------------------------------------------
    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def status(self) -> dict:
        """For the daemon's ``status`` reply: address, subscriptions, messages sent/skipped."""
        return {"url": self.url, "subscriptions": self.listener.subscriptions,
                "published": self.state.published, "skipped": self.state.skipped, "dropped": self.state.dropped}

    def close(self) -> None:
        """Send what is queued (up to 1 s), stop the telemetry thread, then the server."""
        self.flush(1.0)
        self._stop.set()
        self._wake.set()
        self._thread.join(2.0)
        self.server.stop()

    def __enter__(self) -> "TelemetryServer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


_ZERO3 = np.zeros(3)
_UNSATURATED = (False, False, False)