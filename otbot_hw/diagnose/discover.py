"""Beyond the catalog: the law the model misses, by sparse regression on the residual generalized forces.

When no catalog effect brings the model to the noise level, what the model misses is still measured:
the torque residual per joint (``residuals.torque_residual``: the command minus the torque the model
needs for the motion estimated from the encoders, N m; unmodelled friction reads as +friction). It is
regressed on a library of candidate terms evaluated along the estimated motion, per joint j (r, l, p):

* joint rate w_j (viscous), its sign tanh(w_j / 0.02 rad/s) (Coulomb-like), w_j |w_j| (quadratic);
* joint angle sin(k phi_j), cos(k phi_j), k = 1, 2, 4 (cogging, eccentricity, position-dependent
  friction);
* pivot-force terms on the floor: the joint torques J^T v and J^T |v| v of a force -v, -|v| v at the
  pivot (linear and quadratic drag of the platform; J the pivot rows of M_FIK), and |v|;
* the command u_j, u_j |u_j|, u_j^3, its dead-zone part clip(u_j, -d, d) (d on a grid) and its
  saturating part T tanh(u_j / T) - u_j (T on a grid).

Sparse regression is sequentially thresholded least squares (STLSQ, as in SINDy) written on numpy
rather than ``pysindy``: the library is tiny (a few dozen columns), the threshold is on each term's
t-statistic (columns have different units) and is chosen by held-out error, which pysindy's
fixed-threshold optimizer does not do without scikit-learn's model selection on top (a new runtime
dependency for ~40 lines). The threshold (and the grid parameters d, T) minimise the residual
RMS on held-out data: the held-out recordings, or the last 30 % of each fitting recording when none.
Reported per term: coefficient in physical units with its std (HAC-free least squares on the
smoothed residual; correlated residuals make it optimistic), and per joint the held-out RMS before/after.

What it does not do (yet): write the discovered law into the model file as a steppable effect; the
held-out improvement is on the equation (torque) residual, not a re-simulation.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from otbot_hw.diagnose.data import DiagnosisData
from otbot_hw.diagnose.residuals import estimate_motion, torque_residual
from otbot_hw.model.effects import ExtendedModel
from otbot_hw.model.kinematics import forward_kinematics_matrix

JOINTS = ("r", "l", "p")
SIGN_WIDTH = 0.02  # rad/s
HARMONICS = (1, 2, 4)
DEADZONE_GRID = (0.2, 0.5, 1.0)  # N m
SATURATION_GRID = (2.0, 4.0, 8.0)  # N m
THRESHOLDS = (2.0, 3.0, 4.0, 6.0, 10.0, 20.0)  # |t| below which a term is dropped
HOLDOUT_FRACTION = 0.3
EDGE = 0.1  # s dropped at each end (filter edges)


@dataclass
class Term:
    name: str
    joint: str
    unit: str
    meaning: str


def _library(d: DiagnosisData, model: ExtendedModel, nominal: list[str]) -> tuple[np.ndarray, list[Term], np.ndarray,
                                                                                  np.ndarray]:
    """(columns (N, 3, K): term k's generalized force on each joint, terms, residual (N, 3) N m, the
    commands u (N, 3) of the kept samples) -- the grid terms are added by ``_grid_columns``. The first
    columns are the free nominal parameters' (the change of the residual per unit change, by finite
    differences): kept in every fit, so that a discovered term is not what a refit of them would absorb."""
    m = estimate_motion(d, model)
    res = torque_residual(d, model, m)
    n = len(d)
    w = m.qd[:, 3:6]
    phi = d.enc_pos
    u = d.u
    cols, terms = [], []

    def add(col3, name, joint, unit, meaning):
        cols.append(col3)
        terms.append(Term(name, joint, unit, meaning))

    for name in nominal:
        v = model.get(name)
        h = 1e-3 * max(abs(v), 1e-2)
        add((res - torque_residual(d, model.with_values({name: v + h}), m)) / h, name, "nominal", "", "nominal")

    for j, jn in enumerate(JOINTS):
        if d.fixture == "locked" and jn != "p":
            continue

        def on(x, j=j):
            c = np.zeros((n, 3))
            c[:, j] = x
            return c

        if ("b_p" if jn == "p" else "b_w") not in nominal:  # else the refit viscous friction is that column
            add(on(w[:, j]), f"w_{jn}", jn, "N m s/rad", "viscous friction (torque per rate)")
        add(on(np.tanh(w[:, j] / SIGN_WIDTH)), f"sgn(w_{jn})", jn, "N m", "Coulomb-like friction")
        add(on(w[:, j] * np.abs(w[:, j])), f"w_{jn}|w_{jn}|", jn, "N m s^2/rad^2", "quadratic drag")
        for k in HARMONICS:
            add(on(np.sin(k * phi[:, j])), f"sin({k} phi_{jn})", jn, "N m", "position-dependent torque (cogging)")
            add(on(np.cos(k * phi[:, j])), f"cos({k} phi_{jn})", jn, "N m", "position-dependent torque (cogging)")
        add(on(u[:, j]), f"u_{jn}", jn, "1", "torque gain error (-k: delivers (1 + k) u)")
        add(on(u[:, j] * np.abs(u[:, j])), f"u_{jn}|u_{jn}|", jn, "1/(N m)", "torque-dependent gain")
    if d.fixture == "floor":
        J = np.array([forward_kinematics_matrix(q, model.params)[:2] for q in m.q])  # (N, 2, 3)
        v = np.einsum("nij,nj->ni", J, w)  # pivot velocity (N, 2) m/s
        sp = np.linalg.norm(v, axis=1)
        add(np.einsum("nij,ni->nj", J, v), "J^T v", "all", "N s/m", "linear drag force c v at the platform's pivot")
        add(np.einsum("nij,ni->nj", J, sp[:, None] * v), "J^T |v| v", "all", "N s^2/m^2",
            "quadratic drag force c |v| v at the platform's pivot")
    keep = np.zeros(n, bool)
    e = int(round(EDGE / d.dt))
    keep[e:n - e] = True
    return np.stack(cols, axis=2)[keep], terms, res[keep], u[keep]


def _grid_columns(u: np.ndarray, fixture: str, dz: float, sat: float) -> tuple[np.ndarray, list[Term]]:
    """Dead-zone and saturating-delivery columns (N, 3, K) of the commands for one grid point."""
    cols, terms = [], []
    for j, jn in enumerate(JOINTS):
        if fixture == "locked" and jn != "p":
            continue
        c = np.zeros((len(u), 3))
        c[:, j] = np.clip(u[:, j], -dz, dz)
        cols.append(c)
        terms.append(Term(f"clip(u_{jn}, {dz:g})", jn, "1",
                          f"dead zone of {dz:g} N m (coefficient 1: nothing delivered below it)"))
        c = np.zeros((len(u), 3))
        c[:, j] = u[:, j] - sat * np.tanh(u[:, j] / sat)
        cols.append(c)
        terms.append(Term(f"sat{sat:g}(u_{jn})", jn, "1",
                          f"saturating delivery T tanh(u / T), T = {sat:g} N m (coefficient 1: fully)"))
    return np.stack(cols, axis=2), terms


def _stlsq(A: np.ndarray, y: np.ndarray, threshold: float, protected: int = 0) -> tuple[np.ndarray, np.ndarray,
                                                                                       np.ndarray]:
    """Sequentially thresholded least squares on t-statistics: (coef, std, active mask); the first
    ``protected`` columns are never dropped."""
    k = A.shape[1]
    active = np.ones(k, bool)
    coef = np.zeros(k)
    std = np.full(k, np.nan)
    for _ in range(k):
        if not active.any():
            break
        Aa = A[:, active]
        c, *_ = np.linalg.lstsq(Aa, y, rcond=None)
        r = y - Aa @ c
        dof = max(len(y) - active.sum(), 1)
        cov = np.linalg.pinv(Aa.T @ Aa) * float(r @ r) / dof
        s = np.sqrt(np.maximum(np.diag(cov), 1e-300))
        t = np.abs(c) / s
        coef[:] = 0.0
        std[:] = np.nan
        coef[active], std[active] = c, s
        drop = t < threshold
        drop[: int(np.sum(active[:protected]))] = False
        if not drop.any():
            break
        idx = np.nonzero(active)[0]
        active[idx[drop]] = False
    return coef, std, active


def discover(recordings: list[DiagnosisData], holdout: list[DiagnosisData], model: ExtendedModel,
             nominal: list[str] | None = None) -> dict:
    """``nominal``: the free nominal parameters (default ``select.free_nominal``), refitted beside the terms.
    Discovered terms {name, joint, value, std, unit, meaning}, the held-out RMS per joint before/after,
    the chosen threshold and grid parameters, and what was held out."""
    from otbot_hw.diagnose.select import free_nominal

    nominal = list(free_nominal(recordings) if nominal is None else nominal)
    best = None
    base_fit = [_library(d, model, nominal) for d in recordings]
    base_hold = [_library(d, model, nominal) for d in holdout]
    for dz in DEADZONE_GRID:
        for sat in SATURATION_GRID:
            def grid(L, d):
                G, gt = _grid_columns(L[3], d.fixture, dz, sat)
                return np.concatenate([L[0], G], axis=2), L[1] + gt, L[2]

            libs = [grid(L, d) for L, d in zip(base_fit, recordings)]
            hold = [grid(L, d) for L, d in zip(base_hold, holdout)]
            terms = libs[0][1]
            if hold:
                fit = [(L[0], L[2]) for L in libs]
                test = [(L[0], L[2]) for L in hold]
            else:
                fit, test = [], []
                for C, _, R in libs:
                    cut = int((1 - HOLDOUT_FRACTION) * len(R))
                    fit.append((C[:cut], R[:cut]))
                    test.append((C[cut:], R[cut:]))
            A = np.concatenate([C.reshape(-1, C.shape[2]) for C, _ in fit])
            y = np.concatenate([R.reshape(-1) for _, R in fit])
            At = np.concatenate([C.reshape(-1, C.shape[2]) for C, _ in test])
            yt = np.concatenate([R.reshape(-1) for _, R in test])
            scale = np.maximum(np.sqrt(np.mean(A ** 2, axis=0)), 1e-12)
            for th in THRESHOLDS:
                c, s, act = _stlsq(A / scale, y, th, protected=len(nominal))
                err = float(np.sqrt(np.mean((yt - (At / scale) @ c) ** 2)))
                key = (round(err, 6), int(act.sum()))
                if best is None or key < best[0]:
                    best = (key, dz, sat, th, c / scale, s / scale, act, terms, At, yt, test)
    (_, dz, sat, th, c, s, act, terms, At, yt, test) = best
    per_joint = {}
    pred = At @ c
    # held-out RMS per joint before/after (rows of the flattened (N, 3) blocks: joint = row index mod 3)
    rows = np.arange(len(yt)) % 3
    for j, jn in enumerate(JOINTS):
        sel = rows == j
        if not np.any(yt[sel] != 0):
            continue
        per_joint[jn] = {"before_rms": float(np.sqrt(np.mean(yt[sel] ** 2))),
                         "after_rms": float(np.sqrt(np.mean((yt[sel] - pred[sel]) ** 2))), "unit": "N m"}
    found = [{"term": terms[k].name, "joint": terms[k].joint, "value": float(c[k]), "std": float(s[k]),
              "unit": terms[k].unit, "meaning": terms[k].meaning} for k in np.nonzero(act)[0] if k >= len(nominal)]
    shift = {terms[k].name: float(c[k]) for k in range(len(nominal))}
    found.sort(key=lambda f: -abs(f["value"] / f["std"]) if f["std"] > 0 else 0.0)
    return {"terms": found, "nominal_shift": shift, "heldout": per_joint, "threshold_t": th, "deadzone_grid_nm": dz,
            "saturation_grid_nm": sat, "heldout_source": "held-out recordings" if holdout else
            f"last {100 * HOLDOUT_FRACTION:.0f} % of each fitting recording",
            "method": "STLSQ on t-statistics (numpy), threshold and grid by held-out RMS of the torque residual"}
