"""Simulated CANopen slaves built on canopen's ``LocalNode``: a CiA 402 torque drive and a CiA 406
absolute encoder.

Each slave serves SDO requests over its EDS object dictionary (canopen's ``SdoServer``), boots
with an NMT boot-up message and produces heartbeats (``NmtSlave``), obeys NMT commands (reset
node / reset communication reboot it), maps PDOs as the master configures them over SDO, applies
synchronous RPDOs and transmits synchronous TPDOs when the plant calls ``latch()`` / ``send_tpdos()``
on every SYNC, and sends EMCY messages on faults. Joint quantities come from the plant, which
owns the physics; the slaves only turn them into device units (counts, per-mille).

Fault injection for tests: ``inject_fault(code)``, ``drop_tpdos``, ``go_silent()``.
"""
from __future__ import annotations

import logging
import math
import struct
import threading
from pathlib import Path

import canopen
from canopen.profiles.p402 import OperationMode
from canopen.sdo import SdoAbortedError

from drivers.config import DriveConfig, EncoderConfig
from drivers.device import pdo_get, pdo_put

log = logging.getLogger(__name__)

NMT_RESET_NODE = 0x81
NMT_RESET_COMMUNICATION = 0x82
INT32 = 2 ** 32


def wrap_int32(v: int) -> int:
    """Two's-complement wrap of an integer into INTEGER32."""
    return (v + 2 ** 31) % INT32 - 2 ** 31


