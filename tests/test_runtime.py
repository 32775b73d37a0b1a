"""The loop runner and its back ends: period accounting, one recorded sample per cycle, faults that
quick-stop the robot (judged from the drives' own state), the direct back end against the bus back
end and against the old zero-delay closed loop, --plant-params, the EKF path, bad input."""
from __future__ import annotations

import json
import sys
import time
import types
from dataclasses import dataclass, field

import numpy as np
import pytest

from drivers.config import load_robot_config
from otbot_hw.cli import main
from otbot_hw.control.computed_torque import ComputedTorqueController, TaskState
from otbot_hw.control.gains import gains_from_tstab
from otbot_hw.control.limiter import TorqueLimiter
from otbot_hw.control.scenarios import corridor_spec
from otbot_hw.model import effects as fx
from otbot_hw.model import sensor_model
from otbot_hw.motors import MotorLimits, load_motor_limits
from otbot_hw.params import nominal
from otbot_hw.recording import read_recording
from otbot_hw.runtime import (ControlStep, LoopRunner, OpenLoopTorques, SafetyConfig, StateEstimate, Supervisor,
                              TrackingController, TruthFeedback)
from otbot_hw.runtime.backends import BusSimBackend, DirectBackend
from otbot_hw.runtime.openloop import run_torques
from otbot_hw.runtime.tracking import track_reference
from otbot_hw.sensors import NoiseModel
from otbot_hw.simulation.simulator import Stepper, rest_state, simulate, simulate_extended
from sim.direct import DirectSimRobot

CFG = load_robot_config()
P = nominal()
LIMITS = load_motor_limits()


def corridor_law():
    return ComputedTorqueController(P, gains_from_tstab(3.0))


# -- the runner itself ---------------------------------------------------------------------------
def test_every_cycle_is_one_sample_with_every_topic_and_the_file_equals_memory(tmp_path):
    """Tracking on the direct back end with an IMU at a tenth of the loop rate: cycles = samples at
    t_k = k T exactly, every per-sample topic present, the MCAP file loads to what the runner kept, the
    IMU changes only on its own ticks, the timing report adds up."""
    path = tmp_path / "run.mcap"
    ref = corridor_spec(smooth=True).reference
    backend = DirectBackend(rate=500.0, noise=NoiseModel.paper(), imu_rate=50.0)
    run = track_reference(ref, corridor_law(), P, LIMITS, backend, duration=2.0, path=path)
    res = run.loop
    assert res.completed and res.fault is None
    rec = res.recording
    n = int(round(2.0 * 500)) + 2
    assert len(rec) == res.stats.cycles == n
    np.testing.assert_array_equal(rec.t, np.arange(n) * 0.002)
    assert res.stats.robot_time == pytest.approx(n * 0.002)
    # lockstep: no pacing; the real-time factor is robot time over wall time (its size is a benchmark's business)
    assert res.stats.wall_time > 0 and res.stats.realtime_factor == pytest.approx(res.stats.robot_time / res.stats.wall_time)
    assert res.stats.period_p50 > 0 and res.stats.compute_p50 > 0 and res.stats.period_max >= res.stats.period_p99
    disk = read_recording(path)
    assert not disk.truncated and disk.channels() == ["/otbot/command", "/otbot/joints", "/otbot/imu", "/otbot/truth",
                                                      "/otbot/estimate", "/otbot/reference", "/otbot/events"]
    for name in ("t", "torque", "joint_pos", "joint_vel", "imu_accel", "imu_gyro", "truth_q", "truth_qd",
                 "estimate_pose", "estimate_std", "reference_p", "reference_pd"):
        np.testing.assert_array_equal(getattr(disk, name), getattr(rec, name), err_msg=name)
    assert disk.metadata["sample_period"] == 0.002 and disk.metadata["feedback"] == "truth"
    assert [e["kind"] for e in disk.events] == ["mode", "mode"]              # start, and the quick stop at the end
    new_imu = np.flatnonzero(np.any(np.diff(rec.imu_accel, axis=0) != 0, axis=1)) + 1
    assert set(new_imu) <= set(range(0, n, 10)) and len(new_imu) >= n // 10 - 2
    # sample k: the command held on [t_k, t_k+1) and the reference it was computed for
    assert np.all(rec.torque[0] == 0) and np.all(rec.reference_pd[0] == 0)   # robot read before it moves
    assert run.t[0] == 0.0 and rec.t[1] == pytest.approx(0.002)             # the reference starts at sample 1


