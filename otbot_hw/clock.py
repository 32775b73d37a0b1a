"""The one clock of a control loop (ros2_control's controller manager owns it the same way).

The runtime owns the clock: ``LoopRunner`` makes one (``clock_for(period, paced(robot))``: real time
unless the back end declares it runs in lockstep with a simulated plant, ``Robot.lockstep``) and hands it
to its robot (``Robot.use_clock``), so that the robot's own multi-cycle sequences (a CANopen
driver's enable, fault reaction and fault reset, which run SYNCs of their own) tick the same clock
as the loop's cycles; no driver sleeps to pace. Defined here, in the library's lowest layer
(standard library only), so that drivers may import it.

* ``Pacer``   — real time: the loop's ticks one ``period`` apart on the wall clock
  (``time.monotonic``); a tick claimed late is taken at once and the grid continues from it (no
  burst of catch-up ticks); a back end's sequence waits with ``wait_until`` for a tick it dates
  itself (a driver: one period after its last SYNC, so that a tick claimed by a thread that then
  waited for the bus is not lost), and the loop's grid continues a period after it;
* ``Unpaced`` — cycles back to back (a lockstep simulation, faster than real time): never waits.

Thread-safe: the loop's thread and a driver's safety thread may wait on it concurrently.
"""
from __future__ import annotations

import threading
import time


class Unpaced:
    """A clock that never waits: each tick is due at once (cycles back to back)."""

    realtime = False

    def __init__(self, period: float):
        self.period = float(period)

    def wait(self, wake: threading.Event | None = None) -> float:
        """Claim the next tick (here: now); returns its time (s, ``time.monotonic``)."""
        return time.monotonic()

    def wait_until(self, t: float) -> None:
        """A tick of a back end's own multi-cycle sequence, due at ``t`` (s, ``time.monotonic``; a
        driver: one period after its last SYNC): here at once."""


class Pacer(Unpaced):
    """Real time: ticks ``period`` s apart on the wall clock (see the module docstring)."""

    realtime = True

    def __init__(self, period: float):
        super().__init__(period)
        self._next: float | None = None  # when the next tick is due (s, time.monotonic); None: now
        #: s (time.monotonic): the last tick ``wait`` had to wait for (its work left time in the period);
        #: at construction until then
        self.waited = time.monotonic()
        self._lock = threading.Lock()

    def wait(self, wake: threading.Event | None = None) -> float:
        """Claim the next tick and wait for it; returns its due time (s, ``time.monotonic``). ``wake``:
        an event that ends the wait early (an operator's estop; cleared here), the tick stays claimed."""
        with self._lock:
            now = time.monotonic()
            due = now if self._next is None or self._next < now else self._next
            self._next = due + self.period
        delay = due - time.monotonic()
        if delay > 0:
            self.waited = due  # the caller's work left time in the period
            if wake is None:
                time.sleep(delay)
            else:
                wake.wait(delay)
                wake.clear()
        return due


    def wait_until(self, t: float) -> None:
        """Wait until ``t`` (s, ``time.monotonic``), a tick of a back end's own multi-cycle sequence
        (a driver's: one period after its last SYNC, whoever sent it); the grid's next tick comes no
        sooner than one period after it."""
        with self._lock:
            if self._next is None or self._next < t + self.period:
                self._next = t + self.period
        delay = t - time.monotonic()
        if delay > 0:
            time.sleep(delay)


def paced(robot, realtime: bool | None = None) -> bool:
    """Whether a loop over ``robot`` runs in real time: ``realtime`` when the caller chooses (a test that
    paces a simulation), else what the back end declares (``otbot_hw.robot.Robot.lockstep``: a lockstep
    simulation runs unpaced, hardware and a plant paced in real time are paced)."""
    return (not robot.lockstep) if realtime is None else bool(realtime)


def clock_for(period: float, realtime: bool) -> Unpaced:
    """``Pacer(period)`` for a loop paced in real time, else ``Unpaced(period)``."""
    return Pacer(period) if realtime else Unpaced(period)
