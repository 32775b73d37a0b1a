"""Every watchdog time pinned from both sides, with bounds derived from the configuration: the
master's heartbeat consumer (timeout and check period), the stale-TPDO window (realtime and
lockstep), and the drives' own watchdogs the master configures at boot (its heartbeat, SYNC
loss, RPDO deadline), measured on the simulated drives' own clocks."""
from __future__ import annotations

import time
from dataclasses import replace

import pytest

from drivers.config import LOCKSTEP_TIMEOUT, load_robot_config
from otbot_hw.robot import RobotFault
from sim.canopen_slaves.node import SYNC_LOSS_CYCLES
from sim.bus_robot import simulated_robot

CFG = load_robot_config()
SLACK = 0.1  # s: scheduling noise a loaded 2-core machine adds to a wall-clock watchdog
# The designed windows (docs/bus.md), written out so that a changed constant shows:
TPDO_WINDOW = 0.8  # realtime: part of the period a read() waits for the TPDOs of its SYNC
LOCKSTEP_SETTLE = 0.05  # lockstep: s the others are awaited after the first TPDO of a SYNC


def with_times(cfg, consumer=None, master_consumer=None, rate=None):
    if rate is not None:
        cfg = cfg.replace_bus(control_rate=rate)
    drives = tuple(replace(d, heartbeat_consumer=consumer or d.heartbeat_consumer,
                           master_heartbeat_consumer=master_consumer or d.master_heartbeat_consumer)
                   for d in cfg.drives)
    enc = replace(cfg.pivot_encoder, heartbeat_consumer=consumer or cfg.pivot_encoder.heartbeat_consumer)
    return replace(cfg, drives=drives, pivot_encoder=enc)


def test_master_heartbeat_consumer_timeout_and_check_period():
    consumer, producer = 0.4, CFG.drives[0].heartbeat_producer
    cfg = with_times(CFG, consumer=consumer)
    with simulated_robot(cfg, with_imu=False, heartbeat_consumer=None) as (robot, plant):
        robot.enable()
        # the watcher checks every consumer / 10 s, with or without control cycles
        calls = []
        real = robot.heartbeats.check
        robot.heartbeats.check = lambda *a: calls.append(time.monotonic()) or real(*a)
        time.sleep(0.5)
        robot.heartbeats.check = real
        assert 0.5 / (consumer / 10) * 0.6 <= len(calls) <= 0.5 / (consumer / 10) + 2, len(calls)
        plant.drives[2].go_silent()
        t0 = time.monotonic()
        while not any(f.kind == "heartbeat" for f in robot.faults):
            assert time.monotonic() - t0 < 3 * consumer, "no heartbeat fault"
            time.sleep(0.002)
        elapsed = time.monotonic() - t0
        f = next(f for f in robot.faults if f.kind == "heartbeat")
        assert f.device == "pivot" and f.code == 0x8130
        silence = float(f.meaning.split("no heartbeat for ")[1].split(" s")[0])
        # silent since the last heartbeat: the fault comes after the consumer time, at most one check later
        assert consumer <= silence <= consumer + consumer / 10 + SLACK, silence
        assert consumer - producer - 0.01 <= elapsed <= consumer + consumer / 10 + SLACK, elapsed


def test_stale_tpdo_window_realtime_and_lockstep():
    rate = 25.0
    cfg = CFG.replace_bus(control_rate=rate)
    period = 1 / rate
    n = cfg.bus.tpdo_timeout
    def realtime():
        with simulated_robot(cfg, with_imu=False, realtime=True) as (robot, plant):
            def cycles():
                for _ in range(3):
                    robot.write([0.0, 0.0, 0.0])
                    s = robot.read()
                    if time.monotonic() - s.host_time >= TPDO_WINDOW * period:  # all TPDOs in time, else
                        raise Disturbed("a TPDO of the set-up came after its window (the plant held up)")

            _set_up(robot, cycles)
            _undisturbed(robot, plant)
            plant.encoder.drop_tpdos = True
            for k in range(n):
                robot.write([0.0, 0.0, 0.0])
                s = robot.read()
                waited = time.monotonic() - s.host_time
                if k < n - 1 and s.faults:  # another TPDO late too: a stale fault one SYNC early
                    raise Disturbed(f"a fault before the encoder's stale window ran out: {s.faults}")
                assert bool(s.faults) == (k == n - 1), (k, s.faults)
                if k < n - 1:  # (the last one also runs the fault reaction)
                    # a missing TPDO is awaited for the window, never into the next period; a wait
                    # that returns later than that is a thread the machine woke late: run again
                    assert TPDO_WINDOW * period - 0.002 <= waited, waited
                    if waited > period + SLACK / 2:
                        raise Disturbed(f"the read returned {waited:.3f} s after its SYNC (window "
                                        f"{TPDO_WINDOW * period:.3f} s): the thread woke late")

    _measured(realtime)
    with simulated_robot(CFG, with_imu=False) as (robot, plant):  # lockstep
        robot.enable()
        plant.encoder.drop_tpdos = True
        robot.write([0.0, 0.0, 0.0])
        arrivals = []
        m = robot.drives[0].node.tpdo[1]
        m.add_callback(lambda _m: arrivals.append(time.monotonic()))
        s = robot.read()
        waited = time.monotonic() - arrivals[-1]
        # the plant answered the SYNC; the missing encoder TPDO is awaited LOCKSTEP_SETTLE more
        assert LOCKSTEP_SETTLE - 0.002 <= waited <= LOCKSTEP_SETTLE + SLACK, waited
        assert time.monotonic() - s.host_time < LOCKSTEP_TIMEOUT + SLACK


