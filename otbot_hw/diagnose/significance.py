"""Whether an effect matters, in physical terms.

Evidence (BIC, held-out prediction) says an effect is *there*; this module says whether
it *matters*, by what it does to the robot, not by the fit % of a channel (a large signal
hides a gyro bias that turns the heading by degrees per minute):

* forces and torques (friction, floor, drag, gain errors, saturation, traction): the joint
  torque they take from or add to the motors, against the RMS command of those motors
  in the recordings (``TORQUE_FRACTION``);
* sensor offsets: the drift they cause if integrated -- heading per minute for a gyro bias
  (``HEADING_DRIFT``), position over ``POSITION_HORIZON`` for an accelerometer bias
  (``POSITION_DRIFT``);
* geometry and scale: the IMU lever arm (``LEVER_ARM``), misalignment (``MISALIGNMENT``),
  odometry distance per metre for encoder scale, unequal radii and slip
  (``ODOMETRY_FRACTION``), heading per metre driven for unequal radii;
* time: delays of torques or IMU samples (``DELAY``).

An effect matters when that impact reaches its threshold *and* its size is at least
``Z_MIN`` of its own standard deviations. ``significance`` returns the impact as a
sentence (e.g. "gyro bias 5.9 ± 0.3 mrad/s: 20° of heading per minute if integrated").
"""
from __future__ import annotations

import numpy as np

from otbot_hw.diagnose.data import DiagnosisData
from otbot_hw.model.effects import GRAVITY, ExtendedModel

TORQUE_FRACTION = 0.01  # of the RMS command of the motors the effect acts on
HEADING_DRIFT = 1.0  # deg per minute
POSITION_HORIZON = 10.0  # s
POSITION_DRIFT = 0.05  # m over POSITION_HORIZON
LEVER_ARM = 0.01  # m
MISALIGNMENT = np.deg2rad(0.2)  # rad
ODOMETRY_FRACTION = 0.002  # distance error per distance driven
DELAY = 1e-3  # s
Z_MIN = 2.0

WHEELS, PIVOT = (0, 1), (2,)


def motion_scales(recordings: list[DiagnosisData], r: float, l1: float, l2: float) -> dict[str, np.ndarray | float]:
    """RMS command per motor (N m), RMS joint speed per motor (rad/s) and RMS speed of the pivot P (m/s:
    the axle midpoint's r (w_r + w_l) / 2 along the chassis axis and l1 theta_dot across it), over the
    recordings."""
    u = np.concatenate([d.u for d in recordings])
    w = np.concatenate([np.where(np.isfinite(d.enc_vel), d.enc_vel, 0.0) if d.enc_vel is not None
                        else np.zeros_like(d.u) for d in recordings])
    v = r * 0.5 * (w[:, 0] + w[:, 1])
    thd = r * (w[:, 0] - w[:, 1]) / (2 * l2)
    return {"u_rms": np.sqrt(np.mean(u ** 2, axis=0)), "w_rms": np.sqrt(np.mean(w ** 2, axis=0)),
            "v_rms": float(np.sqrt(np.mean(v ** 2 + (l1 * thd) ** 2))), "u": u}


def format_with_std(v: float, s: float | None) -> str:
    """``v ± s`` to the precision of s (one significant digit, two when it starts with 1)."""
    if s is None or not np.isfinite(s) or s <= 0:
        return f"{v:.4g}"
    e = int(np.floor(np.log10(abs(s))))
    digits = max(0, -e + (1 if abs(s) / 10.0 ** e < 2 else 0))
    return f"{v:.{digits}f} ± {s:.{digits}f}"


_fmt = format_with_std


def _z(values: dict, std: dict, names) -> float:
    zs = [abs(values[n]) / std[n] for n in names if std.get(n) is not None and np.isfinite(std[n]) and std[n] > 0]
    return float(max(zs)) if zs else float("nan")


