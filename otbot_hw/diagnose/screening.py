"""Screening catalog effects by evidence: sparse regression on the equation residuals and a score test
on the simulation residuals (the first stage of ``select``).

The equation residuals (torque per joint, IMU vs
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
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from otbot_hw.diagnose import catalog as cat
from otbot_hw.diagnose.data import DiagnosisData
from otbot_hw.diagnose.refit import weighted_residuals
from otbot_hw.diagnose.residuals import estimate_motion, imu_residual, torque_residual
from otbot_hw.diagnose.rules import MAX_ROUNDS, SCREEN_DBIC
from otbot_hw.identification.model import map_prediction_rows
from otbot_hw.model.effects import ExtendedModel


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
                      effects: list[cat.Effect], exclude: set[str] = frozenset(),
                      energy: dict | None = None) -> dict[str, tuple[float, dict]]:
    """Score-test screening on the simulation residuals (the objective of the nested fits).

    One linearised Gauss-Newton step per effect: the simulation output change for the
    effect's catalog step (finite differences through the extended simulator), with the free
    nominal parameters' sensitivities projected out. Returns {effect: (Delta BIC of that step
    with per-channel concentrated likelihoods, parameter guess)}. Integration accumulates small
    force effects into large velocity residuals, so this catches effects whose per-sample torque
    signature is below the equation-residual noise.

    ``energy``: if given, filled with {effect: (chi2, k, n, magnitude)}: the signature energy of the
    effect at its catalog step (the largest over its grid variants), ||P A 1||^2 in noise units, with k
    its columns, n the weighted samples and magnitude the step's parameter values
    (``identifiability.effect_identifiability``).
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
        if energy is not None:
            chi2 = float(np.sum(A, axis=1) @ np.sum(A, axis=1))  # the catalog step: coefficient 1 on every column
            if chi2 >= energy.get(v.effect, (-1.0,))[0]:
                energy[v.effect] = (chi2, A.shape[1], n_tot, {**v.values, **v.fixed})
        coef, *_ = np.linalg.lstsq(A, z0, rcond=None)
        # the simulated output changes by A coef; the residual by -A coef
        dres = z0 - A @ coef
        d_bic = float(bic(dres, A.shape[1]) - b0)
        guess = _guess_from_coefficients(v, coef)
        if d_bic < out.get(v.effect, (np.inf, {}))[0]:
            out[v.effect] = (d_bic, guess)
    return out
