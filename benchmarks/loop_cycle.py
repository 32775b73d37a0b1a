"""One daemon cycle's CPU work, in process: ``otbot daemon --bus sim`` (the plant behind python-can's
virtual bus in the same process) at a control rate, enabled and driven around a 0.5 m circle in
velocity mode (a new twist every 0.1 s), telemetry and recording on — as benchmarks/daemon.py
``--in-process`` does, but measured from inside.

    python benchmarks/loop_cycle.py [--rate 500] [--seconds 30] [--profile FILE] [--label NAME] [--json]
    (cd /work/main && python /path/to/benchmarks/loop_cycle.py ...)   # another checkout's code

The code measured is the checkout in the current directory when it holds ``otbot_hw`` (so the same
script times the code before and after a change in one session), else this script's checkout.

Per cycle, on the loop thread, CPU time (``time.thread_time``: what the thread ran, not what it
waited; a loaded machine stretches it far less than wall time): ``read`` = ``robot.read()`` (SYNC
out, then what the loop thread does with the frames once they are in), ``compute + write`` = from
``read()``'s return to ``write()``'s (EKF, supervisor, recording, law, limiter, RPDOs), ``work`` =
their sum (the master's cycle work excluding the wait for frames). Cycles without a write (the
first, unpowered ones) are left out. Sections of it, timed the same way: the EKF step, the
supervisor's check, the recording's loop side, the limiter, the loop's timing bookkeeping and the
CAN sends (SYNC and RPDOs: python-can's virtual bus copies each frame for its receivers, which a
real bus's send does not; *work less virtual-bus sends* takes them out cycle by cycle). The plant's
SYNC handler (the simulated drives' latch and TPDOs, the IMU sample, the model step), CPU per SYNC.
Besides, per thread of the process, CPU time per cycle over the window, and their sum (the
interpreter's whole load per cycle: in process, one lock runs one thread at a time): the master's CAN notifier (which decodes the TPDOs: the rest of the master's work), the
plant's (the simulated drives: not the master's), heartbeats, telemetry, ...; and the loop's own
timing from ``status`` (period, overruns: wall time, distorted by the machine's load).

Work is also split by cycles whose snapshot brought a new IMU sample (100 Hz: one cycle in eight at 800
Hz; they run the IMU's parse and the gyro update) and the others. ``--yardstick S`` (default 10 s, first):
the machine's own tail, a fixed piece of pure-Python work paced at the rate on the same CPUs and priority
(``benchmarks/machine_tail.py``): the work's p99 cannot beat its p99 / p50 ratio on the same machine.

Also: the garbage collections in the window (``gc``: per generation the count, the longest in µs and the
threads they ran on), and ``--record-in-background``: the daemon's ``LoopRunner`` with
``record_in_background=True`` (the recording written by a ``recording-writer`` thread).

``--profile FILE``: pyinstrument on the loop thread over the window (text: wall time, call tree);
``--flame PNG`` with it: the cycle's call tree as a flame graph (``benchmarks/flame_graph.py``);
``--cprofile FILE``: cProfile on the loop thread, in ``FILE.plant.txt`` on the plant's CAN receive
thread and in ``FILE.master_rx.txt`` on the master's (wall time per function, waits included); either slows the cycle, so the timing of a
profiled run is not representative.
"""
from __future__ import annotations

import argparse
import contextlib
import gc
import json
import math
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path.cwd() if (Path.cwd() / "otbot_hw").is_dir() else Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

#: as benchmarks/daemon.py: overruns counted, not a fault; heartbeat consumers given 0.5 s (a stall of
#: the shared machine ends no measurement)
RELAX = {"max_consecutive_overruns: {value: 5": "max_consecutive_overruns: {value: 1000000000",
         "master_heartbeat_consumer: {value: 100, unit: ms}": "master_heartbeat_consumer: {value: 500, unit: ms}",
         "heartbeat_consumer: {value: 200, unit: ms}": "heartbeat_consumer: {value: 500, unit: ms}"}


