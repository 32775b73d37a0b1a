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
reaches the robot. ``publish(sample)`` is called by the loop once per cycle; it sends at most
``rate`` Hz (a skipped call costs one comparison), except that a changed mode or fault list goes
out at once, and the status channel repeats every second for clients that join later.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from otbot_hw.model.angles import wrap_angle  # noqa: F401  (the one angle wrap, [-pi, pi))
from otbot_hw.motors import MOTORS

JOINT_NAMES = list(MOTORS)  # right_wheel, left_wheel, pivot
WORLD, PLATFORM, CHASSIS, REFERENCE = "world", "platform", "chassis", "reference"
STATUS_REPEAT_S = 1.0

_VEC = {"type": "array", "items": {"type": "number"}}
_SCHEMAS: dict[str, tuple[str, dict]] = {
    "/otbot/joints": ("otbot.JointState", {"type": "object", "properties": {
        "t": {"type": "number", "description": "loop time, s"},
        "name": {"type": "array", "items": {"type": "string"}},
        "position": {**_VEC, "description": "rad"}, "velocity": {**_VEC, "description": "rad/s"}}}),
    "/otbot/torques": ("otbot.Torques", {"type": "object", "properties": {
        "t": {"type": "number"}, "name": {"type": "array", "items": {"type": "string"}},
        "commanded": {**_VEC, "description": "N m after the limiter"},
        "limit": {**_VEC, "description": "N m, motors.*.max_torque"},
        "ratio": {**_VEC, "description": "commanded / limit"},
        "saturated": {"type": "array", "items": {"type": "boolean"}}}}),
    "/otbot/tracking_error": ("otbot.TrackingError", {"type": "object", "properties": {
        "t": {"type": "number"}, "x": {"type": "number", "description": "m"},
        "y": {"type": "number", "description": "m"}, "alpha": {"type": "number", "description": "rad, wrapped"},
        "norm": {"type": "number", "description": "m, position error"}}}),
    "/otbot/estimate": ("otbot.Estimate", {"type": "object", "properties": {
        "t": {"type": "number"}, "pose": {**_VEC, "description": "x, y (m), alpha (rad)"},
        "twist": {**_VEC, "description": "m/s, m/s, rad/s"},
        "std": {**_VEC, "description": "sigma of pose and twist, same units"},
        "gyro_bias": {"type": "number", "description": "rad/s"}}}),
    "/otbot/status": ("otbot.Status", {"type": "object", "properties": {
        "t": {"type": "number"}, "mode": {"type": "string"},
        "faults": {"type": "array", "items": {"type": "string"}},
        "drive_states": {"type": "array", "items": {"type": "string"}}}}),
}


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


def chassis_in_platform(phi_p: float, l1: float) -> tuple[tuple[float, float], float]:
    """((x, y) m, yaw rad) of the chassis frame B' (origin at the wheel-axis midpoint M, axis 1'
    along the heading theta = alpha - phi_p) in the platform frame B'' (origin at the pivot P).
    The rolling constraints (``model.kinematics.constraint_jacobian``) give P = M + l1 (cos theta,
    sin theta) in the ground frame (the pivot leads the wheel axis by l1), so M sits at
    -l1 (cos phi_p, -sin phi_p) in B'', turned by -phi_p."""
    return (-l1 * math.cos(phi_p), l1 * math.sin(phi_p)), -phi_p


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
    counts: dict = field(default_factory=dict)


