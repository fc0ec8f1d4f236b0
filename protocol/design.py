"""The design step of Algorithm 1: K (89)-(90), c (91), F (98)-(99), B_tilde/B_bar, gamma (78),
the feasibility test (76) and the stability conditions (77).

Observer sign convention: F here is the Kalman gain of (98), F = P_bar C_r^T R_bar^-1, and the
observer is  xhat_dot = A_r xhat + B_r v + c F (y - C_r xhat).  The paper's (73) writes "- c F y~"
with the opposite sign of F; both describe the same observer, whose error matrix A_r - c F C_r must
be Hurwitz (the paper's (77) "A_r + c F C_r" with its F = -ours).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import scipy.linalg

from . import kernels
from .errors import FormationError, ParameterError
from .graph import Schedule
from .rfl import RFL
from .solutions import kept

ROW_GROUPS = (
    (slice(0, 3), "velocity rows 1-3"),
    (slice(3, 6), "Euler-rate rows 4-6"),
    (slice(6, 9), "attitude rows 7-9"),
    (slice(9, 12), "position rows 10-12"),
)


DEFAULT_R_BAR_ACCEL = (0.1**2,) * 3
"""An accelerometer's noise at the control rate, the airframe's vibration in it, per axis [m^2/s^4]."""
DEFAULT_Q_ACCEL_BIAS = (1e-2,) * 3
"""An accelerometer bias that may wander by 0.1 m/s^2 in a second, per axis [m^2/s^5]: fast enough for the
observer to follow a bias fixed in the body, earth frame, as the drone turns."""


@dataclass(frozen=True)
class DesignWeights:
    """Weights of the two Riccati equations and the coupling-gain margin.

    Q, R: the LQR cost (96) on x_r and v. Q_bar, R_bar: process and measurement noise covariances of
    Remark 2 (97). c = coupling_margin / (2 lambda_R) with lambda_R the smallest real part of an
    eigenvalue of L + G over every topology of the schedule; (91) asks coupling_margin >= 1.

    Q_disturbance (an extension of the paper, zero to switch it off): intensity of a random-walk
    acceleration disturbance on x_r rows 1-6 (three earth-frame translational accelerations
    [m^2/s^5], three Euler-angle accelerations [rad^2/s^5]) that the observer estimates and the
    controller cancels; it absorbs wind and model error (mass, inertia, k_f)."""

    Q: np.ndarray
    R: np.ndarray
    Q_bar: np.ndarray
    R_bar: np.ndarray
    coupling_margin: float = 1.0
    Q_disturbance: np.ndarray = field(default_factory=lambda: np.zeros(6))
    R_bar_rates: np.ndarray = field(default_factory=lambda: np.full(3, 0.01**2))
    """Measurement noise of the Euler rates Psi(eta) omega that a gyro gives [rad^2/s^2], the three
    more outputs of the observer used where body rates are measured."""
    R_bar_accel: np.ndarray = field(default_factory=lambda: np.array(DEFAULT_R_BAR_ACCEL))
    """Measurement noise of the earth-frame acceleration an accelerometer gives (its specific force
    turned to the earth frame, gravity taken out) [m^2/s^4], the three more outputs of the observer
    (with a disturbance estimate) used where the specific force is measured."""
    Q_accel_bias: np.ndarray = field(default_factory=lambda: np.array(DEFAULT_Q_ACCEL_BIAS))
    """Intensity of the random walk of the accelerometer's bias, earth frame [m^2/s^5]: how fast
    the observer lets it wander."""

    def __post_init__(self) -> None:
        qd = np.array(self.Q_disturbance, dtype=float).reshape(-1)
        if qd.shape != (6,) or not np.all(np.isfinite(qd)) or np.any(qd < 0):
            raise ParameterError(f"design weight Q_disturbance must be 6 non-negative numbers, got {self.Q_disturbance!r}")
        if np.any(qd == 0) and np.any(qd > 0):
            raise ParameterError("design weight Q_disturbance must be all positive (disturbance estimation on) or all zero (off)")
        qd.setflags(write=False)
        object.__setattr__(self, "Q_disturbance", qd)
        for name in ("R_bar_rates", "R_bar_accel", "Q_accel_bias"):
            rr = np.array(getattr(self, name), dtype=float).reshape(-1)
            if rr.shape != (3,) or not np.all(np.isfinite(rr)) or np.any(rr <= 0):
                raise ParameterError(f"design weight {name} must be 3 positive numbers, got {getattr(self, name)!r}")
            rr.setflags(write=False)
            object.__setattr__(self, name, rr)
        for name, n in (("Q", 12), ("R", 6), ("Q_bar", 12), ("R_bar", 6)):
            M = np.array(getattr(self, name), dtype=float)
            if M.ndim == 1:
                M = np.diag(M)
            if M.shape != (n, n):
                raise ParameterError(f"design weight {name} must be {n}x{n} or {n} diagonal entries, got shape {M.shape}")
            if not np.all(np.isfinite(M)):
                raise ParameterError(f"design weight {name} must be finite numbers")
            if not np.allclose(M, M.T):
                raise ParameterError(f"design weight {name} must be symmetric")
            if np.linalg.eigvalsh(M).min() <= 0:
                raise ParameterError(f"design weight {name} must be positive definite")
            M.setflags(write=False)
            object.__setattr__(self, name, M)
        if not (np.isfinite(self.coupling_margin) and self.coupling_margin >= 1.0):
            raise ParameterError(f"coupling margin must be a number >= 1 so that (91) holds, got {self.coupling_margin!r}")


@dataclass(frozen=True)
class SampledLoop:
    """The worst block of the formation's feedback sampled at the control rate (``Design.sampled_loop``)."""

    radius: float
    """The largest |z| of its poles: below 1, the loop settles; from 1, it diverges."""
    topology: str
    eigenvalue: complex
    """The eigenvalue of L + G of ``topology`` whose block it is."""
    rate_hz: float

    def problem(self) -> str | None:
        """Why the formation would diverge at this rate (one sentence), or None."""
        if self.radius < 1.0:
            return None
        lam = f"{self.eigenvalue.real:.3g}" if self.eigenvalue.imag == 0 else f"{self.eigenvalue:.3g}"
        return (f"the feedback is too fast for the control rate: sampled at {self.rate_hz:g} Hz ([controller] rate_hz), "
                f"the loop of topology {self.topology} (eigenvalue {lam} of L+G) has a pole at |z| = {self.radius:.3g}, "
                "outside the unit circle, and the formation would diverge; raise rate_hz, or lower [design] Q_diag "
                "or raise R_diag")


