"""``otbot run``: apply constant joint torques through the drivers and record what they report.

``--bus sim`` runs the simulated robot in this process: CANopen slaves on canopen's LocalNode
and the Otbot model in lockstep with the SYNC, on python-can's virtual bus, with the simulated
VectorNav IMU on a pseudo-terminal. ``--bus config`` uses the bus and IMU port of the hardware
configuration: the real robot (or an ``otbot plant`` process, with --interface/--channel/--imu-port).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from otbot_hw.cli import CliError, add_json_flag, parse_vector, progress
from otbot_hw.cli.backend_args import add_bus_options, bus_config, noise_model
from otbot_hw.cli.checks import (default_input, duration, output_file, output_folder, rounding_notice, sample_count,
                                write_failure)


def register(sub) -> None:
    p = sub.add_parser(
        "run",
        help="apply torques through the CANopen drivers (simulated or real robot) and record",
        description="Enable the three CiA 402 drives, apply constant joint torques (N m) for --duration s "
                    "at --rate Hz (one SYNC per period) through the loop runner (open-loop torque controller, "
                    "safety supervisor: motor limits and joint-rate limits of the configuration), record joint "
                    "angles (rad) and rates (rad/s) from the drives and the pivot encoder and the IMU's specific "
                    "force (m/s^2) and rate (rad/s) in the platform frame, then quick-stop. Exit code 1 if a drive, "
                    "encoder or IMU fault or a safety limit stops the run.",
    )
    p.add_argument("--bus", choices=("sim", "config"), default="sim",
                   help="sim: simulated robot in this process (virtual CAN); config: the bus of --config")
    p.add_argument("--torques", default="6,-10,6", help="tau_r,tau_l,tau_p in N m (default 6,-10,6)")
    p.add_argument("--duration", type=duration, default=3.0, help="s (default 3)")
    p.add_argument("--fixture", choices=("floor", "stand", "locked"), default="floor",
                   help="bench fixture: floor, stand (chassis held, wheels free), locked (chassis and wheels "
                        "held); simulated with --bus sim, declared (recorded in the metadata) with --bus config")
    p.add_argument("--plant-params", type=Path, default=None,
                   help="--bus sim: the robot to simulate, a parameter YAML or a diagnosed-model file with 'effects' "
                        "(default config/otbot.yaml)")
    add_bus_options(p, "default: bus.control_rate of the config")
    p.add_argument("--inject", default=None, metavar="KIND@SECONDS[:DRIVE]",
                   help="--bus sim: inject a fault at this plant time (s since the drives were enabled): "
                        "drive-silent, emcy, fault-bit, imu-loss, imu-error ($VNERR), bus-off, plant-kill (runs the "
                        "plant as its own process over slcan); DRIVE: right_wheel, left_wheel (default) or pivot. "
                        "--json then gives 'reaction': injected_s, detected_s, all_stopped_s (from the simulated "
                        "drives' own state), drive_states_after")
    p.add_argument("--out", type=Path, default=None, metavar="RUN.mcap",
                   help="MCAP recording to write (its folder must exist)")
    p.add_argument("--plot", type=Path, default=None, metavar="DIR",
                   help="folder for PNG plots of the run (created if missing; its parent must exist)")
    add_json_flag(p)
    p.set_defaults(func=run)


def _fail(result: dict, message: str, as_json: bool):
    if as_json:
        print(json.dumps(result, allow_nan=False))
    print(f"otbot run: {message}", file=sys.stderr)
    raise SystemExit(1)


def run(args: argparse.Namespace) -> dict:
    from drivers.faults import DeviceConfigError
    from drivers.imu import ImuFault
    from otbot_hw.model.effects import ExtendedModel
    from otbot_hw.robot import RobotError
    from otbot_hw.runtime.backends import BackendOptions, make_backend, source
    from otbot_hw.runtime.openloop import run_torques, saturated_samples
    from otbot_hw.runtime.supervisor import SafetyConfig

    quiet = args.json
    output_file(args.out, "--out", inputs={"plant parameter file": default_input(args.plant_params, "otbot.yaml"),
                                           "hardware configuration": default_input(args.config, "robot.yaml")})
    output_folder(args.plot, "--plot")
    tau = parse_vector(args.torques, 3, "--torques")
    if args.plant_params is not None and args.bus != "sim":
        raise CliError("--plant-params sets the simulated robot (--bus sim); the configured bus runs the robot "
                       "that is there")
    cfg, load = bus_config(args, args.rate, quiet, "run")
    n = sample_count(args.duration, cfg.bus.control_rate)
    note = rounding_notice(args.duration, cfg.bus.control_rate, n, "run")
    progress(note or "", note is not None)  # a duration that is not a whole number of periods: say so
    plant = ExtendedModel.load(args.plant_params) if args.plant_params is not None else None
    safety = SafetyConfig.load(args.config)
    inject = None
    if args.inject is not None:
        from sim.injection import Injection

        if args.bus != "sim":
            raise CliError("--inject needs --bus sim (faults are injected into the simulated robot)")
        try:
            inject = Injection.parse(args.inject)
        except ValueError as exc:
            raise CliError(str(exc)) from None
        if inject.at >= n * cfg.bus.period:
            raise CliError(f"--inject {args.inject}: {inject.at:g} s is outside the run ({n * cfg.bus.period:g} s "
                           "of plant time from the enable): nothing would be injected; give a time within --duration")
        if inject.kind.startswith("imu") and (cfg.imu is None or args.no_imu):
            raise CliError(f"--inject {inject.kind}: the run has no IMU")
        if inject.kind == "plant-kill" and args.plant_params is not None:
            raise CliError("--inject plant-kill runs the nominal robot in its own process: no --plant-params")
    torques = np.tile(tau, (n, 1))
    meta = {"bus": {"mode": args.bus, "interface": cfg.bus.interface, "channel": cfg.bus.channel,
                    "bitrate": cfg.bus.bitrate, "control_rate": cfg.bus.control_rate},
            "nodes": {d.name: d.node_id for d in cfg.drives}, "config": str(cfg.path),
            "pivot_source": cfg.pivot_encoder.source, "fixture": args.fixture}
    with_imu = cfg.imu is not None and not args.no_imu
    if args.bus == "config" and with_imu:
        from drivers.robot import open_imu

        try:  # a port that cannot be opened is bad input (exit 2), as in `otbot imu read`; checked before the bus
            open_imu(cfg.imu, port=args.imu_port, configure=False).close()
        except ImuFault as exc:
            raise CliError(str(exc)) from None
    progress(f"[run] {args.bus} bus ({cfg.bus.interface}:{cfg.bus.channel}), tau = {tau} N m for "
             f"{args.duration:g} s at {cfg.bus.control_rate:g} Hz", not quiet)
    say = None if quiet else (lambda m: progress(f"[run] {m}"))
    process = inject is not None and inject.kind == "plant-kill"
    backend = make_backend(f"bus {args.bus}", cfg, BackendOptions(
        noise=noise_model(args), seed=args.seed, with_imu=with_imu, imu_port=args.imu_port, lockstep=args.lockstep,
        inject=inject, process=process))
    meta.update(source(backend))
    model = None
    if backend.simulated:  # what is simulated is recorded with the run
        meta.update(noise=backend.noise.to_dict(), seed=args.seed)
        if inject is not None:
            meta["inject"] = str(inject)
        model = plant if plant is not None else ExtendedModel.load(None)
        meta["params"] = model.params.to_dict()
        if model.active_effects():
            meta["effects"] = model.active_effects()
    try:
        with backend.open(None if process else model, fixture=args.fixture) as robot:
            _warn(robot, quiet)
            res = run_torques(robot, torques, cfg.limits, safety, args.out, meta, realtime=backend.realtime,
                              progress=say)
    except DeviceConfigError:
        raise  # the devices cannot run as configured: bad input, exit 2
    except RobotError as exc:
        _fail({"completed": False, "error": str(exc), "faults": [f.to_dict() for f in exc.faults]},
              f"error: {exc}", args.json)
    except OSError as exc:
        raise write_failure(exc, args.out or "output") from None
    except ImuFault as exc:
        _fail({"completed": False, "error": str(exc), "faults": []}, f"IMU error: {exc}", args.json)
    rec = res.recording
    result = {
        "completed": res.completed, "bus": args.bus, "interface": cfg.bus.interface, "channel": cfg.bus.channel,
        "rate": cfg.bus.control_rate, "duration": args.duration, "samples": len(rec),
        "t_final": float(rec.t[-1]) if len(rec) else None,
        "phi": rec.joint_pos[-1].tolist() if len(rec) else None,
        "phi_dot": rec.joint_vel[-1].tolist() if len(rec) else None,
        "torque_commanded": rec.torque[-1].tolist() if len(rec) else None,
        "saturated_samples": int(saturated_samples(res, cfg.limits).sum()),
        "imu": bool(rec.imu_accel is not None),
        "recording": str(args.out) if args.out else None,
        "faults": [f.to_dict() for f in res.robot_faults],
        "fault": res.fault.to_dict() if res.fault is not None else None,
        "busload": {"bits_per_cycle": load.bits_per_cycle, "max_rate": load.max_rate, "load": load.load},
        "loop": res.stats.to_dict(),
        "wall_time": res.stats.wall_time,
        "warnings": list(robot.warnings),
        "close_problems": list(robot.close_report),
    }
    if inject is not None:
        from sim.injection import reaction

        sim_plant = backend.plant
        result["reaction"] = reaction(inject, sim_plant.injected_t, robot, sim_plant.after, cfg.bus.period)
    if backend.simulated and rec.truth_q is not None and len(rec):
        result["q_final"] = rec.truth_q[-1].tolist()
    if args.plot is not None and len(rec) > 1:
        result["plots"] = write_run_plots(args.plot, rec)
    if not res.completed:
        if not quiet and "reaction" in result:
            _print_reaction(result["reaction"])
        _fail(result, f"stopped by fault: {res.fault}" + (f"; recording up to the fault: {args.out}" if args.out else ""),
              args.json)
    if not quiet:
        print(f"[run] {len(rec)} samples, final phi = " + ", ".join(f"{v:.4f}" for v in result["phi"]) + " rad")
        if result["saturated_samples"]:
            print(f"[run] torque limits cut the command in {result['saturated_samples']} samples")
        if args.out:
            print(f"[run] recording: {args.out}")
        for p in result.get("plots", []):
            print(f"[run] plot: {p}")
    return result


def _warn(robot, quiet: bool) -> None:
    """What the devices cannot do that the loop would use, said once."""
    for w in robot.warnings:
        progress(f"[run] warning: {w}", not quiet)


def _print_reaction(r: dict) -> None:
    def t(v):
        return "never" if v is None else f"{v:.3f} s"

    print(f"[run] injected {r['kind']} at {t(r['injected_s'])}, detected at {t(r['detected_s'])}; by their own "
          f"state the drives on the bus stopped at {t(r['healthy_stopped_s'])}, every drive at "
          f"{t(r['all_stopped_s'])}; drives after the run: {r['drive_states_after']}")


def write_run_plots(folder: Path, rec) -> list[str]:
    """Joint angles/rates (and IMU) as the drivers reported them; path and states when simulated."""
    from otbot_hw.cli.simulate import write_plots
    from otbot_hw.params import OtbotParams, nominal
    from otbot_hw.plots import plot_series

    folder.mkdir(parents=True, exist_ok=True)
    out = [str(plot_series(folder / "joints.png", rec.t, {
        "phi_r": (rec.joint_pos[:, 0], "rad"), "phi_l": (rec.joint_pos[:, 1], "rad"),
        "phi_p": (rec.joint_pos[:, 2], "rad"), "dphi_r": (rec.joint_vel[:, 0], "rad/s"),
        "dphi_l": (rec.joint_vel[:, 1], "rad/s"), "dphi_p": (rec.joint_vel[:, 2], "rad/s")},
        title="Joints as the drives and the pivot encoder reported them"))]
    if rec.truth_q is not None:
        params = OtbotParams.from_dict(rec.metadata["params"]) if "params" in rec.metadata else nominal()
        out += [p for p in write_plots(folder, rec, params, "Bus run") if not p.endswith("joints.png")]
    elif rec.imu_accel is not None:
        out.append(str(plot_series(folder / "imu.png", rec.t, {
            "a_x''": (rec.imu_accel[:, 0], "m/s^2"), "a_y''": (rec.imu_accel[:, 1], "m/s^2"),
            "omega_z": (rec.imu_gyro[:, 2], "rad/s")}, title="IMU (platform frame)")))
    return out


def bus_demo(out_dir: Path, seed: int = 0, quiet: bool = False, reference=None) -> dict:
    """``otbot demo`` part: the paper's chassis experiment (6, -10, 6 N m, 3 s, 100 Hz) through the
    CANopen drivers against the simulated robot on a virtual CAN bus, IMU on a pseudo-terminal, run by
    the loop runner with an open-loop torque controller.

    Writes ``chassis_bus.mcap`` and plots into ``out_dir``; with ``reference`` (the pure-simulation
    recording of the same experiment) reports how far the bus readings are from its ground truth.
    """
    from drivers.config import load_robot_config
    from otbot_hw.cli.simulate import write_plots
    from otbot_hw.params import nominal
    from otbot_hw.plots import plot_series
    from otbot_hw.recording import source_metadata
    from otbot_hw.runtime.backends import BusSimBackend
    from otbot_hw.runtime.openloop import run_torques
    from otbot_hw.sensors import NoiseModel

    cfg = load_robot_config()
    progress("[demo] 3/6 the same experiment through the CANopen drivers (simulated robot on virtual CAN)", not quiet)
    path = out_dir / "chassis_bus.mcap"
    params = nominal()
    with BusSimBackend(cfg, NoiseModel.paper(), seed).open(params) as robot:
        res = run_torques(robot, np.tile([6.0, -10.0, 6.0], (300, 1)), cfg.limits, None, path,
                          {"experiment": "chassis (paper §4.3.2) over CAN",
                           **source_metadata(simulated=True, bus=True),
                           "noise": NoiseModel.paper().to_dict(), "seed": seed, "params": params.to_dict()})
    wall = res.stats.wall_time
    if not res.completed:
        raise RuntimeError(f"bus demo stopped by fault: {res.fault}")
    rec = res.recording
    err = rec.joint_pos - rec.truth_q[:, 3:6]
    plots = write_plots(out_dir / "chassis_bus", rec, params, "Chassis experiment over CAN")
    plots.append(str(plot_series(out_dir / "chassis_bus" / "encoder_error.png", rec.t, {
        "phi_r": (err[:, 0], "rad"), "phi_l": (err[:, 1], "rad"), "phi_p": (err[:, 2], "rad")},
        title="Encoder reading - true joint angle (count quantization)")))
    out = {"recording": str(path), "plots": plots, "phi": rec.joint_pos[-1].tolist(),
           "max_encoder_error": float(np.abs(err).max()), "wall_time": wall,
           "realtime_factor": float(rec.t[-1] / wall)}
    if reference is not None and reference.truth_q is not None:
        out["max_state_difference_vs_pure_simulation"] = float(np.abs(rec.truth_q - reference.truth_q).max())
    if not quiet:
        print(f"[demo] bus recording: {path} ({len(rec)} samples, {out['realtime_factor']:.1f}x real time)")
        print("[demo] bus final joint angles (drives and pivot encoder): " + ", ".join(
            f"{n} {v:.4f} rad" for n, v in zip(("phi_r", "phi_l", "phi_p"), out["phi"]))
              + f"; |encoder - true angle| <= {out['max_encoder_error']:.2e} rad")
        for p in plots:
            print(f"[demo] plot: {p}")
    return out
