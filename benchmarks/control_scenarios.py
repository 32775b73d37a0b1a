"""Scenario report: the paper's test cases and their robustness variants, as markdown tables.

    python benchmarks/control_scenarios.py [--plot DIR] [--json]

Runs corridor, corridor-smooth, figure8 and planned (closed loop at 1 kHz, nominal parameters,
motor limits from config/robot.yaml) with both robustness variants; prints the tables of
docs/control.md. Takes about a minute on 2 cores.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from otbot_hw.control.scenarios import SCENARIOS  # noqa: E402
from otbot_hw.motors import load_motor_limits  # noqa: E402
from otbot_hw.params import nominal  # noqa: E402
from otbot_hw.runtime.tracking import run_scenario  # noqa: E402


def fmt_settle(events) -> str:
    vals = [e["settle_time_s"] for e in events]
    return ", ".join("-" if v is None else f"{v:.2f}" for v in vals) or "n/a"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--plot", type=Path, default=None)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    params, limits = nominal(), load_motor_limits()
    results = {}
    for name in SCENARIOS:
        print(f"[scenarios] {name} ...", file=sys.stderr, flush=True)
        results[name] = run_scenario(name, params, limits, plot_dir=args.plot)
    if args.json:
        print(json.dumps(results))
        return
    print("| scenario | variant | max / rms e_x (mm) | max / rms e_y (mm) | max e_alpha (rad) | max e_v xy (mm/s) "
          "| settle per event (s) | peak torque r, l, p (N m) |")
    print("|---|---|---|---|---|---|---|---|")
    for name, r in results.items():
        rows = [("nominal", r)] + list(r.get("robustness", {}).items())
        for variant, d in rows:
            m, q = d["max_abs_error"], d["rms_error"]
            pt = ", ".join(f"{v['peak_Nm']:.1f}" for v in d["peak_torque"].values())
            print(f"| {name} | {variant} | {m['x'] * 1e3:.3g} / {q['x'] * 1e3:.3g} | {m['y'] * 1e3:.3g} / "
                  f"{q['y'] * 1e3:.3g} | {m['alpha']:.2g} | {max(m['x_dot'], m['y_dot']) * 1e3:.3g} | "
                  f"{fmt_settle(d['events'])} | {pt} |")
    print()
    f8 = results["figure8"]["events"]
    print("figure8 settle after each force's end, isolated runs (s): "
          + ", ".join(f"{e['settle_time_isolated_s']:.3f}" for e in f8))
    pl = results["planned"]
    print(f"planned: {pl['planner']['duration_s']:.2f} s plan, IPOPT {pl['planner']['solve_time_s']:.2f} s; "
          f"open loop final error {pl['open_loop']['final_position_error_m']:.3f} m, "
          f"collisions {[(c['obstacle'], round(c['t_start'], 2)) for c in pl['open_loop'].get('collisions', [])]}; "
          f"closed loop collisions {len(pl.get('collisions', []))}; share of samples within the paper's figures "
          + ", ".join(f"{k} {v:.3f}" for k, v in pl["fraction_within"].items()))
    for name, r in results.items():
        fz = r["feasibility"]
        print(f"feasibility {name}: feasible={fz['feasible']}, peak bound "
              + ", ".join(f"{v:.1f}" for v in fz["peak_bound_Nm"].values()) + " N m"
              + (f", first violation {fz['violations'][0]}" if fz["violations"] else ""))
        if r.get("saturation"):
            print(f"saturation {name}: {len(r['saturation'])} episodes at "
                  + ", ".join(f"{s['t_start']:.2f} s {s['motor']}" for s in r["saturation"]))


if __name__ == "__main__":
    main()
