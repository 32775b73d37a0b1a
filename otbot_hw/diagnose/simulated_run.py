"""The diagnosis's simulation of a whole recorded run: the initial state estimated from the encoders (angles
from the first samples, joint rates fitted to the head of the record), the RK4 step by the stiffest active
term, the simulated channels (kept in a small cache of recent simulations) and the simulation residual
(measured minus simulated, per channel). The equation residuals and the motion estimate are
``otbot_hw.diagnose.residuals``.
"""
from __future__ import annotations

import functools
import hashlib
import threading
from collections import OrderedDict

import numpy as np

from otbot_hw.diagnose.data import CHANNELS, DiagnosisData
from otbot_hw.diagnose.residuals import ACTUATOR_ENTRIES, estimate_motion, initial_tau
from otbot_hw.model import effect_physics as phys
from otbot_hw.model import effects as fx
from otbot_hw.model import sensor_model
from otbot_hw.model.effects import GRAVITY, ExtendedModel
from otbot_hw.simulation.simulator import default_substeps, simulate_extended

X0_CACHE_SIZE = 4096  # initial states kept per recording (one per combination of the entries x0 depends on)
HEAD_TIME = 0.25  # s: the start of the record whose encoder rates fix the initial joint rates (at least 2 windows)
REST_QUANTILE = 0.999  # chi-square quantile under which the fitted initial rates are taken as a start at rest


def encoder_state(data: DiagnosisData, model: ExtendedModel) -> np.ndarray:
    """x0 (12,) in rolling-angle coordinates read from the first encoder samples alone (alpha(0) = 0):
    angles, and rates from ``start_rates`` (0 within 3 sigma of rest, else a 5-sample edge fit).

    Computed on the recording's first ``2 window`` samples (``DiagnosisData.head``: the edge
    filters see only the first window, so x0 is the same as from the whole record) and kept in
    the recording's memo per model entries x0 depends on: geometry, encoder scale and radius
    asymmetry; with wheel slip on the floor also the slip law and what sets the slipping torque
    (viscous friction and its asymmetry, actuator gains, saturation, lag).
    """
    p, eff = model.params, model.eff
    deps = [fx.E_R, fx.E_L, fx.DR_R, fx.DR_L, fx.K_SLIP, fx.T_TRAC]
    slip = (eff[fx.K_SLIP] != 0.0 or eff[fx.T_TRAC] != 0.0) and data.fixture == "floor"
    if slip:  # estimate_motion's slip correction: the delivered torque through the slip law
        deps += [fx.DB_W] + ACTUATOR_ENTRIES
    key = (p.l1, p.l2, p.r, p.b_w if slip else None, tuple(eff[deps]))
    cache = data.memo("encoder_states", dict)
    x0 = cache.get(key)  # one lookup: another prediction thread may clear the cache meanwhile
    if x0 is None:
        if len(cache) > X0_CACHE_SIZE:
            cache.clear()
        head = data.memo("head", lambda: data.head(2 * data.window))
        m = estimate_motion(head, model, smooth_rates=False, accelerations=False)
        x0 = cache[key] = np.concatenate([m.q[0], m.qd[0]])
    return x0.copy()


def _with_rates(x0: np.ndarray, w: np.ndarray, fixture: str, p) -> np.ndarray:
    from otbot_hw.identification.initial_state import state_with_rates

    return state_with_rates(x0, w, fixture, p.l1, p.l2, p.r)


