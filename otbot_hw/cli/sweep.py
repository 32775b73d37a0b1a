"""``otbot sweep``: sensitivity of step 3 to the initial guess (paper Figs 10-11), on an executor."""
from __future__ import annotations

import argparse
from pathlib import Path

from otbot_hw.cli import CliError, add_json_flag, progress
from otbot_hw.cli.checks import count, number, output_folder


def register(sub) -> None:
    p = sub.add_parser(
        "sweep",
        help="step-3 identification error vs initial-guess deviation, over noise seeds",
        description="For each noise seed, simulate the platform experiment (tau = 6, -10, 6 N m, 1 s) and "
                    "identify m_p (kg), I_p (kg m^2), x_F, y_F (m) from initial guesses deviating by up to "
                    "--max-deviation percent: at PCT percent the guess adds a load of PCT percent of 500 kg, "
                    "PCT percent of 0.45 m away from the true centre of mass. By default every fit starts from "
                    "that guess alone (the paper's method), so the sweep measures how the guess affects the "
                    "result. With --global-start each fit first tries the equation-error estimate, which does "
                    "not depend on the guess; the guess is then only a fallback, and the report counts how many "
                    "fits used it. Runs on local processes, or on a Dask cluster with --scheduler; Ctrl-C ends "
                    "the workers and exits 130.",
    )
    p.add_argument("--max-deviation", type=number(above=0, maximum=1000), default=100.0, metavar="PCT",
                   help="largest deviation in percent, in (0, 1000] (default 100)")
    p.add_argument("--points", type=count(1), default=40, metavar="N", help="number of deviations (default 40)")
    p.add_argument("--seeds", type=count(1), default=20, metavar="N", help="number of noise seeds (default 20)")
    p.add_argument("--load", default=None, metavar="KG@X,Y[,I]",
                   help="true load on the simulated platform: KG kg at (X, Y) m (own inertia I kg m^2)")
    p.add_argument("--params", type=Path, default=None, help="robot parameters (YAML; default config/otbot.yaml)")
    start = p.add_mutually_exclusive_group()
    start.add_argument("--local-only", action="store_true",
                       help="a single fit from each guess (the paper's method; the default)")
    start.add_argument("--global-start", action="store_true",
                       help="the full identify pipeline: equation-error start first, the guess only as fallback")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="Dask distributed scheduler (e.g. tcp://10.0.0.5:8786); default: local processes")
    p.add_argument("--workers", type=count(1), default=None, metavar="N",
                   help="local worker processes (default: CPU count; 1 = in this process)")
    p.add_argument("--plot", type=Path, default=None, metavar="DIR",
                   help="write the sensitivity plots into DIR (created if missing; its parent must exist)")
    add_json_flag(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> dict:
    from otbot_hw.cli.identify import parse_load
    from otbot_hw.identification.executors import make_executor
    from otbot_hw.identification.sweep import deviation_grid, plot_sweep, run_sweep
    from otbot_hw.model.well_posed import check_well_posed, load_params
    from otbot_hw.params import ParameterError

    if args.scheduler and args.workers is not None:
        raise CliError("give --scheduler or --workers, not both (a Dask cluster has its own workers)")
    output_folder(args.plot, "--plot")
    base = load_params(args.params)
    load = parse_load(args.load)
    try:
        truth = check_well_posed(base.with_load(*load), "the loaded robot") if load else base
    except ParameterError as exc:
        raise CliError(f"--load: {exc}") from None
    quiet = args.json
    try:
        ex = make_executor(args.scheduler, args.workers)
    except (ConnectionError, OSError, ValueError) as exc:
        raise CliError(f"--scheduler: {exc}") from None
    devs = deviation_grid(args.max_deviation / 100.0, args.points)
    mode = "equation-error start, guess as fallback" if args.global_start else "single fit from each guess"
    with ex:
        progress(f"[sweep] {args.points} deviations x {args.seeds} seeds ({mode}) on {ex.describe()}", True)

        def report(done: int, total: int) -> None:
            if done == total or done % max(1, total // 10) == 0:
                progress(f"[sweep] {done}/{total} work items done", True)

        res = run_sweep(truth, devs, range(args.seeds), ex, base=base, global_start=args.global_start,
                        progress=report)
    if args.plot:
        res["plots"] = plot_sweep(args.plot, res)
    if not quiet:
        s = res["summary"]
        print(f"{res['fits']} fits ({mode}) in {res['wall_time']:.1f} s on {res['executor']}: "
              f"{100 * s['converged_fraction']:.1f} % converged")
        starts = s["accepted_start"]
        if args.global_start:
            print(f"  accepted start: " + ", ".join(f"{k} {v}" for k, v in starts.items())
                  + " (only fits accepted from 'guess' depend on the deviation)")
        for n, v in s["parameters"].items():
            spread = v["spread_over_deviations"]
            print(f"  {n}: max |error| {v['max_abs_error']:.3g} {v['unit']}, "
                  f"{100 * (v['within_3_sigma'] or 0):.1f} % within 3 sigma, estimates differ by up to "
                  + (f"{spread:.3g} {v['unit']}" if spread is not None else "-") + " between deviations")
        for p in res.get("plots", []):
            print(f"plot: {p}")
    return res
