"""Catalog of physical effects the paper's model leaves out (§1.5.2) and their fingerprints.

Each ``Effect`` names its physics (implemented in ``otbot_hw.model.effects``), its
parameters (units and bounds from the effect vector; ``c_w`` ties both wheels), what
it looks like in the inverse-dynamics torque residual and in the IMU / encoder
residuals, the effects it can be mistaken for, and the experiment that separates them.

``magnitudes`` are the *concealed* sizes used by the demonstration and the
confusion study (``sim/concealed.py``): small enough that a nominal fit of the
paper's model still converges with a plausible fit percentage.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

from otbot_hw.model.effects import parameter_bounds, parameter_unit


@dataclass(frozen=True)
class Effect:
    """One candidate effect: ``parameters`` are names understood by ``ExtendedModel.with_values``."""

    name: str
    title: str  # plain-language name used in verdicts
    category: str  # friction, floor, actuator, sensor, asymmetry
    model: str
    parameters: tuple[str, ...]
    torque_signature: str
    imu_signature: str
    lookalikes: tuple[str, ...]
    separating_experiment: str
    magnitudes: tuple[dict[str, float], ...]
    floor_only: bool = False
    #: parameters profiled on a grid in screening (nonlinear), with their grid (empty grid: the
    #: saturation levels, set from the recorded commands)
    grids: dict[str, tuple[float, ...]] = field(default_factory=dict)
    #: delays s whose simulated readings jump where the delay crosses a whole sample period
    #: (``sensor_model.delay_held``): their fits start inside an interval (``select.mid_interval_delays``)
    held_delays: tuple[str, ...] = ()

    def units(self) -> dict[str, str]:
        return {p: parameter_unit(p) for p in self.parameters}

    def bounds(self) -> dict[str, tuple[float, float]]:
        return {p: parameter_bounds(p) for p in self.parameters}

    def to_dict(self) -> dict:
        return {"name": self.name, "title": self.title, "category": self.category, "model": self.model,
                "parameters": {p: {"unit": parameter_unit(p), "bounds": list(parameter_bounds(p))}
                               for p in self.parameters},
                "torque_signature": self.torque_signature, "imu_signature": self.imu_signature,
                "lookalikes": list(self.lookalikes), "separating_experiment": self.separating_experiment,
                "floor_only": self.floor_only}


CATALOG: tuple[Effect, ...] = (
    Effect("coulomb_wheels", "Coulomb friction at the wheel motors", "friction",
           "tau_f = c_w sgn(phi_dot) at each wheel shaft (smoothed sign)", ("c_w",),
           "wheel residuals are square waves +c_w sgn(phi_dot), flipping at direction reversals; a nominal fit "
           "hides them in an inflated b_w", "a_x/a_y lag the model after reversals and at low speed",
           ("rolling_resistance", "stribeck_wheels", "caster_drag"),
           "spin the wheels on the stand (wheels off the ground): motor friction stays, rolling resistance "
           "and caster drag vanish", ({"c_w": 0.15}, {"c_w": 0.3})),
    Effect("coulomb_pivot", "Coulomb friction at the pivot motor", "friction",
           "tau_f = c_p sgn(phi_p_dot) at the pivot shaft", ("c_p",),
           "pivot residual +c_p sgn(phi_p_dot)", "gyro z and platform accelerations deviate after pivot reversals",
           ("gain_pivot",), "pivot torque steps of both signs at several amplitudes (locked wheels)",
           ({"c_p": 0.15}, {"c_p": 0.3})),
    Effect("stribeck_wheels", "Stribeck (breakaway) friction at the wheel motors", "friction",
           "tau_f = s_w exp(-(phi_dot/v_s)^2) sgn(phi_dot): friction that fades with speed", ("s_w", "v_s"),
           "wheel residual spikes near zero speed and at reversals, ~0 at high speed",
           "accelerations lag the model only while starting or reversing",
           ("coulomb_wheels",), "slow ramps through zero wheel speed on the stand (friction vs speed curve)",
           ({"s_w": 0.3, "v_s": 0.5}, {"s_w": 0.6, "v_s": 0.5}), grids={"v_s": (0.25, 0.6, 1.5)}),
    Effect("rolling_resistance", "rolling resistance of the wheels", "floor",
           "tau = c_rr (m_c+m_p) g r / 2 sgn(psi_dot) per wheel, at the ground contact", ("c_rr",),
           "identical in shape to wheel Coulomb friction on the floor",
           "like wheel Coulomb friction", ("coulomb_wheels",),
           "repeat the run on the stand: rolling resistance needs ground contact, motor friction does not; "
           "or add a known load (it scales with weight)", ({"c_rr": 0.0015}, {"c_rr": 0.003}), floor_only=True),
    Effect("caster_drag", "caster-wheel drag", "floor",
           "force f_cst shared by the casters, each opposing the velocity of its contact point (positions from "
           "the robot configuration's casters, else one caster at a fitted (x_c1, y_c1) in B')", ("f_cst",),
           "both wheel residuals resist translation; a turning moment appears when the chassis rotates",
           "decelerations along the chassis axis", ("rolling_resistance", "coulomb_wheels"),
           "turn in place (wheels counter-rotating) vs drive straight: caster drag scales with caster speed, "
           "rolling resistance with wheel speed sign", ({"f_cst": 2.0}, {"f_cst": 4.0}), floor_only=True),
    Effect("wheel_slip", "longitudinal wheel slip", "floor",
           "the contact creeps at k_slip * ground torque: encoders count more than the wheel rolls",
           ("k_slip",), "torque residual ~ -b_w k_slip tau (small)",
           "encoder-predicted accelerations exceed the IMU's in proportion to torque changes",
           ("encoder_scale", "wheel_radii", "traction_limit"),
           "drive with large then small torques at the same speed: slip depends on torque, scale errors do not",
           ({"k_slip": 0.03}, {"k_slip": 0.06}), floor_only=True),
    Effect("traction_limit", "wheel slip with saturating traction", "floor",
           "ground torque t_trac tanh(h(y)), y = slip rate / (k_slip t_trac), knee kn_trac (0: the magic formula, C = 1, "
           "t_trac y / sqrt(1 + y^2); 1 tanh; 3 a hard clip; fitted when the data ask for it, SHAPE_REFINEMENTS): above the traction limit the wheel spins up "
           "(slip rate k_slip tau_g + (tau_tr - tau_g) / b_w)", ("k_slip", "t_trac"),
           "wheel residuals = transmitted minus traction-limited torque at high torque",
           "IMU accelerations flatten at high wheel torque while the encoders race ahead",
           ("wheel_slip", "torque_saturation", "encoder_scale"),
           "accelerate hard from rest on the same floor at several torques: traction saturates above a torque "
           "that scales with the load, a drive limit does not move the encoders ahead of the IMU",
           ({"k_slip": 0.02, "t_trac": 3.0}, {"k_slip": 0.02, "t_trac": 2.5}), floor_only=True,
           grids={"t_trac": (2.0, 3.0, 4.5)}),
    Effect("floor_slope", "a sloped floor (gravity component)", "floor",
           "gravity component (g_x, g_y) in the floor plane, ground frame of the recording start",
           ("g_x", "g_y"), "torque residual follows the heading: downhill force projected on the wheels",
           "IMU reads -R(alpha)^T (g_x, g_y): an offset that rotates with the platform",
           ("imu_bias",), "turn the platform in place: a slope offset rotates with alpha, an IMU bias does not",
           ({"g_x": 0.02, "g_y": -0.015}, {"g_x": 0.04, "g_y": 0.03}), floor_only=True),
    Effect("air_drag", "air drag", "floor", "F = -c_air |v| v at the pivot", ("c_air",),
           "wheel residuals grow with the square of the speed", "decelerations grow with speed^2",
           ("caster_drag",), "coast down from several top speeds: drag ~ v^2, Coulomb-like drag constant",
           ({"c_air": 15.0}, {"c_air": 30.0}), floor_only=True),
    Effect("gain_right", "a torque-constant (gain) error of the right wheel motor", "actuator",
           "delivered torque = (1 + k_r) * command", ("k_r",), "right-wheel residual proportional to its command",
           "robot turns more/less than predicted under equal wheel torques", ("gain_left", "wheel_radii"),
           "run the right wheel alone on the stand with known inertia: gain scales the acceleration",
           ({"k_r": -0.05}, {"k_r": -0.1})),
    Effect("gain_left", "a torque-constant (gain) error of the left wheel motor", "actuator",
           "delivered torque = (1 + k_l) * command", ("k_l",), "left-wheel residual proportional to its command",
           "robot turns more/less than predicted under equal wheel torques", ("gain_right", "wheel_radii"),
           "run the left wheel alone on the stand with known inertia", ({"k_l": -0.05}, {"k_l": -0.1})),
    Effect("gain_pivot", "a torque-constant (gain) error of the pivot motor", "actuator",
           "delivered torque = (1 + k_p) * command", ("k_p",), "pivot residual proportional to its command",
           "platform turns more/less than predicted", ("coulomb_pivot",),
           "pivot steps with a known added inertia (load) on the platform", ({"k_p": -0.05}, {"k_p": -0.1})),
    Effect("torque_saturation", "torque saturation of the drives", "actuator",
           "delivered torque of every motor clipped to +-u_max", ("u_max",),
           "residual = command - u_max only while |command| > u_max", "accelerations flatten at high torque",
           ("gain_right", "gain_left", "gain_pivot", "saturation_right", "saturation_left", "saturation_pivot"),
           "torque staircase up to the limit on the stand, one motor at a time",
           ({"u_max": 3.6}, {"u_max": 3.2}), grids={"u_max": ()}),
    Effect("saturation_right", "torque saturation of the right wheel motor", "actuator",
           "right motor's delivered torque clipped to +-u_max_r", ("u_max_r",),
           "right-wheel residual = command - u_max_r only while |command| > u_max_r",
           "accelerations flatten when the right wheel's command is high", ("gain_right", "torque_saturation"),
           "torque staircase on the right wheel alone (stand): a limit clips, a gain error scales",
           ({"u_max_r": 3.4}, {"u_max_r": 3.0}), grids={"u_max_r": ()}),
    Effect("saturation_left", "torque saturation of the left wheel motor", "actuator",
           "left motor's delivered torque clipped to +-u_max_l", ("u_max_l",),
           "left-wheel residual = command - u_max_l only while |command| > u_max_l",
           "accelerations flatten when the left wheel's command is high", ("gain_left", "torque_saturation"),
           "torque staircase on the left wheel alone (stand): a limit clips, a gain error scales",
           ({"u_max_l": 3.4}, {"u_max_l": 3.0}), grids={"u_max_l": ()}),
    Effect("saturation_pivot", "torque saturation of the pivot motor", "actuator",
           "pivot motor's delivered torque clipped to +-u_max_p", ("u_max_p",),
           "pivot residual = command - u_max_p only while |command| > u_max_p",
           "platform accelerations flatten when the pivot command is high", ("gain_pivot", "torque_saturation"),
           "pivot torque staircase with locked wheels: a limit clips, a gain error scales",
           ({"u_max_p": 2.2}, {"u_max_p": 1.9}), grids={"u_max_p": ()}),
    Effect("current_lag", "a current-loop lag of the drives", "actuator",
           "delivered torque follows the command through a first-order lag, time constant T_i", ("T_i",),
           "residual ~ T_i d(tau)/dt: spikes right after torque steps", "accelerations lag torque steps by T_i",
           ("imu_latency",), "torque steps with encoders only: an IMU latency does not move the encoders",
           ({"T_i": 0.02}, {"T_i": 0.04}), grids={"T_i": (0.01, 0.03, 0.08)}),
    Effect("imu_bias", "an IMU bias", "sensor", "constant offsets (b_ax, b_ay) m/s^2 and b_gz rad/s in the IMU frame",
           ("b_ax", "b_ay", "b_gz"), "none (encoders and torques agree)", "constant IMU offset in the IMU frame",
           ("floor_slope",), "record the IMU at standstill at two platform angles: a bias stays, a slope rotates",
           ({"b_ax": 0.03, "b_ay": -0.02, "b_gz": 0.005}, {"b_ax": 0.06, "b_ay": 0.04, "b_gz": -0.01})),
    Effect("imu_lever_arm", "the IMU mounted away from the pivot", "sensor",
           "IMU at (d_x, d_y) in B'': adds alpha_dd x d - alpha_dot^2 d", ("d_x", "d_y"),
           "none", "tangential (alpha_dd) and centripetal (alpha_dot^2) accelerations",
           ("imu_misalignment",), "spin the platform alone (locked wheels): only a lever arm gives a_x, a_y",
           ({"d_x": 0.05, "d_y": -0.03}, {"d_x": 0.1, "d_y": 0.05})),
    Effect("imu_misalignment", "an IMU yaw misalignment", "sensor", "IMU frame = B'' rotated by psi about z",
           ("psi",), "none", "a_x leaks into a_y and vice versa: residual psi (a_y, -a_x)",
           ("imu_lever_arm",), "drive straight along the platform x axis: a misalignment shows a_y",
           ({"psi": 0.03}, {"psi": 0.06})),
    Effect("imu_latency", "IMU latency", "sensor", "the IMU sample stamped t_k was taken at t_k - d_imu",
           ("d_imu",), "none", "IMU residual ~ -d_imu d(a)/dt: spikes at torque steps",
           ("current_lag",), "torque steps: a current lag delays the encoders too, an IMU latency does not",
           ({"d_imu": 0.02}, {"d_imu": 0.04}), grids={"d_imu": (0.01, 0.03, 0.08)}, held_delays=("d_imu",)),
    Effect("encoder_scale", "a wheel-encoder scale error", "sensor", "wheel encoder readings = (1 + e) * angle",
           ("e_r", "e_l"), "residual from misjudged wheel accelerations (inertia-weighted)",
           "encoder-predicted accelerations scaled against the IMU", ("wheel_radii", "wheel_slip"),
           "roll straight over a measured distance: a scale error changes the count, a radius also the distance "
           "per wheel turn and the force",
           ({"e_r": 0.02, "e_l": -0.01}, {"e_r": 0.04, "e_l": -0.02})),
    Effect("wheel_friction_asymmetry", "different viscous friction on the two wheels", "asymmetry",
           "b_right = b_w + db_w, b_left = b_w - db_w", ("db_w",),
           "opposite residuals on the wheels proportional to their speeds", "slow yaw drift in straight runs",
           ("gain_right", "gain_left"), "spin each wheel on the stand and compare coast-downs",
           ({"db_w": 0.03}, {"db_w": 0.06})),
    Effect("wheel_radii", "wheel radii that differ from the nominal radius", "asymmetry",
           "r_right = r (1 + dr_r), r_left = r (1 + dr_l): one wheel or both; the rolling kinematics use r_i, "
           "the encoders count the wheel angle", ("dr_r", "dr_l"),
           "torque residual from the mis-scaled lever of each wheel",
           "turn-rate and a_x mismatch vs encoders in straight runs", ("encoder_scale", "gain_right", "gain_left"),
           "roll straight over a measured distance and turn in place by a measured angle: radii change the "
           "distance per wheel turn and curve the path; an encoder scale error changes the count only; "
           "a mass change changes neither",
           ({"dr_r": 0.015, "dr_l": -0.015}, {"dr_r": 0.03, "dr_l": 0.0}), floor_only=True),
)

BY_NAME: dict[str, Effect] = {e.name: e for e in CATALOG}


def effect(name: str) -> Effect:
    """The catalog entry called ``name``."""
    try:
        return BY_NAME[name]
    except KeyError:
        raise KeyError(f"unknown effect '{name}' (catalog: {', '.join(BY_NAME)})") from None


#: shape parameters refined after an effect is found (``refinements.refine_shape``): effect -> (parameter, the BIC
#: gain it must bring (1 more parameter), start values tried in turn until one gains it). The traction curve's knee (kn_trac: 0 the magic formula, 1 tanh, 3 a hard
#: clip) is a modelling assumption -- real tyres and other simulators have other knees,
#: and fitted with the wrong one the data see the knee, not the creep slope (k_slip -45 % .. +58 %) -- but on a
#: recording that hardly reaches the limit it is not identifiable, so it is fitted only when the data ask for it.
SHAPE_REFINEMENTS: dict[str, tuple[str, float, tuple[float, ...]]] = {"traction_limit": ("kn_trac", 10.0, (0.0, 3.0))}

#: parameters of the caster position, fitted with the drag when the robot configuration has no casters
CASTER_POSITION_PARAMS = ("x_c1", "y_c1")


def applicable(fixtures: set[str], casters_configured: bool = True) -> list[Effect]:
    """Effects that can act in recordings made on these fixtures (floor-only effects need the floor).

    ``casters_configured``: the robot configuration gives the caster positions; else the caster drag
    is fitted with one caster's position (x_c1, y_c1) in B', screened on its ``grids``."""
    out = []
    for e in CATALOG:
        if e.floor_only and "floor" not in fixtures:
            continue
        if e.name == "caster_drag" and not casters_configured:
            e = replace(e, parameters=e.parameters + CASTER_POSITION_PARAMS, grids={"x_c1": (0.3, -0.45)})
        out.append(e)
    return out
