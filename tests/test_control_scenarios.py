"""Scenario acceptance (paper §5.4): corridor corners, smooth corridor, force rejection; CLI."""
import json

import numpy as np
import pytest

from otbot_hw.cli import main
from otbot_hw.control.gains import gains_from_tstab
from otbot_hw.control.metrics import Event, event_summary
from otbot_hw.control.scenarios import FIGURE8_FORCES, corridor_spec, figure8_spec
from otbot_hw.motors import MotorLimits, load_motor_limits
from otbot_hw.params import nominal
from otbot_hw.runtime.tracking import track
from otbot_hw.simulation.simulator import ForceSchedule

T_STAB = 3.0


def predicted_settle_after_velocity_step(t_stab: float, fraction: float = 0.02) -> float:
    """Linear theory: after a velocity step the position error is Dv/(s1-s2) (e^s1t - e^s2t);
    seconds until it stays below ``fraction`` of its peak (the velocity error settles sooner)."""
    g = gains_from_tstab(t_stab)
    s1, s2 = g.poles()[0]
    t = np.arange(0, 3 * t_stab, 1e-4)
    e = (np.exp(s1 * t) - np.exp(s2 * t)) / (s1 - s2)
    above = np.flatnonzero(e > fraction * e.max())
    return t[above[-1] + 1]


@pytest.fixture(scope="module")
def paper():
    return nominal()


def test_corridor_settles_after_each_corner_as_designed(paper):
    """Unlimited torques: every corner is a velocity step and the errors settle exactly as the
    designed poles predict (3.2 s: 2 % of the peak, measured from the corner)."""
    spec = corridor_spec()
    run = track(spec, paper, MotorLimits(np.array([1e4, 1e4, 1e4])), gains_from_tstab(T_STAB))
    events = event_summary(run.t, run.e_p, run.e_v, spec.events)
    assert [e["kind"] for e in events] == ["start", "corner", "corner", "corner", "corner", "stop"]
    expected = predicted_settle_after_velocity_step(T_STAB)
    assert 3.1 < expected < 3.3
    for e in events:
        assert e["settle_time_s"] == pytest.approx(expected, abs=0.01)
        assert e["velocity_settle_s"] < 1.5
    assert np.abs(run.e_p[:, 2]).max() < 1e-4  # alpha stays 0


def test_corridor_with_motor_limits_saturates_visibly_and_still_settles(paper):
    limits = load_motor_limits()
    spec = corridor_spec()
    run = track(spec, paper, limits, gains_from_tstab(T_STAB))
    assert np.all(np.abs(run.u) <= limits.max_torque + 1e-12)
    # the velocity steps ask for more than the motors give: reported, at each corner and the ends
    starts = sorted({round(s["t_start"], 3) for s in run.saturation})
    assert starts == [0.0, 5.0, 10.0, 15.0, 20.0, 25.0]
    events = event_summary(run.t, run.e_p, run.e_v, spec.events)
    for e in events:
        assert e["settle_time_s"] is not None and e["settle_time_s"] < 1.1 * T_STAB
    assert np.hypot(*run.e_p[-1, :2]) < 0.02 * max(e["peak_position_error_m"] for e in events)


def test_smooth_corridor_tracks_without_overshoot(paper):
    spec = corridor_spec(smooth=True)
    run = track(spec, paper, load_motor_limits(), gains_from_tstab(T_STAB))
    assert run.saturation == []
    assert np.abs(run.e_p[:, :2]).max() < 1e-4 and np.abs(run.e_v[:, :2]).max() < 1e-3
    assert run.x[:, 0].max() < 9.0 + 1e-4 and np.allclose(run.x[-1, :2], [9, 0], atol=1e-4)
    from otbot_hw.control.scenarios import goal_overshoot
    assert goal_overshoot(spec.reference, run.x[:, :2]) < 1e-4


def test_force_on_pivot_is_rejected_within_tstab(paper):
    spec = figure8_spec()
    f = FIGURE8_FORCES[2]  # 350 N along -x at 11 s for 1 s
    run = track(spec, paper, load_motor_limits(), gains_from_tstab(T_STAB), forces=ForceSchedule([f]))
    ev, = event_summary(run.t, run.e_p, run.e_v, [Event(f.start, "force", f.start + f.duration)])
    assert ev["peak_position_error_m"] > 0.05                       # the push is felt ...
    assert ev["settle_time_s"] is not None and ev["settle_time_s"] < 1.1 * T_STAB   # ... and undone
    before = run.t < f.start
    assert np.abs(run.e_p[before, :2]).max() < 1e-3


