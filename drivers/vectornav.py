"""VectorNav ASCII serial protocol: framing, checksums and sentence decoding (pure, no I/O).

The protocol, as documented in the VectorNav VN-100 User Manual (UM001, firmware v2.1,
rev 2.22) and the VectorNav C library headers (``vndevice.h``):

* A sentence is ``$`` + header (``VN`` + three letters) + ``,``-separated fields + ``*`` +
  checksum + ``\\r\\n``, e.g. ``$VNRRG,5,9600*65`` (UM001 §5.1.1).
* Checksum (UM001 §3.8.2): 8-bit XOR of every byte between, not including, ``$`` and ``*``
  (commas included), written as two hex digits. Optionally a 16-bit CRC16-CCITT written as
  four hex digits (UM001 §3.8, Checksum / CRC; Communication Protocol Control register, SerialChecksum=2).
  Checksum bypass (UM001 §3.8.1): ``XX`` (or ``XXXX``) in place of the digits means
  "unchecked", e.g. ``$VNRRG,1*XX``; it is accepted and counted as ``unchecked``.
* Register commands (UM001 §5.1.1-5.1.2): ``$VNRRG,<id>`` reads, ``$VNWRG,<id>,<values>``
  writes; the device answers with the same header, the register id and the register's
  values. Errors come back as ``$VNERR,<code>`` (codes in :data:`DEVICE_ERRORS`).
* Register 6, Async Data Output Type (ADOR, UM001 §5.2.7; example ``$VNWRG,06,0*6C``),
  selects the asynchronous sentence: 0 off, 14 ``VNYMR``, 19 ``VNIMU`` (``VNASYNC_VNYMR 14``,
  ``VNASYNC_VNIMU 19`` in ``vndevice.h``).
* Register 7, Async Data Output Frequency (ADOF, UM001 §5.2.8): 1, 2, 4, 5, 10, 20, 25, 40,
  50, 100 or 200 Hz.
* ``$VNYMR`` (register 27, UM001 §7.2.3): yaw, pitch, roll (deg), mag x,y,z (Gauss), accel
  x,y,z (m/s^2), gyro x,y,z (rad/s) -- compensated values.
* ``$VNIMU`` (ADOR 19, "Calibrated Inertial Measurements"): mag x,y,z (Gauss), accel x,y,z
  (m/s^2), gyro x,y,z (rad/s) -- uncompensated -- then temperature (deg C) and pressure (kPa);
  the field order of ``VnUartPacket_parseVNIMU`` in VectorNav's programming library and of
  the VNIMU table (MagX..GyroZ, Temp, Pressure) in VectorNav's register documentation.

All vectors are in the sensor frame (the sensor's own x, y, z axes).

:class:`SentenceParser` is incremental: feed it bytes as they arrive, in chunks of any
size; it resynchronizes on the next ``$`` after garbage, and counts what it rejects.
"""
from __future__ import annotations

import binascii
import math
from dataclasses import asdict, dataclass, field

#: Register ids (UM001 §5.2).
REG_MODEL = 1
REG_ASYNC_TYPE = 6  # ADOR
REG_ASYNC_FREQ = 7  # ADOF

#: ADOR values for the asynchronous outputs this project decodes (VNASYNC_* in vndevice.h).
ASYNC_OUTPUT_TYPES = {"VNOFF": 0, "VNYMR": 14, "VNIMU": 19}
#: Allowed ADOF values, Hz (UM001 §5.2.8).
ASYNC_RATES_HZ = (1, 2, 4, 5, 10, 20, 25, 40, 50, 100, 200)
#: Serial baud rates the VN-100 supports (UM001, Serial Baud Rate register, id 5).
BAUD_RATES = (9600, 19200, 38400, 57600, 115200, 128000, 230400, 460800, 921600)

#: Number of fields after the header, per decoded sentence type.
FIELD_COUNTS = {"VNIMU": 11, "VNYMR": 12}

#: System error codes of ``$VNERR`` (UM001, System Error Codes; SENSORERROR in VectorNav's vnenum.h).
DEVICE_ERRORS = {
    1: "hard fault",
    2: "serial buffer overflow",
    3: "invalid checksum",
    4: "invalid command",
    5: "not enough parameters",
    6: "too many parameters",
    7: "invalid parameter",
    8: "invalid register",
    9: "unauthorized access",
    10: "watchdog reset",
    11: "output buffer overflow",
    12: "insufficient baud rate",
    255: "error buffer overflow",
}

