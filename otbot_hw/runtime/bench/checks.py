"""The bench's checks, judged from the sensors: before any torque, before the excitation, after it.

Each check is a ``Check`` (name, passed, what was found, what to do when it failed):

=============  ====================================================================================
name           passes when
=============  ====================================================================================
drives         the drives enabled (OPERATION ENABLED) and no drive, encoder or IMU reported a fault
imu            the IMU streams: at least 80 % of the expected samples arrived, all finite
at_rest        no encoder rate above 0.05 rad/s (the identification's rest threshold) and no mean rate
               beyond 4 std of the mean of the stated noise, the gyro below 0.05 rad/s and the
               accelerometer's spread within 3x its stated noise
settled        at_rest again after the probe and the brake (the excitation starts from rest)
limits         the excitation's predicted peaks (best-known robot) within the experiment limits and
               the free area (``excitation.predicted_margins``)
fixture        stand: a spinning right wheel moves no IMU; locked: the wheel encoders stay still under
               wheel torque; floor: the pivot's speed from the encoders (kinematics) and from the IMU
               (integrated specific force) agree within 30 % under a forward push
saturation     the torques the drives applied are the planned excitation (within 0.05 N m)
clipping       no sensor channel sits at its extreme value for 5 samples or more (a clipped sensor)
=============  ====================================================================================

The fixture probe's IMU statistics use the IMU's own noise, measured in the rest window just
before: the velocity (m/s) and angle (rad) changes the IMU integrates over the probe, in units of
what white noise of that level integrates to (sigma dt sqrt(k) after k samples); a change beyond
``IMU_MOVED`` such units is motion.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from otbot_hw.identification.experiment import REST_THRESHOLD
from otbot_hw.model.kinematics import forward_kinematics_matrix
from otbot_hw.params import OtbotParams

IMU_MOVED = 5.0          # integrated IMU change, in units of its noise, that counts as motion
WHEEL_TURNED = 0.2       # rad/s: a wheel rate above this turned (20 x the encoder-rate noise)
LOCKED_ANGLE = 0.01      # rad: a locked wheel's encoder moves less than this (backlash)
LOCKED_RATE = 0.1        # rad/s: ... and reports rates below this (10 x the encoder-rate noise)
SPEED_AGREEMENT = 0.3    # relative: encoders and IMU agree on the pivot's speed within this
MOVED_SPEED = 20.0       # units of integrated IMU noise the encoder speed must reach to count as moving
REST_GYRO = 0.05         # rad/s
REST_MEAN_SIGMAS = 4.0   # a joint's mean rate over the rest window within this many of its noise's std of the mean
MIN_REST_MEAN = 1e-3     # rad/s, the floor of that bound (noise-free encoders)
SATURATION_TOL = 0.05    # N m
CLIP_RUN = 5             # samples


@dataclass
class Check:
    """One check: ``name`` (module table), ``passed``, ``message`` (what was found), ``fix`` (what to do
    when it failed), ``value`` (the judged number, where there is one)."""

    name: str
    passed: bool
    message: str
    fix: str = ""
    value: float | None = None

    def to_dict(self) -> dict:
        d = asdict(self)
        if d["value"] is not None and not math.isfinite(d["value"]):
            d["value"] = None
        return d

    def __str__(self) -> str:
        return self.message + (f"; {self.fix}" if (self.fix and not self.passed) else "")


def drives_check(res) -> Check:
    """From the zero-torque run's ``LoopResult``."""
    if res.completed and not res.robot_faults:
        return Check("drives", True, "drives enabled, no fault reported")
    why = str(res.fault) if res.fault is not None else "; ".join(map(str, res.robot_faults))
    return Check("drives", False, f"the drives did not enable or reported a fault: {why}",
                 "check power and the emergency stop, read the fault (otbot run --json shows it), reset it and "
                 "check again")


