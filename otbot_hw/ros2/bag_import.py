"""A ROS 2 bag as a project recording (``otbot import BAG --out RUN.mcap``).

Reading: ``rosbags`` opens the bag (rosbag2 folder with ``metadata.yaml`` — MCAP or SQLite
storage — or a single ``.mcap`` file) and deserializes the CDR messages; a MCAP cut short (no
footer: the recorder was killed) is refused unless ``allow_truncated``, then its complete
messages are read with the ``mcap`` package's streaming reader (deserialized by ``rosbags`` too).

Conversion (docs/recording-format.md §9): joint angles and rates keep their values times the
map's sign (REP-103 wheels turning about +y and the pivot about +z have the project's signs);
the effort (N m) is the torque command; the IMU message's vectors are rotated into B'' by the
map's rpy (identity by default: a REP-103 body frame x forward, y left, z up is B''), and its
linear acceleration *with* gravity (+g up at rest, as ROS reports it) is the project's specific
force; ``gravity: removed`` adds +g on z. Angles of quaternions (odom, reference) are unwrapped.

Time: the messages' header stamps (``time: receive``: the bag's log times). When every mapped
topic shares the joint stamps on a uniform grid, the samples are those stamps, values unchanged.
Otherwise one grid at ``rate`` Hz (default the joint-state rate) spans the time every required
topic covers; positions, rates, IMU and optional channels are interpolated linearly in time, the
torque is held (zero-order hold: the latest command at or before the grid time, a quarter period
of stamp jitter allowed), and the interpolation error is estimated by predicting every source
sample from its two neighbours (rms, max per channel: an upper bound, sensor noise included).

Refused (``BagError``, exit 2) where the result would be wrong: another robot's joints, no torque
(effort) channel, a topic with no messages, a mapped topic or field missing, a non-CDR topic, a
clock jump (header stamps going back, or jumping while the receive times do not), a gap (no
sample of a required topic for more than two grid periods: import the part before or after it
with ``start``/``end``), a wrapped encoder that cannot be unwrapped. Said as a notice where the
result is merely less: no IMU, dropped single messages, unwrapped encoder wraps, rates derived
from angles, trimmed ends.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from otbot_hw.recording import FORMAT_NAME, MCAP_MAGIC, Recording, source_metadata
from otbot_hw.ros2 import BagError, rosbags
from otbot_hw.ros2 import messages as M
from otbot_hw.ros2.mapping import BagMap
from otbot_hw.ros2.writer import CUSTOM_KEY, TURNS_KEY

G = 9.80665  # m/s^2, the project's gravity (docs/recording-format.md §4)


# --- opening a bag -----------------------------------------------------------------------------

@dataclass
class Connection:
    topic: str
    msgtype: str
    encoding: str
    count: int | None
    msgdef: str = ""
    msgdef_format: str = "ros2msg"


@dataclass
class OpenBag:
    """What was found in a bag: connections by topic, the project metadata it carries (a bag
    written by ``otbot export``), storage kind, whether it was cut short, and its messages."""

    path: Path
    storage: str
    connections: dict[str, Connection]
    custom: dict[str, Any]
    truncated: bool
    turns: dict[str, Any]
    messages: Any  # callable(topics) -> iterator of (topic, log_ns, raw bytes)


def _custom(meta: dict | None, key: str = CUSTOM_KEY) -> dict[str, Any]:
    data = (meta or {}).get(key)
    if isinstance(data, str):
        try:
            v = json.loads(data)
            return v if isinstance(v, dict) else {}
        except json.JSONDecodeError:
            return {}
    return {}


def _rosbags_open(path: Path):
    return rosbags("rosbags.rosbag2").Reader(path)


def _stream_mcap(path: Path) -> tuple[dict[str, Connection], dict[str, Any], list]:
    """(connections, custom metadata, [(topic, log_ns, data)]) of every complete record of a MCAP
    file read front to back (a file cut short ends at its last complete record)."""
    from mcap.exceptions import McapError
    from mcap.records import Channel, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader

    schemas: dict[int, Schema] = {}
    chans: dict[int, tuple[str, Connection]] = {}
    conns: dict[str, Connection] = {}
    custom: dict[str, Any] = {}
    msgs: list = []
    with open(path, "rb") as f:
        try:
            for r in StreamReader(f, record_size_limit=256 * 2 ** 20).records:
                if isinstance(r, Schema):
                    schemas[r.id] = r
                elif isinstance(r, Channel):
                    s = schemas.get(r.schema_id)
                    c = Connection(r.topic, s.name if s else "", r.message_encoding, 0,
                                   s.data.decode() if s else "", s.encoding if s else "")
                    chans[r.id] = (r.topic, c)
                    conns.setdefault(r.topic, c)
                elif isinstance(r, Message) and r.channel_id in chans:
                    topic, c = chans[r.channel_id]
                    c.count += 1
                    msgs.append((topic, r.log_time, r.data))
                elif isinstance(r, Metadata) and r.name == CUSTOM_KEY:
                    custom = _custom(r.metadata)
        except (McapError, EOFError, ValueError, IndexError, OSError) as exc:  # the cut: keep what came before
            if not conns:
                raise BagError(f"{path}: MCAP file cut short before its first channel ({exc or 'truncated'})") from None
    return conns, custom, msgs


def open_bag(path: str | Path, allow_truncated: bool = False) -> OpenBag:
    """Open a rosbag2 folder or a single ``.mcap`` file (see the module doc); BagError when it is
    none, cut short (unless ``allow_truncated``), or not CDR."""
    ReaderError = rosbags("rosbags.rosbag2").ReaderError

    path = Path(path)
    if not path.exists():
        raise BagError(f"{path}: no such file or folder")
    meta_yaml: dict = {}
    mcap_files: list[Path]
    if path.is_dir():
        mfile = path / "metadata.yaml"
        if not mfile.is_file():
            raise BagError(f"{path}: folder without metadata.yaml: not a rosbag2 bag (a bag folder holds "
                           "metadata.yaml and its storage files; `ros2 bag reindex` rebuilds a lost one)")
        try:
            meta_yaml = (yaml.safe_load(mfile.read_text()) or {}).get("rosbag2_bagfile_information") or {}
        except (yaml.YAMLError, UnicodeDecodeError, AttributeError):
            raise BagError(f"{mfile}: not a rosbag2 metadata file (invalid YAML)") from None
        except OSError as exc:
            raise BagError(f"{mfile}: cannot read: {exc.strerror}") from None
        if not isinstance(meta_yaml, dict):
            raise BagError(f"{mfile}: no rosbag2_bagfile_information mapping")
        for tm in meta_yaml.get("topics_with_message_count") or []:
            md = (tm or {}).get("topic_metadata") or {}
            fmt = md.get("serialization_format", "cdr")
            if fmt != "cdr":
                raise BagError(f"{path}: topic {md.get('name')} is serialized as '{fmt}', not CDR (ROS 2's "
                               "default, the only encoding read)")
        storage = str(meta_yaml.get("storage_identifier", ""))
        mcap_files = [path / p for p in meta_yaml.get("relative_file_paths") or [] if str(p).endswith(".mcap")]
        custom = _custom(meta_yaml.get("custom_data"))
        turns = _custom(meta_yaml.get("custom_data"), TURNS_KEY)
    elif path.suffix.lower() == ".mcap":
        storage, custom, turns = "mcap", {}, {}
        mcap_files = [path]
        with open(path, "rb") as f:
            head = f.read(64)
        if not head.startswith(MCAP_MAGIC[:len(head)]) or len(head) < len(MCAP_MAGIC):
            raise BagError(f"{path}: not an MCAP file (it does not start with the MCAP magic bytes)")
        if b"otbot" in head and b"ros2" not in head:
            raise BagError(f"{path}: is a project recording (JSON messages), not a ROS 2 bag: read it as it is, "
                           "or `otbot export` it to a bag")
    else:
        raise BagError(f"{path}: not a ROS 2 bag (expected a rosbag2 folder with metadata.yaml, or a .mcap file)")

    try:
        reader = _rosbags_open(path)
        reader.open()
    except ReaderError as exc:
        text = str(exc)
        cut = any(s in text for s in ("end magic", "MCAP footer", "summary offset", "Could not read", "not enough"))
        if cut and mcap_files:
            if not allow_truncated:
                raise BagError(f"{mcap_files[0]}: MCAP file is truncated (no footer: the recorder stopped without "
                               "closing it); --allow-truncated imports the complete messages before the cut") from None
            conns: dict[str, Connection] = {}
            msgs: list = []
            for f in mcap_files:
                c, cust, m = _stream_mcap(f)
                for tp, cc in c.items():
                    conns.setdefault(tp, cc)
                custom = custom or cust
                msgs += m
            for c in conns.values():
                if c.encoding != "cdr":
                    raise BagError(f"{path}: topic {c.topic} is encoded '{c.encoding}', not CDR")
            counts: dict[str, int] = {}
            for tp, _, _ in msgs:
                counts[tp] = counts.get(tp, 0) + 1
            for tp, c in conns.items():
                c.count = counts.get(tp, 0)

            def stream(topics, _msgs=msgs):
                return ((tp, ns, raw) for tp, ns, raw in _msgs if tp in topics)

            return OpenBag(path, storage or "mcap", conns, custom, True, turns, stream)
        if "Profile is not ros2" in text:
            raise BagError(f"{path}: MCAP profile is not ros2: not a ROS 2 bag") from None
        raise BagError(f"{path}: cannot read the bag: {text}") from None
    except FileNotFoundError as exc:
        raise BagError(f"{path}: {exc}") from None
    conns = {}
    for c in reader.connections:
        fmt = getattr(c.ext, "serialization_format", "cdr")
        if fmt != "cdr":
            reader.close()
            raise BagError(f"{path}: topic {c.topic} is encoded '{fmt}', not CDR (ROS 2's default, the only "
                           "encoding read)")
        if c.topic in conns:
            conns[c.topic].count = (conns[c.topic].count or 0) + c.msgcount
            continue
        conns[c.topic] = Connection(c.topic, c.msgtype, fmt, c.msgcount, c.msgdef.data,
                                    "ros2idl" if c.msgdef.format.name == "IDL" else "ros2msg")
    if not custom and path.suffix.lower() == ".mcap":
        custom, turns = _mcap_custom(path, CUSTOM_KEY), _mcap_custom(path, TURNS_KEY)
    by_topic = {}
    for c in reader.connections:
        by_topic.setdefault(c.topic, []).append(c)

    def messages(topics, _reader=reader):
        wanted = [c for tp in topics for c in by_topic.get(tp, [])]
        try:
            for c, ns, raw in _reader.messages(connections=wanted):
                yield c.topic, ns, raw
        except ReaderError as exc:
            raise BagError(f"{path}: cannot read the messages: {exc}") from None

    return OpenBag(path, storage or ("mcap" if path.suffix == ".mcap" else "sqlite3"), conns, custom, False, turns,
                   messages)


def _mcap_custom(path: Path, key: str) -> dict[str, Any]:
    """A project metadata record (``key``) of a complete MCAP file (read through its summary)."""
    try:
        from mcap.reader import make_reader

        with open(path, "rb") as f:
            for m in make_reader(f).iter_metadata():
                if m.name == key:
                    return _custom(m.metadata, key)
    except Exception:  # noqa: BLE001 - a bag without our record has none
        return {}
    return {}


class _Types:
    """Deserialization with the standard store; types the store lacks come from the bag's definitions."""

    def __init__(self, conns: dict[str, Connection]):
        typesys = rosbags("rosbags.typesys")
        get_types_from_idl, get_types_from_msg = typesys.get_types_from_idl, typesys.get_types_from_msg
        self.store = typesys.get_typestore(typesys.Stores.ROS2_JAZZY)
        add: dict = {}
        for c in conns.values():
            if c.msgtype and c.msgtype not in self.store.types and c.msgdef:
                try:
                    add.update(get_types_from_idl(c.msgdef) if c.msgdef_format == "ros2idl"
                               else get_types_from_msg(c.msgdef, c.msgtype))
                except Exception as exc:  # noqa: BLE001 - named below when the topic is used
                    c.msgdef = f"!{exc}"
        if add:
            self.store.register(add)

    def decode(self, topic: str, msgtype: str, raw: bytes):
        try:
            return self.store.deserialize_cdr(raw, msgtype)
        except Exception as exc:  # noqa: BLE001 - rosbags raises several kinds on bad data
            raise BagError(f"{topic}: a {msgtype} message does not decode as CDR ({type(exc).__name__}: "
                           f"{' '.join(str(exc).split())[:80]})") from None


