"""Designed excitation for the floor steps: torques that minimise the Cramer-Rao bound within the limits.

The paper excites the chassis and the platform steps with constant torques (6, -10, 6) N m.
Here the torques of each motor are continuous piecewise-linear through knots every
``knot_spacing`` s (the robot starts at rest; |tau| <= limits.torque at the knots bounds it
everywhere) and are chosen, on the model at the design parameters, to minimise

    mean over the step's parameters of (CRB_i / CRB_i of the paper's excitation)^2,

the squared std relative to what the paper's experiment of the same duration gives
(A-optimal on parameters normalised by the paper's bounds: it targets the reported
quantity, the std of every parameter, where a D-optimal design, -log det F, may buy a
large gain on one parameter with a loss on another; in trials SLSQP also ended
D-optimal designs outside the limits), subject to the ``ExperimentLimits`` on the predicted motion (wheel speed, pivot speed,
platform speed, travel with the stop), checked on every sample window and on every robot
of ``prior_scenarios`` (the corners of the prior ``RobotSpread``: the robot is not known
before it is identified, and an informative excitation is one whose motion is sensitive
to the parameters, so a design kept within the limits on the nominal robot only went 2.5
times past the travel limit on robots 20 % lighter). The Fisher
information is J^T Sigma^-1 J of the step's output channels for the stated sensor
noise (``identification.experiments.paper_noise``), J by central differences on the
compiled model. Minimiser: scipy's SLSQP from the paper's torques (scaled into the
limits) and ``starts - 1`` random knot sets; the best design that meets every limit wins.

The design is local: it is optimal for the design parameters (the earlier steps'
estimates and a guess of the load); ``benchmarks/bench_accuracy.py`` measures the gain on
robots and loads it was not designed for.
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.optimize import minimize

from otbot_hw.experiment_limits import ExperimentLimits, motion_fractions, motion_margins, violations
from otbot_hw.identification.errors import IdentificationError
from otbot_hw.identification.experiment import Experiment
from otbot_hw.identification.experiments import PAPER_EXPERIMENTS, ExperimentSpec, paper_noise
from otbot_hw.identification.model import OtbotModel
from otbot_hw.identification.prediction_error import TYPICAL_SCALE
from otbot_hw.identification.residual_problem import ResidualProblem
from otbot_hw.model.fixtures import fixture_code
from otbot_hw.params import OtbotParams
from otbot_hw.sensors import NoiseModel
from otbot_hw.simulation.integrators import rk4_zoh

DESIGNABLE = ("chassis", "platform")
WINDOW = 5  # samples per constraint window (the peak within each window is constrained)
MARGIN = 0.05  # default: the design keeps each quantity below (1 - margin) of its limit on the model


@dataclass(frozen=True)
class RobotSpread:
    """How far the robot may be from the design parameters: a prior, for designing and for studies.

    scale: masses, inertias and frictions within +- this fraction; com_shift: the chassis' centre
    of mass moved up to this many m in x and y; load_mass (kg), load_radius (m), load_inertia
    (kg m^2): the load on the platform (platform step).
    """

    scale: float = 0.2
    com_shift: float = 0.05
    load_mass: tuple[float, float] = (20.0, 300.0)
    load_radius: float = 0.35
    load_inertia: tuple[float, float] = (0.0, 5.0)


def prior_scenarios(step: str, params: OtbotParams, spread: RobotSpread | None = None) -> list[OtbotParams]:
    """Robots at the corners of the prior on which a design must keep to the limits.

    Chassis and platform steps: the design robot, and every combination of masses/inertias/
    frictions all at (1 -+ scale) with the chassis' centre of mass moved diagonally by com_shift
    (the lighter the robot, the faster it goes); a light robot with heavy inertias and the reverse.
    Platform step also: those robots unloaded (the design point) and the lightest and heaviest
    loads at the edge of load_radius in four directions.
    """
    sp = spread or RobotSpread()
    out = [params]

    def scaled(m: float, i: float, dx: float = 0.0, dy: float = 0.0) -> OtbotParams:
        return params.replace(m_c=params.m_c * m, I_c=params.I_c * i, I_a=params.I_a * i, I_p=params.I_p * i,
                              b_w=params.b_w * m, b_p=params.b_p * m, x_B=params.x_B + dx, y_B=params.y_B + dy)

    c = sp.com_shift
    for f in (1.0 - sp.scale, 1.0 + sp.scale):
        for dx, dy in ((c, c), (c, -c), (-c, c), (-c, -c)):
            out.append(scaled(f, f, dx, dy))
    out += [scaled(1.0 - sp.scale, 1.0 + sp.scale), scaled(1.0 + sp.scale, 1.0 - sp.scale)]
    if step == "platform":
        light = scaled(1.0 - sp.scale, 1.0 - sp.scale)
        r = sp.load_radius
        for m in sp.load_mass:
            for x, y in ((r, 0.0), (0.0, r), (-r, 0.0), (0.0, -r)):
                out.append(light.with_load(m, x, y, sp.load_inertia[0]))
    return out


def knot_torques(knots: np.ndarray, samples: int, rate: float, spacing: float) -> np.ndarray:
    """Torques (samples, 3) N m at t_k = k / rate, linear between knots (K, 3) at 0, spacing, 2 spacing, ..."""
    t = np.arange(samples) / rate
    tk = np.arange(len(knots)) * spacing
    return np.stack([np.interp(t, tk, knots[:, j]) for j in range(3)], axis=1)


def _experiment(spec: ExperimentSpec, torques: np.ndarray, noise: NoiseModel) -> Experiment:
    """A data-free experiment (zeros as measurements) on which to evaluate sensitivities."""
    n = len(torques) + 1
    U = np.vstack([torques, torques[-1:]])
    sig = {"a_x": noise.accel, "a_y": noise.accel, "omega_z": noise.gyro, "w_r": noise.enc_rate,
           "w_l": noise.enc_rate, "w_p": noise.enc_rate}
    return Experiment(spec.step, np.arange(n) / spec.rate, U, {c: np.zeros(n) for c in spec.channels},
                      {c: sig[c] for c in spec.channels}, np.zeros(12), fixture=spec.fixture)


def fisher_information(spec: ExperimentSpec, torques: np.ndarray, params: OtbotParams,
                       noise: NoiseModel | None = None) -> np.ndarray:
    """Fisher information (p, p) of the step's free parameters (``spec.free`` order, SI) for these torques."""
    e = _experiment(spec, torques, noise or paper_noise())
    model = OtbotModel()
    theta = params.as_array()
    idx = [list(model.names).index(n) for n in spec.free]
    z = theta[idx]
    sc = np.array([max(abs(v), TYPICAL_SCALE[n]) for v, n in zip(z, spec.free)])
    inf = np.full(len(z), np.inf)
    J = ResidualProblem(model, [e], spec.free, theta, sc, -inf, inf).jac(z, "central")
    return J.T @ J


