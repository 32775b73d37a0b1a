"""A simulated CiA 406 multi-turn absolute encoder on the pivot."""
from __future__ import annotations

import math

import canopen

from drivers.config import EncoderConfig
from sim.canopen_slaves.node import SimulatedNode


class SimulatedEncoder(SimulatedNode):
    """A CiA 406 multi-turn absolute encoder on the pivot: 0x6004 position value in measuring
    units, (offset + direction * floor(phi_p * gear * units_per_rev / 2 pi)) mod total range,
    units per revolution 0x6001 and total range 0x6002 as configured in the object dictionary."""

    def __init__(self, network: canopen.Network, cfg: EncoderConfig):
        super().__init__(network, cfg.node_id, cfg.eds, "pivot_encoder")
        self.cfg = cfg
        self._preset_shift = 0
        self.values.update({(0x6004, 0): 0, (0x6503, 0): 0, (0x6505, 0): 0, (0x1001, 0): 0})

    def on_sdo_write(self, index: int, subindex: int, value) -> None:
        pass

    def _on_write(self, index, subindex, od, data):
        super()._on_write(index, subindex, od, data)
        if index == 0x6003:  # preset: the current position reads the preset value from now on
            self._preset_shift += od.decode_raw(data) - self.values[(0x6004, 0)]

    def position_counts(self, phi: float) -> int:
        upr = self.od_value(0x6001)
        rng = self.od_value(0x6002)
        c = math.floor(phi * self.cfg.gear_ratio * upr / (2 * math.pi) + 1e-9)
        if self.od_value(0x6000, 0, 0) & 0x1:  # code sequence: counting direction inverted
            c = -c
        return (self.cfg.offset + self.cfg.direction * c + self._preset_shift) % rng

    def sample(self, phi: float) -> None:
        self.values[(0x6004, 0)] = self.position_counts(phi)

    def inject_fault(self, code: int = 0x7320) -> None:
        """Position sensor fault: alarm bit, error register and EMCY."""
        with self.lock:
            self.values[(0x6503, 0)] = 0x0001
            self.values[(0x1001, 0)] = 0x01
            if not self.silent:
                self.node.emcy.send(code, 0x01)
