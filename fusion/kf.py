"""The shared error-state Kalman filter and the closed-loop INS correction (the measurement models are
``fusion.measurements``').

Every filter of the project exposes the interface of design section 6: ``predict(dt, ins_state, imu)``,
``update(z, H, R)``, ``state``, ``covariance``, and the loop's ``update_batch(observations)`` (the measurements of
one update, each an :class:`Observation` with its kind, which the filter routes); :class:`KalmanFilter` is the
15-state one (``fusion.errmodel`` for the state order and the model). Closed loop: after each GPS epoch the estimate
is fed back into the INS (:func:`correct_ins`) and the biases, and the error state is reset to zero.

Both the centralised ``kf`` (one filter, z = [dv; dp]) and the two local filters of ``dkf``
(``fusion.dkf``) are this class; they differ only in the measurements they are given.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fieldlog.fusion import earth, errmodel, kernels
from fieldlog.fusion.errmodel import ATT, N_STATES, VEL
from fieldlog.fusion.ins import NavState

Measurement = tuple[np.ndarray, np.ndarray, np.ndarray]  # (z (m,), H (m, 15), R (m, m))
MAX_ROWS = 32  # rows of one update the compiled update takes (fusion/_cycles.c MAXM)


@dataclass(frozen=True)
class Observation:
    """A measurement's matrices m = (z, H, R) with what the filters route on: kind "velocity" or "position"
    (``fusion.measurements``); receiver: R is the GPS receiver's own figure."""

    kind: str
    m: Measurement
    receiver: bool = False


def gps_observations(vel: Measurement | None, pos: Measurement | None) -> list[Observation]:
    """The GPS velocity and position measurements given as observations, in that order.

    Parameters
    ----------
    vel, pos : Measurement or None
        (z, H, R) of the GPS velocity and position; None: left out.

    Returns
    -------
    list of Observation
        Of kind "velocity" and "position", R the receiver's own.
    """
    return [Observation(k, m, True) for k, m in (("velocity", vel), ("position", pos)) if m is not None]


class BatchUpdates:
    """What :class:`KalmanFilter` and ``fusion.dkf.DistributedKF`` share: one cycle's prediction through the
    ``propagate`` and noise PSD ``q`` the filter defines, the GPS and vehicle-aid updates through its
    ``update_batch``, and the outage notice (nothing to do)."""

    def predict(self, dt: float, ins_state: NavState, imu: tuple[np.ndarray, np.ndarray]) -> None:
        """Propagate over one filter cycle (``propagate`` of its Phi and Q, the noise PSD ``q``).

        Parameters
        ----------
        dt : float
            Cycle length, s.
        ins_state : NavState
            The INS state in the middle of the cycle.
        imu : tuple of ndarray (3,)
            (omega_ib_b rad/s, f_b m/s^2): the mean bias-corrected rate and specific force over the cycle, body RFU.
        """
        self.propagate(*cycle_matrices(dt, ins_state, imu, self.q))

    def update_gps(self, vel: Measurement | None, pos: Measurement | None) -> None:
        """Update with the available GPS measurements (:meth:`update_batch`, velocity then position).

        Parameters
        ----------
        vel, pos : Measurement or None
            The GPS velocity and position measurements (z, H, R); None: left out.
        """
        self.update_batch(gps_observations(vel, pos))

    def update_aid(self, m: Measurement) -> None:
        """A vehicle-motion aid (``fusion.measurements``), a velocity-kind observation.

        Parameters
        ----------
        m : Measurement
            (z (k,), H (k, 15), R (k, k)).
        """
        self.update_batch([Observation("velocity", m)])

    def start_outage(self) -> None:
        """Told at each unusable GPS epoch; nothing to do for a linear filter (``fusion.ukf.HybridKfUkf`` acts
        on it)."""


