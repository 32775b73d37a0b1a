"""``otbot track``: computed-torque tracking of a scenario or a CSV trajectory through the loop runner,
on the in-process simulated robot (``--sim``), the simulated robot over CAN (``--bus sim``) or the
configured bus (``--bus config``), fed by the EKF or (simulators only) the true state."""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from otbot_hw.cli import CliError, add_json_flag, checks, progress
from otbot_hw.cli.backend_args import add_bus_options, bus_config, noise_model
from otbot_hw.cli.checks import default_input, output_file, output_folder, write_failure

_TIMES = "Settle times: seconds until the position and velocity errors stay below 2 % of the event's peak"


def register(sub) -> None:
    p = sub.add_parser(
        "track",
        help="track a trajectory with the computed-torque controller (closed loop on a simulated or real robot)",
        description="Closed-loop tracking with the computed-torque law u = M_bar (p_dd_d - K_p e_p - K_v e_v) "
                    "+ C_bar p_dot, through the loop runner (read -> estimate -> supervise -> control -> limit -> "
                    "write). SCENARIO is corridor, corridor-smooth, figure8, planned or a trajectory CSV (columns t "
                    "[s], x, y [m], alpha [rad], optional x_dot, y_dot [m/s], alpha_dot [rad/s], tau_r, tau_l, tau_p "
                    "[N m]). Back end: --sim (in-process simulated robot, no bus, lockstep), --bus sim (the simulated "
                    "robot behind the CANopen drivers on virtual CAN, lockstep) or --bus config (the configured bus: "
                    "the real robot, or an otbot plant process). Errors are reported in m, rad, m/s, rad/s (of the true "
                    "pose where the back end knows it); torques in N m against the motor limits; estimation errors "
                    "(estimate - truth) in m and rad. " + _TIMES + ". Exit 1 if a fault stops the run (drive, encoder, "
                    "IMU, estimator, or a safety limit of config/robot.yaml); the recording up to the fault is kept.",
    )
    p.add_argument("scenario", help="corridor | corridor-smooth | figure8 | planned | FILE.csv")
    p.add_argument("--sim", action="store_true", help="the in-process simulated robot (direct back end, no bus)")
    p.add_argument("--bus", choices=("sim", "config"), default=None,
                   help="sim: the simulated robot over the CANopen drivers (virtual CAN, in this process); "
                        "config: the bus of --config")
    p.add_argument("--feedback", choices=("ekf", "truth"), default="ekf",
                   help="state fed to the controller: the pose EKF on encoders and IMU (default), or the "
                        "simulator's true state (--sim and --bus sim only)")
    p.add_argument("--params", type=Path, default=None,
                   help="parameter YAML for the controller (and the simulated robot unless --plant-params; default "
                        "config/otbot.yaml; an identified file works; a diagnosed model from otbot diagnose --out adds "
                        "its 'effects', which the controller compensates by feedforward)")
    p.add_argument("--plant-params", type=Path, default=None,
                   help="the robot to simulate (--sim, --bus sim) when it differs from the controller's --params: a "
                        "parameter YAML or a diagnosed-model file with 'effects' (missing physics the simulated robot has)")
    add_bus_options(p, "default 1000 for --sim, the configuration's bus.control_rate over a bus")
    p.add_argument("--tstab", default="3", help="stabilization time T_stab in s, one value or x,y,alpha (default 3)")
    p.add_argument("--error-bounds", default=None, metavar="EX,EY,EA,EVX,EVY,EVA",
                   help="feasibility-check error bounds: |e_p| in m, m, rad and |e_v| in m/s, m/s, rad/s "
                        "(default 0.02,0.02,0.01,0.05,0.05,0.02)")
    p.add_argument("--strict", action="store_true",
                   help="refuse (exit 2) a trajectory whose torque bound can exceed a motor limit")
    p.add_argument("--no-robustness", action="store_true",
                   help="skip the robustness reruns (platform params 20 %% off, unmodelled friction)")
    p.add_argument("--fixes", type=checks.rate, default=None, metavar="HZ",
                   help="feed the EKF absolute pose fixes from a simulated motion-capture system at HZ Hz (its own "
                        "white noise, --fix-std; --sim and --bus sim with --feedback ekf)")
    p.add_argument("--fix-std", default="0.002,0.002,0.002", metavar="SX,SY,SA",
                   help="noise std of the simulated motion capture: x, y in m, alpha in rad (default 0.002,0.002,0.002)")
    p.add_argument("--slip-burst", action="append", default=None, metavar="T0:DURATION:K_SLIP",
                   help="a burst of wheel slip in the simulated robot: the extended model's k_slip (rad/(s N m)) for "
                        "DURATION s from T0 s of robot time (repeatable; --sim and --bus sim)")
    p.add_argument("--adapt", choices=("payload",), default=None,
                   help="payload: estimate the platform + load (m_p, I_p, x_F, y_F) online and let the law use it once "
                        "confident (settings and bounds: daemon.adaptation in --config); --json adds payload_estimate "
                        "and adaptation")
    p.add_argument("--out", type=Path, default=None, metavar="RUN.mcap", help="record the run (project MCAP format)")
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


