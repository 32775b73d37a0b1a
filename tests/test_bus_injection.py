"""The fault matrix: ``otbot run --bus sim --inject KIND@SECONDS`` for every kind on virtual CAN,
the same kinds with the plant as its own process over slcan, the master killed mid-run, and a
flood of random frames on the devices' COB-IDs. Judged from the simulated drives' own state:
drives on the bus stopped within two periods of the detection, faults in plain words, exit 1,
the recording up to the fault loadable."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import can
import numpy as np
import pytest

from drivers.config import LOCKSTEP_HEARTBEAT, load_robot_config
from drivers.faults import DeviceConfigError, DriverError
from otbot_hw.cli import main
from otbot_hw.recording import read_recording
from otbot_hw.robot import RobotFault
from otbot_hw.runtime.openloop import run_torques
from sim.injection import Injection, reaction
from sim.bus_robot import simulated_robot
from sim.plant_process import PlantProcess, flood_frames, send_flood

CFG = load_robot_config()
PERIOD = CFG.bus.period
AT = 0.1  # s of plant time
#: what each fault must be called, in words
WORDS = {"drive-silent": "TPDO1 missing", "emcy": "excess drive temperature", "fault-bit": "over-current",
         "imu-loss": "disconnected", "imu-error": "insufficient baud rate", "bus-off": "missing"}
IN_PROCESS = list(WORDS)


def check_reaction(r: dict, kind: str, consumer: float) -> None:
    """The reaction block against the targets: detection within the TPDO timeout (two periods),
    every drive still on the bus at zero torque within two periods of it, the others stopped by
    their own watchdog (the master's heartbeat, ``consumer`` s) — judged from the drives' state."""
    assert r["kind"] == kind and r["injected_s"] == pytest.approx(AT), r
    assert r["detected_s"] is not None, r
    assert 0.0 <= r["detected_s"] - r["injected_s"] <= CFG.bus.tpdo_timeout * PERIOD + 1e-9, r
    if kind in ("drive-silent", "bus-off") and r.get("first_fault_kind", "stale") == "stale":
        # the stale-TPDO window (a heartbeat that lapsed first over slcan: SLCAN_WORDS)
        assert r["detected_s"] - r["injected_s"] == pytest.approx((CFG.bus.tpdo_timeout - 1) * PERIOD), r
    if kind != "bus-off":  # with the bus gone no drive can be reached: they stop by themselves
        assert 0.0 <= r["healthy_stopped_s"] - r["detected_s"] <= 2 * PERIOD + 1e-9, r
    assert r["all_stopped_s"] is not None, r
    if kind in ("drive-silent", "bus-off"):
        assert r["all_stopped_s"] - r["injected_s"] <= consumer + MATRIX_SLACK, r
    assert "OPERATION ENABLED" not in r["drive_states_after"].values(), r


@pytest.mark.parametrize("kind", IN_PROCESS)
def test_otbot_run_inject_on_virtual_can(kind, tmp_path, capsys):
    out = tmp_path / "run.mcap"
    for _ in range(3):
        with pytest.raises(SystemExit) as exc:
            main(["run", "--bus", "sim", "--inject", f"{kind}@{AT}", "--duration", "0.25", "--noise", "none",
                  "--out", str(out), "--json"])
        assert exc.value.code == 1
        captured = capsys.readouterr()
        res = json.loads(captured.out)
        # A wall-clock watchdog a loaded machine tripped before the injection ended the run without
        # one (injected_s null): nothing to judge; run it again (a fault that comes every time fails).
        if res["reaction"]["injected_s"] is not None:
            break
    else:
        pytest.fail(f"every run faulted before the injection; the last: {res['faults']}")
    assert res["completed"] is False
    check_reaction(res["reaction"], kind, LOCKSTEP_HEARTBEAT)
    assert any(WORDS[kind] in f["meaning"] for f in res["faults"]), res["faults"]
    assert WORDS[kind] in captured.err  # said in the text output too
    assert "Traceback" not in captured.err
    rec = read_recording(out)  # the recording up to the fault loads
    assert len(rec) == res["samples"] and rec.t[-1] < AT + CFG.bus.tpdo_timeout * PERIOD
    assert any(e["kind"] == "fault" and WORDS[kind] in e["text"] for e in rec.events)


def test_inject_refuses_what_it_cannot_do(capsys):
    for args, words in ((["--inject", "melt@1"], "unknown fault kind 'melt'"),
                        (["--inject", "emcy"], "KIND@SECONDS"),
                        (["--inject", "emcy@-1"], ">= 0"),
                        (["--inject", "emcy@1:elbow"], "device must be one of"),
                        (["--inject", "imu-loss@0.05", "--no-imu"], "has no IMU"),
                        (["--bus", "config", "--inject", "emcy@0.1"], "needs --bus sim")):
        assert main(["run", *args, "--duration", "0.1"]) == 2
        err = capsys.readouterr().err
        assert words in err and len(err.strip().splitlines()) == 1, err


def test_plant_kill_with_the_plant_as_its_own_process(tmp_path, capsys):
    out = tmp_path / "run.mcap"
    with pytest.raises(SystemExit) as exc:
        main(["run", "--bus", "sim", "--inject", f"plant-kill@{AT}", "--duration", "0.3", "--out", str(out),
              "--json"])
    assert exc.value.code == 1
    captured = capsys.readouterr()
    res = json.loads(captured.out)
    r = res["reaction"]
    assert r["injected_s"] == pytest.approx(AT) and 0 <= r["detected_s"] - AT <= 2 * PERIOD + 1e-9
    assert r["all_stopped_s"] is None and r["drive_states_after"] is None and "gone" in r["note"]
    assert {f["kind"] for f in res["faults"]} & {"bus", "stale", "imu"}
    assert res["close_problems"] and "Traceback" not in captured.err  # reported, not raised
    assert len(read_recording(out)) == res["samples"]


MATRIX_CONSUMER = 0.3  # s: the heartbeat consumer times of the matrix runs (both sides, ``relaxed``)
MATRIX_SLACK = 0.3  # s: what a loaded machine may add to a drive's stop by its own heartbeat watchdog


def _lost_for(why: str) -> float | None:
    """X of a simulated drive's abort text '... lost for X s'."""
    head, sep, tail = why.partition("lost for ")
    try:
        return float(tail.split(" s")[0]) if sep else None
    except ValueError:
        return None


def _matrix_run(pp: PlantProcess, kind: str) -> tuple[dict, list, str | None]:
    """One run with the fault ``kind`` injected: (reaction, the loop's faults, why the run is no
    measurement of the reaction or None).

    A run is no measurement when the machine disturbed it before the injection: the boot timed out
    (an SDO answer or boot-up later than its wall-clock timeout), the plant never
    started its clock (no injection happened), or the master latched a fault before the injected
    SYNC (a wall-clock watchdog, here the heartbeats relaxed to 0.3 s, lapsed while the machine
    held a process up; the drives then stopped before anything was injected), or a drive's own
    heartbeat watchdog tripped more than MATRIX_SLACK after its consumer time by its own account
    (the plant process was held up: its watchdog thread checked late), or a drive the master could
    still reach lost the master's heartbeat (the master process was held up longer than the consumer
    time, so its reaction came after the drives' own). A drive misconfigured with
    a longer consumer time says so in every run, and fails."""
    cfg = CFG.relaxed(MATRIX_CONSUMER)
    robot = pp.robot(cfg)
    reported_at: list[int] = []  # the SYNC whose read first reported a fault
    with robot:
        try:
            robot.open()
        except DeviceConfigError:
            raise
        except DriverError as exc:  # an SDO or boot-up answer later than its wall-clock timeout
            return {}, [], f"the boot timed out (plant held up): {exc}"
        read = robot.read

        def read_and_note():
            k = robot._syncs  # the index the read's SYNC gets (a fault reaction in it may send more)
            s = read()
            if s.faults and not reported_at:
                reported_at.append(k)
            return s

        robot.read = read_and_note
        res = run_torques(robot, np.tile([4.0, -4.0, 2.0], (30, 1)))
    pp.after = pp.report(wait_stopped=True, timeout=1.0)
    r = reaction(Injection(kind, AT), pp.injected_t, robot, pp.after, PERIOD)
    start = (pp.after or {}).get("start_sync")
    if start is None:
        return r, list(res.robot_faults), f"the plant never started its clock: {pp.after}"
    stamps = robot.fault_syncs()
    injected_sync = start + pp.injected_t / PERIOD
    early = [str(f) for f, k in stamps.items() if k < injected_sync - 1e-6]
    if reported_at and reported_at[0] < injected_sync - 1e-6:  # the loop saw it before (its stamp may be late)
        early = early or [str(f) for f in stamps]
    if early:
        return r, list(res.robot_faults), f"faults before the injection: {early}"
    cut = {d["name"] for d in pp.after["drives"]} if kind == "bus-off" else {pp.injection.device} if (
        kind == "drive-silent") else set()
    lapsed = [d["name"] for d in pp.after["drives"]
              if d["name"] not in cut and any(code == 0x8130 for code, _, _ in d["aborts"])]
    if lapsed:  # drives the master could reach lost its heartbeat: the master process was held up
        return r, list(res.robot_faults), f"the master's heartbeat lapsed at {lapsed} (master held up)"
    late = [(d["name"], x) for d in pp.after["drives"] for code, why, _ in d["aborts"]
            if code == 0x8130 and (x := _lost_for(why)) is not None and x > MATRIX_CONSUMER + MATRIX_SLACK]
    if late:  # the drive's own check ran that late: a measurement of the machine, not of the drive
        return r, list(res.robot_faults), f"a drive's heartbeat watchdog checked late (plant held up): {late}"
    if stamps:  # the first the master latched, in wall-clock order (the stamps of a loaded lockstep run are not)
        r["first_fault_kind"] = min(stamps, key=lambda f: f.time).kind
    return _bounded_by_the_read(r, reported_at, pp.after), list(res.robot_faults), None


def _bounded_by_the_read(r: dict, reported_at: list[int], after: dict | None) -> dict:
    """``r`` with its detection no later than the SYNC whose read reported the fault.

    In lockstep the master stamps a fault found between SYNCs (an EMCY, an IMU error) at the last
    SYNC plus the wall time since it in periods (``CanopenRobot.fault_syncs``). On a loaded machine
    that wall time is no bus time: the plant waits for the next SYNC whatever the wall clock does, and
    an EMCY of SYNC k handled 25 ms late was stamped k + 2.5, after the quick stop it caused at
    k + 1. The read that reported the fault is on the SYNC grid both sides count: detection happened
    at or before it. (A run the machine did not hold up keeps its own stamp.)"""
    start = (after or {}).get("start_sync")
    if not reported_at or start is None or r["detected_s"] is None:
        return r
    read_s = (reported_at[0] - start) * PERIOD
    if r["detected_s"] <= read_s + 1e-9:
        return r
    out = dict(r, detected_s=read_s, detected_late_by_wall_s=r["detected_s"] - read_s)
    if out["injected_s"] is not None:
        out["detection_periods"] = (read_s - out["injected_s"]) / PERIOD
    if out["healthy_stopped_s"] is not None:
        out["stop_periods"] = (out["healthy_stopped_s"] - read_s) / PERIOD
    return out


#: over slcan a bus-off may first be named by the heartbeats: the master waits LOCKSTEP_TIMEOUT
#: (0.25 s) at each SYNC for TPDOs that no longer come, the stale fault needs two such SYNCs, and
#: the nodes' heartbeats (consumer 0.3 s here) lapse in between; which the master latches first
#: depends on when a loaded machine runs its threads. Either names the bus-off in words.
SLCAN_WORDS = {**{k: (w,) for k, w in WORDS.items()}, "bus-off": (WORDS["bus-off"], "no heartbeat")}


def test_fault_matrix_with_the_plant_as_its_own_process_over_slcan():
    """Each kind against a plant in its own process (slcan on a pty), restarted fresh for each."""
    with PlantProcess(CFG) as pp:
        for kind in IN_PROCESS:
            for _ in range(3):
                pp.restart(Injection(kind, AT))
                r, faults, disturbed = _matrix_run(pp, kind)
                if disturbed is None:
                    break
            else:
                pytest.fail(f"{kind}: the machine disturbed every one of 3 runs before the injection; the last: "
                            f"{disturbed}")
            check_reaction(r, kind, MATRIX_CONSUMER)
            assert any(w in f.meaning for f in faults for w in SLCAN_WORDS[kind]), (kind, faults)
            assert pp.alive()


def test_master_killed_mid_run_the_drives_stop_within_their_consumer_time(robot_yaml):
    consumer = 0.15
    cfg = robot_yaml({"  options: {}": "  options: {sleep_after_open: 0}",
                      "heartbeat_consumer: {value: 200, unit: ms}": "heartbeat_consumer: {value: 1000, unit: ms}",
                      "master_heartbeat_consumer: {value: 100, unit: ms}":
                          f"master_heartbeat_consumer: {{value: {consumer * 1000:g}, unit: ms}}"})
    with PlantProcess(CFG) as pp:
        master = subprocess.Popen([sys.executable, "-m", "otbot_hw", "run", "--bus", "config", "--config",
                                   str(cfg), "--interface", "slcan", "--channel",
                                   pp.info["can_channel"], "--imu-port", pp.info["imu_port"], "--lockstep",
                                   "--duration", "1000", "--json"], stdout=subprocess.DEVNULL,
                                  stderr=subprocess.DEVNULL)
        try:
            t0 = time.monotonic()
            while True:
                rep = pp.report()
                if rep["started"] and rep["t"] > 0.2:
                    break
                assert time.monotonic() - t0 < 30 and master.poll() is None, "the master did not start"
                time.sleep(0.01)
            assert all(d["state"] == "OPERATION ENABLED" and d["torque_permille"] for d in rep["drives"])
            os.kill(master.pid, signal.SIGKILL)
            killed = time.monotonic()
        finally:
            master.kill()
            master.wait()
        rep = pp.report(wait_stopped=True, timeout=consumer + 1.0)
        for d in rep["drives"]:
            assert d["state"] == "QUICK STOP ACTIVE" and d["torque_permille"] == 0, d
            assert d["aborts"][0][0] == 0x8130  # the master's heartbeat was lost
            # the last heartbeat came at most one producer period before the kill
            stopped = d["stopped_wall"] - killed
            assert consumer - CFG.bus.master_heartbeat - 0.005 <= stopped <= consumer + 0.12, stopped


def _flood_run(robot, plant_or_process, n_cycles=60):
    """Drive the robot while frames flood the bus in cycles 5..34; faults must be plain words."""
    faults_at = None
    for c in range(n_cycles):
        if 5 <= c < 35:
            plant_or_process(c)
        try:
            robot.write([2.0, -2.0, 1.0])
        except RobotFault:
            pass
        s = robot.read()
        if s.faults and faults_at is None:
            faults_at = c
    for f in robot.faults:
        assert f.meaning and "Error" not in f.meaning and "Traceback" not in f.meaning, f
    return faults_at


@pytest.mark.parametrize("seed", [0, 1])
def test_a_flood_of_random_frames_on_the_devices_ids_on_virtual_can(seed, caplog):
    with simulated_robot(CFG, with_imu=False) as (robot, plant):
        robot.enable()
        intruder = can.Bus(interface="virtual", channel=robot.config.bus.channel)
        frames = flood_frames(robot.config, 300, seed)
        try:
            faulted = _flood_run(robot, lambda c: send_flood(intruder, frames[(c - 5) * 10:(c - 4) * 10]))
        finally:
            intruder.shutdown()
        assert faulted is not None  # 300 random frames on these IDs do not go unnoticed
    # after close every drive is at zero torque and not enabled, by its own state
    assert all(d.state != "OPERATION ENABLED" and d.applied_permille() == 0 for d in plant.drives)
    assert not [r for r in caplog.records if r.name.startswith(("drivers", "sim")) and r.levelname == "ERROR"]


def test_a_flood_over_slcan_both_ways_with_the_plant_as_its_own_process():
    with PlantProcess(CFG, with_imu=False) as pp:
        robot = pp.robot(CFG.relaxed(0.5), with_imu=False)
        frames = flood_frames(robot.config, 150, 7)
        with robot:
            robot.open()
            robot.enable()

            def flood(c):
                send_flood(robot.network.bus, frames[(c - 5) * 5:(c - 4) * 5])  # to the drives
                pp.flood(5, seed=c)  # and from the plant's side to the master

            _flood_run(robot, flood)
        rep = pp.report(wait_stopped=True, timeout=1.0)
        assert pp.alive()
        assert all(d["state"] != "OPERATION ENABLED" and d["torque_permille"] == 0 for d in rep["drives"]), rep