class KalmanFilter(BatchUpdates):
    """Linear KF on the 15-state INS error (``fusion.errmodel``).

    P0 (15, 15) initial covariance; q (12, 12) noise PSD (``errmodel.noise_psd``); q_scale multiplies
    the discrete Q (the information-sharing factor 1/beta of a federated local filter; 1 otherwise).

    What a filter needs from the loop, and what it carries, it declares (class attributes, all False here):
    ``wants_nodes``: the navigation solution at each cycle's RK4 nodes (``queue``, ``fusion.ukf.CycleFilter``);
    ``wants_cycle_lengths``: the cycle lengths before each ``propagate`` (``cycles``, ``fusion.gpserror``);
    ``models_gps_error``: the correlated GPS error is in its states (nothing is added to its sigmas);
    ``has_locals``: local filters whose solutions are written too (``locals``, ``local_states``,
    ``local_diag``, ``fusion.dkf``); ``feeds_prediction``: its state prediction between epochs is an estimate,
    fed back at every epoch without a fix (the distributed filter's fused X(n|n-1)); ``keeps_predicted`` (True
    here): each ``propagate`` leaves ``covariance`` after each of its cycles in ``predicted`` (m, 15, 15), so a
    smoother's record of every cycle needs no call per cycle.
    """

    wants_nodes = False
    wants_cycle_lengths = False
    models_gps_error = False
    has_locals = False
    feeds_prediction = False
    keeps_predicted = True

    def __init__(self, P0: np.ndarray, q: np.ndarray, q_scale: float = 1.0) -> None:
        self.x = np.zeros(N_STATES)
        self.P = np.array(P0, dtype=float)
        self.q = np.asarray(q, dtype=float)
        self.q_scale = float(q_scale)

    @property
    def state(self) -> np.ndarray:
        """Error-state estimate (15,), ``fusion.errmodel`` order and units."""
        return self.x

    @property
    def covariance(self) -> np.ndarray:
        """Error covariance (15, 15)."""
        return self.P

    def propagate(self, Phi: np.ndarray, Q: np.ndarray) -> np.ndarray:
        """Apply a sequence of discrete cycles (the covariance compiled, ``errmodel.propagate_covariance``).

        Parameters
        ----------
        Phi, Q : ndarray (m, 15, 15)
            The cycles' transition matrices and process noise (``fusion.errmodel`` order and units).

        Returns
        -------
        ndarray (m, 15)
            diag(P) after each cycle (P itself after each: ``predicted``).
        """
        self.x = propagate_state(Phi, self.x)[-1] if len(Phi) else self.x
        self.predicted = hist = errmodel.propagate_covariance(Phi, Q, self.P, self.q_scale)
        if len(hist):
            self.P = hist[-1].copy()
        return np.diagonal(hist, axis1=1, axis2=2).copy()

    def update(self, z: np.ndarray, H: np.ndarray, R: np.ndarray) -> np.ndarray:
        """Measurement update (Joseph form, :func:`joseph_update`); the gain K (15, m) is kept in ``gain``.

        Parameters
        ----------
        z : ndarray (m,)
            Measurement (the observation's units, ``fusion.measurements``).
        H : ndarray (m, 15)
            Its sensitivity to the error state (``fusion.errmodel`` order).
        R : ndarray (m, m)
            Its noise covariance.

        Returns
        -------
        ndarray (15,)
            The innovation component of the estimate, K (z - H x) (the distributed-KF paper's Delta X, eq. 7).
        """
        self.x, self.P, self.gain, dx, _ = joseph_update(self.x, self.P, z, H, R)
        return dx

    def update_batch(self, obs: list[Observation]) -> None:
        """One update with the observations' matrices stacked in their order (the centralised filter: one z).

        Parameters
        ----------
        obs : list of Observation
            One epoch's observations; none: no update.
        """
        m = stack(*(o.m for o in obs))
        if m is not None:
            self.update(*m)

    def reset(self) -> None:
        """Closed-loop reset after the estimate has been fed back: x = 0 (P unchanged)."""
        self.x = np.zeros(N_STATES)


