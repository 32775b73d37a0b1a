"""The one way an input file is opened (parameter and configuration YAML, recordings, CSV files, byte captures):
only a regular file is read. A FIFO or pipe (``mkfifo``, ``<(cat run.mcap)``) blocks the open or the read,
a device (``/dev/zero``) never ends and a socket cannot be read; each is refused before a byte is read, with an
``OSError`` whose ``strerror`` says what it is ("is a FIFO (pipe), not a file"), so every reader's own
``except OSError`` words the error as for any unreadable file. A folder raises ``IsADirectoryError`` as
``open`` does.
"""
from __future__ import annotations

import errno
import os
import stat
from pathlib import Path
from typing import IO

#: (test on st_mode, what the file is)
_KINDS = ((stat.S_ISFIFO, "a FIFO (pipe)"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


class NotARegularFile(OSError):
    """An input that is not a regular file (FIFO, device, socket); ``strerror`` says what it is."""


def _check(mode: int, path) -> None:
    if stat.S_ISDIR(mode):
        raise IsADirectoryError(errno.EISDIR, os.strerror(errno.EISDIR), str(path))
    if not stat.S_ISREG(mode):
        what = next((name for test, name in _KINDS if test(mode)), "not a regular file")
        raise NotARegularFile(errno.EINVAL, f"is {what}, not a file", str(path))


def check_input(path: str | Path) -> None:
    """``OSError`` unless ``path`` is a regular file (following links): FileNotFoundError, a loop of
    symbolic links (ELOOP), IsADirectoryError or ``NotARegularFile``."""
    _check(os.stat(path).st_mode, path)


def open_input(path: str | Path, mode: str = "rb", encoding: str | None = None) -> IO:
    """``open(path, mode)`` for reading a regular file; ``OSError`` as ``check_input`` otherwise (the open
    itself never blocks: a FIFO is opened non-blocking and refused)."""
    if "r" not in mode or any(c in mode for c in "wax+"):
        raise ValueError(f"open_input reads: mode {mode!r}")
    check_input(path)  # a socket cannot be opened at all: say what it is
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    try:
        _check(os.fstat(fd).st_mode, path)  # the file opened is the file checked
        os.set_blocking(fd, True)
        return os.fdopen(fd, mode, encoding=encoding) if "b" not in mode else os.fdopen(fd, mode)
    except BaseException:
        os.close(fd)
        raise


def read_bytes(path: str | Path) -> bytes:
    """The bytes of a regular file (``Path.read_bytes`` for inputs)."""
    with open_input(path, "rb") as f:
        return f.read()


def read_text(path: str | Path, encoding: str | None = None) -> str:
    """The text of a regular file (``Path.read_text`` for inputs: universal newlines, UnicodeDecodeError)."""
    with open_input(path, "r", encoding=encoding) as f:
        return f.read()
