"""Faults over the simulated bus: EMCY and statusword, heartbeat timeout, stale TPDOs,
malformed frames, and configuration errors named by key."""
from __future__ import annotations

import re
import time

import can
import numpy as np
import pytest

from drivers.config import load_robot_config
from drivers.faults import error_meaning
from otbot_hw.robot import RobotFault
from otbot_hw.params import ParameterError
from sim.bus_robot import simulated_robot

CFG = load_robot_config()


def test_drive_fault_and_emcy_surface_within_one_cycle_and_reset():
    with simulated_robot(CFG, with_imu=False) as (robot, plant):
        robot.enable()
        for _ in range(3):
            robot.write([2.0, 2.0, 2.0])
            assert not robot.read().faults
        plant.drives[1].inject_fault(0x2310)
        robot.write([2.0, 2.0, 2.0])  # may race with the EMCY; the fault must show in this cycle's read
        s = robot.read()
        kinds = {(f.device, f.kind, f.code) for f in s.faults}
        assert ("left_wheel", "emcy", 0x2310) in kinds
        assert ("left_wheel", "statusword", 0x2310) in kinds
        f = next(f for f in s.faults if f.kind == "emcy")
        assert "over-current" in f.meaning and f.node == 2 and "0x2310" in str(f)
        assert s.drive_states[1] == "FAULT"
        with pytest.raises(RobotFault, match="left_wheel"):
            robot.write([1.0, 1.0, 1.0])
        # the reaction ran inside that read(): quick stop confirmed by the others, then disabled
        assert [sd.state for sd in plant.drives] == ["SWITCH ON DISABLED", "FAULT", "SWITCH ON DISABLED"]
        assert [sd.joint_torque() for sd in plant.drives] == [0.0, 0.0, 0.0]
        assert plant.drives[1].od_value(0x1003, 1) == 0x2310  # error history on the drive
        robot.fault_reset()
        assert not robot.faults and plant.drives[1].state == "SWITCH ON DISABLED"
        robot.enable()
        robot.write([1.0, 1.0, 1.0])
        assert not robot.read().faults


def test_error_meanings():
    assert error_meaning(0x3210) == "DC link over-voltage"
    assert error_meaning(0x8611) == "following error"
    assert "temperature" in error_meaning(0x4399)  # class fallback
    assert "unknown" in error_meaning(0x0123)


def test_silent_drive_trips_the_heartbeat_timeout_within_its_consumer_time():
    consumer = CFG.drives[2].heartbeat_consumer
    with simulated_robot(CFG, with_imu=False, heartbeat_consumer=None) as (robot, plant):
        robot.enable()
        assert not robot.faults
        t0 = time.monotonic()
        plant.drives[2].go_silent()
        while not any(f.kind == "heartbeat" for f in robot.faults):
            assert time.monotonic() - t0 < consumer + 1.0, "no heartbeat fault"
            time.sleep(0.002)
        elapsed = time.monotonic() - t0
        f = next(f for f in robot.faults if f.kind == "heartbeat")
        assert f.device == "pivot" and f.code == 0x8130
        # Last heartbeat came at most one producer period before the silence; the watchdog checks
        # every consumer/10 s.
        assert consumer - CFG.drives[2].heartbeat_producer - 0.01 <= elapsed <= consumer + consumer / 10 + 0.1
        with pytest.raises(RobotFault):
            robot.write([0, 0, 0])


def test_missing_tpdos_raise_a_stale_data_fault():
    with simulated_robot(CFG, with_imu=False) as (robot, plant):
        robot.enable()
        robot.write([1.0, 1.0, 1.0])
        assert not robot.read().faults
        plant.encoder.drop_tpdos = True
        for k in range(CFG.bus.tpdo_timeout):
            robot.write([1.0, 1.0, 1.0])
            s = robot.read()
            assert bool(s.faults) == (k == CFG.bus.tpdo_timeout - 1)
        stale = [f for f in s.faults if f.kind == "stale"]
        assert [(f.device, f.node) for f in stale] == [("pivot_encoder", 4)]
        assert "TPDO1" in stale[0].meaning