#: A sentence longer than this without a line end is dropped (VN_MAX_RESPONSE_SIZE is 256).
MAX_SENTENCE_BYTES = 256

_START = 0x24  # '$'
_NL = 0x0A
_WHITESPACE = b"\r\n"


class ProtocolError(ValueError):
    """A sentence or command that does not follow the VectorNav ASCII protocol."""


def checksum8(payload: bytes) -> int:
    """8-bit XOR of ``payload`` (the bytes between ``$`` and ``*``), UM001 §3.8.2."""
    x = int.from_bytes(payload, "little")
    width = len(payload)
    while width > 1:  # fold the integer onto itself: XOR of its halves, log2(n) steps
        half = (width + 1) // 2
        x = (x & ((1 << (8 * half)) - 1)) ^ (x >> (8 * half))
        width = half
    return x


def crc16(payload: bytes) -> int:
    """CRC16-CCITT (polynomial 0x1021, initial value 0) of ``payload`` (UM001 §3.8, the 16-bit CRC)."""
    return binascii.crc_hqx(payload, 0)


def frame(body: str | bytes, check: str = "checksum") -> bytes:
    """One sentence ``$<body>*<check>\\r\\n``; ``check`` is ``checksum`` (8-bit XOR),
    ``crc`` (16-bit) or ``unchecked`` (``XX``, the protocol's checksum bypass)."""
    b = body.encode("ascii") if isinstance(body, str) else bytes(body)
    if check == "checksum":
        tail = b"%02X" % checksum8(b)
    elif check == "crc":
        tail = b"%04X" % crc16(b)
    elif check == "unchecked":
        tail = b"XX"
    else:
        raise ValueError(f"check must be 'checksum', 'crc' or 'unchecked', got {check!r}")
    return b"$" + b + b"*" + tail + b"\r\n"


def write_register_command(register: int, *values, check: str = "checksum") -> bytes:
    """``$VNWRG,<id>,<values>*CS`` (UM001 §5.1.2); the id is written with two digits."""
    return frame(",".join([f"VNWRG,{register:02d}", *map(str, values)]), check)


def read_register_command(register: int, check: str = "checksum") -> bytes:
    """``$VNRRG,<id>*CS`` (UM001 §5.1.1)."""
    return frame(f"VNRRG,{register:02d}", check)


@dataclass(frozen=True, slots=True)
class Sentence:
    """A well-framed sentence whose checksum passed (or was bypassed with ``XX``).

    ``header`` e.g. ``VNWRG``; ``fields`` the comma-separated fields after it (text);
    ``checked`` False for ``*XX``; ``offset`` byte position of its ``$`` in the stream.
    """

    header: str
    fields: tuple[str, ...]
    checked: bool
    offset: int


@dataclass(frozen=True, slots=True)
class ImuRecord:
    """A decoded ``$VNIMU`` or ``$VNYMR`` sentence, sensor frame, the units VectorNav documents.

    accel m/s^2, gyro rad/s, mag Gauss (x, y, z); temperature deg C and pressure kPa (VNIMU
    only, else None); ypr = (yaw, pitch, roll) deg (VNYMR only, else None).
    """

    kind: str
    accel: tuple[float, float, float]
    gyro: tuple[float, float, float]
    mag: tuple[float, float, float]
    temperature: float | None
    pressure: float | None
    ypr: tuple[float, float, float] | None
    checked: bool
    offset: int

    def to_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}


@dataclass
class ParserStats:
    """What the parser has seen so far (counts).

    good: sentences accepted (checksum passed or bypassed); records: of these, decoded
    VNIMU/VNYMR; unchecked: accepted with ``*XX``; bad_checksum: wrong checksum or a
    checksum field that is not 2/4 hex digits; truncated: sentences cut short (a new ``$``
    or the line end before ``*`` + digits, or the stream ended); malformed: checksum fine
    but fields wrong (count, numbers, header); garbage_bytes: bytes outside any sentence,
    skipped (line ends between sentences are not garbage); device_errors: ``$VNERR``.
    """

    good: int = 0
    records: int = 0
    unchecked: int = 0
    bad_checksum: int = 0
    truncated: int = 0
    malformed: int = 0
    garbage_bytes: int = 0
    device_errors: int = 0
    bytes_total: int = 0
    last_error: str | None = field(default=None, compare=False)

    def to_dict(self) -> dict:
        return asdict(self)


