"""What every CANopen device driver here shares: boot (NMT reset, wait for the boot-up
message), SDO access with errors naming the object, PDO mapping through canopen's ``PdoMap``,
validated TPDO reception, and EMCY messages turned into ``Fault`` s.

``CycleTracker`` lets the master wait, after each SYNC, until every expected TPDO has arrived.
"""
from __future__ import annotations

import logging
import threading
import time
from typing import Callable, Iterable

import canopen
from canopen.emcy import EmcyError
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from drivers.faults import DriverError, error_meaning
from otbot_hw.robot import Fault

log = logging.getLogger(__name__)

NMT_RESET_COMMUNICATION = 0x82


class CycleTracker:
    """Which (node, TPDO number) pairs have arrived since the last SYNC; thread-safe."""

    def __init__(self):
        self._cond = threading.Condition()
        self._missing: set = set()
        self._active = False

    def begin(self, expected: Iterable) -> None:
        with self._cond:
            self._missing = set(expected)
            self._active = True

    def arrived(self, key) -> None:
        with self._cond:
            if self._active and key in self._missing:
                self._missing.discard(key)
                if not self._missing:
                    self._cond.notify_all()

    def wait(self, timeout: float) -> set:
        """Block until all expected TPDOs arrived or ``timeout`` s passed; return the missing ones."""
        with self._cond:
            self._cond.wait_for(lambda: not self._missing, timeout)
            self._active = False
            return set(self._missing)


def pdo_get(var):
    """Value of a mapped variable from its PDO's last data (canopen's decoding, minus the
    per-access debug strings ``Variable.raw`` builds)."""
    return var.od.decode_raw(var.get_data())


def pdo_put(var, value) -> None:
    """Write ``value`` into the PDO's data at the variable's place (byte-aligned fast path)."""
    if var.offset % 8 or var.length % 8:
        var.raw = value
        return
    data = var.od.encode_raw(value)
    off = var.offset // 8
    var.pdo_parent.data[off:off + len(data)] = data


def pdo_bytes(pdo_map) -> int:
    """Length in bytes of a mapped PDO."""
    return (pdo_map.length + 7) // 8


