"""``otbot plant``: the simulated robot as its own process, behind a CAN adapter.

The plant (simulated CiA 402 drives and CiA 406 encoder on canopen's LocalNode, the Otbot model
advancing one control period per SYNC) listens on an slcan adapter it emulates on a new
pseudo-terminal, or on a socketcan interface; the simulated IMU writes VectorNav sentences into
another pseudo-terminal. It prints one JSON line (can_interface, can_channel, imu_port) and runs
until its standard input closes; each input line ``report`` is answered with one JSON line of
the simulated drives' own state. ``--inject KIND@SECONDS`` makes the plant inject a fault at that
plant time (``sim.injection``; ``plant-kill`` kills this process). A master then runs e.g.
``otbot run --bus config --interface slcan --channel PTY --imu-port PTY2``.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from otbot_hw.cli import positive_float


def register(sub) -> None:
    p = sub.add_parser(
        "plant",
        help="serve the simulated robot over slcan (pseudo-terminal) or socketcan, as a separate process",
        description="Run the simulated Otbot (CANopen slaves + dynamic model in lockstep with SYNC) behind an "
                    "emulated slcan USB-CAN adapter on a pseudo-terminal, or on a socketcan interface. Prints one "
                    "JSON line {can_interface, can_channel, imu_port}; stops when stdin closes. Units: SI.",
    )
    p.add_argument("--transport", choices=("slcan", "socketcan"), default="slcan")
    p.add_argument("--channel", default="vcan0", help="socketcan interface (default vcan0, a virtual CAN device)")
    p.add_argument("--config", type=Path, default=None, help="hardware configuration (default config/robot.yaml)")
    p.add_argument("--rate", type=positive_float("--rate"), default=None, help="control (SYNC) rate, Hz")
    p.add_argument("--fixture", choices=("floor", "stand", "locked"), default="floor")
    p.add_argument("--noise", choices=("paper", "none"), default="paper")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-imu", action="store_true", help="no simulated IMU")
    p.add_argument("--inject", default=None, metavar="KIND@SECONDS[:DRIVE]",
                   help="inject a fault at this plant time (s since the drives were enabled): drive-silent, emcy, "
                        "fault-bit, imu-loss, imu-error, bus-off, plant-kill (SIGKILL of this process); DRIVE: "
                        "right_wheel, left_wheel (default) or pivot")
    p.add_argument("--json", action="store_true", help="accepted for uniformity: the output is always one JSON line")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> None:
    from drivers.config import load_robot_config
    from otbot_hw.cli import CliError
    from otbot_hw.sensors import NoiseModel
    from sim.injection import Injection
    from sim.plant import serve

    try:
        inject = Injection.parse(args.inject) if args.inject is not None else None
    except ValueError as exc:
        raise CliError(str(exc)) from None
    cfg = load_robot_config(args.config)
    if args.rate is not None:
        cfg = cfg.replace_bus(control_rate=args.rate)
    noise = NoiseModel.paper() if args.noise == "paper" else NoiseModel()
    try:
        serve(cfg, transport=args.transport, channel=args.channel, with_imu=not args.no_imu,
              fixture=args.fixture, noise=noise, seed=args.seed, inject=inject)
    except ValueError as exc:  # an injection this plant cannot do
        raise CliError(str(exc)) from None
    return None
