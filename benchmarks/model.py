"""Benchmark of the Otbot model and simulator (a script, not a test).

Prints, side by side in one run:

* forward dynamics, microseconds per call, for each formulation: numpy
  conventional (9x9 augmented solve), numpy multiplier-free (K q_dd = b_FD),
  compiled (numba; called from Python, and per evaluation inside the compiled
  integrator);
* wall time to simulate the paper's chassis experiment (tau = (6, -10, 6) N m,
  3 s, 100 Hz zero-order hold) by the default fast path, by a plain
  implementation (numpy 9x9 solve inside scipy ``solve_ivp`` RK45, restarted on
  every ZOH interval, at the loosest tolerance that still reaches 1e-8) and by
  the reference (``method="reference"``), with each one's maximum state error
  against the reference.

Target (issue 2): default path >= 100x faster than the plain one with <= 1e-8
maximum state error. Exit code 1 when the target is missed.

    python benchmarks/model.py [--repeat N] [--json]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from scipy.integrate import solve_ivp  # noqa: E402

from otbot_hw.model import compiled  # noqa: E402
from otbot_hw.model import dynamics as dyn  # noqa: E402
from otbot_hw.model import kinematics as kin  # noqa: E402
from otbot_hw.params import nominal  # noqa: E402
from otbot_hw.simulation.simulator import default_substeps, simulate  # noqa: E402

DT = 0.01  # s, 100 Hz zero-order hold
STEPS = 300  # 3 s
TORQUES = (6.0, -10.0, 6.0)  # N m
TARGET_SPEEDUP = 100.0
TARGET_ERROR = 1e-8
PLAIN_TOLERANCES = (1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10)


def progress(msg: str) -> None:
    print(f"[bench] {msg}", file=sys.stderr, flush=True)


def machine() -> dict:
    cpu = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import numba
    import scipy

    return {"nproc": os.cpu_count(), "cpu": cpu, "python": platform.python_version(),
            "numpy": np.__version__, "scipy": scipy.__version__, "numba": numba.__version__}


def best_time(fn, repeat: int, number: int = 1) -> float:
    """Smallest wall time (s) of ``number`` calls, over ``repeat`` trials, per call."""
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        for _ in range(number):
            fn()
        best = min(best, (time.perf_counter() - t0) / number)
    return best


def forward_dynamics_timings(params, repeat: int) -> dict:
    """Microseconds per call of each forward-dynamics formulation at a random admissible state."""
    rng = np.random.default_rng(1)
    q = rng.uniform(-3, 3, 6)
    qd = kin.admissible_velocity(q, rng.normal(scale=3.0, size=3), params)
    u = np.array(TORQUES)
    f = np.array([3.0, -2.0])
    x = np.concatenate([q, qd])
    prm, gen = params.as_array(), np.zeros(6)
    compiled.accelerations(x, u, f, gen, prm)  # compile
    return {
        "numpy_conventional_9x9": 1e6 * best_time(lambda: dyn.forward_dynamics_conventional(q, qd, u, params, f),
                                                  repeat, 2000),
        "numpy_multiplier_free": 1e6 * best_time(lambda: dyn.forward_dynamics(q, qd, u, params, f), repeat, 2000),
        "compiled_python_call": 1e6 * best_time(lambda: compiled.accelerations(x, u, f, gen, prm), repeat, 20000),
    }


def plain_simulation(params, U: np.ndarray, tol: float) -> np.ndarray:
    """The plain implementation: 9x9 numpy solve in scipy RK45, restarted on every ZOH interval."""
    x = np.zeros(12)
    X = np.empty((len(U) + 1, 12))
    X[0] = x
    for k, u in enumerate(U):
        def rhs(_t, s, u=u):
            return np.concatenate([s[6:], dyn.forward_dynamics_conventional(s[:6], s[6:], u, params)[0]])

        sol = solve_ivp(rhs, (k * DT, (k + 1) * DT), x, method="RK45", rtol=tol, atol=tol)
        x = sol.y[:, -1]
        X[k + 1] = x
    return X


def run(repeat: int) -> dict:
    params = nominal()
    U = np.tile(TORQUES, (STEPS, 1))
    progress("forward dynamics per call ...")
    fd = forward_dynamics_timings(params, repeat)

    progress("reference (RK45, rtol = atol = 1e-12) ...")
    t0 = time.perf_counter()
    ref = simulate(params, U, DT, method="reference").x
    t_ref = time.perf_counter() - t0

    progress("default fast path ...")
    simulate(params, U[:2], DT)  # compile
    t_fast = best_time(lambda: simulate(params, U, DT), max(repeat, 20))
    err_fast = float(np.abs(simulate(params, U, DT).x - ref).max())
    substeps = default_substeps(DT)
    evals = STEPS * substeps * 4
    fd["compiled_in_integrator"] = 1e6 * t_fast / evals

    progress("plain implementation: tolerance sweep ...")
    sweep = []
    for tol in PLAIN_TOLERANCES:
        t_plain = best_time(lambda tol=tol: plain_simulation(params, U, tol), repeat)
        err = float(np.abs(plain_simulation(params, U, tol) - ref).max())
        sweep.append({"tol": tol, "seconds": t_plain, "max_state_error": err})
        progress(f"  rtol = atol = {tol:g}: {t_plain * 1e3:.1f} ms, max error {err:.2e}")
    ok = [s for s in sweep if s["max_state_error"] <= TARGET_ERROR]
    plain = min(ok, key=lambda s: s["seconds"]) if ok else min(sweep, key=lambda s: s["max_state_error"])

    speedup = plain["seconds"] / t_fast
    met = speedup >= TARGET_SPEEDUP and err_fast <= TARGET_ERROR
    return {
        "machine": machine(),
        "forward_dynamics_us_per_call": fd,
        "chassis_experiment": {
            "torques": list(TORQUES), "duration_s": STEPS * DT, "zoh_period_s": DT,
            "fast": {"seconds": t_fast, "max_state_error": err_fast,
                     "method": f"compiled RK4, {substeps} substeps per interval"},
            "plain": {"seconds": plain["seconds"], "max_state_error": plain["max_state_error"],
                      "method": f"numpy 9x9 in scipy RK45 per interval, rtol = atol = {plain['tol']:g}"},
            "reference": {"seconds": t_ref, "max_state_error": 0.0,
                          "method": "numpy multiplier-free in scipy RK45 per interval, rtol = atol = 1e-12"},
            "plain_tolerance_sweep": sweep,
            "speedup_fast_vs_plain": speedup,
        },
        "target": {"speedup": TARGET_SPEEDUP, "max_state_error": TARGET_ERROR, "met": met},
    }


def print_table(r: dict) -> None:
    m = r["machine"]
    print(f"machine: {m['nproc']} CPUs, {m['cpu']}; Python {m['python']}, numpy {m['numpy']}, "
          f"scipy {m['scipy']}, numba {m['numba']}")
    print()
    print("forward dynamics                          us/call")
    labels = {"numpy_conventional_9x9": "numpy conventional (9x9 solve)",
              "numpy_multiplier_free": "numpy multiplier-free (K, b_FD)",
              "compiled_python_call": "compiled, called from Python",
              "compiled_in_integrator": "compiled, inside the RK4 integrator"}
    for key, label in labels.items():
        print(f"  {label:<38s} {r['forward_dynamics_us_per_call'][key]:9.2f}")
    c = r["chassis_experiment"]
    print()
    print("chassis experiment, 3 s at 100 Hz ZOH   wall time   max state error   speed-up   method")
    for key in ("fast", "plain", "reference"):
        s = c[key]
        print(f"  {key:<37s} {s['seconds'] * 1e3:8.2f} ms   {s['max_state_error']:15.2e}   "
              f"{c['plain']['seconds'] / s['seconds']:7.1f}x   {s['method']}")
    t = r["target"]
    print()
    print(f"target: fast >= {t['speedup']:.0f}x plain with error <= {t['max_state_error']:g}: "
          f"{'met' if t['met'] else 'MISSED'} ({c['speedup_fast_vs_plain']:.0f}x, {c['fast']['max_state_error']:.1e})")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=5, help="timing trials, best is kept (default 5)")
    ap.add_argument("--json", action="store_true", help="print one JSON object (seconds, us) instead of the table")
    args = ap.parse_args(argv)
    if args.repeat < 1:
        ap.error("--repeat must be >= 1")
    r = run(args.repeat)
    if args.json:
        print(json.dumps(r))
    else:
        print_table(r)
    return 0 if r["target"]["met"] else 1


if __name__ == "__main__":
    sys.exit(main())
