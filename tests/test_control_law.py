"""Computed-torque law: gains, compiled model, exact tracking, designed error dynamics, limiter."""
import numpy as np
import pytest

from otbot_hw.control.computed_torque import ComputedTorqueController, TaskState
from otbot_hw.control.gains import Gains, axis_gains, gains_from_tstab
from otbot_hw.control.limiter import TorqueLimiter
from otbot_hw.control.task_model import task_space
from otbot_hw.control.sampled_trajectory import SampledTrajectory
from otbot_hw.control.trajectories import PolylineTrajectory, figure_eight
from otbot_hw.model.kinematics import inverse_kinematics_matrix
from otbot_hw.model.task_space import task_space_model
from otbot_hw.motors import MotorLimits
from otbot_hw.runtime.feedback import StateEstimate
from otbot_hw.runtime.supervisor import SafetyConfig
from otbot_hw.runtime.tracking import track_reference
from otbot_hw.simulation.simulator import rest_state


def test_gains_from_tstab_paper_values():
    g = gains_from_tstab(3.0)
    assert np.allclose(g.kp, 17.7777777, atol=1e-6) and np.allclose(g.kv, 14.6666666, atol=1e-6)
    assert np.allclose(g.poles(), [[-4 / 3, -40 / 3]] * 3)
    g2 = gains_from_tstab([1.0, 2.0, 4.0])
    assert np.allclose(g2.poles()[:, 0], [-4.0, -2.0, -1.0]) and np.allclose(g2.poles()[:, 1], [-40.0, -20.0, -10.0])
    assert axis_gains(2.0) == pytest.approx((40.0, 22.0))  # s1 = -2, s2 = -20


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), [1.0, 2.0]])
def test_gains_reject_bad_tstab(bad):
    with pytest.raises(ValueError):
        gains_from_tstab(bad)
    with pytest.raises(ValueError):
        Gains(kp=np.array([1.0, -1.0, 1.0]), kv=np.ones(3))


def test_compiled_task_model_matches_numpy_model(params, rng):
    prm = params.as_array()
    for _ in range(20):
        q = rng.normal(size=6) * 2
        pd = rng.normal(size=3)
        qd = np.concatenate([pd, inverse_kinematics_matrix(q, params) @ pd])
        M, C = task_space_model(q, qd, params)
        M2, C2 = task_space(q[2], q[5], pd, prm)
        assert np.allclose(M, M2, atol=1e-12 * np.abs(M).max())
        assert np.allclose(C, C2, atol=1e-12 * max(1.0, np.abs(C).max()))


def test_law_splits_into_u_traj_and_u_corr(params):
    c = ComputedTorqueController(params)
    s = TaskState(p=np.array([0.1, -0.2, 0.3]), p_dot=np.array([0.4, 0.1, -0.2]), phi_p=0.7)
    out = c.update(s, np.array([0.12, -0.25, 0.29]), np.array([0.35, 0.12, -0.1]), np.array([0.5, -0.3, 0.2]))
    M, C = task_space(0.3, 0.7, s.p_dot, params.as_array())
    assert np.allclose(out.u_traj, M @ [0.5, -0.3, 0.2] + C @ s.p_dot)
    assert np.allclose(out.u_corr, M @ (-c.gains.kp * out.e_p - c.gains.kv * out.e_v))
    assert np.allclose(out.u, out.u_traj + out.u_corr)


def test_exact_model_tracks_smooth_trajectory_to_numerical_precision(params):
    """Exact parameters, no disturbance, a C^2 rest-to-rest reference: the only error left is the
    zero-order hold of the torques, so it is tiny at 1 kHz and halves when the period halves."""
    ref = PolylineTrajectory([(0, 0), (1.5, 0), (1.5, 1.5), (0, 1.5)], speed=0.6, smoothing=1.0, alpha=0.2)
    errs = []
    for rate in (500.0, 1000.0):
        run = track_reference(ref, ComputedTorqueController(params), params, rate_hz=rate)
        errs.append((np.abs(run.e_p).max(), np.abs(run.e_v).max()))
    assert errs[1][0] < 3e-5 and errs[1][1] < 1e-4          # m (and rad), m/s
    assert 1.8 < errs[0][0] / errs[1][0] < 2.2               # first order in the hold period
    assert 1.8 < errs[0][1] / errs[1][1] < 2.2


