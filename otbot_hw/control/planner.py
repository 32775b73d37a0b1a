"""Trajectory planner: direct collocation on the full dynamic model (CasADi + IPOPT).

The robot's dynamics in task space, M_bar(q) p_dd + C_bar(q, q_dot) p_dot = u, together with
the pivot-angle kinematics phi_p_dot = (sin(theta) x_dot - cos(theta) y_dot) / l1 + alpha_dot
(theta = alpha - phi_p), are exact for the full model: the wheel angles are cyclic and do
not enter the dynamics. M_bar and C_bar are built symbolically from the model's own pure
functions (``otbot_hw.model``) evaluated on CasADi symbols.

Decision variables: the reduced state z = (x, y, alpha, phi_p, x_dot, y_dot, alpha_dot) and
torques u = (tau_r, tau_l, tau_p) at N + 1 nodes, plus the final time T for minimum time.
Constraints: trapezoidal collocation z_{k+1} - z_k = h/2 (f_k + f_{k+1}), h = T/N; torque
limits (scaled by ``torque_margin`` to leave room for the feedback); speed limits; rest-to-rest
boundary conditions; corridor walls; circular obstacles kept clear of the platform
footprint: |P - c_j| >= r_j + footprint + clearance at every node. Objective: T (+ a small
torque regularization) for minimum time, or the torque effort for a fixed T.

As in the paper, the discrete states and torques are only consistent up to the
collocation error: replaying the torques open loop drifts, tracking the states in closed
loop does not. The initial guess is a collision-free weave around the obstacles, checked.
"""
from __future__ import annotations

import contextlib
import math
import signal
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from otbot_hw.extras import require
from otbot_hw.motors import MotorLimits
from otbot_hw.params import OtbotParams


class PlannerError(RuntimeError):
    """The planning problem is malformed, the warm start collides or IPOPT found no solution."""


@dataclass
class PlanningProblem:
    """Rest-to-rest motion from ``start`` to ``goal`` (x, y, alpha) in m, rad.

    ``obstacles``: (cx, cy, r) m; ``walls``: (y_min, y_max) m bounding the footprint, or None;
    ``duration``: fixed T (s) or None for minimum time (T in [t_min, t_max]);
    ``max_speed`` (m/s) and ``max_turn_rate`` (rad/s) bound the platform twist.
    """

    params: OtbotParams
    limits: MotorLimits
    start: tuple[float, float, float]
    goal: tuple[float, float, float]
    obstacles: Sequence[tuple[float, float, float]] = ()
    walls: tuple[float, float] | None = None
    clearance: float = 0.05
    duration: float | None = None
    t_min: float = 1.0
    t_max: float = 60.0
    intervals: int = 60
    torque_margin: float = 0.8
    start_heading: float = 0.0
    guess_speed: float = 0.5
    max_speed: float = 1.0          # m/s, pivot speed |(x_dot, y_dot)|
    max_turn_rate: float = 1.0      # rad/s, |alpha_dot|

    def __post_init__(self):
        if self.intervals < 4:
            raise PlannerError(f"need at least 4 collocation intervals, got {self.intervals}")
        if not 0 < self.torque_margin <= 1:
            raise PlannerError(f"torque_margin must be in (0, 1], got {self.torque_margin}")
        for o in self.obstacles:
            if len(o) != 3 or not o[2] > 0:
                raise PlannerError(f"obstacle must be (cx, cy, r > 0), got {o}")
        if self.duration is not None and not self.duration > 0:
            raise PlannerError(f"duration must be > 0 s, got {self.duration}")

    def keep_out(self) -> list[float]:
        """Minimum pivot distance (m) to each obstacle centre."""
        return [r + self.params.radius + self.clearance for _, _, r in self.obstacles]

    def obstacles_with_radius(self) -> list[tuple[float, float, float]]:
        return [tuple(map(float, o)) for o in self.obstacles]


def crowded_corridor_problem(params: OtbotParams, limits: MotorLimits, intervals: int = 60) -> PlanningProblem:
    """The ``planned`` scenario: an 8 m corridor, 3.2 m wide, with four circular obstacles."""
    obstacles = [(1.8, 0.7, 0.3), (3.4, -0.6, 0.35), (5.0, 0.6, 0.3), (6.5, -0.65, 0.3)]
    return PlanningProblem(params, limits, start=(0.0, 0.0, 0.0), goal=(8.0, 0.0, 0.0), obstacles=obstacles,
                           walls=(-1.6, 1.6), intervals=intervals)


