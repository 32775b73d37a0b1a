"""CAN bus load of the control cycle: bits per cycle of SYNC and the PDOs planned from each
device's object dictionary (drives and pivot encoder), heartbeats (the nodes' and the master's)
as background load, and the highest control rate the bitrate
allows.

A classical CAN 2.0A data frame with n data bytes has 47 + 8n bits (SOF, 11-bit ID, RTR,
IDE, r0, DLC, data, 15-bit CRC, CRC delimiter, ACK slot and delimiter, 7-bit EOF) plus 3 bits
of interframe space; bit stuffing inserts up to floor((34 + 8n - 1) / 4) bits into the 34 + 8n
bits from SOF to the end of the CRC (worst case). An 8-byte frame thus takes 135 bit times.
"""
from __future__ import annotations

from dataclasses import dataclass

from drivers import cia402, cia406, mapping
from drivers.config import RobotConfig
from drivers.faults import DeviceConfigError
from otbot_hw.robot import Fault

INTERFRAME_BITS = 3


def frame_bits(n_bytes: int, stuffing: bool = True) -> int:
    """Bit times of a standard-ID data frame with ``n_bytes`` data bytes, incl. interframe space."""
    if not 0 <= n_bytes <= 8:
        raise ValueError(f"a classical CAN frame carries 0..8 data bytes, got {n_bytes}")
    stuffed_region = 34 + 8 * n_bytes
    stuff = (stuffed_region - 1) // 4 if stuffing else 0
    return stuffed_region + stuff + 10 + INTERFRAME_BITS  # + CRC delimiter, ACK (2), EOF (7)


def pdo_plan(name: str, node_id: int, eds, encoder: bool = False) -> mapping.Plan:
    """The PDO plan of a device from its EDS alone (no bus): ``DeviceConfigError`` naming the device
    and the object when the dictionary cannot carry what the loop needs."""
    device = f"{name} (node {node_id})"
    try:
        od = mapping.import_dictionary(eds, node_id, device)
        if encoder:
            return mapping.plan_pdos(od, node_id, device, [], cia406.TX_NEEDS, {}, cia406.TPDO_LAYOUT)
        return cia402.plan_drive_pdos(od, node_id, device)
    except mapping.PlanError as exc:
        raise DeviceConfigError(str(exc), (Fault(name, node_id, "config", str(exc).split(": ", 1)[1]),)) from None


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
    background = frame_bits(1) / config.bus.master_heartbeat
    for d in config.drives:
        plan = pdo_plan(d.name, d.node_id, d.eds)
        for no, n in mapping.sizes(plan.rx).items():
            frames.append((f"{d.name} RPDO{no}", n, frame_bits(n)))
        for no, n in mapping.sizes(plan.tx).items():
            frames.append((f"{d.name} TPDO{no}", n, frame_bits(n)))
        background += frame_bits(1) / d.heartbeat_producer
    enc = config.pivot_encoder
    if enc.source == "encoder":
        for no, n in mapping.sizes(pdo_plan("pivot_encoder", enc.node_id, enc.eds, encoder=True).tx).items():
            frames.append((f"pivot_encoder TPDO{no}", n, frame_bits(n)))
        background += frame_bits(1) / enc.heartbeat_producer
    return BusLoad(frames=tuple(frames), bits_per_cycle=sum(f[2] for f in frames), background_bps=background,
                   bitrate=config.bus.bitrate, rate=rate if rate is not None else config.bus.control_rate)