def backend_name(args) -> str:
    """"sim", "bus sim" or "bus config" from --sim / --bus; CliError when none or both."""
    if args.sim and args.bus is not None:
        raise CliError("choose one back end: --sim or --bus sim|config, not both")
    if not args.sim and args.bus is None:
        raise CliError("choose a back end: --sim (in-process simulated robot), --bus sim (simulated robot over CAN) "
                       "or --bus config (the configured bus)")
    return "sim" if args.sim else f"bus {args.bus}"


def check_feedback(kind: str, feedback: str) -> None:
    """--feedback truth needs a simulator. CliError otherwise."""
    if feedback == "truth" and kind == "bus config":
        raise CliError("--feedback truth needs a back end that knows the true state (--sim or --bus sim); "
                       "the configured bus has none: use --feedback ekf")


def parse_bursts(items) -> list[tuple[float, float, float]]:
    """--slip-burst T0:DURATION:K_SLIP values as (t0 s, duration s, k_slip rad/(s N m)); CliError if malformed."""
    out = []
    for text in items or ():
        parts = text.split(":")
        try:
            t0, dur, k = (float(v) for v in parts)
        except ValueError:
            raise CliError(f"--slip-burst needs T0:DURATION:K_SLIP (s, s, rad/(s N m)), got {text!r}") from None
        if not all(map(math.isfinite, (t0, dur, k))) or t0 < 0 or dur <= 0 or not 0 < k <= 1:
            raise CliError(f"--slip-burst {text!r}: T0 >= 0 s, DURATION > 0 s and 0 < K_SLIP <= 1 rad/(s N m)")
        out.append((t0, dur, k))
    return out


def check_sizes(name: str, duration: float, rate_hz: float) -> None:
    """CliError before any work when a trajectory of ``duration`` s is too long to check or run at ``rate_hz``."""
    from otbot_hw.control.feasibility import MAX_POINTS, feasibility_points

    n = duration * rate_hz  # inf when the product overflows
    if not math.isfinite(duration) or not n - 1e-9 <= checks.MAX_SAMPLES:  # ceil(n - 1e-9) <= the limit
        raise CliError(f"trajectory {name} lasts {duration:g} s: at {rate_hz:g} Hz that is "
                       f"{checks.count_text(math.ceil(n - 1e-9) if math.isfinite(n) else n)} samples; at most "
                       f"{checks.MAX_SAMPLES} (lower --rate or shorten the trajectory)")
    pts = feasibility_points(duration)
    if pts > MAX_POINTS:
        raise CliError(f"trajectory {name} lasts {duration:g} s: its torque-feasibility check would bound {pts} "
                       f"points (every 0.01 s); at most {MAX_POINTS} ({(MAX_POINTS - 1) * 0.01:g} s)")


def make_backend(kind: str, args, quiet: bool):
    """The back end ``kind`` (a name of ``runtime.backends.BACKENDS``) configured from the command line:
    the in-process robot takes the configuration as written (its rate --rate, default 1 kHz), a bus
    back end the bus configuration with the command line's overrides."""
    from otbot_hw.runtime import backends

    if kind == "sim":  # no bus: the configuration's sensors and drives, not its bus
        from drivers.config import load_robot_config

        cfg = load_robot_config(args.config)
    else:
        cfg, _ = bus_config(args, args.rate, quiet, "track")
    return backends.make_backend(kind, cfg, backends.BackendOptions(
        rate=args.rate, noise=noise_model(args), seed=args.seed, with_imu=not args.no_imu, imu_port=args.imu_port,
        lockstep=args.lockstep))


