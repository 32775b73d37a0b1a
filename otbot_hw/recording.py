"""Recordings of Otbot runs in MCAP (the container ROS 2 bags and Foxglove use).

One file holds one run: a metadata record ``otbot`` and, for every sample k, one
JSON message on each recorded topic, all stamped with the same time t_k. The
layout is specified in ``docs/recording-format.md``; in short:

==================  ===============================================  ==========
topic               payload (JSON)                                   required
==================  ===============================================  ==========
/otbot/command      t (s), torque [tau_r, tau_l, tau_p] (N m)        yes
/otbot/joints       t, position [phi_r, phi_l, phi_p] (rad),         no
                    velocity (rad/s)
/otbot/imu          t, accel [x, y, z] (m/s^2), gyro [x, y, z]       no
                    (rad/s), platform frame B''
/otbot/truth        t, q (6), qd (6), force [f_x, f_y] (N, ground)   no (sim)
/otbot/estimate     t, pose [x, y, alpha] (m, rad), twist (m/s,      no (loop)
                    rad/s), std (6) of pose and twist, gyro_bias
/otbot/reference    t, p [x, y, alpha], pd, pdd (desired motion)     no (loop)
/otbot/events       t, kind, text: sparse (mode changes, faults,     no (loop)
                    saturation), not one per sample
==================  ===============================================  ==========

Messages are written unchunked and uncompressed and flushed every few samples,
so a file cut short (process killed mid-write) still loads every complete sample.
Floats are written with Python's shortest round-trip repr: loading gives back the
exact float64 values.
"""
from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

import numpy as np

FORMAT_NAME = "otbot-recording"
FORMAT_VERSION = 1
PROFILE = "otbot"

#: Metadata ``source`` values for the robot a recording comes from (``source_metadata``).
SOURCE_SIMULATION = "simulation"  # the model simulated in this process, no bus
SOURCE_BUS_SIMULATION = "bus-simulation"  # the simulated robot behind the CANopen drivers
SOURCE_ROBOT = "robot"  # the configured bus: the robot that is there


def source_metadata(*, simulated: bool | None = None, bus: bool = False, program: str | None = None) -> dict:
    """The ``source`` entry of a recording's metadata, built here only (docs/recording-format.md §2):
    from what the robot was (``simulated``; ``bus``: behind the CANopen drivers) -- "simulation",
    "bus-simulation" or "robot" -- or, when that is not what the producer knows, the producing
    ``program``'s name ("loop", "otbot daemon", "ros2 bag"). ValueError for neither or both."""
    if (simulated is None) == (program is None):
        raise ValueError("a recording's source is either what the robot was (simulated, bus) or a program name")
    if program is not None:
        if not isinstance(program, str) or not program.strip():
            raise ValueError(f"a recording's source program must be a non-empty name, got {program!r}")
        return {"source": program}
    if not simulated:
        return {"source": SOURCE_ROBOT}
    return {"source": SOURCE_BUS_SIMULATION if bus else SOURCE_SIMULATION}


#: The 8 bytes every MCAP file starts (and ends) with.
MCAP_MAGIC = b"\x89MCAP0\r\n"

TOPIC_COMMAND = "/otbot/command"
TOPIC_JOINTS = "/otbot/joints"
TOPIC_IMU = "/otbot/imu"
TOPIC_TRUTH = "/otbot/truth"
TOPIC_ESTIMATE = "/otbot/estimate"
TOPIC_REFERENCE = "/otbot/reference"
TOPIC_EVENTS = "/otbot/events"
TOPIC_PAYLOAD = "/otbot/payload"
#: Topics carried once per sample (every other topic of ``TOPICS`` is sparse).
SAMPLE_TOPICS = ("/otbot/command", "/otbot/joints", "/otbot/imu", "/otbot/truth", "/otbot/estimate", "/otbot/reference",
                 "/otbot/payload")

