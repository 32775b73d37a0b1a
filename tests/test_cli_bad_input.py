"""Every subcommand on bad input: exit code 2, exactly one line on stderr, no traceback, nothing on stdout.

``BAD_INPUT`` is the table: one row per case, ``(command, argv, expected part of the message)``; argv
may name the files of the ``files`` fixture as ``{ok}``, ``{missing}`` ... (see ``files``). A row
whose command is not registered (a subcommand another branch adds) is skipped, so rows can be
added before the command lands; ``test_unknown_option_names_the_subcommand_usage`` covers every
registered command automatically. Most rows run in-process through ``otbot_hw.cli.main``; a few
run the real ``python -m otbot_hw`` to show the console entry point behaves the same.
"""
from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from otbot_hw.cli import SUBCOMMANDS, build_parser
from otbot_hw.params import nominal
from otbot_hw.recording import write_recording
from otbot_hw.sensors import NoiseModel
from otbot_hw.simulation.runs import simulated_recording

ROOT = Path(__file__).resolve().parents[1]

BAD_INPUT = [
    # --- demo
    ("demo", "--seed -1", "argument --seed: must be an integer >= 0, got '-1'"),
    ("demo", "--seed 1.5", "argument --seed: must be an integer >= 0"),
    ("demo", "--out-dir {ok}", "exists and is not a folder"),
    ("demo", "--out-dir {missing}/demo", "does not exist (otbot creates no parent folders)"),
    # --- simulate
    ("simulate", "--duration nan", "argument --duration: must be a finite number of seconds > 0, got 'nan'"),
    ("simulate", "--duration inf", "argument --duration: must be a finite number of seconds > 0"),
    ("simulate", "--duration 0", "argument --duration: must be a finite number of seconds > 0"),
    ("simulate", "--duration -1", "argument --duration: must be a finite number of seconds > 0"),
    ("simulate", "--duration 3s", "argument --duration: must be a finite number of seconds > 0"),
    ("simulate", "--rate inf", "argument --rate: must be a finite number of Hz > 0"),
    ("simulate", "--torques 1,x,3", "--torques: 'x' is not a number"),
    ("simulate", "--torques 1,nan,3", "--torques: values must be finite"),
    ("simulate", "--torques 1e9,0,0 --duration 0.1 --out {tmp}/diverged.mcap",
     "the simulation diverged: the state is not finite from t = 0.01 s"),
    ("simulate", "--seed -3", "argument --seed: must be an integer >= 0"),
    ("simulate", "--params {missing}/p.yaml", "cannot read parameter file: No such file or directory"),
    ("simulate", "--params {ok}", "not a text file"),
    ("simulate", "--params {folder}", "cannot read parameter file"),
    ("simulate", "--params {unreadable}", "Permission denied"),
    ("simulate", "--out {missing}/run.mcap", "folder {missing} does not exist"),
    ("simulate", "--out {ok}/run.mcap", "is not a folder"),
    ("simulate", "--out {folder}", "is a folder; give a file name"),
    ("simulate", "--plot {ok}", "exists and is not a folder"),
    # --- identify
    ("identify", "chassis --sim --seed -3", "argument --seed: must be an integer >= 0, got '-3'"),
    ("identify", "chassis --sim --deviation nan", "argument --deviation: must be a finite number"),
    ("identify", "chassis --sim --deviation -5", "argument --deviation: must be a finite number >= 0 and <= 1000"),
    ("identify", "chassis --sim --load -5@0,0", "--load mass must be >= 0 kg, got -5"),
    ("identify", "chassis --sim --load 5@inf,0", "--load position: values must be finite"),
    ("identify", "chassis --sim --guess m_c=-5", "guess m_c = -5 kg lies outside its bounds"),
    ("identify", "chassis --sim --guess m_c=heavy", "--guess m_c: 'heavy' is not a number"),
    ("identify", "chassis --sim --guess m_p=5", "step chassis estimates m_c, I_c, x_B, y_B"),
    ("identify", "chassis --recording {missing}/a.mcap", "no such file"),
    ("identify", "chassis --recording {ok} {missing}/b.mcap", "b.mcap: no such file"),
    ("identify", "chassis --recording {empty}", "empty file, expected an MCAP recording"),
    ("identify", "chassis --recording {text}", "not an MCAP recording (the file does not start with the MCAP magic"),
    ("identify", "chassis --recording {folder}", "is a folder, expected an MCAP recording file"),
    ("identify", "chassis --recording {unreadable}", "cannot read: Permission denied"),
    ("identify", "chassis --recording {cut_before_samples}", "truncated"),
    ("identify", "wheel --recording {ok}", "recording was made on the 'floor' fixture, step wheel needs 'stand'"),
    ("identify", "chassis --sim --out {missing}/p.yaml", "does not exist"),
    ("identify", "chassis --sim --plot {ok}", "exists and is not a folder"),
    ("identify", "chassis --sim --params {binary_yaml}", "not a text file"),
    ("identify", "chassis", "one of the arguments --recording --sim is required"),
    # --- sweep
    ("sweep", "--points 0", "argument --points: must be an integer >= 1, got '0'"),
    ("sweep", "--points many", "argument --points: must be an integer >= 1"),
    ("sweep", "--seeds -2", "argument --seeds: must be an integer >= 1"),
    ("sweep", "--max-deviation nan", "argument --max-deviation: must be a finite number > 0 and <= 1000"),
    ("sweep", "--max-deviation 0", "argument --max-deviation: must be a finite number > 0"),
    ("sweep", "--workers 0", "argument --workers: must be an integer >= 1"),
    ("sweep", "--load heavy", "--load must look like KG@X,Y or KG@X,Y,I"),
    ("sweep", "--plot {ok}", "exists and is not a folder"),
    ("sweep", "--local-only --global-start", "not allowed with argument"),
    ("sweep", "--guess m_p=5", "unrecognized arguments: --guess"),
    # --- diagnose (generic input errors only; its own checks are tested with it)
    # --- estimate
    ("estimate", "{missing}/a.mcap", "no such file"),
    ("estimate", "{text}", "not an MCAP recording"),
    ("estimate", "{folder}", "is a folder"),
    ("estimate", "{ok} --out {missing}/est.mcap", "does not exist (otbot creates no parent folders)"),
    ("estimate", "{ok} --prediction kalman", "invalid choice"),
    # --- ctl (checked before any daemon is asked)
    ("ctl", "velocity nan 0 0", "VX must be finite"),
    ("ctl", "velocity 0 0", "the following arguments are required: WZ"),
    ("ctl", "record pause", "invalid choice"),
    ("diagnose", "{missing}/a.mcap", "no such file"),
    ("diagnose", "{text}", "not an MCAP recording"),
    ("diagnose", "{ok} --report {ok}", "exists and is not a folder"),
    ("diagnose", "--demo --demo-dir {missing}/demo", "does not exist (otbot creates no parent folders)"),
    # --- imu
    ("imu", "parse {missing}/capture.bin", "cannot read: No such file or directory"),
    ("imu", "parse {folder}", "is a directory"),
    ("imu", "parse {ok} --limit -1", "argument --limit: must be an integer >= 0"),
    ("imu", "parse {ok} --limit x", "argument --limit: must be an integer >= 0"),
    ("imu", "read --duration 0", "argument --duration: must be a finite number of seconds > 0"),
    ("imu", "read --duration nan", "argument --duration: must be a finite number of seconds > 0"),
    ("imu", "read --sim --seed -1", "argument --seed: must be an integer >= 0"),
    ("imu", "read --port {missing}/ttyUSB0", "cannot open"),
    ("imu", "read --config {binary_yaml}", "not a text file"),
    ("imu", "", "the following arguments are required: ACTION"),
    # --- track
    ("track", "{binary_csv} --sim", "not a text file; a trajectory is a CSV text file"),
    ("track", "{ok} --sim", "not a text file"),
    ("track", "{missing}/traj.csv --sim", "unknown scenario"),
    ("track", "corridor --sim --tstab nan", "--tstab: values must be finite"),
    ("track", "corridor --sim --tstab -1", "--tstab needs 1 or 3 numbers of seconds > 0"),
    ("track", "corridor --sim --rate 0", "argument --rate: must be a finite number of Hz > 0"),
    ("track", "corridor --sim --animate {missing}/a.gif", "does not exist"),
    ("track", "corridor --sim --animate {tmp}/a.png", "the file name must end in .gif"),
    ("track", "corridor --sim --plot {ok}", "exists and is not a folder"),
    ("track", "corridor --sim --params {ok}", "not a text file"),
    ("track", "corridor --sim --error-bounds 1,2", "--error-bounds needs 6 comma-separated numbers"),
    ("track", "corridor --sim --fixes 0", "argument --fixes: must be a finite number of Hz > 0"),
    ("track", "corridor --sim --fixes 1 --feedback truth", "--fixes feeds the EKF: use --feedback ekf"),
    ("track", "corridor --bus config --fixes 1", "act on a simulated robot (--sim, --bus sim)"),
    ("track", "corridor --sim --fixes 1 --fix-std 0.002,0,0.002", "--fix-std needs 3 numbers > 0"),
    ("track", "corridor --sim --slip-burst 2:0.3", "--slip-burst needs T0:DURATION:K_SLIP"),
    ("track", "corridor --sim --slip-burst 2:-1:0.05", "DURATION > 0 s"),
    # --- plan
    ("plan", "--out {missing}/p.csv", "folder {missing} does not exist"),
    ("plan", "--out {folder}", "is a folder; give a file name"),
    ("plan", "--out {tmp}/p.csv --duration nan", "argument --duration: must be a finite number of seconds > 0"),
    ("plan", "--out {tmp}/p.csv --duration -1", "argument --duration: must be a finite number of seconds > 0"),
    ("plan", "--out {tmp}/p.csv --intervals x", "argument --intervals: must be an integer >= 4 and <= 400"),
    ("plan", "--out {tmp}/p.csv --intervals 2", "argument --intervals: must be an integer >= 4"),
    ("plan", "--out {tmp}/p.csv --max-speed inf", "argument --max-speed: must be a finite number > 0"),
    ("plan", "--out {tmp}/p.csv --clearance -0.1", "argument --clearance: must be a finite number >= 0"),
    ("plan", "--out {tmp}/p.csv --start 1,2", "--start needs 3 comma-separated numbers"),
    ("plan", "--out {tmp}/p.csv --start -1,0,nan", "--start: values must be finite"),
    ("plan", "--out {tmp}/p.csv --obstacle 1,2,nan", "--obstacle: values must be finite"),
    ("plan", "--out {tmp}/p.csv --goal 3,3,0", "goal y = 3 m puts the footprint outside the walls"),
    ("plan", "", "the following arguments are required: --out"),
    # --- run
    ("run", "--duration 0", "argument --duration: must be a finite number of seconds > 0"),
    ("run", "--duration nan", "argument --duration: must be a finite number of seconds > 0"),
    ("run", "--duration 1e9", "samples; at most"),
    ("run", "--rate -1", "argument --rate: must be a finite number of Hz > 0"),
    ("run", "--rate 0.3", "cannot be written as 0x60C2"),
    ("run", "--seed -1", "argument --seed: must be an integer >= 0"),
    ("run", "--torques nan,0,0", "--torques: values must be finite"),
    ("run", "--out {missing}/r.mcap", "folder {missing} does not exist"),
    ("run", "--plot {ok}", "exists and is not a folder"),
    ("run", "--bus config --imu-port {missing}/ttyUSB0", "cannot open"),
    ("run", "--config {binary_yaml}", "not a text file"),
    # --- plant
    ("plant", "--seed -1", "argument --seed: must be an integer >= 0"),
    ("plant", "--rate 0", "argument --rate: must be a finite number of Hz > 0"),
    ("plant", "--rate 0.5", "cannot be written as 0x60C2"),
    ("plant", "--config {binary_yaml}", "not a text file"),
    ("plant", "--transport socketcan --channel otbot-no-such-can", "cannot open the CAN interface"),
    # --- bench (checked before the bus opens; the sensors' and the data's verdicts are in test_bench.py)
    ("bench", "--steps wheel,moon", "--steps: unknown step(s) moon (known: wheel, pivot, chassis, platform)"),
    ("bench", "--steps wheel,wheel", "--steps: a step is named twice"),
    ("bench", "--session {tmp}/a --resume {tmp}/b", "give --session DIR for a new session or --resume DIR"),
    ("bench", "--resume {missing}", "--resume {missing}: no such session folder"),
    ("bench", "--resume {folder}", "not a bench session (no session.json)"),
    ("bench", "--resume {folder} --excitation designed", "--excitation: --resume continues the session with the "
                                                         "settings it was started with"),
    ("bench", "--session {ok}", "exists and is not a folder"),
    ("bench", "--session {missing}/s", "does not exist (otbot creates no parent folders)"),
    ("bench", "--rate 200", "the bench runs at 100 Hz, the paper's sampling"),
    ("bench", "--bus config --sim-load 5@0,0", "--sim-params and --sim-load set the simulated robot"),
    ("bench", "--sim-load heavy", "--sim-load must look like KG@X,Y or KG@X,Y,I"),
    ("bench", "--sim-load -5@0,0", "--sim-load mass must be >= 0 kg"),
    ("bench", "--sim-load 5@0.9,0", "the load at (0.9, 0) m is off the platform (radius 0.5 m)"),
    ("bench", "--sim-params {binary_yaml}", "not a text file"),
    ("bench", "--params {missing}/p.yaml", "cannot read parameter file"),
    ("bench", "--free-area 0", "argument --free-area: must be a finite number of m > 0"),
    ("bench", "--attempts 0", "argument --attempts: must be an integer >= 1"),
    ("bench", "--excitation random", "invalid choice"),
    ("bench", "--out {missing}/p.yaml", "does not exist"),
    ("bench", "--report {ok}", "exists and is not a folder"),
    ("bench", "--config {binary_yaml}", "not a text file"),
    # --- issue 22: hangs and silent wrong answers
    ("track", "corridor --sim --rate 1e9", "trajectory corridor lasts 30 s: at 1e+09 Hz that is 30000000000 samples; "
                                           "at most 10000000"),
    ("track", "{long_csv} --sim", "samples; at most 10000000 (lower --rate or shorten the trajectory)"),
    ("track", "{dup_column_csv} --sim", "dup_column.csv: column x is named twice in the header (columns 2 and 5)"),
    ("track", "{long_csv} --sim --rate 50", "its torque-feasibility check would bound"),
    ("simulate", "--params {dup_yaml}", "key 'm_c' is written twice (line 14 and line 15); keys must be unique"),
    ("simulate", "--params {huge_yaml}", "a parameter file is at most 4 MiB, this file is 300 MiB"),
    ("track", "corridor --sim --config {dup_robot}", "key 'channel' is written twice (line 11 and line 12)"),
    # each value passes its own rule, together they make the model singular (numba divided by zero)
    ("simulate", "--params {singular_yaml}", "these parameters make the model singular"),
    ("simulate", "--params {overflow_yaml}", "largest m_c = 1e+308 kg"),
    ("track", "corridor --sim --params {singular_yaml}", "these parameters make the model singular"),
    ("plan", "--out {tmp}/p.csv --params {singular_yaml}", "these parameters make the model singular"),
    ("identify", "chassis --recording {ok} --params {singular_yaml}", "these parameters make the model singular"),
    ("identify", "platform --sim --load 1e30@0,0", "--load: the loaded robot: these parameters make the model singular"),
    ("sweep", "--load 1e30@0,0", "--load: the loaded robot: these parameters make the model singular"),
    ("identify", "chassis --recording {ok} {ok}", "--recording {ok}: is named twice; each recording counts once"),
    ("identify", "chassis --recording {ok} {ok_copy}", "--recording {ok_copy}: has the same content as {ok}"),
    ("diagnose", "{ok} {ok}", "recording {ok}: is named twice; each recording counts once"),
    ("diagnose", "{ok} --holdout {ok_copy}", "recording {ok_copy}: has the same content as {ok}"),
    ("run", "--bus sim --duration 1 --inject bus-off@1e9", "--inject bus-off@1e9: 1e+09 s is outside the run (1 s"),
    ("estimate", "{ok} --out /dev/full", "cannot write /dev/full: No space left on device"),
    # --- numbers that overflow: a one-line refusal, never an OverflowError or a 300-digit count
    ("simulate", "--duration 1e308", "--duration 1e+308 s at 100 Hz gives inf samples; at most 10000000"),
    ("simulate", "--rate 1e308 --duration 1", "gives 1e+308 samples; at most 10000000"),
    ("simulate", "--duration 1e300", "gives 1e+302 samples; at most 10000000"),
    ("run", "--bus sim --duration 1e308", "gives inf samples; at most 10000000"),
    ("run", "--bus sim --duration 1 --rate 1e-320", "control period inf s cannot be written as 0x60C2"),
    ("plant", "--rate 1e-320", "cannot be written as 0x60C2"),
    ("track", "corridor --sim --rate 1e308", "at 1e+308 Hz that is inf samples; at most 10000000"),
    ("track", "corridor --sim --rate 1e300", "at 1e+300 Hz that is 3e+301 samples; at most 10000000"),
    ("track", "{close_csv} --sim --no-robustness", "lines 2 and 3 are 1e-160 s apart (t = 0 s, 1e-160 s); rows must "
                                                   "be at least 1e-06 s apart"),
    ("track", "{denormal_csv} --sim --no-robustness", "lines 2 and 3 are 1e-320 s apart"),
    ("track", "{far_csv} --sim --no-robustness", "line 3, column x: 1e+300 is beyond 1e+06"),
    ("estimate", "{ok} --config {sigma_robot}", "estimator.encoder_rate_sigma must be at most 1e+06 rad/s (its "
                                                "square enters the covariance), got 1e+160"),
    ("estimate", "{ok} --config {window_robot}", "estimator.walk_adaptation_window must be 0 (off) or at least "
                                                 "0.001 s"),
    ("simulate", "--torques 1e308,0,0 --duration 0.1", "the simulation diverged: the state is not finite from "
                                                       "t = 0.01 s (sample 1)"),
    ("plan", "--out {tmp}/p.csv --intervals 8 --goal 1e308,0,0", "the goal is 1e+308 m from the start: at the largest "
                                                                 "pivot speed 1 m/s (--max-speed) that takes at least"),
    ("plan", "--out {tmp}/p.csv --intervals 8 --duration 1e-320", "--duration 9.99989e-321 s is outside the planner's "
                                                                   "range [1, 60] s"),
    ("plan", "--out {tmp}/p.csv --intervals 8 --duration 1e308", "--duration 1e+308 s is outside the planner's range"),
    ("plan", "--out {tmp}/p.csv --intervals 8 --duration 60.001", "--duration 60.001 s is outside the planner's range"),
    ("plan", "--out {tmp}/p.csv --intervals 8 --duration 2 --max-speed 0.1", "more than the fixed --duration of 2 s"),
    # --- the entry point itself
    (None, "no-such-command", "argument COMMAND: invalid choice: 'no-such-command'"),
    (None, "", "the following arguments are required: COMMAND"),    # --- import (ROS 2 bag -> recording), export (recording -> ROS 2 bag)
    ("import", "{missing}/bag --out {tmp}/imported.mcap", "bag: no such file or folder"),
    ("import", "{folder} --out {tmp}/imported.mcap", "folder without metadata.yaml: not a rosbag2 bag"),
    ("import", "{ok} --out {tmp}/imported.mcap", "is a project recording (JSON messages), not a ROS 2 bag"),
    ("import", "{text} --out {tmp}/imported.mcap", "not an MCAP file"),
    ("import", "{empty} --out {tmp}/imported.mcap", "not an MCAP file"),
    ("import", "{ok} --out {missing}/imported.mcap", "does not exist (otbot creates no parent folders)"),
    ("import", "{ok} --out {tmp}/imported.mcap --rate 0", "argument --rate: must be a finite number of Hz > 0"),
    ("import", "{ok} --out {tmp}/imported.mcap --map {binary_yaml}", "not a text file"),
    ("import", "{bag} --out {tmp}/imported.mcap --rate 1e9", "--rate 1e+09 Hz over the bag's 0.2 s gives "
                                                              "200000001 samples; at most 10000000"),
    ("import", "{bag} --out {tmp}/imported.mcap --rate 1e10", "gives 2000000001 samples; at most 10000000"),
    ("import", "{bag} --out {tmp}/imported.mcap --rate 1e-320", "the sample period 1/rate is not a finite number"),
    ("import", "{bag} --out {tmp}/imported.mcap --end 1e308", "--end 1e+308 s: at most 9e+09 s after the first"),
    ("import", "{bag} --out {tmp}/imported.mcap --start 1e308", "--start 1e+308 s: at most 9e+09 s"),
    ("export", "{missing}/run.mcap --ros2 {tmp}/bag", "run.mcap: no such file"),
    ("export", "{ok} --ros2 {ok}", "exists and is not a folder (a rosbag2 bag is a folder)"),
    ("export", "{ok} --ros2 {missing}/bag", "does not exist (otbot creates no parent folders)"),
    ("export", "{cut_before_samples} --ros2 {tmp}/bag", "truncated"),
    ("estimate", "{cut_before_samples}", "{cut_before_samples} is truncated (the writer stopped before closing it): it "
                                         "holds no complete sample: nothing to estimate"),
    # --- an output that names an input (also through a link) would replace what the work reads: refused first
    ("identify", "chassis --local-only --recording {victim} --out {victim}", "--out {victim}: is the recording itself"),
    ("identify", "chassis --sim --params {victim_yaml} --out {victim_link}",
     "--out {victim_link}: is the parameter file itself"),
    ("diagnose", "{victim} --out {victim}", "--out {victim}: is the recording itself"),
    ("diagnose", "{cut_before_samples} --holdout {victim} --out {victim}", "--out {victim}: is the recording itself"),
    ("track", "{victim_csv} --sim --no-robustness --out {victim_csv}", "--out {victim_csv}: is the trajectory itself"),
    ("track", "corridor --sim --params {victim_yaml} --out {victim_link}", "is the parameter file itself"),
    ("simulate", "--params {victim_yaml} --out {victim_yaml}", "--out {victim_yaml}: is the parameter file itself"),
    ("simulate", "--params {victim_yaml} --out {victim_link}", "--out {victim_link}: is the parameter file itself"),
    ("estimate", "{victim} --out {victim}", "--out {victim}: is the recording itself"),
    ("estimate", "{ok} --params {victim_yaml} --out {victim_yaml}", "is the parameter file itself"),
    ("import", "{victim} --out {victim}", "--out {victim}: is the bag itself"),
    ("plan", "--params {victim_yaml} --out {victim_yaml}", "is the parameter file itself"),
    ("bench", "--params {victim_yaml} --out {victim_link}", "is the parameter file itself"),
    ("run", "--plant-params {victim_yaml} --out {victim_yaml}", "is the plant parameter file itself"),
    # --- inputs that are not regular files: refused before the open (a FIFO blocked it, /dev/zero never ended)
    ("estimate", "{fifo}", "{fifo}: cannot read: is a FIFO (pipe), not a file"),
    ("simulate", "--params {fifo}", "cannot read parameter file: is a FIFO (pipe), not a file"),
    ("track", "{fifo} --sim", "{fifo}: cannot read: is a FIFO (pipe), not a file"),
    ("track", "corridor --sim --config {fifo}", "is a FIFO (pipe), not a file"),
    ("identify", "chassis --recording {fifo}", "{fifo}: cannot read: is a FIFO (pipe), not a file"),
    ("export", "{fifo} --ros2 {tmp}/bag", "is a FIFO (pipe), not a file"),
    ("imu", "parse /dev/zero", "/dev/zero: cannot read: is a character device, not a file"),
    ("estimate", "{loop}", "{loop}: cannot read: Too many levels of symbolic links"),
    ("identify", "chassis --recording {loop}", "Too many levels of symbolic links"),
]


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, str]:
    """Paths the table's argv may name: a valid recording and many broken inputs."""
    d = tmp_path_factory.mktemp("bad-input")
    ok = d / "ok.mcap"
    write_recording(ok, simulated_recording(nominal(), np.tile([6.0, -10.0, 6.0], (20, 1)), 0.01, NoiseModel.paper()))
    data = ok.read_bytes()
    (d / "cut_before_samples.mcap").write_bytes(data[:data.index(b'{"t": 0.0') + 5])  # inside sample 0
    (d / "empty.mcap").write_bytes(b"")
    (d / "text.mcap").write_text("t,x,y\n0,0,0\n")
    (d / "binary.csv").write_bytes(data[:4000])
    (d / "binary.yaml").write_bytes(data[:4000])
    (d / "folder").mkdir()
    (d / "ok_copy.mcap").write_bytes(data)
    (d / "dup_column.csv").write_text("t,x,y,alpha,x\n0,0,0,0,1\n2,0.5,0,0,1\n")
    (d / "long.csv").write_text("t,x,y,alpha\n0,0,0,0\n100000,0,0,0\n")
    (d / "close.csv").write_text("t,x,y,alpha\n0,0,0,0\n1e-160,0.5,0,0\n")
    (d / "denormal.csv").write_text("t,x,y,alpha\n0,0,0,0\n1e-320,0.5,0,0\n")
    (d / "far.csv").write_text("t,x,y,alpha\n0,0,0,0\n1,1e300,0,0\n")
    params = (ROOT / "config" / "otbot.yaml").read_text().splitlines(keepends=True)
    i = next(k for k, line in enumerate(params) if line.strip().startswith("m_c:"))
    (d / "dup.yaml").write_text("".join(params[:i + 1] + [params[i].replace("109.14", "5")] + params[i + 1:]))
    (d / "singular.yaml").write_text("".join(params).replace("m_c: {value: 109.14", "m_c: {value: 1e30"))
    (d / "overflow.yaml").write_text("".join(params).replace("m_c: {value: 109.14", "m_c: {value: 1e308"))
    robot = (ROOT / "config" / "robot.yaml").read_text().splitlines(keepends=True)
    i = next(k for k, line in enumerate(robot) if line.strip().startswith("channel:"))
    (d / "dup_robot.yaml").write_text("".join(robot[:i + 1] + [robot[i]] + robot[i + 1:]))
    for name, key, value in (("sigma", "encoder_rate_sigma", "1e160"), ("window", "walk_adaptation_window", "1e-320")):
        text, k = re.subn(rf"(\n  {key}: {{value: )[^,]+", rf"\g<1>{value}", "".join(robot))
        assert k == 1, key
        (d / f"{name}_robot.yaml").write_text(text)
    with open(d / "huge.yaml", "wb") as f:  # sparse: 300 MB long, no disk used
        f.write(b"geometry:\n")
        f.truncate(300 * 1024 * 1024)
    os.mkfifo(d / "fifo.mcap")
    (d / "victim.mcap").write_bytes(data)  # inputs a row names as its output too (rows must leave them as they are)
    (d / "victim.yaml").write_text("".join(params))
    (d / "victim_link.yaml").symlink_to(d / "victim.yaml")
    (d / "victim.csv").write_text("t,x,y,alpha\n0,0,0,0\n2,0.5,0,0\n")
    (d / "loop_a").symlink_to(d / "loop_b")
    (d / "loop_b").symlink_to(d / "loop_a")
    from otbot_hw.recording import read_recording
    from otbot_hw.ros2.bag_export import export_recording

    export_recording(read_recording(ok), d / "bag")  # a ROS 2 bag of 0.2 s at 100 Hz
    unreadable = d / "unreadable.mcap"
    unreadable.write_bytes(data)
    unreadable.chmod(0)
    return {"tmp": str(d), "ok": str(ok), "missing": str(d / "missing"), "folder": str(d / "folder"),
            "empty": str(d / "empty.mcap"), "text": str(d / "text.mcap"), "binary_csv": str(d / "binary.csv"),
            "binary_yaml": str(d / "binary.yaml"), "unreadable": str(unreadable),
            "cut_before_samples": str(d / "cut_before_samples.mcap"), "ok_copy": str(d / "ok_copy.mcap"),
            "long_csv": str(d / "long.csv"), "dup_yaml": str(d / "dup.yaml"), "dup_robot": str(d / "dup_robot.yaml"),
            "huge_yaml": str(d / "huge.yaml"), "singular_yaml": str(d / "singular.yaml"),
            "overflow_yaml": str(d / "overflow.yaml"), "fifo": str(d / "fifo.mcap"), "loop": str(d / "loop_a"),
            "victim": str(d / "victim.mcap"), "victim_yaml": str(d / "victim.yaml"),
            "victim_link": str(d / "victim_link.yaml"), "victim_csv": str(d / "victim.csv"),
            "dup_column_csv": str(d / "dup_column.csv"),
            "bag": str(d / "bag"),
            "sigma_robot": str(d / "sigma_robot.yaml"), "window_robot": str(d / "window_robot.yaml"),
            **{k: str(d / f"{k.removesuffix('_csv')}.csv") for k in ("close_csv", "denormal_csv", "far_csv")}}


