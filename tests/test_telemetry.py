"""Live telemetry through a real WebSocket client speaking the Foxglove protocol (websockets):
serverInfo and advertise, subscribe, binary message frames decoded (protobuf from the advertised
schema, JSON); rate limit; faults at once; read-only (client advertise refused, no services);
the chassis frame obeys the rolling constraints."""
from __future__ import annotations

import json
import math
import struct
import threading
import time

import numpy as np
import pytest
from scipy.linalg import null_space

pytest.importorskip("foxglove")
pytest.importorskip("websockets.sync.client")
pytest.importorskip("google.protobuf.descriptor_pb2")

from foxglove_client import FoxgloveClient  # noqa: E402
from otbot_hw.model.kinematics import constraint_jacobian  # noqa: E402
from otbot_hw.params import nominal  # noqa: E402
from otbot_hw.robot import Fault  # noqa: E402
from otbot_hw.runtime.telemetry import (  # noqa: E402
    TelemetryError, TelemetrySample, TelemetryServer, chassis_in_platform, parse_host_port, wrap_angle)

TOPICS = {"/tf", "/otbot/log", "/otbot/joints", "/otbot/torques", "/otbot/tracking_error", "/otbot/estimate",
          "/otbot/status"}
L1 = 0.27


@pytest.fixture
def telemetry():
    srv = TelemetryServer(host="127.0.0.1", port=0, rate=50.0, limits=[40.0, 40.0, 30.0], l1=L1)
    yield srv
    srv.close()


def sample(k: int, **kw) -> TelemetrySample:
    base = dict(t=k * 0.004, joint_pos=np.array([1.0 + k, -2.0, 0.3]), joint_vel=np.array([0.1, 0.2, -0.3]),
                torque=np.array([4.0, -40.0, 3.0]), saturated=(False, True, False),
                pose=np.array([1.5, -0.25, 3.1]), twist=np.array([0.2, 0.0, 0.1]), std=np.full(6, 0.01),
                gyro_bias=0.002, reference=np.array([1.6, -0.2, -3.1]), mode="track",
                drive_states=("OPERATION ENABLED",) * 3)
    base.update(kw)
    return TelemetrySample(**base)


def test_a_foxglove_client_subscribes_and_decodes_every_channel(telemetry):
    c = FoxgloveClient(telemetry.url)
    try:
        assert c.ws.subprotocol == "foxglove.sdk.v1"  # the SDK's name for the v1 protocol
        assert c.info["capabilities"] == []           # read-only: no clientPublish, services, parameters
        assert set(c.by_topic) == TOPICS
        tf = c.by_topic["/tf"]
        assert (tf["schemaName"], tf["encoding"], tf["schemaEncoding"]) == ("foxglove.FrameTransforms", "protobuf",
                                                                             "protobuf")
        assert c.by_topic["/otbot/joints"]["schemaName"] == "otbot.JointState"
        c.subscribe(TOPICS)
        deadline = time.monotonic() + 5
        while telemetry.listener.subscriptions < len(TOPICS) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert telemetry.listener.subscriptions == len(TOPICS)
        for k in range(250):  # 1 s of a 250 Hz loop
            telemetry.publish(sample(k), now=k * 0.004)
        msgs = c.messages()
    finally:
        c.close()
    by = {}
    for topic, stamp, m in msgs:
        by.setdefault(topic, []).append(m)
    assert len(by["/otbot/joints"]) == 50  # 50 Hz of 250 Hz calls
    assert telemetry.state.published == 50 and telemetry.state.skipped == 200
    assert [j["t"] for j in by["/otbot/joints"][:3]] == pytest.approx([0.0, 0.02, 0.04])
    last = sample(245)
    frames = {(t.parent_frame_id, t.child_frame_id): t for t in by["/tf"][-1].transforms}
    w = frames[("world", "platform")]
    assert (w.translation.x, w.translation.y, w.translation.z) == (1.5, -0.25, 0.0)
    assert 2 * math.atan2(w.rotation.z, w.rotation.w) == pytest.approx(3.1)
    ch = frames[("platform", "chassis")]
    assert (ch.translation.x, ch.translation.y) == pytest.approx((-L1 * math.cos(0.3), L1 * math.sin(0.3)))
    assert 2 * math.atan2(ch.rotation.z, ch.rotation.w) == pytest.approx(-0.3)
    assert ("world", "reference") in frames
    j = by["/otbot/joints"][-1]
    assert j["name"] == ["right_wheel", "left_wheel", "pivot"] and j["position"] == list(last.joint_pos)
    tq = by["/otbot/torques"][-1]
    assert tq["limit"] == [40.0, 40.0, 30.0] and tq["ratio"] == [0.1, -1.0, 0.1] and tq["saturated"] == [False, True, False]
    err = by["/otbot/tracking_error"][-1]
    assert err["x"] == pytest.approx(0.1) and err["y"] == pytest.approx(0.05)
    assert err["alpha"] == pytest.approx(2 * math.pi - 6.2)  # wrapped, not -6.2
    est = by["/otbot/estimate"][-1]
    assert est["std"] == [0.01] * 6 and est["gyro_bias"] == 0.002
    assert by["/otbot/status"][0] == {"t": 0.0, "mode": "track", "faults": [], "drive_states": ["OPERATION ENABLED"] * 3}
    assert "mode - -> track" in by["/otbot/log"][0].message


