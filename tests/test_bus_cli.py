"""``otbot run`` and the bus part of ``otbot demo``."""
from __future__ import annotations

import json

import numpy as np

from otbot_hw.cli import main
from otbot_hw.params import nominal
from otbot_hw.recording import read_recording
from otbot_hw.sensors import encoders_ideal
from otbot_hw.simulation.simulator import simulate


def test_otbot_run_sim_json_and_recording(tmp_path, capsys):
    out = tmp_path / "run.mcap"
    rc = main(["run", "--bus", "sim", "--fixture", "floor", "--torques", "6,-10,6", "--duration", "0.5",
               "--rate", "100", "--out", str(out), "--plot", str(tmp_path / "plots"), "--json"])
    assert rc == 0
    res = json.loads(capsys.readouterr().out)
    assert res["completed"] and res["samples"] == 51 and res["t_final"] == 0.5 and res["imu"]
    traj = simulate(nominal(), np.tile([6.0, -10.0, 6.0], (50, 1)), 0.01)
    wheels = encoders_ideal(traj.x[-1:], 40960)[0][0]
    pivot = encoders_ideal(traj.x[-1:], 16384)[0][0]
    np.testing.assert_allclose(res["phi"], [wheels[0], wheels[1], pivot[2]], atol=1e-9)
    rec = read_recording(out)
    assert len(rec) == 51 and rec.imu_accel is not None and rec.truth_q is not None
    np.testing.assert_allclose(rec.joint_pos[-1], res["phi"])
    assert rec.metadata["bus"]["interface"] == "virtual" and rec.metadata["fixture"] == "floor"
    assert {p.split("/")[-1] for p in res["plots"]} == {"joints.png", "xy_path.png", "states.png", "imu.png"}


def test_otbot_run_locked_fixture_and_1khz(capsys):
    assert main(["run", "--fixture", "locked", "--torques", "0,0,3", "--duration", "0.05", "--rate", "1000",
                 "--noise", "none", "--json"]) == 0
    captured = capsys.readouterr()
    res = json.loads(captured.out)
    assert res["samples"] == 51 and res["q_final"][:3] == [0.0, 0.0, res["q_final"][2]]
    assert res["phi"][0] == 0.0 and res["phi"][2] > 0  # wheels locked, pivot turning
    assert "exceeds" in captured.err and res["busload"]["max_rate"] < 1000  # bus-load warning


def test_otbot_run_config_bus_without_a_robot_fails_cleanly(capsys, robot_yaml):
    # The configured virtual bus has nobody on it: boot-up never comes, exit 1 with the reason.
    cfg = robot_yaml({"boot_timeout: {value: 2.0, unit: s}": "boot_timeout: {value: 0.2, unit: s}"})
    try:
        main(["run", "--bus", "config", "--config", str(cfg), "--interface", "virtual", "--channel", "nobody-here",
              "--no-imu", "--duration", "0.1", "--json"])
    except SystemExit as exc:
        assert exc.code == 1
    else:
        raise AssertionError("expected exit 1")
    captured = capsys.readouterr()
    assert "no boot-up message" in captured.err
    assert json.loads(captured.out)["completed"] is False


def test_otbot_run_against_an_otbot_plant_process(capsys, robot_yaml):
    """Daemon and plant as two processes: `otbot plant` (slcan on a pty) and `otbot run --bus config`."""
    import subprocess
    import sys

    cfg = robot_yaml({"  options: {}": "  options: {sleep_after_open: 0}",
                      "heartbeat_consumer: {value: 200, unit: ms}": "heartbeat_consumer: {value: 1000, unit: ms}",
                      "master_heartbeat_consumer: {value: 100, unit: ms}":
                          "master_heartbeat_consumer: {value: 1000, unit: ms}"})
    code = "import sys; from otbot_hw.cli import main; sys.exit(main())"
    proc = subprocess.Popen([sys.executable, "-c", code, "plant", "--noise", "none"], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    try:
        info = json.loads(proc.stdout.readline())
        assert main(["run", "--bus", "config", "--config", str(cfg), "--interface", "slcan",
                     "--channel", info["can_channel"], "--imu-port", info["imu_port"], "--lockstep",
                     "--torques", "6,-10,6", "--duration", "0.3", "--json"]) == 0
    finally:
        proc.stdin.close()
        assert proc.wait(timeout=20) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["completed"] and res["interface"] == "slcan" and res["samples"] == 31 and res["imu"]
    traj = simulate(nominal(), np.tile([6.0, -10.0, 6.0], (30, 1)), 0.01)
    wheels = encoders_ideal(traj.x[-1:], 40960)[0][0]
    np.testing.assert_allclose(res["phi"][:2], wheels[:2], atol=1e-9)