def assert_one_line_error(rc: int, out: str, err: str, expected: str) -> None:
    assert rc == 2, (rc, err)
    assert "Traceback" not in err, err
    assert err.count("\n") == 1 and err.endswith("\n"), f"expected one line on stderr, got:\n{err}"
    assert err.startswith("otbot"), err
    assert expected in err, err
    assert out == "", out


def _skip_reason(command: str | None, argv: str) -> str | None:
    if command is not None and command not in SUBCOMMANDS:
        return f"otbot {command} is not on this branch"
    if "{unreadable}" in argv and os.geteuid() == 0:
        return "root reads files without read permission"
    if "/dev/zero" in argv and not os.path.exists("/dev/zero"):
        return "no /dev/zero on this machine"
    if "/dev/full" in argv and not os.path.exists("/dev/full"):
        return "no /dev/full on this machine"
    return None


@pytest.mark.parametrize("command, argv, expected", BAD_INPUT,
                         ids=[f"{c or 'otbot'} {a}".strip() for c, a, _ in BAD_INPUT])
def test_bad_input_exits_2_with_one_line(command, argv, expected, files, otbot_cli):
    reason = _skip_reason(command, argv)
    if reason:
        pytest.skip(reason)
    args = ([command] if command else []) + [a.format(**files) for a in argv.split()]
    rc, out, err = otbot_cli(args)
    assert_one_line_error(rc, out, err, expected.format(**files))


