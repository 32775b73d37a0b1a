"""Direct-collocation planner on a tiny instance: collision-free, rest-to-rest, within limits."""
import numpy as np
import pytest

from otbot_hw.control.planner import PlannerError, PlanningProblem, _symbolic_model, plan
from otbot_hw.control.task_model import task_space
from otbot_hw.motors import MotorLimits


def test_symbolic_model_matches_compiled_law(params, rng):
    f = _symbolic_model(params)
    for _ in range(5):
        z = rng.normal(size=7)
        u = rng.normal(size=3) * 5
        zd = np.asarray(f(z, u)).ravel()
        M, C = task_space(z[2], z[3], z[4:7], params.as_array())
        assert np.allclose(zd[4:7], np.linalg.solve(M, u - C @ z[4:7]))
        th = z[2] - z[3]
        assert zd[3] == pytest.approx((np.sin(th) * z[4] - np.cos(th) * z[5]) / params.l1 + z[6])


@pytest.fixture(scope="module")
def tiny(params):
    limits = MotorLimits(np.array([30.0, 30.0, 30.0]))
    prob = PlanningProblem(params, limits, start=(0.0, 0.0, 0.0), goal=(3.0, 0.0, 0.5),
                           obstacles=[(1.5, 0.1, 0.25)], walls=(-1.5, 1.5), intervals=24)
    return prob, plan(prob)


def test_planner_returns_collision_free_rest_to_rest_plan(tiny):
    prob, res = tiny
    assert res.status == "Solve_Succeeded"
    assert np.allclose(res.z[0], [0, 0, 0, 0, 0, 0, 0], atol=1e-8)
    assert np.allclose(res.z[-1, :3], [3.0, 0.0, 0.5], atol=1e-8) and np.allclose(res.z[-1, 4:], 0, atol=1e-8)
    assert np.all(np.abs(res.u) <= 0.8 * 30.0 + 1e-6)
    (cx, cy, r), = prob.obstacles
    d = np.hypot(res.z[:, 0] - cx, res.z[:, 1] - cy)
    assert d.min() >= r + prob.params.radius + prob.clearance - 1e-6
    assert res.min_clearance_m > 0          # between the nodes too (interpolated path)
    assert np.all(np.hypot(res.z[:, 4], res.z[:, 5]) <= prob.max_speed + 1e-6)
    # minimum time: torques at the (margin-scaled) limit somewhere
    assert np.abs(res.u).max() > 0.75 * 30.0


def test_planned_states_are_dynamically_consistent_up_to_collocation_error(tiny, params):
    """Replaying the planned torques open loop drifts (the plan is only collocation-consistent),
    but the start of the motion agrees with the plan."""
    from otbot_hw.runtime.tracking import replay_torques

    prob, res = tiny
    t, X = replay_torques(res.u[:-1], res.t[:-1], params, res.x[0], rate_hz=500.0, duration=res.t[-1])
    P = res.trajectory().sample(t)[0]
    err = np.hypot(X[:, 0] - P[:, 0], X[:, 1] - P[:, 1])
    first = err[t <= res.t[1]].max()   # after one collocation interval: small
    assert first < 0.05
    assert err[-1] > 3 * first          # ... and the drift accumulates


def test_planner_rejects_impossible_warm_start(params):
    limits = MotorLimits(np.array([30.0, 30.0, 30.0]))
    prob = PlanningProblem(params, limits, start=(0.0, 0.0, 0.0), goal=(3.0, 0.0, 0.0),
                           obstacles=[(1.5, 0.0, 0.8)], walls=(-1.2, 1.2), intervals=10)
    with pytest.raises(PlannerError, match=r"no collision-free initial path: .* hits obstacle 0 at \(1.5, 0\) m"):
        plan(prob)
    with pytest.raises(PlannerError):
        PlanningProblem(params, limits, (0, 0, 0), (1, 0, 0), intervals=2)
    with pytest.raises(PlannerError, match="goal .* obstacle 0"):
        plan(PlanningProblem(params, limits, (0, 0, 0), (3, 0, 0), obstacles=[(3.2, 0.0, 0.2)], intervals=10))
    with pytest.raises(PlannerError, match="outside the walls"):
        plan(PlanningProblem(params, limits, (0, 0, 0), (3, 1.0, 0), walls=(-1.2, 1.2), intervals=10))


def test_fixed_time_plan_takes_the_given_time_with_less_torque(tiny, params):
    prob, res_min = tiny
    from dataclasses import replace

    fixed = plan(replace(prob, duration=2.0 * res_min.t[-1]))
    assert fixed.status == "Solve_Succeeded" and fixed.t[-1] == pytest.approx(2.0 * res_min.t[-1])
    assert np.abs(fixed.u).max() < np.abs(res_min.u).max()
    (cx, cy, r), = prob.obstacles
    assert np.hypot(fixed.z[:, 0] - cx, fixed.z[:, 1] - cy).min() >= r + params.radius + prob.clearance - 1e-6
