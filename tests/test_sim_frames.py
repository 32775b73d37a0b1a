"""The simulated bus's fast paths change no frame: ``sim.bus_robot.SimVirtualBus`` (a frame per
receiver built field by field, not deep-copied; a SYNC's TPDOs queued with one wake-up) and the
simulated slaves' precompiled PDO frames (``sim.canopen_slaves.node``) put on the bus, in the same order, the bytes python-can's
``VirtualBus`` and canopen's per-variable PDO path put there; the bench's BLF bus log still sees
every frame of the master's bus.

The same lockstep run (boot, enable, torques that change every cycle, a quick stop) is made twice, once
with each path, while a plain python-can ``VirtualBus`` listens on the channel (opened first, so it
hears every frame before the master or the plant reacts to it). Heartbeats (timer threads) are left
out of the ordered comparison; everything else — NMT, SDO, SYNC, RPDOs, TPDOs, EMCY — must be equal
frame by frame.
"""
from __future__ import annotations

import collections
import time
import uuid

import can
import numpy as np
import pytest
from can.interfaces.virtual import VirtualBus

import sim.bus_robot as bus_robot
import sim.canopen_slaves.node as node_mod
import sim.plant as plant_mod
from drivers.config import load_robot_config
from otbot_hw.runtime.bench.buslog import BusLog
from otbot_hw.sensors import NoiseModel

CFG = load_robot_config()
CYCLES = 40


def _key(msg: can.Message) -> tuple:
    return (msg.arbitration_id, msg.is_extended_id, msg.is_remote_frame, msg.is_error_frame, msg.dlc,
            bytes(msg.data))


def _run(monkeypatch, fast: bool, blf=None) -> tuple[list, dict, int]:
    """The frames a listener on the channel heard (in order) during one simulated run, the plant's
    report, and how many frames it had heard when the ``BusLog`` on the master's network (``blf``:
    its path) was attached, once the robot booted, and when it was stopped, after the quick stop."""
    with monkeypatch.context() as m:
        if not fast:
            m.setattr(bus_robot, "SimVirtualBus", VirtualBus)
            m.setattr(node_mod, "_layout", lambda pdo_map: None)
            m.setattr(plant_mod.Plant, "_send_frames",  # canopen's send, one frame at a time
                      lambda self, frames: [self.network.send_message(cob, data) for cob, data in frames])
        hexid = uuid.uuid4().hex
        m.setattr(bus_robot.uuid, "uuid4", lambda: uuid.UUID(hexid))
        sniffer = VirtualBus(channel=f"otbot-sim-{hexid[:12]}")
        log = None
        attached = stopped = 0
        try:
            with bus_robot.simulated_robot(CFG.relaxed(1.0), with_imu=False, noise=NoiseModel(),
                                           position_offsets=(2 ** 31 - 300, 5, 123)) as (robot, plant):
                if blf is not None:
                    attached = sniffer.queue.qsize()  # (lockstep: nothing is in flight but heartbeats)
                    log = BusLog(blf).attach(robot.network)
                robot.enable()
                for k in range(CYCLES):
                    robot.write(np.array([40.0 * np.sin(0.3 * k), -25.0 + k, 3.0 * (-1) ** k]))
                    robot.read()
                robot.quick_stop()
                if log is not None:
                    time.sleep(0.2)  # the receive thread logs the last TPDOs after the master has them
                    stopped = sniffer.queue.qsize()  # (no SYNC until close(): nothing cyclic in flight)
                    log.stop()
                    log = None
            frames = []
            while (msg := sniffer.recv(0)) is not None:
                frames.append(msg)
        finally:
            if log is not None:
                log.stop()
            sniffer.shutdown()
        return frames, plant.after, (attached, stopped)


def _ordered(frames) -> list:
    return [_key(f) for f in frames if not 0x700 <= f.arbitration_id <= 0x7FF]


def test_fast_paths_put_the_same_frames_on_the_bus_as_python_can_and_canopen(monkeypatch, tmp_path):
    fast, after_fast, (attached, stopped) = _run(monkeypatch, True, blf=tmp_path / "bus.blf")
    ref, after_ref, _ = _run(monkeypatch, False)
    a, b = _ordered(fast), _ordered(ref)
    assert len(a) > CYCLES * 11  # SYNC, 7 TPDOs, 3 RPDOs per cycle, and the boot's SDO traffic
    assert a == b
    pdo_ids = {k[0] for k in a if 0x180 <= k[0] < 0x580}
    assert len(pdo_ids) >= 7  # TPDOs and RPDOs of every drive and the encoder compared
    assert [d["state"] for d in after_fast["drives"]] == [d["state"] for d in after_ref["drives"]]
    # every frame a receiver gets is its own (a copy), stamped with the channel like VirtualBus's
    assert all(f.channel == fast[0].channel and f.is_rx for f in fast)
    assert len({id(f.data) for f in fast}) == len(fast)

    # the BLF bus log (attached once booted, before enabling) saw every SYNC and PDO of the run
    logged = list(can.BLFReader(str(tmp_path / "bus.blf")))
    cyclic = lambda frames: collections.Counter(  # noqa: E731
        _key(f) for f in frames if f.arbitration_id == 0x80 or 0x180 <= f.arbitration_id < 0x580)
    assert cyclic(logged) == cyclic(fast[attached:stopped])
    assert sum(cyclic(logged).values()) > CYCLES * 11


def test_sim_virtual_bus_gives_each_receiver_its_own_frame():
    ch = f"otbot-test-{uuid.uuid4().hex[:8]}"
    tx, rx1, rx2 = bus_robot.SimVirtualBus(channel=ch), VirtualBus(channel=ch), bus_robot.SimVirtualBus(channel=ch)
    try:
        msg = can.Message(arbitration_id=0x201, data=[1, 2, 3, 4], is_extended_id=False)
        tx.send(msg)
        msg.data[0] = 99  # the sender reusing its frame changes nothing already sent
        a, b = rx1.recv(1), rx2.recv(1)
        assert tx.recv(0) is None  # no own frames
        assert a is not b and a.data is not b.data
        for r in (a, b):
            assert bytes(r.data) == b"\x01\x02\x03\x04" and r.arbitration_id == 0x201 and r.is_rx
            assert r.channel == ch and r.dlc == 4 and not r.is_extended_id
        batch = [can.Message(arbitration_id=0x181 + i, data=[i] * (i % 9), is_extended_id=False) for i in range(7)]
        tx.send_many(batch)
        for r in (rx1, rx2):
            got = [r.recv(1) for _ in batch]
            assert [(g.arbitration_id, bytes(g.data), g.dlc) for g in got] == \
                [(b.arbitration_id, bytes(b.data), b.dlc) for b in batch]
            assert all(g is not b and g.is_rx and g.channel == ch for g, b in zip(got, batch))
            assert r.recv(0) is None
        tx.shutdown()
        with pytest.raises(can.CanOperationError):
            tx.send(msg)
    finally:
        for b_ in (rx1, rx2):
            b_.shutdown()
