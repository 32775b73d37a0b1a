"""Choosing effects by evidence: sparse regression screening, then nested fits.

1. **Screening** (fast, linear): the equation residuals (torque per joint, IMU vs
   encoders; ``residuals.py``) of the nominal fit are regressed on the catalog's
   regressors -- the change of those residuals when one effect parameter is switched on
   (finite differences through the extended model, so the regressors are exactly the
   model's) -- after projecting out the regressors of the free nominal parameters (what a
   refit could absorb). Group orthogonal matching pursuit (numpy only) adds one effect
   (all its parameters) at a time while BIC drops by more than ``SCREEN_DBIC``; BIC uses
   per-channel concentrated likelihoods and an effective sample count N / L (L = the
   Savitzky-Golay window, over which filtered residuals are correlated). Nonlinear
   parameters (Stribeck speed, saturation level, lag, latency) are profiled on a grid.
   A second screen, ``screen_simulation``, is a score test on the simulation residuals
   (one linearised Gauss-Newton step per effect); the shortlist is the union of both.
2. **Nested fits**: the shortlisted candidates (``shortlist``) are re-identified jointly with
   the free nominal parameters by simulation output error through ``refit.refit`` (a quick
   look of ``QUICK_NFEV`` iterations, continued only with evidence). The rules, pure
   functions pinned by ``tests/test_diagnose_rules.py``:

   * ``has_evidence``: BIC beats the base by ``ACCEPT_DBIC`` *effective* samples (divided by
     the residual correlation factor kappa = N / N_eff, ``refit.correlation_factor``) and the
     held-out recordings are not predicted worse;
   * ``ambiguous_group``: candidates within ``AMBIGUOUS_DBIC`` effective samples of the best
     (a candidate that only adds parameters to another is not a look-alike);
   * ``matters``: the effect's physical significance (``significance.py``) -- torque, drift,
     odometry, delay -- not a channel's fit %; with evidence but not mattering it is listed as
     detected but small;
   * ``pair_adds``: a second effect fitted beside the best adds evidence of its own;
   * ``white``: residuals white (kappa <= ``KAPPA_WHITE``): nothing left to search for.

   Before a name is given, the best candidate's catalog look-alikes get a nested fit too. The
   search goes on after an accepted effect, an ambiguous group or a small detection, up to
   ``MAX_ROUNDS`` rounds (``choose``).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from itertools import zip_longest

import numpy as np

from otbot_hw.diagnose import catalog as cat
from otbot_hw.diagnose.data import DiagnosisData
from otbot_hw.diagnose.refit import FitResult, refit, weighted_residuals
from otbot_hw.diagnose.residuals import estimate_motion, imu_residual, torque_residual
from otbot_hw.identification.model import map_prediction_rows
from otbot_hw.model.effects import ExtendedModel, parameter_bounds

SCREEN_DBIC = 10.0
ACCEPT_DBIC = 10.0
AMBIGUOUS_DBIC = 10.0
MAX_CANDIDATES = 3
SHORTLIST_FRACTION = 0.1
LATER_ROUND_FACTOR = 5.0
MAX_NESTED = 4  # nested fits per round, taken alternately from the two screenings' shortlists
MAX_LOOKALIKES = 2  # catalog look-alikes of the best candidate fitted beside it before it is named
MAX_PAIR_TRIES = 2  # second candidates fitted beside a best that leaves correlated residuals
MAX_ROUNDS = 3  # rounds of screening + nested fits (each adds one effect, group or small detection)
NESTED_NFEV = 12  # iterations (function evaluations) of a nested fit
QUICK_NFEV = 5  # ... after which a candidate without BIC evidence is given up
KAPPA_WHITE = 1.2  # residual correlation factor of white residuals: nothing left for a further effect
NESTED_TOL = 1e-5  # relative cost/step tolerance of a nested fit (1e-5 of a cost ~ N: < 0.1 BIC)


def _guess_from_coefficients(v, coef) -> dict[str, float]:
    """Starting values of an effect from its screening coefficients.

    The regressor columns are the change of the residual per unit step of each
    parameter, so the model change that cancels the residual is -coef * step.
    Nonlinear lags (current_lag, imu_latency) scale their probe value instead.
    """
    guess = dict(v.fixed)
    for c, p in zip(coef, v.linear):
        guess[p] = float(-c * v.values[p])
    if not v.linear and v.effect in ("current_lag", "imu_latency"):
        (k, val), = v.fixed.items()
        guess[k] = float(val * np.clip(-coef[0], 0.05, 2.0))
    return guess


FLOOR_NOMINAL = ("m_c", "I_c", "x_B", "y_B", "I_p", "b_w", "b_p")
STAND_NOMINAL = ("I_a", "b_w", "I_p", "b_p")
LOCKED_NOMINAL = ("I_p", "b_p")


def free_nominal(recordings: list[DiagnosisData]) -> list[str]:
    """Nominal parameters the data can identify (paper §4.2 steps): bench runs free the wheel
    inertia and frictions, floor runs the chassis; platform mass and centre are taken as known."""
    out: list[str] = []
    for d in recordings:
        names = {"floor": FLOOR_NOMINAL, "stand": STAND_NOMINAL, "locked": LOCKED_NOMINAL}[d.fixture]
        out += [n for n in names if n not in out]
    return out


# --- screening ---------------------------------------------------------------

def _stack(recordings, model, trim):
    """Equation residuals of every recording: list of (N_k, 6) arrays (torque r, l, p; a_x, a_y, g_z)."""
    out = []
    for d in recordings:
        m = estimate_motion(d, model)
        tr = torque_residual(d, model, m)
        ir = imu_residual(d, model, m)
        if ir is None:
            ir = np.full((len(d), 3), np.nan)
        z = np.column_stack([tr, ir])[trim:len(d) - trim]
        if d.fixture == "locked":
            z[:, :2] = np.nan
        out.append(z)
    return out


@dataclass
class Variant:
    """One screening column group: an effect with its linear step values (and grid values)."""

    effect: str
    values: dict[str, float]  # parameter values of the unit step (coefficient 1 = these values)
    linear: tuple[str, ...]  # parameters whose columns are separate
    fixed: dict[str, float] = field(default_factory=dict)  # profiled nonlinear parameters


SATURATION_MOTORS = {"u_max": (0, 1, 2), "u_max_r": (0,), "u_max_l": (1,), "u_max_p": (2,)}
SATURATION_GRID = (0.9, 0.75, 0.6)  # fractions of the largest recorded command of the motor(s)


def _variants(recordings: list[DiagnosisData], effects: list[cat.Effect]) -> list[Variant]:
    """Screening column groups: every effect at its catalog step, nonlinear parameters on their grid
    (saturation levels: fractions of the largest recorded command of the motors concerned)."""
    out = []
    for e in effects:
        step = dict(e.magnitudes[0])
        if e.grids:
            (gname, grid), = e.grids.items()
            if gname in SATURATION_MOTORS:
                top = max(float(np.max(np.abs(d.u[:, list(SATURATION_MOTORS[gname])]))) for d in recordings)
                grid = tuple(f * top for f in SATURATION_GRID)
            lin = tuple(p for p in e.parameters if p != gname and p in step)
            for g in grid:
                if lin:
                    out.append(Variant(e.name, {p: step[p] for p in lin}, lin, {gname: g}))
                else:
                    out.append(Variant(e.name, {}, (), {gname: g}))
        else:
            out.append(Variant(e.name, {p: step[p] for p in e.parameters}, tuple(e.parameters)))
    return out


@dataclass
class Screening:
    """Screening outcome: single-effect BIC gains, the greedy selection and coefficient estimates."""

    single: dict[str, float]  # effect -> best Delta BIC alone (negative = evidence)
    guesses: dict[str, dict[str, float]]  # effect -> parameter guess from the regression
    selected: list[str]
    channel_rms: list[float]


def screen(recordings: list[DiagnosisData], model: ExtendedModel, nominal_free: list[str],
           effects: list[cat.Effect], exclude: set[str] = frozenset()) -> Screening:
    """Rank catalog effects by how much of the equation residuals they explain (see module doc)."""
    trim = max(d.window for d in recordings)
    base = _stack(recordings, model, trim)
    z = np.concatenate(base)  # (N, 6)
    valid = np.all(np.isfinite(z), axis=0) | (np.mean(np.isfinite(z), axis=0) > 0.5)
    ok = np.isfinite(z)
    rms = np.array([np.sqrt(np.nanmean(z[:, j] ** 2)) if valid[j] and np.any(ok[:, j]) else 1.0
                    for j in range(6)])
    rms = np.maximum(rms, 1e-9)

    def vec(stacks):  # whitened, channel-major, NaN -> 0 (masked rows stay 0 in both z and columns)
        a = np.concatenate(stacks)
        a = np.where(ok, a, 0.0) / rms
        return a.T.reshape(-1)

    zv = vec(base)
    n_ch = z.shape[0]
    L = max(d.window for d in recordings)
    variants = [v for v in _variants(recordings, effects) if v.effect not in exclude]
    # every perturbed model's residuals at once, on the prediction threads (the kernels release the GIL)
    steps = {n: 1e-4 * max(abs(model.get(n)), 1e-2) for n in nominal_free}
    models = [model.with_values({n: model.get(n) + h}) for n, h in steps.items()]
    layout = []
    for i, v in enumerate(variants):
        for p in (v.linear or (None,)):
            layout.append(i)
            models.append(model.with_values({**v.fixed, p: v.values[p]} if p is not None else v.fixed))
    stacks = map_prediction_rows(lambda j: vec(_stack(recordings, models[j], trim)), len(models))
    # nominal columns
    nom_cols = [(stacks[j] - zv) / h for j, h in enumerate(steps.values())]
    Y = np.column_stack(nom_cols) if nom_cols else np.zeros((len(zv), 0))
    if Y.shape[1]:
        Qn, Rn = np.linalg.qr(Y)
        keep = np.abs(np.diag(Rn)) > 1e-8 * np.max(np.abs(np.diag(Rn)))
        Qn = Qn[:, keep]
    else:
        Qn = np.zeros((len(zv), 0))

    def proj(a):
        return a - Qn @ (Qn.T @ a)

    z0 = proj(zv)
    chans = [slice(j * n_ch, (j + 1) * n_ch) for j in range(6)]
    active = [j for j in range(6) if valid[j] and np.any(ok[:, j])]
    n_eff = n_ch / L

    def bic(res, k):
        return sum(n_eff * np.log(max(res[c] @ res[c], 1e-300) / n_ch) for c in (chans[j] for j in active)) \
            + k * np.log(n_eff * len(active))

    per_variant: dict[int, list] = {}
    for i, st in zip(layout, stacks[len(steps):]):
        per_variant.setdefault(i, []).append(proj(st - zv))
    cols = {i: np.column_stack(cs) for i, cs in per_variant.items()}
    bic0 = bic(z0, 0)
    single: dict[str, float] = {}
    guesses: dict[str, dict[str, float]] = {}
    best_var: dict[str, int] = {}
    for i, v in enumerate(variants):
        A = cols[i]
        if not np.any(A):
            continue
        coef, *_ = np.linalg.lstsq(A, z0, rcond=None)
        d = bic(z0 - A @ coef, A.shape[1]) - bic0
        if d < single.get(v.effect, np.inf):
            single[v.effect] = float(d)
            best_var[v.effect] = i
            guesses[v.effect] = _guess_from_coefficients(v, coef)
    # greedy group selection
    selected: list[str] = []
    A_sel = np.zeros((len(z0), 0))
    cur = bic0
    res = z0
    for _ in range(MAX_ROUNDS + 1):
        best = None
        for e, i in best_var.items():
            if e in selected:
                continue
            A = np.column_stack([A_sel, cols[i]])
            coef, *_ = np.linalg.lstsq(A, z0, rcond=None)
            r = z0 - A @ coef
            b = bic(r, A.shape[1])
            if best is None or b < best[0]:
                best = (b, e, A, r)
        if best is None or best[0] - cur > -SCREEN_DBIC:
            break
        cur, e, A_sel, res = best[0], best[1], best[2], best[3]
        selected.append(e)
    return Screening(single=single, guesses=guesses, selected=selected, channel_rms=rms.tolist())


def screen_simulation(recordings: list[DiagnosisData], model: ExtendedModel, nominal_free: list[str],
                      effects: list[cat.Effect], exclude: set[str] = frozenset()) -> dict[str, tuple[float, dict]]:
    """Score-test screening on the simulation residuals (the objective of the nested fits).

    One linearised Gauss-Newton step per effect: the simulation output change for the
    effect's catalog step (finite differences through the extended simulator), with the free
    nominal parameters' sensitivities projected out. Returns {effect: (Delta BIC of that step
    with per-channel concentrated likelihoods, parameter guess)}. Integration accumulates small
    force effects into large velocity residuals, so this catches effects whose per-sample torque
    signature is below the equation-residual noise.
    """
    from otbot_hw.diagnose.refit import channel_sigmas

    sig = channel_sigmas(recordings)
    base = weighted_residuals(recordings, model, sig)
    keys = list(base)
    r0 = np.concatenate([base[k] for k in keys])
    sl, i = {}, 0
    for k in keys:
        sl[k] = slice(i, i + len(base[k]))
        i += len(base[k])

    def vec(m):
        res = weighted_residuals(recordings, m, sig)
        return np.concatenate([res[k] for k in keys])

    variants = [v for v in _variants(recordings, effects) if v.effect not in exclude]
    models, layout = [], []
    for n in nominal_free:
        models.append(model.with_values({n: model.get(n) + 1e-4 * max(abs(model.get(n)), 1e-2)}))
    for i, v in enumerate(variants):
        for p in (v.linear or (None,)):
            try:
                models.append(model.with_values({**v.fixed, p: v.values[p]} if p is not None else v.fixed))
            except ValueError:
                continue
            layout.append(i)
    outputs = map_prediction_rows(lambda j: vec(models[j]) - r0, len(models))
    cols = outputs[:len(nominal_free)]
    Qn = np.zeros((len(r0), 0))
    if cols:
        Qn, Rn = np.linalg.qr(np.column_stack(cols))
        Qn = Qn[:, np.abs(np.diag(Rn)) > 1e-8 * np.max(np.abs(np.diag(Rn)))]
    z0 = r0 - Qn @ (Qn.T @ r0)
    n_tot = len(r0)

    def bic(res, k):
        return sum(len(base[key]) * np.log(max(res[sl[key]] @ res[sl[key]], 1e-300) / len(base[key]))
                   for key in keys) + k * np.log(n_tot)

    b0 = bic(z0, 0)
    out: dict[str, tuple[float, dict]] = {}
    per_variant: dict[int, list] = {}
    for i, d in zip(layout, outputs[len(nominal_free):]):
        per_variant.setdefault(i, []).append(d - Qn @ (Qn.T @ d))
    for i, A in per_variant.items():
        v = variants[i]
        A = np.column_stack(A)
        coef, *_ = np.linalg.lstsq(A, z0, rcond=None)
        # the simulated output changes by A coef; the residual by -A coef
        dres = z0 - A @ coef
        d_bic = float(bic(dres, A.shape[1]) - b0)
        guess = _guess_from_coefficients(v, coef)
        if d_bic < out.get(v.effect, (np.inf, {}))[0]:
            out[v.effect] = (d_bic, guess)
    return out


# --- nested fits -------------------------------------------------------------

def information_criteria(fit_rss: dict, n_samples: dict, k: int) -> tuple[float, float]:
    """(AIC, BIC) from per-channel concentrated Gaussian likelihoods; k free parameters."""
    n_tot = sum(n_samples.values())
    ll = sum(n * np.log(max(fit_rss[key], 1e-300) / n) for key, n in n_samples.items())
    return float(ll + 2 * k), float(ll + k * np.log(n_tot))


def holdout_cost(holdout: list[DiagnosisData], model: ExtendedModel) -> float:
    """Sum over held-out channels of N ln(RSS / N) (noise-weighted): lower predicts better."""
    if not holdout:
        return float("nan")
    from otbot_hw.diagnose.refit import channel_sigmas

    res = weighted_residuals(holdout, model, channel_sigmas(holdout))
    return float(sum(len(v) * np.log(max(v @ v, 1e-300) / len(v)) for v in res.values()))


@dataclass
class Candidate:
    """A nested fit of one effect: the fit, its BIC gain over the base model, its held-out gain, the
    correlation factor of its residuals (``refit.correlation_factor``) and its physical significance."""

    effect: str
    fit: FitResult
    dbic: float
    daic: float
    dholdout: float
    screen_dbic: float
    sim_screen_dbic: float = float("nan")
    kappa: float = 1.0
    significance: dict = field(default_factory=dict)
    parameters: tuple[str, ...] = ()

    @property
    def evidence(self) -> float:
        """BIC gain in effective samples: Delta BIC / kappa (negative = evidence for the effect)."""
        return self.dbic / max(self.kappa, 1.0)


@dataclass
class Selection:
    """Accepted effects (in order), ambiguous groups, effects detected but too small to matter, every
    candidate tried and the final fit."""

    accepted: list[Candidate]
    ambiguous: list[list[Candidate]]
    tried: list[Candidate]
    screenings: list[Screening]
    base_fit: FitResult
    final_fit: FitResult
    sim_screenings: list[dict[str, float]] = field(default_factory=list)
    small: list[Candidate] = field(default_factory=list)
    effects: dict[str, cat.Effect] = field(default_factory=dict)  # the catalog entries as applied


def _effect_guess(e: cat.Effect, screening: Screening, sim_guess: dict | None = None,
                  model: ExtendedModel | None = None) -> dict[str, float]:
    """Start values: the simulation screening's step when it has one, else the equation screening's,
    else half the catalog step, else (a position) the model's value."""
    g = dict(screening.guesses.get(e.name, {}))
    g.update(sim_guess or {})
    out = {}
    for p in e.parameters:
        lo, hi = parameter_bounds(p)
        default = e.magnitudes[0][p] * 0.5 if p in e.magnitudes[0] else (model.get(p) if model is not None else 0.0)
        v = g.get(p, default)
        span = hi - lo
        out[p] = float(np.clip(v, lo + 1e-3 * span, hi - 1e-3 * span))
    return out


