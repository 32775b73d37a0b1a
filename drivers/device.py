"""What every CANopen device driver here shares: boot (NMT reset, wait for the boot-up
message), SDO access with errors naming the object, PDO mapping through canopen's ``PdoMap``,
validated TPDO reception, and EMCY messages turned into ``Fault`` s.

``CycleTracker`` lets the master wait, after each SYNC, until every expected TPDO has arrived.
"""
from __future__ import annotations

import logging
import struct
import threading
import time
from typing import Callable, Iterable

import canopen
from canopen.emcy import EmcyError
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from drivers import mapping, pdo_codec
from drivers.faults import DeviceConfigError, DriverError, error_meaning
from otbot_hw.robot import Fault

log = logging.getLogger(__name__)

NMT_START = 0x01
NMT_STOP = 0x02
NMT_ENTER_PRE_OPERATIONAL = 0x80
NMT_RESET_COMMUNICATION = 0x82


class CycleTracker:
    """Which (node, TPDO number) pairs have arrived since the last SYNC; thread-safe. The waiter is
    woken by the first arrival (it starts the ``settle`` time) and by the last one, not by each: every
    wake-up costs the waiting loop thread a few microseconds of Condition machinery (issue 22)."""

    def __init__(self):
        self._cond = threading.Condition()
        self._missing: set = set()
        self._active = False
        self._last_arrival: float | None = None

    def begin(self, expected: Iterable) -> None:
        with self._cond:
            self._missing = set(expected)
            self._active = True
            self._last_arrival = None

    def arrived(self, key) -> None:
        with self._cond:
            if self._active and key in self._missing:
                self._missing.discard(key)
                first = self._last_arrival is None
                self._last_arrival = time.monotonic()
                if first or not self._missing:
                    self._cond.notify_all()

    def wait(self, timeout: float, settle: float | None = None) -> set:
        """Block until all expected TPDOs arrived or ``timeout`` s passed; return the missing ones.

        ``settle`` (s): once one TPDO of this SYNC has arrived, wait at most this long after the
        latest arrival for the others (a plant answers a SYNC with all its TPDOs at once)."""
        end = time.monotonic() + timeout
        with self._cond:
            while self._missing:
                now = time.monotonic()
                limit = end
                if settle is not None and self._last_arrival is not None:
                    limit = min(end, self._last_arrival + settle)
                if now >= limit:
                    break
                self._cond.wait(limit - now)
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


