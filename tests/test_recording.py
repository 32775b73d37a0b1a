"""MCAP recordings: bit-exact round trips, truncation (killed writer), and rejected bad files."""
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.writer import CompressionType, Writer

from otbot_hw.recording import (
    TOPIC_COMMAND,
    TOPIC_IMU,
    TOPIC_JOINTS,
    Recording,
    RecordingError,
    RecordingWriter,
    read_recording,
    write_recording,
)
from otbot_hw.sensors import NoiseModel
from otbot_hw.simulation.runs import simulated_recording
from otbot_hw.simulation.simulator import ForceSchedule, PivotForce

ARRAYS = ("t", "torque", "joint_pos", "joint_vel", "imu_accel", "imu_gyro", "truth_q", "truth_qd", "truth_force")
FORMAT_KEYS = ("format", "format_version", "units", "frames")


def assert_same_bits(a: np.ndarray, b: np.ndarray) -> None:
    """Equal as float64 bit patterns (so -0.0 != 0.0 and NaN payloads compare)."""
    assert a.shape == b.shape and a.dtype == b.dtype == np.float64
    assert np.array_equal(a.view(np.int64), b.view(np.int64))


def test_simulated_recording_round_trips_bit_exactly(params, tmp_path):
    forces = ForceSchedule([PivotForce(0.2, 0.3, 15.0, -5.0)])
    U = np.column_stack([np.linspace(-5, 5, 80), np.full(80, -3.0), np.sin(np.arange(80))])
    rec = simulated_recording(params, U, 0.01, NoiseModel.paper(), seed=4, forces=forces,
                              extra_metadata={"experiment": "round trip", "nested": {"a": [1, 2.5e-300]}})
    path = tmp_path / "run.mcap"
    write_recording(path, rec)
    back = read_recording(path)
    for name in ARRAYS:
        a, b = getattr(rec, name), getattr(back, name)
        assert np.array_equal(a, b), name
        assert_same_bits(np.asarray(a, dtype=float), b)
    meta = {k: v for k, v in back.metadata.items() if k not in FORMAT_KEYS}
    assert meta == json.loads(json.dumps(rec.metadata))  # tuples become lists, nothing else changes
    assert back.metadata["format"] == "otbot-recording" and back.metadata["format_version"] == 1
    assert back.truncated is False
    assert back.sample_period == 0.01


def test_extreme_floats_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    n = 64
    special = np.array([5e-324, -5e-324, 2.2250738585072014e-308, 1.7976931348623157e308, -0.0, 0.1, 1 / 3, np.pi])
    vals = rng.normal(size=(n, 3)) * 10.0 ** rng.integers(-300, 300, size=(n, 3))
    vals[:8, 0] = special
    t = np.cumsum(rng.uniform(1e-4, 0.02, n))
    rec = Recording(t=t, torque=vals, joint_pos=vals[::-1].copy(), joint_vel=-vals,
                    metadata={"sample_period": 0.01})
    write_recording(tmp_path / "x.mcap", rec)
    back = read_recording(tmp_path / "x.mcap")
    for name in ("t", "torque", "joint_pos", "joint_vel"):
        assert_same_bits(getattr(rec, name), getattr(back, name))
    assert back.imu_accel is None and back.truth_q is None
    assert back.channels() == [TOPIC_COMMAND, TOPIC_JOINTS]


def test_command_only_and_truth_without_force(tmp_path):
    t = np.arange(5) * 0.02
    rec = Recording(t=t, torque=np.ones((5, 3)), truth_q=np.zeros((5, 6)), truth_qd=np.ones((5, 6)))
    write_recording(tmp_path / "a.mcap", rec)
    back = read_recording(tmp_path / "a.mcap")
    assert back.truth_force is None and back.joint_pos is None
    assert np.array_equal(back.truth_qd, rec.truth_qd)
    rec2 = Recording(t=t, torque=np.ones((5, 3)))
    write_recording(tmp_path / "b.mcap", rec2)
    assert read_recording(tmp_path / "b.mcap").channels() == [TOPIC_COMMAND]


