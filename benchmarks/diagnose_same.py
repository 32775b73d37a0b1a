"""Check that a speed-up of ``diagnose()`` changes no result: save the diagnosis JSON of a fixed set of
cases, then compare another checkout's against it (verdict, named effects, every number to 1e-6 relative).

Cases: the slow and typical ones of ``benchmarks/diagnose.py`` (independent check, seed pair 0), three
discovery cases of ``benchmarks/diagnose_discovery.py`` (linear drag, cogging, pivot dead zone; rep 0) and
(``--cases slow``) the slowest diagnoses of the issue-20 studies (``SLOW``: a traction limit and configured
casters under the paper's constant torques, the traction limit with a tanh and a hard-clip knee, the clean 30 s
stand multisine of the calibration study, #380).
``--conclusions``: compare only what the diagnosis concludes (verdict, named / ambiguous / withheld / small
effects, discovered laws; effect values within ``VALUE_RULE`` relative) -- for a speed-up that may move numbers.
Prints the process CPU time of each diagnosis (``time.process_time``: what the load of other jobs does not
change), its wall time and the load average before and after (the wall time is what a user waits for, on an
idle machine between CPU / 2 and CPU: the diagnosis predicts on two threads).

    .venv/bin/python benchmarks/diagnose_same.py --recordings DIR --save before.json
    .venv/bin/python benchmarks/diagnose_same.py --recordings DIR --compare before.json
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

INDEPENDENT = ["coulomb_wheels", "none", "caster+asymmetry", "traction_limit", "phantom_load"]
DISCOVERY = ["linear_drag", "cogging", "pivot_dead_zone"]
#: label: (case of benchmarks/diagnose_independent.py, excitation family of its fitting run, traction curve)
SLOW = {"traction_constant": ("traction_limit", "constant", "magic"),
        "caster_constant": ("caster_configured", "constant", "magic"),
        "traction_tanh": ("traction_limit", "piecewise", "tanh"),
        "traction_clip": ("traction_limit", "piecewise", "clip")}
CALIBRATION = {"clean_stand_multisine": 380}  # index in benchmarks/diagnose_calibration.py's plan(500)
VALUE_RULE = 0.2  # effect values of two diagnoses within this relative difference: the same conclusion
#: keys that measure time, not results
TIMING = {"elapsed_s", "cpu_s", "wall_s", "load", "regression_s"}


def _strip(x):
    """The diagnosis JSON without its timings."""
    if isinstance(x, dict):
        return {k: _strip(v) for k, v in x.items() if k not in TIMING}
    if isinstance(x, (list, tuple)):
        return [_strip(v) for v in x]
    return x


def diff(a, b, path="", rtol=1e-6) -> list[str]:
    """Differences between two stripped diagnoses (numbers to ``rtol`` relative)."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = [f"{path}.{k}: only in one" for k in set(a) ^ set(b)]
        for k in set(a) & set(b):
            out += diff(a[k], b[k], f"{path}.{k}", rtol)
        return out
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{path}: length {len(a)} != {len(b)}"]
        return [d for i, (u, v) in enumerate(zip(a, b)) for d in diff(u, v, f"{path}[{i}]", rtol)]
    if isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool):
        if (math.isnan(a) and math.isnan(b)) or math.isclose(a, b, rel_tol=rtol, abs_tol=1e-12):
            return []
        return [f"{path}: {a!r} != {b!r}"]
    return [] if a == b else [f"{path}: {a!r} != {b!r}"]


def cases(folder: Path, which: list[str]):
    """(label, fitting recordings, held-out, parameters, geometry) of each chosen case, recording what is missing."""
    import diagnose_discovery as dd
    import diagnose_independent as di
    from otbot_hw.diagnose.data import load
    from otbot_hw.params import nominal

    for c in di.CASES:
        if c.label in which:
            fit, held = folder / f"{c.label}_0_fit.mcap", folder / f"{c.label}_0_heldout.mcap"
            if not (fit.exists() and held.exists()):
                di.make_recordings(c, 0, folder)
            P, geometry = di.tool_inputs(c)
            yield c.label, load([fit]), load([held]), P, geometry
    for label in DISCOVERY:
        if label in which:
            fit, held = dd._record(folder, label, dd.LAWS[label][0], 0)
            yield label, load([fit]), load([held]), nominal(), None
    for label, (name, family, curve) in SLOW.items():
        if label in which:
            c = di.with_traction_curve(di.BY_LABEL[name], curve)
            sub = folder / label
            sub.mkdir(exist_ok=True)
            paths = [sub / f"{c.label}_0_{k}.mcap" for k in ("fit", "heldout")]
            if not all(p.exists() for p in paths):
                paths = di.make_recordings(c, 0, sub, di.DURATION, family)
            P, geometry = di.tool_inputs(c)
            yield label, load(paths[:1]), load(paths[1:]), P, geometry
    for label, index in CALIBRATION.items():
        if label in which:
            import diagnose_calibration as dc

            spec = dc.plan(500)[index]
            path = folder / f"cal_{spec.index}_{spec.simulator}_{spec.family}.mcap"
            if not path.exists():
                dc.record(spec, folder)
            yield label, load([path]), [], nominal(), None


