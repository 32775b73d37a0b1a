"""Speed benchmarks of two checkouts, run interleaved, with a before/after table.

Each benchmark script is run as its own process from each checkout's root (so that
checkout's code, and its own copy of the script, is what runs), the two checkouts
alternating A B B A A B ... so that the load of other jobs on a shared machine hits both
alike; every run is `nice`d the same. The numbers compared are the numeric leaves of the
script's `--json` output (or, for a script without `--json`, the numbers of its printed
lines, keyed by the line's label). Per number: the median over the repeats of each
checkout, the ratio after / before, and the noise = the larger relative spread
((max - min) / median) of the two checkouts' repeats; a number "moved" when the ratio is
further from 1 than that noise and than ``--min-change`` (5 %), and the two checkouts' ranges do not overlap.

    python benchmarks/compare_refs.py --before ../before --after . --rounds 3 [--only model,bus]
    python benchmarks/compare_refs.py --load results.json          # reprint a saved run

A warm-up run of each benchmark in each checkout comes first and is discarded (numba's
on-disk cache is per source path, so a fresh checkout compiles on its first run).
`--json` prints one JSON object (the raw values per run as well as the table);
`--save FILE` writes it after every run, so an interrupted comparison keeps what it has.
Exit 2 on bad arguments (a checkout without `otbot_hw/`, an unknown benchmark name).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent

#: name -> (script, arguments, output kind). Reduced sizes: each run takes seconds to ~1 min.
BENCHES: dict[str, tuple[str, list[str], str]] = {
    "model": ("model.py", ["--repeat", "3", "--json"], "json"),
    "estimation": ("estimation.py", ["--repeat", "2", "--json"], "json"),
    "control": ("control.py", ["--json"], "json"),
    "imu_parser": ("imu_parser.py", ["--sentences", "20000", "--reads", "1000", "--json"], "json"),
    "bus": ("bus.py", ["--cycles", "1000", "--json"], "json"),
    "daemon_parts": ("daemon_parts.py", ["--calls", "2000", "--json"], "json"),
    "identification": ("identification.py", ["--seeds", "3", "--skip-sweep"], "text"),
    "loop": ("loop.py", ["--rates", "100,250", "--skip-bus-1khz", "--json"], "json"),
    "loop_cycle": ("loop_cycle.py", ["--rate", "500", "--seconds", "10", "--json"], "json"),
    "direct_cpu": ("-c", [], "json"),  # DIRECT_CPU below
}

#: Process CPU per cycle (us) of the 30 s corridor's first 10 s through the loop runner on the direct
#: back end at 1 kHz, truth feedback (exact sensors; like the robot: encoders, IMU 100 Hz, paper noise),
#: and of ``DirectSimRobot`` write + read alone; best of 3. CPU time, which the load of other jobs
#: distorts less than wall time. Uses what ``benchmarks/loop.py`` has in both checkouts.
DIRECT_CPU = """
import json, os, sys, time
sys.path.insert(0, os.getcwd()); sys.path.insert(0, os.path.join(os.getcwd(), "benchmarks"))
from loop import robot_alone, runner
from drivers.config import load_robot_config
from otbot_hw.control.scenarios import corridor_spec
from otbot_hw.params import nominal
from otbot_hw.runtime.backends import DirectBackend
from otbot_hw.sensors import NoiseModel
params, cfg = nominal(), load_robot_config()
ref = corridor_spec().reference
runner(ref, params, cfg.limits, DirectBackend(), "truth", duration=0.2)
out = {}
for name, make in (("runner_exact_us", lambda: DirectBackend(rate=1000.0, imu_rate=None)),
                   ("runner_like_robot_us", lambda: DirectBackend.from_config(cfg, 1000.0, NoiseModel.paper()))):
    best = float("inf")
    for _ in range(3):
        t0 = time.process_time()
        run = runner(ref, params, cfg.limits, make(), "truth", duration=10.0)
        best = min(best, (time.process_time() - t0) / run.loop.stats.cycles * 1e6)
    out[name] = best
robot_alone(params, 100)
best = float("inf")
for _ in range(3):
    t0 = time.process_time()
    robot_alone(params, 10000)
    best = min(best, (time.process_time() - t0) / 10000 * 1e6)