_VEC3 = {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3}
_VEC6 = {"type": "array", "items": {"type": "number"}, "minItems": 6, "maxItems": 6}
_VEC2 = {"type": "array", "items": {"type": "number"}, "minItems": 2, "maxItems": 2}

#: topic -> (schema name, JSON schema of the payload)
TOPICS: dict[str, tuple[str, dict]] = {
    TOPIC_COMMAND: ("otbot.Command", {
        "type": "object", "required": ["t", "torque"],
        "properties": {"t": {"type": "number", "description": "s since start"},
                       "torque": {**_VEC3, "description": "tau_r, tau_l, tau_p in N m, held until next t"}}}),
    TOPIC_JOINTS: ("otbot.Joints", {
        "type": "object", "required": ["t", "position", "velocity"],
        "properties": {"t": {"type": "number"},
                       "position": {**_VEC3, "description": "phi_r, phi_l, phi_p in rad"},
                       "velocity": {**_VEC3, "description": "rad/s"}}}),
    TOPIC_IMU: ("otbot.Imu", {
        "type": "object", "required": ["t", "accel", "gyro"],
        "properties": {"t": {"type": "number"},
                       "accel": {**_VEC3, "description": "specific force, m/s^2, platform frame B''"},
                       "gyro": {**_VEC3, "description": "angular rate, rad/s, platform frame B''"}}}),
    TOPIC_TRUTH: ("otbot.Truth", {
        "type": "object", "required": ["t", "q", "qd"],
        "properties": {"t": {"type": "number"},
                       "q": {**_VEC6, "description": "x, y (m), alpha, phi_r, phi_l, phi_p (rad)"},
                       "qd": {**_VEC6, "description": "time derivative of q"},
                       "force": {**_VEC2, "description": "f_x, f_y at the pivot, N, ground frame"}}}),
    TOPIC_ESTIMATE: ("otbot.Estimate", {
        "type": "object", "required": ["t", "pose", "twist", "std"],
        "properties": {"t": {"type": "number"},
                       "pose": {**_VEC3, "description": "estimated x, y (m), alpha (rad) of the platform, frame B"},
                       "twist": {**_VEC3, "description": "estimated x_dot, y_dot (m/s), alpha_dot (rad/s)"},
                       "std": {**_VEC6, "description": "standard deviations of pose and twist (same units)"},
                       "gyro_bias": {"type": "number", "description": "estimated gyro z bias, rad/s"}}}),
    TOPIC_REFERENCE: ("otbot.Reference", {
        "type": "object", "required": ["t", "p", "pd"],
        "properties": {"t": {"type": "number"},
                       "p": {**_VEC3, "description": "desired x, y (m), alpha (rad), frame B"},
                       "pd": {**_VEC3, "description": "desired velocity, m/s, m/s, rad/s"},
                       "pdd": {**_VEC3, "description": "desired acceleration, m/s^2, m/s^2, rad/s^2"}}}),
    TOPIC_PAYLOAD: ("otbot.Payload", {
        "type": "object", "required": ["t", "value", "std", "used"],
        "properties": {"t": {"type": "number"},
                       "value": {"type": "array", "items": {"type": "number"}, "minItems": 4, "maxItems": 4,
                                 "description": "online estimate of platform + load m_p (kg), I_p (kg m^2), x_F, y_F (m, B'')"},
                       "std": {"type": "array", "items": {"type": "number"}, "minItems": 4, "maxItems": 4,
                               "description": "its standard deviations, same units"},
                       "used": {"type": "array", "items": {"type": "number"}, "minItems": 4, "maxItems": 4,
                                "description": "m_p, I_p, x_F, y_F the control law uses"},
                       "state": {"type": "string", "description": "file, adapting, reestimating, fault"}}}),
    TOPIC_EVENTS: ("otbot.Event", {
        "type": "object", "required": ["t", "kind", "text"],
        "properties": {"t": {"type": "number", "description": "s since start (the sample it belongs to)"},
                       "kind": {"type": "string", "description": "mode, fault, saturation, note, ..."},
                       "text": {"type": "string", "description": "what happened, in words"}}}),
}