def _leaf_parsers():
    """(name, parser) of every command that runs, e.g. ('imu parse', <parser>)."""
    def walk(prefix, parser):
        sub = parser._subparsers
        if sub is None:
            yield prefix, parser
            return
        for action in sub._group_actions:
            for name, child in action.choices.items():
                yield from walk(f"{prefix} {name}".strip(), child)
    return list(walk("", build_parser()))


@pytest.mark.parametrize("name", [n for n, _ in _leaf_parsers()])
def test_unknown_option_names_the_subcommand_usage(name, otbot_cli):
    needs = {"identify": ["chassis", "--sim"], "imu parse": ["capture.bin"], "plan": ["--out", "p.csv"],
             "track": ["corridor", "--sim"], "ctl track": ["corridor-smooth"], "ctl velocity": ["0", "0", "0"],
             "ctl excite": ["/tmp/x.csv"], "ctl record": ["start"], "estimate": ["x.mcap"],
             "import": ["bag", "--out", "x.mcap"], "export": ["x.mcap", "--ros2", "bag"]}
    rc, out, err = otbot_cli([*name.split(), *needs.get(name, []), "--no-such-option"])
    assert_one_line_error(rc, out, err, "unrecognized arguments: --no-such-option")
    assert f"; usage: otbot {name} [-h]" in err and "usage: otbot [-h] COMMAND" not in err


