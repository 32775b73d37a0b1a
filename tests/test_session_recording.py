"""Session recordings rotate by time and size, every file loads on its own and the pieces join up;
a writer killed with SIGKILL (after rotations) leaves files that load and lose at most one second."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from otbot_hw.recording import TOPIC_COMMAND, TOPIC_ESTIMATE, TOPIC_JOINTS, RecordingError, read_recording
from otbot_hw.runtime.session_recording import SessionRecording

ROOT = Path(__file__).resolve().parents[1]
TOPICS = (TOPIC_JOINTS, TOPIC_ESTIMATE)


def messages(k: int, rate: float) -> dict:
    t = k / rate
    return {TOPIC_COMMAND: {"t": t, "torque": [0.1 * k, -1.0, 2.0]},
            TOPIC_JOINTS: {"t": t, "position": [k * 1e-3, 0.0, 0.5], "velocity": [0.1, 0.0, 0.0]},
            TOPIC_ESTIMATE: {"t": t, "pose": [k * 1e-4, 0.0, 0.1], "twist": [0.0] * 3, "std": [0.01] * 6}}


def test_rotation_by_time_gives_files_that_load_and_join(tmp_path):
    rate = 100.0
    (tmp_path / "rec").mkdir()  # a session never creates its folder (the daemon's rule: docs/daemon.md)
    with SessionRecording(tmp_path / "rec", {"source": "test"}, TOPICS, rate=rate, rotate_time=2.0,
                          session_id="s1") as rec:
        rec.write_event(0.0, "mode", "idle")
        for k in range(700):  # 7 s
            if k == 250:
                rec.write_event(k / rate, "mode", "track corridor")
            if k == 260:
                rec.write_event(k / rate, "fault", "pivot: emcy")
            rec.write_sample(messages(k, rate))
        status = rec.status()
    assert [p.name for p in rec.files] == ["s1-000.mcap", "s1-001.mcap", "s1-002.mcap", "s1-003.mcap"]
    assert status["files"] == 4 and status["samples"] == 700 and status["index"] == 3
    parts = [read_recording(p) for p in rec.files]
    assert [len(r) for r in parts] == [200, 200, 200, 100]
    assert not any(r.truncated for r in parts)
    t = np.concatenate([r.t for r in parts])
    assert np.allclose(t, np.arange(700) / rate)  # nothing lost or doubled at the seams
    assert np.allclose(np.concatenate([r.estimate_pose[:, 0] for r in parts]), np.arange(700) * 1e-4)
    for i, r in enumerate(parts):
        s = r.metadata["session"]
        assert (s["id"], s["index"], s["rate"]) == ("s1", i, rate)
        assert s["previous"] == (None if i == 0 else f"s1-{i - 1:03d}.mcap")
        assert r.metadata["source"] == "test"
    # every file says the mode it starts in; the fault stays in its own file
    assert [(e["t"], e["text"]) for e in parts[0].events if e["kind"] == "mode"] == [(0.0, "idle")]
    assert [(e["t"], e["text"]) for e in parts[1].events if e["kind"] == "mode"] == [(2.0, "idle"), (2.5, "track corridor")]
    assert [(e["t"], e["text"]) for e in parts[2].events] == [(4.0, "track corridor")]
    assert [e["text"] for e in parts[1].events if e["kind"] == "fault"] == ["pivot: emcy"]


def test_rotation_by_size(tmp_path):
    rate = 500.0
    rec = SessionRecording(tmp_path, {}, TOPICS, rate=rate, rotate_size=200_000, rotate_time=1e9)
    for k in range(5000):
        rec.write_sample(messages(k, rate))
    rec.close()
    rec.close()  # twice is fine
    sizes = [p.stat().st_size for p in rec.files]
    assert len(rec.files) >= 4
    per_sample = sum(sizes) / 5000
    # a file ends at the first flush (every rate * 1 s samples) past the limit
    assert all(s <= 200_000 + rec.flush_every * per_sample * 1.2 for s in sizes)
    assert sum(len(read_recording(p)) for p in rec.files) == 5000
    assert rec.flush_every == 500


def test_an_open_file_loads_with_at_most_one_second_missing(tmp_path):
    rate = 250.0
    rec = SessionRecording(tmp_path, {}, TOPICS, rate=rate, flush_interval=1.0)
    for k in range(1234):
        rec.write_sample(messages(k, rate))
        if k % 97 == 0:
            r = read_recording(rec.path)  # what a crash now would leave
            assert r.truncated and k + 1 - rate <= len(r) <= k + 1
    rec.close()
    # a slow loop (10 Hz samples at a configured 250 Hz) is flushed by time, not only by count
    slow = SessionRecording(tmp_path, {}, TOPICS, rate=rate, session_id="slow")
    for k in range(35):
        slow.write_sample(messages(k, 10.0))
    assert len(read_recording(slow.path)) >= 35 - 10
    slow.close()


def test_bad_settings_and_no_overwrite(tmp_path):
    with pytest.raises(ValueError, match="flush_interval"):
        SessionRecording(tmp_path, {}, rate=100, flush_interval=2.0)
    with pytest.raises(ValueError, match="rate"):
        SessionRecording(tmp_path, {}, rate=float("nan"))
    SessionRecording(tmp_path, {}, rate=100, session_id="dup").close()
    with pytest.raises(RecordingError, match="already exists"):
        SessionRecording(tmp_path, {}, rate=100, session_id="dup")
    (tmp_path / "file").write_text("")
    with pytest.raises(RecordingError, match="recording folder does not exist"):
        SessionRecording(tmp_path / "file" / "sub", {}, rate=100)
    with pytest.raises(RecordingError, match="recording folder does not exist"):
        SessionRecording(tmp_path / "missing", {}, rate=100)
    assert not (tmp_path / "missing").exists()


WRITER = """
import sys, time
sys.path.insert(0, sys.argv[2])
from tests.test_session_recording import TOPICS, messages
from otbot_hw.runtime.session_recording import SessionRecording
rate = 500.0
rec = SessionRecording(sys.argv[1], {}, TOPICS, rate=rate, rotate_time=2.0, session_id="killed")
rec.write_event(0.0, "mode", "track")
k = 0
while True:
    for _ in range(50):
        rec.write_sample(messages(k, rate))
        k += 1
    print(k, flush=True)
    time.sleep(0.002)
