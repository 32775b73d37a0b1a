"""The extended model's effect catalog: names, units, bounds and the flat effect vector.

The paper (§1.5.2) assumes ideal torque motors, no caster dynamics, perfect rolling,
a flat floor and viscous motor friction only. This module adds those effects back,
each switched off by a zero parameter, without touching the compiled paper model:
physics enters through its ``gen`` hook (an extra generalized force, 6,), actuator
effects transform the commanded torque, sensor effects transform the outputs.

Effect parameters form one flat vector ``eff`` (order ``EFFECT_PARAM_NAMES``, all
zeros = the paper's model):

=============  =========  ====================================================================
name           unit       meaning
=============  =========  ====================================================================
c_r, c_l, c_p  N m        Coulomb friction at the right/left wheel and pivot motor shafts
s_w            N m        Stribeck excess friction at both wheel motors, s_w exp(-(w/v_s)^2) sgn w
v_s            rad/s      Stribeck velocity (only used when s_w != 0)
c_rr           1          rolling-resistance coefficient: torque c_rr (m_c+m_p) g / 2 r per wheel
f_cst          N          caster drag: a Coulomb-like force at the caster point opposing its velocity
k_slip         rad/(s N m) longitudinal slip: wheel spins k_slip * (ground torque) faster than it rolls
g_x, g_y       m/s^2      floor slope: in-plane gravity component, ground frame (recording start frame)
c_air          N s^2/m^2  air drag at the pivot: F = -c_air |v| v
k_r, k_l, k_p  1          torque gain error: delivered torque = (1 + k) * command
u_max_r, ...   N m        torque saturation of the right/left wheel and pivot motors (0 = none;
  u_max_l,                ``u_max`` sets all three)
  u_max_p
T_i            s          current-loop lag: first-order lag of the delivered torque (0 = none)
db_w           N m s/rad  viscous asymmetry: b_right = b_w + db_w, b_left = b_w - db_w
dr_r, dr_l     1          wheel radii: r_right = r (1 + dr_r), r_left = r (1 + dr_l) (r: the nominal radius)
t_trac         N m        traction limit of each wheel: ground torque t_trac tanh(h(y)), y = slip / (k_slip t_trac), creep
                          slope 1 / k_slip (0 = none; the knee h: kn_trac, ``slip_law``)
kn_trac        1          knee of the traction curve (with t_trac), -3..5: 0 = magic formula C = 1, y / sqrt(1 + y^2)
                          (h = asinh); 1 = tanh y (h = y); 3 = a hard clip (h = atanh); < 0 softer than the magic formula
n_cst          1          number of casters (1..4) sharing the caster drag f_cst equally
x_c1 .. y_c4   m          caster contact points in the chassis frame B' (from the robot configuration)
c_lin          N s/m      linear drag at the pivot: F = -c_lin v (discovered law)
dz_r, dz_l,    N m        drive dead zone: delivered = sgn(u) max(|u| - dz, 0) (discovered law)
  dz_p
ts_r, ts_l,    N m        soft torque limit: delivered = ts tanh(u / ts) (0 = none; discovered law)
  ts_p
cog_r, ...     N m        cogging torque -cog sin(cogn phi + cogph) at the right/left wheel and pivot
cogn_r, ...    1/turn     cogging cycles per turn (whole number; 0 = none)
cogph_r, ...   rad        cogging phase
b_ax, b_ay     m/s^2      IMU accelerometer bias (x, y of the IMU frame)
b_gz           rad/s      gyro bias (z)
d_x, d_y       m          IMU position in the platform frame B'' (lever arm from the pivot)
psi            rad        IMU yaw misalignment: IMU frame = B'' rotated by psi about z
d_imu          s          IMU latency: the IMU sample stamped t_k was taken at t_k - d_imu
e_r, e_l       1          encoder scale error of the wheel encoders: reading = (1 + e) * angle
=============  =========  ====================================================================

The physics is ``otbot_hw.model.effect_physics``, the sensor effects ``otbot_hw.model.sensor_model``,
the model object and its YAML file ``otbot_hw.model.effects``.
"""
from __future__ import annotations

import numpy as np

