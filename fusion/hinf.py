"""The H-infinity filter of the KF-versus-H-infinity paper (eqs. 20-26) on the shared filter interface.

The paper's recursion (eq. 26, one-step predictor form, A = Phi, C = H, B B^T = Q, D D^T = R)::

    H_k     = P_k^-1 - L^T L / gamma^2
    K_k     = A H_k^-1 C^T (D D^T + C H_k^-1 C^T)^-1
    P_{k+1} = (A - K_k C) H_k^-1 (A - K_k C)^T + (B - K_k D)(B - K_k D)^T

is the Kalman filter run on Pbar = H_k^-1 = (P^-1 - gamma^-2 L^T L)^-1 instead of P: its gain is A times
the KF gain computed with Pbar, and its P_{k+1} is the Joseph-form KF update of Pbar followed by the KF
prediction (B D^T = 0). So :class:`HInfinityFilter` is :class:`fusion.kf.KalmanFilter` (same predict,
same closed loop) whose measurement update first inflates P to Pbar. As gamma -> infinity Pbar -> P: the
Kalman filter. (The paper's text says "when gamma -> 0, H_k -> P^-1, the filter is transformed into the
Kalman filter": a slip, it is gamma -> infinity, as its own next sentence says.)

L (eq. 20, z = L x, the combination of states to be estimated) defaults to the position and velocity
error (the paper estimates "the speed and position error"); gamma is then in metres / (m/s) of those.

Existence: the paper's form inverts H_k and uses H_k^-1 as a covariance, so it needs
H_k = P^-1 - gamma^-2 L^T L > 0, i.e. gamma^2 > lambda_max(S^T L^T L S) with P = S S^T. That is the
condition checked here, at every update; a smaller gamma raises :class:`GammaTooSmall` naming the bound.
It is stricter than the general H-infinity existence condition P^-1 - gamma^-2 L^T L + H^T R^-1 H > 0
(Simon, Optimal State Estimation, sec. 11.3), which it implies.

The bound grows with P, so during a long GPS outage any fixed gamma is eventually too small (even a large
one, with a MEMS IMU). The paper gives no rule for choosing gamma. Two
policies: ``min_ratio = 0`` keeps gamma fixed and raises; ``min_ratio = c > 1`` (the engine's default,
``[fusion] hinf_min_ratio``) uses gamma_k = max(gamma, c * bound_k) at each update, i.e. the
filter is never closer to its existence limit than c, and moves towards the KF (gamma -> infinity) when
the covariance is large. ``raised`` counts the epochs where gamma_k > gamma. The inflation is applied once per
epoch (the first update after a propagation), not again for each measurement of the epoch.

What ran: ``gamma_run`` the smallest and largest gamma_k used, ``worst_inflation`` the largest factor by which Pbar
exceeded P along any direction, 1 / (1 - (bound_k / gamma_k)^2), over the drive. Close to 1 the filter is the
Kalman filter (:func:`summary` says so): the paper's gamma = 3 (units of position metres) lies below the bound
wherever the position sigma exceeds 3 m, and a gamma far above the bound inflates nothing.
"""

from __future__ import annotations

import numpy as np

from fieldlog.fusion.errmodel import N_STATES
from fieldlog.fusion.kf import KalmanFilter


PAPER_GAMMA = 3.0  # the KF-versus-H-infinity paper's gamma (its section 4)


class GammaTooSmall(ValueError):
    """gamma below the existence bound of the H-infinity filter at this step."""


def position_velocity_weights() -> np.ndarray:
    """Default L (6, 15): picks the position (m) and velocity (m/s) errors.

    Returns
    -------
    (6, 15) ndarray, [I 0]: z = L x is the position error (ENU, m) then the velocity error (ENU, m/s).
    """
    L = np.zeros((6, N_STATES))
    L[:, 0:6] = np.eye(6)
    return L


def existence_bound(P: np.ndarray, L: np.ndarray) -> float:
    """Smallest gamma for which H_k = P^-1 - gamma^-2 L^T L is positive definite: sqrt(lambda_max(S^T L^T L S)).

    Parameters
    ----------
    P : (15, 15) ndarray, error covariance (``fusion.errmodel`` order and units), positive definite
    L : (p, 15) ndarray, the estimated combination z = L x (e.g. :func:`position_velocity_weights`)

    Returns
    -------
    float
        The bound, in the units of z (m and m/s for the default L).
    """
    S = np.linalg.cholesky(P)
    LS = L @ S
    return float(np.sqrt(max(np.linalg.eigvalsh(LS.T @ LS)[-1], 0.0)))


