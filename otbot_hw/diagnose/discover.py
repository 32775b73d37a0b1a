"""Beyond the catalog: the law the model misses, by grouped sparse regression on the residual generalized forces.

When no catalog effect brings the model to the noise level, what the model misses is still measured:
the torque residual per joint (``residuals.torque_residual``: the command minus the torque the model
needs for the motion estimated from the encoders, N m; unmodelled friction reads as +friction). It is
regressed on a library of candidate *laws*, each a group of columns sharing one physical meaning and
each a law the model can step (``otbot_hw.model.effect_catalog``: the catalog's entries or the laws
beyond it; the library is ``law_library``), per joint j (r, l, p):

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
pass two gates -- a held-out gain of ``MIN_HELDOUT_GAIN`` and an F test at ``ALPHA`` on the fitting data
with the sample count divided by the residual correlation factor (``refit.correlation_factor``: the
residual is smoothed and coloured) -- the one that lowers the held-out error most is taken; none passing
ends the search. A law whose coefficients are not physical (negative drag or friction, a dead-zone or limit coefficient far from 1) is not a candidate. So
nearly collinear command terms do not mix: one law per joint at a time, with its meaning. Held-out: the
held-out recordings, else the last ``HOLDOUT_FRACTION`` of each fitting recording.

Reported per law: the effect entries it sets in physical units with a Newey-West (HAC) std on the
coloured residual, what it does, and the held-out torque-residual RMS per joint before/after. Then
(``discover_laws``, what the diagnosis runs) the laws are stepped: refit by simulation with the nominal
parameters, dropped when the simulation does not need them (``LAW_DBIC``), and the held-out recordings
re-simulated with them; that fit is the model ``--out`` writes.

``pysindy`` is not used: its optimizers threshold single raw coefficients of columns with different
units, with no grouping of columns into laws and no held-out choice without scikit-learn on top.
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np
from scipy import stats

from otbot_hw.diagnose.adequacy import assess
from otbot_hw.diagnose.data import DiagnosisData
from otbot_hw.diagnose.law_library import (JOINTS, MEANING, Law, basis, candidate_groups, effect_std,
                                           model_with_laws)
from otbot_hw.diagnose.refit import bandwidth, correlation_factor, refit, robust_std, weighted_residuals
from otbot_hw.model.effects import ExtendedModel, parameter_unit

MAX_LAWS = 4
MIN_HELDOUT_GAIN = 0.03  # relative drop of the held-out weighted mean square a law must bring
ALPHA = 1e-3  # F test size per step
HOLDOUT_FRACTION = 0.3


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
    fit_b = [basis(d, model, nominal) for d in recordings]
    if holdout:
        hold_b = [basis(d, model, nominal) for d in holdout]
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
        est = effect_std(law, cf, cs)
        laws.append({"law": law.label, "kind": law.kind, "joint": law.joint, "grid": law.grid, "effect": eff,
                     "std": est, "coefficient": [float(v) for v in cf], "coefficient_std": [float(v) for v in cs],
                     "meaning": MEANING[law.kind], "heldout_gain": float(gain), "free": law.free()})
        i += k
    terms = [{"term": lw["law"], "joint": lw["joint"], "value": float(next(iter(lw["effect"].values()))),
              "std": float(next(iter(lw["std"].values()))), "unit": parameter_unit(next(iter(lw["effect"]))),
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


DISCOVERY_NFEV = 15  # iterations of the simulation refit of the discovered laws
LAW_DBIC = 10.0  # effective BIC a discovered law must be worth in the refit model's simulation, else dropped


def _resim(sets, model) -> dict[str, dict]:
    """RMS of measured minus simulated per channel over ``sets`` and its ratio to the channel noise."""
    from otbot_hw.diagnose.simulated_run import simulation_residual

    acc: dict[str, list] = {}
    for d in sets:
        for ch, r in simulation_residual(d, model).items():
            acc.setdefault(ch, []).append((r, d.noise_sigma(ch)))
    return {ch: {"rms": float(np.sqrt(np.mean(np.concatenate([r for r, _ in v]) ** 2))),
                 "noise_ratio": float(np.sqrt(np.mean(np.concatenate([(r / s) ** 2 for r, s in v]))))}
            for ch, v in acc.items()}


def _step_laws(recordings, holdout, base, disc: dict, nominal_free, params, progress):
    """The discovered laws stepped: their entries (and the nominal parameters) refit by simulation from the
    regression's values, standard deviations by HAC, and the held-out recordings (else the fitting ones)
    re-simulated with and without them. Updates ``disc`` (``laws[i].refit``, ``resimulation``,
    ``improves``, ``adequate_with_laws``); returns the fit (std = HAC) or None when the refit fails."""
    try:
        start = model_with_laws(base.model, disc)
    except ValueError as exc:
        disc["refit_error"] = str(exc)
        return None
    free = list(nominal_free) + [n for lw in disc["laws"] for n in lw["free"] if n not in nominal_free]
    fit = refit(recordings, start, free, max_nfev=DISCOVERY_NFEV)
    progress(f"[diagnose] discovered laws refit by simulation: {fit.message} ({fit.nfev} evaluations)")
    hac = robust_std(recordings, fit)
    std = {n: max(fit.std.get(n, np.nan), hac.get(n, np.nan)) if np.isfinite(hac.get(n, np.nan)) else
           fit.std.get(n, np.nan) for n in free}
    # a law the simulation does not need is dropped: removing it from the refit model costs less than its
    # BIC penalty in effective samples (the residual correlation factor divides the RSS change)
    res = weighted_residuals(recordings, fit.model, fit.sigma)
    rss = sum(float(r @ r) for r in res.values())
    n_all = sum(len(r) for r in res.values())
    kappa = correlation_factor(res)
    dropped = {}
    for lw in disc["laws"]:
        lw["refit"] = {n: {"value": float(fit.model.get(n)), "std": _finite(std.get(n)), "unit": parameter_unit(n)}
                       for n in lw["effect"]}
        without = fit.model.with_values({n: base.model.get(n) for n in lw["effect"]})
        rss_wo = sum(float(r @ r) for r in weighted_residuals(recordings, without, fit.sigma).values())
        gain = (rss_wo - rss) / kappa
        lw["simulation_delta_bic"] = float(-gain + len(lw["free"]) * np.log(n_all))
        if lw["simulation_delta_bic"] > -LAW_DBIC:
            dropped.update({n: base.model.get(n) for n in lw["effect"]})
            lw["dropped"] = (f"the simulation does not need it (removing it from the refit model: effective dBIC "
                             f"{-lw['simulation_delta_bic']:+.1f})")
    disc["dropped"] = [lw for lw in disc["laws"] if lw.get("dropped")]
    disc["laws"] = [lw for lw in disc["laws"] if not lw.get("dropped")]
    disc["terms"] = [t for t in disc["terms"] if any(t["term"] == lw["law"] for lw in disc["laws"])]
    if not disc["laws"]:
        return None
    if dropped:
        fit = dataclasses.replace(fit, model=fit.model.with_values(dropped))
    sets = holdout or recordings
    before, after = _resim(sets, base.model), _resim(sets, fit.model)
    cost = [sum(v["noise_ratio"] ** 2 for v in x.values()) for x in (before, after)]
    disc["resimulation"] = {"set": "held-out" if holdout else "fitting",
                            "channels": {ch: {"before_rms": before[ch]["rms"], "after_rms": after[ch]["rms"],
                                              "before_noise_ratio": before[ch]["noise_ratio"],
                                              "after_noise_ratio": after[ch]["noise_ratio"]} for ch in before},
                            "cost_before": cost[0], "cost_after": cost[1]}
    disc["improves"] = bool(cost[1] < cost[0])
    disc["adequate_with_laws"] = bool(assess(recordings, holdout, fit, params).adequate)
    return dataclasses.replace(fit, std=std)


def discover_laws(recordings, holdout, base, nominal_free, params, progress=lambda msg: None):
    """Beyond the catalog (``discover``): laws in the nominal fit's torque residual, then stepped (``_step_laws``).
    Returns (the ``discovered`` JSON, the fit with the laws or None)."""
    law_fit = None
    try:
        t_disc, c_disc = time.perf_counter(), time.process_time()
        discovered = discover(recordings, holdout, base.model, nominal_free)
        discovered["regression_s"] = time.perf_counter() - t_disc
        progress(f"[diagnose] discovered laws: {', '.join(lw['law'] for lw in discovered['laws']) or 'none'}")
        if discovered["laws"]:
            law_fit = _step_laws(recordings, holdout, base, discovered, nominal_free, params, progress)
        discovered["elapsed_s"] = time.perf_counter() - t_disc
        discovered["cpu_s"] = time.process_time() - c_disc  # process CPU (all threads), unaffected by load
    except (ValueError, np.linalg.LinAlgError, FloatingPointError) as exc:
        discovered = {"error": f"{type(exc).__name__}: {exc}"}
    return discovered, law_fit


def _finite(v):
    return None if v is None or not np.isfinite(v) else float(v)
