"""What the daemon added to the runtime, on its own: the stop/hold and placed trajectories, the twist
reference of the velocity mode, the loop runner running indefinitely (unpowered start, enable
between cycles, a trip from another thread, reading on after a fault until reset, a robot clock
that restarts, recordings started and stopped), torque sequences for ``excite``, and the
``otbot daemon`` command's bad input."""
from __future__ import annotations

import socket
import threading
import time

import numpy as np
import pytest

from otbot_hw.control.gains import gains_from_tstab
from otbot_hw.control.computed_torque import ComputedTorqueController
from otbot_hw.control.scenarios import corridor_spec
from otbot_hw.control.trajectories import PlacedTrajectory, StopTrajectory
from otbot_hw.motors import load_motor_limits
from otbot_hw.params import ParameterError, nominal
from otbot_hw.recording import RecordingWriter, read_recording
from otbot_hw.runtime import LoopRunner, SafetyConfig, Supervisor, TrackingController, TruthFeedback, Violation
from otbot_hw.runtime.controllers import TwistReference
from otbot_hw.runtime.daemon_config import daemon_config_from_dict
from otbot_hw.runtime.openloop import TorqueSequenceError, load_torque_sequence
from sim.direct import DirectSimRobot

P = nominal()
LIMITS = load_motor_limits()


def _integrates(t, P_, PD, PDD, tol):
    """P and PD are the integrals of PD and PDD (trapezoid on a fine grid)."""
    dt = np.diff(t)[:, None]
    assert np.abs(P_[1:] - P_[:-1] - 0.5 * dt * (PD[1:] + PD[:-1])).max() < tol
    assert np.abs(PD[1:] - PD[:-1] - 0.5 * dt * (PDD[1:] + PDD[:-1])).max() < tol


def test_stop_trajectory_takes_over_the_motion_and_comes_to_rest_within_the_limits():
    p0, v0 = np.array([1.0, -2.0, 0.3]), np.array([0.4, -0.3, 0.8])
    tr = StopTrajectory(p0, v0, max_acceleration=0.5, max_angular_acceleration=1.0)
    t = np.linspace(-0.5, tr.stop_time + 1.0, 20001)
    P_, PD, PDD = tr.sample(t)
    at0 = np.searchsorted(t, 0.0)
    np.testing.assert_allclose(PD[:at0], np.tile(v0, (at0, 1)))            # before: the motion it takes over
    np.testing.assert_allclose(tr.sample(np.zeros(1))[0][0], p0)
    _integrates(t, P_, PD, PDD, 1e-6)
    assert np.hypot(PDD[:, 0], PDD[:, 1]).max() <= 0.5 * (1 + 1e-3)        # both limits held, one of them reached
    assert np.abs(PDD[:, 2]).max() <= 1.0 * (1 + 1e-3)
    assert max(np.hypot(PDD[:, 0], PDD[:, 1]).max() / 0.5, np.abs(PDD[:, 2]).max()) > 0.99
    rest = t >= tr.stop_time
    np.testing.assert_allclose(P_[rest], np.tile(p0 + 0.5 * v0 * tr.stop_time, (rest.sum(), 1)), atol=1e-12)
    assert np.abs(PD[rest]).max() == 0 and np.abs(PDD[rest]).max() == 0
    d = P_[-1, :2] - p0[:2]                                                 # on the straight line along v0
    assert abs(d[0] * v0[1] - d[1] * v0[0]) < 1e-12
    hold = StopTrajectory(p0)                                               # v0 = 0: a hold of p0
    assert hold.stop_time == 0 and np.all(hold.sample(np.array([0.0, 5.0]))[0] == p0)


