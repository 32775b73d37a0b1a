"""``otbot diagnose``: find the physics a model leaves out, from recordings.

Compares recordings with the identified model, locates where they part ways, names
the missing effect from the catalog (``otbot_hw.diagnose.catalog``), re-identifies the
model with it and shows the fit before/after. ``--demo`` runs the whole thing on
simulated recordings with a hidden effect (Coulomb friction at the wheel motors by
default, ``--demo-effect`` to choose another catalog effect or ``none``).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from otbot_hw.cli import CliError, add_json_flag, progress
from otbot_hw.cli.checks import default_input, distinct_files, output_file, output_folder


def register(sub) -> None:
    p = sub.add_parser(
        "diagnose",
        help="find the physics the model leaves out (locate, name, refit, before/after)",
        description=(
            "Diagnose recordings (MCAP, docs/recording-format.md) against the identified model: refit the "
            "nominal parameters, flag the time windows and channels where simulation and recording part ways "
            "(simulation residuals of encoder rates w_* in rad/s, IMU a_x, a_y in m/s^2 and g_z in rad/s; "
            "inverse-dynamics torque residuals in N m), choose missing effects from the catalog by BIC and "
            "held-out prediction, refit them with the nominal parameters (values with one-sigma std, SI units) "
            "and report the fit before/after. Only commands, encoders and IMU are used; /otbot/truth is ignored. "
            "Exit 1 when the model is inadequate (no catalog effect brings it to the noise level, an estimate on its "
            "bound or an implausible refit): no finding is named, the suspect parameters are listed. What the "
            "recording cannot determine (an effect whose signature at the catalog's smallest size is below the "
            "evidence it would need; a parameter on its bound whose std says the data do not determine it) is "
            "reported as 'not identifiable from this recording' with what to record instead (exit 0; JSON "
            "not_identifiable, identifiability)."),
    )
    p.add_argument("recordings", nargs="*", type=Path, metavar="RECORDING", help="fitting recordings (.mcap)")
    p.add_argument("--params", type=Path, default=None,
                   help="identified parameter file (default config/otbot.yaml)")
    p.add_argument("--robot", type=Path, default=None, metavar="ROBOT.yaml",
                   help="hardware configuration with the effect geometry (default config/robot.yaml): 'casters' "
                        "(contact points in the chassis frame B', m) and 'imu.mounting.position' (B'', m); where "
                        "absent, the diagnosis fits the positions")
    p.add_argument("--holdout", nargs="+", type=Path, default=[], metavar="RECORDING",
                   help="held-out recordings: used only to judge prediction")
    p.add_argument("--report", type=Path, default=None, metavar="DIR",
                   help="write residual plots (PNG) and diagnosis.json into DIR")
    p.add_argument("--out", type=Path, default=None, metavar="MODEL.yaml",
                   help="write the diagnosed model: refit nominal parameters and accepted effects, each with its "
                        "one-sigma std (SI units), as a parameter YAML with an 'effects' section that otbot simulate "
                        "and otbot track load with --params / --plant-params")
    p.add_argument("--each", action="store_true",
                   help="diagnose every RECORDING on its own, in parallel (a fleet's runs): local worker "
                        "processes, or a Dask cluster with --scheduler; JSON: {runs: [one diagnosis each]}")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="with --each: local worker processes (default one per CPU; 1 = in this process)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="with --each: Dask distributed scheduler (e.g. tcp://10.0.0.5:8786) whose workers run the "
                        "diagnoses (recordings are sent to them, no shared file system needed)")
    p.add_argument("--demo", action="store_true",
                   help="simulate recordings with a hidden effect and diagnose them")
    p.add_argument("--demo-effect", default="coulomb_wheels",
                   help="catalog effect hidden in the demo ('none' for a negative control)")
    p.add_argument("--demo-dir", type=Path, default=Path("otbot-diagnose-demo"),
                   help="folder for the demo recordings (default otbot-diagnose-demo)")
    add_json_flag(p)
    p.set_defaults(func=run)


def _catalog_names() -> list[str]:
    from otbot_hw.diagnose.catalog import CATALOG

    return [e.name for e in CATALOG]


def demo_recordings(effect_name: str, out_dir: Path, seed: int = 0) -> tuple[list[Path], list[Path], dict]:
    """Write the demo's fitting and held-out recordings; returns their paths and the hidden truth."""
    from otbot_hw.diagnose.catalog import effect
    from otbot_hw.params import nominal
    from otbot_hw.recording import write_recording
    from otbot_hw.simulation.concealed import concealed_recording

    values = {} if effect_name == "none" else dict(effect(effect_name).magnitudes[0])
    params = nominal()
    out_dir.mkdir(parents=True, exist_ok=True)
    fit_kinds = ["multisine", "stand"] if effect_name in ("coulomb_wheels", "stribeck_wheels") else ["multisine"]
    fitting, held = [], []
    for i, kind in enumerate(fit_kinds):
        path = out_dir / f"fit_{i}_{kind}.mcap"
        write_recording(path, concealed_recording(params, values, kind, duration=10.0 if kind != "stand" else 4.0,
                                                  seed=seed + i, effect_name=effect_name))
        fitting.append(path)
    path = out_dir / "heldout_tracking.mcap"
    write_recording(path, concealed_recording(params, values, "tracking", duration=10.0, seed=seed + 50,
                                              effect_name=effect_name))
    held.append(path)
    return fitting, held, {"effect": effect_name, "parameters": values}