# --- reading the mapped topics -----------------------------------------------------------------

@dataclass
class Series:
    """One topic's samples: header (or log) stamps and log stamps in ns, values (n, k)."""

    topic: str
    stamps: np.ndarray
    log: np.ndarray
    values: dict[str, np.ndarray] = field(default_factory=dict)


def _field(msg, name: str, topic: str, msgtype: str, key: str):
    try:
        return getattr(msg, name)
    except AttributeError:
        fields = [f for f in getattr(msg, "__dataclass_fields__", {}) if not f.startswith("_") and f.islower()]
        raise BagError(f"{key}: {msgtype} on {topic} has no field '{name}' (fields: {', '.join(fields)})") from None


def _stamp(msg, log_ns: int, use_header: bool) -> int:
    h = getattr(msg, "header", None)
    if use_header and h is not None:
        return M.stamp_ns(h)
    return int(log_ns)


def _require(bag: OpenBag, topic: str, role: str, types: tuple[str, ...] | None = None) -> Connection:
    c = bag.connections.get(topic)
    if c is None:
        have = ", ".join(sorted(bag.connections)) or "none"
        raise BagError(f"{bag.path}: no topic {topic} ({role}); the bag has: {have}")
    if not c.count:
        raise BagError(f"{bag.path}: topic {topic} ({role}) has no messages")
    if types and c.msgtype not in types:
        raise BagError(f"{bag.path}: topic {topic} ({role}) is {c.msgtype}, expected {' or '.join(types)}")
    return c


