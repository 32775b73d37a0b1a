"""Object dictionaries written by others (``../shared/eds/``, ros2_canopen's CiA 402 test slaves):
each file as it is gets its documented outcome (a one-line refusal naming the missing object or
capability, exit 2, before any motion); variants derived from them that can run do run, with the
configuration supplying what the dictionary lacks; fixed mappings are used where they carry what
the loop needs and refused by name where they do not; a mapping the device does not keep is
caught by the read-back."""
from __future__ import annotations

import json

import numpy as np
import pytest

import eds_variants as ev
from drivers.config import load_robot_config
from otbot_hw.cli import main
from otbot_hw.params import nominal
from otbot_hw.sensors import encoders_ideal
from otbot_hw.simulation.simulator import simulate

CFG = load_robot_config()


@pytest.mark.parametrize("eds,words", [
    (ev.CIA402_SLAVE, "0x6502 supported drive modes = 0x000000A5 (pp, pv, hm, csp): neither cyclic synchronous "
                      "torque (bit 9) nor profile torque (bit 3)"),
    (ev.ROBOT_CONTROL_SLAVE, "0x6502 supported drive modes = 0x001F0065 (pp, pv, hm, ip): neither cyclic "
                             "synchronous torque"),
])
def test_third_party_dictionaries_as_they_are_are_refused_by_name(eds, words, tmp_path, capsys):
    cfg = ev.robot_config_with(tmp_path, eds)
    assert main(["run", "--bus", "sim", "--config", str(cfg), "--duration", "0.1", "--json"]) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and "right_wheel (node 1)" in lines[0] and words in lines[0], captured.err
    assert captured.out == ""


def test_a_dictionary_without_target_torque_is_refused_by_name(tmp_path, capsys):
    eds = ev.Eds(ev.CIA402_SLAVE).add_modes(ev.CST_BIT).write(tmp_path / "slave_cst.eds")
    assert main(["run", "--bus", "sim", "--config", str(ev.robot_config_with(tmp_path, eds)),
                 "--duration", "0.1"]) == 2
    err = capsys.readouterr().err
    assert "right_wheel (node 1): the object dictionary has no 0x6071 target torque" in err
    assert len(err.strip().splitlines()) == 1


def test_fixed_mappings_that_cannot_carry_target_torque_are_refused_by_name(tmp_path, capsys):
    eds = ev.robot_control_fixed_without_torque(tmp_path)
    assert main(["run", "--bus", "sim", "--config", str(ev.robot_config_with(tmp_path, eds)),
                 "--duration", "0.1"]) == 2
    err = capsys.readouterr().err
    assert "0x6071 target torque fits in no RPDO (fixed mappings: RPDO1, RPDO2, RPDO3, RPDO4" in err


def _pure_phi(duration_s: float):
    n = int(round(duration_s * CFG.bus.control_rate))
    traj = simulate(nominal(), np.tile([6.0, -10.0, 6.0], (n, 1)), CFG.bus.period)
    wheels = encoders_ideal(traj.x[-1:], 40960)[0][0]
    pivot = encoders_ideal(traj.x[-1:], 16384)[0][0]
    return [wheels[0], wheels[1], pivot[2]]


@pytest.mark.parametrize("variant,missing", [
    (ev.robot_control_cst, ["0x1016:01", "0x6072:00", "0x6076", "0x603F", "0x1400:05"]),
    (ev.cia402_slave_torque, ["0x6077 torque actual value", "0x6072:00", "0x6076", "0x6007"]),
    (ev.robot_control_fixed, ["0x1016:01", "0x6076"]),
])
def test_derived_dictionaries_run_with_the_configuration_filling_in(variant, missing, tmp_path, capsys):
    eds = variant(tmp_path)
    rc = main(["run", "--bus", "sim", "--config", str(ev.robot_config_with(tmp_path, eds)), "--duration", "0.3",
               "--noise", "none", "--json"])
    assert rc == 0
    res = json.loads(capsys.readouterr().out)
    assert res["completed"] and res["samples"] == 31
    # the robot moved as the model says: the per-mille of the configured rated torque was right
    np.testing.assert_allclose(res["phi"], _pure_phi(0.3), atol=1e-9)
    text = " | ".join(res["warnings"])
    for m in missing:
        assert m in text, (m, res["warnings"])
    assert all(w.startswith("right_wheel, left_wheel, pivot: ") for w in res["warnings"])  # said once


