"""``otbot demo``: the main job against the built-in simulated robot, in five stages.

1. the paper's chassis experiment (tau = (6, -10, 6) N m for 3 s, 100 Hz zero-order hold, IMU
   noise sigma = ND sqrt(SR) = 13.7e-3): MCAP recording and plots;
2. chassis identification (paper step 2) from that recording;
3. the same experiment through the CANopen drivers (simulated robot on virtual CAN);
4. the bench procedure (``otbot bench --yes``) on a robot carrying a load, over the simulated CAN
   bus: the four steps with their checks, identification with std, diagnosis, report (``bench/``);
5. the paper's narrow corridor tracked by the computed-torque controller over the simulated CAN
   bus on that loaded robot, with the parameters the bench identified, fed by the pose EKF on the
   encoders and IMU (recording and plots in ``corridor/``);
6. online payload adaptation: the smooth corridor over the simulated CAN bus with EKF feedback, a
   box the parameter file does not know put on the platform mid-run; the loop's payload adapter
   detects it, re-estimates the payload and the tracking error recovers (``adaptation/``).

Every file written is announced on stdout (text mode) or listed in the JSON.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from otbot_hw.cli import add_json_flag, progress
from otbot_hw.cli.checks import output_folder, seed, writing

#: Names of q's entries with their units, for printing a configuration.
Q_LABELS = (("x", "m"), ("y", "m"), ("alpha", "rad"), ("phi_r", "rad"), ("phi_l", "rad"), ("phi_p", "rad"))


def register(sub) -> None:
    p = sub.add_parser(
        "demo",
        help="run the main job against the built-in simulated robot (simulate, identify, CAN, bench, track, adapt)",
        description="The main job on the built-in simulated robot, in six stages, all files in --out-dir: "
                    "(1) the paper's chassis experiment (tau = 6, -10, 6 N m for 3 s at 100 Hz): MCAP recording "
                    "chassis.mcap and PNG plots in chassis/; (2) chassis identification (paper step 2: m_c in kg, "
                    "I_c in kg m^2, x_B, y_B in m) from that recording, plot in identification/; (3) the same "
                    "experiment through the CANopen drivers against the simulated robot on a virtual CAN bus: "
                    "chassis_bus.mcap and plots in chassis_bus/; (4) the bench identification procedure (otbot bench "
                    "--yes) on a robot carrying a 40 kg load, over the simulated CAN bus: four steps with checks, "
                    "estimates with std (SI units) against the simulated truth, diagnosis, report, all in bench/; "
                    "(5) the paper's narrow corridor (five 3 m "
                    "segments at 0.6 m/s) tracked on that loaded robot over the simulated CAN bus at the bus's "
                    "control rate with the parameters the bench identified and EKF feedback: tracking errors of the true pose and estimation errors (estimate - truth) in "
                    "mm and rad, settle times in s per event, recording and plots in corridor/; (6) online payload "
                    "adaptation: the smooth corridor over the simulated CAN bus, a 60 kg box the parameter file does "
                    "not know put on the platform at t = 7 s; when the adapter detected it and re-estimated m_p (kg), "
                    "I_p (kg m^2), x_F, y_F (m) with std, the tracking error (mm) before, until re-estimated and after, "
                    "recording in adaptation/.",
    )
    p.add_argument("--out-dir", type=Path, default=Path("otbot-demo"), metavar="DIR",
                   help="output folder, created if missing (its parent must exist); default otbot-demo")
    p.add_argument("--seed", type=seed, default=0, help="sensor noise seed, an integer >= 0 (default 0)")
    add_json_flag(p)
    p.set_defaults(func=run)


def format_q(q) -> str:
    """'x 1.0000 m, y ..., phi_p ... rad' for a configuration q (6,)."""
    return ", ".join(f"{n} {v:.4f} {u}" for (n, u), v in zip(Q_LABELS, q))


def run(args: argparse.Namespace) -> dict:
    from otbot_hw.cli.simulate import write_plots
    from otbot_hw.model.well_posed import load_params
    from otbot_hw.params import nominal
    from otbot_hw.recording import write_recording
    from otbot_hw.sensors import NoiseModel
    from otbot_hw.simulation.runs import simulated_recording

    out = output_folder(args.out_dir, "--out-dir")
    params = nominal()
    quiet = args.json
    progress("[demo] 1/6 chassis experiment: tau = (6, -10, 6) N m, 3 s, 100 Hz", not quiet)
    rec = simulated_recording(params, np.tile([6.0, -10.0, 6.0], (300, 1)), 0.01, NoiseModel.paper(),
                              seed=args.seed, extra_metadata={"experiment": "chassis (paper §4.3.2)"})
    path = out / "chassis.mcap"
    with writing("--out-dir"):
        out.mkdir(exist_ok=True)
        write_recording(path, rec)
        plots = write_plots(out / "chassis", rec, params, "Chassis experiment")
    result = {"chassis_experiment": {"recording": str(path), "plots": plots,
                                     "final_q": rec.truth_q[-1].tolist(), "final_qd": rec.truth_qd[-1].tolist()}}
    if not quiet:
        print(f"[demo] recording: {path}")
        for p in plots:
            print(f"[demo] plot: {p}")
        print(f"[demo] final configuration q at t = {rec.t[-1]:g} s: {format_q(rec.truth_q[-1])}")
    progress("[demo] 2/6 identification: chassis parameters (step 2) from the recording", not quiet)
    from otbot_hw.identification.steps import demo_stage
    result["identification"] = demo_stage(rec, params, out, quiet)
    from otbot_hw.cli.run import bus_demo
    result["bus_run"] = bus_demo(out, args.seed, quiet, reference=rec)
    result["bench"] = _bench(out, quiet, args.seed)
    identified = load_params(result["bench"]["params_file"])
    result["corridor"] = _corridor(out, identified, quiet, args.seed, plant=params.with_load(*DEMO_LOAD))
    result["adaptation"] = _adaptation(out, params, quiet, args.seed)
    return result


#: the box put on the platform in the adaptation stage (kg, m, m, kg m^2) and when (s of plant time)
BOX, BOX_AT, ADAPT_DURATION = (60.0, 0.15, -0.1, 1.0), 7.0, 20.0


def _adaptation(out: Path, params, quiet: bool, seed: int = 0) -> dict:
    """The smooth corridor over the simulated CAN bus with EKF feedback and online payload adaptation; the
    box BOX put on at BOX_AT s; recording in ``adaptation/``."""
    from drivers.config import load_robot_config
    from otbot_hw.control.computed_torque import ComputedTorqueController
    from otbot_hw.control.gains import gains_from_tstab
    from otbot_hw.control.scenarios import build_spec
    from otbot_hw.estimation.payload import AdaptationConfig
    from otbot_hw.runtime.backends import BusSimBackend
    from otbot_hw.runtime.supervisor import SafetyConfig
    from otbot_hw.runtime.tracking import track_reference
    from otbot_hw.sensors import NoiseModel
    from sim.load_schedule import LoadSchedule, with_loads

    cfg = load_robot_config()
    progress(f"[demo] 6/6 payload adaptation: the smooth corridor over the simulated CAN bus, feedback ekf; a "
             f"{BOX[0]:g} kg box the parameter file does not know put on the platform at ({BOX[1]:g}, {BOX[2]:g}) m, "
             f"t = {BOX_AT:g} s", not quiet)
    folder = out / "adaptation"
    folder.mkdir(parents=True, exist_ok=True)
    spec = build_spec("corridor-smooth", params, cfg.limits)
    backend = with_loads(BusSimBackend(cfg, NoiseModel.paper(), seed), LoadSchedule([(0.0, None), (BOX_AT, BOX)]))
    law = ComputedTorqueController(params, gains_from_tstab(3.0))
    path = folder / "adaptation.mcap"
    run = track_reference(spec.reference, law, params, cfg.limits, backend, "ekf", x0=spec.x0,
                          duration=ADAPT_DURATION, safety=SafetyConfig.load(), path=path,
                          adapt=AdaptationConfig.load().with_(enabled=True),
                          metadata={"command": "otbot demo", "scenario": spec.name, "box": list(BOX),
                                    "box_at_s": BOX_AT, "noise": NoiseModel.paper().to_dict(), "seed": seed})
    if not run.completed:
        raise RuntimeError(f"adaptation stage stopped by fault: {run.loop.fault}")
    rec = run.loop.recording
    origin = float(rec.t[len(rec.t) - len(run.t)])
    ad = run.adapter.summary(origin)
    truth = params.with_load(*BOX)
    est = run.adapter.payload_estimate()
    box = BOX_AT - origin
    change = ad["changes"][0] if ad["changes"] else {"detected_s": None, "reconverged_s": None}
    exy = np.hypot(run.e_p[:, 0], run.e_p[:, 1]) * 1e3

    def peak(lo, hi):
        m = (run.t >= lo) & (run.t < hi)
        return float(exy[m].max()) if m.any() else None

    back = change["reconverged_s"]
    res = {"recording": str(path), "box": {"mass_kg": BOX[0], "x_m": BOX[1], "y_m": BOX[2], "inertia_kg_m2": BOX[3],
                                           "t_s": box},
           "adaptation": ad, "payload_estimate": est,
           "truth": {"m_p": truth.m_p, "I_p": truth.I_p, "x_F": truth.x_F, "y_F": truth.y_F},
           "max_error_mm": {"before_box": peak(2.0, box), "box_to_reestimated": peak(box, back or run.t[-1] + 1),
                            "after_reestimated_plus_3s": peak(back + 3.0, run.t[-1] + 1) if back is not None else None},
           "saturation": run.saturation, "completed": run.completed}
    if not quiet:
        e = res["max_error_mm"]
        f = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
        print(f"[demo] adaptation: box put on at t = {box:.2f} s; detected at t = {f(change['detected_s'])} s, "
              f"re-estimated at t = {f(back)} s")
        print("[demo] adaptation: payload estimate (platform + box) against the truth: " + ", ".join(
            f"{n} {est[n]['value']:.4g} +- {est[n]['std']:.2g} (true {res['truth'][n]:.4g})" for n in est)
              + " (kg, kg m^2, m; an I_p the motion cannot tell stays at the file's, with the prior's std)")
        print(f"[demo] adaptation: max tracking error of the true pose: before the box {f(e['before_box'])} mm, from "
              f"the box until re-estimated {f(e['box_to_reestimated'])} mm, from 3 s after on "
              f"{f(e['after_reestimated_plus_3s'])} mm")
        print(f"[demo] recording: {path}")
    return res


#: the load (kg, m, m, kg m^2) the nominal robot carries in the bench and corridor stages
DEMO_LOAD = (40.0, 0.15, -0.1, 0.4)


def _bench(out: Path, quiet: bool, seed: int) -> dict:
    """The bench procedure as ``otbot bench --yes --json`` runs it, on the nominal robot carrying DEMO_LOAD."""
    from otbot_hw.cli import build_parser

    progress("[demo] 4/6 bench procedure (otbot bench --yes) on the robot with a "
             f"{DEMO_LOAD[0]:g} kg load at ({DEMO_LOAD[1]:g}, {DEMO_LOAD[2]:g}) m, over the simulated CAN bus", not quiet)
    folder = out / "bench"
    if folder.exists():  # a demo run before: its session is replaced
        import shutil

        shutil.rmtree(folder)
    load = "{:g}@{:g},{:g},{:g}".format(*DEMO_LOAD)
    args = build_parser().parse_args(["bench", "--bus", "sim", "--yes", "--json", "--session", str(folder),
                                      "--sim-load", load, "--seed", str(seed)])
    res = args.func(args)
    keep = ("session", "passed", "steps", "parameters", "truth", "error_sigma", "diagnosis", "params_file", "report",
            "report_files", "bus_logs", "recordings", "timing", "load")
    res = {k: res[k] for k in keep if k in res}
    res["files"] = sorted(str(p) for p in folder.rglob("*") if p.is_file())
    if not quiet:
        print(f"[demo] bench: {'passed' if res['passed'] else 'NOT passed'}; "
              + ", ".join(f"{n} {d['status']}" for n, d in res["steps"].items()))
        es = res["error_sigma"]
        print("[demo] bench estimates (value +- std, error in std against the simulated truth): " + ", ".join(
            f"{n} {p['value']:.4g} +- {p['std']:.2g} ({es[n]:+.1f})" for n, p in res["parameters"].items()
            if es.get(n) is not None))
        if res.get("diagnosis"):
            print(f"[demo] bench diagnosis: {res['diagnosis']['verdict']}")
        print(f"[demo] bench parameters: {res['params_file']}")
        for p in res["files"]:
            print(f"[demo] bench file: {p}")
    return res


def saturation_line(saturation: list[dict], events: list[dict], rate_hz: float) -> str | None:
    """One line explaining a run's saturation episodes: how many, which motors, how long, and
    whether they all start at the reference's velocity steps (``events``), where they are expected."""
    if not saturation:
        return None
    motors = sorted({s["motor"] for s in saturation})
    longest_ms = 1e3 * max(s["ticks"] for s in saturation) / rate_hz
    peak = max(s["peak_request_Nm"] for s in saturation)
    limit = min(s["limit_Nm"] for s in saturation)
    steps = [e["t"] for e in events]
    at_steps = all(any(abs(s["t_start"] - t) <= 2.0 / rate_hz for t in steps) for s in saturation)
    head = (f"the torque limiter clipped {', '.join(motors)} in {len(saturation)} episode(s) of at most "
            f"{longest_ms:.0f} ms (up to {peak:.1f} N m asked, limit {limit:g} N m)")
    if at_steps:
        return head + ("; expected: every episode starts at a velocity step of the reference (start, corner "
                       "or stop), which no motor can follow instantly")
    return head + "; not all at the reference's velocity steps: see 'saturation' in --json for when"