def test_drives_stop_when_the_masters_heartbeat_stops():
    # the master's consumer of the nodes' heartbeats is not under test: widened (1 s) so that a loaded
    # machine spoils fewer set-ups
    cfg = with_times(CFG, consumer=1.0, master_consumer=0.15)
    consumer, producer = 0.15, cfg.bus.master_heartbeat

    def scenario():
        with simulated_robot(cfg, with_imu=False, heartbeat_consumer=None) as (robot, plant):
            _set_up(robot, lambda: _one_cycle(robot))
            _undisturbed(robot, plant)
            assert all(d.node.sdo[0x1016][1].raw == (cfg.bus.master_node_id << 16 | 150) for d in robot.drives)
            assert all(d.od_value(0x6007) == 3 for d in plant.drives)  # quick stop, as configured
            robot.master_heartbeat.stop()  # the master's process hangs or dies: its heartbeat stops
            t0 = time.monotonic()
            assert plant.wait_all_stopped(consumer + 5.0), [d.state for d in plant.drives]
            for d in plant.drives:
                # quick stop by itself (the master, told by EMCY, may have disabled it since)
                assert d.state in ("QUICK STOP ACTIVE", "SWITCH ON DISABLED") and d.applied_permille() == 0
                assert d.aborts, f"{d.name} stopped without its own watchdog"
                code, why, _ = d.aborts[0]
                assert code == 0x8130 and "master (node 127)" in why
                if _lost_for(why) > consumer + SLACK:  # by its own account its check came that late
                    raise Disturbed(f"{d.name}'s heartbeat watchdog checked late (the machine held it up): {why}")
                # from the drive's side: its stop after the master's last heartbeat it heard (stop()
                # above joins the producer thread: t0 may come later than that heartbeat on a loaded machine)
                seen = d._master_seen
                assert seen <= t0 and t0 - seen <= producer + SLACK, (t0 - seen)
                assert consumer <= d.stopped_since[1] - seen <= consumer + 0.01 + SLACK, d.stopped_since[1] - seen
            # and they say so: EMCY 0x8130 from each drive
            assert _until(lambda: len([f for f in robot.faults if f.kind == "emcy"]) >= 3, 1.0), robot.faults
            assert {f.code for f in robot.faults if f.kind == "emcy"} == {0x8130}

    _measured(scenario)


def _lost_for(why: str) -> float:
    """X of a simulated drive's abort text '... lost for X s'."""
    return float(why.partition("lost for ")[2].split(" s")[0])


class Disturbed(Exception):
    """A machine stall spoiled an attempt's set-up: a watchdog fired, or the master latched a fault
    of its own, before the watchdog under test could. No measurement of that watchdog, not a failure
    of it: the attempt is run again (``_measured``)."""


def _one_cycle(robot) -> None:
    """One control cycle at 2 N m on every joint (a set-up's)."""
    robot.write([2.0, 2.0, 2.0])
    robot.read()


def _set_up(robot, steps) -> None:
    """Enable and run ``steps`` (a callable); Disturbed when a real-time deadline a loaded machine
    missed spoiled it (the driver raised a fault, or latched one, or a drive aborted)."""
    try:
        robot.enable()
        steps()
    except RobotFault as exc:
        raise Disturbed(f"faulted while setting up: {exc}") from None