def test_malformed_frames_are_ignored_without_crash():
    n = 20
    with simulated_robot(CFG, with_imu=False) as (robot, plant):
        robot.enable()
        intruder = can.Bus(interface="virtual", channel=robot.config.bus.channel)
        bad = [can.Message(arbitration_id=0x181, data=b"\x01\x02\x03", is_extended_id=False),  # short TPDO1
               can.Message(arbitration_id=0x082, data=b"\x10\x23", is_extended_id=False),  # short EMCY
               can.Message(arbitration_id=0x701, data=b"", is_extended_id=False),  # empty heartbeat
               can.Message(arbitration_id=0x202, data=b"\x0f", is_extended_id=False),  # short RPDO1
               can.Message(arbitration_id=0x080, data=b"\x01\x02\x03\x04\x05", is_extended_id=False),  # SYNC
               can.Message(arbitration_id=0x000, data=b"\x81", is_extended_id=False),  # short NMT
               can.Message(arbitration_id=0x603, data=bytes(range(8)), is_extended_id=False),  # bad SDO
               can.Message(arbitration_id=0x181, data=bytes(8), is_extended_id=True),  # extended ID
               can.Message(arbitration_id=0x184, is_remote_frame=True, dlc=4, is_extended_id=False),
               can.Message(arbitration_id=0x281, data=bytes(8), is_extended_id=False)]  # 8 bytes on 7-byte TPDO2
        try:
            res = []
            for k in range(n):
                if k == 5:
                    for m in bad:
                        intruder.send(m)
                    time.sleep(0.05)  # let both sides process them
                    # CANopen uses 11-bit IDs: the extended-ID frame 0x181 must not count as TPDO1.
                    assert robot.drives[0].node.state == "OPERATION ENABLED"
                robot.write([3.0, -3.0, 2.0])
                res.append(robot.read())
        finally:
            intruder.shutdown()
        assert not robot.faults
        assert robot.drives[0].malformed >= 1 and robot.drives[1].malformed >= 1
        assert plant.drives[1].malformed >= 1 and plant.malformed_sync >= 1
        assert plant.drives[0].foreign >= 1  # the short frame on its own TPDO1 COB-ID, ignored
        assert all(sd.state == "OPERATION ENABLED" for sd in plant.drives)
        # Readings stayed consistent with the plant: monotone wheel angle under constant torque.
        right = np.array([s.joint_pos[0] for s in res])
        assert np.all(np.diff(right) >= 0) and right[-1] > 0
        truth = np.array(plant.truth.x)[len(plant.truth.x) - 1]
        assert abs(res[-1].joint_pos[0] - truth[3]) < 2 * np.pi / 40960 + 1e-9


