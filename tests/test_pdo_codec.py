"""``drivers.pdo_codec``: the precompiled TPDO/RPDO frames give exactly canopen's values.

Offline (no bus): the configured robot's drives and pivot encoder get their planned PDO maps set
locally, as ``map_pdos`` does after verifying them on the device; frames are fed to the network as
the receive thread would. Each device is built twice — once decoding with ``FastTpdo``, once with
canopen's per-variable path — and both must read the same positions (counted across the 32-bit wrap
and the encoder's range), velocities, torques, statuswords and states, and both must ignore and
count frames of the wrong length.
"""
from __future__ import annotations

import struct

import canopen
import pytest
from hypothesis import Phase, given, settings
from hypothesis import strategies as st

from drivers import mapping, pdo_codec
from drivers.config import load_robot_config
from drivers.device import pdo_bytes
from drivers.robot import CanopenRobot


#: no shrinking: each example builds the robot twice (EDS parsing); a failure prints its example
FAST = (Phase.explicit, Phase.reuse, Phase.generate)


def _robot():
    return CanopenRobot(load_robot_config())


def _offline(dev, fast: bool, monkeypatch=None):
    """Set up ``dev``'s planned PDO maps locally and hook its TPDOs (fast or canopen's path)."""
    plan = dev.static_plan
    mapping.set_local_maps(dev.node, plan)
    dev.plan = plan
    dev.tpdos = sorted(plan.tx.pdos)
    if hasattr(dev, "_pos_tpdo"):
        dev._pos_tpdo = plan.tx.carrying(0x6064)
        dev._last_raw_pos = None
        dev.node.tpdo_values.clear()
        dev.node.tpdo_pointers.clear()
        dev.node.rpdo_pointers.clear()
        dev.node.setup_pdos(upload=False)
    else:
        dev.units_per_rev, dev.total_range, dev._last = 4096, 4096 * 64, None
    if fast:
        dev.hook_tpdos()
    else:
        original = pdo_codec.compile_map
        pdo_codec.compile_map = lambda m: None
        try:
            dev.hook_tpdos()
        finally:
            pdo_codec.compile_map = original
    return dev


def _maps(dev, direction):
    pdos = dev.node.tpdo if direction == "tx" else dev.node.rpdo
    plan = dev.static_plan.tx if direction == "tx" else dev.static_plan.rx
    return [(no, pdos[no]) for no in sorted(plan.pdos)]


def _planned_layouts(r):
    """(device, direction, PDO number, canopen map, compiled layout) of every planned PDO of ``r``,
    each device taken offline (its maps as planned)."""
    for dev in r.devices:
        _offline(dev, True)
        for direction in ("tx", "rx"):
            for no, m in _maps(dev, direction):
                yield dev, direction, no, m, pdo_codec.compile_map(m)


def test_layouts_compile_for_every_planned_pdo():
    r = _robot()
    for dev, direction, no, m, layout in _planned_layouts(r):
        assert layout is not None, f"{dev.name} {direction}PDO{no}"
        assert layout.size == pdo_bytes(m)
        assert layout.keys == tuple((v.index, v.subindex) for v in m)
    for dev in r.devices:
        for no, m in _maps(dev, "tx"):  # canopen's PdoMap.on_message replaced by one FastTpdo
            assert [type(cb) for cb in r.network.subscribers[m.cob_id]] == [pdo_codec.FastTpdo]


@settings(max_examples=20, deadline=None, phases=FAST)
@given(st.data())
def test_decode_and_encode_match_canopen(data):
    for _, _, _, m, layout in _planned_layouts(_robot()):
        frame = bytearray(data.draw(st.binary(min_size=layout.size, max_size=layout.size)))
        m.data = frame
        assert list(layout.decode(frame)) == [mapping_var.raw for mapping_var in m]
        values = layout.decode(frame)
        assert layout.encode(values) == bytes(frame)


def test_wrong_length_is_refused():
    r = _robot()
    d = _offline(r.drives[0], True)
    no, m = _maps(d, "tx")[0]
    layout = pdo_codec.compile_map(m)
    for n in (0, layout.size - 1, layout.size + 1, 9):
        with pytest.raises(pdo_codec.PdoLengthError, match=f"{n} bytes, its mapping has {layout.size}"):
            layout.decode(bytes(n))
    with pytest.raises(struct.error):
        layout.encode([2 ** 40] * len(layout.keys))


def _frame(m, values: dict) -> bytearray:
    layout = pdo_codec.compile_map(m)
    return bytearray(layout.encode([values.get(i, 0) for i in layout.indices]))


SW = [0x0000, 0x0040, 0x0021, 0x0023, 0x0027, 0x0007, 0x000F, 0x0008, 0x0237, 0x0217, 0x0260]


@settings(max_examples=15, deadline=None, phases=FAST)
@given(st.lists(st.tuples(st.integers(-2 ** 31, 2 ** 31 - 1), st.integers(-40000, 40000), st.integers(0, len(SW) - 1),
                          st.integers(-1000, 1000), st.booleans()), min_size=1, max_size=30),
       st.integers(-2 ** 31, 2 ** 31 - 1))
