"""CAN bus load of the control cycle: bits per cycle of SYNC and the configured PDOs (drives
and pivot encoder), heartbeats as background load, and the highest control rate the bitrate
allows.

A classical CAN 2.0A data frame with n data bytes has 47 + 8n bits (SOF, 11-bit ID, RTR,
IDE, r0, DLC, data, 15-bit CRC, CRC delimiter, ACK slot and delimiter, 7-bit EOF) plus 3 bits
of interframe space; bit stuffing inserts up to floor((34 + 8n - 1) / 4) bits into the 34 + 8n
bits from SOF to the end of the CRC (worst case). An 8-byte frame thus takes 135 bit times.
"""
from __future__ import annotations

from dataclasses import dataclass

import canopen

from drivers import cia402, cia406
from drivers.config import RobotConfig

INTERFRAME_BITS = 3


def frame_bits(n_bytes: int, stuffing: bool = True) -> int:
    """Bit times of a standard-ID data frame with ``n_bytes`` data bytes, incl. interframe space."""
    if not 0 <= n_bytes <= 8:
        raise ValueError(f"a classical CAN frame carries 0..8 data bytes, got {n_bytes}")
    stuffed_region = 34 + 8 * n_bytes
    stuff = (stuffed_region - 1) // 4 if stuffing else 0
    return stuffed_region + stuff + 10 + INTERFRAME_BITS  # + CRC delimiter, ACK (2), EOF (7)


def _pdo_sizes(eds, layout: dict) -> list[int]:
    od = canopen.import_od(str(eds), 1)
    return [sum(len(od[i]) for i in objs) // 8 for objs in layout.values()]


@dataclass(frozen=True)
class BusLoad:
    """Per control cycle: frames (name, bytes, bits), bits per cycle; background heartbeat load
    (bit/s); the highest feasible control rate (Hz) at 100 % bus load; load at ``rate`` (fraction)."""

    frames: tuple
    bits_per_cycle: int
    background_bps: float
    bitrate: int
    rate: float

    @property
    def max_rate(self) -> float:
        return (self.bitrate - self.background_bps) / self.bits_per_cycle

    @property
    def load(self) -> float:
        return (self.bits_per_cycle * self.rate + self.background_bps) / self.bitrate

    def warning(self) -> str | None:
        if self.rate > self.max_rate:
            return (f"control rate {self.rate:g} Hz exceeds what {self.bitrate / 1000:g} kbit/s carries: "
                    f"{self.bits_per_cycle} bits per cycle (worst-case stuffing) allow at most "
                    f"{self.max_rate:.0f} Hz")
        return None

    def to_dict(self) -> dict:
        return {"frames": [{"frame": f, "bytes": b, "bits": n} for f, b, n in self.frames],
                "bits_per_cycle": self.bits_per_cycle, "background_bps": self.background_bps,
                "bitrate": self.bitrate, "rate": self.rate, "max_rate": self.max_rate, "load": self.load}


def bus_load(config: RobotConfig, rate: float | None = None) -> BusLoad:
    """Bus load of ``config`` at ``rate`` Hz (default: the configured control rate)."""
    frames = [("SYNC", 0, frame_bits(0))]
    rsizes = _pdo_sizes(config.drives[0].eds, cia402.RPDO_LAYOUT)
    tsizes = _pdo_sizes(config.drives[0].eds, cia402.TPDO_LAYOUT)
    background = 0.0
    for d in config.drives:
        for no, n in zip(cia402.RPDO_LAYOUT, rsizes):
            frames.append((f"{d.name} RPDO{no}", n, frame_bits(n)))
        for no, n in zip(cia402.TPDO_LAYOUT, tsizes):
            frames.append((f"{d.name} TPDO{no}", n, frame_bits(n)))
        background += frame_bits(1) / d.heartbeat_producer
    enc = config.pivot_encoder
    if enc.source == "encoder":
        for no, n in zip(cia406.TPDO_LAYOUT, _pdo_sizes(enc.eds, cia406.TPDO_LAYOUT)):
            frames.append((f"pivot_encoder TPDO{no}", n, frame_bits(n)))
        background += frame_bits(1) / enc.heartbeat_producer
    return BusLoad(frames=tuple(frames), bits_per_cycle=sum(f[2] for f in frames), background_bps=background,
                   bitrate=config.bus.bitrate, rate=rate if rate is not None else config.bus.control_rate)