class HInfinityFilter(KalmanFilter):
    """H-infinity filter (paper eq. 26) with performance bound gamma; L (p, 15) the estimated combination
    (default :func:`position_velocity_weights`). P0, q, q_scale as :class:`fusion.kf.KalmanFilter`."""

    def __init__(self, P0: np.ndarray, q: np.ndarray, gamma: float, L: np.ndarray | None = None,
                 q_scale: float = 1.0, min_ratio: float = 0.0) -> None:
        super().__init__(P0, q, q_scale)
        if not gamma > 0.0:
            raise ValueError(f"gamma must be > 0, got {gamma}")
        if min_ratio != 0.0 and not min_ratio > 1.0:
            raise ValueError(f"min_ratio must be 0 (fixed gamma) or > 1, got {min_ratio}")
        self.gamma = float(gamma)
        self.min_ratio = float(min_ratio)
        self.raised = 0
        self._inflate = True
        self.L = position_velocity_weights() if L is None else np.asarray(L, dtype=float)
        self.gamma_run = (np.inf, 0.0)  # smallest, largest gamma_k used
        self.worst_inflation = 1.0  # largest factor of Pbar over P along any direction
        self.epochs = 0
        self.paper_exists = 0  # epochs where the paper's gamma lay above the existence bound

    def inflated(self) -> np.ndarray:
        """Pbar = H_k^-1 = (P^-1 - gamma_k^-2 L^T L)^-1 (15, 15); raises GammaTooSmall if H_k is not > 0
        (fixed gamma only).

        Returns
        -------
        (15, 15) ndarray, Pbar, symmetric, ``fusion.errmodel`` order and units squared; gamma_k is gamma, or
        ``min_ratio`` times the existence bound when that is larger.
        """
        S = np.linalg.cholesky(self.P)
        LS = self.L @ S
        lt_l = LS.T @ LS  # S^T L^T L S; the bound is sqrt of its largest eigenvalue
        gamma = self.gamma
        bound = float(np.sqrt(max(np.linalg.eigvalsh(lt_l)[-1], 0.0)))
        self.paper_exists += bound < PAPER_GAMMA
        if self.min_ratio:
            if self.min_ratio * bound > gamma:
                gamma = self.min_ratio * bound
                self.raised += 1
        w, V = np.linalg.eigh(np.eye(N_STATES) - lt_l / gamma ** 2)  # S^T H_k S
        if w[0] <= 0.0:
            bound = gamma * np.sqrt(1.0 - w[0])
            raise GammaTooSmall(f"H-infinity gamma={gamma:g} is below the existence bound {bound:.4g} at this "
                                f"step (P^-1 - gamma^-2 L^T L must be positive definite); use a larger gamma")
        self.gamma_run = (min(self.gamma_run[0], gamma), max(self.gamma_run[1], gamma))
        self.worst_inflation = max(self.worst_inflation, 1.0 / float(w[0]))
        self.epochs += 1
        SV = S @ V
        Pbar = (SV / w) @ SV.T
        return 0.5 * (Pbar + Pbar.T)

    def propagate(self, Phi: np.ndarray, Q: np.ndarray) -> np.ndarray:
        """``KalmanFilter.propagate``; the next update inflates P again (a new epoch).

        Parameters
        ----------
        Phi, Q : (m, 15, 15) ndarray, as :meth:`fusion.kf.KalmanFilter.propagate`

        Returns
        -------
        (m, 15) ndarray, diag(P) after each cycle (P, not the inflated Pbar).
        """
        self._inflate = True
        return super().propagate(Phi, Q)

    def update(self, z: np.ndarray, H: np.ndarray, R: np.ndarray) -> np.ndarray:
        """H-infinity measurement update: the KF update (Joseph form) of Pbar. Returns K (z - H x) (15,).

        P is inflated to Pbar once per epoch, at its first update (the vehicle aid or the GPS): eq. 26 has one
        H_k per step, and the updates of one epoch are the parts of that step's measurement.

        Parameters
        ----------
        z, H, R : as :meth:`fusion.kf.KalmanFilter.update` (z (m,), H (m, 15), R (m, m))

        Returns
        -------
        (15,) ndarray, K (z - H x) with the gain of Pbar, ``fusion.errmodel`` order and units.

        Raises
        ------
        GammaTooSmall
            With a fixed gamma (``min_ratio = 0``) below the existence bound at this epoch.
        """
        if self._inflate:
            self.P = self.inflated()
            self._inflate = False
        return super().update(z, H, R)


KF_EQUAL_INFLATION = 1.01  # Pbar within 1 % of P along every direction: the update is the Kalman filter's


def summary(f: HInfinityFilter) -> dict[str, str]:
    """What gamma ran, as the fused file's ``fusion.hinf`` metadata record and ``fieldlog fuse``'s line:
    ``gamma`` (configured), ``min_ratio``, ``gamma_run_min``/``_max``, ``raised``, ``epochs``,
    ``worst_inflation``, ``paper_gamma_exists`` (epochs where gamma = 3 lay above the bound) and ``note``: whether the filter equalled ``kf`` on this drive.

    Parameters
    ----------
    f : HInfinityFilter, the filter after the drive

    Returns
    -------
    dict[str, str]
        The record's fields, values as text.
    """
    lo, hi = f.gamma_run if f.epochs else (f.gamma, f.gamma)
    same = f.worst_inflation < KF_EQUAL_INFLATION
    note = (f"gamma {lo:.3g}..{hi:.3g} ran (configured {f.gamma:g}, raised at {f.raised} of {f.epochs} epochs); "
            f"P inflated at most {f.worst_inflation:.3f}x: "
            + ("equal to kf here (the H-infinity term is negligible at this gamma)" if same else
               "differs from kf (the H-infinity term inflates P)")
            + f"; the paper's gamma {PAPER_GAMMA:g} exists at {f.paper_exists} of {f.epochs} epochs")
    return {"gamma": repr(f.gamma), "min_ratio": repr(f.min_ratio), "gamma_run_min": repr(float(lo)),
            "gamma_run_max": repr(float(hi)), "raised": str(f.raised), "epochs": str(f.epochs),
            "worst_inflation": repr(float(f.worst_inflation)), "equals_kf": str(same).lower(),
            "paper_gamma_exists": str(f.paper_exists), "note": note}
