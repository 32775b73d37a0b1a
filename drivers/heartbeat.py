"""Heartbeat consumer (CiA 301 §7.2.8.3.2.2): a node whose heartbeat stops for longer than its
consumer time, or that reports an unexpected NMT state, is faulted.

canopen's ``NmtMaster`` records heartbeats but never times out; this class does. It watches
the heartbeat COB-IDs (0x700 + node ID) on a ``canopen.Network``; ``check()`` returns new
faults, and ``start()`` runs the check in a background thread every consumer time / 10 so a
silent node is reported even while no control cycle runs.
"""
from __future__ import annotations

import struct
import threading
import time
from dataclasses import dataclass
from typing import Callable

from canopen.nmt import NMT_STATES

from otbot_hw.robot import Fault


@dataclass
class _Watch:
    device: str
    node: int
    timeout: float
    last: float | None = None
    state: int | None = None
    expected: int | None = None  # NMT state the node must report (None: any)
    previous: int | None = None  # also accepted until the node first reports ``expected``
    faulted: bool = False
    rebooted: bool = False  # a boot-up message arrived while monitoring
    malformed: int = 0


class HeartbeatConsumer:
    """Monitors heartbeats of several nodes; times in seconds (host monotonic clock)."""

    def __init__(self, network, on_fault: Callable[[Fault], None] | None = None):
        self.network = network
        self.on_fault = on_fault
        self._watch: dict[int, _Watch] = {}
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    def add(self, node_id: int, device: str, timeout: float) -> None:
        """Watch node ``node_id``: fault when no heartbeat for ``timeout`` s once monitoring started."""
        self._watch[node_id] = _Watch(device=device, node=node_id, timeout=timeout)
        self.network.subscribe(0x700 + node_id, self._on_heartbeat)

    def _on_heartbeat(self, can_id: int, data: bytes, timestamp: float) -> None:
        w = self._watch.get(can_id - 0x700)
        if w is None:
            return
        if len(data) != 1:
            w.malformed += 1
            return
        (state,) = struct.unpack("B", data)
        with self._lock:
            w.last = time.monotonic()
            w.state = state & 0x7F
            if w.state == w.expected:
                w.previous = None
            if w.state == 0 and w.expected is not None:
                w.rebooted = True

    def expect_state(self, state: str | None) -> None:
        """From now on every watched node must report NMT ``state`` (e.g. 'OPERATIONAL'); None: any."""
        code = None if state is None else {v: k for k, v in NMT_STATES.items()}[state]
        with self._lock:
            now = time.monotonic()
            for w in self._watch.values():
                w.expected = code
                w.previous = None
                w.faulted = False
                w.rebooted = False
                if w.last is None:
                    w.last = now  # the timeout counts from the start of monitoring

    def expect_node(self, node_id: int, state: str) -> None:
        """Node ``node_id`` must report NMT ``state`` from now on (e.g. 'STOPPED' after the master's own
        NMT STOP: expected, not a fault)."""
        code = {v: k for k, v in NMT_STATES.items()}[state]
        with self._lock:
            w = self._watch[node_id]
            w.previous = w.expected if w.state != code else None  # heartbeats sent before the command
            w.expected = code
            w.rebooted = False

    def check(self, now: float | None = None) -> list[Fault]:
        """Faults that appeared since the last check (each node is reported once until it recovers)."""
        now = time.monotonic() if now is None else now
        out = []
        with self._lock:
            for w in self._watch.values():
                if w.faulted or w.last is None:
                    continue
                if now - w.last > w.timeout:
                    w.faulted = True
                    out.append(Fault(w.device, w.node, "heartbeat", f"no heartbeat for {now - w.last:.3f} s "
                                     f"(consumer time {w.timeout:.3f} s)", code=0x8130))
                elif w.rebooted or (w.expected is not None and w.state is not None
                                    and w.state not in (w.expected, w.previous)):
                    w.faulted = True
                    if w.rebooted:
                        meaning = "boot-up message: the node rebooted (power loss or reset) and lost its setup"
                    else:
                        meaning = (f"node reports NMT state {NMT_STATES.get(w.state, w.state)}, expected "
                                   f"{NMT_STATES[w.expected]} (reset or power loss?)")
                    out.append(Fault(w.device, w.node, "nmt", meaning))
        if self.on_fault:
            for f in out:
                self.on_fault(f)
        return out

    def start(self) -> None:
        """Check in a background thread every min(timeout) / 10 s."""
        if self._thread is not None or not self._watch:
            return
        period = min(w.timeout for w in self._watch.values()) / 10
        self._stop.clear()

        def loop():
            while not self._stop.wait(period):
                self.check()

        self._thread = threading.Thread(target=loop, name="heartbeat-consumer", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
            self._thread = None

    def state(self, node_id: int) -> int | None:
        """Last NMT state code ``node_id`` reported in a heartbeat (None before the first)."""
        return self._watch[node_id].state

    def age(self, node_id: int) -> float | None:
        """Seconds since the last heartbeat of ``node_id`` (None before the first)."""
        w = self._watch[node_id]
        return None if w.last is None else time.monotonic() - w.last


class HeartbeatProducer:
    """The master's own heartbeat (CiA 301 §7.2.8.3.2.1): NMT state OPERATIONAL (0x05) on COB-ID
    0x700 + ``node_id`` every ``period`` s, from a thread of its own. The drives consume it through
    0x1016 and apply their abort connection option when it stops. ``alive()`` (optional) is asked
    before every frame: while it says False (the control loop stalled) no heartbeat goes out
    (``withheld`` counts them), so the master's liveness is the loop's, not this thread's. A frame
    the bus cannot carry is counted (``failures``, last error in ``error``) and the next one tried a
    period later."""

    OPERATIONAL = 0x05

    def __init__(self, network, node_id: int, period: float, alive=None):
        self.network = network
        self.node_id = node_id
        self.period = period
        self.alive = alive
        self.withheld = 0  # times the heartbeat was withheld (loop stalls)
        self.withholding = False
        self.sent = 0
        self.failures = 0
        self.error: str | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def running(self) -> bool:
        return self._thread is not None

    def start(self) -> None:
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name=f"heartbeat-0x{0x700 + self.node_id:03X}",
                                            daemon=True)
            self._thread.start()

    def _run(self) -> None:
        due = time.monotonic()
        while not self._stop.is_set():
            if self.alive is not None and not self.alive():
                if not self.withholding:
                    self.withholding = True
                    self.withheld += 1
                self._stop.wait(self.period / 4)  # sends at once when the loop runs again
                continue
            self.withholding = False
            try:
                self.network.send_message(0x700 + self.node_id, bytes([self.OPERATIONAL]))
                self.sent += 1
            except Exception as exc:  # noqa: BLE001 - the bus is gone: keep trying, say why
                self.failures += 1
                self.error = str(exc) or type(exc).__name__
            due = max(due + self.period, time.monotonic())
            self._stop.wait(max(0.0, due - time.monotonic()))

    def stop(self) -> None:
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join(timeout=1.0)