@pytest.mark.parametrize("v0, moving", [
    ((0.0, 0.0, 0.0), False),
    ((0.01, 0.0, 0.0), False),             # REST_SPEED itself: standing
    ((0.0, -0.01, 0.0), False),
    ((0.006, -0.008, 0.0), False),         # |v| = 0.01: standing
    ((0.0101, 0.0, 0.0), True),
    ((0.0, -0.0101, 0.0), True),
    ((0.0, 0.0, 0.02), False),             # REST_TURN itself
    ((0.0, 0.0, -0.02), False),
    ((0.0, 0.0, 0.0201), True),
    ((0.0, 0.0, -0.0201), True),
    ((0.3, 0.0, 0.0), True),
])
def test_a_hold_that_starts_from_rest_is_standing_for_the_overrun_rule(v0, moving):
    """``ModeMachine.moving``: a hold ramping from a twist within the rest thresholds (enable's, from the
    estimate's noise) is standing -- overruns there are warnings; from above them it moves until its
    ramp ends; either sign."""
    import types

    from otbot_hw.runtime.daemon_modes import ModeMachine

    m = ModeMachine(law=None, velocity=None, notify=lambda _: None)
    m.runner = types.SimpleNamespace(t=0.0, period=0.01)
    traj = StopTrajectory((0.0, 0.0, 0.0), v0, 0.5, 1.0)
    ramp = {"done": False}
    m.holding = types.SimpleNamespace(reference=traj, finished=lambda t: ramp["done"])
    m.mode = "hold"
    assert m.moving() is moving
    ramp["done"] = True
    assert m.moving() is False                                    # ramp over: standing whatever it began at
    m.holding = None
    assert m.moving() is True                                     # a hold without its controller: assume motion
    for mode in ("track", "velocity", "excite"):
        m.mode = mode
        assert m.moving() is True
    m.mode = "idle"
    assert m.moving() is False


def test_placed_trajectory_is_the_same_motion_started_elsewhere():
    ref = corridor_spec(smooth=True).reference
    start = np.array([3.0, -1.0, 2.0])
    placed = PlacedTrajectory(ref, start)
    t = np.linspace(0, ref.duration, 3001)
    P0, PD0, PDD0 = ref.sample(t)
    P1, PD1, PDD1 = placed.sample(t)
    np.testing.assert_allclose(P1[0], start, atol=1e-12)
    _integrates(t, P1, PD1, PDD1, 1e-4)
    for a, b in ((P0, P1), (PD0, PD1), (PDD0, PDD1)):                        # rigid: lengths and turns kept
        np.testing.assert_allclose(np.hypot(*(a[:, :2] - (a[0, :2] if a is P0 else 0)).T),
                                   np.hypot(*(b[:, :2] - (b[0, :2] if b is P1 else 0)).T), atol=1e-9)
    np.testing.assert_allclose(P1[:, 2] - P0[:, 2], start[2] - P0[0, 2], atol=1e-12)
    np.testing.assert_allclose(PD1[:, 2], PD0[:, 2], atol=1e-12)


def test_twist_reference_is_consistent_and_reaches_each_twist_within_the_limits():
    h = 0.004
    tw = TwistReference([0.5, 0.5, 0.1], [0.0, 0.0, 0.0], h, max_acceleration=0.5, max_angular_acceleration=1.0)
    tw.command([0.3, -0.4, 0.6])
    rows = [tw.at(k * h) for k in range(1, 1500)]
    tw.command([0.0, 0.0, 0.0])
    rows += [tw.at(k * h) for k in range(1500, 2500)]
    t = np.arange(1, 2500) * h
    P_, PD, PDD = (np.array([getattr(r, n) for r in rows]) for n in ("p", "pd", "pdd"))
    # exact integration of piecewise-constant accelerations: p(t+h) = p + v h + a h^2 / 2
    np.testing.assert_allclose(P_[1:], P_[:-1] + PD[:-1] * h + 0.5 * PDD[:-1] * h * h, atol=1e-12)
    np.testing.assert_allclose(PD[1:], PD[:-1] + PDD[:-1] * h, atol=1e-12)
    assert np.hypot(PDD[:, 0], PDD[:, 1]).max() <= 0.5 + 1e-9 and np.abs(PDD[:, 2]).max() <= 1.0 + 1e-9
    i = np.searchsorted(t, 1.3)
    np.testing.assert_allclose(PD[i], [0.3, -0.4, 0.6], atol=1e-9)            # reached (0.5 m/s needs 1 s)
    lin = PD[: i, :2]                                                         # the change keeps one direction
    assert np.abs(lin[:, 0] * 0.4 + lin[:, 1] * 0.3).max() < 1e-9
    assert tw.at_rest() and np.abs(PD[-1]).max() == 0.0
    assert tw.at(0.5 * h).p.tolist() == tw.p.tolist()                         # never backwards


def _runner(robot, **kw):
    sup = Supervisor(LIMITS, SafetyConfig(), robot.period, realtime=False)
    return LoopRunner(robot, None, sup, TruthFeedback(), keep_samples=False, continue_after_fault=True,
                      stop_at_end=False, record_reference=True, **kw)