@dataclass
class PlanResult:
    """Planned nodes: t (N+1,) s, z (N+1, 7) reduced states, u (N+1, 3) N m, full states x (N+1, 12)."""

    t: np.ndarray
    z: np.ndarray
    u: np.ndarray
    x: np.ndarray
    status: str
    solve_time_s: float
    iterations: int
    min_clearance_m: float
    problem: PlanningProblem = field(repr=False)

    def trajectory(self, hold: float = 0.0):
        """The planned states as a desired trajectory (cubic Hermite through positions and velocities)."""
        from otbot_hw.control.sampled_trajectory import SampledTrajectory

        return SampledTrajectory(self.t, self.z[:, :3], self.z[:, 4:7], torques=self.u, source="planner", hold=hold)

    def save_csv(self, path: str | Path) -> Path:
        from otbot_hw.control.sampled_trajectory import save_csv

        return save_csv(path, self.t, self.z[:, :3], self.z[:, 4:7], self.u,
                        comment=f"otbot plan: T = {self.t[-1]:.4f} s, {len(self.t) - 1} collocation intervals, "
                                f"status {self.status}", obstacles=self.problem.obstacles_with_radius())

    def summary(self) -> dict:
        return {"status": self.status, "duration_s": float(self.t[-1]), "intervals": len(self.t) - 1,
                "solve_time_s": self.solve_time_s, "iterations": self.iterations,
                "min_clearance_m": self.min_clearance_m,
                "peak_torque_Nm": np.max(np.abs(self.u), axis=0).tolist(),
                "obstacles": self.problem.obstacles_with_radius()}


def _symbolic_model(params: OtbotParams):
    """CasADi function f(z, u) -> z_dot for the reduced state, from the model's pure functions."""
    ca = require("casadi")

    try:  # numpy ufuncs on CasADi symbols (np.sin in the model): keep the legacy, type-following result
        ca.GlobalOptions.setNumpyMode(-1)
    except AttributeError:
        pass
    from otbot_hw.model.kinematics import inverse_kinematics_matrix
    from otbot_hw.model.task_space import task_space_model

    z = ca.SX.sym("z", 7)
    u = ca.SX.sym("u", 3)
    q = np.empty(6, dtype=object)
    q[:] = [z[0], z[1], z[2], 0.0, 0.0, z[3]]
    pd = np.empty(3, dtype=object)
    pd[:] = [z[4], z[5], z[6]]
    qd = np.concatenate([pd, inverse_kinematics_matrix(q, params) @ pd])
    Mbar, Cbar = task_space_model(q, qd, params)

    def sx(A):
        return ca.vertcat(*[ca.horzcat(*[A[i, j] for j in range(A.shape[1])]) for i in range(A.shape[0])])

    Mb, Cb = sx(Mbar), sx(Cbar)
    pdd = ca.solve(Mb, u - ca.mtimes(Cb, z[4:7]))
    phipd = qd[5]
    return ca.Function("f", [z, u], [ca.vertcat(z[4], z[5], z[6], phipd, pdd)])


def warm_start_path(prob: PlanningProblem) -> np.ndarray:
    """Waypoints (n, 2) weaving around the obstacles: a short straight pass beside each obstacle,
    on the side away from the corridor axis, within the walls."""
    pts = [prob.start[:2]]
    keep = prob.keep_out()
    order = np.argsort([o[0] for o in prob.obstacles])
    lo, hi = (-np.inf, np.inf) if prob.walls is None else (prob.walls[0] + prob.params.radius,
                                                          prob.walls[1] - prob.params.radius)
    for j in order:
        cx, cy, _ = prob.obstacles[j]
        side = -1.0 if cy >= 0 else 1.0
        y = float(np.clip(cy + side * (keep[j] + 0.2), lo, hi))
        a = 0.5 * keep[j]
        pts += [(cx - a, y), (cx + a, y)]
    pts.append(prob.goal[:2])
    return np.array(pts, dtype=float)


def _guess(prob: PlanningProblem, N: int):
    from otbot_hw.control.feasibility import reference_states
    from otbot_hw.control.trajectories import PolylineTrajectory

    W = warm_start_path(prob)
    length = float(np.sum(np.linalg.norm(np.diff(W, axis=0), axis=1)))
    T0 = prob.duration or max(prob.t_min, min(prob.t_max, length / prob.guess_speed))
    w = 0.05 * T0
    ref = PolylineTrajectory(W, speed=length / (T0 - 2 * w), alpha=prob.start[2], smoothing=w)
    tf = np.linspace(0, ref.duration, 2000)
    P, _, _ = ref.sample(tf)
    clear = _clearance(P, prob)
    if clear < 0:
        raise PlannerError(f"no collision-free initial path: the path that passes each obstacle in turn from "
                           f"start to goal {_first_contact(P, prob)}; move the start, goal or obstacles")
    t = np.linspace(0, ref.duration, N + 1)
    X = reference_states(ref, prob.params, t, prob.start_heading)
    z = np.column_stack([X[:, :3], X[:, 5], X[:, 6:9]])
    return z, ref.duration


