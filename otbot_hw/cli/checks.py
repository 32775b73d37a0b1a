"""Checks of command-line input shared by every subcommand: numbers, durations, seeds, output paths.

Number parsers are argparse ``type=`` callables: they raise ``argparse.ArgumentTypeError``, which
``otbot_hw.cli.main`` prints as one line ``otbot CMD: error: argument --opt: must be ...`` with exit
code 2. Each rejects what cannot be meant: NaN and infinity always, negative or zero values where
the quantity cannot be (durations, rates, counts), non-integers for seeds and counts.

Output paths follow one rule (README, "CLI reference"): **otbot creates the file or folder you name,
never the folders above it.** The folder that will hold an output must already exist and be
writable; a file output must not be an existing folder, a folder output must not be an existing
file; an existing file is replaced, unless it is one of the command's inputs (a recording, parameter
file, trajectory: ``not_an_input``). ``output_file`` / ``output_folder`` check this before the work
starts (they create nothing that stays), and ``writing`` turns a file-system error that still happens
while writing (disk full, a folder removed meanwhile) into the same one-line error.
"""
from __future__ import annotations

import argparse
import contextlib
import math
import os
import tempfile
from pathlib import Path
from typing import Callable, Iterator



def finite_number(*args, **kwargs):
    """``otbot_hw.params.finite_number``, imported when first used (``otbot ctl`` starts without numpy)."""
    from otbot_hw.params import finite_number as parse

    return parse(*args, **kwargs)


class CliError(Exception):
    """Bad input to a command: printed as ``otbot CMD: error: ...`` with exit code 2."""


# --- numbers (argparse types) -----------------------------------------------------------------------

def number(*, minimum: float | None = None, above: float | None = None, maximum: float | None = None,
           integer: bool = False, unit: str = "") -> Callable[[str], float | int]:
    """argparse type: a finite number (an integer with ``integer``) within the given bounds.

    minimum: smallest allowed value (inclusive); above: exclusive lower bound; maximum: inclusive
    upper bound; unit: named in the message (e.g. "s", "Hz").
    """
    kind = "an integer" if integer else "a finite number"
    if unit:
        kind += f" of {unit}"
    bounds = []
    if above is not None:
        bounds.append(f"> {above:g}")
    if minimum is not None:
        bounds.append(f">= {minimum:g}")
    if maximum is not None:
        bounds.append(f"<= {maximum:g}")
    rule = f"must be {kind}" + (" " + " and ".join(bounds) if bounds else "")

    def convert(text: str) -> float | int:
        try:
            value: float | int = int(text, 10) if integer else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{rule}, got {text!r}") from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"{rule}, got {text!r}")
        if ((above is not None and not value > above) or (minimum is not None and value < minimum)
                or (maximum is not None and value > maximum)):
            raise argparse.ArgumentTypeError(f"{rule}, got {text!r}")
        return value

    convert.__name__ = "integer" if integer else "number"
    return convert


#: A duration in s, > 0.
duration = number(above=0, unit="seconds")
#: A rate in Hz, > 0.
rate = number(above=0, unit="Hz")
#: A noise seed: an integer >= 0 (numpy's generators take no negative seeds).
seed = number(minimum=0, integer=True)
#: A finite number >= 0.
non_negative = number(minimum=0)


def count(minimum: int = 1, maximum: int | None = None) -> Callable[[str], int]:
    """argparse type: an integer count in [minimum, maximum]."""
    return number(minimum=minimum, maximum=maximum, integer=True)  # type: ignore[return-value]


def positive_float(name: str | None = None) -> Callable[[str], float]:
    """argparse type: a finite number > 0 (``name`` is kept for callers that pass it; argparse
    already names the option in its message)."""
    return number(above=0)  # type: ignore[return-value]


#: Longest run a command accepts (samples); 10^7 samples of 12 states are about 1 GB.
MAX_SAMPLES = 10_000_000


def count_text(n: float) -> str:
    """A count for a message: exact below 10^15, else 3 significant digits (no 300-digit numbers)."""
    return f"{int(n)}" if math.isfinite(n) and abs(n) < 1e15 else f"{n:.3g}"


def sample_count(duration_s: float, rate_hz: float, limit: int = MAX_SAMPLES) -> int:
    """Number of control/sample periods in ``duration_s`` at ``rate_hz`` (the nearest whole number);
    CliError when there is none or more than ``limit`` (also when the product overflows)."""
    product = duration_s * rate_hz
    if not product <= limit + 0.5:  # inf, or beyond what int(round()) should see
        raise CliError(f"--duration {duration_s:g} s at {rate_hz:g} Hz gives {count_text(product)} samples; "
                       f"at most {limit}")
    n = int(round(product))
    if n < 1:
        raise CliError(f"--duration {duration_s:g} s at {rate_hz:g} Hz is shorter than one period "
                       f"({1 / rate_hz:g} s)")
    if n > limit:
        raise CliError(f"--duration {duration_s:g} s at {rate_hz:g} Hz gives {n} samples; at most {limit}")
    return n