def run(args: argparse.Namespace) -> dict:
    from otbot_hw.diagnose.data import load
    from otbot_hw.diagnose.diagnosis import diagnose
    from otbot_hw.diagnose.geometry import load_geometry
    from otbot_hw.model.well_posed import load_params
    from otbot_hw.params import nominal

    quiet = args.json
    say = (lambda m: progress(m, True))
    truth = None
    output_folder(args.report, "--report")
    if args.demo:
        output_folder(args.demo_dir, "--demo-dir")
    if args.demo:
        if args.recordings:
            raise CliError("--demo simulates its own recordings; give no RECORDING")
        if args.demo_effect not in _catalog_names() + ["none"]:
            raise CliError(f"--demo-effect {args.demo_effect!r} is not in the catalog "
                           f"(known: {', '.join(_catalog_names())}, none)")
        say(f"[diagnose] demo: simulating recordings with hidden effect '{args.demo_effect}'")
        fitting, held, truth = demo_recordings(args.demo_effect, args.demo_dir)
    else:
        if not args.recordings:
            raise CliError("give at least one RECORDING (or --demo)")
        fitting, held = args.recordings, args.holdout
    overlap = {str(p) for p in fitting} & {str(p) for p in held}
    if overlap:
        raise CliError(f"recording(s) both fitting and held-out: {sorted(overlap)}")
    if not args.demo:
        distinct_files(list(fitting) + list(held), "recording")
    params = load_params(args.params) if args.params else nominal()
    geometry = load_geometry(args.robot)
    if args.out is not None:
        if args.each:
            raise CliError("--out writes one model; it does not apply with --each")
        output_file(args.out, "--out", inputs={"recording": list(fitting) + list(held), "parameter file":
                                               default_input(args.params, "otbot.yaml"),
                                               "hardware configuration": default_input(args.robot, "robot.yaml")})
    if not args.each and (args.workers is not None or args.scheduler):
        raise CliError("--workers and --scheduler apply only with --each")
    if args.each:
        from otbot_hw.diagnose.fleet import diagnose_each
        from otbot_hw.identification.executors import make_executor

        if args.workers is not None and args.workers < 1:
            raise CliError(f"--workers must be >= 1, got {args.workers}")
        if args.scheduler and args.workers is not None:
            raise CliError("give --scheduler or --workers, not both (a Dask cluster has its own workers)")
        try:
            ex = make_executor(args.scheduler, args.workers)
        except (ConnectionError, OSError, ValueError) as exc:
            raise CliError(f"--scheduler: {exc}") from None
        with ex:
            runs = diagnose_each(list(fitting), params, list(held), executor=ex, progress=say, geometry=geometry)
        if not quiet:
            for r in runs:
                print(f"{r['recording']}: {r.get('verdict', 'error: ' + str(r.get('error')))}")
        inadequate = [r["recording"] for r in runs if r.get("model_adequate") is False]
        if inadequate:
            if quiet:
                print(json.dumps({"runs": runs}, allow_nan=False))
            print("otbot diagnose: model inadequate for " + ", ".join(inadequate), file=sys.stderr)
            raise SystemExit(1)
        return {"runs": runs}
    recs = load(fitting)
    hold = load(held)
    for d in recs + hold:
        for ch, why in d.unusable.items():
            say(f"[diagnose] {d.name}: channel {ch} not used: {why}")
    for d in recs + hold:
        if d.truncated:
            say(f"[diagnose] {d.name}: cut short; diagnosed on its {len(d)} complete samples")
    result = diagnose(recs, params, hold, report_dir=args.report, progress=say, model_out=args.out, geometry=geometry)
    if truth is not None:
        result["demo_truth"] = truth
    if args.report:
        args.report.mkdir(parents=True, exist_ok=True)
        (args.report / "diagnosis.json").write_text(json.dumps(result, indent=1, allow_nan=False))
    if not quiet:
        _print_summary(result)
    if not result["model_adequate"]:
        if quiet:
            print(json.dumps(result, allow_nan=False))
        print("otbot diagnose: model inadequate: suspect " + ", ".join(result["suspect_parameters"]) +
              ("" if args.out is None else f" (the model with the discovered laws: {result['model_file']})"
               if result.get("model_file") else " (no model file written)"), file=sys.stderr)
        raise SystemExit(1)
    return result


def _percent(channel: dict | None) -> str:
    """A channel's fit percentage with one decimal, "n/a" where there is none (a channel that does not move:
    the locked fixture's wheels)."""
    value = (channel or {}).get("fit_percent")
    return "n/a" if value is None else f"{value:.1f}"


def _print_summary(r: dict) -> None:
    out = sys.stdout
    print(r["verdict"], file=out)
    for key in ("fitting", "heldout"):
        b, a = r["fit_before"].get(key) or {}, r["fit_after"].get(key) or {}
        if not b:
            continue
        print(f"{key} fit %:  " + "  ".join(f"{ch} {_percent(b[ch])} -> {_percent(a.get(ch))}" for ch in b),
              file=out)
    moved = {n: v for n, v in r["nominal_shift"].items() if v["shift"] != 0}
    if r["effects"] or r["ambiguous"]:
        print("nominal parameters moved: " + ", ".join(f"{n} {v['before']:.4g} -> {v['after']:.4g} {v['unit']}"
                                                     for n, v in moved.items()), file=out)
    print(f"located windows: {len(r['located'])} ({r['located_summary']['per_channel']})", file=out)
    if r.get("model_file"):
        print(f"diagnosed model: {r['model_file']}", file=out)
    for p in r.get("plots", []):
        print(f"plot: {p}", file=out)
    if "demo_truth" in r:
        print(f"demo truth (hidden from the diagnosis): {r['demo_truth']}", file=out)