def _floats(fields: tuple[str, ...] | list[str]) -> list[float]:
    out = [float(f) for f in fields]
    for v in out:
        if not math.isfinite(v):
            raise ValueError("non-finite value")
    return out


def decode_imu(sentence: Sentence) -> ImuRecord:
    """Decode a ``VNIMU``/``VNYMR`` sentence; :class:`ProtocolError` on wrong fields."""
    kind = sentence.header
    n = FIELD_COUNTS.get(kind)
    if n is None:
        raise ProtocolError(f"{kind}: not an IMU sentence (decoded: {', '.join(FIELD_COUNTS)})")
    if len(sentence.fields) != n:
        raise ProtocolError(f"{kind}: expected {n} fields, got {len(sentence.fields)}")
    try:
        v = _floats(sentence.fields)
    except ValueError:
        raise ProtocolError(f"{kind}: a field is not a finite number: {','.join(sentence.fields)}") from None
    if kind == "VNIMU":
        return ImuRecord(kind, (v[3], v[4], v[5]), (v[6], v[7], v[8]), (v[0], v[1], v[2]),
                         v[9], v[10], None, sentence.checked, sentence.offset)
    return ImuRecord(kind, (v[6], v[7], v[8]), (v[9], v[10], v[11]), (v[3], v[4], v[5]),
                     None, None, (v[0], v[1], v[2]), sentence.checked, sentence.offset)


def format_imu(kind: str, accel, gyro, mag=(0.0, 0.0, 0.0), temperature: float = 25.0,
               pressure: float = 101.325, ypr=(0.0, 0.0, 0.0)) -> str:
    """Sentence body (without ``$`` and checksum) in the device's fixed-point layout.

    Resolution as the device prints it: accel 1e-3 m/s^2, gyro 1e-6 rad/s, mag 1e-4 Gauss,
    temperature 0.1 deg C, pressure 1e-3 kPa, angles 1e-3 deg.
    """
    a = ",".join(f"{float(x) + 0.0:+07.3f}" for x in accel)  # + 0.0: no "-0.000"
    g = ",".join(f"{float(x) + 0.0:+09.6f}" for x in gyro)
    m = ",".join(f"{float(x) + 0.0:+07.4f}" for x in mag)
    if kind == "VNIMU":
        return f"VNIMU,{m},{a},{g},{temperature:+05.1f},{pressure:+08.3f}"
    if kind == "VNYMR":
        y = ",".join(f"{float(x) + 0.0:+08.3f}" for x in ypr)
        return f"VNYMR,{y},{m},{a},{g}"
    raise ValueError(f"output type must be one of {', '.join(FIELD_COUNTS)}, got {kind!r}")


