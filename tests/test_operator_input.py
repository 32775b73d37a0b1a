"""Inputs as people write them, no hangs, no silent wrong answers (issue 22, "Hangs and silent wrong
answers"); the one-line refusals are rows of tests/test_cli_bad_input.py, here what they cannot show."""
from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from otbot_hw.params import OtbotParams, ParameterError, nominal, parse_yaml, read_yaml

ROOT = Path(__file__).resolve().parents[1]


# -- YAML: numbers as YAML 1.2 writes them, keys once, files of a sane size ---------------------------
@pytest.mark.parametrize("text, value", [("1e2", 100.0), ("1.0914e2", 109.14), ("1E2", 100.0), ("1e+2", 100.0),
                                         ("1.5e-3", 1.5e-3), (".5e1", 5.0), ("1e308", 1e308), ("-2e1", -20.0)])
def test_exponent_floats_are_numbers(text, value):
    assert parse_yaml(f"a: {text}\n") == {"a": value}


def test_what_was_text_or_an_integer_stays_so():
    assert parse_yaml("a: 100\nb: '1e2'\nc: abc1e2\nd: 1e2x\ne: 0x1f\nf: 1_000\n") == \
        {"a": 100, "b": "1e2", "c": "abc1e2", "d": "1e2x", "e": 31, "f": 1000}


def test_a_parameter_file_with_exponent_values_loads(tmp_path):
    text = (ROOT / "config" / "otbot.yaml").read_text()
    assert "m_c: {value: 109.14, unit: kg}" in text
    p = tmp_path / "p.yaml"
    p.write_text(text.replace("m_c: {value: 109.14, unit: kg}", "m_c: {value: 1.0914e2, unit: kg}"))
    assert OtbotParams.load(p).m_c == pytest.approx(109.14)
    p.write_text(text.replace("m_c: {value: 109.14, unit: kg}", "m_c: {value: 1e400, unit: kg}"))
    with pytest.raises(ParameterError, match="m_c: value must be finite"):
        OtbotParams.load(p)


def test_a_key_written_twice_is_an_error_naming_both_lines(tmp_path):
    p = tmp_path / "p.yaml"
    p.write_text("chassis:\n  m_c: {value: 109.14, unit: kg}\n  I_c: {value: 1.3, unit: kg m^2}\n"
                 "  m_c: {value: 5, unit: kg}\n")
    with pytest.raises(ParameterError) as err:
        read_yaml(p, "parameter file")
    assert str(err.value) == f"{p}: parameter file: key 'm_c' is written twice (line 2 and line 4); keys must be unique"
    # the same key in two mappings, and a merge key's override, are no duplicates
    assert parse_yaml("a: {x: 1}\nb: {x: 2}\n") == {"a": {"x": 1}, "b": {"x": 2}}
    assert parse_yaml("base: &b {x: 1, y: 2}\nc:\n  <<: *b\n  x: 3\n")["c"] == {"x": 3, "y": 2}


def test_every_configuration_reader_uses_the_same_rules(tmp_path):
    """robot.yaml's sections (motors, safety, estimator, drivers) are read through the same loader."""
    from drivers.config import load_robot_config
    from otbot_hw.motors import load_motor_limits
    from otbot_hw.runtime.supervisor import SafetyConfig

    text = (ROOT / "config" / "robot.yaml").read_text()
    for eds in (ROOT / "config").glob("*.eds"):
        (tmp_path / eds.name).write_text(eds.read_text())
    cfg = tmp_path / "robot.yaml"
    assert "  channel: can0\n" in text
    cfg.write_text(text.replace("  channel: can0\n", "  channel: can0\n  channel: can1\n", 1))
    for load in (load_robot_config, load_motor_limits, SafetyConfig.load):
        with pytest.raises(ParameterError, match=r"key 'channel' is written twice \(line \d+ and line \d+\)"):
            load(cfg)


