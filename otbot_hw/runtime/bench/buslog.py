"""The raw CAN bus log of a bench session: python-can's BLF writer on the master's bus.

``BusLog(path).attach(network)`` makes a ``can.BLFWriter`` a listener of the master's
``canopen.Network`` notifier (every frame the master receives: TPDOs, heartbeats, EMCY, SDO
answers) and logs every frame the master sends (SYNC, RPDOs, NMT, SDO requests) through the
network's ``send_message`` (canopen's documented hook for integrating another back end), marked
``is_rx=False``. One lock serializes the two threads. The log starts when the bench takes the
robot over (after the drivers booted and configured the nodes). Read it with ``can.BLFReader``
(or any BLF viewer).
"""
from __future__ import annotations

import threading
import time
from pathlib import Path

import can


class BusLog(can.Listener):
    """A BLF file of both directions of the master's bus traffic."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.writer = can.BLFWriter(str(self.path))
        self.lock = threading.Lock()
        self.frames = 0
        self.errors: list[str] = []
        self._network = None
        self._send = None

    def on_message_received(self, msg: can.Message) -> None:
        """Log one frame on BLF channel 1 (the bus's own channel names, e.g. a virtual bus's, are not
        numbers). Never raises: a logging problem must not stop the notifier that runs the bus."""
        frame = can.Message(timestamp=msg.timestamp, arbitration_id=msg.arbitration_id,
                            is_extended_id=msg.is_extended_id, is_remote_frame=msg.is_remote_frame,
                            is_error_frame=msg.is_error_frame, dlc=msg.dlc, data=msg.data, is_rx=msg.is_rx,
                            channel=None)
        with self.lock:
            if self.writer is None:
                return
            try:
                self.writer.on_message_received(frame)
                self.frames += 1
            except Exception as exc:  # noqa: BLE001 - counted and reported, the bus goes on
                self.errors.append(f"{type(exc).__name__}: {exc}")

    def attach(self, network) -> "BusLog":
        """Log ``network``'s (a connected ``canopen.Network``) received and sent frames."""
        network.notifier.add_listener(self)
        send = network.send_message

        def send_message(can_id: int, data: bytes, remote: bool = False) -> None:
            send(can_id, data, remote)
            self.on_message_received(can.Message(timestamp=time.time(), arbitration_id=can_id,
                                                 is_extended_id=can_id > 0x7FF, data=bytes(data),
                                                 is_remote_frame=remote, is_rx=False))

        network.send_message = send_message
        self._network, self._send = network, send
        return self

    def stop(self) -> None:
        """Detach and close the file (idempotent)."""
        if self._network is not None:
            try:
                self._network.notifier.remove_listener(self)
            except (ValueError, AttributeError):
                pass
            self._network.send_message = self._send
            self._network = None
        with self.lock:
            if self.writer is not None:
                self.writer.stop()
                self.writer = None
