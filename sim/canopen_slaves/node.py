"""A simulated CANopen slave (CiA 301) on canopen's ``LocalNode``: SDO server over its EDS, NMT state
machine with boot-up and heartbeat, PDO mapping configured by the master over SDO, synchronous RPDOs
applied and TPDOs sent when the plant calls ``latch()`` / ``send_tpdos()`` on every SYNC, EMCY.
The drive and the encoder (``drive``, ``encoder``) build on it.

The PDO frames the master mapped are packed and unpacked with one precompiled struct each
(``drivers.pdo_codec``, compiled whenever the mapping changes) instead of canopen's per-variable
Python; a layout one struct cannot express, an object with limits (canopen warns when a value
exceeds them) or a value the struct refuses (a float for an integer object: canopen truncates it)
takes canopen's per-variable path, so the frames are those canopen would build.
"""
from __future__ import annotations

import struct
import threading
from pathlib import Path

import canopen
from canopen.sdo import SdoAbortedError

from drivers import pdo_codec
from drivers.device import pdo_get, pdo_put
from drivers.mapping import has_object

NMT_RESET_NODE = 0x81
NMT_RESET_COMMUNICATION = 0x82
NMT_STOP = 0x02
NMT_ENTER_PRE_OPERATIONAL = 0x80
INT32 = 2 ** 32
#: SYNC loss: no SYNC for this many communication cycle periods (0x1006), CANopenNode's rule.
SYNC_LOSS_CYCLES = 1.5


def wrap_int32(v: int) -> int:
    """Two's-complement wrap of an integer into INTEGER32."""
    return (v + 2 ** 31) % INT32 - 2 ** 31


