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

from dataclasses import dataclass

import numpy as np

from fieldlog.fusion import earth, errmodel
from fieldlog.fusion.errmodel import ATT, N_STATES, VEL
from fieldlog.fusion.ins import NavState

Measurement = tuple[np.ndarray, np.ndarray, np.ndarray]  # (z (m,), H (m, 15), R (m, m))


@dataclass(frozen=True)
class Observation:
    """A measurement's matrices m = (z, H, R) with what the filters route on: kind "velocity" or "position"
    (``fusion.measurements``); receiver: R is the GPS receiver's own figure."""

    kind: str
    m: Measurement
    receiver: bool = False


def gps_observations(vel: Measurement | None, pos: Measurement | None) -> list[Observation]:
    """The GPS velocity and position measurements given (None: left out) as observations, in that order."""
    return [Observation(k, m, True) for k, m in (("velocity", vel), ("position", pos)) if m is not None]


class KalmanFilter:
    """Linear KF on the 15-state INS error (``fusion.errmodel``).

    P0 (15, 15) initial covariance; q (12, 12) noise PSD (``errmodel.noise_psd``); q_scale multiplies
    the discrete Q (the information-sharing factor 1/beta of a federated local filter; 1 otherwise).

    What a filter needs from the loop, and what it carries, it declares (class attributes, all False here):
    ``wants_nodes``: the navigation solution at each cycle's RK4 nodes (``queue``, ``fusion.ukf.CycleFilter``);
    ``wants_cycle_lengths``: the cycle lengths before each ``propagate`` (``cycles``, ``fusion.gpserror``);
    ``models_gps_error``: the correlated GPS error is in its states (nothing is added to its sigmas);
    ``has_locals``: local filters whose solutions are written too (``locals``, ``local_states``,
    ``local_diag``, ``fusion.dkf``); ``feeds_prediction``: its state prediction between epochs is an estimate,
    fed back at every epoch without a fix (the distributed filter's fused X(n|n-1)).
    """

    wants_nodes = False
    wants_cycle_lengths = False
    models_gps_error = False
    has_locals = False
    feeds_prediction = False

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

    def predict(self, dt: float, ins_state: NavState, imu: tuple[np.ndarray, np.ndarray]) -> None:
        """Propagate over one filter cycle of dt s.

        ins_state: the INS state in the middle of the cycle; imu = (omega_ib_b, f_b), the mean
        bias-corrected rate (rad/s) and specific force (m/s^2) over the cycle, body RFU.
        """
        self.propagate(*cycle_matrices(dt, ins_state, imu, self.q))

    def propagate(self, Phi: np.ndarray, Q: np.ndarray) -> np.ndarray:
        """Apply a sequence of discrete cycles: Phi, Q (m, 15, 15). Returns diag(P) after each, (m, 15)."""
        self.x = propagate_state(Phi, self.x)[-1] if len(Phi) else self.x
        hist = errmodel.propagate_covariance(Phi, Q, self.P, self.q_scale)
        if len(hist):
            self.P = hist[-1].copy()
        return np.diagonal(hist, axis1=1, axis2=2).copy()

    def update(self, z: np.ndarray, H: np.ndarray, R: np.ndarray) -> np.ndarray:
        """Measurement update (Joseph form). z (m,), H (m, 15), R (m, m).

        Returns the innovation component of the estimate, K (z - H x) (15,) (the distributed-KF
        paper's Delta X, eq. 7).
        """
        S = H @ self.P @ H.T + R
        K = np.linalg.solve(S, H @ self.P).T
        self.gain = K
        dx = K @ (z - H @ self.x)
        self.x = self.x + dx
        A = np.eye(len(self.x)) - K @ H
        P = A @ self.P @ A.T + K @ R @ K.T
        self.P = 0.5 * (P + P.T)
        return dx

    def update_batch(self, obs: list[Observation]) -> None:
        """One update with the observations' matrices stacked in their order (the centralised filter: one z)."""
        m = stack(*(o.m for o in obs))
        if m is not None:
            self.update(*m)

    def update_gps(self, vel: Measurement | None, pos: Measurement | None) -> None:
        """Update with the available GPS measurements, z = [dv; dp] (:meth:`update_batch`)."""
        self.update_batch(gps_observations(vel, pos))

    def update_aid(self, m: Measurement) -> None:
        """A vehicle-motion aid (``fusion.measurements``), a velocity-kind observation."""
        self.update_batch([Observation("velocity", m)])

    def start_outage(self) -> None:
        """Told at each unusable GPS epoch; nothing to do for a linear KF (``fusion.ukf.HybridKfUkf`` acts on it)."""

    def reset(self) -> None:
        """Closed-loop reset after the estimate has been fed back: x = 0 (P unchanged)."""
        self.x = np.zeros(N_STATES)


def propagate_state(Phi: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The error state x (15,) through the cycles Phi (m, 15, 15): x after each, (m, 15). A zero state (the closed
    loop's, between updates) stays zero without a product."""
    if not x.any():
        return np.zeros((len(Phi), len(x)))
    out = np.empty((len(Phi), len(x)))
    for i in range(len(Phi)):
        x = Phi[i] @ x
        out[i] = x
    return out


def cycle_matrices(dt: float, ins_state: NavState, imu: tuple[np.ndarray, np.ndarray], q: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Phi, Q (1, 15, 15) of one filter cycle (``KalmanFilter.predict`` for the arguments; q the noise PSD)."""
    C = ins_state.C_bn
    F, G = errmodel.system_matrices(ins_state.lat, ins_state.h, ins_state.v_n, C, C @ np.asarray(imu[1]))
    return errmodel.discretise(F[None], G[None], q, np.array([dt]))


def stack(*ms: Measurement | None) -> Measurement | None:
    """The given measurements as one (z, H, R), R block-diagonal; None when there is none."""
    ms = tuple(m for m in ms if m is not None)
    if not ms:
        return None
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
    """Small ENU displacement (m) of (lat, lon, h) from (lat_ref, lon_ref, h_ref) (rad, rad, m)."""
    rm, rn = earth.principal_radii(lat_ref, h_ref)
    return np.array([(lon - lon_ref) * rn * np.cos(lat_ref), (lat - lat_ref) * rm, h - h_ref])


def correct_ins(nav: NavState, x: np.ndarray) -> NavState:
    """Feed the error estimate x (15,) back into the navigation state (errors are computed - true)."""
    rm, rn = earth.principal_radii(nav.lat, nav.h)
    lat = nav.lat - x[1] / rm
    lon = nav.lon - x[0] / (rn * np.cos(nav.lat))
    q = earth.quat_multiply(earth.rotvec_to_quat(x[ATT]), nav.q)  # C_true = (I + [phi x]) C_computed
    q = q / np.linalg.norm(q)
    q = q if q[3] >= 0.0 else -q
    return NavState(nav.t, float(lat), float(lon), float(nav.h - x[2]), nav.v_n - x[VEL], q)
