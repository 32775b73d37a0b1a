"""The daemon's control protocol: JSON lines over a Unix socket (server: ``control_socket``).

One request per line (UTF-8 JSON object, ``\\n``-terminated)::

    {"id": 7, "cmd": "velocity", "args": {"vx": 0.2, "vy": 0.0, "wz": 0.1}}

one reply per request, with the same ``id``::

    {"id": 7, "ok": true, "result": {...}}
    {"id": 7, "ok": false, "error": {"code": "bad_request", "message": "velocity: 'vx' must be ..."}}

``id`` is a string (at most 256 characters) or an integer; a request without a readable id is
answered with ``"id": null``. ``args`` may be omitted when a command takes none. Commands, their
arguments (units) and who may send them are in ``COMMANDS``; error codes in ``ERROR_CODES``.
This module holds what server and client share: validation, encoding, the status contract. It
does no I/O.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

#: command -> (argument names, what it does). Argument units: vx, vy m/s and wz rad/s (the
#: platform twist x_dot, y_dot, alpha_dot in the ground frame B); target a scenario name or the
#: absolute path of a trajectory CSV; path the absolute path of a recording (.mcap) or torque CSV.
COMMANDS: dict[str, tuple[tuple[str, ...], str]] = {
    "status": ((), "mode, loop timing, pose estimate with sigma, tracking errors, faults, drive states, recording"),
    "enable": ((), "power the drives (needs a fault-free robot); the robot then holds its pose"),
    "disable": ((), "remove motor power (idle)"),
    "hold": ((), "computed-torque hold of the current pose"),
    "track": (("target",), "track a named scenario or a trajectory CSV (absolute path)"),
    "velocity": (("vx", "vy", "wz"), "follow the platform twist (m/s, m/s, rad/s, ground frame) until the deadman"),
    "excite": (("path",), "play a torque sequence from a recording (.mcap) or CSV (absolute path)"),
    "stop": ((), "end the current motion: ramp to zero and hold"),
    "estop": ((), "quick stop now; the fault is latched until reset"),
    "reset": ((), "clear latched faults (those still present come back)"),
    "record": (("action",), "start or stop the session recording"),
    "shutdown": ((), "quick stop, disable, close the recording, exit 0"),
}
#: Commands open to every local user who can reach the socket; the rest need authorization.
OPEN_COMMANDS = frozenset({"status"})
RECORD_ACTIONS = ("start", "stop")
TRACK_SUFFIXES = (".csv",)
EXCITE_SUFFIXES = (".mcap", ".csv")

#: error code -> meaning. ``BAD_INPUT_CODES`` are the client's fault (``otbot ctl`` exits 2).
ERROR_CODES = {
    "not_json": "the line is not UTF-8 JSON",
    "bad_request": "the request breaks the protocol or an argument is invalid",
    "unknown_command": "no such command",
    "too_large": "the request line is longer than the configured limit",
    "forbidden": "the peer's user and groups may not send this command",
    "refused": "the daemon refuses in its current state (e.g. faulted, not enabled)",
    "busy": "too many clients or requests in flight",
    "timeout": "the request line was not completed in time",
    "internal": "the daemon failed to carry out the command",
}
BAD_INPUT_CODES = frozenset({"not_json", "bad_request", "unknown_command", "too_large"})
MAX_ID_LENGTH = 256
#: Bounds the decoder applies before any number or path is used: digits of an integer literal
#: (an id is below 2**53, 16 digits), characters of a float literal (a double needs 25), bytes of
#: a path and of each of its names (Linux PATH_MAX, NAME_MAX).
MAX_INT_DIGITS = 20
MAX_FLOAT_CHARS = 40
PATH_MAX = 4096
NAME_MAX = 255

#: Keys every ``status`` result carries: mode (str), faults (list, empty when none), drive_states
#: (joint name -> CiA 402 state name as the drive reports it).
STATUS_REQUIRED = {"mode": str, "faults": list, "drive_states": dict}


class ProtocolError(ValueError):
    """A request that cannot be carried out; ``code`` is one of ``ERROR_CODES``."""

    def __init__(self, code: str, message: str, request_id: Any = None):
        super().__init__(message)
        self.code = code
        self.request_id = request_id


class CommandRefused(RuntimeError):
    """Raised by a handler that will not carry out a valid command in the current state; the
    message says why in words (e.g. "robot is faulted: reset first")."""


@dataclass(frozen=True)
class ArgumentLimits:
    """What the server checks beyond types: velocity bounds (m/s, rad/s, from ``daemon.velocity``)
    and the scenario names ``track`` knows."""

    max_linear: float = math.inf
    max_angular: float = math.inf
    scenarios: tuple[str, ...] = ()
    check_files: bool = True


@dataclass(frozen=True)
class Request:
    id: str | int
    cmd: str
    args: dict[str, Any] = field(default_factory=dict)


def _bounded_int(text: str) -> int:
    """json's integer hook: at most ``MAX_INT_DIGITS`` digits (Python's own limit is 4300, and
    converting even that many costs time a request must not buy)."""
    if len(text.lstrip("-")) > MAX_INT_DIGITS:
        raise ProtocolError("bad_request", f"a number has {len(text.lstrip('-'))} digits "
                                           f"(at most {MAX_INT_DIGITS})")
    return int(text)


def _bounded_float(text: str) -> float:
    """json's float hook: at most ``MAX_FLOAT_CHARS`` characters. One beyond a double's range
    becomes inf, which every numeric argument refuses (``_number``: "must be finite")."""
    if len(text) > MAX_FLOAT_CHARS:
        raise ProtocolError("bad_request", f"a number is written with {len(text)} characters "
                                           f"(at most {MAX_FLOAT_CHARS})")
    return float(text)


def _loads(line: bytes) -> Any:
    try:
        return json.loads(line.decode("utf-8"), parse_int=_bounded_int, parse_float=_bounded_float)
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise ProtocolError("not_json", f"request is not UTF-8 JSON: {str(exc)[:80]}") from None


def _request_id(obj: dict) -> str | int:
    if "id" not in obj:
        raise ProtocolError("bad_request", "request has no 'id'")
    rid = obj["id"]
    if isinstance(rid, bool) or not isinstance(rid, (str, int)):
        raise ProtocolError("bad_request", f"'id' must be a string or an integer, got {type(rid).__name__}")
    if isinstance(rid, str) and len(rid) > MAX_ID_LENGTH:
        raise ProtocolError("bad_request", f"'id' is longer than {MAX_ID_LENGTH} characters")
    if isinstance(rid, int) and abs(rid) >= 2 ** 53:
        raise ProtocolError("bad_request", "'id' must be an integer of magnitude below 2**53")
    return rid


def _number(cmd: str, name: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ProtocolError("bad_request", f"{cmd}: '{name}' must be a number, got {_show(v)}")
    if isinstance(v, int) and abs(v) >= 10 ** MAX_INT_DIGITS:
        raise ProtocolError("bad_request", f"{cmd}: '{name}' has more than {MAX_INT_DIGITS} digits")
    v = float(v)
    if not math.isfinite(v):
        raise ProtocolError("bad_request", f"{cmd}: '{name}' must be finite, got {v}")
    return v


def _show(v: Any, n: int = 40) -> str:
    """A short JSON rendering of a client's value for an error message (never raises)."""
    try:
        text = json.dumps(v, allow_nan=True)
    except (TypeError, ValueError, RecursionError):
        text = type(v).__name__
    return text if len(text) <= n else text[:n] + "..."