out["direct_robot_alone_us"] = best
print(json.dumps(out))
"""
#: scripts that time the checkout in the current folder, so the newer copy may time an older
#: checkout that lacks them
CWD_SCRIPTS = {"loop_cycle.py"}

_NUM = re.compile(r"[-+]?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")


def flatten(obj, prefix: str = "") -> dict[str, float]:
    """Numeric leaves of a JSON value, keyed by their path (`a.b[2].c`); a string leaf
    gives each number in it (`key#0`, `key#1`, ...)."""
    out: dict[str, float] = {}
    if isinstance(obj, bool) or obj is None:
        return out
    if isinstance(obj, (int, float)):
        if math.isfinite(obj):
            out[prefix] = float(obj)
        return out
    if isinstance(obj, str):  # "4.95 s wall (165 us per cycle)": every number, #k
        for k, m in enumerate(_NUM.finditer(obj)):
            out[f"{prefix}#{k}"] = float(m.group())
        return out
    if isinstance(obj, dict):
        for k, v in obj.items():
            out.update(flatten(v, f"{prefix}.{k}" if prefix else str(k)))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            out.update(flatten(v, f"{prefix}[{i}]"))
    return out


def text_numbers(text: str) -> dict[str, float]:
    """Numbers of printed lines, keyed `label#k`: the label is the line's first cell (a
    table row) or its text before the first number; k counts the numbers in the line."""
    out: dict[str, float] = {}
    for line in text.splitlines():
        line = line.strip()
        if not line or set(line) <= set("|-: "):
            continue
        cells = [c.strip() for c in line.strip("|").split("|")] if "|" in line else None
        label = cells[0] if cells else _NUM.split(line, 1)[0].strip()
        body = " | ".join(cells[1:]) if cells else line[len(label):]
        for k, m in enumerate(_NUM.finditer(body)):
            out[f"{label or line[:30]}#{k}"] = float(m.group())
    return out


def run_one(tree: Path, name: str, nice: int, timeout: float) -> dict[str, float]:
    """One run of benchmark `name` in checkout `tree`: its numbers, or {} if it failed."""
    script, args, kind = BENCHES[name]
    if script == "-c":
        cmd = ["nice", "-n", str(nice), sys.executable, "-c", DIRECT_CPU]
    else:
        path = tree / "benchmarks" / script
        if not path.exists():
            if script not in CWD_SCRIPTS:
                return {}
            path = HERE / script
        cmd = ["nice", "-n", str(nice), sys.executable, str(path), *args]
    try:
        proc = subprocess.run(cmd, cwd=tree, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        print(f"  {name} @ {tree}: timed out after {timeout:.0f} s", file=sys.stderr)
        return {}
    if proc.returncode not in (0, 1):  # 1: some scripts' "target missed"
        tail = (proc.stderr.strip().splitlines() or ["?"])[-1]
        print(f"  {name} @ {tree}: exit {proc.returncode}: {tail}", file=sys.stderr)
        return {}
    if kind == "text":
        return text_numbers(proc.stdout)
    try:
        start = proc.stdout.index("{")
        return flatten(json.loads(proc.stdout[start:]))
    except ValueError:
        print(f"  {name} @ {tree}: no JSON on stdout", file=sys.stderr)
        return {}


def loadavg() -> float:
    return os.getloadavg()[0]


def summarize(runs: dict, min_change: float = 0.05) -> dict:
    """Per benchmark and number: medians, ratio, noise, moved (ranges disjoint and the ratio further from
    1 than both the noise and ``min_change``)."""
    table: dict[str, list[dict]] = {}
    for name, sides in runs.items():
        before, after = sides.get("before", []), sides.get("after", [])
        keys = [k for k in (after[0] if after else {}) if before and all(k in r for r in before + after)]
        rows = []
        for key in keys:
            b = [r[key] for r in before]
            a = [r[key] for r in after]
            mb, ma = statistics.median(b), statistics.median(a)
            spread = max((max(v) - min(v)) / abs(m) if m else 0.0 for v, m in ((b, mb), (a, ma)))
            ratio = ma / mb if mb else (1.0 if ma == mb else math.inf)
            disjoint = min(a) > max(b) or max(a) < min(b)
            moved = disjoint and abs(ratio - 1.0) > max(spread, min_change)
            rows.append(dict(key=key, before=mb, after=ma, ratio=ratio, noise=spread, moved=moved,
                             n_before=len(b), n_after=len(a)))
        table[name] = rows
    return table


def print_table(table: dict, keys: re.Pattern | None) -> None:
    for name, rows in table.items():
        rows = [r for r in rows if keys is None or keys.search(r["key"])]
        if not rows:
            continue
        print(f"\n### {name}\n")
        print("| number | before (median) | after (median) | after / before | noise (spread) | moved |")
        print("|---|---|---|---|---|---|")
        for r in rows:
            print(f"| {r['key']} | {r['before']:.4g} | {r['after']:.4g} | {r['ratio']:.3f} | "
                  f"{100 * r['noise']:.0f} % | {'**yes**' if r['moved'] else ''} |")


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):
        """One line, exit 2 (the project's rule for bad input)."""
        print(f"{self.prog}: error: {message}", file=sys.stderr)
        sys.exit(2)


def main() -> int:
    ap = _Parser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--before", type=Path, help="checkout of the code before (its root folder)")
    ap.add_argument("--after", type=Path, default=HERE.parent, help="checkout after (default: this one)")
    ap.add_argument("--only", default="", help=f"comma list of {', '.join(BENCHES)} (default: all)")
    ap.add_argument("--rounds", type=int, default=3, help="measured runs per checkout (default 3)")
    ap.add_argument("--no-warmup", action="store_true", help="skip the discarded first run per checkout")
    ap.add_argument("--nice", type=int, default=10, help="nice level of every run (default 10)")
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds per run (default 900)")
    ap.add_argument("--keys", default=None, help="regular expression: only numbers whose key matches")
    ap.add_argument("--save", type=Path, default=None, help="write the raw runs to this JSON file as they come")
    ap.add_argument("--load", type=Path, default=None, help="reprint the table of a saved JSON file")
    ap.add_argument("--min-change", type=float, default=0.05,
                    help="smallest relative change called moved, whatever the noise (default 0.05)")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    args = ap.parse_args()

    try:
        keys = re.compile(args.keys) if args.keys else None
    except re.error as exc:
        ap.error(f"--keys: not a regular expression: {exc}")
    if args.load is not None:
        try:
            saved = json.loads(args.load.read_text())
            runs = saved["runs"]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            ap.error(f"--load {args.load}: not a saved comparison ({exc})")
        table = summarize(runs, args.min_change)
        if args.json:
            print(json.dumps(dict(saved, table=table), indent=1))
        else:
            print_table(table, keys)
        return 0
    if args.before is None:
        ap.error("--before is required (or --load)")
    for label, tree in (("--before", args.before), ("--after", args.after)):
        if not (tree / "otbot_hw").is_dir():
            ap.error(f"{label} {tree}: not a checkout (no otbot_hw/ folder)")
    names = [n.strip() for n in args.only.split(",") if n.strip()] or list(BENCHES)
    unknown = [n for n in names if n not in BENCHES]
    if unknown:
        ap.error(f"--only: unknown benchmark(s) {', '.join(unknown)} (known: {', '.join(BENCHES)})")
    if args.rounds < 1:
        ap.error("--rounds must be >= 1")

    trees = {"before": args.before.resolve(), "after": args.after.resolve()}
    runs: dict = {n: {"before": [], "after": []} for n in names}
    meta = dict(trees={k: str(v) for k, v in trees.items()}, rounds=args.rounds, nice=args.nice,
                started=time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()), load=[])

    def save() -> None:
        if args.save is not None:
            args.save.write_text(json.dumps(dict(meta, runs=runs), indent=1))

    for name in names:
        if not args.no_warmup:
            for side in ("before", "after"):
                run_one(trees[side], name, args.nice, args.timeout)
        for i in range(args.rounds):
            order = ("before", "after") if i % 2 == 0 else ("after", "before")
            for side in order:
                load0 = loadavg()
                t0 = time.perf_counter()
                values = run_one(trees[side], name, args.nice, args.timeout)
                meta["load"].append(dict(bench=name, side=side, round=i, load_before=load0,
                                         load_after=loadavg(), seconds=time.perf_counter() - t0))
                if values:
                    runs[name][side].append(values)
                print(f"  {name} round {i} {side}: {len(values)} numbers, load {load0:.1f}, "
                      f"{time.perf_counter() - t0:.0f} s", file=sys.stderr)
                save()
    meta["finished"] = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())
    save()
    table = summarize(runs, args.min_change)
    if args.json:
        print(json.dumps(dict(meta, runs=runs, table=table), indent=1))
    else:
        loads = [x["load_before"] for x in meta["load"]]
        if loads:
            print(f"load average (1 min) at the runs' starts: {min(loads):.1f}-{max(loads):.1f}")
        print_table(table, keys)
    return 0


if __name__ == "__main__":
    sys.exit(main())
