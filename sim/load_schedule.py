"""A load put on or taken off the simulated robot's platform during a run (a box placed while tracking).

``LoadSchedule`` [(t_start s, (mass kg, x m, y m, own inertia kg m^2) or None)] gives the load in force
at plant time t (None: the bare platform of the plant's parameters); ``with_loads(backend, schedule)``
wraps a simulated back end (``DirectBackend``, ``BusSimBackend``) so that before every read the plant
steps with the platform + load of t_k (``Stepper.set_params``, ``OtbotParams.with_load``). The paper's
model only (an ``ExtendedModel`` plant keeps its effects; its physical parameters change). The robot is
not told: the controller and its payload adapter must find out from the motion.
"""
from __future__ import annotations

from contextlib import contextmanager

from sim.effect_schedule import _stepper_and_clock


class LoadSchedule:
    """[(t_start s, load or None)] sorted by time; load = (mass kg, x m, y m[, inertia kg m^2]) in B''."""

    def __init__(self, entries):
        self.entries = sorted(((float(t), None if v is None else tuple(float(a) for a in v)) for t, v in entries),
                              key=lambda e: e[0])

    def load_at(self, t: float):
        cur = None
        for t0, v in self.entries:
            if t0 > t + 1e-9:
                break
            cur = v
        return cur


class LoadedRobot:
    """A simulated robot whose platform carries the scheduled load (everything else delegated)."""

    def __init__(self, robot, schedule: LoadSchedule, base):
        self.robot = robot
        self.schedule = schedule
        self.stepper, self._clock = _stepper_and_clock(robot)
        self.base = base
        self._current = "unset"

    def _apply(self) -> None:
        load = self.schedule.load_at(self._clock())
        if load != self._current:
            self._current = load
            p = self.base if load is None else self.base.with_load(*load)
            if hasattr(self.stepper, "set_params"):
                self.stepper.set_params(p)
            else:  # an extended-model stepper: its physical parameters
                self.stepper.params = p
                self.stepper._prm = p.as_array()

    def read(self):
        self._apply()
        return self.robot.read()

    def __getattr__(self, name):
        return getattr(self.robot, name)


class _LoadedBackend:
    def __init__(self, backend, schedule: LoadSchedule):
        self._backend = backend
        self.schedule = schedule

    def __getattr__(self, name):
        return getattr(self._backend, name)

    @contextmanager
    def open(self, plant, *args, **kwargs):
        with self._backend.open(plant, *args, **kwargs) as robot:
            yield LoadedRobot(robot, self.schedule, getattr(plant, "params", plant))

    def describe(self) -> dict:
        return {**self._backend.describe(), "load_schedule": [[t, v] for t, v in self.schedule.entries]}


def with_loads(backend, schedule: LoadSchedule):
    """``backend`` with its robots' platform load following ``schedule``."""
    return _LoadedBackend(backend, schedule)
