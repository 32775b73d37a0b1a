"""A trajectory given by samples (``SampledTrajectory``: a C^2 cubic spline, or a cubic Hermite spline when
velocities are given, so p, p_dot and p_dd are the exact derivatives of one interpolant) and its CSV
file (``load_csv`` / ``save_csv``; ``csv_table`` / ``csv_numbers`` also read the open-loop torque files).

CSV format (``load_csv`` / ``save_csv``): a header row, comma separated, SI units.
Required columns ``t`` (s, strictly increasing, rows at least ``MIN_SPACING`` apart), ``x``, ``y`` (m),
``alpha`` (rad), each within ``MAX_VALUE`` (so is every other column read).
Optional ``x_dot``, ``y_dot``, ``alpha_dot`` (m/s, rad/s; all three or none) and
``tau_r``, ``tau_l``, ``tau_p`` (N m; the planner's open-loop torques, held from each
sample to the next). Other columns are ignored. Times are shifted so the first row is t = 0.
Lines starting with ``#`` are comments; ``# obstacle: cx, cy, r`` (m) declares a circular
obstacle (written by the planner) so tracking runs can report collisions.
"""
from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Sequence

import numpy as np

from otbot_hw.control.trajectories import DesiredTrajectory, TrajectoryError
from otbot_hw.params import finite_number

REQUIRED_COLUMNS = ("t", "x", "y", "alpha")
VELOCITY_COLUMNS = ("x_dot", "y_dot", "alpha_dot")
TORQUE_COLUMNS = ("tau_r", "tau_l", "tau_p")
#: Closest two samples may be (s): a microsecond, finer than any control period; closer rows gave a
#: spline with infinite derivatives (x 0.5 m apart in 1e-160 s).
MIN_SPACING = 1e-6
#: Largest magnitude of a position (m), angle (rad), rate or torque in a trajectory: a million.
MAX_VALUE = 1e6


class SampledTrajectory(DesiredTrajectory):
    """Interpolated samples: t (N,) s strictly increasing from 0, P (N, 3), optional PD (N, 3).

    Without velocities: a C^2 cubic spline with zero end velocities ("clamped", rest-to-rest).
    With velocities: a cubic Hermite spline through (P, PD). Either way p_dot and p_dd are
    the interpolant's exact derivatives. ``torques`` (N, 3) N m are kept for open-loop replay;
    ``hold`` (s) of rest at the last sample is added to ``duration``.
    """

    def __init__(self, t: np.ndarray, P: np.ndarray, PD: np.ndarray | None = None,
                 torques: np.ndarray | None = None, source: str = "samples", hold: float = 0.0):
        from scipy.interpolate import CubicHermiteSpline, CubicSpline

        t = np.asarray(t, dtype=float)
        P = np.asarray(P, dtype=float)
        _check_samples(t, P, PD, source)
        self.t_samples = t - t[0]
        self.P_samples = P
        self.PD_samples = None if PD is None else np.asarray(PD, dtype=float)
        self.torques = None if torques is None else np.asarray(torques, dtype=float)
        self.obstacles: list[tuple[float, float, float]] = []
        with np.errstate(all="ignore"):  # an overflow is reported below, in one line
            if self.PD_samples is None:
                self._spline = CubicSpline(self.t_samples, P, axis=0, bc_type="clamped")
            else:
                self._spline = CubicHermiteSpline(self.t_samples, P, self.PD_samples, axis=0)
            self._d1 = self._spline.derivative(1)
            self._d2 = self._spline.derivative(2)
        if not (np.isfinite(self._d1.c).all() and np.isfinite(self._d2.c).all()):
            raise TrajectoryError(f"{source}: the interpolated trajectory is not finite (samples too close for "
                                  "the distance between them)")
        self.end = float(self.t_samples[-1])
        self.duration = self.end + max(0.0, float(hold))

    def sample(self, t):
        t = np.atleast_1d(np.asarray(t, dtype=float))
        tc = np.clip(t, 0.0, self.end)
        inside = ((t >= 0) & (t <= self.end))[:, None]
        return self._spline(tc), np.where(inside, self._d1(tc), 0.0), np.where(inside, self._d2(tc), 0.0)


def _check_samples(t, P, PD, source):
    if t.ndim != 1 or len(t) < 2:
        raise TrajectoryError(f"{source}: need at least 2 samples, got {t.size}")
    if P.shape != (len(t), 3):
        raise TrajectoryError(f"{source}: positions must be (N, 3) = (x, y, alpha), got {P.shape}")
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        raise TrajectoryError(f"{source}: time is not strictly increasing at row {i + 1} "
                              f"(t = {t[i]:g} s after {t[i - 1]:g} s)")
    if not np.all(np.isfinite(P)) or np.abs(P).max() > MAX_VALUE:
        i = int(np.argmax(~(np.abs(P) <= MAX_VALUE).all(axis=1)))
        raise TrajectoryError(f"{source}: row {i + 1}: position {P[i].tolist()} beyond {MAX_VALUE:g} m (rad)")


def csv_table(path, text: str, required: Sequence[str], error: type[Exception] = TrajectoryError):
    """(header, data rows) of a CSV text with a header row; lines starting with ``#`` are comments.
    ``error`` (naming ``path``) when it is empty, lacks a ``required`` column or names a column twice (which
    of the two would be meant?). A leading byte-order mark (what spreadsheets write by default) is dropped."""
    text = text.removeprefix("\ufeff")
    rows = list(csv.reader(line for line in text.splitlines() if line.strip() and not line.startswith("#")))
    if not rows:
        raise error(f"{path}: empty file (expected a header with columns {', '.join(required)})")
    header = [h.strip() for h in rows[0]]
    for j, name in enumerate(header):
        if name and name in header[:j]:
            raise error(f"{path}: column {name} is named twice in the header (columns {header.index(name) + 1} and "
                        f"{j + 1}); each column once")
    missing = [c for c in required if c not in header]
    if missing:
        raise error(f"{path}: missing column(s) {', '.join(missing)} (header: {', '.join(header)})")
    return header, rows[1:]


