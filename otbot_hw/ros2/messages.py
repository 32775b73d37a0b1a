"""The standard ROS 2 messages a project recording maps to, built and read with ``rosbags``.

Frames (REP-103/105): ``odom`` is the ground frame B (x, y horizontal, z up); ``platform`` is
B'' (x along 1'', y along 2'', z up; the pivot P is its origin); ``chassis`` is B' (x along 1',
the chassis' forward direction). A pose (x, y, alpha) in B is the transform odom -> platform
with translation (x, y, 0) and the yaw alpha as a quaternion (0, 0, sin alpha/2, cos alpha/2).
Joint angles keep the project's signs (docs/recording-format.md §3): for the usual URDF with
the wheel axes along +y and the pivot axis along +z these are the ROS joint signs too.
"""
from __future__ import annotations

import json
import math
from functools import lru_cache
from typing import Any

import numpy as np

#: joint names of Otbot in sensor_msgs/JointState, in the project's order (phi_r, phi_l, phi_p)
JOINT_NAMES = ("right_wheel", "left_wheel", "pivot")
#: names of the generalized coordinates q on the /truth JointState (docs/recording-format.md §3)
TRUTH_NAMES = ("x", "y", "alpha", "right_wheel", "left_wheel", "pivot")
GROUND_FRAME = "odom"
PLATFORM_FRAME = "platform"
CHASSIS_FRAME = "chassis"

JOINT_STATE = "sensor_msgs/msg/JointState"
IMU = "sensor_msgs/msg/Imu"
ODOMETRY = "nav_msgs/msg/Odometry"
MULTI_DOF = "trajectory_msgs/msg/MultiDOFJointTrajectory"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"
TF = "tf2_msgs/msg/TFMessage"
WRENCH = "geometry_msgs/msg/WrenchStamped"
VECTOR3 = "geometry_msgs/msg/Vector3Stamped"
PAYLOAD = "std_msgs/msg/Float64MultiArray"
#: the /payload array (``payload``): rows, columns (units kg, kg m^2, m, m; x_F, y_F in B'')
PAYLOAD_ROWS = ("value", "std", "used")
PAYLOAD_COLUMNS = ("m_p", "I_p", "x_F", "y_F")

#: event kind -> DiagnosticStatus level (OK 0, WARN 1, ERROR 2)
EVENT_LEVELS = {"fault": 2, "estop": 2, "saturation": 1, "limit": 1, "warning": 1}


@lru_cache(maxsize=1)
def typestore():
    """The rosbags type store with the standard ROS 2 (Jazzy) message definitions."""
    from otbot_hw.ros2 import rosbags

    typesys = rosbags("rosbags.typesys")
    return typesys.get_typestore(typesys.Stores.ROS2_JAZZY)


def msgdef(msgtype: str) -> tuple[str, str]:
    """(message definition text in ros2msg form, RIHS01 type hash) of a standard type."""
    ts = typestore()
    text, _ = ts.generate_msgdef(msgtype, ros_version=2)
    return text, ts.hash_rihs01(msgtype)


def serialize(msg: Any) -> bytes:
    return bytes(typestore().serialize_cdr(msg, msg.__msgtype__))


def _T(name: str):
    return typestore().types[name]


def stamp(ns: int):
    """builtin_interfaces/Time of ``ns`` nanoseconds (>= 0)."""
    sec, nsec = divmod(int(ns), 1_000_000_000)
    return _T("builtin_interfaces/msg/Time")(sec=sec, nanosec=nsec)


def header(ns: int, frame: str = ""):
    return _T("std_msgs/msg/Header")(stamp=stamp(ns), frame_id=frame)


def stamp_ns(h) -> int:
    """Nanoseconds of a std_msgs/Header's stamp."""
    return int(h.stamp.sec) * 1_000_000_000 + int(h.stamp.nanosec)


def _vec3(v):
    return _T("geometry_msgs/msg/Vector3")(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def yaw_quaternion(alpha: float):
    """geometry_msgs/Quaternion of a rotation by ``alpha`` rad about z."""
    return _T("geometry_msgs/msg/Quaternion")(x=0.0, y=0.0, z=math.sin(alpha / 2), w=math.cos(alpha / 2))


def quaternion_yaw(q) -> float:
    """Yaw (rad, in (-pi, pi]) of a geometry_msgs/Quaternion (any rotation; its z-axis part)."""
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def _diag3(values) -> np.ndarray:
    out = np.zeros(9)
    out[[0, 4, 8]] = values
    return out


# --- project sample -> ROS messages --------------------------------------------------------------

def joint_state(ns: int, position, velocity, effort):
    """sensor_msgs/JointState of Otbot's three joints: position rad, velocity rad/s, effort N m
    (the torque command); absent fields are empty arrays."""
    arr = (lambda v: np.array([], dtype=np.float64) if v is None else np.asarray(v, dtype=np.float64))
    return _T(JOINT_STATE)(header=header(ns), name=list(JOINT_NAMES), position=arr(position),
                           velocity=arr(velocity), effort=arr(effort))


def imu(ns: int, accel, gyro, accel_var: float, gyro_var: float):
    """sensor_msgs/Imu in the platform frame: linear_acceleration = the specific force (gravity
    included: +g on z at rest, as ROS reports it), angular_velocity; no orientation
    (orientation_covariance[0] = -1, REP-145); covariances diagonal (m^2/s^4, rad^2/s^2)."""
    ocov = np.zeros(9)
    ocov[0] = -1.0
    return _T(IMU)(header=header(ns, PLATFORM_FRAME),
                   orientation=_T("geometry_msgs/msg/Quaternion")(x=0.0, y=0.0, z=0.0, w=1.0),
                   orientation_covariance=ocov, angular_velocity=_vec3(gyro),
                   angular_velocity_covariance=_diag3([gyro_var] * 3), linear_acceleration=_vec3(accel),
                   linear_acceleration_covariance=_diag3([accel_var] * 3))


def _rot2(alpha: float) -> np.ndarray:
    c, s = math.cos(alpha), math.sin(alpha)
    return np.array([[c, -s], [s, c]])


def odometry(ns: int, pose, twist, std):
    """nav_msgs/Odometry odom -> platform: pose (x, y m, alpha rad as a yaw quaternion) with its
    covariance (x, y, yaw variances; z, roll, pitch 0: planar), twist in the platform frame
    (REP-105: the child frame) rotated from the ground-frame (x_dot, y_dot) with its covariance."""
    x, y, a = (float(v) for v in pose)
    R = _rot2(a)
    v_body = R.T @ np.asarray(twist[:2], dtype=float)
    pcov = np.zeros(36)
    pcov[0], pcov[7], pcov[35] = std[0] ** 2, std[1] ** 2, std[2] ** 2
    S = R.T @ np.diag([std[3] ** 2, std[4] ** 2]) @ R
    tcov = np.zeros(36)
    tcov[0], tcov[1], tcov[6], tcov[7], tcov[35] = S[0, 0], S[0, 1], S[1, 0], S[1, 1], std[5] ** 2
    P = _T("geometry_msgs/msg/Pose")(position=_T("geometry_msgs/msg/Point")(x=x, y=y, z=0.0),
                                     orientation=yaw_quaternion(a))
    Tw = _T("geometry_msgs/msg/Twist")(linear=_vec3([v_body[0], v_body[1], 0.0]), angular=_vec3([0, 0, twist[2]]))
    return _T(ODOMETRY)(header=header(ns, GROUND_FRAME), child_frame_id=PLATFORM_FRAME,
                        pose=_T("geometry_msgs/msg/PoseWithCovariance")(pose=P, covariance=pcov),
                        twist=_T("geometry_msgs/msg/TwistWithCovariance")(twist=Tw, covariance=tcov))


def odometry_values(msg) -> tuple[list[float], list[float], list[float]]:
    """(pose [x, y, alpha], twist [x_dot, y_dot, alpha_dot] in the ground frame, std (6)) of a
    nav_msgs/Odometry written by ``odometry`` (alpha in (-pi, pi]: unwrap a series)."""
    p = msg.pose.pose
    a = quaternion_yaw(p.orientation)
    R = _rot2(a)
    lin = msg.twist.twist.linear
    v = R @ np.array([lin.x, lin.y])
    tc = np.asarray(msg.twist.covariance, dtype=float).reshape(6, 6)
    S = R @ tc[:2, :2] @ R.T
    pc = np.asarray(msg.pose.covariance, dtype=float)
    std = [math.sqrt(max(pc[0], 0)), math.sqrt(max(pc[7], 0)), math.sqrt(max(pc[35], 0)),
           math.sqrt(max(S[0, 0], 0)), math.sqrt(max(S[1, 1], 0)), math.sqrt(max(tc[5, 5], 0))]
    return [p.position.x, p.position.y, a], [float(v[0]), float(v[1]), msg.twist.twist.angular.z], std


def payload(value, std, used):
    """std_msgs/Float64MultiArray of the online payload estimate (``/otbot/payload``): a 3 x 4
    row-major array, rows ``PAYLOAD_ROWS`` (the estimate, its std, what the control law uses),
    columns ``PAYLOAD_COLUMNS`` (m_p kg, I_p kg m^2, x_F m, y_F m in B''), named by the layout's
    dimension labels. The message has no header: its stamp is the bag's log time (the sample's t).
    The adapter's ``state`` is not carried (its changes are on /events)."""
    D = _T("std_msgs/msg/MultiArrayDimension")
    layout = _T("std_msgs/msg/MultiArrayLayout")(
        dim=[D(label=",".join(PAYLOAD_ROWS), size=3, stride=12), D(label=",".join(PAYLOAD_COLUMNS), size=4, stride=4)],
        data_offset=0)
    data = np.concatenate([np.asarray(v, dtype=np.float64).reshape(4) for v in (value, std, used)])
    return _T(PAYLOAD)(layout=layout, data=data)


def payload_values(msg) -> list[float]:
    """The 12 numbers (value, std, used; ``payload``) of a /payload message; ValueError naming what
    differs when its layout is not that 3 x 4 array."""
    dims = [(d.label, int(d.size), int(d.stride)) for d in msg.layout.dim]
    want = [(",".join(PAYLOAD_ROWS), 3, 12), (",".join(PAYLOAD_COLUMNS), 4, 4)]
    data = np.asarray(msg.data, dtype=float)
    off = int(msg.layout.data_offset)
    if dims != want or len(data) < off + 12:
        raise ValueError(f"a payload array must have the layout {want} (rows {', '.join(PAYLOAD_ROWS)}; columns "
                         f"{', '.join(PAYLOAD_COLUMNS)}) and 12 numbers, got {dims} with {len(data) - off}")
    return [float(x) for x in data[off:off + 12]]


def truth_state(ns: int, q, qd):
    """The simulated state as a sensor_msgs/JointState over the generalized coordinates
    ``TRUTH_NAMES``: position q (m, m, rad x 4), velocity qd (m/s, m/s, rad/s x 4)."""
    return _T(JOINT_STATE)(header=header(ns, GROUND_FRAME), name=list(TRUTH_NAMES),
                           position=np.asarray(q, dtype=np.float64), velocity=np.asarray(qd, dtype=np.float64),
                           effort=np.array([], dtype=np.float64))


def wrench(ns: int, force):
    """geometry_msgs/WrenchStamped: the horizontal force (fx, fy) N at the pivot, ground frame."""
    return _T(WRENCH)(header=header(ns, GROUND_FRAME),
                      wrench=_T("geometry_msgs/msg/Wrench")(force=_vec3([force[0], force[1], 0.0]),
                                                            torque=_vec3([0, 0, 0])))


def vector(ns: int, frame: str, v):
    return _T(VECTOR3)(header=header(ns, frame), vector=_vec3(v))


def reference(ns: int, p, pd, pdd):
    """trajectory_msgs/MultiDOFJointTrajectory with one point for the joint ``platform``: the
    desired pose (transform in odom), velocity and acceleration (ground frame; m, rad, s)."""
    tf = _T("geometry_msgs/msg/Transform")(translation=_vec3([p[0], p[1], 0.0]), rotation=yaw_quaternion(float(p[2])))
    tw = (lambda v: _T("geometry_msgs/msg/Twist")(linear=_vec3([v[0], v[1], 0.0]), angular=_vec3([0, 0, v[2]])))
    point = _T("trajectory_msgs/msg/MultiDOFJointTrajectoryPoint")(
        transforms=[tf], velocities=[tw(pd)], accelerations=[] if pdd is None else [tw(pdd)],
        time_from_start=_T("builtin_interfaces/msg/Duration")(sec=0, nanosec=0))
    return _T(MULTI_DOF)(header=header(ns, GROUND_FRAME), joint_names=[PLATFORM_FRAME], points=[point])


def transforms(ns: int, pose, phi_p: float | None):
    """tf2_msgs/TFMessage: odom -> platform from ``pose`` (x, y, alpha) and, with the pivot angle
    phi_p, platform -> chassis (a turn by -phi_p about z)."""
    TS = _T("geometry_msgs/msg/TransformStamped")
    Tr = _T("geometry_msgs/msg/Transform")
    out = [TS(header=header(ns, GROUND_FRAME), child_frame_id=PLATFORM_FRAME,
              transform=Tr(translation=_vec3([pose[0], pose[1], 0.0]), rotation=yaw_quaternion(float(pose[2]))))]
    if phi_p is not None and math.isfinite(phi_p):
        out.append(TS(header=header(ns, PLATFORM_FRAME), child_frame_id=CHASSIS_FRAME,
                      transform=Tr(translation=_vec3([0, 0, 0]), rotation=yaw_quaternion(-float(phi_p)))))
    return _T(TF)(transforms=out)


def diagnostic(ns: int, kind: str, text: str, extra: dict[str, Any]):
    """diagnostic_msgs/DiagnosticArray with one status: name ``otbot/<kind>``, level by kind
    (fault ERROR, saturation WARN, else OK), message = the text, values: ``kind`` and the extra
    keys as JSON text."""
    KV = _T("diagnostic_msgs/msg/KeyValue")
    values = [KV(key="kind", value=kind)] + [KV(key=str(k), value=json.dumps(v)) for k, v in extra.items()]
    st = _T("diagnostic_msgs/msg/DiagnosticStatus")(level=EVENT_LEVELS.get(kind, 0), name=f"otbot/{kind}",
                                                    message=text, hardware_id="otbot", values=values)
    return _T(DIAGNOSTIC_ARRAY)(header=header(ns), status=[st])


def diagnostic_events(msg, t: float) -> list[dict[str, Any]]:
    """Project events (dicts t, kind, text, extras) of a diagnostic_msgs/DiagnosticArray at t s."""
    out = []
    for st in msg.status:
        ev: dict[str, Any] = {"t": t, "kind": st.name.split("/", 1)[-1] if st.name else "note", "text": st.message}
        for kv in st.values:
            if kv.key == "kind":
                ev["kind"] = kv.value
            elif kv.key not in ("t", "text"):
                try:
                    ev[kv.key] = json.loads(kv.value)
                except json.JSONDecodeError:
                    ev[kv.key] = kv.value
        out.append(ev)
    return out
