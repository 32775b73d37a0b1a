"""A CiA 402 torque drive written from CiA 301 / CiA 402 on raw python-can frames, for testing the
master (``drivers.robot.CanopenRobot``) against a device this project's simulator did not build.

It shares no code with ``sim/canopen_slaves.py`` (nor with ``canopen`` or ``drivers``): its own
object dictionary (a table below), SDO expedited server, NMT slave with heartbeat producer, PDO
mapping in the CiA 301 order, synchronous RPDO/TPDO handling on SYNC, EMCY producer, heartbeat
consumer (0x1016), SYNC monitoring (0x1006), RPDO deadline (0x1400:05 event timer), abort connection
option 0x6007 (default 1, fault), quick stop option 0x605A (1-4: the stop, then SWITCH ON DISABLED at
the next SYNC; 5-8: stay in QUICK STOP ACTIVE, where "enable operation" re-enables: transition 16)
and the CiA 402 state machine driven by the controlword.

Everything a test judges is the drive's own record: ``log`` (wall time, SYNC count, event, detail),
``transitions`` (time, SYNC count, old state, new state, cause), ``received_cw`` (SYNC count, the
controlword applied, state before), ``emcy_sent`` (time, code). Misbehaviours a test can switch on:
``silent``, ``ignore_quick_stop``, ``quick_stop_delay`` (SYNCs), ``own_quick_stop()``,
``inject_fault(code)``, ``reject_mapping`` (objects it refuses to map: SDO abort 0x06040041),
``absent`` (indices its dictionary lacks: SDO abort 0x06020000).
"""
from __future__ import annotations

import struct
import threading
import time

import can

# CiA 301 SDO abort codes
ABORT_TOGGLE = 0x05030000
ABORT_COMMAND = 0x05040001
ABORT_READ_ONLY = 0x06010002
ABORT_WRITE_ONLY = 0x06010001
ABORT_NO_OBJECT = 0x06020000
ABORT_CANNOT_MAP = 0x06040041
ABORT_LENGTH = 0x06070010
ABORT_NO_SUB = 0x06090011
ABORT_RANGE = 0x06090030
ABORT_STATE = 0x08000022

# NMT states as a heartbeat reports them (CiA 301 §7.2.8.3.2)
BOOT, STOPPED, OPERATIONAL, PRE_OPERATIONAL = 0x00, 0x04, 0x05, 0x7F

# CiA 402 statusword patterns (bits 0-3, 5, 6) of each state, plus bit 4 "voltage enabled"
STATUS = {"NOT READY TO SWITCH ON": 0x0000, "SWITCH ON DISABLED": 0x0040, "READY TO SWITCH ON": 0x0031,
          "SWITCHED ON": 0x0033, "OPERATION ENABLED": 0x0037, "QUICK STOP ACTIVE": 0x0017,
          "FAULT REACTION ACTIVE": 0x001F, "FAULT": 0x0008}
REMOTE = 0x0200

FORMATS = {"u8": "<B", "u16": "<H", "u32": "<I", "i8": "<b", "i16": "<h", "i32": "<i"}


