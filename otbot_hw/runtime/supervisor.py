"""The safety supervisor: between controller and robot, once per cycle (ros2_control's safety layer).

``Supervisor.limit`` clamps every command to the motor limits (``otbot_hw.control.limiter.TorqueLimiter``:
never silent, each saturation episode is reported). ``Supervisor.check`` judges each sample against
the ``safety:`` section of the hardware configuration (``config/robot.yaml``, every key documented
there with its unit):

=====================  ===========================================================================
kind                   violation
=====================  ===========================================================================
joint_rate             an encoder rate |phi_dot| above max_wheel_rate / max_pivot_rate
platform_speed         the estimated |(x_dot, y_dot)| above max_speed or |alpha_dot| above max_turn_rate
workspace              the estimated pivot position outside the workspace rectangle
travel                 the estimated pivot farther than max_travel from where the run started, counting
                       the distance it needs to stop, speed^2 / (2 stop_deceleration) (a free area)
tracking_error         |(x, y) - (x_d, y_d)| above max_position_error or |alpha - alpha_d| above
                       max_heading_error (estimate against the reference of the acting command)
estimator              a non-finite estimate, position/heading std above its maximum, or more than
                       max_rejected_fraction of the innovations rejected over rejection_window
overrun                real-time loops only: more than max_consecutive_overruns cycles in a row whose
                       period exceeded overrun_factor periods (the daemon judges them only while the
                       robot is meant to move; a streak begun at rest counts from the first such cycle)
command                the controller produced a non-finite torque
=====================  ===========================================================================

The first violation is latched (``fault``) until ``reset()``: the runner quick-stops the robot and
records it. Faults the robot itself reports (drives, encoder, IMU) and estimator faults reach the
runner directly and latch here too (``latch``).
"""
from __future__ import annotations

import dataclasses
import math
from collections import deque
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Callable

import numpy as np

from otbot_hw.control.limiter import TorqueLimiter
from otbot_hw.motors import DEFAULT_ROBOT_FILE, MotorLimits
from otbot_hw.params import ParameterError, read_entry, read_yaml

SECTION = "safety"
JOINT_NAMES = ("right wheel", "left wheel", "pivot")
#: Innovations needed in the rejection window before the rejected fraction is judged.
MIN_INNOVATIONS = 10


