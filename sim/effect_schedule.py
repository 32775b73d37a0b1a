"""Effects of the simulated robot that change during a run (e.g. bursts of wheel slip).

``EffectSchedule`` [(t_start s, {effect: value})] sets entries of the extended model's effect vector
(``otbot_hw.model.effects``) at plant time; ``ScheduledEffects`` wraps a simulated ``Robot``
(``sim.direct.DirectSimRobot`` or ``sim.bus_robot.SimulatedBusRobot``) so that before every read --
before the sample at t_k is taken and the model steps on from it -- the effects of t_k are in force;
``with_schedule(backend, schedule)`` wraps a simulated back end's robots. The robot must step the
extended model: its plant an ``ExtendedModel`` whose effects include every scheduled one (give them
their burst value; the schedule's first entry sets the value at t = 0).
"""
from __future__ import annotations

from contextlib import contextmanager

import numpy as np

from otbot_hw.model import effects as fx
from otbot_hw.robot import SimulatedRobot


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


def _stepper_and_clock(robot: SimulatedRobot):
    if robot.plant is robot:  # sim.direct.DirectSimRobot: its own plant
        return robot.stepper, (lambda: robot.t_plant)
    plant = robot.plant  # sim.bus_robot.SimulatedBusRobot: the Plant behind the bus
    return plant.stepper, (lambda: plant.t)


class ScheduledEffects(SimulatedRobot):
    """A simulated robot whose extended-model effects follow ``schedule`` (everything else delegated)."""

    def __init__(self, robot: SimulatedRobot, schedule: EffectSchedule):
        self.robot = robot
        self.schedule = schedule
        self.stepper, self._clock = _stepper_and_clock(robot)
        eff = getattr(self.stepper, "eff", None)
        if eff is None:
            raise ValueError("scheduled effects need a robot that steps the extended model (an ExtendedModel "
                             "plant with the scheduled effects active)")
        self._eff = eff
        self.period = robot.period

    def _schedule(self) -> None:
        for name, v in self.schedule.values_at(self._clock()).items():
            self._eff[fx.EFFECT_INDEX[name]] = v

    def read(self):
        self._schedule()
        return self.robot.read()

    def write(self, torques):
        return self.robot.write(torques)

    def _apply(self, torques):  # pragma: no cover - write() is the inner robot's
        return self.robot._apply(torques)

    def enable(self) -> None:
        self.robot.enable()

    def disable(self) -> None:
        self.robot.disable()

    def quick_stop(self) -> None:
        self.robot.quick_stop()

    def fault_reset(self) -> None:
        self.robot.fault_reset()

    @property
    def faults(self):
        return self.robot.faults

    @property
    def faulted(self) -> bool:
        return self.robot.faulted

    @property
    def has_imu(self) -> bool:
        return self.robot.has_imu

    def truth(self):
        return self.robot.truth()

    def truth_force(self):
        return self.robot.truth_force()

    @property
    def plant(self):
        return self.robot.plant

    @property
    def simulated_params(self):
        return self.robot.simulated_params

    @property
    def has_operator(self) -> bool:
        return self.robot.has_operator

    def operator(self, command: str) -> dict:
        return self.robot.operator(command)

    @property
    def imu(self):
        return self.robot.imu

    @property
    def imu_rate(self):
        return self.robot.imu_rate

    @property
    def warnings(self):
        return self.robot.warnings

    @property
    def close_report(self):
        return self.robot.close_report

    def node_identities(self) -> dict:
        return self.robot.node_identities()

    def close(self):
        return self.robot.close()

    def __getattr__(self, name):
        return getattr(self.robot, name)


class _ScheduledBackend:
    """A simulated back end whose robots follow an effect schedule (attributes of the inner back end)."""

    def __init__(self, backend, schedule: EffectSchedule):
        self._backend = backend
        self.schedule = schedule

    def __getattr__(self, name):
        return getattr(self._backend, name)

    @contextmanager
    def open(self, plant, *args, **kwargs):
        if not hasattr(plant, "eff") or any(plant.eff[fx.EFFECT_INDEX[n]] == 0.0 for n in self.schedule.names):
            raise ValueError("scheduled effects need an ExtendedModel plant with every scheduled effect active "
                             f"({', '.join(self.schedule.names)})")
        own = fx.ExtendedModel(plant.params, np.array(plant.eff, dtype=float))  # the schedule writes into its effects
        with self._backend.open(own, *args, **kwargs) as robot:
            yield ScheduledEffects(robot, self.schedule)

    def describe(self) -> dict:
        return {**self._backend.describe(), "effect_schedule": [[t, v] for t, v in self.schedule.entries]}


def with_schedule(backend, schedule: EffectSchedule):
    """``backend`` (``DirectBackend`` or ``BusSimBackend``) with its robots' effects following ``schedule``."""
    return _ScheduledBackend(backend, schedule)