def run(args: argparse.Namespace) -> dict:
    from otbot_hw.cli import parse_vector
    from otbot_hw.control.feasibility import ErrorBounds, check_feasibility
    from otbot_hw.control.gains import gains_from_tstab
    from otbot_hw.control.scenarios import SCENARIOS, build_spec
    from otbot_hw.control.trajectories import TrajectoryError
    from otbot_hw.model.effects import EFFECT_INDEX, ExtendedModel
    from otbot_hw.motors import load_motor_limits
    from otbot_hw.robot import RobotError
    from otbot_hw.runtime.supervisor import SafetyConfig
    from otbot_hw.runtime.tracking import run_scenario

    kind = backend_name(args)
    if args.plant_params is not None and kind == "bus config":
        raise CliError("--plant-params sets the simulated robot (--sim, --bus sim); the configured bus runs the "
                       "robot that is there")
    check_feedback(kind, args.feedback)
    fix_std = parse_vector(args.fix_std, 3, "--fix-std")
    if any(v <= 0 for v in fix_std):
        raise CliError(f"--fix-std needs 3 numbers > 0 (m, m, rad), got {args.fix_std!r}")
    bursts = parse_bursts(args.slip_burst)
    if (args.fixes is not None or bursts) and kind == "bus config":
        raise CliError("--fixes and --slip-burst act on a simulated robot (--sim, --bus sim); the configured bus "
                       "runs the robot that is there")
    if args.fixes is not None and args.feedback != "ekf":
        raise CliError("--fixes feeds the EKF: use --feedback ekf")
    if args.scenario not in SCENARIOS and not Path(args.scenario).exists():
        raise CliError(f"unknown scenario {args.scenario!r}: use {', '.join(SCENARIOS)} or an existing CSV file")
    inputs = {"trajectory": None if args.scenario in SCENARIOS else args.scenario, "parameter file":
              default_input(args.params, "otbot.yaml"), "plant parameter file": args.plant_params,
              "hardware configuration": default_input(args.config, "robot.yaml")}
    output_file(args.animate, "--animate", suffix=".gif", inputs=inputs)
    output_folder(args.plot, "--plot")
    output_file(args.out, "--out", inputs=inputs)
    tstab = parse_tstab(args.tstab)
    adapt = None
    if args.adapt == "payload":
        from otbot_hw.estimation.payload import AdaptationConfig

        adapt = AdaptationConfig.load(args.config).with_(enabled=True)
    model = ExtendedModel.load(args.params)
    params = model.params
    effects = model.eff if model.active_effects() else None
    plant = ExtendedModel.load(args.plant_params) if args.plant_params is not None else (
        model if effects is not None else None)
    limits = load_motor_limits(args.config)
    eb = None
    if args.error_bounds is not None:
        v = parse_vector(args.error_bounds, 6, "--error-bounds")
        if any(x < 0 for x in v):
            raise CliError("--error-bounds must be >= 0")
        eb = ErrorBounds(tuple(v[:3]), tuple(v[3:]))
    say = (lambda m: progress(f"[track] {m}", not args.json))
    try:
        spec = build_spec(args.scenario, params, limits, say)
        # the in-process robot's rate is known without its configuration; a bus's comes with its configuration
        backend = None if kind == "sim" else make_backend(kind, args, args.json)
        check_sizes(spec.name, spec.reference.duration, args.rate or 1000.0 if backend is None else backend.rate)
        if args.strict:
            rep = check_feasibility(spec.reference, params, gains_from_tstab(tstab), limits, eb)
            if not rep.feasible:
                v = rep.violations[0]
                raise CliError(f"infeasible trajectory: {v['motor']} torque bound {v['bound_Nm']:.1f} N m exceeds "
                               f"the {v['limit_Nm']:g} N m limit from t = {v['t_start']:.2f} s to {v['t_end']:.2f} s "
                               f"({len(rep.violations)} violation(s))")
        safety = SafetyConfig.load(args.config)
        backend = backend or make_backend(kind, args, args.json)
        fixes = None
        if args.fixes is not None:
            from sim.mocap import MotionCapture

            fixes = MotionCapture(args.fixes, fix_std, seed=10_000 + args.seed)
        if bursts:
            import numpy as np

            from otbot_hw.model.effects import effect_vector
            from sim.effect_schedule import EffectSchedule, with_schedule

            base = plant if plant is not None else model
            eff = np.array(base.eff if hasattr(base, "eff") else effect_vector(), dtype=float)
            eff[EFFECT_INDEX["k_slip"]] = max(k for _, _, k in bursts)
            plant = ExtendedModel(getattr(base, "params", base), eff)
            entries = [(0.0, {"k_slip": 0.0})]
            for t0, dur, k in sorted(bursts):
                entries += [(t0, {"k_slip": k}), (t0 + dur, {"k_slip": 0.0})]
            backend = with_schedule(backend, EffectSchedule(entries))
        meta = {"params": params.to_dict(), "command": "otbot track"}
        if plant is not None:
            meta["plant"] = plant.to_dict() if hasattr(plant, "to_dict") else None
        if backend.simulated:
            meta.update(noise=noise_model(args).to_dict(), seed=args.seed)
        result = run_scenario(args.scenario, params, limits, t_stab=tstab, robustness=not args.no_robustness,
                              plot_dir=args.plot, animate=args.animate, progress=say, error_bounds=eb, spec=spec,
                              plant=plant, effects=effects, backend=backend, feedback=args.feedback, safety=safety,
                              path=args.out, metadata=meta, config_path=args.config, fixes=fixes, adapt=adapt)
        if effects is not None:
            result["compensated_effects"] = model.active_effects()
    except TrajectoryError as exc:
        raise CliError(str(exc)) from None
    except RobotError as exc:
        _fail({"completed": False, "error": str(exc), "faults": [f.to_dict() for f in exc.faults]},
              f"error: {exc}", args.json)
    except OSError as exc:
        raise write_failure(exc, args.out or args.plot or args.animate or "output") from None
    if not result["completed"]:
        where = f"; recording up to the fault: {args.out}" if args.out else ""
        if not args.json and "max_abs_error" in result:
            _print_human(result)
        _fail(result, f"stopped by fault: {result['fault']['kind']} at t = {result['fault']['t']:.3f} s: "
                      f"{result['fault']['text']}{where}", args.json)
    if not args.json:
        _print_human(result)
    return result