def imu_check(rec, imu_rate: float | None) -> Check:
    """IMU streaming during the zero-torque run (``imu_rate`` Hz expected; None: no IMU configured)."""
    if imu_rate is None or rec.imu_accel is None:
        return Check("imu", False, "no IMU samples: the bench needs the IMU (the floor steps measure with it, the "
                                   "stand check watches it)", "configure the imu section of config/robot.yaml and "
                                                              "connect the IMU")
    a = np.column_stack([rec.imu_accel, rec.imu_gyro])
    finite = np.all(np.isfinite(a), axis=1)
    fresh = 1 + int(np.sum(np.any(np.diff(a[finite], axis=0) != 0, axis=1))) if finite.any() else 0
    expected = max(1, int(math.floor(len(rec) * (rec.t[1] - rec.t[0]) * imu_rate)))
    frac = fresh / expected
    if frac >= 0.8 and finite.all():
        return Check("imu", True, f"IMU streaming: {fresh} samples in {len(rec)} periods ({imu_rate:g} Hz expected)",
                     value=frac)
    return Check("imu", False, f"the IMU is not streaming: {fresh} fresh samples of {expected} expected"
                               + ("" if finite.all() else f", {int(np.sum(~finite))} not finite"),
                 "check the IMU's cable, port and output rate (otbot imu read shows what arrives)", frac)


def rest_check(rec, noise, what: str = "", start: int = 0) -> Check:
    """The robot stands still over the samples ``start``.. of ``rec``: every encoder rate below the
    identification's rest threshold and its mean within ``REST_MEAN_SIGMAS`` of the stated rate
    noise over the window (a slow coast biases the fit, which starts the run at rest), the gyro
    quiet, the accelerometer's spread within 3x its stated noise. ``noise``: the stated sensor noise
    (``NoiseModel``)."""
    vel = np.asarray(rec.joint_vel[start:])
    n = len(vel)
    w = float(np.max(np.abs(vel))) if n else math.inf
    m = float(np.max(np.abs(np.mean(vel, axis=0)))) if n else math.inf
    mean_lim = max(REST_MEAN_SIGMAS * (noise.enc_rate or 0.0) / math.sqrt(max(n, 1)), MIN_REST_MEAN)
    found = [f"largest encoder rate {w:.3f} rad/s, largest mean rate {m:.4f} rad/s"]
    ok = w <= REST_THRESHOLD and m <= mean_lim
    if rec.imu_gyro is not None and np.all(np.isfinite(rec.imu_gyro[start:])):
        g = float(np.max(np.abs(np.mean(rec.imu_gyro[start:], axis=0))))
        s = float(np.max(np.std(rec.imu_accel[start:, :2], axis=0)))
        found += [f"mean gyro {g:.3f} rad/s", f"accelerometer spread {s:.4f} m/s^2"]
        ok = ok and g <= REST_GYRO and s <= 3.0 * (noise.accel or 0.0137)
    head = "the robot stands still" if ok else "the robot is moving"
    msg = f"{head}{' ' + what if what else ''} (" + ", ".join(found) + ")"
    return Check("at_rest", ok, msg, "" if ok else
                 f"wait until it stands still (encoder rates below {REST_THRESHOLD} rad/s, on average below "
                 f"{mean_lim:.4f} rad/s; gyro below {REST_GYRO} rad/s) and nothing touches or shakes it", m)


def limits_check(step: str, margins: dict[str, tuple[float, float]], excitation: str) -> Check:
    """The predicted peaks of the step's excitation against its limits."""
    from otbot_hw.experiment_limits import LIMIT_UNITS

    units = {**LIMIT_UNITS, "travel_radius": "m"}
    over = {k: v for k, v in margins.items() if v[0] > v[1] * (1 + 1e-9)}
    text = ", ".join(f"{k.replace('_', ' ')} {p:.3g} of {lim:.3g} {units.get(k, '')}" for k, (p, lim) in margins.items())
    worst = max((p / lim for p, lim in margins.values()), default=0.0)
    if not over:
        return Check("limits", True, f"predicted peaks within the limits: {text}", value=worst)
    name = ", ".join(f"{k.replace('_', ' ')} {p:.3g} {units.get(k, '')} (limit {lim:.3g})" for k, (p, lim) in over.items())
    if "travel_radius" in over:
        fix = "clear a larger free area and declare it with --free-area M"
    else:
        fix = f"raise experiment_limits.{next(iter(over))} in config/robot.yaml if the robot allows it"
    if excitation == "paper" and step in ("chassis", "platform"):
        fix = "use --excitation designed (torques designed within the limits), or " + fix
    return Check("limits", False, f"the {step} excitation would exceed its limits: {name}", fix, worst)