def rounding_notice(duration_s: float, rate_hz: float, n: int, command: str) -> str | None:
    """The notice when ``n`` periods (``sample_count``) do not last ``duration_s``: e.g. "otbot simulate:
    note: --duration 0.5 s at 3 Hz is 1.5 periods; running 2 periods (0.667 s)"; None when they do."""
    if abs(n - duration_s * rate_hz) <= 1e-9 * n:
        return None
    return (f"otbot {command}: note: --duration {duration_s:g} s at {rate_hz:g} Hz is {duration_s * rate_hz:.6g} "
            f"periods; running {n} period{'s' if n != 1 else ''} ({n / rate_hz:.6g} s)")


def bus_config(config_path: Path | None, rate_hz: float | None = None):
    """The hardware configuration (``drivers.config.RobotConfig``) with ``--rate`` applied; CliError
    when the control period 1/rate cannot be programmed into the drives (0x60C2)."""
    from drivers.cia402_setup import interpolation_period
    from drivers.config import load_robot_config

    cfg = load_robot_config(config_path)
    if rate_hz is not None:
        cfg = cfg.replace_bus(control_rate=rate_hz)
    try:
        interpolation_period(cfg.bus.period)
    except ValueError as exc:
        raise CliError(f"--rate {cfg.bus.control_rate:g} Hz: {exc}") from None
    return cfg


def parse_vector(text: str, n: int, name: str) -> list[float]:
    """Parse 'a,b,c' into n finite floats or raise CliError naming the option."""
    parts = [s.strip() for s in text.split(",")]
    if len(parts) != n:
        raise CliError(f"{name} needs {n} comma-separated numbers, got {text!r}")
    return [finite_number(s, name, CliError) for s in parts]


# --- output paths -----------------------------------------------------------------------------------

def _writable_folder(folder: Path, option: str, path: Path) -> None:
    """CliError unless ``folder`` exists, is a folder and accepts a new file (tried, then removed)."""
    if not folder.exists():
        raise CliError(f"{option} {path}: folder {folder} does not exist (otbot creates no parent folders)")
    if not folder.is_dir():
        raise CliError(f"{option} {path}: {folder} is not a folder")
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        raise CliError(f"{option} {path}: cannot write in folder {folder}: {exc.strerror}") from None


def same_file(a: Path | str, b: Path | str) -> bool:
    """True when ``a`` and ``b`` name one file: the same inode when both exist (a link or another spelling
    counts), else the same resolved path."""
    try:
        return os.path.samefile(a, b)
    except OSError:
        try:
            return Path(a).resolve() == Path(b).resolve()
        except (OSError, RuntimeError):  # a loop of links: its reader says so
            return False


def default_input(path: Path | str | None, name: str) -> Path | str:
    """``path``, or the project's configuration file ``config/NAME`` (otbot.yaml, robot.yaml) that a command
    reads when ``path`` is not given: an output must not replace it either."""
    return path if path is not None else Path(__file__).resolve().parents[2] / "config" / name


def not_an_input(path: Path | str | None, option: str, inputs: dict[str, object], folder: bool = False) -> None:
    """CliError when the output ``path`` is one of the command's inputs: ``inputs`` maps what an input is
    ("recording", "parameter file") to its path, None or a list of paths. Writing the output would replace
    the input the work reads (``otbot import --out bag.mcap bag.mcap``: "--out bag.mcap: is the bag itself").
    folder: ``path`` is a folder output that replaces an existing folder (``export --ros2``): an input inside
    it is refused too."""
    if path is None:
        return
    for what, given in inputs.items():
        for q in given if isinstance(given, (list, tuple)) else [given]:
            if q is None:
                continue
            if same_file(path, q):
                raise CliError(f"{option} {path}: is the {what} itself")
            if folder and Path(path).is_dir() and _inside(q, path):
                raise CliError(f"{option} {path}: holds the {what} {q}; replacing the folder would remove it")


def _inside(file: Path | str, folder: Path | str) -> bool:
    try:
        return Path(file).resolve().is_relative_to(Path(folder).resolve())
    except (OSError, RuntimeError):
        return False