def test_drive_readings_identical_to_canopen(frames, start):
    """Position counts (32-bit wrap: steps of up to +-2^31 counts), velocity, torque, statusword and
    state after every frame; a short or long frame changes nothing and is counted."""
    fast, ref = _offline(_robot().drives[0], True), _offline(_robot().drives[0], False)
    pos = start
    for step, vel, sw_i, torque, bad in frames:
        pos = (pos + step + 2 ** 31) % 2 ** 32 - 2 ** 31  # the drive's int32 counter wraps
        values = {0x6064: pos, 0x606C: vel, 0x6041: SW[sw_i], 0x6077: torque, 0x6061: 10}
        for d in (fast, ref):
            for no, m in _maps(d, "tx"):
                f = _frame(m, values)
                if bad and no == d._pos_tpdo:
                    f = f + b"\x00" if len(f) < 8 else f[:-1]
                d.network.notify(m.cob_id, f, 0.0)
        a, b = fast.reading(), ref.reading()
        assert a == b or (a.torque != a.torque and b.torque != b.torque and a.position == b.position)
        assert fast.malformed == ref.malformed
        fa, fb = fast.check_statusword(), ref.check_statusword()  # a FAULT statusword: reported once
        assert fast.state == ref.state and str(fa) == str(fb)
    assert fast.malformed == sum(1 for f in frames if f[4])


def test_position_counts_across_the_wrap():
    d = _offline(_robot().drives[0], True)
    no = d._pos_tpdo
    m = d.node.tpdo[no]
    for raw in (2 ** 31 - 10, -2 ** 31 + 5, -2 ** 31 + 20, 2 ** 31 - 1):
        d.network.notify(m.cob_id, _frame(m, {0x6064: raw, 0x6041: 0x0027}), 0.0)
    assert d._pos_counts == 9  # +15 over the wrap, +15, then -21 back over it
    assert d.node.tpdo_values[0x6041] == 0x0027 and d.state == "OPERATION ENABLED"


@settings(max_examples=15, deadline=None, phases=FAST)
@given(st.lists(st.integers(0, 4096 * 64 - 1), min_size=1, max_size=20))
def test_encoder_identical_to_canopen(raws):
    fast, ref = _offline(_robot().encoder, True), _offline(_robot().encoder, False)
    assert any(isinstance(cb, pdo_codec.FastTpdo) for cb in fast.network.subscribers[fast.node.tpdo[1].cob_id])
    for raw in raws:
        for d in (fast, ref):
            m = d.node.tpdo[1]
            d.network.notify(m.cob_id, _frame(m, {0x6004: raw}), 0.0)
            d.network.notify(m.cob_id, b"\x01\x02", 0.0)  # short: ignored
        assert fast.position == ref.position
    assert fast.malformed == ref.malformed == len(raws)


def test_hooking_again_keeps_one_decoder():
    """A reconfiguration (canopen re-subscribes its maps) leaves exactly one FastTpdo per COB-ID."""
    d = _offline(_robot().drives[0], True)
    for no, m in _maps(d, "tx"):
        m.subscribe()
    d.node.setup_pdos(upload=False)
    d.hook_tpdos()
    for no, m in _maps(d, "tx"):
        subs = d.network.subscribers[m.cob_id]
        assert sum(isinstance(cb, pdo_codec.FastTpdo) for cb in subs) == 1
        assert m.on_message not in subs
    assert isinstance(d.network, canopen.Network)


def test_callbacks_others_add_to_a_map_still_run():
    """What a caller hooks on a TPDO map (``add_callback``) still sees each valid frame, not BaseNode402's
    per-variable decoder the fast path replaces."""
    d = _offline(_robot().drives[0], True)
    no, m = _maps(d, "tx")[0]
    seen = []
    m.add_callback(lambda pdo_map: seen.append(bytes(pdo_map.data)))
    f = _frame(m, {0x6041: 0x0027})
    d.network.notify(m.cob_id, f, 0.0)
    d.network.notify(m.cob_id, f[:-1], 0.0)  # short: not seen
    assert seen == [bytes(f)]
    assert d.node.on_TPDOs_update_callback in m.callbacks  # there, and skipped


class _Capture:
    """A stand-in bus: keeps what is sent."""

    def __init__(self):
        self.sent = []

    def send(self, msg, timeout=None):
        self.sent.append((msg.arbitration_id, bytes(msg.data)))


@settings(max_examples=15, deadline=None, phases=FAST)
@given(st.lists(st.tuples(st.sampled_from([0x0000, 0x0002, 0x0006, 0x0007, 0x000F, 0x0080]),
                          st.integers(-32768, 32767)), min_size=1, max_size=10))
def test_rpdo_frames_identical_to_canopen(commands):
    """The RPDOs ``transmit`` sends (controlword, target torque, the constant fill) are the bytes
    canopen's variables give."""
    fast, ref = _offline(_robot().drives[0], True), _offline(_robot().drives[0], False)
    for d in (fast, ref):
        d.network.bus = _Capture()
        d._fill = {i: (10 if i == 0x6060 else 0) for no, objs in d.static_plan.rx.pdos.items()
                   for i, _, _ in objs if i not in (0x6040, 0x6071)}
        d._rpdo_frames = None
    original = pdo_codec.compile_map
    pdo_codec.compile_map = lambda m: None
    try:
        ref.transmit()  # compiles nothing: canopen's path from now on
    finally:
        pdo_codec.compile_map = original
    fast.transmit()
    assert fast._rpdo_frames and not ref._rpdo_frames
    for cw, pm in commands:
        for d in (fast, ref):
            d.controlword, d.target_permille = cw, pm
            d.transmit()
    assert fast.network.bus.sent == ref.network.bus.sent
    assert len(fast.network.bus.sent) == len(commands) + 1
