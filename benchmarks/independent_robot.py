"""An Otbot simulator written independently of ``otbot_hw`` (no import of its model, simulator,
sensors or recording writer), to make recordings the diagnosis has never seen.

* **Parameters**: read from ``config/otbot.yaml`` with plain ``yaml``.
* **Dynamics**: Lagrange's equations with multipliers as one 9x9 linear system per
  evaluation, built here from body kinematics: the mass matrix from the Jacobians of the two
  centres of mass (chassis B, platform F) and the angular velocities (chassis theta_dot =
  alpha_dot - phi_p_dot, platform alpha_dot, wheels), the velocity-product term from the
  centripetal accelerations of B and F, the three rolling constraints from the velocities of
  the wheel centres C_r, C_l (rolling with each wheel's own radius) and of the axle midpoint
  M (no side slip). Integrated by classical RK4 on every zero-order-hold interval in steps of
  5 ms, 0.5 ms on intervals where the argument of a nearly hard sign (wheel or pivot rate, caster
  velocity) comes within 20 of its widths of zero; the system in scalar form solved by LAPACK.
  ``reference=True``: the same physics assembled from the body Jacobians (matrix form) by scipy's
  adaptive RK45 (rtol 1e-8) restarted on every interval, Brent's method for the slip split -- about
  10x slower; the default's recorded signals differ from it by < 2e-3 of the sensor noise
  (docs/diagnose.md).
* **Effects**, each in this file's own form: Coulomb friction with a nearly hard sign
  (tanh(w / 0.005 rad/s)); Stribeck excess s exp(-(w/v_s)^2) with that sign; rolling resistance
  as a force c_rr N at each wheel's contact, N = (m_c + m_p) g / 2; caster drag as forces at the
  contact points of one or several casters (direction v / sqrt(|v|^2 + (1 mm/s)^2)); slip with
  the traction torque T_max x / sqrt(1 + x^2), x = sigma / (k T_max) (sigma: wheel spin over
  rolling rate; linear creep sigma = k tau_g for small torques, saturating at T_max), the spin
  rate solved from the wheel's torque balance traction(sigma) = tau - friction(spin) - I_a psi_dd
  at every evaluation (Newton's method from the previous root, bracketed), iterated with the 9x9
  solve (quasi-static: the creep settles within k I_a ~ 0.3 ms), the slip angles integrated; floor
  slope as
  gravity on both centres of mass; quadratic air drag at the pivot; per-motor gain and hard
  saturation, a first-order current lag as three integrated states; unequal wheel radii in the
  constraints; viscous asymmetry of the wheels.
* **Sensors**: encoders read the wheel spin angles (x (1 + e) for a scale error) and the pivot
  angle; the IMU is the specific force of the sensor point D = P + R(alpha) d in axes turned by
  psi, plus biases, sampled d_imu late (from the integrator's dense output); paper noise levels.
* **Excitations**: random piecewise-constant torques (hold 0.15-0.8 s) for fitting, random
  smooth sums of sines for held-out runs.
* **Files**: the documented MCAP layout written with the plain ``mcap`` package.

``tests/test_diagnose_independent.py`` checks this simulator against the project's model
with no effect (they must agree: same physics, different derivation and integrator).
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp
from scipy.linalg.lapack import dgesv as _dgesv

ROOT = Path(__file__).resolve().parent.parent
G = 9.80665
SHARP = 0.005  # rad/s: width of the nearly hard friction sign
CASTER_EPS = 1e-3  # m/s
SIGMA_IMU = 1.37e-3 * np.sqrt(100.0)  # paper §4.3.2, m/s^2 and rad/s at 100 Hz
SIGMA_ENC_RATE = 0.01  # rad/s
#: s: the longest RK4 step of the default integration: smooth dynamics (slip included: its split is algebraic) /
#: with a nearly hard sign (Coulomb, Stribeck, rolling resistance, caster drag: RK4 loses its order across
#: them); the error against the reference (RK45, rtol 1e-8): docs/diagnose.md "Detection across excitations",
#: tested in tests/test_diagnose_independent.py
H_MAX = 5e-3
H_MAX_SHARP = 5e-4
#: widths of a nearly hard sign (SHARP, CASTER_EPS) within which the sharp step is taken (tanh(20): 1 - 1e-17)
SHARP_MARGIN = 20.0


def load_params(path: Path = ROOT / "config" / "otbot.yaml") -> dict[str, float]:
    """{symbol: value} from the parameter YAML (sections of {value, unit} entries)."""
    import yaml

    data = yaml.safe_load(Path(path).read_text())
    return {k: float(v["value"]) for sec in data.values() if isinstance(sec, dict) for k, v in sec.items()}


def with_load(p: dict, mass: float, x: float, y: float, inertia: float = 0.0) -> dict:
    """Platform parameters with a point-like load of ``inertia`` about its centre at (x, y) in B''."""
    m = p["m_p"] + mass
    xf, yf = (p["m_p"] * p["x_F"] + mass * x) / m, (p["m_p"] * p["y_F"] + mass * y) / m
    ip = (p["I_p"] + p["m_p"] * ((p["x_F"] - xf) ** 2 + (p["y_F"] - yf) ** 2) + inertia
          + mass * ((x - xf) ** 2 + (y - yf) ** 2))
    return {**p, "m_p": m, "x_F": xf, "y_F": yf, "I_p": ip}


@dataclass
class World:
    """What the simulated robot really has (this simulator's own terms; zero = absent)."""

    coulomb_w: float = 0.0  # N m, both wheel motors
    coulomb_p: float = 0.0  # N m, pivot motor
    stribeck: tuple[float, float] = (0.0, 0.5)  # (s N m, v_s rad/s), wheel motors
    c_rr: float = 0.0  # rolling-resistance coefficient
    casters: tuple[tuple[float, float], ...] = ((0.15, 0.0),)  # contact points in B' (m)
    caster_drag: float = 0.0  # N, shared equally by the casters
    slip_k: float = 0.0  # rad/(s N m): creep rate per traction torque
    slip_tmax: float = np.inf  # N m: traction limit per wheel
    #: knee of the traction curve (same creep slope 1 / slip_k and limit slip_tmax): "magic" x / sqrt(1 + x^2)
    #: (Pacejka, C = 1), "tanh" tanh x, "clip" a hard clip max(-1, min(x, 1))
    traction_curve: str = "magic"
    slope: tuple[float, float] = (0.0, 0.0)  # m/s^2, ground frame
    c_air: float = 0.0  # N s^2/m^2
    gain: tuple[float, float, float] = (0.0, 0.0, 0.0)  # delivered = (1 + k) command
    u_max: tuple[float, float, float] = (np.inf, np.inf, np.inf)  # N m per motor
    lag: float = 0.0  # s, current loop
    db_w: float = 0.0  # N m s/rad: b_r = b_w + db, b_l = b_w - db
    radius_change: tuple[float, float] = (0.0, 0.0)  # relative: r_i = r (1 + dr_i)
    imu_bias: tuple[float, float, float] = (0.0, 0.0, 0.0)  # m/s^2, m/s^2, rad/s
    imu_position: tuple[float, float] = (0.0, 0.0)  # m in B''
    imu_yaw: float = 0.0  # rad
    imu_latency: float = 0.0  # s
    encoder_scale: tuple[float, float] = (0.0, 0.0)
    params: dict = field(default_factory=dict)  # overrides of the nominal parameters (the true robot)
    # laws outside the diagnosis's catalog (issue 20 item 4)
    lin_drag: float = 0.0  # N s/m: linear drag force -c v at the pivot
    cogging: tuple[float, int] = (0.0, 1)  # (amplitude N m, cycles per turn): -A sin(n phi_r) on the right wheel
    pivot_deadzone: float = 0.0  # N m: the pivot drive delivers nothing below it, u - d sgn(u) above


def _knee(curve: str, x: float) -> tuple[float, float]:
    """(traction / limit, its slope in x) of the traction curve ``curve`` (``World.traction_curve``) at
    x = sigma / (k T); every curve has slope 1 at x = 0 and limit 1."""
    if curve == "magic":
        r = 1.0 + x * x
        return x / math.sqrt(r), 1.0 / (r * math.sqrt(r))
    if curve == "tanh":
        t = math.tanh(x)
        return t, 1.0 - t * t
    if curve == "clip":
        return (x, 1.0) if abs(x) < 1.0 else (math.copysign(1.0, x), 0.0)
    raise ValueError(f"unknown traction curve {curve!r} (magic, tanh, clip)")


def _solve(K: np.ndarray, b: np.ndarray) -> np.ndarray:
    """K x = b by LAPACK's dgesv (np.linalg.solve without its per-call checks)."""
    _, _, x, info = _dgesv(K, b)
    if info:
        raise np.linalg.LinAlgError(f"singular system (dgesv info {info})")
    return x


def _rot(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s], [s, c]])


