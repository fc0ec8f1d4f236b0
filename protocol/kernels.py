"""The arithmetic of one control tick, compiled (numba): the observer update and prediction, the RFL
law in x_r coordinates, thrust adaptation and the actuator inverse, for N rows at once.

``RFL.control_xr`` and ``FormationController`` call them, so the batch simulation and a companion
run the same code. The actuator inverse at the end of ``actuate`` is ``model.actuator_inverse``
(Remark 1) written per element, inside the compiled loop. Pure functions of arrays; outputs are
written into arrays the caller passes.
"""

from __future__ import annotations

import math

import numpy as np

from .jit import njit

TORQUE_PRIORITY = 100.0
"""How much more an angular acceleration counts than a specific force [(m/s^2) / (rad/s^2)] where the
servo range leaves a drone short (``allocate_within_range``): per unit of rotor input the angular rows
of G are already 10-70 times the force rows, so the attitude is kept and the force gives way."""


@njit()
def _matvec_add(M, x, out, scale=1.0):
    for r in range(M.shape[0]):
        acc = 0.0
        for c in range(M.shape[1]):
            acc += M[r, c] * x[c]
        out[r] += scale * acc


@njit(inline="always")
def drag_share(xr, drag, wind):
    """What the thrust must add to the specific force, earth frame [m/s^2], to cancel the body's drag
    -drag |r| r, r = lambda_dot - wind its velocity through the air, at x_r (lambda_dot = xr[0:3]) in
    the wind ``wind`` (3, earth frame [m/s]; zeros: still air); drag = k / m [1/m]."""
    rx, ry, rz = xr[0] - wind[0], xr[1] - wind[1], xr[2] - wind[2]
    s = drag * math.sqrt(rx * rx + ry * ry + rz * rz)
    return s * rx, s * ry, s * rz


@njit()
def update_wind_estimate(xr, d, drag, gain, floor, wind):
    """One step of the wind estimate ``wind`` (3, earth frame [m/s], updated in place) from the
    translational disturbance d (3, [m/s^2]) that is left once the drag in that wind is cancelled:
    d ~ drag J(r) (w - wind), J(r) = |r| I + r r^T / |r| the Jacobian of |r| r, r = lambda_dot - wind.
    The step is gain J^-1 d / drag (gain = rate [1/s] times the period [s]), with |r| taken at least
    ``floor`` [m/s] (slow air says little about the wind), and horizontal: the mean wind is, and a
    vertical one would be told apart from a thrust error only by the vertical speed."""
    rx, ry, rz = xr[0] - wind[0], xr[1] - wind[1], xr[2] - wind[2]
    speed = max(math.sqrt(rx * rx + ry * ry + rz * rz), floor)
    # J^-1 = (I - r r^T / (2 |r|^2)) / |r|
    rd = (rx * d[0] + ry * d[1] + rz * d[2]) / (2.0 * speed * speed)
    k = gain / (drag * speed)
    wind[0] += k * (d[0] - rx * rd)
    wind[1] += k * (d[1] - ry * rd)


