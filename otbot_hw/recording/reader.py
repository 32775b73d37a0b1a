"""Reading recordings: ``read_recording`` loads an MCAP file into a ``Recording``, checking what it reads
(``RecordingError`` naming the file and what is wrong); a file cut short yields its complete samples.
"""
from __future__ import annotations

import json
import math
import struct
from pathlib import Path
from typing import Any

import numpy as np

from otbot_hw.input_files import open_input
from otbot_hw.recording.format import (
    FORMAT_NAME, FORMAT_VERSION, MCAP_MAGIC, SAMPLE_TOPICS, TOPIC_COMMAND, TOPIC_ESTIMATE, TOPIC_EVENTS, TOPIC_IMU,
    TOPIC_JOINTS, TOPIC_PAYLOAD, TOPIC_REFERENCE, TOPIC_TRUTH, TOPICS, Recording, RecordingError)

#: per-sample topic -> the ``Recording`` fields read from its messages: (field, message key, width, required)
FIELDS: dict[str, tuple[tuple[str, str, int, bool], ...]] = {
    TOPIC_JOINTS: (("joint_pos", "position", 3, True), ("joint_vel", "velocity", 3, True)),
    TOPIC_IMU: (("imu_accel", "accel", 3, True), ("imu_gyro", "gyro", 3, True)),
    TOPIC_TRUTH: (("truth_q", "q", 6, True), ("truth_qd", "qd", 6, True), ("truth_force", "force", 2, False)),
    TOPIC_ESTIMATE: (("estimate_pose", "pose", 3, True), ("estimate_twist", "twist", 3, True),
                     ("estimate_std", "std", 6, True)),
    TOPIC_REFERENCE: (("reference_p", "p", 3, True), ("reference_pd", "pd", 3, True),
                      ("reference_pdd", "pdd", 3, False)),
    TOPIC_PAYLOAD: (("payload_value", "value", 4, True), ("payload_std", "std", 4, True),
                    ("payload_used", "used", 4, True)),
}


def _records(path: Path) -> tuple[list, bool]:
    """All readable MCAP records; ``truncated`` is True when the file ends early."""
    from mcap.exceptions import McapError
    from mcap.stream_reader import StreamReader

    records = []
    truncated = False
    if path.is_dir():
        raise RecordingError(f"{path}: is a folder, expected an MCAP recording file")
    try:
        with open_input(path) as f:
            magic = f.read(len(MCAP_MAGIC))
            if not magic:
                raise RecordingError(f"{path}: empty file, expected an MCAP recording")
            if magic != MCAP_MAGIC[:len(magic)]:
                raise RecordingError(f"{path}: not an MCAP recording (the file does not start with the MCAP "
                                     "magic bytes)")
            if len(magic) < len(MCAP_MAGIC):
                raise RecordingError(f"{path}: MCAP file cut short inside its magic bytes (truncated)")
            f.seek(0)
            reader = StreamReader(f, record_size_limit=64 * 2 ** 20)
            try:
                for rec in reader.records:
                    records.append(rec)
            except (McapError, EOFError, ValueError, IndexError, struct.error) as exc:
                if len(records) <= 1:  # at most the header: nothing to load
                    why = f": {exc}" if str(exc) else ""
                    raise RecordingError(f"{path}: MCAP file cut short before its first record "
                                         f"(truncated{why})") from None
                truncated = True
    except OSError as exc:
        raise RecordingError(f"{path}: cannot read: {exc.strerror or exc}") from None
    return records, truncated


