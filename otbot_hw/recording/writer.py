"""Writing recordings: ``RecordingWriter`` streams samples and events into an MCAP file (unchunked,
uncompressed, flushed every few samples: a file cut short keeps every complete sample);
``write_recording`` writes a whole ``Recording``.
"""
from __future__ import annotations

import json
import math
import struct
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from otbot_hw.recording.format import (
    FORMAT_NAME, FORMAT_VERSION, FRAMES, PROFILE, SAMPLE_TOPICS, TOPIC_COMMAND, TOPIC_EVENTS, TOPICS, UNITS,
    Recording)


# An MCAP Message record as the mcap library writes it unchunked: opcode 0x05, record length (u64),
# channel id (u16), sequence (u32), log time and publish time (u64 ns), then the data.
_MESSAGE_HEADER = struct.Struct("<BQHIQQ")
_MESSAGE_FIXED = _MESSAGE_HEADER.size - 9  # record length = this + len(data)
# json.dumps's own encoder (C, floats by their repr, NaN/Infinity written as today) without the
# circular-reference bookkeeping a sample's flat dicts do not need: the same text
_encode = json.JSONEncoder(check_circular=False).encode


def _encode_metadata(meta: dict[str, Any]) -> dict[str, str]:
    """MCAP metadata values are strings: each value is stored as JSON text."""
    return {str(k): json.dumps(v, allow_nan=False) for k, v in meta.items()}


