"""``otbot plant``: the simulated robot as its own process, behind a CAN adapter.

The plant (simulated CiA 402 drives and CiA 406 encoder on canopen's LocalNode, the Otbot model
advancing one control period per SYNC) listens on an slcan adapter it emulates on a new
pseudo-terminal, or on a socketcan interface; the simulated IMU writes VectorNav sentences into
another pseudo-terminal. It prints one JSON line (can_interface, can_channel, imu_port) and runs
until its standard input closes; each input line ``report`` is answered with one JSON line of
the simulated drives' own state, and the operator commands (``sim.plant.Plant.operator``:
``fixture stand``, ``load 40@0.2,-0.1``, ``unload``, ``status``: what a person at the bench does)
with one JSON line each. ``--inject KIND@SECONDS`` makes the plant inject a fault at that
plant time (``sim.injection``; ``plant-kill`` kills this process). A master then runs e.g.
``otbot run --bus config --interface slcan --channel PTY --imu-port PTY2``.
"""
from __future__ import annotations

import argparse
import errno
from pathlib import Path

from otbot_hw.cli import CliError
from otbot_hw.cli.checks import bus_config, rate, seed


def register(sub) -> None:
    p = sub.add_parser(
        "plant",
        help="serve the simulated robot over slcan (pseudo-terminal) or socketcan, as a separate process",
        description="Run the simulated Otbot (CANopen slaves + dynamic model in lockstep with SYNC) behind an "
                    "emulated slcan USB-CAN adapter on a pseudo-terminal, or on a socketcan interface. Prints one "
                    "JSON line {can_interface, can_channel, imu_port}; stops when stdin closes. Lines on stdin: "
                    "'report' (the drives' state) or an operator command, each answered with one JSON line: "
                    "'fixture floor|stand|locked', 'load KG@X,Y[,I]' (a load of KG kg at X, Y m in the platform "
                    "frame, own inertia I kg m^2), 'unload', 'status'; the robot is at rest after each. Units: SI.",
    )
    p.add_argument("--transport", choices=("slcan", "socketcan"), default="slcan",
                   help="slcan: emulate a USB-CAN adapter on a new pseudo-terminal (default, works everywhere); "
                        "socketcan: use the Linux CAN interface --channel (needs kernel CAN support)")
    p.add_argument("--channel", default="vcan0", help="socketcan interface (default vcan0, a virtual CAN device)")
    p.add_argument("--config", type=Path, default=None, help="hardware configuration (default config/robot.yaml)")
    p.add_argument("--rate", type=rate, default=None,
                   help="control (SYNC) rate in Hz: one model step per SYNC (default: bus.control_rate of the config)")
    p.add_argument("--fixture", choices=("floor", "stand", "locked"), default="floor",
                   help="bench fixture: floor, stand (chassis held, wheels free), locked (chassis and wheels held)")
    p.add_argument("--plant-params", type=Path, default=None,
                   help="the robot to simulate: a parameter YAML or a diagnosed-model file with 'effects' (default "
                        "config/otbot.yaml); with effects the extended model is stepped and its sensor effects appear "
                        "in the encoder and IMU samples")
    p.add_argument("--noise", choices=("paper", "none"), default="paper",
                   help="sensor noise: the paper's IMU and encoder-rate sigmas (default), or none")
    p.add_argument("--seed", type=seed, default=0, help="noise seed, an integer >= 0 (default 0)")
    p.add_argument("--no-imu", action="store_true", help="no simulated IMU")
    p.add_argument("--inject", default=None, metavar="KIND@SECONDS[:DRIVE]",
                   help="inject a fault at this plant time (s since the drives were enabled): drive-silent, emcy, "
                        "fault-bit, imu-loss, imu-error, bus-off, plant-kill (SIGKILL of this process); DRIVE: "
                        "right_wheel, left_wheel (default) or pivot")
    p.add_argument("--json", action="store_true", help="accepted for uniformity: the output is always one JSON line")
    p.set_defaults(func=run)


def check_socketcan(channel: str) -> None:
    """CliError unless the socketcan interface ``channel`` can be opened (tried and closed again)."""
    import can

    try:
        can.Bus(interface="socketcan", channel=channel).shutdown()
    except (OSError, can.CanError) as exc:
        code = getattr(exc, "errno", None) or getattr(getattr(exc, "__cause__", None), "errno", None)
        hint = {errno.EAFNOSUPPORT: "this kernel has no SocketCAN support; use --transport slcan",
                errno.ENODEV: f"no interface {channel}; create one with `ip link add dev {channel} type vcan` "
                              f"and `ip link set up {channel}`, or use --transport slcan"}.get(code, "")
        raise CliError(f"--transport socketcan --channel {channel}: cannot open the CAN interface: "
                       f"{getattr(exc, 'strerror', None) or exc}" + (f" ({hint})" if hint else "")) from None


def run(args: argparse.Namespace) -> None:
    from otbot_hw.model.effects import ExtendedModel
    from otbot_hw.sensors import NoiseModel
    from sim.injection import Injection
    from sim.plant_process import serve

    model = ExtendedModel.load(args.plant_params)
    cfg = bus_config(args.config, args.rate)
    if args.transport == "socketcan":
        check_socketcan(args.channel)
    try:
        inject = Injection.parse(args.inject) if args.inject is not None else None
    except ValueError as exc:
        raise CliError(str(exc)) from None
    noise = NoiseModel.paper() if args.noise == "paper" else NoiseModel()
    import gc

    gc.collect()  # the plant answers SYNCs as hardware would: no full collection of everything
    gc.freeze()   # imported in the middle of one (measured: 20-70 ms pauses without)
    try:
        serve(cfg, transport=args.transport, channel=args.channel, with_imu=not args.no_imu,
              fixture=args.fixture, noise=noise, seed=args.seed, inject=inject, params=model)
    except ValueError as exc:  # an injection this plant cannot do
        raise CliError(str(exc)) from None
    return None