def _fail(result: dict, message: str, as_json: bool):
    if as_json:
        from otbot_hw.json_output import json_safe

        print(json.dumps(json_safe(result), allow_nan=False, default=str))
    print(f"otbot track: {message}", file=sys.stderr)
    raise SystemExit(1)


def _print_human(r: dict) -> None:
    be = r.get("backend", {})
    print(f"scenario {r['scenario']}: {r['duration_s']:.1f} s at {r['rate_hz']:g} Hz on {be.get('mode', '?')}, "
          f"feedback {r.get('feedback')}")
    what = "true pose" if r.get("true_pose_known", True) else "estimated pose (no ground truth on this back end)"
    print(f"  tracking errors of the {what}:")
    for key in ("max_abs_error", "rms_error"):
        e = r[key]
        print(f"  {key}: x {e['x'] * 1e3:.3f} mm, y {e['y'] * 1e3:.3f} mm, alpha {e['alpha']:.2e} rad; "
              f"x_dot {e['x_dot'] * 1e3:.2f} mm/s, y_dot {e['y_dot'] * 1e3:.2f} mm/s")
    ee = r.get("estimation_error")
    if ee is not None:
        from otbot_hw.estimation.errors import describe_estimation_error

        print("  " + describe_estimation_error(ee))
    for m, v in r["peak_torque"].items():
        print(f"  peak torque {m}: {v['peak_Nm']:.2f} N m (limit {v['limit_Nm']:g})")
    for ev in r["events"]:
        s = ev["settle_time_s"]
        print(f"  event t = {ev['t']:g} s {ev['kind']}: settle " + ("not within window" if s is None else f"{s:.3f} s"))
    if r.get("saturation"):
        print(f"  saturation episodes: {len(r['saturation'])}")
    if r.get("payload_estimate"):
        pe, ad = r["payload_estimate"], r["adaptation"]
        print("  payload estimate (platform + load): " + ", ".join(
            f"{k} {v['value']:.3g} ± {v['std']:.2g}" for k, v in pe.items())
              + f" (kg, kg m^2, m); converged {_s(ad['converged_s'])}, law switched {_s(ad['switched_s'])}, {ad['state']}")
    if "feasibility" in r:
        print(f"  feasibility: {'ok' if r['feasibility']['feasible'] else 'limits can be exceeded'}")
    if "open_loop" in r:
        print(f"  open loop (planned torques replayed): final position error "
              f"{r['open_loop']['final_position_error_m']:.3f} m" + (f", {len(r['open_loop']['collisions'])} collision(s)"
                                                                       if "collisions" in r["open_loop"] else ""))
    if "collisions" in r:
        print(f"  closed loop collisions: {len(r['collisions'])}")
    for v, s in r.get("robustness", {}).items():
        e = s["max_abs_error"]
        print(f"  robustness {v}: max |e| x {e['x'] * 1e3:.2f} mm, y {e['y'] * 1e3:.2f} mm, alpha {e['alpha']:.2e} rad")
    lp = r.get("loop") or {}
    if lp.get("cycles") and lp.get("period_p50") is not None:
        print(f"  loop: {lp['cycles']} cycles, {lp['robot_time']:.2f} s robot time in {lp['wall_time']:.2f} s wall "
              f"({lp['realtime_factor']:.1f}x real time), period p50/p99 {lp['period_p50'] * 1e3:.3f}/"
              f"{lp['period_p99'] * 1e3:.3f} ms, {lp['overruns']} overrun(s)")
    if r.get("recording"):
        print(f"  recording: {r['recording']}")
    if r.get("fault"):
        print(f"  FAULT: {r['fault']['kind']} at t = {r['fault']['t']:.3f} s: {r['fault']['text']}")
    for p in r.get("plots", []):
        print(f"  plot: {p}")


def _s(v) -> str:
    return "never" if v is None else f"at {v:.2f} s"