def crb(spec: ExperimentSpec, torques: np.ndarray, params: OtbotParams, noise: NoiseModel | None = None) -> dict[str, float]:
    """Cramer-Rao bound (std) of each of the step's parameters for these torques."""
    F = fisher_information(spec, torques, params, noise)
    try:
        cov = np.linalg.inv(F)
    except np.linalg.LinAlgError:
        return {n: math.inf for n in spec.free}
    return {n: float(math.sqrt(max(cov[i, i], 0.0))) if cov[i, i] > 0 else math.inf for i, n in enumerate(spec.free)}


def _held(torques: np.ndarray) -> np.ndarray:
    """Torques per sample of a run (the last command repeats at the final sample)."""
    return np.vstack([torques, torques[-1:]])


def predicted_motion(spec: ExperimentSpec, torques: np.ndarray, params: OtbotParams) -> tuple[np.ndarray, np.ndarray]:
    """States q, qd (samples + 1, 6) of the step's fixture under the torques, from rest."""
    n = len(torques)
    X = rk4_zoh(np.zeros(12), np.ascontiguousarray(torques), np.zeros((n, 2)), 1.0 / spec.rate, 4,
                         params.as_array(), fixture_code(spec.fixture))
    return X[:, :6], X[:, 6:]


@dataclass
class DesignedExcitation:
    """A designed experiment: ``spec`` (with the torque ``profile``), its CRB and the paper's at equal duration."""

    step: str
    spec: ExperimentSpec
    knots: np.ndarray
    knot_spacing: float
    crb: dict[str, float]
    paper_crb: dict[str, float]
    margins: dict[str, float]        # largest fraction of each limit over the scenario robots
    paper_margins: dict[str, float]  # the same for the paper's excitation
    limits: ExperimentLimits
    design_params: dict[str, float]
    objective: float
    wall_time: float
    history: list[dict[str, Any]] = field(default_factory=list)

    @property
    def torques(self) -> np.ndarray:
        return self.spec.torques()

    def ratio(self) -> dict[str, float]:
        """CRB of the design / CRB of the paper's excitation, per parameter (< 1: better)."""
        return {n: self.crb[n] / self.paper_crb[n] for n in self.crb}

    def to_dict(self) -> dict[str, Any]:
        return {"step": self.step, "duration": self.spec.duration,
                "knot_spacing": self.knot_spacing, "knots": self.knots.tolist(),
                "crb": self.crb, "paper_crb": self.paper_crb, "crb_ratio": self.ratio(),
                "margins": self.margins, "paper_margins": self.paper_margins, "limits": self.limits.to_dict(),
                "wall_time": self.wall_time}