def test_the_runner_runs_unpowered_then_enables_trips_reads_on_and_resets(tmp_path):
    robot = DirectSimRobot(P, period=0.01, imu_rate=None, limits=LIMITS)
    sessions = []

    def recorder(meta, topics):
        w = RecordingWriter(tmp_path / f"s{len(sessions)}.mcap", meta, topics=topics)
        sessions.append(w)
        return w

    r = _runner(robot, recorder=recorder)
    r.start(enable=False)
    for _ in range(20):
        r.cycle()
    assert r.armed is False and robot.states == ["SWITCH ON DISABLED"] * 3 and r.t == pytest.approx(0.19)
    law = ComputedTorqueController(P, gains_from_tstab(3.0))
    hold = TrackingController(law, StopTrajectory(robot.truth()[:3], np.zeros(3)), r.period, origin=r.t)
    r.enable(hold, "hold")                                    # DirectSimRobot's clock restarts at enable
    for _ in range(30):
        r.cycle()
    assert robot.states == ["OPERATION ENABLED"] * 3 and r.last_command is not None
    assert r.t == pytest.approx(0.49)                          # the loop's clock went on
    tw = TwistReference(robot.truth()[:3], np.zeros(3), r.period, 0.5, 1.0)
    tw.command([0.2, 0.0, 0.0])
    origin, _ = r.reference_state()
    r.set_controller(TrackingController(law, tw, r.period, origin=origin), "velocity")
    for _ in range(80):
        r.cycle()
    assert robot.truth()[6] > 0.15
    th = threading.Thread(target=r.trip, args=(Violation("estop", r.t, "from another thread"),))
    th.start()
    th.join()  # the trip is in (a fixed sleep may not outlast a loaded machine's scheduling)
    assert r.cycle() is False and r.fault.kind == "estop"
    assert robot.states == ["QUICK STOP ACTIVE"] * 3 and not r.armed
    t_fault = r.t
    for _ in range(10):
        assert r.cycle() is False                            # reads on, writes nothing
    assert r.t == pytest.approx(t_fault + 0.1) and robot.applied_torque().tolist() == [0.0] * 3
    with pytest.raises(Exception, match="faulted"):
        r.enable(hold)
    r.reset()
    assert r.fault is None and r.supervisor.fault is None
    r.stop_recording()
    r.start_recording()
    for _ in range(5):
        r.cycle()
    r.event(r.t, "mode", "end")
    r.close()
    first, second = (read_recording(w.path if hasattr(w, "path") else tmp_path / f"s{i}.mcap")
                     for i, w in enumerate(sessions))
    assert not first.truncated and len(first) == 141 and len(second) == 5   # the trip cycle reads too
    assert np.all(np.diff(np.concatenate([first.t, second.t])) > 0)         # one clock across both files
    kinds = [(e["kind"], e["text"]) for e in first.events]
    assert ("mode", "hold") in kinds and ("mode", "velocity") in kinds
    assert [k for k, _ in kinds[-2:]] == ["fault", "mode"] and kinds[-1][1] == "reset"
    assert not any(k == "overrun" for k, _ in kinds)                         # lockstep: no deadline to miss
    assert np.isnan(first.reference_p[:19]).all() and np.isfinite(first.reference_p[25:100]).all()
    assert r.result().stats.cycles == 146 and r.timing()["cycles"] == 146


def test_torque_sequences_load_from_csv_and_recordings_and_bad_files_are_named(tmp_path):
    f = tmp_path / "u.csv"
    f.write_text("# excitation\nt,tau_r,tau_l,tau_p,note\n1.0,1,2,3,x\n1.5,-1,0,0.5,y\n")
    t, u = load_torque_sequence(f)
    np.testing.assert_allclose(t, [0.0, 0.5])
    np.testing.assert_allclose(u, [[1, 2, 3], [-1, 0, 0.5]])
    for text, msg in (("t,tau_r,tau_l\n0,1,2\n", "missing column"), ("t,tau_r,tau_l,tau_p\n0,1,2,x\n", "line 2, column tau_p"),
                      ("t,tau_r,tau_l,tau_p\n0,1,2,3\n0,1,2,3\n", "does not increase"),
                      ("t,tau_r,tau_l,tau_p\n0,1,2,nan\n", "must be finite"), ("", "empty")):
        f.write_text(text)
        with pytest.raises(TorqueSequenceError, match=msg):
            load_torque_sequence(f)
    robot = DirectSimRobot(P, period=0.01, imu_rate=None)
    from otbot_hw.runtime.openloop import run_torques

    run_torques(robot, np.tile([1.0, -1.0, 0.2], (10, 1)), path=tmp_path / "r.mcap")
    t, u = load_torque_sequence(tmp_path / "r.mcap")
    assert len(t) == 11 and np.allclose(u[0], [1.0, -1.0, 0.2])


