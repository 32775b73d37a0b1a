"""PDO layout of a device, planned from its object dictionary and verified on the device.

The loop needs some objects in PDOs (``Need``): a CiA 402 drive receives controlword and target
torque and sends statusword, position and velocity (torque actual, error code and mode display
where the dictionary has them). ``plan_pdos`` decides, from the EDS alone, which PDO carries
which object:

1. a PDO whose mapping is fixed (its mapping entries are read-only in the dictionary) is used as
   it is when it carries any needed object; a PDO whose entry count is read-only (``const``) but
   whose entries are writable is configurable within that count: at most ``count`` objects, the
   count itself never written, its unused entries written empty (0);
2. the needed objects still missing go into configurable PDOs, in the preferred layout where the
   dictionary allows it, else into the first configurable PDO with room (64 bits, map entries);
3. a required object that is absent from the dictionary or fits nowhere is refused by name
   (``DeviceConfigError``); an optional one is left out and noted.

``configure_pdos`` writes the plan over SDO (canopen's ``PdoMap.save`` for configurable PDOs,
the communication parameters only for fixed ones), disables every other PDO, and
``verify_pdos`` reads every planned PDO back (COB-ID, transmission type, mapping entries) and
refuses, naming node, PDO and object, what does not carry the plan; only the ``count`` entries
the PDO declares are compared, and empty entries (0, no bits) among them carry nothing. Only then
are the local ``PdoMap`` objects set up for encoding and decoding.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import canopen
from canopen.objectdictionary import ODVariable

PDO_NOT_VALID = 1 << 31
RX, TX = "RPDO", "TPDO"
_BASE = {RX: (0x1400, 0x1600, 0x200), TX: (0x1800, 0x1A00, 0x180)}

#: CiA 301 / 402 / 406 names of the objects the drivers map, for messages about absent ones.
OBJECT_NAMES = {0x6040: "controlword", 0x6071: "target torque", 0x6041: "statusword",
                0x6064: "position actual value", 0x606C: "velocity actual value",
                0x6077: "torque actual value", 0x603F: "error code", 0x6061: "modes of operation display",
                0x6060: "modes of operation", 0x6004: "position value", 0x6076: "motor rated torque",
                0x6072: "max torque", 0x6502: "supported drive modes", 0x1016: "consumer heartbeat time",
                0x1006: "communication cycle period", 0x6007: "abort connection option code"}


def object_name(index: int, sub: int | None = None) -> str:
    """'0x6071 target torque', '0x1016:01 consumer heartbeat time' (the CiA name where known)."""
    name = OBJECT_NAMES.get(index)
    where = f"0x{index:04X}" + (f":{sub:02X}" if sub is not None else "")
    return f"{where} {name}" if name else where


@dataclass(frozen=True)
class Need:
    """An object the loop needs in a PDO; ``required=False``: used where the dictionary has it."""

    index: int
    required: bool = True


@dataclass
class PdoPlan:
    """Which objects (index, subindex, bits) each PDO of one direction carries; ``fixed``: the
    numbers whose mapping the device fixes; ``cob_ids``: each planned PDO's COB-ID as the device has it."""

    direction: str
    pdos: dict[int, list[tuple[int, int, int]]] = field(default_factory=dict)
    fixed: set[int] = field(default_factory=set)
    cob_ids: dict[int, int] = field(default_factory=dict)

    def carrying(self, index: int) -> int | None:
        """Number of the PDO that carries ``index`` (None if none)."""
        for no, objs in self.pdos.items():
            if any(i == index for i, _, _ in objs):
                return no
        return None

    def bytes(self, number: int) -> int:
        return (sum(b for _, _, b in self.pdos[number]) + 7) // 8


@dataclass
class Plan:
    rx: PdoPlan
    tx: PdoPlan
    notes: list[str] = field(default_factory=list)  # what was left out (said once, without the device)


class PlanError(ValueError):
    """The dictionary cannot carry what the loop needs; the message names the object."""


def has_object(od, index: int, subindex: int = 0) -> bool:
    """Whether object dictionary ``od`` describes ``index:subindex``."""
    if index not in od:
        return False
    obj = od[index]
    return subindex == 0 if isinstance(obj, ODVariable) else subindex in obj