class _Problem:
    """Objective and constraints of one design (a function of the knot vector)."""

    def __init__(self, spec: ExperimentSpec, params: OtbotParams, limits: ExperimentLimits, spacing: float,
                 ref: dict[str, float], noise: NoiseModel, margin: float, scenarios: list[OtbotParams]):
        self.spec, self.params, self.limits, self.spacing = spec, params, limits, spacing
        self.margin, self.scenarios = margin, scenarios
        self.ref, self.noise = ref, noise
        self.n_knots = int(round(spec.duration / spacing)) + 1

    def torques(self, x: np.ndarray) -> np.ndarray:
        knots = x.reshape(self.n_knots, 3) * self.limits.torque
        return knot_torques(knots, self.spec.samples, self.spec.rate, self.spacing)

    def objective(self, x: np.ndarray) -> float:
        F = fisher_information(self.spec, self.torques(x), self.params, self.noise)
        try:
            cov = np.linalg.inv(F)
        except np.linalg.LinAlgError:
            return 1e6
        r = np.array([cov[i, i] / self.ref[n] ** 2 for i, n in enumerate(self.spec.free)])
        return float(np.mean(r)) if np.all(r > 0) else 1e6

    def constraints(self, x: np.ndarray) -> np.ndarray:
        """1 - margin - (peak of each limited quantity in each sample window) / limit, on every scenario robot
        (>= 0: within the limits)."""
        U = self.torques(x)
        out = []
        for robot in self.scenarios:
            q, qd = predicted_motion(self.spec, U, robot)
            fr = motion_fractions(q, qd, _held(U), self.limits)
            for k in ("wheel_speed", "pivot_speed", "platform_speed", "travel_radius"):
                v = fr[k]
                w = np.pad(v, (0, (-len(v)) % WINDOW), mode="edge").reshape(-1, WINDOW).max(axis=1)
                out.append(1.0 - self.margin - w)
        return np.concatenate(out)

    def worst_margins(self, U: np.ndarray) -> dict[str, float]:
        """Largest fraction of each limit over the scenario robots."""
        out: dict[str, float] = {}
        for robot in self.scenarios:
            q, qd = predicted_motion(self.spec, U, robot)
            for k, v in motion_margins(q, qd, _held(U), self.limits).items():
                out[k] = max(out.get(k, 0.0), v)
        return out


def paper_torques(step: str, duration: float | None = None, rate: float = 100.0) -> np.ndarray:
    """The paper's constant torques of a step for ``duration`` s (default the paper's)."""
    spec = PAPER_EXPERIMENTS[step]
    n = int(round((duration or spec.duration) * rate))
    return np.tile(np.asarray(spec.torque, dtype=float), (n, 1))