def initial_state(data: DiagnosisData, model: ExtendedModel, rates_from: ExtendedModel | None = None) -> np.ndarray:
    """x0 (12,) in rolling-angle coordinates: angles from the first encoder samples, joint rates fitted
    to the first ``HEAD_TIME`` s of encoder rates through the model.

    Why: one noisy sample cannot set the initial rate. The platform's rate decays with I_p / b_p ~ 9 s,
    so an initial pivot-rate error of one encoder sigma (0.01-0.03 rad/s) is carried through the whole
    simulation and reads as a misfit of several noise levels on w_p, a_x, a_y, g_z -- a clean record
    judged "model inadequate" (issue 20: the reading exceeded 3 sigma at t_0, so it was taken as motion).
    Here the rates w0 (rad/s per joint) are the weighted least-squares solution over the head of the
    record (one Gauss-Newton step from ``encoder_state``: the response to w0 is linear to first order,
    its sensitivity by finite differences of the model's simulation), std about sigma / sqrt(n_head).
    When the fitted rates are consistent with rest (chi-square below its ``REST_QUANTILE`` quantile)
    the start is at rest, exactly (recordings start from standstill; an estimate of zero carries
    noise into the long simulation). Kept in the recording's memo per model (parameters and effects).

    ``rates_from``: a model next to ``model`` (a finite-difference Jacobian's centre, ``model`` one of its
    columns): the same fit, with the rate sensitivity of that model instead of the 3 head simulations that
    measure it (it moves by the step's relative size, second order in the fitted rates): 1 head simulation per
    column instead of 4 (the head simulations were a fifth of a slow diagnosis's CPU).
    """
    if rates_from is not None:
        sens = _start(data, rates_from)[1]
        if sens is not None:
            return _fitted_start(data, model, sens)[0].copy()
    return _start(data, model)[0].copy()


def _start(data: DiagnosisData, model: ExtendedModel) -> tuple:
    """``_fitted_start`` of ``model``, memoized."""
    key = (model.params.as_array().tobytes(), np.asarray(model.eff, dtype=float).tobytes())
    cache = data.memo("initial_states", dict)
    out = cache.get(key)
    if out is None:
        if len(cache) > X0_CACHE_SIZE:
            cache.clear()
        out = cache[key] = _fitted_start(data, model)
    return out


@functools.lru_cache(maxsize=8)
def _rest_bound(k: int) -> float:
    """The chi-square ``REST_QUANTILE`` quantile with k degrees of freedom (scipy's ppf costs 50 us a call,
    made once per initial-state fit: once per Jacobian column)."""
    from scipy.stats import chi2

    return float(chi2.ppf(REST_QUANTILE, k))


def _fitted_start(data: DiagnosisData, model: ExtendedModel, sens: np.ndarray | None = None) -> tuple:
    """(x0, its rate sensitivity S over the head (n, joints) in noise units or None when x0 is
    ``encoder_state``'s: no rate channel, or the fit failed). ``sens``: S given (``initial_state``'s
    ``rates_from``), not simulated."""
    x_enc = encoder_state(data, model)
    n = min(len(data), max(2 * data.window, int(round(HEAD_TIME / data.dt)) + 1))
    head = data.memo("x0_head", lambda: data.head(n))
    chans = [c for c in ("w_r", "w_l", "w_p") if head.measured(c) is not None]
    joints = [2] if data.fixture == "locked" else [0, 1, 2]
    if not chans:
        return x_enc, None
    p = model.params
    x_rest = _with_rates(x_enc, np.zeros(3), data.fixture, p)
    try:
        base = simulate_outputs(head, model, x_rest, cached=False)
        if sens is None:
            cols = []
            h = 1e-3  # rad/s
            for j in joints:
                w = np.zeros(3)
                w[j] = h
                sj = simulate_outputs(head, model, _with_rates(x_enc, w, data.fixture, p), cached=False)
                cols.append(np.concatenate([(sj[c] - base[c]) / h / head.noise_sigma(c) for c in chans]))
    except (ValueError, ZeroDivisionError, FloatingPointError, np.linalg.LinAlgError):
        return x_enc, None
    S = np.column_stack(cols) if sens is None else sens
    r = np.concatenate([(head.measured(c) - base[c]) / head.noise_sigma(c) for c in chans])
    if not (np.all(np.isfinite(S)) and np.all(np.isfinite(r))):
        return x_enc, None
    A = S.T @ S
    try:
        dw = np.linalg.solve(A, S.T @ r)
    except np.linalg.LinAlgError:
        return x_enc, None
    if float(dw @ A @ dw) < _rest_bound(len(joints)):
        return x_rest, S  # consistent with a start at rest
    w = np.zeros(3)
    w[joints] = dw
    return _with_rates(x_enc, w, data.fixture, p), S