def significance(name: str, values: dict[str, float], std: dict[str, float], model: ExtendedModel,
                 recordings: list[DiagnosisData]) -> dict:
    """Physical impact of effect ``name`` with fitted ``values`` (± ``std``) on ``model``'s robot in these
    recordings (the diagnosis passes fitting and held-out runs: the motion the robot does):
    {statement, quantity, value, unit, threshold, size_over_std, matters}."""
    p = model.params
    sc = motion_scales(recordings, p.r, p.l1, p.l2)
    u_rms, w_rms = sc["u_rms"], sc["w_rms"]

    def torque(t_joint: float, motors, what: str, main: tuple[str, ...]):
        ref = float(np.mean(u_rms[list(motors)]))
        frac = abs(t_joint) / ref if ref > 0 else float("inf")
        where = "each wheel motor" if motors == WHEELS else "the pivot motor"
        return (f"{what}{abs(t_joint):.3g} N m at {where}, {100 * frac:.1f} % of its RMS command",
                "torque fraction", frac, "1", TORQUE_FRACTION, main)

    def clipped(levels: dict[int, float]):
        u = sc["u"]
        lost, ref = 0.0, 0.0
        for i, m in levels.items():
            lost += np.mean((u[:, i] - np.clip(u[:, i], -m, m)) ** 2)
            ref += u_rms[i] ** 2
        frac = float(np.sqrt(lost / ref)) if ref > 0 else 0.0
        share = max(float(np.mean(np.abs(u[:, i]) > m)) for i, m in levels.items())
        return frac, share

    v = values
    f = {k: _fmt(v[k], std.get(k)) for k in v}  # values with their std, for positions quoted in statements
    if name == "coulomb_wheels":
        out = torque(v["c_w"], WHEELS, "takes ", ("c_w",))
    elif name == "coulomb_pivot":
        out = torque(v["c_p"], PIVOT, "takes ", ("c_p",))
    elif name == "stribeck_wheels":
        out = torque(v["s_w"], WHEELS, f"near standstill (below ~{v['v_s']:.2g} rad/s) takes up to ", ("s_w",))
    elif name == "rolling_resistance":
        out = torque(v["c_rr"] * (p.m_c + p.m_p) * GRAVITY * 0.5 * p.r, WHEELS, "takes ", ("c_rr",))
    elif name == "caster_drag":
        where = ""
        if "x_c1" in v:
            known = all(np.isfinite(std.get(k, np.nan)) and std[k] < 0.1 for k in ("x_c1", "y_c1"))
            where = (f"caster at ({f['x_c1']}, {f['y_c1']}) m in B'; " if known
                     else "caster position not determined by the data; ")
            if "x_c2" in v:
                known = known and all(np.isfinite(std.get(k, np.nan)) and std[k] < 0.1 for k in ("x_c2", "y_c2"))
                where = (f"two casters at ({f['x_c1']}, {f['y_c1']}) and ({f['x_c2']}, {f['y_c2']}) m in B', "
                         "drag shared equally; " if known else "caster positions not determined by the data; ")
        out = torque(v["f_cst"] * p.r / 2, WHEELS, f"{where}takes ", ("f_cst",))
    elif name == "floor_slope":
        g = float(np.hypot(v["g_x"], v["g_y"]))
        out = torque((p.m_c + p.m_p) * g * p.r / 2, WHEELS,
                     f"a {np.rad2deg(np.arcsin(min(g / GRAVITY, 1.0))):.2f}° slope pulls {(p.m_c + p.m_p) * g:.3g} N "
                     "downhill: ", ("g_x", "g_y"))
    elif name == "air_drag":
        out = torque(v["c_air"] * sc["v_rms"] ** 2 * p.r / 2, WHEELS,
                     f"{v['c_air'] * sc['v_rms'] ** 2:.3g} N at the RMS speed {sc['v_rms']:.2g} m/s: ", ("c_air",))
    elif name in ("gain_right", "gain_left", "gain_pivot"):
        k = {"gain_right": "k_r", "gain_left": "k_l", "gain_pivot": "k_p"}[name]
        motor = {"gain_right": "right wheel", "gain_left": "left wheel", "gain_pivot": "pivot"}[name]
        out = (f"the {motor} motor delivers {100 * (1 + v[k]):.1f} % of its command",
               "torque fraction", abs(v[k]), "1", TORQUE_FRACTION, (k,))
    elif name in ("torque_saturation", "saturation_right", "saturation_left", "saturation_pivot"):
        keys = {"torque_saturation": {0: "u_max", 1: "u_max", 2: "u_max"}, "saturation_right": {0: "u_max_r"},
                "saturation_left": {1: "u_max_l"}, "saturation_pivot": {2: "u_max_p"}}[name]
        frac, share = clipped({i: v[k] for i, k in keys.items()})
        k0 = next(iter(keys.values()))
        out = (f"the limit clips {100 * share:.1f} % of the commands, {100 * frac:.1f} % of the RMS torque",
               "torque fraction", frac, "1", TORQUE_FRACTION, (k0,))
    elif name == "traction_limit":
        u = sc["u"][:, :2]
        T = v["t_trac"]
        lost = np.sqrt(np.mean((u - T * np.tanh(u / T)) ** 2)) / max(float(np.mean(u_rms[:2])), 1e-12)
        out = (f"{100 * lost:.1f} % of the RMS wheel torque does not reach the ground", "torque fraction",
               float(lost), "1", TORQUE_FRACTION, ("t_trac",))
    elif name == "wheel_friction_asymmetry":
        out = torque(v["db_w"] * float(np.mean(w_rms[:2])), WHEELS, "at the RMS wheel speed the difference is ",
                     ("db_w",))
    elif name == "current_lag":
        out = (f"the motor torques follow the commands {_fmt(1e3 * v['T_i'], 1e3 * std.get('T_i', np.nan))} ms late",
               "delay", v["T_i"], "s", DELAY, ("T_i",))
    elif name == "imu_latency":
        out = (f"IMU samples are {_fmt(1e3 * v['d_imu'], 1e3 * std.get('d_imu', np.nan))} ms old", "delay",
               v["d_imu"], "s", DELAY, ("d_imu",))
    elif name == "imu_bias":
        heading = abs(np.rad2deg(v["b_gz"]) * 60.0)
        pos = 0.5 * float(np.hypot(v["b_ax"], v["b_ay"])) * POSITION_HORIZON ** 2
        ratio = max(heading / HEADING_DRIFT, pos / POSITION_DRIFT)
        out = (f"gyro bias {_fmt(1e3 * v['b_gz'], 1e3 * std.get('b_gz', np.nan))} mrad/s: {heading:.2g}° of "
               f"heading per minute if integrated; accelerometer bias ({f['b_ax']}, {f['b_ay']}) m/s²: "
               f"{pos:.2g} m in {POSITION_HORIZON:g} s if integrated twice", "drift / threshold", ratio, "1", 1.0,
               ("b_ax", "b_ay", "b_gz"))
    elif name == "imu_lever_arm":
        d = float(np.hypot(v["d_x"], v["d_y"]))
        known = all(np.isfinite(std.get(k, np.nan)) for k in ("d_x", "d_y"))
        out = (f"the IMU sits {100 * d:.2g} cm from the pivot"
               + ("" if known else " (position not determined by the data)"), "distance", d, "m", LEVER_ARM,
               ("d_x", "d_y"))
    elif name == "imu_misalignment":
        out = (f"the IMU is turned by {_fmt(np.rad2deg(v['psi']), np.rad2deg(std.get('psi', np.nan)))}° about the "
               "vertical: that share of each acceleration appears on the other axis", "angle", abs(v["psi"]), "rad",
               MISALIGNMENT, ("psi",))
    elif name == "encoder_scale":
        e = max(abs(v["e_r"]), abs(v["e_l"]))
        out = (f"odometry off by up to {100 * e:.2g} % of the distance", "odometry fraction", e, "1", ODOMETRY_FRACTION,
               ("e_r", "e_l"))
    elif name == "wheel_radii":
        e = max(abs(v["dr_r"]), abs(v["dr_l"]))
        turn = np.rad2deg((v["dr_r"] - v["dr_l"]) / (2 * p.l2))
        out = (f"wheel radii {1e3 * p.r * (1 + v['dr_r']):.2f} mm (right), {1e3 * p.r * (1 + v['dr_l']):.2f} mm "
               f"(left) against {1e3 * p.r:.1f} mm: distance per wheel turn off by up to {100 * e:.2g} %, "
               f"{abs(turn):.2g}° of heading per metre driven with equal wheel turns", "odometry fraction", e, "1",
               ODOMETRY_FRACTION, ("dr_r", "dr_l"))
    elif name == "wheel_slip":
        ref = float(np.mean(w_rms[:2]))
        e = v["k_slip"] * float(np.mean(u_rms[:2])) / ref if ref > 0 else float("inf")
        out = (f"odometry {100 * e:.2g} % long at the RMS torque",
               "odometry fraction", e, "1", ODOMETRY_FRACTION, ("k_slip",))
    else:
        raise KeyError(f"no physical significance rule for effect '{name}'")
    statement, quantity, value, unit, threshold, main = out
    z = _z(values, std, main)
    matters = bool(value >= threshold and (not np.isfinite(z) or z >= Z_MIN) and np.isfinite(value))
    if np.isfinite(z) and z < Z_MIN:
        statement += f" (size only {z:.1f} of its standard deviations)"
    return {"statement": statement, "quantity": quantity, "value": float(value), "unit": unit,
            "threshold": float(threshold), "size_over_std": z, "matters": matters}