class SimulatedNode:
    """A CANopen slave on ``network`` (a connected ``canopen.Network``) with live process values.

    ``values[(index, subindex)]`` holds the objects that change at run time; SDO reads of them
    return the live value, SDO writes update them.
    """

    def __init__(self, network: canopen.Network, node_id: int, eds: str | Path, name: str):
        self.name = name
        self.network = network
        self.node = canopen.LocalNode(node_id, str(eds))
        network.add_node(self.node)
        self.values: dict[tuple[int, int], object] = {}
        self._od_cache: dict[tuple[int, int], object] = {}  # stored (non-live) values; cleared on writes
        self.node.add_read_callback(self._on_read)
        self.node.add_write_callback(self._on_write)
        network.subscribe(0, self._on_nmt)
        self.lock = threading.RLock()
        self._pdo_dirty = True
        self._sync_count = 0
        self._rpdo_pending: dict[int, bytes] = {}
        self._rpdo_hooked: set[int] = set()
        self.silent = False
        self.drop_tpdos = False
        self.malformed = 0  # frames addressed to this node that were ignored (wrong length)
        self.tpdos_sent = 0
        self.reset_listeners: list = []  # called with (node, application) after an NMT reset

    @property
    def node_id(self) -> int:
        return self.node.id

    @property
    def operational(self) -> bool:
        return self.node.nmt.state == "OPERATIONAL"

    # -- SDO / OD ------------------------------------------------------------------------------
    def _on_read(self, index: int, subindex: int, od):
        return self.values.get((index, subindex))

    def _on_write(self, index: int, subindex: int, od, data: bytes):
        self._od_cache.clear()
        if 0x1400 <= index <= 0x1BFF:
            self._pdo_dirty = True
        key = (index, subindex)
        if key in self.values:
            value = od.decode_raw(data)
            self.on_sdo_write(index, subindex, value)
            self.values[key] = value

    def on_sdo_write(self, index: int, subindex: int, value) -> None:
        """Hook: validate or act on an SDO write of a live value (raise SdoAbortedError to refuse)."""

    def od_value(self, index: int, subindex: int = 0):
        """Current value of any object (live, written, or the EDS default)."""
        key = (index, subindex)
        if key in self.values:
            return self.values[key]
        if key not in self._od_cache:
            self._od_cache[key] = self._od_read(index, subindex)
        return self._od_cache[key]

    def _od_read(self, index: int, subindex: int):
        obj = self.node.object_dictionary[index]
        if not isinstance(obj, canopen.objectdictionary.ODVariable):
            obj = obj[subindex]
        return obj.decode_raw(self.node.get_data(index, subindex))

    def set_od(self, index: int, subindex: int, value) -> None:
        """Set an object's stored value locally (no SDO traffic)."""
        obj = self.node.object_dictionary[index]
        if isinstance(obj, canopen.objectdictionary.ODVariable):
            data = obj.encode_raw(value)
        else:
            data = obj[subindex].encode_raw(value)
        self.node.set_data(index, subindex, data)

    # -- NMT -------------------------------------------------------------------------------------
    def _on_nmt(self, can_id: int, data: bytes, timestamp: float) -> None:
        if len(data) != 2:
            self.malformed += 1
            return
        cmd, node = struct.unpack("BB", data)
        if node not in (0, self.node.id) or self.silent:
            return
        if cmd in (NMT_RESET_NODE, NMT_RESET_COMMUNICATION):
            self.reset(application=cmd == NMT_RESET_NODE)
            self.boot()

    def reset(self, application: bool) -> None:
        """Forget written communication objects (and application objects on a node reset)."""
        with self.lock:
            self._od_cache.clear()
            for index in list(self.node.data_store):
                if index < 0x2000 or application:
                    if index not in self.keep_on_reset():
                        del self.node.data_store[index]
            self._pdo_dirty = True
            self._sync_count = 0
            self._rpdo_pending.clear()
            self.on_reset(application)
        for listener in self.reset_listeners:
            listener(self, application)

    def keep_on_reset(self) -> set[int]:
        """Objects that model hardware (not configuration) and survive resets."""
        return set()

    def on_reset(self, application: bool) -> None:
        """Hook: reset process values."""

    def boot(self) -> None:
        """Power-on / reset: boot-up message, then PRE-OPERATIONAL with the heartbeat of 0x1017."""
        self.node.nmt.send_command(NMT_RESET_NODE)  # INITIALISING: sends the boot-up message
        self.node.nmt.send_command(0x80)  # PRE-OPERATIONAL: starts the heartbeat producer

    def go_silent(self) -> None:
        """Simulate a dead node: no heartbeat, no PDO, no SDO answer, no EMCY."""
        self.silent = True
        self.node.nmt.stop_heartbeat()
        self.network.unsubscribe(self.node.sdo.rx_cobid, self.node.sdo.on_request)

    def stop(self) -> None:
        self.node.nmt.stop_heartbeat()

    # -- PDO -------------------------------------------------------------------------------------
    def _reload_pdos(self) -> None:
        self.node.tpdo.read(from_od=False)
        self.node.rpdo.read(from_od=False)
        for no, m in self.node.rpdo.map.items():
            if no not in self._rpdo_hooked:
                m.add_callback(self._on_rpdo)
                self._rpdo_hooked.add(no)
        self._pdo_dirty = False

    def _on_rpdo(self, pdo_map) -> None:
        if self.silent or not self.operational:
            return
        data = bytes(pdo_map.data)
        if len(data) != (pdo_map.length + 7) // 8:
            self.malformed += 1
            return
        with self.lock:
            if pdo_map.trans_type is not None and pdo_map.trans_type <= 240:
                self._rpdo_pending[pdo_map.cob_id] = data  # applied at the next SYNC
            else:
                self._apply_rpdo(pdo_map, data)

    def _apply_rpdo(self, pdo_map, data: bytes) -> None:
        pdo_map.data = bytearray(data)
        values = {(v.index, v.subindex): pdo_get(v) for v in pdo_map.map}
        for (index, sub), value in values.items():
            if (index, sub) in self.values:
                self.on_sdo_write(index, sub, value)
                self.values[(index, sub)] = value
        self.on_rpdo_applied()

    def on_rpdo_applied(self) -> None:
        """Hook: act on newly applied RPDO values."""

    def latch(self) -> None:
        """At SYNC: apply the synchronous RPDOs received since the previous SYNC."""
        with self.lock:
            if self._pdo_dirty:
                self._reload_pdos()
            if not self.operational or self.silent:
                self._rpdo_pending.clear()
                return
            for m in self.node.rpdo.map.values():
                data = self._rpdo_pending.pop(m.cob_id, None) if m.enabled else None
                if data is not None:
                    self._apply_rpdo(m, data)
            self.on_sync()

    def on_sync(self) -> None:
        """Hook: per-SYNC device dynamics (after the RPDOs are applied)."""

    def send_tpdos(self) -> None:
        """At SYNC (after ``latch`` and the plant's update of the values): transmit due TPDOs."""
        with self.lock:
            if self._pdo_dirty:
                self._reload_pdos()
            if not self.operational or self.silent:
                return
            self._sync_count += 1
            for m in self.node.tpdo.map.values():
                tt = m.trans_type
                if not m.enabled or tt is None or tt > 240:
                    continue
                if tt == 0 or self._sync_count % tt == 0:
                    for v in m.map:
                        pdo_put(v, self.values.get((v.index, v.subindex), 0))
                    if not self.drop_tpdos:
                        m.transmit()
                        self.tpdos_sent += 1


# CiA 402 statusword bits of each state (State402.SW_MASK values) plus "voltage enabled" (bit 4).
_SW = {"NOT READY TO SWITCH ON": 0x00, "SWITCH ON DISABLED": 0x40, "READY TO SWITCH ON": 0x31,
       "SWITCHED ON": 0x33, "OPERATION ENABLED": 0x37, "QUICK STOP ACTIVE": 0x17,
       "FAULT REACTION ACTIVE": 0x1F, "FAULT": 0x08}
