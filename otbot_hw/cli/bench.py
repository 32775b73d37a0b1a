"""``otbot bench``: identify the robot end to end through its drivers, step by step, with honest std.

The paper's experiments (wheel on the stand, pivot with the wheels locked, chassis on the floor,
platform with its load) run through the loop runner over the bus (``--bus sim``: the simulated
CANopen robot in lockstep; ``--bus config``: the configured bus, the real robot or an ``otbot
plant``), with operator guidance and checks from the sensors before any torque, the safety
supervisor tightened to the experiment limits, identification with quality gates after each step
(redo when they fail), then the session's joint fit, the mismatch finder and a report. The
procedure is ``otbot_hw.runtime.bench``; the session folder's layout is in docs/identification.md.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

from otbot_hw.cli import CliError, add_json_flag, progress
from otbot_hw.cli.backend_args import add_bus_options, bus_config, noise_model
from otbot_hw.cli.checks import count, default_input, number, output_file, output_folder, writing

STEP_NAMES = ("wheel", "pivot", "chassis", "platform")
RATE = 100.0  # Hz: the paper's experiments are sampled at 100 Hz
SIM_HEARTBEAT = 5.0  # s: heartbeat consumer times of the simulated bus (lockstep; a real bus keeps its own)


def register(sub) -> None:
    p = sub.add_parser(
        "bench",
        help="identify the robot end to end through its drivers: guided steps, checks, safe excitation, "
             "identification with honest std, diagnosis, report",
        description="The bench identification procedure (paper §4): for each step (wheel on the stand, pivot "
                    "with the wheels locked, chassis on the floor, platform with its load) the operator is told "
                    "what to set up, the sensors check it before any torque (drives enabled and fault-free, IMU "
                    "streaming and at rest, the fixture, the excitation's predicted travel inside the free area), "
                    "the excitation runs through the loop runner and the drivers with the safety supervisor "
                    "holding the experiment limits (config/robot.yaml experiment_limits: torque N m, wheel and "
                    "pivot speed rad/s, platform speed m/s, free area m), and the step is identified with its "
                    "quality gates (pass, or redo). Then one joint fit of all recordings (std in SI units with the "
                    "earlier steps' uncertainty), otbot diagnose on the recordings, params.yaml and a Markdown "
                    "report with PNG plots. Everything goes into the session folder, with the raw bus log (BLF); "
                    "an abort leaves a session --resume continues. Exit 2: a check or the data say the set-up is "
                    "wrong (the message names the step and what to do); 1: a run stopped by a fault or limit.")
    p.add_argument("--bus", choices=("sim", "config"), default="sim",
                   help="sim: the simulated robot on virtual CAN in lockstep (default); config: the configured bus "
                        "(the real robot, or an otbot plant process)")
    p.add_argument("--steps", default=None,
                   help="comma-separated steps to run, in the paper's order (default wheel,pivot,chassis,platform); "
                        "the others keep the values and std of --params")
    p.add_argument("--session", type=Path, default=None, metavar="DIR",
                   help="new session folder (created; its parent must exist; default otbot-bench-<date>-<time>)")
    p.add_argument("--resume", type=Path, default=None, metavar="DIR",
                   help="continue the session in DIR at its first step not passed (same robot, same settings)")
    p.add_argument("--yes", action="store_true",
                   help="no questions (automation): with the simulated robot its operator sets each step up; with a "
                        "real robot the set-up is assumed done and the checks verify it; a failed check ends the run")
    p.add_argument("--out", type=Path, default=None, metavar="PARAMS.yaml",
                   help="identified parameters with std, what otbot track --params, the daemon and otbot diagnose "
                        "--params load (default SESSION/params.yaml)")
    p.add_argument("--report", type=Path, default=None, metavar="DIR",
                   help="Markdown report with PNG plots (default SESSION/report)")
    p.add_argument("--excitation", choices=("paper", "designed"), default=None,
                   help="designed (default): for the chassis and platform steps torques that minimise the "
                        "Cramer-Rao bound within the limits on the prior's corner robots (identification.design; "
                        "designed once per parameter file and limits, minutes, then kept; shipped for the nominal "
                        "file and default limits); paper: the paper's constant torques (6, -10, 6) N m, which leave "
                        "the default limits on about half of the robots that differ from the file")
    p.add_argument("--params", type=Path, default=None,
                   help="the robot's parameters before the session (unloaded platform; default config/otbot.yaml): "
                        "the geometry (l1, l2, r) is taken as known, the rest are first guesses; the unloaded "
                        "platform's mass is weighed by the operator (or kept with a 20 %% prior std and reported "
                        "as not separable from the chassis' mass), its centre estimated from the floor runs")
    p.add_argument("--sim-params", type=Path, default=None,
                   help="--bus sim: the robot to simulate, a parameter file or a diagnosed model with effects "
                        "(default config/otbot.yaml)")
    p.add_argument("--sim-load", default=None, metavar="KG@X,Y[,I]",
                   help="--bus sim: the load the simulated operator fixes on the platform for the platform step, KG kg "
                        "at (X, Y) m in the platform frame with its own inertia I kg m^2")
    p.add_argument("--free-area", type=number(above=0, unit="m"), default=None, metavar="M",
                   help="radius (m) of the free area around the robot on the floor (default "
                        "experiment_limits.travel_radius)")
    p.add_argument("--attempts", type=count(1, 10), default=None,
                   help="runs per step before giving up when its gates say redo (default 2)")
    p.add_argument("--no-diagnose", action="store_true", help="skip the mismatch finder")
    add_bus_options(p, "must be 100 Hz, the paper's sampling: the default of config/robot.yaml")
    add_json_flag(p)
    p.set_defaults(func=run)


def parse_steps(text: str | None) -> list[str]:
    if text is None:
        return list(STEP_NAMES)
    names = [s.strip() for s in text.split(",") if s.strip()]
    bad = [s for s in names if s not in STEP_NAMES]
    if bad or not names:
        raise CliError(f"--steps: unknown step(s) {', '.join(bad) or repr(text)} (known: {', '.join(STEP_NAMES)})")
    if len(set(names)) != len(names):
        raise CliError(f"--steps: a step is named twice in {text!r}")
    return [s for s in STEP_NAMES if s in names]


def _fail(result: dict | None, message: str, as_json: bool):
    if as_json and result is not None:
        print(json.dumps(result, allow_nan=False))
    print(f"otbot bench: {message}", file=sys.stderr)
    raise SystemExit(1)


def run(args: argparse.Namespace) -> dict:
    from otbot_hw.cli.identify import parse_load
    from otbot_hw.estimation.config import EstimatorConfig
    from otbot_hw.experiment_limits import load_experiment_limits
    from otbot_hw.model.effects import ExtendedModel
    from otbot_hw.model.well_posed import load_params
    from otbot_hw.runtime.bench.steps import BenchSettings, SimulatedRobot, settings_from_manifest
    from otbot_hw.runtime.bench.session import SessionError, SessionFolder
    from otbot_hw.runtime.supervisor import SafetyConfig
    from otbot_hw.sensors import NoiseModel

    quiet = args.json
    say = (lambda m: None) if quiet else (lambda m: progress(m))
    if args.session is not None and args.resume is not None:
        raise CliError("give --session DIR for a new session or --resume DIR to continue one, not both")
    if args.bus == "config" and (args.sim_params is not None or args.sim_load is not None):
        raise CliError("--sim-params and --sim-load set the simulated robot (--bus sim); the configured bus runs the "
                       "robot that is there")
    output_file(args.out, "--out", inputs={"parameter file": default_input(args.params, "otbot.yaml"),
                                           "simulated robot's parameter file": args.sim_params,
                                           "hardware configuration": default_input(args.config, "robot.yaml")})
    output_folder(args.report, "--report")
    cfg, _ = bus_config(args, args.rate, quiet, "bench")
    if abs(cfg.bus.control_rate - RATE) > 1e-9:
        raise CliError(f"the bench runs at {RATE:g} Hz, the paper's sampling of its experiments; the bus runs at "
                       f"{cfg.bus.control_rate:g} Hz (--rate or bus.control_rate)")
    limits = load_experiment_limits(args.config)
    if args.free_area is not None:
        limits = limits.replace(travel_radius=float(args.free_area))
    est = EstimatorConfig.load(args.config)
    with_imu = cfg.imu is not None and not args.no_imu
    base = BenchSettings(steps=parse_steps(args.steps), excitation=args.excitation or "designed",
                         attempts=args.attempts or 2, limits=limits, safety=SafetyConfig.load(args.config),
                         motor_limits=cfg.limits, params_start=load_params(args.params),
                         noise=NoiseModel(accel=est.accel_sigma, gyro=est.gyro_sigma, enc_rate=est.encoder_rate_sigma),
                         imu_rate=float(cfg.imu.rate_hz) if with_imu else None, diagnose=not args.no_diagnose)
    session = None
    sim_load_text = args.sim_load
    try:
        if args.resume is not None:
            given = [o for o, v in (("--steps", args.steps), ("--excitation", args.excitation),
                                    ("--params", args.params), ("--free-area", args.free_area),
                                    ("--attempts", args.attempts)) if v is not None]
            if given:
                raise CliError(f"{', '.join(given)}: --resume continues the session with the settings it was "
                               "started with")
            session = SessionFolder.open(args.resume)
            settings = settings_from_manifest(session.data, base)
            stored = session.settings.get("sim_load")
            if sim_load_text is not None and stored is not None and sim_load_text != stored:
                raise CliError(f"--sim-load {sim_load_text}: the session's platform load is {stored}")
            sim_load_text = sim_load_text or stored
            invocation = len(session.data["invocations"]) + 1
            _notice_truncated(session, settings.steps)
        else:
            settings = base
            invocation = 1
    except SessionError as exc:
        raise CliError(str(exc)) from None
    sim = None
    model = None
    if args.bus == "sim":
        model = ExtendedModel.load(args.sim_params)
        load = parse_load(sim_load_text, "--sim-load") if sim_load_text else None
        sim = SimulatedRobot(model.params, load, model.active_effects())
        if load is not None and math.hypot(load[1], load[2]) > model.params.radius:
            raise CliError(f"--sim-load {sim_load_text}: the load at ({load[1]:g}, {load[2]:g}) m is off the platform "
                           f"(radius {model.params.radius:g} m)")
        sim.loaded  # a load the parameters cannot take raises ParameterError (bad input)
    folder = args.resume or args.session or Path(time.strftime("otbot-bench-%Y%m%d-%H%M%S"))
    if args.resume is None:
        output_folder(folder, "--session")
        if folder.is_dir() and any(folder.iterdir()):
            what = "a session already" if (folder / "session.json").is_file() else "files"
            raise CliError(f"--session {folder}: the folder holds {what}; continue a session with --resume {folder}, "
                           "or name a new folder")
    return _run(args, cfg, settings, session, folder, invocation, sim, model, sim_load_text, with_imu, say, quiet)


def _notice_truncated(session, steps) -> None:
    """A notice (as ``otbot identify`` gives) for every passed step whose recording was cut short since: the
    session's fit uses what is left of it."""
    from otbot_hw.cli.checks import truncation_notice
    from otbot_hw.recording import read_recording

    for step in steps:
        if session.status(step) != "passed":
            continue
        for path in session.accepted_recordings(step):
            rec = read_recording(path)
            if rec.truncated:
                if len(rec) < 2:
                    raise CliError(f"step {step}: {truncation_notice(path, rec)}: nothing to fit; start a new "
                                   "session or remove the step's attempt")
                progress(f"[bench] notice: step {step}: {truncation_notice(path, rec)}; fitting those", True)


