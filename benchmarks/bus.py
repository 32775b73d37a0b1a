"""Cost of one control cycle over the simulated CAN bus, in lockstep.

A cycle is the full round the control loop pays for: three RPDOs (controlword + target torque)
written, SYNC, the plant's step (slaves apply RPDOs, model advances one period, IMU sentence
published on its pty), seven TPDOs back (two per drive + the pivot encoder), the IMU sentence
read and decoded by the VectorNav driver. Reported per configuration: wall and CPU time per
cycle (CPU = the whole process, all threads: plant, notifiers, IMU), p50 / p99, and the
simulated-time / wall-time ratio.

    .venv/bin/python benchmarks/bus.py [--cycles 2000] [--json] [--markdown]

Progress goes to stderr; --json prints one JSON object, --markdown the table for
docs/performance.md.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from drivers.config import load_robot_config  # noqa: E402
from otbot_hw.sensors import NoiseModel  # noqa: E402


def measure_inprocess(rate: float, cycles: int, with_imu: bool) -> dict:
    from sim.bus_robot import simulated_robot

    cfg = load_robot_config().replace_bus(control_rate=rate)
    wall = np.empty(cycles)
    cpu = np.empty(cycles)
    u = np.array([6.0, -10.0, 6.0])
    with simulated_robot(cfg, with_imu=with_imu, noise=NoiseModel.paper()) as (robot, plant):
        robot.enable()
        for _ in range(20):  # warm-up
            robot.write(u)
            robot.read()
        t_start = time.perf_counter()
        for k in range(cycles):
            w0, c0 = time.perf_counter(), time.process_time()
            robot.write(u)
            s = robot.read()
            wall[k] = time.perf_counter() - w0
            cpu[k] = time.process_time() - c0
        total = time.perf_counter() - t_start
        assert not s.faults, s.faults
    return summarize(f"in-process virtual CAN, {'IMU on pty' if with_imu else 'no IMU'}", rate, cycles, wall, cpu,
                     total)


def measure_slcan(rate: float, cycles: int) -> dict:
    import subprocess

    from drivers.robot import open_imu
    from sim.lockstep import LockstepCanopenRobot

    code = "import sys; from otbot_hw.cli import main; sys.exit(main())"
    proc = subprocess.Popen([sys.executable, "-c", code, "plant", "--transport", "slcan", "--rate", str(rate)],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        info = json.loads(proc.stdout.readline())
        cfg = load_robot_config().replace_bus(control_rate=rate, interface="slcan", channel=info["can_channel"],
                                              options={"sleep_after_open": 0})
        robot = LockstepCanopenRobot(cfg, imu=open_imu(cfg.imu, port=info["imu_port"]))
        wall = np.empty(cycles)
        cpu = np.empty(cycles)
        with robot:
            robot.open()
            robot.enable()
            t_start = time.perf_counter()
            for k in range(cycles):
                w0, c0 = time.perf_counter(), time.process_time()
                robot.write([6.0, -10.0, 6.0])
                s = robot.read()
                wall[k] = time.perf_counter() - w0
                cpu[k] = time.process_time() - c0
            total = time.perf_counter() - t_start
            assert not s.faults, s.faults
    finally:
        proc.stdin.close()
        proc.wait(timeout=20)
    return summarize("plant process over slcan (pty), IMU on pty (CPU: master process only)", rate, cycles, wall,
                     cpu, total)


def summarize(name, rate, cycles, wall, cpu, total) -> dict:
    return {"setup": name, "rate": rate, "cycles": cycles,
            "wall_p50_ms": float(np.percentile(wall, 50) * 1e3), "wall_p99_ms": float(np.percentile(wall, 99) * 1e3),
            "cpu_p50_ms": float(np.percentile(cpu, 50) * 1e3), "cpu_p99_ms": float(np.percentile(cpu, 99) * 1e3),
            "cpu_mean_ms": float(cpu.mean() * 1e3),
            "sim_over_wall": float(cycles / rate / total)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cycles", type=int, default=2000, help="cycles per configuration (default 2000)")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--markdown", action="store_true")
    args = ap.parse_args()
    rows = []
    for rate, imu in ((100.0, True), (1000.0, True), (100.0, False)):
        print(f"[bench] in-process, {rate:g} Hz, imu={imu}, {args.cycles} cycles", file=sys.stderr, flush=True)
        rows.append(measure_inprocess(rate, args.cycles, imu))
    print(f"[bench] slcan plant process, 100 Hz, {args.cycles // 4} cycles", file=sys.stderr, flush=True)
    rows.append(measure_slcan(100.0, args.cycles // 4))
    load = os.getloadavg()
    if args.json:
        print(json.dumps({"rows": rows, "loadavg": load}))
        return
    print("| setup | rate | wall p50 / p99 (ms) | CPU p50 / p99 (ms) | sim / wall |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['setup']} | {r['rate']:g} Hz | {r['wall_p50_ms']:.2f} / {r['wall_p99_ms']:.2f} | "
              f"{r['cpu_p50_ms']:.2f} / {r['cpu_p99_ms']:.2f} | {r['sim_over_wall']:.1f}x |")
    print(f"\n(load average during the run: {load[0]:.1f}, {load[1]:.1f}, {load[2]:.1f})")


if __name__ == "__main__":
    main()
