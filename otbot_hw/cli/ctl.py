"""``otbot ctl``: command the on-robot daemon over its control socket (``docs/daemon.md``).

Exit codes: 0 done; 2 bad input (arguments, or the daemon's reply says the request was bad:
``control_protocol.BAD_INPUT_CODES``); 1 for everything that is not the caller's input: no daemon
at the socket, not allowed, refused in the daemon's state, internal failure. A missing daemon is
a failure to carry out a well-formed command, not bad input, hence 1.

Start-up cost matters (the velocity deadman is 0.5 s): this module imports only the control
protocol and client (stdlib); the configuration is read with PyYAML alone when no ``--socket`` is
given (the full loader only to word an error). ``velocity --hold`` keeps one connection and
repeats the command at 5 Hz until Ctrl-C, then sends ``stop``.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

from otbot_hw.cli import CliError

_SUPPRESS = argparse.SUPPRESS


def _common(p: argparse.ArgumentParser, top: bool) -> None:
    p.add_argument("--socket", type=Path, default=None if top else _SUPPRESS,
                   help="control socket of the daemon (default: daemon.socket.path of --config, else the first "
                        "existing of $RUNTIME_DIRECTORY/control.sock, /run/otbot/control.sock, "
                        "$XDG_RUNTIME_DIR/otbot/control.sock)")
    p.add_argument("--config", type=Path, default=None if top else _SUPPRESS,
                   help="hardware configuration whose daemon.socket.path to use (default config/robot.yaml)")
    p.add_argument("--timeout", type=float, default=5.0 if top else _SUPPRESS,
                   help="seconds to wait for the daemon's reply (default 5)")
    p.add_argument("--json", action="store_true", default=False if top else _SUPPRESS,
                   help="print the daemon's reply (its result) as one JSON object")


#: s between two velocity commands of ``ctl velocity --hold`` (5 Hz)
HOLD_PERIOD = 0.2


def _finite(name: str, unit: str):
    def conv(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be a number in {unit}, got {text!r}") from None
        if not math.isfinite(v):
            raise argparse.ArgumentTypeError(f"{name} must be finite, got {text!r}")
        return v
    return conv


def register(subparsers) -> None:
    from otbot_hw.runtime.control_protocol import COMMANDS, RECORD_ACTIONS

    p = subparsers.add_parser(
        "ctl", help="command the on-robot daemon (status, enable, track, velocity, estop, ...)",
        description="Send one command to the running daemon (otbot daemon) over its Unix control socket and "
                    "print the reply. status is open to every local user who can reach the socket; the other "
                    "commands need a user or group allowed by daemon.socket in config/robot.yaml. Units: "
                    "velocities in m/s and rad/s (the platform twist x_dot, y_dot, alpha_dot in the ground "
                    "frame B), poses in m and rad, times in s. Exit 0 done, 2 bad input, 1 not done (no "
                    "daemon, not allowed, refused, failed).")
    _common(p, top=True)
    sub = p.add_subparsers(dest="ctl_command", metavar="COMMAND")
    sub.required = True
    for name, (_, what) in COMMANDS.items():
        c = sub.add_parser(name, help=what, description=what[:1].upper() + what[1:] + ".")
        _common(c, top=False)
        if name == "track":
            c.add_argument("target", metavar="NAME|FILE",
                           help="a scenario (corridor, corridor-smooth, figure8, planned) or a trajectory CSV "
                                "(otbot plan --out; t in s, x, y in m, alpha in rad)")
        elif name == "velocity":
            c.add_argument("vx", type=_finite("VX", "m/s"), metavar="VX", help="x_dot, m/s (ground frame B)")
            c.add_argument("vy", type=_finite("VY", "m/s"), metavar="VY", help="y_dot, m/s (ground frame B)")
            c.add_argument("wz", type=_finite("WZ", "rad/s"), metavar="WZ", help="alpha_dot, rad/s")
            c.add_argument("--hold", action="store_true",
                           help=f"keep the twist: repeat it every {HOLD_PERIOD:g} s ({1 / HOLD_PERIOD:g} Hz, well within "
                                f"the daemon's deadman, daemon.velocity.deadman, default 0.5 s) until Ctrl-C, then send "
                                f"stop (ramp to rest and hold) and exit 0. Without it one command is sent and the "
                                f"robot ramps to rest once the deadman expires")
        elif name == "excite":
            c.add_argument("path", metavar="FILE", help="torque sequence: a recording (.mcap; its /otbot/command "
                                                        "torques in N m) or a CSV (t in s, tau_r, tau_l, tau_p in N m)")
        elif name == "record":
            c.add_argument("action", choices=RECORD_ACTIONS, help="start or stop the session recording")
    p.set_defaults(func=ctl)


def _null_socket_path(text: str) -> bool:
    """Whether the YAML ``text`` plainly says ``daemon: socket: path: null`` (or leaves it out) in
    the block style config/robot.yaml uses — decided without a YAML parser (importing one costs
    more than the rest of ``otbot ctl``). False means "not sure": the caller parses the file."""
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    tops = [i for i, ln in enumerate(lines) if ln.split("#")[0].rstrip() == "daemon:"]
    if len(tops) != 1:
        return "\ndaemon" not in "\n" + text  # no daemon section at all: the default
    block = []
    for ln in lines[tops[0] + 1:]:
        if not ln.startswith((" ", "\t")):
            break
        block.append(ln)
    sockets = [i for i, ln in enumerate(block) if ln.split("#")[0].strip() == "socket:"]
    if len(sockets) != 1:
        return not any("socket" in ln for ln in block)
    indent = len(block[sockets[0]]) - len(block[sockets[0]].lstrip())
    paths = []
    for ln in block[sockets[0] + 1:]:
        if len(ln) - len(ln.lstrip()) <= indent:
            break
        key, _, value = ln.split("#")[0].strip().partition(":")
        if key == "path":
            paths.append(value.strip())
    return paths in ([], ["null"], ["~"], [""])


def _configured_socket(config: Path | None) -> Path | None:
    """daemon.socket.path of ``config`` (default config/robot.yaml), relative to its folder; the
    usual null is seen without a YAML parser, a set path read with PyYAML alone. Anything unusual
    goes to the full loader, whose errors name the key."""
    path = Path(config) if config is not None else Path(__file__).resolve().parents[2] / "config" / "robot.yaml"
    from otbot_hw.input_files import open_input, read_text

    try:
        if _null_socket_path(read_text(path, encoding="utf-8")):
            return None
    except (OSError, UnicodeError):
        pass
    import yaml

    try:
        with open_input(path) as f:
            data = yaml.load(f, Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))
        sock = (data.get("daemon") or {}).get("socket") or {}
        value = sock.get("path")
        if value is None or (isinstance(value, str) and value):
            return None if value is None else path.resolve().parent / value
    except (OSError, yaml.YAMLError, AttributeError, ValueError):
        pass
    from otbot_hw.runtime.daemon_config import load_daemon_config  # words the error (ParameterError, exit 2)

    return load_daemon_config(config).socket.path


def socket_path(args: argparse.Namespace) -> Path:
    """--socket, else the configuration's daemon.socket.path, else the first existing default."""
    from otbot_hw.runtime.control_client import socket_candidates

    if args.socket is not None:
        return args.socket
    configured = _configured_socket(args.config)
    if configured is not None:
        return configured
    candidates = socket_candidates()
    return next((c for c in candidates if c.exists()), candidates[0])


def request_args(args: argparse.Namespace) -> dict:
    cmd = args.ctl_command
    if cmd == "track":
        t = args.target
        is_file = "/" in t or t.lower().endswith(".csv")
        return {"target": str(Path(t).resolve()) if is_file else t}
    if cmd == "velocity":
        return {"vx": args.vx, "vy": args.vy, "wz": args.wz}
    if cmd == "excite":
        return {"path": str(Path(args.path).resolve())}
    if cmd == "record":
        return {"action": args.action}
    return {}


def _fail(message: str) -> None:
    print(f"otbot ctl: {message}", file=sys.stderr)
    raise SystemExit(1)



def _unprefixed(cmd: str, message: str) -> str:
    """The daemon's message without its leading ``cmd:`` (the error line, ``otbot ctl CMD: error:``,
    names the command already)."""
    return message[len(cmd) + 1:].lstrip() if message.startswith(f"{cmd}:") else message


def ctl(args: argparse.Namespace) -> dict:
    from otbot_hw.runtime.control_client import ControlClient, ControlError, DaemonUnreachable
    from otbot_hw.runtime.control_protocol import BAD_INPUT_CODES

    if not (math.isfinite(args.timeout) and args.timeout > 0):
        raise CliError(f"--timeout must be a number of seconds > 0, got {args.timeout}")
    cmd = args.ctl_command
    path = socket_path(args)
    hold = cmd == "velocity" and getattr(args, "hold", False)
    try:
        with ControlClient(path, timeout=args.timeout) as client:
            result = client.request(cmd, request_args(args))
            if hold:
                result = _hold_velocity(client, request_args(args), result, args.json)
    except DaemonUnreachable as exc:
        _fail(str(exc))
    except ControlError as exc:
        if exc.code in BAD_INPUT_CODES:
            raise CliError(_unprefixed(cmd, str(exc))) from None
        _fail(f"{cmd} {exc.code}: {_unprefixed(cmd, str(exc))}")
    result = result if result is not None else {}
    if not args.json:
        print(format_status(result) if cmd == "status" else format_reply(cmd, result))
    return result


