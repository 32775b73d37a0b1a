"""The loop's power lifecycle and fault reaction: part of ``LoopRunner`` (``otbot_hw.runtime.loop``).

``LoopPower`` (mixed into ``LoopRunner``): ``start()`` (enable and write u_0, or start unpowered),
``enable()``/``disable()`` between cycles (only armed cycles write commands), ``power_down()`` when
the loop ends for good, ``trip(violation)`` — a fault raised from another thread (an operator's
estop), acted on at once: it also wakes the real-time wait — ``reset()`` (the drives' and the
supervisor's latch cleared, drives left unpowered), and ``_fail``: any fault (the robot's, the
estimator's, a supervisor violation) is latched, the robot is quick-stopped through
``robot.quick_stop()``, a ``fault`` event is recorded and the recording flushed. A drive operation
runs bus cycles of its own: the next period is then not a loop period (``_interrupted``).
"""
from __future__ import annotations

import threading
import time
from typing import Callable

import numpy as np

from otbot_hw.robot import RobotError
from otbot_hw.runtime.controllers import Controller
from otbot_hw.runtime.supervisor import Violation


class LoopPower:
    """The power lifecycle of ``LoopRunner``. Expects on the runner: ``robot``, ``supervisor``,
    ``controller``, ``feedback``, ``continue_after_fault``, ``event``, ``set_controller``,
    ``_command``, the recording's ``writer`` and ``_write_pending``."""

    def _init_power(self) -> None:
        self.armed = False  # the drives are powered and commands are written
        self.fault: Violation | None = None
        self.robot_faults: tuple = ()
        self._trip: Violation | None = None
        self._trip_lock = threading.Lock()
        self.wake = threading.Event()

    def start(self, enable: bool = True) -> None:
        """Enable the robot and write the first command (asked without feedback); with ``enable``
        False the loop starts with the drives unpowered (``enable()`` later)."""
        self._t_wall0 = time.perf_counter()
        if not enable:
            self.event(0.0, "mode", "start: drives disabled"
                                    + (f", feedback {self.feedback.name}" if self.feedback is not None else ""))
            return
        try:
            self.robot.enable()
        except RobotError as exc:
            self._fail(Violation("robot", 0.0, f"enabling failed: {exc}"), stop=True)
            return
        self.armed = True
        self._command(0.0, None, None)
        self.event(0.0, "mode", f"start: {type(self.controller).__name__}"
                                + (f", feedback {self.feedback.name}" if self.feedback is not None else ""))

    def enable(self, controller: Controller, mode: str | None = None) -> None:
        """Between cycles: power the drives (``robot.enable()``, a few bus cycles) and hand the next
        command to ``controller``. A failure is latched as a fault (quick stop) and re-raised."""
        if self.fault is not None:
            raise RobotError(f"cannot enable while faulted: {self.fault}")
        try:
            self.robot.enable()
        except RobotError as exc:
            self._fail(Violation("robot", self.t, f"enabling failed: {exc}"))
            raise
        self._interrupted()
        self._no_torque()
        self.armed = True
        self._held = None
        self.set_controller(controller, mode)

    def disable(self, mode: str = "disabled") -> None:
        """Between cycles: remove motor power (``robot.disable()``); no commands until ``enable``."""
        try:
            self._unpowered(self.robot.disable)
        finally:
            self.event(self.t, "mode", mode)

    def _unpowered(self, operation: Callable[[], None]) -> None:
        """A drive operation between cycles after which nothing is commanded (it runs bus cycles of
        its own: the next period is not a loop period)."""
        self.armed = False
        self._held = None
        self._no_torque()
        try:
            operation()
        finally:
            self._interrupted()

    def power_down(self, text: str) -> list[str]:
        """Between cycles, when the loop ends for good: quick stop (if the drives are powered), then
        disable; recorded as a mode event. Never raises: returns what could not be done."""
        problems = []
        if self.armed:
            self.armed = False
            note = self._quick_stop()
            if note:
                problems.append(note)
        try:
            self.robot.disable()
        except Exception as exc:  # noqa: BLE001 - the bus may be gone: say so
            problems.append(f"disable failed: {exc}")
        self._held = None
        self._no_torque()
        self.event(self.t, "mode", text + (f" ({'; '.join(problems)})" if problems else ""))
        return problems

    def trip(self, v: Violation) -> None:
        """A fault from another thread (e.g. an estop): quick stop and latch at once — before the next
        read, and before any command not yet written. Thread-safe; wakes a real-time wait."""
        with self._trip_lock:
            if self._trip is None:
                self._trip = v
        self.wake.set()

    def _take_trip(self) -> bool:
        """Act on a pending ``trip``; returns whether the loop is (now) faulted."""
        if self._trip is not None:
            with self._trip_lock:
                v, self._trip = self._trip, None
            if v is not None:
                self._fail(v)
        return self.fault is not None

    def reset(self, feedback=None) -> None:
        """Clear the latched fault (``robot.fault_reset()``, the supervisor's latch); the drives stay
        unpowered. ``feedback``: a new state source (an estimator that faulted starts again)."""
        self._unpowered(self.robot.fault_reset)
        self.supervisor.reset()
        self.fault = None
        self.robot_faults = ()
        if feedback is not None:
            self.feedback = feedback
            self._feedback_started = False
        self.event(self.t, "mode", "reset")

    def pause(self) -> None:
        """The caller held the loop up on purpose (a warm-up): the next period is not a loop period."""
        self._interrupted()

    def _no_torque(self) -> None:
        """The drives produce no torque from now on: what is recorded as commanded and what the
        estimator is told acted."""
        self._u_held = self._u_prev = np.zeros(3)

    def _interrupted(self) -> None:
        """A drive operation ran bus cycles of its own: the next period is not a loop period (the
        clock they ticked is the loop's: the next read still comes a period after their last)."""
        self._t_last_read = None

    # -- faults and stopping -----------------------------------------------------------------------
    def _quick_stop(self) -> str | None:
        try:
            self.robot.quick_stop()
        except Exception as exc:  # the bus may be gone: say so, keep the fault
            return f"quick stop failed: {exc}"
        return None

    def _fail(self, v: Violation, stop: bool = True) -> None:
        self.supervisor.latch(v)
        self.fault = self.supervisor.fault
        self.armed = False
        note = self._quick_stop() if stop else None
        if self.continue_after_fault:  # the cycles go on: they record (and estimate with) no torque
            self._no_torque()
        self._interrupted()
        t = max(v.t, self.t)
        self.event(t, "fault", str(self.fault) + (f" ({note})" if note else ""))
        if self.writer is not None:
            self._write_pending()
            self.writer.flush()
