"""Interval torque-feasibility check (paper §5.3) against sampled closed-loop runs."""
import numpy as np
import pytest

from otbot_hw.runtime.tracking import track_reference
from otbot_hw.simulation.simulator import rest_state
from otbot_hw.control.computed_torque import ComputedTorqueController
from otbot_hw.control.feasibility import (
    ErrorBounds, check_feasibility, reference_states,
)
from otbot_hw.control.gains import gains_from_tstab
from otbot_hw.control.interval import Interval
from otbot_hw.control.trajectories import PolylineTrajectory, figure_eight
from otbot_hw.model.dynamics import coriolis_matrix
from otbot_hw.motors import MotorLimits
from otbot_hw.simulation.simulator import ForceSchedule, PivotForce


def test_interval_sine_encloses_samples(rng):
    lo = rng.uniform(-10, 10, 500)
    hi = lo + rng.uniform(0, 4, 500)
    iv = Interval(lo, hi)
    for f, s in ((np.sin, iv.sin()), (np.cos, iv.cos())):
        x = lo[:, None] + (hi - lo)[:, None] * np.linspace(0, 1, 400)[None, :]
        v = f(x)
        assert np.all(v.min(axis=1) >= s.lo - 1e-12) and np.all(v.max(axis=1) <= s.hi + 1e-12)
        assert np.all(s.hi - s.lo <= (v.max(axis=1) - v.min(axis=1)) + 2e-4)  # sin/cos enclosures are tight
    prod = Interval(-1.0, 2.0) * Interval(-3.0, 0.5)
    assert (float(prod.lo), float(prod.hi)) == (-6.0, 3.0)


def test_interval_task_space_model_encloses_point_values(params, rng):
    """The model's pure functions evaluated on intervals enclose their values at points inside."""
    from otbot_hw.model.task_space import task_space_model

    q0, qd0 = rng.normal(size=6), rng.normal(size=6)
    w = 0.05
    qi = np.empty(6, dtype=object)
    qi[:] = [Interval(v - w, v + w) for v in q0]
    qdi = np.empty(6, dtype=object)
    qdi[:] = [Interval(v - w, v + w) for v in qd0]
    Mi, Ci = task_space_model(qi, qdi, params)
    for _ in range(20):
        q = q0 + rng.uniform(-w, w, 6)
        qd = qd0 + rng.uniform(-w, w, 6)
        assert coriolis_matrix(q, qd, params).dtype == float
        for I, P in zip((Mi, Ci), task_space_model(q, qd, params)):
            for i in range(3):
                for j in range(3):
                    e = I[i, j]
                    lo, hi = (e.lo, e.hi) if isinstance(e, Interval) else (e, e)
                    assert np.all(lo - 1e-12 <= P[i, j]) and np.all(P[i, j] <= hi + 1e-12)


def test_reference_states_follow_the_rolling_constraints(params):
    """Simulating u_traj open loop from a state on p_d reproduces the reference states."""
    from otbot_hw.simulation.simulator import simulate
    from otbot_hw.control.task_model import task_space

    ref = PolylineTrajectory([(0, 0), (1.0, 0), (1.0, 1.0)], speed=0.8, smoothing=0.6, alpha=0.3)
    dt = 1e-3
    t = np.arange(0, 4.0 + dt / 4, dt / 2)
    X = reference_states(ref, params, t, heading0=0.2)
    _, _, PDD = ref.sample(t)
    # u_traj along the reference (exact inverse dynamics, at mid-interval) replayed open loop for 2 s
    n = 2000
    U = np.empty((n, 3))
    for k in range(n):
        m = 2 * k + 1
        M, C = task_space(X[m, 2], X[m, 5], X[m, 6:9], params.as_array())
        U[k] = M @ PDD[m] + C @ X[m, 6:9]
    run = simulate(params, U, dt, x0=X[0])
    assert np.abs(run.x[:, :3] - X[0:2 * n + 1:2, :3]).max() < 1e-5
    assert np.abs(run.x[:, 5] - X[0:2 * n + 1:2, 5]).max() < 1e-5