SW_REMOTE = 0x0200
SW_TARGET_REACHED = 0x0400
TORQUE_MODES = (OperationMode.PROFILED_TORQUE, OperationMode.CYCLIC_SYNCHRONOUS_TORQUE)
_ERROR_REGISTER_BITS = {0x2: 0x02, 0x3: 0x04, 0x4: 0x08, 0x8: 0x10}  # current, voltage, temperature, comm


class SimulatedDrive(SimulatedNode):
    """A CiA 402 servo drive in a torque mode (CST 10 / PT 4) on the joint described by ``cfg``.

    The plant reads ``joint_torque()`` (N m at the joint, after gear and polarity) and writes the
    joint angle and rate with ``sample(phi, phi_dot)``; 0x6064 is floor-quantized to motor counts
    and wraps as an INTEGER32 (``position_offset`` counts at phi = 0), 0x606C is rounded to the
    configured velocity unit (counts/s by default).
    """

    def __init__(self, network: canopen.Network, cfg: DriveConfig, position_offset: int = 0,
                 supported_modes: int | None = None):
        super().__init__(network, cfg.node_id, cfg.eds, cfg.name)
        self.cfg = cfg
        self.position_offset = int(position_offset)
        self.set_od(0x6076, 0, int(round(cfg.rated_torque * 1000)))
        self.set_od(0x608F, 1, cfg.counts_per_rev)
        self.set_od(0x608F, 2, 1)
        if supported_modes is not None:
            self.set_od(0x6502, 0, supported_modes)
        self.state = "SWITCH ON DISABLED"
        self._last_cw = 0
        self._actual_pm = 0
        self.values.update({(0x6040, 0): 0, (0x6041, 0): 0, (0x6060, 0): 0, (0x6061, 0): 0,
                            (0x6064, 0): 0, (0x606C, 0): 0, (0x6071, 0): 0, (0x6077, 0): 0,
                            (0x603F, 0): 0, (0x1001, 0): 0})
        self._update_statusword()

    def keep_on_reset(self) -> set[int]:
        return {0x6076, 0x608F, 0x6502}

    def on_reset(self, application: bool) -> None:
        if application:
            self.state = "SWITCH ON DISABLED"
            for key in ((0x6040, 0), (0x6060, 0), (0x6061, 0), (0x6071, 0), (0x6077, 0), (0x603F, 0), (0x1001, 0)):
                self.values[key] = 0
            self._last_cw = 0
            self._actual_pm = 0
        self._update_statusword()

    # -- state machine ---------------------------------------------------------------------------
    def on_sdo_write(self, index: int, subindex: int, value) -> None:
        if index == 0x6060:
            supported = self.od_value(0x6502)
            bit = {v: OperationMode.SUPPORTED[k] for k, v in OperationMode.NAME2CODE.items()}.get(value)
            if value != 0 and (bit is None or not supported & bit):
                raise SdoAbortedError(0x06090030)  # value range of parameter exceeded
            self.values[(0x6061, 0)] = value
        elif index == 0x6040:
            self._controlword(value)

    def _controlword(self, cw: int) -> None:
        rising_reset = bool(cw & 0x80) and not (self._last_cw & 0x80)
        self._last_cw = cw
        s = self.state
        if s == "FAULT":
            if rising_reset:
                self.values[(0x603F, 0)] = 0
                self.values[(0x1001, 0)] = 0
                self.state = "SWITCH ON DISABLED"
                if not self.silent:
                    self.node.emcy.reset()
        elif s == "FAULT REACTION ACTIVE" or cw & 0x80:
            pass
        elif cw & 0x02 == 0:  # disable voltage
            self.state = "SWITCH ON DISABLED"
        elif cw & 0x04 == 0:  # quick stop
            self.state = "QUICK STOP ACTIVE" if s in ("OPERATION ENABLED", "QUICK STOP ACTIVE") else "SWITCH ON DISABLED"
            if self.state == "QUICK STOP ACTIVE" and self.od_value(0x605A) not in (5, 6, 7, 8):
                self.state = "SWITCH ON DISABLED"
        elif cw & 0x01 == 0:  # shutdown
            if s in ("SWITCH ON DISABLED", "SWITCHED ON", "OPERATION ENABLED"):
                self.state = "READY TO SWITCH ON"
        elif cw & 0x08 == 0:  # switch on / disable operation
            if s in ("READY TO SWITCH ON", "OPERATION ENABLED"):
                self.state = "SWITCHED ON"
        else:  # switch on + enable operation
            if s in ("READY TO SWITCH ON", "SWITCHED ON", "QUICK STOP ACTIVE"):
                self.state = "OPERATION ENABLED"
        self._update_statusword()

    def _update_statusword(self) -> None:
        sw = _SW[self.state] | SW_REMOTE
        if self.state == "OPERATION ENABLED":
            sw |= SW_TARGET_REACHED
        self.values[(0x6041, 0)] = sw

    def on_rpdo_applied(self) -> None:
        self._update_statusword()

    def inject_fault(self, code: int) -> None:
        """A drive error: FAULT state, 0x603F = ``code``, error register, 0x1003 history, EMCY."""
        with self.lock:
            reg = 0x01 | _ERROR_REGISTER_BITS.get(code >> 12, 0)
            self.state = "FAULT"
            self._actual_pm = 0
            self.values[(0x603F, 0)] = code
            self.values[(0x1001, 0)] = reg
            n = min(self.od_value(0x1003, 0) + 1, 4)
            for i in range(n, 1, -1):
                self.set_od(0x1003, i, self.od_value(0x1003, i - 1))
            self.set_od(0x1003, 1, code)
            self.set_od(0x1003, 0, n)
            self._update_statusword()
            if not self.silent:
                self.node.emcy.send(code, reg)

    # -- process values --------------------------------------------------------------------------
    def on_sync(self) -> None:
        """Torque the power stage produces until the next SYNC: the target torque limited by 0x6072
        (CST), ramped at the torque slope 0x6087 per-mille/s in profile torque mode (slope 0: step);
        zero unless OPERATION ENABLED."""
        mode = self.values[(0x6061, 0)]
        if self.state != "OPERATION ENABLED" or mode not in TORQUE_MODES:
            self._actual_pm = 0
            return
        limit = self.od_value(0x6072)
        target = int(max(-limit, min(limit, self.values[(0x6071, 0)])))
        slope = self.od_value(0x6087)
        if mode == OperationMode.PROFILED_TORQUE and slope > 0:
            period = self.od_value(0x60C2, 1) * 10.0 ** self.od_value(0x60C2, 2)
            step = max(1, int(slope * period))
            target = self._actual_pm + max(-step, min(step, target - self._actual_pm))
        self._actual_pm = target

    def applied_permille(self) -> int:
        """Torque the power stage produces, per-mille of rated torque (set at each SYNC)."""
        return self._actual_pm

    def joint_torque(self) -> float:
        """Torque at the joint, N m."""
        return self.cfg.polarity * self.cfg.gear_ratio * self.applied_permille() / 1000.0 * self.cfg.rated_torque

    def sample(self, phi: float, phi_dot: float) -> None:
        """Joint angle (rad) and rate (rad/s) into 0x6064 (counts) and 0x606C (counts/s)."""
        per_rad = self.cfg.gear_ratio * self.cfg.counts_per_rev / (2 * math.pi)
        counts = math.floor(phi * per_rad + 1e-9)
        self.values[(0x6064, 0)] = wrap_int32(self.position_offset + self.cfg.polarity * counts)
        self.values[(0x606C, 0)] = int(round(self.cfg.polarity * phi_dot / self.cfg.rad_s_per_velocity_unit))
        self.values[(0x6077, 0)] = self.applied_permille()
        self._update_statusword()


