"""Beyond the catalog: the law the model misses, by grouped sparse regression on the residual generalized forces.

When no catalog effect brings the model to the noise level, what the model misses is still measured:
the torque residual per joint (``residuals.torque_residual``: the command minus the torque the model
needs for the motion estimated from the encoders, N m; unmodelled friction reads as +friction). It is
regressed on a library of candidate *laws*, each a group of columns sharing one physical meaning and
each a law the model can step (``otbot_hw.model.effect_catalog``: the catalog's entries or the laws
beyond it), per joint j (r, l, p):

* ``cogging``: sin(n phi_j), cos(n phi_j) for n in ``HARMONICS`` -> cog_j, cogn_j, cogph_j;
* ``dead_zone``: clip(u_j, -d, d), d on ``DEADZONE_GRID`` -> dz_j (coefficient ~1 for a true dead zone);
* ``soft_limit``: u_j - T tanh(u_j / T), T on ``SOFT_GRID`` -> ts_j (coefficient ~1 likewise);
* ``coulomb``: tanh(w_j / ``SIGN_WIDTH``) -> c_j (a gain law u_j -> k_j is defined but not in the library:
  in the equation residual a command column trades off against the inertias and read k_p ~ -0.12 on 2 of 10
  clean independent runs, which the simulation refit then took back; the catalog tests gains by simulation);
* on the floor, for the platform: ``linear_drag`` J^T v (joint torques of a force -v at the pivot; J the
  pivot rows of M_FIK) -> c_lin, and ``quadratic_drag`` J^T |v| v -> c_air.

Command columns pass the filter the residual's torque passed (``integral_rate``: the SG derivative of the
running integral), so a step command and its smoothed residual compare sample by sample. The free nominal
parameters' columns (finite differences of the residual) are fitted beside the laws and never dropped, so
a law is not what a nominal refit would absorb. Rows are weighted per joint by the joint's residual level
after the nominal fit (the pivot and the wheels have different torque noise).

Selection is greedy over *laws* (the catalog's group-OMP style): at each step every law not yet chosen is
fitted beside the chosen ones (a grid law at the grid point of least fitting error); among the laws that
pass two gates -- a held-out gain of ``MIN_HELDOUT_GAIN`` and an F test at ``ALPHA`` on the fitting data with the sample count divided by the residual correlation factor
(``refit.correlation_factor``: the residual is smoothed and coloured) -- the one that lowers the held-out
error most is taken; none passing ends the search. A law whose coefficients are not
physical (negative drag or friction, a dead-zone or limit coefficient far from 1) is not a candidate. So
nearly collinear command terms do not mix: one law per joint at a time, with its meaning. Held-out: the
held-out recordings, else the last ``HOLDOUT_FRACTION`` of each fitting recording.

Reported per law: the effect entries it sets in physical units with a Newey-West (HAC) std on the
coloured residual, what it does, and the held-out torque-residual RMS per joint before/after. The
diagnosis (``diagnosis``) then refits the laws' parameters by simulation and re-simulates the held-out
recordings with them stepped (``model_with_laws`` builds the model that ``--out`` writes).

``pysindy`` is not used: its optimizers threshold single raw coefficients of columns with different
units, with no grouping of columns into laws and no held-out choice without scikit-learn on top.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from otbot_hw.diagnose.data import DiagnosisData
from otbot_hw.diagnose.refit import bandwidth, correlation_factor
from otbot_hw.diagnose.residuals import estimate_motion, integral_rate, torque_residual
from otbot_hw.model.effects import ExtendedModel
from otbot_hw.model.kinematics import fik_entries

JOINTS = ("r", "l", "p")
SIGN_WIDTH = 0.02  # rad/s
HARMONICS = (1, 2, 3, 4, 6, 8)  # cogging cycles per turn tried
DEADZONE_GRID = tuple(float(v) for v in np.geomspace(0.05, 3.0, 16))  # N m
SOFT_GRID = tuple(float(v) for v in np.geomspace(1.0, 12.0, 12))  # N m
SHAPE_COEF = (0.6, 1.5)  # a dead-zone or soft-limit coefficient outside this is not that law
MAX_LAWS = 4
MIN_HELDOUT_GAIN = 0.03  # relative drop of the held-out weighted mean square a law must bring
ALPHA = 1e-3  # F test size per step
HOLDOUT_FRACTION = 0.3
EDGE = 0.1  # s dropped at each end (filter edges)

#: what each law does (torque, drift, odometry), for the report
MEANING = {
    "cogging": "a torque ripple with the motor's angle: rate wobble at n cycles per turn, no net drift",
    "dead_zone": "commands below the width deliver nothing: the joint does not start, small corrections are lost "
                 "(the path drifts under feedback)",
    "soft_limit": "large commands deliver less (ts tanh(u / ts)): accelerations fall short at high torque",
    "coulomb": "a constant friction torque opposing the joint's rotation",
    "gain": "the drive delivers (1 + k) times the command",
    "linear_drag": "a force -c_lin v at the pivot: the platform slows in proportion to its speed (odometry and IMU "
                   "agree; the model over-predicts speed and distance)",
    "quadratic_drag": "a force -c_air |v| v at the pivot: the platform slows with the square of its speed",
}


@dataclass
class Basis:
    """What the library is built from, for one recording (kept samples only): residual (n, 3) N m, nominal
    columns (n, 3, k0), joint rates w and angles phi (n, 3), raw commands u (n, 3) and the pivot Jacobian J
    (n, 2, 3) with the pivot velocity v (n, 2) m/s on the floor."""

    res: np.ndarray
    nominal: np.ndarray
    w: np.ndarray
    phi: np.ndarray
    u: np.ndarray
    J: np.ndarray | None
    v: np.ndarray | None
    data: DiagnosisData
    keep: np.ndarray

    def filtered(self, y: np.ndarray) -> np.ndarray:
        """A command-derived series (N, 3) of the whole record through the residual's torque filter, kept rows."""
        return integral_rate(self.data, y)[self.keep]


