"""Square-root cubature Kalman filters of the adaptive SSR-SCKF paper: ``sckf`` (its baseline) and ``ssr-sckf``.

Both are :class:`fusion.ukf.CycleFilter` s (the shared KalmanFilter interface, closed loop: the engine feeds
the estimate back into the INS and resets x after each update) carrying the covariance as a square-root
factor S (P = S S^T). At every filter cycle (10 Hz), with or without GPS as in the paper, the time update
takes the cubature points x + S xi_j of the rule, integrates each by RK4 through the nonlinear SINS error
model with the navigation solution at the cycle's start, middle and end (``fusion.ukf.propagate_points``,
the hybrid KF/UKF's model and nodes), and re-factors the weighted centred points and sqrt(Q) by QR::

    x- = sum_j w_j X_j,   S- = tria([sqrt(w_j) (X_j - x-) ..., sqrt(Q)])      (tria: R^T of qr(A^T))

Q is the cycle's discrete Q (additive, linearised at x = 0 as in the KF). Phi is not used.

======== ============================================ ====================== ==============================
method   points (n = 15)                              measurement update     R
======== ============================================ ====================== ==============================
sckf     third-degree spherical-radial (eq. 12):     cubature points again  the nominal R of the fix
         +-sqrt(n) e_i, w = 1/(2n): 2n = 30           (eq. 13): 30 points
ssr-sckf spherical simplex-radial: +-sqrt(n) a_i      SVD, no points         moving-window estimate
         (a_i the n + 1 simplex vertices of eq. 14),  (eqs. 16-21)           (eqs. 22-25)
         w = 1/(2(n+1)): 2(n+1) = 32
======== ============================================ ====================== ==============================

Per GPS epoch that is 60 points for sckf and 32 for ssr-sckf: the paper's Table 1 (60 and 32). So the SSR
rule has 2(n+1) points, not the n + 1 vertices alone (those are a degree-2 rule). Both rules are exact for
all polynomials of degree <= 3 against the Gaussian and not for degree 4 (tests/test_sckf.py); for a linear
measurement both measurement updates equal the KF's.

SVD update (eqs. 16-21), with S_R a square root of R::

    U, D = svd([H S-, S_R]);  P_zz = U D^2 U^T;  P_xz = S- (H S-)^T;  G = P_xz U D^-2 U^T
    x = x- + G (z - H x-);    S = tria([S- - G H S-, G S_R])

Singular values below 1e-12 of the largest are dropped from D^-2 (pseudo-inverse): the "no interruption when
the innovation covariance is not invertible" of the paper.

Adaptive R (eqs. 22-25, :class:`MovingWindowR`): each GPS row is one of six channels (position E, N, U,
velocity E, N, U: the unit column of its H). Per epoch the innovation y = z - H x- and the diagonal of
D = y y^T - H P- H^T, divided by the nominal variance of that epoch (the receiver's reported covariance,
which changes epoch by epoch in a city), are kept for the last ``window`` epochs (20 by default, 20 s at 1 Hz).
An epoch's R comes from the window of the epochs before it (the paper's k > N; the nominal R until the
window is full, or when fewer than half its epochs have all the current channels), so its gain does not
depend on its own innovation. Each channel's ratio is the window mean, and R is the current nominal R with
each variance scaled by its ratio. With a constant nominal R this is eq. 24's window mean. Three departures
from the paper, each compared against it (docs/results.md, "Fusion"):

- eq. 24 estimates the full matrix; we estimate only the diagonal, because the GPS channels' noises are
  independent in the measurement model and 20 epochs cannot estimate the 15 correlations: the spurious
  correlations cost position accuracy even with constant noise.
- eq. 24 replaces R by the window mean; we scale the receiver's per-epoch R, so a receiver that reports its
  degradation (urban canyon, few satellites) keeps that information.
- the ratio is floored at ``floor``, by default 1: R is only ever inflated above the receiver's figure.
  Innovations see only the part of the GPS error that is white over the window; the time-correlated part
  (multipath, atmosphere; the larger part for a real receiver, and in the ``urban`` scenario) is absorbed in
  the state and is invisible to them, so the window estimate falls below the reported variance (to 0.1 of it
  on urban) and the filter then over-trusts the GPS, worse than ``sckf`` in the outages that follow. A floor
  below 1 also covers eq. 25's Cholesky failing (a negative ratio).

Only GPS updates (the receiver's rows, ``update_batch``) feed and use the window; another aid through ``update(z, H, R)`` keeps
its own R.

Slips of the paper, fixed here:

- eq. 12: the second half of the points is x - sqrt(n P) e_i (printed with +).
- eq. 13 is not the simplex-radial points it introduces but the SCKF's QR measurement update of S (with
  the centred points X' and Z); we use it as such for ``sckf``. The points themselves are +-sqrt(n) a_i with
  eq. 14's a_i, per Table 1's 32 points (the spherical simplex-radial rule of Wang, Feng and Tse, IEEE SPL
  2014). Eq. 14 itself is right: unit vectors, summing to zero, sum a_i a_i^T = (n+1)/n I.
- Sec. 3.2: "the initialization module and measured update module are the same as the SCKF except the
  sampling rules": it is the time update that uses the new rule; the measurement update is the SVD one.
- eq. 23 names the innovation covariance R_v and writes R_k = S_k S_k^T: it is R_y, and R_k = S_R S_R^T.
- eq. 24 sums j = 0..N (N + 1 terms) and divides by N: we average the last N epochs.
- eq. 25 subtracts the current H P- H^T from a window mean of y y^T, biased whenever P changed inside the
  window (after an outage or at the start the window's early innovations carry the large P of their time and
  inflate R for N epochs); we subtract each epoch's own H P- H^T (eq. 23 holds per epoch). Equal to the
  paper's in steady state. Eq. 25 also gives no rule for an indefinite estimate: the floor above.
- eq. 24's full-matrix estimate of R itself: the diagonal, as a scale on the reported R, above.
- eq. 4: a_12 = cos phi_N sin phi_U + sin phi_E sin phi_N cos phi_U (printed with -, the matrix is then not
  orthogonal). We do not use eqs. 1-5: the nonlinear model is ``fusion.ukf.error_rates`` (the hybrid KF/UKF
  paper's, Euler errors in the X-Y-Z sequence instead of this paper's Z-X-Y one; both are I - [phi x] to first
  order, so the closed-loop feedback is the KF's).
- eq. 5: omega_en^n = [-v_N / (R_M + h), v_E / (R_N + h), v_E tan L / (R_N + h)] (its second component is
  printed with tan L), and the first component of d-omega_en is -dv_N / (R_M + h) + v_N dh / (R_M + h)^2
  (printed with +dv_N). ``error_rates`` differences the exact rates, so it is not affected.
- Sec. 4: the initial position error is (10, 10, 10) m, not m/s.
"""

