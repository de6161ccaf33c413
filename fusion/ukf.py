"""Hybrid KF/UKF (the hybrid KF-UKF paper): the linear KF while GPS is good, the unscented transform through
the nonlinear SINS error model during an outage, the linear measurement update when GPS returns.

:class:`HybridKfUkf` is :class:`fusion.kf.KalmanFilter` (same state, same update, same closed loop) whose
``propagate`` switches, once told of an outage (:meth:`HybridKfUkf.start_outage`, called by the engine at
the first unusable GPS epoch), from Phi P Phi^T + Q to the unscented transform (eqs. 24-27): 2n+1 sigma
points of (x, P), each integrated over the filter cycle by RK4 through the nonlinear error model
(eqs. 9-11) with the navigation solution at the start, middle and end of the cycle (the paper's
"SINS information at t = k+s-1, k+s-0.5 and k+s"), then the weighted mean and covariance plus the cycle's
discrete Q (additive noise, linearised at x = 0 as in the KF). The first GPS update after the outage is
the KF's (eqs. 17-19) and switches the filter back to the linear prediction.

Shared with the cubature filters of ``fusion.sckf``: :class:`CycleFilter` (the queue of navigation nodes the
engine fills before each ``propagate``) and :func:`propagate_points` (the points x + S xi_j of a rule through
the nonlinear model by RK4).

Nonlinear model in this project's frames (module ``fusion.errmodel`` for the state): navigation frame ENU
instead of the paper's NED, so delta-h' = +dv_U (the paper's -dv_D); the attitude states are the paper's
Euler error angles psi about the E, N, U axes, C_n^n' = C_X(psi_x) C_Y(psi_y) C_Z(psi_z), which is
I - [psi x] to first order, the same as the KF's phi (C_bn computed = (I - [phi x]) C_bn true); so the
KF's state is the UT's to first order and the closed-loop feedback is shared. Position is integrated
in eq. 11's form (delta-lambda, delta-L, delta-h), converted from and to the state's ENU metres at the
cycle's start and end; gyro and accelerometer bias errors are constant over a cycle (random walks: in Q).

Slips of the paper, fixed here:

- eq. 3 writes C_n^n' = C_z C_y C_x, but the matrix it prints (and the rate relation eq. 7/8) is
  C_X C_Y C_Z, the z-then-y-then-x rotation sequence; we use the printed matrix. Its first line,
  "C_n^n' = C_n^n' C_b^n", means C_b^n' = C_n^n' C_b^n.
- eqs. 21 and 25 propagate sigma points i = 1..2n; the sums of eqs. 22, 26, 27 run over i = 0..2n, so the
  centre point is propagated too.
- eq. 23 gives W_i = lambda / (2 (n + lambda)) for i >= 1; the unscented weights are 1 / (2 (n + lambda))
  (with the paper's value the weights do not sum to one).
- eqs. 22 and 27 name Q_{k-1} in their text but leave it out of P; it is added (without it the outage
  covariance ignores the sensor noise and bias walk).
- eq. 11: the NED height rate -dv_D becomes +dv_U in ENU (not a slip, a frame change).

Parameters: beta = 2 and kappa = 3 - n as in the paper; alpha is left by the paper in [1e-4, 1]; we take
alpha = 1 (n + lambda = 3: the points at sqrt(3) sigma, the Gaussian-kurtosis choice). With kappa = 3 - n
a smaller alpha makes the centre weight -(n - 3 alpha^2) / (3 alpha^2), about -5e6 at alpha = 1e-3, and the
covariance loses its positive definiteness to rounding.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fieldlog.fusion import earth
from fieldlog.fusion.errmodel import BA, BG, N_STATES, VEL
from fieldlog.fusion.ins import NavState
from fieldlog.fusion.kf import KalmanFilter


@dataclass
class Cycles:
    """Navigation solution at the RK4 nodes of m filter cycles (node 0 start, 1 middle, 2 end).

    lat (m, 3) rad, h (m, 3) m, v_n (m, 3, 3) ENU m/s, C_bn (m, 3, 3, 3) body RFU -> ENU, f_b (m, 3) mean
    bias-corrected specific force over the cycle, body RFU, m/s^2; dt (m,) s.
    """

    lat: np.ndarray
    h: np.ndarray
    v_n: np.ndarray
    C_bn: np.ndarray
    f_b: np.ndarray
    dt: np.ndarray

    def __len__(self) -> int:
        return len(self.dt)

    def __getitem__(self, s: slice) -> Cycles:
        return Cycles(self.lat[s], self.h[s], self.v_n[s], self.C_bn[s], self.f_b[s], self.dt[s])


def cycles_from_ins(lat: np.ndarray, h: np.ndarray, v_n: np.ndarray, q: np.ndarray, starts: np.ndarray,
                    mid: np.ndarray, ends: np.ndarray, f_b: np.ndarray, dt: np.ndarray) -> Cycles:
    """Cycles from an INS solution (per sample: lat, h, v_n (n, 3), q (n, 4) of C_bn) and the sample indices
    of each cycle's start, middle and end; f_b (m, 3) the cycles' mean specific force, dt (m,) their lengths.

    Parameters
    ----------
    lat : (n,) ndarray, INS latitude per sample, rad
    h : (n,) ndarray, INS ellipsoidal height per sample, m
    v_n : (n, 3) ndarray, INS velocity per sample, ENU, m/s
    q : (n, 4) ndarray, INS ``[x, y, z, w]`` quaternion of ``C_bn`` per sample
    starts, mid, ends : (m,) int ndarray, sample index of each cycle's start, middle and end
    f_b : (m, 3) array_like, mean bias-corrected specific force per cycle, body RFU, m/s^2
    dt : (m,) array_like, cycle lengths, s

    Returns
    -------
    Cycles
        The m cycles.
    """
    idx = np.stack([starts, mid, ends], axis=1)
    return Cycles(lat[idx], h[idx], v_n[idx], earth.quat_to_dcm(q[idx]), np.asarray(f_b, float), np.asarray(dt, float))


def cycle_at(nav: NavState, f_b: np.ndarray, dt: float) -> Cycles:
    """One cycle with the navigation state held constant over it (the ``predict`` interface).

    Parameters
    ----------
    nav : NavState, the INS state used at all three nodes
    f_b : (3,) array_like, mean bias-corrected specific force over the cycle, body RFU, m/s^2
    dt : float, cycle length, s

    Returns
    -------
    Cycles
        One cycle.
    """
    C = nav.C_bn
    return Cycles(np.full((1, 3), nav.lat), np.full((1, 3), nav.h), np.tile(nav.v_n, (1, 3, 1)),
                  np.tile(C, (1, 3, 1, 1)), np.asarray(f_b, float)[None], np.array([dt], float))


def euler_error_dcm(psi: np.ndarray) -> np.ndarray:
    """C_n^n' (..., 3, 3) of the Euler error angles psi (..., 3) (paper eq. 3, the printed matrix).

    Parameters
    ----------
    psi : (..., 3) ndarray, Euler error angles about E, N, U, rad

    Returns
    -------
    (..., 3, 3) ndarray
        C_n^n', ENU -> the computed (erroneous) navigation frame.
    """
    sx, sy, sz = np.sin(psi[..., 0]), np.sin(psi[..., 1]), np.sin(psi[..., 2])
    cx, cy, cz = np.cos(psi[..., 0]), np.cos(psi[..., 1]), np.cos(psi[..., 2])
    return np.stack([
        np.stack([cy * cz, cy * sz, -sy], axis=-1),
        np.stack([-cx * sz + sx * sy * cz, cx * cz + sx * sy * sz, sx * cy], axis=-1),
        np.stack([sx * sz + cx * sy * cz, -sx * cz + cx * sy * sz, cx * cy], axis=-1)], axis=-2)


def _euler_rates(psi: np.ndarray, w: np.ndarray) -> np.ndarray:
    """psi' = C_psi^-1 w (eq. 8), w = omega_nn'^n' (..., 3)."""
    sx, cx = np.sin(psi[..., 0]), np.cos(psi[..., 0])
    sy, cy = np.sin(psi[..., 1]), np.cos(psi[..., 1])
    a = sx * w[..., 1] + cx * w[..., 2]
    return np.stack([w[..., 0] + sy / cy * a, cx * w[..., 1] - sx * w[..., 2], a / cy], axis=-1)