def test_faults_go_out_at_once_and_nan_never_reaches_json(telemetry):
    c = FoxgloveClient(telemetry.url)
    try:
        subscribed(telemetry, c, {"/otbot/status", "/otbot/log", "/otbot/estimate"})
        telemetry.publish(sample(0), now=0.0)
        fault = Fault("pivot", 3, "emcy", "excess current", code=0x2310)
        # 4 ms later: inside the 20 ms rate window, but a new fault is never held back
        assert telemetry.publish(sample(1, faults=(fault,), mode="idle", pose=np.array([np.nan, 0.0, 0.0])), now=0.004)
        msgs = c.messages()
    finally:
        c.close()
    status = [m for t, _, m in msgs if t == "/otbot/status"]
    assert status[-1]["faults"] == ["pivot (node 3): emcy 0x2310: excess current"] and status[-1]["mode"] == "idle"
    logs = [m for t, _, m in msgs if t == "/otbot/log"]
    assert any(m.message == "fault: pivot (node 3): emcy 0x2310: excess current" and m.level == 4 for m in logs)
    assert any(m.message == "mode track -> idle" for m in logs)
    assert len([1 for t, _, _ in msgs if t == "/otbot/estimate"]) == 1  # the cycle itself was rate limited
    telemetry.publish(sample(10, pose=np.array([np.nan, 0.0, 0.0])), now=1.0)
    # json.loads in the client would have accepted NaN; the server must not send it
    assert telemetry.state.published == 2


def test_a_stalled_consumer_drops_the_oldest_and_never_blocks_the_loop():
    """The telemetry thread stuck in a send: the loop's 100 publishes (each due) all return, the oldest
    queued samples are dropped and counted, and once the consumer runs again it sends the newest ones."""
    srv = TelemetryServer(host="127.0.0.1", port=0, rate=50.0, limits=[40.0, 40.0, 30.0], l1=L1, queue_size=8)
    release, sent = threading.Event(), []
    send = srv._send

    def stalled(slot):
        release.wait(30)
        sent.append(slot.t)
        send(slot)

    srv._send = stalled
    try:
        loop = threading.Thread(target=lambda: [srv.publish(sample(k), now=k * 0.02) for k in range(100)])
        loop.start()
        loop.join(20)
        assert not loop.is_alive()  # the loop never waited for the stalled consumer
        assert srv.state.published == 100 and srv.state.dropped >= 100 - 10  # 8 queued + 2 spare slots at most
        release.set()
        assert srv.flush(10)
    finally:
        release.set()
        srv.close()
    assert len(sent) + srv.state.dropped == 100 and srv.state.errors == 0
    assert sent[-9:] == pytest.approx([k * 0.004 for k in range(91, 100)])  # the newest survive