from __future__ import annotations

import numpy as np

from fieldlog.fusion import kf, ukf
from fieldlog.fusion.errmodel import N_STATES

Rule = tuple[np.ndarray, np.ndarray]  # unit points xi (m, n) (point j = x + S xi_j), weights w (m,)
_PINV_RTOL = 1e-12


def simplex_vertices(n: int) -> np.ndarray:
    """Eq. 14: the n + 1 vertices a_i (rows, (n+1, n)) of the regular simplex on the unit sphere in R^n.

    Parameters
    ----------
    n : int, state dimension (>= 1)

    Returns
    -------
    (n+1, n) ndarray
        Unit vectors a_i summing to zero.
    """
    i = np.arange(1, n + 2)[:, None]
    j = np.arange(1, n + 1)[None, :]
    below = -np.sqrt((n + 1) / (n * (n - j + 2) * (n - j + 1)))
    diag = np.sqrt((n + 1) * (n - j + 1) / (n * (n - j + 2)))
    return np.where(j < i, below, np.where(j == i, diag, 0.0))


def spherical_radial_rule(n: int) -> Rule:
    """Third-degree spherical-radial rule (eq. 12): +-sqrt(n) e_i, weights 1/(2n); 2n points.

    Parameters
    ----------
    n : int, state dimension (>= 1)

    Returns
    -------
    xi : (m, n) ndarray, unit points (point j = x + S xi_j)
    w : (m,) ndarray, weights (sum to one)
    """
    e = np.sqrt(n) * np.eye(n)
    return np.concatenate([e, -e]), np.full(2 * n, 0.5 / n)


