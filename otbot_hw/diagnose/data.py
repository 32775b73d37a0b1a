"""Recordings as the diagnosis sees them: only what a real robot records, checked.

A ``DiagnosisData`` keeps the commands, the encoders and the IMU of a recording and
the two metadata entries a robot knows (``sample_period``, ``fixture``). Ground
truth (``/otbot/truth``, hidden-effect metadata) is never copied. Channels that
cannot be used (NaN, absent) are listed with the reason; problems that make the
recording unusable raise ``DiagnosisInputError``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.signal import savgol_filter

from otbot_hw.model.fixtures import FIXTURES
from otbot_hw.recording import Recording, RecordingError, read_recording

#: Channels of the simulation residual: encoder rates (rad/s), IMU specific force x, y (m/s^2), gyro z (rad/s).
CHANNELS = ("w_r", "w_l", "w_p", "a_x", "a_y", "g_z")
CHANNEL_UNITS = {"w_r": "rad/s", "w_l": "rad/s", "w_p": "rad/s", "a_x": "m/s^2", "a_y": "m/s^2", "g_z": "rad/s"}
MIN_SAMPLES = 50
SMOOTH_WINDOW = 0.11  # s, Savitzky-Golay window for derivatives of measured signals


class DiagnosisInputError(RecordingError):
    """A recording cannot be diagnosed; the message names the file, channel and reason."""


@dataclass
class DiagnosisData:
    """One recording: t (N,) s from 0, u (N, 3) N m held on [t_k, t_k+1), enc_pos/enc_vel (N, 3)
    rad, rad/s, imu_acc/imu_gyro (N, 3) m/s^2, rad/s (IMU frame), ``fixture``, ``dt`` s."""

    name: str
    t: np.ndarray
    dt: float
    u: np.ndarray
    enc_pos: np.ndarray
    enc_vel: np.ndarray | None
    imu_acc: np.ndarray | None
    imu_gyro: np.ndarray | None
    fixture: str
    unusable: dict[str, str] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    truncated: bool = False  # the file was cut short; these are its complete samples
    noise_levels: dict[str, float] | None = None  # channel -> white-noise level given, not measured (``head``)
    _memo: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def memo(self, key, compute):
        """``compute()`` once per key (a fixed name) for this recording: filtered signals that depend on
        the data alone, or a dict the caller bounds itself. Kept with the object, so a cache entry never
        outlives or mixes up its recording; the recording's arrays are not changed in place anywhere
        (``segment``, ``dataclasses.replace`` give new objects with an empty memo). Arrays are stored
        read-only."""
        value = self._memo.get(key)
        if value is None:
            value = compute()
            for a in (value if isinstance(value, tuple) else (value,)):
                if isinstance(a, np.ndarray):
                    a.flags.writeable = False  # shared: a caller that changes it works on a copy
            value = self._memo.setdefault(key, value)  # two threads computing it at once keep one
        return value

    def __len__(self) -> int:
        return len(self.t)

    def measured(self, ch: str) -> np.ndarray | None:
        """Measured channel ``ch`` (one of CHANNELS), None when not usable."""
        if ch in self.unusable:
            return None
        src = {"w_r": (self.enc_vel, 0), "w_l": (self.enc_vel, 1), "w_p": (self.enc_vel, 2),
               "a_x": (self.imu_acc, 0), "a_y": (self.imu_acc, 1), "g_z": (self.imu_gyro, 2)}[ch]
        return None if src[0] is None else src[0][:, src[1]]

    def channels(self) -> list[str]:
        """Usable channels of the simulation residual."""
        return [c for c in CHANNELS if self.measured(c) is not None]

    @property
    def window(self) -> int:
        """Savitzky-Golay window length (odd number of samples, about SMOOTH_WINDOW s)."""
        w = max(5, int(round(SMOOTH_WINDOW / self.dt)) | 1)
        return w

    def smooth(self, y: np.ndarray, deriv: int = 0) -> np.ndarray:
        """Savitzky-Golay smoothing (deriv 0) or derivative (1, 2) along time, order 2 (3 for deriv 2)."""
        order = 3 if deriv == 2 else 2
        return savgol_filter(y, self.window, order, deriv=deriv, delta=self.dt, axis=0, mode="interp")

    def noise_sigma(self, ch: str) -> float:
        """White-noise level of a measured channel from its second differences (robust, MAD).

        sigma = 1.4826 * MAD(y_k+1 - 2 y_k + y_k-1) / sqrt(6); floored at the reading's quantization
        q / sqrt(12) when the channel is quantized (``resolution``: a reading in steps of q whose noise
        is below a step has second differences that are mostly 0) and at 1e-6 (units of ``ch``) so
        noiseless simulations stay finite. A level in ``noise_levels`` is returned as given.
        """
        if self.noise_levels is not None and ch in self.noise_levels:
            return self.noise_levels[ch]
        y = self.measured(ch)
        return float(max(mad_sigma(y), resolution(y) / np.sqrt(12.0), 1e-6))

    def segment(self, k0: int, k1: int) -> "DiagnosisData":
        """Samples k0..k1-1 as a recording of its own (time restarts at 0)."""
        sl = slice(k0, k1)
        pick = (lambda a: None if a is None else a[sl].copy())
        return DiagnosisData(f"{self.name}[{k0}:{k1}]", self.t[sl] - self.t[k0], self.dt, self.u[sl].copy(),
                             self.enc_pos[sl].copy(), pick(self.enc_vel), pick(self.imu_acc), pick(self.imu_gyro),
                             self.fixture, dict(self.unusable), list(self.notes), self.truncated)

    def head(self, n: int) -> "DiagnosisData":
        """The first n samples (all when shorter) carrying the whole recording's noise levels: what a
        quantity at the start of the record needs (the Savitzky-Golay filters fit their first samples
        from the first ``window`` samples alone, so n >= ``window`` gives the same values there)."""
        h = self.segment(0, min(n, len(self)))
        h.name = self.name
        h.noise_levels = {ch: self.noise_sigma(ch) for ch in CHANNELS if self.measured(ch) is not None}
        return h


def mad_sigma(y: np.ndarray) -> float:
    """White-noise level of a series from its second differences: 1.4826 MAD(d2) / sqrt(6)."""
    d2 = np.diff(np.asarray(y, dtype=float), 2)
    return float(1.4826 * np.median(np.abs(d2 - np.median(d2))) / np.sqrt(6.0))


def resolution(y: np.ndarray) -> float:
    """Quantization step of a reading (its units), 0 when it is not quantized: the smallest gap between
    its distinct values when fewer than half the samples are distinct and every gap is a whole number of
    that step (to 1 %)."""
    y = np.asarray(y, dtype=float)
    u = np.unique(y[np.isfinite(y)])
    if len(u) < 3 or len(u) > len(y) // 2:
        return 0.0
    gaps = np.diff(u)
    q = float(np.min(gaps))
    if q <= 0 or not np.all(np.abs(gaps / q - np.round(gaps / q)) < 0.01):
        return 0.0
    return q


def from_recording(rec: Recording, name: str = "recording") -> DiagnosisData:
    """Check a recording and keep what a real robot records; raise DiagnosisInputError if unusable."""
    n = len(rec.t)
    if n < MIN_SAMPLES:
        raise DiagnosisInputError(f"{name}: {n} samples; the diagnosis needs at least {MIN_SAMPLES}")
    t = np.asarray(rec.t, dtype=float)
    steps = np.diff(t)
    med = float(np.median(steps))
    meta = rec.metadata or {}
    notes: list[str] = []
    dt = med
    if "sample_period" in meta:
        try:
            dt = float(meta["sample_period"])
        except (TypeError, ValueError):
            raise DiagnosisInputError(f"{name}: metadata sample_period {meta['sample_period']!r} is not a number") \
                from None
        if not (dt > 0 and np.isfinite(dt)):
            raise DiagnosisInputError(f"{name}: metadata sample_period must be > 0 s, got {dt}")
        if abs(med - dt) > 0.01 * dt:
            raise DiagnosisInputError(f"{name}: metadata sample_period {dt} s disagrees with the median time step "
                                      f"{med:.6g} s of the samples")
    else:
        notes.append(f"no sample_period in the metadata; using the median step {med:.6g} s")
    bad = np.nonzero(np.abs(steps - dt) > 0.25 * dt)[0]
    if len(bad):
        k = int(bad[0])
        raise DiagnosisInputError(f"{name}: gap or uneven sampling at sample {k + 1}: t jumps from {t[k]:.6g} s to "
                                  f"{t[k + 1]:.6g} s (period {dt:.6g} s); {len(bad)} such step(s). Split the "
                                  "recording at gaps")
    fixture = meta.get("fixture", "floor")
    if fixture not in FIXTURES:
        raise DiagnosisInputError(f"{name}: metadata fixture {fixture!r} is unknown (known: {', '.join(FIXTURES)})")
    if "fixture" not in meta:
        notes.append("no fixture in the metadata; assuming the robot is on the floor")
    u = np.asarray(rec.torque, dtype=float)
    if not np.all(np.isfinite(u)):
        k = int(np.argmax(~np.all(np.isfinite(u), axis=1)))
        raise DiagnosisInputError(f"{name}: /otbot/command torque is NaN or inf at sample {k}: the commands "
                                  "are needed to simulate the run")
    if rec.joint_pos is None or rec.joint_vel is None:
        raise DiagnosisInputError(f"{name}: no /otbot/joints channel: the diagnosis needs the wheel and pivot "
                                  "encoders (initial state, inverse-dynamics residual)")
    unusable: dict[str, str] = {}
    pos = np.asarray(rec.joint_pos, dtype=float)
    if not np.all(np.isfinite(pos)):
        k = int(np.argmax(~np.all(np.isfinite(pos), axis=1)))
        raise DiagnosisInputError(f"{name}: /otbot/joints position is NaN or inf at sample {k}: the encoder "
                                  "angles are needed for the platform heading")
    vel = np.asarray(rec.joint_vel, dtype=float)
    for j, ch in enumerate(("w_r", "w_l", "w_p")):
        if not np.all(np.isfinite(vel[:, j])):
            unusable[ch] = (f"/otbot/joints velocity[{j}] has {int(np.sum(~np.isfinite(vel[:, j])))} NaN/inf "
                            "samples; rates are differentiated from the angles instead")
    acc = gyro = None
    if rec.imu_accel is None:
        for ch in ("a_x", "a_y", "g_z"):
            unusable[ch] = "no /otbot/imu channel in the recording"
    else:
        acc = np.asarray(rec.imu_accel, dtype=float)
        gyro = np.asarray(rec.imu_gyro, dtype=float)
        for ch, arr, j in (("a_x", acc, 0), ("a_y", acc, 1), ("g_z", gyro, 2)):
            nbad = int(np.sum(~np.isfinite(arr[:, j])))
            if nbad:
                unusable[ch] = f"/otbot/imu has {nbad} NaN/inf samples in {ch}"
    imu_rate = meta.get("imu_rate")
    if acc is not None and isinstance(imu_rate, (int, float)) and 0 < imu_rate < 0.99 / dt:
        for ch in ("a_x", "a_y", "g_z"):  # a held reading is late by up to one IMU period and not white
            unusable.setdefault(ch, f"the IMU runs at {imu_rate:g} Hz, below the {1 / dt:g} Hz sample rate: "
                                    "/otbot/imu repeats its readings (record at the IMU rate to use it)")
    if fixture == "locked":
        for ch in ("w_r", "w_l"):
            unusable.setdefault(ch, "wheels are locked on this fixture")
    if rec.truncated:
        notes.append(f"the file was cut short: diagnosed on its {n} complete samples ({t[-1] - t[0]:.3g} s)")
    return DiagnosisData(name, t - t[0], dt, u, pos, vel, acc, gyro, fixture, unusable, notes, bool(rec.truncated))


MIN_DURATION = 0.25  # s: shorter records test nothing (the initial rates alone take the first 0.25 s)
QUIET_SIGMAS = 5.0  # a joint whose encoder rate never leaves this many noise levels of zero did not move


def check_testable(recordings: list[DiagnosisData]) -> None:
    """Raise DiagnosisInputError when the fitting recordings cannot test anything: every one shorter than
    ``MIN_DURATION`` or with no joint moving (every usable encoder rate within ``QUIET_SIGMAS`` noise levels
    of zero, and no IMU channel beyond that of its mean); the message says what to record instead."""
    what = ("record at least 1 s (better 10 s) with torques that move the wheels and the pivot, e.g. "
            "random piecewise-constant torques of a few N m per motor (otbot bench --steps chassis, or "
            "otbot simulate --torques 6,-10,6 --duration 10 on the simulated robot)")
    if all(float(d.t[-1]) < MIN_DURATION for d in recordings):
        longest = max(float(d.t[-1]) for d in recordings)
        raise DiagnosisInputError(f"{recordings[0].name}: too short to test anything ({longest:.3g} s < "
                                  f"{MIN_DURATION} s): {what}")

    def moves(d: DiagnosisData) -> bool:
        for ch in ("w_r", "w_l", "w_p"):
            y = d.measured(ch)
            if y is not None and np.max(np.abs(y)) > QUIET_SIGMAS * d.noise_sigma(ch):
                return True
        for ch in ("a_x", "a_y", "g_z"):
            y = d.measured(ch)
            if y is not None and np.max(np.abs(y - np.mean(y))) > 2 * QUIET_SIGMAS * d.noise_sigma(ch):
                return True
        return False

    if not any(moves(d) for d in recordings):
        raise DiagnosisInputError(f"{', '.join(d.name for d in recordings)}: too quiet to test anything (no "
                                  f"encoder rate leaves {QUIET_SIGMAS:g} noise levels of zero: the robot did not "
                                  f"move): {what}")


def load(paths: list[str | Path]) -> list[DiagnosisData]:
    """Read and check recordings; errors name the file."""
    out = []
    for p in paths:
        out.append(from_recording(read_recording(p), name=str(p)))
    return out