def test_fixed_mapping_is_used_as_it_is_and_its_extra_object_filled(tmp_path):
    from dataclasses import replace

    from sim.bus_robot import simulated_robot

    eds = ev.robot_control_fixed(tmp_path)
    cfg = replace(CFG, drives=tuple(replace(d, eds=eds) for d in CFG.drives))
    with simulated_robot(cfg, with_imu=False) as (robot, plant):
        d = robot.drives[0]
        assert d.plan.rx.pdos[1] == [(0x6040, 0, 16), (0x6060, 0, 8), (0x6071, 0, 16)] and 1 in d.plan.rx.fixed
        assert d.plan.tx.pdos[1] == [(0x6041, 0, 16), (0x6061, 0, 8)] and 1 in d.plan.tx.fixed
        assert d.plan.tx.carrying(0x6064) == 2 and d.plan.tx.carrying(0x6077) is not None
        robot.enable()
        robot.write([2.0, 2.0, 2.0])
        s = robot.read()
        # the mode of operation travels in the fixed RPDO: the driver fills in the mode it selected
        assert plant.drives[0].values[(0x6061, 0)] == d.mode == 10
        np.testing.assert_allclose(s.joint_torque, [2.0, 2.0, 2.0])
        # no 0x603F: a drive fault is named by its EMCY code
        plant.drives[0].inject_fault(0x3210)
        robot.write([2.0, 2.0, 2.0])
        robot.read()
        f = next(f for f in robot.faults if f.kind == "statusword")
        assert f.code == 0x3210 and "DC link over-voltage" in f.meaning


def test_torque_actual_absent_reads_nan_and_the_dictionary_defaults_apply(tmp_path):
    from dataclasses import replace

    from sim.bus_robot import simulated_robot

    eds = ev.cia402_slave_torque(tmp_path)
    cfg = replace(CFG, drives=tuple(replace(d, eds=eds) for d in CFG.drives))
    with simulated_robot(cfg, with_imu=False) as (robot, plant):
        robot.enable()
        robot.write([2.0, 2.0, 2.0])
        s = robot.read()
        assert np.isnan(s.joint_torque).all() and np.isfinite(s.joint_pos).all()
        assert plant.drives[0].od_value(0x6007) is None  # no 0x6007: the drive's CiA 402 default (fault)
        robot.master_heartbeat.stop()
        assert plant.wait_all_stopped(plant.longest_watchdog() + 0.5)
        assert all(d.state == "FAULT" and d.values[(0x603F, 0)] == 0x8130 for d in plant.drives)