def simplex_radial_rule(n: int) -> Rule:
    """Spherical simplex-radial rule: +-sqrt(n) a_i with eq. 14's vertices, weights 1/(2(n+1)); 2(n+1) points.

    Parameters
    ----------
    n : int, state dimension (>= 1)

    Returns
    -------
    Rule
        As :func:`spherical_radial_rule`, 2(n+1) points.
    """
    a = np.sqrt(n) * simplex_vertices(n)
    return np.concatenate([a, -a]), np.full(2 * (n + 1), 0.5 / (n + 1))


def tria(A: np.ndarray) -> np.ndarray:
    """Lower-triangular square root of A A^T (A (n, k), k >= n): R^T of the QR decomposition of A^T.

    Parameters
    ----------
    A : (n, k) ndarray, k >= n

    Returns
    -------
    (n, n) ndarray
        Lower-triangular L with L L^T = A A^T.
    """
    return np.linalg.qr(A.T, mode="r").T


def psd_sqrt(M: np.ndarray) -> np.ndarray:
    """A square root L of a symmetric positive semi-definite M (L L^T = M): Cholesky, or the eigen-decomposition
    with negative (rounding) eigenvalues set to zero when Cholesky fails.

    Parameters
    ----------
    M : (n, n) ndarray, symmetric positive semi-definite

    Returns
    -------
    (n, n) ndarray
        L with L L^T = M (to rounding), in the units of the square root of M.
    """
    try:
        return np.linalg.cholesky(M)
    except np.linalg.LinAlgError:
        w, V = np.linalg.eigh(0.5 * (M + M.T))
        return V * np.sqrt(np.maximum(w, 0.0))