@njit()
def rfl_xr_row(xr, v, L, M0, I, Ii, G_inv, g, drag, wind, max_pitch, u, yddot):
    """(49) in x_r coordinates for one row (see RFL.control_xr): writes u (6) and y_ddot (6). With
    drag = k / m > 0 [1/m] the law also cancels the body's drag in the wind ``wind`` (3, earth frame
    [m/s]; zeros: still air) (``rfl`` module docstring)."""
    for k in range(6):
        acc = 0.0
        for c in range(12):
            acc += L[k, c] * xr[c]
        for c in range(6):
            acc += M0[k, c] * v[c]
        yddot[k] = acc
    phi = xr[6]
    theta = min(max(xr[7], -max_pitch), max_pitch)
    psi = xr[8]
    dphi, dth, dpsi = xr[3], xr[4], xr[5]
    sf, cf = math.sin(phi), math.cos(phi)
    st, ct = math.sin(theta), math.cos(theta)
    sp, cp = math.sin(psi), math.cos(psi)
    # omega = W eta_dot
    p = dphi - st * dpsi
    q = cf * dth + sf * ct * dpsi
    r = -sf * dth + cf * ct * dpsi
    # eta_ddot - Psi_dot omega
    tt, sec = st / ct, 1.0 / ct
    a0 = yddot[0] - ((cf * tt * dphi + sf * sec * sec * dth) * q + (-sf * tt * dphi + cf * sec * sec * dth) * r)
    a1 = yddot[1] - ((-sf * dphi) * q + (-cf * dphi) * r)
    a2 = yddot[2] - ((cf * sec * dphi + sf * sec * tt * dth) * q + (-sf * sec * dphi + cf * sec * tt * dth) * r)
    # omega_dot = W (eta_ddot - Psi_dot omega) + I^-1 (omega x I omega)
    Iw0 = I[0, 0] * p + I[0, 1] * q + I[0, 2] * r
    Iw1 = I[1, 0] * p + I[1, 1] * q + I[1, 2] * r
    Iw2 = I[2, 0] * p + I[2, 1] * q + I[2, 2] * r
    c0, c1, c2 = q * Iw2 - r * Iw1, r * Iw0 - p * Iw2, p * Iw1 - q * Iw0
    w = np.empty(6)
    w[3] = a0 - st * a2 + Ii[0, 0] * c0 + Ii[0, 1] * c1 + Ii[0, 2] * c2
    w[4] = cf * a1 + sf * ct * a2 + Ii[1, 0] * c0 + Ii[1, 1] * c1 + Ii[1, 2] * c2
    w[5] = -sf * a1 + cf * ct * a2 + Ii[2, 0] * c0 + Ii[2, 1] * c1 + Ii[2, 2] * c2
    # body specific force = R^T (lambda_ddot + g e_z)
    fx, fy, fz = yddot[3], yddot[4], yddot[5] + g
    if drag > 0.0:  # (no air: not a single operation more, the paper's law to the bit)
        dx, dy, dz = drag_share(xr, drag, wind)
        fx, fy, fz = fx + dx, fy + dy, fz + dz
    w[0] = ct * cp * fx + ct * sp * fy - st * fz
    w[1] = (sf * st * cp - cf * sp) * fx + (sf * st * sp + cf * cp) * fy + sf * ct * fz
    w[2] = (cf * st * cp + sf * sp) * fx + (cf * st * sp - sf * cp) * fy + cf * ct * fz
    u[:] = 0.0
    _matvec_add(G_inv, w, u)


@njit(inline="always")
def body_to_earth(phi, theta, psi, b0, b1, b2):
    """R(eta) b: a body-frame vector in the earth frame (paper frames, ZYX Euler angles)."""
    sf, cf = math.sin(phi), math.cos(phi)
    st, ct = math.sin(theta), math.cos(theta)
    sp, cp = math.sin(psi), math.cos(psi)
    return (ct * cp * b0 + (sf * st * cp - cf * sp) * b1 + (cf * st * cp + sf * sp) * b2,
            ct * sp * b0 + (sf * st * sp + cf * cp) * b1 + (cf * st * sp - sf * cp) * b2,
            -st * b0 + sf * ct * b1 + cf * ct * b2)


@njit()
def input_shortfall_v(xr, du, G, M0_inv, max_pitch, dv):
    """The protocol input dv (6) that the RFL at x_r would have turned into the input change du (6,
    rad^2/s^2): the inverse of ``rfl_xr_row``'s map v -> u at that state, which is affine in v
    (u = G^-1 blockdiag(R^T, W) M0 v + ..., W = Psi^-1). dv = M0^-1 [Psi (G du)[3:6]; R (G du)[0:3]]."""
    phi = xr[6]
    theta = min(max(xr[7], -max_pitch), max_pitch)
    psi = xr[8]
    sf, cf = math.sin(phi), math.cos(phi)
    st, ct = math.sin(theta), math.cos(theta)
    w = np.zeros(6)
    _matvec_add(G, du, w)
    y = np.empty(6)
    tt, sec = st / ct, 1.0 / ct
    # eta rows: Psi(eta) times the Euler-acceleration part of w
    y[0] = w[3] + sf * tt * w[4] + cf * tt * w[5]
    y[1] = cf * w[4] - sf * w[5]
    y[2] = sf * sec * w[4] + cf * sec * w[5]
    # lambda rows: R_b2e times the body specific force
    y[3], y[4], y[5] = body_to_earth(phi, theta, psi, w[0], w[1], w[2])
    dv[:] = 0.0
    _matvec_add(M0_inv, y, dv)


