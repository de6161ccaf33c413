"""The distributed filter of the distributed-KF paper, section 2.1 (Fig. 1), on the shared filter interface.

KF_I is fed by the GPS velocity only (H1, R1), KF_II by the GPS position only (H2, R2); both are
:class:`fusion.kf.KalmanFilter` instances over the same 15 states, each with its own P0, Q and P. Their
estimates are fused by inverse-covariance weighting (paper eqs. 3-4)::

    P = (P_I^-1 + P_II^-1)^-1,    x = P (P_I^-1 x_I + P_II^-1 x_II)

and the fused x corrects the INS (closed loop). Each local estimate is then shifted by the correction applied,
x_i <- x_i - x (it now estimates the error of the corrected INS), not replaced: a local filter keeps what it
knows that the fused estimate did not take, and its covariance (the error of x_i is unchanged by the shift).

What eqs. 3-4 ignore
--------------------
Eqs. 3-4 are the fusion of two *independent* estimates. Ours are not: both local errors e_i = x_i - dx (dx the
true INS error) carry the same prior (both start at P0 from the one alignment) and the same process noise w,
the one INS error both model. Their cross-covariance P_12 = E[e_I e_II^T] follows::

    start:       P_12 = P0
    prediction:  P_12 <- Phi P_12 Phi^T + Q          (the common w)
    update:      P_12 <- (I - K_I H_I) P_12 (I - K_II H_II)^T   (independent velocity and position noise)
    aid to KF_I: P_12 <- (I - K_a H_a) P_12
    feedback:    unchanged (the shift moves both estimate and truth)

The optimal combination of two correlated estimates (Bar-Shalom and Campo) would use P_12; eqs. 3-4 set it to
zero, i.e. count the common prior and process noise twice. The fused estimate therefore loses information
against the centralised KF (as the paper's section 2.1 says of distributed fusion), and the eq. 4 covariance
is optimistic. We keep the paper's estimate (eq. 3) and report, as ``covariance``, the actual covariance of
that estimate's error, W_I P_I W_I^T + W_I P_12 W_II^T + W_II P_12^T W_I^T + W_II P_II W_II^T with
W_i = P P_i^-1 (honest sigmas); ``fused_covariance`` is eq. 4's. P_12 is tracked for that (a third 15x15
recursion). tests/test_dkf.py checks the loss against ``kf`` over seeds; its size is in docs/results.md
("Fusion").

The federated variant (``fusion="federated"``, ``[fusion] dkf_fusion = "federated"``): information sharing
with full reset (Carlson): each local filter runs with P_i = P / beta and Q_i = Q / beta, beta = 1/2, and after
each fusion both are reset to x_i = 0, P_i = P / beta. With linear models and both updates at the same epoch
eqs. 3-4 then give exactly the centralised estimate: it equals ``kf`` (to rounding), and is not the paper's
filter.

Vehicle aids (NHC, ZUPT: velocity-domain constraints) go to KF_I only: given to both, eqs. 3-4 would count
them twice.

The hybrid predictor (``fusion.predictors``) needs, per epoch, each local filter's innovation component
K_i nu_i (:attr:`DistributedKF.innovations`) and, in an outage, its state prediction plus a predicted
innovation (:meth:`DistributedKF.predicted_update`).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from fieldlog.fusion.errmodel import N_STATES, propagate_covariance
from fieldlog.fusion.ins import NavState
from fieldlog.fusion.kf import (KalmanFilter, Measurement, Observation, cycle_matrices, gps_observations,
                                propagate_state, stack)

BETA = 0.5  # information share of each local filter (federated)
FUSIONS = ("paper", "federated")


class DistributedKF:
    """KF_I (velocity) + KF_II (position) with eqs. 3-4 fusion; the interface of :class:`fusion.kf.KalmanFilter`.

    P0 (15, 15), q (12, 12) as KalmanFilter; fusion "paper" (default) or "federated". Its declarations
    (:class:`fusion.kf.KalmanFilter`): local filters, and the fused state prediction fed back between fixes."""

    wants_nodes = False
    wants_cycle_lengths = False
    models_gps_error = False
    has_locals = True
    feeds_prediction = True

    def __init__(self, P0: np.ndarray, q: np.ndarray, fusion: str = "paper") -> None:
        if fusion not in FUSIONS:
            raise ValueError(f"dkf_fusion must be one of {FUSIONS}, got {fusion!r}")
        self.federated = fusion == "federated"
        scale = 1.0 / BETA if self.federated else 1.0
        self.kf_vel = KalmanFilter(P0 * scale, q, q_scale=scale)
        self.kf_pos = KalmanFilter(P0 * scale, q, q_scale=scale)
        self.P12 = None if self.federated else np.array(P0, dtype=float)
        self.innovations = (np.zeros(N_STATES), np.zeros(N_STATES))  # K_i nu_i of the last GPS update
        self._fuse()

    @property
    def state(self) -> np.ndarray:
        """Fused error-state estimate (15,), eq. 3."""
        return self.x

    @property
    def covariance(self) -> np.ndarray:
        """Covariance of the fused estimate's error (15, 15): with the cross-covariance (paper), eq. 4 (federated,
        where it is exact)."""
        return self.P

    @property
    def fused_covariance(self) -> np.ndarray:
        """Eq. 4's P (15, 15)."""
        return self.P4

    @property
    def locals(self) -> tuple[KalmanFilter, KalmanFilter]:
        """(KF_I, KF_II)."""
        return self.kf_vel, self.kf_pos

    def predict(self, dt: float, ins_state: NavState, imu: tuple[np.ndarray, np.ndarray]) -> None:
        """One filter cycle (``KalmanFilter.predict`` for the arguments)."""
        self.propagate(*cycle_matrices(dt, ins_state, imu, self.kf_vel.q))

    def propagate(self, Phi: np.ndarray, Q: np.ndarray) -> np.ndarray:
        """Both local filters over a sequence of cycles Phi, Q (m, 15, 15); returns the diagonal of the fused
        error covariance after each (m, 15). ``local_states`` (m, 2, 15) and ``local_diag`` (m, 2, 15) hold the
        local estimates and variances after each cycle."""
        m = len(Phi)
        if self.federated:  # between fusions P_i = P / beta each, so the fused P is beta * P_i
            d1 = self.kf_vel.propagate(Phi, Q)
            self.kf_pos.propagate(Phi, Q)
            self._fuse()
            self.local_states = np.zeros((m, 2, N_STATES))
            self.local_diag = np.stack([d1, d1], axis=1)
            return BETA * d1
        xs = np.stack([propagate_state(Phi, self.kf_vel.x), propagate_state(Phi, self.kf_pos.x)], axis=1)
        Ps = np.stack([propagate_covariance(Phi, Q, self.kf_vel.P), propagate_covariance(Phi, Q, self.kf_pos.P),
                       propagate_covariance(Phi, Q, self.P12, sym=False)])  # P1, P2, P12 after each cycle
        # every cycle's information matrices and fused error covariance at once: the same per-matrix LAPACK and
        # BLAS calls as one by one, so the last cycle's are what _fuse would compute again
        infos = _inv_spd(Ps[0]), _inv_spd(Ps[1])
        Pe = _fused_error_cov(*Ps, *infos)[1]
        if m:
            self.kf_vel.x, self.kf_pos.x = xs[-1, 0], xs[-1, 1]
            self.kf_vel.P, self.kf_pos.P, self.P12 = Ps[0, -1].copy(), Ps[1, -1].copy(), Ps[2, -1].copy()
            self._fuse((infos[0][-1], infos[1][-1]), Pe[-1])
        else:
            self._fuse()
        self.local_states = xs
        self.local_diag = np.diagonal(Ps[:2], axis1=2, axis2=3).transpose(1, 0, 2).copy()
        return np.diagonal(Pe, axis1=1, axis2=2).copy()

    def update(self, z: np.ndarray, H: np.ndarray, R: np.ndarray) -> np.ndarray:
        """A measurement of the shared interface: to KF_II when it observes position, else to KF_I; then fusion.
        Returns the change of the fused estimate (15,)."""
        before = self.x.copy()
        if np.any(H[:, 0:3]):
            self._update_local(1, (z, H, R))
        else:
            self._update_local(0, (z, H, R))
        self._fuse()
        return self.x - before

    def update_batch(self, obs: list[Observation]) -> None:
        """The velocity kind (stacked) to KF_I, the position kind to KF_II, then fusion by eqs. 3-4. The
        innovation components K_i nu_i are kept in ``innovations``."""
        vel = stack(*(o.m for o in obs if o.kind == "velocity"))
        pos = stack(*(o.m for o in obs if o.kind == "position"))
        dx1 = self._update_local(0, vel) if vel is not None else np.zeros(N_STATES)
        dx2 = self._update_local(1, pos) if pos is not None else np.zeros(N_STATES)
        self.innovations = (dx1, dx2)
        self._fuse()

    def update_gps(self, vel: Measurement | None, pos: Measurement | None) -> None:
        """KF_I with the GPS velocity, KF_II with the position (:meth:`update_batch`)."""
        self.update_batch(gps_observations(vel, pos))

    def update_aid(self, m: Measurement) -> None:
        """A vehicle-motion aid (velocity-domain constraint): to KF_I only (:meth:`update_batch`)."""
        self.update_batch([Observation("velocity", m)])

    def predicted_update(self, dx_vel: np.ndarray, dx_pos: np.ndarray) -> None:
        """Paper eq. 7 in an outage: X_i(n) = X_i(n|n-1) + predicted innovation dx_i (15,) (KF_I: dx_vel,
        KF_II: dx_pos); the covariances are untouched (a prediction is not a measurement); then fusion."""
        self.kf_vel.x = self.kf_vel.x + dx_vel
        self.kf_pos.x = self.kf_pos.x + dx_pos
        self._fuse()

    def shift(self, b: np.ndarray) -> None:
        """A known correction b (15,) was applied to the INS (an outage predictor's): the local estimates, of the
        INS error, move by it (paper); the federated filter's are zero and stay so."""
        if not self.federated:
            for f in self.locals:
                f.x = f.x - b
            self._fuse()

    def start_outage(self) -> None:
        """Told at each unusable GPS epoch: nothing to do."""

    def reset(self) -> None:
        """After the fused estimate has been fed back: paper, each local estimate shifted by it, covariances
        kept; federated, local states to zero and local covariances to P / beta."""
        for f in self.locals:
            f.x = f.x - self.x if not self.federated else np.zeros(N_STATES)
            if self.federated:
                f.P = self.P / BETA
        self.x = np.zeros(N_STATES)

    def _update_local(self, i: int, m: Measurement) -> np.ndarray:
        f = self.locals[i]
        dx = f.update(*m)
        if self.P12 is not None:
            A = np.eye(N_STATES) - f.gain @ m[1]
            self.P12 = A @ self.P12 if i == 0 else self.P12 @ A.T
        return dx

    def _fuse(self, infos: tuple[np.ndarray, np.ndarray] | None = None, P: np.ndarray | None = None) -> None:
        """Eqs. 3-4 on the local filters as they stand; ``infos`` (their inverse covariances) and ``P`` (the
        fused estimate's error covariance, paper fusion) when the caller has them."""
        if infos is None:
            infos = tuple(_inv_spd(f.covariance) for f in self.locals)  # each local information matrix, once
        self.x, self.P4 = fuse(self.locals, list(infos))
        if self.P12 is None:
            self.P = self.P4
        else:
            self.P = _fused_error_cov(self.kf_vel.P, self.kf_pos.P, self.P12, *infos)[1] if P is None else P


