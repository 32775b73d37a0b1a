"""The ``otbot`` command line: one entry point, one module per subcommand.

Each module in ``SUBCOMMANDS`` defines ``register(subparsers)``, which adds its
parser and sets ``func(args) -> dict``. The returned dict is printed as one JSON
object with ``--json``; otherwise the command prints its own human summary.
Exit codes: 0 success, 2 bad input (arguments, config, recordings), 1 failure.
"""
from __future__ import annotations

import argparse
import importlib
import json
import sys
from typing import Sequence

#: Subcommand modules under otbot_hw.cli, in --help order.
SUBCOMMANDS = ("demo", "simulate", "identify", "sweep", "diagnose", "imu", "track", "plan", "run", "plant", "estimate")


class CliError(Exception):
    """Bad input to a command: printed as ``otbot: error: ...`` with exit code 2."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="otbot",
        description="Otbot control stack: model, simulation, identification, control and drivers. "
                    "Units are SI throughout: m, rad, s, kg, N, N m.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in SUBCOMMANDS:
        importlib.import_module(f"otbot_hw.cli.{name}").register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    from otbot_hw.params import ParameterError
    from otbot_hw.recording import RecordingError

    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        result = args.func(args)
    except (CliError, ParameterError, RecordingError) as exc:
        print(f"otbot {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"otbot {args.command}: interrupted", file=sys.stderr)
        return 130
    if getattr(args, "json", False) and result is not None:
        print(json.dumps(result, allow_nan=False))
    return 0


def add_json_flag(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="print one JSON object (SI units) instead of text")


def parse_vector(text: str, n: int, name: str) -> list[float]:
    """Parse 'a,b,c' into n finite floats or raise CliError naming the option."""
    import math

    parts = [s.strip() for s in text.split(",")]
    if len(parts) != n:
        raise CliError(f"{name} needs {n} comma-separated numbers, got {text!r}")
    out = []
    for s in parts:
        try:
            v = float(s)
        except ValueError:
            raise CliError(f"{name}: {s!r} is not a number") from None
        if not math.isfinite(v):
            raise CliError(f"{name}: values must be finite, got {s!r}")
        out.append(v)
    return out


def positive_float(name: str):
    """argparse type: a finite number > 0, errors naming the option."""
    import math

    def conv(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be a number, got {text!r}") from None
        if not (math.isfinite(v) and v > 0):
            raise argparse.ArgumentTypeError(f"{name} must be a finite number > 0, got {text!r}")
        return v

    return conv


def progress(msg: str, enabled: bool = True) -> None:
    """Progress line on stderr (stdout stays clean for --json)."""
    if enabled:
        print(msg, file=sys.stderr, flush=True)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
