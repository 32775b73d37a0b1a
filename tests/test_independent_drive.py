"""``CanopenRobot`` (unchanged) against CiA 402 drives written from the standards on raw python-can
frames (``tests/independent_drive.py``, no code shared with ``sim/canopen_slaves.py``): boot,
mapping, enable, torque, EMCY, an ignored quick stop, a drive's own quick stop under the cyclic
controlword, a silent drive, a stalled master, a rejected mapping, a missing 0x6007 and the
reaction's last allowed SYNC. Every reaction is judged from the drives' own records."""
from __future__ import annotations

import configparser
import time
import uuid
from contextlib import contextmanager
from dataclasses import replace

import can
import pytest

from drivers.config import EncoderConfig, load_robot_config
from drivers.faults import DeviceConfigError
from drivers.robot import CanopenRobot
from independent_drive import IndependentDrive
from otbot_hw.robot import RobotFault
from sim.lockstep import LockstepCanopenRobot

CFG = load_robot_config()
ENABLED = "OPERATION ENABLED"


def config(channel: str, eds=None, heartbeats: float | None = 0.5, **bus):
    """The robot's configuration on ``channel``, phi_p from the pivot drive, no IMU; ``heartbeats``:
    heartbeat consumer times at least this (s) both ways where they are not under test (a loaded
    machine must not trip them), None: as configured."""
    cfg = CFG.replace_bus(interface="virtual", channel=channel, **bus)
    if heartbeats is not None:
        cfg = cfg.relaxed(heartbeats)
    return replace(cfg, drives=tuple(replace(d, eds=eds or d.eds) for d in cfg.drives),
                   pivot_encoder=EncoderConfig(source="drive"), imu=None)


@contextmanager
def independent(realtime: bool = False, eds=None, absent=(), reject_mapping=(), open_=True,
                heartbeats: float | None = 0.5, edit=None, **bus):
    """Three independent drives (nodes 1-3) and a ``CanopenRobot`` on a fresh virtual channel;
    ``edit``: a function of the configuration that returns the one to use."""
    channel = f"indep-{uuid.uuid4().hex[:10]}"
    cfg = config(channel, eds, heartbeats, **bus)
    if edit is not None:
        cfg = edit(cfg)
    drives = [IndependentDrive(d.node_id, channel, absent=absent, reject_mapping=reject_mapping).start()
              for d in cfg.drives]
    bus = can.Bus(interface="virtual", channel=channel)
    # paced: the real driver as it is; else lockstep, the simulated back end's (no period is kept)
    robot = CanopenRobot(cfg, bus=bus) if realtime else LockstepCanopenRobot(cfg, bus=bus)
    try:
        if open_:
            robot.open()
        yield robot, drives
    finally:
        robot.close()
        for d in drives:
            d.close()


def cycle(robot, u=(0.0, 0.0, 0.0), period: float | None = None):
    """One loop cycle (write, read); a faulted robot only reads. ``period``: pace it (s)."""
    if period:  # the test is the loop: it ticks the robot's clock (one SYNC per period)
        robot.clock.wait()
    try:
        robot.write(list(u))
    except RobotFault:
        pass
    return robot.read()


def test_boot_mapping_enable_and_torque():
    with independent() as (robot, drives):
        for d in drives:
            assert d.get(0x1016, 1) == (CFG.bus.master_node_id << 16) | 500
            assert d.get(0x6007) == 3 and d.get(0x605A) == CFG.drives[0].quick_stop_option == 2
            assert d.get(0x6060) == d.get(0x6061) == 10
            assert d._map(0x1600) == [(0x6040, 0, 16), (0x6071, 0, 16)]
            assert d._map(0x1A00) == [(0x6041, 0, 16), (0x6064, 0, 32), (0x6077, 0, 16)]
            assert d._map(0x1A01) == [(0x606C, 0, 32), (0x603F, 0, 16), (0x6061, 0, 8)]
            assert d.get(0x1006) == 0 and d.get(0x1400, 5) == 0  # lockstep: no period kept
        robot.enable()
        for d in drives:
            assert [(old, new) for _, _, old, new, _ in d.transitions] == [
                ("SWITCH ON DISABLED", "READY TO SWITCH ON"), ("READY TO SWITCH ON", "SWITCHED ON"),
                ("SWITCHED ON", ENABLED)]
            # "enable operation" only from SWITCHED ON (then to stay enabled)
            assert all(state in ("SWITCHED ON", ENABLED) for _, cw, state in d.received_cw if cw == 0x000F)
        for _ in range(3):
            s = cycle(robot, (2.0, -2.0, 2.0))
        assert [d.get(0x6071) for d in drives] == [100, 100, 100]  # 2 N m / (10 x 2 N m / 1000), polarity
        assert s.joint_torque.tolist() == pytest.approx([2.0, -2.0, 2.0])
        assert s.drive_states == (ENABLED,) * 3 and not s.faults