def _unwrap_angles(a: np.ndarray) -> np.ndarray:
    return np.unwrap(a) if len(a) else a


@dataclass
class ImportResult:
    recording: Recording
    report: dict[str, Any]


def import_bag(path: str | Path, bag_map: BagMap | None = None, rate: float | None = None,
               start: float | None = None, end: float | None = None, allow_truncated: bool = False) -> ImportResult:
    """Read the bag at ``path`` into a project ``Recording`` (see the module doc). ``rate``: grid
    rate (Hz; default the joint-state rate); ``start``/``end``: the part to import (s after the
    first joint state). Returns the recording and a report (method, errors, notices)."""
    bm = bag_map or BagMap()
    bag = open_bag(path, allow_truncated)
    notices: list[str] = []
    if bag.truncated:
        notices.append("the bag's MCAP was cut short (no footer): imported its complete messages up to the cut")
    use_header = bm.time == "header"
    jc = _require(bag, bm.joints_topic, "joints", (M.JOINT_STATE,))
    tc = _require(bag, bm.torque_topic, "torque")
    imu_c = None
    if bm.imu_topic:
        if bm.imu_topic in bag.connections or bm.imu_topic in bm.explicit:
            imu_c = _require(bag, bm.imu_topic, "IMU", (M.IMU,))
        else:
            notices.append(f"no IMU: the bag has no {bm.imu_topic} (the recording has no /otbot/imu: `estimate` "
                           "predicts with the model, `diagnose` fits the encoders only)")
    optional: dict[str, Connection] = {}
    for key, types in (("odom", (M.ODOMETRY,)), ("truth", (M.JOINT_STATE,)), ("reference", (M.MULTI_DOF,)),
                       ("events", (M.DIAGNOSTIC_ARRAY,))):
        tp = getattr(bm, f"{key}_topic")
        if tp and (tp in bag.connections or tp in bm.explicit):
            c = bag.connections.get(tp)
            if tp in bm.explicit or (c is not None and c.msgtype in types and c.count):
                optional[key] = _require(bag, tp, key, types)
    extra_topics = {}
    for sub, ty in (("/truth/force", M.WRENCH), ("/odom/gyro_bias", M.VECTOR3)):
        base = bm.truth_topic if sub.startswith("/truth") else bm.odom_topic
        name = None if base is None else base + sub[sub.rindex("/"):]
        if name and name in bag.connections and bag.connections[name].msgtype == ty and bag.connections[name].count:
            extra_topics[sub] = name
    types = _Types(bag.connections)
    wanted = {c.topic for c in (jc, tc, imu_c, *optional.values()) if c is not None} | set(extra_topics.values())
    raw: dict[str, list] = {tp: [] for tp in wanted}
    for tp, ns, data in bag.messages(wanted):
        raw[tp].append((ns, data))

    # joints
    names = bm.joint_names
    sign = np.array(bm.joint_sign)
    js_ns, js_log, pos, vel, eff = [], [], [], [], []
    index_cache: dict[tuple, list[int]] = {}
    for k, (lns, data) in enumerate(raw[jc.topic]):
        m = types.decode(jc.topic, jc.msgtype, data)
        key = tuple(m.name)
        if key not in index_cache:
            missing = [n for n in names if n not in key]
            if missing and len(missing) < len(names):
                raise BagError(f"{jc.topic}: message {k} carries joints {list(key)}, without "
                               f"{', '.join(map(repr, missing))}: the three joints must come in one message "
                               "(messages of split publishers are not merged)")
            if missing:
                raise BagError(f"{jc.topic}: joints {list(key)} are not this robot's: no "
                               f"{', '.join(map(repr, missing))} "
                               f"(the map's joints.names {list(names)} name the right wheel, left wheel and pivot)")
            index_cache[key] = [key.index(n) for n in names]
        idx = index_cache[key]
        p = np.asarray(_field(m, bm.position_field, jc.topic, jc.msgtype, "joints.position"), dtype=float)
        v = np.asarray(_field(m, bm.velocity_field, jc.topic, jc.msgtype, "joints.velocity"), dtype=float)
        js_ns.append(_stamp(m, lns, use_header))
        js_log.append(lns)
        pos.append(p[idx] if len(p) == len(key) else np.full(3, np.nan))
        vel.append(v[idx] if len(v) == len(key) else np.full(3, np.nan))
        if tc.topic == jc.topic:
            e = np.asarray(_field(m, bm.torque_field, jc.topic, jc.msgtype, "torque.field"), dtype=float)
            if bm.torque_index is not None:
                eff.append(e[list(bm.torque_index)] if len(e) > max(bm.torque_index) else np.full(3, np.nan))
            else:
                eff.append(e[idx] if len(e) == len(key) else np.full(3, np.nan))
    joints = Series(jc.topic, np.array(js_ns, dtype=np.int64), np.array(js_log, dtype=np.int64))
    pos, vel = np.array(pos) * sign, np.array(vel) * sign
    no_joints = bool(np.all(np.isnan(pos)) and np.all(np.isnan(vel)))
    if no_joints:  # effort only (a command-only recording exported): less, not wrong
        notices.append(f"{jc.topic} carries no {bm.position_field} and no {bm.velocity_field}: the recording has no "
                       "/otbot/joints (diagnose, estimate and identify need the encoders)")
        pos = vel = np.zeros((len(pos), 3))
    elif np.all(np.isnan(pos)):
        raise BagError(f"{jc.topic}: field {bm.position_field} is empty in every message: no joint angles")
    if np.any(np.isnan(pos)):
        raise BagError(f"{jc.topic}: field {bm.position_field} is empty or short in "
                       f"{int(np.isnan(pos).any(axis=1).sum())} of {len(pos)} messages")
    vel_from_angles = bool(np.any(np.isnan(vel)))
    joints.values = {"position": pos, "velocity": vel}

    # torque
    if tc.topic == jc.topic:
        torque = Series(tc.topic, joints.stamps, joints.log, {"torque": np.array(eff) * sign * bm.torque_scale})
    else:
        t_ns, t_log, vals = [], [], []
        for lns, data in raw[tc.topic]:
            m = types.decode(tc.topic, tc.msgtype, data)
            e = _field(m, bm.torque_field, tc.topic, tc.msgtype, "torque.field")
            if isinstance(e, (int, float)):
                raise BagError(f"torque.field: {tc.msgtype}.{bm.torque_field} on {tc.topic} is one number; the "
                               "torque needs an array of the three joints (torque.index)")
            e = np.asarray(e, dtype=float)
            if hasattr(m, "name") and bm.torque_index is None:
                key = tuple(m.name)
                if not all(n in key for n in names):
                    raise BagError(f"{tc.topic}: joints {list(key)} are not this robot's (map joints.names)")
                row = e[[key.index(n) for n in names]] if len(e) == len(key) else np.full(3, np.nan)
            else:
                ix = list(bm.torque_index or (0, 1, 2))
                row = e[ix] if len(e) > max(ix) else np.full(3, np.nan)
            t_ns.append(_stamp(m, lns, use_header))
            t_log.append(lns)
            vals.append(row)
        torque = Series(tc.topic, np.array(t_ns, dtype=np.int64), np.array(t_log, dtype=np.int64),
                        {"torque": np.array(vals) * sign * bm.torque_scale})
    tq = torque.values["torque"]
    if np.all(np.isnan(tq)):
        raise BagError(f"{tc.topic}: field {bm.torque_field} (the torque command, N m) is empty in every message: "
                       "the recording needs the torques (map torque.topic/field to where the robot publishes them)")
    if np.any(np.isnan(tq)):
        raise BagError(f"{tc.topic}: field {bm.torque_field} (torque) is empty or short in "
                       f"{int(np.isnan(tq).any(axis=1).sum())} of {len(tq)} messages")

    # IMU
    imu = None
    if imu_c is not None:
        R = bm.imu_rotation()
        i_ns, i_log, acc, gyr = [], [], [], []
        for lns, data in raw[imu_c.topic]:
            m = types.decode(imu_c.topic, imu_c.msgtype, data)
            a, w = m.linear_acceleration, m.angular_velocity
            i_ns.append(_stamp(m, lns, use_header))
            i_log.append(lns)
            acc.append((a.x, a.y, a.z))
            gyr.append((w.x, w.y, w.z))
        acc, gyr = np.array(acc, dtype=float), np.array(gyr, dtype=float)
        if R is not None:
            acc, gyr = acc @ R.T, gyr @ R.T
        if bm.imu_gravity == "removed":
            acc[:, 2] += G
        imu = Series(imu_c.topic, np.array(i_ns, dtype=np.int64), np.array(i_log, dtype=np.int64),
                     {"accel": acc, "gyro": gyr})

    # optional channels
    opt: dict[str, Series] = {}
    events_raw: list[tuple[int, Any]] = []
    for key, c in optional.items():
        s_ns, s_log, rows = [], [], []
        for lns, data in raw[c.topic]:
            m = types.decode(c.topic, c.msgtype, data)
            ns = _stamp(m, lns, use_header)
            if key == "events":
                events_raw.append((ns, m))
                continue
            if key == "odom":
                if m.child_frame_id != M.PLATFORM_FRAME:  # e.g. a robot's own base_link odometry
                    notices.append(f"{c.topic} is the pose of frame '{m.child_frame_id}', not of the platform "
                                   f"('{M.PLATFORM_FRAME}'): not imported as the estimate")
                    break
                p, tw, sd = M.odometry_values(m)
                rows.append(p + tw + sd)
            elif key == "truth":
                nm = tuple(m.name)
                if not all(n in nm for n in M.TRUTH_NAMES):
                    raise BagError(f"{c.topic}: truth JointState names {list(nm)} are not {list(M.TRUTH_NAMES)}")
                ix = [nm.index(n) for n in M.TRUTH_NAMES]
                rows.append(list(np.asarray(m.position)[ix]) + list(np.asarray(m.velocity)[ix]))
            elif key == "reference":
                pt = m.points[0]
                tf = pt.transforms[0]
                v = pt.velocities[0]
                acc_ = pt.accelerations[0] if pt.accelerations else None
                rows.append([tf.translation.x, tf.translation.y, M.quaternion_yaw(tf.rotation),
                             v.linear.x, v.linear.y, v.angular.z]
                            + ([acc_.linear.x, acc_.linear.y, acc_.angular.z] if acc_ else [np.nan] * 3))
            s_ns.append(ns)
            s_log.append(lns)
        if key != "events" and rows:
            vals = np.array(rows, dtype=float)
            if key in ("odom", "reference"):
                n_turns = bag.turns.get(c.topic, 0) if isinstance(bag.turns.get(c.topic, 0), int) else 0
                vals[:, 2] = _unwrap_angles(vals[:, 2]) + 2 * math.pi * n_turns
            opt[key] = Series(c.topic, np.array(s_ns, dtype=np.int64), np.array(s_log, dtype=np.int64),
                              {"v": vals})
    for sub, name in extra_topics.items():
        c = bag.connections[name]
        s_ns, s_log, rows = [], [], []
        for lns, data in raw[name]:
            m = types.decode(name, c.msgtype, data)
            s_ns.append(_stamp(m, lns, use_header))
            s_log.append(lns)
            rows.append([m.wrench.force.x, m.wrench.force.y] if sub == "/truth/force" else [m.vector.z])
        opt[sub] = Series(name, np.array(s_ns, dtype=np.int64), np.array(s_log, dtype=np.int64),
                          {"v": np.array(rows, dtype=float)})

    # --- time checks -----------------------------------------------------------------------------
    required = [joints] + ([torque] if torque.topic != joints.topic else []) + ([imu] if imu is not None else [])
    if use_header and np.all(joints.stamps == 0):
        raise BagError(f"{joints.topic}: every header stamp is zero; use `time: receive` in the map to take the "
                       "bag's receive times")
    for s in required + list(opt.values()):
        _check_clock(s, use_header)
    origin_custom = bool(bag.custom.get("format") == FORMAT_NAME or bag.custom.get("format_version"))
    t_first = int(joints.stamps[0])
    lo = t_first + (int(round(start * 1e9)) if start is not None else 0)
    hi = (t_first + int(round(end * 1e9))) if end is not None else None
    if hi is not None and hi <= lo:
        raise BagError(f"--end {end} s is not after --start {start or 0} s")

    js_step = float(np.median(np.diff(joints.stamps))) if len(joints.stamps) > 1 else math.nan
    if not len(joints.stamps) > 1:
        raise BagError(f"{joints.topic}: {len(joints.stamps)} message(s); at least 2 are needed")
    every = required + list(opt.values())
    common = min(len(s.stamps) for s in every)  # a bag cut mid-sample ends one topic early
    shared = (rate is None or abs(rate * js_step * 1e-9 - 1) < 1e-9) and _uniform(joints.stamps) and all(
        np.array_equal(s.stamps[:common], joints.stamps[:common]) and len(s.stamps) - common <= 1 for s in every)
    if shared:
        grid = joints.stamps[:common]
        grid = grid[(grid >= lo) & ((grid <= hi) if hi is not None else True)]
        period_ns = float(np.median(np.diff(joints.stamps)))
        method = {"method": "none: every topic shares the joint-state stamps on a uniform grid; values as recorded"}
        rate_hz = 1e9 / period_ns
    else:
        rate_hz = float(rate) if rate is not None else _nominal_rate(js_step)
        period_ns = 1e9 / rate_hz
        half = period_ns / 2
        first = max(int(s.stamps[0]) for s in required) - half  # a topic's edge value serves half a period
        g1 = int(min(int(s.stamps[-1]) for s in required) + half)
        cand = joints.stamps[(joints.stamps >= max(first, lo))]  # the grid keeps the joint states' phase
        if not len(cand):
            raise BagError(f"{path}: no joint state after every required topic has begun")
        g0 = int(cand[0])
        trimmed = []
        if g0 > t_first + period_ns and start is None:
            trimmed.append(f"start by {(g0 - t_first) * 1e-9:.3f} s (until every required topic has begun)")
        if g1 < int(joints.stamps[-1]) - period_ns and end is None:
            trimmed.append(f"end by {(int(joints.stamps[-1]) - g1) * 1e-9:.3f} s (where a required topic ends)")
        if hi is not None:
            g1 = min(g1, hi)
        n = int(math.floor((g1 - g0) / period_ns + 1e-9)) + 1
        if n < 2:
            raise BagError(f"{path}: the required topics ({', '.join(s.topic for s in required)}) overlap for less "
                           "than two samples")
        grid = g0 + np.round(np.arange(n) * period_ns).astype(np.int64)
        if trimmed:
            notices.append("trimmed the " + " and the ".join(trimmed))
        if len(torque.stamps) > 1:
            cmd_period = float(np.median(np.diff(torque.stamps)))
            changes = np.any(np.diff(torque.values["torque"], axis=0) != 0, axis=1)
            if cmd_period < 0.9 * period_ns and changes.mean() > 0.5 * cmd_period / period_ns:
                notices.append(f"the torque commands come at {1e9 / cmd_period:.4g} Hz and change faster than the "
                               f"{rate_hz:.4g} Hz grid: held at the grid, the commands between its samples are "
                               "dropped and the recording's torque is not all that drove the robot (import at the "
                               "command rate for identification and diagnosis)")
        for s in required:
            _check_gaps(s, grid, period_ns, notices)
        method = {"method": "linear interpolation in time onto one grid (joints, IMU, optional channels); torque "
                            "by zero-order hold (latest command at or before the grid time, 1/4 period jitter "
                            "allowed)",
                  "error": {}}
    if len(grid) < 2:
        raise BagError(f"{path}: fewer than 2 samples between --start and --end")

    # --- wrapped encoders ---------------------------------------------------------------------
    pos = joints.values["position"]
    unwrapped = pos.copy()
    dts = np.diff(joints.stamps) * 1e-9
    for j, name in enumerate(("right wheel", "left wheel", "pivot")):
        d = np.diff(pos[:, j])
        wraps = np.nonzero(np.abs(d) > math.pi)[0]
        if not len(wraps):
            continue
        uw = np.unwrap(pos[:, j])
        if not vel_from_angles:
            v = joints.values["velocity"][:, j]
            pred = 0.5 * (v[:-1] + v[1:]) * dts
            bad = wraps[np.abs(np.diff(uw)[wraps] - pred[wraps]) > math.pi / 2]
            if len(bad):
                k = int(bad[0]) + 1
                raise BagError(f"{joints.topic}: {names[j]} ({name}) position jumps by {d[k - 1]:.3f} rad at message "
                               f"{k} and its velocity does not say which way it wrapped: not a continuous angle "
                               "(docs/recording-format.md §3)")
        unwrapped[:, j] = uw
        notices.append(f"{names[j]} ({name}) position wraps at +-pi {len(wraps)} time(s) (first at "
                       f"{(joints.stamps[wraps[0] + 1] - t_first) * 1e-9:.3f} s): unwrapped to a continuous angle")
    joints.values["position"] = unwrapped
    if vel_from_angles:
        ts_ = (joints.stamps - t_first) * 1e-9
        joints.values["velocity"] = np.gradient(unwrapped, ts_, axis=0)
        notices.append(f"{joints.topic} has no {bm.velocity_field}: joint rates differentiated from the angles "
                       "(central differences)")

    # --- values on the grid -------------------------------------------------------------------
    def on_grid(s: Series, key: str, err_name: str | None = None, unit: str = "") -> np.ndarray:
        v = s.values[key]
        if shared:
            return v[np.searchsorted(s.stamps, grid)]
        x = (s.stamps - grid[0]).astype(float)
        xg = (grid - grid[0]).astype(float)
        out = np.column_stack([np.interp(xg, x, v[:, c]) for c in range(v.shape[1])])
        out[(xg < x[0] - period_ns / 2) | (xg > x[-1] + period_ns / 2)] = np.nan  # beyond the held edge
        inside = (x >= -period_ns) & (x <= xg[-1] + period_ns)  # the source samples of the imported part
        if err_name is not None and inside.sum() > 2:
            e = _loo_error(x[inside], v[inside])
            method["error"][err_name] = {"rms": e[0], "max": e[1], "unit": unit}
        return out

    def hold(s: Series, key: str) -> np.ndarray:
        v = s.values[key]
        if shared:
            return v[np.searchsorted(s.stamps, grid)]
        i = np.searchsorted(s.stamps, grid + int(period_ns / 4), side="right") - 1
        return v[np.clip(i, 0, len(v) - 1)]

    origin = 0 if origin_custom else int(grid[0])
    t = (grid - origin) * 1e-9
    rec = Recording(t=t, torque=hold(torque, "torque"))
    if not no_joints:
        rec.joint_pos = on_grid(joints, "position", "joint position", "rad")
        rec.joint_vel = on_grid(joints, "velocity", "joint velocity", "rad/s")
    if imu is not None:
        rec.imu_accel = on_grid(imu, "accel", "IMU accel", "m/s^2")
        rec.imu_gyro = on_grid(imu, "gyro", "IMU gyro", "rad/s")
    if "truth" in opt:
        v = on_grid(opt["truth"], "v")
        rec.truth_q, rec.truth_qd = v[:, :6], v[:, 6:]
        if "/truth/force" in opt:
            rec.truth_force = on_grid(opt["/truth/force"], "v")
    if "odom" in opt:
        v = on_grid(opt["odom"], "v")
        rec.estimate_pose, rec.estimate_twist, rec.estimate_std = v[:, :3], v[:, 3:6], v[:, 6:]
        if "/odom/gyro_bias" in opt:
            rec.estimate_gyro_bias = on_grid(opt["/odom/gyro_bias"], "v")[:, 0]
    if "reference" in opt:
        v = on_grid(opt["reference"], "v")
        rec.reference_p, rec.reference_pd = v[:, :3], v[:, 3:6]
        rec.reference_pdd = None if np.all(np.isnan(v[:, 6:])) else v[:, 6:]
    for ns, m in events_raw:
        if ns < grid[0] - period_ns / 2 or ns > grid[-1] + period_ns / 2:
            continue
        k = int(np.clip(np.searchsorted(grid, ns + int(period_ns / 4), side="right") - 1, 0, len(grid) - 1))
        rec.events.extend(M.diagnostic_events(m, float(t[k])))
    for name, arr in (("joint angles", rec.joint_pos), ("IMU", rec.imu_accel)):
        if arr is not None and np.any(np.isnan(arr)):
            raise BagError(f"{path}: {name} undefined at {int(np.isnan(arr).any(axis=1).sum())} grid samples")

    # --- metadata and report ------------------------------------------------------------------
    topics = {c.topic: {"type": c.msgtype, "messages": c.count} for c in (jc, tc, imu_c, *optional.values())
              if c is not None}
    for s in [joints] + ([imu] if imu else []) + ([torque] if torque.topic != joints.topic else []):
        if len(s.stamps) > 1:
            d = np.diff(s.stamps) * 1e-9
            topics[s.topic].update({"rate_hz": float(1 / np.median(d)), "jitter_s": float(np.std(d))})
    conversion = ("joints: angle, rate and effort times the map's sign "
                  f"{list(bm.joint_sign)} (REP-103 wheel axes +y, pivot +z: the project's signs); effort N m x "
                  f"{bm.torque_scale} = torque command; IMU: "
                  + ("identity (REP-103 body axes x forward, y left, z up = B'' axes 1'', 2'', 3'')"
                     if bm.imu_rotation() is None else f"rotated into B'' by rpy {list(bm.imu_rpy)} rad")
                  + ("; linear acceleration with gravity (+g up at rest) = specific force"
                     if bm.imu_gravity == "included"
                     else "; +g added on z (gravity removed by the source, flat ground assumed)"))
    resampling = {"rate_hz": rate_hz, "period_s": period_ns * 1e-9, **method}
    meta = {k: v for k, v in bag.custom.items() if k not in ("format", "format_version")}
    if not (shared and "sample_period" in meta):  # an exported recording keeps its own
        meta["sample_period"] = period_ns * 1e-9
    meta.setdefault("source", source_metadata(program="ros2 bag")["source"])
    meta.setdefault("fixture", bm.fixture)
    meta["import"] = {"bag": str(Path(path).resolve()), "storage": bag.storage, "truncated": bag.truncated,
                      "topics": topics, "mapping": bm.to_dict(), "conversion": conversion, "resampling": resampling,
                      "start_time_ns": int(grid[0]), "time_origin_ns": origin, "notices": notices}
    rec.metadata = meta
    report = {"bag": str(path), "samples": len(rec), "duration_s": float(t[-1] - t[0]), "rate_hz": rate_hz,
              "topics": topics, "conversion": conversion, "resampling": resampling, "notices": notices,
              "truncated": bag.truncated, "channels": rec.channels()}
    return ImportResult(rec, report)


