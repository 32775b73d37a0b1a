"""``otbot plan``: plan a rest-to-rest trajectory around circular obstacles (CasADi + IPOPT)."""
from __future__ import annotations

import argparse
from pathlib import Path

from otbot_hw.cli import CliError, add_json_flag, parse_vector, progress
from otbot_hw.cli.checks import count, default_input, duration, non_negative, number, output_file, writing


def register(sub) -> None:
    p = sub.add_parser(
        "plan",
        help="plan a collision-free rest-to-rest trajectory (direct collocation, torque limits)",
        description="Direct-collocation planner on the full dynamic model: rest-to-rest from --start to --goal "
                    "(x, y in m, alpha in rad), circular obstacles kept clear of the platform footprint "
                    "(radius from the parameter file) plus --clearance (m), torques within --torque-margin times "
                    "the motor limits (N m, config/robot.yaml), pivot speed <= --max-speed (m/s). Minimum time "
                    "unless --duration (s) is given. Without --obstacle the crowded corridor's obstacles are used, "
                    "without --walls its walls (y = -1.6 and 1.6 m). Writes a trajectory CSV (t, x, y, alpha, x_dot, y_dot, alpha_dot, tau_r, tau_l, tau_p) "
                    "for `otbot track FILE.csv --sim`.",
    )
    p.add_argument("--out", type=Path, required=True, metavar="TRAJ.csv",
                   help="trajectory CSV to write (its folder must exist; checked before planning)")
    p.add_argument("--start", default=None, help="x,y,alpha (m, m, rad); default 0,0,0")
    p.add_argument("--goal", default=None, help="x,y,alpha (m, m, rad); default 8,0,0")
    p.add_argument("--obstacle", action="append", default=None, metavar="CX,CY,R",
                   help="circular obstacle, centre and radius in m (repeatable; default: the crowded corridor)")
    p.add_argument("--walls", default=None, metavar="YMIN,YMAX",
                   help="corridor walls in m bounding the footprint, e.g. --walls=-1.6,1.6 (the default, crowded corridor)")
    p.add_argument("--clearance", type=non_negative, default=0.05,
                   help="extra clearance from obstacles in m, >= 0 (default 0.05)")
    p.add_argument("--duration", type=duration, default=None,
                   help="fixed duration in s, within the planner's [t_min, t_max] = [1, 60] s (default: minimum time)")
    p.add_argument("--intervals", type=count(4, 400), default=60, help="collocation intervals, 4..400 (default 60)")
    p.add_argument("--max-speed", type=number(above=0), default=1.0, help="largest pivot speed, m/s (default 1)")
    p.add_argument("--torque-margin", type=number(above=0, maximum=1), default=0.8,
                   help="fraction of the motor limits the plan may use (default 0.8, room for feedback)")
    p.add_argument("--params", type=Path, default=None, help="parameter YAML (default config/otbot.yaml)")
    p.add_argument("--robot", type=Path, default=None, help="hardware YAML with motor limits")
    add_json_flag(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> dict:
    from otbot_hw.control.planner import PlannerError, PlanningProblem, crowded_corridor_problem, plan
    from otbot_hw.motors import load_motor_limits
    from otbot_hw.model.well_posed import load_params

    output_file(args.out, "--out", inputs={"parameter file": default_input(args.params, "otbot.yaml"),
                                           "hardware configuration": default_input(args.robot, "robot.yaml")})
    params = load_params(args.params)
    limits = load_motor_limits(args.robot)
    base = crowded_corridor_problem(params, limits, args.intervals)
    start = tuple(parse_vector(args.start, 3, "--start")) if args.start else base.start
    goal = tuple(parse_vector(args.goal, 3, "--goal")) if args.goal else base.goal
    obstacles = base.obstacles if args.obstacle is None else [tuple(parse_vector(o, 3, "--obstacle"))
                                                              for o in args.obstacle]
    if any(o[2] <= 0 for o in obstacles):
        raise CliError("--obstacle radius must be > 0 m")
    walls = base.walls if args.walls is None else tuple(parse_vector(args.walls, 2, "--walls"))
    if walls is not None and walls[1] - walls[0] <= 2 * params.radius:
        raise CliError(f"--walls {walls} leave no room for the {2 * params.radius:g} m wide footprint")
    try:
        prob = PlanningProblem(params, limits, start, goal, obstacles, walls, clearance=args.clearance,
                               duration=args.duration, intervals=args.intervals, torque_margin=args.torque_margin,
                               max_speed=args.max_speed)
        res = plan(prob, progress=lambda m: progress(f"[plan] {m}", not args.json))
    except PlannerError as exc:
        default = [] if args.obstacle is not None else ["the crowded corridor's obstacles (no --obstacle given)"]
        default += [] if args.walls is not None else ["its walls (no --walls given)"]
        raise CliError(f"{exc}" + (f" [planned with {' and '.join(default)}]" if default else "")) from None
    with writing("--out"):
        res.save_csv(args.out)
    out = {"out": str(args.out), **res.summary()}
    if not args.json:
        print(f"planned {out['duration_s']:.2f} s ({out['status']}, {out['iterations']} iterations, "
              f"{out['solve_time_s']:.2f} s); min clearance {out['min_clearance_m'] * 1e3:.0f} mm; wrote {args.out}")
    return out
