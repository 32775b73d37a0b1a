"""Serial IMU driver: a VectorNav sensor speaking its ASCII protocol over pyserial.

Frames: the sensor reports specific force (m/s^2) and angular rate (rad/s) in its own
sensor frame S; the driver rotates both into the platform frame B'' with the mounting
rotation ``R`` (3x3, sensor -> platform: ``v_B'' = R @ v_S``; its columns are the sensor
axes written in B''). Times are host ``time.monotonic()`` seconds at reception.

The protocol itself (framing, checksums, sentence layouts, register numbers) lives in
:mod:`drivers.vectornav`, which cites the VectorNav documentation; the configuration
(``imu`` section of ``config/robot.yaml``) and its checks in :mod:`drivers.imu_config`.
"""
from __future__ import annotations

import dataclasses
import numbers
import select
import time
from dataclasses import dataclass

import numpy as np

from drivers import vectornav as vn
from drivers.imu_config import ImuConfig, check_bandwidth, check_output, check_rotation


class ImuFault(RuntimeError):
    """The IMU stopped delivering valid data, refused a command, or its port failed."""


@dataclass(frozen=True)
class ImuSample:
    """One IMU measurement in the platform frame B''.

    t: host monotonic time of reception (s); accel: specific force (3,) m/s^2;
    gyro: angular rate (3,) rad/s.
    """

    t: float
    accel: np.ndarray
    gyro: np.ndarray