def _hold_velocity(client, twist: dict, first: dict, quiet: bool) -> dict:
    """Repeat ``velocity`` every ``HOLD_PERIOD`` s on one connection until Ctrl-C, then ``stop``;
    returns the stop's reply with the number of commands sent. A refusal or a lost daemon ends it
    (ControlError / DaemonUnreachable, as for one command)."""
    if not quiet:
        print(f"velocity: holding vx {twist['vx']:g} m/s, vy {twist['vy']:g} m/s, wz {twist['wz']:g} rad/s "
              f"({1 / HOLD_PERIOD:g} Hz); Ctrl-C to stop", file=sys.stderr, flush=True)
    sent = 1
    try:
        t_next = time.monotonic()
        while True:
            t_next += HOLD_PERIOD
            delay = t_next - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            else:
                t_next = time.monotonic()
            client.request("velocity", twist)
            sent += 1
    except KeyboardInterrupt:
        pass
    stopped = client.request("stop", None) or {}
    return {**stopped, "velocity_commands": sent, "stopped": True}


def _num(v, fmt: str = "{:.4f}") -> str:
    return fmt.format(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else "?"


def format_fault(f) -> str:
    if isinstance(f, dict):
        where = f.get("device", "?") + (f" (node {f['node']})" if f.get("node") is not None else "")
        code = f" 0x{f['code']:04X}" if isinstance(f.get("code"), int) else ""
        return f"{where}: {f.get('kind', 'fault')}{code}: {f.get('meaning', '')}".rstrip(": ")
    return str(f)


def format_status(s: dict) -> str:
    """The ``status`` result as aligned lines (SI units; ms for loop timing, mm/mrad for errors)."""
    lines = [("mode", str(s.get("mode", "?")))]
    loop = s.get("loop")
    if isinstance(loop, dict):
        per, jit = loop.get("period") or {}, loop.get("jitter") or {}
        ms = lambda v: _num(v * 1e3 if isinstance(v, (int, float)) else v, "{:.3f}")  # noqa: E731
        lines.append(("loop", f"{_num(loop.get('rate'), '{:.1f}')} Hz: period p50 {ms(per.get('p50'))} ms, "
                              f"p99 {ms(per.get('p99'))} ms; jitter p99 {ms(jit.get('p99'))} ms, max "
                              f"{ms(jit.get('max'))} ms; overruns {loop.get('overruns', '?')} in "
                              f"{loop.get('cycles', '?')} cycles"))
    pose = s.get("pose")
    if isinstance(pose, dict):
        std = pose.get("std") or [None] * 3
        lines.append(("pose", f"x {_num(pose.get('x'))} ± {_num(std[0])} m, y {_num(pose.get('y'))} ± "
                              f"{_num(std[1])} m, alpha {_num(pose.get('alpha'))} ± {_num(std[2])} rad"))
    else:
        lines.append(("pose", "no estimate"))
    err = s.get("tracking_error")
    if isinstance(err, dict):
        k = lambda v: _num(v * 1e3 if isinstance(v, (int, float)) else v, "{:.1f}")  # noqa: E731
        lines.append(("tracking", f"error x {k(err.get('x'))} mm, y {k(err.get('y'))} mm, "
                                  f"alpha {k(err.get('alpha'))} mrad"))
    pay = s.get("payload")
    if isinstance(pay, dict) and isinstance(pay.get("estimate"), dict):
        units = {"m_p": "kg", "I_p": "kg m^2", "x_F": "m", "y_F": "m"}
        est = ", ".join(f"{n} {_num(e.get('value'), '{:.4g}')} ± {_num(e.get('std'), '{:.2g}')} {units.get(n, '')}"
                        + ("" if e.get("confident") else " (file)") for n, e in pay["estimate"].items()
                        if isinstance(e, dict))
        lines.append(("payload", f"{est}; {pay.get('state')}"))
    faults = s.get("faults") or []
    lines.append(("faults", "none" if not faults else format_fault(faults[0])))
    lines += [("", format_fault(f)) for f in faults[1:]]
    drives = s.get("drive_states") or {}
    lines.append(("drives", ", ".join(f"{k} {v}" for k, v in drives.items()) or "none reported"))
    rec = s.get("recording")
    if isinstance(rec, dict) and rec.get("path"):
        size = rec.get("bytes")
        extra = [f"{rec['samples']} samples" if "samples" in rec else None,
                 f"{size / 2 ** 20:.1f} MiB" if isinstance(size, (int, float)) else None]
        lines.append(("recording", f"{rec['path']}" + (f" ({', '.join(e for e in extra if e)})" if any(extra) else "")))
    else:
        lines.append(("recording", "off"))
    return "\n".join(f"{k:<10} {v}" for k, v in lines)


def format_reply(cmd: str, result: dict) -> str:
    extra = ", ".join(f"{k} {v}" for k, v in result.items()) if isinstance(result, dict) else str(result)
    return f"{cmd}: ok" + (f" ({extra})" if extra else "")