def _imu_sigmas(rest) -> tuple[np.ndarray, float, np.ndarray]:
    """(accel xy sigma (2,), gyro z sigma, accel xy rest mean (2,)) from the rest window."""
    acc = np.asarray(rest.imu_accel[:, :2], dtype=float)
    return (np.maximum(np.std(acc, axis=0), 1e-4), max(float(np.std(rest.imu_gyro[:, 2])), 1e-4),
            np.mean(acc, axis=0))


def _integrated(y: np.ndarray, dt: float) -> np.ndarray:
    return np.cumsum(y, axis=0) * dt


def fixture_check(kind: str, probe, rest, params: OtbotParams, n_probe: int) -> Check:
    """The fixture of a step judged from its probe run (``probe``, the doublet in its first
    ``n_probe`` samples) and the rest run before it (IMU noise and offsets): ``kind`` stand, locked
    or floor, the fixture the step needs."""
    dt = float(probe.t[1] - probe.t[0])
    n = min(n_probe, len(probe))
    w = np.asarray(probe.joint_vel[:n], dtype=float)
    if kind == "locked":
        dphi = np.abs(probe.joint_pos[:, :2] - probe.joint_pos[0, :2]).max(axis=0)
        moved = float(dphi.max())
        if moved <= LOCKED_ANGLE and np.abs(w[:, :2]).max() <= LOCKED_RATE:
            return Check("fixture", True, f"wheels locked: the wheel encoders moved at most {moved:.4f} rad under "
                                          "wheel torque", value=moved)
        return Check("fixture", False, f"the wheels are not locked: the wheel encoders moved {dphi[0]:.3f} rad "
                                       f"(right) and {dphi[1]:.3f} rad (left) under 1 N m of wheel torque",
                     "lock both wheels (brake or chocks) so that neither wheel nor chassis can move; the platform "
                     "must stay free to turn", moved)
    if probe.imu_accel is None or rest.imu_accel is None:
        return Check("fixture", False, "no IMU samples: the fixture cannot be verified",
                     "connect the IMU (otbot imu read shows what arrives)")
    sig_a, sig_g, mean_a = _imu_sigmas(rest)
    k = np.arange(1, n + 1)[:, None]
    dv = _integrated(np.asarray(probe.imu_accel[:n, :2]) - mean_a, dt)          # m/s, platform frame
    z_v = float(np.max(np.abs(dv) / (sig_a * dt * np.sqrt(k))))
    if kind == "stand":
        dth = _integrated(np.asarray(probe.imu_gyro[:n, 2]) - float(np.mean(rest.imu_gyro[:, 2])), dt)
        z = max(z_v, float(np.max(np.abs(dth) / (sig_g * dt * np.sqrt(k[:, 0])))))
        wr = float(np.max(np.abs(w[:, 0])))
        if wr < WHEEL_TURNED:
            return Check("fixture", False, f"the right wheel did not turn under 1 N m (peak {wr:.3f} rad/s)",
                         "put the robot on the stand with both wheels free to spin; check that the right wheel's "
                         "drive delivers torque", wr)
        if z > IMU_MOVED:
            return Check("fixture", False, f"the IMU moved while the right wheel spun ({z:.0f} x its noise): the "
                                           "robot is not held on the stand",
                         "lift the robot onto the stand: chassis held, both wheels off the ground", z)
        return Check("fixture", True, f"on the stand: the right wheel spun to {wr:.2f} rad/s and the IMU felt "
                                      f"nothing (at most {z:.1f} x its noise)", value=z)
    # floor: pivot speed from the encoders (kinematics) against the IMU's integrated specific force
    M = forward_kinematics_matrix(np.zeros(6), params)[:2]  # |(x_dot, y_dot)| does not depend on the heading
    v_enc = np.linalg.norm(w @ M.T, axis=1)
    v_imu = np.linalg.norm(np.vstack([np.zeros((1, 2)), dv[:-1]]), axis=1)
    noise = float(np.max(sig_a)) * dt * math.sqrt(n)
    i = int(np.argmax(v_enc))
    if v_enc[i] < MOVED_SPEED * noise:
        return Check("fixture", False, f"the robot did not move under 2 N m on both wheels (encoders: {v_enc[i]:.4f} "
                                       "m/s)", "unlock the wheels and put the robot on the floor; check that the "
                                                "drives deliver torque", float(v_enc[i]))
    ratio = float(v_imu[i] / v_enc[i])
    if abs(ratio - 1.0) <= SPEED_AGREEMENT:
        return Check("fixture", True, f"on the floor: encoders and IMU agree on the pivot's speed ({v_enc[i]:.3f} "
                                      f"and {v_imu[i]:.3f} m/s)", value=ratio)
    if ratio < 1.0:
        return Check("fixture", False, f"the encoders say the robot rolled at {v_enc[i]:.3f} m/s but the IMU felt "
                                       f"{v_imu[i]:.3f} m/s: the wheels are not on the floor",
                     "put the robot on the floor with the wheels free (off the stand)", ratio)
    return Check("fixture", False, f"the IMU felt {v_imu[i]:.3f} m/s where the encoders explain {v_enc[i]:.3f} m/s",
                 "check for wheel slip (floor, tyres), the wheel radius r in the parameters and imu.mounting in "
                 "config/robot.yaml", ratio)