def test_daemon_velocity_configuration_names_bad_keys():
    cfg = daemon_config_from_dict({"velocity": {"max_acceleration": {"value": 0.8, "unit": "m/s^2"}}})
    assert cfg.velocity.max_acceleration == 0.8 and cfg.velocity.max_angular_acceleration == 1.0
    for bad, key in (({"max_acceleration": {"value": -1, "unit": "m/s^2"}}, "daemon.velocity.max_acceleration"),
                     ({"max_angular_acceleration": {"value": 1, "unit": "rad/s"}}, "max_angular_acceleration")):
        with pytest.raises(ParameterError, match=key):
            daemon_config_from_dict({"velocity": bad})
    # the deadman's bound: 10 s itself is accepted, beyond is no deadman
    assert daemon_config_from_dict({"velocity": {"deadman": {"value": 10, "unit": "s"}}}).velocity.deadman == 10.0
    for v in (10.001, 1e300):
        with pytest.raises(ParameterError, match=r"'daemon.velocity.deadman' must be at most 10 s \(a longer one"):
            daemon_config_from_dict({"velocity": {"deadman": {"value": v, "unit": "s"}}})


@pytest.mark.parametrize("section, block, message", [
    ("socket", {"max_request": {"value": 64, "unit": ["KiB"]}}, "'daemon.socket.max_request' must be {value: N, unit"),
    ("socket", {"max_request": {"value": 64, "unit": {"KiB": 1}}}, "'daemon.socket.max_request' must be"),
    ("recording", {"rotate_size": {"value": 1, "unit": ["GiB"]}}, "'daemon.recording.rotate_size' must be"),
    ("recording", {"dir": None}, "'daemon.recording.dir' must be a non-empty string, got None"),
])
def test_daemon_configuration_of_the_wrong_type_is_named_not_a_traceback(section, block, message):
    with pytest.raises(ParameterError) as e:
        daemon_config_from_dict({section: block})
    assert message in str(e.value) and "\n" not in str(e.value)


def test_the_innovation_share_is_a_share():
    from otbot_hw.runtime.supervisor import SafetyConfig

    assert SafetyConfig.from_dict({"max_rejected_fraction": {"value": 1, "unit": "1"}}).max_rejected_fraction == 1.0
    for v in (1.0001, 1e300):
        with pytest.raises(ParameterError, match=r"'safety.max_rejected_fraction' must be a share in \(0, 1\]"):
            SafetyConfig.from_dict({"max_rejected_fraction": {"value": v, "unit": "1"}})


@pytest.mark.parametrize("argv, message", [
    (["--telemetry", "localhost:99999"], "--telemetry"),
    (["--start-pose", "1,2"], "--start-pose"),
    (["--bus", "sim", "--channel", "/dev/pts/9"], "--bus config"),
    (["--bus", "sim", "--lockstep"], "--bus config"),
    (["--bus", "config", "--plant-params", "config/otbot.yaml"], "--plant-params"),
    (["--record-dir", "README.md"], "--record-dir"),
    (["--rate", "-5"], "--rate"),
    (["--telemetry", "a:1", "--no-telemetry"], "not allowed with"),
])
def test_bad_daemon_arguments_are_one_line_and_exit_2(argv, message, tmp_path, otbot_cli):
    rc, out, err = otbot_cli(["daemon", "--socket", str(tmp_path / "s.sock"), "--record-dir", str(tmp_path), *argv])
    assert rc == 2 and message in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not (tmp_path / "s.sock").exists()


def test_a_second_daemon_on_a_live_socket_is_refused_before_touching_the_bus(tmp_path, otbot_cli):
    path = tmp_path / "control.sock"
    live = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    live.bind(str(path))
    live.listen(1)
    try:
        rc, out, err = otbot_cli(["daemon", "--bus", "config", "--socket", str(path), "--record-dir", str(tmp_path),
                                  "--no-telemetry", "--channel", "nowhere"])
    finally:
        live.close()
    assert rc == 2 and "another daemon is running" in err and len(err.strip().splitlines()) == 1