FREE_STEP = 1e-2  # s: RK4 step on the floor without a friction sign (caster drag included)
OFF_FLOOR_STEP = 5e-3  # s: on the stand or with the wheels locked, no friction sign


SIGN_STABILITY = 2.1  # h * rate of the stiffest smoothed friction sign, as the simulator's default step keeps it
#: smallest effective inertia (kg m^2) a friction sign acts on (``default_substeps``): wheel on the floor, on the
#: stand (the wheel alone), pivot
I_EFF_MIN = {"floor": 0.048, "stand": 0.0104, "pivot": 0.31}


def sign_rate(eff: np.ndarray, fixture: str, params=None) -> float:
    """Rate (1/s) of the stiffest smoothed friction sign: friction level / (sign width x effective inertia), the
    width proportional to the level above its minimum (``effect_physics.sign_width``): at most 1 / (0.025
    I_eff) at a wheel -- the simulator's default step is set for that --, but a small friction level (a
    candidate's start, c_w = 0.002 N m) is far from stiff."""
    rr = 0.0
    if eff[fx.C_RR] and params is not None:
        rr = eff[fx.C_RR] * (params.m_c + params.m_p) * GRAVITY * 0.5 * params.r
    elif eff[fx.C_RR]:
        return np.inf
    rate = 0.0
    if fixture != "locked":
        for c in (eff[fx.C_R], eff[fx.C_L]):
            level = abs(c) + abs(eff[fx.S_W]) + abs(rr)
            if level > 0:
                width = max(fx.WIDTH_MIN_WHEEL, fx.WIDTH_PER_NM_WHEEL * level)
                rate = max(rate, level / (width * I_EFF_MIN["stand" if fixture == "stand" else "floor"]))
    if eff[fx.C_P]:
        level = abs(eff[fx.C_P])
        rate = max(rate, level / (max(fx.WIDTH_MIN_PIVOT, fx.WIDTH_PER_NM_PIVOT * level) * I_EFF_MIN["pivot"]))
    return rate


def diagnosis_substeps(dt: float, fixture: str, eff: np.ndarray, params=None) -> int:
    """RK4 steps per sample for the diagnosis's simulations, by the stiffest active term. Without a friction sign
    ``FREE_STEP`` on the floor and ``OFF_FLOOR_STEP`` off it. Measured against 64 steps per sample (10 s, 100 Hz
    runs): slope, drag, slip, lag and sensor effects at 10 ms within 7e-4 rad/s and m/s^2; caster drag of 6 N
    (its smoothed direction, the stiffest of these) at 10 ms within 0.3 sigma at its worst sample, 5 ms within
    0.12 sigma (issue 20 item 6: the caster's 5 ms step made it a fifth of the slowest diagnoses; the fitted
    f_cst moved by 0.1 % with 10 ms). Off the floor the default's 0.5 ms step on the stand is there for the
    friction signs of a free wheel (I_a / b_w ~ 58 ms is no stiffer than the floor's terms): on the 30 s stand
    multisine of the calibration study (#380) 5 ms steps are within 5e-5 sigma of 64 steps per sample without
    effects, 3e-3 sigma with a 5 ms current lag -- a tenth of the default's work.

    With a friction sign (Coulomb, Stribeck, rolling resistance) the step keeps h x ``sign_rate`` within
    ``SIGN_STABILITY``, never below the simulator's default (``default_substeps``, which does that for the
    largest friction levels): a friction level of a few mN m -- the start of a friction candidate's nested fit,
    or what it fits on a robot without that friction -- runs at the free step, not at 2.5 ms (a traction-limit
    diagnosis spent 40 % of its CPU on such fits). ``params``: the model's parameters (rolling resistance's
    torque; without them a rolling resistance takes the default step)."""
    free = FREE_STEP if fixture == "floor" else OFF_FLOOR_STEP
    rate = sign_rate(eff, fixture, params)
    if not np.isfinite(rate):
        return default_substeps(dt, fixture)
    if rate > 0:
        n_default = default_substeps(dt, fixture)
        h = min(free, SIGN_STABILITY / rate)
        return min(n_default, max(1, int(np.ceil(dt / h - 1e-9))))
    return max(1, int(np.ceil(dt / free - 1e-9)))