# --- truncation -----------------------------------------------------------------

#: Executed both here and in the writer subprocess: the deterministic data the child writes.
DATA_SOURCE = '''
import numpy as np
def killed_writer_data(n):
    keys = ("torque", "position", "velocity", "accel", "gyro")  # one stream each: prefixes agree for any n
    d = {key: np.random.default_rng([2024, i]).normal(size=(n, 3)) for i, key in enumerate(keys)}
    d["t"] = np.arange(n) * 0.01
    return d
'''

CHILD = DATA_SOURCE + '''
import sys, time
from otbot_hw.recording import RecordingWriter
N = 100000
d = killed_writer_data(N)
w = RecordingWriter(sys.argv[1], {"sample_period": 0.01, "source": "killed writer"},
                    topics=["/otbot/joints", "/otbot/imu"], flush_every=1)
for k in range(N):
    t = float(d["t"][k])
    w.write_sample({
        "/otbot/command": {"t": t, "torque": d["torque"][k].tolist()},
        "/otbot/joints": {"t": t, "position": d["position"][k].tolist(), "velocity": d["velocity"][k].tolist()},
        "/otbot/imu": {"t": t, "accel": d["accel"][k].tolist(), "gyro": d["gyro"][k].tolist()},
    })
    if k == 199:
        print("ready", flush=True)
    if k >= 199:
        time.sleep(0.001)
'''


def killed_writer_data(n):
    ns: dict = {}
    exec(DATA_SOURCE, ns)
    return ns["killed_writer_data"](n)


