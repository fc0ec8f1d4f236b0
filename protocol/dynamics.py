"""The tri-rotor's rigid-body dynamics, compiled (numba): the one copy of (24), (25) and (27), with
the propulsive force (3), the torques (11), (13), (14) and the aerodynamic drag of the body.

Two callers evaluate it: the simulated plant (``sitl/physics.py``, which carries the attitude as a
quaternion and integrates with RK4) and ``model.state_derivative`` (the paper's state (28) with
Euler angles and (26)). Each passes its own rotation body-to-earth; what happens to the body's
velocity and rates, and how it moves over the earth, is computed here only.

Frames as in ``model``: earth x north, y west, z up; body z the thrust axis at zero tilt.

Drag (``drag``), on top of the paper's model: F_e = -1/2 rho_air C_d A |v_rel| v_rel with
v_rel = R v_b - wind_e the air-relative velocity in the earth frame, acting at the centre of mass (no
torque), with one C_d A in every direction. Its factor 1/2 rho_air C_d A [kg/m] is the last entry of
the parameter vector. A caller in no air leaves it out: the paper's model, exactly as it was.

numba's cache does not notice an edit here in the compiled code of a caller in another file
(``sitl/physics.py``): after changing this file, delete the ``__pycache__/*.nbi`` and ``*.nbc`` files
(``tests/test_physics.py`` compares the two callers and fails on a stale one).
"""

from __future__ import annotations

import math

import numpy as np

from .airframe import Airframe
from .jit import njit

# Entries of the parameter vector (``airframe_vector``).
MASS, GRAVITY, ARM, IXX, IYY, IZZ, IYZ, KF, KD, MAX_OMEGA, SERVO_LIMIT, DRAG, SERVO_RATE = range(13)
PARAM_DIM = 13

_S3 = math.sqrt(3.0) / 2.0


def airframe_vector(af: Airframe, air_density_kg_m3: float = 0.0) -> np.ndarray:
    """The numbers the compiled dynamics need, in the order of the constants above. DRAG is the
    drag factor 1/2 rho_air C_d A [kg/m]: air density 0 (the default) is the paper's drag-free
    model."""
    drag = af.drag_factor_kg_m(air_density_kg_m3)
    return np.array([af.mass_kg, af.gravity_m_s2, af.arm_length_m, af.Ixx_kg_m2, af.Iyy_kg_m2, af.Izz_kg_m2,
                     af.Iyz_kg_m2, af.k_f_N_s2, af.k_d_N_m_s2, af.max_rotor_speed_rad_s, af.servo_limit_rad, drag,
                     af.servo_rate_rad_s])


@njit(inline="always")
def propulsive_force(rho):
    """(3) over k_f: H_f rho, the body-frame thrust per unit k_f [rad^2/s^2], as (x, y, z)."""
    return (-_S3 * rho[1] + _S3 * rho[2],
            rho[0] - 0.5 * rho[1] - 0.5 * rho[2],
            rho[3] + rho[4] + rho[5])


@njit(inline="always")
def rigid_body(u, v, w, p, q, r, R, rho, P):
    """d/dt of the body velocity (24) [m/s^2], the body rates (25) [rad/s^2] and the position (27)
    [m/s], as one 9-tuple, for body velocity (u, v, w), body rates (p, q, r), the rotation
    body-to-earth R as a row-major 9-tuple, input rho (29) and parameters P (``airframe_vector``).
    In no air; ``drag`` adds the air's share to the first three."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = R
    m, g, l, Ixx, Iyy, Izz, Iyz, kf, kd = P[MASS], P[GRAVITY], P[ARM], P[IXX], P[IYY], P[IZZ], P[IYZ], P[KF], P[KD]
    # (3), (13), (14): body force / k_f and torque.
    hf0, hf1, hf2 = propulsive_force(rho)
    tx = kf * l * (_S3 * rho[4] - _S3 * rho[5]) - kd * hf0
    ty = kf * l * (-rho[3] + 0.5 * rho[4] + 0.5 * rho[5]) - kd * hf1
    tz = kf * l * (rho[0] + rho[1] + rho[2]) - kd * hf2
    # (24): gravity in the body frame is R^T [0, 0, -g].
    ud = -g * r20 - (q * w - r * v) + kf / m * hf0
    vd = -g * r21 - (r * u - p * w) + kf / m * hf1
    wd = -g * r22 - (p * v - q * u) + kf / m * hf2
    # (25): I w_dot = tau - w x (I w), I = [[Ixx,0,0],[0,Iyy,-Iyz],[0,-Iyz,Izz]].
    Iwx = Ixx * p
    Iwy = Iyy * q - Iyz * r
    Iwz = -Iyz * q + Izz * r
    bx = tx - (q * Iwz - r * Iwy)
    by = ty - (r * Iwx - p * Iwz)
    bz = tz - (p * Iwy - q * Iwx)
    det = Iyy * Izz - Iyz * Iyz
    # (27): earth velocity = R v_b.
    return (ud, vd, wd, bx / Ixx, (Izz * by + Iyz * bz) / det, (Iyz * by + Iyy * bz) / det,
            r00 * u + r01 * v + r02 * w, r10 * u + r11 * v + r12 * w, r20 * u + r21 * v + r22 * w)


@njit(inline="always")
def drag(vel_e, R, P, wind):
    """The drag's share of (24), body frame [m/s^2], as (x, y, z): F_e = -k |v_rel| v_rel over the
    mass, brought into the body frame by R^T, for the earth velocity vel_e (3-tuple, (27)), the
    wind (3) [m/s] and k = P[DRAG]."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = R
    ax, ay, az = vel_e[0] - wind[0], vel_e[1] - wind[1], vel_e[2] - wind[2]
    k = -P[DRAG] * math.sqrt(ax * ax + ay * ay + az * az) / P[MASS]
    return (k * (r00 * ax + r10 * ay + r20 * az), k * (r01 * ax + r11 * ay + r21 * az),
            k * (r02 * ax + r12 * ay + r22 * az))


@njit()
def rigid_body_rows(vel_b, rate_b, R, rho, P, wind_e, out):
    """``rigid_body`` and ``drag`` for N rows: vel_b, rate_b, wind_e (N, 3), R (N, 3, 3), rho (N, 6);
    writes out (N, 9) = [v_b_dot, omega_dot, lambda_dot]."""
    for i in range(vel_b.shape[0]):
        Ri = R[i]
        Rt = (Ri[0, 0], Ri[0, 1], Ri[0, 2], Ri[1, 0], Ri[1, 1], Ri[1, 2], Ri[2, 0], Ri[2, 1], Ri[2, 2])
        d = rigid_body(vel_b[i, 0], vel_b[i, 1], vel_b[i, 2], rate_b[i, 0], rate_b[i, 1], rate_b[i, 2], Rt, rho[i], P)
        for k in range(9):
            out[i, k] = d[k]
        if P[DRAG] > 0.0:
            a = drag((d[6], d[7], d[8]), Rt, P, wind_e[i])
            for k in range(3):
                out[i, k] += a[k]
