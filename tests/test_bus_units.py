"""Unit conversions between the drivers and the simulated hardware on a configuration that differs
from the default everywhere a sign, a ratio or a unit can be dropped or doubled: a mounting that is
not its own transpose, polarity -1 on some joints, gear ratios that differ per joint, an encoder
counting backwards through a gear, and every velocity unit of 0x606C. The simulated drives convert
with their own CiA 402 formulas, so a wrong factor on either side shows against the plant's truth."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from drivers.config import VELOCITY_UNITS, load_robot_config
from otbot_hw.sensors import NoiseModel, accelerations, imu_ideal
from sim.bus_robot import simulated_robot

CFG = load_robot_config()
#: sensor x -> B'' y, sensor y -> B'' z, sensor z -> B'' x: a proper rotation with R != R^T
MOUNTING = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
GEARS = (7.5, 12.0, 5.0)
POLARITIES = (-1, 1, -1)
#: 0x606C units per motor revolution per second (CiA 402), written out independently of both sides
PER_REV_PER_S = {"counts/s": None, "rpm": 60.0, "0.1 rpm": 600.0, "0.001 rpm": 60000.0}


def varied(unit: str):
    drives = tuple(replace(d, gear_ratio=g, polarity=p, velocity_unit=unit)
                   for d, g, p in zip(CFG.drives, GEARS, POLARITIES))
    enc = replace(CFG.pivot_encoder, direction=-1, gear_ratio=2.0, offset=1000)
    return replace(CFG, drives=drives, pivot_encoder=enc, imu=replace(CFG.imu, mounting=MOUNTING))


@pytest.mark.parametrize("unit", VELOCITY_UNITS)
def test_readings_match_the_plant_on_a_configuration_unlike_the_default(unit):
    assert not np.allclose(MOUNTING, MOUNTING.T)
    cfg = varied(unit)
    u = np.array([6.0, -10.0, 4.0])
    with simulated_robot(cfg, noise=NoiseModel()) as (robot, plant):
        robot.enable()
        snaps = []
        for _ in range(40):
            cmd = robot.write(u)
            snaps.append(robot.read())
        x = np.array(plant.truth.x)
        # the torques the plant applied are the commanded joint torques (gear, polarity, rated
        # torque), within the per-mille quantum of each joint
        np.testing.assert_allclose(plant.truth.u[-1], cmd.commanded, atol=1e-9)
        assert np.all(np.abs(cmd.commanded - u) <= [0.5 * 2.0 * g / 1000 + 1e-12 for g in GEARS])
        cpr = cfg.drives[0].counts_per_rev
        upr = plant.encoder.od_value(0x6001)
        for k, s in enumerate(snaps):
            q = x[k]
            for j in (0, 1):  # wheel drives: one motor count at the joint
                assert abs(s.joint_pos[j] - q[3 + j]) <= 2 * np.pi / (cpr * GEARS[j]) + 1e-12, (k, j)
            assert abs(s.joint_pos[2] - q[5]) <= 2 * np.pi / (upr * 2.0) + 1e-12, k  # the pivot encoder
            for j in range(3):
                per = PER_REV_PER_S[unit] or cpr
                quantum = 2 * np.pi / per / GEARS[j]  # rad/s at the joint of one 0x606C unit
                assert abs(s.joint_vel[j] - q[9 + j]) <= 0.5 * quantum + 1e-9, (k, j, unit)
        # IMU: the driver's platform-frame reading is the plant's platform-frame specific force and rate
        zero_noise = plant.noise.accel == 0 and plant.noise.gyro == 0
        assert zero_noise
        for k in (5, 20, 39):  # expected from the model's own sensor functions, not the plant's code path
            s = snaps[k]
            u_k, f_k = np.array(plant.truth.u[k:k + 1]), np.array(plant.truth.f[k:k + 1])
            acc, gyro = imu_ideal(x[k:k + 1], accelerations(x[k:k + 1], u_k, f_k, plant.params))
            np.testing.assert_allclose(s.imu_accel, acc[0], atol=2e-3)  # sentence resolution
            np.testing.assert_allclose(s.imu_gyro, gyro[0], atol=2e-5)
        assert np.abs(x[-1, 9:12]).min() > 0.05  # every joint moved: signs were exercised