@pytest.mark.parametrize("old,new,key", [
    ("right_wheel: {node_id: 1,", "right_wheel: {node_id: 200,", "drives.right_wheel.node_id"),
    ("left_wheel: {node_id: 2,", "left_wheel: {node_id: 1,", "node IDs must be distinct"),
    ("polarity: -1}", "polarity: 2}", "drives.left_wheel.polarity"),
    ("heartbeat_consumer: {value: 200, unit: ms}  # no", "heartbeat_consumer: {value: 20, unit: ms}  # no",
     "drives.heartbeat_consumer"),
    ("    - [0x6087, 0, 0]", "    - [0x1A00, 1, 0]", "drives.sdo_config[1]"),
    ("eds: cia402_torque_drive.eds", "eds: nowhere.eds", "drives.eds"),
    ("bitrate: {value: 1000000, unit: bit/s}", "bitrate: {value: 1000000, unit: kbit/s}", "bus.bitrate"),
    ("control_rate: {value: 100, unit: Hz}", "control_rate: {value: -5, unit: Hz}", "bus.control_rate"),
    ("source: encoder", "source: magic", "pivot_encoder.source"),
    ("interface: socketcan", "interface: carrier-pigeon", "bus.interface"),
    ("bus:\n", "bus_renamed:\n", "missing section 'bus'"),
    ("quick_stop_option: 2", "quick_stop_option: 9", "drives.quick_stop_option"),
    ("quick_stop_option: 2", "quick_stop_option: fast", "drives.quick_stop_option"),
    ("sync_watchdog: true", "sync_watchdog: 1.5", "drives.sync_watchdog"),
    ("loop_liveness: {value: 3, unit: periods}", "loop_liveness: {value: 0, unit: periods}", "bus.loop_liveness"),
    ("loop_liveness: {value: 3, unit: periods}", "loop_liveness: {value: 2.5, unit: periods}", "bus.loop_liveness"),
    # values that turned a protection off, or crashed the loader or the plant (a fuzzing of every key)
    ("loop_liveness: {value: 3, unit: periods}", "loop_liveness: {value: 1e300, unit: periods}",
     "'bus.loop_liveness' must be at most 2 s of periods (200 at 100 Hz"),
    ("loop_liveness: {value: 3, unit: periods}", "loop_liveness: {value: 2.01, unit: s}",
     "'bus.loop_liveness' must be at most 2 s (a detection time), got 2.01"),
    ("tpdo_timeout: {value: 2, unit: periods}", "tpdo_timeout: {value: 201, unit: periods}", "'bus.tpdo_timeout'"),
    ("reaction_timeout: {value: 2, unit: periods}", "reaction_timeout: {value: 1e300, unit: periods}",
     "'bus.reaction_timeout'"),
    ("boot_timeout: {value: 2.0, unit: s}", "boot_timeout: {value: 1.0e+300, unit: s}",
     "'bus.boot_timeout' must be at most 60 s"),
    ("master_heartbeat: {value: 20, unit: ms}", "master_heartbeat: {value: 65536, unit: ms}",
     "'bus.master_heartbeat' must be at most 65535 ms"),
    ("heartbeat_consumer: {value: 200, unit: ms}  # no", "heartbeat_consumer: {value: 1e300, unit: ms}  # no",
     "'drives.heartbeat_consumer' must be at most 65535 ms"),
    ("  heartbeat_consumer: {value: 200, unit: ms}\n\nmotors", "  heartbeat_consumer: {value: 65536, unit: ms}\n\nmotors",
     "'pivot_encoder.heartbeat_consumer' must be at most 65535 ms"),
    ("counts_per_rev: 4096", "counts_per_rev: 4294967296", "'drives.counts_per_rev' must be at most 4.29497e+09"),
    ("rated_torque: {value: 2.0, unit: N m}", "rated_torque: {value: 1.0e+300, unit: N m}",
     "'drives.rated_torque' must be at most 4.29497e+06 N m (0x6076 is UNSIGNED32 mN m)"),
    ("right_wheel: {node_id: 1, gear_ratio: 10.0,", "right_wheel: {node_id: 1, gear_ratio: 1.0e+300,",
     "'drives.right_wheel.gear_ratio' must be at most 100000"),
    ("abort_connection_option: quick_stop", "abort_connection_option: [quick_stop]", "drives.abort_connection_option"),
    ("abort_connection_option: quick_stop", "abort_connection_option: {a: 1}", "drives.abort_connection_option"),
    ("offset: {value: 8192, unit: counts}", "offset: {value: -1, unit: counts}",
     "'pivot_encoder.offset' must be a position >= 0 counts"),
    ("offset: {value: 8192, unit: counts}", "offset: {value: 1.0e+300, unit: counts}", "'pivot_encoder.offset'"),
    ("    - [0x6087, 0, 0]", "    - [0x6087, 0, -1]", "'drives.sdo_config[1]' -1 does not fit 0x6087:00"),
    ("    - [0x6072, 0, 2500]", "    - [0x6072, 0, 70000]", "'drives.sdo_config[0]' 70000 does not fit 0x6072:00"),
    ("  options: {}", "  options: {}\n  sync_watchdg: false", "'bus' has unknown key(s) ['sync_watchdg']"),
    ("  sync_watchdog: true", "  sync_watchdg: true", "'drives' has unknown key(s) ['sync_watchdg']"),
    ("right_wheel: {node_id: 1,", "right_wheel: {nodeid: 5, node_id: 1,", "'drives.right_wheel' has unknown key(s)"),
    ("  direction: 1", "  direction: 1\n  offest: 3", "'pivot_encoder' has unknown key(s) ['offest']"),
    ("bitrate: {value: 1000000, unit: bit/s}", "bitrate: {value: 1000000, unit: bit/s, std: 3}",
     "'bus.bitrate' has unknown key(s) ['std']"),
    ("right_wheel: {max_torque: {value: 40.0, unit: N m}}", "right_wheel: {max_torque: {value: 40.0, unit: N m}, x: 1}",
     "'motors.right_wheel' has unknown key(s)"),
    ("right_wheel: {max_torque: {value: 40.0, unit: N m}}",
     "right_wheel: {max_torque: {value: 40.0, unit: N m, limit: 5}}", "'motors.right_wheel.max_torque' has unknown"),
    ("  timeout: 0.5", "  timeout: 1.0e+300", "'imu.timeout' must be a number of seconds in (0, 10]"),
    ("      - [1.0, 0.0, 0.0]", "      - [1.0e+300, 0.0, 0.0]", "'imu.mounting.matrix' is not a rotation: entry 1e+300"),
    ("eds: cia402_torque_drive.eds", "eds: .", "which is a folder, not an EDS file"),
    ("  timeout: 0.5", "  timeout: 0.5\n  timout: 2", "'imu' has unknown key(s) ['timout']"),
])
def test_bad_config_is_rejected_naming_the_key(robot_yaml, old, new, key):
    with pytest.raises(ParameterError, match=re.escape(key)) as e:
        load_robot_config(robot_yaml({old: new}))
    assert "\n" not in str(e.value)