def output_file(path: Path | str | None, option: str, suffix: str | None = None,
                inputs: dict[str, object] | None = None) -> Path | None:
    """Check an output file before the work starts (see the module's rule); None passes through.

    suffix: required file ending (e.g. ".gif"), compared case-insensitively. inputs: the command's input
    files by what they are (``not_an_input``); the output must not be one of them.
    """
    if path is None:
        return None
    path = Path(path)
    not_an_input(path, option, inputs or {})
    if suffix is not None and path.suffix.lower() != suffix:
        raise CliError(f"{option} {path}: the file name must end in {suffix}")
    if path.is_dir():
        raise CliError(f"{option} {path}: is a folder; give a file name")
    _writable_folder(path.parent if str(path.parent) else Path("."), option, path)
    if path.exists() and not os.access(path, os.W_OK):
        raise CliError(f"{option} {path}: the existing file is not writable")
    return path


def output_folder(path: Path | str | None, option: str) -> Path | None:
    """Check an output folder before the work starts (see the module's rule); None passes through.

    An existing folder must accept new files; a missing one is created by the writer, so its
    parent must exist.
    """
    if path is None:
        return None
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise CliError(f"{option} {path}: exists and is not a folder")
    if path.is_dir():
        _writable_folder(path, option, path)
    else:
        _writable_folder(path.parent if str(path.parent) else Path("."), option, path)
    return path


def write_failure(exc: OSError, target) -> CliError:
    """The one-line error for an ``OSError`` while writing ``target`` (the file the error names, if any):
    e.g. "cannot write est.mcap: No space left on device"."""
    name = exc.filename if exc.filename is not None else target
    return CliError(f"cannot write {name}: {exc.strerror or exc}")


@contextlib.contextmanager
def writing(what: str) -> Iterator[None]:
    """Turn an ``OSError`` while writing outputs into ``CliError`` naming ``what`` and the file."""
    try:
        yield
    except OSError as exc:
        where = f": {exc.filename}" if exc.filename else ""
        raise CliError(f"{what}: cannot write{where}: {exc.strerror or exc}") from None


def write_complete(out: Path, write: Callable[[Path], None]) -> None:
    """``write(path)`` the output ``out`` so that an interrupted write leaves no truncated file: into a file
    beside it, renamed over it when complete. An existing ``out`` that is not a regular file (a device such as
    ``/dev/null``, a FIFO) is written as it is, never replaced (as root a rename would put a file in its place)."""
    out = Path(out)
    if out.exists() and not out.is_file():
        write(out)
        return
    tmp = out.with_name(f".{out.name}.tmp-{os.getpid()}")
    try:
        write(tmp)
        os.replace(tmp, out)
    finally:
        if tmp.exists():
            tmp.unlink()


# --- input files ------------------------------------------------------------------------------------

def truncation_notice(path, rec) -> str:
    """One line saying that ``rec`` (read from ``path``) was cut short and what is left of it."""
    n = len(rec)
    end = (f"ends at t = {rec.t[-1]:g} s after {n} complete sample{'' if n == 1 else 's'}" if n
           else "holds no complete sample")
    return f"{path} is truncated (the writer stopped before closing it): it {end}"


def complete_samples(path, rec, command: str, work: str, doing: str, minimum: int = 2) -> bool:
    """Whether ``rec`` (read from ``path``) was cut short. When it was: CliError naming the file when fewer than
    ``minimum`` complete samples are left ("X is truncated ...: nothing to {work}"), else a notice line on stderr
    ("[{command}] notice: X is truncated ...; {doing} those")."""
    if not rec.truncated:
        return False
    if len(rec) < minimum:
        raise CliError(f"{truncation_notice(path, rec)}: nothing to {work}")
    import sys

    print(f"[{command}] notice: {truncation_notice(path, rec)}; {doing} those", file=sys.stderr, flush=True)
    return True


def distinct_files(paths, option: str) -> None:
    """CliError when two of ``paths`` hold the same bytes (a file named twice, a copy, a link): each
    input must count once. Unreadable files are skipped (their reader says what is wrong)."""
    import hashlib

    from otbot_hw.input_files import open_input

    seen: dict[tuple[int, str], Path] = {}
    for p in paths:
        p = Path(p)
        try:
            with open_input(p) as f:
                size = os.fstat(f.fileno()).st_size
                digest = hashlib.file_digest(f, "sha256").hexdigest()
        except OSError:
            continue
        first = seen.setdefault((size, digest), p)
        if first is not p:
            same = "is named twice" if os.path.abspath(first) == os.path.abspath(p) else \
                f"has the same content as {first}"
            raise CliError(f"{option} {p}: {same}; each recording counts once (a duplicate would shrink the "
                           "reported std as if it were new data)")
