"""The paper's identification experiments (§4.3) as defaults: fixture, excitation, sensors, guesses.

=========  ========  ====================  ========  ====================  ==================
step       fixture   torque (N m)          duration  outputs (100 Hz)      estimates
=========  ========  ====================  ========  ====================  ==================
wheel      stand     (6, 0, 0)             0.5 s     w_r, sigma 0.01 rad/s I_a, b_w
pivot      locked    (0, 0, 6)             1.5 s     w_p, sigma 0.01 rad/s I_p0, b_p
chassis    floor     (6, -10, 6)           3 s       a_x, a_y, omega_z     m_c, I_c, x_B, y_B
platform   floor     (6, -10, 6)           1 s       a_x, a_y, omega_z     m_p, I_p, x_F, y_F
=========  ========  ====================  ========  ====================  ==================

IMU noise sigma = 13.73e-3 (paper Eq. chap4IMUnoise), encoder-rate noise 0.01 rad/s.
Initial guesses: 50 % of nominal in step 1, (54.57, 0.65, -0.07, 0.25) in step 2,
and in step 3 a deviation d from the truth: a load of d * 500 kg guessed d * 0.45 m
from the true centre of mass (45 degrees), I_p by Steiner. (The paper's 25 % guess
(146.95 kg, 5.94 kg m^2, 0.11 m, 0.11 m) moved each coordinate by d * 0.45 m, which
at 100 % would put the centre of mass 0.64 m out, off the 0.5 m platform; the
paper's exact 25 % guess is ``PAPER_PLATFORM_GUESS``.)
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from otbot_hw.params import OtbotParams
from otbot_hw.sensors import NoiseModel, imu_sigma

STEPS: tuple[str, ...] = ("wheel", "pivot", "chassis", "platform")
MAX_LOAD = 500.0  # kg, heaviest load the sweep considers (paper §4.3.3)
MAX_OFFSET = 0.45  # m, farthest load position from the pivot (paper §4.3.3)

#: The paper's Table 7 initial guess (25 % deviation around the unloaded platform).
PAPER_PLATFORM_GUESS = {"m_p": 146.95, "I_p": 2.22 + 146.95 * 2 * 0.1125 ** 2, "x_F": 0.1125, "y_F": 0.1125}


def paper_noise() -> NoiseModel:
    """IMU sigma 13.73e-3 on every IMU channel and encoder rates 0.01 rad/s."""
    s = imu_sigma()
    return NoiseModel(accel=s, gyro=s, enc_rate=0.01)


@dataclass(frozen=True)
class ExperimentSpec:
    """One identification experiment: constant torques on a fixture, what is measured and estimated.

    ``report`` maps model parameter names to the paper's symbols where they differ
    (the locked-wheel pivot test estimates the unloaded platform's I_p as I_p0).
    """

    step: str
    fixture: str
    torque: tuple[float, float, float]
    duration: float
    channels: tuple[str, ...]
    free: tuple[str, ...]
    rate: float = 100.0
    report: dict[str, str] = field(default_factory=dict)
    description: str = ""
    #: a torque sequence (samples, 3) N m replacing the constant ``torque`` (a designed excitation)
    profile: np.ndarray | None = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        if self.profile is not None and np.shape(self.profile) != (self.samples, 3):
            raise ValueError(f"{self.step}: torque profile must have shape ({self.samples}, 3) for "
                             f"{self.duration} s at {self.rate} Hz, got {np.shape(self.profile)}")

    @property
    def samples(self) -> int:
        return int(round(self.duration * self.rate))

    def torques(self) -> np.ndarray:
        """(N, 3) N m held for 1/rate s each."""
        if self.profile is not None:
            return np.array(self.profile, dtype=float)
        return np.tile(np.asarray(self.torque, dtype=float), (self.samples, 1))

    def symbol(self, name: str) -> str:
        return self.report.get(name, name)


PAPER_EXPERIMENTS: dict[str, ExperimentSpec] = {
    "wheel": ExperimentSpec("wheel", "stand", (6.0, 0.0, 0.0), 0.5, ("w_r",), ("I_a", "b_w"),
                            description="right wheel spinning freely, robot on a stand"),
    "pivot": ExperimentSpec("pivot", "locked", (0.0, 0.0, 6.0), 1.5, ("w_p",), ("I_p", "b_p"),
                            report={"I_p": "I_p0"},
                            description="unloaded platform turning, both wheels locked"),
    "chassis": ExperimentSpec("chassis", "floor", (6.0, -10.0, 6.0), 3.0, ("a_x", "a_y", "omega_z"),
                              ("m_c", "I_c", "x_B", "y_B"), description="unloaded robot on the floor"),
    "platform": ExperimentSpec("platform", "floor", (6.0, -10.0, 6.0), 1.0, ("a_x", "a_y", "omega_z"),
                               ("m_p", "I_p", "x_F", "y_F"), description="loaded robot on the floor"),
}


def simulate_experiment(step: str, truth: OtbotParams, seed: int | None = 0, noise: NoiseModel | None = None,
                        spec: ExperimentSpec | None = None):
    """A simulated ``Recording`` of a step's experiment on a robot with parameters ``truth``."""
    from otbot_hw.simulation.runs import simulated_recording

    spec = spec or PAPER_EXPERIMENTS[step]
    return simulated_recording(truth, spec.torques(), 1.0 / spec.rate, noise or paper_noise(), seed=seed,
                               fixture=spec.fixture,
                               extra_metadata={"experiment": f"{spec.step}: {spec.description}"})


def paper_guess(step: str, nominal: OtbotParams) -> dict[str, float]:
    """The paper's initial guess for a step (step 3: the 25 % deviation of Table 7)."""
    if step == "wheel":
        return {"I_a": 0.5 * nominal.I_a, "b_w": 0.5 * nominal.b_w}
    if step == "pivot":
        return {"I_p": 0.5 * nominal.I_p, "b_p": 0.5 * nominal.b_p}
    if step == "chassis":
        return {"m_c": 54.57, "I_c": 0.65, "x_B": -0.07, "y_B": 0.25}
    if step == "platform":
        return deviation_guess("platform", nominal, 0.25)
    raise ValueError(f"unknown step '{step}' (known: {', '.join(STEPS)})")


def deviation_guess(step: str, truth: OtbotParams, deviation: float, angle: float = math.pi / 4) -> dict[str, float]:
    """Initial guess ``deviation`` (fraction, 0.25 = 25 %) away from ``truth``.

    Platform: a load of deviation * 500 kg guessed deviation * 0.45 m from the true
    centre of mass (direction ``angle`` rad in B'', kept inside the platform), I_p by
    Steiner. Other steps: positive parameters scaled by (1 - deviation) (50 % = the
    paper's step-1 guess), centre-of-mass coordinates moved by deviation * 0.45 m.
    """
    if not (math.isfinite(deviation) and deviation >= 0):
        raise ValueError(f"deviation must be a finite fraction >= 0, got {deviation}")
    spec = PAPER_EXPERIMENTS[step]
    if step == "platform":
        dist = deviation * MAX_OFFSET
        x = truth.x_F + dist * math.cos(angle)
        y = truth.y_F + dist * math.sin(angle)
        lim = 0.98 * truth.radius
        rho = math.hypot(x, y)
        if rho > lim:
            x, y = x * lim / rho, y * lim / rho
        m = truth.m_p + deviation * MAX_LOAD
        shift2 = (x - truth.x_F) ** 2 + (y - truth.y_F) ** 2
        return {"m_p": m, "I_p": truth.I_p + m * shift2, "x_F": x, "y_F": y}
    out = {}
    for n in spec.free:
        v = getattr(truth, n)
        if n in ("x_B", "y_B"):
            out[n] = v + deviation * MAX_OFFSET / math.sqrt(2)
        else:
            out[n] = max(v * (1.0 - deviation), 1e-3 * v)
    return out