def test_a_ros2_map_is_read_with_the_same_rules(tmp_path):
    from otbot_hw.ros2 import BagError
    from otbot_hw.ros2.mapping import load_map

    m = tmp_path / "map.yaml"
    m.write_text("torque:\n  scale: 1e0\n  scale: 2.0\n")
    with pytest.raises(BagError, match=rf"--map {m}: map file: key 'scale' is written twice \(line 2 and line 3\)"):
        load_map(m)


def test_an_oversized_yaml_is_refused_before_it_is_read(tmp_path):
    p = tmp_path / "huge.yaml"
    with open(p, "wb") as f:  # sparse: 300 MB long, nothing on disk
        f.write(b"geometry:\n")
        f.truncate(300 * 1024 * 1024)
    t0 = time.monotonic()
    with pytest.raises(ParameterError, match="a parameter file is at most 4 MiB, this file is 300 MiB"):
        OtbotParams.load(p)
    assert time.monotonic() - t0 < 10.0  # generous: it is refused from its size, not parsed for minutes


# -- CSV: a byte-order mark (what spreadsheets save) -------------------------------------------------
def test_a_trajectory_csv_with_a_byte_order_mark_loads(tmp_path):
    from otbot_hw.control.sampled_trajectory import csv_table, load_csv

    body = "# obstacle: 1, 0.5, 0.2\nt,x,y,alpha\n0,0,0,0\n2,1,0,0.5\n"
    plain, bom = tmp_path / "plain.csv", tmp_path / "bom.csv"
    plain.write_text(body)
    bom.write_bytes(b"\xef\xbb\xbf" + body.encode())
    a, b = load_csv(plain), load_csv(bom)
    np.testing.assert_array_equal(a.P_samples, b.P_samples)
    assert b.obstacles == [(1.0, 0.5, 0.2)]
    bom.write_bytes(b"\xef\xbb\xbft,x,y,alpha\n0,0,0,0\n2,1,0,0.5\n")
    np.testing.assert_array_equal(load_csv(bom).P_samples, a.P_samples)
    # every CSV reader's table (the open-loop torque files too)
    header, rows = csv_table(bom, "\ufefft,tau_r,tau_l,tau_p\n0,1,2,3\n", ["t", "tau_r"])
    assert header == ["t", "tau_r", "tau_l", "tau_p"] and rows == [["0", "1", "2", "3"]]



def test_a_csv_naming_a_column_twice_is_refused_by_every_csv_reader(tmp_path):
    """'t,x,y,alpha,x' was read with the first x, silently; the torque files of ctl excite share the reader."""
    from otbot_hw.control.sampled_trajectory import load_csv
    from otbot_hw.control.trajectories import TrajectoryError
    from otbot_hw.runtime.openloop import TorqueSequenceError, load_torque_sequence

    traj, torques = tmp_path / "traj.csv", tmp_path / "torques.csv"
    traj.write_text("t,x,y,alpha,x\n0,0,0,0,1\n2,0.5,0,0,1\n")
    torques.write_text("t,tau_r,tau_l,tau_p,tau_l\n0,1,2,3,4\n1,1,2,3,4\n")
    with pytest.raises(TrajectoryError, match=r"traj.csv: column x is named twice in the header \(columns 2 and 5\)"):
        load_csv(traj)
    with pytest.raises(TorqueSequenceError, match=r"column tau_l is named twice in the header \(columns 3 and 5\)"):
        load_torque_sequence(torques)
    torques.write_text("t,tau_r,tau_l,tau_p,note,note\n0,1,2,3,a,b\n1,1,2,3,a,b\n")  # an ignored column too
    with pytest.raises(TorqueSequenceError, match="column note is named twice"):
        load_torque_sequence(torques)
    torques.write_text("t,tau_r,tau_l,tau_p,,\n0,1,2,3,,\n1,1,2,3,,\n")  # empty names (trailing commas) are no names
    assert load_torque_sequence(torques)[1].shape == (2, 3)