class CanopenDevice:
    """A CANopen slave seen from the master: ``name`` (joint or device), node ID, EDS path.

    ``on_fault(fault)`` is called (from the receiving thread) for every EMCY error; ``tracker``
    is told about every valid TPDO.
    """

    node_class = canopen.RemoteNode

    def __init__(self, network: canopen.Network, name: str, node_id: int, eds, tracker: CycleTracker,
                 on_fault: Callable[[Fault], None]):
        self.name = name
        self.network = network
        self.node = self.node_class(node_id, str(eds))
        network.add_node(self.node)
        self.tracker = tracker
        self.on_fault = on_fault
        self.malformed = 0  # ignored frames from this node (wrong length)
        self._bootup = threading.Event()
        network.subscribe(0x700 + node_id, self._on_heartbeat_frame)
        # Length checks run before canopen's own handlers (which raise on short frames; the
        # network's listener logs and drops those).
        network.subscribers.setdefault(0x80 + node_id, []).insert(0, self._check_emcy_length)
        self.node.emcy.add_callback(self._on_emcy)
        self.tpdos: list[int] = []  # numbers of the TPDOs this driver mapped (expected on every SYNC)

    @property
    def node_id(self) -> int:
        return self.node.id

    # -- boot ------------------------------------------------------------------------------------
    def _on_heartbeat_frame(self, can_id: int, data: bytes, timestamp: float) -> None:
        if len(data) == 1 and data[0] & 0x7F == 0:
            self._bootup.set()

    def reset_and_wait_bootup(self, timeout: float) -> None:
        """NMT reset communication, then wait up to ``timeout`` s for the boot-up message."""
        self._bootup.clear()
        self.node.nmt.send_command(NMT_RESET_COMMUNICATION)
        if not self._bootup.wait(timeout):
            f = Fault(self.name, self.node_id, "boot",
                      f"no boot-up message within {timeout:g} s after NMT reset communication "
                      f"(node powered, wired, node ID {self.node_id}, bitrate?)")
            raise DriverError(str(f), (f,))
        # The first heartbeat after boot-up reports PRE-OPERATIONAL; SDO is available now.

    def fault(self, kind: str, meaning: str, code: int | None = None) -> Fault:
        return Fault(self.name, self.node_id, kind, meaning, code)

    # -- SDO -------------------------------------------------------------------------------------
    def _sdo_var(self, index: int, subindex: int):
        obj = self.node.sdo[index]
        return obj if subindex == 0 and isinstance(obj, canopen.sdo.SdoVariable) else obj[subindex]

    def sdo_read(self, index: int, subindex: int = 0):
        try:
            return self._sdo_var(index, subindex).raw
        except (SdoAbortedError, SdoCommunicationError, KeyError) as exc:
            f = self.fault("config", f"SDO read of 0x{index:04X}:{subindex:02X} failed: {exc}")
            raise DriverError(str(f), (f,)) from None

    def sdo_write(self, index: int, subindex: int, value) -> None:
        try:
            self._sdo_var(index, subindex).raw = value
        except (SdoAbortedError, SdoCommunicationError, KeyError, ValueError, OverflowError) as exc:
            f = self.fault("config", f"SDO write of {value!r} to 0x{index:04X}:{subindex:02X} failed: {exc}")
            raise DriverError(str(f), (f,)) from None

    # -- PDO -------------------------------------------------------------------------------------
    def map_pdos(self, rpdos: dict[int, list], tpdos: dict[int, list], trans_type: int = 1) -> None:
        """Map RPDOs/TPDOs ``{number: [index, ...]}`` synchronous (``trans_type``); disable the others."""
        try:
            self.node.pdo.read()
            for pdos, base, layout in ((self.node.rpdo, 0x200, rpdos), (self.node.tpdo, 0x180, tpdos)):
                for no, m in pdos.map.items():
                    m.clear()
                    if no in layout:
                        for index in layout[no]:
                            m.add_variable(index)
                        m.cob_id = base + 0x100 * (no - 1) + self.node_id
                        m.trans_type = trans_type
                        m.enabled = True
                    else:
                        m.enabled = False
            self.node.pdo.save()
        except (SdoAbortedError, SdoCommunicationError) as exc:
            f = self.fault("config", f"PDO mapping failed: {exc}")
            raise DriverError(str(f), (f,)) from None
        self.tpdos = sorted(tpdos)

    def hook_tpdos(self) -> None:
        """Receive the mapped TPDOs (call after any other decoder, e.g. BaseNode402's cache, is hooked)."""
        for no in self.tpdos:
            m = self.node.tpdo[no]
            if self._on_tpdo not in m.callbacks:
                m.add_callback(self._on_tpdo)

    def _on_tpdo(self, pdo_map) -> None:
        """Validate a received TPDO; valid ones go to ``on_valid_tpdo`` and the cycle tracker."""
        if len(pdo_map.data) != pdo_bytes(pdo_map):
            self.malformed += 1
            return
        no = (pdo_map.cob_id - 0x180 - self.node_id) // 0x100 + 1
        self.on_valid_tpdo(no, pdo_map)
        self.tracker.arrived((self.node_id, no))

    def on_valid_tpdo(self, number: int, pdo_map) -> None:
        """Hook: decode a valid TPDO."""

    def expected_tpdos(self) -> list[tuple[int, int]]:
        return [(self.node_id, no) for no in self.tpdos]

    def start(self) -> None:
        """NMT start: PDOs flow from now on."""
        self.node.nmt.state = "OPERATIONAL"

    # -- EMCY ------------------------------------------------------------------------------------
    def _check_emcy_length(self, can_id: int, data: bytes, timestamp: float) -> None:
        if len(data) != 8:
            self.malformed += 1

    def _on_emcy(self, entry: EmcyError) -> None:
        if entry.code & 0xFF00 == 0:
            return  # error reset / no error
        self.on_fault(self.fault("emcy", f"{error_meaning(entry.code)} (error register 0x{entry.register:02X})",
                                 entry.code))


def wait_until(predicate: Callable[[], bool], timeout: float, step: float = 0.001) -> bool:
    """Poll ``predicate`` until true or ``timeout`` s; returns its last value."""
    end = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > end:
            return False
        time.sleep(step)
    return True
