"""The bench procedure's steps and settings: what each step sets up (``BENCH_STEPS``), what a session runs
(``BenchSettings``, also as a resumed session's manifest gives them back), what the bench knows of a
simulated robot (``SimulatedRobot``), and the two ways a step ends badly (``BenchError``: bad input,
exit 2; ``BenchAbort``: a stopped run, exit 1).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from otbot_hw.experiment_limits import ExperimentLimits
from otbot_hw.identification.uncertainty import session_vector
from otbot_hw.motors import MotorLimits
from otbot_hw.params import OtbotParams
from otbot_hw.runtime.supervisor import SafetyConfig
from otbot_hw.sensors import NoiseModel


@dataclass(frozen=True)
class BenchStep:
    """A step of the procedure: its fixture, whether the platform carries its load, what to set up."""

    name: str
    fixture: str
    loaded: bool
    setup: str

    def instructions(self, limits: ExperimentLimits) -> str:
        if self.fixture == "floor":
            return f"{self.setup}; clear a free area of {limits.travel_radius:g} m radius around the pivot"
        return self.setup


BENCH_STEPS: dict[str, BenchStep] = {
    "wheel": BenchStep("wheel", "stand", False, "put the robot on the stand (chassis held, both wheels free to "
                                               "spin, platform unloaded); keep hands away from the wheels"),
    "pivot": BenchStep("pivot", "locked", False, "lock both wheels (brake or chocks) so the chassis cannot move, "
                                                "platform unloaded and free to turn"),
    "chassis": BenchStep("chassis", "floor", False, "put the robot on the floor, wheels free, platform unloaded"),
    "platform": BenchStep("platform", "floor", True, "fix the load on the platform and put the robot on the floor, "
                                                    "wheels free"),
}


class BenchError(Exception):
    """Bad input found by a step (wrong fixture, robot that does not move, saturated or clipped data, a
    step that cannot identify its parameters): the CLI exits 2. The session is kept."""

    def __init__(self, step: str, reason: str):
        super().__init__(f"step {step}: {reason}")
        self.step = step
        self.reason = reason


class BenchAbort(Exception):
    """A run stopped by the safety supervisor or a fault (the CLI exits 1); recording and session kept."""

    def __init__(self, step: str, reason: str):
        super().__init__(f"step {step}: {reason}")
        self.step = step
        self.reason = reason


@dataclass
class BenchSettings:
    """What the procedure runs and how: ``steps`` in order, ``excitation`` paper/designed, at most
    ``attempts`` per step, experiment ``limits`` (its travel_radius is the free area), the ``safety``
    section, the motors' ``motor_limits``, ``params_start`` (the robot before the session, unloaded
    platform), the ``noise`` the sensors are stated to have (recorded; the fits' weights and the
    gates' Cramer-Rao bounds), the IMU's rate, ``diagnose`` (run the mismatch finder)."""

    steps: list[str]
    excitation: str
    attempts: int
    limits: ExperimentLimits
    safety: SafetyConfig
    motor_limits: MotorLimits
    params_start: OtbotParams
    noise: NoiseModel
    imu_rate: float | None
    diagnose: bool = True

    def to_dict(self) -> dict:
        return {"steps": list(self.steps), "excitation": self.excitation, "attempts": self.attempts,
                "limits": self.limits.to_dict(), "params_start": self.params_start.to_dict(),
                "noise": self.noise.to_dict()}


@dataclass
class SimulatedRobot:
    """What the bench knows about a simulated robot (for metadata and ``truth``): the unloaded robot's
    parameters and the load the simulated operator fixes for the platform step."""

    unloaded: OtbotParams
    load: tuple[float, float, float, float] | None = None
    effects: dict = field(default_factory=dict)

    @property
    def loaded(self) -> OtbotParams:
        return self.unloaded.with_load(*self.load) if self.load else self.unloaded

    def truth(self) -> dict[str, float]:
        return session_vector(self.unloaded, self.loaded)  # with the unloaded platform's m_p0, x_F0, y_F0



def settings_from_manifest(data: dict, base: BenchSettings) -> BenchSettings:
    """The settings a session was started with (``--resume``), the hardware's limits and safety kept."""
    from otbot_hw.experiment_limits import limits_from_dict

    s = data["settings"]
    lim = ExperimentLimits(**s["limits"]) if isinstance(s.get("limits"), dict) else limits_from_dict(None)
    return dataclasses.replace(base, steps=list(s["steps"]), excitation=s["excitation"], attempts=int(s["attempts"]),
                               limits=lim, params_start=OtbotParams.from_dict(s["params_start"], "session.json"),
                               noise=NoiseModel(**s["noise"]))