@dataclass(frozen=True)
class Design:
    """Everything Algorithm 1 computes once for a swarm."""

    rfl: RFL
    weights: DesignWeights
    K: np.ndarray
    P: np.ndarray
    F: np.ndarray
    P_bar: np.ndarray
    c: float
    lambda_R: float
    eigenvalues: tuple[np.ndarray, ...]
    """Eigenvalues of L + G per topology of the schedule."""
    B_tilde: np.ndarray
    B_bar: np.ndarray
    topology_names: tuple[str, ...] = field(default=())
    F_aug: np.ndarray | None = None
    """Kalman gain (18 x 6) of the observer augmented with the acceleration disturbance, or None."""
    F_measured: tuple[np.ndarray, ...] = ()
    """Kalman gains of the observer the controller runs, one for each set of outputs a tick
    measures (index ``RATES`` | ``ACCEL`` bits), of ``measured_observer_model``: (eta, lambda)
    always; the Euler rates x_r[3:6] where a gyro gives the body rates; the earth-frame acceleration
    where an accelerometer gives the specific force (with a disturbance estimate only: without one,
    the ACCEL gains are those without it). Index 0 is F (or F_aug) itself."""

    @property
    def estimates_disturbance(self) -> bool:
        return self.F_aug is not None

    @cached_property
    def cK(self) -> np.ndarray:
        """c K, the feedback gain of (72) (kept: the protocol uses it every tick)."""
        return np.ascontiguousarray(self.c * self.K)

    def measured_observer_model(self, measured: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(A, B, C, F) of the observer with the outputs ``measured`` (``RATES`` | ``ACCEL``) as well:
        y = (eta, lambda[, eta_dot][, R(eta) f - g e_z - B_r v]). With the acceleration, the model
        is ``observer_model``'s with the accelerometer's bias as three more states (``accel_model``)."""
        taken = self._taken(measured)
        A, B, C, _ = self.observer_model()
        if taken & ACCEL:
            A, B, C = accel_model(A, B, C)
        else:
            C = full_output(A, C)
        return A, B, C[measured_outputs(taken)], self.F_measured[measured]

    def outputs_measured(self, measured: int) -> list[int]:
        """The rows of ``full_output`` the observer takes on a tick that measures ``measured``
        (``RATES`` | ``ACCEL``): without a disturbance estimate the acceleration is not taken."""
        return measured_outputs(self._taken(measured))

    def _taken(self, measured: int) -> int:
        return measured if self.estimates_disturbance else measured & RATES

    def observer_model(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(A, B, C, F) of the observer the controller runs: the paper's (73), or (73) augmented
        with the disturbance state d (x_r rows 1-6 get + d, d_dot = 0)."""
        if self.F_aug is None:
            return self.A_r, self.B_r, self.C_r, self.F
        return (*augmented_model(self.A_r, self.B_r, self.C_r), self.F_aug)

    @property
    def A_r(self) -> np.ndarray:
        return self.rfl.A_r

    @property
    def B_r(self) -> np.ndarray:
        return self.rfl.B_r

    @property
    def C_r(self) -> np.ndarray:
        return self.rfl.C_r

    def closed_loop_matrices(self) -> list[tuple[str, complex, np.ndarray]]:
        """(77): A_r - c lambda_i B_r K for every eigenvalue of every topology."""
        out = []
        for name, lams in zip(self.topology_names, self.eigenvalues):
            for lam in lams:
                out.append((name, lam, self.A_r - self.c * lam * (self.B_r @ self.K)))
        return out

    def observer_matrix(self) -> np.ndarray:
        """(77): observer error matrix A_r - c F C_r (our sign of F)."""
        return self.A_r - self.c * self.F @ self.C_r

    def augmented_observer_matrix(self) -> np.ndarray | None:
        if self.F_aug is None:
            return None
        A, _, C, F = self.observer_model()
        return A - self.c * F @ C

    def stability_margins(self) -> dict:
        """Largest real part of the eigenvalues of each matrix of (77) (all must be < 0)."""
        ctrl = max(np.linalg.eigvals(M).real.max() for _, _, M in self.closed_loop_matrices())
        obs = np.linalg.eigvals(self.observer_matrix()).real.max()
        out = {"controller_max_real_part": float(ctrl), "observer_max_real_part": float(obs)}
        aug = self.augmented_observer_matrix()
        if aug is not None:
            out["augmented_observer_max_real_part"] = float(np.linalg.eigvals(aug).real.max())
        if self.F_measured:
            for measured, name in ((RATES, "rates"), (ACCEL, "accel"), (RATES | ACCEL, "imu")):
                A, _, C, F = self.measured_observer_model(measured)
                out[f"{name}_observer_max_real_part"] = float(np.linalg.eigvals(A - self.c * F @ C).real.max())
        return out

    def sampled_loop(self, rate_hz: float) -> SampledLoop:
        """The feedback of (72) as the controllers run it, once a period at ``rate_hz``: the reference
        model (58) with v held over the period, v_k = -c lambda_i K x_k, for every eigenvalue lambda_i
        of every topology (the diagonal blocks of (88), sampled). Where (77) asks the continuous
        loop's poles to lie left of the imaginary axis, the sampled loop's must lie inside the unit
        circle: a gain fast enough for (77) can be too fast for the rate. Returns the worst block."""
        Phi, Gamma = zoh(self.A_r, self.B_r, 1.0 / rate_hz)
        GK = Gamma @ self.K
        worst = SampledLoop(0.0, "", 0j, rate_hz)
        for name, lams in zip(self.topology_names, self.eigenvalues):
            for lam in np.unique(np.round(np.asarray(lams, dtype=complex), 12)):
                radius = float(np.abs(np.linalg.eigvals(Phi - self.c * lam * GK)).max())
                if radius > worst.radius:
                    worst = SampledLoop(radius, name, complex(lam), rate_hz)
        return worst

    def gamma(self, h: np.ndarray, h_dot: np.ndarray) -> np.ndarray:
        """(78): gamma_i = B_tilde (h_dot_i - A_r h_i), for h, h_dot (..., 12)."""
        h, h_dot = np.broadcast_arrays(np.asarray(h, dtype=float), np.asarray(h_dot, dtype=float))
        flat_h = np.ascontiguousarray(h.reshape(-1, h.shape[-1]))
        out = np.empty((flat_h.shape[0], self.B_tilde.shape[0]))
        kernels.gamma_rows(self.A_r, self.B_tilde, flat_h, np.ascontiguousarray(h_dot.reshape(flat_h.shape)), out)
        return out.reshape(h.shape[:-1] + (self.B_tilde.shape[0],))


def left_inverse_pair(B_r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """B_tilde (pseudo-inverse, B_tilde B_r = I) and B_bar (B_bar B_r = 0, [B_tilde; B_bar] invertible).

    B_r is zero in rows 6-11 (attitude and position are not driven directly), so B_bar selects
    those rows, as in Section 5."""
    B_tilde = np.linalg.pinv(B_r)
    zero_rows = np.flatnonzero(np.all(B_r == 0.0, axis=1))
    B_bar = np.eye(B_r.shape[0])[zero_rows]
    if B_bar.shape[0] != B_r.shape[0] - B_r.shape[1] or np.linalg.matrix_rank(np.vstack([B_tilde, B_bar])) != B_r.shape[0]:
        raise ParameterError("B_r does not have the structure (full column rank, zero rows 7-12) the design expects")
    return B_tilde, B_bar


def augmented_model(A_r: np.ndarray, B_r: np.ndarray, C_r: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """x_r extended with a 6-dim acceleration disturbance d on rows 1-6: (A, B, C), 18 states."""
    E = np.zeros((12, 6))
    E[0:6, :] = np.eye(6)
    A = np.block([[A_r, E], [np.zeros((6, 18))]])
    B = np.vstack([B_r, np.zeros((6, 6))])
    C = np.hstack([C_r, np.zeros((6, 6))])
    return A, B, C


RATES, ACCEL = 1, 2
"""The outputs a tick measures beyond (eta, lambda), as bits: the body rates (a gyro) and the
specific force (an accelerometer)."""


def measured_outputs(measured: int) -> list[int]:
    """The rows of ``full_output`` a tick with the outputs ``measured`` (``RATES`` | ``ACCEL``) has."""
    return list(range(6)) + ([6, 7, 8] if measured & RATES else []) + ([9, 10, 11] if measured & ACCEL else [])


def full_output(A: np.ndarray, C: np.ndarray) -> np.ndarray:
    """The observer's 12 outputs where every sensor gives one: C's (eta, lambda), the Euler rates
    (x_r rows 4-6) and the earth-frame acceleration x_r rows 1-3 change at, less its B_r v: the
    rows 1-3 of A (with a disturbance estimate, they carry it: an accelerometer measures it)."""
    E = np.zeros((3, C.shape[1]))
    E[:, 3:6] = np.eye(3)
    return np.vstack([C, E, A[0:3]])


def accel_model(A: np.ndarray, B: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The model (A, B, C) extended with an accelerometer's bias, earth frame, as three more states
    (a random walk, ``DesignWeights.Q_accel_bias``) that only the acceleration output sees: (A, B,
    full_output) of n + 3 states. The position tells a bias from a disturbance: a disturbance moves
    the drone, a bias does not."""
    n = A.shape[0]
    A_b = scipy.linalg.block_diag(A, np.zeros((3, 3)))
    B_b = np.vstack([B, np.zeros((3, B.shape[1]))])
    C_b = np.hstack([full_output(A, C), np.zeros((12, 3))])
    C_b[9:12, n:] = np.eye(3)
    return A_b, B_b, C_b


def _solved(kind: str, *matrices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``control.lqr(A, B, Q, R)`` (kind "lqr") or ``control.lqe(A, G, C, Q_n, R_n)`` ("lqe"): the
    gain and the Riccati equation's solution, kept by ``solutions.keep_solutions`` under a digest of the
    matrices. Kept or solved, they are the same bits."""
    store = kept()
    mats = [np.ascontiguousarray(m, dtype="<f8") for m in matrices]
    digest = hashlib.sha256(kind.encode())
    for m in mats:
        digest.update(repr(m.shape).encode())
        digest.update(m.tobytes())
    key = f"{kind}-{digest.hexdigest()}"
    n = mats[0].shape[0]
    gain_shape = (mats[1].shape[1], n) if kind == "lqr" else (n, mats[2].shape[0])
    blob = store[0](key) if store is not None else None
    if blob is not None and len(blob) == 32 + 8 * (gain_shape[0] * gain_shape[1] + n * n) \
            and hashlib.sha256(blob[32:]).digest() == blob[:32]:
        values = np.frombuffer(blob, dtype="<f8", offset=32).astype(float)
        split = gain_shape[0] * gain_shape[1]
        return values[:split].reshape(gain_shape), values[split:].reshape(n, n)
    # Imported here: python-control brings scipy.signal and matplotlib.pyplot (about 0.7 s), which a
    # command that never designs (monitor, --help) or finds its equations kept should not wait for.
    import control

    gain, P = (np.asarray(x, dtype=float) for x in (control.lqr if kind == "lqr" else control.lqe)(*mats)[:2])
    if store is not None:
        payload = gain.astype("<f8").tobytes() + P.astype("<f8").tobytes()
        store[1](key, hashlib.sha256(payload).digest() + payload)
    return gain, P


def zoh(A: np.ndarray, B: np.ndarray, T: float) -> tuple[np.ndarray, np.ndarray]:
    """x(T) = Phi x(0) + Gamma u for x' = A x + B u with u held."""
    n, m = B.shape
    M = np.zeros((n + m, n + m))
    M[:n, :n] = A * T
    M[:n, n:] = B * T
    E = scipy.linalg.expm(M)
    return E[:n, :n], E[:n, n:]


def design(rfl: RFL, schedule: Schedule, weights: DesignWeights) -> Design:
    """Algorithm 1's gains for a swarm flying ``schedule``. Refuses a topology without Assumption 1."""
    schedule.check()
    A, B, C = rfl.A_r, rfl.B_r, rfl.C_r
    K, P = _solved("lqr", A, B, weights.Q, weights.R)           # (89)-(90)
    F, P_bar = _solved("lqe", A, np.eye(12), C, weights.Q_bar, weights.R_bar)  # (98)-(99)
    eigs = tuple(t.eigenvalues() for t in schedule.topologies)
    lambda_R = float(min(e.real.min() for e in eigs))
    c = weights.coupling_margin / (2.0 * lambda_R)               # (91) with a margin
    B_tilde, B_bar = left_inverse_pair(B)
    F_aug = None
    if np.all(weights.Q_disturbance > 0):
        Aa, _, Ca = augmented_model(A, B, C)
        Qa = np.zeros((18, 18))
        Qa[:12, :12] = weights.Q_bar
        Qa[12:, 12:] = np.diag(weights.Q_disturbance)
        F_aug = _solved("lqe", Aa, np.eye(18), Ca, Qa, weights.R_bar)[0]
        A_o, C_o, Q_o = Aa, Ca, Qa
    else:
        A_o, C_o, Q_o = A, C, weights.Q_bar
    R_full = scipy.linalg.block_diag(weights.R_bar, np.diag(weights.R_bar_rates), np.diag(weights.R_bar_accel))
    F_measured = [F if F_aug is None else F_aug]
    for measured in (RATES, ACCEL, RATES | ACCEL):
        if F_aug is None and measured & ACCEL:
            F_measured.append(F_measured[measured & RATES])
            continue
        idx = measured_outputs(measured)
        if measured & ACCEL:
            A_m, _, C_m = accel_model(A_o, np.zeros((A_o.shape[0], 0)), C_o)
            Q_m = scipy.linalg.block_diag(Q_o, np.diag(weights.Q_accel_bias))
        else:
            A_m, C_m, Q_m = A_o, full_output(A_o, C_o), Q_o
        F_measured.append(_solved("lqe", A_m, np.eye(A_m.shape[0]), C_m[idx], Q_m, R_full[np.ix_(idx, idx)])[0])
    d = Design(rfl, weights, np.asarray(K), np.asarray(P), np.asarray(F), np.asarray(P_bar), c, lambda_R, eigs,
               B_tilde, B_bar, tuple(t.name for t in schedule.topologies), F_aug, tuple(F_measured))
    margins = d.stability_margins()
    if any(value >= 0 for value in margins.values()):
        raise ParameterError(f"design is not stable (77): {margins}")
    return d


def feasibility_residual(A_r: np.ndarray, B_bar: np.ndarray, h: np.ndarray, h_dot: np.ndarray) -> np.ndarray:
    """(76): B_bar (A_r h_i - h_dot_i) for h, h_dot (..., 12); zero for a feasible formation."""
    return (h @ A_r.T - h_dot) @ B_bar.T


def check_feasibility(A_r: np.ndarray, B_bar: np.ndarray, formation, times_s, tol: float = 1e-6,
                      source: str = "formation") -> None:
    """Evaluate (76) at the given times; raise FormationError naming the agents and rows that fail."""
    selected = np.flatnonzero(np.any(B_bar != 0, axis=0))  # x_r rows B_bar looks at
    worst: dict[tuple[int, str], tuple[float, float]] = {}
    for t in np.atleast_1d(times_s):
        h, h_dot = formation.offsets(float(t))
        if not (np.all(np.isfinite(h)) and np.all(np.isfinite(h_dot))):
            raise FormationError(f"{source}: offsets are not finite numbers at t = {t:g} s")
        full = h @ A_r.T - h_dot  # (N, 12); B_bar picks rows `selected`
        for rows, label in ROW_GROUPS:
            idx = [r for r in range(rows.start, rows.stop) if r in selected]
            if not idx:
                continue
            err = np.abs(full[:, idx]).max(axis=1)
            for i in np.flatnonzero(err > tol):
                key = (int(i), label)
                if key not in worst or err[i] > worst[key][0]:
                    worst[key] = (float(err[i]), float(t))
    if worst:
        parts = []
        for (i, label), (err, t) in sorted(worst.items()):
            derivative_of = {"attitude rows 7-9": "Euler-rate rows 4-6", "position rows 10-12": "velocity rows 1-3"}
            parts.append(f"drone {i + 1} {label} do not change at the rate its {derivative_of.get(label, 'rows')} "
                         f"give (residual {err:.3g} at t = {t:g} s)")
        raise FormationError(f"{source} fails the feasibility condition (76): " + "; ".join(parts))