def _run(args, cfg, settings, session, folder, invocation, sim, model, sim_load_text, with_imu, say, quiet) -> dict:
    from otbot_hw.recording import source_metadata
    from otbot_hw.robot import RobotError, operator_channel
    from otbot_hw.runtime.backends import BusConfigBackend, BusSimBackend
    from otbot_hw.runtime.bench.buslog import BusLog
    from otbot_hw.runtime.bench.operator import AutomaticOperator, NoOperator, OperatorStopped, PromptOperator
    from otbot_hw.runtime.bench.procedure import BenchProcedure
    from otbot_hw.runtime.bench.runs import warm_up
    from otbot_hw.runtime.bench.report import write_report
    from otbot_hw.runtime.bench.session import SessionError, SessionFolder, identity
    from otbot_hw.runtime.bench.steps import BenchAbort, BenchError

    meta = {"command": "otbot bench", "config": str(cfg.path),
            "bus": {"mode": args.bus, "interface": cfg.bus.interface, "channel": cfg.bus.channel,
                    "bitrate": cfg.bus.bitrate, "control_rate": cfg.bus.control_rate},
            "nodes": {d.name: d.node_id for d in cfg.drives}, "pivot_source": cfg.pivot_encoder.source,
            **source_metadata(simulated=args.bus == "sim", bus=True),
            "params_file": str(args.params) if args.params else "config/otbot.yaml"}
    if args.bus == "sim":
        seed = args.seed + 1000 * (invocation - 1)  # a resumed simulated session draws new noise
        meta.update(seed=seed, simulated_noise=noise_model(args).to_dict())
        # lockstep: how late a heartbeat comes depends on the host's scheduling, not on the simulated robot;
        # a bench session computes for seconds between runs, on a machine that may be busy
        backend = BusSimBackend(cfg.relaxed(SIM_HEARTBEAT), noise_model(args), seed, with_imu)
        opened = backend.open(model, fixture="floor")
        label = str(args.sim_params) if args.sim_params else "config/otbot.yaml"
    else:
        if with_imu:
            from drivers.imu import ImuFault
            from drivers.robot import open_imu

            try:  # a port that cannot be opened is bad input, as in otbot run
                open_imu(cfg.imu, port=args.imu_port, configure=False).close()
            except ImuFault as exc:
                raise CliError(str(exc)) from None
        backend = BusConfigBackend(cfg, args.imu_port, args.lockstep, with_imu)
        opened = backend.open()
        label = None
    log = None
    summary = None
    warm_up(settings.params_start, cfg.bus.period)
    try:
        with opened as robot:
            ident = identity(robot, args.bus, sim, label)
            try:
                if session is None:
                    session = SessionFolder.create(folder, ident, {**settings.to_dict(), "sim_load": sim_load_text})
                else:
                    session.check_robot(ident)
            except SessionError as exc:
                raise CliError(str(exc)) from None
            log_path = session.path / f"bus-{invocation}.blf"
            log = BusLog(log_path).attach(robot.network)
            session.begin_invocation({"bus_log": session.rel(log_path), "bus": args.bus,
                                      **({"seed": meta["seed"]} if "seed" in meta else {})})
            plant = operator_channel(robot)  # a simulated robot's operator channel, or None
            operator = (AutomaticOperator(plant, sim_load_text, say=say) if args.yes else
                        PromptOperator(plant, sim_load_text, say=progress))
            say(f"[bench] session {session.path}: steps {', '.join(settings.steps)}, {settings.excitation} excitation, "
                f"{args.bus} bus")
            proc = BenchProcedure(robot, settings, session, operator, realtime=backend.realtime, progress=say, sim=sim,
                                  metadata=meta)
            try:
                summary = proc.run()
            except (BenchError, NoOperator) as exc:
                session.end_invocation(outcome="failed", reason=str(exc))
                raise CliError(f"{exc} (session kept: {session.path})") from None
            except (BenchAbort, OperatorStopped) as exc:
                session.end_invocation(outcome="stopped", reason=str(exc))
                _fail({"session": str(session.path), "completed": False, "reason": str(exc)},
                      f"{exc}; resume with --resume {session.path}", quiet)
            final = proc.result
    except RobotError as exc:
        _fail({"completed": False, "error": str(exc), "faults": [f.to_dict() for f in exc.faults]}, f"error: {exc}",
              quiet)
    finally:
        if log is not None:
            log.stop()
    out = args.out or session.path / "params.yaml"
    report_dir = args.report or session.path / "report"
    with writing("--out"):
        final.save_params(out)
    with writing("--report"):
        files = write_report(report_dir, summary, final)
    summary.update(params_file=str(out), report=files[0], report_files=files,
                   bus_logs=[i["bus_log"] for i in session.data["invocations"] if i.get("bus_log")],
                   bus_log_frames=log.frames if log is not None else None,
                   recordings=session.all_recordings(), robot=session.data["robot"])
    session.data["result"] = {k: summary[k] for k in ("passed", "parameters", "params_file", "report")}
    session.end_invocation(outcome="finished")
    (session.path / "result.json").write_text(json.dumps(summary, indent=1, allow_nan=False))
    if not quiet:
        _print_summary(summary)
    return summary


