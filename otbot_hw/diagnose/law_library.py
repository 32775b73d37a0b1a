"""The library of laws beyond the catalog that ``discover`` selects from: each law a group of columns with one
physical meaning, the model entries it writes (``otbot_hw.model.effect_catalog``: ``c_lin``, ``dz_*``,
``ts_*``, ``cog_*``/``cogn_*``/``cogph_*`` or catalog entries) and what it does; the per-recording basis the
columns are built from; the model with the discovered laws.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from otbot_hw.diagnose.data import DiagnosisData
from otbot_hw.diagnose.residuals import estimate_motion, integral_rate, torque_residual
from otbot_hw.model.effects import ExtendedModel
from otbot_hw.model.kinematics import fik_entries

JOINTS = ("r", "l", "p")
SIGN_WIDTH = 0.02  # rad/s
HARMONICS = (1, 2, 3, 4, 6, 8)  # cogging cycles per turn tried
DEADZONE_GRID = tuple(float(v) for v in np.geomspace(0.05, 3.0, 16))  # N m
SOFT_GRID = tuple(float(v) for v in np.geomspace(1.0, 12.0, 12))  # N m
SHAPE_COEF = (0.6, 1.5)  # a dead-zone or soft-limit coefficient outside this is not that law
EDGE = 0.1  # s dropped at each end (filter edges)

#: what each law does (torque, drift, odometry), for the report
MEANING = {
    "cogging": "a torque ripple with the motor's angle: rate wobble at n cycles per turn, no net drift",
    "dead_zone": "commands below the width deliver nothing: the joint does not start, small corrections are lost "
                 "(the path drifts under feedback)",
    "soft_limit": "large commands deliver less (ts tanh(u / ts)): accelerations fall short at high torque",
    "coulomb": "a constant friction torque opposing the joint's rotation",
    "gain": "the drive delivers (1 + k) times the command",
    "linear_drag": "a force -c_lin v at the pivot: the platform slows in proportion to its speed (odometry and IMU "
                   "agree; the model over-predicts speed and distance)",
    "quadratic_drag": "a force -c_air |v| v at the pivot: the platform slows with the square of its speed",
}


@dataclass
class Basis:
    """What the library is built from, for one recording (kept samples only): residual (n, 3) N m, nominal
    columns (n, 3, k0), joint rates w and angles phi (n, 3), raw commands u (n, 3) and the pivot Jacobian J
    (n, 2, 3) with the pivot velocity v (n, 2) m/s on the floor."""

    res: np.ndarray
    nominal: np.ndarray
    w: np.ndarray
    phi: np.ndarray
    u: np.ndarray
    J: np.ndarray | None
    v: np.ndarray | None
    data: DiagnosisData
    keep: np.ndarray

    def filtered(self, y: np.ndarray) -> np.ndarray:
        """A command-derived series (N, 3) of the whole record through the residual's torque filter, kept rows."""
        return integral_rate(self.data, y)[self.keep]


@dataclass(frozen=True)
class Law:
    kind: str
    joint: str  # r, l, p, or "platform"
    grid: float = 0.0  # harmonic, dead-zone width or soft limit

    @property
    def group(self) -> tuple[str, str]:
        return self.kind, self.joint

    @property
    def label(self) -> str:
        j = self.joint
        return {"cogging": f"cogging {self.grid:g}/turn on {j}", "dead_zone": f"dead zone {self.grid:.3g} N m on {j}",
                "soft_limit": f"soft limit {self.grid:.3g} N m on {j}", "coulomb": f"Coulomb friction on {j}",
                "gain": f"torque gain on {j}", "linear_drag": "linear drag at the pivot",
                "quadratic_drag": "quadratic drag at the pivot"}[self.kind]

    def columns(self, b: Basis) -> np.ndarray:
        """(n, 3, k) generalized-force columns of this law on the kept samples."""
        n = len(b.res)
        if self.kind in ("linear_drag", "quadratic_drag"):
            v = b.v if self.kind == "linear_drag" else np.linalg.norm(b.v, axis=1)[:, None] * b.v
            return np.einsum("nij,ni->nj", b.J, v)[:, :, None]
        j = JOINTS.index(self.joint)

        def on(*xs):
            c = np.zeros((n, 3, len(xs)))
            for k, x in enumerate(xs):
                c[:, j, k] = x
            return c

        if self.kind == "cogging":
            a = self.grid * b.phi[:, j]
            return on(np.sin(a), np.cos(a))
        if self.kind == "coulomb":
            return on(np.tanh(b.w[:, j] / SIGN_WIDTH))
        u = np.zeros((len(b.data), 3))
        uj = b.data.u[:, j]
        if self.kind == "gain":
            u[:, j] = uj
        elif self.kind == "dead_zone":
            u[:, j] = np.clip(uj, -self.grid, self.grid)
        else:  # soft_limit
            u[:, j] = uj - self.grid * np.tanh(uj / self.grid)
        return on(b.filtered(u)[:, j])

    def effect(self, coef: np.ndarray) -> dict[str, float] | None:
        """The model's effect entries of this law for its fitted coefficients; None when not physical."""
        c = coef[0]
        j = self.joint
        if self.kind in ("linear_drag", "quadratic_drag", "coulomb"):
            name = {"linear_drag": "c_lin", "quadratic_drag": "c_air", "coulomb": f"c_{j}"}[self.kind]
            return {name: float(c)} if c > 0 else None
        if self.kind == "gain":
            return {f"k_{j}": float(-c)} if abs(c) < 0.5 else None
        if self.kind == "cogging":
            return {f"cog_{j}": float(np.hypot(coef[0], coef[1])), f"cogn_{j}": float(self.grid),
                    f"cogph_{j}": float(np.arctan2(coef[1], coef[0]))}
        if not SHAPE_COEF[0] <= c <= SHAPE_COEF[1]:
            return None
        return {("dz_" if self.kind == "dead_zone" else "ts_") + j: float(self.grid)}

    def free(self) -> list[str]:
        """Effect entries a simulation refit adjusts (the harmonic stays)."""
        j = self.joint
        return {"cogging": [f"cog_{j}", f"cogph_{j}"], "dead_zone": [f"dz_{j}"], "soft_limit": [f"ts_{j}"],
                "coulomb": [f"c_{j}"], "gain": [f"k_{j}"], "linear_drag": ["c_lin"],
                "quadratic_drag": ["c_air"]}[self.kind]