def _mv(M: np.ndarray, x: np.ndarray) -> np.ndarray:
    return np.einsum("...ij,...j->...i", M, x)


def error_rates(y: np.ndarray, lat: float, h: float, v_n: np.ndarray, C_bn: np.ndarray, f_b: np.ndarray
                ) -> np.ndarray:
    """Nonlinear SINS error model (paper eqs. 9-11, ENU), noise-free: y' for y (..., 15).

    y = [d-lambda (rad), d-L (rad), dh (m), dv_n (m/s), psi (rad), gyro bias err (rad/s), accel bias err
    (m/s^2)], errors = computed - true; (lat, h, v_n, C_bn) the computed navigation state, f_b the
    specific force (body RFU).

    Parameters
    ----------
    y : (..., 15) ndarray, error state in the angle form above
    lat : float, computed latitude, rad
    h : float, computed ellipsoidal height, m
    v_n : (3,) ndarray, computed velocity, ENU, m/s
    C_bn : (3, 3) ndarray, computed attitude, body RFU -> ENU
    f_b : (3,) ndarray, specific force, body RFU, m/s^2

    Returns
    -------
    (..., 15) ndarray
        y', same order: rad/s, rad/s, m/s, m/s^2, rad/s, and zero for the bias errors.
    """
    dL, dh = y[..., 1], y[..., 2]  # no rate depends on the longitude error
    dv, psi = y[..., VEL], y[..., 6:9]
    lat_t, h_t, v_t = lat - dL, h - dh, v_n - dv
    w_ie, w_en = earth.omega_ie_n(lat), earth.omega_en_n(lat, h, v_n)
    d_ie = w_ie - earth.omega_ie_n(lat_t)
    d_en = w_en - earth.omega_en_n(lat_t, h_t, v_t)
    Cnn = euler_error_dcm(psi)  # C_n^n'
    Cn_n = np.swapaxes(Cnn, -1, -2)  # C_n'^n
    w_nn = (w_ie + w_en) - _mv(Cnn, w_ie + w_en) + _mv(Cnn, d_ie + d_en) - _mv(C_bn, y[..., BG])
    f_n = C_bn @ f_b
    d2 = 2.0 * d_ie + d_en
    dg_up = earth.gravity(lat_t, h_t) - earth.gravity(lat, h)  # computed minus true of the -g up component
    dv_dot = (f_n - _mv(Cn_n, f_n) - earth.cross(2.0 * w_ie + w_en, dv) - earth.cross(d2, v_n) + earth.cross(d2, dv)
              + _mv(Cn_n, _mv(C_bn, y[..., BA])))
    dv_dot[..., 2] += dg_up
    rm, rn = earth.principal_radii(lat, h)  # R + h
    rm_t, rn_t = earth.principal_radii(lat_t, h_t)
    dL_dot = v_n[1] / rm - v_t[..., 1] / rm_t
    dlam_dot = v_n[0] / (np.cos(lat) * rn) - v_t[..., 0] / (np.cos(lat_t) * rn_t)
    out = np.zeros_like(y)
    out[..., 0], out[..., 1], out[..., 2] = dlam_dot, dL_dot, dv[..., 2]
    out[..., VEL] = dv_dot
    out[..., 6:9] = _euler_rates(psi, w_nn)
    return out


