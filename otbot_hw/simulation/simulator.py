"""Zero-order-hold simulation of Otbot (the integrator; the physics is in ``otbot_hw.model``).

Torques u_k (N m) and pivot forces f_k (N, ground frame) are held constant on
[t_k, t_k + dt). Two integrators:

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
from typing import Sequence

import numpy as np
from scipy.integrate import solve_ivp

from otbot_hw.model import compiled
from otbot_hw.model import effects as fx
from otbot_hw.model.dynamics import forward_dynamics
from otbot_hw.model.fixtures import fixture_code, held_chassis_accelerations
from otbot_hw.params import OtbotParams

MAX_STEP = 2.5e-3  # s, largest RK4 step of the fast path


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
    """A simulated run: t (N+1,) s, x (N+1, 12) states (q, q_dot), u (N+1, 3) N m, f (N+1, 2) N.

    u[k] and f[k] are held on [t_k, t_k+1); the last row repeats the last command.
    """

    t: np.ndarray
    x: np.ndarray
    u: np.ndarray
    f: np.ndarray
    dt: float
    fixture: str = "floor"

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
    terms, the smoothed Coulomb signs (rate c / width / I_eff, ``effects.sign_width``), stay
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
             method: str = "fast", substeps: int | None = None) -> Trajectory:
    """Simulate N = len(torques) ZOH intervals of ``dt`` seconds from ``x0`` (default rest at 0).

    ``torques`` (N, 3) N m; ``forces`` a ``ForceSchedule`` or an (N, 2) array of held
    pivot forces (N, ground frame); ``fixture`` one of floor, stand, locked.
    """
    n = len(torques)
    t = np.arange(n + 1) * dt
    F = forces.sample(t[:-1]) if isinstance(forces, ForceSchedule) else forces
    U, F, x0 = check_inputs(torques, dt, F, x0)
    code = fixture_code(fixture)
    if method == "fast":
        X = compiled.rk4_zoh(x0, U, F, dt, substeps or default_substeps(dt, fixture), params.as_array(), code)
    elif method == "reference":
        X = _reference(params, U, F, dt, x0, fixture)
    else:
        raise ValueError(f"unknown method '{method}' (fast, reference)")
    Uf = np.vstack([U, U[-1:]]) if n else np.zeros((1, 3))
    Ff = np.vstack([F, F[-1:]]) if n else np.zeros((1, 2))
    return Trajectory(t=t, x=X, u=Uf, f=Ff, dt=dt, fixture=fixture)


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


class Stepper:
    """Step-by-step simulation for closed loops: ``step(u, f)`` advances one ZOH interval.

    Holds the state x (12,) and time t (s); uses the compiled RK4 path.
    """

    def __init__(self, params: OtbotParams, dt: float, x0: np.ndarray | None = None,
                 fixture: str = "floor", substeps: int | None = None):
        _, _, x0 = check_inputs(np.zeros((1, 3)), dt, None, x0)
        self.params = params
        self.dt = dt
        self.x = x0.copy()
        self.t = 0.0
        self.fixture = fixture
        self._code = fixture_code(fixture)
        self._prm = params.as_array()
        self._substeps = substeps or default_substeps(dt, fixture)

    def set_params(self, params: OtbotParams) -> None:
        """Change the plant parameters (e.g. a load placed on the platform)."""
        self.params = params
        self._prm = params.as_array()

    def step(self, u: np.ndarray, f: np.ndarray | None = None) -> np.ndarray:
        """Apply torques u (3,) N m and pivot force f (2,) N for one interval; return the new state."""
        U = np.asarray(u, dtype=float).reshape(1, 3)
        if not all(map(math.isfinite, U[0].tolist())):
            raise ValueError(f"torques must be finite, got {u}")
        F = np.zeros((1, 2)) if f is None else np.asarray(f, dtype=float).reshape(1, 2)
        self.x = compiled.rk4_zoh(self.x, U, F, self.dt, self._substeps, self._prm, self._code)[1]
        self.t += self.dt
        return self.x


@dataclass
class ExtendedTrajectory:
    """A run of the extended model: t (N+1,) s; x (N+1, 12) in rolling-angle coordinates;
    tau (N+1, 3) delivered torque N m; slip (N+1, 2) rad; qdd (N+1, 6); u (N+1, 3) commands."""

    t: np.ndarray
    x: np.ndarray
    tau: np.ndarray
    slip: np.ndarray
    qdd: np.ndarray
    u: np.ndarray
    dt: float
    fixture: str


def simulate_extended(params: OtbotParams, eff: np.ndarray, torques: np.ndarray, dt: float,
                      x0: np.ndarray | None = None, fixture: str = "floor", tau0: np.ndarray | None = None,
                      forces: np.ndarray | None = None, substeps: int | None = None) -> ExtendedTrajectory:
    """Simulate the extended model under commanded ``torques`` (N, 3) N m held for ``dt`` s.

    ``tau0``: delivered torque before t_0 (default 0: the drives start from rest), only
    matters with a current-loop lag. ``x0`` (12,) in rolling-angle coordinates (default rest).
    """
    U, F, x0 = check_inputs(torques, dt, forces, x0)
    eff = np.asarray(eff, dtype=float)
    if eff.shape != (fx.N_EFFECT,) or not np.all(np.isfinite(eff)):
        raise ValueError(f"effect vector must be {fx.N_EFFECT} finite numbers")
    code = fixture_code(fixture)
    prm = params.as_array()
    sub = substeps or default_substeps(dt, fixture)
    t0 = np.zeros(3) if tau0 is None else np.asarray(tau0, dtype=float)
    X, TAU, S = fx.ext_rk4_zoh(x0, t0, U, F, dt, sub, prm, eff, code)
    Uf = np.vstack([U, U[-1:]]) if len(U) else np.zeros((1, 3))
    Ff = np.vstack([F, F[-1:]]) if len(U) else np.zeros((1, 2))
    qdd = fx.ext_sample_accelerations(X, TAU, Ff, eff, prm, code)
    return ExtendedTrajectory(t=np.arange(len(X)) * dt, x=X, tau=TAU, slip=S, qdd=qdd, u=Uf, dt=dt,
                              fixture=fixture)



class ExtendedStepper(Stepper):
    """``Stepper`` for the extended model (``otbot_hw.model.effects.ExtendedModel``: the paper's
    dynamics plus missing-physics effects, e.g. a diagnosed model as a closed loop's plant).

    ``step(u, f)`` takes the *commanded* torques; the drives' gain, saturation and current lag act on
    them. x (12,) holds rolling angles for the wheels (equal to the wheel angles without a radius
    asymmetry); ``tau`` is the torque the drives deliver at the end of the last step (N m);
    ``slip`` (2,) rad the wheel slip accumulated since the start (what the wheel encoders read on
    top of the rolling angles, ``effects.sensor_outputs``).
    """

    def __init__(self, model, dt: float, x0: np.ndarray | None = None, fixture: str = "floor",
                 substeps: int | None = None):
        super().__init__(model.params, dt, x0, fixture, substeps)
        self.eff = np.asarray(model.eff, dtype=float)
        self.tau = np.zeros(3)
        self.slip = np.zeros(2)

    def step(self, u: np.ndarray, f: np.ndarray | None = None) -> np.ndarray:
        U = np.asarray(u, dtype=float).reshape(1, 3)
        if not all(map(math.isfinite, U[0].tolist())):
            raise ValueError(f"torques must be finite, got {u}")
        F = np.zeros((1, 2)) if f is None else np.asarray(f, dtype=float).reshape(1, 2)
        X, TAU, S = fx.ext_rk4_zoh(self.x, self.tau, U, F, self.dt, self._substeps, self._prm, self.eff, self._code)
        self.x, self.tau = X[1], TAU[1]
        self.slip = self.slip + S[1]  # the slip rate does not depend on the slip: the steps add up
        self.t += self.dt
        return self.x


def rest_state(p, heading: float = 0.0) -> np.ndarray:
    """State (12,) at rest with the pivot at p = (x, y, alpha) (m, m, rad) and chassis heading theta (rad)."""
    x0 = np.zeros(12)
    x0[:3] = p
    x0[5] = p[2] - heading
    return x0


def make_stepper(plant, dt: float, x0: np.ndarray | None = None, fixture: str = "floor") -> Stepper:
    """A ``Stepper`` for ``OtbotParams`` (the paper's model) or an ``ExtendedStepper`` for an
    ``ExtendedModel`` with active effects."""
    if hasattr(plant, "eff"):
        if plant.active_effects():
            return ExtendedStepper(plant, dt, x0, fixture)
        plant = plant.params
    return Stepper(plant, dt, x0, fixture)