UNITS = {
    "t": "s", "torque": "N m", "position": "rad", "velocity": "rad/s", "accel": "m/s^2",
    "gyro": "rad/s", "q": "m, m, rad, rad, rad, rad", "qd": "m/s, m/s, rad/s, rad/s, rad/s, rad/s",
    "force": "N",
}
FRAMES = {
    "ground": "B: inertial, z up; x, y of q are the pivot P in B",
    "platform": "B'': origin at the pivot P, x along 1'', y along 2'', z up; rotated by alpha from B",
    "imu": "accel and gyro are expressed in B''",
    "joints": "phi_r, phi_l: wheel angles relative to the chassis, positive when the wheel drives the "
              "robot forward along 1'; phi_p: platform angle relative to the chassis, counter-clockwise",
}


class RecordingError(ValueError):
    """A recording is unreadable or inconsistent; the message says what and where."""


@dataclass
class Recording:
    """A run as numpy arrays (N samples). Optional channels are None when not recorded.

    t (N,) s; torque (N, 3) N m held on [t_k, t_k+1); joint_pos/joint_vel (N, 3)
    rad, rad/s; imu_accel/imu_gyro (N, 3) m/s^2, rad/s in B''; truth_q/truth_qd
    (N, 6) and truth_force (N, 2) N for simulated runs; estimate_pose/estimate_twist (N, 3),
    estimate_std (N, 6), estimate_gyro_bias (N,) from a loop's estimator; reference_p/pd/pdd
    (N, 3) the desired motion; payload_value/payload_std/payload_used (N, 4) the online payload
    estimate m_p, I_p, x_F, y_F, its std and what the law used (``/otbot/payload``); events: the sparse ``/otbot/events`` messages (dicts with t, kind,
    text); metadata: see ``docs/recording-format.md``.
    """

    t: np.ndarray
    torque: np.ndarray
    joint_pos: np.ndarray | None = None
    joint_vel: np.ndarray | None = None
    imu_accel: np.ndarray | None = None
    imu_gyro: np.ndarray | None = None
    truth_q: np.ndarray | None = None
    truth_qd: np.ndarray | None = None
    truth_force: np.ndarray | None = None
    estimate_pose: np.ndarray | None = None
    estimate_twist: np.ndarray | None = None
    estimate_std: np.ndarray | None = None
    estimate_gyro_bias: np.ndarray | None = None
    reference_p: np.ndarray | None = None
    reference_pd: np.ndarray | None = None
    reference_pdd: np.ndarray | None = None
    payload_value: np.ndarray | None = None
    payload_std: np.ndarray | None = None
    payload_used: np.ndarray | None = None
    events: list[dict[str, Any]] = field(default_factory=list)
    metadata: dict[str, Any] = field(default_factory=dict)
    truncated: bool = False

    def __len__(self) -> int:
        return len(self.t)

    @property
    def sample_period(self) -> float:
        """Nominal sample period (s) from the metadata, else the median time step."""
        if "sample_period" in self.metadata:
            return float(self.metadata["sample_period"])
        if len(self.t) < 2:
            raise RecordingError("recording has fewer than 2 samples: no sample period")
        return float(np.median(np.diff(self.t)))

    def channels(self) -> list[str]:
        """Topics present in this recording."""
        out = [TOPIC_COMMAND]
        if self.joint_pos is not None:
            out.append(TOPIC_JOINTS)
        if self.imu_accel is not None:
            out.append(TOPIC_IMU)
        if self.truth_q is not None:
            out.append(TOPIC_TRUTH)
        if self.estimate_pose is not None:
            out.append(TOPIC_ESTIMATE)
        if self.reference_p is not None:
            out.append(TOPIC_REFERENCE)
        if self.payload_value is not None:
            out.append(TOPIC_PAYLOAD)
        if self.events:
            out.append(TOPIC_EVENTS)
        return out

    def sample(self, k: int) -> dict[str, dict[str, Any]]:
        """The messages of sample k, keyed by topic."""
        msgs: dict[str, dict[str, Any]] = {TOPIC_COMMAND: {"t": float(self.t[k]), "torque": self.torque[k].tolist()}}
        if self.joint_pos is not None:
            msgs[TOPIC_JOINTS] = {"t": float(self.t[k]), "position": self.joint_pos[k].tolist(),
                                  "velocity": self.joint_vel[k].tolist()}
        if self.imu_accel is not None:
            msgs[TOPIC_IMU] = {"t": float(self.t[k]), "accel": self.imu_accel[k].tolist(),
                               "gyro": self.imu_gyro[k].tolist()}
        if self.truth_q is not None:
            m = {"t": float(self.t[k]), "q": self.truth_q[k].tolist(), "qd": self.truth_qd[k].tolist()}
            if self.truth_force is not None:
                m["force"] = self.truth_force[k].tolist()
            msgs[TOPIC_TRUTH] = m
        if self.estimate_pose is not None:
            m = {"t": float(self.t[k]), "pose": self.estimate_pose[k].tolist(),
                 "twist": self.estimate_twist[k].tolist(), "std": self.estimate_std[k].tolist()}
            if self.estimate_gyro_bias is not None:
                m["gyro_bias"] = float(self.estimate_gyro_bias[k])
            msgs[TOPIC_ESTIMATE] = m
        if self.reference_p is not None:
            m = {"t": float(self.t[k]), "p": self.reference_p[k].tolist(), "pd": self.reference_pd[k].tolist()}
            if self.reference_pdd is not None:
                m["pdd"] = self.reference_pdd[k].tolist()
            msgs[TOPIC_REFERENCE] = m
        if self.payload_value is not None:
            msgs[TOPIC_PAYLOAD] = {"t": float(self.t[k]), "value": self.payload_value[k].tolist(),
                                   "std": self.payload_std[k].tolist(), "used": self.payload_used[k].tolist()}
        return msgs


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
        self._count = 0
        self._last_t: float | None = None
        self._flush_every = max(1, int(flush_every))
        self._closed = False
        self._writer.flush()

    def write_sample(self, messages: dict[str, dict[str, Any]]) -> None:
        """Write one sample: ``{topic: payload}`` for the command and every registered per-sample
        topic (``SAMPLE_TOPICS``); sparse topics go through ``write_event``."""
        missing = {tp for tp in self._channels if tp in SAMPLE_TOPICS} - set(messages)
        if missing:
            raise ValueError(f"sample {self._count} lacks topic(s) {sorted(missing)}")
        t = messages[TOPIC_COMMAND]["t"]
        if not math.isfinite(t) or t < 0:
            raise ValueError(f"sample {self._count}: time must be finite and >= 0, got {t}")
        if self._last_t is not None and not t > self._last_t:
            raise ValueError(f"sample {self._count}: time {t} s does not increase (previous {self._last_t} s)")
        sample_topics = [tp for tp in self._channels if tp in SAMPLE_TOPICS]
        for topic in sample_topics:
            if messages[topic].get("t") != t:
                raise ValueError(f"sample {self._count}: {topic} has t = {messages[topic].get('t')!r}, but "
                                 f"{TOPIC_COMMAND} has t = {t}: all topics of a sample share its time")
        self._last_t = t
        stamp = int(round(t * 1e9))
        for topic in sample_topics:
            data = json.dumps(messages[topic], allow_nan=True).encode()
            self._writer.add_message(channel_id=self._channels[topic], log_time=stamp, publish_time=stamp,
                                     data=data, sequence=self._count)
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