def _to_angles(x: np.ndarray, lat: float, h: float) -> np.ndarray:
    rm, rn = earth.principal_radii(lat, h)
    y = x.copy()
    y[..., 0], y[..., 1] = x[..., 0] / (rn * np.cos(lat)), x[..., 1] / rm
    return y


def _to_metres(y: np.ndarray, lat: float, h: float) -> np.ndarray:
    rm, rn = earth.principal_radii(lat, h)
    x = y.copy()
    x[..., 0], x[..., 1] = y[..., 0] * rn * np.cos(lat), y[..., 1] * rm
    return x


def propagate_samples(x: np.ndarray, c: Cycles) -> np.ndarray:
    """Integrate error states x (..., 15) (``fusion.errmodel`` order, ENU m) through the nonlinear model over
    the cycles c in turn, RK4 with the start, middle and end nodes of each cycle; noise-free.

    Parameters
    ----------
    x : (..., 15) ndarray, error states, ``fusion.errmodel`` order and units
    c : Cycles, navigation nodes of the filter cycles, in order

    Returns
    -------
    (..., 15) ndarray
        The states at the end of the last cycle, same order and units.
    """
    for i in range(len(c)):
        node = [(c.lat[i, j], c.h[i, j], c.v_n[i, j], c.C_bn[i, j], c.f_b[i]) for j in range(3)]
        dt = c.dt[i]
        y = _to_angles(x, c.lat[i, 0], c.h[i, 0])
        k1 = error_rates(y, *node[0])
        k2 = error_rates(y + 0.5 * dt * k1, *node[1])
        k3 = error_rates(y + 0.5 * dt * k2, *node[1])
        k4 = error_rates(y + dt * k3, *node[2])
        x = _to_metres(y + dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4), c.lat[i, 2], c.h[i, 2])
    return x