def _clearance(P: np.ndarray, prob: PlanningProblem) -> float:
    """Smallest distance (m) between the footprint (plus clearance) and an obstacle or wall; < 0 collides."""
    out = np.inf
    for (cx, cy, _), k in zip(prob.obstacles, prob.keep_out()):
        out = min(out, float(np.min(np.hypot(P[:, 0] - cx, P[:, 1] - cy) - k)))
    if prob.walls is not None:
        r = prob.params.radius
        out = min(out, float(np.min(P[:, 1] - r - prob.walls[0])), float(np.min(prob.walls[1] - r - P[:, 1])))
    return out


def _first_contact(P: np.ndarray, prob: PlanningProblem) -> str:
    """What the footprint along P (n, 2) m hits first: 'hits obstacle j at (cx, cy) m' or a wall."""
    hits = []
    for j, ((cx, cy, _), k) in enumerate(zip(prob.obstacles, prob.keep_out())):
        inside = np.flatnonzero(np.hypot(P[:, 0] - cx, P[:, 1] - cy) < k)
        if inside.size:
            hits.append((inside[0], f"hits obstacle {j} at ({cx:g}, {cy:g}) m"))
    if prob.walls is not None:
        r = prob.params.radius
        for y, out in ((prob.walls[0], P[:, 1] - r < prob.walls[0]), (prob.walls[1], P[:, 1] + r > prob.walls[1])):
            idx = np.flatnonzero(out)
            if idx.size:
                hits.append((idx[0], f"crosses the wall y = {y:g} m"))
    return min(hits)[1] if hits else "collides"


@contextlib.contextmanager
def _interrupt_flag():
    """A list that gets an entry when SIGINT arrives inside the block (Python's handler still raises
    KeyboardInterrupt, which CasADi catches and reports as a failed solve)."""
    flag: list[int] = []
    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield flag
        return

    def handler(signum, frame):
        flag.append(signum)
        raise KeyboardInterrupt

    signal.signal(signal.SIGINT, handler)
    try:
        yield flag
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def check_reachable(prob: PlanningProblem) -> None:
    """PlannerError when the goal is farther from the start than ``max_speed`` covers in the time the plan
    may last (the fixed ``duration``, else ``t_max``): a goal 1e308 m away, or --duration 1e-320 s, made the
    warm start's speed infinite ("speed must be > 0 m/s, got inf")."""
    if prob.duration is not None and not prob.t_min <= prob.duration <= prob.t_max:
        raise PlannerError(f"--duration {prob.duration:g} s is outside the planner's range [{prob.t_min:g}, "
                           f"{prob.t_max:g}] s (a minimum-time plan is searched there too)")
    dist = math.hypot(prob.goal[0] - prob.start[0], prob.goal[1] - prob.start[1])
    longest = prob.t_max if prob.duration is None else prob.duration
    if dist > prob.max_speed * longest:
        what = (f"the fixed --duration of {longest:g} s" if prob.duration is not None
                else f"the longest plan, {longest:g} s")
        raise PlannerError(f"the goal is {dist:.6g} m from the start: at the largest pivot speed "
                           f"{prob.max_speed:g} m/s (--max-speed) that takes at least {dist / prob.max_speed:.6g} s, more than {what}")