def test_runner_equals_the_zero_delay_closed_loop_on_truth_feedback():
    """The runner over the direct back end, commands one period after their sensors (the bus
    convention) with the law evaluated on the predicted state, gives the errors of the old closed
    loop (feedback and command at the same instant), restated here, to round-off."""
    spec = corridor_spec()
    T, rate = 12.0, 1000.0
    run = track_reference(spec.reference, corridor_law(), P, LIMITS, rate_hz=rate, duration=T)
    # the old closed loop: tick k reads x_k, computes u_k with p_d(t_k), clamps, steps
    n = int(T * rate)
    t = np.arange(n + 1) / rate
    Pd, PDd, PDDd = (np.ascontiguousarray(a) for a in spec.reference.sample(t))
    law, lim = corridor_law(), TorqueLimiter(LIMITS)
    st = Stepper(P, 1 / rate, rest_state(Pd[0]))
    X, U = [st.x.copy()], []
    for k in range(n):
        s = TaskState.from_state(st.x)
        u = lim.apply(law.update_fast(s.p, s.p_dot, s.phi_p, Pd[k], PDd[k], PDDd[k])[0], t[k])[0]
        U.append(u.copy())
        X.append(st.step(u).copy())
    X, U = np.array(X), np.array(U)
    assert run.x.shape == X.shape and run.u.shape == U.shape
    assert np.abs(run.x - X).max() < 1e-9 and np.abs(run.u - U).max() < 1e-9
    e_old = np.abs(X[:, :3] - Pd).max(axis=0)
    np.testing.assert_allclose(np.abs(run.e_p).max(axis=0), e_old, rtol=1e-9)
    assert e_old[0] > 0.05  # the corridor's corners: a real test, not zeros
    # without the prediction the command acts one period late: measurably worse
    late = track_reference(spec.reference, corridor_law(), P, LIMITS, rate_hz=rate, duration=T, predict=False)
    assert np.abs(late.e_p[:, 0]).max() > np.abs(run.e_p[:, 0]).max() * (1 + 1e-5)


def test_realtime_pacing_holds_the_period():
    robot = DirectSimRobot(P, period=0.01, imu_rate=None)
    sup = Supervisor(LIMITS, SafetyConfig(), 0.01, realtime=True)
    t0 = time.perf_counter()
    res = LoopRunner(robot, OpenLoopTorques(np.zeros((1, 3)), 0.01), sup, realtime=True).run(21)
    wall = time.perf_counter() - t0
    # pacing never runs ahead of the wall clock; a loaded machine may only make it late
    assert res.completed and wall >= 0.2 - 1e-3
    assert 0.009 <= res.stats.period_p50 < 0.02, res.stats
    assert res.stats.realtime_factor <= 21 / 20 + 0.01, res.stats
    assert np.isfinite(res.stats.jitter_rms)


# -- faults: latched, quick stop, recording kept ------------------------------------------------
class Scripted:
    """Open loop, with something done to the robot at robot time ``at`` (s)."""

    def __init__(self, u, at=None, action=None):
        self.u, self.at, self.action = np.asarray(u, float), at, action

    def update(self, t, feedback, snapshot):
        if self.at is not None and t >= self.at and self.action is not None:
            out = self.action(t)
            self.action = None
            if out is not None:
                return out
        return ControlStep(self.u.copy())


@dataclass
class ScriptedFeedback:
    """Truth, with the estimate's std, rejected/accepted innovation counts or a NaN changed from ``at`` s."""

    at: float
    std: float = 0.0
    nan: bool = False
    rejected_per_step: int = 0
    name: str = "scripted"
    faults: tuple = ()
    counts: dict = field(default_factory=lambda: {"rej": 0, "acc": 0})

    def start(self, s, robot):
        return self.step(s, robot, None)

    def step(self, s, robot, u_prev):
        x = robot.truth()
        late = s.t >= self.at
        self.counts["rej"] += self.rejected_per_step if late else 0
        self.counts["acc"] += 1
        pose = x[:3].copy()
        if late and self.nan:
            pose[0] = np.nan
        return StateEstimate(s.t, pose, x[6:9], np.full(6, self.std if late else 0.0), float(x[5]),
                             rejected={"wheels": self.counts["rej"]}, updates={"wheels": self.counts["acc"]})