class Otbot:
    """The true robot: parameters ``p`` and effects ``w``; states q (6), q_dot (6) [+ lag torques (3)]
    [+ slip rates (2), slip angles (2)]; wheel coordinates are rolling angles (= wheel angles without slip)."""

    def __init__(self, p: dict, w: World, reference: bool = False, h_max: float | None = None):
        """``reference``: the slow reference integration (Lagrange's 9x9 system assembled from the body Jacobians,
        scipy RK45 at rtol 1e-8 restarted on every sample, Brent's method for the slip split); default: the same
        equations in scalar form (``accelerations_fast``) by classical RK4 with steps of at most ``h_max``
        (default ``H_MAX_SHARP`` on the intervals near a nearly hard sign, ``H_MAX`` elsewhere), see ``run``."""
        self.p = {**p, **w.params}
        self.w = w
        self.slip = w.slip_k > 0 or np.isfinite(w.slip_tmax)
        self.radii = (self.p["r"] * (1 + w.radius_change[0]), self.p["r"] * (1 + w.radius_change[1]))
        self.n_lag = 3 if w.lag > 0 else 0
        self.reference = reference
        self.sharp = bool(w.coulomb_w or w.coulomb_p or w.stribeck[0] or w.c_rr or w.caster_drag)
        self.h_max = (H_MAX_SHARP if self.sharp else H_MAX) if h_max is None else h_max
        self._sigma_guess = [0.0, 0.0]

    # -- kinematics of points of the chassis (B' coordinates c) and of the platform (B'' coordinates c)
    def _chassis_point(self, q, qd, c):
        th, thd = q[2] - q[5], qd[2] - qd[5]
        d = _rot(th + np.pi / 2) @ c
        J = np.zeros((2, 6))
        J[:, :2] = np.eye(2)
        J[:, 2], J[:, 5] = d, -d
        return J, J @ qd, -thd ** 2 * (_rot(th) @ c)  # Jacobian, velocity, J_dot q_dot

    def _platform_point(self, q, qd, c):
        d = _rot(q[2] + np.pi / 2) @ c
        J = np.zeros((2, 6))
        J[:, :2] = np.eye(2)
        J[:, 2] = d
        return J, J @ qd, -qd[2] ** 2 * (_rot(q[2]) @ c)

    def _wheel_friction(self, i, w):
        """Motor friction torque (opposing) at wheel motor i turning at w rad/s."""
        p, e = self.p, self.w
        b = p["b_w"] + (e.db_w if i == 0 else -e.db_w)
        sg = np.tanh(w / SHARP)
        s, vs = e.stribeck
        return b * w + e.coulomb_w * sg + s * np.exp(-(w / vs) ** 2) * sg

    def traction(self, sigma):
        """Traction torque (N m) for a spin-over-rolling rate sigma (rad/s)."""
        k, T = self.w.slip_k, self.w.slip_tmax
        if not np.isfinite(T):
            return sigma / k
        x = sigma / (k * T) if k > 0 else sigma * 1e6
        return T * _knee(self.w.traction_curve, x)[0]

    def delivered(self, u):
        """Torque the drives settle to for command u (gain, then each motor's saturation)."""
        d = np.asarray(u, float) * (1.0 + np.asarray(self.w.gain))
        if self.w.pivot_deadzone:
            d[2] = np.sign(d[2]) * max(abs(d[2]) - self.w.pivot_deadzone, 0.0)
        return np.clip(d, -np.asarray(self.w.u_max), np.asarray(self.w.u_max))

    def spin_over_rolling(self, i, rolling_rate, tau, inertial):
        """Slip rate sigma (rad/s) of wheel i: root of tau - friction(rolling + sigma) - inertial - traction(sigma)
        (decreasing in sigma; inertial = I_a psi_dd), bracketed and solved by Brent's method."""
        from scipy.optimize import brentq

        def g(s):
            return tau - inertial - self._wheel_friction(i, rolling_rate + s) - self.traction(s)

        lo, hi = -1.0, 1.0
        while g(lo) < 0:
            lo *= 4
        while g(hi) > 0:
            hi *= 4
        return brentq(g, lo, hi, xtol=1e-12, rtol=1e-12)

    def accelerations(self, q, qd, tau):
        """(q_ddot (6,), slip rates sigma (2,) or None) from the 9x9 system."""
        p, e = self.p, self.w
        th = q[2] - q[5]
        thd = qd[2] - qd[5]
        e1, e2 = np.array([np.cos(th), np.sin(th)]), np.array([-np.sin(th), np.cos(th)])
        JB, vB, aB0 = self._chassis_point(q, qd, np.array([p["x_B"], p["y_B"]]))
        JF, vF, aF0 = self._platform_point(q, qd, np.array([p["x_F"], p["y_F"]]))
        w_th = np.array([0, 0, 1.0, 0, 0, -1.0])
        w_al = np.array([0, 0, 1.0, 0, 0, 0])
        M = p["m_c"] * JB.T @ JB + p["m_p"] * JF.T @ JF + p["I_c"] * np.outer(w_th, w_th) \
            + p["I_p"] * np.outer(w_al, w_al)
        M[3, 3] += p["I_a"]
        M[4, 4] += p["I_a"]
        h = p["m_c"] * JB.T @ aB0 + p["m_p"] * JF.T @ aF0
        Q = np.zeros(6)
        # pivot motor
        Q[5] += tau[2] - p["b_p"] * qd[5] - e.coulomb_p * np.tanh(qd[5] / SHARP)
        # wheels: motor torque minus friction at the wheel's spin, on the rolling angle (= the wheel angle
        # without slip); with slip the wheel spins sigma faster, sigma from the traction law (below)
        sigma = np.zeros(2)
        # constraints and their velocity terms
        rows, bias = [], []
        for i, (side, rad) in enumerate(((-1.0, self.radii[0]), (1.0, self.radii[1]))):
            c = np.array([-p["l1"], side * p["l2"]])
            Jc, vc, ac0 = self._chassis_point(q, qd, c)
            row = e1 @ Jc
            row[3 + i] -= rad
            rows.append(row)
            bias.append(thd * (e2 @ vc) + e1 @ ac0)
            if e.c_rr:
                n = (p["m_c"] + p["m_p"]) * G / 2
                Q += Jc.T @ (-e.c_rr * n * np.tanh((e1 @ vc) / (SHARP * rad)) * e1)
        Jm, vm, am0 = self._chassis_point(q, qd, np.array([-p["l1"], 0.0]))
        rows.append(e2 @ Jm)
        bias.append(-thd * (e1 @ vm) + e2 @ am0)
        A = np.array(rows)
        # floor effects
        if e.caster_drag:
            f = e.caster_drag / len(e.casters)
            for c in e.casters:
                Jc, vc, _ = self._chassis_point(q, qd, np.asarray(c, float))
                Q += Jc.T @ (-f * vc / np.sqrt(vc @ vc + CASTER_EPS ** 2))
        gs = np.asarray(e.slope, float)
        if gs.any():
            Q += JB.T @ (p["m_c"] * gs) + JF.T @ (p["m_p"] * gs)
        if e.c_air:
            v = qd[:2]
            Q[:2] -= e.c_air * np.linalg.norm(v) * v
        if e.lin_drag:
            Q[:2] -= e.lin_drag * qd[:2]
        if e.cogging[0]:
            Q[3] -= e.cogging[0] * np.sin(e.cogging[1] * q[3])
        K = np.zeros((9, 9))
        K[:6, :6], K[:6, 6:], K[6:, :6] = M, -A.T, A
        psidd = np.zeros(2)
        for _ in range(4 if self.slip else 1):
            if self.slip:
                sigma = np.array([self.spin_over_rolling(i, qd[3 + i], tau[i], p["I_a"] * psidd[i]) for i in range(2)])
            Qw = Q.copy()
            Qw[3] += tau[0] - self._wheel_friction(0, qd[3] + sigma[0])
            Qw[4] += tau[1] - self._wheel_friction(1, qd[4] + sigma[1])
            sol = np.linalg.solve(K, np.concatenate([Qw - h, -np.array(bias)]))
            psidd = sol[3:5]
        return sol[:6], (sigma if self.slip else None)

    # -- the fast path: the same equations in scalar form (no per-call Jacobian arrays), one 9x9 solve
    def _friction_fast(self, i, w):
        """(friction torque, its derivative in w) of wheel motor i at w rad/s (``_wheel_friction``)."""
        e = self.w
        b = self.p["b_w"] + (e.db_w if i == 0 else -e.db_w)
        f, df = b * w, b
        if e.coulomb_w or e.stribeck[0]:
            sg = math.tanh(w / SHARP)
            dsg = (1.0 - sg * sg) / SHARP
            f += e.coulomb_w * sg
            df += e.coulomb_w * dsg
            s, vs = e.stribeck
            if s:
                ex = s * math.exp(-(w / vs) ** 2)
                f += ex * sg
                df += ex * (dsg - 2.0 * w / vs ** 2 * sg)
        return f, df

    def _spin_fast(self, i, rolling_rate, rhs_torque):
        """Slip rate sigma of wheel i: root of rhs_torque - friction(rolling + sigma) - traction(sigma) (the root
        ``spin_over_rolling`` brackets), by Newton's method from the previous root, kept inside a bracket."""
        k, T = self.w.slip_k, self.w.slip_tmax
        inv_k = 1.0 / k if k > 0 else 1e6
        finite = np.isfinite(T)
        curve = self.w.traction_curve

        def g(s):
            f, df = self._friction_fast(i, rolling_rate + s)
            if finite and curve != "magic":
                v, dv = _knee(curve, s * inv_k / T)
                return rhs_torque - f - T * v, -df - inv_k * dv
            if finite:
                x = s * inv_k / T
                r = 1.0 + x * x
                return rhs_torque - f - T * x / math.sqrt(r), -df - inv_k / (r * math.sqrt(r))
            return rhs_torque - f - s * inv_k, -df - inv_k

        s = self._sigma_guess[i]
        lo, hi = -math.inf, math.inf
        for _ in range(60):
            v, dv = g(s)
            if v > 0:
                lo = s
            else:
                hi = s
            step = -v / dv
            if abs(step) <= 1e-13 + 1e-11 * abs(s):
                s += step
                break
            s_new = s + step
            if not lo < s_new < hi:  # outside the bracket: bisect (or widen while unbounded)
                s_new = (lo + hi) / 2 if np.isfinite(lo) and np.isfinite(hi) else s + 4 * step
            s = s_new
        self._sigma_guess[i] = s
        return s

    def _k_template(self):
        if getattr(self, "_k0", None) is None:
            K = np.zeros((9, 9))
            K[0, 0] = K[1, 1] = self.p["m_c"] + self.p["m_p"]
            K[3, 3] = K[4, 4] = self.p["I_a"]
            K[6, 3], K[7, 4] = -self.radii[0], -self.radii[1]
            self._k0 = K
        return self._k0

    def accelerations_fast(self, q, qd, tau):
        """``accelerations`` in scalar form: the same 9x9 system (mass matrix from the Jacobians of B and F,
        velocity-product terms, the three rolling constraints), with the constraint rows written out
        (e1 . d_c = -c_y, e2 . d_c = c_x for a chassis point c)."""
        p, e = self.p, self.w
        q, qd, tau = q.tolist(), qd.tolist(), list(tau)  # Python floats: scalar arithmetic without numpy overhead
        mc, mp = p["m_c"], p["m_p"]
        l1, l2 = p["l1"], p["l2"]
        al, th = q[2], q[2] - q[5]
        ald, thd = qd[2], qd[2] - qd[5]
        ct, st = math.cos(th), math.sin(th)
        ca, sa = math.cos(al), math.sin(al)
        xb, yb, xf, yf = p["x_B"], p["y_B"], p["x_F"], p["y_F"]
        dbx, dby = -st * xb - ct * yb, ct * xb - st * yb  # R(theta + pi/2) c_B
        dfx, dfy = -sa * xf - ca * yf, ca * xf - sa * yf
        abx, aby = -thd * thd * (ct * xb - st * yb), -thd * thd * (st * xb + ct * yb)  # J_dot q_dot of B, F
        afx, afy = -ald * ald * (ca * xf - sa * yf), -ald * ald * (sa * xf + ca * yf)
        K = self._k_template().copy()  # constant entries: total mass, wheel inertias, the radii in the constraints
        m = mc + mp
        db2, df2 = dbx * dbx + dby * dby, dfx * dfx + dfy * dfy
        K[0, 2] = K[2, 0] = mc * dbx + mp * dfx
        K[1, 2] = K[2, 1] = mc * dby + mp * dfy
        K[0, 5] = K[5, 0] = -mc * dbx
        K[1, 5] = K[5, 1] = -mc * dby
        K[2, 2] = mc * db2 + mp * df2 + p["I_c"] + p["I_p"]
        K[2, 5] = K[5, 2] = -mc * db2 - p["I_c"]
        K[5, 5] = mc * db2 + p["I_c"]
        h0, h1 = mc * abx + mp * afx, mc * aby + mp * afy
        hb = mc * (dbx * abx + dby * aby)
        h = [h0, h1, hb + mp * (dfx * afx + dfy * afy), 0.0, 0.0, -hb]
        # constraints: wheel i at c = (-l1, side l2): [ct, st, -c_y, -r_i at 3 + i, c_y]; axle midpoint: no side slip
        e1v, e2v = ct * qd[0] + st * qd[1], -st * qd[0] + ct * qd[1]
        # rows of A (wheel i: [ct, st, -c_y, -r_i at 3 + i, c_y]; the radii in the template) and -A^T
        K[6, 0], K[6, 1], K[6, 2], K[6, 5] = ct, st, l2, -l2
        K[7, 0], K[7, 1], K[7, 2], K[7, 5] = ct, st, -l2, l2
        K[8, 0], K[8, 1], K[8, 2], K[8, 5] = -st, ct, -l1, l1
        K[:6, 6:] = -K[6:, :6].T
        bias = (thd * e2v, thd * e2v, -thd * e1v)
        Q = [0.0, 0.0, 0.0, 0.0, 0.0, tau[2] - p["b_p"] * qd[5]]
        if e.coulomb_p:
            Q[5] -= e.coulomb_p * math.tanh(qd[5] / SHARP)
        if e.c_rr:
            n = m * G / 2
            for side, rad in ((-1.0, self.radii[0]), (1.0, self.radii[1])):
                cy = side * l2
                f = -e.c_rr * n * math.tanh((e1v - cy * thd) / (SHARP * rad))
                Q[0] += f * ct
                Q[1] += f * st
                Q[2] -= f * cy
                Q[5] += f * cy
        if e.caster_drag:
            fc = e.caster_drag / len(e.casters)
            for cx, cy in e.casters:
                dx, dy = -st * cx - ct * cy, ct * cx - st * cy
                vx, vy = qd[0] + dx * thd, qd[1] + dy * thd
                s = -fc / math.sqrt(vx * vx + vy * vy + CASTER_EPS ** 2)
                Fx, Fy = s * vx, s * vy
                Q[0] += Fx
                Q[1] += Fy
                Q[2] += dx * Fx + dy * Fy
                Q[5] -= dx * Fx + dy * Fy
        gx, gy = e.slope
        if gx or gy:
            Q[0] += m * gx
            Q[1] += m * gy
            gb = mc * (dbx * gx + dby * gy)
            Q[2] += gb + mp * (dfx * gx + dfy * gy)
            Q[5] -= gb
        if e.c_air:
            sp = math.hypot(qd[0], qd[1])
            Q[0] -= e.c_air * sp * qd[0]
            Q[1] -= e.c_air * sp * qd[1]
        if e.lin_drag:
            Q[0] -= e.lin_drag * qd[0]
            Q[1] -= e.lin_drag * qd[1]
        if e.cogging[0]:
            Q[3] -= e.cogging[0] * math.sin(e.cogging[1] * q[3])
        rhs = np.array([Q[0] - h[0], Q[1] - h[1], Q[2] - h[2], Q[3], Q[4], Q[5] - h[5], -bias[0], -bias[1], -bias[2]])
        sigma = [0.0, 0.0]
        psidd = [0.0, 0.0]
        for _ in range(4 if self.slip else 1):  # as the reference: the slip split iterated with the solve
            for i in range(2):
                if self.slip:
                    sigma[i] = self._spin_fast(i, qd[3 + i], tau[i] - p["I_a"] * psidd[i])
                rhs[3 + i] = Q[3 + i] + tau[i] - self._friction_fast(i, qd[3 + i] + sigma[i])[0]
            sol = _solve(K, rhs)
            psidd = sol[3:5].tolist()
        return sol[:6], (np.array(sigma) if self.slip else None)

    def rhs(self, z, u_del):
        q, qd = z[:6], z[6:12]
        k = 12
        if self.n_lag:
            tau = z[k:k + 3]
            dtau = (u_del - tau) / self.w.lag
            k += 3
        else:
            tau = u_del
        qdd, sigma = (self.accelerations if self.reference else self.accelerations_fast)(q, qd, tau)
        out = [qd, qdd]
        if self.n_lag:
            out.append(dtau)
        if self.slip:
            out.append(sigma)
        return np.concatenate(out)

    def state_size(self) -> int:
        return 12 + self.n_lag + (2 if self.slip else 0)

    def _sharp_points(self, z) -> list[tuple[np.ndarray, float]]:
        """The arguments of the nearly hard signs at state z, each with its width: wheel and pivot rates (rad/s;
        Coulomb, Stribeck, rolling resistance) and caster contact velocities (m/s)."""
        e, qd = self.w, z[6:12]
        out = []
        if e.coulomb_w or e.stribeck[0] or e.c_rr:
            out += [(qd[3:4], SHARP), (qd[4:5], SHARP)]
        if e.coulomb_p:
            out.append((qd[5:6], SHARP))
        if e.caster_drag:
            th, thd = z[2] - z[5], qd[2] - qd[5]
            for c in e.casters:
                out.append((qd[:2] + thd * (_rot(th + np.pi / 2) @ np.asarray(c, float)), CASTER_EPS))
        return out

    def _step(self, z, ud, dt) -> float:
        """RK4 step for the interval from z: h_max (the sharp step) when a nearly hard sign's argument comes
        within SHARP_MARGIN widths of zero on the straight line from z to its Euler prediction z + dt z_dot,
        H_MAX otherwise (always h_max in a world without a sharp sign or with h_max >= H_MAX)."""
        if self.h_max >= H_MAX or not self.sharp:
            return self.h_max
        z1 = z + dt * self.rhs(z, ud)
        for (a, wd), (b, _) in zip(self._sharp_points(z), self._sharp_points(z1)):
            d = b - a
            s = 0.0 if not d.any() else min(max(-(a @ d) / (d @ d), 0.0), 1.0)
            if np.linalg.norm(a + s * d) < SHARP_MARGIN * wd:
                return self.h_max
        return H_MAX

    def _rk4(self, z, ud, t0, t1, h_max=None):
        """Classical RK4 from t0 to t1 under the delivered command ud, in equal steps of at most h_max."""
        m = max(1, int(math.ceil((t1 - t0) / (h_max or self.h_max) - 1e-9)))
        h = (t1 - t0) / m
        for _ in range(m):
            k1 = self.rhs(z, ud)
            k2 = self.rhs(z + 0.5 * h * k1, ud)
            k3 = self.rhs(z + 0.5 * h * k2, ud)
            k4 = self.rhs(z + h * k3, ud)
            z = z + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        return z

    def run(self, U: np.ndarray, dt: float, controller=None) -> dict:
        """Simulate N ZOH intervals of commands U (N, 3) from rest: states and sensor-side signals at the
        N + 1 sample instants and at the instants d_imu earlier (IMU latency).

        ``controller(k, pos, vel) -> command (3,)``, if given, sets U[k] (filled in place) from the noise-free
        encoder reading at t_k (``encoder_reading``; slip rates with the command of the interval before):
        closed-loop runs.

        Default integration: RK4 in steps of at most ``h_max`` (intervals split at the IMU's latency instants);
        ``reference``: adaptive RK45 at rtol 1e-8 on every interval with its dense output."""
        n = len(U)
        z = np.zeros(self.state_size())
        sols, Z = [], [z.copy()]
        lat = self.w.imu_latency
        frac = (lat / dt) % 1.0 if lat > 0 else 0.0
        split = frac > 1e-9 and frac < 1 - 1e-9
        for k in range(n):
            if controller is not None:
                sig = self._outputs(z, U[k - 1])[1] if (self.slip and k) else np.zeros(2)
                U[k] = controller(k, *self.encoder_reading(z, sig))
            ud = self.delivered(U[k])
            t0, t1 = k * dt, (k + 1) * dt
            if self.reference:
                sol = solve_ivp(lambda _t, s, ud=ud: self.rhs(s, ud), (t0, t1), z, method="RK45",
                                rtol=1e-8, atol=1e-10, dense_output=lat > 0)
                if not sol.success:
                    raise RuntimeError(f"interval {k}: {sol.message}")
                z = sol.y[:, -1]
                sols.append(sol.sol)
            elif split:  # the state at t0 + (1 - frac) dt is an IMU sample instant minus the latency
                tm = t0 + (1.0 - frac) * dt
                h = self._step(z, ud, dt)
                zm = self._rk4(z, ud, t0, tm, h)
                sols.append(zm)
                z = self._rk4(zm, ud, tm, t1, h)
            else:
                z = self._rk4(z, ud, t0, t1, self._step(z, ud, dt))
            Z.append(z.copy())
        Z = np.array(Z)
        t = np.arange(n + 1) * dt

        def state_at(tq):
            """State at time tq and the interval whose command acts then (the sample's own at t_k)."""
            k = int(np.floor(tq / dt + 1e-9))
            if tq <= 0 or lat == 0 or abs(tq - k * dt) < 1e-12:
                k = min(max(k, 0), n)
                return Z[k], min(k, n - 1)
            if self.reference:
                return sols[k](tq), k
            assert split and abs(tq - (k + 1.0 - frac) * dt) < 1e-9 * dt + 1e-12, tq
            return sols[k], k

        imu = [state_at(tq) for tq in t - lat]
        enc = [self._outputs(Z[k], U[min(k, n - 1)]) for k in range(n + 1)]
        return {"t": t, "Z": Z, "imu_state": np.array([s for s, _ in imu]),
                "qdd": np.array([self._outputs(s, U[k])[0] for s, k in imu]),
                "sigma": np.array([s for _, s in enc])}

    def encoder_reading(self, z, sigma) -> tuple[np.ndarray, np.ndarray]:
        """Noise-free encoder angles and rates (3,) at state z with wheel slip rates sigma (2,) (``sensors``)."""
        pos, vel = z[3:6].copy(), z[9:12].copy()
        if self.slip:
            k = 12 + self.n_lag
            pos[:2] += z[k:k + 2]
            vel[:2] += sigma
        for i in range(2):
            pos[i] *= 1.0 + self.w.encoder_scale[i]
            vel[i] *= 1.0 + self.w.encoder_scale[i]
        return pos, vel

    def _outputs(self, s, u):
        """(q_ddot, slip rates) at state s with command u acting."""
        tau = s[12:15] if self.n_lag else self.delivered(u)
        qdd, sigma = (self.accelerations if self.reference else self.accelerations_fast)(s[:6], s[6:12], tau)
        return qdd, (sigma if sigma is not None else np.zeros(2))

    def sensors(self, run: dict, rng: np.random.Generator, enc_noise: np.ndarray | None = None) -> dict:
        """Encoder angles/rates (N, 3) and IMU specific force/rate (N, 3), noisy. ``enc_noise``: the encoder-rate
        noise (N, 3) rad/s drawn beforehand (a closed-loop run, whose controller saw it); default drawn here."""
        Z, e = run["Z"], self.w
        pos, vel = Z[:, 3:6].copy(), Z[:, 9:12].copy()
        if self.slip:
            k = 12 + self.n_lag
            pos[:, :2] += Z[:, k:k + 2]
            vel[:, :2] += run["sigma"]
        for i in range(2):
            pos[:, i] *= 1.0 + e.encoder_scale[i]
            vel[:, i] *= 1.0 + e.encoder_scale[i]
        S, A = run["imu_state"], run["qdd"]
        gs = np.asarray(e.slope, float)
        d = np.asarray(e.imu_position, float)
        a, ad, add = S[:, 2], S[:, 8], A[:, 2]
        ca, sa = np.cos(a), np.sin(a)
        # a_D = a_P + alpha_dd R(alpha + pi/2) d - alpha_d^2 R(alpha) d, then in axes turned by alpha + psi
        rdx, rdy = ca * d[0] - sa * d[1], sa * d[0] + ca * d[1]
        ax = A[:, 0] - add * rdy - ad ** 2 * rdx - gs[0]
        ay = A[:, 1] + add * rdx - ad ** 2 * rdy - gs[1]
        cb, sb = np.cos(a + e.imu_yaw), np.sin(a + e.imu_yaw)
        acc = np.empty((len(S), 3))
        acc[:, 0] = cb * ax + sb * ay + e.imu_bias[0]
        acc[:, 1] = -sb * ax + cb * ay + e.imu_bias[1]
        acc[:, 2] = np.sqrt(G ** 2 - gs @ gs)
        gyro = np.zeros((len(S), 3))
        gyro[:, 2] = S[:, 8] + e.imu_bias[2]
        acc += SIGMA_IMU * rng.standard_normal(acc.shape)
        gyro += SIGMA_IMU * rng.standard_normal(gyro.shape)
        vel += SIGMA_ENC_RATE * rng.standard_normal(vel.shape) if enc_noise is None else enc_noise
        return {"pos": pos, "vel": vel, "acc": acc, "gyro": gyro}


