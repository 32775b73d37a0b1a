"""Does an operator still reach a daemon whose loop cannot keep its period? ``otbot daemon --bus sim``
started under SCHED_FIFO (as the unit starts it) on one CPU at a control rate its in-process plant and
loop cannot sustain, enabled; then ``status`` asked ``--requests`` times and ``estop`` once, each
round trip timed (ms) from the client's side.

    python benchmarks/operator_starvation.py [--rate 2500] [--below 1] [--cpu 1] [--fifo 50] [--json]

``--below N``: ``daemon.scheduling.operator_threads_below`` (0: every thread at one priority). Needs
CAP_SYS_NICE (SCHED_FIFO). Results in docs/performance.md, "Seventh pass".
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from otbot_hw.runtime.daemon_process import DaemonProcess, local_config  # noqa: E402

#: overruns counted, not a fault; heartbeat consumers relaxed (a saturated core delays the heartbeats)
RELAX = {"max_consecutive_overruns: {value: 5": "max_consecutive_overruns: {value: 1000000000",
         "master_heartbeat_consumer: {value: 100, unit: ms}": "master_heartbeat_consumer: {value: 500, unit: ms}",
         "heartbeat_consumer: {value: 200, unit: ms}": "heartbeat_consumer: {value: 500, unit: ms}"}


def run(rate: float, below: int, cpu: int, fifo: int, requests: int, timeout: float) -> dict:
    with tempfile.TemporaryDirectory(prefix="otbot-starve-") as tmp:
        tmp = Path(tmp)
        cfg = local_config(tmp / "cfg", replace={
            **RELAX, "control_rate: {value: 100, unit: Hz}": f"control_rate: {{value: {rate:g}, unit: Hz}}",
            "    cpus: null": f"    cpus: [{cpu}]", "operator_threads_below: 1": f"operator_threads_below: {below}"})
        d = DaemonProcess(["--bus", "sim", "--config", str(cfg), "--record-dir", str(tmp / "rec"),
                           "--telemetry", "127.0.0.1:0"], tmp / "control.sock", tmp / "daemon.log", priority=fifo)
        try:
            d.request("enable", timeout=timeout)
            time.sleep(1.0)
            rt = []
            for _ in range(requests):
                t = time.monotonic()
                d.request("status", timeout=timeout)
                rt.append(time.monotonic() - t)
                time.sleep(0.05)
            t = time.monotonic()
            d.request("estop", timeout=timeout)
            estop = time.monotonic() - t
            st = d.request("status", timeout=timeout)
            d.terminate()
        finally:
            d.kill()
    loop = st["loop"]
    return {"rate": rate, "below": below, "cpu": cpu, "fifo": fifo, "status_rt_ms_p50": 1e3 * statistics.median(rt),
            "status_rt_ms_max": 1e3 * max(rt), "estop_rt_ms": 1e3 * estop, "cycles": loop["cycles"],
            "overruns": loop["overruns"], "mode": st["mode"], "drive_states": st["drive_states"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rate", type=float, default=2500.0, help="control rate (Hz); 0x60C2 must express its period")
    ap.add_argument("--below", type=int, default=1, help="daemon.scheduling.operator_threads_below")
    ap.add_argument("--cpu", type=int, default=1, help="the one CPU the daemon runs on")
    ap.add_argument("--fifo", type=int, default=50, help="SCHED_FIFO priority the daemon starts under")
    ap.add_argument("--requests", type=int, default=30, help="status requests timed")
    ap.add_argument("--timeout", type=float, default=10.0, help="s a request may take before it counts as lost")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    if not a.rate > 0 or a.requests < 1 or not a.timeout > 0 or not 0 <= a.below <= 98 or not 1 <= a.fifo <= 99:
        ap.error("--rate and --timeout must be > 0, --requests >= 1, --below in 0..98, --fifo in 1..99")
    row = run(a.rate, a.below, a.cpu, a.fifo, a.requests, a.timeout)
    if a.json:
        print(json.dumps(row))
    else:
        print(f"{row['rate']:g} Hz, operator threads {row['below']} below: status p50 {row['status_rt_ms_p50']:.1f} ms, "
              f"max {row['status_rt_ms_max']:.1f} ms; estop {row['estop_rt_ms']:.1f} ms; {row['overruns']} overruns "
              f"in {row['cycles']} cycles; then {row['mode']}, drives {row['drive_states']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
