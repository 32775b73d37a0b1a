"""The mapped topics of a ROS 2 bag read into time series, for ``otbot import`` (``bag_import``).

Each reader decodes its topic's messages (``bag_open.Types``) into a ``Series``: header stamps
(``time: receive``, or a message without a header: the bag's log times) and values in the
project's units and signs (the map's joint signs and torque scale; the IMU rotated into B''; +g
added on z when the source removed gravity).

Joint states split over several messages (one per joint, as some ROS drivers publish them) are
merged: messages whose header stamps agree within the map's ``joints.stamp_tolerance`` (s) make one
sample, stamped with the earliest of them. A joint missing at a stamp, or stamps of one cycle that
disagree by more than the tolerance, are refused (``BagError``) with the joint and the time named.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from otbot_hw.ros2 import BagError
from otbot_hw.ros2 import messages as M
from otbot_hw.ros2.bag_open import Connection, OpenBag, Types
from otbot_hw.ros2.mapping import BagMap

G = 9.80665  # m/s^2, the project's gravity (docs/recording-format.md §4)


@dataclass
class Series:
    """One topic's samples: header (or log) stamps and log stamps in ns, values (n, k)."""

    topic: str
    stamps: np.ndarray
    log: np.ndarray
    values: dict[str, np.ndarray] = field(default_factory=dict)


@dataclass
class Source:
    """What the readers share: the open bag, its decoder, the map, the raw messages by topic
    (``[(log ns, CDR bytes)]``) and the notices of the import."""

    bag: OpenBag
    types: Types
    bm: BagMap
    raw: dict[str, list]
    notices: list[str]

    @property
    def use_header(self) -> bool:
        return self.bm.time == "header"


def field_of(msg, name: str, topic: str, msgtype: str, key: str):
    try:
        return getattr(msg, name)
    except AttributeError:
        fields = [f for f in getattr(msg, "__dataclass_fields__", {}) if not f.startswith("_") and f.islower()]
        raise BagError(f"{key}: {msgtype} on {topic} has no field '{name}' (fields: {', '.join(fields)})") from None


def stamp_of(msg, log_ns: int, use_header: bool) -> int:
    h = getattr(msg, "header", None)
    if use_header and h is not None:
        return M.stamp_ns(h)
    return int(log_ns)


def require(bag: OpenBag, topic: str, role: str, types: tuple[str, ...] | None = None) -> Connection:
    c = bag.connections.get(topic)
    if c is None:
        have = ", ".join(sorted(bag.connections)) or "none"
        raise BagError(f"{bag.path}: no topic {topic} ({role}); the bag has: {have}")
    if not c.count:
        raise BagError(f"{bag.path}: topic {topic} ({role}) has no messages")
    if types and c.msgtype not in types:
        raise BagError(f"{bag.path}: topic {topic} ({role}) is {c.msgtype}, expected {' or '.join(types)}")
    return c


def unwrap_angles(a: np.ndarray) -> np.ndarray:
    return np.unwrap(a) if len(a) else a


def _series(topic: str, stamps: list, log: list, values: dict) -> Series:
    return Series(topic, np.array(stamps, dtype=np.int64), np.array(log, dtype=np.int64), values)


# --- joints ------------------------------------------------------------------------------------

@dataclass
class Joints:
    """The joint states: ``series`` (position, velocity in the project's signs), ``effort`` (n, 3)
    when the torque is on the joints topic (None otherwise), whether the velocities must be
    differentiated from the angles, and whether the topic carries no angles at all (effort only)."""

    series: Series
    effort: np.ndarray | None
    vel_from_angles: bool
    no_joints: bool


def _pick(values, key: tuple, idx: list[int]) -> np.ndarray:
    a = np.asarray(values, dtype=float)
    return a[idx] if len(a) == len(key) else np.full(len(idx), np.nan)