def test_export_refuses_to_replace_the_bag_that_holds_its_recording(tmp_path, otbot_cli):
    """An earlier bag at --ros2 is replaced (removed once the new one is complete): a recording kept inside it
    went with it, after exit 0."""
    from otbot_hw.recording import write_recording
    from otbot_hw.sensors import NoiseModel
    from otbot_hw.simulation.runs import simulated_recording

    run, bag = tmp_path / "run.mcap", tmp_path / "bag"
    write_recording(run, simulated_recording(nominal(), np.tile([2.0, 2.0, 0.0], (20, 1)), 0.01, NoiseModel.paper()))
    assert otbot_cli(["export", str(run), "--ros2", str(bag), "--json"])[0] == 0
    inside = bag / "run.mcap"
    inside.write_bytes(run.read_bytes())
    rc, out, err = otbot_cli(["export", str(inside), "--ros2", str(bag)])
    assert rc == 2 and out == "" and err.count("\n") == 1, err
    assert f"--ros2 {bag}: holds the recording {inside}; replacing the folder would remove it" in err
    assert inside.read_bytes() == run.read_bytes()



@pytest.mark.skipif(os.geteuid() != 0, reason="making a device node needs root")
def test_an_output_that_is_a_device_is_written_as_it_is_never_replaced(tmp_path, otbot_cli):
    """simulate and import write their recording beside --out and rename it over --out when complete; a
    device (here a node equal to /dev/null, made in tmp_path) is written as it is: a rename as root would have
    put a regular file in the device's place."""
    import stat

    from otbot_hw.recording import read_recording, write_recording
    from otbot_hw.ros2.bag_export import export_recording
    from otbot_hw.sensors import NoiseModel
    from otbot_hw.simulation.runs import simulated_recording

    null = tmp_path / "null"
    os.mknod(null, stat.S_IFCHR | 0o666, os.makedev(1, 3))
    run, bag = tmp_path / "run.mcap", tmp_path / "bag"
    write_recording(run, simulated_recording(nominal(), np.tile([2.0, 2.0, 0.0], (20, 1)), 0.01, NoiseModel.paper()))
    export_recording(read_recording(run), bag)
    for argv in (["simulate", "--duration", "0.1", "--out", str(null), "--json"],
                 ["import", str(bag), "--out", str(null), "--json"]):
        rc, out, err = otbot_cli(argv)
        assert rc == 0, err
        assert stat.S_ISCHR(os.stat(null).st_mode), argv          # still the device
        assert not list(tmp_path.glob(".null.tmp-*"))             # nothing left beside it


@pytest.mark.parametrize("argv, what", [
    ("simulate --duration 0.01 --out config/otbot.yaml", "is the parameter file itself"),
    ("identify chassis --sim --out config/otbot.yaml", "is the parameter file itself"),
    ("estimate {run} --out config/robot.yaml", "is the configuration file itself"),
    ("track corridor --sim --out config/robot.yaml", "is the hardware configuration itself"),
    ("plan --out config/otbot.yaml", "is the parameter file itself"),
])
def test_an_output_may_not_replace_the_default_configuration_it_reads(argv, what, tmp_path, otbot_cli, monkeypatch):
    """config/otbot.yaml and config/robot.yaml are read when --params / --config are not given: inputs too."""
    from otbot_hw.recording import write_recording
    from otbot_hw.sensors import NoiseModel
    from otbot_hw.simulation.runs import simulated_recording

    run = tmp_path / "run.mcap"
    write_recording(run, simulated_recording(nominal(), np.tile([2.0, 2.0, 0.0], (20, 1)), 0.01, NoiseModel.paper()))
    monkeypatch.chdir(ROOT)
    kept = {name: (ROOT / "config" / name).read_bytes() for name in ("otbot.yaml", "robot.yaml")}
    try:
        rc, out, err = otbot_cli(argv.format(run=run).split())
    finally:  # a regression must not leave the project's configuration replaced
        changed = [n for n, data in kept.items() if (ROOT / "config" / n).read_bytes() != data]
        for n in changed:
            (ROOT / "config" / n).write_bytes(kept[n])
    assert not changed
    assert rc == 2 and out == "" and err.count("\n") == 1 and "--out config/" in err and what in err, err