def joseph_update(x: np.ndarray, P: np.ndarray, z: np.ndarray, H: np.ndarray, R: np.ndarray,
                  P12: np.ndarray | None = None, side: int = 0
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """One Kalman update in Joseph form, compiled (fusion/_cycles.c); new arrays, the given ones left alone.

    K = P H^T (H P H^T + R)^-1, dx = K (z - H x), x + dx, and sym((I - K H) P (I - K H)^T + K R K^T).

    Parameters
    ----------
    x : ndarray (n,)
        Error state (``fusion.errmodel`` order and units; n = 15 compiled, an augmented state in numpy).
    P : ndarray (n, n)
        Its covariance.
    z, H, R : ndarray (m,), (m, n), (m, m)
        The measurement, its sensitivity to the error state and its noise covariance (at most 32 rows).
    P12 : ndarray (15, 15), optional
        A cross-covariance of this filter's error with another's (``fusion.dkf``): A P12 (side 0, this filter's
        error first) or P12 A^T (side 1) after the update, A = I - K H.
    side : int
        0 or 1 (P12).

    Returns
    -------
    x, P, K, dx, P12 : ndarray
        The updated state (n,) and covariance (n, n), the gain K (n, m), the change K (z - H x) (n,), and the
        updated P12 (None when not given).

    Raises
    ------
    numpy.linalg.LinAlgError
        When H P H^T + R is singular.
    """
    z, H, R = (np.ascontiguousarray(a, dtype=float) for a in (z, H, R))
    m, n = len(z), len(x)
    if H.shape != (m, n) or R.shape != (m, m) or m > MAX_ROWS or (n != N_STATES and P12 is not None):
        raise ValueError(f"an update needs z (m,), H (m, {n}), R (m, m) with m <= {MAX_ROWS}: "
                         f"{z.shape}, {H.shape}, {R.shape}")
    if n != N_STATES:  # an augmented state (fusion.gpserror's GPS error states): the same formulas in numpy
        K = np.linalg.solve(H @ P @ H.T + R, H @ P).T
        dx = K @ (z - H @ x)
        A = np.eye(n) - K @ H
        P = A @ P @ A.T + K @ R @ K.T
        return x + dx, 0.5 * (P + P.T), K, dx, None
    x, P = np.array(x, dtype=float), np.array(P, dtype=float, order="C")
    K, dx = np.empty((N_STATES, m)), np.empty(N_STATES)
    P12 = None if P12 is None else np.array(P12, dtype=float, order="C")
    if errmodel.cycle_kernel().fieldlog_kf_update(m, *map(kernels.address, (z, H, R, x, P, K, dx)),
                                                  None if P12 is None else kernels.address(P12), side):
        raise np.linalg.LinAlgError("Singular matrix: the innovation covariance H P H^T + R")
    return x, P, K, dx, P12


def nis(x: np.ndarray, P: np.ndarray, m: Measurement) -> float:
    """The normalised innovation squared of an update, y^T (H P H^T + R)^-1 y / k with y = z - H x: compiled for 15
    states and at most 32 rows (fusion/_cycles.c), numpy otherwise.

    Parameters
    ----------
    x : ndarray (n,)
        Error state before the update (``fusion.errmodel`` order and units).
    P : ndarray (n, n)
        Its covariance.
    m : Measurement
        (z (k,), H (k, n), R (k, k)), k >= 1.

    Returns
    -------
    float
        The NIS; inf when H P H^T + R is singular (the covariance has collapsed or blown up).
    """
    z, H, R = (np.ascontiguousarray(a, dtype=float) for a in m)
    if len(x) != N_STATES or len(z) > MAX_ROWS:
        y = z - H @ x
        try:
            return float(y @ np.linalg.solve(H @ P @ H.T + R, y)) / len(z)
        except np.linalg.LinAlgError:
            return math.inf
    out = np.empty(1)
    x, P = np.ascontiguousarray(x, dtype=float), np.ascontiguousarray(P, dtype=float)
    if errmodel.cycle_kernel().fieldlog_nis(len(z), *map(kernels.address, (z, H, R, x, P, out))):
        return math.inf
    return float(out[0])


def propagate_state(Phi: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The error state through the cycles (15 states compiled, fusion/_cycles.c; an augmented state in numpy). A
    zero state (the closed loop's, between updates) stays zero without a product.

    Parameters
    ----------
    Phi : ndarray (m, n, n)
        The cycles' transition matrices.
    x : ndarray (n,)
        The state before the first.

    Returns
    -------
    ndarray (m, n)
        x after each cycle.
    """
    if not x.any():
        return np.zeros((len(Phi), len(x)))
    out = np.empty((len(Phi), len(x)))
    if x.shape == (N_STATES,) and Phi.shape[1:] == (N_STATES, N_STATES):
        errmodel.cycle_kernel().fieldlog_propagate_state(len(Phi), kernels.address(np.ascontiguousarray(Phi, float)),
                                                         kernels.address(np.array(x, float)), kernels.address(out))
        return out
    for i in range(len(Phi)):
        x = Phi[i] @ x
        out[i] = x
    return out


def cycle_matrices(dt: float, ins_state: NavState, imu: tuple[np.ndarray, np.ndarray], q: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Phi, Q of one filter cycle.

    Parameters
    ----------
    dt, ins_state, imu
        As :meth:`KalmanFilter.predict`.
    q : ndarray (12, 12)
        Noise PSD (``errmodel.noise_psd``).

    Returns
    -------
    Phi, Q : ndarray (1, 15, 15)
    """
    C = ins_state.C_bn
    F, G = errmodel.system_matrices(ins_state.lat, ins_state.h, ins_state.v_n, C, C @ np.asarray(imu[1]))
    return errmodel.discretise(F[None], G[None], q, np.array([dt]))


def stack(*ms: Measurement | None) -> Measurement | None:
    """The given measurements as one.

    Parameters
    ----------
    *ms : Measurement or None
        (z, H, R) each; None ones are left out.

    Returns
    -------
    Measurement or None
        z and H stacked in order, R block-diagonal; a single one as it is (its readers, the updates, the listeners
        and the tests on it, write nothing into it); None when there is none.
    """
    ms = tuple(m for m in ms if m is not None)
    if len(ms) <= 1:
        return ms[0] if ms else None
    return np.concatenate([m[0] for m in ms]), np.concatenate([m[1] for m in ms]), _block_diag([m[2] for m in ms])


def _block_diag(blocks: list[np.ndarray]) -> np.ndarray:
    n = sum(len(b) for b in blocks)
    out = np.zeros((n, n))
    i = 0
    for b in blocks:
        out[i:i + len(b), i:i + len(b)] = b
        i += len(b)
    return out


def enu_offset(lat: float, lon: float, h: float, lat_ref: float, lon_ref: float, h_ref: float) -> np.ndarray:
    """Small ENU displacement (m) of (lat, lon, h) from (lat_ref, lon_ref, h_ref) (rad, rad, m).

    Parameters
    ----------
    lat, lon : float
        The point's geodetic latitude and longitude, rad.
    h : float
        Its ellipsoidal height, m.
    lat_ref, lon_ref : float
        The reference's latitude and longitude, rad.
    h_ref : float
        Its ellipsoidal height, m.

    Returns
    -------
    ndarray (3,)
        [E, N, U], m: the differences scaled by the principal radii at the reference (a flat-Earth step, for
        offsets small against the Earth's radius).
    """
    rm, rn = earth.principal_radii(lat_ref, h_ref)
    return np.array([(lon - lon_ref) * rn * np.cos(lat_ref), (lat - lat_ref) * rm, h - h_ref])


def correct_ins(nav: NavState, x: np.ndarray) -> NavState:
    """Feed the error estimate back into the navigation state (errors are computed - true).

    Parameters
    ----------
    nav : NavState
        The INS state.
    x : ndarray (15,)
        The error estimate (``fusion.errmodel`` order and units).

    Returns
    -------
    NavState
        The corrected state.
    """
    # the quaternion in floats (one state: numpy's per-call cost would be most of the work), by the formulas of
    # earth.rotvec_to_quat and earth.quat_multiply
    e, n, u, px, py, pz = x[:3].tolist() + x[ATT].tolist()
    rm, rn = (float(r) for r in earth.principal_radii(nav.lat, nav.h))
    a = math.sqrt(px * px + py * py + pz * pz)
    k = 0.5 - a * a / 48.0 + (a * a) * (a * a) / 3840.0 if a < 1e-4 else math.sin(0.5 * a) / a
    px, py, pz, pw = k * px, k * py, k * pz, math.cos(0.5 * a)  # C_true = (I + [phi x]) C_computed
    qx, qy, qz, qw = nav.q.tolist()
    q = np.array([pw * qx + qw * px + (py * qz - pz * qy), pw * qy + qw * py + (pz * qx - px * qz),
                  pw * qz + qw * pz + (px * qy - py * qx), pw * qw - (px * qx + py * qy + pz * qz)])
    q /= math.sqrt(float(q @ q))
    q = q if q[3] >= 0.0 else -q
    return NavState(nav.t, float(nav.lat - n / rm), float(nav.lon - e / (rn * math.cos(nav.lat))), float(nav.h - u),
                    nav.v_n - x[VEL], q)
