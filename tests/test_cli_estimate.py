"""``otbot estimate``: the estimate topic it writes, the truth comparison, and bad input (one line, exit 2)."""
import dataclasses
import json

import numpy as np
import pytest

from otbot_hw.params import nominal
from otbot_hw.recording import read_recording, write_recording
from otbot_hw.sensors import NoiseModel
from otbot_hw.simulation.runs import simulated_recording


@pytest.fixture(scope="module")
def run_file(tmp_path_factory):
    """A 3 s simulated run (paper noise, encoders of 40960 counts) as a recording."""
    t = np.arange(300) * 0.01
    U = np.column_stack([8 * np.sin(t), -6 * np.cos(0.7 * t), 5 * np.sin(1.3 * t)])
    noise = dataclasses.replace(NoiseModel.paper(), counts_per_rev=40960)
    rec = simulated_recording(nominal(), U, 0.01, noise, seed=3)
    path = tmp_path_factory.mktemp("est") / "run.mcap"
    write_recording(path, rec)
    return path, rec


def test_out_carries_the_estimate_and_json_compares_with_truth(run_file, tmp_path, otbot_cli):
    path, rec = run_file
    out = tmp_path / "est.mcap"
    rc, stdout, err = otbot_cli(["estimate", str(path), "--out", str(out), "--plot", str(tmp_path / "plots"), "--json"])
    assert rc == 0, err
    r = json.loads(stdout)
    assert r["prediction"] == "imu" and r["initial_pose_source"] == "truth"
    assert r["rejected"]["encoders"] == 0 and r["updates"]["encoders"] == len(rec) - 1
    err_max = r["estimation_error"]["max"]
    assert err_max["x"] < 1e-3 and err_max["y"] < 1e-3 and err_max["alpha"] < 1e-3
    est = read_recording(out)
    assert est.estimate_pose.shape == (len(rec), 3) and est.estimate_std.shape == (len(rec), 6)
    assert est.estimate_gyro_bias is not None and np.all(est.estimate_std > 0)
    assert np.abs(est.estimate_pose - rec.truth_q[:, :3]).max() < 1e-3
    assert est.metadata["estimator"]["prediction"] == "imu"
    np.testing.assert_array_equal(est.joint_pos, rec.joint_pos)
    assert sorted(p.rsplit("/", 1)[1] for p in r["plots"]) == ["errors.png", "innovations.png", "path.png"]
    assert all(open(p, "rb").read(8) == b"\x89PNG\r\n\x1a\n" for p in r["plots"])


def test_without_imu_the_model_prediction_runs_and_says_so(run_file, tmp_path, otbot_cli):
    _, rec = run_file
    path = tmp_path / "noimu.mcap"
    write_recording(path, dataclasses.replace(rec, imu_accel=None, imu_gyro=None))
    rc, stdout, err = otbot_cli(["estimate", str(path), "--json"])
    assert rc == 0, err
    r = json.loads(stdout)
    assert r["prediction"] == "model" and "no /otbot/imu" in r["notes"][0]
    assert r["estimation_error"]["max"]["x"] < 5e-3


def _one_line_exit_2(argv, otbot_cli, words):
    rc, stdout, err = otbot_cli(argv)
    assert rc == 2, (stdout, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert words in lines[0], lines[0]


def test_bad_recordings_exit_2_with_one_line(run_file, tmp_path, otbot_cli):
    _, rec = run_file
    _one_line_exit_2(["estimate", str(tmp_path / "missing.mcap")], otbot_cli, "no such file")
    nojoints = tmp_path / "nojoints.mcap"
    write_recording(nojoints, dataclasses.replace(rec, joint_pos=None, joint_vel=None))
    _one_line_exit_2(["estimate", str(nojoints)], otbot_cli, "no /otbot/joints")
    nan = tmp_path / "nan.mcap"
    bad = dataclasses.replace(rec, joint_vel=rec.joint_vel.copy())
    bad.joint_vel[42, 0] = np.nan
    write_recording(nan, bad)
    _one_line_exit_2(["estimate", str(nan)], otbot_cli, "sample 42")
    nan_imu = tmp_path / "nanimu.mcap"
    bad = dataclasses.replace(rec, imu_accel=rec.imu_accel.copy())
    bad.imu_accel[7, 1] = np.inf
    write_recording(nan_imu, bad)
    _one_line_exit_2(["estimate", str(nan_imu)], otbot_cli, "non-finite imu_accel")
    _one_line_exit_2(["estimate", str(nan), "--out", str(tmp_path / "nowhere" / "x.mcap")], otbot_cli, "does not exist")


def test_non_monotonic_time_exits_2(tmp_path, otbot_cli):
    """A file whose sample times go back (written with the plain mcap writer, as another tool would)."""
    from mcap.writer import CompressionType, Writer

    path = tmp_path / "back.mcap"
    with open(path, "wb") as f:
        w = Writer(f, compression=CompressionType.NONE, use_chunking=False)
        w.start(profile="otbot", library="test")
        ids = {}
        for topic in ("/otbot/command", "/otbot/joints"):
            sid = w.register_schema(name=topic, encoding="jsonschema", data=b"{}")
            ids[topic] = w.register_channel(topic=topic, message_encoding="json", schema_id=sid)
        for k, t in enumerate((0.0, 0.01, 0.005, 0.02)):
            for topic, msg in (("/otbot/command", {"t": t, "torque": [0, 0, 0]}),
                               ("/otbot/joints", {"t": t, "position": [0, 0, 0], "velocity": [0, 0, 0]})):
                w.add_message(channel_id=ids[topic], log_time=k, publish_time=k, sequence=k,
                              data=json.dumps(msg).encode())
        w.finish()
    _one_line_exit_2(["estimate", str(path)], otbot_cli, "sample times must increase")