class TelemetryServer:
    """The Foxglove WebSocket server and its channels, on a context of its own (nothing else in
    the process publishes into it). ``limits`` (3,) N m: the motors' torque limits; ``l1`` (m):
    pivot offset (paper Table 3) for the chassis frame; ``port`` 0 picks a free port (``port``
    attribute after start)."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, rate: float = 50.0, limits=None,
                 l1: float | None = None, name: str = "otbot"):
        import foxglove
        from foxglove.channels import FrameTransformsChannel, LogChannel

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
        self._tf = FrameTransformsChannel("/tf", context=self.context)
        self._log = LogChannel("/otbot/log", context=self.context)
        self._json = {topic: foxglove.Channel(topic, context=self.context, schema=foxglove.Schema(
            name=name_, encoding="jsonschema", data=_json_bytes(schema)), message_encoding="json")
            for topic, (name_, schema) in _SCHEMAS.items()}
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

    # -- the loop's call ---------------------------------------------------------------------
    def publish(self, sample: TelemetrySample, now: float | None = None) -> bool:
        """Called once per loop cycle; ``now`` monotonic s. Returns whether it sent the sample."""
        now = time.monotonic() if now is None else now
        st = self.state
        faults = tuple(sample.faults)
        changed = sample.mode != st.mode or faults != st.faults or tuple(sample.drive_states) != st.drive_states
        due = now >= st.next_due - 1e-6
        if not changed and not due:
            st.skipped += 1
            return False
        stamp = time.time_ns()
        if changed:
            self._log_changes(sample, faults, stamp)
        if changed or now - st.last_status >= STATUS_REPEAT_S:
            self._json["/otbot/status"].log(
                {"t": sample.t, "mode": sample.mode, "faults": [str(f) for f in faults],
                 "drive_states": list(sample.drive_states)}, log_time=stamp)
            st.last_status = now
        if due:  # on a fixed grid of 1/rate, restarted after a gap
            self._publish_cycle(sample, stamp)
            st.next_due = st.next_due + self.period if now - st.next_due < self.period else now + self.period
            st.published += 1
        return True

    def _log_changes(self, sample: TelemetrySample, faults: tuple, stamp: int) -> None:
        from foxglove.messages import Log, LogLevel, Timestamp

        ts = Timestamp(stamp // 1_000_000_000, stamp % 1_000_000_000)
        st = self.state
        if sample.mode != st.mode:
            self._log.log(Log(timestamp=ts, level=LogLevel.Info, name="otbot",
                              message=f"mode {st.mode or '-'} -> {sample.mode}"), log_time=stamp)
        for f in faults:
            if f not in st.faults:
                self._log.log(Log(timestamp=ts, level=LogLevel.Error, name="otbot", message=f"fault: {str(f)}"),
                              log_time=stamp)
        if st.faults and not faults:
            self._log.log(Log(timestamp=ts, level=LogLevel.Info, name="otbot", message="faults cleared"),
                          log_time=stamp)
        st.mode, st.faults, st.drive_states = sample.mode, faults, tuple(sample.drive_states)

    def _publish_cycle(self, s: TelemetrySample, stamp: int) -> None:
        from foxglove.messages import FrameTransform, FrameTransforms, Quaternion, Timestamp, Vector3

        ts = Timestamp(stamp // 1_000_000_000, stamp % 1_000_000_000)
        t = float(s.t)

        def tf(parent, child, x, y, yaw):
            return FrameTransform(timestamp=ts, parent_frame_id=parent, child_frame_id=child,
                                  translation=Vector3(x=float(x), y=float(y), z=0.0),
                                  rotation=Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)))

        phi_p = float(s.joint_pos[2])
        (cx, cy), cyaw = chassis_in_platform(phi_p, self.l1)
        transforms = [tf(PLATFORM, CHASSIS, cx, cy, cyaw)]
        if s.pose is not None:
            transforms.append(tf(WORLD, PLATFORM, s.pose[0], s.pose[1], float(s.pose[2])))
        if s.reference is not None:
            transforms.append(tf(WORLD, REFERENCE, s.reference[0], s.reference[1], float(s.reference[2])))
        self._tf.log(FrameTransforms(transforms=transforms), log_time=stamp)
        self._json["/otbot/joints"].log({"t": t, "name": JOINT_NAMES, "position": _list(s.joint_pos),
                                         "velocity": _list(s.joint_vel)}, log_time=stamp)
        torque = np.asarray(s.torque, float)
        self._json["/otbot/torques"].log(
            {"t": t, "name": JOINT_NAMES, "commanded": _list(torque), "limit": _list(self.limits),
             "ratio": _list(torque / self.limits), "saturated": [bool(b) for b in s.saturated]}, log_time=stamp)
        if s.pose is not None:
            est = {"t": t, "pose": _list(s.pose)}
            if s.twist is not None:
                est["twist"] = _list(s.twist)
            if s.std is not None:
                est["std"] = _list(s.std)
            if s.gyro_bias is not None:
                est["gyro_bias"] = _num(float(s.gyro_bias))
            self._json["/otbot/estimate"].log(est, log_time=stamp)
            if s.reference is not None:
                ex, ey = float(s.reference[0] - s.pose[0]), float(s.reference[1] - s.pose[1])
                self._json["/otbot/tracking_error"].log(
                    {"t": t, "x": _num(ex), "y": _num(ey), "alpha": _num(wrap_angle(float(s.reference[2] - s.pose[2]))),
                     "norm": _num(math.hypot(ex, ey))}, log_time=stamp)

    # -- life cycle --------------------------------------------------------------------------
    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def status(self) -> dict:
        """For the daemon's ``status`` reply: address, subscriptions, messages sent/skipped."""
        return {"url": self.url, "subscriptions": self.listener.subscriptions,
                "published": self.state.published, "skipped": self.state.skipped}

    def close(self) -> None:
        self.server.stop()

    def __enter__(self) -> "TelemetryServer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _num(x: float) -> float | None:
    return x if math.isfinite(x) else None


def _list(v) -> list[float]:
    """Plain floats; non-finite values become None (JSON has no NaN)."""
    return [float(x) if math.isfinite(x) else None for x in np.asarray(v, float).ravel()]


def _json_bytes(schema: dict) -> bytes:
    import json
    return json.dumps(schema).encode()