__all__ = [
    'B_AX', 'B_AY', 'B_GZ', 'CASTER_POSITION', 'C_AIR', 'C_L', 'C_P', 'C_R', 'C_RR', 'DB_W', 'DR_L', 'DR_R',
    'D_IMU', 'D_X', 'D_Y', 'EFFECT_BOUNDS', 'EFFECT_INDEX', 'EFFECT_PARAMS', 'EFFECT_PARAM_NAMES',
    'EFFECT_UNITS', 'E_L', 'E_R', 'F_CST', 'GEOMETRY_PARAMS', 'G_X', 'G_Y', 'K_L', 'K_P', 'K_R', 'K_SLIP',
    'MAX_CASTERS', 'N_CST', 'N_EFFECT', 'PSI', 'S_W', 'TIED_PARAMS', 'T_I', 'T_TRAC', 'U_MAX_L', 'U_MAX_P',
    'U_MAX_R', 'V_S', 'C_LIN', 'DZ_R', 'TS_R', 'COG_R', 'COGN_R', 'COGPH_R', 'KN_TRAC', 'KN_TRAC_BOUNDS', 'DISCOVERED_PARAMS', 'MAX_COGN', 'WIDTH_MIN_CASTER', 'WIDTH_MIN_PIVOT', 'WIDTH_MIN_WHEEL', 'WIDTH_PER_NM_PIVOT',
    'WIDTH_PER_NM_WHEEL', 'WIDTH_PER_N_CASTER', 'X_C1', 'effect_vector', 'parameter_bounds', 'parameter_unit']

WIDTH_PER_NM_PIVOT = 0.005  # rad/s per N m of friction level: smoothed sign width at the pivot motor
WIDTH_PER_NM_WHEEL = 0.025  # rad/s per N m ... at a wheel motor
WIDTH_MIN_PIVOT = 0.001  # rad/s, narrowest sign at the pivot
WIDTH_MIN_WHEEL = 0.002  # rad/s, narrowest sign at a wheel
WIDTH_PER_N_CASTER = 5e-5  # m/s per N of caster drag: smoothed direction of a caster contact
WIDTH_MIN_CASTER = 1e-3  # m/s
CASTER_POSITION = (0.15, 0.0)  # m, default single caster contact in the chassis frame B'
MAX_CASTERS = 4
MAX_COGN = 64  # cogging cycles per turn, at most
KN_TRAC_BOUNDS = (-3.0, 5.0)  # knee of the traction curve: 0 magic formula, 1 tanh, 3 a hard clip, < 0 softer, > 3
# reaching the limit before y = 1 (the clip inside the bounds: a fit on a bound is judged inadequate)