def dictionary() -> dict:
    """(index, sub) -> [type, access, value]: the objects this drive has (CiA 301 / 402 numbering)."""
    od = {(0x1000, 0): ["u32", "ro", 0x00020192], (0x1001, 0): ["u8", "ro", 0],
          (0x1005, 0): ["u32", "rw", 0x80], (0x1006, 0): ["u32", "rw", 0], (0x1014, 0): ["u32", "rw", 0x80],
          (0x1016, 0): ["u8", "ro", 1], (0x1016, 1): ["u32", "rw", 0], (0x1017, 0): ["u16", "rw", 0],
          (0x1018, 0): ["u8", "ro", 4], (0x1018, 1): ["u32", "ro", 0x4F54], (0x1018, 2): ["u32", "ro", 402],
          (0x1018, 3): ["u32", "ro", 1], (0x1018, 4): ["u32", "ro", 7],
          (0x6007, 0): ["i16", "rw", 1], (0x603F, 0): ["u16", "ro", 0], (0x6040, 0): ["u16", "rw", 0],
          (0x6041, 0): ["u16", "ro", 0x0040], (0x605A, 0): ["i16", "rw", 6], (0x6060, 0): ["i8", "rw", 0],
          (0x6061, 0): ["i8", "ro", 0], (0x6064, 0): ["i32", "ro", 0], (0x606C, 0): ["i32", "ro", 0],
          (0x6071, 0): ["i16", "rw", 0], (0x6072, 0): ["u16", "rw", 3000], (0x6076, 0): ["u32", "rw", 2000],
          (0x6077, 0): ["i16", "ro", 0], (0x6087, 0): ["u32", "rw", 0], (0x608F, 0): ["u8", "ro", 2],
          (0x608F, 1): ["u32", "rw", 4096], (0x608F, 2): ["u32", "rw", 1], (0x60C2, 0): ["u8", "ro", 2],
          (0x60C2, 1): ["u8", "rw", 10], (0x60C2, 2): ["i8", "rw", -3], (0x6502, 0): ["u32", "ro", 0x208],
          (0x1003, 0): ["u8", "rw", 0]}
    for k in range(1, 5):
        od[(0x1003, k)] = ["u32", "ro", 0]
    for k in range(4):  # 4 RPDOs, 4 TPDOs, 8 entries each
        od[(0x1400 + k, 0)] = ["u8", "ro", 5]
        od[(0x1400 + k, 1)] = ["u32", "rw", (0x200 + 0x100 * k) | (0 if k == 0 else 0x80000000)]
        od[(0x1400 + k, 2)] = ["u8", "rw", 1 if k == 0 else 255]
        od[(0x1400 + k, 5)] = ["u16", "rw", 0]
        od[(0x1800 + k, 0)] = ["u8", "ro", 6]
        od[(0x1800 + k, 1)] = ["u32", "rw", (0x180 + 0x100 * k) | (0 if k < 2 else 0x80000000)]
        od[(0x1800 + k, 2)] = ["u8", "rw", 1 if k == 0 else 254]
        od[(0x1800 + k, 3)] = ["u16", "rw", 0]
        od[(0x1800 + k, 5)] = ["u16", "rw", 0]
        od[(0x1800 + k, 6)] = ["u8", "rw", 0]
        for base in (0x1600, 0x1A00):
            od[(base + k, 0)] = ["u8", "rw", 0]
            for s in range(1, 9):
                od[(base + k, s)] = ["u32", "rw", 0]
    od[(0x1600, 0)][2], od[(0x1600, 1)][2], od[(0x1600, 2)][2] = 2, 0x60400010, 0x60710010
    od[(0x1A00, 0)][2], od[(0x1A00, 1)][2], od[(0x1A00, 2)][2] = 2, 0x60410010, 0x60640020
    return od


# objects a PDO may carry (CiA 402 mapping attributes)
RX_MAPPABLE = {0x6040, 0x6060, 0x6071}
TX_MAPPABLE = {0x6041, 0x6061, 0x6064, 0x606C, 0x6077, 0x603F}


