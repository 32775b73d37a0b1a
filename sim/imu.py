"""Simulated VectorNav IMU on a pseudo-terminal.

:class:`SimulatedIMU` opens a pty pair; the driver (:class:`drivers.imu.VectorNavIMU`)
opens ``sim.port`` (the slave path) with pyserial exactly as it would open
``/dev/ttyUSB0``. The simulator:

* writes one ``$VNIMU``/``$VNYMR`` sentence per :meth:`SimulatedIMU.publish` call, with a
  correct 8-bit checksum, in the device's fixed-point format (sensor frame);
* answers ``$VNWRG``/``$VNRRG`` on register 6 (output type) and 7 (output rate) like the
  device -- the reply echoes the register and its value with a checksum -- and register 1
  (model) for reads; anything else gets ``$VNERR,<code>`` (see ``drivers.vectornav``);
* injects faults for tests: garbage bytes, a bad checksum, a truncated sentence, silence,
  a ``$VNERR`` system error, a closed port.

Who decides *when* to publish is the caller (the plant publishes once per IMU period of
``rate_hz``, in lockstep with its simulation; :meth:`SimulatedIMU.publish_at` does the
decimation). Values are sensor-frame: a plant with
platform-frame values uses :meth:`publish_platform`, which applies ``R^T`` of the mounting.
Noise is the caller's business too (``otbot_hw.sensors.measure`` adds it).
"""
from __future__ import annotations

import os
import select
import threading
import tty

import numpy as np

from drivers import vectornav as vn

#: Register 1 (model number) answer of the simulator.
MODEL = "VN-100-SIM"
_SAFE_GARBAGE = bytes(b for b in range(256) if b not in (0x24, 0x0A, 0x0D))  # no '$', CR, LF