def test_initial_error_decays_with_designed_poles(params):
    """e_dd + kv e_d + kp e = 0 per axis: compare with the analytic two-pole solution."""
    gains = gains_from_tstab([3.0, 2.0, 1.5])
    ref = SampledTrajectory(np.array([0.0, 4.0]), np.zeros((2, 3)))  # rest at the origin
    e0 = np.array([0.05, -0.08, 0.03])
    x0 = rest_state(e0, heading=0.3)
    run = track_reference(ref, ComputedTorqueController(params, gains), params, rate_hz=1000.0, x0=x0)
    t = run.t
    for i in range(3):
        s1, s2 = gains.poles()[i]
        c1 = -s2 * e0[i] / (s1 - s2)
        c2 = s1 * e0[i] / (s1 - s2)
        e = c1 * np.exp(s1 * t) + c2 * np.exp(s2 * t)
        assert np.abs(run.e_p[:, i] - e).max() < 1e-3 * abs(e0[i])
        # at T_stab the error is (c1/e0) e^-4 ~ 2 % of the initial error
        k = int(round(4.0 / -s1 * 1000))
        assert abs(run.e_p[k, i] / e0[i] - c1 / e0[i] * np.exp(-4)) < 1e-3


def test_wrong_parameters_still_converge(params):
    """20 % platform error: errors stay small and vanish at rest (the law is robust)."""
    plant = params
    ctrl = params.replace(m_p=0.8 * params.m_p, I_p=0.8 * params.I_p, m_c=1.1 * params.m_c)
    fast = SafetyConfig(max_speed=2.0)  # this figure-8 reaches 1.5 m/s, the default speed limit
    run = track_reference(figure_eight(duration=10.0, hold=4.0), ComputedTorqueController(ctrl), plant, safety=fast)
    assert run.completed, run.loop.fault
    assert np.abs(run.e_p[:, :2]).max() < 0.02
    assert np.abs(run.e_p[-1, :2]).max() < 1e-3


def test_limiter_clamps_and_reports_every_episode():
    seen = []
    lim = TorqueLimiter(MotorLimits(np.array([10.0, 10.0, 5.0])), on_saturation=seen.append)
    u, m = lim.apply(np.array([3.0, -4.0, 1.0]), 0.0)
    assert np.allclose(u, [3, -4, 1]) and not m.any() and lim.episodes == []
    for k, tau in enumerate([12.0, 15.0, 11.0]):
        u, m = lim.apply(np.array([tau, -4.0, -7.0]), 0.1 + 0.001 * k)
        assert u[0] == 10.0 and u[2] == -5.0 and m.tolist() == [True, False, True]
    lim.apply(np.array([0.0, 0.0, 0.0]), 0.2)
    lim.apply(np.array([0.0, -20.0, 0.0]), 0.3)
    rep = lim.report()
    assert [(r["motor"], r["ticks"]) for r in rep] == [("right_wheel", 3), ("pivot", 3), ("left_wheel", 1)]
    assert rep[0]["peak_request_Nm"] == 15.0 and rep[0]["t_start"] == 0.1 and rep[0]["t_end"] == pytest.approx(0.102)
    assert len(seen) == 3
    with pytest.raises(ValueError, match="non-finite"):
        lim.apply(np.array([np.nan, 0, 0]), 0.4)


def test_loop_uses_any_feedback_source_and_tells_it_the_torques(params):
    """The law only sees what the feedback source reports: a biased estimator biases the robot; the
    source is told, each cycle, the command that acted over the last period."""
    told = []

    class Biased:
        name, faults = "biased", ()

        def start(self, s, robot):
            return self.step(s, robot, None)

        def step(self, s, robot, u_prev):
            told.append((s.t, None if u_prev is None else u_prev.copy()))
            x = robot.truth()
            return StateEstimate(s.t, x[:3] + np.array([0.01, 0.0, 0.0]), x[6:9], np.zeros(6), float(x[5]))

    ref = SampledTrajectory(np.array([0.0, 3.0]), np.zeros((2, 3)))
    run = track_reference(ref, ComputedTorqueController(params), params, rate_hz=500.0, feedback=Biased())
    rec = run.loop.recording
    assert len(told) == len(rec.t)
    np.testing.assert_allclose(told[8][1], rec.torque[7])     # cycle 8 is told the command of sample 7
    assert run.x[-1, 0] == pytest.approx(-0.01, abs=1e-3)    # settles where the estimate says x = 0
