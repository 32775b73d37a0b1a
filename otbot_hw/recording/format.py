"""The recording format (``docs/recording-format.md``): format name and version, the topics with the JSON
schema of each payload, units and frames written into every file's metadata, the metadata ``source``
(``source_metadata``), and a run in memory (``Recording``: numpy arrays, one row per sample).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

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
