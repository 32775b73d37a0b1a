"""What a bench step applies: the excitation (the paper's or a designed one), the probe, the brake.

* ``step_spec``: the step's ``ExperimentSpec``: the paper's constant torques (§4.3), or for the
  floor steps (chassis, platform) the designed excitation of ``identification.design`` (torques
  minimising the Cramer-Rao bound within the ``ExperimentLimits`` on the prior's corner robots).
  Designing takes minutes, so a design is kept as JSON and found again by its key (step, design
  parameters, limits, knot spacing): in the session folder (``designs/``), in the shipped designs
  (``config/excitation/``: the nominal robot and the default limits) and in the user's cache
  (``$XDG_CACHE_HOME/otbot/excitation``, default ``~/.cache``).
* ``ExcitationController``: the loop runner's controller of a step's run: the torque rows, one per
  period, then a brake that brings every joint to rest.
* ``brake_gains``: the brake is joint-rate damping u = -K phi_dot (scaled into the torque limit), K =
  c / T * A^+ with A = d(phi_ddot)/du the robot's joint-space acceleration per torque at rest on the
  fixture (``compiled.derivative``) and T the period: each joint's rate falls by c per period
  (c = 0.2; with the one-period delay of the loop the closed loop z^2 - z + c has real roots 0.72,
  0.28, and stays stable for inertias up to about 4 times smaller than modelled).
* ``probe_torques``: the small torque doublets (+tau, then -tau) the fixture checks apply.
* ``predicted_margins``: the step's predicted motion (the best-known robot) as fractions of its limits.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from pathlib import Path
from typing import Callable

import numpy as np

from otbot_hw.experiment_limits import ExperimentLimits, motion_margins
from otbot_hw.identification.experiments import PAPER_EXPERIMENTS, ExperimentSpec
from otbot_hw.model import compiled
from otbot_hw.model.fixtures import fixture_code
from otbot_hw.params import OtbotParams
from otbot_hw.runtime.controllers import ControlStep

EXCITATIONS = ("paper", "designed")
DESIGNABLE = ("chassis", "platform")
#: knot spacing (s) of the designed torques per step (the benchmark's choice, docs/identification.md)
KNOT_SPACING = {"chassis": 0.5, "platform": 0.25}
SHIPPED_DESIGNS = Path(__file__).resolve().parents[3] / "config" / "excitation"
BRAKE_FRACTION = 0.2
BRAKE_FULL = 0.3  # fraction of the brake at full gain, before it starts averaging
#: torque (N m) and duration (s) of each half of a probe doublet, per fixture check
PROBE = {"stand": ((1.0, 0.0, 0.0), 0.3), "locked": ((1.0, 1.0, 0.0), 0.3), "floor": ((2.0, 2.0, 0.0), 0.3)}


def user_cache() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "otbot" / "excitation"


def design_key(step: str, params: OtbotParams, limits: ExperimentLimits) -> dict:
    """What a design depends on (the cache key): step, design parameters, limits, knot spacing, duration."""
    return {"step": step, "params": {k: round(float(v), 12) for k, v in params.values().items()},
            "limits": limits.to_dict(), "knot_spacing": KNOT_SPACING[step],
            "duration": PAPER_EXPERIMENTS[step].duration}


def _key_name(key: dict) -> str:
    return f"{key['step']}-{hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]}.json"


def designed_spec(step: str, params: OtbotParams, limits: ExperimentLimits, folders: list[Path],
                  progress: Callable[[str], None] | None = None) -> tuple[ExperimentSpec, dict]:
    """The designed excitation of ``step`` for ``params`` within ``limits``: (spec, record).

    Looked up in ``folders``, then the shipped designs and the user cache; else designed
    (``identification.design.design_excitation``, minutes) and written to the first folder and the
    user cache. ``record``: the design's JSON (torques, Cramer-Rao bounds against the paper's
    excitation at equal duration, margins), with ``source`` where it came from."""
    key = design_key(step, params, limits)
    name = _key_name(key)
    for folder in [*folders, SHIPPED_DESIGNS, user_cache()]:
        path = Path(folder) / name
        if path.is_file():
            try:
                rec = json.loads(path.read_text())
            except (OSError, ValueError):
                continue
            if rec.get("key") == key:
                rec["source"] = str(path)
                return _spec(step, rec), rec
    from otbot_hw.identification.design import design_excitation

    if progress:
        progress(f"designing the {step} excitation (A-optimal within the limits on the prior's corner robots; "
                 "a few minutes, kept for next time)")
    d = design_excitation(step, params, limits, knot_spacing=KNOT_SPACING[step], progress=progress)
    rec = {"key": key, **d.to_dict(), "torques": d.torques.tolist()}
    for folder in (folders[:1] + [user_cache()]):
        try:
            Path(folder).mkdir(parents=True, exist_ok=True)
            (Path(folder) / name).write_text(json.dumps(rec))
        except OSError:
            pass
    rec["source"] = "designed now"
    return _spec(step, rec), rec


def _spec(step: str, rec: dict) -> ExperimentSpec:
    U = np.asarray(rec["torques"], dtype=float)
    base = PAPER_EXPERIMENTS[step]
    return dataclasses.replace(base, torque=tuple(float(v) for v in U[0]), profile=U,
                               description=f"{base.description}, designed excitation")


def step_spec(step: str, excitation: str, params: OtbotParams, limits: ExperimentLimits, folders: list[Path],
              progress=None) -> tuple[ExperimentSpec, dict | None]:
    """(the step's experiment, the design record or None for the paper's)."""
    if excitation == "designed" and step in DESIGNABLE:
        return designed_spec(step, params, limits, folders, progress)
    return PAPER_EXPERIMENTS[step], None


def joint_acceleration_per_torque(params: OtbotParams, fixture: str) -> np.ndarray:
    """A (3, 3): d(phi_ddot)/du at rest on ``fixture`` (rad/s^2 per N m)."""
    x = np.zeros(12)
    prm, code, gen, f = params.as_array(), fixture_code(fixture), np.zeros(6), np.zeros(2)
    base = compiled.derivative(x, np.zeros(3), f, gen, prm, code)[9:12]
    return np.column_stack([compiled.derivative(x, np.eye(3)[j], f, gen, prm, code)[9:12] - base
                            for j in range(3)])


def brake_gains(params: OtbotParams, fixture: str | None, period: float) -> np.ndarray:
    """K (3, 3) N m s/rad of the brake on ``fixture``; ``None``: the fixture is not verified yet,
    gains safe on every fixture (each joint's smallest gain)."""
    if fixture is None:
        ks = [brake_gains(params, fx, period) for fx in ("floor", "stand", "locked")]
        d = np.min([np.where(np.diag(k) > 0, np.diag(k), np.inf) for k in ks], axis=0)
        return np.diag(np.where(np.isfinite(d), d, 0.0))
    A = joint_acceleration_per_torque(params, fixture)
    return BRAKE_FRACTION / period * np.linalg.pinv(A, rcond=1e-9)


class ExcitationController:
    """Torque rows (N, 3) N m, row k held on sample k (from the first command on), then the brake
    u = -g K phi_dot on the latest joint rates, scaled down as a whole to at most ``brake_limit`` N m
    (clamping each motor alone would turn the torque and could speed a joint up).

    The brake's gain factor g is 1 for the first ``BRAKE_FULL`` of ``brake_samples`` (the motion
    dies), then falls as 1 / (1 + c j) over the brake samples j after that: each period then takes
    the fraction c / (1 + c j) of the measured rate away, which averages the rate noise the brake
    feeds back (stochastic approximation): the joints are left at a rate std of about
    sigma / sqrt(2 j) instead of sigma sqrt(c / 2) (0.003 rad/s for 0.01 rad/s of noise: a start
    that slow moves the chassis step's estimates by about one std)."""

    def __init__(self, torques, period: float, gains: np.ndarray, brake_limit: float, brake_samples: int = 0):
        self.torques = np.asarray(torques, dtype=float).reshape(-1, 3)
        self.period = float(period)
        self.gains = np.asarray(gains, dtype=float)
        self.limit = float(brake_limit)
        self.brake_samples = int(brake_samples)
        self.origin: float | None = None

    def gain(self, j: int) -> float:
        """Brake gain factor at brake sample j."""
        j0 = BRAKE_FULL * self.brake_samples
        if self.brake_samples <= 0 or j <= j0:
            return 1.0
        return 1.0 / (1.0 + BRAKE_FRACTION * (j - j0))

    def update(self, t: float, feedback, snapshot) -> ControlStep:
        if self.origin is None:
            self.origin = float(t)
        k = int(round((t - self.origin) / self.period))
        if k < len(self.torques):
            return ControlStep(self.torques[k].copy())
        w = np.zeros(3) if snapshot is None else np.asarray(snapshot.joint_vel, dtype=float)
        u = -self.gain(k - len(self.torques)) * (self.gains @ w)
        peak = float(np.max(np.abs(u)))
        if peak > self.limit:  # scaled as a whole: the torques keep their direction (every rate falls)
            u *= self.limit / peak
        return ControlStep(u)


def probe_torques(kind: str, period: float) -> np.ndarray:
    """The doublet of the ``kind`` fixture check: +tau for a half, -tau for the other, (N, 3) N m."""
    tau, half = PROBE[kind]
    n = int(round(half / period))
    return np.vstack([np.tile(tau, (n, 1)), np.tile(np.negative(tau), (n, 1))])


def predicted_motion(spec: ExperimentSpec, params: OtbotParams) -> tuple[np.ndarray, np.ndarray]:
    """States q, qd (N + 1, 6) of the step's run on its fixture, from rest, for ``params``."""
    from otbot_hw.identification.design import predicted_motion as motion

    return motion(spec, spec.torques(), params)


def predicted_margins(spec: ExperimentSpec, params: OtbotParams, limits: ExperimentLimits,
                      max_wheel_rate: float | None, max_pivot_rate: float | None) -> dict[str, tuple[float, float]]:
    """Peak of each limited quantity of the step's predicted run and its limit: {name: (peak, limit)}.

    Floor: torque, wheel speed, pivot speed, platform speed, travel with the stop (``ExperimentLimits``);
    stand / locked: torque and the joint rates against the supervisor's limits (the wheels spin
    freely on the stand)."""
    q, qd = predicted_motion(spec, params)
    U = spec.torques()
    held = np.vstack([U, U[-1:]])
    if spec.fixture == "floor":
        fr = motion_margins(q, qd, held, limits)
        return {k: (fr[k] * getattr(limits, k), getattr(limits, k)) for k in fr}
    out = {"torque": (float(np.max(np.abs(U))), limits.torque)}
    if spec.fixture == "stand" and max_wheel_rate is not None:
        out["wheel_speed"] = (float(np.max(np.abs(qd[:, 3:5]))), max_wheel_rate)
    if max_pivot_rate is not None:
        out["pivot_speed"] = (float(np.max(np.abs(qd[:, 5]))), max_pivot_rate)
    return out