def _request(sock: Path, cmd: str, **args):
    from otbot_hw.runtime.control_client import ControlClient

    with ControlClient(sock, timeout=10.0) as c:
        return c.request(cmd, args or None)


def _loop_call(daemon, fn):
    """Run ``fn`` on the daemon's loop thread between two cycles."""
    if hasattr(daemon, "_loop_call"):  # older daemons
        return daemon._loop_call(fn)
    return daemon.mailbox.call(fn, timeout=5.0)


class _Probe:
    """Wraps the robot's read/write (instance attributes: the runner looks them up each cycle) and
    keeps the loop thread's CPU times per cycle."""

    def __init__(self, robot, n: int):
        self.robot = robot
        self.read_cpu = np.full(n, np.nan)
        self.work_cpu = np.full(n, np.nan)
        self.fresh_imu = np.zeros(n, bool)  # the cycle's snapshot brought a new IMU sample
        self._imu_time = self._fresh = None
        self.k = 0
        self.n = n
        self._t_ask = self._t_read = 0.0
        self._read, self._write = robot.read, robot.write
        self.active = False
        self.loop_ident = None
        self.sections: dict[str, list] = {}  # name -> [per-cycle CPU (s), this cycle's sum so far]

    def read(self):
        t0 = time.thread_time()
        s = self._read()
        self._t_ask, self._t_read = t0, time.thread_time()
        self._fresh = s.imu_time is not None and s.imu_time != self._imu_time
        self._imu_time = s.imu_time
        if self.loop_ident is None:
            self.loop_ident = threading.get_ident()
        return s

    def write(self, u):
        c = self._write(u)
        t = time.thread_time()
        if self.active and self.k < self.n and self._t_read:
            self.read_cpu[self.k] = self._t_read - self._t_ask
            self.work_cpu[self.k] = t - self._t_ask
            self.fresh_imu[self.k] = self._fresh
            for acc in self.sections.values():
                acc[0][self.k] = acc[1]
            self.k += 1
        for acc in self.sections.values():
            acc[1] = 0.0
        self._t_read = 0.0
        return c

    def install(self):
        self.robot.read, self.robot.write = self.read, self.write

    def section(self, obj, attr: str, name: str) -> None:
        """Also time ``obj.attr`` (an instance attribute replaces it): loop-thread CPU per cycle."""
        fn = getattr(obj, attr)
        acc = self.sections.setdefault(name, [np.full(self.n, np.nan), 0.0])

        def timed(*a, **kw):
            t0 = time.thread_time()
            try:
                return fn(*a, **kw)
            finally:
                acc[1] += time.thread_time() - t0

        setattr(obj, attr, timed)


def _thread_cpu() -> dict[str, float]:
    """CPU seconds per live thread of this process, by name (same names summed)."""
    out: dict[str, float] = {}
    for th in threading.enumerate():
        if th.ident is None:
            continue
        try:
            c = time.clock_gettime(time.pthread_getcpuclockid(th.ident))
        except (OSError, AttributeError):
            continue
        out[th.name] = out.get(th.name, 0.0) + c
    return out