def _layout(pdo_map) -> pdo_codec.PdoLayout | None:
    """The precompiled frame of a PDO map, or None (canopen's per-variable path): a layout one struct
    cannot express, or an object with limits (canopen's encoding warns beyond them)."""
    if any(v.od.min is not None or v.od.max is not None for v in pdo_map.map):
        return None
    return pdo_codec.compile_map(pdo_map)


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
        self._guards: list = []
        self.node.add_read_callback(self._on_read)
        self.node.add_write_callback(self._on_write)
        # SDO requests are 8 bytes, NMT commands 2 (CiA 301): canopen's server would raise on others;
        # a silent node hears neither
        self._intercept(self.node.sdo.rx_cobid, self.node.sdo.on_request, 8)
        self._intercept(0, self.node.nmt.on_command, 2)
        network.subscribe(0, self._on_nmt)
        self.lock = threading.RLock()
        self._pdo_dirty = True
        self._sync_count = 0
        self._rpdo_pending: dict[int, bytes] = {}
        self._rpdo_hooked: set[int] = set()
        self._layouts: dict[int, pdo_codec.PdoLayout | None] = {}  # id(PdoMap) -> its compiled frame
        self._rpdo_maps: list = []  # the RPDO maps, and the TPDO maps with their layouts (set by _reload_pdos)
        self._tpdo_maps: list = []
        self.silent = False
        self.drop_tpdos = False
        self.malformed = 0  # frames addressed to this node that were ignored (wrong length)
        self.foreign = 0  # frames on this node's own TPDO COB-IDs sent by someone else (ignored)
        self.tpdos_sent = 0
        self.reset_listeners: list = []  # called with (node, application) after an NMT reset

    @property
    def node_id(self) -> int:
        return self.node.id

    def _intercept(self, can_id: int, callback, length: int) -> None:
        def guarded(cid, data, timestamp):
            if self.silent:
                return
            if len(data) != length:
                self.malformed += 1
                return
            callback(cid, data, timestamp)

        subs = self.network.subscribers.get(can_id, [])
        subs[subs.index(callback)] = guarded
        self._guards.append(guarded)

    @property
    def operational(self) -> bool:
        return self.node.nmt.state == "OPERATIONAL"

    # -- SDO / OD ------------------------------------------------------------------------------
    def has(self, index: int, subindex: int = 0) -> bool:
        """Whether this device's dictionary describes ``index:subindex``."""
        return has_object(self.node.object_dictionary, index, subindex)

    def _on_read(self, index: int, subindex: int, od):
        return self.values.get((index, subindex))

    def _on_write(self, index: int, subindex: int, od, data: bytes):
        self._od_cache.clear()
        if 0x1400 <= index <= 0x1BFF:
            self._pdo_dirty = True
        key = (index, subindex)
        value = od.decode_raw(data)
        if key in self.values:
            self.on_sdo_write(index, subindex, value)
            self.values[key] = value
        self.on_config_write(index, subindex, value)

    def on_sdo_write(self, index: int, subindex: int, value) -> None:
        """Hook: validate or act on an SDO write of a live value (raise SdoAbortedError to refuse)."""

    def on_config_write(self, index: int, subindex: int, value) -> None:
        """Hook: an object is being written with ``value`` (``od_value`` still gives the old one)."""

    def od_value(self, index: int, subindex: int = 0, default=None):
        """Current value of any object (live, written, or the EDS default); ``default`` where the
        dictionary does not have it or gives it no value."""
        key = (index, subindex)
        if key in self.values:
            return self.values[key]
        if key not in self._od_cache:
            if not self.has(index, subindex):
                return default
            try:
                self._od_cache[key] = self._od_read(index, subindex)
            except (SdoAbortedError, KeyError, struct.error):
                return default
        return self._od_cache[key]

    def _od_read(self, index: int, subindex: int):
        obj = self.node.object_dictionary[index]
        if not isinstance(obj, canopen.objectdictionary.ODVariable):
            obj = obj[subindex]
        return obj.decode_raw(self.node.get_data(index, subindex))

    def set_od(self, index: int, subindex: int, value) -> bool:
        """Set an object's stored value locally (no SDO traffic); False where the dictionary lacks it."""
        if not self.has(index, subindex):
            return False
        obj = self.node.object_dictionary[index]
        if isinstance(obj, canopen.objectdictionary.ODVariable):
            data = obj.encode_raw(value)
        else:
            data = obj[subindex].encode_raw(value)
        self.node.set_data(index, subindex, data)
        self._od_cache.clear()
        return True

    # -- NMT -------------------------------------------------------------------------------------
    def _on_nmt(self, can_id: int, data: bytes, timestamp: float) -> None:
        if len(data) != 2:
            self.malformed += 1
            return
        cmd, node = struct.unpack("BB", data)
        if node not in (0, self.node.id) or self.silent:
            return
        if cmd in (NMT_RESET_NODE, NMT_RESET_COMMUNICATION, NMT_STOP, NMT_ENTER_PRE_OPERATIONAL):
            self.on_leave_operational(cmd)
        if cmd in (NMT_RESET_NODE, NMT_RESET_COMMUNICATION):
            self.reset(application=cmd == NMT_RESET_NODE)
            self.boot()

    def on_leave_operational(self, command: int) -> None:
        """Hook: an NMT command takes the node out of OPERATIONAL (stop, pre-operational, reset)."""

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
        """Simulate a node cut off the bus (transceiver dead): it sends nothing (no heartbeat, PDO,
        SDO answer, EMCY) and hears nothing (no SYNC, RPDO, NMT, heartbeat)."""
        self.silent = True
        self.node.nmt.stop_heartbeat()

    def stop(self) -> None:
        self.node.nmt.stop_heartbeat()

    def detach(self) -> None:
        """Leave the network for good (a plant being replaced): no heartbeat, no subscription left."""
        self.stop()
        owners = {id(o) for o in (self, self.node, self.node.sdo, self.node.nmt, self.node.emcy,
                                  *self.node.tpdo.map.values(), *self.node.rpdo.map.values())}
        guards = {id(g) for g in self._guards}
        for can_id in list(self.network.subscribers):
            keep = [cb for cb in self.network.subscribers[can_id]
                    if id(getattr(cb, "__self__", None)) not in owners and id(cb) not in guards]
            if keep:
                self.network.subscribers[can_id] = keep
            else:
                del self.network.subscribers[can_id]
        self.network.nodes.pop(self.node.id, None)

    # -- PDO -------------------------------------------------------------------------------------
    def _reload_pdos(self) -> None:
        self.node.tpdo.read(from_od=False)
        self.node.rpdo.read(from_od=False)
        for m in self.node.tpdo.map.values():
            # A TPDO is transmitted, never received: frames others send on its COB-ID are foreign.
            subs = self.network.subscribers.get(m.cob_id, []) if m.cob_id is not None else []
            if m.on_message in subs:
                self.network.unsubscribe(m.cob_id, m.on_message)
                if self._on_foreign not in self.network.subscribers.get(m.cob_id, []):
                    self.network.subscribe(m.cob_id, self._on_foreign)
        for no, m in self.node.rpdo.map.items():
            if no not in self._rpdo_hooked:
                m.add_callback(self._on_rpdo)
                self._rpdo_hooked.add(no)
        self._layouts = {id(m): _layout(m) for maps in (self.node.tpdo.map, self.node.rpdo.map)
                         for m in maps.values()}
        self._rpdo_maps = list(self.node.rpdo.map.values())
        self._tpdo_maps = [(m, self._layouts[id(m)]) for m in self.node.tpdo.map.values()]
        self._pdo_dirty = False

    def _on_foreign(self, can_id: int, data: bytes, timestamp: float) -> None:
        self.foreign += 1

    def _on_rpdo(self, pdo_map) -> None:
        if self.silent or not self.operational:
            return
        data = bytes(pdo_map.data)
        if len(data) != (pdo_map.length + 7) // 8:
            self.malformed += 1
            return
        self.on_rpdo_received(pdo_map)
        with self.lock:
            if pdo_map.trans_type is not None and pdo_map.trans_type <= 240:
                self._rpdo_pending[pdo_map.cob_id] = data  # applied at the next SYNC
            else:
                self._apply_rpdo(pdo_map, data)

    def on_rpdo_received(self, pdo_map) -> None:
        """Hook: a valid RPDO arrived (deadline monitoring)."""

    def _apply_rpdo(self, pdo_map, data: bytes) -> None:
        pdo_map.data = bytearray(data)
        layout = self._layouts.get(id(pdo_map))
        if layout is not None:  # (the frame's length was checked on receipt)
            values = dict(zip(layout.keys, layout.struct.unpack(data)))
        else:
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
            if self.silent:
                self._rpdo_pending.clear()
                return
            self.on_sync_received()
            if not self.operational:
                self._rpdo_pending.clear()
                return
            pending = self._rpdo_pending
            if pending:
                for m in self._rpdo_maps:
                    data = pending.pop(m.cob_id, None) if m.enabled else None
                    if data is not None:
                        self._apply_rpdo(m, data)
            self.on_sync()

    def on_sync_received(self) -> None:
        """Hook: a SYNC arrived (SYNC monitoring)."""

    def on_sync(self) -> None:
        """Hook: per-SYNC device dynamics (after the RPDOs are applied)."""

    def send_tpdos(self, out: list | None = None) -> None:
        """At SYNC (after ``latch`` and the plant's update of the values): transmit due TPDOs; with
        ``out``, append them to it as (COB-ID, data) instead, for the caller to send (in that order)."""
        with self.lock:
            if self._pdo_dirty:
                self._reload_pdos()
            if not self.operational or self.silent:
                return
            self._sync_count += 1
            for m, layout in self._tpdo_maps:
                tt = m.trans_type
                if not m.enabled or tt is None or tt > 240:
                    continue
                if tt == 0 or self._sync_count % tt == 0:
                    try:
                        if layout is None:
                            raise struct.error
                        get = self.values.get
                        m.data = bytearray(layout.struct.pack(*[get(k, 0) for k in layout.keys]))
                    except struct.error:  # canopen's path: int() of floats, limits, its errors
                        m.data = bytearray((m.length + 7) // 8)
                        for v in m.map:
                            pdo_put(v, self.values.get((v.index, v.subindex), 0))
                    if not self.drop_tpdos:
                        if out is None:
                            m.transmit()
                        else:
                            out.append((m.cob_id, m.data))
                        self.tpdos_sent += 1
