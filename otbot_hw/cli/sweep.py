"""``otbot sweep``: sensitivity of step 3 to the initial guess (paper Figs 10-11), on an executor."""
from __future__ import annotations

import argparse
from pathlib import Path

from otbot_hw.cli import CliError, add_json_flag, progress


def register(sub) -> None:
    p = sub.add_parser(
        "sweep",
        help="step-3 identification error vs initial-guess deviation, over noise seeds",
        description="For each noise seed, simulate the platform experiment (tau = 6, -10, 6 N m, 1 s) and "
                    "identify m_p (kg), I_p (kg m^2), x_F, y_F (m) from guesses deviating by up to "
                    "--max-deviation percent (a load of PCT %% of 500 kg guessed PCT %% of 0.45 m off). "
                    "Runs on local processes, or on a Dask cluster with --scheduler.",
    )
    p.add_argument("--max-deviation", type=float, default=100.0, metavar="PCT",
                   help="largest deviation in percent (default 100)")
    p.add_argument("--points", type=int, default=40, help="number of deviations (default 40)")
    p.add_argument("--seeds", type=int, default=20, help="number of noise seeds (default 20)")
    p.add_argument("--load", default=None, metavar="KG@X,Y[,I]",
                   help="true load on the simulated platform: KG kg at (X, Y) m (own inertia I kg m^2)")
    p.add_argument("--params", type=Path, default=None, help="robot parameters (YAML; default config/otbot.yaml)")
    p.add_argument("--local-only", action="store_true", help="single fit from each guess (the paper's method)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="Dask distributed scheduler (e.g. tcp://10.0.0.5:8786); default: local processes")
    p.add_argument("--workers", type=int, default=None, help="local worker processes (default: CPU count)")
    p.add_argument("--plot", type=Path, default=None, metavar="DIR", help="write the sensitivity plots into DIR")
    add_json_flag(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> dict:
    from otbot_hw.cli.identify import parse_load
    from otbot_hw.identification.executors import make_executor
    from otbot_hw.identification.sweep import deviation_grid, plot_sweep, run_sweep
    from otbot_hw.params import OtbotParams, ParameterError

    if not (0 < args.max_deviation <= 1000):
        raise CliError(f"--max-deviation must be in (0, 1000] percent, got {args.max_deviation}")
    if args.points < 1 or args.seeds < 1:
        raise CliError("--points and --seeds must be >= 1")
    if args.workers is not None and args.workers < 1:
        raise CliError(f"--workers must be >= 1, got {args.workers}")
    base = OtbotParams.load(args.params)
    load = parse_load(args.load)
    try:
        truth = base.with_load(*load) if load else base
    except ParameterError as exc:
        raise CliError(f"--load: {exc}") from None
    quiet = args.json
    try:
        ex = make_executor(args.scheduler, args.workers)
    except (ConnectionError, OSError, ValueError) as exc:
        raise CliError(f"--scheduler: {exc}") from None
    devs = deviation_grid(args.max_deviation / 100.0, args.points)
    with ex:
        progress(f"[sweep] {args.points} deviations x {args.seeds} seeds on {ex.describe()}", True)

        def report(done: int, total: int) -> None:
            if done == total or done % max(1, total // 10) == 0:
                progress(f"[sweep] {done}/{total} work items done", True)

        res = run_sweep(truth, devs, range(args.seeds), ex, base=base, global_start=not args.local_only,
                        progress=report)
    if args.plot:
        res["plots"] = plot_sweep(args.plot, res)
    if not quiet:
        s = res["summary"]
        print(f"{res['fits']} fits in {res['wall_time']:.1f} s on {res['executor']}: "
              f"{100 * s['converged_fraction']:.1f} % converged")
        for n, v in s["parameters"].items():
            print(f"  {n}: max |error| {v['max_abs_error']:.3g} {v['unit']}, "
                  f"{100 * (v['within_3_sigma'] or 0):.1f} % within 3 sigma")
        for p in res.get("plots", []):
            print(f"plot: {p}")
    return res
