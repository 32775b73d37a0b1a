"""CiA 406 absolute rotary encoder on the pivot (phi_p feedback).

Setup: heartbeat producer time (0x1017), resolution read from the device: measuring units per
revolution 0x6001 and total measuring range 0x6002; TPDO1 = position value 0x6004, synchronous
(type 1), the other TPDOs disabled. phi_p = direction * (counts - offset) / (units_per_rev *
gear_ratio) * 2 pi rad; readings are unwrapped modulo the total range, the first one taken in
(-range/2, range/2] around the offset.
"""
from __future__ import annotations

import math

import canopen

from drivers.config import EncoderConfig
from drivers.device import CanopenDevice, pdo_get
from drivers.faults import DriverError
from drivers.mapping import Need

TPDO_LAYOUT = {1: [0x6004]}
TX_NEEDS = [Need(0x6004)]


class CiA406Encoder(CanopenDevice):
    """The pivot encoder (configuration ``cfg``) on ``network``."""

    def __init__(self, network: canopen.Network, cfg: EncoderConfig, tracker, on_fault):
        super().__init__(network, "pivot_encoder", cfg.node_id, cfg.eds, tracker, on_fault)
        self.cfg = cfg
        self.units_per_rev = 0
        self.total_range = 0
        self._last: int | None = None
        self._counts = 0  # unwrapped counts relative to the offset
        self.static_plan = self.plan_pdos([], TX_NEEDS, {}, TPDO_LAYOUT)

    def configure(self) -> None:
        self.sdo_write(0x1017, 0, int(round(self.cfg.heartbeat_producer * 1000)))
        self.units_per_rev = int(self.sdo_read(0x6001))
        self.total_range = int(self.sdo_read(0x6002))
        if self.units_per_rev <= 0 or self.total_range < self.units_per_rev:
            f = self.fault("config", f"encoder resolution 0x6001 = {self.units_per_rev}, range 0x6002 = "
                                     f"{self.total_range}: not a usable absolute encoder")
            raise DriverError(str(f), (f,))
        if not 0 <= self.cfg.offset < self.total_range:
            f = self.fault("config", f"'pivot_encoder.offset' = {self.cfg.offset} counts is outside the encoder "
                                     f"range 0..{self.total_range - 1} (0x6002)")
            raise DriverError(str(f), (f,))
        self.map_pdos(self.static_plan)
        self.hook_tpdos()
        self._last = None

    def on_valid_tpdo(self, number: int, pdo_map) -> None:
        raw = int(pdo_get(pdo_map[0x6004]))
        rng = self.total_range
        if self._last is None:
            d = (raw - self.cfg.offset) % rng
            self._counts = d - rng if d > rng // 2 else d
        else:
            d = (raw - self._last) % rng
            self._counts += d - rng if d > rng // 2 else d
        self._last = raw

    @property
    def position(self) -> float:
        """phi_p, rad."""
        return self.cfg.direction * self._counts * 2 * math.pi / (self.units_per_rev * self.cfg.gear_ratio)
