"""The distributed filter of the distributed-KF paper, section 2.1.

KF_I is fed by GPS velocity, KF_II by GPS position; both are :class:`fusion.kf.KalmanFilter` instances
over the same 15 states, differing only in H and R. Their estimates are fused by inverse-covariance
weighting (paper eqs. 3-4)::

    P = (P_I^-1 + P_II^-1)^-1,    x = P (P_I^-1 x_I + P_II^-1 x_II)

and the fused x corrects the INS (closed loop).

The two local filters share the same process and prior, so eqs. 3-4 alone would count that common
information twice. We use the federated filter's information sharing with full reset (Carlson): each
local filter runs with P_i = P / beta and Q_i = Q / beta, beta = 1/2, and after each fusion both are
reset to x_i = 0, P_i = P / beta. With linear models and both updates at the same epoch this makes
eqs. 3-4 give exactly the centralised estimate, which is the paper's "global optimal fusion" claim.
"""

from __future__ import annotations

import numpy as np

from fieldlog.fusion.kf import KalmanFilter, Measurement

BETA = 0.5  # information share of each local filter


class DistributedKF:
    """KF_I (velocity) + KF_II (position) with eqs. 3-4 fusion; same interface as KalmanFilter."""

    def __init__(self, P0: np.ndarray, q: np.ndarray) -> None:
        self.kf_vel = KalmanFilter(P0 / BETA, q, q_scale=1.0 / BETA)
        self.kf_pos = KalmanFilter(P0 / BETA, q, q_scale=1.0 / BETA)
        self.x, self.P = fuse([self.kf_vel, self.kf_pos])

    @property
    def state(self) -> np.ndarray:
        """Fused error-state estimate (15,)."""
        return self.x

    @property
    def covariance(self) -> np.ndarray:
        """Fused covariance (15, 15)."""
        return self.P

    @property
    def locals(self) -> tuple[KalmanFilter, KalmanFilter]:
        """(KF_I, KF_II)."""
        return self.kf_vel, self.kf_pos

    def predict(self, dt, ins_state, imu) -> None:
        """Both local filters, then fusion (``KalmanFilter.predict`` for the arguments)."""
        for f in self.locals:
            f.predict(dt, ins_state, imu)
        self.x, self.P = fuse(self.locals)

    def propagate(self, Phi: np.ndarray, Q: np.ndarray) -> np.ndarray:
        """Both local filters over a sequence of cycles; returns diag of the fused P after each (m, 15).

        Between fusions the local covariances are P_i = P / beta each, so the fused P is beta * P_i.
        """
        d = self.kf_vel.propagate(Phi, Q)
        self.kf_pos.propagate(Phi, Q)
        self.x, self.P = fuse(self.locals)
        return BETA * d

    def update_gps(self, vel: Measurement | None, pos: Measurement | None) -> None:
        """KF_I with the velocity, KF_II with the position, then fusion by eqs. 3-4."""
        if vel is not None:
            self.kf_vel.update(*vel)
        if pos is not None:
            self.kf_pos.update(*pos)
        self.x, self.P = fuse(self.locals)

    def update_aid(self, m: Measurement) -> None:
        """A vehicle-motion aid (non-holonomic, stationary: velocity-domain constraints) to KF_I only, then
        fusion. With information sharing a measurement given to exactly one local filter fuses into the
        centralised update (the information added is H^T R^-1 H once); given to both it would count twice."""
        self.kf_vel.update(*m)
        self.x, self.P = fuse(self.locals)

    def start_outage(self) -> None:
        """Told at each unusable GPS epoch: nothing to do."""

    def reset(self) -> None:
        """After feedback: fused and local states to zero, local covariances to P / beta."""
        self.x = np.zeros_like(self.x)
        for f in self.locals:
            f.x = np.zeros_like(self.x)
            f.P = self.P / BETA


def fuse(filters) -> tuple[np.ndarray, np.ndarray]:
    """Inverse-covariance fusion of local estimates (paper eqs. 3-4): returns (x, P)."""
    info = np.zeros_like(filters[0].covariance)
    vec = np.zeros_like(filters[0].state)
    for f in filters:
        Pi = _inv_spd(f.covariance)
        info += Pi
        vec += Pi @ f.state
    P = _inv_spd(info)
    return P @ vec, P


def _inv_spd(P: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive definite matrix through Cholesky, symmetrised."""
    L = np.linalg.cholesky(P)
    Li = np.linalg.solve(L, np.eye(len(P)))
    return Li.T @ Li
