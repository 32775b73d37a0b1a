"""Pins of places where a planted bug survived the suite (issue 18, item 8): each test fails under
the mutation ``benchmarks/mutation_probe.py`` names next to it."""
from __future__ import annotations

import dataclasses
import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

from otbot_hw.motors import MotorLimits
from otbot_hw.params import nominal
from otbot_hw.runtime.feedback import StateEstimate
from otbot_hw.runtime.supervisor import SafetyConfig, Supervisor

LIMITS = MotorLimits(np.array([10.0, 10.0, 10.0]))


def _estimate(x: float, y: float) -> StateEstimate:
    return StateEstimate(0.0, np.array([x, y, 0.0]), np.zeros(3), np.zeros(6), 0.0)


def _config(**config) -> SafetyConfig:
    return dataclasses.replace(SafetyConfig.off(), **config)


# -- supervisor: |rate| and the workspace's y bounds ---------------------------------------------------
@pytest.mark.parametrize("joint, limit_key", [(0, "max_wheel_rate"), (1, "max_wheel_rate"), (2, "max_pivot_rate")])
def test_a_joint_turning_backwards_past_its_rate_limit_latches(joint, limit_key):
    sup = Supervisor(LIMITS, _config(**{limit_key: 5.0}), 0.01)
    w = np.zeros(3)
    w[joint] = -4.9
    assert sup.check(0.0, w) is None                     # backwards within the limit: fine
    w[joint] = -5.1
    v = sup.check(0.01, w)
    assert v is not None and v.kind == "joint_rate" and v.value == pytest.approx(5.1)
    assert sup.check(0.02, np.zeros(3)) is v             # latched


@pytest.mark.parametrize("x, y, left", [
    (0.0, 3.5, True), (0.0, -2.5, True),                 # out through y only (x well inside)
    (4.9, 2.9, False), (-0.9, -1.9, False),              # inside, near the asymmetric corners
    (5.5, 0.0, True), (-1.5, 0.0, True),
])
def test_an_asymmetric_workspace_is_left_through_y_alone(x, y, left):
    sup = Supervisor(LIMITS, _config(workspace=(-1.0, 5.0, -2.0, 3.0)), 0.01)
    v = sup.check(0.0, np.zeros(3), _estimate(x, y))
    assert (v is not None and v.kind == "workspace") == left, v


# -- MCAP log_time = round(t 1e9) ns on every message -------------------------------------------------
def test_every_written_message_has_log_time_round_t_ns(tmp_path):
    from mcap.reader import make_reader

    from otbot_hw.recording import read_recording, write_recording
    from otbot_hw.sensors import NoiseModel
    from otbot_hw.simulation.runs import simulated_recording

    rec = simulated_recording(nominal(), np.tile([6.0, -10.0, 6.0], (30, 1)), 0.01, NoiseModel.paper())
    # times whose ns value has a fraction > 0.5: truncation (int) or microsecond stamps give other numbers
    rec.t = np.arange(len(rec)) * (0.02 / 3) + 2e-7 / 3
    rec.events = [{"t": float(rec.t[3]) + 1e-3 / 3, "kind": "note", "text": "a"},
                  {"t": float(rec.t[20]) + 2e-3 / 3, "kind": "note", "text": "b"}]
    assert sum(int(t * 1e9) != round(t * 1e9) for t in rec.t.tolist()) > 5
    path = tmp_path / "r.mcap"
    write_recording(path, rec)
    seen = 0
    with open(path, "rb") as f:
        for _schema, channel, msg in make_reader(f).iter_messages(log_time_order=False):
            t = json.loads(msg.data)["t"]
            assert msg.log_time == round(t * 1e9), (channel.topic, t, msg.log_time)
            assert msg.publish_time == msg.log_time, (channel.topic, t)
            seen += 1
    assert seen == len(rec) * (len(rec.channels()) - 1) + len(rec.events)
    np.testing.assert_array_equal(read_recording(path).t, rec.t)