# --- the selection rules (pure functions: pinned by tests/test_diagnose_rules.py) ---------------

def shortlist(equation_gains: dict[str, float], simulation_gains: dict[str, float], round_index: int) -> list[str]:
    """Effects worth a nested fit: from each screening (equation residuals, simulation score test) the
    ``MAX_CANDIDATES`` best whose BIC gain beats the bar (``SCREEN_DBIC``, ``LATER_ROUND_FACTOR`` times
    that after the first round: residuals are then smaller and relatively more correlated) and reaches
    ``SHORTLIST_FRACTION`` of that screening's best gain; merged alternately, at most ``MAX_NESTED``."""
    bar = SCREEN_DBIC * (1 if round_index == 0 else LATER_ROUND_FACTOR)
    lists = []
    for gains in (equation_gains, simulation_gains):
        ranked = sorted((d, e) for e, d in gains.items() if d < -bar)
        lists.append([e for d, e in ranked[:MAX_CANDIDATES] if d <= SHORTLIST_FRACTION * ranked[0][0]])
    out: list[str] = []
    for pair in zip_longest(*lists):  # alternately, so both screenings are heard within MAX_NESTED
        for e in pair:
            if e is not None and e not in out:
                out.append(e)
    return out[:MAX_NESTED]


def has_evidence(c: Candidate) -> bool:
    """Accepted by evidence: the BIC gain in effective samples beats ``ACCEPT_DBIC`` and held-out
    recordings (if any) are not predicted worse."""
    return c.evidence < -ACCEPT_DBIC and not (c.dholdout > 0)