@njit()
def rfl_xr(xr, v, L, M0, I, Ii, G_inv, g, drag, wind, max_pitch, u, yddot):
    for i in range(xr.shape[0]):
        rfl_xr_row(xr[i], v[i], L, M0, I, Ii, G_inv, g, drag, wind[i], max_pitch, u[i], yddot[i])


@njit()
def euler_rates(phi, theta, p, q, r, max_pitch, out):
    """eta_dot = Psi(eta) omega (23, errata) into out (3), pitch clipped to +-max_pitch."""
    theta = min(max(theta, -max_pitch), max_pitch)
    sf, cf = math.sin(phi), math.cos(phi)
    tt, sec = math.tan(theta), 1.0 / math.cos(theta)
    out[0] = p + sf * tt * q + cf * tt * r
    out[1] = cf * q - sf * r
    out[2] = sf * sec * q + cf * sec * r


@njit()
def observe(rows, z, v_applied, y_prev, y, fresh, Phi, Gv, Gy0, Gy1, Phi1, G1, pred_Phi, pred_G, v_pipe, z_pred,
            rate_b, accel_b, B_accel, g, max_pitch):
    """One observer step for each agent row in ``rows`` (FOH on y, ZOH on v), then the prediction
    over the pipe; y[k] is row rows[k]'s measurement (eta, lambda). A row whose measurement is not
    finite runs the open-loop model instead; a fresh row (just reset at this instant) only takes the
    measurement. Updates z, y_prev, fresh, z_pred of those rows.

    The observer has up to 12 outputs (``design.full_output``), and Phi, Gv, Gy0, Gy1 (4, ...) one
    discretisation per set of them measured (index: 1 with rates, + 2 with the acceleration).
    rate_b[k] is row rows[k]'s measured body rates (NaN: none): they give the Euler rates
    Psi(eta) omega (eta measured). accel_b[k] is its measured specific force, body frame [m/s^2]
    (NaN: none): it gives the earth-frame acceleration R(eta) f - g e_z, less B_accel v_applied (the
    part the model's input explains, x_r rows 1-3 of B_r). An output measured now and not the tick
    before starts its first-order hold from now. y_prev (N, 12) keeps the last outputs (NaN: not
    measured). A row with (eta, lambda) alone runs as the observer of 6 outputs, bit for bit."""
    nz = z.shape[1]
    tmp = np.empty(nz)
    ed = np.empty(3)
    yk = np.empty(12)
    for k in range(rows.shape[0]):
        i = rows[k]
        ok = True
        for c in range(y.shape[1]):
            if not math.isfinite(y[k, c]):
                ok = False
        yk[:6] = y[k, :]
        yk[6:] = math.nan
        rated = ok and math.isfinite(rate_b[k, 0]) and math.isfinite(rate_b[k, 1]) and math.isfinite(rate_b[k, 2])
        if rated:
            euler_rates(y[k, 0], y[k, 1], rate_b[k, 0], rate_b[k, 1], rate_b[k, 2], max_pitch, ed)
            yk[6:9] = ed
        felt = ok and math.isfinite(accel_b[k, 0]) and math.isfinite(accel_b[k, 1]) and math.isfinite(accel_b[k, 2])
        if felt:
            ax, ay, az = body_to_earth(y[k, 0], y[k, 1], y[k, 2], accel_b[k, 0], accel_b[k, 1], accel_b[k, 2])
            yk[9], yk[10], yk[11] = ax, ay, az - g
            for r in range(3):
                for c in range(6):
                    yk[9 + r] -= B_accel[r, c] * v_applied[i, c]
        m = (1 if rated else 0) + (2 if felt else 0)
        if fresh[i]:
            fresh[i] = False
            if ok:
                y_prev[i, :] = yk
            else:
                y_prev[i, 6:] = math.nan
        else:
            tmp[:] = 0.0
            if ok:
                for c in range(6, 12):
                    if not math.isfinite(y_prev[i, c]):
                        y_prev[i, c] = yk[c]
                _matvec_add(Phi[m], z[i], tmp)
                _matvec_add(Gv[m], v_applied[i], tmp)
                _matvec_add(Gy0[m][:, :6], y_prev[i, :6], tmp)
                if rated:
                    _matvec_add(Gy0[m][:, 6:9], y_prev[i, 6:9], tmp)
                if felt:
                    _matvec_add(Gy0[m][:, 9:12], y_prev[i, 9:12], tmp)
                _matvec_add(Gy1[m][:, :6], yk[:6], tmp)
                if rated:
                    _matvec_add(Gy1[m][:, 6:9], yk[6:9], tmp)
                if felt:
                    _matvec_add(Gy1[m][:, 9:12], yk[9:12], tmp)
                y_prev[i, :] = yk
            else:
                _matvec_add(Phi1, z[i], tmp)
                _matvec_add(G1, v_applied[i], tmp)
                y_prev[i, 6:] = math.nan
            z[i, :] = tmp
        z_pred[i, :] = 0.0
        _matvec_add(pred_Phi, z[i], z_pred[i])
        for j in range(pred_G.shape[0]):
            _matvec_add(pred_G[j], v_pipe[j, i], z_pred[i])