class SentenceParser:
    """Incremental framer/decoder for a VectorNav ASCII byte stream.

    ``feed(data)`` returns, in stream order, :class:`ImuRecord` for decoded VNIMU/VNYMR
    sentences and :class:`Sentence` for every other accepted sentence (register replies,
    ``VNERR``, other async types). Rejected input is counted in :attr:`stats`.
    """

    def __init__(self, max_sentence: int = MAX_SENTENCE_BYTES):
        self.stats = ParserStats()
        self._buf = b""
        self._base = 0  # stream offset of _buf[0]
        self._max = int(max_sentence)

    def _garbage(self, chunk: bytes) -> None:
        n = len(chunk) - chunk.count(b"\r") - chunk.count(b"\n")
        if n:
            self.stats.garbage_bytes += n

    def _reject(self, kind: str, msg: str) -> None:
        setattr(self.stats, kind, getattr(self.stats, kind) + 1)
        self.stats.last_error = msg

    def feed(self, data: bytes) -> list:
        """Consume ``data``; return the sentences completed by it (see class doc)."""
        self.stats.bytes_total += len(data)
        buf = self._buf + bytes(data) if self._buf else bytes(data)
        base = self._base
        out: list = []
        pos = 0
        n = len(buf)
        while pos < n:
            start = buf.find(b"$", pos)
            if start < 0:
                self._garbage(buf[pos:])
                pos = n
                break
            if start > pos:
                self._garbage(buf[pos:start])
            nl = buf.find(b"\n", start + 1)
            nxt = buf.find(b"$", start + 1, nl if nl >= 0 else n)
            if nxt >= 0:  # a new sentence starts before this one ended
                self._reject("truncated", f"sentence at byte {base + start} cut short by a new '$'")
                pos = nxt
                continue
            if nl < 0:
                if n - start > self._max:
                    self._reject("truncated", f"no line end within {self._max} bytes at byte {base + start}")
                    pos = n  # drop it (no '$' follows in the buffer); resync on the next '$'
                    break
                pos = start  # incomplete: keep for the next chunk
                break
            end = nl - 1 if nl > start and buf[nl - 1] == 0x0D else nl
            item = self._sentence(buf[start + 1:end], base + start)
            if item is not None:
                out.append(item)
            pos = nl + 1
        self._buf = buf[pos:]
        self._base = base + pos
        return out

    def finish(self) -> None:
        """End of stream: a pending incomplete sentence counts as truncated."""
        if self._buf:
            if self._buf.startswith(b"$"):
                self._reject("truncated", f"stream ended inside the sentence at byte {self._base}")
            else:
                self._garbage(self._buf)
            self._base += len(self._buf)
            self._buf = b""

    def _sentence(self, line: bytes, offset: int):
        star = line.rfind(b"*")
        if star < 0:
            self._reject("truncated", f"sentence at byte {offset} has no '*checksum'")
            return None
        body, tail = line[:star], line[star + 1:]
        if len(tail) < 2:
            self._reject("truncated", f"sentence at byte {offset} ends inside its checksum")
            return None
        checked = True
        if tail == b"XX" or tail == b"XXXX":
            checked = False
        elif len(tail) == 2 or len(tail) == 4:
            try:
                got = int(tail, 16)
            except ValueError:
                self._reject("bad_checksum", f"sentence at byte {offset}: checksum {tail!r} is not hex")
                return None
            want = checksum8(body) if len(tail) == 2 else crc16(body)
            if got != want:
                self._reject("bad_checksum", f"sentence at byte {offset}: checksum {tail.decode('ascii', 'replace')}"
                                             f", computed {want:0{len(tail)}X}")
                return None
        else:
            self._reject("bad_checksum", f"sentence at byte {offset}: checksum field {tail!r} is not 2 or 4 hex digits")
            return None
        try:
            text = body.decode("ascii")
        except UnicodeDecodeError:
            self._reject("malformed", f"sentence at byte {offset} is not ASCII")
            return None
        parts = text.split(",")
        header = parts[0]
        if len(header) != 5 or not header.startswith("VN") or not (header.isalpha() and header.isupper()):
            self._reject("malformed", f"sentence at byte {offset}: header {header!r} is not VN + 3 letters")
            return None
        s = Sentence(header, tuple(parts[1:]), checked, offset)
        if header in FIELD_COUNTS:
            try:
                rec = decode_imu(s)
            except ProtocolError as exc:
                self._reject("malformed", f"sentence at byte {offset}: {exc}")
                return None
            self.stats.good += 1
            self.stats.records += 1
            if not checked:
                self.stats.unchecked += 1
            return rec
        self.stats.good += 1
        if not checked:
            self.stats.unchecked += 1
        if header == "VNERR":
            self.stats.device_errors += 1
        return s


def device_error_text(sentence: Sentence) -> str:
    """Human text for a ``$VNERR,<code>`` sentence (code may be hex-looking, e.g. ``0C``)."""
    code_text = sentence.fields[0] if sentence.fields else "?"
    code = None
    for base in (10, 16):
        try:
            code = int(code_text, base)
            break
        except ValueError:
            continue
    meaning = DEVICE_ERRORS.get(code, "unknown error") if code is not None else "unreadable code"
    return f"VNERR {code_text} ({meaning})"


def parse_bytes(data: bytes) -> tuple[list, ParserStats]:
    """Decode a complete captured stream: (items in order, stats); the tail counts as truncated."""
    p = SentenceParser()
    items = p.feed(data)
    p.finish()
    return items, p.stats
