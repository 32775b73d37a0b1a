"""The daemon's session recordings as ROS 2 bags (``daemon.recording.format: ros2``): rotation gives
complete bags that rosbags reads, and a writer killed with SIGKILL leaves a bag that imports up to
the crash (at most flush_interval = 1 s lost)."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import time
import sys
from pathlib import Path

import numpy as np
import pytest

from otbot_hw.cli import main
from otbot_hw.recording import TOPIC_COMMAND, TOPIC_ESTIMATE, TOPIC_IMU, TOPIC_JOINTS, read_recording
from otbot_hw.runtime.daemon_config import daemon_config_from_dict

ROOT = Path(__file__).resolve().parents[1]
TOPICS = (TOPIC_JOINTS, TOPIC_IMU, TOPIC_ESTIMATE)


def messages(k: int, rate: float) -> dict:
    t = k / rate
    return {TOPIC_COMMAND: {"t": t, "torque": [0.1 * k, -1.0, 2.0]},
            TOPIC_JOINTS: {"t": t, "position": [k * 1e-3, 0.0, 0.5], "velocity": [0.1, 0.0, 0.0]},
            TOPIC_IMU: {"t": t, "accel": [0.0, 0.1, 9.80665], "gyro": [0.0, 0.0, 0.01 * k]},
            TOPIC_ESTIMATE: {"t": t, "pose": [k * 1e-4, 0.0, 0.1], "twist": [0.0] * 3, "std": [0.01] * 6}}


def test_config_selects_the_format():
    assert daemon_config_from_dict(None).recording.format == "otbot"
    assert daemon_config_from_dict({"recording": {"format": "ros2"}}).recording.format == "ros2"
    from otbot_hw.params import ParameterError

    with pytest.raises(ParameterError, match="'daemon.recording.format' must be otbot or ros2, got 'rosbag'"):
        daemon_config_from_dict({"recording": {"format": "rosbag"}})


WRITER = """
import sys, time
sys.path.insert(0, sys.argv[2])
from tests.test_ros2_session import TOPICS, messages
from otbot_hw.runtime.session_recording import SessionRecording
rate = 500.0
rec = SessionRecording(sys.argv[1], {"source": "test"}, TOPICS, rate=rate, rotate_time=2.0, session_id="killed",
                       format="ros2")
rec.write_event(0.0, "mode", "track")
k = 0
while True:
    for _ in range(50):
        rec.write_sample(messages(k, rate))
        k += 1
    print(k, flush=True)
    time.sleep(0.002)