@dataclass(frozen=True)
class SafetyConfig:
    """Limits of the supervisor (None: that check is off). Units: rad/s, m/s, m, rad, s, 1.

    The defaults (those of config/robot.yaml) admit the paper's identification experiments (§4.3:
    the chassis experiment turns the platform at 7.5 rad/s and the pivot at 5.6 rad/s; 3 s of 10 N m
    on the stand spin a wheel to 56 rad/s) and the tracking scenarios (at most 1.5 m/s)."""

    max_wheel_rate: float | None = 60.0
    max_pivot_rate: float | None = 10.0
    max_speed: float | None = 2.0
    max_turn_rate: float | None = 10.0
    workspace: tuple[float, float, float, float] | None = (-50.0, 50.0, -50.0, 50.0)  # x_min, x_max, y_min, y_max (m)
    max_position_error: float | None = 0.3
    max_heading_error: float | None = 0.3
    max_position_std: float | None = 0.1
    max_heading_std: float | None = 0.1
    max_rejected_fraction: float | None = 0.5
    rejection_window: float = 1.0
    overrun_factor: float = 1.5
    max_consecutive_overruns: int = 5
    max_travel: float | None = None
    stop_deceleration: float = 1.0

    #: key -> unit in the YAML file
    UNITS = {"max_wheel_rate": "rad/s", "max_pivot_rate": "rad/s", "max_speed": "m/s", "max_turn_rate": "rad/s",
             "workspace": "m", "max_position_error": "m", "max_heading_error": "rad", "max_position_std": "m",
             "max_heading_std": "rad", "max_rejected_fraction": "1", "rejection_window": "s",
             "overrun_factor": "1", "max_consecutive_overruns": "1", "max_travel": "m", "stop_deceleration": "m/s^2"}

    @classmethod
    def off(cls) -> "SafetyConfig":
        """Every check off (model studies where nothing real can get hurt, e.g. an open-loop replay)."""
        return cls(**{k: None for k in ("max_wheel_rate", "max_pivot_rate", "max_speed", "max_turn_rate",
                                        "max_position_error", "max_heading_error", "max_position_std",
                                        "max_heading_std", "max_rejected_fraction")})

    @classmethod
    def load(cls, path: str | Path | None = None) -> "SafetyConfig":
        """The ``safety:`` section of the hardware YAML (default config/robot.yaml); keys left out keep
        the defaults above, ``value: null`` turns a check off. Bad keys raise ``ParameterError``."""
        p = Path(path) if path is not None else DEFAULT_ROBOT_FILE
        data = read_yaml(p) or {}
        if not isinstance(data, dict):
            raise ParameterError(f"{p}: expected a mapping of sections")
        block = data.get(SECTION)
        if block is None:
            return cls()
        if not isinstance(block, dict):
            raise ParameterError(f"{p}: section '{SECTION}' must be a mapping")
        return cls.from_dict(block, str(p))

    @classmethod
    def from_dict(cls, block: dict, source: str = "<dict>") -> "SafetyConfig":
        known = {f.name for f in fields(cls)}
        values = {}
        for key, entry in block.items():
            name = f"{SECTION}.{key}"
            if key not in known:
                raise ParameterError(f"{source}: unknown key '{name}' (known: {', '.join(sorted(known))})")
            v, _ = read_entry(source, name, entry, cls.UNITS[key])
            if v is None:
                if key in ("rejection_window", "overrun_factor", "max_consecutive_overruns", "stop_deceleration"):
                    raise ParameterError(f"{source}: '{name}' cannot be null")
                values[key] = None
            elif key == "workspace":
                if (not isinstance(v, (list, tuple)) or len(v) != 4 or not all(_number(e) for e in v)
                        or not (v[0] < v[1] and v[2] < v[3])):
                    raise ParameterError(f"{source}: '{name}' must be [x_min, x_max, y_min, y_max] in m with "
                                         f"min < max, got {v!r}")
                values[key] = tuple(float(e) for e in v)
            elif key == "max_consecutive_overruns":
                if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                    raise ParameterError(f"{source}: '{name}' must be an integer >= 1, got {v!r}")
                values[key] = v
            else:
                if not _number(v) or not v > 0:
                    raise ParameterError(f"{source}: '{name}' must be a number > 0, got {v!r}")
                if key == "overrun_factor" and not v > 1:
                    raise ParameterError(f"{source}: '{name}' must be > 1 (a multiple of the period), got {v!r}")
                if key == "max_rejected_fraction" and not v <= 1:
                    raise ParameterError(f"{source}: '{name}' must be a share in (0, 1] (above 1 the check never "
                                         f"fires; null turns it off), got {v!r}")
                values[key] = float(v)
        return cls(**values)

    def to_dict(self) -> dict:
        d = asdict(self)
        d.pop("UNITS", None)
        return d

    def within(self, limits, fixture: str = "floor") -> "SafetyConfig":
        """These checks tightened to an identification experiment's ``ExperimentLimits``
        (``otbot_hw.experiment_limits``, section ``experiment_limits``) on ``fixture``.

        floor: wheel and pivot rates, platform speed, and the free area (``max_travel`` =
        travel_radius around the start, with the stop at stop_deceleration); stand / locked (the
        chassis held, the wheels spinning freely on the stand): the pivot rate only, the wheels keep
        this config's limit. Tracking errors are off (no reference). The torque limit is the
        limiter's: give the ``Supervisor`` motor limits clipped to ``limits.torque``."""
        def tight(mine, theirs):
            return theirs if mine is None else min(mine, theirs)

        common = {"max_pivot_rate": tight(self.max_pivot_rate, limits.pivot_speed), "max_position_error": None,
                  "max_heading_error": None}
        if fixture != "floor":
            return dataclasses.replace(self, **common)
        return dataclasses.replace(self, **common, max_wheel_rate=tight(self.max_wheel_rate, limits.wheel_speed),
                                   max_speed=tight(self.max_speed, limits.platform_speed),
                                   max_travel=tight(self.max_travel, limits.travel_radius),
                                   stop_deceleration=limits.stop_deceleration)


