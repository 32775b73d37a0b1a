"""Zero-order-hold simulation of Otbot (the physics is in ``otbot_hw.model``, the compiled integrators
in ``otbot_hw.simulation.integrators``).

Torques u_k (N m) and pivot forces f_k (N, ground frame) are held constant on
[t_k, t_k + dt). The paper's model is the extended model with every effect at zero: one
trajectory type (``Trajectory``), one stepper (``Stepper``, for closed loops), one sensor model
(``otbot_hw.model.sensor_model``). Two integrators for the paper's model:

* ``method="fast"`` (default): compiled classical RK4 with ``substeps`` steps per
  interval (default: steps of at most 2.5 ms), the path every tool uses;
* ``method="reference"``: scipy's adaptive Dormand-Prince (``RK45``, the paper's
  ode45) on the numpy model, restarted on every interval, rtol = atol = 1e-12.

The fast path agrees with the reference to better than 1e-8 in every state on the
paper's chassis experiment (tested in ``tests/test_simulator.py``, measured in
``benchmarks/model.py``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np
from scipy.integrate import solve_ivp

from otbot_hw.interrupts import deferred_sigint
from otbot_hw.model.dynamics import forward_dynamics
from otbot_hw.model.effect_catalog import EFFECT_INDEX, N_EFFECT, effect_vector
from otbot_hw.model.effect_physics import actuated_torque
from otbot_hw.model.fixtures import fixture_code, held_chassis_accelerations
from otbot_hw.model.sensor_model import WORK
from otbot_hw.params import OtbotParams
from otbot_hw.simulation.integrators import ext_rk4_into, ext_rk4_zoh_samples, rk4_zoh, rk4_zoh_into

T_I_INDEX = EFFECT_INDEX["T_i"]

MAX_STEP = 2.5e-3  # s, largest RK4 step of the fast path

#: ZOH intervals per call of the compiled integrator in ``simulate`` (fast path): between calls Python
#: runs again, so Ctrl-C is honoured and progress can be reported (about 0.3 s per call on the floor at
#: 100 Hz). The intervals are independent given the state, so the chunks give the one-call result bit
#: for bit (``tests/test_simulator.py``).
CHUNK = 100_000

#: Layout of ``Stepper._buf`` (float64): one interval's X (2, 12), TAU (2, 3), S (2, 2); the sensor
#: readings (5, 3) and the sensor model's scratch (``WORK``) of ``StepperSensors``; the interval's
#: command (1, 3) and force (1, 2); then the parameters (``OtbotParams.as_array``) to the end
BUF_X = 0
BUF_TAU = BUF_X + 24
BUF_S = BUF_TAU + 6
BUF_OUT = BUF_S + 4
BUF_WORK = BUF_OUT + 15
BUF_U = BUF_WORK + WORK
BUF_F = BUF_U + 3
BUF_PRM = BUF_F + 2


@dataclass(frozen=True)
class PivotForce:
    """A horizontal force (f_x, f_y) N, ground frame, applied at the pivot for t in [start, start+duration)."""

    start: float
    duration: float
    fx: float
    fy: float


@dataclass
class ForceSchedule:
    """External forces on the pivot; sampled at interval starts and held (ZOH) like the torques."""

    forces: Sequence[PivotForce] = field(default_factory=tuple)

    def at(self, t: float) -> np.ndarray:
        """Total force (2,) N acting at time t (s)."""
        out = np.zeros(2)
        for f in self.forces:
            if f.start <= t < f.start + f.duration:
                out += (f.fx, f.fy)
        return out

    def sample(self, times: np.ndarray) -> np.ndarray:
        """Forces (N, 2) at the given interval start times (with a half-sample tolerance)."""
        return np.array([self.at(t + 1e-9) for t in times]).reshape(len(times), 2)


@dataclass
class Trajectory:
    """A simulated run: t (N+1,) s, x (N+1, 12) states (q, q_dot), u (N+1, 3) commanded torques N m,
    f (N+1, 2) pivot forces N; for the extended model x holds the wheels' rolling angles.

    u[k] and f[k] are held on [t_k, t_k+1); the last row repeats the last command. ``tau`` (N+1, 3) the
    torque the drives deliver just after each sample (N m; u for the paper's model), ``slip`` (N+1, 2)
    the wheel slip angles (rad), ``qdd`` (N+1, 6) and ``slip_rate`` (N+1, 2) the accelerations and slip
    rates just after each sample when the integrator gave them (None: evaluated where needed).
    """

    t: np.ndarray
    x: np.ndarray
    u: np.ndarray
    f: np.ndarray
    dt: float
    fixture: str = "floor"
    tau: np.ndarray | None = None
    slip: np.ndarray | None = None
    qdd: np.ndarray | None = None
    slip_rate: np.ndarray | None = None

    def __post_init__(self):
        if self.tau is None:
            self.tau = self.u
        if self.slip is None:
            self.slip = np.zeros((len(self.x), 2))

    @property
    def q(self) -> np.ndarray:
        return self.x[:, :6]

    @property
    def qd(self) -> np.ndarray:
        return self.x[:, 6:]


def default_substeps(dt: float, fixture: str = "floor") -> int:
    """RK4 steps per ZOH interval so that no step exceeds ``MAX_STEP``.

    On the stand a free wheel has the short time constant I_a / b_w (about 58 ms
    nominally), so the step there is five times smaller. The extended model's stiffest
    terms, the smoothed Coulomb signs (rate c / width / I_eff, ``effect_physics.sign_width``), stay
    inside RK4's stability limit (h * rate < 2.78) with these steps for c up to its 2 N m
    bound: h * rate = 2.1 for a wheel on the floor (I_eff >= 0.048 kg m^2), 1.9 on the stand
    (I_a = 0.0104 kg m^2), 1.6 at the pivot (>= 0.31 kg m^2).
    """
    h = MAX_STEP / 5 if fixture == "stand" else MAX_STEP
    return max(1, math.ceil(dt / h - 1e-9))


def check_inputs(U: np.ndarray, dt: float, F: np.ndarray | None, x0: np.ndarray | None):
    """Validate and normalize torques (N, 3), sample period, forces (N, 2) and initial state (12,)."""
    U = np.asarray(U, dtype=float)
    if U.ndim != 2 or U.shape[1] != 3:
        raise ValueError(f"torques must have shape (N, 3), got {U.shape}")
    if not (dt > 0 and math.isfinite(dt)):
        raise ValueError(f"sample period must be > 0 s, got {dt}")
    if not np.all(np.isfinite(U)):
        raise ValueError("torques contain NaN or inf")
    F = np.zeros((len(U), 2)) if F is None else np.asarray(F, dtype=float).reshape(len(U), 2)
    if not np.all(np.isfinite(F)):
        raise ValueError("pivot forces contain NaN or inf")
    x0 = np.zeros(12) if x0 is None else np.asarray(x0, dtype=float)
    if x0.shape != (12,) or not np.all(np.isfinite(x0)):
        raise ValueError(f"initial state must be 12 finite numbers (q, q_dot), got shape {x0.shape}")
    return U, F, x0


def simulate(params: OtbotParams, torques: np.ndarray, dt: float, x0: np.ndarray | None = None,
             forces: ForceSchedule | np.ndarray | None = None, fixture: str = "floor",
             method: str = "fast", substeps: int | None = None, chunk: int = CHUNK,
             progress: Callable[[int, int], None] | None = None) -> Trajectory:
    """Simulate N = len(torques) ZOH intervals of ``dt`` seconds from ``x0`` (default rest at 0).

    ``torques`` (N, 3) N m; ``forces`` a ``ForceSchedule`` or an (N, 2) array of held
    pivot forces (N, ground frame); ``fixture`` one of floor, stand, locked. The fast path integrates
    ``chunk`` intervals per compiled call and calls ``progress(done, N)`` after each.
    """
    n = len(torques)
    t = np.arange(n + 1) * dt
    F = forces.sample(t[:-1]) if isinstance(forces, ForceSchedule) else forces
    U, F, x0 = check_inputs(torques, dt, F, x0)
    code = fixture_code(fixture)
    if method == "fast":
        X = _chunked_rk4(x0, U, F, dt, substeps or default_substeps(dt, fixture), params.as_array(), code, chunk,
                         progress)
    elif method == "reference":
        X = _reference(params, U, F, dt, x0, fixture)
    else:
        raise ValueError(f"unknown method '{method}' (fast, reference)")
    Uf, Ff = _held(U, F)
    return Trajectory(t=t, x=X, u=Uf, f=Ff, dt=dt, fixture=fixture)


def _chunked_rk4(x0, U, F, dt, substeps, prm, code, chunk, progress) -> np.ndarray:
    """``rk4_zoh`` in calls of at most ``chunk`` intervals, each from the last one's final state."""
    n = len(U)
    if n <= chunk and progress is None:
        return rk4_zoh(x0, U, F, dt, substeps, prm, code)
    X = np.empty((n + 1, 12))
    X[0] = x0
    with deferred_sigint() as pending:  # Ctrl-C: KeyboardInterrupt after the chunk, not inside numba
        for k0 in range(0, n, max(1, int(chunk))):
            k1 = min(n, k0 + max(1, int(chunk)))
            rk4_zoh_into(X[k0].copy(), U[k0:k1], F[k0:k1], dt, substeps, prm, code, X[k0:k1 + 1])
            pending.check()
            if progress is not None:
                progress(k1, n)
    return X


def _reference(params: OtbotParams, U, F, dt, x0, fixture: str) -> np.ndarray:
    """Adaptive Dormand-Prince (RK45) restarted on every ZOH interval, numpy model."""
    X = np.empty((len(U) + 1, 12))
    X[0] = x0
    x = x0
    for k in range(len(U)):
        u, f = U[k], F[k]
        if fixture == "floor":
            def rhs(_t, s, u=u, f=f):
                return np.concatenate([s[6:], forward_dynamics(s[:6], s[6:], u, params, f)])
        else:
            def rhs(_t, s, u=u):
                return np.concatenate([s[6:], held_chassis_accelerations(s[6:], u, params, fixture)])
        sol = solve_ivp(rhs, (k * dt, (k + 1) * dt), x, method="RK45", rtol=1e-12, atol=1e-12)
        if not sol.success:
            raise RuntimeError(f"reference integration failed on interval {k}: {sol.message}")
        x = sol.y[:, -1]
        X[k + 1] = x
    return X


def _held(U: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Commands and forces per sample (N+1 rows): the last interval's repeated at t_N."""
    if len(U):
        return np.vstack([U, U[-1:]]), np.vstack([F, F[-1:]])
    return np.zeros((1, 3)), np.zeros((1, 2))


def check_effects(eff) -> np.ndarray:
    """The effect vector as N_EFFECT finite floats (ValueError otherwise)."""
    eff = np.asarray(eff, dtype=float)
    if eff.shape != (N_EFFECT,) or not np.all(np.isfinite(eff)):
        raise ValueError(f"effect vector must be {N_EFFECT} finite numbers")
    return eff


def simulate_extended(params: OtbotParams, eff: np.ndarray, torques: np.ndarray, dt: float,
                      x0: np.ndarray | None = None, fixture: str = "floor", tau0: np.ndarray | None = None,
                      forces: np.ndarray | None = None, substeps: int | None = None, chunk: int = CHUNK,
                      progress: Callable[[int, int], None] | None = None) -> Trajectory:
    """Simulate the extended model under commanded ``torques`` (N, 3) N m held for ``dt`` s.

    ``tau0``: delivered torque before t_0 (default 0: the drives start from rest), only
    matters with a current-loop lag. ``x0`` (12,) in rolling-angle coordinates (default rest).
    The accelerations and slip rates at the samples come from the integrator's first stage
    (``ext_rk4_zoh_samples``: one model evaluation per sample fewer than evaluating them again).
    Without a current-loop lag the intervals run ``chunk`` per compiled call, ``progress(done, N)`` after
    each, bit for bit the one call's numbers (with a lag, whose state is not an output, in one call).
    """
    U, F, x0 = check_inputs(torques, dt, forces, x0)
    eff = check_effects(eff)
    sub = substeps or default_substeps(dt, fixture)
    t0 = np.zeros(3) if tau0 is None else np.asarray(tau0, dtype=float)
    n, prm, code = len(U), params.as_array(), fixture_code(fixture)
    if (n <= chunk and progress is None) or eff[T_I_INDEX] > 0:
        X, TAU, S, QDD, SD = ext_rk4_zoh_samples(x0, t0, U, F, dt, sub, prm, eff, code)
    else:
        X, TAU, S = np.empty((n + 1, 12)), np.empty((n + 1, 3)), np.zeros((n + 1, 2))
        QDD, SD = np.empty((n + 1, 6)), np.empty((n + 1, 2))
        X[0] = x0
        step = max(1, int(chunk))
        with deferred_sigint() as pending:  # Ctrl-C: KeyboardInterrupt after the chunk, not inside numba
            for k0 in range(0, n, step):  # each chunk rewrites its first sample's row, as one call has it
                k1 = min(n, k0 + step)
                rows = slice(k0, k1 + 1)
                ext_rk4_into(X[k0].copy(), t0, U[k0:k1], F[k0:k1], dt, sub, prm, eff, code, X[rows], TAU[rows],
                             S[rows], QDD[rows], SD[rows])
                pending.check()
                if progress is not None:
                    progress(k1, n)
    Uf, Ff = _held(U, F)
    return Trajectory(t=np.arange(len(X)) * dt, x=X, u=Uf, f=Ff, dt=dt, fixture=fixture, tau=TAU, slip=S, qdd=QDD,
                      slip_rate=SD)


class Stepper:
    """Step-by-step simulation for closed loops: ``step(u, f)`` advances one ZOH interval.

    ``plant``: ``OtbotParams`` (the paper's model) or an ``otbot_hw.model.effects.ExtendedModel`` (the
    paper's dynamics plus missing-physics effects, e.g. a diagnosed model as a closed loop's plant): one
    stepper for both, the paper's model being the extended one with every effect at zero.
    ``step(u, f)`` takes the *commanded* torques; the drives' gain, saturation and current lag act on
    them. Holds the state x (12,) (rolling angles for the wheels, equal to the wheel angles without a
    radius asymmetry), the time t (s), ``tau`` the torque the drives deliver at the end of the last step
    (N m), ``slip`` (2,) rad the wheel slip accumulated since the start (what the wheel encoders read on
    top of the rolling angles, ``otbot_hw.model.sensor_model``), and the last step's command and force
    (``u_last``, ``f_last``; None before the first step). ``eff`` may be changed in place between steps
    (``sim.effect_schedule``).
    """

    def __init__(self, plant, dt: float, x0: np.ndarray | None = None, fixture: str = "floor",
                 substeps: int | None = None):
        _, _, x0 = check_inputs(np.zeros((1, 3)), dt, None, x0)
        if isinstance(plant, OtbotParams):
            params, eff = plant, effect_vector()
        else:
            params, eff = plant.params, check_effects(plant.eff)  # shared: sim.effect_schedule writes into it
        self.params = params
        self.eff = eff
        self.dt = dt
        self.x = x0.copy()
        self.t = 0.0
        self.fixture = fixture
        self.tau = np.zeros(3)
        self.slip = np.zeros(2)
        self.u_last: np.ndarray | None = None
        self.f_last: np.ndarray | None = None
        self._code = fixture_code(fixture)
        self._substeps = substeps or default_substeps(dt, fixture)
        # one interval's outputs, the sensor model's scratch and the parameters: one buffer allocated
        # once (``BUF_*``), so that the fused compiled call of ``StepperSensors.sample_and_step`` takes
        # one argument for them (numba's call costs about 70 ns per argument); these are views of it
        prm = params.as_array()
        self._buf = np.zeros(BUF_PRM + len(prm))
        self._buf[BUF_PRM:] = prm
        b = self._buf
        self._X, self._TAU, self._S = (b[BUF_X:BUF_TAU].reshape(2, 12), b[BUF_TAU:BUF_S].reshape(2, 3),
                                       b[BUF_S:BUF_OUT].reshape(2, 2))
        self._x1, self._tau1, self._s1 = self._X[1], self._TAU[1], self._S[1]
        self._prm_view = b[BUF_PRM:]
        self._none6, self._none2 = np.empty((0, 6)), np.empty((0, 2))
        self._zero_f = np.zeros((1, 2))  # the force when none is given (never written)

    @property
    def _prm(self) -> np.ndarray:
        """The parameters as the compiled model takes them (``OtbotParams.as_array``), in ``_buf``."""
        return self._prm_view

    @_prm.setter
    def _prm(self, value) -> None:  # sim.load_schedule assigns it
        self._prm_view[:] = value

    def set_params(self, params: OtbotParams) -> None:
        """Change the plant parameters (e.g. a load placed on the platform)."""
        self.params = params
        self._prm = params.as_array()  # copied into _buf

    def delivered_torque(self, u: np.ndarray) -> np.ndarray:
        """Torque (3,) N m the drives deliver at the current sample with command u acting: with a
        current-loop lag the torque reached at the end of the last interval, else the actuated u."""
        if self.eff[T_I_INDEX] > 0:
            return self.tau
        return actuated_torque(np.asarray(u, dtype=float), self.eff)

    def step(self, u: np.ndarray, f: np.ndarray | None = None) -> np.ndarray:
        """Apply torques u (3,) N m and pivot force f (2,) N for one interval; return the new state."""
        U, F = self.interval_inputs(u, f)
        ext_rk4_into(self.x, self.tau, U, F, self.dt, self._substeps, self._prm, self.eff, self._code, self._X,
                     self._TAU, self._S, self._none6, self._none2)
        return self.advance(U[0], F[0])

    def interval_inputs(self, u: np.ndarray, f: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """One interval's torques U (1, 3) N m and force F (1, 2) N, checked (``step``)."""
        U = np.asarray(u, dtype=float).reshape(1, 3)
        if not all(map(math.isfinite, U[0].tolist())):
            raise ValueError(f"torques must be finite, got {u}")
        return U, (self._zero_f if f is None else np.asarray(f, dtype=float).reshape(1, 2))

    def advance(self, u: np.ndarray, f: np.ndarray, slipped: bool | None = None) -> np.ndarray:
        """Take the interval the integrator wrote into ``_X``, ``_TAU``, ``_S`` under u (3,), f (2,) as
        the new state (``step``; ``otbot_hw.simulation.sensing.StepperSensors.sample_and_step`` integrates
        in the same compiled call as its readings, which says whether a wheel ``slipped``). x is
        replaced, never changed in place."""
        self.x, self.tau = self._x1.copy(), self._tau1.copy()
        if slipped is None:
            ds0, ds1 = self._s1.tolist()
            slipped = bool(ds0 or ds1)
        if slipped:  # the slip rate does not depend on the slip: the steps add up (none without slip)
            self.slip = self.slip + self._s1
        self.u_last, self.f_last = u, f
        self.t += self.dt
        return self.x


def rest_state(p, heading: float = 0.0) -> np.ndarray:
    """State (12,) at rest with the pivot at p = (x, y, alpha) (m, m, rad) and chassis heading theta (rad)."""
    x0 = np.zeros(12)
    x0[:3] = p
    x0[5] = p[2] - heading
    return x0


def make_stepper(plant, dt: float, x0: np.ndarray | None = None, fixture: str = "floor") -> Stepper:
    """A ``Stepper`` for ``OtbotParams`` (the paper's model) or an ``ExtendedModel``."""
    return Stepper(plant, dt, x0, fixture)