# -- track: sizes checked before work, long phases say where they are -------------------------------
def test_the_feasibility_check_works_in_chunks_says_where_it_is_and_refuses_beyond_its_size(monkeypatch):
    from otbot_hw.control import feasibility
    from otbot_hw.control.gains import gains_from_tstab
    from otbot_hw.control.sampled_trajectory import SampledTrajectory
    from otbot_hw.motors import load_motor_limits

    ref = SampledTrajectory(np.array([0.0, 2.0, 5.0]), np.array([[0, 0, 0], [1.0, 0.5, 0.3], [2.0, 0, 0]]))
    g, lim = gains_from_tstab(3.0), load_motor_limits()
    whole = feasibility.check_feasibility(ref, nominal(), g, lim)
    n = len(whole.t)
    monkeypatch.setattr(feasibility, "CHUNK", 97)
    said: list[str] = []
    parts = feasibility.check_feasibility(ref, nominal(), g, lim, progress=said.append)
    np.testing.assert_array_equal(parts.lo, whole.lo)
    np.testing.assert_array_equal(parts.hi, whole.hi)
    assert parts.violations == whole.violations
    assert len(said) == 3 and all(f"of {n} points" in s for s in said), said
    monkeypatch.setattr(feasibility, "MAX_POINTS", n - 1)
    called = []
    monkeypatch.setattr(feasibility, "reference_states", lambda *a, **k: called.append(1))
    with pytest.raises(ValueError, match=f"needs {n} feasibility points every 0.01 s; at most {n - 1}"):
        feasibility.check_feasibility(ref, nominal(), g, lim)
    assert not called  # refused before any work


def test_track_refuses_a_long_csv_before_the_feasibility_check(tmp_path, otbot_cli, monkeypatch):
    from otbot_hw.control import feasibility

    csv = tmp_path / "long.csv"
    csv.write_text("t,x,y,alpha\n0,0,0,0\n100000,0,0,0\n")
    monkeypatch.setattr(feasibility, "torque_enclosure", lambda *a, **k: pytest.fail("the check started"))
    for argv in ([str(csv), "--sim"], [str(csv), "--sim", "--rate", "50"], ["corridor", "--sim", "--rate", "1e9"]):
        rc, out, err = otbot_cli(["track", *argv])
        assert rc == 2 and out == "" and err.count("\n") == 1 and "at most" in err, err


# -- identify: one recording counts once -------------------------------------------------------------
def test_identify_refuses_a_recording_given_twice_by_content(tmp_path, otbot_cli):
    from otbot_hw.recording import write_recording
    from otbot_hw.sensors import NoiseModel
    from otbot_hw.simulation.runs import simulated_recording

    a = tmp_path / "a.mcap"
    write_recording(a, simulated_recording(nominal(), np.tile([6.0, -10.0, 6.0], (20, 1)), 0.01, NoiseModel.paper()))
    b = tmp_path / "b.mcap"
    b.write_bytes(a.read_bytes())
    link = tmp_path / "link.mcap"
    link.symlink_to(a)
    for pair, said in (((a, b), f"{b}: has the same content as {a}"), ((a, link), f"{link}: has the same content"),
                       ((a, a), f"{a}: is named twice")):
        rc, out, err = otbot_cli(["identify", "chassis", "--recording", *map(str, pair)])
        assert rc == 2 and said in err and "counts once" in err, err