def conclusions(r: dict) -> dict:
    """What a diagnosis concludes: verdict, effects by name (with their values), laws discovered."""
    def values(e):
        return {k: v["value"] for k, v in e["parameters"].items()}

    disc = r.get("discovered") or {}
    return {"model_adequate": r["model_adequate"],
            "effects": {e["name"]: values(e) for e in r["effects"]},
            "ambiguous": [[c["name"] for c in g["candidates"]] for g in r["ambiguous"]],
            "ambiguous_values": {c["name"]: values(c) for g in r["ambiguous"] for c in g["candidates"]},
            "withheld": {w["name"]: {k: v["value"] for k, v in w["parameters"].items()} for w in r["withheld"]},
            "small": sorted(e["name"] for e in r["detected_small"]),
            "laws": {lw["law"]: {k: v["value"] for k, v in (lw.get("refit") or {}).items()}
                     for lw in disc.get("laws", [])},
            "laws_improve": disc.get("improves")}


def diff_conclusions(a: dict, b: dict) -> tuple[list[str], list[str]]:
    """(differences in what is concluded, value changes within ``VALUE_RULE``) between two diagnoses."""
    ca, cb = conclusions(a), conclusions(b)
    out, moved = [], []
    for k in ("model_adequate", "ambiguous", "small", "laws_improve"):
        if ca[k] != cb[k]:
            out.append(f"{k}: {ca[k]!r} != {cb[k]!r}")
    for k in ("effects", "withheld", "laws", "ambiguous_values"):
        if set(ca[k]) != set(cb[k]):
            out.append(f"{k}: {sorted(ca[k])} != {sorted(cb[k])}")
            continue
        for name in ca[k]:
            for p, va in ca[k][name].items():
                vb = cb[k][name].get(p)
                if vb is None or va is None:
                    continue
                rel = abs(vb - va) / max(abs(va), 1e-12)
                if rel > 1e-6:
                    (out if rel > VALUE_RULE else moved).append(f"{k}.{name}.{p}: {va:.4g} -> {vb:.4g} ({100 * rel:+.1f} %)")
    return out, moved


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recordings", type=Path, required=True, help="folder of the recordings (made when missing)")
    ap.add_argument("--cases", default=",".join(INDEPENDENT + DISCOVERY))
    ap.add_argument("--save", type=Path)
    ap.add_argument("--warm", action="store_true", help="diagnose the case none once, untimed, before the timed "
                    "runs (numba's compiled kernels loaded)")
    ap.add_argument("--conclusions", action="store_true", help="with --compare: only what the diagnosis concludes "
                    "(verdict, effects, laws; values within VALUE_RULE), every value change listed")
    ap.add_argument("--compare", type=Path)
    args = ap.parse_args()
    from otbot_hw.diagnose.diagnosis import diagnose

    args.recordings.mkdir(parents=True, exist_ok=True)
    ref = json.loads(args.compare.read_text()) if args.compare else None
    out, bad = {}, 0
    which = args.cases.split(",")
    if "slow" in which:
        which += list(SLOW) + list(CALIBRATION) + ["linear_drag"]
    if args.warm:
        for label, fit, held, P, geometry in cases(args.recordings, ["none"]):
            diagnose(fit, P, held, geometry=geometry)
    for label, fit, held, P, geometry in cases(args.recordings, which):
        load_before = os.getloadavg()[0]
        t, w = time.process_time(), time.perf_counter()
        r = diagnose(fit, P, held, geometry=geometry)
        cpu, wall = time.process_time() - t, time.perf_counter() - w
        out[label] = {"cpu_s": cpu, "wall_s": wall, "load": [load_before, os.getloadavg()[0]],
                      "result": _strip(json.loads(json.dumps(r, default=float)))}
        msg = ""
        if ref and label in ref and args.conclusions:
            d, moved = diff_conclusions(ref[label]["result"], out[label]["result"])
            bad += bool(d)
            msg = f" (before {ref[label]['cpu_s']:.1f} s) " + ("SAME CONCLUSIONS" if not d else "DIFFERENT: " + "; ".join(d))
            msg += "".join(f"\n    moved: {m}" for m in moved)
        elif ref and label in ref:
            d = diff(ref[label]["result"], out[label]["result"])
            bad += bool(d)
            msg = f" (before {ref[label]['cpu_s']:.1f} s) " + ("SAME" if not d else "DIFFERENT: " + "; ".join(d[:5]))
        print(f"{label}: CPU {cpu:.1f} s, wall {wall:.1f} s (load {load_before:.1f} -> {os.getloadavg()[0]:.1f}){msg}",
              flush=True)
    if args.save:
        args.save.write_text(json.dumps(out, default=float))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
