"""The adapter side of the slcan (Lawicel / CANable ASCII) protocol on a pseudo-terminal.

A USB-CAN adapter speaking slcan appears to the host as a serial port; python-can's ``slcan``
interface talks to it with CR-terminated ASCII commands (``S8`` bitrate 1 Mbit/s, ``O`` open,
``C`` close, ``tIIILDD..`` transmit a standard frame, ``TIIIIIIIILDD..`` an extended one,
``r``/``R`` remote frames) and reads received frames in the same notation. ``SlcanAdapterBus``
is that adapter for a simulated bus: a python-can ``BusABC`` whose "wire" is the master side of
a new pseudo-terminal (``port`` is the path the host opens). Commands are answered with CR (OK)
or BEL (error), as the Lawicel firmware does; frames are forwarded only while the channel is
open; malformed lines are answered with BEL and counted, never raised.
"""
from __future__ import annotations

import os
import select
import threading
import time
import tty

import can

OK = b"\r"
ERROR = b"\a"
BITRATES = {"S0": 10_000, "S1": 20_000, "S2": 50_000, "S3": 100_000, "S4": 125_000, "S5": 250_000,
            "S6": 500_000, "S7": 750_000, "S8": 1_000_000, "S9": 83_300}


def parse_frame(line: str) -> can.Message | None:
    """A ``t``/``T``/``r``/``R`` line as a message; None if malformed."""
    try:
        kind = line[0]
        ext = kind in "TR"
        n_id = 8 if ext else 3
        can_id = int(line[1:1 + n_id], 16)
        dlc = int(line[1 + n_id], 10)
        if dlc > 8 or can_id > (0x1FFFFFFF if ext else 0x7FF):
            return None
        data = b""
        if kind in "tT":
            hexdata = line[2 + n_id:]
            if len(hexdata) != 2 * dlc:
                return None
            data = bytes.fromhex(hexdata)
        elif len(line) != 2 + n_id:
            return None
        return can.Message(arbitration_id=can_id, is_extended_id=ext, is_remote_frame=kind in "rR", dlc=dlc,
                           data=data, timestamp=time.time())
    except (ValueError, IndexError):
        return None


def format_frame(msg: can.Message) -> bytes:
    if msg.is_extended_id:
        head = f"{'R' if msg.is_remote_frame else 'T'}{msg.arbitration_id:08X}{msg.dlc:d}"
    else:
        head = f"{'r' if msg.is_remote_frame else 't'}{msg.arbitration_id:03X}{msg.dlc:d}"
    body = "" if msg.is_remote_frame else bytes(msg.data).hex().upper()
    return (head + body).encode("ascii") + OK


class SlcanAdapterBus(can.BusABC):
    """An emulated slcan USB-CAN adapter on a new pseudo-terminal (``port``)."""

    def __init__(self, channel=None, **kwargs):
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # keep the slave open and raw: no echo, no CR/LF translation
        os.set_blocking(self._master, False)
        self.port = os.ttyname(self._slave)
        self._buf = bytearray()
        self._wlock = threading.Lock()
        self.is_open = False
        self.bitrate: int | None = None
        self.malformed = 0
        self.overruns = 0
        self.is_cut = False  # bus off: no frame carried either way (``cut()``)
        self._closed = False
        super().__init__(channel=self.port, **kwargs)
        self.channel_info = f"emulated slcan adapter on {self.port}"

    def _write(self, data: bytes) -> None:
        with self._wlock:
            if self._closed:
                return
            try:
                os.write(self._master, data)
            except (BlockingIOError, OSError):
                self.overruns += 1  # host not reading: the adapter drops, as its buffer would overflow

    def _handle(self, line: bytes) -> can.Message | None:
        text = line.decode("ascii", errors="replace")
        if not text:
            return None
        c = text[0]
        if c in "tTrR":
            msg = parse_frame(text)
            if msg is None:
                self.malformed += 1
                self._write(ERROR)
                return None
            return msg if self.is_open and not self.is_cut else None
        if c in "OL" and len(text) == 1:
            self.is_open = True
        elif c == "C" and len(text) == 1:
            self.is_open = False
        elif text in BITRATES:
            self.bitrate = BITRATES[text]
        elif c == "V":
            self._write(b"V1013\r")
            return None
        elif c == "N":
            self._write(b"NOTBT\r")
            return None
        elif c == "F":
            self._write(b"F00\r")
            return None
        else:
            self.malformed += 1
            self._write(ERROR)
            return None
        self._write(OK)
        return None

    def _recv_internal(self, timeout):
        end = None if timeout is None else time.monotonic() + timeout
        while not self._closed:
            while True:
                cut = min((i for i in (self._buf.find(b"\r"), self._buf.find(b"\n")) if i >= 0), default=-1)
                if cut < 0:
                    break
                line = bytes(self._buf[:cut])
                del self._buf[:cut + 1]
                msg = self._handle(line)
                if msg is not None:
                    return msg, False
            remaining = None if end is None else max(0.0, end - time.monotonic())
            try:
                ready, _, _ = select.select([self._master], [], [], remaining)
            except (OSError, ValueError):
                return None, False
            if not ready:
                return None, False
            try:
                chunk = os.read(self._master, 4096)
            except BlockingIOError:
                continue
            except OSError:  # no host has the port open
                time.sleep(0.01)
                chunk = b""
            self._buf += chunk
            if len(self._buf) > 65536:  # garbage without line ends
                self.malformed += 1
                self._buf.clear()
        return None, False

    def cut(self) -> None:
        """The bus stops carrying frames (bus off, connector pulled): nothing is forwarded either way."""
        self.is_cut = True

    def send(self, msg: can.Message, timeout=None) -> None:
        if self.is_open and not self.is_cut:
            self._write(format_frame(msg))

    def shutdown(self) -> None:
        if self._closed:
            return
        super().shutdown()
        with self._wlock:
            self._closed = True
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass
