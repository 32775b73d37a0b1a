"""The telemetry's channels and messages (``otbot_hw.runtime.telemetry``): the JSON schemas, the
preallocated slot a loop cycle is copied into, and ``TelemetryChannels``, which turns a slot into the
Foxglove messages (protobuf ``/tf`` and ``/otbot/log``, JSON for the rest) on the telemetry thread.
Units SI; frames as in ``telemetry``'s table.
"""
from __future__ import annotations

import math

import numpy as np

from otbot_hw.model.angles import wrap_angle
from otbot_hw.motors import MOTORS

JOINT_NAMES = list(MOTORS)  # right_wheel, left_wheel, pivot
WORLD, PLATFORM, CHASSIS, REFERENCE = "world", "platform", "chassis", "reference"

_VEC = {"type": "array", "items": {"type": "number"}}
_SCHEMAS: dict[str, tuple[str, dict]] = {
    "/otbot/joints": ("otbot.JointState", {"type": "object", "properties": {
        "t": {"type": "number", "description": "loop time, s"},
        "name": {"type": "array", "items": {"type": "string"}},
        "position": {**_VEC, "description": "rad"}, "velocity": {**_VEC, "description": "rad/s"}}}),
    "/otbot/torques": ("otbot.Torques", {"type": "object", "properties": {
        "t": {"type": "number"}, "name": {"type": "array", "items": {"type": "string"}},
        "commanded": {**_VEC, "description": "N m after the limiter"},
        "limit": {**_VEC, "description": "N m, motors.*.max_torque"},
        "ratio": {**_VEC, "description": "commanded / limit"},
        "saturated": {"type": "array", "items": {"type": "boolean"}}}}),
    "/otbot/tracking_error": ("otbot.TrackingError", {"type": "object", "properties": {
        "t": {"type": "number"}, "x": {"type": "number", "description": "m"},
        "y": {"type": "number", "description": "m"}, "alpha": {"type": "number", "description": "rad, wrapped"},
        "norm": {"type": "number", "description": "m, position error"}}}),
    "/otbot/estimate": ("otbot.Estimate", {"type": "object", "properties": {
        "t": {"type": "number"}, "pose": {**_VEC, "description": "x, y (m), alpha (rad)"},
        "twist": {**_VEC, "description": "m/s, m/s, rad/s"},
        "std": {**_VEC, "description": "sigma of pose and twist, same units"},
        "gyro_bias": {"type": "number", "description": "rad/s"}}}),
    "/otbot/status": ("otbot.Status", {"type": "object", "properties": {
        "t": {"type": "number"}, "mode": {"type": "string"},
        "faults": {"type": "array", "items": {"type": "string"}},
        "drive_states": {"type": "array", "items": {"type": "string"}}}}),
}


class Slot:
    """One preallocated queued sample: ``vec`` holds joint_pos (rad), joint_vel (rad/s), torque (N m),
    pose, twist (3 each), std (6), reference (3), gyro_bias (rad/s), at the offsets ``TelemetryServer``
    fills; ``has`` which of pose, twist, std, gyro_bias, reference exist;
    what to send (``cycle``, ``status``, ``changed``: the log lines against ``prev_mode``/``prev_faults``)."""

    __slots__ = ("vec", "has", "t", "saturated", "mode", "faults", "drive_states", "prev_mode", "prev_faults",
                 "changed", "status", "cycle", "stamp")

    def __init__(self):
        self.vec = np.zeros(25)
        self.has = [False] * 5


_POSE, _TWIST, _STD, _BIAS, _REF = range(5)


def chassis_in_platform(phi_p: float, l1: float) -> tuple[tuple[float, float], float]:
    """((x, y) m, yaw rad) of the chassis frame B' (origin at the wheel-axis midpoint M, axis 1'
    along the heading theta = alpha - phi_p) in the platform frame B'' (origin at the pivot P).
    The rolling constraints (``model.kinematics.constraint_jacobian``) give P = M + l1 (cos theta,
    sin theta) in the ground frame (the pivot leads the wheel axis by l1), so M sits at
    -l1 (cos phi_p, -sin phi_p) in B'', turned by -phi_p."""
    return (-l1 * math.cos(phi_p), l1 * math.sin(phi_p)), -phi_p


class TelemetryChannels:
    """The channels on a foxglove ``context``; ``limits`` (3,) N m: the motors' torque limits (for the
    ratio); ``l1`` (m): pivot offset for the chassis frame. ``send(slot)`` logs what the slot says is due."""

    def __init__(self, context, limits, l1: float):
        import foxglove
        from foxglove.channels import FrameTransformsChannel, LogChannel

        self.limits = np.asarray(limits, float)
        self.l1 = float(l1)
        self._tf = FrameTransformsChannel("/tf", context=context)
        self._log = LogChannel("/otbot/log", context=context)
        self._json = {topic: foxglove.Channel(topic, context=context, schema=foxglove.Schema(
            name=name_, encoding="jsonschema", data=_json_bytes(schema)), message_encoding="json")
            for topic, (name_, schema) in _SCHEMAS.items()}

    def send(self, slot: Slot) -> None:
        stamp = slot.stamp
        if slot.changed:
            self._log_changes(slot, stamp)
        if slot.status:
            self._json["/otbot/status"].log(
                {"t": slot.t, "mode": slot.mode, "faults": [str(f) for f in slot.faults],
                 "drive_states": list(slot.drive_states)}, log_time=stamp)
        if slot.cycle:
            self._publish_cycle(slot, stamp)

    def _log_changes(self, slot: Slot, stamp: int) -> None:
        from foxglove.messages import Log, LogLevel, Timestamp

        ts = Timestamp(stamp // 1_000_000_000, stamp % 1_000_000_000)
        if slot.mode != slot.prev_mode:
            self._log.log(Log(timestamp=ts, level=LogLevel.Info, name="otbot",
                              message=f"mode {slot.prev_mode or '-'} -> {slot.mode}"), log_time=stamp)
        for f in slot.faults:
            if f not in slot.prev_faults:
                self._log.log(Log(timestamp=ts, level=LogLevel.Error, name="otbot", message=f"fault: {str(f)}"),
                              log_time=stamp)
        if slot.prev_faults and not slot.faults:
            self._log.log(Log(timestamp=ts, level=LogLevel.Info, name="otbot", message="faults cleared"),
                          log_time=stamp)

    def _publish_cycle(self, s: Slot, stamp: int) -> None:
        from foxglove.messages import FrameTransform, FrameTransforms, Quaternion, Timestamp, Vector3

        ts = Timestamp(stamp // 1_000_000_000, stamp % 1_000_000_000)
        t = s.t
        v, has = s.vec, s.has

        def tf(parent, child, x, y, yaw):
            return FrameTransform(timestamp=ts, parent_frame_id=parent, child_frame_id=child,
                                  translation=Vector3(x=float(x), y=float(y), z=0.0),
                                  rotation=Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)))

        (cx, cy), cyaw = chassis_in_platform(float(v[2]), self.l1)
        transforms = [tf(PLATFORM, CHASSIS, cx, cy, cyaw)]
        pose, ref = v[9:12], v[21:24]
        if has[_POSE]:
            transforms.append(tf(WORLD, PLATFORM, pose[0], pose[1], float(pose[2])))
        if has[_REF]:
            transforms.append(tf(WORLD, REFERENCE, ref[0], ref[1], float(ref[2])))
        self._tf.log(FrameTransforms(transforms=transforms), log_time=stamp)
        self._json["/otbot/joints"].log({"t": t, "name": JOINT_NAMES, "position": _list(v[0:3]),
                                         "velocity": _list(v[3:6])}, log_time=stamp)
        torque = v[6:9]
        self._json["/otbot/torques"].log(
            {"t": t, "name": JOINT_NAMES, "commanded": _list(torque), "limit": _list(self.limits),
             "ratio": _list(torque / self.limits), "saturated": [bool(b) for b in s.saturated]}, log_time=stamp)
        if has[_POSE]:
            est = {"t": t, "pose": _list(pose)}
            if has[_TWIST]:
                est["twist"] = _list(v[12:15])
            if has[_STD]:
                est["std"] = _list(v[15:21])
            if has[_BIAS]:
                est["gyro_bias"] = _num(float(v[24]))
            self._json["/otbot/estimate"].log(est, log_time=stamp)
            if has[_REF]:
                ex, ey = float(ref[0] - pose[0]), float(ref[1] - pose[1])
                self._json["/otbot/tracking_error"].log(
                    {"t": t, "x": _num(ex), "y": _num(ey), "alpha": _num(wrap_angle(float(ref[2] - pose[2]))),
                     "norm": _num(math.hypot(ex, ey))}, log_time=stamp)

def _num(x: float) -> float | None:
    return x if math.isfinite(x) else None


def _list(v) -> list[float]:
    """Plain floats; non-finite values become None (JSON has no NaN)."""
    return [float(x) if math.isfinite(x) else None for x in np.asarray(v, float).ravel()]


def _json_bytes(schema: dict) -> bytes:
    import json
    return json.dumps(schema).encode()