def simulate_outputs(data: DiagnosisData, model: ExtendedModel, x0: np.ndarray | None = None,
                     substeps: int | None = None, cached: bool = True) -> dict[str, np.ndarray]:
    """Simulated CHANNELS (each (N,)) for the recording's commands, from the estimated x0
    (``initial_state``; ``substeps`` RK4 steps per sample, default ``diagnosis_substeps``).
    ``cached=False``: neither looked up nor kept in the cache of recent simulations (short ones
    that would push out the whole-record simulations the evidence and adequacy steps reuse).

    The simulator's ``simulate_extended`` then the sensor model's ``sensor_outputs`` (the accelerations
    and slip rates at the samples from the integrator's first stage)."""
    x0 = initial_state(data, model) if x0 is None else x0
    sub = substeps or diagnosis_substeps(data.dt, data.fixture, model.eff, model.params)
    if not cached:
        return _simulate_outputs(data, model, x0, sub)
    key = (data.memo("command_digest", lambda: _digest(data)), model.params.as_array().tobytes(),
           np.asarray(model.eff, dtype=float).tobytes(),
           np.asarray(x0, dtype=float).tobytes(), sub)
    with _SIM_LOCK:
        if key in _SIM_CACHE:
            _SIM_CACHE.move_to_end(key)
            return dict(_SIM_CACHE[key])
    out = _simulate_outputs(data, model, x0, sub)
    for v in out.values():
        v.flags.writeable = False  # shared by the cache
    with _SIM_LOCK:
        _SIM_CACHE[key] = out
        while len(_SIM_CACHE) > SIM_CACHE_SIZE:
            _SIM_CACHE.popitem(last=False)
    return dict(out)


def _digest(data: DiagnosisData) -> tuple:
    """What a simulation takes from a recording besides x0: its commands, sample period and fixture."""
    return hashlib.blake2b(np.ascontiguousarray(data.u).tobytes(), digest_size=16).digest(), len(data), data.dt, \
        data.fixture


SIM_CACHE_SIZE = 32  # recent simulations kept: a fitted model is simulated again by the evidence and adequacy steps
_SIM_CACHE: OrderedDict = OrderedDict()
_SIM_LOCK = threading.Lock()


def _simulate_outputs(data: DiagnosisData, model: ExtendedModel, x0: np.ndarray, sub: int) -> dict[str, np.ndarray]:
    tau_start = initial_tau(data)
    tau0 = phys.actuated_torque(tau_start, np.asarray(model.eff, dtype=float)) if np.any(tau_start) else None
    traj = simulate_extended(model.params, model.eff, data.u[:-1], data.dt, x0=x0, fixture=data.fixture, tau0=tau0,
                             substeps=sub)
    s = sensor_model.sensor_outputs(traj, model.params, np.asarray(model.eff, dtype=float))
    return {"w_r": s["joint_vel"][:, 0], "w_l": s["joint_vel"][:, 1], "w_p": s["joint_vel"][:, 2],
            "a_x": s["imu_accel"][:, 0], "a_y": s["imu_accel"][:, 1], "g_z": s["imu_gyro"][:, 2]}


def simulation_residual(data: DiagnosisData, model: ExtendedModel) -> dict[str, np.ndarray]:
    """Measured minus simulated, per usable channel."""
    sim = simulate_outputs(data, model)
    return {ch: data.measured(ch) - sim[ch] for ch in CHANNELS if data.measured(ch) is not None}
