"""What a stalled cycle was made of: a measurement aid for the daemon's loop, off unless asked for.

``OTBOT_LOOP_TRACE=FILE`` in the daemon's environment (``benchmarks/daemon.py --trace``) installs a
``LoopTrace`` when the loop is set up: instance attributes wrap the parts of a cycle (the SYNC send,
the TPDO wait, the IMU read, the heartbeat check, EKF, supervisor, recording, law + limiter + RPDOs,
the sample's write, telemetry, the mailbox, the pacer's wait) and the other threads' work (the
plant's SYNC handler, each CAN receive thread's dispatch, the heartbeat producers' sends, the
telemetry thread's sends, the simulated IMU's writes), each call stamped (wall ``time.monotonic``
and the thread's CPU ``time.thread_time``, s) into one bounded ring. Garbage collections are
stamped through ``gc.callbacks``. At every overrun (a SYNC-to-SYNC period above ``factor``
periods) the ring's events since the previous SYNC, the loop thread's scheduler statistics over the
period (``/proc/thread-self/schedstat``: on CPU, waiting on the run queue) and every thread's
(policy, priority, CPU, run-queue wait) are kept; at the end everything goes to FILE as JSON.
Without the variable nothing is wrapped: the daemon's cycle runs exactly the code it runs without
this module.
"""
from __future__ import annotations

import collections
import gc
import json
import os
import threading
import time
from pathlib import Path

ENV = "OTBOT_LOOP_TRACE"


def _schedstat(fd: int) -> tuple[int, int]:
    """(on-CPU ns, run-queue wait ns) of the thread whose schedstat ``fd`` is open."""
    a = os.pread(fd, 128, 0).split()
    return int(a[0]), int(a[1])


def _threads() -> list[dict]:
    """Every thread of this process: id, name, policy, priority, CPU s, run-queue wait s, voluntary
    and involuntary context switches."""
    names = {t.native_id: t.name for t in threading.enumerate()}
    out = []
    for tid in sorted(int(t) for t in os.listdir("/proc/self/task")):
        try:
            cpu, runq, _ = (int(x) for x in Path(f"/proc/self/task/{tid}/schedstat").read_text().split())
            pol = os.sched_getscheduler(tid)
            prio = os.sched_getparam(tid).sched_priority
            st = Path(f"/proc/self/task/{tid}/status").read_text()
            sw = {k: int(v) for k, v in (ln.split(":\t") for ln in st.splitlines() if "ctxt_switches" in ln)}
            comm = Path(f"/proc/self/task/{tid}/comm").read_text().strip()
        except (OSError, ValueError):
            continue
        out.append({"tid": tid, "name": names.get(tid, comm), "policy": {os.SCHED_FIFO: "FIFO", os.SCHED_RR: "RR"}.get(
            pol, "OTHER"), "priority": prio, "cpu_s": cpu * 1e-9, "runq_s": runq * 1e-9, **sw})
    return out