def _variable(od, index: int, sub: int = 0) -> ODVariable | None:
    if index not in od:
        return None
    obj = od[index]
    if isinstance(obj, ODVariable):
        return obj if sub == 0 else None
    return obj[sub] if sub in obj else None


def _slots(od, direction: str, node_id: int) -> dict[int, dict]:
    """The PDOs of one direction the dictionary describes: number -> fixed, capacity, default map."""
    comm0, map0, cob0 = _BASE[direction]
    out = {}
    for k in range(512):
        if comm0 + k not in od or map0 + k not in od:
            continue
        mp = od[map0 + k]
        if isinstance(mp, ODVariable):
            continue
        subs = sorted(s for s in mp.subindices if s > 0)
        fixed = not subs or not mp[subs[0]].writable
        default = []
        count = mp[0].default if 0 in mp.subindices and mp[0].default is not None else 0
        count_fixed = 0 in mp.subindices and not mp[0].writable
        for s in subs[:count]:
            v = mp[s].default or 0
            if (v >> 16) and (v & 0xFF):
                default.append((v >> 16, (v >> 8) & 0xFF, v & 0xFF))
        cm = od[comm0 + k]
        cob_default = cm[1].default if not isinstance(cm, ODVariable) and 1 in cm.subindices else None
        cob = (cob0 + 0x100 * k + node_id) if k < 4 else ((cob_default or 0) & 0x7FF)
        cob_fixed = isinstance(cm, ODVariable) or 1 not in cm.subindices or not cm[1].writable
        capacity = min(len(subs), count) if count_fixed and not fixed else len(subs)
        out[k + 1] = {"fixed": fixed, "capacity": capacity, "count_fixed": count_fixed and not fixed,
                      "count": count, "default": default, "cob_id": cob,
                      "cob_fixed": cob_fixed, "cob_default": cob_default}
    return out


def plan_pdos(od, node_id: int, device: str, needs_rx: list[Need], needs_tx: list[Need],
              preferred_rx: dict[int, list[int]], preferred_tx: dict[int, list[int]]) -> Plan:
    """Plan the PDOs of a device from its object dictionary ``od`` (see the module docstring).

    Raises ``PlanError`` naming ``device`` and the object when a required object is absent or
    fits in no PDO."""
    plan = Plan(rx=PdoPlan(RX), tx=PdoPlan(TX))
    for direction, needs, preferred, out in ((RX, needs_rx, preferred_rx, plan.rx),
                                             (TX, needs_tx, preferred_tx, plan.tx)):
        wanted = []
        for n in needs:
            var = _variable(od, n.index)
            if var is None:
                if n.required:
                    raise PlanError(f"{device}: the object dictionary has no {object_name(n.index)}, which the "
                                    f"loop needs ({'received' if direction == RX else 'sent'} every cycle)")
                plan.notes.append(f"no {object_name(n.index)} in the object dictionary: not read")
                continue
            wanted.append((n.index, 0, len(var)))
        slots = _slots(od, direction, node_id)
        # 1. fixed mappings carrying a needed object are used as they are
        for no, slot in sorted(slots.items()):
            if slot["fixed"] and {i for i, _, _ in slot["default"]} & {i for i, _, _ in wanted}:
                for i, s, bits in slot["default"]:
                    var = _variable(od, i, s)
                    if var is None:
                        raise PlanError(f"{device}: {direction}{no} has a fixed mapping with 0x{i:04X}:{s:02X}, "
                                        "which the object dictionary does not describe")
                    if len(var) != bits:
                        raise PlanError(f"{device}: {direction}{no} maps {object_name(i)} with {bits} bits, the "
                                        f"dictionary gives it {len(var)}")
                out.pdos[no] = list(slot["default"])
                out.fixed.add(no)
        carried = {i for objs in out.pdos.values() for i, _, _ in objs}
        remaining = [w for w in wanted if w[0] not in carried]

        def room(no: int, obj) -> bool:
            objs = out.pdos.get(no, [])
            return (len(objs) < slots[no]["capacity"]
                    and sum(b for _, _, b in objs) + obj[2] <= 64)

        # 2. the rest into configurable PDOs: the preferred one first, else the first with room
        for no, objs in sorted(preferred.items()):
            if no not in slots or slots[no]["fixed"] or no in out.fixed:
                continue
            for w in [w for w in remaining if w[0] in objs]:
                if room(no, w):
                    out.pdos.setdefault(no, []).append(w)
                    remaining.remove(w)
        for w in list(remaining):
            for no in sorted(slots):
                if slots[no]["fixed"] or no in out.fixed:
                    continue
                if room(no, w):
                    out.pdos.setdefault(no, []).append(w)
                    remaining.remove(w)
                    break
        for w in remaining:
            need = next(n for n in needs if n.index == w[0])
            fixed = ", ".join(f"{direction}{no}" for no in sorted(slots) if slots[no]["fixed"]) or "none"
            msg = (f"{object_name(w[0])} fits in no {direction} (fixed mappings: {fixed}; no configurable "
                   f"{direction} with room)")
            if need.required:
                raise PlanError(f"{device}: {msg}")
            plan.notes.append(msg + ": not read")
        for no in out.pdos:
            out.cob_ids[no] = slots[no]["cob_id"]
        out.fixed |= {no for no in slots if slots[no]["fixed"]} & set(out.pdos)
    return plan