class VectorNavIMU:
    """VectorNav IMU on a serial port (pyserial), ASCII asynchronous output.

    ``open()`` the port, ``configure()`` the output, then ``read()`` the latest sample.
    ``timeout`` (s) is the stream watchdog: no valid IMU sentence for that long is a fault.
    No background thread: bytes are read and parsed inside ``read()``/``configure()``;
    use one instance from one thread. ``latest`` keeps the last sample returned.
    """

    def __init__(self, port: str, baudrate: int = 115200, mounting: np.ndarray | None = None,
                 timeout: float = 0.5):
        if isinstance(baudrate, bool) or not isinstance(baudrate, numbers.Integral) or baudrate not in vn.BAUD_RATES:
            raise ValueError(f"baudrate must be one of {', '.join(map(str, vn.BAUD_RATES))}, got {baudrate!r}")
        if not (isinstance(timeout, (int, float)) and np.isfinite(timeout) and timeout > 0):
            raise ValueError(f"timeout must be a number of seconds > 0, got {timeout!r}")
        self.port = str(port)
        self.baudrate = int(baudrate)
        self.mounting = np.eye(3) if mounting is None else check_rotation(mounting)
        self.timeout = float(timeout)
        self.output: str | None = None
        self.rate_hz: int | None = None
        self.latest: ImuSample | None = None
        self._serial = None
        self._parser = vn.SentenceParser()
        self._replies: list[vn.Sentence] = []
        self._last_valid = 0.0
        self._in_command = False

    @classmethod
    def from_config(cls, cfg: "ImuConfig", port: str | None = None) -> "VectorNavIMU":
        """Driver for an :class:`ImuConfig` (``port`` overrides the configured one)."""
        return cls(port or cfg.port, cfg.baudrate, cfg.mounting, cfg.timeout)

    # -- port ---------------------------------------------------------------------------
    def open(self) -> None:
        """Open the serial port (8N1, no flow control). ImuFault when it cannot be opened."""
        import serial

        if self._serial is not None:
            return
        try:
            self._serial = serial.Serial(self.port, self.baudrate, timeout=0, write_timeout=self.timeout,
                                         exclusive=True)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise ImuFault(f"IMU port {self.port}: cannot open: {exc}") from None
        self._parser = vn.SentenceParser()
        self._replies.clear()
        self._last_valid = time.monotonic()

    def close(self) -> None:
        """Close the port (safe to call twice)."""
        if self._serial is not None:
            try:
                self._serial.close()
            finally:
                self._serial = None

    def __enter__(self) -> "VectorNavIMU":
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def is_open(self) -> bool:
        return self._serial is not None

    @property
    def stats(self) -> vn.ParserStats:
        """Snapshot of the parser's counts: good, bad_checksum, truncated, garbage_bytes, ..."""
        return dataclasses.replace(self._parser.stats)

    # -- I/O helpers --------------------------------------------------------------------
    def _port(self):
        if self._serial is None:
            raise ImuFault(f"IMU port {self.port} is not open")
        return self._serial

    def _drain(self) -> ImuSample | None:
        """Read everything the port holds (non-blocking); newest new sample or None."""
        import serial

        ser = self._port()
        newest = None  # (reception time, record)
        while True:
            try:
                data = ser.read(4096)
            except (serial.SerialException, OSError) as exc:
                self.close()
                raise ImuFault(f"IMU port {self.port} failed (disconnected?): {exc}") from None
            if not data:
                break
            now = time.monotonic()
            for item in self._parser.feed(data):
                if isinstance(item, vn.ImuRecord):
                    newest = (now, item)
                elif item.header == "VNERR" and not self._in_command:
                    # The device reports a system error while streaming: a fault, with its meaning.
                    raise ImuFault(f"IMU on {self.port} reported {vn.device_error_text(item)}")
                elif item.header in ("VNWRG", "VNRRG", "VNERR"):
                    self._replies.append(item)
        if newest is None:
            return None
        t, rec = newest
        self._last_valid = t
        self.latest = ImuSample(t, self.mounting @ np.array(rec.accel), self.mounting @ np.array(rec.gyro))
        return self.latest

    def _wait_readable(self, seconds: float) -> None:
        ser = self._port()
        fd = ser.fileno() if hasattr(ser, "fileno") else None
        if fd is None:  # pragma: no cover - non-posix ports
            time.sleep(min(seconds, 0.001))
            return
        try:
            select.select([fd], [], [], max(seconds, 0.0))
        except (OSError, ValueError) as exc:
            self.close()
            raise ImuFault(f"IMU port {self.port} failed: {exc}") from None

    def _write(self, data: bytes) -> None:
        import serial

        try:
            self._port().write(data)
        except (serial.SerialException, serial.SerialTimeoutException, OSError) as exc:
            self.close()
            raise ImuFault(f"IMU port {self.port}: write failed: {exc}") from None

    # -- measurements -------------------------------------------------------------------
    def restart_watchdog(self, t: float) -> None:
        """Count the stream watchdog from ``t`` (s, ``time.monotonic``) if that is later than the
        last valid sentence: for a source that only publishes when the master steps it (the
        simulated IMU in lockstep), silence between steps is not a dead stream."""
        self._last_valid = max(self._last_valid, float(t))

    def read(self, timeout: float | None = None) -> ImuSample | None:
        """Latest complete sample received since the previous call, in B''.

        Waits up to ``timeout`` s (None: the watchdog ``self.timeout``; 0: just poll) for a
        new sample. Returns None when none arrived but the stream is still healthy; raises
        :class:`ImuFault` once no valid IMU sentence has arrived for ``self.timeout`` s, and
        when the port fails (e.g. the device is disconnected).
        """
        wait = self.timeout if timeout is None else float(timeout)
        start = time.monotonic()
        while True:
            sample = self._drain()
            if sample is not None:
                return sample
            now = time.monotonic()
            fault_at = self._last_valid + self.timeout
            if now >= fault_at:
                s = self._parser.stats
                raise ImuFault(f"IMU on {self.port}: no valid IMU sentence for {now - self._last_valid:.3f} s "
                               f"(timeout {self.timeout:g} s; {s.bad_checksum} bad checksums, {s.truncated} "
                               f"truncated, {s.garbage_bytes} garbage bytes so far)")
            end = min(start + wait, fault_at)
            if now >= end:
                return None
            self._wait_readable(end - now)

    # -- registers ----------------------------------------------------------------------
    def _command(self, command: bytes, header: str, register: int) -> vn.Sentence:
        """Send a register command and wait (``self.timeout``) for its reply."""
        self._in_command = True
        try:
            return self._command_reply(command, header, register)
        finally:
            self._in_command = False

    def _command_reply(self, command: bytes, header: str, register: int) -> vn.Sentence:
        self._drain()
        self._replies.clear()
        self._write(command)
        text = command.decode("ascii").strip()
        deadline = time.monotonic() + self.timeout
        while True:
            self._drain()
            for reply in self._replies:
                if reply.header == "VNERR":
                    raise ImuFault(f"IMU rejected {text}: {vn.device_error_text(reply)}")
                if reply.header == header and reply.fields and _int(reply.fields[0]) == register:
                    self._replies.clear()
                    return reply
            now = time.monotonic()
            if now >= deadline:
                raise ImuFault(f"IMU on {self.port}: no reply to {text} within {self.timeout:g} s")
            self._wait_readable(deadline - now)

    def write_register(self, register: int, *values) -> tuple[str, ...]:
        """``$VNWRG`` and verify the echoed values; returns them. ImuFault on mismatch/error."""
        reply = self._command(vn.write_register_command(register, *values), "VNWRG", register)
        sent = [str(v) for v in values]
        if not _same_values(reply.fields[1:], sent):
            raise ImuFault(f"IMU register {register}: wrote {','.join(sent)}, device echoed {','.join(reply.fields[1:])}")
        return reply.fields[1:]

    def read_register(self, register: int) -> tuple[str, ...]:
        """``$VNRRG``: the register's values as text fields."""
        return self._command(vn.read_register_command(register), "VNRRG", register).fields[1:]

    def configure(self, output: str = "VNIMU", rate_hz: float = 100) -> None:
        """Select the asynchronous output (register 6) and its frequency (register 7).

        ``output``: VNIMU (uncompensated IMU + temperature, pressure) or VNYMR (attitude +
        compensated IMU); ``rate_hz`` one of 1, 2, 4, 5, 10, 20, 25, 40, 50, 100, 200.
        ValueError for values the device or the line cannot take; ImuFault when the device
        does not confirm.
        """
        rate = check_output(output, rate_hz)
        check_bandwidth(output, rate, self.baudrate)
        self.write_register(vn.REG_ASYNC_TYPE, vn.ASYNC_OUTPUT_TYPES[output])
        self.write_register(vn.REG_ASYNC_FREQ, rate)
        self.output, self.rate_hz = output, rate
        self._last_valid = time.monotonic()


def _int(text: str) -> int | None:
    try:
        return int(text)
    except ValueError:
        return None


def _same_values(got, sent) -> bool:
    if len(got) != len(sent):
        return False
    for g, s in zip(got, sent):
        try:
            if float(g) != float(s):
                return False
        except ValueError:
            if g.strip() != s.strip():
                return False
    return True
