"""Worst-case stop time of each path that stops the drives when the control loop stops, judged from
the simulated drives' own state (drive-side truth), paced in real time with the configured watchdogs.

Paths (the loop runs ``write``/``read`` at the control period, then):

* ``stall``: the loop stops calling ``read``/``write`` (the robot object and its threads alive): the
  drives' SYNC watchdog (0x1006, 1.5 periods) stops them; time from the loop's last SYNC;
* ``setpoints``: the loop keeps reading (SYNC goes on) but writes no more setpoints: the RPDO
  deadline (0x1400:05, ``drives.rpdo_timeout`` periods); time from the last RPDO;
* ``heartbeat``: no SYNC or RPDO watchdog armed (lockstep, or a drive without 0x1006 / 0x1400:05):
  the master withholds its heartbeat ``bus.loop_liveness`` periods after the loop's last cycle and the
  drives' heartbeat consumer (0x1016, ``drives.master_heartbeat_consumer``) stops them; time from the
  loop's last cycle;
* ``quick stop``: the loop's own ``quick_stop()``: time from the call.

    .venv/bin/python benchmarks/stop_paths.py [--runs 5] [--rate 100] [--json]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from drivers.config import load_robot_config  # noqa: E402
from otbot_hw.robot import RobotError  # noqa: E402
from sim.bus_robot import simulated_robot  # noqa: E402

PATHS = ("stall", "setpoints", "heartbeat", "quick stop")


def paced_cycles(robot, period: float, n: int, write: bool = True) -> None:
    for _ in range(n):
        robot.clock.wait()  # the benchmark is the loop: it ticks the robot's clock
        if write:
            robot.write([2.0, -2.0, 1.0])
        robot.read()


def one_run(cfg, path: str) -> float | None:
    """Worst drive's stop time (s) after the path's reference instant; None when a fault stopped the
    run before (a real-time deadline missed on a loaded machine)."""
    period = cfg.bus.period
    realtime = path != "heartbeat"
    with simulated_robot(cfg, with_imu=False, realtime=realtime, heartbeat_consumer=None) as (robot, plant):
        try:
            robot.enable()
            paced_cycles(robot, period, 10)
        except RobotError:
            return None
        if robot.faults:
            return None
        if path == "stall":
            ref = max(d._last_sync for d in plant.drives)
            time.sleep(0.5)
        elif path == "setpoints":
            ref = max(d._last_rpdo for d in plant.drives)
            try:
                paced_cycles(robot, period, cfg.drives[0].rpdo_timeout + 5, write=False)
            except RobotError:
                pass  # the drives' EMCY made it a fault: the reaction runs; the drives' own times count
        elif path == "heartbeat":
            ref = time.monotonic()
            time.sleep(cfg.drives[0].master_heartbeat_consumer + 0.5)
        else:
            ref = time.monotonic()
            robot.quick_stop()
        if not plant.wait_all_stopped(1.0):
            return float("inf")
        return max(d.stopped_since[1] for d in plant.drives) - ref


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--rate", type=float, default=None, help="control rate, Hz (default: the configuration's)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    cfg = load_robot_config()
    if args.rate:
        cfg = cfg.replace_bus(control_rate=args.rate)
    period = cfg.bus.period
    out = {"rate": cfg.bus.control_rate, "runs": args.runs, "paths": {}, "spoiled": 0,
           "load": list(os.getloadavg())}
    for path in PATHS:
        times = []
        while len(times) < args.runs:
            t = one_run(cfg, path)
            if t is None:
                out["spoiled"] += 1
                continue
            times.append(t)
        out["paths"][path] = {"median_ms": sorted(times)[len(times) // 2] * 1e3, "max_ms": max(times) * 1e3,
                              "max_periods": max(times) / period}
    if args.json:
        print(json.dumps(out))
        return 0
    print(f"Control rate {cfg.bus.control_rate:g} Hz (period {period * 1e3:g} ms), {args.runs} runs per path, "
          f"load average {', '.join(f'{v:.1f}' for v in out['load'])}; {out['spoiled']} runs spoiled before the "
          "stop and repeated.\n")
    print("| path | stops the drives | median (ms) | worst (ms) | worst (periods) |")
    print("|---|---|---|---|---|")
    by = {"stall": "SYNC watchdog 0x1006 (1.5 periods), from the loop's last SYNC",
          "setpoints": f"RPDO deadline 0x1400:05 ({cfg.drives[0].rpdo_timeout} periods), from the last RPDO",
          "heartbeat": f"heartbeat withheld after {cfg.bus.loop_liveness} periods + consumer 0x1016 "
                       f"({cfg.drives[0].master_heartbeat_consumer * 1e3:g} ms), from the loop's last cycle (lockstep)",
          "quick stop": "the master's quick stop, from the call"}
    for path, r in out["paths"].items():
        print(f"| {path} | {by[path]} | {r['median_ms']:.1f} | {r['max_ms']:.1f} | {r['max_periods']:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