class RecordingWriter:
    """Streams samples into an MCAP file; usable as a context manager.

    ``topics`` lists the optional topics the run will carry (command is always
    there). Data are flushed to disk every ``flush_every`` samples, so a crash
    loses at most that many samples.
    """

    def __init__(self, path: str | Path, metadata: dict[str, Any], topics: Iterable[str] = (),
                 flush_every: int = 10):
        from mcap.writer import CompressionType, Writer

        self.path = Path(path)
        self._file = open(self.path, "wb")
        self._writer = Writer(self._file, compression=CompressionType.NONE, use_chunking=False)
        self._writer.start(profile=PROFILE, library=f"otbot-hw {FORMAT_NAME} v{FORMAT_VERSION}")
        meta = {"format": FORMAT_NAME, "format_version": FORMAT_VERSION, "units": UNITS,
                "frames": FRAMES, **metadata}
        self._writer.add_metadata("otbot", _encode_metadata(meta))
        self._channels: dict[str, int] = {}
        for topic in [TOPIC_COMMAND, *[t for t in topics if t != TOPIC_COMMAND]]:
            if topic not in TOPICS:
                raise ValueError(f"unknown topic '{topic}' (known: {', '.join(TOPICS)})")
            name, schema = TOPICS[topic]
            sid = self._writer.register_schema(name=name, encoding="jsonschema",
                                               data=json.dumps(schema).encode())
            self._channels[topic] = self._writer.register_channel(topic=topic, message_encoding="json",
                                                                  schema_id=sid)
        self._sample_channels = [(tp, ch) for tp, ch in self._channels.items() if tp in SAMPLE_TOPICS]
        self._sample_set = frozenset(tp for tp, _ in self._sample_channels)
        # samples are framed here and written in one call (what add_message would write, byte for
        # byte); the summary's statistics are the mcap writer's own, kept up to date per sample
        self._stats = getattr(self._writer, "_Writer__statistics", None)
        self._direct = (self._stats is not None and not getattr(self._writer, "_Writer__enable_data_crcs", True)
                        and getattr(self._writer, "_Writer__chunk_builder", True) is None)
        self._count = 0
        self._last_t: float | None = None
        self._flush_every = max(1, int(flush_every))
        self._closed = False
        self._writer.flush()

    def write_sample(self, messages: dict[str, dict[str, Any]]) -> None:
        """Write one sample: ``{topic: payload}`` for the command and every registered per-sample
        topic (``SAMPLE_TOPICS``); sparse topics go through ``write_event``."""
        missing = self._sample_set.difference(messages)
        if missing:
            raise ValueError(f"sample {self._count} lacks topic(s) {sorted(missing)}")
        t = messages[TOPIC_COMMAND]["t"]
        if not math.isfinite(t) or t < 0:
            raise ValueError(f"sample {self._count}: time must be finite and >= 0, got {t}")
        if self._last_t is not None and not t > self._last_t:
            raise ValueError(f"sample {self._count}: time {t} s does not increase (previous {self._last_t} s)")
        chans = self._sample_channels
        for topic, _ in chans:
            if messages[topic].get("t") != t:
                raise ValueError(f"sample {self._count}: {topic} has t = {messages[topic].get('t')!r}, but "
                                 f"{TOPIC_COMMAND} has t = {t}: all topics of a sample share its time")
        self._last_t = t
        stamp = int(round(t * 1e9))
        seq = self._count
        if not self._direct:
            for topic, ch in chans:
                self._writer.add_message(channel_id=ch, log_time=stamp, publish_time=stamp,
                                         data=_encode(messages[topic]).encode(), sequence=seq)
        else:
            parts = []
            pack = _MESSAGE_HEADER.pack
            for topic, ch in chans:
                data = _encode(messages[topic]).encode()
                parts.append(pack(0x05, _MESSAGE_FIXED + len(data), ch, seq, stamp, stamp))
                parts.append(data)
            self._file.write(b"".join(parts))
            st = self._stats
            if st.message_count == 0:
                st.message_start_time = stamp
            elif stamp < st.message_start_time:
                st.message_start_time = stamp
            if stamp > st.message_end_time:
                st.message_end_time = stamp
            counts = st.channel_message_counts
            for _, ch in chans:
                counts[ch] += 1
            st.message_count += len(chans)
        self._count += 1
        if self._count % self._flush_every == 0:
            self.flush()

    def write_event(self, t: float, kind: str, text: str, **extra: Any) -> None:
        """Write one sparse ``/otbot/events`` message (the topic must have been registered):
        at t (s, the sample it belongs to) something of ``kind`` happened, said in ``text``."""
        if TOPIC_EVENTS not in self._channels:
            raise ValueError(f"{TOPIC_EVENTS} was not registered with this writer")
        if not math.isfinite(t) or t < 0:
            raise ValueError(f"event time must be finite and >= 0, got {t}")
        stamp = int(round(t * 1e9))
        data = json.dumps({"t": float(t), "kind": str(kind), "text": str(text), **extra}, allow_nan=True).encode()
        self._writer.add_message(channel_id=self._channels[TOPIC_EVENTS], log_time=stamp, publish_time=stamp,
                                 data=data, sequence=self._count)
        self._writer.flush()

    @property
    def samples(self) -> int:
        """Samples written so far."""
        return self._count

    def flush(self) -> None:
        """Push everything written so far to the operating system."""
        self._writer.flush()

    def close(self) -> None:
        """Write the MCAP summary and footer and close the file (closed also when writing them fails,
        e.g. on a full disk: the error is raised, the file descriptor is not leaked)."""
        if not self._closed:
            self._closed = True
            try:
                self._writer.finish()
            except BaseException:
                try:
                    self._file.close()
                except OSError:
                    pass  # its buffer cannot be written either: the first error is the one raised
                raise
            self._file.close()

    def __enter__(self) -> "RecordingWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _check_shapes(rec: Recording) -> None:
    """ValueError naming the field when the arrays of ``rec`` do not fit together."""
    n = len(rec.t)
    widths = {"torque": 3, "joint_pos": 3, "joint_vel": 3, "imu_accel": 3, "imu_gyro": 3,
              "truth_q": 6, "truth_qd": 6, "truth_force": 2, "estimate_pose": 3, "estimate_twist": 3,
              "estimate_std": 6, "reference_p": 3, "reference_pd": 3, "reference_pdd": 3}
    if np.shape(rec.t) != (n,):
        raise ValueError(f"recording: t must be a 1-D array, got shape {np.shape(rec.t)}")
    for name, width in widths.items():
        arr = getattr(rec, name)
        if arr is not None and np.shape(arr) != (n, width):
            raise ValueError(f"recording: {name} must have shape ({n}, {width}), got {np.shape(arr)}")
    for a, b in (("joint_pos", "joint_vel"), ("imu_accel", "imu_gyro"), ("truth_q", "truth_qd")):
        if (getattr(rec, a) is None) != (getattr(rec, b) is None):
            raise ValueError(f"recording: {a} and {b} go together (one topic); got only one of them")
    if rec.truth_force is not None and rec.truth_q is None:
        raise ValueError("recording: truth_force needs truth_q and truth_qd")
    est = [getattr(rec, a) is None for a in ("estimate_pose", "estimate_twist", "estimate_std")]
    if any(est) and not all(est):
        raise ValueError("recording: estimate_pose, estimate_twist and estimate_std go together (one topic)")
    if (rec.reference_p is None) != (rec.reference_pd is None):
        raise ValueError("recording: reference_p and reference_pd go together (one topic)")
    if rec.estimate_gyro_bias is not None and np.shape(rec.estimate_gyro_bias) != (n,):
        raise ValueError(f"recording: estimate_gyro_bias must have shape ({n},)")


def write_recording(path: str | Path, rec: Recording, progress=None) -> None:
    """Write a whole ``Recording`` to ``path`` (ValueError if its arrays do not fit together);
    ``progress(done, n)`` is called every 100000 samples and at the end."""
    _check_shapes(rec)
    meta = dict(rec.metadata)
    for key in ("format", "format_version", "units", "frames"):
        meta.pop(key, None)
    with RecordingWriter(path, meta, topics=rec.channels(), flush_every=1000) as w:
        write_samples_and_events(w, rec, progress)


def write_samples_and_events(writer, rec: "Recording", progress=None) -> None:
    """Write ``rec``'s samples and events, in time order, through a streaming writer (``RecordingWriter``
    or any writer with the same ``write_sample``/``write_event``): each event after the sample it follows."""
    events = sorted(rec.events, key=lambda e: e["t"])
    j = 0
    n = len(rec)
    for k in range(n):
        if progress is not None and k % 100_000 == 0 and k:
            progress(k, n)
        writer.write_sample(rec.sample(k))
        while j < len(events) and (k + 1 == len(rec) or events[j]["t"] < rec.t[k + 1]):
            e = events[j]
            writer.write_event(e["t"], e["kind"], e["text"],
                               **{a: b for a, b in e.items() if a not in ("t", "kind", "text")})
            j += 1
    if progress is not None:
        progress(n, n)