def test_cli_track_json(capsys):
    assert main(["track", "corridor", "--sim", "--feedback", "truth", "--json", "--no-robustness", "--rate", "500"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out["max_abs_error"]) >= {"x", "y", "alpha"} and set(out["rms_error"]) >= {"x", "y", "alpha"}
    assert set(out["peak_torque"]) == {"right_wheel", "left_wheel", "pivot"}
    assert all("limit_Nm" in v and "peak_Nm" in v for v in out["peak_torque"].values())
    assert all({"t", "kind", "settle_time_s"} <= set(e) for e in out["events"]) and len(out["events"]) == 6
    # the corners are velocity steps: the feasibility check says where the wheels can saturate ...
    assert [s["t"] for s in out["feasibility"]["velocity_steps"]] == pytest.approx([0, 5, 10, 15, 20, 25])
    viol = out["feasibility"]["violations"]
    assert {round(v["t_start"], 2) for v in viol} == {0.0, 5.0, 10.0, 15.0, 20.0, 25.0}
    assert {v["motor"] for v in viol} >= {"right_wheel", "left_wheel"}
    # ... and the limiter reports it when it happens
    assert {round(s["t_start"], 2) for s in out["saturation"]} == {0.0, 5.0, 10.0, 15.0, 20.0, 25.0}
    assert out["goal_overshoot_m"] > 0.01


def test_cli_track_bad_input(tmp_path, capsys):
    assert main(["track", "corridor"]) == 2
    assert "--sim" in capsys.readouterr().err
    assert main(["track", "nowhere.csv", "--sim", "--feedback", "truth"]) == 2
    bad = tmp_path / "bad.csv"
    bad.write_text("t,x,y,alpha\n0,0,0,0\n1,nan,0,0\n")
    assert main(["track", str(bad), "--sim", "--feedback", "truth", "--json"]) == 2
    assert "line 3, column x" in capsys.readouterr().err
    assert main(["track", "corridor", "--sim", "--feedback", "truth", "--tstab", "0"]) == 2
    robot = tmp_path / "robot.yaml"
    robot.write_text("motors:\n" + "".join(f"  {m}: {{max_torque: {{value: 2.0, unit: N m}}}}\n"
                                           for m in ("right_wheel", "left_wheel", "pivot")))
    assert main(["track", "corridor-smooth", "--sim", "--feedback", "truth", "--strict", "--robot", str(robot)]) == 2
    err = capsys.readouterr().err
    assert "infeasible trajectory" in err and "N m limit from t =" in err


def test_cli_plan_writes_a_trackable_csv(tmp_path, capsys):
    out = tmp_path / "traj.csv"
    assert main(["plan", "--out", str(out), "--goal", "3,0,0", "--obstacle", "1.5,0.1,0.25",
                 "--intervals", "20", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["status"] == "Solve_Succeeded" and out.exists()
    assert main(["track", str(out), "--sim", "--feedback", "truth", "--json", "--no-robustness", "--rate", "500"]) == 0
    tr = json.loads(capsys.readouterr().out)
    assert tr["collisions"] == [] and "collisions" in tr["open_loop"]     # obstacles travel in the CSV
    assert tr["max_abs_error"]["x"] < 1e-3 and tr["max_abs_error"]["y"] < 1e-3
    assert main(["plan", "--out", str(out), "--obstacle", "1,1"]) == 2
    assert main(["plan", "--out", str(out), "--walls=-0.2,0.2"]) == 2


def test_plots_and_animation_are_written(tmp_path, paper):
    from otbot_hw.control.plots import animate_run, scenario_plots

    spec = figure8_spec()
    run = track(spec, paper, load_motor_limits(), gains_from_tstab(T_STAB), rate_hz=200.0)
    files = scenario_plots(tmp_path, spec, run, paper, load_motor_limits())
    assert [f.rsplit("_", 1)[1] for f in files] == ["xy.png", "errors.png", "torques.png"]
    assert all((tmp_path / f.rsplit("/", 1)[1]).stat().st_size > 10_000 for f in files)
    gif = animate_run(tmp_path / "a.gif", spec, run, paper, max_frames=4)
    from PIL import Image

    assert Image.open(gif).n_frames == 4


def test_cli_controller_and_plant_parameters_may_differ(tmp_path, capsys, paper):
    wrong = tmp_path / "ctrl.yaml"
    paper.replace(m_p=0.8 * paper.m_p, I_p=0.8 * paper.I_p).save(wrong)
    args = ["track", "corridor-smooth", "--sim", "--feedback", "truth", "--json", "--no-robustness", "--rate", "250"]
    assert main(args) == 0
    exact = json.loads(capsys.readouterr().out)["max_abs_error"]["x"]
    from otbot_hw.params import DEFAULT_PARAMS_FILE
    assert main(args + ["--params", str(wrong), "--plant-params", str(DEFAULT_PARAMS_FILE)]) == 0
    off = json.loads(capsys.readouterr().out)["max_abs_error"]["x"]
    assert off > 10 * exact


def test_planned_scenario_open_loop_collides_closed_loop_tracks(paper):
    from otbot_hw.runtime.tracking import run_scenario

    r = run_scenario("planned", paper, load_motor_limits(), robustness=False)
    assert r["planner"]["status"] == "Solve_Succeeded"
    assert len(r["open_loop"]["collisions"]) >= 1 and r["open_loop"]["final_position_error_m"] > 0.1
    assert r["collisions"] == [] and r["saturation"] == []
    assert r["max_abs_error"]["x"] < 1e-3 and r["max_abs_error"]["y"] < 1e-3 and r["max_abs_error"]["alpha"] < 1e-3
    fw = r["fraction_within"]
    assert fw["velocity_below_1cm_per_s"] > 0.95 and fw["position_below_1mm"] == 1.0