class IndependentDrive:
    """One drive, node ``node_id``, on python-can's virtual ``channel``; ``start()`` powers it on."""

    def __init__(self, node_id: int, channel: str, absent=(), reject_mapping=()):
        self.node_id = node_id
        self.bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        self.absent = set(absent)
        self.reject_mapping = set(reject_mapping)
        self.lock = threading.RLock()
        self.od = {k: v for k, v in dictionary().items() if k[0] not in self.absent}
        self._defaults = {k: list(v) for k, v in self.od.items()}
        self.nmt = BOOT
        self.state = "SWITCH ON DISABLED"
        self.syncs = 0
        self.log: list[tuple[float, int, str, str]] = []
        self.transitions: list[tuple[float, int, str, str, str]] = []
        self.received_cw: list[tuple[int, int, str]] = []
        self.emcy_sent: list[tuple[float, int]] = []
        self.master_heartbeats: list[float] = []
        self.sync_times: list[float] = []
        self.late_checks: list[tuple[float, float]] = []  # (wall time, gap s) of watchdog checks > 10 ms apart
        self.silent = False
        self.ignore_quick_stop = False
        self.quick_stop_delay = 0  # SYNCs a quick stop word is ignored before it acts
        self._qs_seen = 0
        self._qs_syncs = 0
        self._pending: dict[int, bytes] = {}
        self._tx_count: dict[int, int] = {}
        self._last_sync: float | None = None
        self._last_rpdo: float | None = None
        self._master_seen: float | None = None
        self._tripped: set[str] = set()
        self._last_cw = 0
        self._pos = 0.0  # motor counts
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []

    # -- object dictionary ---------------------------------------------------------------------------
    def get(self, index: int, sub: int = 0):
        return self.od[(index, sub)][2]

    def _set(self, index: int, sub: int, value) -> None:
        self.od[(index, sub)][2] = value

    # -- life ----------------------------------------------------------------------------------------
    def start(self) -> "IndependentDrive":
        for target, name in ((self._receive, "rx"), (self._timers, "timers")):
            t = threading.Thread(target=target, name=f"indep-{self.node_id}-{name}", daemon=True)
            t.start()
            self._threads.append(t)
        self._boot()
        return self

    def close(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=1.0)
        self.bus.shutdown()

    def _send(self, can_id: int, data: bytes) -> None:
        if self.silent:
            return
        try:
            self.bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))
        except can.CanError:
            pass

    def _note(self, event: str, detail: str = "") -> None:
        self.log.append((time.monotonic(), self.syncs, event, detail))

    def _boot(self) -> None:
        with self.lock:
            self.nmt = BOOT
            self._send(0x700 + self.node_id, bytes([BOOT]))
            self.nmt = PRE_OPERATIONAL
            self._hb_due = time.monotonic()
            self._note("boot")

    # -- frames --------------------------------------------------------------------------------------
    def _receive(self) -> None:
        while not self._stop.is_set():
            msg = self.bus.recv(timeout=0.05)
            if msg is None or self.silent or msg.is_extended_id:
                continue
            cid, data = msg.arbitration_id, bytes(msg.data)
            try:
                if cid == 0x000:
                    self._on_nmt(data)
                elif cid == self.get(0x1005) & 0x7FF:
                    self._on_sync()
                elif cid == 0x600 + self.node_id:
                    self._on_sdo(data)
                elif cid >= 0x700 and cid == 0x700 + ((self.get(0x1016, 1) >> 16) & 0x7F):
                    self._master_seen = time.monotonic()
                    self.master_heartbeats.append(self._master_seen)
                    self._tripped.discard("heartbeat")
                else:
                    self._on_rpdo(cid, data)
            except Exception as exc:  # noqa: BLE001 - a drive keeps running; the test reads the log
                self._note("error", f"{type(exc).__name__}: {exc}")

    def _on_nmt(self, data: bytes) -> None:
        if len(data) != 2 or data[1] not in (0, self.node_id):
            return
        cmd = data[0]
        with self.lock:
            self._note("nmt", f"0x{cmd:02X}")
            leaving = self.nmt == OPERATIONAL and cmd in (0x02, 0x80, 0x81, 0x82)
            if leaving and self.state == "OPERATION ENABLED":
                self._abort_connection(None, "left NMT OPERATIONAL")
            if cmd == 0x01:
                self.nmt = OPERATIONAL
            elif cmd == 0x02:
                self.nmt = STOPPED
            elif cmd == 0x80:
                self.nmt = PRE_OPERATIONAL
            elif cmd in (0x81, 0x82):
                for key, v in self._defaults.items():
                    if key[0] < 0x2000 or cmd == 0x81:
                        self.od[key] = list(v)
                if cmd == 0x81:
                    self._go("SWITCH ON DISABLED", "reset node")
                self._pending.clear()
                self._tx_count.clear()
                self._last_sync = self._last_rpdo = self._master_seen = None
                self._tripped.clear()
                self._boot()

    # SDO server: expedited transfers (every object here fits 4 bytes)
    def _on_sdo(self, data: bytes) -> None:
        if len(data) != 8:
            return
        ccs = data[0] >> 5
        index, sub = struct.unpack_from("<HB", data, 1)
        with self.lock:
            if self.nmt == STOPPED:
                return  # no SDO in STOPPED (CiA 301)
            if ccs == 2:  # initiate upload
                code = self._check(index, sub, write=False)
                if code:
                    return self._sdo_abort(index, sub, code)
                typ, _, value = self.od[(index, sub)]
                raw = struct.pack(FORMATS[typ], value)
                n = len(raw)
                self._send(0x580 + self.node_id, bytes([0x43 | ((4 - n) << 2)]) + data[1:4] + raw.ljust(4, b"\0"))
            elif ccs == 1:  # initiate download
                if not data[0] & 0x02:
                    return self._sdo_abort(index, sub, ABORT_COMMAND)  # segmented: not needed here
                n = 4 - ((data[0] >> 2) & 0x3) if data[0] & 0x01 else 4
                code = self._check(index, sub, write=True)
                if code:
                    return self._sdo_abort(index, sub, code)
                typ = self.od[(index, sub)][0]
                size = struct.calcsize(FORMATS[typ])
                if n != size:
                    return self._sdo_abort(index, sub, ABORT_LENGTH)
                (value,) = struct.unpack(FORMATS[typ], data[4:4 + size])
                code = self._write(index, sub, value)
                if code:
                    return self._sdo_abort(index, sub, code)
                self._send(0x580 + self.node_id, bytes([0x60]) + data[1:4] + bytes(4))
            else:
                self._sdo_abort(index, sub, ABORT_COMMAND)

    def _check(self, index: int, sub: int, write: bool) -> int:
        if not any(k[0] == index for k in self.od):
            return ABORT_NO_OBJECT
        if (index, sub) not in self.od:
            return ABORT_NO_SUB
        if write and self.od[(index, sub)][1] != "rw":
            return ABORT_READ_ONLY
        return 0

    def _sdo_abort(self, index: int, sub: int, code: int) -> None:
        self._note("sdo abort", f"0x{index:04X}:{sub:02X} 0x{code:08X}")
        self._send(0x580 + self.node_id, bytes([0x80]) + struct.pack("<HBI", index, sub, code))

    def _write(self, index: int, sub: int, value) -> int:
        """Apply an SDO write; an abort code where the value is refused (CiA 301 mapping rules)."""
        if 0x1600 <= index <= 0x1603 or 0x1A00 <= index <= 0x1A03:
            comm = (0x1400 if index < 0x1A00 else 0x1800) + (index & 0xFF)
            if not self.get(comm, 1) & 0x80000000:
                return ABORT_STATE  # mapping only while the PDO is invalid
            mappable = RX_MAPPABLE if index < 0x1A00 else TX_MAPPABLE
            if sub == 0:
                entries = [self.get(index, s) for s in range(1, value + 1)] if value <= 8 else None
                if entries is None:
                    return ABORT_RANGE
                if sum(e & 0xFF for e in entries) > 64:
                    return ABORT_LENGTH
            elif self.get(index, 0) != 0:
                return ABORT_STATE  # entries only while the count is 0
            elif value and ((value >> 16) not in mappable or (value >> 16) in self.reject_mapping):
                return ABORT_CANNOT_MAP
        if index == 0x6060 and value not in (0, 4, 10):
            return ABORT_RANGE
        if index == 0x6060 and value and not self.get(0x6502) & (1 << (value - 1)):
            return ABORT_RANGE
        self._set(index, sub, value)
        if index == 0x6060:
            self._set(0x6061, 0, value)
        if index == 0x6040:
            self._controlword(value)
        if index == 0x1016:
            self._master_seen = None
        return 0

    # -- PDOs ----------------------------------------------------------------------------------------
    def _map(self, map_index: int) -> list[tuple[int, int, int]]:
        return [(v >> 16, (v >> 8) & 0xFF, v & 0xFF) for v in
                (self.get(map_index, s) for s in range(1, self.get(map_index, 0) + 1)) if v >> 16]

    def _on_rpdo(self, cid: int, data: bytes) -> None:
        with self.lock:
            if self.nmt != OPERATIONAL:
                return
            for k in range(4):
                cob = self.get(0x1400 + k, 1)
                if cob & 0x80000000 or cob & 0x7FF != cid:
                    continue
                entries = self._map(0x1600 + k)
                if len(data) != sum(b for _, _, b in entries) // 8:
                    self._emcy(0x8210)
                    return
                self._last_rpdo = time.monotonic()
                self._tripped.discard("rpdo")
                if self.get(0x1400 + k, 2) <= 240:
                    self._pending[k] = data  # synchronous: applied at the next SYNC
                else:
                    self._apply_rpdo(k, data)

    def _apply_rpdo(self, k: int, data: bytes) -> None:
        off = 0
        for index, sub, bits in self._map(0x1600 + k):
            typ = self.od[(index, sub)][0]
            (value,) = struct.unpack_from(FORMATS[typ], data, off)
            off += bits // 8
            if index == 0x6040:
                self.received_cw.append((self.syncs, value, self.state))
                self._set(index, sub, value)
                self._controlword(value)
            else:
                self._write(index, sub, value)

    def _on_sync(self) -> None:
        with self.lock:
            self._last_sync = time.monotonic()
            self.sync_times.append(self._last_sync)
            self._tripped.discard("sync")
            if self.nmt != OPERATIONAL:
                return
            self.syncs += 1
            for k in sorted(self._pending):
                self._apply_rpdo(k, self._pending[k])
            self._pending.clear()
            if self.state == "QUICK STOP ACTIVE":  # the stop takes one SYNC, then transition 12 (1-4)
                self._qs_syncs += 1
                if self._qs_syncs > 1 and 1 <= self.get(0x605A) <= 4:
                    self._go("SWITCH ON DISABLED", "quick stop done (0x605A 1-4)")
            torque = 0
            if self.state == "OPERATION ENABLED" and self.get(0x6061) in (4, 10):
                limit = self.get(0x6072)
                torque = max(-limit, min(limit, self.get(0x6071)))
            self._set(0x6077, 0, torque)
            speed = torque * 4  # counts/s of a light, damped motor
            self._set(0x606C, 0, speed)
            self._pos += speed * 0.01
            self._set(0x6064, 0, (int(self._pos) + 2 ** 31) % 2 ** 32 - 2 ** 31)
            self._status()
            for k in range(4):
                cob = self.get(0x1800 + k, 1)
                tt = self.get(0x1800 + k, 2)
                if cob & 0x80000000 or not 1 <= tt <= 240:
                    continue
                self._tx_count[k] = self._tx_count.get(k, 0) + 1
                if self._tx_count[k] % tt:
                    continue
                frame = b"".join(struct.pack(FORMATS[self.od[(i, s)][0]], self.get(i, s))
                                 for i, s, _ in self._map(0x1A00 + k))
                self._send(cob & 0x7FF, frame)

    # -- CiA 402 -------------------------------------------------------------------------------------
    def _status(self) -> None:
        self._set(0x6041, 0, STATUS[self.state] | REMOTE)

    def _go(self, state: str, cause: str) -> None:
        if state != self.state:
            self.transitions.append((time.monotonic(), self.syncs, self.state, state, cause))
            if state == "QUICK STOP ACTIVE":
                self._qs_syncs = 0
            self.state = state
            self._status()

    def _controlword(self, cw: int) -> None:
        s = self.state
        reset_edge = cw & 0x80 and not self._last_cw & 0x80
        self._last_cw = cw
        cause = f"controlword 0x{cw:04X}"
        if s == "FAULT":
            if reset_edge:
                self._set(0x603F, 0, 0)
                self._set(0x1001, 0, 0)
                self._go("SWITCH ON DISABLED", cause)  # transition 15
            return
        if s == "FAULT REACTION ACTIVE" or cw & 0x80:
            return
        if not cw & 0x02:  # disable voltage: 7, 9, 10, 12
            if s in ("READY TO SWITCH ON", "SWITCHED ON", "OPERATION ENABLED", "QUICK STOP ACTIVE"):
                self._go("SWITCH ON DISABLED", cause)
        elif not cw & 0x04:  # quick stop: 7, 10, 11
            if s in ("READY TO SWITCH ON", "SWITCHED ON"):
                self._go("SWITCH ON DISABLED", cause)
            elif s == "OPERATION ENABLED" and not self.ignore_quick_stop:
                self._qs_seen += 1
                if self._qs_seen > self.quick_stop_delay:
                    self._go("SWITCH ON DISABLED" if self.get(0x605A) == 0 else "QUICK STOP ACTIVE", cause)
        elif not cw & 0x01:  # shutdown: 2, 6, 8
            if s in ("SWITCH ON DISABLED", "SWITCHED ON", "OPERATION ENABLED"):
                self._go("READY TO SWITCH ON", cause)
        elif not cw & 0x08:  # switch on (3) / disable operation (5)
            if s in ("READY TO SWITCH ON", "OPERATION ENABLED"):
                self._go("SWITCHED ON", cause)
        else:  # switch on + enable operation: 3 + 4, 4, and 16 only with 0x605A 5-8
            if s == "READY TO SWITCH ON":
                self._go("SWITCHED ON", cause)
                self._go("OPERATION ENABLED", cause)
            elif s == "SWITCHED ON":
                self._go("OPERATION ENABLED", cause)
            elif s == "QUICK STOP ACTIVE" and 5 <= self.get(0x605A) <= 8:
                self._go("OPERATION ENABLED", cause + " (transition 16)")
        if cw & 0x04:  # any word but quick stop ends a delayed quick stop's count
            self._qs_seen = 0

    def _emcy(self, code: int) -> None:
        reg = 0x01 | (0x10 if code >> 12 == 8 else 0)
        self._set(0x1001, 0, reg)
        self._send(0x080 + self.node_id, struct.pack("<HB5x", code, reg))
        self.emcy_sent.append((time.monotonic(), code))
        self._note("emcy", f"0x{code:04X}")

    def _abort_connection(self, code: int | None, why: str) -> None:
        """The master is lost: EMCY ``code`` (None: none) and the abort connection option 0x6007."""
        option = self.get(0x6007) if (0x6007, 0) in self.od else 1  # CiA 402 default: fault
        self._note("abort connection", f"{why}: 0x6007 = {option}")
        if code is not None:
            self._emcy(code)
        if self.state not in ("OPERATION ENABLED", "QUICK STOP ACTIVE"):
            return
        if option == 1:
            self._fault(code or 0x8100, emcy=False)
        elif option == 2:
            self._go("SWITCH ON DISABLED", why)
        elif option == 3 and self.state == "OPERATION ENABLED":
            self._go("QUICK STOP ACTIVE", why)

    def _fault(self, code: int, emcy: bool = True) -> None:
        self._go("FAULT REACTION ACTIVE", f"fault 0x{code:04X}")
        self._set(0x603F, 0, code)
        if emcy:
            self._emcy(code)
        self._go("FAULT", f"fault 0x{code:04X}")

    # -- drive-side watchdogs and heartbeat producer ------------------------------------------------------
    def _timers(self) -> None:
        self._hb_due = prev = time.monotonic()
        while not self._stop.wait(0.002):
            now = time.monotonic()
            if now - prev > 0.01:  # this thread was held up (a loaded machine): its watchdogs were late
                self.late_checks.append((now, now - prev))
            prev = now
            with self.lock:
                hb = self.get(0x1017) / 1000.0
                if hb and now >= self._hb_due and self.nmt != BOOT:
                    self._send(0x700 + self.node_id, bytes([self.nmt]))
                    self._hb_due = now + hb
                entry = self.get(0x1016, 1)
                consumer = (entry & 0xFFFF) / 1000.0
                if consumer and (entry >> 16) & 0x7F and self._master_seen is not None \
                        and "heartbeat" not in self._tripped and now - self._master_seen > consumer:
                    self._tripped.add("heartbeat")  # CiA 301 heartbeat event, in any NMT state
                    self._abort_connection(0x8130, f"master heartbeat lost for {now - self._master_seen:.4f} s")
                if self.state != "OPERATION ENABLED" or self.nmt != OPERATIONAL:
                    continue
                cycle = self.get(0x1006) * 1e-6
                if cycle and self._last_sync is not None and "sync" not in self._tripped \
                        and now - self._last_sync > 1.5 * cycle:
                    self._tripped.add("sync")
                    self._abort_connection(0x8100, f"SYNC lost for {now - self._last_sync:.4f} s")
                deadline = min((self.get(0x1400 + k, 5) / 1000.0 for k in range(4)
                                if not self.get(0x1400 + k, 1) & 0x80000000 and self.get(0x1400 + k, 5)),
                               default=0.0)
                if deadline and self._last_rpdo is not None and "rpdo" not in self._tripped \
                        and now - self._last_rpdo > deadline:
                    self._tripped.add("rpdo")
                    self._abort_connection(0x8250, f"no RPDO for {now - self._last_rpdo:.4f} s")

    # -- test hooks ------------------------------------------------------------------------------------
    def own_quick_stop(self, emcy: int | None = None) -> None:
        """The drive stops by itself (a local reason: a safety input, its own limit)."""
        with self.lock:
            if emcy is not None:
                self._emcy(emcy)
            self._go("QUICK STOP ACTIVE", "own quick stop")

    def inject_fault(self, code: int) -> None:
        with self.lock:
            self._fault(code)

    def enabled_after(self, t: float) -> bool:
        """Whether the drive entered OPERATION ENABLED after wall time ``t``."""
        return any(tt > t and new == "OPERATION ENABLED" for tt, _, _, new, _ in self.transitions)

    def left_enabled_at(self, after: float) -> float | None:
        """Wall time the drive left OPERATION ENABLED after ``after`` (None: it did not)."""
        for tt, _, old, _, _ in self.transitions:
            if tt >= after and old == "OPERATION ENABLED":
                return tt
        return None
