"""``otbot track``: computed-torque tracking of a scenario or a CSV trajectory (simulated robot)."""
from __future__ import annotations

import argparse
from pathlib import Path

from otbot_hw.cli import CliError, add_json_flag, progress
from otbot_hw.cli.checks import output_file, output_folder, rate

_TIMES = "Settle times: seconds until the position and velocity errors stay below 2 % of the event's peak"


def register(sub) -> None:
    p = sub.add_parser(
        "track",
        help="track a trajectory with the computed-torque controller (closed loop, simulated robot)",
        description="Closed-loop tracking with the computed-torque law u = M_bar (p_dd_d - K_p e_p - K_v e_v) "
                    "+ C_bar p_dot on the simulated robot. SCENARIO is corridor, corridor-smooth, figure8, "
                    "planned or a trajectory CSV (columns t [s], x, y [m], alpha [rad], optional x_dot, y_dot "
                    "[m/s], alpha_dot [rad/s], tau_r, tau_l, tau_p [N m]). Errors are reported in m, rad, "
                    "m/s, rad/s; torques in N m against the limits of config/robot.yaml. " + _TIMES + ".",
    )
    p.add_argument("scenario", help="corridor | corridor-smooth | figure8 | planned | FILE.csv")
    p.add_argument("--sim", action="store_true", help="run against the simulated robot (required: the only "
                   "plant available to this command)")
    p.add_argument("--params", type=Path, default=None,
                   help="parameter YAML for plant and controller (default config/otbot.yaml; an identified file "
                        "works; a diagnosed model from otbot diagnose --out adds its 'effects', which the controller "
                        "compensates by feedforward: friction, slope, drag, torque-gain errors)")
    p.add_argument("--plant-params", type=Path, default=None,
                   help="parameter YAML of the simulated robot when it differs from the controller's --params "
                        "(e.g. --params identified.yaml --plant-params config/otbot.yaml); may hold 'effects' "
                        "(missing physics the simulated robot has)")
    p.add_argument("--robot", type=Path, default=None, help="hardware YAML with motor limits (default config/robot.yaml)")
    p.add_argument("--tstab", default="3", help="stabilization time T_stab in s, one value or x,y,alpha (default 3)")
    p.add_argument("--rate", type=rate, default=1000.0, help="control rate in Hz (default 1000)")
    p.add_argument("--error-bounds", default=None, metavar="EX,EY,EA,EVX,EVY,EVA",
                   help="feasibility-check error bounds: |e_p| in m, m, rad and |e_v| in m/s, m/s, rad/s "
                        "(default 0.02,0.02,0.01,0.05,0.05,0.02)")
    p.add_argument("--strict", action="store_true",
                   help="refuse (exit 2) a trajectory whose torque bound can exceed a motor limit")
    p.add_argument("--no-robustness", action="store_true",
                   help="skip the robustness reruns (platform params 20 %% off, unmodelled friction)")
    p.add_argument("--plot", type=Path, default=None, metavar="DIR", help="write PNG plots into DIR")
    p.add_argument("--animate", type=Path, default=None, metavar="OUT.gif", help="write a GIF animation")
    add_json_flag(p)
    p.set_defaults(func=run)


def parse_tstab(text: str):
    from otbot_hw.cli import parse_vector

    parts = text.split(",")
    vals = parse_vector(text, len(parts), "--tstab")
    if len(vals) not in (1, 3) or any(v <= 0 for v in vals):
        raise CliError(f"--tstab needs 1 or 3 numbers of seconds > 0 (x, y, alpha), got {text!r}")
    return vals[0] if len(vals) == 1 else vals


