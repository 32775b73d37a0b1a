"""Calibration of the diagnosis on clean recordings: how often does it find something that is not there?

Every recording here comes from a robot that is exactly the parameter file (no effect, paper sensor
noise), so every "model inadequate", named effect or ambiguous group is a false finding. The
recordings come from generators the diagnosis's rules were not tuned on:

* **simulators**: ``independent`` (``benchmarks/independent_robot.py``: own 9x9 dynamics, adaptive
  RK45, own sensor model and MCAP writer; floor only) and ``project`` (``otbot_hw.simulation.runs``:
  the project's simulator and sensor model with 4096*4*10-count encoders; floor, stand, locked);
  closed-loop runs come from ``otbot track ... --sim`` (computed-torque tracking with EKF feedback
  through the loop runner, recorded by the loop); ``daemon``: sessions of the on-robot daemon
  (``otbot daemon --bus sim`` in-process, real time: enable, random velocity commands with EKF
  feedback, stop), its own session recording; ``bus``: the open-loop families played through the
  CANopen drivers against the simulated robot on virtual CAN (``otbot run --bus sim``'s path, with the
  supervisor and motor limits; a run the supervisor stops is replayed at half the torque);
* **excitation families**: the paper's constant torques (``constant``), random piecewise-constant
  torques with three hold ranges (``piecewise_short`` 0.15-0.8 s +-4 N m, ``piecewise_long``
  0.4-1.2 s +-8 N m -- the case of issue 20 --, ``piecewise_slow`` 1-3 s +-6 N m), ``multisine``
  (5 random sines 0.1-2 Hz per motor), ``prbs`` (+-A switched at random on a 50-200 ms clock),
  ``chirp`` (0.05 Hz up to 1-4 Hz), ``closed_loop`` (``otbot track corridor`` / ``corridor-smooth``,
  no external forces), ``closed_loop_independent`` (the independent robot tracking a random platform
  twist with its own PI loop on its noisy encoder rates, torques through J^T, no model: 3-30 s, 100-200 Hz);
* **lengths** 1-60 s and **rates** 100-1000 Hz (at most 3000 samples per recording -- 2000 from the
  independent simulator, whose adaptive RK45 per interval is slow -- so that the study fits the
  machine: a 30 s run is recorded at 100 Hz, a 1000 Hz run is 1-3 s long; longer records are in
  ``benchmarks/diagnose.py``'s timing); **fixtures** floor / stand / locked (the stand and locked-wheel runs with the smaller
  torques those set-ups take).

A recording is diagnosed alone (no held-out run). Results are appended to a JSON-lines file as they
come (an interrupted study keeps what it did); ``--doc`` writes the table between the CALIBRATION
markers of docs/diagnose.md.

    nice .venv/bin/python benchmarks/diagnose_calibration.py --count 500 --per-family 50 --workers 1 --doc
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

#: the families of the first plan (``plan``: indices 0..count-1, cycling through these)
PLAN_FAMILIES = ("constant", "piecewise_short", "piecewise_long", "piecewise_slow", "multisine", "prbs", "chirp",
                 "closed_loop")
#: the recording paths added after it (``plan_paths``: indices from PATH_INDEX[family]): daemon sessions
#: (velocity sessions with EKF feedback, in real time), the simulated CAN bus (open-loop excitations
#: of the other families played through the CANopen drivers) and the independent robot's own closed loop
#: (``independent_robot.closed_loop``: a PI on its noisy encoder-measured twist, no model)
PATH_INDEX = {"daemon": 10000, "sim_bus": 20000, "closed_loop_independent": 30000}
FAMILIES = PLAN_FAMILIES + tuple(PATH_INDEX)
OPEN_LOOP = ("constant", "piecewise_short", "piecewise_long", "piecewise_slow", "multisine", "prbs", "chirp")
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
    excitation: str = ""  # sim_bus: the open-loop family played over the bus


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
        family = PLAN_FAMILIES[i % len(PLAN_FAMILIES)]
        if family == "closed_loop":
            out.append(Spec(i, "track", family, 0.0, float(rng.choice((100.0, 200.0))), "floor", int(seed0 + i)))
            continue
        sim = "independent" if (i // len(PLAN_FAMILIES)) % 2 == 0 else "project"
        fixture = "floor" if sim == "independent" else str(rng.choice(("floor", "floor", "stand", "locked")))
        while True:
            duration, rate = float(rng.choice(lengths)), float(rng.choice(rates))
            if duration * rate <= MAX_SAMPLES and (sim == "project" or duration * rate <= 2000):
                break  # the independent simulator (adaptive RK45 per interval) is slow: <= 2000 samples
        out.append(Spec(i, sim, family, duration, rate, fixture, int(seed0 + i)))
    return out


def plan_paths(per_family: int, seed0: int = 0) -> list[Spec]:
    """``per_family`` recordings of each added path (deterministic): daemon velocity sessions of 3-10 s at
    100 Hz on the floor; the simulated bus at 100 or 200 Hz, 1-10 s, floor / stand / locked, cycling
    through the open-loop families."""
    rng = np.random.default_rng(20261126 + seed0)
    out = []
    for i in range(per_family):
        k = PATH_INDEX["daemon"] + i
        out.append(Spec(k, "daemon", "daemon", float(rng.choice((3.0, 5.0, 10.0))), 100.0, "floor", int(seed0 + k)))
    for i in range(per_family):
        k = PATH_INDEX["sim_bus"] + i
        fixture = str(rng.choice(("floor", "floor", "stand", "locked")))
        out.append(Spec(k, "bus", "sim_bus", float(rng.choice((1.0, 3.0, 10.0))), float(rng.choice((100.0, 200.0))),
                        fixture, int(seed0 + k), OPEN_LOOP[i % len(OPEN_LOOP)]))
    rng = np.random.default_rng(20261127 + seed0)  # its own stream: the specs above stay as they were
    for i in range(per_family):
        k = PATH_INDEX["closed_loop_independent"] + i
        duration, rate = ((3.0, 100.0), (3.0, 200.0), (10.0, 100.0), (10.0, 200.0), (30.0, 100.0))[int(rng.integers(5))]
        out.append(Spec(k, "independent", "closed_loop_independent", duration, rate, "floor", int(seed0 + k)))
    return out


def record_bus(spec: Spec, path: Path) -> Path:
    """The open-loop excitation ``spec.excitation`` played through the CANopen drivers against the simulated
    robot on virtual CAN (``otbot run --bus sim``'s path: ``BusSimBackend``, the loop runner, the supervisor
    with the motor limits), paper noise; the drives' encoders and the pivot encoder as configured."""
    from otbot_hw.cli.checks import bus_config
    from otbot_hw.params import nominal
    from otbot_hw.recording import source_metadata
    from otbot_hw.runtime.backends import BusSimBackend
    from otbot_hw.runtime.openloop import run_torques
    from otbot_hw.sensors import NoiseModel

    from otbot_hw.runtime.daemon_process import local_config

    cfg = bus_config(local_config(path.parent / "cfg", replace=SHARED_MACHINE), spec.rate)
    cfg = cfg.replace_bus(interface="virtual", channel=f"otbot-cal-{os.getpid()}")
    U = excitation(spec.excitation, spec.duration, 1.0 / spec.rate, spec.seed, spec.fixture)
    params = nominal()
    for scale in BUS_SCALES:  # the supervisor stopped the run at a joint-rate limit: as an operator would, less torque
        with BusSimBackend(cfg, NoiseModel.paper(), spec.seed + 1000).open(params, fixture=spec.fixture) as robot:
            res = run_torques(robot, scale * U, cfg.limits, None, path,
                              {"fixture": spec.fixture, **source_metadata(simulated=True, bus=True),
                               "noise": NoiseModel.paper().to_dict(), "seed": spec.seed + 1000,
                               "params": params.to_dict(), "excitation_scale": scale})
        if res.completed:
            return path
    raise RuntimeError(f"bus run stopped by fault: {res.fault}")