def _run_direct(controller, safety, feedback=None, cycles=300, path=None, realtime=False, period=0.01):
    robot = DirectSimRobot(P, period=period, imu_rate=None, limits=LIMITS)
    sup = Supervisor(LIMITS, safety, period, realtime=realtime)
    res = LoopRunner(robot, controller, sup, feedback, path=path, realtime=realtime).run(cycles)
    return robot, sup, res


@pytest.mark.parametrize("kind, controller, safety, feedback", [
    ("joint_rate", Scripted([20.0, 20.0, 0.0]), SafetyConfig(max_wheel_rate=3.0), None),
    ("platform_speed", Scripted([20.0, 20.0, 0.0]), SafetyConfig(max_speed=0.2), "truth"),
    ("platform_speed", Scripted([-5.0, 5.0, 8.0]), SafetyConfig(max_turn_rate=0.5), "truth"),
    ("workspace", Scripted([20.0, 20.0, 0.0]), SafetyConfig(workspace=(-0.1, 0.1, -1.0, 1.0)), "truth"),
    ("estimator", Scripted([1.0, 1.0, 0.0]), SafetyConfig(max_position_std=0.05), ScriptedFeedback(0.5, std=0.2)),
    ("estimator", Scripted([1.0, 1.0, 0.0]), SafetyConfig(), ScriptedFeedback(0.5, nan=True)),
    ("estimator", Scripted([1.0, 1.0, 0.0]), SafetyConfig(), ScriptedFeedback(0.5, rejected_per_step=3)),
    ("command", Scripted([1.0, 1.0, 0.0], 0.5, lambda t: ControlStep(np.array([np.nan, 0.0, 0.0]))),
     SafetyConfig(), None),
    ("robot", None, SafetyConfig(), None),
])
def test_each_violation_latches_a_fault_and_quick_stops_the_robot(kind, controller, safety, feedback, tmp_path):
    if kind == "robot":
        holder = {}
        controller = Scripted([2.0, 2.0, 1.0], 0.5, lambda t: holder["robot"].inject_fault(1))
    fb = TruthFeedback() if feedback == "truth" else feedback
    path = tmp_path / "f.mcap"
    robot = DirectSimRobot(P, period=0.01, imu_rate=None, limits=LIMITS)
    if kind == "robot":
        holder["robot"] = robot
    sup = Supervisor(LIMITS, safety, 0.01)
    res = LoopRunner(robot, controller, sup, fb, path=path).run(300)
    assert not res.completed and res.fault.kind == kind and sup.fault is res.fault
    # the drives' own state: nothing enabled, no torque, and it stays that way
    assert "OPERATION ENABLED" not in robot.states and np.all(robot.applied_torque() == 0)
    before = robot.truth()
    robot.read()
    assert sup.check(res.fault.t + 1, np.zeros(3)) is res.fault          # latched until reset
    sup.reset()
    assert sup.fault is None
    rec = read_recording(path)                                           # everything up to the fault
    assert len(rec) == len(res.recording)
    # the last sample is the one that showed the fault, or the one before the command that caused it
    assert res.fault.t - 0.01 - 1e-9 <= rec.t[-1] <= res.fault.t + 1e-9
    assert rec.events[-1]["kind"] == "fault" and kind in rec.events[-1]["text"]
    assert np.all(np.isfinite(before))


def test_overruns_stop_a_realtime_loop_but_only_count_in_lockstep():
    class Slow:
        def update(self, t, fb, s):
            if t > 0.05:
                time.sleep(0.025)
            return ControlStep(np.zeros(3))

    cfg = SafetyConfig(overrun_factor=1.5, max_consecutive_overruns=3)
    robot, sup, res = _run_direct(Slow(), cfg, cycles=40, realtime=True)
    assert not res.completed and res.fault.kind == "overrun" and res.stats.overruns >= 4
    assert "OPERATION ENABLED" not in robot.states
    assert res.fault.t < 0.05 + 6 * 0.01 + 1e-9                       # within a few cycles of the first overrun
    robot, sup, res = _run_direct(Slow(), cfg, cycles=12, realtime=False)
    assert res.completed and res.stats.overruns >= 4                    # lockstep: no deadline, counted only