def test_cli_exits_2_on_bad_config_and_arguments(capsys, robot_yaml):
    from otbot_hw.cli import main

    bad = robot_yaml({"right_wheel: {node_id: 1,": "right_wheel: {node_id: 0,"})
    assert main(["run", "--config", str(bad), "--duration", "0.1"]) == 2
    assert "drives.right_wheel.node_id" in capsys.readouterr().err
    assert main(["run", "--torques", "1,2", "--duration", "0.1"]) == 2
    assert main(["run", "--rate", "0.7", "--duration", "10"]) == 2
    assert "0x60C2" in capsys.readouterr().err


def test_encoder_emcy_and_a_rebooting_drive_are_faults():
    with simulated_robot(CFG, with_imu=False) as (robot, plant):
        robot.enable()
        robot.write([0.0, 0.0, 0.0])
        robot.read()
        plant.encoder.inject_fault(0x7320)
        plant.drives[0].reset(application=True)  # the right wheel drive loses power and reboots
        plant.drives[0].boot()
        t0 = time.monotonic()
        while len({f.kind for f in robot.faults}) < 2:
            assert time.monotonic() - t0 < 1.0, robot.faults
            time.sleep(0.002)
        got = {(f.device, f.kind, f.code) for f in robot.faults}
        assert ("pivot_encoder", "emcy", 0x7320) in got
        nmt = [f for f in robot.faults if f.kind == "nmt"]
        assert nmt and nmt[0].device == "right_wheel" and "rebooted" in nmt[0].meaning


def test_device_refusing_the_configuration_is_a_clear_boot_error(monkeypatch):
    from dataclasses import replace

    from drivers.faults import DeviceConfigError

    # A configured write to an object the drive's dictionary lacks: skipped, said once by name.
    drives = tuple(replace(d, sdo_config=((0x2345, 0, 1),)) for d in CFG.drives)
    with simulated_robot(replace(CFG, drives=drives), with_imu=False) as (robot, plant):
        assert robot.warnings == ["right_wheel, left_wheel, pivot: no 0x2345:00 in the object dictionary: "
                                  "configured write skipped"]
    # A configured write the drive refuses (read-only statusword): refused by name, bad input.
    drives = tuple(replace(d, sdo_config=((0x6041, 0, 1),)) for d in CFG.drives)
    with pytest.raises(DeviceConfigError, match=r"right_wheel \(node 1\): config: SDO write of 1 to 0x6041:00 "
                                                 r"statusword failed"):
        with simulated_robot(replace(CFG, drives=drives), with_imu=False):
            pass
    # The drive's rated torque 0x6076 disagrees with the configuration.
    from sim import plant as plant_mod

    class WrongRated(plant_mod.SimulatedDrive):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            self.set_od(0x6076, 0, 1500)

    monkeypatch.setattr(plant_mod, "SimulatedDrive", WrongRated)
    with pytest.raises(DeviceConfigError, match=r"0x6076 = 1\.5 N m.*drives\.rated_torque"):
        with simulated_robot(CFG, with_imu=False):
            pass
