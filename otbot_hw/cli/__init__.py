"""The ``otbot`` command line: one entry point, one module per subcommand.

Each module in ``SUBCOMMANDS`` (named as the command, or as ``MODULES`` says) defines
``register(subparsers)``, which adds its parser and sets ``func(args) -> dict``. The returned dict is printed as one JSON
object with ``--json``; otherwise the command prints its own human summary.
Exit codes: 0 success, 2 bad input (arguments, config, recordings), 1 failure,
130 interrupted.

Bad input ends in exactly one line on stderr, ``otbot CMD: error: <what is wrong>``,
never a traceback: commands raise ``CliError`` (or a library error listed in
``input_errors()``), argparse's own errors go through ``CliParser.error``. Shared
parsers and the output-path rule are in ``otbot_hw.cli.checks``.
"""
from __future__ import annotations

import argparse
import importlib
import json
import re
import sys
from typing import Sequence

from otbot_hw.cli.checks import CliError, parse_vector, positive_float  # noqa: F401  (re-exported)

#: Subcommand modules under otbot_hw.cli, in --help order.
SUBCOMMANDS = ("demo", "simulate", "identify", "sweep", "diagnose", "estimate", "imu", "track", "plan", "run", "plant",
               "bench", "daemon", "ctl", "import", "export")
#: Subcommands whose module has another name (``import`` is a Python keyword).
MODULES = {"import": "import_bag"}


class UsageError(CliError):
    """An argparse error (unknown option, missing or malformed argument) of one (sub)command."""

    def __init__(self, parser: argparse.ArgumentParser, message: str):
        super().__init__(message)
        self.parser = parser

    def line(self) -> str:
        """One line: the error, with the (sub)command's usage when the arguments do not fit its form."""
        text = f"{self.parser.prog}: error: {self}"
        if not str(self).startswith("argument "):  # unknown or missing arguments: show the form
            text += "; " + " ".join(self.parser.format_usage().split())
        return text


class CliParser(argparse.ArgumentParser):
    """argparse with one-line errors, subcommands that name their own unknown options, and values
    that start like a negative number (``--load -5@0,0``, ``--torques -6,10,6``) taken as values."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = re.compile(r"^-\.?\d")

    def error(self, message: str):
        raise UsageError(self, message)

    def parse_known_args(self, args=None, namespace=None):
        ns, extras = super().parse_known_args(args, namespace)
        if self._subparsers is None:  # a leaf: the command that runs
            if extras:
                self.error("unrecognized arguments: " + " ".join(extras))
            setattr(ns, "_prog", self.prog)
        return ns, extras


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The ``otbot`` parser; ``only``: register that subcommand alone (``main`` does so when the
    command line names one, so a call imports only its own command's module: ``otbot ctl`` starts
    fast)."""
    parser = CliParser(
        prog="otbot",
        description="Otbot control stack: model, simulation, identification, control and drivers. "
                    "Units are SI throughout: m, rad, s, kg, N, N m.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in SUBCOMMANDS:
        if only is None or name == only:
            importlib.import_module(f"otbot_hw.cli.{MODULES.get(name, name)}").register(sub)
    return parser


def input_errors() -> tuple[type[BaseException], ...]:
    """The exception types that mean bad input (exit 2, one line): the CLI's own and the library's
    errors documented as "bad input" (parameters/config, recordings, trajectories, identification)."""
    from otbot_hw.control.trajectories import TrajectoryError
    from otbot_hw.extras import MissingExtraError
    from otbot_hw.identification.errors import IdentificationError
    from otbot_hw.params import ParameterError
    from otbot_hw.recording import RecordingError

    return CliError, ParameterError, RecordingError, TrajectoryError, IdentificationError, MissingExtraError


def one_line(text: str) -> str:
    """``text`` on one line (messages quoting multi-line library errors)."""
    return "; ".join(s.strip() for s in str(text).splitlines() if s.strip())


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``otbot argv``; returns the exit code (commands may also raise ``SystemExit(1)``)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(argv[0] if argv and argv[0] in SUBCOMMANDS else None)
    try:
        args = parser.parse_args(argv)
    except UsageError as exc:
        print(one_line(exc.line()), file=sys.stderr)
        return 2
    prog = getattr(args, "_prog", f"otbot {args.command}")
    try:
        result = args.func(args)
        if getattr(args, "json", False) and result is not None:
            print(json.dumps(result, allow_nan=False))
        sys.stdout.flush()
    except BrokenPipeError:  # the reader left (``otbot ... --json | head -c 100``): no traceback
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # the exit's own flush must not fail
        print(f"{prog}: output closed by the reader", file=sys.stderr)
        return 1
    except Exception as exc:  # the input errors, imported only when something failed
        if _interrupted(exc):  # Ctrl-C inside a compiled call surfaces as SystemError caused by it
            print(f"{prog}: interrupted", file=sys.stderr)
            return 130
        if not isinstance(exc, CliError) and not isinstance(exc, input_errors()):
            raise
        print(f"{prog}: error: {one_line(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
    return 0


def _interrupted(exc: BaseException) -> bool:
    """Whether ``exc`` is a ``SystemError`` raised because a ``KeyboardInterrupt`` was pending when a compiled
    (numba) call returned ("... returned a result with an exception set": the interrupt is its cause)."""
    seen = 0
    while isinstance(exc, SystemError) and seen < 8:
        cause = exc.__cause__ or exc.__context__
        if isinstance(cause, KeyboardInterrupt):
            return True
        exc, seen = cause, seen + 1
    return False


def add_json_flag(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="print one JSON object (SI units) instead of text")


def progress(msg: str, enabled: bool = True) -> None:
    """Progress line on stderr (stdout stays clean for --json)."""
    if enabled:
        print(msg, file=sys.stderr, flush=True)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
