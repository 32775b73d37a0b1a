"""The recording writer's framed sample path (issue 22, fourth pass): samples are framed by
``RecordingWriter`` itself and written in one call; the file must be what the mcap library's
``add_message`` with ``json.dumps`` wrote before, byte for byte, and decode to the same messages."""
from __future__ import annotations

import json
import math
import struct

import numpy as np
from mcap.reader import make_reader

from otbot_hw.recording import (SAMPLE_TOPICS, TOPIC_COMMAND, TOPIC_ESTIMATE, TOPIC_EVENTS, TOPIC_IMU,
                                TOPIC_JOINTS, TOPIC_PAYLOAD, TOPIC_REFERENCE, TOPIC_TRUTH, RecordingWriter,
                                read_recording)

TOPICS = [TOPIC_JOINTS, TOPIC_EVENTS, TOPIC_IMU, TOPIC_TRUTH, TOPIC_ESTIMATE, TOPIC_REFERENCE, TOPIC_PAYLOAD]
ODD = [math.nan, math.inf, -math.inf, -0.0, 5e-324, 2.2250738585072014e-308, 1.7976931348623157e308, 1e16, 1e-5,
       0.1 + 0.2, -123456789.12345678, 1.0]


class OldWriter(RecordingWriter):
    """``write_sample`` as it was before the fourth pass: one ``json.dumps`` and one mcap
    ``add_message`` per topic."""

    def write_sample(self, messages):
        t = messages[TOPIC_COMMAND]["t"]
        self._last_t = t
        stamp = int(round(t * 1e9))
        for topic in [tp for tp in self._channels if tp in SAMPLE_TOPICS]:
            data = json.dumps(messages[topic], allow_nan=True).encode()
            self._writer.add_message(channel_id=self._channels[topic], log_time=stamp, publish_time=stamp,
                                     data=data, sequence=self._count)
        self._count += 1
        if self._count % self._flush_every == 0:
            self.flush()


def _samples(n: int):
    rng = np.random.default_rng(7)
    for k in range(n):
        v = rng.standard_normal(45) * 10.0 ** rng.integers(-12, 12, 45)
        odd = [ODD[(k + i) % len(ODD)] for i in range(6)]
        v[k % 45], v[(3 * k + 1) % 45] = odd[0], odd[1]
        v = v.tolist()
        t = k * 0.00125 + 1e-7 * (k % 3)
        yield {TOPIC_COMMAND: {"t": t, "torque": v[0:3]},
               TOPIC_JOINTS: {"t": t, "position": v[3:6], "velocity": v[6:9]},
               TOPIC_IMU: {"t": t, "accel": v[9:12], "gyro": odd[2:5]},
               TOPIC_TRUTH: {"t": t, "q": v[12:18], "qd": v[18:24], "force": v[24:26]},
               TOPIC_ESTIMATE: {"t": t, "pose": v[26:29], "twist": v[29:32], "std": v[32:38],
                                "gyro_bias": odd[5]},
               TOPIC_REFERENCE: {"t": t, "p": v[38:41], "pd": v[41:44], "pdd": [v[44], 0, 1]},
               TOPIC_PAYLOAD: {"t": t, "value": v[0:4], "std": v[4:8], "used": [1, 2.5, v[8], -3],
                               "state": "converged" if k % 2 else "learning"}}


def _write(cls, path, n=300):
    with cls(path, {"program": "test", "note": "framed"}, topics=TOPICS, flush_every=7) as w:
        for k, s in enumerate(_samples(n)):
            w.write_sample(s)
            if k % 50 == 3:
                w.write_event(s[TOPIC_COMMAND]["t"], "note", f"event {k}", value=ODD[k % len(ODD)])
    return w._direct  # the writer framed the samples itself (not the mcap library's add_message)


def _bits(x):
    return struct.pack("<d", x) if type(x) is float else repr(x)


def _messages(path):
    with open(path, "rb") as f:
        out = []
        for _, ch, m in make_reader(f).iter_messages():
            v = json.loads(m.data)
            out.append((ch.topic, m.log_time, m.publish_time, m.sequence,
                        {k: [_bits(x) for x in x] if isinstance(x, list) else _bits(x) for k, x in v.items()}))
        return out


def test_framed_samples_are_the_old_files_byte_for_byte(tmp_path):
    old, new = tmp_path / "old.mcap", tmp_path / "new.mcap"
    _write(OldWriter, old)
    assert _write(RecordingWriter, new)
    assert new.read_bytes() == old.read_bytes()
    a, b = _messages(old), _messages(new)
    assert a == b and len(b) == 300 * 7 + 6  # same topics, times, sequences, values bit for bit
    assert any(isinstance(x, list) and _bits(math.nan) in x for *_, v in b for x in v.values())


def test_framed_samples_decode_with_nan_where_nan_and_a_right_summary(tmp_path):
    path = tmp_path / "new.mcap"
    _write(RecordingWriter, path, n=40)
    rec = read_recording(path)
    want = list(_samples(40))
    gyro = np.array([s[TOPIC_IMU]["gyro"] for s in want])
    assert np.array_equal(rec.imu_gyro, gyro, equal_nan=True)
    assert np.isnan(rec.imu_gyro).any() and np.isposinf(rec.imu_gyro).any() and np.isneginf(rec.imu_gyro).any()
    assert rec.t.tolist() == [s[TOPIC_COMMAND]["t"] for s in want]
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    st = summary.statistics
    assert st.message_count == 40 * 7 + 1
    assert st.message_start_time == 0 and st.message_end_time == int(round(want[-1][TOPIC_COMMAND]["t"] * 1e9))
    by_topic = {summary.channels[c].topic: n for c, n in st.channel_message_counts.items()}
    assert by_topic == {**{tp: 40 for tp in TOPICS if tp != TOPIC_EVENTS}, TOPIC_COMMAND: 40, TOPIC_EVENTS: 1}


def test_a_file_cut_mid_run_keeps_its_complete_samples(tmp_path):
    path = tmp_path / "cut.mcap"
    w = RecordingWriter(path, {"program": "test"}, topics=TOPICS, flush_every=5)
    for s in list(_samples(23)):
        w.write_sample(s)
    w._file.flush()  # the process dies here: no summary, the last 3 samples maybe unflushed
    rec = read_recording(path)
    assert len(rec) == 23 and rec.truncated
    w.close()