def fuse(filters, infos: list[np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Inverse-covariance fusion of local estimates (paper eqs. 3-4): returns (x, P). ``infos``: the filters'
    inverse covariances when the caller has them."""
    info = np.zeros_like(filters[0].covariance)
    vec = np.zeros_like(filters[0].state)
    if infos is None:
        infos = [_inv_spd(f.covariance) for f in filters]
    for f, Pi in zip(filters, infos):
        info += Pi
        vec += Pi @ f.state
    P = _inv_spd(info)
    return P @ vec, P


def _fused_error_cov(P1: np.ndarray, P2: np.ndarray, P12: np.ndarray, I1: np.ndarray | None = None,
                     I2: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(eq. 4's P, the covariance of the eqs. 3-4 estimate's error given the cross-covariance P12); of one
    cycle's (15, 15) matrices or of a stack of them (m, 15, 15). I1, I2: the inverses of P1, P2 when the caller
    has them. P is inverted again from I1 + I2 rather than taken from ``fuse``, whose sum starts from zeros."""
    I1 = _inv_spd(P1) if I1 is None else I1
    I2 = _inv_spd(P2) if I2 is None else I2
    P = _inv_spd(I1 + I2)
    W1, W2 = P @ I1, P @ I2
    C = W1 @ P12 @ _t(W2)
    return P, _sym(W1 @ P1 @ _t(W1) + W2 @ P2 @ _t(W2) + C + _t(C))


def _t(A: np.ndarray) -> np.ndarray:
    """The transpose of a matrix, or of each of a stack."""
    return np.swapaxes(A, -1, -2)


def _sym(P: np.ndarray) -> np.ndarray:
    return 0.5 * (P + _t(P))


def _inv_spd(P: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive definite matrix (or of each of a stack) through Cholesky, symmetrised."""
    L = np.linalg.cholesky(P)
    Li = np.linalg.solve(L, _identity(P.shape))
    return _t(Li) @ Li


@lru_cache(maxsize=32)
def _identity(shape: tuple[int, ...]) -> np.ndarray:
    """The identity broadcast to a matrix's or a stack's shape (read-only; shared, as it is asked for per cycle)."""
    return np.broadcast_to(np.eye(shape[-1]), shape)
