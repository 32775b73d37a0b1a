"""``otbot simulate`` and ``otbot demo`` from the command line: JSON output, bad input, plots, recordings."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from otbot_hw.params import nominal
from otbot_hw.recording import read_recording
from otbot_hw.simulation.simulator import simulate

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def test_json_reports_final_state_of_a_direct_simulation(otbot_cli):
    rc, out, err = otbot_cli(["simulate", "--torques", "6,-10,6", "--duration", "3", "--rate", "100", "--json"])
    assert rc == 0
    assert out.count("\n") == 1  # one JSON object, on one line
    result = json.loads(out)
    assert len(result["q"]) == 6 and len(result["qd"]) == 6
    x = simulate(nominal(), np.tile([6.0, -10.0, 6.0], (300, 1)), 0.01).x[-1]
    assert result["q"] == x[:6].tolist() and result["qd"] == x[6:].tolist()
    assert result["t_final"] == pytest.approx(3.0) and result["samples"] == 301
    assert result["max_constraint_residual"] < 1e-8 and result["max_holonomic_residual"] < 1e-8


def test_json_with_fixture_rate_and_negative_first_torque(otbot_cli):
    rc, out, _ = otbot_cli(["simulate", "--torques", "-2,1.5,0.5", "--duration", "0.5", "--rate", "50",
                          "--fixture", "stand", "--json"])
    assert rc == 0
    result = json.loads(out)
    x = simulate(nominal(), np.tile([-2.0, 1.5, 0.5], (25, 1)), 0.02, fixture="stand").x[-1]
    assert result["q"] == x[:6].tolist() and result["qd"] == x[6:].tolist()
    assert result["q"][:2] == [0.0, 0.0]  # the chassis is held on the stand


@pytest.mark.parametrize("args, message", [
    (["--torques", "6,x,6"], "--torques: 'x' is not a number"),
    (["--torques", "6,-10"], "--torques needs 3 comma-separated numbers"),
    (["--torques", "6,-10,6,1"], "--torques needs 3 comma-separated numbers"),
    (["--torques", "nan,0,0"], "--torques: values must be finite"),
    (["--torques", "1,inf,0"], "--torques: values must be finite"),
    (["--torques", ""], "--torques needs 3"),
    (["--duration", "-1"], "argument --duration: must be a finite number of seconds > 0, got '-1'"),
    (["--duration", "0"], "argument --duration: must be a finite number of seconds > 0"),
    (["--duration", "nan"], "argument --duration: must be a finite number of seconds > 0"),
    (["--duration", "three"], "--duration"),
    (["--duration", "0.001", "--rate", "100"], "is shorter than one period (0.01 s)"),
    (["--rate", "-100"], "argument --rate: must be a finite number of Hz > 0"),
    (["--rate", "nan"], "argument --rate: must be a finite number of Hz > 0"),
    (["--fixture", "ceiling"], "invalid choice"),
    (["--seed", "1.5"], "argument --seed: must be an integer >= 0"),
    (["--seed", "-1"], "argument --seed: must be an integer >= 0"),
    (["--duration", "1e9"], "samples; at most"),
    (["--out", "/nonexistent-folder/run.mcap"], "--out /nonexistent-folder/run.mcap: folder /nonexistent-folder does not exist"),
    (["--torques", "1e9,0,0", "--duration", "0.1"], "the simulation diverged: the state is not finite from t = "),
    (["--params", "/nonexistent-folder/p.yaml"], "cannot read parameter file"),
])
def test_bad_arguments_exit_2_with_a_message(otbot_cli, args, message):
    rc, out, err = otbot_cli(["simulate", *args, "--json"])
    assert rc == 2
    assert message in err, err
    assert out == ""


def test_out_and_plot_write_a_readable_recording_and_pngs(tmp_path, otbot_cli):
    rec_path, plot_dir = tmp_path / "run.mcap", tmp_path / "plots"
    rc, out, _ = otbot_cli(["simulate", "--duration", "1", "--rate", "100", "--seed", "5",
                          "--out", str(rec_path), "--plot", str(plot_dir), "--json"])
    assert rc == 0
    result = json.loads(out)
    rec = read_recording(rec_path)
    assert len(rec) == 101 and rec.truncated is False
    assert rec.truth_q[-1].tolist() == result["q"] and rec.truth_qd[-1].tolist() == result["qd"]
    assert rec.sample_period == 0.01 and rec.metadata["seed"] == 5
    assert np.all(rec.torque == [6.0, -10.0, 6.0])
    assert rec.imu_accel.std(axis=0)[2] > 5e-3  # paper noise on by default
    names = {Path(p).name for p in result["plots"]}
    assert {"xy_path.png", "states.png"} <= names
    for p in result["plots"]:
        data = Path(p).read_bytes()
        assert data[:8] == PNG_MAGIC and len(data) > 10_000


def test_text_output_and_seeds(tmp_path, otbot_cli):
    rc, out, _ = otbot_cli(["simulate", "--duration", "0.2", "--seed", "1", "--out", str(tmp_path / "a.mcap")])
    assert rc == 0 and "final q" in out and "x, y m" in out
    otbot_cli(["simulate", "--duration", "0.2", "--seed", "2", "--out", str(tmp_path / "b.mcap")])
    otbot_cli(["simulate", "--duration", "0.2", "--seed", "1", "--out", str(tmp_path / "c.mcap")])
    a, b, c = (read_recording(tmp_path / f"{n}.mcap") for n in "abc")
    assert np.array_equal(a.imu_accel, c.imu_accel) and not np.array_equal(a.imu_accel, b.imu_accel)
    assert np.array_equal(a.truth_q, b.truth_q)


def test_unwritable_outputs_exit_2(tmp_path, otbot_cli):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    rc, out, err = otbot_cli(["simulate", "--duration", "0.1", "--plot", str(blocker), "--json"])
    assert rc == 2 and "exists and is not a folder" in err and out == ""
    rc, out, err = otbot_cli(["demo", "--out-dir", str(blocker / "sub"), "--json"])
    assert rc == 2 and "--out-dir" in err and out == ""


def test_help_explains_units(otbot_cli):
    rc, out, _ = otbot_cli(["simulate", "--help"])
    assert rc == 0
    for unit in ("N m", "in s", "Hz", "rad"):
        assert unit in out, unit


def test_demo_writes_recording_and_plots(tmp_path, otbot_cli):
    out_dir = tmp_path / "demo"
    rc, out, err = otbot_cli(["demo", "--out-dir", str(out_dir), "--json"])
    assert rc == 0
    result = json.loads(out)["chassis_experiment"]
    rec = read_recording(result["recording"])
    assert len(rec) == 301 and np.all(rec.torque == [6.0, -10.0, 6.0])
    assert rec.truth_q[-1].tolist() == result["final_q"]
    for p in result["plots"]:
        assert Path(p).read_bytes()[:8] == PNG_MAGIC
    assert Path(result["recording"]).parent == out_dir


def test_installed_entry_point_runs(tmp_path):
    script = Path(sys.executable).parent / "otbot"
    cmd = [str(script)] if script.exists() else [
        sys.executable, "-c", "import sys; from otbot_hw.cli import main; sys.exit(main())"]
    ok = subprocess.run([*cmd, "simulate", "--duration", "0.1", "--json"], capture_output=True, text=True)
    assert ok.returncode == 0 and len(json.loads(ok.stdout)["q"]) == 6
    bad = subprocess.run([*cmd, "simulate", "--torques", "1,2"], capture_output=True, text=True)
    assert bad.returncode == 2 and "--torques needs 3" in bad.stderr


def test_a_duration_that_is_not_whole_periods_is_said(otbot_cli):
    """--duration 0.5 s at 3 Hz is 1.5 periods: the run lasts 2 periods, and a notice line says so."""
    rc, out, err = otbot_cli(["simulate", "--rate", "3", "--duration", "0.5", "--json"])
    assert rc == 0 and json.loads(out)["t_final"] == pytest.approx(2 / 3)
    assert err == ("otbot simulate: note: --duration 0.5 s at 3 Hz is 1.5 periods; running 2 periods "
                   "(0.666667 s)\n")
    rc, out, err = otbot_cli(["simulate", "--rate", "100", "--duration", "0.5", "--json"])
    assert rc == 0 and err == ""


def test_an_interrupted_write_leaves_no_truncated_recording(otbot_cli, tmp_path, monkeypatch):
    """The recording is written beside --out and renamed when complete: Ctrl-C while writing (minutes at
    10^7 samples) leaves neither a truncated RUN.mcap nor the temporary file."""
    import otbot_hw.recording as recording

    def interrupted(path, rec, progress=None):
        Path(path).write_bytes(b"\x89MCAP0\r\n partial")
        raise KeyboardInterrupt

    monkeypatch.setattr(recording, "write_recording", interrupted)
    rc, _, err = otbot_cli(["simulate", "--duration", "0.1", "--out", str(tmp_path / "run.mcap")])
    assert rc == 130 and err.endswith("otbot simulate: interrupted\n")
    assert list(tmp_path.iterdir()) == []