def read_joints(src: Source, jc: Connection, tc: Connection) -> Joints:
    """The joints topic as a ``Joints`` (see the module doc for split publishers)."""
    bm = src.bm
    names = bm.joint_names
    with_effort = tc.topic == jc.topic
    msgs = []  # (k, stamp, log, names, position, velocity, effort)
    for k, (lns, data) in enumerate(src.raw[jc.topic]):
        m = src.types.decode(jc.topic, jc.msgtype, data)
        msgs.append((k, stamp_of(m, lns, src.use_header), lns, tuple(m.name),
                     field_of(m, bm.position_field, jc.topic, jc.msgtype, "joints.position"),
                     field_of(m, bm.velocity_field, jc.topic, jc.msgtype, "joints.velocity"),
                     field_of(m, bm.torque_field, jc.topic, jc.msgtype, "torque.field") if with_effort else None))
    ours = [mm for mm in msgs if any(n in mm[3] for n in names)]
    if not ours:
        key = msgs[0][3] if msgs else ()
        raise BagError(f"{jc.topic}: joints {list(key)} are not this robot's: no "
                       f"{', '.join(map(repr, names))} "
                       f"(the map's joints.names {list(names)} name the right wheel, left wheel and pivot)")
    if all(all(n in mm[3] for n in names) for mm in ours):
        stamps, logs, pos, vel, eff = [], [], [], [], []
        for k, st, lns, key, p, v, e in ours:
            idx = [key.index(n) for n in names]
            stamps.append(st)
            logs.append(lns)
            pos.append(_pick(p, key, idx))
            vel.append(_pick(v, key, idx))
            if with_effort:
                e = np.asarray(e, dtype=float)
                if bm.torque_index is not None:
                    eff.append(e[list(bm.torque_index)] if len(e) > max(bm.torque_index) else np.full(3, np.nan))
                else:
                    eff.append(_pick(e, key, idx))
    else:
        stamps, logs, pos, vel, eff = _merge_split(jc.topic, ours, names, bm.stamp_tolerance, with_effort)
        src.notices.append(f"{jc.topic}: the joints come in separate messages; merged those whose stamps agree "
                           f"within {bm.stamp_tolerance * 1e3:g} ms into one sample each ({len(stamps)} samples "
                           f"from {len(ours)} messages)")
    sign = np.array(bm.joint_sign)
    pos, vel = np.array(pos) * sign, np.array(vel) * sign
    no_joints = bool(np.all(np.isnan(pos)) and np.all(np.isnan(vel)))
    if no_joints:  # effort only (a command-only recording exported): less, not wrong
        src.notices.append(f"{jc.topic} carries no {bm.position_field} and no {bm.velocity_field}: the recording has "
                           "no /otbot/joints (diagnose, estimate and identify need the encoders)")
        pos = vel = np.zeros((len(pos), 3))
    elif np.all(np.isnan(pos)):
        raise BagError(f"{jc.topic}: field {bm.position_field} is empty in every message: no joint angles")
    if np.any(np.isnan(pos)):
        raise BagError(f"{jc.topic}: field {bm.position_field} is empty or short in "
                       f"{int(np.isnan(pos).any(axis=1).sum())} of {len(pos)} messages")
    series = _series(jc.topic, stamps, logs, {"position": pos, "velocity": vel})
    return Joints(series, np.array(eff) if with_effort else None, bool(np.any(np.isnan(vel))), no_joints)


def _merge_split(topic: str, msgs: list, names: tuple, tolerance: float, with_effort: bool):
    """Joint states of split publishers merged (module doc): (stamps, logs, pos, vel, effort) lists,
    one entry per sample; BagError naming the joint and time when one is missing or the stamps of
    a cycle disagree."""
    tol = int(round(tolerance * 1e9))
    order = sorted(msgs, key=lambda mm: mm[1])  # stable: bag order within equal stamps
    t0 = order[0][1]
    groups: list[dict] = []  # {stamp, log, joints: {name: (k, stamp, p, v, e)}}
    for k, st, lns, key, p, v, e in order:
        g = groups[-1] if groups else None
        mine = [n for n in names if n in key]
        if g is None or st - g["stamp"] > tol or any(n in g["joints"] for n in mine):
            g = {"stamp": st, "log": lns, "joints": {}}
            groups.append(g)
        g["log"] = max(g["log"], lns)
        for n in mine:
            i = key.index(n)
            g["joints"][n] = (k, st, *(float(a[i]) if a is not None and len(a) == len(key) else math.nan
                                       for a in (p, v, e)))
    stamps, logs, pos, vel, eff = [], [], [], [], []
    for gi, g in enumerate(groups):
        missing = [n for n in names if n not in g["joints"]]
        if missing:
            n = missing[0]
            t = (g["stamp"] - t0) * 1e-9
            near = [h["joints"][n] for h in groups[max(0, gi - 1):gi + 2] if n in h["joints"]]
            near = min(near, key=lambda j: abs(j[1] - g["stamp"]), default=None)
            if near is not None and abs(near[1] - g["stamp"]) < 2 * tol + _step(groups):
                raise BagError(f"{topic}: split joint states disagree: {n!r} is stamped {(near[1] - t0) * 1e-9:.6f} s "
                               f"and {', '.join(repr(j) for j in names if j in g['joints'])} {t:.6f} s, "
                               f"{abs(near[1] - g['stamp']) * 1e-6:.3f} ms apart, beyond the "
                               f"{tolerance * 1e3:g} ms tolerance (map joints.stamp_tolerance)")
            raise BagError(f"{topic}: split joint states: no {n!r} at stamp {t:.6f} s (message "
                           f"{min(j[0] for j in g['joints'].values())}; joints {[j for j in names if j in g['joints']]}): every joint "
                           "is needed at every stamp")
        stamps.append(g["stamp"])
        logs.append(g["log"])
        pos.append([g["joints"][n][2] for n in names])
        vel.append([g["joints"][n][3] for n in names])
        if with_effort:
            eff.append([g["joints"][n][4] for n in names])
    return stamps, logs, pos, vel, eff


def _step(groups: list[dict]) -> int:
    """Half the median step (ns) between the groups' stamps: how near another cycle's message is."""
    if len(groups) < 2:
        return 0
    return int(np.median(np.diff([g["stamp"] for g in groups])) / 2)