def run(rate: float, seconds: float, folder: Path, profile: Path | None = None, cprofile: Path | None = None,
        record_in_background: bool = False, flame: Path | None = None) -> dict:
    from otbot_hw.cli import build_parser
    from otbot_hw.cli.daemon import prepare
    from otbot_hw.runtime.daemon_process import local_config

    cfg = local_config(folder / "cfg", replace={**RELAX, "control_rate: {value: 100, unit: Hz}":
                                                f"control_rate: {{value: {rate:g}, unit: Hz}}"})
    (folder / "rec").mkdir()
    sock = folder / "control.sock"
    args = build_parser().parse_args(["daemon", "--bus", "sim", "--config", str(cfg), "--socket", str(sock),
                                      "--record-dir", str(folder / "rec"), "--telemetry", "127.0.0.1:0"])
    if record_in_background:  # the recording-writer thread variant (LoopRunner's record_in_background)
        import otbot_hw.runtime.daemon as daemon_mod

        base = daemon_mod.LoopRunner

        class BackgroundRunner(base):
            def __init__(self, *a, **kw):
                super().__init__(*a, record_in_background=True, **kw)

        daemon_mod.LoopRunner = BackgroundRunner
    daemon, opener = prepare(args)
    summary: dict = {}
    prof_box: dict = {}

    def serve():
        if profile is not None:
            from pyinstrument import Profiler

            prof_box["p"] = Profiler(interval=0.0002)
        summary.update(daemon.serve(opener))

    th = threading.Thread(target=serve, name="loop", daemon=True)
    th.start()
    end = time.monotonic() + 60
    while (daemon.runner is None or daemon.mode == "starting") and time.monotonic() < end:
        time.sleep(0.05)
    if daemon.runner is None:
        raise RuntimeError("the daemon did not start")
    robot = daemon.robot
    n = int(seconds * rate * 1.5) + 100
    probe = _Probe(robot, n)
    probe.install()
    runner = daemon.runner
    for obj, attr, name in ((runner.feedback, "step", "estimator (EKF step)"),
                            (runner.supervisor, "check", "supervisor check"),
                            (runner, "_record", "recording (loop side)"),
                            (runner.supervisor, "limit", "limiter"),
                            (runner, "_timing", "loop timing"),
                            (robot.network.bus, "send", "CAN send (virtual bus)")):
        probe.section(obj, attr, name)
    if hasattr(robot.network.bus, "send_frames"):  # several frames in one call (a cycle's RPDOs): CAN sends too
        probe.section(robot.network.bus, "send_frames", "CAN send (virtual bus)")  # (same name: same sum)
    # parts of read() and of the command (where the checkout has them)
    for obj, attr, name in ((robot, "_await_tpdos", "read: TPDO wait (CPU)"),
                            (robot, "_read_imu", "read: IMU"),
                            (getattr(robot, "heartbeats", None), "check", "read: heartbeat check"),
                            (runner, "_command", "command (law, limiter, RPDOs)")):
        if obj is not None and hasattr(obj, attr):
            probe.section(obj, attr, name)
    if daemon.telemetry is not None:  # after the cycle (the daemon's _after_cycle), not in read -> write
        name = "publish_cycle" if hasattr(daemon.telemetry, "publish_cycle") else "publish"  # (code before: publish)
        probe.section(daemon.telemetry, name, "telemetry publish (after the write)")
    plant_sync, plant_k = np.full(n, np.nan), [0]  # the plant's SYNC handler (simulated drives + model step)
    plant = getattr(robot, "plant", None)
    if plant is not None and hasattr(plant, "_on_sync"):
        handler, subs = plant._on_sync, plant.network.subscribers.get(0x80, [])

        def timed_sync(*a):
            t0 = time.thread_time()
            try:
                return handler(*a)
            finally:
                if probe.active and plant_k[0] < n:
                    plant_sync[plant_k[0]] = time.thread_time() - t0
                    plant_k[0] += 1

        subs[:] = [timed_sync if cb == handler else cb for cb in subs]
    _request(sock, "enable")
    time.sleep(1.0)  # the hold settles
    notifier_threads = set()
    with contextlib.suppress(Exception):
        notifier_threads = {t.name for t in robot.network.notifier._readers if isinstance(t, threading.Thread)}
    if profile is not None:  # start the profiler on the loop thread, between two cycles
        _loop_call(daemon, lambda: prof_box["p"].start())
    if cprofile is not None:  # cProfile, enabled on the loop thread: that thread only
        import cProfile

        prof_box["c"] = cProfile.Profile()
        _loop_call(daemon, prof_box["c"].enable)
        plant = getattr(robot, "plant", None)
        # the plant's receive thread and the master's: each enabled from inside its thread, at its next frame
        for key, net in (("plant", plant.network if plant is not None else None), ("master_rx", robot.network)):
            if net is None:
                continue
            prof_box[key] = cProfile.Profile()

            def notify_once(*a, net=net, key=key, notify=net.notify):
                del net.notify  # back to the class's method
                prof_box[key].enable()
                return notify(*a)

            net.notify = notify_once
    gc_log: list = []  # (generation, thread name, seconds) of each collection in the window
    gc_t0: dict = {}

    def on_gc(phase, info):
        if not probe.active:
            return
        if phase == "start":
            gc_t0[threading.get_ident()] = time.perf_counter()
        elif threading.get_ident() in gc_t0:
            gc_log.append((info["generation"], threading.current_thread().name,
                           time.perf_counter() - gc_t0.pop(threading.get_ident())))

    gc.callbacks.append(on_gc)
    cpu0 = _thread_cpu()
    st0 = _request(sock, "status")
    probe.active = True
    t0 = time.monotonic()
    commands = 0
    while time.monotonic() - t0 < seconds:
        a = 0.4 * (time.monotonic() - t0)
        _request(sock, "velocity", vx=0.2 * math.cos(a), vy=0.2 * math.sin(a), wz=0.0)
        commands += 1
        time.sleep(0.1)
    probe.active = False
    gc.callbacks.remove(on_gc)
    wall = time.monotonic() - t0
    st = _request(sock, "status")
    cpu1 = _thread_cpu()
    row_flame = None
    if profile is not None:
        p = prof_box["p"]
        _loop_call(daemon, p.stop)
        profile.write_text(p.output_text(unicode=False, color=False, show_all=False))
        if flame is not None:
            from flame_graph import cycle_flame

            row_flame = cycle_flame(p.last_session, flame, f"loop thread, {rate:g} Hz, {seconds:g} s, in process "
                                    f"(otbot daemon --bus sim), pyinstrument every 0.2 ms of wall time")
    if cprofile is not None:
        import io
        import pstats

        _loop_call(daemon, prof_box["c"].disable)
        for key, what, dest in (("c", "the loop thread", cprofile),
                                ("plant", "the plant's CAN receive thread", cprofile.with_suffix(".plant.txt")),
                                ("master_rx", "the master's CAN receive thread",
                                 cprofile.with_suffix(".master_rx.txt"))):
            if key not in prof_box:
                continue
            out = io.StringIO()
            stats = pstats.Stats(prof_box[key], stream=out)
            out.write(f"cProfile of {what}, {rate:g} Hz, {wall:.0f} s (wall time per function, waits included; "
                      f"profiling itself slows each call)\n")
            stats.sort_stats("tottime").print_stats(40)
            stats.sort_stats("cumulative").print_stats(50)
            dest.write_text(out.getvalue().replace(str(ROOT) + "/", ""))
    load = os.getloadavg()[0]
    _request(sock, "shutdown")
    th.join(30)
    loop, loop0 = st["loop"], st0["loop"]
    cycles = loop["cycles"] - loop0["cycles"]
    per = {name: (cpu1[name] - cpu0.get(name, 0.0)) / max(cycles, 1) for name in cpu1}
    main_name = threading.current_thread().name
    master_rx = sum(v for k, v in per.items() if k in notifier_threads)
    others = {k: v for k, v in per.items() if k not in notifier_threads and k != main_name}
    us = lambda a, q: float(np.nanpercentile(a, q) * 1e6)  # noqa: E731
    k = probe.k
    r, w = probe.read_cpu[:k], probe.work_cpu[:k]
    sends = probe.sections["CAN send (virtual bus)"][0][:k]  # the simulated transport's share of the work
    return {"rate": rate, "seconds": wall, "cycles": cycles, "measured": k, "commands": commands,
            "read_p50_us": us(r, 50), "read_p99_us": us(r, 99),
            "compute_write_p50_us": us(w - r, 50), "compute_write_p99_us": us(w - r, 99),
            "work_p50_us": us(w, 50), "work_p99_us": us(w, 99), "work_max_us": us(w, 100),
            "work_imu_cycles_p50_p99_us": (us(w[probe.fresh_imu[:k]], 50), us(w[probe.fresh_imu[:k]], 99)),
            "work_other_cycles_p50_p99_us": (us(w[~probe.fresh_imu[:k]], 50), us(w[~probe.fresh_imu[:k]], 99)),
            "imu_cycle_share": float(np.mean(probe.fresh_imu[:k])),
            "work_less_sends_p50_us": us(w - sends, 50), "work_less_sends_p99_us": us(w - sends, 99),
            "master_rx_us_per_cycle": master_rx * 1e6,
            "plant_sync_p50_us": us(plant_sync[:plant_k[0]], 50), "plant_sync_p99_us": us(plant_sync[:plant_k[0]], 99),
            "process_us_per_cycle": sum(v for k2, v in per.items() if k2 != main_name) * 1e6,
            "sections_p50_p99_us": {name: (us(acc[0][:k], 50), us(acc[0][:k], 99))
                                    for name, acc in probe.sections.items()},
            "threads_us_per_cycle": {k2: round(v * 1e6, 1) for k2, v in sorted(others.items(), key=lambda x: -x[1])
                                     if v > 0},
            "overruns": loop["overruns"] - loop0["overruns"],
            "overruns_per_min": (loop["overruns"] - loop0["overruns"]) / (wall / 60.0),
            "period_p99_ms": None if loop["period"]["p99"] is None else 1e3 * loop["period"]["p99"],
            "gc": {f"gen{g}": {"count": sum(1 for x in gc_log if x[0] == g),
                               "max_us": max((x[2] * 1e6 for x in gc_log if x[0] == g), default=0.0),
                               "total_us_per_cycle": sum(x[2] for x in gc_log if x[0] == g) * 1e6 / max(cycles, 1),
                               "threads": sorted({x[1] for x in gc_log if x[0] == g})} for g in range(3)},
            "fault": (st.get("faults") or [None])[0], "load": load, "flame_top_shares": row_flame}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rate", type=float, default=500.0, help="control rate (Hz)")
    ap.add_argument("--seconds", type=float, default=30.0, help="measured window (s)")
    ap.add_argument("--profile", type=Path, default=None, help="write a pyinstrument text profile of the loop thread")
    ap.add_argument("--flame", type=Path, default=None, metavar="PNG",
                    help="with --profile: a flame graph of LoopRunner.cycle (benchmarks/flame_graph.py)")
    ap.add_argument("--cprofile", type=Path, default=None,
                    help="write a cProfile table (by own time, then cumulative) of the loop thread")
    ap.add_argument("--record-in-background", action="store_true",
                    help="the daemon's LoopRunner with record_in_background=True (a recording-writer thread)")
    ap.add_argument("--cpus", default=None, metavar="LIST",
                    help="run the process (every thread) on these CPUs, e.g. 1 (as the unit's CPUAffinity=)")
    ap.add_argument("--fifo", type=int, default=None, metavar="PRIORITY",
                    help="SCHED_FIFO at this priority for every thread (as the unit's CPUSchedulingPolicy=fifo)")
    ap.add_argument("--yardstick", type=float, default=10.0, metavar="SECONDS",
                    help="first, this long: the machine's own tail (benchmarks/machine_tail.py: a fixed piece of "
                         "pure-Python work paced at --rate, placed as the daemon; 0: skip)")
    ap.add_argument("--label", default=str(ROOT), help="what the row is called")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    if a.flame is not None and a.profile is None:
        ap.error("--flame needs --profile FILE")
    if not (a.yardstick >= 0 and math.isfinite(a.yardstick)):
        ap.error(f"argument --yardstick: must be >= 0 s and finite, got {a.yardstick!r}")
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from machine_tail import place, tail

    why = place(a.cpus, a.fifo)  # before any thread starts: every thread inherits it
    if why:
        ap.error(why)
    load0 = os.getloadavg()[0]
    print(f"{a.label}: {a.rate:g} Hz for {a.seconds:g} s (load average {load0:.1f}) ...", file=sys.stderr, flush=True)
    yard = None
    if a.yardstick > 0:  # the machine's tail for fixed work, placed as the daemon (same CPUs, same priority)
        yard = tail(a.rate, a.yardstick, 3000)
    with tempfile.TemporaryDirectory(prefix="otbot-cycle-") as tmp:
        row = run(a.rate, a.seconds, Path(tmp), a.profile, a.cprofile, a.record_in_background, a.flame)
    row["label"] = a.label
    row["cpus"], row["fifo"] = a.cpus, a.fifo
    row["load_before"] = load0  # 1-min load average at the start; "load": at the window's end
    row["yardstick"] = yard
    if a.json:
        print(json.dumps(row))
        return 0
    print("| code | rate (Hz) | cycles | work p50 / p99 / max (us) | work less virtual-bus sends p50 / p99 (us) "
          "| read p50 / p99 (us) | compute + write p50 / p99 (us) | master CAN receive (us per cycle) | overruns (per min) "
          "| load avg (before, end) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    print(f"| {row['label']} | {row['rate']:g} | {row['measured']} | {row['work_p50_us']:.0f} / "
          f"{row['work_p99_us']:.0f} / {row['work_max_us']:.0f} | {row['work_less_sends_p50_us']:.0f} / "
          f"{row['work_less_sends_p99_us']:.0f} | {row['read_p50_us']:.0f} / {row['read_p99_us']:.0f} | "
          f"{row['compute_write_p50_us']:.0f} / {row['compute_write_p99_us']:.0f} | "
          f"{row['master_rx_us_per_cycle']:.0f} | {row['overruns']} ({row['overruns_per_min']:.0f}) | "
          f"{row['load_before']:.1f}, {row['load']:.1f} |")
    print(f"\nwork on cycles with a new IMU sample ({100 * row['imu_cycle_share']:.1f} % of them) p50 / p99: "
          f"{row['work_imu_cycles_p50_p99_us'][0]:.0f} / {row['work_imu_cycles_p50_p99_us'][1]:.0f} us; on the others: "
          f"{row['work_other_cycles_p50_p99_us'][0]:.0f} / {row['work_other_cycles_p50_p99_us'][1]:.0f} us")
    if yard is not None:
        print(f"the machine's tail (benchmarks/machine_tail.py, fixed work at {a.rate:g} Hz for {a.yardstick:g} s): "
              f"CPU p50 / p99 {yard['cpu_p50_us']:.0f} / {yard['cpu_p99_us']:.0f} us, p99 / p50 "
              f"{yard['cpu_p99_over_p50']:.2f}")
    print("\nloop-thread sections, CPU p50 / p99 (us): " + ", ".join(
        f"{k}: {v[0]:.0f} / {v[1]:.0f}" for k, v in row["sections_p50_p99_us"].items()))
    print(f"\nplant SYNC handler (simulated drives, IMU, model step) CPU p50 / p99: {row['plant_sync_p50_us']:.0f} / "
          f"{row['plant_sync_p99_us']:.0f} us; all threads but the benchmark's own: "
          f"{row['process_us_per_cycle']:.0f} us of CPU per cycle ({row['rate']:g} Hz: "
          f"{1e6 / row['rate']:.0f} us period)")
    print("\nother threads, CPU us per cycle: "
          + ", ".join(f"{k}: {v}" for k, v in row["threads_us_per_cycle"].items()))
    if row["fault"]:
        print(f"fault: {row['fault']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