@njit()
def push(rows, v, omega, keep_motor, v_pipe, motor_pipe, v_applied, omega_now):
    """Commit each row's v (and its rotor speeds, unless ``keep_motor``: the actuators kept the
    last ones) to the pipes. The v pipe's depth D = v_pipe.shape[0] is the lead in ticks: the servo
    delay and the latency compensated, the time from a measurement to the servos acting on its
    command; the v leaving it is the one the plant applies at the instant measured now
    (``v_applied``). The motor pipe's depth Dm <= D is the servo delay alone: the rotor speeds leaving
    it are the ones to send now (``omega_now``; with no servo delay, ``omega`` itself), so that the
    motors act with the servos."""
    D, Dm = v_pipe.shape[0], motor_pipe.shape[0]
    for k in range(rows.shape[0]):
        i = rows[k]
        if D == 0:
            v_applied[i, :] = v[k, :]
        else:
            v_applied[i, :] = v_pipe[0, i, :]
            for d in range(D - 1):
                v_pipe[d, i, :] = v_pipe[d + 1, i, :]
            v_pipe[D - 1, i, :] = v[k, :]
        if Dm == 0:
            if not keep_motor:
                omega_now[k, :] = omega[k, :]
            continue
        omega_now[k, :] = motor_pipe[0, i, :]
        for d in range(Dm - 1):
            motor_pipe[d, i, :] = motor_pipe[d + 1, i, :]
        if not keep_motor:
            motor_pipe[Dm - 1, i, :] = omega[k, :]


@njit()
def _nnls(A, b, x):
    """x >= 0 (written) minimising |A x - b|: Lawson and Hanson's active-set method, for the small
    problems of ``allocate_within_reach`` (6 rows, 6 columns)."""
    m, n = A.shape
    x[:] = 0.0
    passive = np.zeros(n, np.bool_)
    r = b.copy()
    grad = A.T @ r
    tol = 1e-12 * (np.abs(grad).max() + 1e-300)
    s = np.zeros(n)
    for _ in range(3 * n):
        j_max, g_max = -1, tol
        for j in range(n):
            if not passive[j] and grad[j] > g_max:
                j_max, g_max = j, grad[j]
        if j_max < 0:
            break
        passive[j_max] = True
        for _inner in range(3 * n):
            idx = np.nonzero(passive)[0]
            s[:] = 0.0
            sol = np.linalg.lstsq(A[:, idx], b)[0]
            for q in range(idx.size):
                s[idx[q]] = sol[q]
            step = 1.0
            for q in range(idx.size):
                c = idx[q]
                if s[c] <= 0.0:
                    t = x[c] / (x[c] - s[c]) if x[c] - s[c] > 0.0 else 0.0
                    step = min(step, t)
            if step >= 1.0:
                x[:] = s
                break
            for c in range(n):
                x[c] += step * (s[c] - x[c])
                if passive[c] and x[c] <= 1e-15 * (abs(s[c]) + 1.0):
                    passive[c] = False
                    x[c] = 0.0
            if not passive.any():
                break
        r = b - A @ x
        grad = A.T @ r