@pytest.mark.parametrize("realtime", [False, True])
def test_an_emcy_stops_every_drive_and_only_the_faulty_one_is_reported(realtime):
    rate = 50.0
    pace = 1 / rate if realtime else None
    for attempt in range(3):  # paced: a machine stall before the fault spoils the set-up, not the test
        with independent(realtime=realtime, control_rate=rate) as (robot, drives):
            try:
                robot.enable()
                for _ in range(3):
                    cycle(robot, (1.0, 1.0, 1.0), pace)
            except RobotFault:
                pass
            if robot.faults:
                assert realtime and attempt < 2, robot.faults
                continue
            s0 = drives[0].syncs
            drives[0].inject_fault(0x2310)
            for _ in range(6):
                cycle(robot, (1.0, 1.0, 1.0), pace)
            for d in drives:
                left = [sy for _, sy, old, _, _ in d.transitions if old == ENABLED and sy >= s0]
                assert left and left[0] - s0 <= CFG.bus.reaction_timeout, (d.node_id, d.transitions)
                assert d.state != ENABLED
            # the drives the master quick-stopped are expected out of OPERATION ENABLED: no second fault
            assert {f.device for f in robot.faults} == {"right_wheel"}, robot.faults
            assert robot.reactions[0]["escalated"] == [] and len(robot.reactions) == 1
        break


def _reaction_to_a_fault_of_the_right_wheel(robot, drives, **pivot) -> dict:
    """Enable, one cycle at 1 N m, the pivot drive given ``pivot``'s misbehaviour, a fault (0x2310) in
    the right wheel's drive, four cycles: the master's reaction record."""
    robot.enable()
    cycle(robot, (1.0, 1.0, 1.0))
    for name, value in pivot.items():
        setattr(drives[2], name, value)
    drives[0].inject_fault(0x2310)
    for _ in range(4):
        cycle(robot)
    return robot.reactions[0]


def test_an_ignored_quick_stop_is_escalated_once_and_close_brings_the_node_back():
    with independent() as (robot, drives):
        rec = _reaction_to_a_fault_of_the_right_wheel(robot, drives, ignore_quick_stop=True)
        assert rec["escalated"] == ["pivot"] and len(robot.reactions) == 1
        # NMT STOP: the drive applied its abort connection option (quick stop) on leaving OPERATIONAL
        assert drives[2].state != ENABLED and drives[2].nmt == 0x04
        time.sleep(0.3)  # heartbeats report STOPPED: the master's own command, not a new fault
        cycle(robot)
        assert not any(f.kind == "nmt" for f in robot.faults), robot.faults
        assert len(robot.reactions) == 1
        problems = robot.close()
        t_close = time.monotonic()
        assert any("NMT STOP" in p for p in problems)
        assert drives[2].nmt == 0x7F and drives[2].get(0x1016, 1) == 0  # back, its consumer off
        time.sleep(0.5 + 0.2)  # the drives' (relaxed) consumer time and then some
        for d in drives:
            assert not [c for t, c in d.emcy_sent if t > t_close], (d.node_id, d.emcy_sent)


def test_a_drives_own_quick_stop_under_the_cyclic_controlword_is_never_undone():
    with independent() as (robot, drives):
        robot.enable()
        for _ in range(3):
            cycle(robot, (1.0, 1.0, 1.0))
        t_stop = time.monotonic()
        robot.write([1.0, 1.0, 1.0])
        drives[1].own_quick_stop()  # no EMCY: the master learns it from the statusword only
        s_stop = drives[1].syncs
        robot.read()
        for _ in range(8):
            cycle(robot, (1.0, 1.0, 1.0))
        d = drives[1]
        assert not d.enabled_after(t_stop), d.transitions
        # the word in flight when it stopped aside, it never again received "enable operation"
        late = [(sy, cw, st) for sy, cw, st in d.received_cw if sy > s_stop + 1]
        assert late and all(cw != 0x000F for _, cw, _ in late), late
        assert all(not dd.enabled_after(t_stop) for dd in drives)
        f = next(f for f in robot.faults if f.device == "left_wheel")
        assert "without a command" in f.meaning and "QUICK STOP ACTIVE" in f.meaning
        assert {f.device for f in robot.faults} == {"left_wheel"}