def check_path_length(cmd: str, name: str, v: str) -> None:
    """A path the kernel would refuse (ENAMETOOLONG) is refused here, before any system call:
    at most ``PATH_MAX`` bytes, each name at most ``NAME_MAX``."""
    try:
        raw = os.fsencode(v)
    except (UnicodeError, ValueError):
        raise ProtocolError("bad_request", f"{cmd}: '{name}' is not a valid path") from None
    if len(raw) >= PATH_MAX:
        raise ProtocolError("bad_request", f"{cmd}: '{name}' is {len(raw)} bytes long (at most {PATH_MAX - 1})")
    longest = max((len(part) for part in raw.split(b"/")), default=0)
    if longest > NAME_MAX:
        raise ProtocolError("bad_request", f"{cmd}: '{name}' has a name of {longest} bytes (at most {NAME_MAX})")


def _file(cmd: str, name: str, v: Any, suffixes: tuple[str, ...], limits: ArgumentLimits) -> str:
    if not isinstance(v, str) or not v or "\0" in v:
        raise ProtocolError("bad_request", f"{cmd}: '{name}' must be a non-empty path string")
    check_path_length(cmd, name, v)
    p = Path(v)
    if not p.is_absolute():
        raise ProtocolError("bad_request", f"{cmd}: '{name}' must be an absolute path (the daemon has its "
                                           f"own working directory), got {_show(v)}")
    if p.suffix.lower() not in suffixes:
        raise ProtocolError("bad_request", f"{cmd}: {_show(v)} must end in {' or '.join(suffixes)}")
    if limits.check_files:
        try:
            is_file, readable = p.is_file(), os.access(p, os.R_OK)
        except (OSError, ValueError) as exc:
            raise ProtocolError("bad_request", f"{cmd}: {v}: {getattr(exc, 'strerror', None) or exc}") from None
        if not is_file:
            raise ProtocolError("bad_request", f"{cmd}: {v} is not an existing file")
        if not readable:
            raise ProtocolError("bad_request", f"{cmd}: {v} is not readable by the daemon")
    return str(p)