"""


def test_a_killed_writer_leaves_loadable_files_after_rotation(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    p = subprocess.Popen([sys.executable, "-c", WRITER, str(tmp_path), str(ROOT)], stdout=subprocess.PIPE,
                         text=True, env=env)
    reported = 0
    try:
        for line in p.stdout:
            reported = int(line)
            if reported >= 2700:  # 5.4 s of samples: two rotations, 0.4 s into the third file
                break
    finally:
        p.send_signal(signal.SIGKILL)
        p.wait(10)
    assert p.returncode == -signal.SIGKILL
    files = sorted(tmp_path.glob("killed-*.mcap"))
    assert [f.name for f in files][:3] == ["killed-000.mcap", "killed-001.mcap", "killed-002.mcap"]
    parts = [read_recording(f) for f in files]
    assert [r.truncated for r in parts[:2]] == [False, False] and parts[-1].truncated
    assert [len(r) for r in parts[:2]] == [1000, 1000]
    loaded = sum(len(r) for r in parts)
    assert loaded >= reported - 500  # at most one second (500 samples at 500 Hz) lost
    t = np.concatenate([r.t for r in parts])
    assert np.allclose(t, np.arange(loaded) / 500.0)
    assert [e["text"] for e in parts[-1].events] == ["track"]  # the mode carried into the cut file
    assert json.dumps(parts[-1].metadata["session"]) == json.dumps(
        {"id": "killed", "index": len(files) - 1, "rate": 500.0, "previous": files[-2].name})
