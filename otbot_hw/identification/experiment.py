"""One identification experiment: commanded torques, measured outputs, initial state, noise levels.

Built from a recording in the project's format (``Experiment.from_recording``),
using only what a real robot logs: the commanded torques and the sensor topics.
Ground truth, when a simulated recording carries it, is never used for fitting
(``truth_params`` keeps the simulated robot's parameters for reporting only).

Initial state x0 (12,) = (q, q_dot):
  * q0 = (0, 0, 0, phi_r, phi_l, phi_p) with the encoder angles of the first
    sample (zeros without encoders). The outputs do not depend on where the pivot
    is or which way the platform points (the dynamics are invariant to planar
    rigid motions and the IMU reads in B''), so x = y = alpha = 0 loses nothing.
  * q_dot0: at rest (zeros) when the first sample's encoder rates are all below
    ``rest_threshold`` (default 0.05 rad/s, five times the paper's encoder noise)
    or when there are no encoders; otherwise those rates mapped through the
    kinematics of the fixture (floor: q_dot = Delta(q) phi_dot). The velocity is
    not refined by the fit (smoothing over the first samples would be biased by the
    fast start of a free wheel): a run that starts moving is fitted with the encoder
    noise of one sample in x0; recordings that start at rest avoid it.

Noise per channel (sigma, same unit as the channel), used as residual weights:
given explicitly > the recording's ``noise`` metadata > the data-driven noise
floor 1.4826 MAD(fourth differences) / sqrt(70), which measures white sensor noise
on any smooth signal sampled fast enough.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from otbot_hw.identification.errors import IdentificationError
from otbot_hw.identification.model import CHANNELS
from otbot_hw.model.fixtures import FIXTURES, fixture_code
from otbot_hw.params import OtbotParams, ParameterError

#: channel -> (recording attribute, column, topic, noise-metadata key)
CHANNEL_SOURCES: dict[str, tuple[str, int, str, str]] = {
    "a_x": ("imu_accel", 0, "/otbot/imu", "accel"),
    "a_y": ("imu_accel", 1, "/otbot/imu", "accel"),
    "omega_z": ("imu_gyro", 2, "/otbot/imu", "gyro"),
    "w_r": ("joint_vel", 0, "/otbot/joints", "enc_rate"),
    "w_l": ("joint_vel", 1, "/otbot/joints", "enc_rate"),
    "w_p": ("joint_vel", 2, "/otbot/joints", "enc_rate"),
    "phi_r": ("joint_pos", 0, "/otbot/joints", "enc_angle"),
    "phi_l": ("joint_pos", 1, "/otbot/joints", "enc_angle"),
    "phi_p": ("joint_pos", 2, "/otbot/joints", "enc_angle"),
}

MIN_SAMPLES = 10
REST_THRESHOLD = 0.05  # rad/s
MAX_JITTER = 0.01  # largest allowed relative deviation of a sample interval from the period


def noise_floor(y: np.ndarray) -> float:
    """White-noise sigma of a smooth signal from its fourth differences (robust MAD estimate).

    The fourth difference of white noise has variance 70 sigma^2, while that of a
    signal sampled well above its bandwidth is nearly zero; the median absolute
    deviation ignores the few samples next to steps.
    """
    d4 = np.diff(np.asarray(y, dtype=float), 4)
    if len(d4) < 5:
        return float("nan")
    mad = np.median(np.abs(d4 - np.median(d4)))
    return float(1.4826 * mad / math.sqrt(70.0))


@dataclass
class Experiment:
    """Data of one run, ready for the fitter.

    t (n,) s; torque (n, 3) N m, command u_k held on [t_k, t_k+1); forces (n, 2) N
    known pivot forces (zeros for a real run); measured {channel: (n,)};
    sigma {channel: noise std}; x0 (12,); fixture floor/stand/locked.
    """

    name: str
    t: np.ndarray
    torque: np.ndarray
    measured: dict[str, np.ndarray]
    sigma: dict[str, float]
    x0: np.ndarray
    fixture: str = "floor"
    forces: np.ndarray | None = None
    substeps: int = 0  # RK4 steps per interval; 0: chosen by the fitter from the noise level
    auto_substeps: bool = False
    truth_params: OtbotParams | None = None
    sigma_source: dict[str, str] = field(default_factory=dict)
    noise_floor: dict[str, float] = field(default_factory=dict)
    metadata: dict[str, Any] = field(default_factory=dict)
    #: summary of the motion for diagnostics: pivot_range (peak-to-peak of the pivot encoder
    #: angle phi_p, rad, 0 when not measured) and moved (largest peak-to-peak of a fitted channel in units of 10 sigma)
    motion: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        from otbot_hw.simulation.simulator import default_substeps

        self.t = np.asarray(self.t, dtype=float)
        self.torque = np.ascontiguousarray(self.torque, dtype=float)
        n = len(self.t)
        if self.forces is None:
            self.forces = np.zeros((n, 2))
        self.forces = np.ascontiguousarray(self.forces, dtype=float)
        self.x0 = np.ascontiguousarray(self.x0, dtype=float)
        if self.fixture not in FIXTURES:
            raise IdentificationError(f"{self.name}: unknown fixture '{self.fixture}' (known: {', '.join(FIXTURES)})")
        if not self.substeps:
            # RK4 steps per sample interval: the simulator's safe default until the fitter
            # tunes it to the noise (``residual_problem.tune_substeps``)
            self.substeps = default_substeps(self.dt, self.fixture)
            self.auto_substeps = True
        for c in self.measured:
            if c not in CHANNELS:
                raise IdentificationError(f"{self.name}: unknown channel '{c}' (known: {', '.join(CHANNELS)})")
        if not self.noise_floor:
            self.noise_floor = {c: noise_floor(y) for c, y in self.measured.items()}
        if "moved" not in self.motion:
            self.motion["moved"] = max((float(np.ptp(y)) / (10 * self.sigma[c]) for c, y in self.measured.items()),
                                       default=0.0)

    @property
    def dt(self) -> float:
        return float((self.t[-1] - self.t[0]) / (len(self.t) - 1))

    @property
    def fixture_code(self) -> int:
        return fixture_code(self.fixture)

    @property
    def channels(self) -> tuple[str, ...]:
        return tuple(self.measured)

    def __len__(self) -> int:
        return len(self.t)

    # ------------------------------------------------------------------
    @classmethod
    def from_recording(cls, rec, channels: Sequence[str], name: str = "recording", fixture: str | None = None,
                       t_max: float | None = None, sigma: Mapping[str, float] | None = None,
                       x0: np.ndarray | None = None, rest_threshold: float = REST_THRESHOLD,
                       geometry: OtbotParams | None = None) -> "Experiment":
        """Check a ``Recording`` and extract the channels to fit.

        ``t_max`` (s) keeps only samples with t - t_0 <= t_max; ``fixture`` defaults to
        the recording's metadata (else floor); ``geometry`` (l1, l2, r) maps the first
        encoder rates to q_dot when the run does not start at rest.
        Raises ``IdentificationError`` naming the problem.
        """
        t = np.asarray(rec.t, dtype=float)
        torque = np.asarray(rec.torque, dtype=float)
        if t_max is not None:
            keep = t - t[0] <= t_max + 1e-9
            t, torque = t[keep], torque[keep]
        else:
            keep = slice(None)
        n = len(t)
        if n < MIN_SAMPLES:
            raise IdentificationError(f"{name}: recording too short: {n} samples, need at least {MIN_SAMPLES}")
        bad_t = ~np.isfinite(t)
        if bad_t.any():
            raise IdentificationError(f"{name}: sample time is NaN/inf at sample {int(np.argmax(bad_t))}")
        steps = np.diff(t)
        if np.any(steps <= 0):
            raise IdentificationError(f"{name}: sample times must increase (sample {int(np.argmax(steps <= 0)) + 1})")
        dt = float(np.median(steps))
        jitter = float(np.max(np.abs(steps - dt)) / dt)
        if jitter > MAX_JITTER:
            raise IdentificationError(
                f"{name}: sample intervals vary by {100 * jitter:.1f} % of the period {dt:.4g} s; the fitter "
                f"holds commands on a uniform grid (at most {100 * MAX_JITTER:.0f} %): resample the recording first")
        bad = ~np.isfinite(torque)
        if bad.any():
            k, j = np.argwhere(bad)[0]
            raise IdentificationError(f"{name}: torque[{['tau_r', 'tau_l', 'tau_p'][j]}] is NaN/inf at sample {k}")
        if np.all(np.abs(torque) < 1e-9):
            raise IdentificationError(f"{name}: no excitation: every commanded torque is zero, the robot was never driven")
        measured: dict[str, np.ndarray] = {}
        for c in channels:
            if c not in CHANNEL_SOURCES:
                raise IdentificationError(f"unknown channel '{c}' (known: {', '.join(CHANNEL_SOURCES)})")
            attr, col, topic, _ = CHANNEL_SOURCES[c]
            arr = getattr(rec, attr)
            if arr is None:
                raise IdentificationError(f"{name}: channel {c} needs topic {topic}, which the recording lacks")
            y = np.asarray(arr, dtype=float)[keep, col]
            bad = ~np.isfinite(y)
            if bad.any():
                raise IdentificationError(f"{name}: channel {c} is NaN/inf at sample {int(np.argmax(bad))} "
                                          f"(t = {t[int(np.argmax(bad))]:.4g} s)")
            measured[c] = y.copy()
        meta = dict(getattr(rec, "metadata", {}) or {})
        fx = fixture or meta.get("fixture", "floor")
        if fx not in FIXTURES:
            raise IdentificationError(f"{name}: unknown fixture '{fx}' (known: {', '.join(FIXTURES)})")
        floors = {c: noise_floor(y) for c, y in measured.items()}
        sig: dict[str, float] = {}
        src: dict[str, str] = {}
        noise_meta = meta.get("noise") if isinstance(meta.get("noise"), Mapping) else {}
        for c, y in measured.items():
            given = (sigma or {}).get(c)
            meta_val = noise_meta.get(CHANNEL_SOURCES[c][3]) if noise_meta else None
            if given is not None:
                sig[c], src[c] = float(given), "given"
            elif isinstance(meta_val, (int, float)) and meta_val > 0:
                sig[c], src[c] = float(meta_val), "metadata"
            else:
                sig[c], src[c] = floors[c], "noise floor"
            tiny = 1e-9 * max(1.0, float(np.max(np.abs(y))))
            if not (math.isfinite(sig[c]) and sig[c] > tiny):
                sig[c], src[c] = tiny, "noise floor (noiseless data)"
        if x0 is None:
            x0 = initial_state(rec, fx, rest_threshold, geometry)
        truth = None
        if meta.get("source") == "simulation" and "params" in meta:
            try:
                truth = OtbotParams.from_dict(meta["params"], source="recording metadata")
            except ParameterError:
                truth = None
        motion = {"pivot_range": 0.0}
        if rec.joint_pos is not None:
            phi = np.asarray(rec.joint_pos, dtype=float)[keep, 2]
            motion["pivot_range"] = float(np.nanmax(phi) - np.nanmin(phi)) if np.isfinite(phi).any() else 0.0
        return cls(name=name, t=t - t[0], torque=torque, measured=measured, sigma=sig, x0=x0, fixture=fx,
                   truth_params=truth, sigma_source=src, noise_floor=floors, motion=motion,
                   metadata={k: meta[k] for k in ("experiment", "seed", "source") if k in meta})


def initial_state(rec, fixture: str, rest_threshold: float = REST_THRESHOLD,
                  geometry: OtbotParams | None = None) -> np.ndarray:
    """x0 (12,) from the first sample's encoders, as described in the module docstring."""
    from otbot_hw.model.kinematics import admissible_velocity
    from otbot_hw.params import nominal

    x0 = np.zeros(12)
    if rec.joint_pos is not None and np.all(np.isfinite(rec.joint_pos[0])):
        x0[3:6] = rec.joint_pos[0]
    if rec.joint_vel is None or not np.all(np.isfinite(rec.joint_vel[0])):
        return x0
    w = np.asarray(rec.joint_vel[0], dtype=float)
    if np.all(np.abs(w) < rest_threshold):
        return x0
    if fixture == "floor":
        x0[6:] = admissible_velocity(x0[:6], w, geometry or nominal())
    else:
        x0[8] = x0[11] = w[2]
        if fixture == "stand":
            x0[9:11] = w[:2]
    return x0
