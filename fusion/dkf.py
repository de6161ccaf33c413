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

import numpy as np

from fieldlog.fusion import kernels
from fieldlog.fusion.errmodel import N_STATES, cycle_kernel
from fieldlog.fusion.kf import BatchUpdates, KalmanFilter, Measurement, Observation, joseph_update, stack

BETA = 0.5  # information share of each local filter (federated)
FUSIONS = ("paper", "federated")


class DistributedKF(BatchUpdates):
    """KF_I (velocity) + KF_II (position) with eqs. 3-4 fusion; the interface of :class:`fusion.kf.KalmanFilter`.

    P0 (15, 15), q (12, 12) as KalmanFilter; fusion "paper" (default) or "federated". Its declarations
    (:class:`fusion.kf.KalmanFilter`): local filters, and the fused state prediction fed back between fixes.
    ``update_gps`` gives KF_I the GPS velocity and KF_II the position, ``update_aid`` a vehicle aid (a
    velocity-domain constraint) to KF_I only (``fusion.kf.BatchUpdates``, through :meth:`update_batch`)."""

    wants_nodes = False
    wants_cycle_lengths = False
    models_gps_error = False
    has_locals = True
    feeds_prediction = True
    keeps_predicted = False  # the paper's fusion keeps them (``predicted``), the federated one does not

    def __init__(self, P0: np.ndarray, q: np.ndarray, fusion: str = "paper") -> None:
        if fusion not in FUSIONS:
            raise ValueError(f"dkf_fusion must be one of {FUSIONS}, got {fusion!r}")
        self.federated = fusion == "federated"
        self.keeps_predicted = not self.federated
        scale = 1.0 / BETA if self.federated else 1.0
        self.kf_vel = KalmanFilter(P0 * scale, q, q_scale=scale)
        self.kf_pos = KalmanFilter(P0 * scale, q, q_scale=scale)
        self.q = self.kf_vel.q  # the noise PSD (12, 12) of one filter cycle (``predict``)
        self.P12 = None if self.federated else np.array(P0, dtype=float)
        self.innovations = (np.zeros(N_STATES), np.zeros(N_STATES))  # K_i nu_i of the last GPS update
        self._cycles = (np.empty((3, 0, N_STATES, N_STATES)), np.empty((0, 2, N_STATES)))  # propagate's last
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

    def propagate(self, Phi: np.ndarray, Q: np.ndarray) -> np.ndarray:
        """Both local filters (and, paper fusion, their cross-covariance) over a sequence of cycles, fused after
        each (paper fusion: all in one compiled call, fusion/_cycles.c; the fused estimate and its covariance are
        made whole after the last cycle, its variances after each); ``local_states`` and ``local_diag`` (m, 2,
        15) get the local estimates and variances after each cycle.

        Parameters
        ----------
        Phi : ndarray (m, 15, 15)
            Transition matrix of each cycle.
        Q : ndarray (m, 15, 15)
            Its process noise, shared by both locals (``fusion.errmodel`` order and units).

        Returns
        -------
        ndarray (m, 15)
            diag of the fused estimate's error covariance (``covariance``) after each cycle (paper fusion: the
            covariance itself after each, ``predicted``).
        """
        m = len(Phi)
        if self.federated:  # between fusions P_i = P / beta each, so the fused P is beta * P_i
            d1 = self.kf_vel.propagate(Phi, Q)
            self.kf_pos.propagate(Phi, Q)
            self._fuse()
            self.local_states = np.zeros((m, 2, N_STATES))
            self.local_diag = np.stack([d1, d1], axis=1)
            return BETA * d1
        Phi, Q = np.ascontiguousarray(Phi, dtype=float), np.ascontiguousarray(Q, dtype=float)
        if Phi.shape != (m, N_STATES, N_STATES) or Q.shape != Phi.shape:
            raise ValueError(f"the cycles need Phi and Q (m, 15, 15): {Phi.shape}, {Q.shape}")
        x1, x2 = np.array(self.kf_vel.x, dtype=float), np.array(self.kf_pos.x, dtype=float)
        P1, P2, P12 = (np.array(a, dtype=float) for a in (self.kf_vel.P, self.kf_pos.P, self.P12))
        xs, hist, d = np.empty((m, 2, N_STATES)), np.empty((3, m, N_STATES, N_STATES)), np.empty((m, N_STATES))
        x, P4, Pe = np.empty(N_STATES), np.empty((N_STATES, N_STATES)), np.empty((N_STATES, N_STATES))
        if cycle_kernel().fieldlog_dkf_propagate(m, *map(kernels.address, (Phi, Q)), self.kf_vel.q_scale,
                                                 *map(kernels.address, (x1, x2, P1, P2, P12, xs, hist, d, x, P4, Pe))):
            raise np.linalg.LinAlgError("Matrix is not positive definite: a local or fused covariance")
        if m:
            self.kf_vel.x, self.kf_pos.x, self.kf_vel.P, self.kf_pos.P, self.P12 = x1, x2, P1, P2, P12
            self.x, self.P4, self.P = x, P4, Pe
        self._cycles = (hist, xs)
        self.local_states = xs
        self.local_diag = np.diagonal(hist[:2], axis1=2, axis2=3).transpose(1, 0, 2).copy()
        return d

    @property
    def predicted(self) -> np.ndarray:
        """The fused estimate's error covariance after each cycle of the last :meth:`propagate` (m, 15, 15), the
        paper's fusion (made when asked: its diagonal is what ``propagate`` returns)."""
        hist, xs = self._cycles
        return fuse(hist[0], hist[1], hist[2], xs[:, 0], xs[:, 1])[2]

    def update(self, z: np.ndarray, H: np.ndarray, R: np.ndarray) -> np.ndarray:
        """A measurement of the shared interface: to KF_II when it observes position, else to KF_I; then fusion.

        Parameters
        ----------
        z, H, R : ndarray (m,), (m, 15), (m, m)
            The measurement, its sensitivity to the error state and its noise covariance.

        Returns
        -------
        ndarray (15,)
            The change of the fused estimate.
        """
        before = self.x.copy()
        if np.any(H[:, 0:3]):
            self._update_local(1, (z, H, R))
        else:
            self._update_local(0, (z, H, R))
        self._fuse()
        return self.x - before

    def update_batch(self, obs: list[Observation]) -> None:
        """The velocity kind (stacked) to KF_I, the position kind to KF_II, then fusion by eqs. 3-4. The
        innovation components K_i nu_i are kept in ``innovations``.

        Parameters
        ----------
        obs : list of Observation
            One epoch's observations (``fusion.kf.Observation``), routed by their kind.
        """
        vel = stack(*(o.m for o in obs if o.kind == "velocity"))
        pos = stack(*(o.m for o in obs if o.kind == "position"))
        dx1 = self._update_local(0, vel) if vel is not None else np.zeros(N_STATES)
        dx2 = self._update_local(1, pos) if pos is not None else np.zeros(N_STATES)
        self.innovations = (dx1, dx2)
        self._fuse()

    def predicted_update(self, dx_vel: np.ndarray, dx_pos: np.ndarray) -> None:
        """Paper eq. 7 in an outage: X_i(n) = X_i(n|n-1) + predicted innovation dx_i; the covariances are
        untouched (a prediction is not a measurement); then fusion.

        Parameters
        ----------
        dx_vel, dx_pos : ndarray (15,)
            The predicted innovation components of KF_I and KF_II (``fusion.errmodel`` order and units).
        """
        self.kf_vel.x = self.kf_vel.x + dx_vel
        self.kf_pos.x = self.kf_pos.x + dx_pos
        self._fuse()

    def shift(self, b: np.ndarray) -> None:
        """A known correction was applied to the INS (an outage predictor's): the local estimates, of the INS
        error, move by it (paper); the federated filter's are zero and stay so.

        Parameters
        ----------
        b : ndarray (15,)
            The correction, in the error state's order and units.
        """
        if not self.federated:
            for f in self.locals:
                f.x = f.x - b
            self._fuse()

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
        f.x, f.P, f.gain, dx, P12 = joseph_update(f.x, f.P, *m, self.P12, i)
        self.P12 = P12 if P12 is not None else self.P12
        return dx

    def _fuse(self) -> None:
        """Eqs. 3-4 on the local filters as they stand, and the fused estimate's error covariance (paper)."""
        x, P4, Pe = fuse(*(f.P[None] for f in self.locals), None if self.P12 is None else self.P12[None],
                         *(f.x[None] for f in self.locals))
        self.x, self.P4 = x[0], P4[0]
        self.P = self.P4 if Pe is None else Pe[0]