def _number(v) -> bool:
    return not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v)


@dataclass(frozen=True)
class Violation:
    """Why the loop stopped: ``kind`` (see the module table, or robot / estimator_fault), at robot time
    t (s), ``text`` in words; ``value`` and ``limit`` where a number was exceeded."""

    kind: str
    t: float
    text: str
    value: float | None = None
    limit: float | None = None

    def to_dict(self) -> dict:
        return {"kind": self.kind, "t": self.t, "text": self.text, "value": self.value, "limit": self.limit}

    def __str__(self) -> str:
        return f"{self.kind} at t = {self.t:.3f} s: {self.text}"


class Supervisor:
    """Limits and checks of one loop. ``limits``: motor torque limits (N m); ``config``: the
    ``SafetyConfig``; ``period`` s; ``realtime``: judge overruns (lockstep loops have no deadline);
    ``on_saturation(episode)``: called when a saturation episode starts."""

    def __init__(self, limits: MotorLimits, config: SafetyConfig | None = None, period: float = 0.01,
                 realtime: bool = False, on_saturation: Callable | None = None):
        self.config = config or SafetyConfig()
        self.limits = limits
        self.period = float(period)
        self.realtime = realtime
        self.limiter = TorqueLimiter(limits, on_saturation=on_saturation)
        self.fault: Violation | None = None
        self._consecutive = 0
        self._innovations: deque = deque()
        self._start: tuple[float, float] | None = None  # first estimated pivot position (travel check)

    # -- command path ------------------------------------------------------------------------------
    def limit(self, t: float, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(u clamped to the motor limits, mask of the clamped motors); a non-finite u latches a fault
        and gives zeros."""
        try:
            return self.limiter.apply(u, t)
        except ValueError:
            self.latch(Violation("command", t, f"controller produced a non-finite torque {np.asarray(u).tolist()}"))
            return np.zeros(3), np.zeros(3, bool)

    # -- sample checks -----------------------------------------------------------------------------
    def latch(self, v: Violation) -> Violation:
        """Latch ``v`` unless a fault is already latched; returns the latched one."""
        if self.fault is None:
            self.fault = v
        return self.fault

    def reset(self) -> None:
        self.fault = None
        self._consecutive = 0
        self._innovations.clear()
        self._start = None

    def check(self, t: float, joint_vel, estimate=None, reference=None,
              wall_period: float | None = None) -> Violation | None:
        """Judge one sample: encoder rates (3,) rad/s, the ``StateEstimate`` (or None), the
        ``Reference`` of the command acting now (or None), the measured wall-clock period (s) since
        the previous sample. Returns the latched fault (the first violation), or None."""
        if self.fault is not None:
            return self.fault
        v = self._check(t, joint_vel, estimate, reference, wall_period)
        return self.latch(v) if v is not None else None

    def _check(self, t, joint_vel, est, ref, wall_period) -> Violation | None:
        # plain floats: this runs every cycle, and numpy on 3-vectors costs more than the checks
        c = self.config
        if wall_period is not None:
            if self.realtime and wall_period > c.overrun_factor * self.period:
                self._consecutive += 1
                if self._consecutive > c.max_consecutive_overruns:
                    return Violation("overrun", t, f"{self._consecutive} cycles in a row longer than "
                                                   f"{c.overrun_factor:g} periods (last {wall_period * 1e3:.2f} ms, "
                                                   f"period {self.period * 1e3:.2f} ms)", wall_period,
                                     c.overrun_factor * self.period)
            else:  # in time, or not judged (lockstep; the daemon's robot at rest): a streak starts afresh, so
                self._consecutive = 0  # one that began at rest counts from the first cycle meant to move
        w = joint_vel.tolist() if hasattr(joint_vel, "tolist") else list(joint_vel)
        for i, lim in ((0, c.max_wheel_rate), (1, c.max_wheel_rate), (2, c.max_pivot_rate)):
            if lim is not None and not abs(w[i]) <= lim:
                return Violation("joint_rate", t, f"{JOINT_NAMES[i]} turns at {abs(w[i]):.3f} rad/s, limit {lim:g} "
                                                  f"rad/s", abs(w[i]), lim)
        if est is None:
            return None
        x, y, a = est.pose.tolist()
        vx, vy, va = est.twist.tolist()
        std = est.std.tolist()
        if not all(map(math.isfinite, (x, y, a, vx, vy, va, *std))):
            return Violation("estimator", t, f"non-finite estimate (pose {[x, y, a]}, twist {[vx, vy, va]}, std {std})")
        if c.max_position_std is not None:
            sp = max(std[0], std[1])
            if sp > c.max_position_std:
                return Violation("estimator", t, f"position std {sp:.4f} m above {c.max_position_std:g} m", sp,
                                 c.max_position_std)
        if c.max_heading_std is not None and std[2] > c.max_heading_std:
            return Violation("estimator", t, f"heading std {std[2]:.4f} rad above {c.max_heading_std:g} rad",
                             std[2], c.max_heading_std)
        v = self._rejections(t, est)
        if v is not None:
            return v
        speed = math.hypot(vx, vy)
        if c.max_speed is not None and speed > c.max_speed:
            return Violation("platform_speed", t, f"platform speed {speed:.3f} m/s, limit {c.max_speed:g} m/s", speed,
                             c.max_speed)
        if c.max_turn_rate is not None and abs(va) > c.max_turn_rate:
            return Violation("platform_speed", t, f"platform turn rate {abs(va):.3f} rad/s, limit "
                                                  f"{c.max_turn_rate:g} rad/s", abs(va), c.max_turn_rate)
        if c.max_travel is not None:
            if self._start is None:
                self._start = (x, y)
            dist = math.hypot(x - self._start[0], y - self._start[1]) + speed * speed / (2.0 * c.stop_deceleration)
            if dist > c.max_travel:
                return Violation("travel", t, f"pivot {math.hypot(x - self._start[0], y - self._start[1]):.3f} m from "
                                              f"its start at {speed:.3f} m/s needs {dist:.3f} m to stop, beyond the "
                                              f"free area of {c.max_travel:g} m", dist, c.max_travel)
        if c.workspace is not None:
            x0, x1, y0, y1 = c.workspace
            if not (x0 <= x <= x1 and y0 <= y <= y1):
                return Violation("workspace", t, f"pivot at ({x:.3f}, {y:.3f}) m left the workspace "
                                                 f"x [{x0:g}, {x1:g}], y [{y0:g}, {y1:g}] m")
        if ref is not None:
            xd, yd, ad = ref.p.tolist()
            e = math.hypot(x - xd, y - yd)
            if c.max_position_error is not None and e > c.max_position_error:
                return Violation("tracking_error", t, f"position error {e:.4f} m, limit {c.max_position_error:g} m",
                                 e, c.max_position_error)
            ea = abs(a - ad)
            if c.max_heading_error is not None and ea > c.max_heading_error:
                return Violation("tracking_error", t, f"heading error {ea:.4f} rad, limit {c.max_heading_error:g} rad",
                                 ea, c.max_heading_error)
        return None

    def _rejections(self, t: float, est) -> Violation | None:
        c = self.config
        if c.max_rejected_fraction is None or not est.updates and not est.rejected:
            return None
        rej = sum(est.rejected.values())
        acc = sum(est.updates.values())
        q = self._innovations
        q.append((t, rej, acc))
        while q and q[0][0] < t - c.rejection_window:
            q.popleft()
        d_rej, d_acc = rej - q[0][1], acc - q[0][2]
        total = d_rej + d_acc
        if total >= MIN_INNOVATIONS and d_rej > c.max_rejected_fraction * total:
            return Violation("estimator", t, f"{d_rej} of {total} innovations rejected in the last "
                                             f"{c.rejection_window:g} s (limit {c.max_rejected_fraction:.0%})",
                             d_rej / total, c.max_rejected_fraction)
        return None