def saturation_check(rec, planned: np.ndarray) -> Check:
    """The applied torques (``/otbot/command``) against the planned excitation rows."""
    n = min(len(planned), len(rec))
    diff = np.abs(np.asarray(rec.torque[:n]) - planned[:n])
    bad = np.any(diff > SATURATION_TOL, axis=1)
    if not bad.any():
        return Check("saturation", True, "the drives applied the planned torques", value=0.0)
    j = int(np.argmax(diff.max(axis=0)))
    k = int(np.argmax(diff[:, j]))
    return Check("saturation", False, f"saturated: the drives applied {rec.torque[k, j]:.2f} N m where "
                                      f"{planned[k, j]:.2f} N m was commanded on {('right wheel', 'left wheel', 'pivot')[j]} "
                                      f"({int(bad.sum())} of {n} samples)",
                 "the drives cap the torque below the experiment's limit: lower experiment_limits.torque to what "
                 "they deliver or raise the drives' max torque (0x6072)", float(bad.sum()))


def clipping_check(rec, n: int) -> Check:
    """No sensor channel held at its extreme value for ``CLIP_RUN`` samples or more (first ``n`` samples)."""
    chans = {"w_r": rec.joint_vel[:n, 0], "w_l": rec.joint_vel[:n, 1], "w_p": rec.joint_vel[:n, 2]}
    if rec.imu_accel is not None:
        chans.update(a_x=rec.imu_accel[:n, 0], a_y=rec.imu_accel[:n, 1], omega_z=rec.imu_gyro[:n, 2])
    for c, y in chans.items():
        y = np.asarray(y, dtype=float)
        peak = float(np.max(np.abs(y))) if len(y) else 0.0
        if peak == 0 or not np.any(np.diff(y)):
            continue
        at = np.abs(np.abs(y) - peak) <= 1e-12 * peak
        run = best = 0
        for v in at:
            run = run + 1 if v else 0
            best = max(best, run)
        if best >= CLIP_RUN and np.std(np.diff(y, 2)[~at[2:]]) > 0:
            return Check("clipping", False, f"clipped: {c} sits at {peak:.4g} for {best} samples in a row",
                         "the sensor's range is too small for this excitation: lower the excitation "
                         "(experiment_limits) or widen the sensor's range", float(best))
    return Check("clipping", True, "no sensor channel clipped")