BUS_SCALES = (1.0, 0.5, 0.25)  # excitation amplitude tried in turn when the supervisor stops a bus run


#: a machine shared with other jobs (load 10-25 on 2 cores) delays the simulated drives' heartbeats and the loop:
#: the tests' relaxed timeouts (tests/test_daemon.py RELAXED_SLCAN), so that no run stops for a reason it does not test
SHARED_MACHINE = {"master_heartbeat_consumer: {value: 100, unit: ms}": "master_heartbeat_consumer: {value: 1000, unit: ms}",
                  "heartbeat_consumer: {value: 200, unit: ms}": "heartbeat_consumer: {value: 1000, unit: ms}",
                  "tpdo_timeout: {value: 2, unit: periods}": "tpdo_timeout: {value: 20, unit: periods}",
                  "reaction_timeout: {value: 2, unit: periods}": "reaction_timeout: {value: 20, unit: periods}"}
DAEMON_CONFIG = {**SHARED_MACHINE, "max_consecutive_overruns: {value: 5": "max_consecutive_overruns: {value: 50"}


def record_daemon(spec: Spec, folder: Path) -> Path:
    """A daemon session (``otbot daemon --bus sim`` in this process, the simulated robot on virtual CAN, EKF
    feedback): enable, velocity commands -- a random twist (|v| <= 0.3 m/s, |w| <= 0.6 rad/s) held 0.5-1.5 s,
    repeated at 5 Hz within the deadman -- for ``spec.duration`` s, stop (ramp to rest, hold) and shut down;
    the session's recording as the daemon wrote it. Runs in real time."""
    import threading

    from otbot_hw.cli import build_parser
    from otbot_hw.cli.daemon import prepare
    from otbot_hw.runtime.control_client import ControlClient
    from otbot_hw.runtime.daemon_process import local_config

    rng = np.random.default_rng(spec.seed)
    sock = folder / "c.sock"
    (folder / "rec").mkdir()
    cfg = local_config(folder / "cfg", replace=DAEMON_CONFIG)
    args = build_parser().parse_args(["daemon", "--bus", "sim", "--config", str(cfg), "--socket", str(sock),
                                      "--record-dir", str(folder / "rec"), "--no-telemetry", "--noise", "paper",
                                      "--seed", str(spec.seed + 1000), "--rate", f"{spec.rate:g}"])
    daemon, opener = prepare(args)
    summary: dict = {}
    thread = threading.Thread(target=lambda: summary.update(daemon.serve(opener)), daemon=True)
    thread.start()

    def ctl(cmd, **kw):
        with ControlClient(sock, timeout=10.0) as c:
            return c.request(cmd, kw or None)

    try:
        t_end = time.monotonic() + 60
        while not (daemon.runner is not None and daemon.mode not in ("starting",)) and time.monotonic() < t_end:
            time.sleep(0.05)
        ctl("enable")
        time.sleep(0.5)
        t_stop = time.monotonic() + spec.duration
        while time.monotonic() < t_stop:
            v = rng.uniform(0.0, 0.3) * np.array([np.cos(a := rng.uniform(0, 2 * np.pi)), np.sin(a)])
            twist = {"vx": float(v[0]), "vy": float(v[1]), "wz": float(rng.uniform(-0.6, 0.6))}
            t_next = min(time.monotonic() + rng.uniform(0.5, 1.5), t_stop)
            while time.monotonic() < t_next:
                ctl("velocity", **twist)
                time.sleep(0.2)
        ctl("stop")
        time.sleep(1.5)
        faults = ctl("status")["faults"]
        ctl("shutdown")
    finally:
        if thread.is_alive():
            daemon.request_stop("calibration run done")
        thread.join(60)
    if faults:
        raise RuntimeError(f"daemon session faulted: {faults}")
    files = sorted((folder / "rec").glob("*.mcap"))
    if len(files) != 1:
        raise RuntimeError(f"daemon session left {len(files)} recording files")
    return files[0]