def test_an_overrun_streak_begun_at_rest_counts_from_the_first_cycle_meant_to_move():
    """The daemon judges overruns only while the robot is meant to move (``realtime``); 300 late cycles
    at rest and then the first moving ones: the fault comes at the (max + 1)-th late cycle in a row
    while moving, not at the first; an in-time cycle while moving restarts the count."""
    from otbot_hw.motors import load_motor_limits
    from otbot_hw.runtime.supervisor import Supervisor

    cfg = SafetyConfig(overrun_factor=1.5, max_consecutive_overruns=3)
    sup = Supervisor(load_motor_limits(), cfg, period=0.01, realtime=False)
    w = np.zeros(3)
    for k in range(300):                                    # at rest: late every cycle, no fault
        assert sup.check(k * 0.01, w, wall_period=0.05) is None
    sup.realtime = True                                     # meant to move from here
    for k in range(3):
        assert sup.check(3 + k * 0.01, w, wall_period=0.05) is None
    assert sup.check(3.03, w, wall_period=0.01) is None     # in time: the streak restarts
    for k in range(3):
        assert sup.check(3.04 + k * 0.01, w, wall_period=0.05) is None
    v = sup.check(3.07, w, wall_period=0.05)                # the 4th late cycle in a row while moving
    assert v is not None and v.kind == "overrun" and v.text.startswith("4 cycles in a row")
    sup.reset()
    sup.realtime = False                                    # at rest again after the reset: warnings only
    assert all(sup.check(4 + k * 0.01, w, wall_period=0.05) is None for k in range(50))


def test_supervisor_over_the_bus_quick_stops_the_simulated_drives():
    """A joint-rate violation over the simulated CAN bus: the plant's drives (not the master's belief)
    end quick-stopped (then disabled) with zero torque, and the plant's pivot coasts without torque."""
    from sim.bus_robot import simulated_robot

    with simulated_robot(CFG, with_imu=False) as (robot, plant):
        sup = Supervisor(LIMITS, SafetyConfig(max_pivot_rate=0.5), robot.period)
        res = LoopRunner(robot, OpenLoopTorques(np.tile([0.0, 0.0, 10.0], (200, 1)), robot.period), sup).run(201)
        assert not res.completed and res.fault.kind == "joint_rate" and "pivot" in res.fault.text
        # quick stop option 0x605A = 2: QUICK STOP ACTIVE, then SWITCH ON DISABLED once stopped
        assert {d.state for d in plant.drives} <= {"QUICK STOP ACTIVE", "SWITCH ON DISABLED"}
        assert [d.joint_torque() for d in plant.drives] == [0.0, 0.0, 0.0]
        assert res.fault.t < 0.3
        assert abs(res.recording.joint_vel[-1, 2]) > 0.5


def test_cli_fault_during_tracking_exits_1_and_keeps_the_recording(tmp_path, capsys, robot_yaml):
    cfg = robot_yaml({"max_position_error: {value: 0.3, unit: m}": "max_position_error: {value: 0.01, unit: m}"})
    out = tmp_path / "t.mcap"
    with pytest.raises(SystemExit) as exc:
        main(["track", "corridor", "--sim", "--feedback", "truth", "--config", str(cfg), "--rate", "200",
              "--no-robustness", "--out", str(out), "--json"])
    assert exc.value.code == 1
    cap = capsys.readouterr()
    r = json.loads(cap.out)
    assert r["completed"] is False and r["fault"]["kind"] == "tracking_error" and "recording up to the fault" in cap.err
    rec = read_recording(out)
    assert 1 < len(rec) < 200 * 30 and rec.events[-1]["kind"] == "fault"
    assert np.hypot(*(rec.truth_q[-1, :2] - rec.reference_p[-1, :2])) > 0.01