# -- bench --resume: a passed step's recording cut short since ---------------------------------------
def _session_with_a_passed_wheel_step(folder: Path, cut: bool) -> Path:
    from otbot_hw.recording import write_recording
    from otbot_hw.runtime.bench.session import SessionFolder
    from otbot_hw.sensors import NoiseModel
    from otbot_hw.simulation.runs import simulated_recording

    s = SessionFolder.create(folder, {"bus": "sim"}, {"steps": ["wheel"], "excitation": "paper", "attempts": 3,
                                                       "params_start": nominal().to_dict(),
                                                       "noise": NoiseModel.paper().to_dict()})
    att = s.new_attempt("wheel")
    path = s.recording_path("wheel", att["attempt"])
    write_recording(path, simulated_recording(nominal(), np.tile([2.0, 2.0, 0.0], (200, 1)), 0.01, NoiseModel.paper()))
    if cut:
        data = path.read_bytes()
        path.write_bytes(data[:len(data) // 2])
    att["recording"] = s.rel(path)
    s.set_status("wheel", "passed", att)
    return path


@pytest.mark.parametrize("cut", [True, False])
def test_bench_resume_says_when_a_passed_steps_recording_was_truncated(tmp_path, otbot_cli, monkeypatch, cut):
    from otbot_hw.cli import bench

    path = _session_with_a_passed_wheel_step(tmp_path / "s", cut)
    monkeypatch.setattr(bench, "_run", lambda *a, **k: {})  # what comes after is the procedure's own tests
    rc, out, err = otbot_cli(["bench", "--resume", str(tmp_path / "s"), "--yes", "--json", "--no-diagnose"])
    assert rc == 0, err
    notices = [line for line in err.splitlines() if "notice" in line]
    if cut:
        assert len(notices) == 1 and f"step wheel: {path} is truncated" in notices[0], err
        assert "complete samples; fitting those" in notices[0]
    else:
        assert notices == []


def test_estimate_says_a_truncated_recording_is_truncated(tmp_path, otbot_cli):
    """As identify and export do: a notice line when complete samples are left, an error naming the file when
    fewer than two are (estimate said nothing, or "fewer than 2 samples" without the file)."""
    from otbot_hw.recording import write_recording
    from otbot_hw.sensors import NoiseModel
    from otbot_hw.simulation.runs import simulated_recording

    full = tmp_path / "full.mcap"
    write_recording(full, simulated_recording(nominal(), np.tile([2.0, 2.0, 0.0], (200, 1)), 0.01, NoiseModel.paper()))
    data = full.read_bytes()
    cut, short = tmp_path / "cut.mcap", tmp_path / "short.mcap"
    cut.write_bytes(data[:len(data) // 2])
    short.write_bytes(data[:data.index(b'{"t": 0.01') + 5])  # inside sample 1: one complete sample
    rc, out, err = otbot_cli(["estimate", str(cut), "--json"])
    assert rc == 0, err
    notices = [line for line in err.splitlines() if "notice" in line]
    assert len(notices) == 1 and f"[estimate] notice: {cut} is truncated (the writer stopped" in notices[0], err
    assert notices[0].endswith("complete samples; estimating on those")
    assert json.loads(out)["truncated"] is True
    rc, out, err = otbot_cli(["estimate", str(full), "--json"])
    assert rc == 0 and "notice" not in err and json.loads(out)["truncated"] is False
    rc, out, err = otbot_cli(["estimate", str(short)])
    assert rc == 2 and out == "" and err.count("\n") == 1, err
    assert f"{short} is truncated (the writer stopped before closing it): it ends at t = 0 s after 1 complete " \
           "sample: nothing to estimate" in err


# -- plan: Ctrl-C is an interrupt ----------------------------------------------------------------------
@pytest.mark.parametrize("chain, code", [
    ("system_from_interrupt", 130),   # numba: "CPUDispatcher(...) returned a result with an exception set"
    ("system_from_system_from_interrupt", 130),
    ("system_alone", None),           # a real SystemError stays a traceback (a bug to see)
    ("system_from_value", None),
])
def test_ctrl_c_inside_a_compiled_call_is_an_interruption(chain, code, monkeypatch, capsys):
    """Ctrl-C while a numba call runs surfaces as SystemError caused by the KeyboardInterrupt (seen once in
    15 interrupted ``diagnose --demo`` runs: exit 1 with a traceback); the entry point treats it as Ctrl-C."""
    import otbot_hw.cli.simulate as sim_cli
    from otbot_hw.cli import main

    def run(args):
        if chain == "system_alone":
            raise SystemError("bad internal call")
        inner = KeyboardInterrupt() if "interrupt" in chain else ValueError("x")
        try:
            raise inner
        except BaseException as k:
            if chain == "system_from_system_from_interrupt":
                try:
                    raise SystemError("inner") from k
                except SystemError as s:
                    raise SystemError("outer") from s
            raise SystemError("CPUDispatcher(<f>) returned a result with an exception set") from k

    monkeypatch.setattr(sim_cli, "run", run)
    if code is None:
        with pytest.raises(SystemError):
            main(["simulate", "--duration", "0.01"])
        return
    assert main(["simulate", "--duration", "0.01"]) == 130
    assert capsys.readouterr().err == "otbot simulate: interrupted\n"


def test_plan_interrupted_inside_ipopt_exits_130(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "otbot_hw", "plan", "--out", str(tmp_path / "p.csv"),
                             "--intervals", "400"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env, start_new_session=True)
    try:
        lines = []
        while not lines or "IPOPT:" not in lines[-1]:  # the solver starts after this line
            line = proc.stderr.readline()
            assert line, f"plan ended before IPOPT started: {lines}"
            lines.append(line)
        time.sleep(0.3)
        os.kill(proc.pid, signal.SIGINT)
        err = proc.stderr.read()
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    if proc.returncode == 0:
        pytest.skip("IPOPT finished before the interrupt arrived (a very fast machine)")
    assert proc.returncode == 130, err
    assert err.strip().splitlines()[-1] == "otbot plan: interrupted" and "did not converge" not in err
    assert not (tmp_path / "p.csv").exists()


# -- plant: a bad stdin line gets an error and the plant runs on -----------------------------------
def test_plant_answers_a_bad_flood_line_with_an_error_and_runs_on():
    from drivers.config import load_robot_config
    from sim.plant_process import serve

    out = io.StringIO()
    lines = ["flood x y", "flood -1 0", "flood 3 -1", "flood 1" + "0" * 5000 + " 1", "flood", "flood 1 2 3",
             "flood 2 1", "report"]
    serve(load_robot_config(), "slcan", with_imu=False, out=out, commands=[f"{x}\n" for x in lines])
    replies = [json.loads(x) for x in out.getvalue().splitlines()]
    assert "can_channel" in replies[0]
    for line, r in zip(lines[:6], replies[1:7]):
        assert isinstance(r, dict) and "flood N SEED" in r["error"], (line, r)
    assert replies[7] == 2                        # the good flood after the bad ones
    assert replies[8]["drives"] and len(replies) == 9


# -- estimate: a write that fails says so in one line -------------------------------------------------
def test_estimate_to_a_full_device_is_one_line(tmp_path, otbot_cli):
    if not os.path.exists("/dev/full"):
        pytest.skip("no /dev/full")
    from otbot_hw.recording import write_recording
    from otbot_hw.sensors import NoiseModel
    from otbot_hw.simulation.runs import simulated_recording

    a = tmp_path / "a.mcap"
    write_recording(a, simulated_recording(nominal(), np.tile([6.0, -10.0, 6.0], (50, 1)), 0.01, NoiseModel.paper()))
    rc, out, err = otbot_cli(["estimate", str(a), "--out", "/dev/full"])
    assert rc == 2 and out == ""
    assert err == "otbot estimate: error: cannot write /dev/full: No space left on device\n"
