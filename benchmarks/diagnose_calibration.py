"""Calibration of the diagnosis on clean recordings: how often does it find something that is not there?

Every recording here comes from a robot that is exactly the parameter file (no effect, paper sensor
noise), so every "model inadequate", named effect or ambiguous group is a false finding. The
recordings come from generators the diagnosis's rules were not tuned on:

* **simulators**: ``independent`` (``benchmarks/independent_robot.py``: own 9x9 dynamics, adaptive
  RK45, own sensor model and MCAP writer; floor only) and ``project`` (``otbot_hw.simulation.runs``:
  the project's simulator and sensor model with 4096*4*10-count encoders; floor, stand, locked);
  closed-loop runs come from ``otbot track ... --sim`` (computed-torque tracking with EKF feedback
  through the loop runner, recorded by the loop);
* **excitation families**: the paper's constant torques (``constant``), random piecewise-constant
  torques with three hold ranges (``piecewise_short`` 0.15-0.8 s +-4 N m, ``piecewise_long``
  0.4-1.2 s +-8 N m -- the case of issue 20 --, ``piecewise_slow`` 1-3 s +-6 N m), ``multisine``
  (5 random sines 0.1-2 Hz per motor), ``prbs`` (+-A switched at random on a 50-200 ms clock),
  ``chirp`` (0.05 Hz up to 1-4 Hz), ``closed_loop`` (``otbot track corridor`` / ``corridor-smooth``,
  no external forces);
* **lengths** 1-60 s and **rates** 100-1000 Hz (at most 3000 samples per recording -- 2000 from the
  independent simulator, whose adaptive RK45 per interval is slow -- so that the study fits the
  machine: a 30 s run is recorded at 100 Hz, a 1000 Hz run is 1-3 s long; longer records are in
  ``benchmarks/diagnose.py``'s timing); **fixtures** floor / stand / locked (the stand and locked-wheel runs with the smaller
  torques those set-ups take).

A recording is diagnosed alone (no held-out run). Results are appended to a JSON-lines file as they
come (an interrupted study keeps what it did); ``--doc`` writes the table between the CALIBRATION
markers of docs/diagnose.md.

    nice .venv/bin/python benchmarks/diagnose_calibration.py --count 500 --workers 2 --doc
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

FAMILIES = ("constant", "piecewise_short", "piecewise_long", "piecewise_slow", "multisine", "prbs", "chirp",
            "closed_loop")
MAX_SAMPLES = 3000
#: torque scale per fixture (wheels, wheels, pivot) relative to the floor's amplitudes
FIXTURE_SCALE = {"floor": np.array([1.0, 1.0, 1.0]), "stand": np.array([0.12, 0.12, 0.6]),
                 "locked": np.array([0.0, 0.0, 0.6])}


@dataclass
class Spec:
    """One clean recording: generator, excitation family, length (s), rate (Hz), fixture, seed."""

    index: int
    simulator: str
    family: str
    duration: float
    rate: float
    fixture: str
    seed: int


def excitation(family: str, duration: float, dt: float, seed: int, fixture: str = "floor") -> np.ndarray:
    """Torques (N, 3) N m of one family, held for dt each (see module doc)."""
    rng = np.random.default_rng(seed)
    n = max(1, int(round(duration / dt)))
    t = np.arange(n) * dt
    if family == "constant":  # the paper's experiments: each motor a constant torque
        U = np.tile(rng.uniform(-1, 1, 3) * np.array([8.0, 8.0, 4.0]), (n, 1))
    elif family.startswith("piecewise"):
        hold, amp = {"piecewise_short": ((0.15, 0.8), [4.0, 4.0, 2.5]),
                     "piecewise_long": ((0.4, 1.2), [8.0, 8.0, 8.0]),
                     "piecewise_slow": ((1.0, 3.0), [6.0, 6.0, 4.0])}[family]
        U = np.empty((n, 3))
        k = 0
        while k < n:
            h = max(1, int(rng.uniform(*hold) / dt))
            U[k:k + h] = rng.uniform(-1, 1, 3) * np.array(amp)
            k += h
    elif family == "multisine":
        U = np.empty((n, 3))
        for j, peak in enumerate((4.0, 4.0, 2.5)):
            s = sum(rng.uniform(0.3, 1.0) * np.sin(2 * np.pi * f * t + rng.uniform(0, 6.3))
                    for f in rng.uniform(0.1, 2.0, 5))
            U[:, j] = peak * s / max(np.max(np.abs(s)), 1e-9)
    elif family == "prbs":
        clock = rng.uniform(0.05, 0.2)
        m = max(1, int(round(clock / dt)))
        bits = rng.choice([-1.0, 1.0], size=((n + m - 1) // m, 3))
        U = np.repeat(bits, m, axis=0)[:n] * np.array([3.0, 3.0, 2.0])
    elif family == "chirp":
        f1 = rng.uniform(1.0, 4.0)
        f0 = 0.05
        T = max(duration, dt)
        phase = 2 * np.pi * (f0 * t + 0.5 * (f1 - f0) / T * t ** 2)
        U = np.column_stack([a * np.sin(phase + rng.uniform(0, 6.3)) for a in (4.0, 4.0, 2.5)])
    else:
        raise ValueError(f"unknown family {family}")
    return U * FIXTURE_SCALE[fixture]


def plan(count: int, seed0: int = 0) -> list[Spec]:
    """``count`` recordings spread over simulators, families, lengths, rates and fixtures (deterministic)."""
    rng = np.random.default_rng(20261125 + seed0)
    out = []
    lengths = (1.0, 3.0, 10.0, 30.0, 60.0)
    rates = (100.0, 200.0, 500.0, 1000.0)
    for i in range(count):
        family = FAMILIES[i % len(FAMILIES)]
        if family == "closed_loop":
            out.append(Spec(i, "track", family, 0.0, float(rng.choice((100.0, 200.0))), "floor", int(seed0 + i)))
            continue
        sim = "independent" if (i // len(FAMILIES)) % 2 == 0 else "project"
        fixture = "floor" if sim == "independent" else str(rng.choice(("floor", "floor", "stand", "locked")))
        while True:
            duration, rate = float(rng.choice(lengths)), float(rng.choice(rates))
            if duration * rate <= MAX_SAMPLES and (sim == "project" or duration * rate <= 2000):
                break  # the independent simulator (adaptive RK45 per interval) is slow: <= 2000 samples
        out.append(Spec(i, sim, family, duration, rate, fixture, int(seed0 + i)))
    return out


def record(spec: Spec, folder: Path) -> Path:
    """Write the clean recording of ``spec`` and return its path."""
    path = folder / f"cal_{spec.index}_{spec.simulator}_{spec.family}.mcap"
    dt = 1.0 / spec.rate
    if spec.simulator == "track":
        scenario = ("corridor", "corridor-smooth")[spec.seed % 2]
        cmd = [sys.executable, "-m", "otbot_hw", "track", scenario, "--sim", "--rate", f"{spec.rate:g}",
               "--seed", str(spec.seed), "--out", str(path), "--json"]
        res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=900)
        if not path.exists():
            raise RuntimeError(f"otbot track failed: {res.stderr.strip().splitlines()[-1:]}")
        return path
    U = excitation(spec.family, spec.duration, dt, spec.seed, spec.fixture)
    if spec.simulator == "independent":
        import independent_robot as ir

        robot = ir.Otbot(ir.load_params(), ir.World())
        sens = robot.sensors(robot.run(U, dt), np.random.default_rng(spec.seed + 1000))
        ir.write_mcap(path, dt, U, sens, spec.fixture)
        return path
    from otbot_hw.params import nominal
    from otbot_hw.recording import write_recording
    from otbot_hw.sensors import NoiseModel
    from otbot_hw.simulation.runs import simulated_recording

    noise = NoiseModel.paper()
    noise = type(noise)(**{**noise.to_dict(), "counts_per_rev": 4096 * 4 * 10})
    rec = simulated_recording(nominal(), U, dt, noise, seed=spec.seed + 1000, fixture=spec.fixture)
    write_recording(path, rec)
    return path


def run_one(spec: Spec) -> dict:
    """Record and diagnose one clean recording; the outcome and what was (wrongly) found."""
    from otbot_hw.diagnose.data import DiagnosisInputError, load
    from otbot_hw.diagnose.diagnosis import diagnose
    from otbot_hw.params import nominal

    t0 = time.perf_counter()
    row = asdict(spec)
    with tempfile.TemporaryDirectory() as tmp:
        try:
            path = record(spec, Path(tmp))
            t1 = time.perf_counter()
            data = load([path])
            row["samples"] = len(data[0])
            r = diagnose(data, nominal())
        except DiagnosisInputError as exc:  # too short / too quiet: refused, not a finding
            row.update(outcome="refused", reason=str(exc), total_s=time.perf_counter() - t0)
            return row
        except Exception as exc:  # noqa: BLE001 - a study row, not a crash
            row.update(outcome="error", reason=f"{type(exc).__name__}: {exc}", total_s=time.perf_counter() - t0)
            return row
    named = [e["name"] for e in r["effects"]] + ["{" + ",".join(c["name"] for c in g["candidates"]) + "}"
                                                 for g in r["ambiguous"]]
    false = (not r["model_adequate"]) or bool(named)
    worst = max(r["adequacy"]["channels"], key=lambda c: c["z"], default=None)
    row.update(outcome="false" if false else "clean", adequate=r["model_adequate"], named=named,
               withheld=[w["name"] for w in r["withheld"]], small=[e["name"] for e in r["detected_small"]],
               worst=None if worst is None else {k: worst[k] for k in ("channel", "noise_ratio", "limit", "samples")},
               on_bound=[b["parameter"] for b in r["adequacy"]["on_bound"]],
               moved=[m["parameter"] for m in r["adequacy"]["moved"]], tests=r["adequacy"]["tests"],
               diagnose_s=r["elapsed_s"], record_s=t1 - t0, total_s=time.perf_counter() - t0)
    return row


def clopper_pearson_upper(k: int, n: int, conf: float = 0.95) -> float:
    from scipy.stats import beta

    return 1.0 if k >= n else float(beta.ppf(conf, k + 1, n - k))


def table(rows: list[dict]) -> list[str]:
    done = [r for r in rows if r["outcome"] in ("clean", "false")]
    lines = [f"{len(rows)} clean recordings ({len(done)} diagnosed, "
             f"{sum(r['outcome'] == 'refused' for r in rows)} refused as too short/quiet, "
             f"{sum(r['outcome'] == 'error' for r in rows)} errors); a false finding is \"model inadequate\", a "
             "named effect or an ambiguous group; upper = one-sided 95 % Clopper-Pearson bound.", "",
             "| group | recordings | false findings | rate | upper 95 % | max diagnose time (s) |", "|---|---|---|---|---|---|"]

    def line(label, sel):
        n = len(sel)
        k = sum(r["outcome"] == "false" for r in sel)
        tmax = max((r.get("diagnose_s", 0.0) for r in sel), default=0.0)
        return (f"| {label} | {n} | {k} | {100 * k / n:.1f} % | {100 * clopper_pearson_upper(k, n):.1f} % | "
                f"{tmax:.1f} |") if n else f"| {label} | 0 | - | - | - | - |"

    lines.append(line("**all**", done))
    for key, values in (("family", FAMILIES), ("simulator", ("independent", "project", "track")),
                        ("fixture", ("floor", "stand", "locked")), ("rate", (100.0, 200.0, 500.0, 1000.0))):
        for v in values:
            lines.append(line(f"{key} {v:g}" if isinstance(v, float) else f"{key} {v}",
                              [r for r in done if r[key] == v]))
    for lo, hi in ((0, 2), (2, 12), (12, 61)):
        lines.append(line(f"length {lo}-{hi} s", [r for r in done if lo <= (r["duration"] or 18) < hi]))
    bad = [r for r in done if r["outcome"] == "false"]
    if bad:
        lines += ["", "False findings:", ""]
        for r in bad:
            lines.append(f"* #{r['index']} {r['simulator']} {r['family']} {r['duration']:g} s {r['rate']:g} Hz "
                         f"{r['fixture']}: adequate {r['adequate']}, named {r['named'] or '-'}, worst {r['worst']}, "
                         f"on bound {r['on_bound'] or '-'}, moved {r['moved'] or '-'}")
    return lines


def write_doc(lines: list[str]) -> None:
    doc = ROOT / "docs" / "diagnose.md"
    text = doc.read_text()
    begin, end = "<!-- CALIBRATION:BEGIN (written by benchmarks/diagnose_calibration.py) -->", "<!-- CALIBRATION:END -->"
    block = begin + "\n\n" + "\n".join(lines) + "\n\n" + end
    if begin in text:
        a, b = text.index(begin), text.index(end) + len(end)
        text = text[:a] + block + text[b:]
    else:
        text += "\n" + block + "\n"
    doc.write_text(text)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=500, help="clean recordings (default 500)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0, help="first seed of the plan")
    ap.add_argument("--families", default="", help="comma-separated families (default: all)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "diagnose_calibration.jsonl",
                    help="JSON lines, appended as results come (rows already there are skipped)")
    ap.add_argument("--doc", action="store_true", help="write the table into docs/diagnose.md")
    ap.add_argument("--table-only", action="store_true", help="only write the table from --out")
    args = ap.parse_args()
    specs = plan(args.count, args.seed)
    if args.families:
        keep = set(args.families.split(","))
        specs = [s for s in specs if s.family in keep]
    rows = []
    if args.out.exists():
        rows = [json.loads(x) for x in args.out.read_text().splitlines() if x.strip()]
    done = {r["index"] for r in rows}
    todo = [s for s in specs if s.index not in done]
    if not args.table_only:
        os.environ.setdefault("OMP_NUM_THREADS", "1")
        with ProcessPoolExecutor(args.workers) as ex, open(args.out, "a") as fh:
            futs = {ex.submit(run_one, s): s for s in todo}
            for f in as_completed(futs):
                row = f.result()
                rows.append(row)
                fh.write(json.dumps(row) + "\n")
                fh.flush()
                print(f"[{len(rows)}/{len(specs)}] #{row['index']} {row['simulator']} {row['family']} "
                      f"{row['duration']:g}s {row['rate']:g}Hz {row['fixture']}: {row['outcome']} "
                      f"{row.get('named') or ''} {row.get('worst') or ''} {row.get('total_s', 0):.1f}s", flush=True)
    lines = table(rows)
    print("\n".join(lines))
    if args.doc:
        write_doc(lines)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