def validate_args(cmd: str, args: Any, limits: ArgumentLimits = ArgumentLimits()) -> dict[str, Any]:
    """Checked, normalized arguments of ``cmd`` (ProtocolError ``bad_request`` naming what is wrong).
    ``track`` gains ``kind``: "scenario" or "file"."""
    if cmd not in COMMANDS:
        raise ProtocolError("unknown_command", f"unknown command {_show(cmd)} (known: {', '.join(COMMANDS)})")
    if args is None:
        args = {}
    if not isinstance(args, dict):
        raise ProtocolError("bad_request", f"{cmd}: 'args' must be an object, got {type(args).__name__}")
    names = COMMANDS[cmd][0]
    unknown = sorted(set(args) - set(names))
    if unknown:
        shown = [_show(u, 40) for u in unknown[:5]]
        raise ProtocolError("bad_request", f"{cmd}: unknown argument(s) {', '.join(shown)}"
                                           + (f" (takes {', '.join(names)})" if names else " (takes none)"))
    missing = [n for n in names if n not in args]
    if missing:
        raise ProtocolError("bad_request", f"{cmd}: missing argument(s) {missing}")
    if cmd == "velocity":
        vx, vy, wz = (_number(cmd, n, args[n]) for n in names)
        if math.hypot(vx, vy) > limits.max_linear:
            raise ProtocolError("bad_request", f"velocity: |(vx, vy)| = {math.hypot(vx, vy):.3g} m/s exceeds "
                                               f"the limit {limits.max_linear:g} m/s")
        if abs(wz) > limits.max_angular:
            raise ProtocolError("bad_request", f"velocity: |wz| = {abs(wz):.3g} rad/s exceeds the limit "
                                               f"{limits.max_angular:g} rad/s")
        return {"vx": vx, "vy": vy, "wz": wz}
    if cmd == "track":
        target = args["target"]
        if isinstance(target, str) and target in limits.scenarios:
            return {"target": target, "kind": "scenario"}
        if isinstance(target, str) and not target.startswith("/") and limits.scenarios:
            raise ProtocolError("bad_request", f"track: {_show(target)} is neither a scenario "
                                               f"({', '.join(limits.scenarios)}) nor an absolute CSV path")
        return {"target": _file(cmd, "target", target, TRACK_SUFFIXES, limits), "kind": "file"}
    if cmd == "excite":
        return {"path": _file(cmd, "path", args["path"], EXCITE_SUFFIXES, limits)}
    if cmd == "record":
        if args["action"] not in RECORD_ACTIONS:
            raise ProtocolError("bad_request", f"record: 'action' must be one of {', '.join(RECORD_ACTIONS)}, "
                                               f"got {_show(args['action'])}")
        return {"action": args["action"]}
    return {}