# -- EKF: the gyro bias walks gyro_bias_walk^2 per second, whatever the step rate -----------------------
@pytest.mark.parametrize("rate", [20.0, 100.0, 1000.0])
def test_gyro_bias_variance_grows_by_the_walk_squared_per_second(rate):
    """At rest with no IMU (model prediction, zero torque), nothing observes b_g: its variance grows by
    exactly gyro_bias_walk^2 over 1 s; with the IMU (its prediction), the process noise added to b_g over
    1 s sums to the same."""
    from otbot_hw.estimation.config import EstimatorConfig
    from otbot_hw.estimation.ekf import BG, PoseEKF

    walk = 3e-3
    cfg = EstimatorConfig(gyro_bias_walk=walk)
    dt = 1.0 / rate
    n = int(round(rate))
    ekf = PoseEKF(nominal(), dt, cfg)
    ekf.initialize(0.0, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    p0 = ekf.kf.P[BG, BG]
    for k in range(1, n + 1):
        ekf.step(k * dt, np.zeros(3), np.zeros(3), torque=np.zeros(3))
    assert ekf.prediction == "model"
    assert ekf.kf.P[BG, BG] - p0 == pytest.approx(walk ** 2, rel=1e-6)

    ekf = PoseEKF(nominal(), dt, EstimatorConfig(gyro_bias_walk=walk, prediction="imu"))
    g = [0.0, 0.0, 9.81]
    ekf.initialize(0.0, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], imu_accel=g, imu_gyro=[0.0, 0.0, 0.0])
    added = 0.0
    for k in range(1, n + 1):
        ekf.step(k * dt, np.zeros(3), np.zeros(3), imu_accel=g, imu_gyro=[0.0, 0.0, 0.0], torque=np.zeros(3))
        assert ekf.prediction == "imu"
        added += ekf.kf.Q[BG, BG]
    assert added == pytest.approx(walk ** 2, rel=1e-6)


# -- identification gates: a weakly excited run gets "redo" ---------------------------------------------
def _fake_fit(best_allows: float, seed: int = 0):
    """A fit whose every gate passes except, possibly, excitation: one run, two channels whose noise
    (sigma 1) lets a perfect model reach ``best_allows`` % and half of it, residuals white at the noise."""
    rng = np.random.default_rng(seed)
    n = 400
    measured, predicted, sigma, fit_percent = {}, {}, {}, {}
    for c, target in (("a_x", best_allows), ("w_z", best_allows / 2)):
        spread = 1.0 / (1.0 - target / 100.0)
        signal = np.sin(np.linspace(0, 6 * np.pi, n))
        signal *= math.sqrt(max(spread ** 2 - 1.0, 1e-12)) / signal.std()
        r = rng.standard_normal(n)
        measured[c] = signal + r
        predicted[c] = signal
        sigma[c] = 1.0
        s = float(np.std(measured[c]))
        fit_percent[f"run/{c}"] = 100.0 * (1.0 - np.linalg.norm(r) / np.linalg.norm(measured[c] - measured[c].mean()))
        assert abs(100.0 * (1.0 - 1.0 / s) - target) < 5
    exp = SimpleNamespace(name="run", channels=list(measured), measured=measured, sigma=sigma)
    fit = SimpleNamespace(converged=True, reasons=[], fit_percent=fit_percent, predicted=[predicted],
                          names=["m_c"], std={"m_c": 0.1}, theta=np.array([1.0]))
    return fit, [exp]


@pytest.mark.parametrize("best", [8.0, 30.0, 45.0])
def test_a_weakly_excited_run_gets_redo(best):
    from otbot_hw.identification.gates import check_fit

    fit, exps = _fake_fit(best)
    g = check_fit("chassis", fit, exps, model=None, crb={"m_c": 0.1})
    assert g.verdict == "redo"
    failed = [c for c in g.checks if not c.passed]
    assert [c.gate for c in failed] == ["excitation"], g.reasons
    assert "barely moved" in g.reasons[0]


def test_a_well_excited_run_passes_the_same_gates():
    from otbot_hw.identification.gates import check_fit

    fit, exps = _fake_fit(80.0)
    g = check_fit("chassis", fit, exps, model=None, crb={"m_c": 0.1})
    assert g.verdict == "pass", g.reasons
