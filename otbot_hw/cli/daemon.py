"""``otbot daemon``: the on-robot daemon (``otbot_hw.runtime.daemon``; ``docs/daemon.md``).

It owns the bus: boots the drives, runs the one loop in real time, takes commands on the control
socket (``otbot ctl``), records every session, serves live telemetry and talks to systemd. It
runs until SIGTERM, SIGINT or ``otbot ctl shutdown``: quick stop, disable, recording closed,
exit 0. Exit 2 for bad input, one line and nothing started: arguments, configuration, a socket
folder that is missing or not writable, a socket path beyond AF_UNIX's 107 bytes, a socket held
by another daemon, a recording folder that is missing or not writable (the daemon creates
neither folder: systemd's RuntimeDirectory=/StateDirectory= do), a telemetry port that is taken
or a host that is not this machine's; 1 when the drives cannot be booted.
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import logging
import os
import signal
import sys
import threading
from pathlib import Path

from otbot_hw.cli import CliError, add_json_flag, parse_vector
from otbot_hw.cli.backend_args import add_bus_options


def register(sub) -> None:
    p = sub.add_parser(
        "daemon", help="the on-robot daemon: one supervised loop, commanded over a local socket (otbot ctl), "
                       "recorded, live in Foxglove, watched by systemd",
        description="Boot the drives and run the control loop in real time (read -> estimate -> control -> "
                    "supervise -> write) until SIGTERM/SIGINT or `otbot ctl shutdown`, then quick stop, disable, "
                    "close the recording and exit 0. Commands arrive on a Unix socket (JSON lines; `otbot ctl`): "
                    "modes idle, hold, track, velocity (twist in m/s, rad/s with a deadman), excite (torques in "
                    "N m). Every session is recorded (MCAP, docs/recording-format.md). Poses are in m and rad in the "
                    "ground frame B, which is where the robot stands at start (--start-pose). Configuration: the "
                    "daemon:, safety:, estimator: and bus sections of --config (docs/daemon.md).")
    p.add_argument("--bus", choices=("sim", "config"), default="config",
                   help="config: the bus and IMU of --config (the robot, or an `otbot plant` process; default); "
                        "sim: the simulated robot behind the CANopen drivers on virtual CAN in this process")
    p.add_argument("--params", type=Path, default=None,
                   help="parameter YAML of the controller and the estimator (default config/otbot.yaml; a diagnosed "
                        "model from otbot diagnose --out adds effects the controller compensates)")
    p.add_argument("--socket", type=Path, default=None,
                   help="control socket (default daemon.socket.path, else $RUNTIME_DIRECTORY/control.sock, "
                        "$XDG_RUNTIME_DIR/otbot/control.sock, /run/otbot/control.sock)")
    p.add_argument("--record-dir", type=Path, default=None,
                   help="folder of the session recordings (default daemon.recording.dir)")
    tel = p.add_mutually_exclusive_group()
    tel.add_argument("--telemetry", default=None, metavar="HOST:PORT",
                     help="Foxglove WebSocket address (default daemon.telemetry: 127.0.0.1:8765; port 0: any free)")
    tel.add_argument("--no-telemetry", action="store_true", help="no live telemetry server")
    p.add_argument("--allow-user", action="append", default=[], metavar="NAME",
                   help="also allow this user (name or numeric uid) to send every command, on top of "
                        "daemon.socket.allowed_users/allowed_groups of --config (repeatable; no copy of the "
                        "configuration needed). --bus sim allows the invoking user anyway (no robot can move)")
    p.add_argument("--start-pose", default="0,0,0", metavar="X,Y,ALPHA",
                   help="where the robot stands at start, m, m, rad (default 0,0,0: frame B is the start pose)")
    add_bus_options(p, "default bus.control_rate of --config", lockstep_help=(
        "--bus config talks to a simulated plant (otbot plant): the robot waits for each SYNC's answers and IMU "
        "sample instead of within the period, and the drives get no period-based watchdogs (their "
        "master-heartbeat consumer stays); the loop still runs in real time"))
    p.add_argument("--plant-params", type=Path, default=None,
                   help="--bus sim: the robot to simulate (parameters or a diagnosed model; default --params)")
    add_json_flag(p)
    p.set_defaults(func=run)


def _writable_folder(path: Path, what: str) -> Path:
    """``path``, an existing folder this user can write; the daemon never creates it (README: otbot
    never creates the folders above an output; under systemd, StateDirectory= does)."""
    from otbot_hw.folders import require_folder

    return require_folder(path, CliError, f"{what} {path}: the folder does not exist (the daemon does not create it: "
                          f"create it, or let systemd's StateDirectory= do it, or choose another with {what})",
                          f"{what} {path}: not a folder",
                          f"{what} {path}: not a folder this user (uid {os.geteuid()}) can write")


def _allowed_users(args: argparse.Namespace, configured: tuple) -> tuple:
    """daemon.socket.allowed_users plus every --allow-user (checked against the user database) and,
    with --bus sim, the invoking user."""
    import pwd

    extra: list = []
    for name in args.allow_user:
        try:
            uid = int(name) if name.isdigit() else pwd.getpwnam(name).pw_uid
        except (KeyError, ValueError):
            raise CliError(f"--allow-user {name!r}: no such user on this machine") from None
        if uid > 2 ** 32 - 2:
            raise CliError(f"--allow-user {name!r}: not a user id")
        extra.append(uid)
    if args.bus == "sim":
        extra.append(os.getuid())
    return tuple(dict.fromkeys([*configured, *extra]))


def prepare(args: argparse.Namespace):
    """(Daemon, open_robot) from the command line; bad input raises ``CliError``/``ParameterError``."""
    from otbot_hw.estimation import EstimatorConfig
    from otbot_hw.model.effects import ExtendedModel
    from otbot_hw.motors import load_motor_limits
    from otbot_hw.runtime.daemon import Daemon, DaemonSettings
    from otbot_hw.runtime.daemon_config import load_daemon_config
    from otbot_hw.runtime.control_socket_file import ControlSocketError, check_socket_path
    from otbot_hw.runtime.supervisor import SafetyConfig
    from otbot_hw.runtime.telemetry import TelemetryError, check_telemetry_address, parse_host_port

    if args.bus == "sim" and (any(v is not None for v in (args.interface, args.channel, args.imu_port))
                              or args.lockstep):
        raise CliError("--interface/--channel/--imu-port/--lockstep are for the configured bus (--bus config), "
                       "not --bus sim")
    if args.bus == "config" and (args.plant_params is not None):
        raise CliError("--plant-params sets the simulated robot (--bus sim); the configured bus runs the robot "
                       "that is there")
    start = parse_vector(args.start_pose, 3, "--start-pose")
    dcfg = load_daemon_config(args.config)
    dcfg = dataclasses.replace(dcfg, socket=dataclasses.replace(
        dcfg.socket, allowed_users=_allowed_users(args, dcfg.socket.allowed_users)))
    telemetry = None
    if not args.no_telemetry:
        if args.telemetry is not None:
            try:
                telemetry = parse_host_port(args.telemetry)
            except ValueError as exc:
                raise CliError(f"--telemetry: {exc}") from None
        elif dcfg.telemetry.enabled:
            telemetry = (dcfg.telemetry.host, dcfg.telemetry.port)
    try:
        check_socket_path(args.socket if args.socket is not None else dcfg.socket.socket_path())
        if telemetry is not None:
            check_telemetry_address(*telemetry)
    except (ControlSocketError, TelemetryError) as exc:
        raise CliError(str(exc)) from None
    if dcfg.scheduling.cpus is not None:
        from otbot_hw.motors import DEFAULT_ROBOT_FILE
        from otbot_hw.runtime.scheduling import SchedulingError, check_cpus

        try:
            check_cpus(dcfg.scheduling.cpus, f"{args.config or DEFAULT_ROBOT_FILE}: 'daemon.scheduling.cpus'")
        except SchedulingError as exc:
            raise CliError(str(exc)) from None
    record_dir = _writable_folder(args.record_dir if args.record_dir is not None else dcfg.recording.dir,
                                  "--record-dir")
    model = ExtendedModel.load(args.params)
    settings = DaemonSettings(
        model=model if model.active_effects() else model.params, limits=load_motor_limits(args.config),
        safety=SafetyConfig.load(args.config), estimator=EstimatorConfig.load(args.config), daemon=dcfg,
        socket_path=args.socket, record_dir=record_dir, telemetry=telemetry, start_pose=tuple(start),
        metadata={"command": "otbot daemon", "bus": args.bus})
    open_robot, period = _opener(args, start)
    return Daemon(settings, period=period), open_robot


def _opener(args: argparse.Namespace, start):
    """(the context manager that opens (boots) the robot of ``--bus``, its period in s)."""
    import numpy as np

    from otbot_hw.cli.backend_args import bus_config, noise_model

    cfg, _ = bus_config(args, args.rate, tag="daemon")
    with_imu = not args.no_imu
    if args.bus == "sim":
        from otbot_hw.model.effects import ExtendedModel
        from otbot_hw.simulation.simulator import rest_state

        plant = ExtendedModel.load(args.plant_params if args.plant_params is not None else args.params)
        plant = plant if plant.active_effects() else plant.params
        x0 = rest_state(np.asarray(start, float))

        @contextlib.contextmanager
        def open_sim():
            from sim.bus_robot import simulated_robot

            with simulated_robot(cfg, with_imu=with_imu, params=plant, x0=x0, noise=noise_model(args),
                                 seed=args.seed) as (robot, _plant):
                yield robot
        return open_sim, cfg.bus.period
    from otbot_hw.runtime.backends import BusConfigBackend

    backend = BusConfigBackend(cfg, args.imu_port, lockstep=args.lockstep, with_imu=with_imu)
    return backend.open, cfg.bus.period


def run(args: argparse.Namespace) -> dict:
    from otbot_hw.robot import RobotError
    from otbot_hw.runtime.control_socket_file import ControlSocketError
    from otbot_hw.runtime.telemetry import TelemetryError

    if not logging.getLogger().handlers:  # the journal's lines: ours at INFO, libraries' warnings
        logging.basicConfig(level=logging.WARNING, stream=sys.stderr, format="otbot daemon: %(levelname)s %(message)s")
        logging.getLogger("otbot_hw").setLevel(logging.INFO)
    daemon, open_robot = prepare(args)
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda signum, frame: daemon.request_stop(signal.Signals(signum).name))
    try:
        summary = daemon.serve(open_robot)
    except (ControlSocketError, TelemetryError) as exc:  # SocketInUse: a second daemon on the socket
        raise CliError(str(exc)) from None
    except RobotError as exc:
        print(f"otbot daemon: cannot start the robot: {exc}", file=sys.stderr)
        raise SystemExit(1) from None
    if not args.json:
        loop = summary.get("loop") or {}
        per = loop.get("period") or {}
        print(f"otbot daemon: stopped ({summary['stopped']}): {loop.get('cycles', 0)} cycles, period p50 "
              f"{_ms(per.get('p50'))} p99 {_ms(per.get('p99'))} ms, overruns {loop.get('overruns', 0)}, faults "
              f"{summary['faults_seen']}; sessions {', '.join(summary['sessions']) or 'none'} in "
              f"{summary['recording_dir']}", file=sys.stderr)
    return summary


def _ms(v) -> str:
    return f"{v * 1e3:.3f}" if isinstance(v, (int, float)) else "?"
