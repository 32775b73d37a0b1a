"""Torque-feasibility check of a desired trajectory (paper §5.3).

For error bounds |e_p| <= E_p, |e_v| <= E_v (per axis) the torques the computed-torque law
can ask for along p_d(t) are bounded by interval arithmetic and compared with the motor
limits. Steps:

1. "Simulate u_traj open loop": along p_d the robot state is fixed by the rolling
   constraints — the chassis heading obeys theta_dot = -(sin(theta) x_dot_d - cos(theta) y_dot_d) / l1
   from the initial heading — so the pivot angle phi_p,d(t) = alpha_d - theta is integrated
   (RK4 on the check grid) and the whole state (q, q_dot) along p_d is known.
2. At each check time the actual state lies in the box p in p_d + [-E_p, E_p],
   p_dot in p_dot_d + [-E_v, E_v], phi_p in phi_p,d + [-E_phi, E_phi] (E_phi: how far the
   chassis heading may stray from its reference, default 0.05 rad). M_bar and C_bar are
   evaluated over that box with the model's own pure functions on intervals, and
       u = M_bar (p_dd_d - K_p [e_p] - K_v [e_v]) + C_bar [p_dot]
   (= u_traj + u_corr) is enclosed. This is the paper's bound made conservative: the
   paper holds M_bar and C_bar at their values on p_d; here their variation over the box
   is enclosed too, so the bound contains every torque the law can command while the
   errors stay inside the bounds.
3. Where the reference velocity jumps (a polyline corner), the velocity error jumps by the
   step: at that instant the robot still has the old velocity, so the enclosure there is
   taken over e_v in -step + [-E_v, E_v] as well.
4. Where an enclosure leaves [-limit, limit] the limit *can* be exceeded: reported as
   episodes (motor, time span, largest bound).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from otbot_hw.control.gains import Gains
from otbot_hw.control.interval import Interval, as_box, bounds
from otbot_hw.control.trajectories import DesiredTrajectory
from otbot_hw.model.kinematics import iik_entries, inverse_kinematics_matrix
from otbot_hw.model.task_space import task_space_model
from otbot_hw.motors import MOTORS, MotorLimits
from otbot_hw.params import OtbotParams


@dataclass(frozen=True)
class ErrorBounds:
    """Bounds on |e_p| (m, m, rad), |e_v| (m/s, m/s, rad/s) and the pivot-angle deviation (rad)."""

    position: tuple[float, float, float]
    velocity: tuple[float, float, float]
    pivot_angle: float = 0.05

    def __post_init__(self):
        for name in ("position", "velocity"):
            v = np.asarray(getattr(self, name), float)
            if v.shape != (3,) or not np.all(np.isfinite(v)) or np.any(v < 0):
                raise ValueError(f"error bounds: {name} must be 3 finite numbers >= 0, got {getattr(self, name)}")
        if not (np.isfinite(self.pivot_angle) and self.pivot_angle >= 0):
            raise ValueError(f"error bounds: pivot_angle must be >= 0 rad, got {self.pivot_angle}")

    @classmethod
    def default(cls) -> "ErrorBounds":
        """2 cm / 0.01 rad in position, 5 cm/s / 0.02 rad/s in velocity, 0.05 rad in phi_p."""
        return cls((0.02, 0.02, 0.01), (0.05, 0.05, 0.02), 0.05)

    def to_dict(self) -> dict:
        return {"position": list(self.position), "velocity": list(self.velocity), "pivot_angle": self.pivot_angle}


@dataclass
class FeasibilityReport:
    """t (N,) s; lo, hi (N, 3) N m torque enclosures; violations: episodes beyond the limits."""

    t: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    limits: np.ndarray
    bounds: ErrorBounds
    violations: list = field(default_factory=list)
    reference_state: np.ndarray | None = None   # (N, 12) state along p_d
    velocity_steps: list = field(default_factory=list)  # reference velocity jumps: t, |step| per axis

    @property
    def feasible(self) -> bool:
        return not self.violations

    def to_dict(self) -> dict:
        peak = np.maximum(np.abs(self.lo), np.abs(self.hi)).max(axis=0)
        return {"feasible": self.feasible, "error_bounds": self.bounds.to_dict(),
                "peak_bound_Nm": dict(zip(MOTORS, peak.tolist())),
                "limits_Nm": dict(zip(MOTORS, self.limits.tolist())),
                "violations": self.violations, "velocity_steps": self.velocity_steps}


def reference_states(reference: DesiredTrajectory, params: OtbotParams, t: np.ndarray,
                     heading0: float = 0.0) -> np.ndarray:
    """States (len(t), 12) along p_d: q from integrating the chassis heading, q_dot = Lambda p_dot_d.

    Wheel angles start at 0. ``heading0`` is the chassis heading theta (rad) at t[0].
    """
    P, PD, _ = reference.sample(t)
    th = np.empty(len(t))
    th[0] = heading0
    l1 = params.l1
    _, PDm, _ = reference.sample(0.5 * (t[1:] + t[:-1]))

    def f(theta, v):
        return -(np.sin(theta) * v[0] - np.cos(theta) * v[1]) / l1

    for k in range(len(t) - 1):
        h = t[k + 1] - t[k]
        k1 = f(th[k], PD[k])
        k2 = f(th[k] + 0.5 * h * k1, PDm[k])
        k3 = f(th[k] + 0.5 * h * k2, PDm[k])
        k4 = f(th[k] + h * k3, PD[k + 1])
        th[k + 1] = th[k] + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    X = np.zeros((len(t), 12))
    X[:, :3] = P
    X[:, 5] = P[:, 2] - th
    X[:, 6:9] = PD
    # joint rates phi_dot = M_IIK p_dot (M_IIK's entries, ``model.kinematics``)
    a00, a01, a10, a11, a20, a21 = iik_entries(np.sin(th), np.cos(th), l1, params.l2, params.r)
    X[:, 9] = a00 * PD[:, 0] + a01 * PD[:, 1]
    X[:, 10] = a10 * PD[:, 0] + a11 * PD[:, 1]
    X[:, 11] = a20 * PD[:, 0] + a21 * PD[:, 1] + PD[:, 2]
    return X


def _enclosure_on_box(X, PDD, params, gains, eb, dalpha, dphi, ev_center=None):
    """Natural interval extension of the law over one box: alpha in alpha_d + dalpha, phi_p in
    phi_p,d + dphi (dalpha, dphi: (lo, hi) offsets), e_v in ev_center + [-E_v, E_v], the rest
    from the error bounds."""
    evc = np.zeros((len(X), 3)) if ev_center is None else np.asarray(ev_center, float)
    def box(center, lo, hi):
        return Interval(center + lo, center + hi)

    q = np.empty(6, dtype=object)
    q[0] = Interval.around(X[:, 0], eb.position[0])
    q[1] = Interval.around(X[:, 1], eb.position[1])
    q[2] = box(X[:, 2], *dalpha)
    q[3], q[4] = Interval(X[:, 3]), Interval(X[:, 4])
    q[5] = box(X[:, 5], *dphi)
    pd = as_box(X[:, 6:9] + evc, np.asarray(eb.velocity))
    qd = np.concatenate([pd, inverse_kinematics_matrix(q, params) @ pd])
    Mbar, Cbar = task_space_model(q, qd, params)
    v = np.empty(3, dtype=object)
    for i in range(3):
        v[i] = Interval(PDD[:, i]) + (-gains.kp[i]) * Interval.around(0.0, eb.position[i]) \
            + (-gains.kv[i]) * Interval.around(evc[:, i], eb.velocity[i])
    u = Mbar @ v + Cbar @ pd
    lo, hi = bounds(u)
    n = len(X)
    return np.broadcast_to(lo, (n, 3)), np.broadcast_to(hi, (n, 3))


def torque_enclosure(X: np.ndarray, PDD: np.ndarray, params: OtbotParams, gains: Gains,
                     eb: ErrorBounds, splits: tuple[int, int] = (2, 6),
                     ev_center: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) (N, 3) N m enclosing the law's torque over the error box around states X (N, 12);
    the velocity-error box is centred on ``ev_center`` (N, 3) (default 0).

    The alpha and phi_p ranges are split into ``splits`` sub-intervals and the enclosures
    united: the model's angles appear many times, so the natural extension overestimates in
    proportion to their width (the dependency effect); splitting shrinks that.
    """
    ea, ep = eb.position[2], eb.pivot_angle
    na, nphi = (max(1, splits[0]) if ea > 0 else 1), (max(1, splits[1]) if ep > 0 else 1)
    ga = np.linspace(-ea, ea, na + 1)
    gp = np.linspace(-ep, ep, nphi + 1)
    lo = np.full((len(X), 3), np.inf)
    hi = np.full((len(X), 3), -np.inf)
    for i in range(na):
        for j in range(nphi):
            l, h = _enclosure_on_box(X, PDD, params, gains, eb, (ga[i], ga[i + 1]), (gp[j], gp[j + 1]), ev_center)
            lo = np.minimum(lo, l)
            hi = np.maximum(hi, h)
    return lo, hi