class SimulatedEncoder(SimulatedNode):
    """A CiA 406 multi-turn absolute encoder on the pivot: 0x6004 position value in measuring
    units, (offset + direction * floor(phi_p * gear * units_per_rev / 2 pi)) mod total range,
    units per revolution 0x6001 and total range 0x6002 as configured in the object dictionary."""

    def __init__(self, network: canopen.Network, cfg: EncoderConfig):
        super().__init__(network, cfg.node_id, cfg.eds, "pivot_encoder")
        self.cfg = cfg
        self._preset_shift = 0
        self.values.update({(0x6004, 0): 0, (0x6503, 0): 0, (0x6505, 0): 0, (0x1001, 0): 0})

    def on_sdo_write(self, index: int, subindex: int, value) -> None:
        pass

    def _on_write(self, index, subindex, od, data):
        super()._on_write(index, subindex, od, data)
        if index == 0x6003:  # preset: the current position reads the preset value from now on
            self._preset_shift += od.decode_raw(data) - self.values[(0x6004, 0)]

    def position_counts(self, phi: float) -> int:
        upr = self.od_value(0x6001)
        rng = self.od_value(0x6002)
        c = math.floor(phi * self.cfg.gear_ratio * upr / (2 * math.pi) + 1e-9)
        if self.od_value(0x6000) & 0x1:  # code sequence: counting direction inverted
            c = -c
        return (self.cfg.offset + self.cfg.direction * c + self._preset_shift) % rng

    def sample(self, phi: float) -> None:
        self.values[(0x6004, 0)] = self.position_counts(phi)

    def inject_fault(self, code: int = 0x7320) -> None:
        """Position sensor fault: alarm bit, error register and EMCY."""
        with self.lock:
            self.values[(0x6503, 0)] = 0x0001
            self.values[(0x1001, 0)] = 0x01
            if not self.silent:
                self.node.emcy.send(code, 0x01)