def ambiguous_group(best: Candidate, others: list[Candidate]) -> list[Candidate]:
    """The best candidate and those the data cannot tell from it: BIC within ``AMBIGUOUS_DBIC``
    effective samples (the best fit's correlation factor deflates the difference). A candidate that
    only adds parameters to another one in the group (wheel slip with a traction limit vs wheel slip)
    is not a look-alike but the same explanation with an unneeded parameter: the simpler one stands
    for both."""
    near = [best] + [c for c in others if c is not best
                     and (c.dbic - best.dbic) / max(best.kappa, 1.0) < AMBIGUOUS_DBIC]
    keep = [c for c in near if not any(set(o.parameters) < set(c.parameters) for o in near)]
    lead = best if best in keep else min(keep, key=lambda c: c.dbic)
    return [lead] + [c for c in keep if c is not lead]


def matters(c: Candidate) -> bool:
    """Whether an effect with evidence matters physically (``significance.significance``)."""
    return bool(c.significance.get("matters"))


def _kappa(recordings: list[DiagnosisData], fit: FitResult) -> float:
    from otbot_hw.diagnose.refit import correlation_factor

    return correlation_factor(weighted_residuals(recordings, fit.model, fit.sigma))


def fitting_evidence(c: Candidate) -> bool:
    """BIC evidence on the fitting recordings alone (``has_evidence`` without the held-out test)."""
    return c.evidence < -ACCEPT_DBIC