def configure_pdos(device, plan: Plan, trans_type: int = 1) -> list[str]:
    """Write ``plan`` to the device over SDO (``device``: a ``drivers.device.CanopenDevice`` in
    PRE-OPERATIONAL); PDOs outside the plan are disabled where their COB-ID is writable.
    Returns notes about PDOs it could not disable."""
    notes = []
    node = device.node
    od = node.object_dictionary
    for direction, pdo_plan, pdos in ((RX, plan.rx, node.rpdo), (TX, plan.tx, node.tpdo)):
        comm0, map0, _ = _BASE[direction]
        slots = _slots(od, direction, device.node_id)
        for no, slot in sorted(slots.items()):
            comm = od[comm0 + no - 1]
            planned = pdo_plan.pdos.get(no)
            if planned is None:
                if slot["cob_fixed"]:
                    if slot["cob_default"] is not None and not slot["cob_default"] & PDO_NOT_VALID:
                        notes.append(f"{direction}{no} cannot be disabled (COB-ID read-only)")
                    continue
                cur = device.sdo_read(comm0 + no - 1, 1)
                if not cur & PDO_NOT_VALID:
                    device.sdo_write(comm0 + no - 1, 1, cur | PDO_NOT_VALID)
                continue
            cob = pdo_plan.cob_ids[no]
            if no in pdo_plan.fixed:
                if not slot["cob_fixed"]:
                    device.sdo_write(comm0 + no - 1, 1, cob | PDO_NOT_VALID)
                if 2 in comm.subindices and comm[2].writable:
                    device.sdo_write(comm0 + no - 1, 2, trans_type)
                if not slot["cob_fixed"]:
                    device.sdo_write(comm0 + no - 1, 1, cob)
                continue
            if slot["count_fixed"]:  # the count is the device's: entries written within it, the rest empty
                write_entries_within_count(device, direction, no, planned, slot["count"], trans_type, cob,
                                           slot["cob_fixed"])
                continue
            m = pdos.map[no]
            m.clear()
            for index, sub, _ in planned:
                m.add_variable(index, sub)
            m.cob_id = cob
            m.trans_type = trans_type
            m.enabled = True
            device.sdo_call(m.save, f"{direction}{no} mapping")
    return notes


def write_entries_within_count(device, direction: str, number: int, planned, count: int, trans_type: int,
                               cob: int, cob_fixed: bool) -> None:
    """CiA 301 mapping order for a PDO whose entry count is read-only: PDO invalid, transmission
    type, entries 1..``count`` (the planned objects, then empty entries), PDO valid again."""
    comm0, map0, _ = _BASE[direction]
    comm = device.node.object_dictionary[comm0 + number - 1]
    if not cob_fixed:
        device.sdo_write(comm0 + number - 1, 1, cob | PDO_NOT_VALID)
    if 2 in comm.subindices and comm[2].writable:
        device.sdo_write(comm0 + number - 1, 2, trans_type)
    for k in range(1, count + 1):
        value = 0
        if k <= len(planned):
            index, sub, bits = planned[k - 1]
            value = (index << 16) | (sub << 8) | bits
        device.sdo_write(map0 + number - 1, k, value)
    if not cob_fixed:
        device.sdo_write(comm0 + number - 1, 1, cob)


