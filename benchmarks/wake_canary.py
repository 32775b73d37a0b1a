"""A wake-up canary: how late this machine wakes a sleeping real-time thread that has nothing else to
wait for (no interpreter lock shared, no I/O), as ``cyclictest`` measures it.

    python benchmarks/wake_canary.py [--seconds 60] [--interval 0.0005] [--fifo 50] [--late 0.5] [--out FILE]

One process, one thread: sleep ``interval`` s, note how late it woke (wall ``time.monotonic``), again.
Every wake-up later than ``--late`` ms is kept as (start, end) of the sleep (s, CLOCK_MONOTONIC, the
clock the daemon's SYNCs are stamped with), so another measurement can ask whether the machine itself
stalled over the same interval. ``--fifo P``: SCHED_FIFO priority P (as the daemon's). Prints (or writes
to FILE) JSON: the wake-ups, the lateness percentiles, the late ones.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import time


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--interval", type=float, default=0.0005, help="sleep per wake-up (s)")
    ap.add_argument("--fifo", type=int, default=None, metavar="PRIORITY")
    ap.add_argument("--late", type=float, default=0.5, help="keep wake-ups later than this (ms)")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    if a.fifo:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(a.fifo))
    stop = [False]
    signal.signal(signal.SIGTERM, lambda *_: stop.__setitem__(0, True))
    late_s, interval = a.late * 1e-3, a.interval
    mono, sleep = time.monotonic, time.sleep
    hist = [0] * 201  # lateness in 0.1 ms bins, last: >= 20 ms
    kept = []
    n = 0
    end = mono() + a.seconds
    t = mono()
    while not stop[0] and t < end:
        sleep(interval)
        t1 = mono()
        late = t1 - t - interval
        hist[min(200, max(0, int(late * 1e4)))] += 1
        if late > late_s:
            kept.append((round(t, 6), round(t1, 6)))
        n += 1
        t = t1

    def pct(q):
        k, acc = q * n, 0
        for i, c in enumerate(hist):
            acc += c
            if acc >= k:
                return i * 0.1
        return None

    out = {"wakeups": n, "interval_ms": interval * 1e3, "late_p50_ms": pct(0.5), "late_p99_ms": pct(0.99),
           "late_p999_ms": pct(0.999), "late_over_ms": a.late, "late": kept}
    text = json.dumps(out)
    if a.out:
        with open(a.out, "w") as f:
            f.write(text)
    else:
        print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