# --- torque, IMU -------------------------------------------------------------------------------

def read_torque(src: Source, tc: Connection, joints: Joints) -> Series:
    """The torque command (N m, the project's signs) from the joints' effort or its own topic."""
    bm, names = src.bm, src.bm.joint_names
    sign = np.array(bm.joint_sign)
    if joints.effort is not None:
        j = joints.series
        torque = Series(tc.topic, j.stamps, j.log, {"torque": joints.effort * sign * bm.torque_scale})
    else:
        t_ns, t_log, vals = [], [], []
        for lns, data in src.raw[tc.topic]:
            m = src.types.decode(tc.topic, tc.msgtype, data)
            e = field_of(m, bm.torque_field, tc.topic, tc.msgtype, "torque.field")
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
            t_ns.append(stamp_of(m, lns, src.use_header))
            t_log.append(lns)
            vals.append(row)
        torque = _series(tc.topic, t_ns, t_log, {"torque": np.array(vals) * sign * bm.torque_scale})
    tq = torque.values["torque"]
    if np.all(np.isnan(tq)):
        raise BagError(f"{tc.topic}: field {bm.torque_field} (the torque command, N m) is empty in every message: "
                       "the recording needs the torques (map torque.topic/field to where the robot publishes them)")
    if np.any(np.isnan(tq)):
        raise BagError(f"{tc.topic}: field {bm.torque_field} (torque) is empty or short in "
                       f"{int(np.isnan(tq).any(axis=1).sum())} of {len(tq)} messages")
    return torque


def read_imu(src: Source, imu_c: Connection | None) -> Series | None:
    """The IMU in B'' (specific force m/s^2, rate rad/s), or None without one."""
    if imu_c is None:
        return None
    bm = src.bm
    R = bm.imu_rotation()
    i_ns, i_log, acc, gyr = [], [], [], []
    for lns, data in src.raw[imu_c.topic]:
        m = src.types.decode(imu_c.topic, imu_c.msgtype, data)
        a, w = m.linear_acceleration, m.angular_velocity
        i_ns.append(stamp_of(m, lns, src.use_header))
        i_log.append(lns)
        acc.append((a.x, a.y, a.z))
        gyr.append((w.x, w.y, w.z))
    acc, gyr = np.array(acc, dtype=float), np.array(gyr, dtype=float)
    if R is not None:
        acc, gyr = acc @ R.T, gyr @ R.T
    if bm.imu_gravity == "removed":
        acc[:, 2] += G
    return _series(imu_c.topic, i_ns, i_log, {"accel": acc, "gyro": gyr})


# --- optional channels ---------------------------------------------------------------------------

def read_optional(src: Source, optional: dict[str, Connection], extra_topics: dict[str, str]
                  ) -> tuple[dict[str, Series], list[tuple[int, Any]]]:
    """({key: Series with values "v"}, [(stamp ns, DiagnosticArray)]) of the optional topics
    present: odom (pose, twist, std), truth (q, qd), reference (p, pd, pdd), payload (value, std,
    used: ``messages.payload_values``), events; ``extra_topics``: /truth/force and /odom/gyro_bias."""
    bag = src.bag
    opt: dict[str, Series] = {}
    events_raw: list[tuple[int, Any]] = []
    for key, c in optional.items():
        s_ns, s_log, rows = [], [], []
        for lns, data in src.raw[c.topic]:
            m = src.types.decode(c.topic, c.msgtype, data)
            ns = stamp_of(m, lns, src.use_header)
            if key == "events":
                events_raw.append((ns, m))
                continue
            if key == "odom":
                if m.child_frame_id != M.PLATFORM_FRAME:  # e.g. a robot's own base_link odometry
                    src.notices.append(f"{c.topic} is the pose of frame '{m.child_frame_id}', not of the platform "
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
            elif key == "payload":
                try:
                    rows.append(M.payload_values(m))
                except ValueError as exc:
                    raise BagError(f"{c.topic}: {exc}") from None
            s_ns.append(ns)
            s_log.append(lns)
        if key != "events" and rows:
            vals = np.array(rows, dtype=float)
            if key in ("odom", "reference"):
                n_turns = bag.turns.get(c.topic, 0) if isinstance(bag.turns.get(c.topic, 0), int) else 0
                vals[:, 2] = unwrap_angles(vals[:, 2]) + 2 * math.pi * n_turns
            opt[key] = _series(c.topic, s_ns, s_log, {"v": vals})
    for sub, name in extra_topics.items():
        c = bag.connections[name]
        s_ns, s_log, rows = [], [], []
        for lns, data in src.raw[name]:
            m = src.types.decode(name, c.msgtype, data)
            s_ns.append(stamp_of(m, lns, src.use_header))
            s_log.append(lns)
            rows.append([m.wrench.force.x, m.wrench.force.y] if sub == "/truth/force" else [m.vector.z])
        opt[sub] = _series(name, s_ns, s_log, {"v": np.array(rows, dtype=float)})
    return opt, events_raw
