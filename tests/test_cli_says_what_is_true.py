"""What the commands report is what they did: truncated recordings, guesses, the sweep's axis,
the demo's labels and files, and the plots' walls and legends."""
from __future__ import annotations

import json
import re

import numpy as np
import pytest

from otbot_hw.identification.experiments import deviation_guess, simulate_experiment
from otbot_hw.params import nominal
from otbot_hw.recording import read_recording, write_recording


@pytest.fixture(scope="module")
def chassis_runs(tmp_path_factory):
    """Two simulated chassis experiments (different noise) and the first one cut in the middle."""
    d = tmp_path_factory.mktemp("chassis")
    paths = []
    for seed in (1, 2):
        p = d / f"chassis{seed}.mcap"
        write_recording(p, simulate_experiment("chassis", nominal(), seed=seed))
        paths.append(p)
    data = paths[0].read_bytes()
    cut = d / "chassis_cut.mcap"
    cut.write_bytes(data[:len(data) // 2])
    return paths, cut


def test_identify_says_a_recording_is_truncated_and_fits_what_it_holds(chassis_runs, otbot_cli):
    _, cut = chassis_runs
    rec = read_recording(cut)
    assert rec.truncated and 10 < len(rec) < 300
    rc, out, err = otbot_cli(["identify", "chassis", "--recording", str(cut), "--json"])
    assert rc == 0
    notices = [line for line in err.splitlines() if "truncated" in line]
    assert len(notices) == 1 and str(cut) in notices[0]
    assert f"ends at t = {rec.t[-1]:g} s after {len(rec)} complete samples" in notices[0]
    d = json.loads(out)
    assert d["truncated_recordings"] == [str(cut)]
    truth = nominal()
    for name, v in d["parameters"].items():  # the first half still identifies the robot
        assert abs(v["value"] - getattr(truth, name)) <= 4 * v["std"], name


def test_recording_option_takes_several_files_in_either_form(chassis_runs, otbot_cli):
    (a, b), _ = chassis_runs
    rc, out_list, _ = otbot_cli(["identify", "chassis", "--recording", str(a), str(b), "--json"])
    assert rc == 0
    rc, out_rep, _ = otbot_cli(["identify", "chassis", "--recording", str(a), "--recording", str(b), "--json"])
    assert rc == 0
    one, two = json.loads(out_list), json.loads(out_rep)
    assert one["source"] == two["source"] == [str(a), str(b)]
    assert one["parameters"] == two["parameters"]
    assert set(one["fit_percent"]) == {f"chassis{i}/{c}" for i in (1, 2) for c in ("a_x", "a_y", "omega_z")}


def test_a_guess_is_fitted_first_not_ignored_without_local_only(otbot_cli):
    rc, out, _ = otbot_cli(["identify", "chassis", "--sim", "--guess", "m_c=150", "--json"])
    assert rc == 0
    d = json.loads(out)
    first = d["attempts"][0]
    assert first["start"] == "guess" and first["guess"]["m_c"] == 150.0
    assert d["converged"] and abs(d["parameters"]["m_c"]["value"] - nominal().m_c) < 1.0


def test_sweep_fits_from_each_guess_by_default_and_says_so_with_global_start(otbot_cli):
    argv = ["sweep", "--points", "2", "--seeds", "1", "--max-deviation", "80", "--workers", "1", "--json"]
    rc, out, err = otbot_cli(argv)
    assert rc == 0 and "single fit from each guess" in err
    local = json.loads(out)
    assert local["global_start"] is False
    truth = nominal()
    for p in local["points"]:
        assert p["converged"] and p["accepted"] == "guess" and p["starts"] == 1
        assert p["guess"] == pytest.approx(deviation_guess("platform", truth, p["deviation"], angle=np.pi / 4))
    assert local["summary"]["accepted_start"] == {"guess": 2}
    rc, out, _ = otbot_cli([*argv, "--global-start"])
    assert rc == 0
    pipeline = json.loads(out)
    s = pipeline["summary"]
    assert pipeline["global_start"] is True and sum(s["accepted_start"].values()) == s["converged"] == 2
    if s["accepted_start"].get("equation error") == 2:  # the guess played no part: the result cannot vary
        assert all(v["spread_over_deviations"] == 0 for v in s["parameters"].values())


def test_demo_labels_numbers_announces_files_and_explains_saturation_once(tmp_path, otbot_cli):
    out_dir = tmp_path / "demo"
    rc, out, err = otbot_cli(["demo", "--out-dir", str(out_dir)])
    assert rc == 0
    written = sorted(str(p) for p in out_dir.rglob("*") if p.is_file())
    assert written and all(p in out for p in written), [p for p in written if p not in out]
    q_line = next(line for line in out.splitlines() if "final configuration q" in line)
    assert re.search(r"x -?\d+\.\d+ m, y -?\d+\.\d+ m, alpha -?\d+\.\d+ rad, phi_r", q_line)
    settle = next(line for line in out.splitlines() if "settle times" in line)
    assert "start at t = 0 s:" in settle and settle.count("corner at t =") == 4 and "stop at t = 25 s:" in settle
    sat = [line for line in (out + err).splitlines() if "saturation" in line or "clipped" in line]
    assert len(sat) == 1 and "expected: every episode starts at a velocity step" in sat[0]
    assert not [line for line in err.splitlines() if "feasibility:" in line]
    walls = re.search(r"footprint to the walls >= (\d+) mm", out)
    assert walls and int(walls.group(1)) > 0
    for stage in ("1/6", "2/6", "3/6", "4/6", "5/6", "6/6"):
        assert f"[demo] {stage}" in err
    # the bench stage identified the loaded robot the corridor then runs on, and says how well
    bench = next(line for line in out.splitlines() if "bench estimates" in line)
    for name in ("I_a", "b_w", "I_p0", "b_p", "m_c", "I_c", "x_B", "y_B", "m_p", "I_p", "x_F", "y_F"):
        assert re.search(rf"\b{name} -?[\d.e+-]+ \+- [\d.e+-]+ \([+-]\d+\.\d\)", bench), name
    assert "with the parameters the bench identified" in err
    assert "[demo] bench diagnosis: no missing physics found" in out  # the simulated robot has none


def test_corridor_walls_lie_half_a_width_from_the_centre_line():
    from otbot_hw.control.scenarios import CORRIDOR_HALF_WIDTH_M, corridor_spec, wall_clearance

    spec = corridor_spec()
    P, _, _ = spec.reference.sample(np.linspace(0, spec.reference.duration, 3001))
    assert len(spec.walls) == 2
    # with a zero footprint the clearance is the distance from the centre line to the nearest wall
    assert wall_clearance(P[:, :2], spec.walls, 0.0) == pytest.approx(CORRIDOR_HALF_WIDTH_M, abs=1e-9)
    assert wall_clearance(P[:, :2], spec.walls, CORRIDOR_HALF_WIDTH_M + 0.01) < 0  # a wider robot touches


def test_robot_legend_names_every_symbol():
    from otbot_hw.plots import _plt, draw_robot, legend_with_robot

    plt = _plt()
    fig, ax = plt.subplots()
    ax.plot([0, 1], [0, 0], label="pivot path")
    draw_robot(ax, np.zeros(6), nominal())
    legend_with_robot(ax, nominal())
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    plt.close(fig)
    assert labels[0] == "pivot path"
    for label in ("platform footprint (r = 0.5 m)", "platform heading (alpha)", "chassis: wheels and axle", "pivot P"):
        assert label in labels