def guard_length(network, can_id: int, callback, length: int, on_bad: Callable[[], None]) -> None:
    """Let ``callback``, already subscribed to ``can_id`` on ``network``, see only frames of
    ``length`` bytes (canopen's handlers unpack fixed layouts and raise on short frames); the others
    go to ``on_bad()``."""
    subs = network.subscribers.get(can_id, [])
    for i, cb in enumerate(subs):
        if cb == callback:
            def guarded(cid, data, timestamp, cb=cb):
                if len(data) == length:
                    cb(cid, data, timestamp)
                else:
                    on_bad()

            subs[i] = guarded


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
        try:
            od = mapping.import_dictionary(eds, node_id, name)
        except mapping.PlanError as exc:
            raise DeviceConfigError(str(exc), (Fault(name, node_id, "config", str(exc)),)) from None
        self.node = self.node_class(node_id, od)
        network.add_node(self.node)
        self.notes: list[str] = []  # what this device cannot do that the loop would use (said once)
        self.plan: mapping.Plan | None = None
        self.tracker = tracker
        self.on_fault = on_fault
        self.malformed = 0  # ignored frames from this node (wrong length)
        self._bootup = threading.Event()
        network.subscribe(0x700 + node_id, self._on_heartbeat_frame)
        # canopen's own handlers see only frames of the length CiA 301 gives them (they would raise
        # on others); frames of another length are counted and ignored.
        for cob, cb, n in ((0x80 + node_id, self.node.emcy.on_emcy, 8), (0x700 + node_id, self.node.nmt.on_heartbeat, 1),
                           (0x580 + node_id, self.node.sdo.on_response, 8), (0, self.node.nmt.on_command, 2)):
            guard_length(network, cob, cb, n, self._count_malformed)
        self.node.emcy.add_callback(self._on_emcy)
        self.tpdos: list[int] = []  # numbers of the TPDOs this driver mapped (expected on every SYNC)
        self._hooked: set[int] = set()
        self._fast: dict[int, pdo_codec.FastTpdo] = {}  # TPDO number -> its fast decoder
        self.tpdo_values: dict[int, object] = {}  # last TPDO values by object index (fast decoding)
        self.last_emcy_code: int | None = None

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
        self.nmt_command(NMT_RESET_COMMUNICATION)
        if not self._bootup.wait(timeout):
            f = Fault(self.name, self.node_id, "boot",
                      f"no boot-up message within {timeout:g} s after NMT reset communication "
                      f"(node powered, wired, node ID {self.node_id}, bitrate?)")
            raise DriverError(str(f), (f,))
        # The first heartbeat after boot-up reports PRE-OPERATIONAL; SDO is available now.

    def fault(self, kind: str, meaning: str, code: int | None = None) -> Fault:
        return Fault(self.name, self.node_id, kind, meaning, code)

    # -- SDO -------------------------------------------------------------------------------------
    def has(self, index: int, subindex: int = 0) -> bool:
        """Whether the object dictionary describes ``index:subindex``."""
        return mapping.has_object(self.node.object_dictionary, index, subindex)

    def config_error(self, meaning: str) -> DeviceConfigError:
        f = self.fault("config", meaning)
        return DeviceConfigError(str(f), (f,))

    def _sdo_var(self, index: int, subindex: int):
        obj = self.node.sdo[index]
        return obj if subindex == 0 and isinstance(obj, canopen.sdo.SdoVariable) else obj[subindex]

    def sdo_read(self, index: int, subindex: int = 0):
        try:
            return self._sdo_var(index, subindex).raw
        except (SdoAbortedError, SdoCommunicationError, KeyError, ValueError, struct.error) as exc:
            f = self.fault("config", f"SDO read of {mapping.object_name(index, subindex)} failed: {exc}")
            raise (DriverError if isinstance(exc, SdoCommunicationError) else DeviceConfigError)(str(f), (f,)) from None

    def sdo_write(self, index: int, subindex: int, value) -> None:
        try:
            self._sdo_var(index, subindex).raw = value
        except (SdoAbortedError, SdoCommunicationError, KeyError, ValueError, OverflowError, struct.error) as exc:
            f = self.fault("config", f"SDO write of {value!r} to {mapping.object_name(index, subindex)} failed: "
                                     f"{exc}")
            raise (DriverError if isinstance(exc, SdoCommunicationError) else DeviceConfigError)(str(f), (f,)) from None

    def sdo_write_if_present(self, index: int, subindex: int, value, what: str) -> bool:
        """Write where the dictionary has the object; otherwise note (once) that ``what`` is not done."""
        if self.has(index, subindex):
            self.sdo_write(index, subindex, value)
            return True
        self.notes.append(f"no {mapping.object_name(index, subindex)} in the object dictionary: {what}")
        return False

    def sdo_call(self, fn, what: str):
        """Run a canopen call that talks SDO; its errors become ``DriverError`` naming ``what``."""
        try:
            return fn()
        except (SdoAbortedError, SdoCommunicationError, KeyError, ValueError, struct.error) as exc:
            f = self.fault("config", f"{what} failed: {exc}")
            raise (DriverError if isinstance(exc, SdoCommunicationError) else DeviceConfigError)(str(f), (f,)) from None

    # -- PDO -------------------------------------------------------------------------------------
    def plan_pdos(self, needs_rx, needs_tx, preferred_rx, preferred_tx) -> mapping.Plan:
        try:
            return mapping.plan_pdos(self.node.object_dictionary, self.node_id, f"{self.name} (node {self.node_id})",
                                     needs_rx, needs_tx, preferred_rx, preferred_tx)
        except mapping.PlanError as exc:
            raise self.config_error(str(exc).split(": ", 1)[1]) from None

    def map_pdos(self, plan: mapping.Plan) -> None:
        """Write ``plan`` (``drivers.mapping``), read it back, refuse what the device does not carry,
        then set up the local PDO maps; the TPDOs carrying planned objects are expected every SYNC."""
        self.notes += mapping.configure_pdos(self, plan)
        try:
            mapping.verify_pdos(self, plan)
        except mapping.PlanError as exc:
            raise self.config_error(str(exc).split(": ", 1)[1]) from None
        mapping.set_local_maps(self.node, plan)
        self.notes += plan.notes
        self.plan = plan
        self.tpdos = sorted(plan.tx.pdos)

    def hook_tpdos(self) -> None:
        """Receive the mapped TPDOs (call after any other decoder, e.g. BaseNode402's cache, is hooked).

        Each TPDO whose layout one struct expresses (``drivers.pdo_codec``) is decoded by a
        ``FastTpdo`` instead of canopen's per-variable path: its values go to ``tpdo_cache`` (the
        node's ``tpdo_values`` where it has them) and the frame to ``_on_tpdo``; the others keep
        canopen's ``PdoMap`` callbacks."""
        cache = self.tpdo_cache()
        for no in self.tpdos:
            m = self.node.tpdo[no]
            layout = pdo_codec.compile_map(m) if cache is not None else None
            if layout is not None:
                fast = self._fast.get(no)
                if fast is None or fast.layout.keys != layout.keys or fast.cob_id != m.cob_id:
                    fast = self._fast[no] = pdo_codec.FastTpdo(
                        self.network, m, layout, cache, lambda vals, no=no, m=m: self._on_tpdo(no, m),
                        lambda data: self._count_malformed(), skip=self._replaced_callbacks())
                fast.attach()
            elif no not in self._hooked:
                m.add_callback(lambda pdo_map, no=no: self._on_tpdo(no, pdo_map))
                self._hooked.add(no)

    def _replaced_callbacks(self) -> tuple:
        """``PdoMap`` callbacks a ``FastTpdo`` does the work of (BaseNode402's value cache)."""
        cb = getattr(self.node, "on_TPDOs_update_callback", None)
        return (cb,) if cb is not None else ()

    def tpdo_cache(self) -> dict | None:
        """Where fast-decoded TPDO values go, by object index: the node's ``tpdo_values`` (a
        ``BaseNode402``), else this device's ``tpdo_values`` (None: canopen decodes)."""
        return getattr(self.node, "tpdo_values", self.tpdo_values)

    def _on_tpdo(self, number: int, pdo_map) -> None:
        """Validate a received TPDO; valid ones go to ``on_valid_tpdo`` and the cycle tracker."""
        if number not in self.tpdos:
            return
        if len(pdo_map.data) != pdo_bytes(pdo_map):
            self.malformed += 1
            return
        self.on_valid_tpdo(number, pdo_map)
        self.tracker.arrived((self.node_id, number))

    def on_valid_tpdo(self, number: int, pdo_map) -> None:
        """Hook: decode a valid TPDO."""

    def expected_tpdos(self) -> list[tuple[int, int]]:
        return [(self.node_id, no) for no in self.tpdos]

    def start(self) -> None:
        """NMT start: PDOs flow from now on."""
        self.nmt_command(NMT_START)

    def _count_malformed(self) -> None:
        self.malformed += 1

    def nmt_command(self, code: int) -> None:
        """Send NMT command ``code`` to this node (straight onto the bus: canopen's NMT bookkeeping
        fails on states a garbled heartbeat reported)."""
        self.network.send_message(0, bytes([code, self.node_id]))

    # -- EMCY ------------------------------------------------------------------------------------
    def _on_emcy(self, entry: EmcyError) -> None:
        if entry.code & 0xFF00 == 0:
            return  # error reset / no error
        self.last_emcy_code = entry.code
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
