"""Opening a ROS 2 bag for ``otbot import`` (``bag_import``): what it holds and its messages.

``rosbags`` opens the bag (rosbag2 folder with ``metadata.yaml`` — MCAP or SQLite storage — or a
single ``.mcap`` file) and ``Types`` deserializes the CDR messages with the standard Jazzy store
(types it lacks from the bag's own definitions); a MCAP cut short (no footer: the recorder was
killed) is refused unless ``allow_truncated``, then its complete messages are read with the
``mcap`` package's streaming reader (deserialized by ``rosbags`` too). A non-CDR topic, a folder
without ``metadata.yaml``, a project recording given as a bag: ``BagError`` (exit 2).
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from otbot_hw.input_files import open_input, read_text
from otbot_hw.recording import MCAP_MAGIC
from otbot_hw.ros2 import BagError, rosbags
from otbot_hw.ros2.writer import CUSTOM_KEY, TURNS_KEY


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
    with open_input(path) as f:
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
            meta_yaml = (yaml.safe_load(read_text(mfile)) or {}).get("rosbag2_bagfile_information") or {}
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
        try:
            with open_input(path) as f:
                head = f.read(64)
        except OSError as exc:
            raise BagError(f"{path}: cannot read: {exc.strerror or exc}") from None
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


class Types:
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
