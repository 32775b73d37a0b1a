"""One clock (issue 19 item 3): ``otbot_hw.clock``, owned by the loop runner and handed down to the
robot, whose own multi-SYNC sequences wait on it instead of sleeping."""
from __future__ import annotations

import threading
import time

import numpy as np

from drivers.config import load_robot_config
from otbot_hw.clock import Pacer, Unpaced, clock_for
from otbot_hw.motors import load_motor_limits
from otbot_hw.params import nominal
from otbot_hw.runtime import LoopRunner, OpenLoopTorques, SafetyConfig, Supervisor
from sim.direct import DirectSimRobot
from sim.scheduled_robot import ScheduledRobot

P = 0.01  # s


def test_a_pacer_ticks_one_period_apart_and_takes_a_late_tick_at_once_without_a_burst():
    c = Pacer(P)
    ticks = [c.wait() for _ in range(4)]
    assert np.all(np.diff(ticks) >= P - 1e-9)  # never early (a loaded machine may only make a tick late)
    assert time.monotonic() >= ticks[-1]  # never ahead of the wall clock
    time.sleep(3 * P)  # the caller was late: the next tick is now, the one after a period later
    late = c.wait()
    assert late >= ticks[-1] + 3 * P
    assert c.wait() >= late + P - 1e-9  # no burst of catch-up ticks


def test_a_pacer_says_when_its_caller_last_waited_for_a_tick():
    """``waited``: the last tick the caller's work left time for (the daemon leaves its core to the
    operator's threads when that is long ago, ``scheduling.OperatorShare``); a late tick leaves it."""
    start = time.monotonic()
    c = Pacer(P)
    assert start <= c.waited <= time.monotonic()  # at construction until the first wait
    c.wait()  # the first tick: at once, no wait
    assert c.waited <= start + P
    second = c.wait()  # a wait of a period
    assert c.waited == second
    for _ in range(3):
        time.sleep(1.5 * P)  # the work overran the period: ticks claimed late, no wait
        c.wait()
        assert c.waited == second
    third = c.wait()  # the grid continues a period after the late tick: a wait again
    assert c.waited == third > second


def test_a_sequence_tick_pushes_the_grid_and_an_unpaced_clock_never_waits():
    c = Pacer(P)
    t0 = c.wait()
    t = time.monotonic() + 2 * P
    c.wait_until(t)  # a driver's SYNC one period after its last: the loop's next tick a period after it
    assert time.monotonic() >= t
    assert c.wait() >= t + P - 1e-9
    u = Unpaced(P)
    start = time.monotonic()
    for _ in range(100):
        u.wait()
        u.wait_until(start + 10.0)
    assert time.monotonic() - start < 0.5 and t0 > 0


def test_the_loop_owns_the_clock_and_hands_it_to_its_robot():
    limits = load_motor_limits()
    for realtime in (False, True):
        robot = DirectSimRobot(nominal(), period=P, imu_rate=None)
        runner = LoopRunner(robot, OpenLoopTorques(np.zeros((1, 3)), P), Supervisor(limits, SafetyConfig(), P),
                            realtime=realtime)
        assert robot.clock is runner.clock and runner.clock.realtime is realtime
        assert type(runner.clock) is type(clock_for(P, realtime))
    inner = DirectSimRobot(nominal(), period=P, imu_rate=None)  # a wrapper hands it down to the robot it wraps
    runner = LoopRunner(ScheduledRobot(inner, lambda: None), OpenLoopTorques(np.zeros((1, 3)), P),
                        Supervisor(limits, SafetyConfig(), P), realtime=True)
    assert inner.clock is runner.clock


def test_the_loop_asks_the_back_end_whether_it_runs_in_real_time():
    """Unless its caller chooses, the loop paces what the back end declares real time (``Robot.lockstep``
    False: hardware, a plant paced in real time) and runs a lockstep simulation back to back."""
    from sim.bus_robot import simulated_robot

    limits = load_motor_limits()

    def runner(robot, **kw):
        return LoopRunner(robot, OpenLoopTorques(np.zeros((1, 3)), P), Supervisor(limits, SafetyConfig(), P), **kw)

    direct = DirectSimRobot(nominal(), period=P, imu_rate=None)
    assert direct.lockstep and type(runner(direct).clock) is Unpaced
    assert type(runner(ScheduledRobot(direct, lambda: None)).clock) is Unpaced  # a wrapper says what it wraps
    assert type(runner(direct, realtime=True).clock) is Pacer  # the caller's choice: a simulation paced

    class Hardware(DirectSimRobot):  # a back end that declares real time
        lockstep = False

    hw = runner(Hardware(nominal(), period=P, imu_rate=None))
    assert type(hw.clock) is Pacer and hw.realtime
    cfg = load_robot_config().relaxed(1.0)
    for realtime in (False, True):
        with simulated_robot(cfg, with_imu=False, realtime=realtime) as (robot, _):
            assert robot.lockstep is (not realtime) and runner(robot).clock.realtime is realtime


class _Watched(Pacer):
    """A pacer that records each sequence tick with the driver's last SYNC time at the call."""

    def __init__(self, period, robot):
        super().__init__(period)
        self.robot, self.ticks, self.inside = robot, [], False

    def wait_until(self, t):
        self.ticks.append((t, self.robot._sync_wall))
        self.inside = True
        try:
            super().wait_until(t)
        finally:
            self.inside = False


def test_the_drivers_sequences_wait_on_the_runtimes_clock_and_never_sleep(monkeypatch):
    """enable (several SYNCs) and the quick stop (SYNC kept alive until confirmed), with a real-time
    clock handed down: each SYNC at the clock's tick one period after the last one; the calling thread
    sleeps only inside the clock. (The plant answers in lockstep: a loaded machine cannot spoil it.)"""
    from sim.bus_robot import simulated_robot

    cfg = load_robot_config().relaxed(1.0)
    me = threading.get_ident()
    sleeps = []
    real_sleep = time.sleep
    with simulated_robot(cfg, with_imu=False) as (robot, plant):
        assert not robot.clock.realtime  # lockstep's own clock, until the runtime hands one down
        clock = _Watched(robot.period, robot)
        robot.use_clock(clock)

        def sleep(s):
            if threading.get_ident() == me and not clock.inside:
                sleeps.append(s)
            real_sleep(s)

        monkeypatch.setattr(time, "sleep", sleep)
        robot.enable()
        n_enable = len(clock.ticks)
        robot.quick_stop()
        monkeypatch.setattr(time, "sleep", real_sleep)
    assert n_enable >= 3 and len(clock.ticks) > n_enable  # the enable path, then the quick stop's SYNCs
    assert all(t == last + robot.period for t, last in clock.ticks)
    assert np.all(np.diff([t for t, _ in clock.ticks]) >= robot.period - 1e-9)
    assert sleeps == []
