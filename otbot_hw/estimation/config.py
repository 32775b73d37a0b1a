"""Noise, priors and gates of the pose EKF: the optional ``estimator:`` section of ``config/robot.yaml``.

Every sensor sigma defaults to the sensor model (``otbot_hw.sensors.NoiseModel.paper()``, paper
§4.3.2): IMU 13.7e-3 (m/s^2, rad/s) per sample, encoder rates 0.01 rad/s. The sensor model's encoder
*angles* are exact; a Kalman update cannot use a zero-noise reading, so their sigma defaults to the
quantization of the configured encoders (config/robot.yaml): the wheel drives' 4096 counts per motor
revolution behind a 10:1 gear, 2 pi / 40960 / sqrt(12) = 4.4e-5 rad, and the CiA 406 pivot encoder's
16384 counts per revolution, 2 pi / 16384 / sqrt(12) = 1.1e-4 rad. The remaining entries are priors (turn-on biases,
their drift) and choices (gate probability, standstill detection) -- one set for every run, not tuned
per scenario. Each YAML entry is ``{value, unit}`` like the rest of the file; absent entries keep the
defaults below.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

from otbot_hw.params import DEFAULT_CONFIG_DIR, ParameterError, read_entry, read_yaml
from otbot_hw.sensors import NoiseModel

SECTION = "estimator"
DEFAULT_FILE = DEFAULT_CONFIG_DIR / "robot.yaml"
PREDICTIONS = ("imu", "model")
QUANTIZATIONS = ("floor", "none")
#: Counts per joint revolution of the encoders in config/robot.yaml: wheel drives (4096 x gear 10), pivot (CiA 406).
WHEEL_ENCODER_COUNTS = 40960
PIVOT_ENCODER_COUNTS = 16384

_PAPER = NoiseModel.paper()


def quantization_sigma(counts_per_rev: int) -> float:
    """Standard deviation (rad) of rounding an angle to whole counts: step / sqrt(12)."""
    return 2 * math.pi / counts_per_rev / math.sqrt(12)


@dataclass(frozen=True)
class EstimatorConfig:
    """Noise, priors and gates of ``PoseEKF`` (SI units; see ``UNITS``).

    prediction: ``imu`` (specific force and yaw rate drive the prediction; the choice measured in
    docs/estimation.md) or ``model`` (the dynamic model under the commanded torques drives it; the IMU
    becomes a measurement). accel_sigma (m/s^2) and gyro_sigma (rad/s): white noise per IMU sample;
    encoder_rate_sigma (rad/s), wheel_angle_sigma and pivot_angle_sigma (rad): per encoder sample. gyro_bias_std (rad/s)
    and accel_bias_std (m/s^2): prior std of the turn-on biases; gyro_bias_walk (rad/s/sqrt(s)) and
    accel_bias_walk (m/s^2/sqrt(s)): their random walk. model_accel_density ((m/s^2)/sqrt(Hz)): white
    acceleration error of the dynamic model's x, y rows (prediction ``model`` only);
    model_angular_density ((rad/s^2)/sqrt(Hz)): white error of its alpha row, which drives alpha_dot in
    both predictions; angular_disturbance_std (rad/s^2) and angular_disturbance_walk
    (rad/s^2/sqrt(s)): prior and random walk of the state d, the alpha_dd of torques the model does not
    know (friction, torque-gain errors; the walk sized so that 0.5 N m of unmodelled pivot friction and
    5 % torque-gain errors keep the filter consistent, docs/estimation.md). gate_probability:
    chi-square probability of the Mahalanobis gate. walk_adaptation_window (s; 0 switches the
    adaptation off) and walk_adaptation_decay (s): the walk of d adapts to a model that is wrong --
    when the gyro's normalized innovations squared, averaged over about this window, exceed their
    chi-square bound at gate_probability, the walk's variance is multiplied by that average at every
    reading (covariance matching: the filter's alpha_dot prediction error made as large as the gyro
    says it is), and relaxes back to the configured walk with this decay time once they do not
    (docs/estimation.md, "A model that is wrong").
    standstill_window (s) / standstill_angle (rad): the robot stands when no joint moved more than
    standstill_angle for standstill_window. imu_timeout (s): longest IMU silence before a fault.
    encoder_quantization: ``floor`` (an angle reading is the lower edge of its count, as the drives and
    the recording format report it: the EKF uses the count's centre, reading + sqrt(12) sigma / 2 with
    each joint's angle sigma) or
    ``none`` (readings are unbiased).
    """

    prediction: str = "imu"
    encoder_quantization: str = "floor"
    accel_sigma: float = _PAPER.accel
    gyro_sigma: float = _PAPER.gyro
    encoder_rate_sigma: float = _PAPER.enc_rate
    wheel_angle_sigma: float = max(_PAPER.enc_angle, quantization_sigma(WHEEL_ENCODER_COUNTS))
    pivot_angle_sigma: float = max(_PAPER.enc_angle, quantization_sigma(PIVOT_ENCODER_COUNTS))
    gyro_bias_std: float = 0.05
    gyro_bias_walk: float = 1e-4
    accel_bias_std: float = 0.02
    accel_bias_walk: float = 1e-3
    model_accel_density: float = 0.5
    model_angular_density: float = 0.003
    angular_disturbance_std: float = 0.5
    angular_disturbance_walk: float = 0.3
    gate_probability: float = 0.9999
    walk_adaptation_window: float = 0.1
    walk_adaptation_decay: float = 1.0
    standstill_window: float = 0.2
    standstill_angle: float = 2 * 2 * math.pi / PIVOT_ENCODER_COUNTS
    imu_timeout: float = 0.5

    def __post_init__(self) -> None:
        if self.prediction not in PREDICTIONS:
            raise ParameterError(f"{SECTION}.prediction must be one of {', '.join(PREDICTIONS)}, "
                                 f"got {self.prediction!r}")
        if self.encoder_quantization not in QUANTIZATIONS:
            raise ParameterError(f"{SECTION}.encoder_quantization must be one of {', '.join(QUANTIZATIONS)}, "
                                 f"got {self.encoder_quantization!r}")
        for f in dataclasses.fields(self):
            if f.name in _WORDS:
                continue
            v = getattr(self, f.name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ParameterError(f"{SECTION}.{f.name} must be a finite number, got {v!r}")
            if f.name in _NONNEGATIVE:
                if v < 0:
                    raise ParameterError(f"{SECTION}.{f.name} must be >= 0 ({UNITS[f.name]}), got {v}")
            elif not v > 0:
                raise ParameterError(f"{SECTION}.{f.name} must be > 0 ({UNITS[f.name]}), got {v}")
            if f.name in _NOISES and v > MAX_NOISE:
                why = "beyond any joint motion" if f.name == "standstill_angle" else "its square enters the covariance"
                raise ParameterError(f"{SECTION}.{f.name} must be at most {MAX_NOISE:g} {UNITS[f.name]} ({why}), "
                                     f"got {v:g}")
            object.__setattr__(self, f.name, float(v))
        if 0 < self.walk_adaptation_window < MIN_WINDOW:
            raise ParameterError(f"{SECTION}.walk_adaptation_window must be 0 (off) or at least {MIN_WINDOW:g} s (one "
                                 f"control period at 1 kHz), got {self.walk_adaptation_window:g}")
        if not self.gate_probability < 1:
            raise ParameterError(f"{SECTION}.gate_probability must be in (0, 1), got {self.gate_probability}")

    def replace(self, **changes) -> "EstimatorConfig":
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, block, source: str = "<dict>") -> "EstimatorConfig":
        """From the ``estimator:`` mapping: ``prediction: imu|model`` and ``{value, unit}`` entries."""
        if block is None:
            return cls()
        if not isinstance(block, dict):
            raise ParameterError(f"{source}: section '{SECTION}' must be a mapping")
        known = {f.name for f in dataclasses.fields(cls)}
        values = {}
        for name, entry in block.items():
            key = f"{SECTION}.{name}"
            if name not in known:
                raise ParameterError(f"{source}: unknown key '{key}' (known: {', '.join(sorted(known))})")
            if name in _WORDS:
                values[name] = entry
                continue
            v, _ = read_entry(source, key, entry, UNITS[name])
            values[name] = v
        try:
            return cls(**values)
        except ParameterError as exc:
            raise ParameterError(f"{source}: {exc}") from None

    @classmethod
    def load(cls, path: str | Path | None = None) -> "EstimatorConfig":
        """The ``estimator:`` section of ``path`` (default config/robot.yaml); defaults when absent."""
        p = Path(path) if path is not None else DEFAULT_FILE
        data = read_yaml(p)
        if data is not None and not isinstance(data, dict):
            raise ParameterError(f"{p}: expected a mapping of sections")
        return cls.from_dict((data or {}).get(SECTION), source=str(p))


UNITS = {
    "accel_sigma": "m/s^2", "gyro_sigma": "rad/s", "encoder_rate_sigma": "rad/s", "wheel_angle_sigma": "rad",
    "pivot_angle_sigma": "rad",
    "gyro_bias_std": "rad/s", "gyro_bias_walk": "rad/s/sqrt(s)", "accel_bias_std": "m/s^2",
    "accel_bias_walk": "m/s^2/sqrt(s)", "model_accel_density": "m/s^2/sqrt(Hz)",
    "model_angular_density": "rad/s^2/sqrt(Hz)", "angular_disturbance_std": "rad/s^2",
    "angular_disturbance_walk": "rad/s^2/sqrt(s)", "gate_probability": "1", "standstill_window": "s",
    "standstill_angle": "rad", "imu_timeout": "s",
    "walk_adaptation_window": "s", "walk_adaptation_decay": "s",
}
#: The sigmas, stds, walks, densities and the standstill angle: at most a million in their SI unit (1e160
#: overflowed when squared), far above any sensor or model error.
_NOISES = {name for name, unit in UNITS.items() if unit not in ("s", "1")}
MAX_NOISE = 1e6
#: Shortest walk_adaptation_window (s) that is not 0 (1e-320 overflowed dt / window).
MIN_WINDOW = 1e-3
_NONNEGATIVE = {"gyro_bias_walk", "accel_bias_walk", "angular_disturbance_walk", "walk_adaptation_window"}
_WORDS = {"prediction", "encoder_quantization"}