def test_interval_bound_contains_applied_torques(params, rng):
    """Closed-loop runs with random initial errors and pivot pushes: whenever the errors are
    inside the bounds, the torque the law applies lies in the interval enclosure."""
    gains = gains_from_tstab(3.0)
    ref = figure_eight(duration=8.0, radius=0.8, center_distance=1.6)
    eb = ErrorBounds((0.03, 0.03, 0.02), (0.08, 0.08, 0.05), pivot_angle=0.08)
    limits = MotorLimits(np.array([100.0, 100.0, 100.0]))
    rep = check_feasibility(ref, params, gains, limits, eb, dt=0.01)
    checked = 0
    for trial in range(3):
        e0 = rng.uniform(-0.6, 0.6, 3) * np.array(eb.position)
        x0 = rest_state(e0, heading=rng.uniform(-0.02, 0.02))
        fs = ForceSchedule([PivotForce(rng.uniform(1, 6), 0.5, *rng.uniform(-40, 40, 2))])
        run = track_reference(ref, ComputedTorqueController(params, gains), params, rate_hz=1000.0, x0=x0, forces=fs)
        k = np.round(rep.t[:-1] * 1000).astype(int)
        ep, ev = run.e_p[k], run.e_v[k]
        dphi = np.abs(run.x[k, 5] - rep.reference_state[:-1, 5])
        inside = (np.all(np.abs(ep) <= eb.position, axis=1) & np.all(np.abs(ev) <= eb.velocity, axis=1)
                  & (dphi <= eb.pivot_angle))
        assert inside.mean() > 0.9, "the sampled runs must mostly stay inside the error bounds"
        u = run.u_cmd[k]
        lo, hi = rep.lo[:-1], rep.hi[:-1]
        ok = (u >= lo - 1e-9) & (u <= hi + 1e-9)
        assert ok[inside].all()
        checked += int(inside.sum())
        # the bound is informative, not trivially wide
        assert np.median((hi - lo)[inside][:, :2]) < 90.0
    assert checked > 1500


def test_infeasible_trajectory_is_reported_with_time_and_motor(params):
    gains = gains_from_tstab(3.0)
    fast = PolylineTrajectory([(0, 0), (2, 0), (2, 2)], speed=1.5, smoothing=0.3, hold=0.5)
    rep = check_feasibility(fast, params, gains, MotorLimits(np.array([15.0, 15.0, 15.0])), ErrorBounds.default())
    assert not rep.feasible
    v = rep.violations[0]
    assert v["motor"] in ("right_wheel", "left_wheel", "pivot") and v["bound_Nm"] > 15.0
    assert 0.0 <= v["t_start"] <= v["t_end"] <= fast.duration
    ok = check_feasibility(fast, params, gains, MotorLimits(np.array([500.0, 500.0, 500.0])), ErrorBounds.default())
    assert ok.feasible and ok.to_dict()["violations"] == []
    with pytest.raises(ValueError, match="position"):
        ErrorBounds((0.1, -1, 0), (0, 0, 0))


def test_bound_covers_the_torque_at_velocity_steps(params):
    """The corridor's corners: the check flags them, and the torque the law asks for right after
    each step (robot still at the old velocity) lies inside the enclosure."""
    from otbot_hw.control.trajectories import corridor

    gains = gains_from_tstab(3.0)
    ref = corridor(hold=1.0)
    limits = MotorLimits(np.array([40.0, 40.0, 40.0]))
    rep = check_feasibility(ref, params, gains, limits, ErrorBounds.default())
    assert [s["t"] for s in rep.velocity_steps] == pytest.approx([0, 5, 10, 15, 20, 25])
    run = track_reference(ref, ComputedTorqueController(params, gains), params, rate_hz=1000.0)
    for s in rep.velocity_steps:
        i = int(round(s["t"] / 0.01))
        k = int(round(s["t"] * 1000))
        assert np.all(rep.lo[i] <= run.u_cmd[k]) and np.all(run.u_cmd[k] <= rep.hi[i])
        assert np.abs(run.u_cmd[k, :2]).max() > 40.0   # and it is beyond the wheels' limit
    assert {v["t_start"] for v in rep.violations} >= {0.0, 5.0, 10.0, 15.0, 20.0, 25.0}