# -- back ends -----------------------------------------------------------------------------------
def test_direct_and_bus_back_ends_give_the_same_physics_on_the_same_torques():
    """The chassis experiment (torques on whole per-mille steps) on the direct robot configured like
    the bus (encoder counts, torque resolution, IMU rate) and over the simulated CAN bus: the true
    states agree to round-off, the encoders count for count, the IMU within the VectorNav ASCII
    resolution (no noise); with the paper's noise, the IMU residuals of both have the paper's sigma."""
    n = 150
    U = np.tile([6.0, -10.0, 6.0], (n, 1))
    runs = {}
    for noise in (NoiseModel(), NoiseModel.paper()):
        direct = DirectBackend.from_config(CFG, CFG.bus.control_rate, noise, seed=1)
        with direct.open(P) as robot:
            d = run_torques(robot, U, CFG.limits).recording
        with BusSimBackend(CFG, noise, seed=2).open(P) as robot:
            b = run_torques(robot, U, CFG.limits).recording
        runs[noise.accel > 0] = (d, b)
    d, b = runs[False]
    ref = simulate(P, U, CFG.bus.period)
    np.testing.assert_allclose(d.truth_q, ref.q, atol=1e-12)
    np.testing.assert_allclose(b.truth_q, ref.q, atol=1e-12)
    np.testing.assert_allclose(d.joint_pos, b.joint_pos, atol=1e-12)
    np.testing.assert_allclose(d.joint_vel, b.joint_vel, atol=1e-12)
    np.testing.assert_allclose(d.imu_accel, b.imu_accel, atol=2e-3)
    np.testing.assert_allclose(d.imu_gyro, b.imu_gyro, atol=2e-3)
    (dn, bn), sigma = runs[True], NoiseModel.paper().accel
    for noisy, clean in ((dn, d), (bn, b)):
        np.testing.assert_allclose(noisy.truth_q, ref.q, atol=1e-12)  # noise is in the sensors only
        r = noisy.imu_accel[:, :2] - clean.imu_accel[:, :2]
        assert np.all(np.abs(r.std(axis=0) / sigma - 1) < 0.2)


def test_plant_params_change_the_physics_behind_the_bus(tmp_path, capsys):
    """A heavier platform behind the bus (otbot run --plant-params) moves less under the same torques,
    exactly as the pure simulation of the heavier robot says."""
    heavy = P.replace(m_p=1.5 * P.m_p, I_p=1.5 * P.I_p)
    f = tmp_path / "heavy.yaml"
    heavy.save(f)
    base = ["run", "--bus", "sim", "--torques", "6,-10,6", "--duration", "0.5", "--noise", "none", "--json"]
    assert main(base) == 0
    nom = json.loads(capsys.readouterr().out)
    assert main(base + ["--plant-params", str(f)]) == 0
    hv = json.loads(capsys.readouterr().out)
    U = np.tile([6.0, -10.0, 6.0], (50, 1))
    for r, prm in ((nom, P), (hv, heavy)):
        np.testing.assert_allclose(r["q_final"], simulate(prm, U, 0.01).q[-1], atol=1e-12)
    assert abs(hv["q_final"][2] - nom["q_final"][2]) > 1e-3


def test_extended_plant_behind_the_bus_steps_the_effects_and_shows_the_sensor_effects():
    """Coulomb friction, a gyro bias and a wheel encoder scale error in the simulated robot behind the
    bus: the states follow the extended model, the gyro reads the bias, the right encoder the scale."""
    m = fx.ExtendedModel.paper(P).with_values({"c_w": 0.3, "b_gz": 0.05, "e_r": 0.02})
    n = 80
    U = np.tile([6.0, -10.0, 6.0], (n, 1))
    with BusSimBackend(CFG, NoiseModel()).open(m) as robot:
        rec = run_torques(robot, U, CFG.limits).recording
    tr = simulate_extended(m.params, m.eff, U, CFG.bus.period)
    ideal = sensor_model.sensor_outputs(tr, m.params, m.eff)
    np.testing.assert_allclose(rec.truth_q, tr.x[:, :6], atol=1e-12)
    np.testing.assert_allclose(rec.imu_gyro[:, 2], ideal["imu_gyro"][:, 2], atol=2e-3)
    assert np.abs(rec.imu_gyro[:, 2] - tr.x[:, 8] - 0.05).max() < 2e-3
    np.testing.assert_allclose(rec.joint_pos[:, 0], ideal["joint_pos"][:, 0], atol=2 * np.pi / 40960 + 1e-9)
    assert abs(rec.joint_pos[-1, 0] / tr.x[-1, 3] - 1.02) < 1e-3
    assert np.abs(tr.x[-1] - simulate(P, U, CFG.bus.period).x[-1]).max() > 1e-2   # the friction is felt