def decode_request(line: bytes) -> tuple[str | int, str | None, Any]:
    """Step 1 of parsing one request line (without its newline): the JSON with bounded numbers,
    the id and the command name — nothing else is looked at, so the server can check authorization
    before any argument is. Returns (id, cmd, raw args); ``cmd`` is None when the line names no
    command as a string (``check_command`` then refuses it). ProtocolError carries the id when read."""
    obj = _loads(line)
    if not isinstance(obj, dict):
        raise ProtocolError("bad_request", f"request must be a JSON object, got {type(obj).__name__}")
    rid = _request_id(obj)
    cmd = obj.get("cmd")
    unknown = sorted(set(obj) - {"id", "cmd", "args"})
    if unknown:
        raise ProtocolError("bad_request", f"unknown request field(s) {', '.join(_show(u) for u in unknown[:5])} "
                                           f"(known: id, cmd, args)", rid)
    return rid, cmd if isinstance(cmd, str) else None, obj.get("args")


def check_command(rid: str | int, cmd: str | None) -> str:
    """The command name of a decoded request, or ProtocolError (``bad_request``/``unknown_command``)."""
    if cmd is None:
        raise ProtocolError("bad_request", "request needs 'cmd' as a string", rid)
    if cmd not in COMMANDS:
        raise ProtocolError("unknown_command", f"unknown command {_show(cmd)} (known: {', '.join(COMMANDS)})", rid)
    return cmd


def parse_request(line: bytes, limits: ArgumentLimits = ArgumentLimits()) -> Request:
    """Decode and validate one request line (without its newline): ``decode_request``,
    ``check_command``, ``validate_args``. ProtocolError carries the request id when it could be
    read, so the error reply can name it."""
    rid, cmd, args = decode_request(line)
    cmd = check_command(rid, cmd)
    try:
        return Request(id=rid, cmd=cmd, args=validate_args(cmd, args, limits))
    except ProtocolError as exc:
        exc.request_id = rid
        raise


def encode_request(rid: str | int, cmd: str, args: dict | None = None) -> bytes:
    return (json.dumps({"id": rid, "cmd": cmd, "args": args or {}}, allow_nan=False) + "\n").encode()


def encode_reply(rid: Any, result: Any = None, error: tuple[str, str] | None = None) -> bytes:
    """One reply line. A result that is not JSON (NaN, objects) becomes an ``internal`` error."""
    if error is None:
        try:
            return (json.dumps({"id": rid, "ok": True, "result": result}, allow_nan=False) + "\n").encode()
        except (TypeError, ValueError) as exc:
            error = ("internal", f"the daemon's reply is not JSON: {exc}")
    code, message = error
    return (json.dumps({"id": rid, "ok": False, "error": {"code": code, "message": message}}) + "\n").encode()


def check_status(result: Any) -> dict:
    """The ``status`` contract (``STATUS_REQUIRED``); ValueError naming the key when broken."""
    if not isinstance(result, dict):
        raise ValueError(f"status must be an object, got {type(result).__name__}")
    for key, typ in STATUS_REQUIRED.items():
        if not isinstance(result.get(key), typ):
            raise ValueError(f"status needs '{key}' as {typ.__name__}, got {result.get(key)!r}")
    return result
