"""Precompiled PDO frames: the layouts ``drivers.mapping`` planned and verified, packed and unpacked
with one ``struct.Struct`` each instead of canopen's per-variable Python on every frame.

canopen stays in charge of configuration (planning, SDO writes, the local ``PdoMap`` objects);
once a device's maps are set, ``compile_map(pdo_map)`` gives a ``PdoLayout`` (object indices and one
little-endian struct covering the whole frame, as CiA 301 lays mapped objects end to end) and
``FastTpdo`` replaces canopen's ``PdoMap.on_message`` subscription of that COB-ID on the network:
one unpack per frame, values straight into the node's value cache, then the device's callback. A
layout canopen's struct types cannot express in one struct (objects not on byte boundaries, 24-,
40-bit ... integers, strings) gives None: that PDO keeps canopen's decoding.
"""
from __future__ import annotations

import struct
from typing import Callable

from canopen.objectdictionary import ODVariable


class PdoLengthError(ValueError):
    """A frame whose length is not that of its PDO's layout."""


class PdoLayout:
    """One PDO's mapped objects, in frame order: ``indices`` (object index per value), ``keys``
    ((index, subindex) per value), ``size`` bytes, ``struct`` (``<`` + one code per object)."""

    __slots__ = ("indices", "keys", "struct", "size")

    def __init__(self, keys: list[tuple[int, int]], codes: str):
        self.keys = tuple(keys)
        self.indices = tuple(k[0] for k in keys)
        self.struct = struct.Struct("<" + codes)
        self.size = self.struct.size

    def decode(self, data) -> tuple:
        """Values of the objects (ints; floats for REAL types) from one frame's data."""
        if len(data) != self.size:
            raise PdoLengthError(f"PDO frame of {len(data)} bytes, its mapping has {self.size}")
        return self.struct.unpack(data)

    def encode(self, values) -> bytes:
        """One frame's data from the objects' values (in ``keys`` order); out-of-range values raise
        ``struct.error``."""
        return self.struct.pack(*values)


def _code(var: ODVariable, bits: int) -> str | None:
    st = ODVariable.STRUCT_TYPES.get(var.data_type)
    if st is None:
        return None
    code = st.format.lstrip("<>=!@")
    if len(code) != 1 or st.size * 8 != bits:
        return None  # 24-, 40-, 48-, 56-bit integers: canopen's own decoding
    return code


def compile_map(pdo_map) -> PdoLayout | None:
    """The ``PdoLayout`` of a canopen ``PdoMap`` (its mapped variables as set locally), or None when
    one struct cannot express it (an object off a byte boundary, a type without a struct code)."""
    keys, codes, bit = [], [], 0
    for var in pdo_map:
        if var.offset != bit or var.offset % 8 or var.length % 8:
            return None
        code = _code(var.od, var.length)
        if code is None:
            return None
        keys.append((var.index, var.subindex))
        codes.append(code)
        bit += var.length
    if not keys:
        return None
    return PdoLayout(keys, "".join(codes))


class FastTpdo:
    """Receives one TPDO on ``network`` in place of canopen's ``PdoMap.on_message``: each frame of the
    layout's length is unpacked once, its values stored in ``values`` (a dict by object index, e.g. a
    ``BaseNode402``'s ``tpdo_values``), the data kept in ``pdo_map.data`` (so canopen's view of the
    map stays current), then ``on_frame(values_tuple)`` is called, then the callbacks others added
    to the map (``pdo_map.add_callback``) except those in ``skip`` (decoders this one replaces); a
    frame of another length goes to ``on_bad(data)`` and changes nothing. Runs in the network's
    receive thread."""

    __slots__ = ("network", "pdo_map", "layout", "values", "on_frame", "on_bad", "cob_id", "skip", "_unpack",
                 "_indices")

    def __init__(self, network, pdo_map, layout: PdoLayout, values: dict, on_frame: Callable[[tuple], None],
                 on_bad: Callable[[bytes], None], skip: tuple = ()):
        self.network = network
        self.pdo_map = pdo_map
        self.layout = layout
        self.values = values
        self.on_frame = on_frame
        self.on_bad = on_bad
        self.cob_id = pdo_map.cob_id
        self.skip = skip
        self._unpack = layout.struct.unpack
        self._indices = layout.indices

    def __call__(self, can_id: int, data, timestamp: float) -> None:
        try:
            vals = self._unpack(data)
        except struct.error:
            self.on_bad(data)
            return
        self.values.update(zip(self._indices, vals))
        m = self.pdo_map
        m.data = data
        m.timestamp = timestamp
        self.on_frame(vals)
        for cb in m.callbacks:
            if cb not in self.skip:
                cb(m)

    def attach(self) -> None:
        """Take the COB-ID over from canopen's ``PdoMap.on_message`` (idempotent; call again after
        canopen re-subscribed the map, e.g. a new ``set_local_maps``)."""
        subs = self.network.subscribers.setdefault(self.cob_id, [])
        subs[:] = [cb for cb in subs if cb != self.pdo_map.on_message and not isinstance(cb, FastTpdo)]
        subs.append(self)

    def detach(self) -> None:
        subs = self.network.subscribers.get(self.cob_id, [])
        subs[:] = [cb for cb in subs if cb is not self]