def test_a_silent_drive_is_reported_and_every_drive_stops():
    with independent() as (robot, drives):
        robot.enable()
        cycle(robot, (1.0, 1.0, 1.0))
        drives[2].silent = True
        t0 = time.monotonic()
        for _ in range(CFG.bus.tpdo_timeout + 3):
            cycle(robot)
        assert any(f.kind == "stale" and f.device == "pivot" for f in robot.faults)
        assert drives[0].state != ENABLED and drives[1].state != ENABLED
        assert robot.reactions[0]["escalated"] == ["pivot"]
        # the silent drive hears nothing: its own heartbeat consumer stops it
        deadline = time.monotonic() + 0.5 + 1.0
        while drives[2].state == ENABLED and time.monotonic() < deadline:
            time.sleep(0.01)
        assert drives[2].state != ENABLED
        assert drives[2].left_enabled_at(t0) - t0 <= 0.5 + 0.5  # (relaxed) consumer time


def test_a_stalled_master_stops_every_drive_within_three_periods():
    """Paced, the robot alive, its loop no longer calling read/write: every drive is out of
    OPERATION ENABLED within 3 periods of the last SYNC (its SYNC watchdog, 0x1006, armed on every
    paced run), and the master withholds its heartbeat after ``bus.loop_liveness`` periods."""
    rate = 50.0
    period = 1 / rate
    for attempt in range(3):
        with independent(realtime=True, control_rate=rate) as (robot, drives):
            assert all(d.get(0x1006) == int(period * 1e6) and d.get(0x1400, 5) == 60 for d in drives)
            try:
                robot.enable()
                for _ in range(10):
                    cycle(robot, (1.0, 1.0, 1.0), period)
            except RobotFault:
                pass
            t_stall = time.monotonic()
            if robot.faults or any(d.state != ENABLED for d in drives):
                assert attempt < 2, f"every attempt disturbed before the stall: {robot.faults}"
                continue
            time.sleep(0.3)  # the loop stalls; the robot object, its threads and its heartbeat live on
            if any(t > t_stall for d in drives for t, _ in d.late_checks):
                assert attempt < 2, "every attempt's drives were held up by the machine"
                continue  # the drives' own watchdog thread was held up: no measurement of the master
            for d in drives:
                left = d.left_enabled_at(t_stall - period)
                assert left is not None, d.transitions
                last_sync = max(t for t in d.sync_times if t <= t_stall)  # the loop's last SYNC
                assert left - last_sync <= 3 * period, (d.node_id, left - last_sync)
            # by their SYNC watchdog, or by the master's reaction to the first one's EMCY
            causes = [next(c for t, _, old, _, c in d.transitions if t == d.left_enabled_at(t_stall - period)
                           and old == ENABLED) for d in drives]
            assert any("SYNC lost" in c for c in causes), causes
            assert all("SYNC lost" in c or c == "controlword 0x0002" for c in causes), causes
        break


