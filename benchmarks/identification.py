"""Speed of identification: our step 2 vs a plain implementation, and a 40 x 20 sweep.

Run: ``.venv/bin/python benchmarks/identification.py [--seeds 3] [--sweep-seeds 20] [--skip-sweep]``

* ours (local fit): ``fit_parameters`` on the paper's chassis experiment from the
  paper's guess (a single fit, no equation-error start, so both sides solve the same
  problem): compiled RK4 zero-order hold with the step tuned to the noise (integration
  error < 1e-3 sigma), finite-difference Jacobian simulated in one compiled batch,
  parameter scaling (x_scale);
* ours (step 2 as the tool runs it): ``identify_step("chassis")``, i.e. the
  equation-error start followed by the prediction-error fit, plus reading the recording;
* plain: scipy ``solve_ivp`` (RK45) restarted on every ZOH interval on the numpy model,
  ``least_squares(method="trf")`` with its 2-point finite-difference Jacobian and no
  scaling, scipy's default tolerances (restarted every 10 ms, RK45 at rtol 1e-3 already
  reproduces our estimates to about 1e-5 sigma: the table's last column is the largest
  difference between the three estimates in units of the estimate's sigma, so all run
  at equal accuracy).

Prints one table (markdown) with both wall times and the speed-up, then the time of a
sensitivity sweep of step 3 (40 deviations x 20 seeds) on local processes.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp
from scipy.optimize import least_squares

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from otbot_hw.identification.experiment import Experiment  # noqa: E402
from otbot_hw.identification.experiments import paper_guess, simulate_experiment  # noqa: E402
from otbot_hw.identification.model import OtbotModel  # noqa: E402
from otbot_hw.identification.prediction_error import DEFAULT_BOUNDS, fit_parameters  # noqa: E402
from otbot_hw.identification.steps import identify_step  # noqa: E402
from otbot_hw.model.dynamics import forward_dynamics  # noqa: E402
from otbot_hw.params import nominal  # noqa: E402

FREE = ("m_c", "I_c", "x_B", "y_B")


def plain_predict(params, U, dt, rtol, atol):
    """IMU outputs (n, 3) by solve_ivp restarted on each interval, numpy model."""
    n = len(U)
    x = np.zeros(12)
    Y = np.empty((n, 3))
    for k in range(n):
        u = U[k]
        qdd = forward_dynamics(x[:6], x[6:], u, params)
        c, s = np.cos(x[2]), np.sin(x[2])
        Y[k] = (c * qdd[0] + s * qdd[1], -s * qdd[0] + c * qdd[1], x[8])
        if k == n - 1:
            break

        def rhs(_t, z, u=u):
            return np.concatenate([z[6:], forward_dynamics(z[:6], z[6:], u, params)])

        x = solve_ivp(rhs, (k * dt, (k + 1) * dt), x, method="RK45", rtol=rtol, atol=atol).y[:, -1]
    return Y


def plain_fit(exp, base, guess, rtol, atol):
    meas = np.stack([exp.measured[c] for c in ("a_x", "a_y", "omega_z")], axis=1)
    w = 1.0 / np.array([exp.sigma[c] for c in ("a_x", "a_y", "omega_z")])
    lo = [DEFAULT_BOUNDS[n][0] for n in FREE]
    hi = [DEFAULT_BOUNDS[n][1] for n in FREE]
    count = [0]

    def res(z):
        count[0] += 1
        p = base.replace(**dict(zip(FREE, z)))
        return ((meas - plain_predict(p, exp.torque, exp.dt, rtol, atol)) * w).ravel()

    sol = least_squares(res, [guess[n] for n in FREE], bounds=(lo, hi), method="trf")
    return dict(zip(FREE, sol.x)), count[0]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=3, help="noise seeds timed for step 2 (default 3)")
    ap.add_argument("--sweep-seeds", type=int, default=20)
    ap.add_argument("--sweep-points", type=int, default=40)
    ap.add_argument("--skip-sweep", action="store_true")
    ap.add_argument("--rtol", type=float, default=1e-3,
                    help="plain solve_ivp rtol (default 1e-3, scipy's default; atol = rtol / 100)")
    args = ap.parse_args()
    truth = nominal()
    model = OtbotModel()
    guess = paper_guess("chassis", truth)
    # warm up (numba compiled code is cached on disk; the first call of a process loads it)
    t0 = time.perf_counter()
    rec0 = simulate_experiment("chassis", truth, seed=999)
    fit_parameters(model, [Experiment.from_recording(rec0, ("a_x", "a_y", "omega_z"))], FREE, truth, guess=guess)
    warm = time.perf_counter() - t0
    rows = []
    for seed in range(args.seeds):
        rec = simulate_experiment("chassis", truth, seed=seed)
        exp = Experiment.from_recording(rec, ("a_x", "a_y", "omega_z"))
        t0 = time.perf_counter()
        ours = fit_parameters(model, [exp], FREE, truth, guess=guess)
        t_ours = time.perf_counter() - t0
        print(f"seed {seed}: ours {t_ours:.3f} s ({ours.simulations} simulations)", file=sys.stderr, flush=True)
        t0 = time.perf_counter()
        step = identify_step("chassis", [rec], truth)
        t_step = time.perf_counter() - t0
        dstep = max(abs(step.fit.estimate[n] - ours.estimate[n]) / ours.std[n] for n in FREE)
        print(f"seed {seed}: ours step 2 pipeline {t_step:.3f} s", file=sys.stderr, flush=True)
        t0 = time.perf_counter()
        plain, nsim = plain_fit(exp, truth, guess, args.rtol, args.rtol * 1e-2)
        t_plain = time.perf_counter() - t0
        dz = max(abs(plain[n] - ours.estimate[n]) / ours.std[n] for n in FREE)
        print(f"seed {seed}: plain {t_plain:.1f} s ({nsim} simulations), max |difference| {dz:.2g} sigma",
              file=sys.stderr, flush=True)
        dz = max(dz, dstep)
        rows.append((seed, t_ours, ours.simulations, t_step, t_plain, nsim, dz))
    print(f"\nfirst call in a fresh process (loading compiled code + one fit): {warm:.2f} s\n")
    print("| seed | ours, local fit (s) | simulations | ours, step 2 pipeline (s) | plain (s) | plain simulations "
          "| speed-up local / pipeline | max estimate difference |")
    print("|---|---|---|---|---|---|---|---|")
    for seed, to, so, ts, tp, sp, dz in rows:
        print(f"| {seed} | {to:.3f} | {so} | {ts:.3f} | {tp:.1f} | {sp} | {tp / to:.0f}x / {tp / ts:.0f}x | {dz:.1g} sigma |")
    to = np.median([r[1] for r in rows])
    ts = np.median([r[3] for r in rows])
    tp = np.median([r[4] for r in rows])
    print(f"| median | {to:.3f} | | {ts:.3f} | {tp:.1f} | | {tp / to:.0f}x / {tp / ts:.0f}x | |")
    if not args.skip_sweep:
        from otbot_hw.identification.executors import LocalExecutor
        from otbot_hw.identification.sweep import deviation_grid, run_sweep

        devs = deviation_grid(1.0, args.sweep_points)
        workers = os.cpu_count() or 1
        with LocalExecutor(workers) as ex:
            def prog(d, n):
                if d % max(1, n // 10) == 0 or d == n:
                    print(f"sweep: {d}/{n} work items", file=sys.stderr, flush=True)

            t0 = time.perf_counter()
            res = run_sweep(truth, devs, range(args.sweep_seeds), ex, progress=prog)
            wall = time.perf_counter() - t0
        s = res["summary"]
        print(f"\nsweep: {len(devs)} deviations x {args.sweep_seeds} seeds = {res['fits']} step-3 identifications "
              f"(full pipeline) on {ex.describe()}: {wall:.1f} s wall, {wall / res['fits'] * 1000:.0f} ms per "
              f"identification, {100 * s['converged_fraction']:.1f} % converged")


if __name__ == "__main__":
    main()
