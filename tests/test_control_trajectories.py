"""Desired trajectories: derivative consistency, corridor geometry, CSV format and bad input."""
import numpy as np
import pytest

from otbot_hw.control.sampled_trajectory import SampledTrajectory, load_csv, save_csv
from otbot_hw.control.trajectories import PolylineTrajectory, TrajectoryError, corridor, figure_eight


def _fd_consistency(traj, dt=1e-4):
    """max |p(t) - p(t0) - integral p_dot| and the same for p_dot vs p_dd (trapezoid on a fine grid):
    the derivatives are consistent when integrating them gives back the trajectory, jumps included."""
    from scipy.integrate import cumulative_trapezoid

    t = np.arange(-0.2, traj.duration + 0.2, dt)
    P, PD, PDD = traj.sample(t)
    d1 = P[1:] - P[0] - cumulative_trapezoid(PD, t, axis=0)
    d2 = PD[1:] - PD[0] - cumulative_trapezoid(PDD, t, axis=0)
    return np.abs(d1).max(), np.abs(d2).max(), P, PD, PDD


def test_smooth_corridor_is_rest_to_rest_with_continuous_derivatives():
    tr = corridor(smoothing=1.0)
    e1, e2, P, PD, PDD = _fd_consistency(tr)
    assert e1 < 1e-6 and e2 < 1e-5
    assert np.abs(np.diff(PD, axis=0)).max() < 1e-3 and np.abs(np.diff(PDD, axis=0)).max() < 1e-3  # continuous
    assert np.allclose(P[0], 0) and np.allclose(P[-1], [9, 0, 0]) and np.allclose(PD[[0, -1]], 0)
    # cruise speed is kept between corners, and no overshoot past the goal along x
    mid = tr.sample(np.array([3.0]))[1][0]
    assert np.hypot(*mid[:2]) == pytest.approx(0.6)
    assert P[:, 0].max() <= 9.0 + 1e-12


def test_corridor_matches_the_paper():
    tr = corridor()
    assert tr.duration == pytest.approx(30.0) and np.allclose(tr.corner_times, [0, 5, 10, 15, 20, 25])
    P, PD, PDD = tr.sample(np.array([0.0, 2.5, 7.5, 24.999, 27.0]))
    assert np.allclose(P[1], [1.5, 0, 0]) and np.allclose(P[2], [3, 1.5, 0]) and np.allclose(P[4], [9, 0, 0])
    assert np.allclose(PD[0], [0.6, 0, 0]) and np.allclose(PD[2], [0, 0.6, 0]) and np.allclose(PD[4], 0)
    # p_dot integrates to p; the velocity jumps are not in p_dd (it is 0: impulses are not represented)
    e1, e2, _, _, _ = _fd_consistency(tr)
    assert e1 < 1e-4 and e2 == pytest.approx(0.6, rel=1e-9)


def test_figure_eight_closes_and_derivatives_agree():
    tr = figure_eight(duration=18.0)
    e1, e2, P, PD, PDD = _fd_consistency(tr)
    assert e1 < 1e-5
    assert np.allclose(P[0], 0) and np.allclose(P[-1], 0, atol=1e-9) and np.allclose(PD[[0, -1]], 0)
    # constant speed on the cruise, centripetal acceleration V^2 / R on the arcs
    t = np.linspace(3, 15, 500)
    _, PD, PDD = tr.sample(t)
    assert np.allclose(np.hypot(PD[:, 0], PD[:, 1]), tr.cruise_speed)
    acc = np.hypot(PDD[:, 0], PDD[:, 1])
    assert np.isclose(acc.max(), tr.cruise_speed ** 2 / 1.0, rtol=1e-6)
    assert e2 < 2e-4  # trapezoid error at the line/arc acceleration jumps, dt * V^2 / R / 2 each


def test_path_rejects_discontinuous_sections():
    from otbot_hw.control.trajectories import Arc, Line, PathTrajectory

    with pytest.raises(TrajectoryError, match="does not continue"):
        PathTrajectory([Line((0, 0), (1, 0)), Line((1, 0), (1, 1))], duration=5.0)  # a corner
    with pytest.raises(TrajectoryError, match="does not continue"):
        PathTrajectory([Line((0, 0), (1, 0)), Line((1.1, 0), (2, 0))], duration=5.0)  # a gap
    ok = PathTrajectory([Line((0, 0), (1, 0)), Arc((1, 1), 1.0, -np.pi / 2, np.pi / 2)], duration=5.0)
    assert ok.length == pytest.approx(1 + np.pi / 2)


