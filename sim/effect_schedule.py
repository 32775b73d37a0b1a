"""Effects of the simulated robot that change during a run (e.g. bursts of wheel slip).

``EffectSchedule`` [(t_start s, {effect: value})] sets entries of the extended model's effect vector
(``otbot_hw.model.effects``) at plant time; ``with_schedule(backend, schedule)`` wraps a simulated back
end so that its robots (``sim.scheduled_robot.ScheduledRobot`` around a ``sim.direct.DirectSimRobot`` or
``sim.bus_robot.SimulatedBusRobot``) have the effects of t_k in force before every read. The robot must step the
extended model: its plant an ``ExtendedModel`` whose effects include every scheduled one (give them
their burst value; the schedule's first entry sets the value at t = 0).
"""
from __future__ import annotations

import numpy as np

from otbot_hw.model import effects as fx
from otbot_hw.robot import SimulatedRobot
from sim.scheduled_robot import ScheduledBackend, stepper_and_clock


class EffectSchedule:
    """[(t_start s, {effect name: value})], sorted by time; the first entry starts at t = 0."""

    def __init__(self, entries):
        self.entries = sorted(((float(t), dict(v)) for t, v in entries), key=lambda e: e[0])
        if not self.entries or self.entries[0][0] != 0.0:
            raise ValueError("an effect schedule starts at t = 0")
        for _, values in self.entries:
            for name in values:
                if name not in fx.EFFECT_INDEX:
                    raise ValueError(f"unknown effect {name!r} (known: {', '.join(fx.EFFECT_PARAM_NAMES)})")
        self.names = sorted({n for _, v in self.entries for n in v})

    @classmethod
    def bursts(cls, name: str, value: float, starts, duration: float) -> "EffectSchedule":
        """``name`` at ``value`` for ``duration`` s from each of ``starts`` (s), 0 otherwise."""
        out = [(0.0, {name: 0.0})]
        for t0 in sorted(starts):
            out += [(float(t0), {name: float(value)}), (float(t0) + duration, {name: 0.0})]
        return cls(out)

    def values_at(self, t: float) -> dict:
        """The scheduled values in force at t (s): each entry's values hold until an entry changes them."""
        cur: dict = {}
        for t0, values in self.entries:
            if t0 > t + 1e-9:
                break
            cur.update(values)
        return cur

    def active(self, t: float, name: str) -> bool:
        return self.values_at(t).get(name, 0.0) != 0.0


def _effect_change(schedule: EffectSchedule):
    """The change before each read: the scheduled effects of the plant's time written into the effect
    vector of the robot's extended-model stepper."""
    def make(robot: SimulatedRobot, plant):
        stepper, clock = stepper_and_clock(robot)
        eff = getattr(stepper, "eff", None)
        if eff is None:
            raise ValueError("scheduled effects need a robot that steps the extended model (an ExtendedModel "
                             "plant with the scheduled effects active)")

        def change() -> None:
            for name, v in schedule.values_at(clock()).items():
                eff[fx.EFFECT_INDEX[name]] = v
        return change
    return make


def with_schedule(backend, schedule: EffectSchedule) -> ScheduledBackend:
    """``backend`` (``DirectBackend`` or ``BusSimBackend``) with its robots' effects following ``schedule``."""
    def prepare(plant):
        if not hasattr(plant, "eff") or any(plant.eff[fx.EFFECT_INDEX[n]] == 0.0 for n in schedule.names):
            raise ValueError("scheduled effects need an ExtendedModel plant with every scheduled effect active "
                             f"({', '.join(schedule.names)})")
        return fx.ExtendedModel(plant.params, np.array(plant.eff, dtype=float))  # the schedule writes into its effects

    return ScheduledBackend(backend, "effect_schedule", schedule.entries, _effect_change(schedule), prepare)