def piecewise_torques(duration: float, dt: float, seed: int) -> np.ndarray:
    """Random piecewise-constant torques (N, 3): holds of 0.15-0.8 s, wheels within +-4 N m, pivot +-2.5 N m."""
    rng = np.random.default_rng(seed)
    n = int(round(duration / dt))
    out = np.empty((n, 3))
    k = 0
    while k < n:
        hold = int(rng.uniform(0.15, 0.8) / dt)
        out[k:k + hold] = rng.uniform(-1, 1, 3) * np.array([4.0, 4.0, 2.5])
        k += hold
    return out


def smooth_torques(duration: float, dt: float, seed: int) -> np.ndarray:
    """Random smooth torques (N, 3): five sines 0.1-1.2 Hz per motor, peaks 3.5 (wheels) and 2 N m (pivot)."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(round(duration / dt))) * dt
    out = np.empty((len(t), 3))
    for j, peak in enumerate((3.5, 3.5, 2.0)):
        f = rng.uniform(0.1, 1.2, 5)
        s = sum(rng.uniform(0.3, 1.0) * np.sin(2 * np.pi * fi * t + rng.uniform(0, 6.3)) for fi in f)
        out[:, j] = peak * s / np.max(np.abs(s))
    return out


def reference_twist(duration: float, dt: float, seed: int) -> np.ndarray:
    """A random smooth platform twist (N, 3) to track, in the platform frame B'': v_x, v_y (m/s) and the yaw
    rate (rad/s), each a sum of four sines 0.05-0.4 Hz with peaks 0.3 m/s, 0.3 m/s and 0.5 rad/s, faded in over
    the first 0.5 s (from rest)."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(round(duration / dt))) * dt
    out = np.empty((len(t), 3))
    for j, peak in enumerate((0.3, 0.3, 0.5)):
        s = sum(rng.uniform(0.3, 1.0) * np.sin(2 * np.pi * f * t + rng.uniform(0, 6.3))
                for f in rng.uniform(0.05, 0.4, 4))
        out[:, j] = peak * s / max(np.max(np.abs(s)), 1e-9)
    return out * np.minimum(t / 0.5, 1.0)[:, None]