@njit()
def allocate_within_range(rho, servo_limit, G, edge):
    """Rotor inputs rho (6: omega_j^2 sin alpha_j, then omega_j^2 cos alpha_j; updated in place) within
    the servo range |alpha_j| <= servo_limit, for the body accelerations w = G rho they were computed
    for (G: ``model.input_matrix``). While every rotor is within the range nothing changes (returns
    False). A rotor beyond it is held at the nearest edge (edge[j] = +-servo_limit; 0 for a rotor
    within), free to push along it, and the three rotors then give the angular accelerations of w
    first and, of its specific force, what is left: least squares with the angular rows weighted
    ``TORQUE_PRIORITY`` times. (The attitude bound is the tighter, and a torque shortfall turns the
    drone within a tenth of a second; a force shortfall moves it slowly, and the feedback takes it
    up.) A rotor that the solution pushes beyond the range joins the held ones in turn; a push along
    the edge that comes out negative is none. Inputs that are not finite (a state already lost) are
    left as they are."""
    edge[:] = 0.0
    w = np.empty(0)  # (the accelerations asked: computed once a rotor is beyond, not every tick)
    held = 0
    for _ in range(3):
        grew = False
        for j in range(3):
            if edge[j] == 0.0:
                a = math.atan2(rho[j], rho[j + 3])
                if abs(a) > servo_limit:
                    edge[j] = math.copysign(servo_limit, a)
                    held += 1
                    grew = True
        if not grew:
            break
        if w.size == 0:
            w = np.zeros(6)
            _matvec_add(G, rho, w)
            for r in range(6):
                if not math.isfinite(w[r]):
                    edge[:] = 0.0
                    return False
        # unknowns: both components of a free rotor, the push along the edge of a held one
        m = 6 - held
        A = np.zeros((6, m))
        col = 0
        for j in range(3):
            if edge[j] == 0.0:
                for r in range(6):
                    A[r, col] = G[r, j]
                    A[r, col + 1] = G[r, j + 3]
                col += 2
            else:
                sa, ca = math.sin(edge[j]), math.cos(edge[j])
                for r in range(6):
                    A[r, col] = G[r, j] * sa + G[r, j + 3] * ca
                col += 1
        b = w.copy()
        for r in range(3, 6):
            b[r] *= TORQUE_PRIORITY
            for c in range(m):
                A[r, c] *= TORQUE_PRIORITY
        p = np.linalg.lstsq(A, b)[0]
        col = 0
        for j in range(3):
            if edge[j] == 0.0:
                rho[j], rho[j + 3] = p[col], p[col + 1]
                col += 2
            else:
                push_n = max(p[col], 0.0)
                rho[j], rho[j + 3] = push_n * math.sin(edge[j]), push_n * math.cos(edge[j])
                col += 1
    return held > 0