def fuse(P1: np.ndarray, P2: np.ndarray, P12: np.ndarray | None, x1: np.ndarray, x2: np.ndarray
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Inverse-covariance fusion (paper eqs. 3-4) of m cycles' local estimates, compiled (fusion/_cycles.c).

    Parameters
    ----------
    P1, P2 : ndarray (m, 15, 15)
        The local filters' error covariances (``fusion.errmodel`` order and units).
    P12 : ndarray (m, 15, 15) or None
        Their cross-covariance E[e_1 e_2^T]; None: not tracked (federated).
    x1, x2 : ndarray (m, 15)
        The local error-state estimates.

    Returns
    -------
    x : ndarray (m, 15)
        The fused estimate, P (P1^-1 x1 + P2^-1 x2).
    P : ndarray (m, 15, 15)
        Eq. 4's covariance, (P1^-1 + P2^-1)^-1.
    Pe : ndarray (m, 15, 15) or None
        The covariance of the fused estimate's error given P12 (module docstring); None without P12.

    Raises
    ------
    numpy.linalg.LinAlgError
        When a local covariance, or the sum of their inverses, is not positive definite.
    """
    arrays = [np.ascontiguousarray(a, dtype=float) for a in (P1, P2, x1, x2)]
    m = len(arrays[0])
    P12 = None if P12 is None else np.ascontiguousarray(P12, dtype=float)
    shapes = [(m, N_STATES, N_STATES)] * 2 + [(m, N_STATES)] * 2
    if [a.shape for a in arrays] != shapes or (P12 is not None and P12.shape != shapes[0]):
        raise ValueError(f"fusion needs P1, P2, P12 (m, 15, 15) and x1, x2 (m, 15): {[a.shape for a in arrays]}")
    x, P, Pe = np.empty((m, N_STATES)), np.empty((m, N_STATES, N_STATES)), None if P12 is None else np.empty(
        (m, N_STATES, N_STATES))
    P1, P2, x1, x2 = map(kernels.address, arrays)
    if cycle_kernel().fieldlog_dkf_fuse(m, P1, P2, None if P12 is None else kernels.address(P12), x1, x2,
                                        kernels.address(x), kernels.address(P),
                                        None if Pe is None else kernels.address(Pe)):
        raise np.linalg.LinAlgError("Matrix is not positive definite: a local or fused covariance")
    return x, P, Pe