def _undisturbed(robot, plant) -> None:
    """The run so far was clean: the master latched no fault and no drive aborted (else Disturbed)."""
    if robot.faults or any(d.aborts for d in plant.drives):
        raise Disturbed(f"a watchdog fired before the stall under test: {robot.faults}, "
                        f"{[d.aborts for d in plant.drives]}")


def _measured(scenario, attempts: int = 5) -> None:
    """Run ``scenario`` until one attempt is undisturbed (at most ``attempts``); its assertions hold."""
    for k in range(attempts):
        try:
            return scenario()
        except Disturbed as exc:
            if k == attempts - 1:
                pytest.fail(f"every one of {attempts} attempts was disturbed; the last: {exc}")


def _until(condition, timeout: float) -> bool:
    """Wait (wall) until ``condition()`` holds, at most ``timeout`` s: for what another thread delivers."""
    end = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > end:
            return False
        time.sleep(0.002)
    return True


def pace(robot, period: float) -> None:
    """The test is the loop: it ticks the robot's clock (the driver never paces; one SYNC per period)."""
    assert robot.clock.realtime and robot.clock.period == period
    robot.clock.wait()


def _emcy_codes(robot) -> set:
    return {f.code for f in robot.faults if f.kind == "emcy"}


def test_drives_stop_on_sync_loss_and_on_an_rpdo_deadline_miss():
    rate = 50.0
    # the drives' watchdogs are under test, not the master's heartbeats or its stale-TPDO window:
    # those are widened so that a loaded machine spoils fewer set-ups
    cfg = CFG.replace_bus(control_rate=rate, tpdo_timeout=10).relaxed(1.0)
    period = 1 / rate

    def sync_loss():
        with simulated_robot(cfg, with_imu=False, realtime=True) as (robot, plant):
            assert all(d.node.sdo[0x1006].raw == int(period * 1e6) for d in robot.drives)
            assert all(d.node.sdo[0x1400][5].raw == round(cfg.drives[0].rpdo_timeout * period * 1000)
                       for d in robot.drives)

            def cycles():
                for _ in range(3):
                    pace(robot, period)
                    robot.write([2.0, 2.0, 2.0])
                    robot.read()

            _set_up(robot, cycles)
            last_sync = {d.name: d._last_sync for d in plant.drives}
            _undisturbed(robot, plant)
            # the loop stalls: no more SYNC (and no RPDO); nothing else of the master's runs on a period
            assert plant.wait_all_stopped(0.5 + SLACK)
            for d in plant.drives:
                assert d.aborts, f"{d.name} stopped without its own watchdog: {robot.faults}"
                code, why, _ = d.aborts[0]
                assert code == 0x8100 and "SYNC lost" in why
                lost = d.stopped_since[1] - last_sync[d.name]
                assert SYNC_LOSS_CYCLES * period <= lost <= SYNC_LOSS_CYCLES * period + SLACK, lost
            # and they say so: EMCY 0x8100 from each drive (received by the master's thread)
            assert _until(lambda: 0x8100 in _emcy_codes(robot), 1.0), robot.faults

    def rpdo_deadline():
        with simulated_robot(cfg, with_imu=False, realtime=True) as (robot, plant):
            _set_up(robot, lambda: _one_cycle(robot))
            _undisturbed(robot, plant)
            last_rpdo = {d.name: d._last_rpdo for d in plant.drives}
            deadline = cfg.drives[0].rpdo_timeout * period
            for _ in range(cfg.drives[0].rpdo_timeout + 3):  # SYNC goes on, the setpoints stop
                pace(robot, period)
                robot.read()
            assert plant.wait_all_stopped(0.3 + SLACK)
            own = [f for f in robot.faults if f.kind != "emcy"]
            if own:  # e.g. TPDOs held up past their window: the master stopped the drives itself
                raise Disturbed(f"the master latched a fault of its own first: {own}")
            if any(d.aborts and d.aborts[0][0] == 0x8100 for d in plant.drives):
                raise Disturbed("a SYNC held up by the machine past the SYNC watchdog")
            for d in plant.drives:
                assert d.aborts, f"{d.name} stopped without its own watchdog: {robot.faults}"
                code, why, _ = d.aborts[0]
                assert code == 0x8250 and "no RPDO" in why
                assert deadline <= d.stopped_since[1] - last_rpdo[d.name] <= deadline + SLACK
            assert _until(lambda: 0x8250 in _emcy_codes(robot), 1.0), robot.faults

    _measured(sync_loss)
    _measured(rpdo_deadline)
