"""A simulated robot whose plant changes during a run on a schedule of plant time: the one wrapper that
``sim.effect_schedule`` (extended-model effects switched on and off) and ``sim.load_schedule`` (a load put
on or taken off the platform) share.

``ScheduledBackend(backend, key, entries, change, prepare)`` wraps a simulated back end (``DirectBackend``,
``BusSimBackend``): each robot it opens is a ``ScheduledRobot`` that calls ``change()`` before every read --
before the sample at t_k is taken and the model steps on from it -- so the plant of t_k is in force; the
robot is not told. ``describe()`` adds the schedule under ``key``.
"""
from __future__ import annotations

from contextlib import contextmanager
from typing import Callable

from otbot_hw.robot import SimulatedRobot


def stepper_and_clock(robot: SimulatedRobot):
    """(the stepper that advances ``robot``'s plant, a function giving its plant time in s)."""
    if robot.plant is robot:  # sim.direct.DirectSimRobot: its own plant
        return robot.stepper, (lambda: robot.t_plant)
    plant = robot.plant  # sim.bus_robot.SimulatedBusRobot: the Plant behind the bus
    return plant.stepper, (lambda: plant.t)


class ScheduledRobot(SimulatedRobot):
    """``robot`` with ``change()`` called before every read (everything else delegated)."""

    def __init__(self, robot: SimulatedRobot, change: Callable[[], None]):
        self.robot = robot
        self._change = change
        self.period = robot.period

    def read(self):
        self._change()
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

    @property
    def clock(self):
        return self.robot.clock

    @property
    def lockstep(self) -> bool:
        return self.robot.lockstep

    def use_clock(self, clock) -> None:
        self.robot.use_clock(clock)  # the inner robot's own sequences tick the loop's clock

    def close(self):
        return self.robot.close()

    def __getattr__(self, name):
        return getattr(self.robot, name)


class ScheduledBackend:
    """A simulated back end whose robots follow a schedule (attributes of the inner back end).

    ``change(robot, plant)`` gives the function a robot calls before every read (``plant``: what
    ``open`` was given); ``prepare(plant)`` the plant actually opened (default: ``plant`` itself);
    ``entries`` [(t_start s, value)] are shown by ``describe()`` under ``key``."""

    def __init__(self, backend, key: str, entries, change: Callable, prepare: Callable | None = None):
        self._backend = backend
        self._key = key
        self._entries = entries
        self._make_change = change
        self._prepare = prepare

    def __getattr__(self, name):
        return getattr(self._backend, name)

    @contextmanager
    def open(self, plant, *args, **kwargs):
        own = self._prepare(plant) if self._prepare is not None else plant
        with self._backend.open(own, *args, **kwargs) as robot:
            yield ScheduledRobot(robot, self._make_change(robot, plant))

    def describe(self) -> dict:
        return {**self._backend.describe(), self._key: [[t, v] for t, v in self._entries]}