def record(spec: Spec, folder: Path) -> Path:
    """Write the clean recording of ``spec`` and return its path."""
    path = folder / f"cal_{spec.index}_{spec.simulator}_{spec.family}.mcap"
    dt = 1.0 / spec.rate
    if spec.simulator == "daemon":
        return record_daemon(spec, folder)
    if spec.simulator == "bus":
        return record_bus(spec, path)
    if spec.simulator == "track":
        scenario = ("corridor", "corridor-smooth")[spec.seed % 2]
        cmd = [sys.executable, "-m", "otbot_hw", "track", scenario, "--sim", "--rate", f"{spec.rate:g}",
               "--seed", str(spec.seed), "--out", str(path), "--json"]
        res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=900)
        if not path.exists():
            raise RuntimeError(f"otbot track failed: {res.stderr.strip().splitlines()[-1:]}")
        return path
    if spec.family == "closed_loop_independent":
        import independent_robot as ir

        U, sens = ir.closed_loop(ir.Otbot(ir.load_params(), ir.World()), spec.duration, dt, spec.seed)
        ir.write_mcap(path, dt, U, sens, spec.fixture)
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
               not_identifiable=[x["name"] for x in r.get("not_identifiable", []) if x["kind"] == "parameter"],
               effects_not_identifiable=sum(x["kind"] == "effect" for x in r.get("not_identifiable", [])),
               diagnose_s=r["elapsed_s"], diagnose_cpu_s=r.get("cpu_s"), record_s=t1 - t0,
               total_s=time.perf_counter() - t0)
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
    for key, values in (("family", FAMILIES), ("simulator", ("independent", "project", "track", "daemon", "bus")),
                        ("fixture", ("floor", "stand", "locked")), ("rate", (100.0, 200.0, 500.0, 1000.0))):
        for v in values:
            lines.append(line(f"{key} {v:g}" if isinstance(v, float) else f"{key} {v}",
                              [r for r in done if r[key] == v]))
    for lo, hi in ((0, 2), (2, 12), (12, 61)):
        lines.append(line(f"length {lo}-{hi} s", [r for r in done if lo <= (r["duration"] or 18) < hi]))
    undetermined = [r for r in done if r.get("not_identifiable")]
    if undetermined:
        lines += ["", "Parameters reported \"not identifiable from this recording\" (on a bound, std too large; "
                  "not a finding): " + ", ".join(f"#{r['index']} {'/'.join(r['not_identifiable'])}"
                                                 for r in undetermined)]
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
    ap.add_argument("--per-family", type=int, default=0,
                    help="at most this many recordings per family: the first of the plan (--count) and of the "
                         "added paths (daemon, sim_bus); default: the plan only, all --count")
    ap.add_argument("--rerun", default="",
                    help="comma-separated indices whose rows are dropped from --out and run again (after a rule "
                         "change that can affect them)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "diagnose_calibration.jsonl",
                    help="JSON lines, appended as results come (rows already there are skipped)")
    ap.add_argument("--doc", action="store_true", help="write the table into docs/diagnose.md")
    ap.add_argument("--table-only", action="store_true", help="only write the table from --out")
    args = ap.parse_args()
    specs = plan(args.count, args.seed)
    if args.per_family:
        specs = [s for s in specs if s.index < args.count] + plan_paths(args.per_family, args.seed)
        specs = [s for f in FAMILIES for s in [x for x in specs if x.family == f][:args.per_family]]
    if args.families:
        keep = set(args.families.split(","))
        specs = [s for s in specs if s.family in keep]
    rows = []
    if args.out.exists():
        rows = [json.loads(x) for x in args.out.read_text().splitlines() if x.strip()]
    rerun = {int(x) for x in args.rerun.split(",") if x.strip()}
    if rerun and not args.table_only:
        rows = [r for r in rows if r["index"] not in rerun]
        args.out.write_text("".join(json.dumps(r) + "\n" for r in rows))
    done = {r["index"] for r in rows}
    todo = [s for s in specs if s.index not in done]
    # round robin over the families, so that an interrupted study has covered every family evenly
    rank = {}
    todo.sort(key=lambda s: (rank.setdefault(s.family, {}).setdefault(s.index, len(rank[s.family])),
                             FAMILIES.index(s.family)))
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