class SimulatedIMU:
    """VectorNav-like sensor behind a pty; ``port`` is the path the driver opens.

    output: initial async output (VNIMU, VNYMR or VNOFF); rate_hz: initial register 7
    (Hz); mounting: rotation sensor -> platform B'' used
    by :meth:`publish_platform`; mag (Gauss), temperature (deg C), pressure (kPa): the
    constant extra fields written into the sentences.
    """

    def __init__(self, output: str = "VNIMU", rate_hz: int = 40, mounting: np.ndarray | None = None,
                 mag=(0.21, 0.0, 0.42), temperature: float = 25.0, pressure: float = 101.325,
                 max_backlog: int = 65536):
        if output not in vn.ASYNC_OUTPUT_TYPES:
            raise ValueError(f"output must be one of {', '.join(vn.ASYNC_OUTPUT_TYPES)}, got {output!r}")
        if rate_hz not in vn.ASYNC_RATES_HZ:
            raise ValueError(f"rate_hz must be one of {vn.ASYNC_RATES_HZ}, got {rate_hz!r}")
        from drivers.imu_config import check_rotation

        self.mounting = np.eye(3) if mounting is None else check_rotation(mounting)
        self.ador = vn.ASYNC_OUTPUT_TYPES[output]
        self.rate_hz = int(rate_hz)
        self.mag = tuple(float(v) for v in mag)
        self.temperature = float(temperature)
        self.pressure = float(pressure)
        self.silent = False
        self.sent = 0  # sentences published
        self.dropped = 0  # sentences dropped because nobody read the port
        self.commands: list[str] = []  # commands received (text, without '$' and checksum)
        self._last_tick: int | None = None  # output period of the last publish_at()
        self._max_backlog = int(max_backlog)
        self._pending = bytearray()
        self._lock = threading.Lock()
        self._parser = vn.SentenceParser()
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.port = os.ttyname(self._slave)
        self._wake_r, self._wake_w = os.pipe()
        self._closed = False
        self._thread = threading.Thread(target=self._serve, name="SimulatedIMU", daemon=True)
        self._thread.start()

    # -- state ----------------------------------------------------------------------------
    @property
    def output(self) -> str | None:
        """Header of the current async output, None when off."""
        for name, code in vn.ASYNC_OUTPUT_TYPES.items():
            if code == self.ador and code != 0:
                return name
        return None

    @property
    def closed(self) -> bool:
        return self._closed

    # -- outputs --------------------------------------------------------------------------
    def sentence(self, accel_sensor, gyro_sensor, ypr=(0.0, 0.0, 0.0)) -> bytes:
        """The bytes :meth:`publish` would write for these sensor-frame values."""
        kind = self.output
        if kind is None:
            return b""
        a, g = np.asarray(accel_sensor, float), np.asarray(gyro_sensor, float)
        if a.shape != (3,) or g.shape != (3,):
            raise ValueError(f"accel and gyro must have shape (3,), got {a.shape} and {g.shape}")
        if not (np.all(np.isfinite(a)) and np.all(np.isfinite(g))):
            raise ValueError(f"accel and gyro must be finite, got {a} and {g}")
        return vn.frame(vn.format_imu(kind, a, g, self.mag, self.temperature, self.pressure, ypr))

    def publish(self, accel_sensor, gyro_sensor, corrupt: str | None = None, ypr=(0.0, 0.0, 0.0)) -> bytes:
        """Write one sentence of the configured type (nothing when off or silent).

        accel_sensor: specific force (3,) m/s^2 and gyro_sensor: rate (3,) rad/s, both in
        the sensor frame; ypr (deg) for VNYMR (the simulator runs no attitude filter).
        corrupt: None, ``checksum`` (wrong checksum digits) or ``truncate`` (the sentence is
        cut after half its bytes, as when bytes are lost on the line). Returns the bytes
        written.
        """
        if self.silent:
            return b""
        data = self.sentence(accel_sensor, gyro_sensor, ypr)
        if not data:
            return b""
        if corrupt == "checksum":
            star = data.rindex(b"*")
            good = int(data[star + 1:star + 3], 16)
            data = data[:star + 1] + b"%02X" % (good ^ 0x5A) + b"\r\n"
        elif corrupt == "truncate":
            data = data[: len(data) // 2]
        elif corrupt is not None:
            raise ValueError(f"corrupt must be None, 'checksum' or 'truncate', got {corrupt!r}")
        if self._send(data):
            self.sent += 1
            return data
        return b""

    def publish_platform(self, accel_platform, gyro_platform, **kw) -> bytes:
        """:meth:`publish` for platform-frame (B'') values: rotates them by ``R^T``."""
        r = self.mounting
        return self.publish(r.T @ np.asarray(accel_platform, float), r.T @ np.asarray(gyro_platform, float), **kw)

    def publish_at(self, t: float, accel_platform, gyro_platform, **kw) -> bytes:
        """Lockstep helper for a plant stepping faster than the output rate: publish
        platform-frame values when simulated time ``t`` (s) enters a new output period
        of ``rate_hz`` (t = 0, 1/rate, 2/rate, ...), otherwise write nothing."""
        tick = int(np.floor(t * self.rate_hz + 1e-9))
        if self._last_tick is not None and tick <= self._last_tick:
            return b""
        self._last_tick = tick
        return self.publish_platform(accel_platform, gyro_platform, **kw)

    def report_error(self, code: int) -> bytes:
        """An asynchronous ``$VNERR,<code>`` sentence, as the device sends on a system error while
        streaming (e.g. 12: insufficient baud rate); returns the bytes written."""
        data = vn.frame(f"VNERR,{int(code):02d}")
        self._send(data)
        return data

    def write_garbage(self, data: bytes | int, seed: int = 0) -> bytes:
        """Write raw bytes onto the line: ``data`` itself, or that many random bytes that
        contain no ``$``, CR or LF (so they cannot start or end a sentence)."""
        if isinstance(data, int):
            rng = np.random.default_rng(seed)
            data = bytes(_SAFE_GARBAGE[i] for i in rng.integers(0, len(_SAFE_GARBAGE), data))
        self._send(bytes(data))
        return bytes(data)

    # -- transport ------------------------------------------------------------------------
    def _send(self, data: bytes) -> bool:
        with self._lock:
            if self._closed:
                return False
            if len(self._pending) + len(data) > self._max_backlog:
                self.dropped += 1
                return False
            self._pending += data
            self._flush_locked()
        return True

    def _flush_locked(self) -> None:
        while self._pending:
            try:
                n = os.write(self._master, self._pending)
            except BlockingIOError:
                return
            except OSError:
                self._pending.clear()
                return
            del self._pending[:n]

    def _serve(self) -> None:
        """Background thread: answer commands, flush pending output."""
        while True:
            with self._lock:
                if self._closed:
                    return
                master = self._master
                if self._pending:
                    self._flush_locked()
                waiting = bool(self._pending)
            try:
                ready, _, _ = select.select([master, self._wake_r], [], [], 0.002 if waiting else 0.5)
            except (OSError, ValueError):
                return
            if self._wake_r in ready:
                return
            if master in ready:
                try:
                    data = os.read(master, 4096)
                except BlockingIOError:
                    continue
                except OSError:
                    continue
                if data:
                    self._handle(data)

    def _handle(self, data: bytes) -> None:
        bad_before = self._parser.stats.bad_checksum
        items = self._parser.feed(data)
        if self.silent:
            return
        for _ in range(self._parser.stats.bad_checksum - bad_before):
            self._error(3)
        for item in items:
            if isinstance(item, vn.ImuRecord):
                self._error(4)  # an output sentence is not a command
                continue
            self.commands.append(",".join((item.header, *item.fields)))
            if item.header == "VNWRG":
                self._write_register(item.fields)
            elif item.header == "VNRRG":
                self._read_register(item.fields)
            else:
                self._error(4)

    def _error(self, code: int) -> None:
        self._send(vn.frame(f"VNERR,{code:02d}"))

    def _write_register(self, fields) -> None:
        if len(fields) < 2:
            return self._error(5)
        reg = _to_int(fields[0])
        if reg is None:
            return self._error(7)
        if reg not in (vn.REG_ASYNC_TYPE, vn.REG_ASYNC_FREQ):
            return self._error(8 if reg != vn.REG_MODEL else 9)
        if len(fields) > 3:  # register value + optional serial-port parameter
            return self._error(6)
        value = _to_int(fields[1])
        if reg == vn.REG_ASYNC_TYPE:
            if value not in vn.ASYNC_OUTPUT_TYPES.values():
                return self._error(7)
            self.ador = value
        else:
            if value not in vn.ASYNC_RATES_HZ:
                return self._error(7)
            self.rate_hz = value
        self._send(vn.frame(",".join(["VNWRG", f"{reg:02d}", str(value), *fields[2:]])))

    def _read_register(self, fields) -> None:
        if len(fields) < 1:
            return self._error(5)
        if len(fields) > 1:
            return self._error(6)
        reg = _to_int(fields[0])
        values = {vn.REG_MODEL: MODEL, vn.REG_ASYNC_TYPE: str(self.ador), vn.REG_ASYNC_FREQ: str(self.rate_hz)}
        if reg not in values:
            return self._error(8)
        self._send(vn.frame(f"VNRRG,{reg:02d},{values[reg]}"))

    # -- lifecycle ------------------------------------------------------------------------
    def disconnect(self) -> None:
        """Pull the cable: close the pty so the driver's port fails (same as :meth:`close`)."""
        self.close()

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            try:
                os.write(self._wake_w, b"x")
            except OSError:
                pass
        self._thread.join(timeout=2.0)
        for fd in (self._master, self._slave, self._wake_r, self._wake_w):
            try:
                os.close(fd)
            except OSError:
                pass

    def __enter__(self) -> "SimulatedIMU":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _to_int(text: str) -> int | None:
    try:
        return int(text)
    except ValueError:
        return None