def _nominal_rate(step_ns: float) -> float:
    """The rate of a median step (ns), snapped to a whole Hz within 0.1 %."""
    r = 1e9 / step_ns
    return float(round(r)) if abs(r - round(r)) < 1e-3 * r else r


def _uniform(stamps: np.ndarray) -> bool:
    d = np.diff(stamps)
    return len(d) > 0 and int(d.max() - d.min()) <= 2


def _check_clock(s: Series, use_header: bool) -> None:
    d = np.diff(s.stamps)
    back = np.nonzero(d <= 0)[0]
    if len(back):
        k = int(back[0]) + 1
        what = (f"the stamp goes back by {-d[k - 1] * 1e-9:.6f} s" if d[k - 1] < 0
                else "the stamp repeats the one before")
        raise BagError(f"{s.topic}: clock jump at message {k}: {what} ({len(back)} such step(s)); stamps must "
                       "increase")
    if use_header and len(d):
        dl = np.diff(s.log)
        med = float(np.median(d))
        jump = np.nonzero(np.abs(d - dl) > max(1e9, 10 * med))[0]
        if len(jump):
            k = int(jump[0]) + 1
            raise BagError(f"{s.topic}: clock jump at message {k}: the header stamp moves {d[k - 1] * 1e-9:.3f} s "
                           "while "
                           f"the bag's receive time moves {dl[k - 1] * 1e-9:.3f} s (the sensor clock was reset or "
                           "synchronized mid-run); import the part before or after it (--start/--end)")


