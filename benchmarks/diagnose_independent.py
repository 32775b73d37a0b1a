"""Diagnose recordings made by an *independent* simulator (not the tool's extended model).

The tool's own study (diagnose_confusion.py) hides effects with the same compiled
extended model the tool fits. Here every recording is made independently of
``otbot_hw/model/effects.py``, ``otbot_hw/sensors.py`` and ``otbot_hw/recording.py``:

* dynamics: the conventional 9x9 Lagrange system with multipliers built from the numpy
  matrices of ``otbot_hw.model.dynamics`` / ``kinematics`` (M, C, E_f, J, J_dot), with the
  effect entering as a generalized force Q (6,) derived here from the physics, integrated
  by scipy's adaptive RK45, restarted on every ZOH interval (the current-loop lag adds
  three states to the integrated vector);
* effects, one per catalog category, with this file's own functional forms: hard-ish
  Coulomb signs (tanh(w / 0.005 rad/s), 2x sharper than the tool's pivot sign and 10x its wheel sign on the floor), the slope as gravity
  on both centres of mass through their position Jacobians, drag as a force at the pivot,
  gain and lag on the delivered torque, and sensor effects on an IMU written here
  (specific force of the sensor point in its own frame, rigid-body lever arm terms);
* recordings: written with the plain ``mcap`` package following docs/recording-format.md
  (no ``/otbot/truth`` topic, metadata only ``format``, ``format_version``, ``sample_period``,
  ``fixture``, ``source``), then handed to the tool's loader.

Per case: 8 s multisine fitting run, 8 s tracking held-out run (sim/concealed.py
excitations), 100 Hz, paper noise levels. Writes the table between the INDEPENDENT
markers of docs/diagnose.md and one JSON object on stdout; progress on stderr.

    .venv/bin/python benchmarks/diagnose_independent.py [--workers 2] [--cases a,b,...]
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from otbot_hw.model.dynamics import coriolis_matrix, friction_matrix, mass_matrix  # noqa: E402
from otbot_hw.model.kinematics import constraint_jacobian, constraint_jacobian_dot  # noqa: E402
from otbot_hw.params import nominal  # noqa: E402
from otbot_hw.simulation.concealed import excitation  # noqa: E402

G = 9.80665
SHARP = 0.005  # rad/s: width of the (nearly hard) friction sign used here
DT = 0.01
DURATION = 8.0
SIGMA_IMU = 1.37e-3 * np.sqrt(100.0)  # paper §4.3.2
SIGMA_ENC_RATE = 0.01


def _rot(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s], [s, c]])


def generalized_effect_force(q, qd, p, e: dict) -> np.ndarray:
    """Generalized force (6,) of the effects that act on the bodies or joints (not the actuators)."""
    Q = np.zeros(6)
    if e.get("coulomb_w"):  # Coulomb friction at both wheel shafts
        Q[3:5] -= e["coulomb_w"] * np.tanh(qd[3:5] / SHARP)
    if e.get("coulomb_p"):  # Coulomb friction at the pivot shaft
        Q[5] -= e["coulomb_p"] * np.tanh(qd[5] / SHARP)
    if e.get("db_w"):  # viscous friction b_w + db on the right wheel, b_w - db on the left
        Q[3] -= e["db_w"] * qd[3]
        Q[4] += e["db_w"] * qd[4]
    if e.get("slope") is not None:  # in-plane gravity g_s on the chassis (B) and platform (F) centres of mass
        gs = np.asarray(e["slope"], float)
        th, a = q[2] - q[5], q[2]
        # d/d(angle) of R(angle) c = R(angle + pi/2) c
        dB = _rot(th + np.pi / 2) @ np.array([p.x_B, p.y_B])
        dF = _rot(a + np.pi / 2) @ np.array([p.x_F, p.y_F])
        fB, fF = p.m_c * gs, p.m_p * gs
        Q[0:2] += fB + fF
        Q[2] += fB @ dB + fF @ dF  # theta = alpha - phi_p: d theta/d alpha = 1
        Q[5] -= fB @ dB  # d theta / d phi_p = -1
    if e.get("c_air"):  # quadratic drag at the pivot, opposing its velocity
        v = qd[:2]
        Q[0:2] -= e["c_air"] * np.linalg.norm(v) * v
    return Q


def accelerations(q, qd, tau, p, e) -> np.ndarray:
    """q_ddot from M q_dd + C q_d + J^T lam = E tau + E_f q_d + Q, J q_dd = -J_dot q_d (own 9x9 solve)."""
    M = mass_matrix(q, p)
    J = constraint_jacobian(q, p)
    A = np.zeros((9, 9))
    A[:6, :6], A[:6, 6:], A[6:, :6] = M, J.T, J
    gen = np.zeros(6)
    gen[3:] = tau
    rhs = np.concatenate([gen + (friction_matrix(p) - coriolis_matrix(q, qd, p)) @ qd
                          + generalized_effect_force(q, qd, p, e),
                          -constraint_jacobian_dot(q, qd, p) @ qd])
    return np.linalg.solve(A, rhs)[:6]


def delivered(u, e) -> np.ndarray:
    """Torque the drive delivers for a command u before any lag (gain error on the right motor)."""
    d = np.array(u, float)
    d[0] *= 1.0 + e.get("gain_r", 0.0)
    return d


def simulate(params, U, e):
    """States (N+1, 12), delivered torques at the sample instants (N+1, 3) and q_ddot just after each t_k."""
    lag = e.get("T_i", 0.0)
    s = np.zeros(15 if lag else 12)
    S, TAU, QDD = [], [], []
    for k in range(len(U)):
        ud = delivered(U[k], e)

        def rhs(_t, z, ud=ud):
            tau = z[12:15] if lag else ud
            out = np.concatenate([z[6:12], accelerations(z[:6], z[6:12], tau, params, e)])
            return np.concatenate([out, (ud - z[12:15]) / lag]) if lag else out

        tau0 = s[12:15] if lag else ud
        S.append(s[:12].copy())
        TAU.append(np.array(tau0))
        QDD.append(accelerations(s[:6], s[6:12], tau0, params, e))
        sol = solve_ivp(rhs, (0.0, DT), s, method="RK45", rtol=1e-8, atol=1e-10)
        if not sol.success:
            raise RuntimeError(sol.message)
        s = sol.y[:, -1]
    ud = delivered(U[-1], e)
    tau0 = s[12:15] if lag else ud
    S.append(s[:12].copy())
    TAU.append(np.array(tau0))
    QDD.append(accelerations(s[:6], s[6:12], tau0, params, e))
    return np.array(S), np.array(TAU), np.array(QDD)


def sensors(X, QDD, e, rng):
    """Encoders (angles, rates) and IMU (specific force, rate) as this file models them, with noise."""
    n = len(X)
    pos, vel = X[:, 3:6].copy(), X[:, 9:12].copy()
    if e.get("enc_r"):  # right wheel encoder reads (1 + e) x its angle
        pos[:, 0] *= 1.0 + e["enc_r"]
        vel[:, 0] *= 1.0 + e["enc_r"]
    gs = np.asarray(e.get("slope", (0.0, 0.0)), float)
    d = np.asarray(e.get("lever", (0.0, 0.0)), float)
    psi = e.get("psi", 0.0)
    acc = np.empty((n, 3))
    for k in range(n):
        a, ad, add = X[k, 2], X[k, 8], QDD[k, 2]
        spec = QDD[k, :2] - gs  # specific force of P in the ground frame (in-plane part)
        f = _rot(a).T @ spec  # in B''
        f = f + add * np.array([-d[1], d[0]]) - ad ** 2 * d  # sensor point D = P + R(a) d, rigid platform
        f = _rot(psi).T @ f  # sensor axes turned by psi about the vertical
        acc[k, :2] = f
        acc[k, 2] = np.sqrt(G ** 2 - gs @ gs)
    gyro = np.zeros((n, 3))
    gyro[:, 2] = X[:, 8]
    b = e.get("bias", (0.0, 0.0, 0.0))
    acc[:, 0] += b[0]
    acc[:, 1] += b[1]
    gyro[:, 2] += b[2]
    acc += SIGMA_IMU * rng.standard_normal((n, 3))
    gyro += SIGMA_IMU * rng.standard_normal((n, 3))
    vel += SIGMA_ENC_RATE * rng.standard_normal((n, 3))
    return pos, vel, acc, gyro


def write_mcap(path: Path, t, U, pos, vel, acc, gyro):
    """The documented format with the plain mcap writer (docs/recording-format.md §1-5)."""
    from mcap.writer import CompressionType, Writer
    with open(path, "wb") as fh:
        w = Writer(fh, compression=CompressionType.NONE, use_chunking=False)
        w.start(profile="otbot", library="independent test writer")
        w.add_metadata("otbot", {"format": json.dumps("otbot-recording"), "format_version": "1",
                                 "sample_period": json.dumps(DT), "fixture": json.dumps("floor"),
                                 "source": json.dumps("benchmarks/diagnose_independent.py")})
        ch = {}
        for topic, schema in (("/otbot/command", "otbot.Command"), ("/otbot/joints", "otbot.Joints"),
                              ("/otbot/imu", "otbot.Imu")):
            sid = w.register_schema(name=schema, encoding="jsonschema", data=b"{}")
            ch[topic] = w.register_channel(topic=topic, message_encoding="json", schema_id=sid)
        for k in range(len(t)):
            stamp = int(round(t[k] * 1e9))
            tk = float(t[k])
            msgs = {"/otbot/command": {"t": tk, "torque": [float(v) for v in U[k]]},
                    "/otbot/joints": {"t": tk, "position": [float(v) for v in pos[k]],
                                      "velocity": [float(v) for v in vel[k]]},
                    "/otbot/imu": {"t": tk, "accel": [float(v) for v in acc[k]], "gyro": [float(v) for v in gyro[k]]}}
            for topic, m in msgs.items():
                w.add_message(channel_id=ch[topic], log_time=stamp, publish_time=stamp, sequence=k,
                              data=json.dumps(m).encode())
        w.finish()


def make_recording(path: Path, params, kind: str, seed: int, e: dict) -> None:
    U, _ = excitation(kind, DURATION, DT, seed)
    X, _tau, QDD = simulate(params, U, e)
    pos, vel, acc, gyro = sensors(X, QDD, e, np.random.default_rng(seed + 1000))
    Uf = np.vstack([U, U[-1:]])
    write_mcap(path, np.arange(len(X)) * DT, Uf, pos, vel, acc, gyro)


#: (label, true catalog effect, this simulator's effect, catalog parameters it corresponds to)
CASES = [
    ("coulomb_wheels", "Coulomb at both wheels, sharp sign", {"coulomb_w": 0.3}, {"c_w": 0.3}),
    ("coulomb_pivot", "Coulomb at the pivot, sharp sign", {"coulomb_p": 0.3}, {"c_p": 0.3}),
    ("floor_slope", "gravity component (0.03, −0.025) m/s² on both centres of mass", {"slope": (0.03, -0.025)},
     {"g_x": 0.03, "g_y": -0.025}),
    ("air_drag", "quadratic drag −c_air ‖v‖ v at the pivot", {"c_air": 20.0}, {"c_air": 20.0}),
    ("gain_right", "right motor delivers 0.92 x command", {"gain_r": -0.08}, {"k_r": -0.08}),
    ("current_lag", "first-order lag on all three motors", {"T_i": 0.03}, {"T_i": 0.03}),
    ("imu_bias", "IMU bias", {"bias": (0.04, -0.03, 0.006)}, {"b_ax": 0.04, "b_ay": -0.03, "b_gz": 0.006}),
    ("imu_lever_arm", "IMU at (0.08, -0.04) m in B''", {"lever": (0.08, -0.04)}, {"d_x": 0.08, "d_y": -0.04}),
    ("imu_misalignment", "IMU yaw misalignment", {"psi": 0.05}, {"psi": 0.05}),
    ("encoder_scale", "right encoder reads 1.03 x angle", {"enc_r": 0.03}, {"e_r": 0.03}),
    ("wheel_friction_asymmetry", "b_r = b_w + 0.04, b_l = b_w - 0.04", {"db_w": 0.04}, {"db_w": 0.04}),
    ("none", "no effect (negative control)", {}, {}),
]


def run_case(case, rep: int = 0, sharp: float | None = None) -> dict:
    from otbot_hw.diagnose.data import load
    from otbot_hw.diagnose.diagnosis import diagnose
    from otbot_hw.recording import read_recording

    global SHARP
    if sharp is not None:
        SHARP = sharp
    label, desc, e, truth = case
    P = nominal()
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        paths = []
        for kind, seed in (("multisine", 21 + 2 * rep), ("tracking", 22 + 2 * rep)):
            path = Path(tmp) / f"{label}_{kind}.mcap"
            make_recording(path, P, kind, seed, e)
            paths.append(path)
        assert read_recording(paths[0]).truth_q is None
        t_sim = time.perf_counter() - t0
        r = diagnose(load(paths[:1]), P, load(paths[1:]))
    named = [x["name"] for x in r["effects"]]
    amb = [[c["name"] for c in g["candidates"]] for g in r["ambiguous"]]
    est = {}
    for x in r["effects"]:
        est.update({k: v["value"] for k, v in x["parameters"].items()})
    for g in r["ambiguous"]:
        for c in g["candidates"]:
            est.update({k: v["value"] for k, v in c["parameters"].items() if k in truth and k not in est})
    err = {k: (est[k] - v) / abs(v) if k in est else None for k, v in truth.items()}
    hb, ha = r["fit_before"]["heldout"], r["fit_after"]["heldout"]
    worst = min(hb, key=lambda ch: hb[ch]["fit_percent"]) if hb else None
    return {"case": label, "rep": rep, "seeds": [21 + 2 * rep, 22 + 2 * rep], "description": desc, "truth": truth, "named": named, "ambiguous": amb,
            "estimate": est, "rel_error": err, "worst_channel": worst,
            "heldout_before": hb[worst]["fit_percent"] if worst else None,
            "heldout_after": ha[worst]["fit_percent"] if worst else None,
            "verdict": r["verdict"], "sim_s": t_sim, "total_s": time.perf_counter() - t0}


def _named(r: dict) -> str:
    named = ", ".join(r["named"])
    if r["ambiguous"]:
        named = (named + "; " if named else "") + "; ".join("ambiguous {" + ", ".join(sorted(g)) + "}" for g in r["ambiguous"])
    return named or "none"


def table(rows: list[dict]) -> list[str]:
    """One row per case (first seed pair): truth, what was named, recovered values, errors, held-out fit."""
    out = ["| true effect (independent form) | truth | tool named | recovered | error | held-out worst channel: fit % before -> after |",
           "|---|---|---|---|---|---|"]
    for r in rows:
        truth = ", ".join(f"{k} = {v:g}" for k, v in r["truth"].items()) or "-"
        extra = {k: v for k, v in r["estimate"].items() if k not in r["truth"]}
        rec = ", ".join(f"{k} = {r['estimate'][k]:.4g}" for k in r["truth"] if k in r["estimate"])
        if extra:
            rec += (" (also " if rec else "(") + ", ".join(f"{k} = {v:.3g}" for k, v in extra.items()) + ")"
        errs = [f"{k} {100 * v:+.1f} %" if v is not None else f"{k} not estimated" for k, v in r["rel_error"].items()]
        fit = (f"{r['worst_channel']}: {r['heldout_before']:.1f} -> {r['heldout_after']:.1f}"
               if r["worst_channel"] else "-")
        out.append(f"| {r['case']}: {r['description']} | {truth} | {_named(r)} | {rec or '-'} | "
                   f"{', '.join(errs) or '-'} | {fit} |")
    return out


def seed_table(rows: list[dict], labels: list[str]) -> list[str]:
    """Per case over all seed pairs: named counts, worst |error| per seed, held-out fit per seed."""
    out = ["| case | seed pairs | named (count) | max abs error per seed pair | held-out worst channel before -> after per seed pair |",
           "|---|---|---|---|---|"]
    for lab in labels:
        rs = sorted((r for r in rows if r["case"] == lab), key=lambda r: r["rep"])
        if not rs:
            continue
        counts: dict[str, int] = {}
        for r in rs:
            counts[_named(r)] = counts.get(_named(r), 0) + 1
        errs = []
        for r in rs:
            v = [abs(x) for x in r["rel_error"].values() if x is not None]
            miss = any(x is None for x in r["rel_error"].values())
            errs.append("n/a" if not r["rel_error"] else ("not estimated" if miss else f"{100 * max(v):.1f} %"))
        fits = [f"{r['worst_channel']} {r['heldout_before']:.1f} -> {r['heldout_after']:.1f}" for r in rs]
        out.append(f"| {lab} | {len(rs)} | {'; '.join(f'{k} ({n})' for k, n in counts.items())} | "
                   f"{', '.join(errs)} | {', '.join(fits)} |")
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workers", type=int, default=2, help="worker processes (default 2)")
    ap.add_argument("--seeds", type=int, default=3, help="seed pairs per case: (21, 22), (23, 24), ... (default 3)")
    ap.add_argument("--cases", default="", help="comma-separated case labels (default: all)")
    ap.add_argument("--sharp", type=float, default=None,
                    help="width of the friction sign in rad/s (default 0.005; the tool's own: 0.01 pivot, 0.05 wheels on the floor) — a diagnostic")
    ap.add_argument("--out", default=str(ROOT / "docs" / "diagnose_independent.json"), help="JSON results file")
    ap.add_argument("--no-doc", action="store_true", help="do not rewrite docs/diagnose.md")
    args = ap.parse_args()
    chosen = [c for c in CASES if not args.cases or c[0] in args.cases.split(",")]
    t0 = time.perf_counter()
    rows = []
    with ProcessPoolExecutor(max_workers=args.workers) as ex:
        futs = {ex.submit(run_case, c, rep, args.sharp): (c[0], rep) for rep in range(args.seeds) for c in chosen}
        for f in as_completed(futs):
            try:
                r = f.result()
            except Exception as exc:  # a failing case is reported, the others go on
                r = {"case": futs[f][0], "rep": futs[f][1], "error": repr(exc)}
            rows.append(r)
            print(f"[independent] {time.perf_counter() - t0:6.0f} s  {r['case']} #{r['rep']}: "
                  f"{r.get('named')} amb={r.get('ambiguous')} err={r.get('rel_error')} "
                  f"held-out {r.get('worst_channel')} {r.get('heldout_before')} -> {r.get('heldout_after')}",
                  file=sys.stderr, flush=True)
    order = {c[0]: i for i, c in enumerate(CASES)}
    rows.sort(key=lambda r: (r["rep"], order[r["case"]]))
    Path(args.out).write_text(json.dumps(rows, indent=1) + "\n")
    ok = [r for r in rows if "error" not in r]
    labels = [c[0] for c in chosen]
    lines = ["<!-- INDEPENDENT:BEGIN (written by benchmarks/diagnose_independent.py) -->", "",
             f"{len(ok)} runs ({len(labels)} cases x {args.seeds} seed pairs; {len(rows) - len(ok)} failed), "
             f"{(time.perf_counter() - t0) / 60:.1f} min on {args.workers} worker process(es). Per run: 8 s multisine "
             "fitting recording + 8 s tracking held-out recording, 100 Hz, paper noise, written with the plain `mcap` "
             "package (no truth topic). Simulator, effects and sensor model are written in the script (see its "
             "docstring), not taken from `otbot_hw/model/effects.py` or `otbot_hw/sensors.py`. Error = "
             "(recovered − true) / |true|. Held-out column: the channel with the worst held-out fit before the "
             "diagnosis, its fit % before → after. All results: `docs/diagnose_independent.json`.", "",
             "First seed pair (21, 22):", ""]
    lines += table([r for r in ok if r["rep"] == 0])
    lines += ["", f"All seed pairs:", ""]
    lines += seed_table(ok, labels)
    for r in rows:
        if "error" in r:
            lines.append(f"\nRun `{r['case']}` #{r['rep']} failed: {r['error']}")
    lines += ["", "<!-- INDEPENDENT:END -->"]
    if not args.no_doc:
        block = "\n".join(lines)
        doc = ROOT / "docs" / "diagnose.md"
        text = doc.read_text()
        a = text.index("<!-- INDEPENDENT:BEGIN")
        b = text.index("<!-- INDEPENDENT:END -->") + len("<!-- INDEPENDENT:END -->")
        doc.write_text(text[:a] + block + text[b:])
    print(json.dumps({"runs": [{k: r.get(k) for k in ("case", "rep", "named", "ambiguous", "rel_error",
                                                       "worst_channel", "heldout_before", "heldout_after", "error")}
                               for r in rows]}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