def unscented_weights(n: int, alpha: float, beta: float, kappa: float) -> tuple[float, np.ndarray, np.ndarray]:
    """(n + lambda, W^(m) (2n+1,), W^(c) (2n+1,)), eq. 23 with the i >= 1 weights 1 / (2 (n + lambda)).

    Parameters
    ----------
    n : int, state dimension
    alpha : float, spread of the points (0, 1]
    beta : float, prior-distribution term (2 for a Gaussian)
    kappa : float, secondary scaling

    Returns
    -------
    scale : float, n + lambda
    wm : (2n+1,) ndarray, mean weights (sum to one)
    wc : (2n+1,) ndarray, covariance weights
    """
    lam = alpha ** 2 * (n + kappa) - n
    wm = np.full(2 * n + 1, 0.5 / (n + lam))
    wc = wm.copy()
    wm[0] = lam / (n + lam)
    wc[0] = wm[0] + 1.0 - alpha ** 2 + beta
    return n + lam, wm, wc


def unscented_points(n: int, scale: float) -> np.ndarray:
    """Eq. 24's unit points (2n+1, n): 0, +sqrt(scale) e_i, -sqrt(scale) e_i (sigma point i = x + S xi_i).

    Parameters
    ----------
    n : int, state dimension
    scale : float, n + lambda (> 0)

    Returns
    -------
    (2n+1, n) ndarray
        The unit points xi_i, centre first.
    """
    e = np.sqrt(scale) * np.eye(n)
    return np.concatenate([np.zeros((1, n)), e, -e])


def propagate_points(x: np.ndarray, S: np.ndarray, xi: np.ndarray, c: Cycles) -> np.ndarray:
    """The points x + S xi_j of a sampling rule (unit points xi (m, n), S (n, n) a square root of P, S S^T = P)
    integrated through the nonlinear error model over the cycles c (:func:`propagate_samples`): (m, n).
    The one point propagation of the unscented (here) and cubature (``fusion.sckf``) filters.

    Parameters
    ----------
    x : (n,) ndarray, error-state mean, ``fusion.errmodel`` order and units
    S : (n, n) ndarray, a square root of the covariance, S S^T = P
    xi : (m, n) ndarray, unit points of the rule
    c : Cycles, navigation nodes of the filter cycles, in order

    Returns
    -------
    (m, n) ndarray
        The propagated points, same order and units.
    """
    return propagate_samples(x + xi @ S.T, c)


