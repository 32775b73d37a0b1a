"""python-can's ``slcan`` interface, reading the serial port in chunks.

python-can's ``slcanBus`` reads its serial port one byte per ``read(1)`` call (a ``select`` and a
``read`` system call per byte, plus Python around them): the seven TPDOs of one control cycle
(140 bytes of slcan text) cost 0.71 ms of CPU (1.1 ms of wall time) on the receiving thread, most
of what an slcan adapter cost the loop; read in chunks, 0.04 ms (``docs/performance.md``).
``ChunkedSlcanBus`` is the same interface (commands, opening, frame parsing, sending: all
python-can's) with ``_read`` taking whatever the port holds at once and cutting it at the slcan
line ends (CR, or BEL for an error), and waiting for more with one ``select`` on the port.
``CanopenRobot`` uses it for ``bus.interface: slcan``.
"""
from __future__ import annotations

import select
import time

from can.interfaces.slcan import slcanBus
from can.exceptions import CanOperationError


class ChunkedSlcanBus(slcanBus):
    """``can.interfaces.slcan.slcanBus`` whose reads take every waiting byte in one call."""

    _ENDS = (ord("\r"), ord("\a"))

    def _line(self) -> str | None:
        buf = self._buffer
        for i, b in enumerate(buf):
            if b in self._ENDS:  # the line with its end, as python-can's reader returns it
                line = buf[:i + 1].decode(errors="replace")
                del buf[:i + 1]
                return line
        return None

    def _read(self, timeout: float | None) -> str | None:
        line = self._line()
        if line is not None:
            return line
        port = self.serialPortOrig
        end = None if timeout is None else time.monotonic() + timeout
        try:
            while True:
                n = port.in_waiting
                if n:
                    self._buffer.extend(port.read(n))
                    line = self._line()
                    if line is not None:
                        return line
                    continue
                left = None if end is None else end - time.monotonic()
                if left is not None and left <= 0:
                    return None
                select.select([port.fileno()], [], [], left)
        except (OSError, ValueError, TypeError) as exc:  # port closed or gone
            raise CanOperationError(f"Could not read from serial device: {exc}") from exc
