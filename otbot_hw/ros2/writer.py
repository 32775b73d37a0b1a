"""A rosbag2 writer that streams a run as it happens and survives being killed.

``BagWriter(folder, metadata, topics)`` takes the same calls as ``otbot_hw.recording.RecordingWriter``
(``write_sample({topic: payload})``, ``write_event``, ``flush``, ``close``) and writes a rosbag2
folder: ``<folder>/<name>.mcap`` (MCAP, profile ``ros2``, CDR messages serialized by ``rosbags``,
schemas ``ros2msg`` with the standard definitions) and ``metadata.yaml`` (rosbag2 version 9).

Topics (one message per sample unless said):

====================  =======================================  =================================
project topic         ROS 2 topic (type)                       content
====================  =======================================  =================================
/otbot/command +      /joint_states (sensor_msgs/JointState)   right_wheel, left_wheel, pivot:
/otbot/joints                                                  position rad, velocity rad/s,
                                                               effort N m = the torque command
/otbot/imu            /imu (sensor_msgs/Imu, frame platform)   specific force (+g up at rest),
                                                               rate; covariances from the noise
/otbot/estimate       /odom (nav_msgs/Odometry)                odom -> platform pose, twist in
                                                               platform frame, covariances;
                      /odom/gyro_bias (Vector3Stamped)         z = gyro bias rad/s (if any)
/otbot/truth          /truth (sensor_msgs/JointState)          q, qd over x, y, alpha, joints;
                      /truth/force (WrenchStamped)             fx, fy N ground frame (if any)
/otbot/reference      /reference (MultiDOFJointTrajectory)     desired pose, velocity, accel.
/otbot/payload        /payload (std_msgs/Float64MultiArray)    online payload estimate: 3 x 4,
                                                               rows value, std, used; columns
                                                               m_p, I_p, x_F, y_F (no header;
                                                               ``messages.payload``)
/otbot/events         /events (diagnostic_msgs/DiagnosticArray) sparse
(pose)                /tf (tf2_msgs/TFMessage)                 odom -> platform (estimate, else
                                                               truth), platform -> chassis
====================  =======================================  =================================

Stamps: header stamp = log time = publish time = round(t * 1e9) ns (the run's t, s).

Durability: the MCAP file is unchunked and uncompressed (rosbags' own writer keeps a 1 MiB chunk
and the schemas in memory until it closes, so a killed process would leave nothing readable) and
is flushed every ``flush_every`` samples and at every event; ``metadata.yaml`` is written when
the bag opens (message counts 0) and rewritten on close. A process killed mid-run leaves a bag
whose MCAP lacks its summary and footer: ``otbot import --allow-truncated`` (any streaming MCAP
reader) reads every complete message up to the cut; rosbags' reader needs the footer.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any, Iterable

import yaml

from otbot_hw.recording import (FORMAT_NAME, FORMAT_VERSION, TOPIC_COMMAND, TOPIC_ESTIMATE, TOPIC_EVENTS,
                                TOPIC_IMU, TOPIC_JOINTS, TOPIC_PAYLOAD, TOPIC_REFERENCE, TOPIC_TRUTH, TOPICS)
from otbot_hw.ros2 import messages as M

#: metadata.yaml / MCAP metadata key holding the project metadata (JSON text)
CUSTOM_KEY = "otbot"
#: ... and the whole turns of the first yaw on /odom and /reference (JSON {topic: n}), written on
#: close: a quaternion keeps alpha modulo 2 pi, the project's alpha is continuous
TURNS_KEY = "otbot_yaw_turns"
ROS_DISTRO = "jazzy"
#: QoS written for every topic: what ``ros2 bag record`` offers for a reliable, volatile publisher
QOS = ("- history: keep_last\n  depth: 10\n  reliability: reliable\n  durability: volatile\n"
       "  deadline: {sec: 9223372036, nsec: 854775807}\n  lifespan: {sec: 9223372036, nsec: 854775807}\n"
       "  liveliness: automatic\n  liveliness_lease_duration: {sec: 9223372036, nsec: 854775807}\n"
       "  avoid_ros_namespace_conventions: false")


def whole_turns(alpha: float) -> int:
    """n with alpha = yaw + 2 pi n, yaw in (-pi, pi] (what a quaternion keeps of alpha)."""
    if not math.isfinite(alpha):
        return 0
    return int(round((alpha - math.atan2(math.sin(alpha), math.cos(alpha))) / (2 * math.pi)))


def noise_variances(metadata: dict[str, Any]) -> tuple[float, float, str]:
    """(accel variance m^2/s^4, gyro variance rad^2/s^2, source) for /imu covariances: the
    recording's ``noise`` metadata when it has one, else the paper's sensor model."""
    noise = metadata.get("noise")
    if isinstance(noise, dict):
        a, g = noise.get("accel"), noise.get("gyro")
        if all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in (a, g)):
            return float(a) ** 2, float(g) ** 2, "recording metadata 'noise'"
    from otbot_hw.sensors import NoiseModel

    n = NoiseModel.paper()
    return n.accel ** 2, n.gyro ** 2, "the paper's sensor model (otbot_hw.sensors.NoiseModel.paper)"


def ros_topics(topics: Iterable[str], has_force: bool = False, has_gyro_bias: bool = False) -> dict[str, str]:
    """ROS 2 topic -> message type written for the project ``topics``."""
    topics = set(topics) | {TOPIC_COMMAND}
    out = {"/joint_states": M.JOINT_STATE}
    if TOPIC_IMU in topics:
        out["/imu"] = M.IMU
    if TOPIC_ESTIMATE in topics:
        out["/odom"] = M.ODOMETRY
        if has_gyro_bias:
            out["/odom/gyro_bias"] = M.VECTOR3
    if TOPIC_TRUTH in topics:
        out["/truth"] = M.JOINT_STATE
        if has_force:
            out["/truth/force"] = M.WRENCH
    if TOPIC_REFERENCE in topics:
        out["/reference"] = M.MULTI_DOF
    if TOPIC_PAYLOAD in topics:
        out["/payload"] = M.PAYLOAD
    if TOPIC_EVENTS in topics:
        out["/events"] = M.DIAGNOSTIC_ARRAY
    if TOPIC_ESTIMATE in topics or TOPIC_TRUTH in topics:
        out["/tf"] = M.TF
    return out


def write_metadata_yaml(folder: Path, mcap_name: str, topics: dict[str, str], counts: dict[str, int],
                        start_ns: int, end_ns: int, custom: dict[str, str]) -> None:
    """rosbag2 ``metadata.yaml`` (version 9), written to a temporary name and renamed."""
    total = sum(counts.values())
    duration = max(0, end_ns - start_ns) if total else 0
    start = start_ns if total else 0
    info = {
        "version": 9, "storage_identifier": "mcap", "relative_file_paths": [mcap_name],
        "duration": {"nanoseconds": duration}, "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": total,
        "topics_with_message_count": [
            {"topic_metadata": {"name": tp, "type": ty, "serialization_format": "cdr",
                                "offered_qos_profiles": yaml.safe_load(QOS),
                                "type_description_hash": M.msgdef(ty)[1]},
             "message_count": counts.get(tp, 0)} for tp, ty in topics.items()],
        "compression_format": "", "compression_mode": "",
        "files": [{"path": mcap_name, "starting_time": {"nanoseconds_since_epoch": start},
                   "duration": {"nanoseconds": duration}, "message_count": total}],
        "custom_data": dict(custom) or None, "ros_distro": ROS_DISTRO,
    }
    tmp = folder / "metadata.yaml.tmp"
    tmp.write_text(yaml.safe_dump({"rosbag2_bagfile_information": info}, sort_keys=False))
    os.replace(tmp, folder / "metadata.yaml")


class BagWriter:
    """Streams samples into a rosbag2 folder (created; it must not exist); see the module doc.

    ``metadata``: the project metadata (kept as JSON in ``custom_data.otbot`` and in an MCAP
    metadata record ``otbot``); ``topics``: the project topics the run carries (command always);
    ``has_force``/``has_gyro_bias``: whether truth carries ``force`` and the estimate ``gyro_bias``
    (their extra ROS topics); ``flush_every``: samples between flushes; ``name``: of the MCAP file
    (``<name>.mcap``; default the folder's name).
    """

    def __init__(self, folder: str | Path, metadata: dict[str, Any], topics: Iterable[str] = (),
                 flush_every: int = 10, has_force: bool = True, has_gyro_bias: bool = False,
                 name: str | None = None):
        from mcap.writer import CompressionType, Writer

        topics = [t for t in topics]
        for tp in topics:
            if tp not in TOPICS:
                raise ValueError(f"unknown topic '{tp}' (known: {', '.join(TOPICS)})")
        self.folder = Path(folder)
        self.project_topics = {TOPIC_COMMAND, *topics}
        # marks the bag as written from a project run: its stamps are the run's t (import keeps them)
        self.metadata = {"format": FORMAT_NAME, "format_version": FORMAT_VERSION, **metadata}
        self.accel_var, self.gyro_var, self.noise_source = noise_variances(self.metadata)
        self.types = ros_topics(self.project_topics, has_force and TOPIC_TRUTH in self.project_topics,
                                has_gyro_bias and TOPIC_ESTIMATE in self.project_topics)
        self.folder.mkdir(mode=0o755)
        self.path = self.folder / f"{name or self.folder.name}.mcap"
        self._file = open(self.path, "xb")
        self._writer = Writer(self._file, compression=CompressionType.NONE, use_chunking=False)
        self._writer.start(profile="ros2", library="otbot-hw ros2 bag writer (rosbags CDR)")
        self.custom = {CUSTOM_KEY: json.dumps(self.metadata)}
        self._writer.add_metadata(CUSTOM_KEY, self.custom)
        schema_ids: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        for tp, ty in self.types.items():
            if ty not in schema_ids:
                text, _ = M.msgdef(ty)
                schema_ids[ty] = self._writer.register_schema(name=ty, encoding="ros2msg", data=text.encode())
            self._channels[tp] = self._writer.register_channel(
                topic=tp, message_encoding="cdr", schema_id=schema_ids[ty],
                metadata={"offered_qos_profiles": QOS})
        self.counts = {tp: 0 for tp in self.types}
        self.turns: dict[str, int] = {}
        self._count = 0
        self._start_ns: int | None = None
        self._end_ns = 0
        self._last_t: float | None = None
        self._flush_every = max(1, int(flush_every))
        self._closed = False
        self._writer.flush()
        self._file.flush()
        write_metadata_yaml(self.folder, self.path.name, self.types, self.counts, 0, 0, self.custom)

    @property
    def samples(self) -> int:
        """Samples written so far."""
        return self._count

    def _put(self, topic: str, ns: int, msg) -> None:
        self._writer.add_message(channel_id=self._channels[topic], log_time=ns, publish_time=ns,
                                 data=M.serialize(msg), sequence=self.counts[topic])
        self.counts[topic] += 1
        if self._start_ns is None:
            self._start_ns = ns
        self._end_ns = max(self._end_ns, ns)

    def write_sample(self, messages: dict[str, dict[str, Any]]) -> None:
        """One sample ``{project topic: payload}`` (``RecordingWriter.write_sample``)."""
        cmd = messages[TOPIC_COMMAND]
        t = cmd["t"]
        if not math.isfinite(t) or t < 0:
            raise ValueError(f"sample {self._count}: time must be finite and >= 0, got {t}")
        if self._last_t is not None and not t > self._last_t:
            raise ValueError(f"sample {self._count}: time {t} s does not increase (previous {self._last_t} s)")
        missing = {tp for tp in self.project_topics if tp != TOPIC_EVENTS} - set(messages)
        if missing:
            raise ValueError(f"sample {self._count} lacks topic(s) {sorted(missing)}")
        self._last_t = t
        ns = int(round(t * 1e9))
        j = messages.get(TOPIC_JOINTS)
        self._put("/joint_states", ns, M.joint_state(ns, j["position"] if j else None, j["velocity"] if j else None,
                                                     cmd["torque"]))
        if "/imu" in self.types:
            m = messages[TOPIC_IMU]
            self._put("/imu", ns, M.imu(ns, m["accel"], m["gyro"], self.accel_var, self.gyro_var))
        pose = None
        if "/odom" in self.types:
            m = messages[TOPIC_ESTIMATE]
            self._put("/odom", ns, M.odometry(ns, m["pose"], m["twist"], m["std"]))
            self.turns.setdefault("/odom", whole_turns(m["pose"][2]))
            if "/odom/gyro_bias" in self.types:
                bias = [0.0, 0.0, m.get("gyro_bias", math.nan)]
                self._put("/odom/gyro_bias", ns, M.vector(ns, M.PLATFORM_FRAME, bias))
            pose = m["pose"]
        if "/truth" in self.types:
            m = messages[TOPIC_TRUTH]
            self._put("/truth", ns, M.truth_state(ns, m["q"], m["qd"]))
            if "/truth/force" in self.types:
                self._put("/truth/force", ns, M.wrench(ns, m.get("force", [math.nan, math.nan])))
            if pose is None:
                pose = m["q"][:3]
        if "/reference" in self.types:
            m = messages[TOPIC_REFERENCE]
            self._put("/reference", ns, M.reference(ns, m["p"], m["pd"], m.get("pdd")))
            self.turns.setdefault("/reference", whole_turns(m["p"][2]))
        if "/payload" in self.types:
            m = messages[TOPIC_PAYLOAD]
            self._put("/payload", ns, M.payload(m["value"], m["std"], m["used"]))
        if "/tf" in self.types and pose is not None:
            self._put("/tf", ns, M.transforms(ns, pose, j["position"][2] if j else None))
        self._count += 1
        if self._count % self._flush_every == 0:
            self.flush()

    def write_event(self, t: float, kind: str, text: str, **extra: Any) -> None:
        """A sparse event on /events (``RecordingWriter.write_event``), flushed at once."""
        if "/events" not in self.types:
            raise ValueError(f"{TOPIC_EVENTS} was not registered with this writer")
        if not math.isfinite(t) or t < 0:
            raise ValueError(f"event time must be finite and >= 0, got {t}")
        ns = int(round(t * 1e9))
        self._put("/events", ns, M.diagnostic(ns, str(kind), str(text), extra))
        self.flush()

    def flush(self) -> None:
        """Push everything written so far to the operating system."""
        self._writer.flush()
        self._file.flush()

    def close(self) -> None:
        """Write the MCAP summary and footer, then ``metadata.yaml`` with the message counts."""
        if not self._closed:
            self._closed = True
            if self.turns:
                self.custom[TURNS_KEY] = json.dumps(self.turns)
                self._writer.add_metadata(TURNS_KEY, {TURNS_KEY: self.custom[TURNS_KEY]})
            self._writer.finish()
            self._file.close()
            write_metadata_yaml(self.folder, self.path.name, self.types, self.counts, self._start_ns or 0,
                                self._end_ns, self.custom)

    def __enter__(self) -> "BagWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