@pytest.mark.parametrize("lag", [0.0, 0.02])
def test_stepper_sensors_equal_the_batch_sensor_model(lag):
    """Sample-by-sample sensor effects (DirectSimRobot, Plant) = the batch ``sensor_outputs`` of the
    same extended run (lever arm, misalignment, biases, latency, slip, radius/scale errors), with and
    without a current-loop lag (without one, the torque jumps at each command step and the latency
    interpolates inside the interval: the case that once differed by 1.5 m/s^2)."""
    m = fx.ExtendedModel.paper(P).with_values({"k_slip": 0.02, "dr_r": 0.03, "dr_l": -0.03, "e_l": -0.02, "b_ax": 0.1, "d_x": 0.05,
                                               "psi": 0.1, "d_imu": 0.015, "T_i": lag, "g_x": 0.1})
    rng = np.random.default_rng(0)
    U = np.repeat(rng.uniform(-8, 8, (15, 3)), 6, axis=0)
    robot = DirectSimRobot(m, period=0.01, imu_rate=100.0)
    res = run_torques(robot, U)
    ideal = sensor_model.sensor_outputs(simulate_extended(m.params, m.eff, U, 0.01), m.params, m.eff)
    rec = res.recording
    for name in ("joint_pos", "joint_vel", "imu_accel", "imu_gyro"):
        np.testing.assert_allclose(getattr(rec, name), ideal[name], atol=1e-12, err_msg=name)


# -- the EKF path, with a stand-in that follows the estimator contract -------------------------------
class _FakeFault(RuntimeError):
    pass


def _fake_estimation(calls, fail_at=None):
    """A stand-in ``otbot_hw.estimation`` (the contract's names): wheel odometry, not a filter."""
    mod = types.ModuleType("otbot_hw.estimation")

    @dataclass
    class Estimate:
        t: float
        pose: np.ndarray
        twist: np.ndarray
        std: np.ndarray
        cov: np.ndarray
        gyro_bias: float = 0.0
        standstill: bool = False
        nis: dict = field(default_factory=dict)
        rejected: dict = field(default_factory=dict)
        updates: dict = field(default_factory=dict)

    class PoseEKF:
        def __init__(self, params, period, config=None):
            self.p, self.period = params, period

        def _est(self, t, pd=np.zeros(3)):
            return Estimate(t, self.pose.copy(), pd.copy(), np.full(6, 1e-3), np.eye(6), rejected={"wheels": 0},
                            updates={"wheels": len(calls)})

        def initialize(self, t, pose, joint_pos, twist=(0.0, 0.0, 0.0), pose_std=None, *, imu_accel=None,
                       imu_gyro=None):
            calls.append(("init", t, None if imu_accel is None else np.asarray(imu_accel, float), None))
            self.pose, self.t, self.theta = np.asarray(pose, float), t, float(pose[2] - joint_pos[2])
            return self._est(t)

        def step(self, t, joint_pos, joint_vel, imu_accel=None, imu_gyro=None, torque=None):
            calls.append(("step", t, imu_gyro is not None, None if torque is None else np.array(torque)))
            if fail_at is not None and t >= fail_at:
                raise _FakeFault(f"stale IMU at t = {t:.3f} s")
            if not t > self.t:
                raise _FakeFault("time did not increase")
            p = self.p
            v = p.r * (joint_vel[0] + joint_vel[1]) / 2
            thd = p.r * (joint_vel[0] - joint_vel[1]) / (2 * p.l2)
            c, s = np.cos(self.theta), np.sin(self.theta)
            pd = np.array([v * c - p.l1 * thd * s, v * s + p.l1 * thd * c, thd + joint_vel[2]])
            dt = t - self.t
            self.theta += thd * dt
            self.pose = self.pose + pd * dt
            self.pose[2] = self.theta + joint_pos[2]
            self.t = t
            return self._est(t, pd)

    mod.PoseEKF, mod.EstimatorFault, mod.Estimate = PoseEKF, _FakeFault, Estimate
    mod.EstimatorConfig = type("EstimatorConfig", (), {"load": classmethod(lambda cls, path=None: cls())})
    return mod


def _use_estimation(monkeypatch, mod):
    """Make the loop's feedback and tracking use the estimator module ``mod`` (a fake honouring the
    estimator contract)."""
    import otbot_hw.runtime.feedback as feedback
    import otbot_hw.runtime.tracking as tracking

    monkeypatch.setattr(feedback, "PoseEKF", mod.PoseEKF)
    monkeypatch.setattr(feedback, "EstimatorFault", mod.EstimatorFault)
    monkeypatch.setattr(tracking, "EstimatorConfig", mod.EstimatorConfig)