def test_recording_of_killed_writer_loads_complete_samples(tmp_path):
    """A writer process killed with SIGKILL mid-run leaves a file whose complete samples all load."""
    path = tmp_path / "killed.mcap"
    root = Path(__file__).resolve().parent.parent
    env = {**os.environ, "PYTHONPATH": f"{root}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    child = subprocess.Popen([sys.executable, "-c", CHILD, str(path)], stdout=subprocess.PIPE, env=env)
    try:
        assert child.stdout.readline().strip() == b"ready"
        time.sleep(0.15)
        child.send_signal(signal.SIGKILL)
    finally:
        child.wait(timeout=30)
    assert child.returncode == -signal.SIGKILL
    rec = read_recording(path)
    n = len(rec)
    assert rec.truncated is True
    assert 200 <= n < 100000
    d = killed_writer_data(n)
    assert np.array_equal(rec.t, d["t"])
    for name, key in (("torque", "torque"), ("joint_pos", "position"), ("joint_vel", "velocity"),
                      ("imu_accel", "accel"), ("imu_gyro", "gyro")):
        assert np.array_equal(getattr(rec, name), d[key]), name
    assert rec.metadata["source"] == "killed writer"


def test_cut_at_any_byte_loads_a_prefix_of_the_samples(params, tmp_path):
    """Cutting a complete file anywhere after its header gives a prefix of its samples, never garbage."""
    rec = simulated_recording(params, np.tile([1.0, -1.0, 0.5], (30, 1)), 0.01, NoiseModel.paper(), seed=1)
    full = tmp_path / "full.mcap"
    write_recording(full, rec)
    data = full.read_bytes()
    cut = tmp_path / "cut.mcap"
    last_n = -1
    header_end = data.index(b"/otbot/truth") + 200  # past the channel registrations
    for size in np.linspace(header_end, len(data) - 1, 60).astype(int):
        cut.write_bytes(data[:size])
        part = read_recording(cut)
        n = len(part)
        assert part.truncated is True
        assert n >= last_n  # more bytes never give fewer samples
        last_n = n
        for name in ARRAYS:
            assert np.array_equal(getattr(part, name), getattr(rec, name)[:n]), (size, name)
    assert last_n >= len(rec) - 1  # a cut inside the summary keeps every sample


def test_cut_inside_header_is_rejected(tmp_path, params):
    rec = simulated_recording(params, np.zeros((3, 3)), 0.01)
    write_recording(tmp_path / "f.mcap", rec)
    data = (tmp_path / "f.mcap").read_bytes()
    for size in (0, 5, 30):
        (tmp_path / "c.mcap").write_bytes(data[:size])
        with pytest.raises(RecordingError, match="empty file|cut short|not an MCAP recording"):
            read_recording(tmp_path / "c.mcap")


# --- bad files ------------------------------------------------------------------

def write_plain(path, messages, metadata=None, encodings=None):
    """Write an MCAP file with the plain mcap Writer: messages is [(topic, payload dict or bytes)]."""
    encodings = encodings or {}
    with open(path, "wb") as f:
        w = Writer(f, compression=CompressionType.NONE)
        w.start(profile="otbot", library="test")
        if metadata is not None:
            w.add_metadata("otbot", metadata)
        ids = {}
        for topic, payload in messages:
            if topic not in ids:
                sid = w.register_schema(name=topic, encoding="jsonschema", data=b"{}")
                ids[topic] = w.register_channel(topic=topic, message_encoding=encodings.get(topic, "json"),
                                                schema_id=sid)
            data = payload if isinstance(payload, bytes) else json.dumps(payload).encode()
            t = payload.get("t", 0) if isinstance(payload, dict) else 0
            w.add_message(channel_id=ids[topic], log_time=int(round(t * 1e9)), publish_time=0, data=data)
        w.finish()


def cmd(t, torque=(0.0, 0.0, 0.0)):
    return (TOPIC_COMMAND, {"t": t, "torque": list(torque)})


def joints(t):
    return (TOPIC_JOINTS, {"t": t, "position": [0.0, 0.0, 0.0], "velocity": [0.0, 0.0, 0.0]})


@pytest.mark.parametrize("case, match", [
    ("missing", "no such file"),
    ("empty", "empty file, expected an MCAP recording"),
    ("text", "not an MCAP recording"),
    ("no command", "no /otbot/command channel"),
    ("time mismatch", "/otbot/joints sample 1 has t = 0.011.*must share sample times"),
    ("not increasing", "sample times must increase; sample 2"),
    ("repeated time", "sample times must increase; sample 1"),
    ("not json", "is not JSON"),
    ("wrong encoding", "message encoding 'cbor'"),
    ("missing field", "/otbot/command messages need 'torque' as 3 numbers"),
    ("short vector", "/otbot/joints messages need 'position' as 3 numbers"),
    ("bad metadata", "metadata 'sample_period' is not JSON text"),
    ("other format", "metadata format is 'rosbag'"),
    ("newer version", "format_version 2"),
    ("unequal counts", "/otbot/joints has 2 messages but /otbot/command has 3"),
    ("nan time", "non-finite sample time"),
    ("string numbers", "/otbot/command messages need 'torque' as 3 numbers; sample 0 has ['6', '-10', '6']"),
    ("boolean", "/otbot/joints messages need 'velocity' as 3 numbers"),
    ("two channels", "registered on two channels"),
])
def test_bad_recordings_are_rejected_with_clear_messages(tmp_path, case, match):
    path = tmp_path / "bad.mcap"
    good3 = [cmd(0.0), joints(0.0), cmd(0.01), joints(0.01), cmd(0.02), joints(0.02)]
    if case == "empty":
        path.write_bytes(b"")
    elif case == "text":
        path.write_text("t,tau_r\n0,1\n")
    elif case == "no command":
        write_plain(path, [joints(0.0), joints(0.01)])
    elif case == "time mismatch":
        write_plain(path, [cmd(0.0), joints(0.0), cmd(0.01), joints(0.011)])
    elif case == "not increasing":
        write_plain(path, [cmd(0.0), cmd(0.02), cmd(0.01)])
    elif case == "repeated time":
        write_plain(path, [cmd(0.0), cmd(0.0)])
    elif case == "not json":
        write_plain(path, [cmd(0.0), (TOPIC_COMMAND, b"\x00\x01 not json")])
    elif case == "wrong encoding":
        write_plain(path, [cmd(0.0)], encodings={TOPIC_COMMAND: "cbor"})
    elif case == "missing field":
        write_plain(path, [(TOPIC_COMMAND, {"t": 0.0, "tau": [0, 0, 0]})])
    elif case == "short vector":
        write_plain(path, [cmd(0.0), (TOPIC_JOINTS, {"t": 0.0, "position": [0, 0], "velocity": [0, 0, 0]})])
    elif case == "bad metadata":
        write_plain(path, [cmd(0.0)], metadata={"sample_period": "ten ms"})
    elif case == "other format":
        write_plain(path, [cmd(0.0)], metadata={"format": '"rosbag"'})
    elif case == "newer version":
        write_plain(path, [cmd(0.0)], metadata={"format": '"otbot-recording"', "format_version": "2"})
    elif case == "unequal counts":
        write_plain(path, good3[:-1])
    elif case == "nan time":
        write_plain(path, [cmd(0.0), (TOPIC_COMMAND, b'{"t": NaN, "torque": [0, 0, 0]}')])
    elif case == "string numbers":
        write_plain(path, [(TOPIC_COMMAND, {"t": 0.0, "torque": ["6", "-10", "6"]})])
    elif case == "boolean":
        write_plain(path, [cmd(0.0), (TOPIC_JOINTS, {"t": 0.0, "position": [0, 0, 0], "velocity": [0, True, 0]})])
    elif case == "two channels":
        with open(path, "wb") as f:
            w = Writer(f)
            w.start(profile="otbot", library="test")
            for _ in range(2):
                w.register_channel(topic=TOPIC_COMMAND, message_encoding="json", schema_id=0)
            w.finish()
    with pytest.raises(RecordingError, match=re.escape(match) if case == "string numbers" else match):
        read_recording(path)


def test_plain_writer_file_with_interleaving_and_unknown_topic_loads(tmp_path):
    """Topics may be interleaved in any order; unknown topics are ignored."""
    path = tmp_path / "ok.mcap"
    msgs = [joints(0.0), cmd(0.0, (1, 2, 3)), ("/camera/info", {"t": 0.0}), cmd(0.01, (4, 5, 6)), joints(0.01)]
    write_plain(path, msgs)
    rec = read_recording(path)
    assert np.array_equal(rec.t, [0.0, 0.01])
    assert np.array_equal(rec.torque, [[1, 2, 3], [4, 5, 6]])
    assert rec.truncated is False
    assert rec.sample_period == pytest.approx(0.01)


@pytest.mark.parametrize("sample, match", [
    ({TOPIC_COMMAND: {"t": -1.0, "torque": [0, 0, 0]}, TOPIC_IMU: {"t": -1.0, "accel": [0] * 3, "gyro": [0] * 3}},
     "time must be finite and >= 0"),
    ({TOPIC_COMMAND: {"t": float("nan"), "torque": [0, 0, 0]},
      TOPIC_IMU: {"t": 0.0, "accel": [0] * 3, "gyro": [0] * 3}}, "time must be finite"),
    ({TOPIC_COMMAND: {"t": 0.0, "torque": [0, 0, 0]}}, "lacks topic"),
])
def test_writer_rejects_bad_samples(tmp_path, sample, match):
    with RecordingWriter(tmp_path / "w.mcap", {}, topics=[TOPIC_IMU]) as w:
        with pytest.raises(ValueError, match=match):
            w.write_sample(sample)


def test_writer_rejects_times_that_disagree_or_do_not_increase(tmp_path):
    def sample(t_cmd, t_imu):
        return {TOPIC_COMMAND: {"t": t_cmd, "torque": [0, 0, 0]}, TOPIC_IMU: {"t": t_imu, "accel": [0] * 3, "gyro": [0] * 3}}

    with RecordingWriter(tmp_path / "w.mcap", {}, topics=[TOPIC_IMU]) as w:
        with pytest.raises(ValueError, match="/otbot/imu has t = 0.5, but /otbot/command has t = 0.0"):
            w.write_sample(sample(0.0, 0.5))
        w.write_sample(sample(0.0, 0.0))
        with pytest.raises(ValueError, match="time 0.0 s does not increase"):
            w.write_sample(sample(0.0, 0.0))
        w.write_sample(sample(0.01, 0.01))
    assert len(read_recording(tmp_path / "w.mcap")) == 2


@pytest.mark.parametrize("change, match", [
    ({"torque": np.zeros((4, 2))}, r"torque must have shape \(4, 3\)"),
    ({"imu_accel": np.zeros((4, 3))}, "imu_accel and imu_gyro go together"),
    ({"truth_force": np.zeros((4, 2))}, "truth_force needs truth_q"),
    ({"t": np.zeros((4, 1))}, "t must be a 1-D array"),
])
def test_write_recording_rejects_misshapen_arrays(tmp_path, change, match):
    rec = Recording(**{"t": np.arange(4) * 0.1, "torque": np.zeros((4, 3)), **change})
    with pytest.raises(ValueError, match=match):
        write_recording(tmp_path / "x.mcap", rec)
    assert not (tmp_path / "x.mcap").exists()  # nothing half-written


def test_writer_rejects_unknown_topic(tmp_path):
    with pytest.raises(ValueError, match="unknown topic '/otbot/lidar'"):
        RecordingWriter(tmp_path / "w.mcap", {}, topics=["/otbot/lidar"])



# --- the format document --------------------------------------------------------

DOC = Path(__file__).resolve().parent.parent / "docs" / "recording-format.md"


def doc_python_blocks() -> list[str]:
    text = DOC.read_text()
    section = text[text.index("## 8. Worked example"):]
    return re.findall(r"```python\n(.*?)```", section, flags=re.S)


def test_format_doc_example_loads(tmp_path, monkeypatch):
    """The worked example of docs/recording-format.md (plain mcap Writer) writes a file the reader loads."""
    monkeypatch.chdir(tmp_path)
    write_block, read_block = doc_python_blocks()
    assert "otbot_hw" not in write_block  # the writer side uses only json and mcap
    ns: dict = {}
    exec(compile(write_block, str(DOC), "exec"), ns)
    rec = read_recording(tmp_path / "example.mcap")
    samples = ns["samples"]
    assert rec.truncated is False and len(rec) == len(samples)
    assert np.array_equal(rec.t, [k * ns["dt"] for k in range(len(samples))])
    for j, name in enumerate(("torque", "joint_pos", "joint_vel", "imu_accel", "imu_gyro")):
        assert np.array_equal(getattr(rec, name), [s[j] for s in samples]), name
    assert rec.truth_q is None
    assert rec.metadata == ns["metadata"] and rec.sample_period == ns["dt"]
    exec(compile(read_block, str(DOC), "exec"), {})


def test_format_doc_sign_conventions_hold_in_the_model(params):
    """§3 of the format document: wheel and torque signs as the model implements them."""
    from otbot_hw.model import kinematics as kin
    from otbot_hw.simulation.simulator import simulate

    q = np.array([0.0, 0.0, 0.9, 0.0, 0.0, 0.4])  # theta = 0.5 rad
    th = q[2] - q[5]
    qd = kin.admissible_velocity(q, np.array([2.0, 2.0, 0.0]), params)  # both wheels forward
    assert np.allclose(qd[:2], params.r * 2.0 * np.array([np.cos(th), np.sin(th)]))  # along +1'
    assert qd[2] == 0.0
    qd = kin.admissible_velocity(q, np.array([2.0, 1.0, 0.0]), params)  # right faster: CCW
    assert qd[2] == pytest.approx(params.r * 1.0 / (2 * params.l2))
    fwd = simulate(params, np.tile([1.0, 1.0, 0.0], (20, 1)), 0.01)
    assert fwd.qd[-1, 3] > 0 and fwd.qd[-1, 4] > 0 and fwd.q[-1, 0] > 0  # theta = 0: forward is +x
    turn = simulate(params, np.tile([0.0, 0.0, 1.0], (20, 1)), 0.01, fixture="locked")
    assert turn.qd[-1, 5] > 0 and turn.q[-1, 2] > 0  # tau_p > 0 turns the platform CCW



@pytest.mark.parametrize("compression", [CompressionType.ZSTD, CompressionType.LZ4, CompressionType.NONE])
def test_chunked_compressed_files_load_and_truncate_by_chunk(tmp_path, compression):
    """§1 of the format document: chunked files (zstd, lz4, none) are read; a cut loses the open chunk only."""
    path = tmp_path / "chunked.mcap"
    torques = np.random.default_rng(5).normal(size=(200, 3))
    with open(path, "wb") as f:
        w = Writer(f, compression=compression, chunk_size=2000)
        w.start(profile="otbot", library="test")
        cid = w.register_channel(topic=TOPIC_COMMAND, message_encoding="json", schema_id=0)
        for k in range(200):
            w.add_message(channel_id=cid, log_time=k * 10_000_000, publish_time=k * 10_000_000,
                          data=json.dumps({"t": k * 0.01, "torque": torques[k].tolist()}).encode())
        w.finish()
    rec = read_recording(path)
    assert len(rec) == 200 and not rec.truncated and np.array_equal(rec.torque, torques)
    data = path.read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[: len(data) // 2])
    part = read_recording(tmp_path / "cut.mcap")
    assert part.truncated and 0 < len(part) < 200
    assert np.array_equal(part.torque, torques[: len(part)])


def test_loop_topics_round_trip_with_sparse_events(tmp_path):
    """Estimate and reference are per-sample topics; events are sparse and keep their times."""
    from otbot_hw.recording import SAMPLE_TOPICS, TOPIC_ESTIMATE, TOPIC_EVENTS, TOPIC_REFERENCE

    n = 6
    rng = np.random.default_rng(1)
    rec = Recording(t=np.arange(n) * 0.01, torque=rng.normal(size=(n, 3)),
                    joint_pos=rng.normal(size=(n, 3)), joint_vel=rng.normal(size=(n, 3)),
                    estimate_pose=rng.normal(size=(n, 3)), estimate_twist=rng.normal(size=(n, 3)),
                    estimate_std=rng.uniform(size=(n, 6)), estimate_gyro_bias=rng.normal(size=n) * 1e-3,
                    reference_p=rng.normal(size=(n, 3)), reference_pd=rng.normal(size=(n, 3)),
                    reference_pdd=rng.normal(size=(n, 3)),
                    events=[{"t": 0.02, "kind": "mode", "text": "hold -> track"},
                            {"t": 0.02, "kind": "fault", "text": "left_wheel: stale", "node": 2}],
                    metadata={"sample_period": 0.01})
    write_recording(tmp_path / "loop.mcap", rec)
    back = read_recording(tmp_path / "loop.mcap")
    assert TOPIC_EVENTS not in SAMPLE_TOPICS
    assert back.channels()[-3:] == [TOPIC_ESTIMATE, TOPIC_REFERENCE, TOPIC_EVENTS]
    for name in ("estimate_pose", "estimate_twist", "estimate_std", "estimate_gyro_bias", "reference_p",
                 "reference_pd", "reference_pdd"):
        np.testing.assert_array_equal(getattr(back, name), getattr(rec, name), err_msg=name)
    assert [(e["t"], e["kind"], e["text"]) for e in back.events] == [(e["t"], e["kind"], e["text"]) for e in rec.events]
    assert back.events[1]["node"] == 2


def test_estimate_topic_needs_its_three_fields(tmp_path):
    rec = Recording(t=np.arange(3) * 0.01, torque=np.zeros((3, 3)), estimate_pose=np.zeros((3, 3)))
    with pytest.raises(ValueError, match="estimate_pose, estimate_twist and estimate_std"):
        write_recording(tmp_path / "x.mcap", rec)