def _print_summary(s: dict) -> None:
    print(f"[bench] session {s['session']}: {'passed' if s['passed'] else 'NOT passed'}")
    for name, d in s["steps"].items():
        print(f"[bench] {name}: {d['status']} after {d['attempts']} attempt(s), recording {d['accepted_recording']}")
    truth = s.get("truth")
    es = s.get("error_sigma") or {}
    for n, p in s["parameters"].items():
        line = f"[bench] {n} = {p['value']:.6g} +- {p['std']:.3g} {s['units'][n]}"
        if truth:
            line += f" (truth {truth[n]:.6g}" + (f", error {es[n]:+.2f} sigma)" if es.get(n) is not None else ")")
        print(line)
    for n, d in (s.get("unloaded_platform") or {}).items():
        print(f"[bench] {n} = {d['value']:.6g} +- {d['std']:.3g} {'kg' if n == 'm_p0' else 'm'} (unloaded platform; "
              f"file {d['file']:.6g}; {d['source']}" + (f"; truth {truth[n]:.6g}" if truth and n in truth else "") + ")")
    for n, d in (s.get("combinations") or {}).items():
        print(f"[bench] {n} = {d['value']:.6g} +- {d['std']:.3g} kg")
    for m in s.get("notices") or []:
        print(f"[bench] notice: {m}")
    if s.get("diagnosis"):
        print(f"[bench] diagnosis: {s['diagnosis']['verdict']}")
    print(f"[bench] parameters: {s['params_file']}")
    print(f"[bench] report: {s['report']}")
    for f in s["report_files"][1:]:
        print(f"[bench] plot: {f}")
    for b in s["bus_logs"]:
        print(f"[bench] bus log: {Path(s['session']) / b}")