def run(args: argparse.Namespace) -> dict:
    from otbot_hw.cli import parse_vector
    from otbot_hw.control.feasibility import ErrorBounds, check_feasibility
    from otbot_hw.control.gains import gains_from_tstab
    from otbot_hw.control.scenarios import SCENARIOS, build_spec, run_scenario
    from otbot_hw.control.trajectories import TrajectoryError
    from otbot_hw.motors import load_motor_limits
    from otbot_hw.model.effects import ExtendedModel

    if not args.sim:
        raise CliError("only the simulated robot is available: add --sim")
    if args.scenario not in SCENARIOS and not Path(args.scenario).exists():
        raise CliError(f"unknown scenario {args.scenario!r}: use {', '.join(SCENARIOS)} or an existing CSV file")
    output_file(args.animate, "--animate", suffix=".gif")
    output_folder(args.plot, "--plot")
    tstab = parse_tstab(args.tstab)
    model = ExtendedModel.load(args.params)
    params = model.params
    effects = model.eff if model.active_effects() else None
    plant = ExtendedModel.load(args.plant_params) if args.plant_params is not None else (
        model if effects is not None else None)
    limits = load_motor_limits(args.robot)
    eb = None
    if args.error_bounds is not None:
        v = parse_vector(args.error_bounds, 6, "--error-bounds")
        if any(x < 0 for x in v):
            raise CliError("--error-bounds must be >= 0")
        eb = ErrorBounds(tuple(v[:3]), tuple(v[3:]))
    say = (lambda m: progress(f"[track] {m}"))
    try:
        spec = build_spec(args.scenario, params, limits, say)
        if args.strict:
            rep = check_feasibility(spec.reference, params, gains_from_tstab(tstab), limits, eb)
            if args.strict and not rep.feasible:
                v = rep.violations[0]
                raise CliError(f"infeasible trajectory: {v['motor']} torque bound {v['bound_Nm']:.1f} N m exceeds "
                               f"the {v['limit_Nm']:g} N m limit from t = {v['t_start']:.2f} s to {v['t_end']:.2f} s "
                               f"({len(rep.violations)} violation(s))")
        result = run_scenario(args.scenario, params, limits, t_stab=tstab, rate_hz=args.rate,
                              robustness=not args.no_robustness, plot_dir=args.plot, animate=args.animate,
                              progress=say, error_bounds=eb, spec=spec, plant=plant, effects=effects)
        if effects is not None:
            result["compensated_effects"] = model.active_effects()
    except TrajectoryError as exc:
        raise CliError(str(exc)) from None
    if not args.json:
        _print_human(result)
    return result


def _print_human(r: dict) -> None:
    print(f"scenario {r['scenario']}: {r['duration_s']:.1f} s at {r['rate_hz']:g} Hz")
    for key in ("max_abs_error", "rms_error"):
        e = r[key]
        print(f"  {key}: x {e['x'] * 1e3:.3f} mm, y {e['y'] * 1e3:.3f} mm, alpha {e['alpha']:.2e} rad; "
              f"x_dot {e['x_dot'] * 1e3:.2f} mm/s, y_dot {e['y_dot'] * 1e3:.2f} mm/s")
    for m, v in r["peak_torque"].items():
        print(f"  peak torque {m}: {v['peak_Nm']:.2f} N m (limit {v['limit_Nm']:g})")
    for ev in r["events"]:
        s = ev["settle_time_s"]
        print(f"  event t = {ev['t']:g} s {ev['kind']}: settle " + ("not within window" if s is None else f"{s:.3f} s"))
    if r.get("saturation"):
        print(f"  saturation episodes: {len(r['saturation'])}")
    if "feasibility" in r:
        print(f"  feasibility: {'ok' if r['feasibility']['feasible'] else 'limits can be exceeded'}")
    for k in ("open_loop",):
        if k in r:
            print(f"  open loop (planned torques replayed): final position error "
                  f"{r[k]['final_position_error_m']:.3f} m" + (f", {len(r[k]['collisions'])} collision(s)"
                                                              if "collisions" in r else ""))
    if "collisions" in r:
        print(f"  closed loop collisions: {len(r['collisions'])}")
    for v, s in r.get("robustness", {}).items():
        e = s["max_abs_error"]
        print(f"  robustness {v}: max |e| x {e['x'] * 1e3:.2f} mm, y {e['y'] * 1e3:.2f} mm, alpha {e['alpha']:.2e} rad")
    for p in r.get("plots", []):
        print(f"  plot: {p}")