def test_ekf_feedback_follows_the_estimator_contract(monkeypatch, tmp_path, capsys):
    calls = []
    _use_estimation(monkeypatch, _fake_estimation(calls))
    ref = corridor_spec(smooth=True).reference
    backend = DirectBackend(rate=200.0, imu_rate=50.0)
    run = track_reference(ref, corridor_law(), P, LIMITS, backend, feedback="ekf", duration=4.0)
    assert run.completed and run.loop.feedback == "ekf"
    rec = run.loop.recording
    assert calls[0][0] == "init" and all(c[0] == "step" for c in calls[1:]) and len(calls) == len(rec)
    np.testing.assert_array_equal(calls[0][2], rec.imu_accel[0])     # the start sample's IMU reading drives step 1
    fresh = [k for k, c in enumerate(calls[1:], 1) if c[2]]
    assert fresh == list(range(4, len(rec), 4))                       # IMU only when it brought a new sample
    for k in (5, 50):
        np.testing.assert_array_equal(calls[k][3], rec.torque[k - 1])  # the command held over the last period
    assert np.abs(run.e_p[:, :2]).max() < 2e-3 and run.estimation_error()["max"]["x"] < 2e-3
    # a fault of the estimator stops the loop: quick stop, exit 1, recording up to it
    calls.clear()
    _use_estimation(monkeypatch, _fake_estimation(calls, fail_at=0.5))
    out = tmp_path / "ekf.mcap"
    with pytest.raises(SystemExit) as exc:
        main(["track", "corridor-smooth", "--sim", "--rate", "200", "--no-robustness", "--out", str(out), "--json"])
    assert exc.value.code == 1
    r = json.loads(capsys.readouterr().out)
    assert r["feedback"] == "ekf" and r["fault"]["kind"] == "estimator_fault" and "stale IMU" in r["fault"]["text"]
    rec = read_recording(out)
    assert rec.t[-1] == pytest.approx(0.5) and rec.estimate_pose is not None