def subscribed(telemetry, c, topics) -> None:
    """Subscribe and wait (5 s at most) until the server has taken the subscriptions: a publish
    before that reaches no one, however long a fixed sleep a loaded machine outlasts."""
    before = telemetry.listener.subscriptions
    c.subscribe(topics)
    deadline = time.monotonic() + 5
    while telemetry.listener.subscriptions < before + len(topics) and time.monotonic() < deadline:
        time.sleep(0.01)
    assert telemetry.listener.subscriptions == before + len(topics)


def test_clients_cannot_publish_or_call_services(telemetry):
    c = FoxgloveClient(telemetry.url)
    try:
        assert not any(m.get("op") == "advertiseServices" for m in c.text)
        c.ws.send(json.dumps({"op": "advertise", "channels": [
            {"id": 1, "topic": "/cmd_vel", "encoding": "json", "schemaName": "x"}]}))
        refusal = c.recv_json("status")
        assert refusal["level"] == 2  # error
        c.ws.send(b"\x01" + struct.pack("<I", 1) + b'{"vx": 1}')                       # client message data
        c.ws.send(b"\x02" + struct.pack("<III", 1, 1, 4) + b"json" + b"{}")            # service call request
        c.ws.send(json.dumps({"op": "setParameters", "parameters": [{"name": "mode", "value": "track"}]}))
        time.sleep(0.3)
        # still connected and serving
        subscribed(telemetry, c, {"/otbot/joints"})
        telemetry.publish(sample(0), now=0.0)
        assert [t for t, _, _ in c.messages()] == ["/otbot/joints"]
    finally:
        c.close()
    assert telemetry.listener.client_messages == 0
    assert not any(m.get("op") in ("advertiseServices", "parameterValues") for m in c.text)


def test_the_chassis_frame_origin_moves_only_along_its_heading():
    """The wheel-axis midpoint cannot slide sideways: placed by ``chassis_in_platform``, its velocity
    under any motion allowed by the rolling constraints is along the chassis heading."""
    p = nominal()
    rng = np.random.default_rng(3)
    for _ in range(20):
        q = rng.uniform(-3, 3, 6)
        qd = null_space(constraint_jacobian(q, p)) @ rng.normal(size=3)

        def m_ground(q):
            (cx, cy), yaw = chassis_in_platform(q[5], p.l1)
            ca, sa = math.cos(q[2]), math.sin(q[2])
            return np.array([q[0] + ca * cx - sa * cy, q[1] + sa * cx + ca * cy]), q[2] + yaw

        h = 1e-6
        (m1, _), (m2, _), (_, yaw) = m_ground(q - h * qd), m_ground(q + h * qd), m_ground(q)
        v = (m2 - m1) / (2 * h)
        theta = q[2] - q[5]
        assert wrap_angle(yaw - theta) == pytest.approx(0.0, abs=1e-12)
        assert abs(-math.sin(theta) * v[0] + math.cos(theta) * v[1]) < 1e-6 * (1 + np.linalg.norm(v))
        assert np.linalg.norm(v) > 1e-3  # a real motion, not a standstill


def test_host_port():
    assert parse_host_port("127.0.0.1:9000") == ("127.0.0.1", 9000)
    assert parse_host_port("localhost") == ("localhost", 8765)
    assert parse_host_port("[::1]:8766") == ("::1", 8766)
    for bad in ("host:port", ":80", "h:70000", "[::1"):
        with pytest.raises(ValueError, match="telemetry address"):
            parse_host_port(bad)


def test_a_taken_port_is_one_sentence(telemetry):
    with pytest.raises(TelemetryError, match=f"cannot serve telemetry on 127.0.0.1:{telemetry.port}: .*in use"):
        TelemetryServer(port=telemetry.port)
