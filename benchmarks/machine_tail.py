"""The machine's own tail: the same fixed piece of pure-Python work, paced at a control rate, timed
per period as the loop's work is timed (thread CPU time, and wall time).

The work neither allocates, waits nor branches on data, so every repetition does the same
instructions; whatever spread its times show (p99 against p50) is the machine's: caches and TLB
cooled by the sleep between periods, the hypervisor's preemptions that the guest counts as the
thread's time, frequency changes. The loop's master-side work (``benchmarks/loop_cycle.py``) is
timed the same way, so its p99 cannot be below ``ratio * p50`` on the same machine, and a target
``p99 <= X`` needs ``p50 <= X / ratio`` there.

    python benchmarks/machine_tail.py [--rate 800] [--seconds 10] [--iterations 3000] [--cpus 1]
                                      [--fifo 50] [--json]

``--iterations`` sizes the work (3000: about 150 us of CPU on the 2.3 GHz Xeon VM of
docs/performance.md); ``--cpus`` and ``--fifo`` place it as the unit places the daemon. Bad
arguments: one line, exit 2.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np


def fixed_work(iterations: int) -> float:
    """A fixed amount of interpreter work (``iterations`` float multiply-adds in a Python loop)."""
    s = 0.0
    for i in range(iterations):
        s += i * 0.5
    return s


def tail(rate: float, seconds: float, iterations: int, paced: bool = True) -> dict:
    """Time ``fixed_work(iterations)`` once per period of ``rate`` Hz for ``seconds`` s on the calling
    thread (``paced``: sleep to each period's start, as the loop does; else back to back). Returns
    CPU and wall p50 / p99 / max (us) and the ratio p99 / p50 of the CPU time."""
    n = max(1, int(round(rate * seconds)))
    cpu, wall = np.empty(n), np.empty(n)
    period = 1.0 / rate
    t_next = time.monotonic()
    for k in range(n):
        if paced:
            t_next += period
            d = t_next - time.monotonic()
            if d > 0:
                time.sleep(d)
        w0, c0 = time.perf_counter(), time.thread_time()
        fixed_work(iterations)
        cpu[k], wall[k] = time.thread_time() - c0, time.perf_counter() - w0
    us = lambda a, q: float(np.percentile(a, q) * 1e6)  # noqa: E731
    out = {"rate": rate, "seconds": seconds, "iterations": iterations, "paced": paced, "samples": n,
           "cpu_p50_us": us(cpu, 50), "cpu_p99_us": us(cpu, 99), "cpu_max_us": us(cpu, 100),
           "wall_p50_us": us(wall, 50), "wall_p99_us": us(wall, 99), "wall_max_us": us(wall, 100)}
    out["cpu_p99_over_p50"] = out["cpu_p99_us"] / out["cpu_p50_us"] if out["cpu_p50_us"] > 0 else float("nan")
    return out


def _positive(kind):
    def parse(text: str):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be a number, got {text!r}") from None
        if not v > 0 or v != v or v == float("inf"):
            raise argparse.ArgumentTypeError(f"must be > 0 and finite, got {text!r}")
        return v
    return parse


def place(cpus: str | None, fifo: int | None) -> str | None:
    """Pin the process to ``cpus`` ("1" or "0,1") and put it under SCHED_FIFO ``fifo``; returns why
    it could not (one line) or None."""
    if cpus:
        try:
            wanted = {int(c) for c in cpus.split(",")}
            os.sched_setaffinity(0, wanted)
        except (ValueError, OSError) as exc:
            return f"--cpus {cpus}: {exc}"
    if fifo:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(fifo))
        except (ValueError, OSError) as exc:
            return f"--fifo {fifo}: {exc}"
    return None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rate", type=_positive(float), default=800.0, help="periods per second (Hz)")
    ap.add_argument("--seconds", type=_positive(float), default=10.0, help="how long (s)")
    ap.add_argument("--iterations", type=_positive(int), default=3000, help="size of the fixed work (loop turns)")
    ap.add_argument("--unpaced", action="store_true", help="back to back, no sleep between repetitions")
    ap.add_argument("--cpus", default=None, metavar="LIST", help="run on these CPUs, e.g. 1")
    ap.add_argument("--fifo", type=int, default=None, metavar="PRIORITY", help="SCHED_FIFO at this priority (1..99)")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    if a.fifo is not None and not 1 <= a.fifo <= 99:
        ap.error(f"argument --fifo: must be 1..99, got {a.fifo}")
    why = place(a.cpus, a.fifo)
    if why:
        ap.error(why)
    row = tail(a.rate, a.seconds, a.iterations, paced=not a.unpaced)
    row["cpus"], row["fifo"], row["load"] = a.cpus, a.fifo, os.getloadavg()[0]
    if a.json:
        print(json.dumps(row))
        return 0
    print("| rate (Hz) | paced | iterations | CPU p50 / p99 / max (us) | wall p50 / p99 / max (us) | CPU p99 / p50 "
          "| load |")
    print("|---|---|---|---|---|---|---|")
    print(f"| {row['rate']:g} | {'yes' if row['paced'] else 'no'} | {row['iterations']} | {row['cpu_p50_us']:.0f} / "
          f"{row['cpu_p99_us']:.0f} / {row['cpu_max_us']:.0f} | {row['wall_p50_us']:.0f} / {row['wall_p99_us']:.0f} / "
          f"{row['wall_max_us']:.0f} | {row['cpu_p99_over_p50']:.2f} | {row['load']:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