# -- bad input ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("argv, message", [
    (["track", "corridor"], "choose a back end"),
    (["track", "corridor", "--sim", "--bus", "sim"], "not both"),
    (["track", "corridor", "--bus", "config", "--feedback", "truth"], "--feedback truth needs"),
    (["track", "corridor", "--bus", "config", "--plant-params", "config/otbot.yaml"], "--plant-params"),
    (["track", "corridor", "--sim", "--feedback", "truth", "--plant-params", "nowhere.yaml"], "nowhere.yaml"),
    (["track", "corridor", "--bus", "sim", "--feedback", "truth", "--rate", "3000.5"], "--rate"),
    (["track", "corridor", "--sim", "--feedback", "truth", "--out", "no/such/dir/x.mcap"], "does not exist"),
    (["track", "corridoor", "--sim", "--feedback", "truth"], "unknown scenario"),
    (["run", "--bus", "config", "--plant-params", "config/otbot.yaml"], "--plant-params"),
    (["run", "--bus", "sim", "--plant-params", "nowhere.yaml"], "nowhere.yaml"),
    (["run", "--bus", "sim", "--torques", "1,2"], "--torques"),
    (["run", "--bus", "sim", "--duration", "0.001"], "shorter than one period"),
    (["run", "--bus", "sim", "--rate", "3000.5"], "--rate"),
])
def test_bad_input_is_one_line_and_exit_2(argv, message, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1 and "Traceback" not in err


def test_bad_safety_configuration_names_the_key(tmp_path, capsys):
    from otbot_hw.params import ParameterError

    for bad, key in (("  max_speed: {value: -1, unit: m/s}\n", "safety.max_speed"),
                     ("  max_speed: {value: 1, unit: km/h}\n", "safety.max_speed"),
                     ("  workspace: {value: [1, 0, 0, 1], unit: m}\n", "safety.workspace"),
                     ("  bogus: {value: 1, unit: m}\n", "safety.bogus")):
        f = tmp_path / "r.yaml"
        f.write_text("safety:\n" + bad)
        with pytest.raises(ParameterError, match=key.replace(".", r"\.")):
            SafetyConfig.load(f)
    assert SafetyConfig.load(CFG.path) == SafetyConfig()                 # the file documents the defaults
    assert SafetyConfig.from_dict({"max_speed": {"value": None, "unit": "m/s"}}).max_speed is None


def test_plant_process_with_plant_params_and_tracking_over_the_configured_bus(monkeypatch, tmp_path, capsys,
                                                                             robot_yaml):
    """``otbot plant --plant-params`` (a heavier platform) as its own process behind slcan; ``otbot run
    --bus config --lockstep`` sees the heavier robot's encoders; ``otbot track FILE.csv --bus config``
    tracks it with EKF feedback (the stand-in) and reports errors of the estimated pose (no truth)."""
    import subprocess

    heavy = P.replace(m_p=1.5 * P.m_p, I_p=1.5 * P.I_p)
    hfile = tmp_path / "heavy.yaml"
    heavy.save(hfile)
    # lockstep against a plant process on a loaded machine: watchdogs at 1 s both ways (this test is about physics)
    cfg = robot_yaml({"  options: {}": "  options: {sleep_after_open: 0}",
                      "master_heartbeat_consumer: {value: 100, unit: ms}":
                          "master_heartbeat_consumer: {value: 1000, unit: ms}",
                      "heartbeat_consumer: {value: 200, unit: ms}": "heartbeat_consumer: {value: 1000, unit: ms}"})
    traj = tmp_path / "step.csv"
    traj.write_text("t,x,y,alpha\n0,0,0,0\n1,0.05,0,0\n2,0.2,0.05,0\n")
    code = "import sys; from otbot_hw.cli import main; sys.exit(main())"
    for step in ("run", "track"):
        proc = subprocess.Popen([sys.executable, "-c", code, "plant", "--noise", "none", "--plant-params", str(hfile)],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        try:
            info = json.loads(proc.stdout.readline())
            bus = ["--bus", "config", "--config", str(cfg), "--interface", "slcan", "--channel", info["can_channel"],
                   "--imu-port", info["imu_port"], "--lockstep", "--json"]
            if step == "run":
                assert main(["run", "--torques", "6,-10,6", "--duration", "0.3", *bus]) == 0
                res = json.loads(capsys.readouterr().out)
                expect = simulate(heavy, np.tile([6.0, -10.0, 6.0], (30, 1)), 0.01).x[-1, 3:5]
                np.testing.assert_allclose(res["phi"][:2], expect, atol=2 * np.pi / 40960 + 1e-9)
            else:
                calls = []
                _use_estimation(monkeypatch, _fake_estimation(calls))
                assert main(["track", str(traj), *bus, "--params", str(hfile)]) == 0
                res = json.loads(capsys.readouterr().out)
                assert res["bus"] == "config" and res["feedback"] == "ekf" and res["true_pose_known"] is False
                assert res["estimation_error"] is None and "robustness_skipped" in res
                assert res["max_abs_error"]["x"] < 5e-3 and res["loop"]["realtime"] is False
                # the estimator of the run (after the warm-up's own, which compiles the loop before the bus opens)
                last_init = max(k for k, c in enumerate(calls) if c[0] == "init")
                assert len(calls) - last_init == res["loop"]["cycles"]
        finally:
            proc.stdin.close()
            assert proc.wait(timeout=20) == 0


def test_controllers_swap_between_cycles_and_a_new_reference_starts_at_its_first_command():
    """The daemon's use: start, cycle open loop, then swap to tracking a hold of the current pose
    without a jump: the swap is a recorded mode event, the new reference starts where the robot is."""
    from otbot_hw.control.sampled_trajectory import SampledTrajectory

    robot = DirectSimRobot(P, period=0.01, imu_rate=None)
    runner = LoopRunner(robot, OpenLoopTorques(np.tile([3.0, 3.0, 0.0], (1, 1)), 0.01), Supervisor(LIMITS), TruthFeedback(),
                        record_reference=True)
    runner.start()
    for _ in range(30):
        assert runner.cycle()
    here = robot.truth()[:3]
    hold = SampledTrajectory(np.array([0.0, 1.0]), np.tile(here, (2, 1)))
    runner.set_controller(TrackingController(corridor_law(), hold, 0.01), "hold")
    for _ in range(150):
        assert runner.cycle()
    runner.close()
    rec = runner.result().recording
    assert [e["text"] for e in rec.events if e["kind"] == "mode"][-1] == "hold"
    assert np.isnan(rec.reference_p[30]).all()                           # open loop: no reference
    np.testing.assert_allclose(rec.reference_p[31], here)               # the hold starts where the robot was
    assert np.abs(rec.truth_qd[-1, :2]).max() < 0.02 < np.abs(rec.truth_qd[30, :2]).max()
