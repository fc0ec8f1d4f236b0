"""Robust feedback linearization (49)-(56) of the tri-rotor.

Outputs y = (eta, lambda) have relative degree 2 each. With
    phi_c(x) = [eta, lambda, Psi(eta) omega, R_b2e(eta) v_b]              (Brunovsky coordinates)
    y_ddot   = b(x) + M(x) u,   b = L_f^2 H,   M (57)
the law u = alpha(x) + beta(x) v (49)-(51) makes x_r = phi_r(x) = U^-1 phi_c(x) (52) obey
    x_r_dot = A_r x_r + B_r v                                           (58)
exactly wherever M(x) is invertible (|theta| < pi/2), where A_r, B_r are the Jacobian
linearization of (24)-(27) at hover. x_r = [lambda_dot (3), eta_dot (3), eta (3), lambda (3)].

U (55) and L (53) are computed here from their definitions: U by differentiating phi_c at the origin
and L by complex-step differentiation of alpha_c, which is exact to rounding.

Drag (not in the paper). In air of density rho the body also feels F = -k |v_rel| v_rel,
k = 1/2 rho C_d A (``dynamics.drag``), a force on the centre of mass: it adds
-(k/m) |lambda_dot| lambda_dot to lambda_ddot in still air, and nothing to eta_ddot. That is a known
function of the state, so the law takes it into b(x) (``air_density_kg_m3``) and cancels it with the
rest of the nonlinearity: the drone in still air then obeys (58) exactly, and what is left for the
disturbance observer is the wind's share, -(k/m) (|v - w| (v - w) - |v| v). The linear model does not
change: d(|v| v)/dv = |v| I + v v^T / |v| vanishes at v = 0, so the Jacobian at hover, A_r, and with
it L, are the paper's (complex steps would not see |v| anyway: it is not analytic).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import kernels
from .airframe import Airframe
from .model import (
    BODY_RATE,
    BODY_VEL,
    EULER,
    POSITION,
    STATE_DIM,
    _cross,
    euler_rate_matrix,
    euler_rate_matrix_dot,
    inertia_matrix,
    input_matrix,
    rotation_body_to_earth,
    torque_matrix,
    H_f,
)

MAX_PITCH_RAD = 1.4
"""Pitch beyond which the law is not evaluated (Psi is singular at +-pi/2, errata)."""

# Slices of x_r.
XR_VEL = slice(0, 3)
XR_EULER_RATE = slice(3, 6)
XR_EULER = slice(6, 9)
XR_POS = slice(9, 12)


def phi_c(x: np.ndarray) -> np.ndarray:
    """Brunovsky coordinates [y, y_dot] = [eta, lambda, Psi omega, R v_b] for x (..., 12)."""
    eta = x[..., EULER]
    eta_dot = (euler_rate_matrix(eta) @ x[..., BODY_RATE, None])[..., 0]
    vel_e = (rotation_body_to_earth(eta) @ x[..., BODY_VEL, None])[..., 0]
    return np.concatenate([eta, x[..., POSITION], eta_dot, vel_e], axis=-1)


def decoupling_matrix(x: np.ndarray, af: Airframe) -> np.ndarray:
    """(57): M(x) with y_ddot = b(x) + M(x) u, shape (..., 6, 6)."""
    eta = x[..., EULER]
    Psi = euler_rate_matrix(eta)
    R = rotation_body_to_earth(eta)
    Iinv_tau = np.linalg.solve(inertia_matrix(af), torque_matrix(af))
    top = Psi @ Iinv_tau
    bottom = (af.k_f_N_s2 / af.mass_kg) * (R @ H_f)
    return np.concatenate([top, bottom], axis=-2)


def drift_output_acceleration(x: np.ndarray, af: Airframe, air_density_kg_m3: float = 0.0,
                              wind_e_m_s: np.ndarray | None = None) -> np.ndarray:
    """b(x) = L_f^2 H(x): y_ddot with zero input, shape (..., 6).

    eta_ddot = Psi_dot omega + Psi I^-1 (-omega x I omega); lambda_ddot = [0, 0, -g] because
    d/dt (R v_b) = R (v_dot + omega x v) and the Coriolis terms cancel. In air of density
    air_density_kg_m3 [kg/m^3] lambda_ddot also has the drag -(k/m) |r| r, r = R v_b - w the velocity
    through the air in the wind w = wind_e_m_s (earth frame [m/s], (..., 3); None: still air)
    (module docstring).
    """
    eta, w = x[..., EULER], x[..., BODY_RATE]
    I = inertia_matrix(af)
    Psi = euler_rate_matrix(eta)
    eta_dot = (Psi @ w[..., None])[..., 0]
    Psi_dot = euler_rate_matrix_dot(eta, eta_dot)
    gyro = -np.linalg.solve(I, _cross(w, w @ I.T)[..., None])[..., 0]
    eta_ddot = (Psi_dot @ w[..., None])[..., 0] + (Psi @ gyro[..., None])[..., 0]
    lam_ddot = np.zeros(x.shape[:-1] + (3,), dtype=eta_ddot.dtype)
    lam_ddot[..., 2] = -af.gravity_m_s2
    if air_density_kg_m3 > 0.0:
        vel_e = (rotation_body_to_earth(eta) @ x[..., BODY_VEL, None])[..., 0]
        if wind_e_m_s is not None:
            vel_e = vel_e - wind_e_m_s
        speed = np.sqrt((vel_e * vel_e).sum(axis=-1, keepdims=True))
        lam_ddot = lam_ddot - af.drag_factor_kg_m(air_density_kg_m3) / af.mass_kg * speed * vel_e
    return np.concatenate([eta_ddot, lam_ddot], axis=-1)


def alpha_c(x: np.ndarray, af: Airframe) -> np.ndarray:
    """(46): classical linearizing feedback alpha_c = -M^-1 b."""
    return -np.linalg.solve(decoupling_matrix(x, af), drift_output_acceleration(x, af)[..., None])[..., 0]


def _complex_step_jacobian(f, x0: np.ndarray, step: float = 1e-30) -> np.ndarray:
    """Jacobian of a real-analytic f at x0 by complex steps (no cancellation error)."""
    cols = []
    for k in range(x0.size):
        xc = x0.astype(complex)
        xc[k] += 1j * step
        cols.append(np.imag(f(xc)) / step)
    return np.stack(cols, axis=-1)


@dataclass(frozen=True)
class RFL:
    """The robust feedback linearization of one airframe around hover at the origin."""

    airframe: Airframe
    U: np.ndarray
    """(55): d phi_c / dx at 0 (a permutation)."""
    L: np.ndarray
    """(53): -M(0) d alpha_c / dx at 0."""
    M0: np.ndarray
    """M(0) = R^-1 (54)."""
    U_inv: np.ndarray
    G_inv: np.ndarray
    """Inverse of the constant input matrix G of (24)-(25) (B_r's non-zero rows)."""
    inertia: np.ndarray
    inertia_inv: np.ndarray
    A_r: np.ndarray
    B_r: np.ndarray
    C_r: np.ndarray

    @classmethod
    def from_airframe(cls, af: Airframe) -> "RFL":
        origin = np.zeros(STATE_DIM)
        U = _complex_step_jacobian(phi_c, origin)
        U = np.round(U, 12)  # exact 0/1 entries; rounding removes nothing but float dust
        L = -decoupling_matrix(origin, af) @ _complex_step_jacobian(lambda x: alpha_c(x, af), origin)
        M0 = decoupling_matrix(origin, af)
        # Brunovsky pair for six double integrators, phi_c = [y, y_dot].
        A_c = np.zeros((12, 12))
        A_c[0:6, 6:12] = np.eye(6)
        B_c = np.zeros((12, 6))
        B_c[6:12, :] = np.eye(6)
        Uinv = np.linalg.inv(U)
        # x_r = U^-1 x_c with y_ddot = w = L x_r + M0 v gives (58):
        A_r = Uinv @ (A_c @ U + B_c @ L)
        B_r = Uinv @ B_c @ M0
        C_r = np.zeros((6, 12))
        C_r[:, 6:12] = np.eye(6)
        G_inv = np.linalg.inv(input_matrix(af))
        inertia = inertia_matrix(af)
        inertia_inv = np.linalg.inv(inertia)
        for arr in (U, L, M0, Uinv, G_inv, inertia, inertia_inv, A_r, B_r, C_r):
            arr.setflags(write=False)
        return cls(af, U, L, M0, Uinv, G_inv, inertia, inertia_inv, A_r, B_r, C_r)

    def phi_r(self, x: np.ndarray) -> np.ndarray:
        """(52): x_r = U^-1 phi_c(x)."""
        return phi_c(x) @ self.U_inv.T

    @staticmethod
    def phi_r_inverse(x_r: np.ndarray, max_pitch_rad: float = MAX_PITCH_RAD) -> np.ndarray:
        """The state x (28) with phi_r(x) = x_r: omega = Psi(eta)^-1 eta_dot, v_b = R^T lambda_dot.

        Pitch is clipped to +-max_pitch_rad so that an estimate far off never meets the
        singularity of Psi at +-pi/2 (the controller's validity limit, errata)."""
        eta = x_r[..., XR_EULER].copy()
        eta[..., 1] = np.clip(eta[..., 1], -max_pitch_rad, max_pitch_rad)
        omega = np.linalg.solve(euler_rate_matrix(eta), x_r[..., XR_EULER_RATE, None])[..., 0]
        R = rotation_body_to_earth(eta)
        v_b = (np.swapaxes(R, -1, -2) @ x_r[..., XR_VEL, None])[..., 0]
        return np.concatenate([v_b, omega, eta, x_r[..., XR_POS]], axis=-1)

    def drag_per_mass_1_m(self, air_density_kg_m3: float) -> float:
        """k / m = 1/2 rho C_d A / m [1/m]: the body's drag acceleration is this times |v| v in still
        air of density air_density_kg_m3 [kg/m^3]."""
        return self.airframe.drag_factor_kg_m(air_density_kg_m3) / self.airframe.mass_kg

    def alpha(self, x: np.ndarray) -> np.ndarray:
        """(50): alpha(x) = alpha_c(x) + beta_c(x) L phi_r(x)."""
        return self.control(x, np.zeros(x.shape[:-1] + (6,)))

    def beta(self, x: np.ndarray) -> np.ndarray:
        """(51): beta(x) = M(x)^-1 M(0), shape (..., 6, 6)."""
        return np.linalg.solve(decoupling_matrix(x, self.airframe), np.broadcast_to(self.M0, x.shape[:-1] + (6, 6)))

    def control(self, x: np.ndarray, v: np.ndarray, air_density_kg_m3: float = 0.0,
                wind_e_m_s: np.ndarray | None = None) -> np.ndarray:
        """(49): u = alpha(x) + beta(x) v = M(x)^-1 (-b(x) + L phi_r(x) + M(0) v), with the drag in
        air of density air_density_kg_m3 [kg/m^3] (0: the paper's law, no air) and the wind
        wind_e_m_s (earth frame [m/s]; None: still air) in b(x)."""
        b = drift_output_acceleration(x, self.airframe, air_density_kg_m3, wind_e_m_s)
        target = -b + self.phi_r(x) @ self.L.T + v @ self.M0.T
        return np.linalg.solve(decoupling_matrix(x, self.airframe), target[..., None])[..., 0]

    def control_xr(self, x_r: np.ndarray, v: np.ndarray, max_pitch_rad: float = MAX_PITCH_RAD,
                   air_density_kg_m3: float = 0.0, wind_e_m_s: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(49) written in x_r coordinates, without a linear solve: returns u (..., 6) and the
        commanded output acceleration y_ddot = L x_r + M(0) v (..., 6) (its rows 4-6 plus g e_z,
        plus (k/m) |r| r in air, r = lambda_dot - wind_e_m_s, are the commanded specific thrust in
        the earth frame).

        M(x) = blockdiag(Psi, R_b2e) G with G constant, so M^-1 t = G^-1 [W t_eta; R^T t_lambda],
        W = Psi^-1; omega = W eta_dot. Equal to ``control(phi_r^-1(x_r), v, air_density_kg_m3, wind_e_m_s)``
        (tested). Compiled (``kernels.rfl_xr_row``): it runs on every tick of every drone."""
        xr2 = np.ascontiguousarray(np.asarray(x_r, dtype=float).reshape(-1, 12))
        v2 = np.ascontiguousarray(np.broadcast_to(np.asarray(v, dtype=float), x_r.shape[:-1] + (6,)).reshape(-1, 6))
        wind2 = np.zeros((xr2.shape[0], 3)) if wind_e_m_s is None else np.ascontiguousarray(
            np.broadcast_to(np.asarray(wind_e_m_s, dtype=float), x_r.shape[:-1] + (3,)).reshape(-1, 3))
        u = np.empty((xr2.shape[0], 6))
        yddot = np.empty((xr2.shape[0], 6))
        kernels.rfl_xr(xr2, v2, self.L, self.M0, self.inertia, self.inertia_inv, self.G_inv,
                       self.airframe.gravity_m_s2, self.drag_per_mass_1_m(air_density_kg_m3), wind2, max_pitch_rad, u,
                       yddot)
        shape = x_r.shape[:-1] + (6,)
        return u.reshape(shape), yddot.reshape(shape)