class LoopTrace:
    """See the module docstring. ``install(daemon, robot, runner)`` wraps; ``close()`` writes FILE."""

    def __init__(self, path: str | Path, period: float, factor: float = 1.5, ring: int = 4000):
        self.path = Path(path)
        self.period = period
        self.limit = factor * period
        self.ring: collections.deque = collections.deque(maxlen=ring)
        self.stalls: list[dict] = []
        self.cycles = 0
        self.gc: list = []
        self._gc_t0: dict = {}
        self._fd = None
        self._fds: dict[str, int] = {}
        self._at_sync = self._at_sync_prev = None  # every thread's schedstat at the last two SYNCs
        self._loop_at_sync = self._loop_at_sync_prev = None  # the loop thread's
        self._sync_mono = self._sync_mono_prev = None  # when the last two reads (SYNCs) began (s)
        self.threads_start: list[dict] = []
        self.t_start = time.monotonic()

    # -- wrapping ------------------------------------------------------------------------------
    def wrap(self, obj, attr: str, name: str) -> None:
        """Stamp every call of ``obj.attr`` (an instance attribute replaces it) as event ``name``."""
        if obj is None or not hasattr(obj, attr):
            return
        fn = getattr(obj, attr)
        ring, mono, cpu, ident = self.ring.append, time.monotonic, time.thread_time, threading.get_ident

        def stamped(*a, **kw):
            t0, c0 = mono(), cpu()
            try:
                return fn(*a, **kw)
            finally:
                ring((name, ident(), t0, mono(), c0, cpu()))

        setattr(obj, attr, stamped)

    def install(self, daemon, robot, runner) -> None:
        w = self.wrap
        for obj, attr, name in ((robot, "_sync_cycle", "read: SYNC + TPDO wait"),
                                (robot, "_await_tpdos", "read: TPDO wait"),
                                (robot, "_read_imu", "read: IMU"),
                                (getattr(robot, "heartbeats", None), "check", "read: heartbeat check"),
                                (robot, "read", "read"),
                                (runner.feedback, "step", "EKF step"),
                                (runner.supervisor, "check", "supervisor check"),
                                (runner, "_record", "recording (loop side)"),
                                (runner, "_command", "law + limiter + write"),
                                (robot, "write", "write (RPDOs)"),
                                (runner, "_write_pending", "recording sample write"),
                                (runner, "_timing", "loop timing"),
                                (runner.clock, "wait", "pacer wait"),
                                (daemon.mailbox, "service", "mailbox"),
                                (daemon.telemetry, "publish_cycle", "telemetry publish"),
                                (daemon.telemetry, "_send", "telemetry thread send")):
            w(obj, attr, name)
        net = getattr(robot, "network", None)
        w(net, "notify", "master rx dispatch")
        # what only the back end knows (a simulated plant's threads): it wraps them with ``w`` itself
        points = getattr(robot, "trace_points", None)
        if points is not None:
            points(w)
        w(net, "send_message", "master send_message")  # SYNC, RPDOs (one at a time), the master's heartbeat
        # the loop's own SYNC-to-SYNC check: after _timing has the period
        timing = runner._timing
        mono = time.monotonic

        read = robot.read

        def read_probe(_r=read):  # every thread's scheduler statistics at the SYNC (a period's start/end)
            self._at_sync, self._at_sync_prev = [_schedstat(fd) for fd in self._fds.values()], self._at_sync
            self._loop_at_sync, self._loop_at_sync_prev = _schedstat(self._fd), self._loop_at_sync
            self._sync_mono, self._sync_mono_prev = mono(), self._sync_mono
            return _r()

        robot.read = read_probe

        def timing_probe(wall_period, _t=timing):
            self.cycles += 1
            if wall_period > self.limit and self._at_sync_prev is not None:  # two SYNCs seen: a whole period
                self._keep(mono(), wall_period, self._at_sync, self._at_sync_prev)
            return _t(wall_period)

        runner._timing = timing_probe
        gc.callbacks.append(self._on_gc)
        self._fd = os.open("/proc/thread-self/schedstat", os.O_RDONLY)
        self.threads_start = _threads()
        names = {t.native_id: t.name for t in threading.enumerate()}
        for tid in sorted(int(t) for t in os.listdir("/proc/self/task")):
            try:
                self._fds[names.get(tid, str(tid)) + f" [{tid}]"] = os.open(f"/proc/self/task/{tid}/schedstat",
                                                                           os.O_RDONLY)
            except OSError:
                pass

    def _on_gc(self, phase, info) -> None:
        if phase == "start":
            self._gc_t0[threading.get_ident()] = (time.monotonic(), time.thread_time())
        else:
            t = self._gc_t0.pop(threading.get_ident(), None)
            if t is not None:
                self.ring.append((f"gc gen{info['generation']}", threading.get_ident(), t[0], time.monotonic(), t[1],
                                  time.thread_time()))
                self.gc.append((info["generation"], threading.current_thread().name, time.monotonic() - t[0]))

    def _keep(self, now, wall_period, every, every_prev) -> None:
        """An overrun: the events from the period's first SYNC on (times relative to it, s), the loop
        thread's CPU and run-queue wait over the period (SYNC to SYNC, s) and every thread's (ms)."""
        t_prev = self._sync_mono_prev
        st, st_prev = self._loop_at_sync, self._loop_at_sync_prev
        threads = {name: (round((a[0] - b[0]) * 1e-6, 3), round((a[1] - b[1]) * 1e-6, 3))
                   for name, a, b in zip(self._fds, every, every_prev) if a != b}
        since = t_prev - 0.5e-3  # from just before the period's first SYNC
        names = {t.ident: t.name for t in threading.enumerate()}
        ev = [(n, names.get(i, str(i)), round(t0 - t_prev, 6), round(t1 - t0, 6), round(c1 - c0, 6))
              for n, i, t0, t1, c0, c1 in list(self.ring) if t1 >= since]
        self.stalls.append({"t": now - self.t_start, "mono": now, "period": wall_period,
                            "loop_cpu": (st[0] - st_prev[0]) * 1e-9, "loop_runq": (st[1] - st_prev[1]) * 1e-9,
                            "since_period_start": now - t_prev, "events": ev, "threads_ms": threads,
                            "load": os.getloadavg()[0]})

    def close(self) -> None:
        if self._on_gc in gc.callbacks:
            gc.callbacks.remove(self._on_gc)
        out = {"period": self.period, "cycles": self.cycles, "wall_s": time.monotonic() - self.t_start,
               "threads_start": self.threads_start, "threads_end": _threads(), "gc": self.gc, "stalls": self.stalls,
               "rt_runtime_us": Path("/proc/sys/kernel/sched_rt_runtime_us").read_text().strip()}
        self.path.write_text(json.dumps(out))
        for fd in [self._fd, *self._fds.values()]:
            if fd is not None:
                os.close(fd)
        self._fd = None
        self._fds = {}


def from_env(period: float, factor: float) -> LoopTrace | None:
    """A ``LoopTrace`` when ``OTBOT_LOOP_TRACE`` names a file, else None."""
    p = os.environ.get(ENV)
    return LoopTrace(p, period, factor) if p else None