def test_a_mapping_the_device_does_not_keep_is_refused_by_the_read_back(monkeypatch, capsys):
    from drivers.faults import DeviceConfigError
    from sim import plant as plant_mod
    from sim.bus_robot import simulated_robot

    class Forgetful(plant_mod.SimulatedDrive):
        """Accepts the write of a third TPDO1 mapping entry but keeps nothing there."""

        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            store = self.node.set_data

            def set_data(index, subindex, data, check_writable=False):
                if (index, subindex) == (0x1A00, 3):
                    data = bytes(len(data))
                store(index, subindex, data, check_writable)

            self.node.set_data = set_data

    monkeypatch.setattr(plant_mod, "SimulatedDrive", Forgetful)
    with pytest.raises(DeviceConfigError, match=r"right_wheel \(node 1\): config: TPDO1 does not carry 0x6077 "
                                                 r"torque actual value \(entry 3\); read back: 0x6041:00/16, "
                                                 r"0x6064:00/32, 0x0000:00/0"):
        with simulated_robot(CFG, with_imu=False):
            pass
    # through the command line: one line, exit 2, before any motion
    assert main(["run", "--bus", "sim", "--no-imu", "--duration", "0.1", "--json"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "TPDO1 does not carry 0x6077" in err[0]


def test_the_simulated_drives_live_with_any_of_these_dictionaries(tmp_path):
    """The simulated slaves built on each third-party file boot and answer SDO without errors."""
    from dataclasses import replace

    import can
    import canopen

    from sim.bus_robot import VirtualPlant

    for eds in (ev.CIA402_SLAVE, ev.ROBOT_CONTROL_SLAVE):
        cfg = replace(CFG, drives=tuple(replace(d, eds=eds) for d in CFG.drives)).replace_bus(
            interface="virtual", channel=f"eds-{eds.stem}")
        with VirtualPlant(cfg, noise=None) as plant:
            net = canopen.Network(can.Bus(interface="virtual", channel=cfg.bus.channel))
            net.connect()
            try:
                node = net.add_node(1, str(eds))
                assert node.sdo[0x6041].raw == plant.drives[0].values[(0x6041, 0)]
                assert node.sdo[0x6502].raw == int(ev.Eds(eds).get(0x6502), 0)
            finally:
                net.disconnect()


def _const_count(eds: "ev.Eds", map_index: int, count: int, entries: list[int]) -> "ev.Eds":
    """A vendor layout: mapping ``map_index``'s entry count read-only (``const``) at ``count``, its
    entries writable with ``entries`` as defaults (0: empty)."""
    eds.set(map_index, 0, "AccessType", "const").set(map_index, 0, "DefaultValue", count)
    for k, v in enumerate(entries, start=1):
        eds.set(map_index, k, "AccessType", "rw").set(map_index, k, "DefaultValue", f"0x{v:08X}")
    return eds


def test_a_const_count_with_writable_entries_is_planned_within_that_count(tmp_path):
    """RPDO1 with a read-only count of 2 (entries rw, the second one empty by default) and TPDO2 with
    a read-only count of 4: the objects are mapped within each count, the count is never written, the
    unused entry stays empty and the read-back compares the declared entries only."""
    from dataclasses import replace

    from drivers.mapping import import_dictionary, plan_pdos
    from sim.bus_robot import simulated_robot

    src = CFG.drives[0].eds
    e = ev.Eds(src)
    _const_count(e, 0x1600, 2, [0x60400010, 0])
    _const_count(e, 0x1A01, 4, [0x606C0020, 0, 0, 0])
    eds = e.write(tmp_path / "const_count.eds")
    cfg = replace(CFG, drives=tuple(replace(d, eds=eds) for d in CFG.drives))
    with simulated_robot(cfg, with_imu=False) as (robot, plant):
        d = robot.drives[0]
        assert d.plan.rx.pdos[1] == [(0x6040, 0, 16), (0x6071, 0, 16)]
        assert d.plan.tx.pdos[2] == [(0x606C, 0, 32), (0x603F, 0, 16), (0x6061, 0, 8)]
        sd = plant.drives[0]
        assert sd.od_value(0x1A01, 0) == 4 and sd.od_value(0x1A01, 4) == 0  # count kept, the rest empty
        robot.enable()
        robot.write([2.0, 2.0, 2.0])
        s = robot.read()
        np.testing.assert_allclose(s.joint_torque, [2.0, 2.0, 2.0])
        assert s.drive_states == ("OPERATION ENABLED",) * 3
    # a count of 2 cannot take the three objects TPDO2 should carry: the planner keeps within it
    e2 = ev.Eds(src)
    _const_count(e2, 0x1A01, 2, [0x606C0020, 0])
    plan = plan_pdos(import_dictionary(e2.write(tmp_path / "c2.eds"), 1, "d"), 1, "d", *_drive_needs())
    assert len(plan.tx.pdos[2]) <= 2


def _drive_needs():
    from drivers.cia402_setup import RPDO_LAYOUT, RX_NEEDS, TPDO_LAYOUT, TX_NEEDS

    return RX_NEEDS, TX_NEEDS, RPDO_LAYOUT, TPDO_LAYOUT