def _corridor(out: Path, params, quiet: bool, seed: int = 0, plant=None) -> dict:
    """The paper's corridor tracked over the simulated CAN bus by the loop runner with the controller's
    model ``params`` on the robot ``plant`` (default ``params``), fed by the pose EKF on the encoders and
    IMU; recording and plots in ``corridor/``."""
    from drivers.config import load_robot_config
    from otbot_hw.runtime.backends import BusSimBackend
    from otbot_hw.runtime.supervisor import SafetyConfig
    from otbot_hw.runtime.tracking import run_scenario
    from otbot_hw.sensors import NoiseModel

    cfg = load_robot_config()
    feedback = "ekf"
    progress(f"[demo] 5/6 corridor: the loaded robot tracked over the simulated CAN bus at {cfg.bus.control_rate:g} Hz "
             f"with the parameters the bench identified, feedback {feedback}, five 3 m segments at 0.6 m/s", not quiet)

    def say(m: str) -> None:
        # per-episode saturation and feasibility notices are summed up in one line after the run
        if not m.startswith(("saturation:", "feasibility:")):
            progress(f"[demo] {m}")

    folder = out / "corridor"
    folder.mkdir(parents=True, exist_ok=True)
    res = run_scenario("corridor", params, cfg.limits, robustness=False, plot_dir=folder, plant=plant,
                       progress=None if quiet else say,
                       backend=BusSimBackend(cfg, NoiseModel.paper(), seed), feedback=feedback,
                       safety=SafetyConfig.load(), path=folder / "corridor.mcap",
                       metadata={"command": "otbot demo", "noise": NoiseModel.paper().to_dict(), "seed": seed})
    keep = ("rate_hz", "max_abs_error", "rms_error", "estimation_error", "peak_torque", "events", "saturation",
            "min_wall_clearance_m", "plots", "wall_time_s", "feedback", "bus", "backend", "loop", "recording",
            "completed", "fault")
    res = {k: res[k] for k in keep if k in res}
    if not res["completed"]:
        raise RuntimeError(f"corridor stopped by fault: {res['fault']}")
    if not quiet:
        e = res["max_abs_error"]
        print(f"[demo] corridor over the bus, feedback {feedback}: tracking error of the true pose, max |e_x| "
              f"{e['x'] * 1e3:.1f} mm, max |e_y| {e['y'] * 1e3:.1f} mm, max |e_alpha| {e['alpha']:.1e} rad"
              + (f"; footprint to the walls >= {res['min_wall_clearance_m'] * 1e3:.0f} mm"
                 if "min_wall_clearance_m" in res else ""))
        ee = res.get("estimation_error")
        if ee is not None:
            from otbot_hw.estimation.errors import describe_estimation_error

            print("[demo] " + describe_estimation_error(ee))
        print("[demo] corridor settle times (until the errors stay below 2 % of the event's peak): "
              + ", ".join(f"{ev['kind']} at t = {ev['t']:g} s: "
                          + (f"{ev['settle_time_s']:.2f} s" if ev["settle_time_s"] is not None else "not settled")
                          for ev in res["events"]))
        line = saturation_line(res["saturation"], res["events"], res.get("rate_hz", cfg.bus.control_rate))
        if line:
            print(f"[demo] corridor: {line}")
        print(f"[demo] recording: {res['recording']}")
        for p in res["plots"]:
            print(f"[demo] plot: {p}")
    return res