#: most points a check bounds (about a minute of compute and memory kept to a chunk): 10^4 s at 0.01 s
MAX_POINTS = 1_000_000
#: points bounded at once (the interval arithmetic holds a few kB per point)
CHUNK = 20_000


def feasibility_points(duration: float, dt: float = 0.01) -> int:
    """Points ``check_feasibility`` bounds for a reference of ``duration`` s sampled every ``dt`` s."""
    return int(np.ceil(duration / dt)) + 1


def check_feasibility(reference: DesiredTrajectory, params: OtbotParams, gains: Gains, limits: MotorLimits,
                      error_bounds: ErrorBounds | None = None, dt: float = 0.01,
                      heading0: float = 0.0, progress: Callable[[str], None] | None = None) -> FeasibilityReport:
    """Bound the law's torques along ``reference`` every ``dt`` s and compare with ``limits``.

    ValueError before any work when that is more than ``MAX_POINTS`` points; ``progress(text)`` gets a
    line per quarter of a check longer than ``4 CHUNK`` points."""
    eb = error_bounds or ErrorBounds.default()
    n = feasibility_points(reference.duration, dt) - 1
    if n + 1 > MAX_POINTS:
        raise ValueError(f"a reference of {reference.duration:g} s needs {n + 1} feasibility points every {dt:g} s; "
                         f"at most {MAX_POINTS} ({(MAX_POINTS - 1) * dt:g} s)")
    t = np.arange(n + 1) * dt
    X = reference_states(reference, params, t, heading0)
    _, _, PDD = reference.sample(t)
    lo = np.empty((n + 1, 3))
    hi = np.empty((n + 1, 3))
    chunks = range(0, n + 1, CHUNK)
    report_at = {chunks[min(len(chunks) - 1, (q * len(chunks)) // 4)] for q in (1, 2, 3)} if n + 1 > 4 * CHUNK \
        else set()
    for a in chunks:
        if progress and a in report_at:
            progress(f"feasibility check: {100 * a / (n + 1):.0f} % of {n + 1} points")
        b = min(a + CHUNK, n + 1)
        lo[a:b], hi[a:b] = torque_enclosure(X[a:b], PDD[a:b], params, gains, eb)
    # velocity steps of the reference (e.g. polyline corners, a start at full speed): the velocity
    # error jumps by the step. A step is a change of p_dot between samples that the trapezoid of
    # p_dd does not explain, beyond 1 cm/s (rad/s) plus what an acceleration jump could cause.
    tp = np.concatenate([[t[0] - dt], t])
    _, PDp, PDDp = reference.sample(tp)
    PDDp[0] = 0.0
    dPDD = np.abs(np.diff(PDDp, axis=0))
    step = np.diff(PDp, axis=0) - 0.5 * dt * (PDDp[1:] + PDDp[:-1])
    jumps = np.flatnonzero(np.any(np.abs(step) > 0.01 + dt * dPDD, axis=1))
    steps = []
    for k in jumps:
        # just after the step the robot still has the old velocity: e_v = -step (+- E_v)
        l, h = torque_enclosure(X[k:k + 1], PDD[k:k + 1], params, gains, eb, ev_center=-step[k:k + 1])
        lo[k] = np.minimum(lo[k], l[0])
        hi[k] = np.maximum(hi[k], h[0])
        steps.append({"t": float(t[k]), "velocity_step": step[k].tolist()})
    lim = np.asarray(limits.max_torque, float)
    viol = []
    for i, motor in enumerate(MOTORS):
        over = (hi[:, i] > lim[i]) | (lo[:, i] < -lim[i])
        if not over.any():
            continue
        edges = np.flatnonzero(np.diff(np.concatenate([[0], over.astype(int), [0]])))
        for a, b in zip(edges[::2], edges[1::2]):
            worst = float(np.max(np.maximum(np.abs(lo[a:b, i]), np.abs(hi[a:b, i]))))
            viol.append({"motor": motor, "t_start": float(t[a]), "t_end": float(t[b - 1]),
                         "bound_Nm": worst, "limit_Nm": float(lim[i])})
    viol.sort(key=lambda v: v["t_start"])
    return FeasibilityReport(t=t, lo=lo, hi=hi, limits=lim, bounds=eb, violations=viol, reference_state=X,
                             velocity_steps=steps)
