"""Sensor models of Otbot: joint encoders and the platform IMU (paper §4.3).

* Encoders: joint angles phi = (phi_r, phi_l, phi_p) (rad) and rates (rad/s),
  optionally quantized to whole counts of an encoder with ``counts_per_rev``
  counts per joint revolution.
* IMU at the pivot P, fixed to the platform: specific force (m/s^2) and angular
  rate (rad/s) in the platform frame B'' (x along 1'', y along 2'', z up). On
  flat ground the horizontal specific force is the pivot acceleration
  R(alpha)^T (x_dd, y_dd); z reads +g; the rate is (0, 0, alpha_dot).
* Gaussian white noise, seeded; the IMU's sigma follows sigma = ND * sqrt(SR)
  (ND noise density in m s^-2 Hz^-1/2, SR sample rate in Hz).

The noise-free readings come from the one sensor model, ``otbot_hw.model.sensor_model`` (the paper's
model is the extended model with every effect at zero). All functions are pure: the random generator
is passed in.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from otbot_hw.interrupts import deferred_sigint
from otbot_hw.model.constants import GRAVITY  # noqa: F401  (m/s^2; the IMU's z reading, re-exported)
from otbot_hw.model.effect_catalog import effect_vector
from otbot_hw.model.effect_physics import ext_sample_accelerations
from otbot_hw.model.fixtures import fixture_code
from otbot_hw.model.sensor_model import imu_from_motion, sensor_samples
from otbot_hw.params import OtbotParams

_PAPER = effect_vector()

#: Paper §4.3.2: noise density of the IMU and its sample rate.
PAPER_NOISE_DENSITY = 1.37e-3  # m s^-2 Hz^-1/2
PAPER_SAMPLE_RATE = 100.0  # Hz


def imu_sigma(noise_density: float = PAPER_NOISE_DENSITY, sample_rate: float = PAPER_SAMPLE_RATE) -> float:
    """sigma = ND * sqrt(SR) (paper Eq. chap4IMUnoise): 13.7e-3 for the paper's values."""
    return noise_density * np.sqrt(sample_rate)


@dataclass(frozen=True)
class NoiseModel:
    """Standard deviations of white sensor noise (0 = noiseless) and encoder resolution.

    accel (m/s^2) and gyro (rad/s) for the IMU, enc_angle (rad) and enc_rate (rad/s)
    for the encoders; ``counts_per_rev`` quantizes encoder angles (None: no quantization).
    """

    accel: float = 0.0
    gyro: float = 0.0
    enc_angle: float = 0.0
    enc_rate: float = 0.0
    counts_per_rev: int | None = None

    @classmethod
    def paper(cls) -> "NoiseModel":
        """The paper's levels: IMU sigma = ND sqrt(SR) = 13.7e-3 (printed 13.73e-3) on every
        channel, encoder rate noise 0.01 rad/s."""
        s = imu_sigma()
        return cls(accel=s, gyro=s, enc_rate=0.01)

    def to_dict(self) -> dict:
        return asdict(self)


def accelerations(x: np.ndarray, u: np.ndarray, f: np.ndarray, params: OtbotParams,
                  fixture: str = "floor") -> np.ndarray:
    """q_ddot (N, 6) for each sample of states x (N, 12), torques u (N, 3), forces f (N, 2)."""
    return ext_sample_accelerations(*(np.ascontiguousarray(a, dtype=float) for a in (x, u, f)), _PAPER,
                                    params.as_array(), fixture_code(fixture))


def imu_ideal(x: np.ndarray, qdd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Noiseless IMU: specific force (N, 3) m/s^2 and rate (N, 3) rad/s in B''."""
    return imu_from_motion(x[:, 2], x[:, 8], qdd[:, 0], qdd[:, 1], qdd[:, 2], _PAPER)


def quantize(phi: np.ndarray, counts_per_rev: int | None) -> np.ndarray:
    """Angles (rad) floored to whole counts of an encoder with ``counts_per_rev`` counts per revolution."""
    if not counts_per_rev:
        return phi
    step = 2 * np.pi / counts_per_rev
    return np.floor(phi / step + 1e-9) * step


def encoders_ideal(x: np.ndarray, counts_per_rev: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Joint angles (N, 3) rad and rates (N, 3) rad/s, angles floored to whole counts if given."""
    return quantize(x[:, 3:6].copy(), counts_per_rev), x[:, 9:12].copy()


@dataclass
class SensorReadings:
    """Sampled sensor outputs: encoder angles/rates (N, 3), IMU accel/gyro (N, 3) in B''."""

    joint_pos: np.ndarray
    joint_vel: np.ndarray
    imu_accel: np.ndarray
    imu_gyro: np.ndarray


#: Samples per compiled call of ``measure``'s sensor model (about 0.2 s each).
MEASURE_BLOCK = 200_000


def measure(x: np.ndarray, u: np.ndarray, f: np.ndarray, params: OtbotParams, noise: NoiseModel,
            rng: np.random.Generator | None = None, fixture: str = "floor") -> SensorReadings:
    """Sensor readings at each sample of a simulated run (states x, held torques u and forces f)."""
    rng = rng if rng is not None else np.random.default_rng(0)
    n = len(x)
    x, u, f = (np.ascontiguousarray(a, dtype=float) for a in (x, u, f))
    prm, code = params.as_array(), fixture_code(fixture)
    # in blocks of rows (each row's readings are its own): Ctrl-C is honoured between the compiled calls
    parts = []
    with deferred_sigint() as pending:  # Ctrl-C: KeyboardInterrupt after the block, not inside numba
        for a in range(0, max(n, 1), MEASURE_BLOCK):
            b = a + MEASURE_BLOCK
            parts.append(sensor_samples(x[a:b], np.zeros((len(x[a:b]), 2)), u[a:b], f[a:b], u[a:b], f[a:b], None, None,
                                        _PAPER, prm, code))
            pending.check()
    phi, phid, acc, gyro = (parts[0][i] if len(parts) == 1 else np.concatenate([p[i] for p in parts])
                            for i in (0, 1, 2, 4))
    phi = quantize(phi, noise.counts_per_rev)
    acc = acc + noise.accel * rng.standard_normal((n, 3))
    gyro = gyro + noise.gyro * rng.standard_normal((n, 3))
    phi = phi + noise.enc_angle * rng.standard_normal((n, 3))
    phid = phid + noise.enc_rate * rng.standard_normal((n, 3))
    return SensorReadings(joint_pos=phi, joint_vel=phid, imu_accel=acc, imu_gyro=gyro)
