"""The client half of the Foxglove WebSocket protocol (websockets), for the telemetry and daemon tests."""
from __future__ import annotations

import base64
import contextlib
import json
import struct

import websockets.sync.client as websockets_sync
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory


class FoxgloveClient:
    """The client half of the Foxglove WebSocket protocol, on the websockets library."""

    def __init__(self, url: str):
        self._stack = contextlib.ExitStack()
        self.ws = self._stack.enter_context(websockets_sync.connect(
            url, subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"], proxy=None, open_timeout=5))
        self.info = self.recv_json("serverInfo")
        self.channels = {c["id"]: c for c in self.recv_json("advertise")["channels"]}
        self.by_topic = {c["topic"]: c for c in self.channels.values()}
        self.subs: dict[int, dict] = {}
        self.decoders = {}
        self.text: list[dict] = []

    def recv_json(self, op: str) -> dict:
        while True:
            m = json.loads(self.ws.recv(timeout=5))
            if m["op"] == op:
                return m
            self.text.append(m)

    def subscribe(self, topics) -> None:
        subs = []
        for i, topic in enumerate(sorted(topics)):
            ch = self.by_topic[topic]
            self.subs[100 + i] = ch
            subs.append({"id": 100 + i, "channelId": ch["id"]})
            if ch["encoding"] == "protobuf":
                fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(ch["schema"]))
                pool = descriptor_pool.DescriptorPool()
                for f in fds.file:
                    pool.Add(f)
                self.decoders[topic] = message_factory.GetMessageClass(pool.FindMessageTypeByName(ch["schemaName"]))
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def messages(self, quiet: float = 0.3, duration: float = float("inf")) -> list[tuple[str, int, object]]:
        """(topic, log time ns, decoded message) of every message data frame until ``quiet`` s pass
        without one, or ``duration`` s in all (a live stream never goes quiet)."""
        import time

        out = []
        end = time.monotonic() + duration
        while time.monotonic() < end:
            try:
                m = self.ws.recv(timeout=min(quiet, max(0.0, end - time.monotonic())))
            except TimeoutError:
                return out
            if isinstance(m, str):
                self.text.append(json.loads(m))
                continue
            assert m[0] == 0x01, f"unexpected binary opcode {m[0]}"
            sub, stamp = struct.unpack_from("<IQ", m, 1)
            topic = self.subs[sub]["topic"]
            payload = m[13:]
            dec = self.decoders.get(topic)
            out.append((topic, stamp, dec.FromString(payload) if dec else json.loads(payload)))
        return out

    def close(self):
        self._stack.close()
