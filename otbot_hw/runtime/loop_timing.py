"""The loop's timing: per-cycle wall-clock periods, jitter, compute and read times, overruns, and
the loop's own clock (a robot clock that restarts is continued). Part of ``LoopRunner``
(``otbot_hw.runtime.loop``), which paces; this module only measures.

* ``LoopStats`` — the timing of a finished run (``LoopResult.stats``);
* ``TimingHistogram`` — percentiles in fixed memory for a loop that runs all day;
* ``LoopTiming`` — the runner's timing state and accounting (mixed into ``LoopRunner``): the
  loop's time ``t``, ``timing()`` for status, overruns (an ``overrun`` event when a streak starts in
  a real-time daemon loop).

Overruns are cycles whose wall-clock period exceeded the supervisor's ``overrun_factor`` times the
nominal period; in a real-time loop the supervisor faults on them.
"""
from __future__ import annotations

import math
import time
from array import array
from dataclasses import dataclass, replace

import numpy as np

from otbot_hw.robot import Snapshot


@dataclass
class LoopStats:
    """Timing of a run. Robot time (s, what the robot's clock advanced) next to wall time (s); per
    cycle the wall-clock period between reads (p50/p99/max, s), the jitter (rms of period minus the
    nominal period, s; meaningful when paced in real time), the compute time from the read's return
    to the write's (p50/p99/max, s) and the overruns (cycles whose period exceeded the overrun
    factor times the nominal period; only a fault in real-time loops)."""

    period: float
    realtime: bool
    cycles: int = 0
    robot_time: float = 0.0
    wall_time: float = 0.0
    period_p50: float = math.nan
    period_p99: float = math.nan
    period_max: float = math.nan
    jitter_rms: float = math.nan
    compute_p50: float = math.nan
    compute_p99: float = math.nan
    compute_max: float = math.nan
    overruns: int = 0

    @property
    def realtime_factor(self) -> float:
        """Robot seconds per wall second."""
        return self.robot_time / self.wall_time if self.wall_time > 0 else math.nan

    def to_dict(self) -> dict:
        d = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in self.__dict__.items()}
        rf = self.realtime_factor
        d["realtime_factor"] = rf if math.isfinite(rf) else None
        return d


class TimingHistogram:
    """Durations (s) counted in ``resolution``-wide bins up to ``span`` (longer ones in the last bin,
    their maximum kept): percentiles of a loop that runs all day in fixed memory, O(1) per cycle."""

    def __init__(self, resolution: float = 1e-5, span: float = 1.0):
        self.resolution = float(resolution)
        # an array, not a list: ``percentiles`` (the daemon's ``status``, another thread) copies it with
        # one memcpy; converting a list of 100 001 ints held the interpreter lock for ~4 ms per
        # histogram, in one C call the loop thread could not interrupt (an overrun per ``status``)
        self.bins = array("q", bytes(8 * (int(span / resolution) + 1)))
        self.count = 0
        self.max = 0.0
        self.total = 0.0
        self.total_sq = 0.0

    def add(self, value: float) -> None:
        i = int(value / self.resolution)
        bins = self.bins
        bins[i if i < len(bins) else -1] += 1
        self.count += 1
        self.total += value
        self.total_sq += value * value
        if value > self.max:
            self.max = value

    def percentiles(self, qs) -> list[float]:
        """Upper bin edges at the percentiles ``qs`` (0..100); NaN while empty."""
        if not self.count:
            return [math.nan for _ in qs]
        counts = np.cumsum(np.frombuffer(self.bins, dtype=np.int64))  # a new array: the loop may add meanwhile
        n = counts[-1]
        out = []
        for q in qs:
            i = int(np.searchsorted(counts, max(1, math.ceil(q / 100.0 * n))))
            out.append(min((i + 1) * self.resolution, self.max) if i < len(self.bins) - 1 else self.max)
        return out


