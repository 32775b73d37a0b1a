"""Driver layer over a simulated CAN bus: boot, PDO mapping, lockstep plant, recordings.

Every run here goes over real CANopen frames (python-can's virtual bus, or slcan on a
pseudo-terminal to a plant in another process) and real VectorNav sentences on a pty.
"""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from drivers.busload import bus_load, frame_bits
from drivers.config import load_robot_config
from drivers.faults import DriverError
from drivers.robot import CanopenRobot, open_imu
from otbot_hw.params import nominal
from otbot_hw.recording import read_recording
from otbot_hw.runtime.openloop import run_torques
from otbot_hw.sensors import NoiseModel, encoders_ideal, imu_sigma
from sim.lockstep import LockstepCanopenRobot
from sim.bus_robot import simulated_robot
from otbot_hw.simulation.runs import simulated_recording
from otbot_hw.simulation.simulator import ForceSchedule, PivotForce, simulate

CFG = load_robot_config()
DRIVE_Q = 2 * np.pi / (4096 * 10)  # rad per motor count at the joint
ENC_Q = 2 * np.pi / 16384  # rad per encoder count
VEL_Q = 0.5 * DRIVE_Q + 1e-12  # velocity rounding to whole counts/s


def lenient(cfg):
    """``cfg`` with watchdogs a loaded test machine cannot trip (lockstep runs have no deadline)."""
    return cfg.relaxed(1.0)