def test_polyline_rejects_bad_definitions():
    with pytest.raises(TrajectoryError):
        PolylineTrajectory([(0, 0)], 1.0)
    with pytest.raises(TrajectoryError, match="repeats"):
        PolylineTrajectory([(0, 0), (0, 0)], 1.0)
    with pytest.raises(TrajectoryError, match="speed"):
        PolylineTrajectory([(0, 0), (1, 0)], 0.0)


def test_csv_round_trip_gives_consistent_derivatives(tmp_path):
    src = figure_eight(duration=12.0)
    t = np.linspace(0, 12.0, 241)
    P, PD, _ = src.sample(t)
    path = save_csv(tmp_path / "fig8.csv", t, P, PD, torques=np.zeros((len(t), 3)), comment="test")
    tr = load_csv(path)
    assert tr.torques.shape == (241, 3) and tr.duration == pytest.approx(12.0)
    e1, e2, Q, QD, _ = _fd_consistency(tr)
    assert e1 < 1e-6 and e2 < 2e-4  # C^1 Hermite: p_dd jumps at the knots
    tt = np.linspace(0.3, 11.7, 97)
    assert np.abs(tr.sample(tt)[0] - src.sample(tt)[0]).max() < 2e-4     # interpolates the source
    # positions only: clamped cubic spline, rest at both ends
    path2 = save_csv(tmp_path / "pos.csv", t + 5.0, P)
    tr2 = load_csv(path2)
    e1, e2, Q, QD, _ = _fd_consistency(tr2)
    assert e1 < 1e-6 and e2 < 1e-6 and np.allclose(QD[[0, -1]], 0)
    assert tr2.duration == pytest.approx(12.0)  # times shifted to start at 0


@pytest.mark.parametrize("text, match", [
    ("t,x,y\n0,0,0\n1,1,0\n", "missing column.*alpha"),
    ("t,x,y,alpha\n0,0,0,0\n1,1,0,0\n0.5,2,0,0\n", "not strictly increasing at line 4"),
    ("t,x,y,alpha\n0,0,0,0\n1,nan,0,0\n", "line 3, column x"),
    ("t,x,y,alpha\n0,0,0,0\n1,abc,0,0\n", "line 3, column x: 'abc'"),
    ("t,x,y,alpha,x_dot\n0,0,0,0,0\n1,1,0,0,0\n", "velocity columns"),
    ("t,x,y,alpha\n0,0,0,0\n", "at least 2"),
    ("t,x,y,alpha\n0,0,0,0\n1,1,0\n", "line 3 has 3 fields"),
    ("", "empty"),
    ("# obstacle: 1, 2\nt,x,y,alpha\n0,0,0,0\n1,1,0,0\n", "line 1: obstacle comment"),
])
def test_bad_csv_is_rejected_with_a_clear_message(tmp_path, text, match):
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(TrajectoryError, match=match):
        load_csv(p)


def test_missing_csv_file(tmp_path):
    with pytest.raises(TrajectoryError, match="cannot read"):
        load_csv(tmp_path / "nope.csv")
    with pytest.raises(TrajectoryError, match="strictly increasing"):
        SampledTrajectory(np.array([0.0, 0.0]), np.zeros((2, 3)))


def test_samples_too_close_or_too_far_are_refused_without_warnings():
    """Rows 1e-160 s apart gave a spline with infinite derivatives (scipy overflow warnings, then a
    traceback in the simulator); a position of 1e300 m ran into a 300-digit tracking error."""
    import warnings

    from otbot_hw.control.sampled_trajectory import SampledTrajectory
    from otbot_hw.control.trajectories import TrajectoryError

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(TrajectoryError, match="the interpolated trajectory is not finite"):
            SampledTrajectory(np.array([0.0, 1e-160]), np.array([[0.0, 0, 0], [0.5, 0, 0]]))
        with pytest.raises(TrajectoryError, match=r"row 2: position \[1e\+300, 0.0, 0.0\] beyond 1e\+06"):
            SampledTrajectory(np.array([0.0, 1.0]), np.array([[0.0, 0, 0], [1e300, 0, 0]]))