@pytest.mark.parametrize("name", [n for n, _ in _leaf_parsers()])
def test_every_option_has_help_and_no_literal_percent_signs(name):
    parser = dict(_leaf_parsers())[name]
    missing = [a.option_strings[0] for a in parser._actions if a.option_strings and not a.help]
    assert not missing, f"otbot {name}: options without help: {missing}"
    text = parser.format_help()
    assert "%%" not in text and "%(" not in text


def test_demo_help_describes_every_stage():
    text = " ".join(dict(_leaf_parsers())["demo"].format_help().split())
    for stage in ("chassis experiment", "identification", "CANopen drivers", "bench identification procedure",
                  "narrow corridor"):
        assert stage in text, stage


# --- the console entry point: a real process behaves the same --------------------------------------

def otbot(*args: str, **kw) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "otbot_hw", *args], capture_output=True, text=True, env=env,
                          timeout=120, **kw)


@pytest.mark.parametrize("argv, expected", [
    ("simulate --torques 1e9,0,0 --duration 0.1 --json", "the simulation diverged"),
    ("simulate --torques 1e308,0,0 --duration 0.1", "the simulation diverged"),  # no numpy warning lines before it
    ("plan --out {missing}/p.csv", "folder {missing} does not exist"),
    ("imu parse {missing}/capture.bin", "cannot read: No such file or directory"),
    ("run --no-such-option", "usage: otbot run"),
])
def test_entry_point_process_exits_2_with_one_line(argv, expected, files):
    proc = otbot(*[a.format(**files) for a in argv.split()])
    assert_one_line_error(proc.returncode, proc.stdout, proc.stderr, expected.format(**files))