def test_a_stalled_loop_withholds_the_heartbeat_whatever_thread_is_alive():
    """Lockstep (no SYNC or RPDO watchdog armed): the loop stops while the drives are enabled; the
    heartbeat thread lives on but sends nothing after ``bus.loop_liveness`` periods, so the drives'
    heartbeat consumers (0x1016) stop them: each by its own, or by the master's reaction to the first
    one's EMCY 0x8130 (a drive whose watchdog thread runs a little later is quick-stopped by the master
    first; the drives then no longer enabled, the master's heartbeat may resume before its consumer
    expires)."""
    period = CFG.bus.period
    consumer = CFG.drives[0].master_heartbeat_consumer

    def drives_heartbeats_relaxed(cfg):
        """The master's consumer of the drives' heartbeats relaxed (not under test: a drive's heartbeat
        late on a loaded machine would start the master's own reaction, which stops the drives first and
        ends the stall); the drives' consumer of the master and the loop's liveness as configured."""
        return replace(cfg, drives=tuple(replace(d, heartbeat_consumer=max(1.0, d.heartbeat_consumer))
                                         for d in cfg.drives))

    with independent(heartbeats=None, edit=drives_heartbeats_relaxed) as (robot, drives):
        robot.enable()
        for _ in range(5):
            cycle(robot, (1.0, 1.0, 1.0))
        t_stall = time.monotonic()
        time.sleep(consumer + 0.3)
        assert robot.master_heartbeat.running and robot.master_heartbeat.withheld >= 1
        assert any("master heartbeat withheld" in p for p in robot.problems)  # close() reports it
        for d in drives:
            last_hb = max(t for t in d.master_heartbeats if t < t_stall + consumer)
            # the last heartbeat went out at most liveness periods (plus one heartbeat period) after the stall
            assert last_hb - t_stall <= CFG.bus.loop_liveness * period + CFG.bus.master_heartbeat + 0.05
            left = d.left_enabled_at(t_stall)
            assert left is not None and left - last_hb <= consumer + 0.05, (d.node_id, d.transitions)
        causes = {d.node_id: next(c for t, _, old, _, c in d.transitions if t == d.left_enabled_at(t_stall)
                                  and old == ENABLED) for d in drives}
        by_consumer = {d.node_id for d in drives if any(code == 0x8130 for _, code in d.emcy_sent)}
        assert by_consumer, (causes, robot.faults)  # at least one drive's own consumer tripped
        for node, cause in causes.items():
            assert ("master heartbeat lost" in cause and node in by_consumer) or cause == "controlword 0x0002", \
                (node, cause, by_consumer)
        assert any(f.kind == "emcy" and f.code == 0x8130 for f in robot.faults), robot.faults


def test_a_refused_mapping_is_a_configuration_error_naming_the_object():
    with pytest.raises(DeviceConfigError, match=r"right_wheel \(node 1\).*TPDO1.*0x06040041"):
        with independent(reject_mapping={0x6077}):
            pass


def _without_6007(tmp_path):
    cp = configparser.RawConfigParser()
    cp.optionxform = str
    cp.read(CFG.drives[0].eds)
    cp.remove_section("6007")
    for listing in ("MandatoryObjects", "OptionalObjects", "ManufacturerObjects"):
        if not cp.has_section(listing):
            continue
        items = [v for k, v in cp.items(listing) if k != "SupportedObjects" and int(v, 0) != 0x6007]
        cp.remove_section(listing)
        cp.add_section(listing)
        cp.set(listing, "SupportedObjects", str(len(items)))
        for k, v in enumerate(items, start=1):
            cp.set(listing, str(k), v)
    path = tmp_path / "no_6007.eds"
    with open(path, "w") as fh:
        cp.write(fh, space_around_delimiters=False)
    return path


def test_a_drive_without_0x6007_is_said_once_and_its_own_default_applies(tmp_path):
    with independent(eds=_without_6007(tmp_path), absent={0x6007}, heartbeats=None) as (robot, drives):
        assert any("0x6007" in w for w in robot.warnings), robot.warnings
        robot.enable()
        cycle(robot, (1.0, 1.0, 1.0))
        robot.master_heartbeat.stop()  # the master is lost
        t0 = time.monotonic()
        deadline = t0 + CFG.drives[0].master_heartbeat_consumer + 1.0
        aborts = lambda d: [x for _, _, ev, x in d.log if ev == "abort connection"]  # noqa: E731
        while not all(aborts(d) for d in drives) and time.monotonic() < deadline:
            time.sleep(0.01)
        # each drive applied its own default (CiA 402: 0x6007 = 1, fault); the first to find the
        # master lost went to FAULT, the others may have been disabled by the master's reaction first
        assert all(aborts(d) and "0x6007 = 1" in aborts(d)[0] for d in drives)
        first = min(drives, key=lambda d: next(t for t, _, ev, _ in d.log if ev == "abort connection"))
        assert first.state == "FAULT" and first.get(0x603F) == 0x8130
        assert all(d.state != ENABLED for d in drives)


@pytest.mark.parametrize("timeout,delay,escalated", [(1, 0, False), (2, 1, False), (2, 2, True)])
def test_a_drive_confirming_at_the_last_allowed_sync_is_confirmed(timeout, delay, escalated):
    """bus.reaction_timeout = N periods: a drive whose quick stop shows at reaction SYNC N is
    confirmed, one whose shows at SYNC N + 1 gets NMT STOP."""
    with independent(reaction_timeout=timeout) as (robot, drives):
        rec = _reaction_to_a_fault_of_the_right_wheel(robot, drives, quick_stop_delay=delay)
        assert rec["escalated"] == (["pivot"] if escalated else []), rec
        assert ("pivot" in rec["confirmed"]) is not escalated
        assert drives[2].state != ENABLED
