"""The tri-rotor model (24)-(27) and the actuator map (29), in the paper's frames.

Frames: earth frame x north, y west, z up (gravity along -z); body z is the thrust axis at zero
tilt. State (28) x = [u_b, v_b, w_b, p, q, r, phi, theta, psi, x, y, z]: body velocity [m/s],
body rates [rad/s], Euler angles ZYX [rad], earth position [m]. Input (29) u = rho =
[w1^2 sin a1, w2^2 sin a2, w3^2 sin a3, w1^2 cos a1, w2^2 cos a2, w3^2 cos a3] in rad^2/s^2.

Every function takes arrays with any leading axes (one drone or a batch) and returns arrays.
"""

from __future__ import annotations

import numpy as np

from . import dynamics
from .airframe import Airframe
from .wind import SEA_LEVEL_AIR_DENSITY_KG_M3

# Slices of the state vector (28).
BODY_VEL = slice(0, 3)
BODY_RATE = slice(3, 6)
EULER = slice(6, 9)
POSITION = slice(9, 12)
STATE_DIM = 12
INPUT_DIM = 6

_S3 = np.sqrt(3.0) / 2.0

# (3): total propulsive force in body frame = k_f * H_f @ rho.
H_f = np.array(
    [
        [0.0, -_S3, _S3, 0.0, 0.0, 0.0],
        [1.0, -0.5, -0.5, 0.0, 0.0, 0.0],
        [0.0, 0.0, 0.0, 1.0, 1.0, 1.0],
    ]
)

# (11) without the factor l: propulsive torque in body frame = k_f * l * H_t_unit @ rho.
H_t_unit = np.array(
    [
        [0.0, 0.0, 0.0, 0.0, _S3, -_S3],
        [0.0, 0.0, 0.0, -1.0, 0.5, 0.5],
        [1.0, 1.0, 1.0, 0.0, 0.0, 0.0],
    ]
)


def inertia_matrix(af: Airframe) -> np.ndarray:
    """(17): inertia matrix in the body frame [kg m^2]."""
    return np.array(
        [
            [af.Ixx_kg_m2, 0.0, 0.0],
            [0.0, af.Iyy_kg_m2, -af.Iyz_kg_m2],
            [0.0, -af.Iyz_kg_m2, af.Izz_kg_m2],
        ]
    )


def torque_matrix(af: Airframe) -> np.ndarray:
    """(14): body torque = (k_f H_t - k_d H_f) @ rho [N m per rad^2/s^2]."""
    return af.k_f_N_s2 * af.arm_length_m * H_t_unit - af.k_d_N_m_s2 * H_f


def input_matrix(af: Airframe) -> np.ndarray:
    """G, the (constant) input matrix of (24)-(25): rows 0-2 body acceleration, rows 3-5 angular
    acceleration per unit rho. It is B_r's non-zero block (B_r = G(0))."""
    return np.vstack([af.k_f_N_s2 / af.mass_kg * H_f, np.linalg.solve(inertia_matrix(af), torque_matrix(af))])


def rotation_body_to_earth(eta: np.ndarray) -> np.ndarray:
    """(7): R_b2e = R_z(psi) R_y(theta) R_x(phi), shape (..., 3, 3)."""
    eta = np.asarray(eta)
    sf, cf = np.sin(eta[..., 0]), np.cos(eta[..., 0])
    st, ct = np.sin(eta[..., 1]), np.cos(eta[..., 1])
    sp, cp = np.sin(eta[..., 2]), np.cos(eta[..., 2])
    R = np.empty(eta.shape[:-1] + (3, 3), dtype=np.result_type(eta, float))
    R[..., 0, 0] = ct * cp
    R[..., 0, 1] = cp * st * sf - cf * sp
    R[..., 0, 2] = cf * cp * st + sf * sp
    R[..., 1, 0] = ct * sp
    R[..., 1, 1] = st * sf * sp + cf * cp
    R[..., 1, 2] = cf * st * sp - cp * sf
    R[..., 2, 0] = -st
    R[..., 2, 1] = ct * sf
    R[..., 2, 2] = cf * ct
    return R


def euler_rate_matrix(eta: np.ndarray) -> np.ndarray:
    """(23) corrected (errata): eta_dot = Psi(eta) @ omega_body, valid for |theta| < pi/2."""
    eta = np.asarray(eta)
    sf, cf = np.sin(eta[..., 0]), np.cos(eta[..., 0])
    tt, sec = np.tan(eta[..., 1]), 1.0 / np.cos(eta[..., 1])
    Psi = np.zeros(eta.shape[:-1] + (3, 3), dtype=np.result_type(eta, float))
    Psi[..., 0, 0] = 1.0
    Psi[..., 0, 1] = sf * tt
    Psi[..., 0, 2] = cf * tt
    Psi[..., 1, 1] = cf
    Psi[..., 1, 2] = -sf
    Psi[..., 2, 1] = sf * sec
    Psi[..., 2, 2] = cf * sec
    return Psi


