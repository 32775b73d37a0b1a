"""Mutation probe of the safety chain: plausible bugs put in one at a time, each must make the
tests that pin it fail (issue 12, item 7; issue 18, item 8).

Each mutation replaces one piece of source text in a copy of the tree (the checkout itself is
never touched) and runs the named tests there; the table says which mutations the tests caught.

    .venv/bin/python benchmarks/mutation_probe.py [--only NAME ...] [--markdown]
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

T_TIMING = "tests/test_bus_timing.py"
T_REACT = "tests/test_bus_reaction.py"
T_UNITS = "tests/test_bus_units.py"
T_FAULTS = "tests/test_bus_faults.py"
T_EDS = "tests/test_bus_eds.py"
T_INJ = "tests/test_bus_injection.py"
T_INDEP = "tests/test_independent_drive.py"
T_BUS = "tests/test_bus.py"
T_PINS = "tests/test_pins.py"

#: name, file, text, replacement (or lists of them, all applied), tests that must fail
MUTATIONS = [
    ("heartbeat timeout 1.5x too long", "drivers/heartbeat.py", "if now - w.last > w.timeout:",
     "if now - w.last > 1.5 * w.timeout:", [T_TIMING]),
    ("heartbeat check period 10x too slow", "drivers/heartbeat.py",
     "period = min(w.timeout for w in self._watch.values()) / 10",
     "period = min(w.timeout for w in self._watch.values())", [T_TIMING]),
    ("stale-TPDO window 5x too long (realtime)", "drivers/cyclic.py", "TPDO_WINDOW = 0.8", "TPDO_WINDOW = 4.0",
     [T_TIMING]),
    ("stale-TPDO wait 5x too long (lockstep)", "sim/lockstep.py", "LOCKSTEP_SETTLE = 0.05",
     "LOCKSTEP_SETTLE = 0.25", [T_TIMING]),
    ("stale fault one SYNC late", "drivers/cyclic.py", "if self._misses[key] == n_max:",
     "if self._misses[key] == n_max + 1:", [T_REACT]),
    ("close() without return to PRE-OPERATIONAL", "drivers/robot.py",
     "lambda dev=dev: dev.nmt_command(NMT_ENTER_PRE_OPERATIONAL))", "lambda dev=dev: None)", [T_REACT]),
    ("close() without stopping the heartbeat watcher", "drivers/robot.py",
     "        self.heartbeats.stop()\n        try:\n            with self._cycle_lock:",
     "        try:\n            with self._cycle_lock:", [T_REACT]),
    ("a node leaving OPERATIONAL without rebooting is no fault", "drivers/heartbeat.py",
     "elif w.rebooted or (w.expected is not None and w.state is not None\n"
     "                                    and w.state not in (w.expected, w.previous)):",
     "elif w.rebooted:", [T_REACT]),
    ("the driver's 0x6072 clamp removed", "drivers/cia402.py",
     "        return max(-self.max_permille, min(self.max_permille, pm))", "        return pm", [T_REACT]),
    ("IMU mounting applied untransposed in the plant", "sim/plant.py",
     "self.imu.publish(self.mounting.T @ acc, self.mounting.T @ gyro)",
     "self.imu.publish(self.mounting @ acc, self.mounting @ gyro)", [T_UNITS]),
    ("encoder direction dropped", "drivers/cia406.py", "return self.cfg.direction * self._counts",
     "return self._counts", [T_UNITS]),
    ("encoder gear ratio dropped", "drivers/cia406.py", "(self.units_per_rev * self.cfg.gear_ratio)",
     "(self.units_per_rev)", [T_UNITS]),
    ("wrong 0.1 rpm factor in the driver", "drivers/config.py", '"0.1 rpm": 2 * np.pi / 600',
     '"0.1 rpm": 2 * np.pi / 60', [T_UNITS]),
    ("drive gear ratio dropped in the simulated velocity", "sim/canopen_slaves/drive.py",
     "revs_per_s = self.cfg.polarity * phi_dot * self.cfg.gear_ratio / (2 * math.pi)",
     "revs_per_s = self.cfg.polarity * phi_dot / (2 * math.pi)", [T_UNITS]),
    ("reaction does not keep SYNC alive", "drivers/reaction.py", "                arrived = self._sync_cycle(spaced=True)\n"
     "                rec[\"cycles\"] += 1\n                off = self._off_bus()",
     "                arrived = set()\n                rec[\"cycles\"] += 1\n                off = self._off_bus()",
     [T_REACT]),
    ("no disable after the confirmed quick stop", "drivers/reaction.py",
     "                    for d in self.drives:\n                        d.stage_disable()",
     "                    for d in self.drives:\n                        d.stage_quick_stop()", [T_REACT]),
    ("no NMT STOP for a drive that does not confirm", "drivers/reaction.py", "d.nmt_command(NMT_STOP)",
     "None", [T_REACT]),
    ("$VNERR while streaming ignored", "drivers/imu.py", 'elif item.header == "VNERR" and not self._in_command:',
     'elif False:', [T_REACT]),
    ("PDO mapping not read back", "drivers/device.py", "            mapping.verify_pdos(self, plan)",
     "            pass", [T_EDS]),
    ("the drives do not watch the master's heartbeat", "sim/canopen_slaves/drive.py",
     "        if (index, subindex) == (0x1016, 1):", "        if False:", [T_TIMING]),
    ("the simulated slaves keep foreign frames on their TPDO IDs", "sim/canopen_slaves/node.py",
     ["                    m.data = bytearray((m.length + 7) // 8)\n", "            if m.on_message in subs:"],
     ["", "            if False:"], [T_FAULTS]),
    ("fault-bit without a statusword check", "drivers/cia402.py", "        if state in FAULT_STATES:\n"
     "            if not self._fault_reported:", "        if False:\n            if not self._fault_reported:",
     [T_REACT]),
    # issue 18 (drivers side): pinned against the independent drive and the vendor mapping layouts
    ("0x605A not configured (a drive's own quick stop undone by the word in flight)", "drivers/cia402_setup.py",
     "        self.configure_quick_stop_option()\n", "", [T_INDEP]),
    ("a drive the master quick-stopped reported as leaving by itself", "drivers/cia402.py",
     '        return ("OPERATION ENABLED", *STOPPED_STATES)', '        return ("OPERATION ENABLED",)', [T_INDEP]),
    ("the master's own NMT STOP taken for a node fault", "drivers/reaction.py",
     '                        self.heartbeats.expect_node(d.node_id, "STOPPED")', "                        pass",
     [T_INDEP]),
    ("close() leaves a node it stopped in STOPPED, its 0x1016 on", "drivers/robot.py",
     "        off = self._off_bus() - self._nmt_stopped", "        off = self._off_bus() | self._nmt_stopped",
     [T_INDEP]),
    ("heartbeat not withheld when the loop stalls", "drivers/robot.py", "alive=self._loop_alive)", "alive=None)",
     [T_INDEP]),
    ("reaction one SYNC short of bus.reaction_timeout", "drivers/reaction.py",
     "        if quick_stop:\n            for _ in range(n_max):",
     "        if quick_stop:\n            for _ in range(n_max - 1):", [T_INDEP]),
    ("const entry count planned like a writable one", "drivers/mapping.py",
     "capacity = min(len(subs), count) if count_fixed and not fixed else len(subs)", "capacity = len(subs)",
     [T_EDS]),
    ("read-back takes empty entries for objects", "drivers/mapping.py",
     "            carried = [e for e in entries if e != (0, 0, 0)]", "            carried = list(entries)", [T_EDS]),
    ("a paced bus-config run without the SYNC/RPDO watchdogs", "otbot_hw/runtime/backends.py",
     "robot = CanopenRobot(config, imu=imu)", "robot = CanopenRobot(config.unpaced(), imu=imu)", [T_BUS]),
    # issue 18 item 8: places a planted bug survived the suite, pinned in tests/test_pins.py
    ("supervisor joint rate without abs (backwards never latches)", "otbot_hw/runtime/supervisor.py",
     "if lim is not None and not abs(w[i]) <= lim:", "if lim is not None and not w[i] <= lim:", [T_PINS]),
    ("workspace y checked against the x bounds", "otbot_hw/runtime/supervisor.py",
     "if not (x0 <= x <= x1 and y0 <= y <= y1):", "if not (x0 <= x <= x1 and x0 <= y <= x1):", [T_PINS]),
    ("MCAP sample log_time truncated, not rounded", "otbot_hw/recording/writer.py",
     "        self._last_t = t\n        stamp = int(round(t * 1e9))", "        self._last_t = t\n        stamp = int(t * 1e9)",
     [T_PINS]),
    ("MCAP event log_time in microseconds", "otbot_hw/recording/writer.py",
     "        stamp = int(round(t * 1e9))\n        data = json.dumps({", "        stamp = int(round(t * 1e6)) * 1000\n"
     "        data = json.dumps({", [T_PINS]),
    ("gyro-bias walk per step, not per second (IMU prediction)", "otbot_hw/estimation/kernels.py",
     "Q[BG, BG] = bg_walk2 * dt", "Q[BG, BG] = bg_walk2 * 0.01", [T_PINS]),
    ("gyro-bias walk per step, not per second (model prediction)", "otbot_hw/estimation/model_prediction.py",
     "Q[BG, BG] = self._var[2] * dt", "Q[BG, BG] = self._var[2] * 0.01", [T_PINS]),
    ("excitation gate at 5 % instead of 50 %", "otbot_hw/identification/gates.py",
     "min_fit_percent: float = 50.0", "min_fit_percent: float = 5.0", [T_PINS]),
    ("excitation gate always passes", "otbot_hw/identification/gates.py",
     "ok = bool(best >= lim.min_fit_percent)", "ok = True", [T_PINS]),
]


def copy_tree(dst: Path) -> None:
    files = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout.split()
    for f in files:
        src = ROOT / f
        if src.is_file():
            (dst / f).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dst / f)


def probe(name, file, old, new, tests, tree: Path) -> dict:
    path = tree / file
    original = path.read_text()
    olds, news = ([old], [new]) if isinstance(old, str) else (old, new)
    mutated = original
    for o, n in zip(olds, news):
        if o not in mutated:
            return {"name": name, "caught": None, "note": "text not found (source changed?)"}
        mutated = mutated.replace(o, n, 1)
    path.write_text(mutated)
    t0 = time.monotonic()
    try:
        env = {**os.environ, "PYTHONPATH": str(tree)}
        r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", *tests], cwd=tree,
                           env=env, capture_output=True, text=True)
    finally:
        path.write_text(original)
    last = (r.stdout.strip().splitlines() or [""])[-1]
    return {"name": name, "caught": r.returncode != 0, "tests": tests, "result": last,
            "seconds": time.monotonic() - t0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", nargs="*", default=None, help="run only mutations whose name contains one of these")
    ap.add_argument("--markdown", action="store_true")
    args = ap.parse_args()
    todo = [m for m in MUTATIONS if not args.only or any(o in m[0] for o in args.only)]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tree = Path(tmp)
        copy_tree(tree)
        for m in todo:
            print(f"[probe] {m[0]}", file=sys.stderr, flush=True)
            rows.append(probe(*m, tree))
            print(f"[probe]   {'caught' if rows[-1]['caught'] else 'MISSED'}: {rows[-1].get('result', '')}",
                  file=sys.stderr, flush=True)
    print("| mutation | pinned by | caught |")
    print("|---|---|---|")
    for r in rows:
        print(f"| {r['name']} | {', '.join(Path(t).name for t in r.get('tests', []))} | "
              f"{'yes' if r['caught'] else ('no' if r['caught'] is False else r['note'])} |")
    missed = [r for r in rows if not r["caught"]]
    print(f"\n{len(rows) - len(missed)} of {len(rows)} caught.")
    sys.exit(1 if missed else 0)


if __name__ == "__main__":
    main()
