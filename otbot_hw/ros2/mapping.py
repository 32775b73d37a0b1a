"""Which topic and field of a ROS 2 bag is which Otbot channel (``otbot import --map MAP.yaml``).

The file (example with every key: ``config/ros2_map.yaml``, the common layout that is also the
default without ``--map``)::

    time: header                # sample times: header stamps, or "receive" (the bag's log times)
    fixture: floor              # floor | stand | locked: how the robot stood during the run
    joints:
      topic: /joint_states      # sensor_msgs/msg/JointState
      names: [right_wheel, left_wheel, pivot]   # the message's names of phi_r, phi_l, phi_p
      sign: [1, 1, 1]           # -1 where the robot's joint turns against the project's sign
      position: position        # field, rad
      velocity: velocity        # field, rad/s
      stamp_tolerance: 0.001    # s: joints split over several messages (one per joint) whose stamps
                                #    agree within this make one sample
    torque:
      topic: /joint_states      # the torque command (N m): the JointState's effort ...
      field: effort             # ... or an array field (std_msgs/msg/Float64MultiArray: data)
      index: null               # with an array field on another type: [i_r, i_l, i_p]
      scale: 1.0                # N m per unit of the field (the joint signs apply as well)
    imu:
      topic: /imu               # sensor_msgs/msg/Imu; null: no IMU
      rpy: [0, 0, 0]            # rad, roll-pitch-yaw of the IMU frame in the platform frame B''
      gravity: included         # included (ROS: +g on z at rest) | removed (+g added on z of B'')
    odom: /odom                 # optional topics, read when present (what `otbot export` writes):
    truth: /truth               #   estimate (nav_msgs/Odometry), simulated truth, reference,
    reference: /reference       #   events, payload estimate (std_msgs/Float64MultiArray,
    events: /events             #   layout in messages.payload); null: ignore
    payload: /payload

Every key is optional (absent: the value above). A key the reader does not know is an error. A
topic the map names other than these defaults must be in the bag; the default IMU and optional
topics are read when present (no IMU: a notice).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from otbot_hw.ros2 import BagError
from otbot_hw.ros2.messages import JOINT_NAMES

FIXTURES = ("floor", "stand", "locked")


@dataclass(frozen=True)
class BagMap:
    """The mapping (see the module doc). ``explicit``: the IMU and optional topics a map file named
    other than the defaults (a missing one is an error; the defaults are only read when present)."""

    time: str = "header"
    fixture: str = "floor"
    joints_topic: str = "/joint_states"
    joint_names: tuple[str, str, str] = JOINT_NAMES
    joint_sign: tuple[float, float, float] = (1.0, 1.0, 1.0)
    position_field: str = "position"
    velocity_field: str = "velocity"
    stamp_tolerance: float = 0.001
    torque_topic: str = "/joint_states"
    torque_field: str = "effort"
    torque_index: tuple[int, int, int] | None = None
    torque_scale: float = 1.0
    imu_topic: str | None = "/imu"
    imu_rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)
    imu_gravity: str = "included"
    odom_topic: str | None = "/odom"
    truth_topic: str | None = "/truth"
    reference_topic: str | None = "/reference"
    events_topic: str | None = "/events"
    payload_topic: str | None = "/payload"
    explicit: frozenset[str] = field(default_factory=frozenset)
    source: str = "default (config/ros2_map.yaml layout)"

    def imu_rotation(self) -> np.ndarray | None:
        """R with v_B'' = R v_imu (None: identity)."""
        r, p, y = self.imu_rpy
        if r == p == y == 0:
            return None
        cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
        Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
        Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
        Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
        return Rz @ Ry @ Rx

    def to_dict(self) -> dict[str, Any]:
        """The mapping in the file's layout (for the recording's metadata)."""
        return {"time": self.time, "fixture": self.fixture,
                "joints": {"topic": self.joints_topic, "names": list(self.joint_names), "sign": list(self.joint_sign),
                           "position": self.position_field, "velocity": self.velocity_field,
                           "stamp_tolerance": self.stamp_tolerance},
                "torque": {"topic": self.torque_topic, "field": self.torque_field,
                           "index": None if self.torque_index is None else list(self.torque_index),
                           "scale": self.torque_scale},
                "imu": {"topic": self.imu_topic, "rpy": list(self.imu_rpy), "gravity": self.imu_gravity},
                "odom": self.odom_topic, "truth": self.truth_topic, "reference": self.reference_topic,
                "events": self.events_topic, "payload": self.payload_topic, "source": self.source}


def _section(src: str, name: str, data: Any, keys: tuple[str, ...]) -> dict:
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise BagError(f"{src}: '{name}' must be a mapping, got {data!r}")
    unknown = sorted(set(data) - set(keys))
    if unknown:
        raise BagError(f"{src}: '{name}' has unknown key(s) {unknown} (known: {', '.join(keys)})")
    return data


def _topic(src: str, key: str, v: Any, nullable: bool) -> str | None:
    if v is None and nullable:
        return None
    if not isinstance(v, str) or not v.startswith("/") or len(v) < 2:
        raise BagError(f"{src}: '{key}' must be a topic name starting with '/'{' or null' if nullable else ''}, "
                       f"got {v!r}")
    return v


def _name(src: str, key: str, v: Any) -> str:
    if not isinstance(v, str) or not v:
        raise BagError(f"{src}: '{key}' must be a field name, got {v!r}")
    return v


def _numbers(src: str, key: str, v: Any, n: int, kind=float) -> tuple:
    if (not isinstance(v, list) or len(v) != n
            or not all(isinstance(e, (int, float)) and not isinstance(e, bool) and math.isfinite(e) for e in v)):
        raise BagError(f"{src}: '{key}' must be a list of {n} numbers, got {v!r}")
    if kind is int and not all(isinstance(e, int) and e >= 0 for e in v):
        raise BagError(f"{src}: '{key}' must be a list of {n} indices >= 0, got {v!r}")
    return tuple(kind(e) for e in v)


def map_from_dict(data: Any, source: str = "<dict>") -> BagMap:
    """Validate a mapping; errors name the file and the key."""
    d = BagMap()
    top = _section(source, "map", data if data is not None else {},
                   ("time", "fixture", "joints", "torque", "imu", "odom", "truth", "reference", "events", "payload"))
    explicit: set[str] = set()
    time = top.get("time", d.time)
    if time not in ("header", "receive"):
        raise BagError(f"{source}: 'time' must be header or receive, got {time!r}")
    fixture = top.get("fixture", d.fixture)
    if fixture not in FIXTURES:
        raise BagError(f"{source}: 'fixture' must be one of {', '.join(FIXTURES)}, got {fixture!r}")
    j = _section(source, "joints", top.get("joints"),
                 ("topic", "names", "sign", "position", "velocity", "stamp_tolerance"))
    joints_topic = _topic(source, "joints.topic", j.get("topic", d.joints_topic), False)
    if "topic" in j:
        explicit.add(joints_topic)
    names = j.get("names", list(d.joint_names))
    if (not isinstance(names, list) or len(names) != 3 or not all(isinstance(s, str) and s for s in names)
            or len(set(names)) != 3):
        raise BagError(f"{source}: 'joints.names' must be 3 different joint names (right wheel, left wheel, "
                       f"pivot), got {names!r}")
    sign = _numbers(source, "joints.sign", j.get("sign", list(d.joint_sign)), 3)
    if any(s not in (1.0, -1.0) for s in sign):
        raise BagError(f"{source}: 'joints.sign' entries must be 1 or -1, got {list(sign)}")
    tol = j.get("stamp_tolerance", d.stamp_tolerance)
    if isinstance(tol, bool) or not isinstance(tol, (int, float)) or not (math.isfinite(tol) and 0 <= tol <= 1):
        raise BagError(f"{source}: 'joints.stamp_tolerance' must be a number of seconds in [0, 1], got {tol!r}")
    t = _section(source, "torque", top.get("torque"), ("topic", "field", "index", "scale"))
    torque_topic = _topic(source, "torque.topic", t.get("topic", joints_topic), False)
    if "topic" in t:
        explicit.add(torque_topic)
    index = t.get("index")
    index = None if index is None else _numbers(source, "torque.index", index, 3, int)
    scale = t.get("scale", 1.0)
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not math.isfinite(scale) or scale == 0:
        raise BagError(f"{source}: 'torque.scale' must be a finite non-zero number (N m per unit), got {scale!r}")
    i = _section(source, "imu", top.get("imu"), ("topic", "rpy", "gravity"))
    imu_topic = _topic(source, "imu.topic", i.get("topic", d.imu_topic), True)
    if imu_topic and imu_topic != d.imu_topic:
        explicit.add(imu_topic)
    gravity = i.get("gravity", d.imu_gravity)
    if gravity not in ("included", "removed"):
        raise BagError(f"{source}: 'imu.gravity' must be included or removed, got {gravity!r}")
    opt = {}
    for key in ("odom", "truth", "reference", "events", "payload"):
        opt[key] = _topic(source, key, top.get(key, getattr(d, f"{key}_topic")), True)
        if opt[key] and opt[key] != getattr(d, f"{key}_topic"):
            explicit.add(opt[key])
    return BagMap(time=time, fixture=fixture, joints_topic=joints_topic, joint_names=tuple(names),
                  joint_sign=sign, position_field=_name(source, "joints.position", j.get("position", d.position_field)),
                  velocity_field=_name(source, "joints.velocity", j.get("velocity", d.velocity_field)),
                  stamp_tolerance=float(tol),
                  torque_topic=torque_topic, torque_field=_name(source, "torque.field", t.get("field", d.torque_field)),
                  torque_index=index, torque_scale=float(scale), imu_topic=imu_topic,
                  imu_rpy=_numbers(source, "imu.rpy", i.get("rpy", list(d.imu_rpy)), 3), imu_gravity=gravity,
                  odom_topic=opt["odom"], truth_topic=opt["truth"], reference_topic=opt["reference"],
                  events_topic=opt["events"], payload_topic=opt["payload"], explicit=frozenset(explicit), source=source)


def load_map(path: str | Path | None) -> BagMap:
    """The mapping of ``path`` (None: the default, the common layout)."""
    if path is None:
        return BagMap()
    from otbot_hw.params import ParameterError, read_yaml

    p = Path(path)
    try:  # the project's YAML rules: 1.2 numbers, a key written twice is an error, a size cap
        data = read_yaml(p, "map file")
    except ParameterError as exc:
        raise BagError(f"--map {' '.join(str(exc).split())}") from None
    return map_from_dict(data, f"--map {p}")