@dataclass(frozen=True)
class Law:
    kind: str
    joint: str  # r, l, p, or "platform"
    grid: float = 0.0  # harmonic, dead-zone width or soft limit

    @property
    def group(self) -> tuple[str, str]:
        return self.kind, self.joint

    @property
    def label(self) -> str:
        j = self.joint
        return {"cogging": f"cogging {self.grid:g}/turn on {j}", "dead_zone": f"dead zone {self.grid:.3g} N m on {j}",
                "soft_limit": f"soft limit {self.grid:.3g} N m on {j}", "coulomb": f"Coulomb friction on {j}",
                "gain": f"torque gain on {j}", "linear_drag": "linear drag at the pivot",
                "quadratic_drag": "quadratic drag at the pivot"}[self.kind]

    def columns(self, b: Basis) -> np.ndarray:
        """(n, 3, k) generalized-force columns of this law on the kept samples."""
        n = len(b.res)
        if self.kind in ("linear_drag", "quadratic_drag"):
            v = b.v if self.kind == "linear_drag" else np.linalg.norm(b.v, axis=1)[:, None] * b.v
            return np.einsum("nij,ni->nj", b.J, v)[:, :, None]
        j = JOINTS.index(self.joint)

        def on(*xs):
            c = np.zeros((n, 3, len(xs)))
            for k, x in enumerate(xs):
                c[:, j, k] = x
            return c

        if self.kind == "cogging":
            a = self.grid * b.phi[:, j]
            return on(np.sin(a), np.cos(a))
        if self.kind == "coulomb":
            return on(np.tanh(b.w[:, j] / SIGN_WIDTH))
        u = np.zeros((len(b.data), 3))
        uj = b.data.u[:, j]
        if self.kind == "gain":
            u[:, j] = uj
        elif self.kind == "dead_zone":
            u[:, j] = np.clip(uj, -self.grid, self.grid)
        else:  # soft_limit
            u[:, j] = uj - self.grid * np.tanh(uj / self.grid)
        return on(b.filtered(u)[:, j])

    def effect(self, coef: np.ndarray) -> dict[str, float] | None:
        """The model's effect entries of this law for its fitted coefficients; None when not physical."""
        c = coef[0]
        j = self.joint
        if self.kind in ("linear_drag", "quadratic_drag", "coulomb"):
            name = {"linear_drag": "c_lin", "quadratic_drag": "c_air", "coulomb": f"c_{j}"}[self.kind]
            return {name: float(c)} if c > 0 else None
        if self.kind == "gain":
            return {f"k_{j}": float(-c)} if abs(c) < 0.5 else None
        if self.kind == "cogging":
            return {f"cog_{j}": float(np.hypot(coef[0], coef[1])), f"cogn_{j}": float(self.grid),
                    f"cogph_{j}": float(np.arctan2(coef[1], coef[0]))}
        if not SHAPE_COEF[0] <= c <= SHAPE_COEF[1]:
            return None
        return {("dz_" if self.kind == "dead_zone" else "ts_") + j: float(self.grid)}

    def free(self) -> list[str]:
        """Effect entries a simulation refit adjusts (the harmonic stays)."""
        j = self.joint
        return {"cogging": [f"cog_{j}", f"cogph_{j}"], "dead_zone": [f"dz_{j}"], "soft_limit": [f"ts_{j}"],
                "coulomb": [f"c_{j}"], "gain": [f"k_{j}"], "linear_drag": ["c_lin"],
                "quadratic_drag": ["c_air"]}[self.kind]