def _check_gaps(s: Series, grid: np.ndarray, period_ns: float, notices: list[str]) -> None:
    inside = s.stamps[(s.stamps >= grid[0] - 2 * period_ns) & (s.stamps <= grid[-1] + 2 * period_ns)]
    pts = np.concatenate([[grid[0]], inside, [grid[-1]]]) if len(inside) else np.array([grid[0], grid[-1]])
    d = np.diff(np.sort(pts))
    big = np.nonzero(d > 2 * period_ns)[0]
    if len(big):
        k = int(big[0])
        t0 = (np.sort(pts)[k] - grid[0]) * 1e-9
        raise BagError(f"{s.topic}: gap of {d[k] * 1e-9:.3f} s at t = {t0:.3f} s (no message for more than two "
                       f"sample periods; {len(big)} gap(s)): the samples across it would be invented; import the part "
                       "before or after it (--start/--end, s after the first joint state)")
    med = float(np.median(np.diff(s.stamps))) if len(s.stamps) > 1 else period_ns
    dropped = int(np.sum(np.diff(inside) > 1.5 * med)) if len(inside) > 1 else 0
    if dropped:
        notices.append(f"{s.topic}: {dropped} dropped message(s) (steps over 1.5 periods, none over two sample "
                       "periods): interpolated across")


def _loo_error(x: np.ndarray, v: np.ndarray) -> tuple[float, float]:
    """(rms, max) over channels of predicting each interior sample from its two neighbours."""
    w = ((x[1:-1] - x[:-2]) / (x[2:] - x[:-2]))[:, None]
    pred = v[:-2] + w * (v[2:] - v[:-2])
    e = pred - v[1:-1]
    e = e[np.isfinite(e)]
    if not len(e):
        return math.nan, math.nan
    return float(np.sqrt(np.mean(e ** 2))), float(np.max(np.abs(e)))
