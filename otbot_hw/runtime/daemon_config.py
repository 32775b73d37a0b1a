"""The ``daemon:`` section of ``config/robot.yaml``: control socket, who may command, velocity mode,
recording, telemetry and thread scheduling of the on-robot daemon (``otbot daemon``, ``docs/daemon.md``).

Quantities are ``{value: V, unit: U}`` like the rest of the file; every error is a
``ParameterError`` naming the file and the key (exit code 2). The section is optional: without it
every key takes the default shown in ``config/robot.yaml``.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from otbot_hw.motors import DEFAULT_ROBOT_FILE
from otbot_hw.params import ParameterError, read_entry, read_yaml

from otbot_hw.runtime.control_client import (  # noqa: F401 - re-exported
    SOCKET_NAME, default_runtime_dir, default_socket_path, socket_candidates)


@dataclass(frozen=True)
class ControlSocketConfig:
    """path (None: ``default_socket_path()``); allowed_users / allowed_groups: names or numeric ids
    that may send every command (``status`` is open to anyone who can reach the socket);
    max_request (bytes per request line); max_clients (connections at once); reserved_clients (of
    those, slots only allowed peers may take: a status-only peer gets at most max_clients -
    reserved_clients, and an allowed peer that finds every slot taken evicts the oldest status-only
    connection); request_timeout (s a started request line may take to arrive); idle_timeout (s a
    connection may stay without sending a byte or awaiting a reply before it is closed)."""

    path: Path | None = None
    allowed_users: tuple[str | int, ...] = ()
    allowed_groups: tuple[str | int, ...] = ("otbot-operators",)
    max_request: int = 65536
    max_clients: int = 32
    reserved_clients: int = 4
    request_timeout: float = 5.0
    idle_timeout: float = 60.0

    def socket_path(self) -> Path:
        return self.path if self.path is not None else default_socket_path()


@dataclass(frozen=True)
class VelocityConfig:
    """Velocity mode: deadman (s without a new ``velocity`` command before the daemon ramps to zero
    and holds), max_linear (m/s, norm of (x_dot, y_dot)) and max_angular (rad/s, |alpha_dot|): the
    largest twist a ``velocity`` request may ask (larger ones are refused, not clamped);
    max_acceleration (m/s^2, of |(x_dd, y_dd)|) and max_angular_acceleration (rad/s^2): how fast the
    reference may change its twist (velocity commands, the ramp to zero of stop, hold and the
    deadman)."""

    deadman: float = 0.5
    max_linear: float = 0.5
    max_angular: float = 1.0
    max_acceleration: float = 0.5
    max_angular_acceleration: float = 1.0


@dataclass(frozen=True)
class RecordingConfig:
    """dir (session files), rotate_size (bytes), rotate_time (s of loop time per file),
    flush_interval (s: at most this much is lost when the process dies), format (``otbot``: the
    project's MCAP recordings; ``ros2``: ROS 2 bag folders, ``otbot_hw.ros2.writer``)."""

    dir: Path = Path("/var/lib/otbot/recordings")
    rotate_size: int = 512 * 2 ** 20
    rotate_time: float = 3600.0
    flush_interval: float = 1.0
    format: str = "otbot"


@dataclass(frozen=True)
class TelemetryConfig:
    """Foxglove WebSocket server: enabled, host (127.0.0.1: this machine only), port (TCP),
    rate (Hz: most messages per channel per second)."""

    enabled: bool = True
    host: str = "127.0.0.1"
    port: int = 8765
    rate: float = 50.0


@dataclass(frozen=True)
class SchedulingConfig:
    """cpus: Linux CPU numbers every thread of the daemon runs on (None: wherever the system puts
    them; ``otbot_hw.runtime.scheduling.pin``); operator_threads_below: real-time priority levels the
    control socket's dispatch thread and telemetry's threads run below the loop's (0: all at one
    priority; only under a real-time policy, e.g. the unit's CPUSchedulingPolicy=fifo)."""

    cpus: tuple[int, ...] | None = None
    operator_threads_below: int = 1


@dataclass(frozen=True)
class DaemonConfig:
    socket: ControlSocketConfig = field(default_factory=ControlSocketConfig)
    velocity: VelocityConfig = field(default_factory=VelocityConfig)
    recording: RecordingConfig = field(default_factory=RecordingConfig)
    telemetry: TelemetryConfig = field(default_factory=TelemetryConfig)
    adaptation: Any = field(default_factory=lambda: _adaptation_default())  # estimation.payload.AdaptationConfig
    scheduling: SchedulingConfig = field(default_factory=SchedulingConfig)


def _adaptation_default():
    from otbot_hw.estimation.payload import AdaptationConfig

    return AdaptationConfig()


#: longest velocity deadman accepted (s)
MAX_DEADMAN = 10.0
_SIZE_UNITS = {"bytes": 1, "KiB": 2 ** 10, "MiB": 2 ** 20, "GiB": 2 ** 30}


class _Section:
    """Reads one mapping of the ``daemon`` section, naming ``file: 'daemon.a.b'`` in errors."""

    def __init__(self, source: str, name: str, data: Any, keys: tuple[str, ...]):
        if data is None:
            data = {}
        if not isinstance(data, dict):
            raise ParameterError(f"{source}: '{name}' must be a mapping, got {data!r}")
        unknown = set(data) - set(keys)
        if unknown:
            raise ParameterError(f"{source}: '{name}' has unknown key(s) {sorted(unknown)} "
                                 f"(known: {', '.join(keys)})")
        self.source, self.name, self.data = source, name, data

    def key(self, k: str) -> str:
        return f"{self.name}.{k}"

    def err(self, k: str, msg: str) -> ParameterError:
        return ParameterError(f"{self.source}: '{self.key(k)}' {msg}")

    def quantity(self, k: str, unit: str, default: float, maximum: tuple[float, str] | None = None) -> float:
        """A ``{value, unit}`` entry that must be a finite number > 0 (and at most ``maximum``: (value,
        why))."""
        if k not in self.data:
            return default
        v, _ = read_entry(self.source, self.key(k), self.data[k], unit)
        v = self._positive(k, v, unit)
        if maximum is not None and v > maximum[0]:
            raise self.err(k, f"must be at most {maximum[0]:g} {unit} ({maximum[1]}), got {v:g}")
        return v

    def size(self, k: str, default: int) -> int:
        """A ``{value, unit}`` byte count with unit bytes, KiB, MiB or GiB."""
        if k not in self.data:
            return default
        e = self.data[k]
        unit = e.get("unit") if isinstance(e, dict) else None
        if not isinstance(unit, str) or unit not in _SIZE_UNITS:
            raise self.err(k, f"must be {{value: N, unit: bytes|KiB|MiB|GiB}}, got {e!r}")
        v, _ = read_entry(self.source, self.key(k), e, unit)
        n = self._positive(k, v, unit) * _SIZE_UNITS[unit]
        if not n.is_integer():
            raise self.err(k, f"must be a whole number of bytes, got {n}")
        return int(n)

    def integer(self, k: str, default: int, lo: int, hi: int) -> int:
        v = self.data.get(k, default)
        if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
            raise self.err(k, f"must be a whole number in {lo}..{hi}, got {v!r}")
        return v

    def ids(self, k: str, default: tuple) -> tuple[str | int, ...]:
        v = self.data.get(k, list(default))
        if not isinstance(v, list) or not all(
                (isinstance(e, str) and e) or (isinstance(e, int) and not isinstance(e, bool) and e >= 0)
                for e in v):
            raise self.err(k, f"must be a list of names or numeric ids >= 0, got {v!r}")
        return tuple(v)

    def cpus(self, k: str) -> tuple[int, ...] | None:
        """null, or a non-empty list of distinct CPU numbers (whole numbers >= 0)."""
        v = self.data.get(k)
        if v is None:
            return None
        if not isinstance(v, list) or not v or not all(isinstance(c, int) and not isinstance(c, bool) and c >= 0
                                                       for c in v):
            raise self.err(k, f"must be null or a non-empty list of CPU numbers (whole numbers >= 0), got {v!r}")
        if len(set(v)) != len(v):
            raise self.err(k, f"lists a CPU twice: {v!r}")
        return tuple(v)

    def text(self, k: str, default: str | None, nullable: bool = True) -> str | None:
        v = self.data.get(k, default)
        if (v is None and not nullable) or (v is not None and (not isinstance(v, str) or not v)):
            raise self.err(k, f"must be a non-empty string, got {v!r}")
        return v

    def _positive(self, k: str, v: Any, unit: str) -> float:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not v > 0:
            raise self.err(k, f"must be a finite number > 0 ({unit}), got {v!r}")
        return float(v)


def daemon_config_from_dict(data: Any, source: str = "<dict>") -> DaemonConfig:
    """Validate a ``daemon`` mapping (None: all defaults); relative paths are relative to the cwd."""
    top = _Section(source, "daemon", data, ("socket", "velocity", "recording", "telemetry", "adaptation", "scheduling"))
    s = _Section(source, "daemon.socket", top.data.get("socket"),
                 ("path", "allowed_users", "allowed_groups", "max_request", "max_clients", "reserved_clients",
                  "request_timeout", "idle_timeout"))
    d = ControlSocketConfig()
    path = s.text("path", None)
    sock = ControlSocketConfig(
        path=Path(path) if path else None,
        allowed_users=s.ids("allowed_users", d.allowed_users),
        allowed_groups=s.ids("allowed_groups", d.allowed_groups),
        max_request=s.size("max_request", d.max_request),
        max_clients=s.integer("max_clients", d.max_clients, 1, 1024),
        reserved_clients=s.integer("reserved_clients", d.reserved_clients, 1, 1024),
        request_timeout=s.quantity("request_timeout", "s", d.request_timeout),
        idle_timeout=s.quantity("idle_timeout", "s", d.idle_timeout))
    if sock.reserved_clients >= sock.max_clients:
        raise s.err("reserved_clients", f"must be below max_clients ({sock.max_clients}), got {sock.reserved_clients}")
    if sock.max_request < 256:
        raise s.err("max_request", f"must be at least 256 bytes, got {sock.max_request}")
    v = _Section(source, "daemon.velocity", top.data.get("velocity"),
                 ("deadman", "max_linear", "max_angular", "max_acceleration", "max_angular_acceleration"))
    dv = VelocityConfig()
    vel = VelocityConfig(deadman=v.quantity("deadman", "s", dv.deadman, maximum=(MAX_DEADMAN, "a longer one lets a "
                                                                                   "lost client's last twist run on")),
                         max_linear=v.quantity("max_linear", "m/s", dv.max_linear),
                         max_angular=v.quantity("max_angular", "rad/s", dv.max_angular),
                         max_acceleration=v.quantity("max_acceleration", "m/s^2", dv.max_acceleration),
                         max_angular_acceleration=v.quantity("max_angular_acceleration", "rad/s^2",
                                                             dv.max_angular_acceleration))
    r = _Section(source, "daemon.recording", top.data.get("recording"),
                 ("dir", "rotate_size", "rotate_time", "flush_interval", "format"))
    dr = RecordingConfig()
    rec = RecordingConfig(dir=Path(r.text("dir", str(dr.dir), nullable=False)),
                          rotate_size=r.size("rotate_size", dr.rotate_size),
                          rotate_time=r.quantity("rotate_time", "s", dr.rotate_time),
                          flush_interval=r.quantity("flush_interval", "s", dr.flush_interval),
                          format=r.text("format", dr.format))
    if rec.format not in ("otbot", "ros2"):
        raise r.err("format", f"must be otbot or ros2, got {rec.format!r}")
    if rec.format == "ros2":
        from otbot_hw.extras import MissingExtraError, require

        try:
            require("rosbags")
        except MissingExtraError as exc:
            raise r.err("format", f"ros2: {exc}") from None
    if rec.flush_interval > 1.0:
        raise r.err("flush_interval", f"must be <= 1 s (a crash may lose at most one second), "
                                      f"got {rec.flush_interval}")
    t = _Section(source, "daemon.telemetry", top.data.get("telemetry"), ("enabled", "host", "port", "rate"))
    dt = TelemetryConfig()
    enabled = t.data.get("enabled", dt.enabled)
    if not isinstance(enabled, bool):
        raise t.err("enabled", f"must be true or false, got {enabled!r}")
    tel = TelemetryConfig(enabled=enabled, host=t.text("host", dt.host),
                          port=t.integer("port", dt.port, 0, 65535), rate=t.quantity("rate", "Hz", dt.rate))
    c = _Section(source, "daemon.scheduling", top.data.get("scheduling"), ("cpus", "operator_threads_below"))
    sched = SchedulingConfig(cpus=c.cpus("cpus"), operator_threads_below=c.integer(
        "operator_threads_below", SchedulingConfig.operator_threads_below, 0, 98))
    from otbot_hw.estimation.payload import AdaptationConfig

    return DaemonConfig(socket=sock, velocity=vel, recording=rec, telemetry=tel,
                        adaptation=AdaptationConfig.from_section(top.data.get("adaptation"), source),
                        scheduling=sched)


def load_daemon_config(path: str | Path | None = None) -> DaemonConfig:
    """The ``daemon`` section of ``path`` (default ``config/robot.yaml``); a relative
    ``recording.dir`` or ``socket.path`` is taken relative to that file's folder."""
    p = Path(path) if path is not None else DEFAULT_ROBOT_FILE
    data = read_yaml(p)
    if not isinstance(data, dict):
        raise ParameterError(f"{p}: expected a mapping of sections, got {type(data).__name__}")
    cfg = daemon_config_from_dict(data.get("daemon"), str(p))
    base = p.resolve().parent
    sock, rec = cfg.socket, cfg.recording
    if sock.path is not None and not sock.path.is_absolute():
        sock = ControlSocketConfig(**{**sock.__dict__, "path": base / sock.path})
    if not rec.dir.is_absolute():
        rec = RecordingConfig(**{**rec.__dict__, "dir": base / rec.dir})
    return DaemonConfig(socket=sock, velocity=cfg.velocity, recording=rec, telemetry=cfg.telemetry,
                        adaptation=cfg.adaptation, scheduling=cfg.scheduling)