@njit()
def allocate_within_reach(rho, servo_limit, lo, hi, G, angle):
    """``allocate_within_range`` for servos of finite speed: each rotor's angle within [lo[j], hi[j]],
    the servo range less what its servo cannot turn in one period from its last command (a window
    of less than 180 degrees). While every rotor is within its window nothing changes (returns
    False). Otherwise each rotor's force is a non-negative combination of its window's two edge
    directions (a convex cone), and the six coefficients are the non-negative least squares of the
    accelerations w = G rho, the angular rows weighted ``TORQUE_PRIORITY`` times: the best the
    rotors can give within reach, the attitude first. angle[j] is then the rotor's angle: its
    force's, or for a rotor given no force, the nearest within reach to the one it was asked (to the
    nearer end of the range for one asked beyond it), so that it turns back into play. Inputs that
    are not finite are left as they are."""
    beyond = False
    for j in range(3):
        a = math.atan2(rho[j], rho[j + 3])
        angle[j] = a
        if a < lo[j] or a > hi[j]:
            beyond = True
    if not beyond:
        return False
    w = np.zeros(6)
    _matvec_add(G, rho, w)
    for r in range(6):
        if not math.isfinite(w[r]):
            return False
    A = np.zeros((6, 6))
    for j in range(3):
        for q in range(2):
            t = lo[j] if q == 0 else hi[j]
            sa, ca = math.sin(t), math.cos(t)
            for r in range(6):
                A[r, 2 * j + q] = (G[r, j] * sa + G[r, j + 3] * ca) * (TORQUE_PRIORITY if r >= 3 else 1.0)
    b = w.copy()
    for r in range(3, 6):
        b[r] *= TORQUE_PRIORITY
    x = np.zeros(6)
    _nnls(A, b, x)
    for j in range(3):
        s = x[2 * j] * math.sin(lo[j]) + x[2 * j + 1] * math.sin(hi[j])
        c = x[2 * j] * math.cos(lo[j]) + x[2 * j + 1] * math.cos(hi[j])
        rho[j], rho[j + 3] = s, c
        if x[2 * j] + x[2 * j + 1] > 0.0:
            angle[j] = min(max(math.atan2(s, c), lo[j]), hi[j])
        else:
            a = angle[j]
            toward = a if abs(a) <= servo_limit else math.copysign(servo_limit, a)
            angle[j] = min(max(toward, lo[j]), hi[j])
    return True