_MOTORS = (("r", "right wheel motor"), ("l", "left wheel motor"), ("p", "pivot motor"))
#: (name, unit, lower bound, upper bound, description)
EFFECT_PARAMS: tuple[tuple[str, str, float, float, str], ...] = (
    ("c_r", "N m", 0.0, 2.0, "Coulomb friction, right wheel motor"),
    ("c_l", "N m", 0.0, 2.0, "Coulomb friction, left wheel motor"),
    ("c_p", "N m", 0.0, 2.0, "Coulomb friction, pivot motor"),
    ("s_w", "N m", 0.0, 2.0, "Stribeck excess friction, wheel motors"),
    ("v_s", "rad/s", 0.05, 5.0, "Stribeck velocity"),
    ("c_rr", "1", 0.0, 0.1, "rolling-resistance coefficient"),
    ("f_cst", "N", 0.0, 200.0, "caster drag force"),
    ("k_slip", "rad/(s N m)", 0.0, 1.0, "longitudinal slip rate per transmitted torque"),
    ("g_x", "m/s^2", -2.0, 2.0, "floor slope: gravity component along ground x"),
    ("g_y", "m/s^2", -2.0, 2.0, "floor slope: gravity component along ground y"),
    ("c_air", "N s^2/m^2", 0.0, 50.0, "air drag coefficient at the pivot"),
    ("k_r", "1", -0.5, 0.5, "torque gain error, right wheel"),
    ("k_l", "1", -0.5, 0.5, "torque gain error, left wheel"),
    ("k_p", "1", -0.5, 0.5, "torque gain error, pivot"),
    ("u_max_r", "N m", 0.0, 100.0, "torque saturation, right wheel motor (0 = none)"),
    ("u_max_l", "N m", 0.0, 100.0, "torque saturation, left wheel motor (0 = none)"),
    ("u_max_p", "N m", 0.0, 100.0, "torque saturation, pivot motor (0 = none)"),
    ("T_i", "s", 0.0, 0.2, "current-loop time constant (0 = none)"),
    ("db_w", "N m s/rad", -0.2, 0.2, "viscous friction asymmetry of the wheels"),
    ("dr_r", "1", -0.1, 0.1, "right wheel radius change relative to the nominal r"),
    ("dr_l", "1", -0.1, 0.1, "left wheel radius change relative to the nominal r"),
    ("t_trac", "N m", 0.0, 50.0, "traction limit per wheel (0 = none)"),
    ("b_ax", "m/s^2", -2.0, 2.0, "accelerometer bias x"),
    ("b_ay", "m/s^2", -2.0, 2.0, "accelerometer bias y"),
    ("b_gz", "rad/s", -0.5, 0.5, "gyro bias z"),
    ("d_x", "m", -0.5, 0.5, "IMU position x in B''"),
    ("d_y", "m", -0.5, 0.5, "IMU position y in B''"),
    ("psi", "rad", -0.5, 0.5, "IMU yaw misalignment"),
    ("d_imu", "s", 0.0, 0.1, "IMU latency"),
    ("e_r", "1", -0.2, 0.2, "right wheel encoder scale error"),
    ("e_l", "1", -0.2, 0.2, "left wheel encoder scale error"),
    ("n_cst", "1", 1.0, float(MAX_CASTERS), "number of casters"),
) + tuple((f"{a}_c{i}", "m", -1.0, 1.0, f"caster {i} contact {a} in B'") for i in range(1, MAX_CASTERS + 1)
          for a in ("x", "y")) + (
    # laws beyond the catalog (otbot_hw.diagnose.discover writes them into a model file)
    ("c_lin", "N s/m", 0.0, 500.0, "linear drag coefficient at the pivot"),
) + tuple((f"dz_{j}", "N m", 0.0, 10.0, f"drive dead zone, {m}") for j, m in _MOTORS) \
  + tuple((f"ts_{j}", "N m", 0.0, 100.0, f"soft torque limit ts tanh(u / ts), {m} (0 = none)") for j, m in _MOTORS) \
  + tuple((f"cog_{j}", "N m", -10.0, 10.0, f"cogging amplitude, {m}") for j, m in _MOTORS) \
  + tuple((f"cogn_{j}", "1/turn", 0.0, float(MAX_COGN), f"cogging cycles per turn, {m}") for j, m in _MOTORS) \
  + tuple((f"cogph_{j}", "rad", -10.0, 10.0, f"cogging phase, {m}") for j, m in _MOTORS) + (
    # appended last so that no earlier index moves (saved effect vectors and models keep their meaning)
    ("kn_trac", "1", *KN_TRAC_BOUNDS, "traction curve knee: 0 magic formula, 1 tanh, 3 hard clip, < 0 softer"),
)
EFFECT_PARAM_NAMES: tuple[str, ...] = tuple(p[0] for p in EFFECT_PARAMS)
EFFECT_INDEX: dict[str, int] = {n: i for i, n in enumerate(EFFECT_PARAM_NAMES)}
EFFECT_UNITS: dict[str, str] = {p[0]: p[1] for p in EFFECT_PARAMS}
EFFECT_BOUNDS: dict[str, tuple[float, float]] = {p[0]: (p[2], p[3]) for p in EFFECT_PARAMS}
N_EFFECT = len(EFFECT_PARAMS)
(C_R, C_L, C_P, S_W, V_S, C_RR, F_CST, K_SLIP, G_X, G_Y, C_AIR, K_R, K_L, K_P, U_MAX_R, U_MAX_L, U_MAX_P, T_I, DB_W,
 DR_R, DR_L, T_TRAC, B_AX, B_AY, B_GZ, D_X, D_Y, PSI, D_IMU, E_R, E_L, N_CST) = range(EFFECT_INDEX["n_cst"] + 1)