def plan(prob: PlanningProblem, progress: Callable[[str], None] | None = None,
         max_iter: int = 500) -> PlanResult:
    """Solve the collocation problem with IPOPT; raises PlannerError when it does not converge."""
    ca = require("casadi")

    for name, pt in (("start", prob.start), ("goal", prob.goal)):
        for j, ((cx, cy, _), k) in enumerate(zip(prob.obstacles, prob.keep_out())):
            if math.hypot(pt[0] - cx, pt[1] - cy) < k:
                raise PlannerError(f"{name} ({pt[0]:g}, {pt[1]:g}) m is within {k:.2f} m of obstacle {j} at "
                                   f"({cx:g}, {cy:g}) m: the platform footprint would overlap it")
        if prob.walls is not None and not (prob.walls[0] + prob.params.radius <= pt[1]
                                           <= prob.walls[1] - prob.params.radius):
            raise PlannerError(f"{name} y = {pt[1]:g} m puts the footprint outside the walls {prob.walls}")
    check_reachable(prob)
    N = prob.intervals
    f = _symbolic_model(prob.params)
    z_guess, T_guess = _guess(prob, N)
    opti = ca.Opti()
    Z = opti.variable(7, N + 1)
    U = opti.variable(3, N + 1)
    T = opti.variable() if prob.duration is None else prob.duration
    h = T / N
    umax = prob.torque_margin * np.asarray(prob.limits.max_torque, float)
    F = f.map(N + 1)(Z, U)
    opti.subject_to(Z[:, 1:] - Z[:, :-1] == h / 2 * (F[:, 1:] + F[:, :-1]))
    for i in range(3):
        opti.subject_to(opti.bounded(-umax[i], U[i, :], umax[i]))
    sx, sy, sa = prob.start
    gx, gy, ga = prob.goal
    opti.subject_to(Z[:, 0] == ca.vertcat(sx, sy, sa, sa - prob.start_heading, 0, 0, 0))
    opti.subject_to(Z[0:3, N] == ca.vertcat(gx, gy, ga))
    opti.subject_to(Z[4:7, N] == 0)
    for (cx, cy, _), k in zip(prob.obstacles, prob.keep_out()):
        opti.subject_to((Z[0, :] - cx) ** 2 + (Z[1, :] - cy) ** 2 >= k ** 2)
    if prob.walls is not None:
        r = prob.params.radius
        opti.subject_to(opti.bounded(prob.walls[0] + r, Z[1, :], prob.walls[1] - r))
    opti.subject_to(Z[4, :] ** 2 + Z[5, :] ** 2 <= prob.max_speed ** 2)
    opti.subject_to(opti.bounded(-prob.max_turn_rate, Z[6, :], prob.max_turn_rate))
    effort = ca.sumsqr(U) / (N + 1) / float(np.sum(umax ** 2))
    if prob.duration is None:
        opti.subject_to(opti.bounded(prob.t_min, T, prob.t_max))
        opti.set_initial(T, T_guess)
        opti.minimize(T + 0.1 * effort * T)
    else:
        opti.minimize(effort * T)
    opti.set_initial(Z, z_guess.T)
    opti.set_initial(U, 0)
    opti.solver("ipopt", {"print_time": False}, {"print_level": 0, "sb": "yes", "max_iter": max_iter, "tol": 1e-8})
    if progress:
        progress(f"IPOPT: {N} intervals, {7 * (N + 1) + 3 * (N + 1) + (prob.duration is None)} variables")
    start = time.perf_counter()
    try:
        with _interrupt_flag() as interrupted:
            sol = opti.solve()
    except RuntimeError as exc:
        if interrupted:  # CasADi turns Ctrl-C inside IPOPT into a solver failure: it is an interrupt
            raise KeyboardInterrupt from None
        stats = opti.stats()
        raise PlannerError(f"IPOPT did not converge ({stats.get('return_status', exc)}) after "
                           f"{stats.get('iter_count', '?')} iterations") from None
    elapsed = time.perf_counter() - start
    stats = sol.stats()
    Tval = float(sol.value(T)) if prob.duration is None else float(prob.duration)
    zv = np.asarray(sol.value(Z)).T
    uv = np.asarray(sol.value(U)).T
    t = np.linspace(0.0, Tval, N + 1)
    res = PlanResult(t=t, z=zv, u=uv, x=_full_states(zv, prob.params), status=stats["return_status"],
                     solve_time_s=elapsed, iterations=int(stats["iter_count"]), min_clearance_m=0.0, problem=prob)
    tf = np.linspace(0.0, Tval, 20 * N + 1)
    res.min_clearance_m = _clearance(res.trajectory().sample(tf)[0], prob) + prob.clearance
    return res


def _full_states(z: np.ndarray, params: OtbotParams) -> np.ndarray:
    """(N+1, 12) states from reduced ones; wheel angles start at 0 (they do not enter the dynamics)."""
    X = np.zeros((len(z), 12))
    X[:, :3] = z[:, :3]
    X[:, 5] = z[:, 3]
    X[:, 6:9] = z[:, 4:7]
    th = z[:, 2] - z[:, 3]
    from otbot_hw.model.kinematics import iik_entries

    a00, a01, a10, a11, a20, a21 = iik_entries(np.sin(th), np.cos(th), params.l1, params.l2, params.r)
    X[:, 9] = a00 * z[:, 4] + a01 * z[:, 5]
    X[:, 10] = a10 * z[:, 4] + a11 * z[:, 5]
    X[:, 11] = a20 * z[:, 4] + a21 * z[:, 5] + z[:, 6]
    return X
