"""The simulated flight controller's parameters: each one's name, default, range and meaning, and
the airframe (the plant) that the airframe parameters describe. Pure data: ``fc.FlightController``
holds the values, ``ardupilot``/``px4`` set the plant of a real firmware from them."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from triswarm.protocol.airframe import RPM_TO_RAD_S, Airframe, ParameterError

from .profiles import TRISWARM, Profile
from .telemetry import STREAMS


@dataclass(frozen=True)
class ParamSpec:
    name: str
    default: float
    lo: float
    hi: float
    doc: str


READ_ONLY_PARAMS = frozenset({"SIM_LOCKSTEP"})
"""Set by the simulator at start, never over MAVLink."""
AIRFRAME_PARAMS = frozenset({"MASS_KG", "IXX_KGM2", "IYY_KGM2", "IZZ_KGM2", "IYZ_KGM2", "KF", "KD", "ARM_LEN_M",
                             "SERVO_DELAY_S", "SERVO_RATE_DPS", "MOT_MAX_RPM", "SERVO_LIM_DEG"})
"""The parameters that change the plant (``FlightController.airframe``)."""


def param_specs(af: Airframe, profile: Profile = TRISWARM) -> list[ParamSpec]:
    """Every parameter; the companion link's stream rates default to ``profile``'s."""
    specs = [
        ParamSpec("MASS_KG", af.mass_kg, 0.05, 50.0, "vehicle mass [kg]"),
        ParamSpec("IXX_KGM2", af.Ixx_kg_m2, 1e-5, 10.0, "inertia about body x [kg m^2]"),
        ParamSpec("IYY_KGM2", af.Iyy_kg_m2, 1e-5, 10.0, "inertia about body y [kg m^2]"),
        ParamSpec("IZZ_KGM2", af.Izz_kg_m2, 1e-5, 10.0, "inertia about body z [kg m^2]"),
        ParamSpec("IYZ_KGM2", af.Iyz_kg_m2, -1.0, 1.0, "product of inertia y-z [kg m^2]"),
        ParamSpec("KF", af.k_f_N_s2, 1e-8, 1e-2, "thrust coefficient [N s^2/rad^2]"),
        ParamSpec("KD", af.k_d_N_m_s2, 0.0, 1e-3, "drag-torque coefficient [N m s^2/rad^2]"),
        ParamSpec("ARM_LEN_M", af.arm_length_m, 0.02, 5.0, "arm length [m]"),
        ParamSpec("SERVO_DELAY_S", af.servo_delay_s, 0.0, 0.2, "servo transport delay [s]"),
        ParamSpec("SERVO_RATE_DPS", math.degrees(af.servo_rate_rad_s), 0.0, 100000.0, "servo speed [deg/s]; 0: at once"),
        ParamSpec("MOT_MAX_RPM", af.max_rotor_speed_rad_s / RPM_TO_RAD_S, 500.0, 100000.0, "motor speed limit [RPM]"),
        ParamSpec("SERVO_LIM_DEG", math.degrees(af.servo_limit_rad), 5.0, 180.0, "servo range +- [deg]"),
        ParamSpec("NOISE_POS_M", 0.0, 0.0, 10.0, "position noise, 1 sigma [m]"),
        ParamSpec("NOISE_VEL_MS", 0.0, 0.0, 10.0, "velocity noise, 1 sigma [m/s]"),
        ParamSpec("NOISE_ATT_RAD", 0.0, 0.0, 1.0, "attitude noise, 1 sigma [rad]"),
        ParamSpec("NOISE_GYRO_RADS", 0.0, 0.0, 10.0, "body-rate noise, 1 sigma [rad/s]"),
        ParamSpec("NOISE_ACC_MS2", 0.0, 0.0, 100.0, "accelerometer noise, 1 sigma [m/s^2]"),
        ParamSpec("FS_TIMEOUT_S", 0.3, 0.02, 60.0, "armed without actuator command this long: hold"),
        ParamSpec("FS_LAND_DELAY_S", 5.0, 0.0, 600.0, "failsafe hold this long, then land"),
        ParamSpec("LAND_SPEED_M_S", 0.7, 0.1, 5.0, "descent speed when landing [m/s]"),
        ParamSpec("TKO_ALT_M", 2.5, 0.5, 100.0, "takeoff altitude above home [m]"),
        ParamSpec("DISARM_DELAY_S", 2.0, 0.0, 60.0, "on the ground in LAND this long: disarm"),
        ParamSpec("DISARM_PRFLT_S", 10.0, 0.5, 600.0, "armed on the ground without commands this long: disarm"),
        ParamSpec("BAT_CAP_MAH", 5000.0, 100.0, 100000.0, "battery capacity [mAh]"),
        ParamSpec("BAT_CELLS", 3.0, 1.0, 14.0, "battery cells in series"),
        ParamSpec("BAT_ARM_PCT", 20.0, 0.0, 100.0, "refuse to arm below this charge [%]"),
        ParamSpec("SIM_LOCKSTEP", 0.0, 0.0, 1.0, "1: the simulator steps when the companion has answered (read-only)"),
    ]
    for code, (_, rate_g) in STREAMS.items():
        rate_c = profile.rates_hz.get(code, 0.0)
        specs.append(ParamSpec(f"SC_{code}_HZ", rate_c, 0.0, 1000.0, f"stream rate of {code} on the companion link [Hz]"))
        specs.append(ParamSpec(f"SG_{code}_HZ", rate_g, 0.0, 1000.0, f"stream rate of {code} on the ground-station link [Hz]"))
    return specs


def airframe_from_params(nominal: Airframe, p: dict[str, float]) -> Airframe:
    """The plant that the airframe parameters ``p`` (every name of AIRFRAME_PARAMS) describe."""
    return dataclasses.replace(
        nominal, mass_kg=p["MASS_KG"], Ixx_kg_m2=p["IXX_KGM2"], Iyy_kg_m2=p["IYY_KGM2"],
        Izz_kg_m2=p["IZZ_KGM2"], Iyz_kg_m2=p["IYZ_KGM2"], k_f_N_s2=p["KF"], k_d_N_m_s2=p["KD"],
        arm_length_m=p["ARM_LEN_M"], servo_delay_s=p["SERVO_DELAY_S"], servo_rate_rad_s=math.radians(p["SERVO_RATE_DPS"]),
        max_rotor_speed_rad_s=p["MOT_MAX_RPM"] * RPM_TO_RAD_S, servo_limit_rad=math.radians(p["SERVO_LIM_DEG"]))


def plant_airframe(nominal: Airframe, changes: dict[str, float]) -> Airframe:
    """``nominal`` with some airframe parameters changed (names of AIRFRAME_PARAMS, each checked
    against its range as a parameter set would be); ParameterError says what is wrong."""
    specs = {s.name: s for s in param_specs(nominal) if s.name in AIRFRAME_PARAMS}
    values = {name: float(spec.default) for name, spec in specs.items()}
    for name, value in changes.items():
        spec = specs.get(name)
        if spec is None:
            raise ParameterError(f"{name} is not an airframe parameter ({', '.join(sorted(specs))})")
        if not (math.isfinite(value) and spec.lo <= value <= spec.hi):
            raise ParameterError(f"{name} must be within [{spec.lo:g}, {spec.hi:g}], got {value:g}")
        values[name] = float(value)
    return airframe_from_params(nominal, values)