class CycleFilter(KalmanFilter):
    """A :class:`fusion.kf.KalmanFilter` whose prediction needs the navigation solution at the RK4 nodes of each
    cycle: the engine queues them (:meth:`queue`) before each ``propagate``, which takes them (:meth:`take`)."""

    wants_nodes = True
    keeps_predicted = False

    def __init__(self, P0: np.ndarray, q: np.ndarray, q_scale: float = 1.0) -> None:
        super().__init__(P0, q, q_scale)
        self._queue: list[Cycles] = []

    def queue(self, cycles: Cycles) -> None:
        """Navigation nodes of the cycles the next ``propagate`` calls cover, in order.

        Parameters
        ----------
        cycles : Cycles, the nodes of the next cycles to be propagated
        """
        self._queue.append(cycles)

    def take(self, m: int) -> Cycles:
        """The nodes of the next m cycles, removed from the queue.

        Parameters
        ----------
        m : int, number of cycles

        Returns
        -------
        Cycles
            Their nodes.

        Raises
        ------
        RuntimeError
            When fewer than m cycles are queued.
        """
        parts, need = [], m
        while need:
            if not self._queue:
                raise RuntimeError(f"{type(self).__name__}.propagate: no navigation nodes queued for the cycles")
            c = self._queue[0]
            parts.append(c[:need])
            self._queue[0] = c[need:]
            need -= len(parts[-1])
            if not len(self._queue[0]):
                self._queue.pop(0)
        return Cycles(*(np.concatenate([getattr(p, k) for p in parts]) for k in
                        ("lat", "h", "v_n", "C_bn", "f_b", "dt")))

    def predict(self, dt: float, ins_state: NavState, imu: tuple[np.ndarray, np.ndarray]) -> None:
        """As :meth:`fusion.kf.KalmanFilter.predict`; the nonlinear model with the navigation state held.

        Parameters
        ----------
        dt, ins_state, imu : as :meth:`fusion.kf.KalmanFilter.predict`
        """
        self.queue(cycle_at(ins_state, imu[1], dt))
        super().predict(dt, ins_state, imu)


class HybridKfUkf(CycleFilter):
    """Hybrid KF/UKF. P0, q, q_scale as :class:`fusion.kf.KalmanFilter`; alpha, beta, kappa of the unscented
    transform (kappa None: 3 - n)."""

    def __init__(self, P0: np.ndarray, q: np.ndarray, q_scale: float = 1.0, alpha: float = 1.0, beta: float = 2.0,
                 kappa: float | None = None) -> None:
        super().__init__(P0, q, q_scale)
        scale, self.wm, self.wc = unscented_weights(N_STATES, alpha, beta, 3.0 - N_STATES if kappa is None
                                                    else kappa)
        self.xi = unscented_points(N_STATES, scale)
        self.outage = False

    def start_outage(self) -> None:
        """GPS lost: propagate with the unscented transform until the next update."""
        self.outage = True

    def propagate(self, Phi: np.ndarray, Q: np.ndarray) -> np.ndarray:
        """Phi P Phi^T + Q with GPS; in an outage the unscented transform of the queued cycles (Phi unused).

        Parameters
        ----------
        Phi, Q : (m, 15, 15) ndarray, as :meth:`fusion.kf.KalmanFilter.propagate`

        Returns
        -------
        (m, 15) ndarray, diag(P) after each cycle (of the unscented transform in an outage).
        """
        cycles = self.take(len(Phi))
        if not self.outage:
            return super().propagate(Phi, Q)
        out = np.empty((len(Phi), N_STATES))
        for i in range(len(Phi)):
            X = propagate_points(self.x, np.linalg.cholesky(self.P), self.xi, cycles[i:i + 1])
            x = self.wm @ X
            d = X - x
            P = (self.wc[:, None] * d).T @ d + self.q_scale * Q[i]
            self.x, self.P = x, 0.5 * (P + P.T)
            out[i] = np.diag(self.P)
        return out

    def update(self, z: np.ndarray, H: np.ndarray, R: np.ndarray) -> np.ndarray:
        """Linear KF update (eqs. 17-19); ends the outage.

        Parameters
        ----------
        z, H, R : as :meth:`fusion.kf.KalmanFilter.update` (z (m,), H (m, 15), R (m, m))

        Returns
        -------
        (15,) ndarray, K (z - H x), as the Kalman filter's.
        """
        self.outage = False
        return super().update(z, H, R)