def candidate_groups(fixture: str) -> list[list[Law]]:
    """The library: one list of grid variants per law (kind, joint)."""
    groups = []
    joints = ("p",) if fixture == "locked" else JOINTS
    for j in joints:
        groups.append([Law("cogging", j, n) for n in HARMONICS])
        groups.append([Law("dead_zone", j, d) for d in DEADZONE_GRID])
        groups.append([Law("soft_limit", j, t) for t in SOFT_GRID])
        groups.append([Law("coulomb", j)])
    if fixture == "floor":
        groups.append([Law("linear_drag", "platform")])
        groups.append([Law("quadratic_drag", "platform")])
    return groups


def basis(d: DiagnosisData, model: ExtendedModel, nominal: list[str]) -> Basis:
    m = estimate_motion(d, model)
    res = torque_residual(d, model, m)
    n = len(d)
    cols = []
    for name in nominal:
        v = model.get(name)
        h = 1e-3 * max(abs(v), 1e-2)
        cols.append((res - torque_residual(d, model.with_values({name: v + h}), m)) / h)
    keep = np.zeros(n, bool)
    e = int(round(EDGE / d.dt))
    keep[e:n - e] = True
    J = v = None
    if d.fixture == "floor":
        th = m.q[:, 2] - m.q[:, 5]
        p = model.params
        b00, b01, b10, b11, _ = fik_entries(np.sin(th), np.cos(th), p.l1, p.l2, p.r)
        J = np.zeros((n, 2, 3))
        J[:, 0, 0], J[:, 0, 1], J[:, 1, 0], J[:, 1, 1] = b00, b01, b10, b11
        v = m.qd[:, :2]
        J, v = J[keep], v[keep]
    nom = np.stack(cols, axis=2)[keep] if cols else np.zeros((int(keep.sum()), 3, 0))
    return Basis(res=res[keep], nominal=nom, w=m.qd[keep, 3:6], phi=d.enc_pos[keep], u=d.u[keep], J=J, v=v,
                 data=d, keep=keep)


def effect_std(law: Law, coef: np.ndarray, std: np.ndarray) -> dict[str, float]:
    """Std of the law's effect entries from its coefficients' (delta method; grid entries: NaN = on the grid)."""
    j = law.joint
    if law.kind == "cogging":
        a, b = coef
        amp = float(np.hypot(a, b)) or 1e-300
        return {f"cog_{j}": float(np.hypot(a * std[0], b * std[1]) / amp),
                f"cogph_{j}": float(np.hypot(b * std[0], a * std[1]) / amp ** 2)}
    if law.kind in ("dead_zone", "soft_limit"):
        # the width from the grid; its coefficient's std relative to 1 scales the width's uncertainty
        return {("dz_" if law.kind == "dead_zone" else "ts_") + j: float(law.grid * std[0])}
    name = law.effect(coef)
    return {next(iter(name)): float(std[0])} if name else {}


def model_with_laws(model: ExtendedModel, disc: dict, nominal_shift: bool = True) -> ExtendedModel:
    """``model`` with the discovered laws' effect entries set (added to what the model has for the catalog's
    entries) and, with ``nominal_shift``, the nominal parameters moved by the regression's shift."""
    values: dict[str, float] = {}
    for lw in disc.get("laws", []):
        for k, v in lw["effect"].items():
            values[k] = v + (model.get(k) if k in ("c_air", "c_r", "c_l", "c_p", "k_r", "k_l", "k_p") else 0.0)
    if nominal_shift:
        for k, dv in disc.get("nominal_shift", {}).items():
            values[k] = model.get(k) + dv
    return model.with_values(values).checked()