class TwistController:
    """A velocity loop as a user would write it, no dynamic model (computed-torque-free): the platform twist
    measured from the noisy encoder rates by the nominal kinematics, nu = (omega_r, omega_l, phi_p_dot) ->
    v'' = J(phi_p) nu (u_x = r (omega_r + omega_l) / 2, theta_dot = r (omega_r - omega_l) / (2 l2), u_y =
    l1 theta_dot in B', turned by -phi_p; yaw rate theta_dot + phi_p_dot), a PI on its error -- a wrench
    F = K_p e + K_i int e at P in B'' (N, N, N m; the integral is a PD on the pose error by odometry) --
    applied through the transpose of the kinematic map, tau = J^T F, clipped to +-8, +-8, +-4 N m."""

    KP = np.array([800.0, 800.0, 40.0])  # N/(m/s), N/(m/s), N m/(rad/s)
    KI = np.array([1600.0, 1600.0, 80.0])  # N/m, N/m, N m/rad
    LIMIT = np.array([8.0, 8.0, 4.0])  # N m

    def __init__(self, p: dict, reference: np.ndarray, dt: float, rate_noise: np.ndarray):
        self.p, self.ref, self.dt, self.noise = p, reference, dt, rate_noise
        self.integral = np.zeros(3)

    def jacobian(self, phi_p: float) -> np.ndarray:
        r, l1, l2 = self.p["r"], self.p["l1"], self.p["l2"]
        chassis = np.array([[r / 2, r / 2], [l1 * r / (2 * l2), -l1 * r / (2 * l2)]])
        J = np.zeros((3, 3))
        J[:2, :2] = _rot(-phi_p) @ chassis
        J[2] = (r / (2 * l2), -r / (2 * l2), 1.0)
        return J

    def __call__(self, k: int, pos: np.ndarray, vel: np.ndarray) -> np.ndarray:
        J = self.jacobian(pos[2])
        err = self.ref[k] - J @ (vel + self.noise[k])
        self.integral += err * self.dt
        return np.clip(J.T @ (self.KP * err + self.KI * self.integral), -self.LIMIT, self.LIMIT)


