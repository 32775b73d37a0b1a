"""A load put on or taken off the simulated robot's platform during a run (a box placed while tracking).

``LoadSchedule`` [(t_start s, (mass kg, x m, y m, own inertia kg m^2) or None)] gives the load in force
at plant time t (None: the bare platform of the plant's parameters); ``with_loads(backend, schedule)``
wraps a simulated back end (``DirectBackend``, ``BusSimBackend``; ``sim.scheduled_robot``) so that before
every read the plant steps with the platform + load of t_k (``Stepper.set_params``,
``OtbotParams.with_load``). The paper's model only (an ``ExtendedModel`` plant keeps its effects; its
physical parameters change). The robot is not told: the controller and its payload adapter must find out from the motion.
"""
from __future__ import annotations

from sim.scheduled_robot import ScheduledBackend, stepper_and_clock


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


def _load_change(schedule: LoadSchedule):
    """The change before each read: the robot's stepper given the platform + load of the plant's time
    (``Stepper.set_params``; an extended-model stepper: its physical parameters)."""
    def make(robot, plant):
        stepper, clock = stepper_and_clock(robot)
        base = getattr(plant, "params", plant)
        current = ["unset"]

        def change() -> None:
            load = schedule.load_at(clock())
            if load != current[0]:
                current[0] = load
                p = base if load is None else base.with_load(*load)
                if hasattr(stepper, "set_params"):
                    stepper.set_params(p)
                else:  # an extended-model stepper: its physical parameters
                    stepper.params = p
                    stepper._prm = p.as_array()
        return change
    return make


def with_loads(backend, schedule: LoadSchedule) -> ScheduledBackend:
    """``backend`` with its robots' platform load following ``schedule``."""
    return ScheduledBackend(backend, "load_schedule", schedule.entries, _load_change(schedule))