def pair_adds(pair: Candidate, first: Candidate) -> bool:
    """A second effect fitted beside ``first`` adds evidence: the pair's BIC beats the first alone by
    ``ACCEPT_DBIC`` effective samples, and it predicts the held-out runs no worse than the first alone."""
    return (pair.dbic - first.dbic) / max(pair.kappa, 1.0) < -ACCEPT_DBIC and not (pair.dholdout > first.dholdout)


class _Search:
    """State of one selection: the data, the base the next candidates are fitted on, what was found."""

    def __init__(self, recordings, holdout, base_fit, nominal_free, progress, casters_configured):
        self.recordings, self.holdout, self.progress = recordings, holdout, progress
        self.nominal_free = nominal_free
        effects = cat.applicable({d.fixture for d in recordings}, casters_configured)
        self.effects = effects
        self.by_name = {e.name: e for e in effects}
        self.current = base_fit
        self.accepted: list[Candidate] = []
        self.ambiguous: list[list[Candidate]] = []
        self.small: list[Candidate] = []
        self.tried: list[Candidate] = []
        self.screenings: list[Screening] = []
        self.sim_screens: list[dict[str, float]] = []
        self.used: set[str] = set()

    def reference(self, fit: FitResult) -> tuple[float, float, float]:
        aic, bic = information_criteria(fit.rss, fit.n_samples, fit.n_params)
        return aic, bic, holdout_cost(self.holdout, fit.model)

    def nested(self, name: str, on: FitResult, ref: tuple, guess: dict, screen_gains=(np.nan, np.nan),
               beside: float | None = None) -> Candidate:
        """Fit effect ``name`` beside the model of ``on``; evidence against the reference (AIC, BIC, held-out).
        The fit goes on after the quick look only while it shows BIC evidence -- against the reference, or
        against ``beside`` (the BIC gain of the effect already in ``on``) for a second effect."""
        e = self.by_name[name]
        names = list(on.names) + [p for p in e.parameters if p not in on.names]
        self.progress(f"[diagnose] nested fit: + {name} (start {guess})")
        fit = refit(self.recordings, on.model, names, guess=guess, max_nfev=QUICK_NFEV, tol=NESTED_TOL)
        aic, bic = information_criteria(fit.rss, fit.n_samples, fit.n_params)
        bar = ref[1] + (beside if beside is not None else 0.0)
        if fit.nfev >= QUICK_NFEV and bic - bar < -ACCEPT_DBIC:  # promising and not converged yet: go on
            fit = refit(self.recordings, fit.model, names, max_nfev=NESTED_NFEV - QUICK_NFEV, tol=NESTED_TOL)
            aic, bic = information_criteria(fit.rss, fit.n_samples, fit.n_params)
        c = Candidate(name, fit, bic - ref[1], aic - ref[0], holdout_cost(self.holdout, fit.model) - ref[2],
                      screen_gains[0], screen_gains[1], parameters=tuple(e.parameters))
        if c.dbic < -ACCEPT_DBIC:
            c.kappa = _kappa(self.recordings, fit)
        self.progress(f"[diagnose]   {name}: dBIC {c.dbic:.1f} (kappa {c.kappa:.1f}), held-out d(cost) {c.dholdout:.1f}")
        self.tried.append(c)
        return c

    def round(self, on: FitResult, ref: tuple, round_index: int, exclude: set[str]) -> list[Candidate]:
        """Screen from the model of ``on`` and fit the shortlist beside it."""
        sc = screen(self.recordings, on.model, self.nominal_free, self.effects, exclude=exclude)
        self.screenings.append(sc)
        ss = screen_simulation(self.recordings, on.model, self.nominal_free, self.effects, exclude=exclude)
        self.sim_screens.append({e: d for e, (d, _) in ss.items()})
        names = shortlist(sc.single, {e: d for e, (d, _) in ss.items()}, round_index)
        if not names:
            self.progress("[diagnose] screening: no further effect explains the equation or simulation residuals")
            return []
        self.progress(f"[diagnose] screening shortlist: {', '.join(names)}")
        return [self.nested(n, on, ref, _effect_guess(self.by_name[n], sc, ss.get(n, (0.0, {}))[1], on.model),
                            (sc.single.get(n, np.nan), ss.get(n, (np.nan, {}))[0])) for n in names]

    def lookalikes(self, best: Candidate, cands: list[Candidate], on: FitResult, ref: tuple,
                   exclude: set[str]) -> list[Candidate]:
        """Fit the best candidate's catalog look-alikes (up to ``MAX_LOOKALIKES``) that the screening did not
        shortlist, beside the same model: before a name is given, the effects it is known to be mistaken
        for get the same chance (e.g. a gain error of the other motor, an encoder scale for a radius)."""
        done = {c.effect for c in cands} | exclude
        out = []
        for name in [n for n in self.by_name[best.effect].lookalikes if n in self.by_name and n not in done][
                :MAX_LOOKALIKES]:
            e = self.by_name[name]
            out.append(self.nested(name, on, ref, {p: e.magnitudes[0].get(p, on.model.get(p)) * 0.5
                                                   for p in e.parameters}))
        return out

    def polish(self, good: list[Candidate], cands: list[Candidate], ref: tuple) -> tuple:
        """Guard against an under-converged base fit: refit the base from the best candidate's nominal
        values; the gains must survive against this polished base (returns the new reference)."""
        best0 = min(good, key=lambda c: c.dbic)
        names = self.current.names
        start = self.current.model.with_values({n: best0.fit.values[n] for n in names})
        polished = refit(self.recordings, start, names, max_nfev=NESTED_NFEV, tol=NESTED_TOL)
        new = self.reference(polished)
        if new[1] < ref[1] - 0.1:
            self.progress(f"[diagnose] base refit from the candidate's nominal values gains {ref[1] - new[1]:.1f} BIC")
            for c in cands:
                c.dbic += ref[1] - new[1]
                c.daic += ref[0] - new[0]
                if np.isfinite(ref[2]) and np.isfinite(new[2]):
                    c.dholdout += ref[2] - new[2]
            self.current = polished
            return new
        return ref

    def judge(self, c: Candidate) -> None:
        from otbot_hw.diagnose.significance import significance

        vals = {p: c.fit.values[p] for p in c.parameters}
        # what the effect does over every run at hand, held-out ones included (their speeds and torques)
        c.significance = significance(c.effect, vals, {p: c.fit.std.get(p, float("nan")) for p in c.parameters},
                                      c.fit.model, self.recordings + self.holdout)

    def take(self, best: Candidate, others: list[Candidate], group: list[Candidate] | None = None) -> None:
        """Add ``best`` (with the candidates the data cannot tell from it: ``group``, default
        ``ambiguous_group(best, others)``) to the findings."""
        group = group or ambiguous_group(best, others)
        best = group[0]  # the simplest of nested explanations leads
        for c in group:
            self.judge(c)
        self.used.update(c.effect for c in group)
        if not matters(best):
            self.progress(f"[diagnose] {best.effect}: detected, small ({best.significance['statement']})")
            self.small.append(best)
            return
        if len(group) > 1:
            self.ambiguous.append(group)
            self.progress(f"[diagnose] ambiguous: {', '.join(c.effect for c in group)}; the search goes on with "
                          f"{best.effect}")
        else:
            self.accepted.append(best)
        self.current = best.fit

    def second_beside(self, first: Candidate, cands: list[Candidate], ref: tuple) -> Candidate | None:
        """Fit a second candidate with fitting evidence beside ``first`` (two effects at once) and return the
        pair's candidate when it adds evidence (``pair_adds``). Tried in order: candidates that are not
        catalog look-alikes of ``first`` (other physics, likely the rest of the residual), then its
        look-alikes, each by BIC gain; at most ``MAX_PAIR_TRIES``. Before this, nothing is grouped as
        ambiguous: two effects that each leave correlated residuals may both be there."""
        look = set(self.by_name[first.effect].lookalikes)
        others = sorted((c for c in cands if c is not first and fitting_evidence(c)
                         and not set(c.parameters) & set(first.parameters)),
                        key=lambda c: (c.effect in look, c.dbic))
        for second in others[:MAX_PAIR_TRIES]:
            guess = {p: second.fit.values[p] for p in second.parameters}
            pair = self.nested(second.effect, first.fit, ref, guess, (second.screen_dbic, second.sim_screen_dbic),
                               beside=first.dbic)
            if pair.dbic < -ACCEPT_DBIC and pair.kappa == 1.0:
                pair.kappa = _kappa(self.recordings, pair.fit)
            if pair_adds(pair, first):
                return pair
        return None