def closed_loop(robot: Otbot, duration: float, dt: float, seed: int, p_controller: dict | None = None,
                noise_seed=None):
    """A closed-loop run: the robot tracking ``reference_twist(seed)`` with ``TwistController`` (nominal
    parameters ``p_controller``, default the parameter file) on the encoder rates it records (the same noise).
    Returns the commands (N, 3) and the noisy sensors (``Otbot.sensors``). The noise draws come from
    ``noise_seed`` (anything ``numpy.random.default_rng`` takes) when given, else IMU seed + 1000 and encoder
    rates seed + 2000."""
    n = int(round(duration / dt))
    enc_rng = np.random.default_rng(seed + 2000 if noise_seed is None else [2000, *np.atleast_1d(noise_seed)])
    noise = SIGMA_ENC_RATE * enc_rng.standard_normal((n + 1, 3))
    ctl = TwistController(p_controller or load_params(), reference_twist(duration, dt, seed), dt, noise)
    U = np.zeros((n, 3))
    run = robot.run(U, dt, controller=ctl)
    imu_rng = np.random.default_rng(seed + 1000 if noise_seed is None else noise_seed)
    return U, robot.sensors(run, imu_rng, enc_noise=noise)


def write_mcap(path: Path, dt: float, U: np.ndarray, sens: dict, fixture: str = "floor") -> None:
    """The documented format with the plain mcap writer (docs/recording-format.md §1-5): command, joints, IMU,
    metadata format, format_version, sample_period, fixture, source only (no truth)."""
    from mcap.writer import CompressionType, Writer

    n = len(sens["pos"])
    Uf = np.vstack([U, U[-1:]])
    with open(path, "wb") as fh:
        w = Writer(fh, compression=CompressionType.NONE, use_chunking=False)
        w.start(profile="otbot", library="independent test writer")
        w.add_metadata("otbot", {"format": json.dumps("otbot-recording"), "format_version": "1",
                                 "sample_period": json.dumps(dt), "fixture": json.dumps(fixture),
                                 "source": json.dumps("benchmarks/independent_robot.py")})
        ch = {}
        for topic, schema in (("/otbot/command", "otbot.Command"), ("/otbot/joints", "otbot.Joints"),
                              ("/otbot/imu", "otbot.Imu")):
            sid = w.register_schema(name=schema, encoding="jsonschema", data=b"{}")
            ch[topic] = w.register_channel(topic=topic, message_encoding="json", schema_id=sid)
        for k in range(n):
            tk = k * dt
            stamp = int(round(tk * 1e9))
            msgs = {"/otbot/command": {"t": tk, "torque": [float(v) for v in Uf[k]]},
                    "/otbot/joints": {"t": tk, "position": [float(v) for v in sens["pos"][k]],
                                      "velocity": [float(v) for v in sens["vel"][k]]},
                    "/otbot/imu": {"t": tk, "accel": [float(v) for v in sens["acc"][k]],
                                   "gyro": [float(v) for v in sens["gyro"][k]]}}
            for topic, m in msgs.items():
                w.add_message(channel_id=ch[topic], log_time=stamp, publish_time=stamp, sequence=k,
                              data=json.dumps(m).encode())
        w.finish()


def record(path: Path, world: World, kind: str, seed: int, duration: float = 10.0, dt: float = 0.01,
           params: dict | None = None) -> None:
    """Simulate one run (``kind`` piecewise / smooth torques) of the true robot and write it."""
    U = piecewise_torques(duration, dt, seed) if kind == "piecewise" else smooth_torques(duration, dt, seed)
    robot = Otbot(params or load_params(), world)
    sens = robot.sensors(robot.run(U, dt), np.random.default_rng(seed + 1000))
    write_mcap(path, dt, U, sens)
