"""Where and at what priority the daemon's threads run (``daemon.scheduling`` in config/robot.yaml;
docs/daemon.md, docs/performance.md "Seventh pass"). Linux: threads are the tasks of
``/proc/self/task`` (elsewhere nothing is lowered).

* ``pin(cpus)``: every thread of this process onto ``cpus`` (Linux CPU numbers); threads started
  later inherit the affinity of the thread that starts them. What the unit's ``CPUAffinity=`` does,
  from the daemon's own configuration, checked against the CPUs the process may use
  (``check_cpus``: a missing CPU is a one-line error, not a refused unit).
* ``lower(tids, levels)``: the operator's threads (the control socket's dispatch thread, telemetry;
  not the socket's I/O thread, where ``estop`` acts) ``levels`` real-time priorities below the
  loop's, so that on a shared core the loop and the bus's receive threads preempt them. One interpreter lock still serialises the Python in both; a lowered thread
  that holds it is asked to let go after the switch interval (0.2 ms, ``daemon.GIL_SWITCH_INTERVAL``)
  once the loop wants it, instead of finishing its work first (a ``status`` reply: ~1 ms). Lowering
  needs no privilege (raising does: CAP_SYS_NICE or RLIMIT_RTPRIO), so it works under the unit's
  empty capability set. Under a normal (SCHED_OTHER) policy nothing is changed.
* ``OperatorShare``: what keeps the lowered threads alive when the loop fills its core.
"""
from __future__ import annotations

import os
import threading
import time
from collections.abc import Iterable

_POLICIES = {getattr(os, "SCHED_FIFO", -1): "fifo", getattr(os, "SCHED_RR", -2): "rr"}


class SchedulingError(ValueError):
    """A scheduling request this machine cannot honour (the message names the key and the CPUs)."""


def tasks() -> set[int]:
    """Thread ids (TIDs) of this process, Python's and foreign ones (foxglove's Rust workers); empty
    where the system has no ``/proc/self/task`` (not Linux: nothing to lower)."""
    try:
        return {int(t) for t in os.listdir("/proc/self/task")}
    except FileNotFoundError:
        return set()


def check_cpus(cpus: Iterable[int], key: str = "daemon.scheduling.cpus") -> frozenset[int]:
    """``cpus`` if this process may run on every one of them, else ``SchedulingError`` naming them."""
    want = frozenset(cpus)
    if not hasattr(os, "sched_getaffinity"):
        raise SchedulingError(f"{key}: CPU affinity needs Linux")
    have = os.sched_getaffinity(0)
    missing = sorted(want - have)
    if missing:
        raise SchedulingError(f"{key}: CPU {', '.join(map(str, missing))} not available to this process "
                              f"(it may run on {', '.join(map(str, sorted(have)))})")
    return want


def pin(cpus: Iterable[int]) -> int:
    """Every thread of this process onto ``cpus`` (check them first: ``check_cpus``); returns how many."""
    want = frozenset(cpus)
    n = 0
    for tid in tasks():
        try:
            os.sched_setaffinity(tid, want)
            n += 1
        except ProcessLookupError:  # the thread ended in between
            pass
    return n


def thread_name(tid: int) -> str:
    """A thread's name: Python's for its own threads, else the kernel's (``comm``), else ``?``."""
    for t in threading.enumerate():
        if t.native_id == tid:
            return t.name
    try:
        with open(f"/proc/self/task/{tid}/comm") as f:
            return f.read().strip()
    except OSError:
        return "?"


def policy(tid: int = 0) -> tuple[str, int]:
    """(``fifo`` | ``rr`` | ``other``, real-time priority; 0 for ``other``) of a thread (0: this one)."""
    p = os.sched_getscheduler(tid)
    name = _POLICIES.get(p, "other")
    return name, (os.sched_getparam(tid).sched_priority if name != "other" else 0)


def lower(tids: Iterable[int], levels: int, reference: int = 0) -> dict:
    """``tids`` ``levels`` real-time priorities below thread ``reference`` (0: the calling thread),
    at least priority 1, in the reference's policy; nothing when that policy is not real-time or
    ``levels`` is 0. Returns what was done: policy, the reference's priority, the lowered one and
    the ids of the threads lowered (a thread that ended in between is skipped)."""
    name, prio = policy(reference) if hasattr(os, "sched_getscheduler") else ("other", 0)
    target = max(1, prio - int(levels))
    done = {"policy": name, "priority": prio, "operator_priority": prio, "lowered": []}
    if name == "other" or target >= prio:
        return done
    pol = os.sched_getscheduler(reference)
    for tid in sorted(set(tids)):
        try:
            os.sched_setscheduler(tid, pol, os.sched_param(target))
            done["lowered"].append(tid)
        except ProcessLookupError:
            pass
    done["operator_priority"] = target
    return done


def lower_operators(tids: Iterable[int], levels: int) -> dict:
    """``lower`` the operator's threads ``tids`` below the calling (loop) thread; what the daemon's
    ``status`` says of it: ``cpus`` (of the calling thread), ``policy``, the loop's ``priority``, the
    ``operator_priority`` and ``operator_threads`` ([thread id, name] of each thread lowered)."""
    done = lower(tids, levels)
    cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    return {"cpus": cpus, "policy": done["policy"], "priority": done["priority"],
            "operator_priority": done["operator_priority"],
            "operator_threads": [[t, thread_name(t)] for t in done["lowered"]]}


class OperatorShare:
    """With the operator's threads below the loop (``active``), a loop that cannot keep its period
    would hold its core for ever and they (every command but ``estop``, ``status``) would never run. Called
    after each cycle with the loop's clock (``otbot_hw.clock.Pacer``): once the loop has not waited for
    a tick (its work filled every period) for ``AFTER`` s, it sleeps ``SLEEP`` s, and again every
    ``AFTER`` s while that lasts. A loop late for less than ``AFTER`` never sleeps."""

    SLEEP = 0.0005  # s
    AFTER = 0.01  # s

    def __init__(self):
        self.active = False
        self.shared = 0.0  # s (time.monotonic): the last sleep
        self.count = 0  # sleeps so far

    def after_cycle(self, clock, now: float) -> None:
        if self.active and now - max(getattr(clock, "waited", now), self.shared) > self.AFTER:
            time.sleep(self.SLEEP)
            self.shared = time.monotonic()
            self.count += 1