def read_back(device, direction: str, number: int) -> tuple[int, int | None, list[tuple[int, int, int]]]:
    """(COB-ID entry, transmission type or None, mapping entries) of one PDO, read over SDO."""
    comm0, map0, _ = _BASE[direction]
    od = device.node.object_dictionary
    cob = device.sdo_read(comm0 + number - 1, 1)
    comm = od[comm0 + number - 1]
    tt = device.sdo_read(comm0 + number - 1, 2) if 2 in comm.subindices else None
    count = device.sdo_read(map0 + number - 1, 0)
    entries = []
    for s in range(1, count + 1):
        v = device.sdo_read(map0 + number - 1, s)
        entries.append((v >> 16, (v >> 8) & 0xFF, v & 0xFF))
    return cob, tt, entries


def verify_pdos(device, plan: Plan) -> None:
    """Read back every planned PDO and raise ``PlanError`` naming node, PDO and object for any
    difference: disabled, wrong COB-ID, not synchronous, objects missing or out of place."""
    where = f"{device.name} (node {device.node_id})"
    for direction, pdo_plan in ((RX, plan.rx), (TX, plan.tx)):
        for no, objs in sorted(pdo_plan.pdos.items()):
            cob, tt, entries = read_back(device, direction, no)
            if cob & PDO_NOT_VALID:
                raise PlanError(f"{where}: {direction}{no} read back disabled (COB-ID entry 0x{cob:08X}); it must "
                                f"carry {', '.join(object_name(i) for i, _, _ in objs)}")
            if cob & 0x7FF != pdo_plan.cob_ids[no]:
                raise PlanError(f"{where}: {direction}{no} read back on COB-ID 0x{cob & 0x7FF:03X}, expected "
                                f"0x{pdo_plan.cob_ids[no]:03X}")
            if tt is not None and not 1 <= tt <= 240 and not (direction == RX and tt == 0):
                raise PlanError(f"{where}: {direction}{no} transmission type {tt} read back: not cyclic "
                                "synchronous (1..240)")
            carried = [e for e in entries if e != (0, 0, 0)]  # empty entries (no bits) carry nothing
            for k, (i, s, bits) in enumerate(objs):
                if k >= len(carried) or carried[k] != (i, s, bits):
                    got = ", ".join(f"0x{e[0]:04X}:{e[1]:02X}/{e[2]}" for e in entries) or "nothing"
                    raise PlanError(f"{where}: {direction}{no} does not carry {object_name(i)} (entry {k + 1}); read "
                                    f"back: {got}")
            if len(carried) > len(objs):
                extra = ", ".join(f"0x{e[0]:04X}" for e in carried[len(objs):])
                raise PlanError(f"{where}: {direction}{no} read back with extra objects {extra}")


def set_local_maps(node, plan: Plan) -> None:
    """Make the local ``PdoMap`` objects of ``node`` match the verified plan (no SDO traffic)."""
    for pdo_plan, pdos in ((plan.rx, node.rpdo), (plan.tx, node.tpdo)):
        for no, m in pdos.map.items():
            objs = pdo_plan.pdos.get(no)
            m.clear()
            if objs is None:
                m.enabled = False
                continue
            for index, sub, _ in objs:
                m.add_variable(index, sub)
            m.cob_id = pdo_plan.cob_ids[no]
            m.trans_type = 1
            m.enabled = True
            m.subscribe()


def sizes(plan: PdoPlan) -> dict[int, int]:
    """Bytes of each planned PDO."""
    return {no: plan.bytes(no) for no in sorted(plan.pdos)}


def import_dictionary(path, node_id: int, device: str):
    """canopen's ``import_od`` with errors as ``PlanError`` naming the device and the file."""
    try:
        return canopen.import_od(str(path), node_id)
    except Exception as exc:  # malformed EDS: canopen raises various types
        raise PlanError(f"{device}: cannot read object dictionary {path}: {exc}") from None