def design_excitation(step: str, params: OtbotParams, limits: ExperimentLimits | None = None,
                      duration: float | None = None, knot_spacing: float = 0.5,
                      starts: int = 2, seed: int = 0, maxiter: int = 150, noise: NoiseModel | None = None,
                      margin: float = MARGIN, spread: RobotSpread | None = None, robust: bool = True,
                      progress=None) -> DesignedExcitation:
    """Torques for the ``step`` experiment that minimise its Cramer-Rao bound within ``limits``.

    params: the robot at which to design (earlier steps' estimates; for the platform step a
    guess of the loaded platform); duration: s (default the paper's, so the comparison is at
    equal duration); knot_spacing: s between torque knots; margin: fraction of each limit kept free
    on the design model; spread, robust: keep to the limits on every robot of ``prior_scenarios``
    (robust, default: the design point is a guess, and a lighter robot goes faster) or on the
    design robot only. Raises ``IdentificationError`` when
    no start meets the limits.
    """
    t0 = time.perf_counter()
    if step not in DESIGNABLE:
        raise IdentificationError(f"designed excitation exists for the floor steps {', '.join(DESIGNABLE)}, not '{step}'")
    limits = limits or ExperimentLimits()
    noise = noise or paper_noise()
    base = PAPER_EXPERIMENTS[step]
    duration = float(duration or base.duration)
    if not (knot_spacing > 0 and duration / knot_spacing >= 1):
        raise IdentificationError(f"knot spacing {knot_spacing} s must be > 0 and at most the duration {duration} s")
    spec = dataclasses.replace(base, duration=duration)
    paper_u = paper_torques(step, duration, spec.rate)
    ref = crb(spec, paper_u, params, noise)
    if not 0 <= margin < 1:
        raise IdentificationError(f"margin must be a fraction in [0, 1), got {margin}")
    scenarios = prior_scenarios(step, params, spread) if robust else [params]
    prob = _Problem(spec, params, limits, knot_spacing, ref, noise, margin, scenarios)
    paper_margins = prob.worst_margins(paper_u)
    rng = np.random.default_rng(seed)
    x_paper = np.tile(np.asarray(base.torque) / max(np.max(np.abs(base.torque)), limits.torque), (prob.n_knots, 1))
    inits = [x_paper.ravel()] + [rng.uniform(-0.6, 0.6, prob.n_knots * 3) for _ in range(max(0, starts - 1))]
    best = None
    history = []
    for i, x0 in enumerate(inits):
        # shrink a start until its motion meets the limits (SLSQP needs a feasible neighbourhood)
        for _ in range(20):
            if np.all(prob.constraints(x0) >= 0):
                break
            x0 = 0.8 * x0
        sol = minimize(prob.objective, x0, method="SLSQP", bounds=[(-1.0, 1.0)] * len(x0),
                       constraints=[{"type": "ineq", "fun": prob.constraints}],
                       options={"maxiter": maxiter, "ftol": 1e-6})
        x, worst = sol.x, float(np.min(prob.constraints(sol.x)))
        for _ in range(50):  # SLSQP may end just outside a limit: shrink the torques until inside
            if worst >= 0:
                break
            x = 0.99 * x
            worst = float(np.min(prob.constraints(x)))
        feasible = worst >= 0
        fun = prob.objective(x)
        history.append({"start": "paper" if i == 0 else f"random {i}", "objective": fun, "feasible": feasible,
                        "worst_margin": worst, "iterations": int(sol.nit), "message": str(sol.message)})
        if progress:
            progress(f"[design] {step} start {i + 1}/{len(inits)}: objective {fun:.4g}, {sol.nit} iterations"
                     + ("" if feasible else f" (violates a limit by {-worst:.3g})"))
        if feasible and (best is None or fun < best[0]):
            best = (fun, x)
    if best is None:
        raise IdentificationError(f"no {step} excitation within the limits was found: {limits.to_dict()}")
    x = best[1]
    U = prob.torques(x)
    margins = prob.worst_margins(U)
    bad = violations(margins, limits, tol=1e-3)
    if bad:
        raise IdentificationError(f"designed {step} excitation violates its limits: {'; '.join(bad)}")
    designed = dataclasses.replace(spec, torque=tuple(float(v) for v in U[0]), profile=U,
                                   description=f"{base.description}, designed excitation")
    return DesignedExcitation(step=step, spec=designed, knots=x.reshape(-1, 3) * limits.torque,
                              knot_spacing=knot_spacing, crb=crb(spec, U, params, noise), paper_crb=ref,
                              margins=margins, paper_margins=paper_margins, limits=limits,
                              design_params=params.values(), objective=best[0],
                              wall_time=time.perf_counter() - t0, history=history)
