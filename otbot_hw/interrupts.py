"""Ctrl-C between compiled calls: ``deferred_sigint`` holds SIGINT while a numba function runs and raises
``KeyboardInterrupt`` at the next ``check()``.

A KeyboardInterrupt raised by Python's own handler while numba's dispatcher is between Python and compiled
code surfaced as ``SystemError: CPUDispatcher(...) returned a result with an exception set`` (exit 1 with a
traceback, seen interrupting ``otbot simulate`` of 10^7 samples in its sensor stage). Long batch work that
runs in chunks (``simulation.simulator.simulate``, ``sensors.measure``) calls ``check()`` after each chunk
instead, so an interrupt ends it within one chunk as a plain KeyboardInterrupt (``otbot``: exit 130).
"""
from __future__ import annotations

import contextlib
import signal
import threading
from typing import Iterator


class PendingInterrupt:
    """Whether SIGINT arrived inside ``deferred_sigint``; ``check()`` raises KeyboardInterrupt if so."""

    def __init__(self) -> None:
        self.arrived = False

    def check(self) -> None:
        if self.arrived:
            self.arrived = False
            raise KeyboardInterrupt


@contextlib.contextmanager
def deferred_sigint() -> Iterator[PendingInterrupt]:
    """Within the block SIGINT only marks the returned ``PendingInterrupt`` (checked by the caller between
    compiled calls; an unchecked one is raised when the block ends). A no-op outside the main thread or when
    someone else handles SIGINT (their handler stays)."""
    pending = PendingInterrupt()
    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield pending
        return

    def handler(signum, frame):
        pending.arrived = True

    signal.signal(signal.SIGINT, handler)
    try:
        yield pending
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    pending.check()