def body_rate_matrix(eta: np.ndarray) -> np.ndarray:
    """W(eta) = Psi(eta)^-1: omega_body = W @ eta_dot (defined for every pitch)."""
    eta = np.asarray(eta)
    sf, cf = np.sin(eta[..., 0]), np.cos(eta[..., 0])
    st, ct = np.sin(eta[..., 1]), np.cos(eta[..., 1])
    W = np.zeros(eta.shape[:-1] + (3, 3), dtype=np.result_type(eta, float))
    W[..., 0, 0] = 1.0
    W[..., 0, 2] = -st
    W[..., 1, 1] = cf
    W[..., 1, 2] = sf * ct
    W[..., 2, 1] = -sf
    W[..., 2, 2] = cf * ct
    return W


def euler_rate_matrix_dot(eta: np.ndarray, eta_dot: np.ndarray) -> np.ndarray:
    """d/dt Psi(eta) along eta_dot (psi does not enter Psi)."""
    sf, cf = np.sin(eta[..., 0]), np.cos(eta[..., 0])
    tt, sec = np.tan(eta[..., 1]), 1.0 / np.cos(eta[..., 1])
    dphi, dth = eta_dot[..., 0], eta_dot[..., 1]
    D = np.zeros(eta.shape[:-1] + (3, 3), dtype=np.result_type(eta, eta_dot, float))
    D[..., 0, 1] = cf * tt * dphi + sf * sec**2 * dth
    D[..., 0, 2] = -sf * tt * dphi + cf * sec**2 * dth
    D[..., 1, 1] = -sf * dphi
    D[..., 1, 2] = -cf * dphi
    D[..., 2, 1] = cf * sec * dphi + sf * sec * tt * dth
    D[..., 2, 2] = -sf * sec * dphi + cf * sec * tt * dth
    return D


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b over the last axis (np.cross, but it accepts complex arrays)."""
    return np.stack(
        [
            a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
            a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
            a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0],
        ],
        axis=-1,
    )


def state_derivative(x: np.ndarray, u: np.ndarray, af: Airframe, wind_e_m_s: np.ndarray | None = None,
                     air_density_kg_m3: float = SEA_LEVEL_AIR_DENSITY_KG_M3) -> np.ndarray:
    """(24)-(27): dx/dt for state x (..., 12) and input u = rho (..., 6). Without a wind this is the
    paper's model; with one (earth frame [m/s], (..., 3)) the body also feels the drag of the air
    (``dynamics``). (24), (25) and (27) are ``dynamics.rigid_body``, the plant's own; (26) is here."""
    x, u = np.asarray(x, dtype=float), np.asarray(u, dtype=float)
    wind = np.zeros(3) if wind_e_m_s is None else np.asarray(wind_e_m_s, dtype=float)
    lead = np.broadcast_shapes(x.shape[:-1], u.shape[:-1], wind.shape[:-1])
    rows = (-1,) if lead else (1,)
    x = np.ascontiguousarray(np.broadcast_to(x, lead + (STATE_DIM,)).reshape(rows + (STATE_DIM,)))
    u = np.ascontiguousarray(np.broadcast_to(u, lead + (INPUT_DIM,)).reshape(rows + (INPUT_DIM,)))
    wind = np.ascontiguousarray(np.broadcast_to(wind, lead + (3,)).reshape(rows + (3,)))
    P = dynamics.airframe_vector(af, 0.0 if wind_e_m_s is None else air_density_kg_m3)
    eta, w_b = x[:, EULER], x[:, BODY_RATE]
    out = np.empty((x.shape[0], 9))
    dynamics.rigid_body_rows(np.ascontiguousarray(x[:, BODY_VEL]), np.ascontiguousarray(w_b),
                             rotation_body_to_earth(eta), u, P, wind, out)
    eta_dot = (euler_rate_matrix(eta) @ w_b[..., None])[..., 0]
    return np.concatenate([out[:, 0:6], eta_dot, out[:, 6:9]], axis=-1).reshape(lead + (STATE_DIM,))


def actuator_map(omega_rad_s: np.ndarray, alpha_rad: np.ndarray) -> np.ndarray:
    """(29): rotor speeds omega (..., 3) [rad/s] and servo angles alpha (..., 3) [rad] to rho (..., 6)."""
    w2 = np.asarray(omega_rad_s) ** 2
    return np.concatenate([w2 * np.sin(alpha_rad), w2 * np.cos(alpha_rad)], axis=-1)


def actuator_inverse(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Remark 1: rho (..., 6) to rotor speeds [rad/s] and servo angles [rad], both (..., 3).

    alpha = atan2(u_i, u_{i+3}) is the four-quadrant form of the paper's arctan(u_i / u_{i+3}), so a
    rotor asked to push along its negative shaft axis gets |alpha| > 90 deg instead of a sign error.
    """
    u = np.asarray(u)
    s, c = u[..., 0:3], u[..., 3:6]
    return np.sqrt(np.hypot(s, c)), np.arctan2(s, c)


def hover_input(af: Airframe) -> np.ndarray:
    """rho that holds the level drone still: body force [0, 0, m g] and zero torque."""
    wrench = np.array([0.0, 0.0, af.gravity_m_s2, 0.0, 0.0, 0.0])
    return np.linalg.solve(input_matrix(af), wrench)


def hover_trim(af: Airframe) -> tuple[np.ndarray, np.ndarray]:
    """Rotor speeds [rad/s] and servo angles [rad] of the hover input."""
    return actuator_inverse(hover_input(af))