def csv_numbers(path, header: list[str], rows: list[list[str]], wanted: Sequence[str],
                error: type[Exception] = TrajectoryError) -> np.ndarray:
    """The ``wanted`` columns of ``rows`` as finite floats (N, len(wanted)); ``error`` names the line
    (the header is line 1, comments not counted) and the column of the first bad field."""
    col = {c: header.index(c) for c in wanted}
    data = np.empty((len(rows), len(wanted)))
    for r, row in enumerate(rows):
        line = r + 2
        if len(row) != len(header):
            raise error(f"{path}: line {line} has {len(row)} fields, header has {len(header)}")
        for j, c in enumerate(wanted):
            data[r, j] = finite_number(row[col[c]].strip(), f"{path}: line {line}, column {c}", error)
    return data


def load_csv(path: str | Path, hold: float = 0.0) -> SampledTrajectory:
    """Read a trajectory CSV (format in the module docstring); errors name the row and column."""
    from otbot_hw.input_files import read_text

    path = Path(path)
    try:
        text = read_text(path)
    except OSError as exc:
        raise TrajectoryError(f"{path}: cannot read: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise TrajectoryError(f"{path}: not a text file; a trajectory is a CSV text file") from None
    text = text.removeprefix("\ufeff")  # Excel's "CSV UTF-8" starts with a byte-order mark
    obstacles = []
    for n, line in enumerate(text.splitlines(), start=1):
        if line.startswith("# obstacle:"):
            try:
                vals = [float(v) for v in line.split(":", 1)[1].split(",")]
            except ValueError:
                vals = []
            if len(vals) != 3 or not all(math.isfinite(v) for v in vals) or vals[2] <= 0:
                raise TrajectoryError(f"{path}: line {n}: obstacle comment must be '# obstacle: cx, cy, r' "
                                      f"(m, r > 0), got {line!r}")
            obstacles.append(tuple(vals))
    header, rows = csv_table(path, text, REQUIRED_COLUMNS)
    vel = [c for c in VELOCITY_COLUMNS if c in header]
    if vel and len(vel) != 3:
        raise TrajectoryError(f"{path}: velocity columns must be all of {', '.join(VELOCITY_COLUMNS)} or none, "
                              f"got {', '.join(vel)}")
    tq = [c for c in TORQUE_COLUMNS if c in header]
    if tq and len(tq) != 3:
        raise TrajectoryError(f"{path}: torque columns must be all of {', '.join(TORQUE_COLUMNS)} or none")
    data = csv_numbers(path, header, rows, list(REQUIRED_COLUMNS) + vel + tq)
    if len(data) < 2:
        raise TrajectoryError(f"{path}: need at least 2 data rows, got {len(data)}")
    t = data[:, 0]
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        raise TrajectoryError(f"{path}: column t is not strictly increasing at line {i + 2} "
                              f"(t = {t[i]:g} s after {t[i - 1]:g} s)")
    close = np.flatnonzero(np.diff(t) < MIN_SPACING)
    if close.size:
        i = int(close[0]) + 1
        raise TrajectoryError(f"{path}: lines {i + 1} and {i + 2} are {t[i] - t[i - 1]:.3g} s apart (t = "
                              f"{t[i - 1]:g} s, {t[i]:g} s); rows must be at least {MIN_SPACING:g} s apart")
    big = np.abs(data) > MAX_VALUE
    big[:, 0] = False  # times: the duration checks bound them
    if big.any():
        r, j = (int(v) for v in np.argwhere(big)[0])
        name = (list(REQUIRED_COLUMNS) + vel + tq)[j]
        raise TrajectoryError(f"{path}: line {r + 2}, column {name}: {data[r, j]:.3g} is beyond {MAX_VALUE:g} "
                              "(m, rad, m/s, rad/s or N m); a trajectory stays within a million")
    PD = data[:, 4:7] if vel else None
    torques = data[:, 4 + len(vel):7 + len(vel)] if tq else None
    traj = SampledTrajectory(t, data[:, 1:4], PD, torques=torques, source=str(path), hold=hold)
    traj.obstacles = obstacles
    return traj


def save_csv(path: str | Path, t: np.ndarray, P: np.ndarray, PD: np.ndarray | None = None,
             torques: np.ndarray | None = None, comment: str = "",
             obstacles: Sequence[tuple[float, float, float]] = ()) -> Path:
    """Write a trajectory CSV readable by ``load_csv`` (obstacles as ``# obstacle:`` comments)."""
    path = Path(path)
    cols = list(REQUIRED_COLUMNS) + (list(VELOCITY_COLUMNS) if PD is not None else []) \
        + (list(TORQUE_COLUMNS) if torques is not None else [])
    parts = [np.asarray(t, float)[:, None], np.asarray(P, float)]
    if PD is not None:
        parts.append(np.asarray(PD, float))
    if torques is not None:
        parts.append(np.asarray(torques, float))
    data = np.hstack(parts)
    with path.open("w", newline="") as fh:
        for line in comment.splitlines():
            fh.write(f"# {line}\n")
        for cx, cy, r in obstacles:
            fh.write(f"# obstacle: {cx!r}, {cy!r}, {r!r}\n")
        w = csv.writer(fh)
        w.writerow(cols)
        for row in data:
            w.writerow([repr(float(v)) for v in row])
    return path