def write_recording(path: str | Path, rec: Recording) -> None:
    """Write a whole ``Recording`` to ``path`` (ValueError if its arrays do not fit together)."""
    _check_shapes(rec)
    meta = dict(rec.metadata)
    for key in ("format", "format_version", "units", "frames"):
        meta.pop(key, None)
    with RecordingWriter(path, meta, topics=rec.channels(), flush_every=1000) as w:
        write_samples_and_events(w, rec)


def write_samples_and_events(writer, rec: "Recording") -> None:
    """Write ``rec``'s samples and events, in time order, through a streaming writer (``RecordingWriter``
    or any writer with the same ``write_sample``/``write_event``): each event after the sample it follows."""
    events = sorted(rec.events, key=lambda e: e["t"])
    j = 0
    for k in range(len(rec)):
        writer.write_sample(rec.sample(k))
        while j < len(events) and (k + 1 == len(rec) or events[j]["t"] < rec.t[k + 1]):
            e = events[j]
            writer.write_event(e["t"], e["kind"], e["text"],
                               **{a: b for a, b in e.items() if a not in ("t", "kind", "text")})
            j += 1


def _records(path: Path) -> tuple[list, bool]:
    """All readable MCAP records; ``truncated`` is True when the file ends early."""
    from mcap.exceptions import McapError
    from mcap.stream_reader import StreamReader

    records = []
    truncated = False
    if path.is_dir():
        raise RecordingError(f"{path}: is a folder, expected an MCAP recording file")
    try:
        with open(path, "rb") as f:
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
    if not path.exists():
        raise RecordingError(f"{path}: no such file")
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
    if TOPIC_JOINTS in present:
        rec.joint_pos = field_array(TOPIC_JOINTS, "position", 3)
        rec.joint_vel = field_array(TOPIC_JOINTS, "velocity", 3)
    if TOPIC_IMU in present:
        rec.imu_accel = field_array(TOPIC_IMU, "accel", 3)
        rec.imu_gyro = field_array(TOPIC_IMU, "gyro", 3)
    if TOPIC_TRUTH in present:
        rec.truth_q = field_array(TOPIC_TRUTH, "q", 6)
        rec.truth_qd = field_array(TOPIC_TRUTH, "qd", 6)
        rec.truth_force = field_array(TOPIC_TRUTH, "force", 2, required=False)
    if TOPIC_ESTIMATE in present:
        rec.estimate_pose = field_array(TOPIC_ESTIMATE, "pose", 3)
        rec.estimate_twist = field_array(TOPIC_ESTIMATE, "twist", 3)
        rec.estimate_std = field_array(TOPIC_ESTIMATE, "std", 6)
        rows = data.get(TOPIC_ESTIMATE, [])[:n]
        if rows and "gyro_bias" in rows[0]:
            rec.estimate_gyro_bias = np.array([float(m.get("gyro_bias", np.nan)) for m in rows])
    if TOPIC_REFERENCE in present:
        rec.reference_p = field_array(TOPIC_REFERENCE, "p", 3)
        rec.reference_pd = field_array(TOPIC_REFERENCE, "pd", 3)
        rec.reference_pdd = field_array(TOPIC_REFERENCE, "pdd", 3, required=False)
    if TOPIC_PAYLOAD in present:
        rec.payload_value = field_array(TOPIC_PAYLOAD, "value", 4)
        rec.payload_std = field_array(TOPIC_PAYLOAD, "std", 4)
        rec.payload_used = field_array(TOPIC_PAYLOAD, "used", 4)
    for k, m in enumerate(data.get(TOPIC_EVENTS, [])):
        if (not isinstance(m, dict) or isinstance(m.get("t"), bool) or not isinstance(m.get("t"), (int, float))
                or not isinstance(m.get("kind"), str) or not isinstance(m.get("text"), str)):
            raise RecordingError(f"{path}: {TOPIC_EVENTS} message {k} needs t (number), kind and text (strings); "
                                 f"got {str(m)[:80]}")
        rec.events.append(m)
    return rec