# --- interrupts ---------------------------------------------------------------------------------------

def _children(pid: int) -> list[int]:
    import psutil

    return [c.pid for c in psutil.Process(pid).children(recursive=True)]


def _alive(pids: list[int]) -> list[int]:
    import psutil

    out = []
    for pid in pids:
        try:
            if psutil.Process(pid).status() != psutil.STATUS_ZOMBIE:
                out.append(pid)
        except psutil.NoSuchProcess:
            pass
    return out


def _interrupt_when_busy(proc: subprocess.Popen, workers: int) -> tuple[float, list[int]]:
    """Wait until ``workers`` child processes exist, SIGINT the parent alone; (seconds to exit, children)."""
    deadline = time.monotonic() + 60
    kids: list[int] = []
    while time.monotonic() < deadline and len(kids) < workers:
        time.sleep(0.1)
        kids = _children(proc.pid)
    assert len(kids) >= workers, f"workers never started: {kids}"
    time.sleep(0.5)  # the workers are inside their first work items now
    t0 = time.monotonic()
    os.kill(proc.pid, signal.SIGINT)  # the parent only, not its process group
    proc.wait(timeout=30)
    return time.monotonic() - t0, kids


def test_sigint_to_the_parent_ends_sweep_workers_and_exits_130():
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "otbot_hw", "sweep", "--points", "400", "--seeds", "8",
                             "--workers", "2"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env, start_new_session=True)
    try:
        elapsed, kids = _interrupt_when_busy(proc, 2)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    err = proc.stderr.read()
    assert proc.returncode == 130, err
    assert elapsed < 1.0, f"took {elapsed:.2f} s to exit after SIGINT"
    assert err.strip().splitlines()[-1] == "otbot sweep: interrupted" and "Traceback" not in err
    assert _alive(kids) == []


