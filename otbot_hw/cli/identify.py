"""``otbot identify``: one step of the paper's three-step grey-box identification (§4)."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from otbot_hw.cli import CliError, add_json_flag, parse_vector, progress
from otbot_hw.cli.checks import (complete_samples, default_input, distinct_files, number, output_file,
                                 output_folder, seed, truncation_notice, writing)  # noqa: F401  (truncation_notice: re-exported)

STEP_HELP = ("wheel: I_a, b_w (robot on a stand, right wheel driven); pivot: I_p0, b_p (wheels locked, "
             "platform driven); chassis: m_c, I_c, x_B, y_B (unloaded robot on the floor); platform: "
             "m_p, I_p, x_F, y_F (loaded robot on the floor, steps 1-2 known)")


def register(sub) -> None:
    p = sub.add_parser(
        "identify",
        help="identify dynamic parameters (one step of the paper's three) from a recording or a simulation",
        description="Prediction-error identification of Otbot's parameters (paper §4). Units: kg, m, "
                    "kg m^2, N m s/rad. Reports each estimate with its standard deviation, the correlation "
                    "matrix and the fit percent per channel; with --sim also the truth, the error and the "
                    "error in sigmas. Steps: " + STEP_HELP + ". Exit code 1 when the fit does not converge "
                    "(nothing is written), 2 on bad input.",
    )
    p.add_argument("step", choices=["wheel", "pivot", "chassis", "platform"], help="identification step")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--recording", type=Path, nargs="+", action="extend", metavar="FILE",
                     help="MCAP recording(s) of the step's experiment, fitted together: --recording a.mcap "
                          "b.mcap or --recording a.mcap --recording b.mcap; a truncated file is used up to its "
                          "last complete sample, with a notice")
    src.add_argument("--sim", action="store_true",
                     help="simulate the paper's experiment for the step (noise at the paper's levels)")
    p.add_argument("--seed", type=seed, default=0, help="noise seed of the simulation, an integer >= 0 (default 0)")
    p.add_argument("--load", default=None, metavar="KG@X,Y[,I]",
                   help="with --sim: a load of KG kg at (X, Y) m in the platform frame (own inertia I kg m^2)")
    p.add_argument("--guess", action="append", default=[], metavar="NAME=VALUE",
                   help="initial guess of a parameter (paper symbol, SI units); repeatable. The fit starts from "
                        "it; without --local-only the equation-error and spread starts follow if that fit does "
                        "not converge")
    p.add_argument("--deviation", type=number(minimum=0, maximum=1000), default=None, metavar="PCT",
                   help="initial guess PCT %% away from the truth (--sim) or from --params: step 3 guesses a "
                        "load of PCT %% of 500 kg at PCT %% of 0.45 m; other steps scale by (1 - PCT/100)")
    p.add_argument("--params", type=Path, default=None,
                   help="known parameters (YAML; default config/otbot.yaml), the robot simulated by --sim")
    p.add_argument("--local-only", action="store_true",
                   help="a single fit from the guess (the paper's method); default also tries the "
                        "equation-error start (before the guess unless --guess/--deviation is given) and "
                        "spread starts")
    p.add_argument("--plot", type=Path, default=None, metavar="DIR",
                   help="write fitting plots (PNG) into DIR (created if missing; its parent must exist)")
    p.add_argument("--out", type=Path, default=None, metavar="PARAMS.YAML",
                   help="write the full parameter set with the identified values and their std (its folder "
                        "must exist)")
    add_json_flag(p)
    p.set_defaults(func=run)


def parse_load(text: str | None, option: str = "--load"):
    """'KG@X,Y[,I]' -> (mass, x, y, inertia) or None (``otbot_hw.params.parse_load``); errors name ``option``."""
    from otbot_hw.params import parse_load as parse

    if not text:
        return None
    try:
        return parse(text)
    except ValueError as exc:
        raise CliError(f"{option} {exc}") from None


def parse_guesses(items: list[str], step: str) -> dict[str, float]:
    from otbot_hw.identification.experiments import PAPER_EXPERIMENTS

    spec = PAPER_EXPERIMENTS[step]
    by_symbol = {spec.symbol(n): n for n in spec.free}
    out = {}
    for it in items:
        if "=" not in it:
            raise CliError(f"--guess must be NAME=VALUE, got {it!r}")
        name, val = it.split("=", 1)
        name = name.strip()
        if name not in by_symbol:
            raise CliError(f"--guess {name}: step {step} estimates {', '.join(by_symbol)}")
        out[by_symbol[name]] = parse_vector(val, 1, f"--guess {name}")[0]
    return out


def run(args: argparse.Namespace) -> dict:
    from otbot_hw.identification.experiments import deviation_guess, simulate_experiment
    from otbot_hw.identification.model import OtbotModel
    from otbot_hw.identification.prediction_error import cramer_rao_std
    from otbot_hw.identification.report import plot_fit, step_table, step_to_dict
    from otbot_hw.identification.steps import check_fixtures, check_guess, identify_step
    from otbot_hw.model.well_posed import check_well_posed, load_params
    from otbot_hw.params import ParameterError
    from otbot_hw.recording import read_recording

    quiet = args.json
    output_file(args.out, "--out", inputs={"recording": args.recording,
                                           "parameter file": default_input(args.params, "otbot.yaml")})
    output_folder(args.plot, "--plot")
    base = load_params(args.params)
    guess = parse_guesses(args.guess, args.step)
    check_guess(args.step, guess, base)
    load = parse_load(args.load)
    if load and not args.sim:
        raise CliError("--load places a load on the simulated robot: use it with --sim")
    truth = None
    if args.sim:
        try:
            truth = check_well_posed(base.with_load(*load), "the loaded robot") if load else base
        except ParameterError as exc:
            raise CliError(f"--load: {exc}") from None
    if args.deviation is not None:
        dev = deviation_guess(args.step, truth or base, args.deviation / 100.0)
        guess = {**dev, **guess}
        check_guess(args.step, guess, base)
    truncated = []
    if args.sim:
        progress(f"[identify] simulating the {args.step} experiment (seed {args.seed})", not quiet)
        recs = [simulate_experiment(args.step, truth, seed=args.seed)]
    else:
        distinct_files(args.recording, "--recording")
        recs = [read_recording(p) for p in args.recording]
        check_fixtures(args.step, recs, [str(p) for p in args.recording])
        for path, rec in zip(args.recording, recs):
            if complete_samples(path, rec, "identify", "fit", "fitting"):
                truncated.append(str(path))
    progress(f"[identify] fitting step {args.step}", not quiet)
    res = identify_step(args.step, recs, base, guess=guess or None, global_start=not args.local_only,
                        truth=truth, guess_first=bool(guess))
    crb = None
    true_params = truth or next((e.truth_params for e in res.experiments if e.truth_params is not None), None)
    if true_params is not None:
        crb = cramer_rao_std(OtbotModel(), res.experiments, res.fit.names, true_params)
    out = step_to_dict(res, crb)
    out["source"] = "simulation" if args.sim else [str(p) for p in args.recording]
    out["truncated_recordings"] = truncated
    with writing("output"):
        if args.plot:
            out["plots"] = plot_fit(args.plot, res)
        if res.converged and args.out:
            res.params.save(args.out, header=f"Identified by `otbot identify {args.step}` (step {args.step}); "
                                             "std = one standard deviation from the Jacobian")
            out["params_file"] = str(args.out)
    if not quiet:
        print(step_table(res, crb))
        if res.converged and not args.local_only:
            print(f"accepted start: {res.attempts[-1]['start']} (tried: "
                  + ", ".join(a["start"] for a in res.attempts) + ")")
        for p in out.get("plots", []):
            print(f"plot: {p}")
        if "params_file" in out:
            print(f"parameters written to {out['params_file']}")
    if not res.converged:
        if quiet:
            print(json.dumps(out, allow_nan=False))
        print(f"otbot identify: the fit did not converge: {'; '.join(out['reasons'])}", file=sys.stderr)
        raise SystemExit(1)
    return out