def candidate_groups(fixture: str) -> list[list[Law]]:
    """The library: one list of grid variants per law (kind, joint)."""
    groups = []
    joints = ("p",) if fixture == "locked" else JOINTS
    for j in joints:
        groups.append([Law("cogging", j, n) for n in HARMONICS])
        groups.append([Law("dead_zone", j, d) for d in DEADZONE_GRID])
        groups.append([Law("soft_limit", j, t) for t in SOFT_GRID])
        groups.append([Law("coulomb", j)])
    if fixture == "floor":
        groups.append([Law("linear_drag", "platform")])
        groups.append([Law("quadratic_drag", "platform")])
    return groups


def _basis(d: DiagnosisData, model: ExtendedModel, nominal: list[str]) -> Basis:
    m = estimate_motion(d, model)
    res = torque_residual(d, model, m)
    n = len(d)
    cols = []
    for name in nominal:
        v = model.get(name)
        h = 1e-3 * max(abs(v), 1e-2)
        cols.append((res - torque_residual(d, model.with_values({name: v + h}), m)) / h)
    keep = np.zeros(n, bool)
    e = int(round(EDGE / d.dt))
    keep[e:n - e] = True
    J = v = None
    if d.fixture == "floor":
        th = m.q[:, 2] - m.q[:, 5]
        p = model.params
        b00, b01, b10, b11, _ = fik_entries(np.sin(th), np.cos(th), p.l1, p.l2, p.r)
        J = np.zeros((n, 2, 3))
        J[:, 0, 0], J[:, 0, 1], J[:, 1, 0], J[:, 1, 1] = b00, b01, b10, b11
        v = m.qd[:, :2]
        J, v = J[keep], v[keep]
    nom = np.stack(cols, axis=2)[keep] if cols else np.zeros((int(keep.sum()), 3, 0))
    return Basis(res=res[keep], nominal=nom, w=m.qd[keep, 3:6], phi=d.enc_pos[keep], u=d.u[keep], J=J, v=v,
                 data=d, keep=keep)


def _flat(c: np.ndarray) -> np.ndarray:
    """(n, 3, k) -> (3n, k), rows sample-major (joint = row mod 3)."""
    return c.reshape(-1, c.shape[2])


