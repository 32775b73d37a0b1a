"""Online payload adaptation on the simulated CAN bus (docs/control.md, "Online payload adaptation").

The robot carries a load the parameter file does not know (default 60 kg at (0.15, -0.10) m in B'',
own inertia 1 kg m^2); the corridor and the smooth corridor are tracked over the simulated bus at the
bus's control rate (100 Hz) with EKF feedback, three ways: the controller with the file's parameters
(no adaptation), with online adaptation (``--adapt payload``), and with the true parameters. Tracking
errors of the true pose after ``--after`` s of motion (default 5), over the whole run, settle times per
event (corridor), torque peaks and saturation episodes, the estimate ± std against the truth, and when
the law switched. Then a load step while tracking: the smooth corridor on the bare robot, the box put on
at ``--step-at`` s (default 12): detection and re-estimation times, errors before / after.

    python benchmarks/payload_adaptation.py [--seeds 0 1 2] [--quick] [--json]

``--quick``: the smooth corridor only, one seed (about a minute).
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np

from drivers.config import load_robot_config
from otbot_hw.control.gains import gains_from_tstab
from otbot_hw.control.scenarios import build_spec, summarize
from otbot_hw.estimation.payload import PAYLOAD_NAMES, AdaptationConfig
from otbot_hw.params import nominal
from otbot_hw.runtime.backends import BusSimBackend
from otbot_hw.runtime.tracking import track
from otbot_hw.sensors import NoiseModel
from sim.load_schedule import LoadSchedule, with_loads

LOAD = (60.0, 0.15, -0.10, 1.0)


def window_errors(run, t_from: float) -> dict:
    """max / rms of |e_xy| (mm) and max |e_alpha| (mrad) of the true pose for reference time >= t_from (s),
    and max / rms |e_xy| of what the controller is fed (estimate - reference: the control alone, without
    the EKF's drift)."""
    m = run.t >= t_from
    if not m.any():  # the run stopped before (a fault: see "completed")
        nan = float("nan")
        return {"max_xy_mm": nan, "rms_xy_mm": nan, "max_alpha_mrad": nan, "fed_max_xy_mm": nan, "fed_rms_xy_mm": nan}
    exy = np.hypot(run.e_p[m, 0], run.e_p[m, 1]) * 1e3
    ea = np.abs(run.e_p[m, 2]) * 1e3
    out = {"max_xy_mm": float(exy.max()), "rms_xy_mm": float(np.sqrt(np.mean(exy ** 2))),
           "max_alpha_mrad": float(ea.max())}
    if run.est_pose is not None:
        fe = np.hypot(*(run.est_pose[m, :2] - run.p_ref[m, :2]).T) * 1e3
        out.update(fed_max_xy_mm=float(fe.max()), fed_rms_xy_mm=float(np.sqrt(np.mean(fe ** 2))))
    return out


def one(scenario: str, variant: str, seed: int, after: float, load=LOAD, schedule=None, feedback="ekf") -> dict:
    cfg = load_robot_config()
    base = nominal()
    truth = base.with_load(*load)
    spec = build_spec(scenario, base, cfg.limits)
    backend = BusSimBackend(cfg, NoiseModel.paper(), seed)
    plant = truth
    if schedule is not None:
        backend, plant = with_loads(backend, schedule), base
    ctrl = truth if variant == "true" else base
    adapt = AdaptationConfig.load().with_(enabled=True) if variant == "adapt" else None
    t0 = time.perf_counter()
    run = track(spec, ctrl, cfg.limits, gains_from_tstab(3.0), backend=backend, feedback=feedback, plant=plant,
                adapt=adapt)
    wall = time.perf_counter() - t0
    s = summarize(spec, run, cfg.limits, ctrl)
    out = {"scenario": scenario, "variant": variant, "seed": seed, "feedback": feedback, "completed": run.completed, "wall_s": wall,
           "after": window_errors(run, after), "after10": window_errors(run, 10.0), "whole": window_errors(run, 0.0),
           "settle_s": [e["settle_time_s"] for e in s["events"]],
           "peak_torque_Nm": [v["peak_Nm"] for v in s["peak_torque"].values()],
           "saturation": len(s["saturation"]),
           "saturation_ticks": int(sum(e["ticks"] for e in s["saturation"]))}
    if run.adapter is not None:
        ad = run.adapter
        origin = float(run.loop.recording.t[len(run.loop.recording.t) - len(run.t)])
        out["adaptation"] = ad.summary(origin)
        out["estimate"] = ad.payload_estimate()
        tv = dict(zip(PAYLOAD_NAMES, (truth.m_p, truth.I_p, truth.x_F, truth.y_F)))
        out["error_sigma"] = {n: (out["estimate"][n]["value"] - tv[n]) / out["estimate"][n]["std"]
                              for n in PAYLOAD_NAMES}
        out["truth"] = tv
    if schedule is not None and run.adapter is not None:
        t_step = schedule.entries[1][0] - origin
        ch = out["adaptation"]["changes"]
        t_re = ch[0]["reconverged_s"] if ch and ch[0]["reconverged_s"] is not None else None
        f = lambda m: float(np.hypot(run.e_p[m, 0], run.e_p[m, 1]).max() * 1e3) if m.any() else None  # noqa: E731
        out["phases"] = {"t_step_s": t_step, "before_mm": f((run.t >= 5.0) & (run.t < t_step)),
                         "step_to_reestimated_mm": f((run.t >= t_step) & (run.t < (t_re or run.t[-1]))),
                         "from_reestimated_plus_3s_mm": f(run.t >= t_re + 3.0) if t_re is not None else None}
    return out


def step_case(seed: int, step_at: float, variant: str = "adapt") -> dict:
    """The smooth corridor on the bare robot; the box put on at ``step_at`` s of plant time."""
    sched = LoadSchedule([(0.0, None), (step_at, LOAD)])
    return one("corridor-smooth", variant, seed, 5.0, schedule=sched)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--after", type=float, default=5.0, help="s of motion before the errors count (default 5)")
    ap.add_argument("--step-at", type=float, default=12.0)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    scenarios = ["corridor-smooth"] if a.quick else ["corridor", "corridor-smooth"]
    seeds = a.seeds[:1] if a.quick else a.seeds
    rows = [one(sc, v, sd, a.after, feedback=fb) for sc in scenarios for fb in ("ekf", "truth") for sd in seeds
            for v in ("file", "adapt", "true") if fb == "ekf" or sd == seeds[0]]
    steps = [step_case(sd, a.step_at) for sd in seeds]
    if a.json:
        print(json.dumps({"rows": rows, "step": steps}, default=float))
        return
    print(f"load {LOAD[0]:g} kg at ({LOAD[1]:g}, {LOAD[2]:g}) m, own inertia {LOAD[3]:g} kg m^2; bus sim 100 Hz, EKF; "
          f"errors of the true pose after {a.after:g} s of motion (whole run in brackets)")
    print("| scenario | feedback | seed | controller | max / rms e_xy (mm) | fed-back max / rms e_xy (mm) | after 10 s | "
          "max e_alpha (mrad) | settle per event (s) | "
          "peak torque r, l, p (N m) | saturation episodes (ticks) | converged / switched (s) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        e, w = r["after"], r["whole"]
        st = ", ".join("-" if v is None else f"{v:.2f}" for v in r["settle_s"]) or "n/a"
        ad = r.get("adaptation")
        cs = f"{ad['converged_s']:.2f} / {ad['switched_s']:.2f}" if ad and ad["converged_s"] is not None else (
            "not converged" if ad else "")
        fed = (f"{e['fed_max_xy_mm']:.3g} / {e['fed_rms_xy_mm']:.3g}" if r["feedback"] == "ekf" else "=")
        if not r["completed"]:
            print(f"| {r['scenario']} | {r['feedback']} | {r['seed']} | {r['variant']} | stopped by a fault |")
            continue
        print(f"| {r['scenario']} | {r['feedback']} | {r['seed']} | {r['variant']} | {e['max_xy_mm']:.3g} / "
              f"{e['rms_xy_mm']:.3g} ({w['max_xy_mm']:.3g} / {w['rms_xy_mm']:.3g}) | {fed} | {r['after10']['max_xy_mm']:.3g} / "
              f"{r['after10']['rms_xy_mm']:.3g} | {e['max_alpha_mrad']:.3g} ({w['max_alpha_mrad']:.3g}) "
              f"| {st} | {', '.join(f'{v:.1f}' for v in r['peak_torque_Nm'])} | {r['saturation']} "
              f"({r['saturation_ticks']}) | {cs} |")
    print()
    print("| scenario | feedback | seed | " + " | ".join(f"{n} estimate ± std (truth, error/std)" for n in PAYLOAD_NAMES) + " |")
    print("|---|---|---|" + "---|" * len(PAYLOAD_NAMES))
    for r in rows:
        if "estimate" not in r:
            continue
        cells = [f"{r['estimate'][n]['value']:.4g} ± {r['estimate'][n]['std']:.2g} ({r['truth'][n]:.4g}, "
                 f"{r['error_sigma'][n]:+.1f})" for n in PAYLOAD_NAMES]
        print(f"| {r['scenario']} | {r['feedback']} | {r['seed']} | " + " | ".join(cells) + " |")
    print()
    print(f"load step: the box put on at t = {a.step_at:g} s (plant time) on the smooth corridor")
    for s in steps:
        ad = s["adaptation"]
        ph = s["phases"]
        print(f"seed {s['seed']}: box at {ph['t_step_s']:.2f} s (reference time), changes {ad['changes']}; max e_xy "
              f"before {ph['before_mm']:.3g} mm, box to re-estimated {ph['step_to_reestimated_mm']:.3g} mm, from "
              f"re-estimated + 3 s on {ph['from_reestimated_plus_3s_mm']} mm; "
              f"final estimate " + ", ".join(f"{n} {s['estimate'][n]['value']:.4g} ± {s['estimate'][n]['std']:.2g}"
                                             for n in PAYLOAD_NAMES) + f"; wall {s['wall_s']:.1f} s")


if __name__ == "__main__":
    main()