def time_update(X: np.ndarray, w: np.ndarray, SQ: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Square-root cubature time update: propagated points X (m, n), weights w (m,) (all positive), sqrt(Q) SQ
    (n, n) -> (x-, S-) with S- S-^T = sum w_j (X_j - x-)(X_j - x-)^T + Q.

    Parameters
    ----------
    X : (m, n) ndarray, propagated cubature points, ``fusion.errmodel`` order and units
    w : (m,) ndarray, positive weights summing to one
    SQ : (n, n) ndarray, a square root of the discrete process noise Q

    Returns
    -------
    x : (n,) ndarray, predicted mean x-
    S : (n, n) ndarray, lower-triangular square root S- of the predicted covariance
    """
    x = w @ X
    Xc = np.sqrt(w)[:, None] * (X - x)
    return x, tria(np.hstack([Xc.T, SQ]))


def cubature_update(x: np.ndarray, S: np.ndarray, rule: Rule, z: np.ndarray, H: np.ndarray, SR: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """SCKF measurement update through the cubature points (eq. 13), linear h(x) = H x: (x, S) after it.
    x (n,), S (n, n) predicted; z (m,), H (m, n), SR (m, m) a square root of R.

    Parameters
    ----------
    x : (n,) ndarray, predicted error state (``fusion.errmodel`` order and units)
    S : (n, n) ndarray, square root of the predicted covariance, S S^T = P-
    rule : Rule, unit points and weights of the cubature rule
    z : (m,) ndarray, measurement (INS minus aid; m, m/s by kind)
    H : (m, n) ndarray, measurement matrix
    SR : (m, m) ndarray, a square root of R, units of z

    Returns
    -------
    x : (n,) ndarray, updated error state
    S : (n, n) ndarray, lower-triangular square root of the updated covariance
    """
    xi, w = rule
    X = x + xi @ S.T
    Z = X @ H.T
    sw = np.sqrt(w)[:, None]
    xm, zm = w @ X, w @ Z
    Xc, Zc = sw * (X - xm), sw * (Z - zm)
    Szz = tria(np.hstack([Zc.T, SR]))
    G = np.linalg.solve(Szz @ Szz.T, Zc.T @ Xc).T  # P_xz P_zz^-1
    return xm + G @ (z - zm), tria(np.hstack([(Xc - Zc @ G.T).T, G @ SR]))


def svd_update(x: np.ndarray, S: np.ndarray, z: np.ndarray, H: np.ndarray, SR: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """Linear measurement update by SVD (eqs. 16-21): (x, S) after it. Arguments as :func:`cubature_update`.

    Parameters
    ----------
    x, S, z, H, SR : as :func:`cubature_update`

    Returns
    -------
    x, S : as :func:`cubature_update`
    """
    HS = H @ S
    U, d, _ = np.linalg.svd(np.hstack([HS, SR]), full_matrices=False)
    keep = d > _PINV_RTOL * d[0]
    inv_d2 = np.where(keep, 1.0 / np.where(keep, d, 1.0) ** 2, 0.0)
    G = (S @ HS.T) @ (U * inv_d2) @ U.T
    return x + G @ (z - H @ x), tria(np.hstack([S - G @ HS, G @ SR]))


def channels(H: np.ndarray) -> np.ndarray:
    """GPS channel of each measurement row (m,): 0-2 position E, N, U, 3-5 velocity E, N, U.

    Parameters
    ----------
    H : (m, 15) ndarray, GPS measurement matrix (one unit entry in columns 0-5 per row)

    Returns
    -------
    (m,) int ndarray
        Channel of each row.
    """
    return np.argmax(np.abs(H[:, 0:6]), axis=1)


class MovingWindowR:
    """Moving-window estimate of the GPS measurement noise R (eqs. 22-25), per channel (module docstring).
    window: epochs; floor: lowest variance relative to the nominal R (1: inflate only)."""

    def __init__(self, window: int = 20, floor: float = 1.0) -> None:
        if window < 2 or not 0.0 < floor <= 1.0:
            raise ValueError(f"window must be >= 2 and floor in (0, 1], got {window}, {floor}")
        self.window, self.floor = window, floor
        self._d = np.full((window, 6), np.nan)  # ring of diag(y y^T - H P- H^T) / diag(R_nom), NaN off its channels
        self.epochs = 0  # epochs pushed
        self.floored = 0  # estimates that needed the floor

    def push(self, ch: np.ndarray, y: np.ndarray, HPH: np.ndarray, R_nom: np.ndarray) -> None:
        """One epoch: its rows' channels (m,), innovation y = z - H x- (m,), H P- H^T (m, m) and the nominal R
        (m, m) the receiver reported.

        Parameters
        ----------
        ch : (m,) int ndarray, channel of each row (:func:`channels`)
        y : (m,) ndarray, innovation z - H x-, m or m/s by channel
        HPH : (m, m) ndarray, H P- H^T, units of y squared
        R_nom : (m, m) ndarray, nominal R reported by the receiver, units of y squared
        """
        D = self._d[self.epochs % self.window]
        D.fill(np.nan)
        D[ch] = (y * y - np.diag(HPH)) / np.diag(R_nom)
        self.epochs += 1

    def estimate(self, ch: np.ndarray, R_nom: np.ndarray) -> np.ndarray:
        """R (m, m) for rows of channels ch: R_nom with each channel's variance scaled by its window mean ratio
        of measured to nominal variance, floored at ``floor`` (correlations of R_nom kept); R_nom itself until
        the window is full or when fewer than half its epochs have all these channels.

        Parameters
        ----------
        ch : (m,) int ndarray, channel of each row (:func:`channels`)
        R_nom : (m, m) ndarray, nominal R of this epoch, m^2 or (m/s)^2 by channel

        Returns
        -------
        (m, m) ndarray
            The R to use, units of R_nom.
        """
        if self.epochs < self.window:
            return R_nom
        block = self._d[:, ch]
        have = np.isfinite(block).all(axis=1)
        if 2 * have.sum() < self.window:
            return R_nom
        ratio = block[have].mean(axis=0)
        if ratio.min() < self.floor:
            self.floored += 1
            ratio = np.maximum(ratio, self.floor)
        s = np.sqrt(ratio)
        return R_nom * np.outer(s, s)


class CubatureKF(ukf.CycleFilter):
    """Square-root cubature KF on the 15-state error with the nonlinear time update (module docstring).

    P0, q, q_scale as :class:`fusion.kf.KalmanFilter`; rule the cubature points; svd: the SVD measurement update
    (else the cubature points' one); adaptive: a :class:`MovingWindowR`, or None for the nominal R.
    ``R`` is the measurement noise covariance used at the last update.
    """

    def __init__(self, P0: np.ndarray, q: np.ndarray, rule: Rule, svd: bool, adaptive: MovingWindowR | None,
                 q_scale: float = 1.0) -> None:
        super().__init__(P0, q, q_scale)
        self.rule, self.svd, self.adaptive = rule, svd, adaptive
        self.R = np.zeros((0, 0))

    @property
    def P(self) -> np.ndarray:
        """Error covariance S S^T (15, 15)."""
        return self.S @ self.S.T

    @P.setter
    def P(self, P: np.ndarray) -> None:
        """Set the covariance through its square root S (:func:`psd_sqrt`).

        Parameters
        ----------
        P : (15, 15) ndarray, error covariance, ``fusion.errmodel`` units squared
        """
        self.S = psd_sqrt(np.asarray(P, dtype=float))

    def propagate(self, Phi: np.ndarray, Q: np.ndarray) -> np.ndarray:
        """Cubature time update through the nonlinear model over the queued cycles (Phi unused); diag(P) after
        each cycle (m, 15).

        Parameters
        ----------
        Phi, Q : (m, 15, 15) ndarray, as :meth:`fusion.kf.KalmanFilter.propagate`

        Returns
        -------
        (m, 15) ndarray, diag(S S^T) after each cycle's cubature time update.
        """
        cycles = self.take(len(Phi))
        xi, w = self.rule
        out = np.empty((len(Phi), N_STATES))
        for i in range(len(Phi)):
            X = ukf.propagate_points(self.x, self.S, xi, cycles[i:i + 1])
            self.x, self.S = time_update(X, w, psd_sqrt(self.q_scale * Q[i]))
            out[i] = np.einsum("ij,ij->i", self.S, self.S)
        return out

    def update_batch(self, obs: list[kf.Observation]) -> None:
        """The observations stacked as :meth:`fusion.kf.KalmanFilter.update_batch`; with the window R if adaptive
        and every row is the receiver's (a GPS update).

        Parameters
        ----------
        obs : list of kf.Observation, the epoch's observations (z, H, R each), in order
        """
        m = kf.stack(*(o.m for o in obs))
        if m is not None:
            self._update(*m, self.adaptive is not None and all(o.receiver for o in obs))

    def update(self, z: np.ndarray, H: np.ndarray, R: np.ndarray) -> np.ndarray:
        """Measurement update with R as given (a non-GPS aid: not part of the GPS window). Returns the change of
        the estimate (15,).

        Parameters
        ----------
        z, H, R : as :meth:`fusion.kf.KalmanFilter.update` (z (m,), H (m, 15), R (m, m))

        Returns
        -------
        (15,) ndarray, the change of the estimate, ``fusion.errmodel`` order and units.
        """
        return self._update(z, H, R, False)

    def _update(self, z: np.ndarray, H: np.ndarray, R: np.ndarray, adapt: bool) -> np.ndarray:
        if adapt:
            HS = H @ self.S
            ch = channels(H)
            R_nom = R
            R = self.adaptive.estimate(ch, R_nom)
            self.adaptive.push(ch, z - H @ self.x, HS @ HS.T, R_nom)
        self.R = R
        SR = psd_sqrt(R)
        x0 = self.x
        if self.svd:
            self.x, self.S = svd_update(self.x, self.S, z, H, SR)
        else:
            self.x, self.S = cubature_update(self.x, self.S, self.rule, z, H, SR)
        return self.x - x0


def sckf(P0: np.ndarray, q: np.ndarray) -> CubatureKF:
    """The paper's baseline SCKF: spherical-radial points, cubature measurement update, nominal R.

    Parameters
    ----------
    P0 : (15, 15) ndarray, initial error covariance, ``fusion.errmodel`` units squared
    q : (12, 12) ndarray, noise PSD (``errmodel.noise_psd``)

    Returns
    -------
    CubatureKF
    """
    return CubatureKF(P0, q, spherical_radial_rule(N_STATES), svd=False, adaptive=None)


def ssr_sckf(P0: np.ndarray, q: np.ndarray) -> CubatureKF:
    """The adaptive SSR-SCKF: simplex-radial points, SVD measurement update, moving-window R.

    Parameters
    ----------
    P0, q : as :func:`sckf`

    Returns
    -------
    CubatureKF
    """
    return CubatureKF(P0, q, simplex_radial_rule(N_STATES), svd=True, adaptive=MovingWindowR())

