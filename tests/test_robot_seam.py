"""The ``Robot`` seam does the common work once: ``write`` checks, clamps and builds the ``Command``
before any back end sees the torques; simulated-only capabilities are declared (``SimulatedRobot``);
a recording's ``source`` and the back ends come from one place each."""
from __future__ import annotations

import math

import numpy as np
import pytest

from otbot_hw.recording import source_metadata
from otbot_hw.robot import Robot, RobotError, RobotFault, SimulatedRobot, Snapshot, operator_channel


class Recorder(Robot):
    """A back end that only records what reaches ``_apply``."""

    period = 0.01
    max_torque = (2.0, 3.0, 1.0)
    torque_quantum = (0.5, 0.5, 0.5)

    def __init__(self):
        self.applied = []
        self.enabled = True
        self._faults = ()

    def _apply(self, torques):
        self._refuse_unless_writable(self._faults, self.enabled)
        self.applied.append(list(torques))
        return np.round(np.array(torques) / 0.5) * 0.5

    def read(self):
        return Snapshot(0.0, 0, 0.0, np.zeros(3), np.zeros(3), np.zeros(3))

    def enable(self):
        self.enabled = True

    def disable(self):
        self.enabled = False

    def quick_stop(self):
        pass

    def fault_reset(self):
        self._faults = ()

    @property
    def faults(self):
        return self._faults


@pytest.mark.parametrize("bad", [[1.0, 2.0], [1.0, math.nan, 0.0], [math.inf, 0.0, 0.0], [[1.0, 2.0, 3.0, 4.0]]])
def test_write_refuses_bad_torques_before_the_back_end_sees_them(bad):
    r = Recorder()
    with pytest.raises(ValueError, match="3 finite numbers"):
        r.write(bad)
    assert r.applied == []


def test_write_clamps_quantizes_and_marks_saturation_once():
    r = Recorder()
    cmd = r.write([5.0, -1.2, 0.3])
    assert r.applied == [[2.0, -1.2, 0.3]]  # clamped to max_torque before the back end
    assert cmd.requested.tolist() == [5.0, -1.2, 0.3]
    assert cmd.commanded.tolist() == [2.0, -1.0, 0.5]
    # clamped (joint 0); -1.2 -> -1.0 and 0.3 -> 0.5 are within half a quantum (0.25): not saturation
    assert cmd.saturated.tolist() == [True, False, False]


def test_write_refuses_a_faulted_or_disabled_back_end_with_the_shared_errors():
    from otbot_hw.robot import Fault

    r = Recorder()
    r._faults = (Fault("pivot", 3, "emcy", "over-current", 0x2310),)
    with pytest.raises(RobotFault, match="robot is faulted: pivot"):
        r.write([0.0, 0.0, 0.0])
    r._faults, r.enabled = (), False
    with pytest.raises(RobotError, match="not enabled"):
        r.write([0.0, 0.0, 0.0])


def test_the_direct_simulated_robot_is_a_simulated_robot_and_the_bus_driver_is_not():
    from drivers.robot import CanopenRobot
    from sim.direct import DirectSimRobot
    from sim.bus_robot import SimulatedBusRobot

    robot = DirectSimRobot(period=0.01, imu_rate=None)
    assert isinstance(robot, SimulatedRobot) and robot.plant is robot
    assert operator_channel(robot) is None  # no operator at this simulated bench
    assert issubclass(SimulatedBusRobot, SimulatedRobot) and SimulatedBusRobot.has_operator
    assert not issubclass(CanopenRobot, SimulatedRobot)
    assert operator_channel(Recorder()) is None
    robot.enable()
    robot.read()
    assert robot.truth() is not None and robot.truth_force().shape == (2,)
    cmd = robot.write([1e6, 0.0, 0.0])  # no limits configured: no clamp
    assert cmd.commanded[0] == 1e6 and not cmd.saturated.any()


def test_source_metadata_from_typed_fields():
    assert source_metadata(simulated=True) == {"source": "simulation"}
    assert source_metadata(simulated=True, bus=True) == {"source": "bus-simulation"}
    assert source_metadata(simulated=False, bus=True) == {"source": "robot"}
    assert source_metadata(program="otbot daemon") == {"source": "otbot daemon"}
    for bad in ({}, {"simulated": True, "program": "loop"}, {"program": " "}):
        with pytest.raises(ValueError):
            source_metadata(**bad)


def test_back_ends_come_from_the_registry():
    from drivers.config import load_robot_config
    from otbot_hw.runtime.backends import BACKENDS, BackendOptions, make_backend, source

    cfg = load_robot_config()
    made = {name: make_backend(name, cfg, BackendOptions(rate=200.0)) for name in BACKENDS}
    assert {n: b.name for n, b in made.items()} == {n: n for n in BACKENDS}
    assert made["sim"].rate == 200.0 and made["bus sim"].rate == cfg.bus.control_rate
    assert [source(b)["source"] for b in made.values()] == ["simulation", "bus-simulation", "robot"]
    with pytest.raises(ValueError, match="unknown back end 'bus moon'"):
        make_backend("bus moon", cfg)


class FakeImu:
    """Records how the driver asks for samples; never has one."""

    timeout = 0.05

    def __init__(self):
        self.reads, self.restarts = [], []

    def read(self, timeout=None):
        self.reads.append(timeout)
        return None

    def restart_watchdog(self, t):
        self.restarts.append(t)


def _driver(cls, **kw):
    import uuid

    import can

    from drivers.config import load_robot_config

    cfg = load_robot_config()
    bus = can.Bus(interface="virtual", channel=f"seam-{uuid.uuid4().hex[:8]}")
    imu = FakeImu()
    return cls(cfg, bus=bus, imu=imu, close_imu=False, **kw), imu, bus


def test_the_real_driver_never_waits_for_its_imu_and_lockstep_is_the_simulated_back_ends():
    from drivers.config import LOCKSTEP_IMU_TIMEOUT
    from drivers.robot import CanopenRobot
    from sim.lockstep import LockstepCanopenRobot

    robot, imu, bus = _driver(CanopenRobot)
    try:
        assert robot._read_imu(0.0, 0) is None and robot._read_imu(0.01, 1) is None
        assert imu.reads == [0, 0] and imu.restarts == [] and not robot.faults  # newest sample, no wait
    finally:
        bus.shutdown()
    robot, imu, bus = _driver(LockstepCanopenRobot)
    try:
        robot._read_imu(5.0, 0)  # the IMU is due at SYNC 0: its sample awaited, the stream's watchdog restarted
        assert imu.restarts == [5.0] and imu.reads == [robot.imu_timeout] and robot.imu_timeout >= LOCKSTEP_IMU_TIMEOUT
        assert [f.kind for f in robot.faults] == ["imu"]  # none came
    finally:
        bus.shutdown()
    robot, imu, bus = _driver(LockstepCanopenRobot, imu_lockstep=False)  # a plant paced in real time
    try:
        robot._read_imu(5.0, 0)
        assert imu.reads == [0] and imu.restarts == []
    finally:
        bus.shutdown()