X_C1 = N_CST + 1  # x_ci at X_C1 + 2 (i - 1), y_ci one after
C_LIN = X_C1 + 2 * MAX_CASTERS
DZ_R = C_LIN + 1  # dz_r, dz_l, dz_p
TS_R = DZ_R + 3  # ts_r, ts_l, ts_p
COG_R = TS_R + 3  # cog_r, cog_l, cog_p
COGN_R = COG_R + 3
COGPH_R = COGN_R + 3
KN_TRAC = COGPH_R + 3  # knee of the traction curve (catalog, after the discovered laws)
#: the entries of the laws beyond the catalog (``otbot_hw.diagnose.discover``): all zero = none
DISCOVERED_PARAMS: tuple[str, ...] = EFFECT_PARAM_NAMES[C_LIN:KN_TRAC]
#: effect entries that describe where things are, not an effect (active only with their effect)
GEOMETRY_PARAMS: tuple[str, ...] = ("n_cst",) + tuple(n for n in EFFECT_PARAM_NAMES if n[1:3] == "_c" and n[3:].isdigit())

def effect_vector(values: dict[str, float] | None = None) -> np.ndarray:
    """Flat effect vector (N_EFFECT,) from ``{name: value}``; unnamed effects are 0 (v_s defaults 0.5)."""
    eff = np.zeros(N_EFFECT)
    eff[V_S] = 0.5
    eff[N_CST] = 1.0
    eff[X_C1], eff[X_C1 + 1] = CASTER_POSITION
    for k, v in (values or {}).items():
        if k not in EFFECT_INDEX:
            raise ValueError(f"unknown effect parameter '{k}' (known: {', '.join(EFFECT_PARAM_NAMES)})")
        if not np.isfinite(v):
            raise ValueError(f"effect parameter {k} must be finite, got {v}")
        eff[EFFECT_INDEX[k]] = float(v)
    if eff[V_S] <= 0:
        raise ValueError(f"v_s must be > 0 rad/s, got {eff[V_S]}")
    for i in (DR_R, DR_L):
        if abs(eff[i]) >= 0.5:
            raise ValueError(f"{EFFECT_PARAM_NAMES[i]} must be in (-0.5, 0.5), got {eff[i]}")
    if eff[N_CST] not in range(1, MAX_CASTERS + 1):
        raise ValueError(f"n_cst must be a whole number of casters 1..{MAX_CASTERS}, got {eff[N_CST]}")
    if not KN_TRAC_BOUNDS[0] <= eff[KN_TRAC] <= KN_TRAC_BOUNDS[1]:
        raise ValueError(f"kn_trac (traction curve knee: 0 magic formula, 1 tanh, 3 hard clip) must be in "
                         f"[{KN_TRAC_BOUNDS[0]:g}, {KN_TRAC_BOUNDS[1]:g}], got {eff[KN_TRAC]}")
    for j in range(3):
        n = eff[COGN_R + j]
        if n != round(n) or not 0 <= n <= MAX_COGN or (eff[COG_R + j] != 0.0 and n == 0):
            raise ValueError(f"{EFFECT_PARAM_NAMES[COGN_R + j]} must be a whole number of cycles per turn "
                             f"1..{MAX_COGN} with a cogging amplitude, got {n}")
    return eff


#: Catalog parameters that set several effect-vector entries at once (tied values).
TIED_PARAMS: dict[str, tuple[str, ...]] = {"c_w": ("c_r", "c_l"), "u_max": ("u_max_r", "u_max_l", "u_max_p")}


def parameter_unit(name: str) -> str:
    """Unit of a nominal, effect or tied parameter name."""
    from otbot_hw.params import UNITS

    if name in TIED_PARAMS:
        return EFFECT_UNITS[TIED_PARAMS[name][0]]
    return EFFECT_UNITS.get(name) or UNITS[name]


def parameter_bounds(name: str) -> tuple[float, float]:
    """Physical bounds of a nominal, effect or tied parameter."""
    from otbot_hw.params import _RULES

    if name in TIED_PARAMS:
        return EFFECT_BOUNDS[TIED_PARAMS[name][0]]
    if name in EFFECT_BOUNDS:
        return EFFECT_BOUNDS[name]
    rule = _RULES[name]
    return (1e-9, np.inf) if rule == "positive" else (0.0, np.inf) if rule == "nonnegative" else (-np.inf, np.inf)