def read_recording(path: str | Path) -> Recording:
    """Load a recording into numpy arrays; a truncated file yields its complete samples."""
    from mcap.records import Channel, Footer, Message, Metadata

    path = Path(path)
    try:
        path.stat()
    except FileNotFoundError:  # a dangling link too; a loop of links is said by the open
        raise RecordingError(f"{path}: no such file") from None
    except OSError:
        pass
    records, truncated = _records(path)
    if not any(isinstance(r, Footer) for r in records):
        truncated = True
    meta: dict[str, Any] = {}
    channels: dict[int, str] = {}
    data: dict[str, list[dict]] = {}
    for r in records:
        if isinstance(r, Metadata) and r.name == "otbot":
            for k, v in r.metadata.items():
                try:
                    meta[k] = json.loads(v)
                except json.JSONDecodeError:
                    raise RecordingError(f"{path}: metadata '{k}' is not JSON text: {v[:60]!r}") from None
        elif isinstance(r, Channel):
            if r.topic in TOPICS:
                if r.message_encoding != "json":
                    raise RecordingError(f"{path}: topic {r.topic} has message encoding "
                                         f"'{r.message_encoding}', expected 'json'")
                other = [i for i, tp in channels.items() if tp == r.topic and i != r.id]
                if other:
                    raise RecordingError(f"{path}: topic {r.topic} is registered on two channels "
                                         f"({other[0]} and {r.id}); one channel per topic")
                channels[r.id] = r.topic
        elif isinstance(r, Message) and r.channel_id in channels:
            try:
                msg = json.loads(r.data)
            except (json.JSONDecodeError, UnicodeDecodeError):
                raise RecordingError(f"{path}: a message on {channels[r.channel_id]} at log time "
                                     f"{r.log_time} ns is not JSON") from None
            data.setdefault(channels[r.channel_id], []).append(msg)
    if meta.get("format", FORMAT_NAME) != FORMAT_NAME:
        raise RecordingError(f"{path}: metadata format is '{meta.get('format')}', expected '{FORMAT_NAME}'")
    version = meta.get("format_version", FORMAT_VERSION)
    if isinstance(version, bool) or not isinstance(version, int) or not 1 <= version <= FORMAT_VERSION:
        raise RecordingError(f"{path}: metadata format_version {version!r} is not supported "
                             f"(this reader knows versions 1..{FORMAT_VERSION})")
    if TOPIC_COMMAND not in channels.values():
        if truncated:
            raise RecordingError(f"{path}: MCAP file cut short before its first sample (truncated)")
        raise RecordingError(f"{path}: no {TOPIC_COMMAND} channel: not an Otbot recording")
    present = sorted((tp for tp in set(channels.values()) if tp in SAMPLE_TOPICS), key=list(TOPICS).index)
    counts = {tp: len(data.get(tp, [])) for tp in present}
    n = min(counts.values())
    if any(c != n for c in counts.values()):
        if not truncated:  # a complete file must carry every topic in every sample
            short = min(counts, key=counts.get)
            raise RecordingError(f"{path}: {short} has {counts[short]} messages but {TOPIC_COMMAND} has "
                                 f"{counts[TOPIC_COMMAND]}: every topic needs one message per sample")
        # a file cut short: keep the complete samples only

    def field_array(topic: str, key: str, width: int, required: bool = True) -> np.ndarray | None:
        rows = data.get(topic, [])[:n]
        if not required and rows and isinstance(rows[0], dict) and key not in rows[0]:
            return None
        arr = np.empty((n, width))
        for k, m in enumerate(rows):
            v = m.get(key) if isinstance(m, dict) else None
            if (not isinstance(v, list) or len(v) != width
                    or not all(isinstance(e, (int, float)) and not isinstance(e, bool) for e in v)):
                raise RecordingError(f"{path}: {topic} messages need '{key}' as {width} numbers; "
                                     f"sample {k} has {str(v)[:80]}")
            arr[k] = v
        return arr

    def times(topic: str) -> np.ndarray:
        out = np.empty(n)
        for k, m in enumerate(data.get(topic, [])[:n]):
            v = m.get("t") if isinstance(m, dict) else None
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise RecordingError(f"{path}: {topic} sample {k}: 't' must be a finite number of "
                                     f"seconds, got {v!r} (non-finite sample time)")
            out[k] = v
        return out

    t = times(TOPIC_COMMAND)
    for tp in present:
        tt = times(tp)
        bad = np.nonzero(tt != t)[0]
        if len(bad):
            raise RecordingError(f"{path}: {tp} sample {bad[0]} has t = {tt[bad[0]]}, but "
                                 f"{TOPIC_COMMAND} has t = {t[bad[0]]}: topics must share sample times")
    if n > 1 and np.any(np.diff(t) <= 0):
        k = int(np.argmax(np.diff(t) <= 0)) + 1
        raise RecordingError(f"{path}: sample times must increase; sample {k} has t = {t[k]} after {t[k - 1]}")
    rec = Recording(t=t, torque=field_array(TOPIC_COMMAND, "torque", 3), metadata=meta, truncated=truncated)
    for topic, fields in FIELDS.items():
        if topic not in present:
            continue
        for attr, key, width, required in fields:
            setattr(rec, attr, field_array(topic, key, width, required))
        rows = data.get(topic, [])[:n]
        if topic == TOPIC_ESTIMATE and rows and "gyro_bias" in rows[0]:
            rec.estimate_gyro_bias = np.array([float(m.get("gyro_bias", np.nan)) for m in rows])
    for k, m in enumerate(data.get(TOPIC_EVENTS, [])):
        if (not isinstance(m, dict) or isinstance(m.get("t"), bool) or not isinstance(m.get("t"), (int, float))
                or not isinstance(m.get("kind"), str) or not isinstance(m.get("text"), str)):
            raise RecordingError(f"{path}: {TOPIC_EVENTS} message {k} needs t (number), kind and text (strings); "
                                 f"got {str(m)[:80]}")
        rec.events.append(m)
    return rec