def expected_joints(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What the drives and the encoder must report for states x (N, 12): floor-quantized angles."""
    wheels, _ = encoders_ideal(x[:, :12], counts_per_rev=40960)
    pivot, _ = encoders_ideal(x[:, :12], counts_per_rev=16384)
    pos = wheels.copy()
    pos[:, 2] = pivot[:, 2]
    return pos, x[:, 9:12]


def test_eds_files_load_with_the_objects_the_drivers_use():
    import canopen

    drive = canopen.import_od(str(CFG.drives[0].eds), 1)
    for index in (0x1000, 0x1001, 0x1017, 0x1018, 0x1400, 0x1600, 0x1800, 0x1A00, 0x603F, 0x6040, 0x6041,
                  0x6060, 0x6061, 0x6064, 0x606C, 0x6071, 0x6072, 0x6076, 0x6077, 0x6502):
        assert index in drive, hex(index)
    assert drive[0x1000].default & 0xFFFF == 402
    assert drive[0x1800][1].default == 0x181  # $NODEID + 0x180 resolved
    enc = canopen.import_od(str(CFG.pivot_encoder.eds), 4)
    for index in (0x1000, 0x1017, 0x1018, 0x1800, 0x1A00, 0x6000, 0x6001, 0x6002, 0x6004):
        assert index in enc, hex(index)
    assert enc[0x1000].default & 0xFFFF == 406


def test_boot_configure_and_enable_over_the_bus():
    with simulated_robot(CFG, noise=NoiseModel()) as (robot, plant):
        for dev in robot.devices:
            assert dev.node.nmt.state == "OPERATIONAL"
        for d, sd in zip(robot.drives, plant.drives):
            assert d.sdo_read(0x6061) == 10  # cyclic synchronous torque
            assert d.sdo_read(0x1017) == 50  # heartbeat producer written from the config
            assert d.sdo_read(0x1A00, 0) == 3 and d.sdo_read(0x1A00, 1) == 0x60410010
            assert d.sdo_read(0x1A00, 2) == 0x60640020 and d.sdo_read(0x1A01, 1) == 0x606C0020
            assert d.sdo_read(0x1600, 1) == 0x60400010 and d.sdo_read(0x1600, 2) == 0x60710010
            assert d.sdo_read(0x1800, 2) == 1 and d.sdo_read(0x1400, 2) == 1  # synchronous
            assert d.sdo_read(0x6072) == 2500  # from the SDO config list
            assert sd.state == "SWITCH ON DISABLED"
        assert robot.encoder.units_per_rev == 16384 and robot.encoder.total_range == 2 ** 26
        robot.enable()
        assert all(sd.state == "OPERATION ENABLED" for sd in plant.drives)
        s = robot.read()
        assert s.drive_states == ("OPERATION ENABLED",) * 3 and not s.faults
        assert s.t == 0.0 and plant.started


def test_profile_torque_used_where_cst_is_missing_and_no_torque_mode_is_an_error():
    with simulated_robot(CFG, with_imu=False, supported_modes=0x08) as (robot, plant):
        assert all(d.mode == 4 for d in robot.drives)
        assert robot.drives[0].sdo_read(0x6061) == 4
        robot.enable()
        robot.write([1.0, 1.0, 1.0])
        robot.read()
        assert plant.drives[0].applied_permille() == 50
    # Profile torque ramps at the torque slope 0x6087 (per-mille/s): 5000 per-mille/s = 50 per 10 ms.
    cfg = CFG
    with simulated_robot(cfg, with_imu=False, supported_modes=0x08) as (robot, plant):
        for d in robot.drives:
            d.sdo_write(0x6087, 0, 5000)
        robot.enable()
        got = []
        for _ in range(5):
            robot.write([4.0, 0.0, 0.0])  # 200 per-mille
            s = robot.read()
            got.append(plant.drives[0].applied_permille())
        assert got == [50, 100, 150, 200, 200]
        np.testing.assert_allclose(s.joint_torque[0], 4.0)  # 0x6077 torque actual
    with pytest.raises(DriverError, match="0x6502"):
        with simulated_robot(CFG, with_imu=False, supported_modes=0x01):
            pass


def test_torques_through_the_drivers_drive_the_plant_like_the_pure_simulation():
    """Constant torques for 1 s (wheel counter started near the INT32 wrap): joint feedback equals
    the pure simulation up to count quantization; the plant state equals it to round-off."""
    n, dt = 100, CFG.bus.period
    u = np.array([6.0, -10.0, 6.0])
    with simulated_robot(CFG, with_imu=False, noise=NoiseModel(),
                         position_offsets=(2 ** 31 - 5000, -(2 ** 31) + 7, 123)) as (robot, plant):
        res = run_torques(robot, np.tile(u, (n, 1)))
        assert res.completed
        raw = plant.drives[0].values[(0x6064, 0)]
    assert raw < 0  # the right wheel's 32-bit counter wrapped during the run
    rec = res.recording
    traj = simulate(nominal(), np.tile(u, (n, 1)), dt)
    np.testing.assert_allclose(rec.torque, np.tile(u, (n + 1, 1)), atol=1e-12)
    np.testing.assert_allclose(np.array(plant.truth.u)[:n], np.tile(u, (n, 1)), atol=1e-12)
    np.testing.assert_allclose(rec.truth_q, traj.q, atol=1e-12)
    pos, vel = expected_joints(traj.x)
    np.testing.assert_allclose(rec.joint_pos, pos, atol=1e-9)
    np.testing.assert_allclose(rec.joint_vel, vel, atol=VEL_Q)
    assert rec.joint_pos[-1, 0] > 5  # the wheel really turned (about one revolution)


@pytest.mark.parametrize("fixture", ["stand", "locked"])
def test_bench_fixtures_and_external_force_match_the_pure_simulation(fixture):
    n, dt = 40, CFG.bus.period
    U = np.column_stack([np.linspace(-3, 5, n), np.full(n, 2.0), np.linspace(4, -4, n)])
    U = np.round(U / 0.02) * 0.02  # whole per-mille steps, so the drives apply exactly these torques
    with simulated_robot(CFG, with_imu=False, fixture=fixture) as (robot, plant):
        res = run_torques(robot, U)
        assert res.completed, res.fault
    traj = simulate(nominal(), U, dt, fixture=fixture)
    np.testing.assert_allclose(res.recording.truth_q, traj.q, atol=1e-12)
    np.testing.assert_allclose(res.recording.joint_pos, expected_joints(traj.x)[0], atol=1e-9)
    assert np.ptp(traj.q[:, 0]) == 0.0  # chassis held


def test_pivot_force_schedule_is_applied_in_plant_time():
    n, dt = 50, CFG.bus.period
    forces = ForceSchedule([PivotForce(start=0.1, duration=0.2, fx=20.0, fy=-5.0)])
    with simulated_robot(CFG, with_imu=False, forces=forces) as (robot, plant):
        res = run_torques(robot, np.zeros((n, 3)))
        assert res.completed, res.fault
    traj = simulate(nominal(), np.zeros((n, 3)), dt, forces=forces)
    np.testing.assert_allclose(res.recording.truth_q, traj.q, atol=1e-12)
    assert abs(traj.q[-1, 0]) > 1e-3  # the push moved the robot


def test_pivot_angle_from_the_pivot_drive_when_configured():
    from dataclasses import replace

    from drivers.config import EncoderConfig

    cfg = replace(CFG, pivot_encoder=EncoderConfig(source="drive"))
    n = 30
    with simulated_robot(cfg, with_imu=False) as (robot, plant):
        assert robot.encoder is None and plant.encoder is None
        res = run_torques(robot, np.tile([0.0, 0.0, 4.0], (n, 1)))
        assert res.completed, res.fault
    traj = simulate(nominal(), np.tile([0.0, 0.0, 4.0], (n, 1)), cfg.bus.period)
    np.testing.assert_allclose(res.recording.joint_pos, encoders_ideal(traj.x, 40960)[0], atol=1e-9)


def test_bus_recording_matches_the_pure_simulation_recording(tmp_path):
    """The paper's chassis experiment over the bus, IMU on a pty, streamed to MCAP, read back:
    sample by sample equal to ``simulated_recording`` up to encoder quantization, IMU noise
    (sigma from the paper) and the VectorNav ASCII format's resolution. Then the chassis
    identification (paper step 2) on the bus recording recovers the parameters as well as on a
    pure-simulation recording with the same noise level.
    """
    n, dt = 300, 0.01
    u = np.tile([6.0, -10.0, 6.0], (n, 1))
    path = tmp_path / "bus.mcap"
    with simulated_robot(CFG, noise=NoiseModel.paper(), seed=3) as (robot, plant):
        run = run_torques(robot, u, path=path, metadata={"experiment": "chassis"})
    assert run.completed
    bus = read_recording(path)
    pure = simulated_recording(nominal(), u, dt, NoiseModel())  # noiseless reference
    assert len(bus) == len(pure) == n + 1 and not bus.truncated
    np.testing.assert_allclose(bus.t, pure.t, atol=1e-12)
    np.testing.assert_allclose(bus.torque, pure.torque, atol=1e-12)
    np.testing.assert_allclose(bus.truth_q, pure.truth_q, atol=1e-12)
    pos, _ = expected_joints(np.hstack([pure.truth_q, pure.truth_qd]))
    np.testing.assert_allclose(bus.joint_pos, pos, atol=1e-9)
    # Joint rates: paper's encoder-rate noise 0.01 rad/s plus rounding to counts/s.
    dv = bus.joint_vel - pure.joint_vel
    assert abs(dv.mean()) < 3e-3 and 0.008 < dv.std() < 0.012
    # IMU: the specific force and rate of the model plus the paper's noise, through the sensor frame.
    sigma = imu_sigma()
    for got, ref in ((bus.imu_accel, pure.imu_accel), (bus.imu_gyro, pure.imu_gyro)):
        r = got - ref
        assert np.all(np.abs(r.mean(axis=0)) < 4 * sigma / np.sqrt(len(r)) + 1e-3)
        assert np.all(np.abs(r.std(axis=0) / sigma - 1) < 0.15)
    assert bus.metadata["experiment"] == "chassis" and bus.metadata["source"] == "loop"
    # Chassis identification end-to-end over the bus, against the same fit on a pure simulation.
    from otbot_hw.identification.steps import identify_step

    truth = nominal()
    noisy = simulated_recording(truth, u, dt, NoiseModel.paper(), seed=3)
    fits = {name: identify_step("chassis", [rec], truth) for name, rec in (("bus", bus), ("pure", noisy))}
    for name, res in fits.items():
        assert res.converged, (name, res.reasons)
        for p in ("m_c", "I_c", "x_B", "y_B"):
            err = res.fit.estimate[p] - getattr(truth, p)
            assert abs(err) < 4 * res.fit.std[p], (name, p, err, res.fit.std[p])
    for p in ("m_c", "I_c", "x_B", "y_B"):  # equally informative: same reported uncertainty
        assert fits["bus"].fit.std[p] == pytest.approx(fits["pure"].fit.std[p], rel=0.25), p


def test_torque_limits_clamp_and_report():
    with simulated_robot(CFG, with_imu=False) as (robot, plant):
        robot.enable()
        cmd = robot.write([100.0, -55.0, 3.0])
        robot.read()
        np.testing.assert_allclose(cmd.commanded, [40.0, -40.0, 3.0])
        assert cmd.saturated.tolist() == [True, True, False]
        assert [sd.applied_permille() for sd in plant.drives] == [2000, 2000, 150]  # left polarity -1
        np.testing.assert_allclose([sd.joint_torque() for sd in plant.drives], [40.0, -40.0, 3.0])
        with pytest.raises(ValueError, match="finite"):
            robot.write([np.nan, 0, 0])


def test_quick_stop_and_disable_walk_the_state_machine():
    with simulated_robot(CFG, with_imu=False) as (robot, plant):
        robot.enable()
        robot.write([5.0, 5.0, 5.0])
        robot.read()
        robot.quick_stop()
        assert {sd.state for sd in plant.drives} == {"QUICK STOP ACTIVE"}
        assert [sd.joint_torque() for sd in plant.drives] == [0.0, 0.0, 0.0]
        robot.enable()  # transition 16 back to OPERATION ENABLED
        assert {sd.state for sd in plant.drives} == {"OPERATION ENABLED"}
        robot.disable()
        assert {sd.state for sd in plant.drives} == {"SWITCH ON DISABLED"}


def test_bus_load_accounting():
    assert frame_bits(0) == 55 and frame_bits(8) == 135  # 47 + 8n + worst-case stuffing + 3 IFS
    load = bus_load(CFG)
    # SYNC + 3 x (RPDO 4 B + TPDO 8 B + TPDO 7 B) + encoder TPDO 4 B
    assert load.bits_per_cycle == 55 + 3 * (95 + 135 + 125) + 95
    assert 800 < load.max_rate < 830 and load.warning() is None
    assert "exceeds" in bus_load(CFG, rate=1000).warning()
    slow = CFG.replace_bus(bitrate=125_000)
    assert bus_load(slow).max_rate < 100 and bus_load(slow).warning()


def _plant_process(*args):
    code = "import sys; from otbot_hw.cli import main; sys.exit(main())"
    return subprocess.Popen([sys.executable, "-c", code, "plant", *args], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)


def test_plant_in_another_process_over_slcan_on_a_pty():
    proc = _plant_process("--transport", "slcan", "--noise", "none")
    try:
        info = json.loads(proc.stdout.readline())
        assert info["can_interface"] == "slcan" and info["can_channel"].startswith("/dev/")
        cfg = lenient(CFG).replace_bus(interface="slcan", channel=info["can_channel"],
                                       options={"sleep_after_open": 0})
        robot = LockstepCanopenRobot(cfg, imu=open_imu(cfg.imu, port=info["imu_port"]))
        n = 60
        with robot:
            robot.open()
            res = run_torques(robot, np.tile([6.0, -10.0, 6.0], (n, 1)))
        assert res.completed
        traj = simulate(nominal(), np.tile([6.0, -10.0, 6.0], (n, 1)), cfg.bus.period)
        np.testing.assert_allclose(res.recording.joint_pos, expected_joints(traj.x)[0], atol=1e-9)
        ref = simulated_recording(nominal(), np.tile([6.0, -10.0, 6.0], (n, 1)), cfg.bus.period)
        np.testing.assert_allclose(res.recording.imu_accel, ref.imu_accel, atol=2e-3)  # ASCII resolution
    finally:
        proc.stdin.close()
        assert proc.wait(timeout=20) == 0


def test_socketcan_transport_where_the_kernel_has_it():
    import socket

    import can

    if not hasattr(socket, "AF_CAN"):
        pytest.skip("no AF_CAN in this Python build")
    try:
        probe = can.Bus(interface="socketcan", channel="vcan0")
    except (OSError, can.CanError) as exc:
        pytest.skip(f"socketcan vcan0 not available on this kernel/machine: {exc}")
    probe.shutdown()
    cfg = lenient(CFG).replace_bus(interface="socketcan", channel="vcan0")
    proc = _plant_process("--transport", "socketcan", "--channel", "vcan0", "--noise", "none", "--no-imu")
    try:
        json.loads(proc.stdout.readline())
        with LockstepCanopenRobot(cfg) as robot:  # a plant process: lockstep is the simulated back end's
            robot.open()
            res = run_torques(robot, np.tile([1.0, 1.0, 1.0], (20, 1)))
        assert res.completed
    finally:
        proc.stdin.close()
        proc.wait(timeout=20)


def test_slcan_adapter_protocol_and_bad_lines():
    import time

    import serial

    from sim.slcan_adapter import SlcanAdapterBus, format_frame, parse_frame

    m = parse_frame("t1232ABCD")
    assert (m.arbitration_id, bytes(m.data), m.is_extended_id) == (0x123, b"\xab\xcd", False)
    assert parse_frame("T1ABCDEF08" + "00" * 8).arbitration_id == 0x1ABCDEF0
    assert parse_frame("r7FF4").is_remote_frame
    for bad in ("t12", "t1233AB", "t8002AABB", "t1239" + "00" * 9, "tXYZ0", "T123"):
        assert parse_frame(bad) is None, bad
    assert format_frame(m) == b"t1232ABCD\r"
    adapter = SlcanAdapterBus()
    host = serial.Serial(adapter.port, 115200, timeout=0.5)
    try:
        host.write(b"t1231AA\r")  # channel not open yet: dropped
        assert adapter.recv(0.2) is None
        host.write(b"S8\rO\r")
        assert adapter.recv(0.2) is None and adapter.is_open and adapter.bitrate == 1_000_000
        assert host.read(2) == b"\r\r"
        host.write(b"garbage\rt12\rt7FF2BEEF\r")
        msg = adapter.recv(1.0)
        assert msg.arbitration_id == 0x7FF and bytes(msg.data) == b"\xbe\xef"
        assert adapter.malformed == 2 and host.read(2) == b"\a\a"  # BEL for each bad line
        adapter.send(parse_frame("t0810"))
        deadline = time.monotonic() + 1
        got = b""
        while not got.endswith(b"\r") and time.monotonic() < deadline:
            got += host.read(1)
        assert got == b"t0810\r"
    finally:
        host.close()
        adapter.shutdown()


def test_the_loop_runner_paces_and_the_driver_never_sleeps_to_pace():
    """One clock: ``read()`` on a paced bus sends its SYNC at once (the driver never sleeps on the
    caller's thread); the loop runner paces the cycles at the control rate."""
    import threading
    import time

    import can

    from otbot_hw.runtime.openloop import run_torques
    from sim.bus_robot import VirtualPlant

    # a pacing test: the drives' period watchdogs (SYNC, RPDO) off, so a loaded machine cannot trip them
    cfg = lenient(CFG).unpaced().replace_bus(channel="otbot-realtime-test")
    with VirtualPlant(cfg) as plant:
        robot = CanopenRobot(cfg, bus=can.Bus(interface="virtual", channel=cfg.bus.channel))  # the real driver
        with robot:
            robot.open()
            robot.enable()
            k0 = plant.k
            me, sleeps = threading.get_ident(), []
            real_sleep = time.sleep

            def recorded(s):
                if threading.get_ident() == me:
                    sleeps.append(s)
                real_sleep(s)

            time.sleep = recorded
            try:
                for _ in range(11):
                    robot.write([0.0, 0.0, 0.0])
                    robot.read()
            finally:
                time.sleep = real_sleep
            with plant.lock:  # the plant steps its model after sending a SYNC's TPDOs: let it finish
                assert plant.k == k0 + 11
            # 11 cycles back to back: the caller's thread never slept (waiting for TPDOs is on events)
            assert sleeps == []
            robot.quick_stop()
            t0 = time.monotonic()
            res = run_torques(robot, np.zeros((11, 3)), realtime=True)
            elapsed = time.monotonic() - t0
    assert res.completed, res.fault
    assert elapsed >= 10 * cfg.bus.period * 0.95
    assert res.stats.period_p50 == pytest.approx(cfg.bus.period, abs=2e-3)


def test_velocity_unit_of_the_drives_is_configurable():
    from dataclasses import replace

    drives = tuple(replace(d, velocity_unit="0.1 rpm") for d in CFG.drives)
    cfg = replace(CFG, drives=drives)
    n = 40
    with simulated_robot(cfg, with_imu=False) as (robot, plant):
        res = run_torques(robot, np.tile([6.0, -10.0, 6.0], (n, 1)))
        assert res.completed, res.fault
    qd = np.array(plant.truth.x)[:n + 1, 9:12]
    # 0.1 rpm at the motor = 2 pi / 600 / 10 rad/s at the joint: rounding error at most half of it.
    err = np.abs(res.recording.joint_vel - qd)
    assert err.max() <= 0.5 * 2 * np.pi / 6000 + 1e-12 and err.max() > 1e-5


def test_a_second_master_on_a_running_plant_keeps_imu_lockstep():
    """The plant keeps running between two masters; with the IMU at a tenth of the SYNC rate the
    IMU ticks of the second master line up with the plant's because the node resets restart the count."""
    import can

    from sim.bus_robot import VirtualPlant, open_sim_imu

    cfg = lenient(CFG).replace_bus(channel="otbot-two-masters", control_rate=1000.0)
    pub, drv = open_sim_imu(cfg)
    try:
        with VirtualPlant(cfg, imu=pub, noise=NoiseModel()) as plant:
            for master in range(2):
                robot = LockstepCanopenRobot(cfg, bus=can.Bus(interface="virtual", channel=cfg.bus.channel), imu=drv,
                                             close_imu=False, sdo_timeout=1.0)
                robot.open()
                robot.enable()
                for _ in range(23 + 10 * master):
                    robot.write([0.0, 0.0, 2.0])
                    s = robot.read()
                    assert not s.faults, s.faults
                robot.close()
            assert plant.k > 50
    finally:
        drv.close()
        pub.close()


def test_controlword_values_live_in_the_cia402_module_only():
    """Issue 19: CiA 402 words only in the profile module — no controlword literal or assignment in
    the rest of the master's code."""
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    pattern = re.compile(r"0x000[0-9A-Fa-f]\b.*(controlword|cw)|controlword\s*=|\.controlword\s*=|0x000F", re.I)
    offenders = []
    for path in [*(root / "drivers").glob("*.py"), *(root / "otbot_hw").rglob("*.py")]:
        if path.name == "cia402.py":
            continue
        for no, line in enumerate(path.read_text().splitlines(), start=1):
            if pattern.search(line):
                offenders.append(f"{path.relative_to(root)}:{no}: {line.strip()}")
    assert not offenders, offenders


def test_every_paced_run_arms_the_drives_sync_and_rpdo_watchdogs():
    """``bus config`` without lockstep (otbot run/track/bench and the daemon alike) arms 0x1006 and
    the RPDO deadline as the configuration says (``drives.sync_watchdog``, ``drives.rpdo_timeout``: plain
    configuration); lockstep with a simulated plant arms neither."""
    from dataclasses import replace

    from otbot_hw.runtime.backends import BusConfigBackend
    from sim.bus_robot import VirtualPlant

    cfg = lenient(CFG).replace_bus(interface="virtual", channel="otbot-paced-arming")
    period_us = int(round(cfg.bus.period * 1e6))
    rpdo_ms = round(cfg.drives[0].rpdo_timeout * cfg.bus.period * 1000)
    off = replace(cfg, drives=tuple(replace(d, sync_watchdog=False, rpdo_timeout=0) for d in cfg.drives))
    for c, lockstep, want in ((cfg, False, (period_us, rpdo_ms)), (cfg, True, (0, 0)), (off, False, (0, 0))):
        with VirtualPlant(c) as plant:
            backend = BusConfigBackend(c, with_imu=False, lockstep=lockstep)
            assert backend.paced is (not lockstep) and backend.realtime is (not lockstep)
            with backend.open():
                armed = [(d.od_value(0x1006), d.od_value(0x1400, 5)) for d in plant.drives]
        assert armed == [want] * 3, (lockstep, armed)


def test_enable_operation_only_to_keep_or_make_a_commanded_drive_enabled():
    """CiA 402 words of ``drivers.cia402``: every (command, reported state) pair; "enable operation"
    is sent only to keep a commanded drive in OPERATION ENABLED and, on the way there, from SWITCHED
    ON; a drive found in QUICK STOP ACTIVE gets quick stop, any other unexpected state disable voltage."""
    from drivers import cia402 as c

    states = ("NOT READY TO SWITCH ON", "SWITCH ON DISABLED", "READY TO SWITCH ON", "SWITCHED ON",
              "OPERATION ENABLED", "QUICK STOP ACTIVE", "FAULT REACTION ACTIVE", "FAULT")
    for commanded in (c.DISABLED, c.ENABLING, c.ENABLED, c.QUICK_STOP):
        for state in states:
            cw = c.cyclic_controlword(commanded, state)
            assert (cw == c.CW_ENABLE_OPERATION) == (commanded == c.ENABLED and state == "OPERATION ENABLED")
            if state == "QUICK STOP ACTIVE" or commanded == c.QUICK_STOP:
                assert cw == c.CW_QUICK_STOP
            elif cw != c.CW_ENABLE_OPERATION:
                assert cw == c.CW_DISABLE_VOLTAGE
    assert {s for s, cw in c.ENABLE_PATH.items() if cw == c.CW_ENABLE_OPERATION} == {"SWITCHED ON",
                                                                                     "OPERATION ENABLED"}
    assert c.expected_states(c.ENABLED) == ("OPERATION ENABLED",)
    assert set(c.expected_states(c.QUICK_STOP)) >= {"QUICK STOP ACTIVE", "SWITCH ON DISABLED", "OPERATION ENABLED"}
