"""Command-line options that choose and configure a back end (shared by ``otbot track`` and ``otbot run``).

Back ends (``otbot_hw.runtime.backends``): ``--sim`` the in-process simulated robot (no bus),
``--bus sim`` the simulated robot behind the CANopen drivers on virtual CAN, ``--bus config`` the
configured bus (the real robot, or an ``otbot plant`` process).
"""
from __future__ import annotations

import argparse
from pathlib import Path

from otbot_hw.cli import CliError, progress
from otbot_hw.cli import checks


def add_bus_options(p: argparse.ArgumentParser, rate_default: str, lockstep_help: str | None = None) -> None:
    """--config, --rate, --noise, --seed, --no-imu, --interface, --channel, --imu-port, --lockstep
    (``lockstep_help``: what it means for this command, when it differs)."""
    p.add_argument("--config", "--robot", dest="config", type=Path, default=None,
                   help="hardware configuration: bus, drives, IMU, motor limits, safety (default config/robot.yaml)")
    p.add_argument("--rate", type=checks.rate, default=None, help=f"control rate in Hz ({rate_default})")
    p.add_argument("--noise", choices=("paper", "none"), default="paper",
                   help="simulated sensor noise: the paper's IMU and encoder-rate sigmas, or none (simulated back ends)")
    p.add_argument("--seed", type=checks.seed, default=0, help="simulated noise seed, an integer >= 0 (default 0)")
    p.add_argument("--no-imu", action="store_true", help="run without the IMU")
    p.add_argument("--interface", default=None, help="--bus config: override bus.interface (a python-can interface)")
    p.add_argument("--channel", default=None, help="--bus config: override bus.channel")
    p.add_argument("--imu-port", default=None, help="--bus config: override imu.port")
    p.add_argument("--lockstep", action="store_true",
                   help=lockstep_help or "--bus config talks to a simulated plant (otbot plant): send SYNCs back to "
                                         "back instead of every 1/rate s, and wait for the IMU sample of each SYNC")


def bus_config(args: argparse.Namespace, rate: float | None, quiet: bool = False, tag: str = "otbot"):
    """The hardware configuration for ``args.bus`` ("sim" or "config") at ``rate`` Hz (None: the
    configured control rate): overrides applied, the rate checked against the drives' interpolation
    period; warns when the bus load exceeds the bitrate. Bad values raise ``CliError``."""
    import can

    from drivers.busload import bus_load

    cfg = checks.bus_config(args.config, rate)
    if args.bus == "sim":
        cfg = cfg.replace_bus(interface="virtual", channel="otbot-sim")
    else:
        if args.interface is not None and args.interface not in can.VALID_INTERFACES:
            raise CliError(f"--interface must be a python-can interface ({', '.join(sorted(can.VALID_INTERFACES))}), "
                           f"got {args.interface!r}")
        kw = {k: v for k, v in (("interface", args.interface), ("channel", args.channel)) if v is not None}
        if kw:
            cfg = cfg.replace_bus(**kw)
    load = bus_load(cfg)
    if load.warning():
        progress(f"[{tag}] warning: {load.warning()}", True)
    return cfg, load


def noise_model(args: argparse.Namespace):
    from otbot_hw.sensors import NoiseModel

    return NoiseModel.paper() if args.noise == "paper" else NoiseModel()