@njit()
def actuate(rows, z_pred, z, v_in, Einv, use_dist, half_Phi, half_G, L, M0, I, Ii, G_inv, g, drag, max_pitch,
            kappa, adapt_k, k_lo, k_hi, wind, wind_gain, wind_floor, servo_limit, servo_step, servo_cmd, v_pipe,
            motor_pipe, v_applied, v_out, omega, alpha, omega_now, G, M0_inv):
    """For each agent row in ``rows`` (v_in[k] is row rows[k]'s): cancel the estimated disturbance,
    predict half a period on, RFL (with the drag in the estimated wind, drag = k / m [1/m], 0 in no
    air), adapt and apply the thrust scale kappa, actuator inverse within the servo range, and
    commit the result to the pipes (``push``). Writes v_out (the v committed), omega (the rotor
    speeds computed), alpha and omega_now (the commands to send now), indexed like v_in; updates
    kappa and the wind estimate ``wind`` (N, 3) in place (``update_wind_estimate``, with wind_gain > 0
    and a disturbance estimate; not while a rotor is held at the servo range's edge, where the
    disturbance is the allocation's shortfall, not the wind: no wind-up). z is the observer state: with a disturbance estimate columns 12-14
    are the translational disturbance.

    A rotor whose force (u_j, u_j+3) lies beyond the servo range (|alpha| > servo_limit), or beyond
    where its servo turns in one period (servo_step [rad] from its last command servo_cmd[i, j];
    servo_step 0: at once), leaves the three rotors to keep the angular accelerations asked, giving
    way in force (``allocate_within_range``; ``allocate_within_reach`` for servos of finite speed);
    servo_cmd is updated to the angles commanded. The v committed for such a row is then the one the
    rotors deliver (``input_shortfall_v``: G and M0_inv, M(0)^-1), so the observer and the predictor run on what the drone is really given and
    its disturbance estimate does not take up what the actuators could not deliver (no wind-up)."""
    nz = z_pred.shape[1]
    zm = np.empty(nz)
    u = np.empty(6)
    yd = np.empty(6)
    du = np.empty(6)
    dv = np.empty(6)
    rho = np.empty(6)
    edge = np.zeros(3)
    lo = np.empty(3)  # (a servo's reach this period: servos of finite speed only)
    hi = np.empty(3)
    for k in range(rows.shape[0]):
        i = rows[k]
        v_out[k, :] = v_in[k, :]
        if use_dist:
            _matvec_add(Einv, z_pred[i, 12:18], v_out[k], -1.0)
        zm[:] = 0.0
        _matvec_add(half_Phi, z_pred[i], zm)
        _matvec_add(half_G, v_out[k], zm)
        rfl_xr_row(zm[:12], v_out[k], L, M0, I, Ii, G_inv, g, drag, wind[i], max_pitch, u, yd)
        if adapt_k > 0.0:
            # the specific thrust the law asks before it cancels the disturbance estimate: a regressor
            # with the cancellation in it (a - d) would correlate with d itself, and run kappa down
            # in any air that moves d about
            a0, a1, a2 = yd[3] + z[i, 12], yd[4] + z[i, 13], yd[5] + g + z[i, 14]
            if drag > 0.0:
                dx, dy, dz = drag_share(zm, drag, wind[i])
                a0, a1, a2 = a0 + dx, a1 + dy, a2 + dz
            norm2 = a0 * a0 + a1 * a1 + a2 * a2
            if norm2 > 1.0:  # below ~1 m/s^2 of commanded thrust the ratio says little
                step = adapt_k * (z[i, 12] * a0 + z[i, 13] * a1 + z[i, 14] * a2) / norm2
                kappa[i] = min(max(kappa[i] * (1.0 + step), k_lo), k_hi)
        for q in range(6):
            rho[q] = u[q] / kappa[i]
        if servo_step > 0.0:
            for j in range(3):
                lo[j] = max(servo_cmd[i, j] - servo_step, -servo_limit)
                hi[j] = min(servo_cmd[i, j] + servo_step, servo_limit)
            saturated = allocate_within_reach(rho, servo_limit, lo, hi, G, edge)
            for j in range(3):
                alpha[k, j] = edge[j] if saturated else math.atan2(rho[j], rho[j + 3])
        else:
            saturated = allocate_within_range(rho, servo_limit, G, edge)
            for j in range(3):
                alpha[k, j] = edge[j] if edge[j] != 0.0 else math.atan2(rho[j], rho[j + 3])
        for j in range(3):
            omega[k, j] = math.sqrt(math.hypot(rho[j], rho[j + 3]))
            servo_cmd[i, j] = alpha[k, j]
        if saturated:  # commit the v the rotors deliver: the observer's disturbance must not take up the shortfall
            for q in range(6):
                du[q] = kappa[i] * rho[q] - u[q]
            input_shortfall_v(zm, du, G, M0_inv, max_pitch, dv)
            for q in range(6):
                v_out[k, q] += dv[q]
        if wind_gain > 0.0 and drag > 0.0 and use_dist and not saturated:
            update_wind_estimate(zm, z[i, 12:15], drag, wind_gain, wind_floor, wind[i])
    push(rows, v_out, omega, False, v_pipe, motor_pipe, v_applied, omega_now)


@njit()
def gamma_rows(A_r, B_tilde, h, h_dot, out):
    """(78) for each row: out[i] = B_tilde (h_dot[i] - A_r h[i]). Written out (not BLAS) so that a
    row's result does not depend on how many rows are computed with it."""
    n, nx = h.shape
    e = np.empty(nx)
    for i in range(n):
        for r in range(nx):
            acc = h_dot[i, r]
            for c in range(nx):
                acc -= A_r[r, c] * h[i, c]
            e[r] = acc
        for r in range(B_tilde.shape[0]):
            acc = 0.0
            for c in range(nx):
                acc += B_tilde[r, c] * e[c]
            out[i, r] = acc


@njit()
def protocol_rows(cK, xi, neighbour_sum, in_degree, pinning, x0, gamma, out):
    """(72) for each row: out[i] = c K (sum_j a_ij xi_j - (d_i + g_i) xi_i + g_i x0_i) + gamma_i,
    with ``cK`` = c K. Written out, as ``gamma_rows``."""
    n, nx = xi.shape
    e = np.empty(nx)
    for i in range(n):
        for c in range(nx):
            e[c] = neighbour_sum[i, c] - (in_degree[i] + pinning[i]) * xi[i, c] + pinning[i] * x0[i, c]
        for r in range(cK.shape[0]):
            acc = gamma[i, r]
            for c in range(nx):
                acc += cK[r, c] * e[c]
            out[i, r] = acc