def test_sigint_stops_a_long_simulation_between_chunks():
    """``simulate`` of 10^7 samples integrates in chunks with progress: SIGINT ends it at once (exit 130)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "otbot_hw", "simulate", "--duration", "100000"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, start_new_session=True)
    try:
        lines = []
        while not any("%" in line for line in lines):  # the integration is under way
            lines.append(proc.stderr.readline())
            assert lines[-1], f"no progress line: {lines}"
        t0 = time.monotonic()
        os.kill(proc.pid, signal.SIGINT)
        proc.wait(timeout=30)
        elapsed = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    err = "".join(lines) + proc.stderr.read()
    assert lines[0].startswith("[simulate] integrating 10000000 intervals"), lines
    assert proc.returncode == 130, err
    assert elapsed < 1.5, f"took {elapsed:.2f} s to exit after SIGINT"
    assert err.strip().splitlines()[-1] == "otbot simulate: interrupted" and "Traceback" not in err


def test_interrupted_local_executor_terminates_running_items():
    """Items that would run 60 s: an interrupt ends them at once instead of waiting (library level)."""
    code = ("import time; from otbot_hw.identification.executors import LocalExecutor\n"
            "with LocalExecutor(2) as ex:\n    ex.map(time.sleep, [60, 60, 60])\n")
    proc = subprocess.Popen([sys.executable, "-c", code], stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, PYTHONPATH=str(ROOT)), start_new_session=True)
    try:
        elapsed, kids = _interrupt_when_busy(proc, 2)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert elapsed < 1.0, f"took {elapsed:.2f} s to exit after SIGINT"
    assert "KeyboardInterrupt" in proc.stderr.read()
    assert _alive(kids) == []
