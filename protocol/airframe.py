"""Physical parameters of a tri-rotor airframe (the paper's Table 1 by default).

One frozen dataclass per airframe, every field with its unit. The controller holds the nominal
airframe; a simulated plant may hold a different one (model mismatch).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from .errors import ParameterError

RPM_TO_RAD_S = 2.0 * math.pi / 60.0


def finite_number(what: str, value, *, positive: bool = False, non_negative: bool = False) -> float:
    """``value`` as a float, or ParameterError saying what ``what`` must be (a finite number, positive
    or not negative; a bool is no number)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ParameterError(f"{what} must be a finite number, got {value!r}")
    if positive and value <= 0:
        raise ParameterError(f"{what} must be positive, got {value!r}")
    if non_negative and value < 0:
        raise ParameterError(f"{what} must not be negative, got {value!r}")
    return float(value)


@dataclass(frozen=True)
class Airframe:
    """A tri-rotor with three independently tilting rotors (paper Section 3, Table 1)."""

    mass_kg: float = 0.5
    """Total mass m."""
    gravity_m_s2: float = 9.81
    """Gravity acceleration g."""
    arm_length_m: float = 0.23
    """Arm length l, centre of mass to each servo axis."""
    Ixx_kg_m2: float = 6.8e-3
    """Moment of inertia about body x."""
    Iyy_kg_m2: float = 5.3e-3
    """Moment of inertia about body y."""
    Izz_kg_m2: float = 1.7e-3
    """Moment of inertia about body z."""
    Iyz_kg_m2: float = 3.1e-4
    """Product of inertia about body y and z (enters (17) with a minus sign)."""
    k_f_N_s2: float = 1.97e-5
    """Thrust coefficient k_f: thrust [N] = k_f * omega^2 [rad^2/s^2]."""
    k_d_N_m_s2: float = 2.88e-7
    """Drag-torque coefficient k_d: reaction torque [N m] = k_d * omega^2."""
    max_rotor_speed_rad_s: float = 12000.0 * RPM_TO_RAD_S
    """Motor speed limit (12000 RPM in the paper's simulation)."""
    servo_limit_rad: float = math.radians(120.0)
    """Servo range is [-servo_limit_rad, +servo_limit_rad] about the untilted position.
    The case study needs more than about +-95 deg (errata); 120 deg leaves a margin."""
    servo_delay_s: float = 0.01
    """Transport delay from a servo command to the servo angle (0.01 s in the paper)."""
    servo_rate_rad_s: float = 0.0
    """How fast a servo turns [rad/s] (its datasheet's speed: 0.1 s per 60 deg is 10.5 rad/s); it
    moves towards the delayed command at that rate, through the middle of its range, never across
    its ends. 0: at once, the paper's model (the transport delay alone)."""
    drag_coefficient: float = 1.0
    """Drag coefficient C_d of the body (dimensionless), on frontal_area_m2: the body's drag is
    1/2 rho_air C_d A |v_rel| v_rel against its velocity relative to the air. Not in the paper: a
    simulated plant in air feels it, and controllers flying in air cancel it (``drag_factor_kg_m``).
    1.0 is a bluff body of plates and cylinders crosswise to the flow (Hoerner, Fluid-Dynamic Drag,
    1965: 1.0 to 1.2)."""
    frontal_area_m2: float = 0.02
    """Area the body shows the air [m^2], the same in every direction: a 0.5 kg frame with 0.23 m
    arms, its hub (about 0.12 m x 0.06 m seen edge-on), arms and motors; the rotor discs are not
    counted (their own drag is not modelled). With C_d = 1 the drag is 1.2 N at 10 m/s in sea-level
    air, a quarter of the weight."""

    def __post_init__(self) -> None:
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ParameterError(f"airframe parameter {field.name} must be a finite number, got {value!r}")
            allowed_zero = field.name in ("Iyz_kg_m2", "servo_delay_s", "servo_rate_rad_s", "k_d_N_m_s2",
                                           "drag_coefficient", "frontal_area_m2")
            if field.name == "Iyz_kg_m2":
                continue
            if value < 0 or (value == 0 and not allowed_zero):
                raise ParameterError(f"airframe parameter {field.name} must be positive, got {value!r}")
        if self.Iyz_kg_m2**2 >= self.Iyy_kg_m2 * self.Izz_kg_m2:
            raise ParameterError("airframe inertia is not positive definite: Iyz^2 must be below Iyy*Izz")
        if self.servo_limit_rad > math.pi:
            raise ParameterError("airframe parameter servo_limit_rad must not exceed pi")

    def drag_factor_kg_m(self, air_density_kg_m3: float) -> float:
        """1/2 rho_air C_d A [kg/m]: the body's drag is this times |v_rel| v_rel [N] in air of the
        given density [kg/m^3] (0: no air, no drag)."""
        return 0.5 * air_density_kg_m3 * self.drag_coefficient * self.frontal_area_m2

    @property
    def max_omega_sq(self) -> float:
        """Largest rotor speed squared [rad^2/s^2]."""
        return self.max_rotor_speed_rad_s**2

    def replace(self, **changes: float) -> "Airframe":
        return dataclasses.replace(self, **changes)

    def with_mismatch(self, inertia_scale: float, k_f_scale: float) -> "Airframe":
        """A plant whose mass and inertias are scaled by `inertia_scale` and k_f by `k_f_scale`."""
        return dataclasses.replace(
            self,
            mass_kg=self.mass_kg * inertia_scale,
            Ixx_kg_m2=self.Ixx_kg_m2 * inertia_scale,
            Iyy_kg_m2=self.Iyy_kg_m2 * inertia_scale,
            Izz_kg_m2=self.Izz_kg_m2 * inertia_scale,
            Iyz_kg_m2=self.Iyz_kg_m2 * inertia_scale,
            k_f_N_s2=self.k_f_N_s2 * k_f_scale,
        )


TABLE_1 = Airframe()
"""The airframe of the paper's Table 1 with the simulation's 12000 RPM limit and 0.01 s servo delay."""