class LoopTiming:
    """The timing part of ``LoopRunner``: histograms (kept for a daemon), per-cycle lists (kept with
    ``keep_samples``), overrun accounting and the loop's clock. Expects ``period``, ``realtime``,
    ``keep_samples``, ``supervisor`` and ``event`` on the runner."""

    def _init_timing(self) -> None:
        self.stats = LoopStats(self.period, self.realtime)
        self.period_hist = TimingHistogram()
        self.jitter_hist = TimingHistogram()
        self.compute_hist = TimingHistogram()
        self.read_hist = TimingHistogram()
        self._periods: list[float] = []
        self._compute: list[float] = []
        self._overrunning = False
        self.cycles = 0
        self.overruns = 0
        self.last_period: float | None = None
        self._t_wall0 = None
        self._t_offset = 0.0
        self._t_prev_raw = None
        self._t_prev = None

    @property
    def t(self) -> float:
        """The loop's time (s): that of the last sample (0 before the first)."""
        return self._t_prev if self._t_prev is not None else 0.0

    def _loop_time(self, s: Snapshot) -> Snapshot:
        """The snapshot on the loop's clock: a robot clock that restarts (at ``enable()``) is
        continued one period after the last sample."""
        raw = s.t
        if self._t_prev_raw is not None and raw + self._t_offset <= self._t_prev + 1e-9 * self.period:
            self._t_offset = self._t_prev + self.period - raw
        self._t_prev_raw = raw
        t = raw + self._t_offset
        self._t_prev = t
        return s if self._t_offset == 0.0 else replace(s, t=t)

    def _timing(self, wall_period: float) -> None:
        self.last_period = wall_period
        self.period_hist.add(wall_period)
        self.jitter_hist.add(abs(wall_period - self.period))
        if wall_period > self.supervisor.config.overrun_factor * self.period:
            self.overruns += 1
            if not self._overrunning and self.realtime and not self.keep_samples:  # a streak starts: say when
                self.event(self.t, "overrun", f"period {wall_period * 1e3:.2f} ms (target {self.period * 1e3:.2f} ms)",
                           defer=True)  # written after the cycle's command (record_after_write)
            self._overrunning = True
        else:
            self._overrunning = False
        if self.keep_samples:
            self._periods.append(wall_period)

    def timing(self) -> dict:
        """Timing so far (any thread): rate (Hz), period {target, p50, p99, max}, jitter (|period -
        target|) {p50, p99, max}, compute {p50, p99} (read's return to write's), read {p50, p99}
        (``robot.read()``: SYNC to every TPDO and the IMU) (s), overruns, cycles."""
        p50, p99 = self.period_hist.percentiles((50, 99))
        j50, j99 = self.jitter_hist.percentiles((50, 99))
        c50, c99 = self.compute_hist.percentiles((50, 99))
        r50, r99 = self.read_hist.percentiles((50, 99))
        f = lambda v: None if not math.isfinite(v) else float(v)  # noqa: E731
        return {"rate": 1.0 / self.period, "period": {"target": self.period, "p50": f(p50), "p99": f(p99),
                                                      "max": f(self.period_hist.max) if self.period_hist.count else None},
                "jitter": {"p50": f(j50), "p99": f(j99),
                           "max": f(self.jitter_hist.max) if self.jitter_hist.count else None},
                "compute": {"p50": f(c50), "p99": f(c99)}, "read": {"p50": f(r50), "p99": f(r99)},
                "overruns": self.overruns, "cycles": self.cycles}

    def _final_stats(self, t: list) -> LoopStats:
        """``stats`` filled in for a result: from the per-cycle lists (``keep_samples``; ``t`` the
        samples' times) or else from the histograms (percentiles to their 10 us bins)."""
        n = len(t)
        st = self.stats
        st.cycles = n
        st.wall_time = time.perf_counter() - self._t_wall0 if self._t_wall0 is not None else 0.0
        st.robot_time = (t[-1] - t[0] + self.period) if n else 0.0
        if not self.keep_samples:
            st.cycles = self.cycles
            st.robot_time = self.cycles * self.period
            if self.period_hist.count:
                st.period_p50, st.period_p99 = self.period_hist.percentiles((50, 99))
                st.period_max = self.period_hist.max
                st.jitter_rms = math.sqrt(self.jitter_hist.total_sq / self.jitter_hist.count)
                st.overruns = self.overruns
            if self.compute_hist.count:
                st.compute_p50, st.compute_p99 = self.compute_hist.percentiles((50, 99))
                st.compute_max = self.compute_hist.max
        if self._periods:
            p = np.asarray(self._periods)
            st.period_p50, st.period_p99, st.period_max = (float(v) for v in np.percentile(p, [50, 99, 100]))
            st.jitter_rms = float(np.sqrt(np.mean((p - self.period) ** 2)))
            st.overruns = int(np.sum(p > self.supervisor.config.overrun_factor * self.period))
        if self._compute:
            q = np.asarray(self._compute)
            st.compute_p50, st.compute_p99, st.compute_max = (float(v) for v in np.percentile(q, [50, 99, 100]))
        return st
