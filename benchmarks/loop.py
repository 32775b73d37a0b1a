"""Loop benchmarks: the 30 s corridor in closed loop through the loop runner on each back end.

    python benchmarks/loop.py [--rates 100,250,500,1000] [--skip-bus-1khz] [--json]

Prints the markdown tables of docs/performance.md ("Loop runner"): wall time of the 30 s corridor
(25 s motion + 5 s hold) with truth feedback, and with EKF feedback where ``otbot_hw.estimation`` is
importable, on the direct back end (1 kHz) and over the simulated CAN bus (the configured 100 Hz and
1 kHz), next to the retired closed loop's algorithm restated and timed in the same run (and its
docs/performance.md figure); then how fast the simulated bus runs against real time at several rates
(lockstep, 5 s of the corridor each).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from drivers.config import load_robot_config  # noqa: E402
from otbot_hw.control.computed_torque import ComputedTorqueController, TaskState  # noqa: E402
from otbot_hw.control.gains import gains_from_tstab  # noqa: E402
from otbot_hw.control.limiter import TorqueLimiter  # noqa: E402
from otbot_hw.control.scenarios import corridor_spec  # noqa: E402
from otbot_hw.params import nominal  # noqa: E402
from otbot_hw.runtime.backends import BusSimBackend, DirectBackend  # noqa: E402
from otbot_hw.runtime.tracking import track_reference  # noqa: E402
from otbot_hw.sensors import NoiseModel  # noqa: E402
from otbot_hw.simulation.simulator import Stepper, rest_state  # noqa: E402

OLD_DOCS_S = 1.11  # docs/performance.md, "Control": the retired run_closed_loop, 30 s corridor at 1 kHz


def old_closed_loop(ref, params, limits, rate=1000.0) -> float:
    """The retired ``control/closed_loop.py`` algorithm (truth read, law, limiter, RK4 step, no delay)."""
    t0 = time.perf_counter()
    n = int(round(ref.duration * rate))
    t = np.arange(n + 1) / rate
    P, PD, PDD = (np.ascontiguousarray(a) for a in ref.sample(t))
    law, lim = ComputedTorqueController(params, gains_from_tstab(3.0)), TorqueLimiter(limits)
    st = Stepper(params, 1 / rate, rest_state(P[0]))
    for k in range(n):
        s = TaskState.from_state(st.x)
        st.step(lim.apply(law.update_fast(s.p, s.p_dot, s.phi_p, P[k], PD[k], PDD[k])[0], t[k])[0])
    return time.perf_counter() - t0


def robot_alone(params, n=30000, rate=1000.0) -> float:
    """``DirectSimRobot`` without a loop around it: write + read per cycle (the back end's own cost)."""
    from sim.direct import DirectSimRobot

    robot = DirectSimRobot(params, period=1 / rate, imu_rate=None)
    robot.enable()
    u = np.zeros(3)
    t0 = time.perf_counter()
    for _ in range(n):
        robot.write(u)
        robot.read()
    return time.perf_counter() - t0


def runner(ref, params, limits, backend, feedback, duration=None):
    law = ComputedTorqueController(params, gains_from_tstab(3.0))
    run = track_reference(ref, law, params, limits, backend, feedback, duration=duration)
    if not run.completed:
        raise RuntimeError(f"benchmark run stopped: {run.loop.fault}")
    return run


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rates", default="100,250,500,1000", help="bus rates (Hz) for the real-time table")
    ap.add_argument("--skip-bus-1khz", action="store_true", help="skip the 30 s corridor over the bus at 1 kHz")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    params, cfg = nominal(), load_robot_config()
    limits = cfg.limits
    ref = corridor_spec().reference
    feedbacks = ["truth", "ekf"]
    runner(ref, params, limits, DirectBackend(), "truth", duration=0.2)  # compile / warm up
    old_closed_loop(ref, params, limits)
    rows = [{"setup": "retired closed loop (docs/performance.md)", "rate": 1000.0, "feedback": "truth",
             "wall_s": OLD_DOCS_S, "cycles": 30000}]
    rows.append({"setup": "retired closed loop, restated, this run", "rate": 1000.0, "feedback": "truth",
                 "wall_s": min(old_closed_loop(ref, params, limits) for _ in range(2)), "cycles": 30000})
    robot_alone(params, 100)
    rows.append({"setup": "DirectSimRobot alone (write + read, no controller, no runner)", "rate": 1000.0,
                 "feedback": "-", "wall_s": min(robot_alone(params) for _ in range(2)), "cycles": 30000})
    setups = [("runner, direct back end, exact sensors", DirectBackend(rate=1000.0, imu_rate=None)),
              ("runner, direct back end like the robot (encoders, IMU 100 Hz, noise)",
               DirectBackend.from_config(cfg, 1000.0, NoiseModel.paper())),
              ("runner, simulated CAN bus (configured rate)", BusSimBackend(cfg, NoiseModel.paper()))]
    if not args.skip_bus_1khz:
        setups.append(("runner, simulated CAN bus", BusSimBackend(cfg.replace_bus(control_rate=1000.0),
                                                                  NoiseModel.paper())))
    for name, backend in setups:
        for fb in feedbacks:
            if fb == "truth" or backend.name != "sim" or backend.imu_rate is not None:
                print(f"[loop] {name}, {backend.rate:g} Hz, feedback {fb} ...", file=sys.stderr, flush=True)
                run = runner(ref, params, limits, backend, fb)
                st = run.loop.stats
                rows.append({"setup": name, "rate": backend.rate, "feedback": fb, "wall_s": st.wall_time,
                             "cycles": st.cycles, "compute_p50_us": st.compute_p50 * 1e6,
                             "period_p50_us": st.period_p50 * 1e6, "period_p99_us": st.period_p99 * 1e6,
                             "max_error_mm": float(np.abs(run.e_p[:, :2]).max() * 1e3)})
    rt = []
    for rate in (float(r) for r in args.rates.split(",")):
        print(f"[loop] simulated bus against real time at {rate:g} Hz ...", file=sys.stderr, flush=True)
        run = runner(ref, params, limits, BusSimBackend(cfg.replace_bus(control_rate=rate), NoiseModel.paper()),
                     "truth", duration=5.0)
        st = run.loop.stats
        rt.append({"rate": rate, "realtime_factor": st.realtime_factor, "period_p50_ms": st.period_p50 * 1e3,
                   "period_p99_ms": st.period_p99 * 1e3, "slower_than_period": st.overruns,
                   "cycles": st.cycles})
    if args.json:
        print(json.dumps({"corridor": rows, "bus_realtime": rt}))
        return
    print("| setup | rate (Hz) | feedback | wall time (s) | per cycle (us) | loop compute p50 (us) | max error (mm) |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        comp = f"{r['compute_p50_us']:.0f}" if "compute_p50_us" in r else "-"
        err = f"{r['max_error_mm']:.1f}" if "max_error_mm" in r else "-"
        print(f"| {r['setup']} | {r['rate']:g} | {r['feedback']} | {r['wall_s']:.2f} | "
              f"{r['wall_s'] / r['cycles'] * 1e6:.0f} | {comp} | {err} |")
    print()
    print("| bus rate (Hz) | robot s per wall s | period p50 / p99 (ms) | cycles longer than 1.5 periods |")
    print("|---|---|---|---|")
    for r in rt:
        print(f"| {r['rate']:g} | {r['realtime_factor']:.1f} | {r['period_p50_ms']:.2f} / {r['period_p99_ms']:.2f} | "
              f"{r['slower_than_period']} of {r['cycles']} |")


if __name__ == "__main__":
    main()
