"""Control benchmarks: computed-torque law cost per tick and closed-loop simulation wall time.

    python benchmarks/control.py [--json]

Prints a markdown table (the ``## Control`` section of docs/performance.md). Targets: the law
<= 50 us per evaluation so it never limits a 1 kHz loop.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from otbot_hw.control.computed_torque import ComputedTorqueController, TaskState  # noqa: E402
from otbot_hw.control.feasibility import check_feasibility  # noqa: E402
from otbot_hw.control.gains import gains_from_tstab  # noqa: E402
from otbot_hw.control.limiter import TorqueLimiter  # noqa: E402
from otbot_hw.control.scenarios import corridor_spec  # noqa: E402
from otbot_hw.motors import load_motor_limits  # noqa: E402
from otbot_hw.params import nominal  # noqa: E402
from otbot_hw.runtime.tracking import track_reference  # noqa: E402


def per_call_us(fn, n: int) -> float:
    fn()
    best = np.inf
    for _ in range(5):
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        best = min(best, (time.perf_counter() - t0) / n)
    return best * 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    params = nominal()
    limits = load_motor_limits()
    ctrl = ComputedTorqueController(params, gains_from_tstab(3.0))
    rng = np.random.default_rng(0)
    state = TaskState(p=rng.normal(size=3), p_dot=rng.normal(size=3), phi_p=0.3)
    ref = [np.ascontiguousarray(rng.normal(size=3)) for _ in range(3)]
    rows = []
    rows.append(("control law, hot path (`update_fast`: M_bar, C_bar, u, u_traj, u_corr)",
                 f"{per_call_us(lambda: ctrl.update_fast(state.p, state.p_dot, state.phi_p, *ref), 20000):.2f} us"))
    rows.append(("control law, convenience API (`update` -> ControlOutput)",
                 f"{per_call_us(lambda: ctrl.update(state, *ref), 20000):.2f} us"))
    lim = TorqueLimiter(limits)
    u = np.array([10.0, -5.0, 1.0])
    rows.append(("torque limiter, one command", f"{per_call_us(lambda: lim.apply(u, 0.0), 20000):.2f} us"))
    spec = corridor_spec()
    track_reference(spec.reference, ctrl, params, limits, duration=0.1)  # compile / warm up
    walls = []
    for _ in range(3):
        t0 = time.perf_counter()
        run = track_reference(spec.reference, ctrl, params, limits, rate_hz=1000.0)
        walls.append(time.perf_counter() - t0)
    n = len(run.t) - 1
    rows.append((f"closed-loop corridor through the loop runner, {spec.reference.duration:g} s simulated (25 s motion "
                 f"+ 5 s hold) at 1 kHz on the direct back end, truth feedback ({n} cycles: read, feedback, "
                 f"supervisor, record, prediction, law, limiter, RK4 plant step)", f"{min(walls):.2f} s wall "
                 f"({min(walls) / n * 1e6:.0f} us per cycle, {spec.reference.duration / min(walls):.0f}x real time)"))
    t0 = time.perf_counter()
    check_feasibility(spec.reference, params, gains_from_tstab(3.0), limits)
    rows.append(("feasibility check of the corridor (interval bound every 10 ms)", f"{time.perf_counter() - t0:.2f} s"))
    try:
        from otbot_hw.control.planner import crowded_corridor_problem, plan

        res = plan(crowded_corridor_problem(params, limits))
        rows.append((f"planner, crowded corridor ({res.summary()['intervals']} intervals, IPOPT)",
                     f"{res.solve_time_s:.2f} s ({res.iterations} iterations)"))
    except ImportError:
        pass
    if args.json:
        print(json.dumps(dict(rows)))
        return
    print("| measurement | result |\n|---|---|")
    for k, v in rows:
        print(f"| {k} | {v} |")


if __name__ == "__main__":
    main()