def white(c: Candidate) -> bool:
    """The candidate's residuals are white (``KAPPA_WHITE``): the model explains the data to the noise."""
    return c.kappa <= KAPPA_WHITE


def choose(recordings: list[DiagnosisData], holdout: list[DiagnosisData], base_fit: FitResult,
           nominal_free: list[str], progress=lambda msg: None, casters_configured: bool = True) -> Selection:
    """Greedy forward selection of effects: screen, nested fits, accept by evidence, judge by physics.

    Each round adds the best candidate with evidence (``has_evidence``): alone, or as an ambiguous
    group (carried on with its best member, its members excluded from later rounds), or -- when it
    does not matter physically -- listed as detected but small and left out of the model. Two effects
    at once: when a second candidate also has evidence, it is fitted beside the best and kept when the
    pair adds evidence (``pair_adds``); when the best has evidence on the fitting data but predicts the
    held-out runs worse (a second effect it cannot stand in for), it is carried provisionally for one
    round and kept only if an effect beside it passes both tests. The search goes on after each of
    these, up to ``MAX_ROUNDS`` rounds."""
    S = _Search(recordings, holdout, base_fit, nominal_free, progress, casters_configured)
    provisional: Candidate | None = None
    ref = S.reference(S.current)
    for round_index in range(MAX_ROUNDS):
        on = provisional.fit if provisional else S.current
        cands = S.round(on, ref, round_index, S.used | ({provisional.effect} if provisional else set()))
        good = [c for c in cands if has_evidence(c)]
        if good:
            ref = S.polish(good, cands, ref)
            good = [c for c in cands if has_evidence(c)]
        if good:
            exclude = S.used | ({provisional.effect} if provisional else set())
            cands += S.lookalikes(min(good, key=lambda c: c.dbic), cands, on, ref, exclude)
            good = [c for c in cands if has_evidence(c)]
        if not good:
            # the first round's best explains the fitting data but predicts the held-out runs worse: a
            # second effect it cannot stand in for may be at work
            fit_only = [c for c in cands if fitting_evidence(c)]
            if provisional is None and fit_only and round_index == 0:
                provisional = min(fit_only, key=lambda c: c.dbic)
                progress(f"[diagnose] {provisional.effect} explains the fitting data but not the held-out runs: "
                         "carried provisionally, to try a second effect beside it")
                continue
            break
        good.sort(key=lambda c: c.dbic)
        # the best candidate that matters physically leads; better-evidenced ones that do not matter are listed
        # as detected but small; when none matters, nothing on this model does: the search ends
        for c in good:
            S.judge(c)
        lead = next((c for c in good if matters(c)), None)
        for c in good[:good.index(lead) if lead is not None else len(good)]:
            progress(f"[diagnose] {c.effect}: detected, small ({c.significance['statement']})")
            S.small.append(c)
            S.used.add(c.effect)
        if lead is None:
            break
        good = good[good.index(lead):]
        best = lead
        if provisional is not None:
            # the pair passed where the provisional effect alone did not: both are findings
            first = dataclasses.replace(provisional, fit=best.fit, dbic=provisional.dbic,
                                        dholdout=min(provisional.dholdout, best.dholdout))
            S.take(first, [])
            S.used.add(first.effect)
            provisional = None
            S.take(best, good[1:])
            ref = S.reference(S.current)
            continue
        # a second effect beside the best only when the best leaves structure (correlated residuals)
        pair = S.second_beside(best, cands, ref) if round_index + 1 < MAX_ROUNDS and not white(best) else None
        if pair is not None:
            single = next(c for c in cands if c.effect == pair.effect)
            # the second effect's look-alikes (as hard to tell from it alone) get their own fit beside the first
            alike = [c for c in good if c is not best and c is not single
                     and abs(c.dbic - single.dbic) / max(single.kappa, 1.0) < AMBIGUOUS_DBIC
                     and not set(c.parameters) & set(best.parameters)]
            beside = [S.nested(c.effect, best.fit, ref, {p: c.fit.values[p] for p in c.parameters},
                               (c.screen_dbic, c.sim_screen_dbic), beside=best.dbic) for c in alike]
            for c in [pair] + beside:
                c.dbic -= best.dbic  # each second effect's own evidence, beside the first
            progress(f"[diagnose] {pair.effect} beside {best.effect}: the pair adds {-pair.dbic:.0f} BIC")
            # the first's look-alikes are judged with the correlation the pair leaves (the second effect's
            # residual inflated every single fit's alike)
            S.take(dataclasses.replace(best, fit=pair.fit, kappa=pair.kappa),
                   [c for c in good[1:] if c.effect != pair.effect])
            S.take(pair, beside)
        else:
            S.take(best, good[1:])
        last = pair or best
        if white(last) and S.current is last.fit:
            progress(f"[diagnose] residuals white after {last.effect} (kappa {last.kappa:.2f}): search done")
            break
        ref = S.reference(S.current)
    return Selection(S.accepted, S.ambiguous, S.tried, S.screenings, base_fit, S.current, S.sim_screens, S.small,
                     S.by_name)