class _Design:
    """Weighted design matrices on the fitting and test rows for a growing set of laws."""

    def __init__(self, fit_parts, test_parts, active_joints):
        self.fit_parts, self.test_parts = fit_parts, test_parts
        self.active = np.array(active_joints, bool)
        self.wj = np.ones(3)
        y = self._stack(fit_parts, lambda b: b.res[:, :, None])[:, 0]
        X0 = self._stack(fit_parts, lambda b: b.nominal)
        r = y - X0 @ np.linalg.lstsq(X0, y, rcond=None)[0] if X0.shape[1] else y
        jr = np.tile(np.arange(3), len(y) // 3)
        for j in range(3):
            s = np.sqrt(np.mean(r[jr == j] ** 2)) if self.active[j] else 0.0
            self.wj[j] = 1.0 / s if s > 0 else 0.0

    def _stack(self, parts, fn) -> np.ndarray:
        blocks = []
        for b, sl in parts:
            blocks.append(_flat(fn(b)[sl] * self.wj[None, :, None]))
        return np.concatenate(blocks)

    def matrices(self, fn):
        return self._stack(self.fit_parts, fn), self._stack(self.test_parts, fn)

    def blocks(self) -> list[int]:
        """Row count of each fitting part (for per-recording HAC sums)."""
        return [3 * len(range(*sl.indices(len(b.res)))) for b, sl in self.fit_parts]


def _kappa(r: np.ndarray, blocks: list[int]) -> float:
    """Residual correlation factor of the weighted fitting residual, per (recording, joint) series."""
    series, i = {}, 0
    for k, n in enumerate(blocks):
        part = r[i:i + n].reshape(-1, 3)
        for j in range(3):
            if np.any(part[:, j] != 0):
                series[(k, j)] = part[:, j]
        i += n
    return max(correlation_factor(series), 1.0)


def _hac_cov(X: np.ndarray, r: np.ndarray, blocks: list[int]) -> np.ndarray:
    """Newey-West covariance of least-squares coefficients, scores summed per (recording, joint) series
    up to each series' ``bandwidth`` (Bartlett weights)."""
    B = np.linalg.pinv(X.T @ X)
    meat = np.zeros((X.shape[1], X.shape[1]))
    i = 0
    for n in blocks:
        Xb, rb = X[i:i + n].reshape(-1, 3, X.shape[1]), r[i:i + n].reshape(-1, 3)
        for j in range(3):
            if not np.any(rb[:, j] != 0):
                continue
            g = Xb[:, j, :] * rb[:, j:j + 1]
            L = bandwidth(rb[:, j])
            m = g.T @ g
            for lag in range(1, L + 1):
                c = g[lag:].T @ g[:-lag]
                m += (1.0 - lag / (L + 1)) * (c + c.T)
            meat += m
        i += n
    return B @ meat @ B


def discover(recordings: list[DiagnosisData], holdout: list[DiagnosisData], model: ExtendedModel,
             nominal: list[str] | None = None) -> dict:
    """Laws beyond the catalog in the torque residual of ``model`` (the nominal fit) on ``recordings``.
    ``nominal``: the free nominal parameters (default ``select.free_nominal``), fitted beside the laws.

    Returns {laws: [{law, kind, joint, effect: {entry: value}, std: {entry: std}, coefficient, meaning,
    heldout_gain}], terms (one line per law for the verdict), heldout: {joint: {before_rms, after_rms}},
    nominal_shift, tried (the best variant of every law at the first step: held-out gain, F p-value),
    heldout_source, method}."""
    from otbot_hw.diagnose.select import free_nominal

    nominal = list(free_nominal(recordings) if nominal is None else nominal)
    fit_b = [_basis(d, model, nominal) for d in recordings]
    if holdout:
        hold_b = [_basis(d, model, nominal) for d in holdout]
        fit_parts = [(b, slice(None)) for b in fit_b]
        test_parts = [(b, slice(None)) for b in hold_b]
        source = "held-out recordings"
    else:
        fit_parts, test_parts = [], []
        for b in fit_b:
            cut = int((1 - HOLDOUT_FRACTION) * len(b.res))
            fit_parts.append((b, slice(0, cut)))
            test_parts.append((b, slice(cut, None)))
        source = f"last {100 * HOLDOUT_FRACTION:.0f} % of each fitting recording"
    fixtures = {d.fixture for d in recordings + holdout}
    # the pivot-drag laws need every recording on the floor; locked wheels leave the pivot alone
    fixture = fixtures.pop() if len(fixtures) == 1 else "stand"
    D = _Design(fit_parts, test_parts, [fixture != "locked", fixture != "locked", True])
    y, yt = D.matrices(lambda b: b.res[:, :, None])
    y, yt = y[:, 0], yt[:, 0]
    X0, X0t = D.matrices(lambda b: b.nominal)
    groups = candidate_groups(fixture)
    cols_cache: dict[Law, tuple[np.ndarray, np.ndarray]] = {}

    def cols(law: Law):
        if law not in cols_cache:
            cols_cache[law] = D.matrices(law.columns)
        return cols_cache[law]

    def solve(X, Xt):
        c = np.linalg.lstsq(X, y, rcond=None)[0] if X.shape[1] else np.zeros(0)
        r = y - X @ c
        rt = yt - Xt @ c
        return c, r, float(r @ r), float(np.mean(rt ** 2))

    chosen: list[Law] = []
    X, Xt = X0, X0t
    c, r, rss, mse_t = solve(X, Xt)
    mse_start = mse_t
    tried = []
    gains = []
    blocks = D.blocks()
    for step in range(MAX_LAWS):
        best = None
        for grp in groups:
            if any(g.group == grp[0].group for g in chosen):
                continue
            best_v = None
            for law in grp:
                A, At = cols(law)
                Xc, Xct = np.hstack([X, A]), np.hstack([Xt, At])
                cc, rc, rss_c, mse_c = solve(Xc, Xct)
                eff = law.effect(cc[-A.shape[1]:])
                if eff is None:
                    continue
                if best_v is None or rss_c < best_v[1]:
                    best_v = (law, rss_c, mse_c, Xc, Xct, rc)
            if best_v is None:
                continue
            law, rss_c, mse_c, Xc, Xct, rc = best_v
            k = Xc.shape[1] - X.shape[1]
            kappa = _kappa(rc, blocks)
            n_eff = len(y) / kappa
            F = ((rss - rss_c) / k) / max(rss_c / max(n_eff - Xc.shape[1], 1.0), 1e-300) / kappa
            p = float(stats.f.sf(F, k, max(n_eff - Xc.shape[1], 1.0)))
            gain = (mse_t - mse_c) / mse_t if mse_t > 0 else 0.0
            if step == 0:
                tried.append({"law": law.label, "heldout_gain": gain, "p_value": p})
            if gain < MIN_HELDOUT_GAIN or p > ALPHA:  # the gates, then the best held-out error
                continue
            if best is None or mse_c < best[2]:
                best = (law, rss_c, mse_c, Xc, Xct, gain, p)
        if best is None:
            break
        law, rss_c, mse_c, Xc, Xct, gain, p = best
        chosen.append(law)
        gains.append(gain)
        X, Xt = Xc, Xct
        c, r, rss, mse_t = solve(X, Xt)
    # coefficients with HAC std on the final design
    cov = _hac_cov(X, r, blocks) if X.shape[1] else np.zeros((0, 0))
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    laws = []
    i = X0.shape[1]
    for law, gain in zip(chosen, gains):
        k = law.columns(fit_b[0]).shape[2]
        cf, cs = c[i:i + k], std[i:i + k]
        eff = law.effect(cf) or {}
        est = _effect_std(law, cf, cs)
        laws.append({"law": law.label, "kind": law.kind, "joint": law.joint, "grid": law.grid, "effect": eff,
                     "std": est, "coefficient": [float(v) for v in cf], "coefficient_std": [float(v) for v in cs],
                     "meaning": MEANING[law.kind], "heldout_gain": float(gain), "free": law.free()})
        i += k
    terms = [{"term": lw["law"], "joint": lw["joint"], "value": float(next(iter(lw["effect"].values()))),
              "std": float(next(iter(lw["std"].values()))), "unit": _unit(next(iter(lw["effect"]))),
              "meaning": lw["meaning"]} for lw in laws]
    heldout = {}
    rt = yt - Xt @ c
    rt0 = yt - X0t @ np.linalg.lstsq(X0, y, rcond=None)[0] if X0.shape[1] else yt
    rows = np.arange(len(yt)) % 3
    for j, jn in enumerate(JOINTS):
        sel = rows == j
        if D.wj[j] == 0 or not np.any(yt[sel] != 0):
            continue
        heldout[jn] = {"before_rms": float(np.sqrt(np.mean(rt0[sel] ** 2)) / D.wj[j]),
                       "after_rms": float(np.sqrt(np.mean(rt[sel] ** 2)) / D.wj[j]), "unit": "N m"}
    shift = {name: float(c[k]) for k, name in enumerate(nominal)}
    tried.sort(key=lambda t: -t["heldout_gain"])
    return {"laws": laws, "terms": terms, "heldout": heldout, "nominal_shift": shift,
            "heldout_weighted_mse": {"before": mse_start, "after": mse_t}, "tried": tried[:8],
            "heldout_source": source,
            "method": "greedy selection of laws (groups of library columns) by held-out torque-residual error, "
                      f"F test at {ALPHA:g} with the sample count over the residual correlation factor, "
                      "HAC standard deviations"}


def _unit(name: str) -> str:
    from otbot_hw.model.effects import parameter_unit

    return parameter_unit(name)


def _effect_std(law: Law, coef: np.ndarray, std: np.ndarray) -> dict[str, float]:
    """Std of the law's effect entries from its coefficients' (delta method; grid entries: NaN = on the grid)."""
    j = law.joint
    if law.kind == "cogging":
        a, b = coef
        amp = float(np.hypot(a, b)) or 1e-300
        return {f"cog_{j}": float(np.hypot(a * std[0], b * std[1]) / amp),
                f"cogph_{j}": float(np.hypot(b * std[0], a * std[1]) / amp ** 2)}
    if law.kind in ("dead_zone", "soft_limit"):
        # the width from the grid; its coefficient's std relative to 1 scales the width's uncertainty
        return {("dz_" if law.kind == "dead_zone" else "ts_") + j: float(law.grid * std[0])}
    name = law.effect(coef)
    return {next(iter(name)): float(std[0])} if name else {}


def model_with_laws(model: ExtendedModel, disc: dict, nominal_shift: bool = True) -> ExtendedModel:
    """``model`` with the discovered laws' effect entries set (added to what the model has for the catalog's
    entries) and, with ``nominal_shift``, the nominal parameters moved by the regression's shift."""
    values: dict[str, float] = {}
    for lw in disc.get("laws", []):
        for k, v in lw["effect"].items():
            values[k] = v + (model.get(k) if k in ("c_air", "c_r", "c_l", "c_p", "k_r", "k_l", "k_p") else 0.0)
    if nominal_shift:
        for k, dv in disc.get("nominal_shift", {}).items():
            values[k] = model.get(k) + dv
    return model.with_values(values).checked()