"""


def test_a_killed_ros2_session_leaves_bags_that_load_up_to_the_crash(tmp_path, capsys):
    from rosbags.rosbag2 import Reader

    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    p = subprocess.Popen([sys.executable, "-c", WRITER, str(tmp_path), str(ROOT)], stdout=subprocess.PIPE,
                         text=True, env=env)
    reported = 0
    try:
        for line in p.stdout:
            reported = int(line)
            if reported >= 2700:  # 5.4 s of samples: two rotations, 0.4 s into the third bag
                break
    finally:
        p.send_signal(signal.SIGKILL)
        p.wait(10)
    assert p.returncode == -signal.SIGKILL
    bags = sorted(d for d in tmp_path.iterdir() if d.name.startswith("killed-"))
    assert [b.name for b in bags][:3] == ["killed-000", "killed-001", "killed-002"]
    for b in bags[:2]:  # rotated: complete bags, rosbags reads them with their counts
        with Reader(b) as r:
            assert {c.topic: c.msgcount for c in r.connections if c.topic == "/joint_states"} == {"/joint_states": 1000}
    loaded = []
    for b in bags:
        out = tmp_path / f"{b.name}.mcap"
        args = ["import", str(b), "--out", str(out), "--json"]
        if b == bags[-1]:  # cut: refused by default, imported up to the cut when asked
            assert main(args) == 2
            assert "MCAP file is truncated (no footer" in capsys.readouterr().err
            args.append("--allow-truncated")
        assert main(args) == 0
        rep = json.loads(capsys.readouterr().out)
        assert rep["resampling"]["method"].startswith("none") and rep["truncated"] == (b == bags[-1])
        loaded.append(read_recording(out))
    assert [len(r) for r in loaded[:2]] == [1000, 1000]
    total = sum(len(r) for r in loaded)
    assert total >= reported - 500  # at most one second (500 samples at 500 Hz) lost
    t = np.concatenate([r.t for r in loaded])
    assert np.array_equal(np.round(t * 1e9), np.round(np.arange(total) / 500.0 * 1e9))
    assert np.allclose(np.concatenate([r.torque[:, 0] for r in loaded]), 0.1 * np.arange(total))
    assert [e["text"] for e in loaded[-1].events] == ["track"]  # the mode carried into the cut bag
    assert loaded[-1].metadata["session"] == {"id": "killed", "index": len(bags) - 1, "rate": 500.0,
                                              "previous": bags[-2].name}
    assert loaded[-1].estimate_pose is not None and loaded[-1].imu_gyro is not None


def test_the_daemon_records_its_session_as_a_ros2_bag(tmp_path, capsys):
    """``otbot daemon`` with ``daemon.recording.format: ros2``: SIGTERM closes a complete bag that rosbags
    reads and that imports with the loop's estimate, reference and mode events."""
    from rosbags.rosbag2 import Reader

    from otbot_hw.runtime.daemon_process import DaemonProcess, local_config

    cfg = local_config(tmp_path / "cfg", replace={
        "max_consecutive_overruns: {value: 5": "max_consecutive_overruns: {value: 50",
        "    format: otbot ": "    format: ros2  "})
    d = DaemonProcess(["--bus", "sim", "--config", str(cfg), "--record-dir", str(tmp_path / "rec"), "--no-telemetry"],
                      tmp_path / "control.sock", tmp_path / "daemon.log")
    try:
        d.request("enable")
        end = time.monotonic() + 30  # a loaded machine runs the loop slower, never the check sooner
        while (d.request("status").get("recording") or {}).get("samples", 0) <= 20:
            assert time.monotonic() < end, "the daemon recorded no 21 samples in 30 s"
            time.sleep(0.05)
        code, summary = d.terminate()
    finally:
        d.kill()
    assert code == 0, d.log()[-2000:]
    (bag,) = [p for p in (tmp_path / "rec").iterdir()]
    assert bag.is_dir() and (bag / "metadata.yaml").is_file()
    with Reader(bag) as r:
        topics = {c.topic: c.msgcount for c in r.connections}
    assert {"/joint_states", "/imu", "/odom", "/reference", "/events", "/tf"} <= set(topics)
    assert main(["import", str(bag), "--out", str(tmp_path / "session.mcap"), "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    rec = read_recording(tmp_path / "session.mcap")
    assert len(rec) == topics["/joint_states"] > 20 and rep["resampling"]["method"].startswith("none")
    assert rec.estimate_pose is not None and rec.reference_p is not None
    assert rec.events[-1]["text"] == "idle: stopped (SIGTERM)" and rec.metadata["source"] == "otbot daemon"


def test_the_payload_estimate_goes_into_the_ros2_session_and_comes_back_on_import(tmp_path, capsys):
    """A session with the payload adapter's ``/otbot/payload`` written as a ROS 2 bag: ``/payload``
    (std_msgs/Float64MultiArray, 3 x 4: value, std, used) that ``otbot import`` gives back as the
    native recording's payload channel, to the float (the same samples as the native session)."""
    from rosbags.rosbag2 import Reader

    from otbot_hw.recording import TOPIC_PAYLOAD
    from otbot_hw.ros2 import messages as M
    from otbot_hw.runtime.session_recording import SessionRecording

    rate, n = 100.0, 40
    rng = np.random.default_rng(3)
    est = rng.normal([60.0, 4.0, 0.05, -0.02], [5.0, 0.5, 0.01, 0.01], (n, 4))
    std = np.abs(rng.normal(0.0, [2.0, 0.2, 0.005, 0.005], (n, 4)))
    topics = TOPICS + (TOPIC_PAYLOAD,)

    def sample(k):
        m = messages(k, rate)
        m[TOPIC_PAYLOAD] = {"t": m[TOPIC_COMMAND]["t"], "value": est[k].tolist(), "std": std[k].tolist(),
                            "used": est[min(k, 20)].tolist(), "state": "adapting"}
        return m

    recs = {}
    for fmt in ("otbot", "ros2"):
        (tmp_path / fmt).mkdir()
        with SessionRecording(tmp_path / fmt, {"source": "test"}, topics, rate=rate, session_id="s",
                              format=fmt) as rec:
            for k in range(n):
                rec.write_sample(sample(k))
            recs[fmt] = rec.path
    native = read_recording(recs["otbot"])
    bag = recs["ros2"]
    with Reader(bag) as r:
        conns = {c.topic: c for c in r.connections}
        assert conns["/payload"].msgtype == M.PAYLOAD and conns["/payload"].msgcount == n
        first = next(m for c, _, m in r.messages(connections=[conns["/payload"]]))
    msg = M.typestore().deserialize_cdr(first, M.PAYLOAD)
    assert [(d.label, d.size, d.stride) for d in msg.layout.dim] == [("value,std,used", 3, 12),
                                                                     ("m_p,I_p,x_F,y_F", 4, 4)]
    assert main(["import", str(bag), "--out", str(tmp_path / "back.mcap"), "--json"]) == 0
    capsys.readouterr()
    back = read_recording(tmp_path / "back.mcap")
    for name in ("payload_value", "payload_std", "payload_used"):
        assert np.array_equal(getattr(back, name), getattr(native, name)), name
    assert np.array_equal(back.payload_value, est) and np.array_equal(back.payload_used[30], est[20])
    assert np.array_equal(np.round(back.t * 1e9), np.round(native.t * 1e9))  # stamps to the nanosecond


def test_a_payload_array_of_another_layout_is_refused_by_name(tmp_path, capsys):
    """A /payload that is a Float64MultiArray of another shape: one line naming the topic, exit 2."""
    from otbot_hw.recording import TOPIC_PAYLOAD
    from otbot_hw.ros2 import messages as M
    from otbot_hw.ros2.writer import BagWriter

    real = M.payload
    try:  # a writer of the same type whose layout is 12 x 1
        def flat(value, std, used):
            msg = real(value, std, used)
            D = M.typestore().types["std_msgs/msg/MultiArrayDimension"]
            msg.layout.dim = [D(label="", size=12, stride=12)]
            return msg
        M.payload = flat
        with BagWriter(tmp_path / "bag", {"source": "test"}, TOPICS + (TOPIC_PAYLOAD,)) as w:
            for k in range(5):
                m = messages(k, 100.0)
                m[TOPIC_PAYLOAD] = {"t": k / 100.0, "value": [1.0] * 4, "std": [0.1] * 4, "used": [1.0] * 4}
                w.write_sample(m)
    finally:
        M.payload = real
    assert main(["import", str(tmp_path / "bag"), "--out", str(tmp_path / "x.mcap")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "/payload: a payload array must have the layout" in err, err
    assert not (tmp_path / "x.mcap").exists()
