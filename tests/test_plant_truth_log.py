"""The plant's truth log stays bounded (issue 22): a plant behind a daemon steps one SYNC after
another for hours; the log keeps the latest entries (all of a short run's) and counts the rest."""
from __future__ import annotations

import numpy as np

from drivers.config import load_robot_config
from otbot_hw.runtime.openloop import run_torques
from otbot_hw.sensors import NoiseModel
from sim.bus_robot import simulated_robot
from sim.plant import TruthLog


def test_truth_log_stays_bounded_and_keeps_the_latest_entries():
    log = TruthLog(keep=100)
    for k in range(100_000):
        log.append(k * 1e-3, np.full(12, k), np.full(3, k), np.full(2, k))
        assert len(log.t) < 200
    assert len(log.t) == len(log.x) == len(log.u) == len(log.f) >= 100
    assert log.dropped + len(log.t) == 100_000
    assert [x[0] for x in log.x] == list(range(log.dropped, 100_000))  # in order, the newest last
    assert log.t[-1] == 99.999 and log.f[-1][0] == 99_999
    short = TruthLog()
    for k in range(1000):
        short.append(k, k, k, k)
    assert short.t == list(range(1000)) and short.dropped == 0  # a short run keeps all of its truth


def test_the_plant_over_many_syncs_keeps_a_bounded_log_with_the_latest_truth():
    n = 60
    u = np.array([1.0, -1.0, 0.5])
    with simulated_robot(load_robot_config(), with_imu=False, noise=NoiseModel()) as (robot, plant):
        plant.truth.keep = 8
        res = run_torques(robot, np.tile(u, (n, 1)))
        assert res.completed
        with plant.lock:  # (the SYNC after the run may be stepping)
            assert len(plant.truth.t) < 16
            assert plant.truth.dropped + len(plant.truth.t) == plant.k  # every started SYNC counted
            np.testing.assert_array_equal(plant.truth.x[-1], plant.sync_x)  # the latest SYNC's state
        kept = np.array(plant.truth.u)[:-1]  # the run's torques (the last SYNC: the stop after it)
        np.testing.assert_allclose(kept, np.tile(u, (len(kept), 1)), atol=1e-12)
