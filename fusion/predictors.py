"""Outage predictors of the distributed-KF paper (sections 2.2-2.3): six SISO RBF networks, the TDLN, and
the training history that feeds them from the fusion loop.

Networks (pure numpy, one per channel, fitted in batch on a window of GPS epochs):

- :class:`Rbfn`, eq. 6: y = sum_i w_i exp(-((x - c_i) / s_i)^2 / 2), no bias term. The input is
  normalised within the window (mean, std); centres by k-means on it (``scipy.cluster.vq.kmeans2``,
  k-means++ start, fixed seed); width s_i = the distance from c_i to its nearest other centre times
  ``width_scale`` (2); output weights by batch least squares with a ridge chosen by generalised
  cross-validation (:func:`ridge_solve`). Without a bias term
  (as eq. 6) the output decays to zero for inputs far outside the training window: the correction
  then falls back to none, i.e. to the plain KF.
- :class:`Tdln`: a linear network with a tapped delay line on its input,
  y_n = b + sum_{j<taps} w_j x_{n-j}, taps = 200 as in the paper, least squares on the window with a
  ridge chosen by generalised cross-validation: with 200 taps the window often holds fewer epochs than
  weights, and an unregularised (minimum-norm) fit extrapolates wildly as soon as the INS input leaves
  the training range.
  Before the line is full it is padded with the oldest input.

Channels: inputs INS east, north, up position and vE, vN, vU; each network maps one input to the target
of the same component. The positions are given in metres from a fixed origin: an affine map of the
paper's longitude, latitude, altitude, which the window normalisation removes anyway.

How the paper maps onto our closed-loop filter
----------------------------------------------
The paper (eq. 7) splits a KF's estimate into the state prediction X(n|n-1) and the innovation
component dX(n) = K(n) nu(n). Our filters (``fusion.kf``, ``fusion.dkf``) are closed loop: after every
GPS epoch the estimate is fed into the INS and the biases and the error state is reset, so
X(n|n-1) = Phi X(n-1|n-1) is identically zero. Its role, carrying the estimated attitude and bias errors
forward through the dynamics of F, is played by the corrected INS itself (the fed-back estimate makes
the INS evolve as the open-loop estimate Phi X would predict, to first order). Hence:

- the KF prediction alone is ``dkf`` during the outage (the free INS with the fed-back biases);
- eq. 7 in closed loop: the correction actually applied at a GPS epoch is dX(n) = x(n|n), the
  innovation component. ``dkf-rbfn`` trains its six networks on the position and velocity components of
  that applied correction, and during an outage applies the predicted components at each GPS epoch
  time (each epoch that is unusable or withheld) as a correction of the INS (``fusion.kf.correct_ins``);
  the error state stays zero and the covariance is untouched (a prediction is not a measurement).
  0 + predicted dX is exactly eq. 7's "state prediction plus predicted innovation".
- ``rbfn`` and ``tdln``, the predictors alone (section 2.2): their targets are "the errors between INS
  positions & velocities and GPS positions & velocities", i.e. the observations z = INS - GPS of KF_II
  (position) and KF_I (velocity) at the epoch, before correction. During an outage the predicted z is
  subtracted from the INS in full at each epoch (gain 1), with no KF involved.

Consequence, worth knowing when reading the results: in a closed loop, z is the error grown since the
last correction plus GPS noise. In steady state a systematic drift d per epoch gives E[z] = d / K and
E[K z] = d, so the full-gain ``rbfn``/``tdln`` correction over-corrects a systematic drift by a factor
1/K, and carries the GPS noise of z at full weight; the hybrid's target already has the gain (the KF's
dynamics) in it. In the paper, the predictors alone seem to correct a free-running INS (Table 3:
altitude errors of kilometres), where z is the whole INS error; we do not reproduce that set-up, since
the free INS is our ``ins`` method.

Where the paper is ambiguous
----------------------------
- The six networks predict 6 numbers: the velocity components of KF_I's innovation component and the
  position components of KF_II's. Eqs. 3-4 then need whole 15-state local estimates and the covariances
  an update would have produced; neither exists during an outage. With our information sharing
  (``fusion.dkf``) the fused correction equals the centralised K nu, so we learn the position and
  velocity components of the fused (applied) correction directly; attitude and biases get no predicted
  correction (the paper predicts none either: "particularly referred to the position errors and velocity
  errors").
- The rate: targets exist at the GPS epochs (1 Hz); the paper holds GPS values between epochs ("the GPS
  signals maintained the latest receiving values"), which suggests networks run at the IMU rate on
  zero-order-held targets. We train and predict at the GPS epochs only: held targets add no information.
  A 200-step delay is then 200 s of input history (0.4 s at 500 Hz in the paper's reading).
- Window length, number of centres, widths and regularisation are not given; ours are in
  :class:`PredictorConfig`.
- Training "in real time while GPS is good": batch least squares has no memory, so refitting on the
  sliding window at every epoch and using the last fit equals fitting once, on the window, at the
  first epoch of an outage. We do the latter (6 k-means and solves per outage, not per second). The
  epochs within ``settle_s`` after the filter starts or GPS returns are left out of training: their
  corrections are the reconvergence from the previous outage, not a function of the INS state.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from scipy.cluster.vq import kmeans2

N_CHANNELS = 6  # position E, N, U (m), velocity E, N, U (m/s)
_STD_FLOOR = 1e-3  # m or m/s: a constant input is not stretched into noise


@dataclass
class PredictorConfig:
    """Predictor settings (not given by the paper: see the module docstring)."""

    window: int = 300  # training epochs kept (GPS epochs, s at 1 Hz)
    min_train: int = 30  # fewer training epochs in the window: no prediction (the plain KF bridges)
    settle_s: float = 20.0  # epochs this long after the filter starts or GPS returns are not trained on
    centres: int = 10  # Gaussian units per RBFN
    width_scale: float = 2.0  # Gaussian width / nearest-centre spacing (1 leaves a ripple of a few %)
    taps: int = 200  # TDLN delay line
    ridge: float | None = None  # relative to the mean diagonal of the normal matrix; None: by GCV
    seed: int = 0  # k-means++ start


def _normaliser(x: np.ndarray) -> tuple[float, float]:
    return float(np.mean(x)), max(float(np.std(x)), _STD_FLOOR)


RIDGE_GRID = 10.0 ** np.arange(-12.0, 2.0)  # relative ridges tried by generalised cross-validation


def ridge_solve(A: np.ndarray, y: np.ndarray, ridge: float | None = None) -> tuple[np.ndarray, float]:
    """argmin |A w - y|^2 + lam |w|^2 with lam = ridge * mean(diag(A^T A)); returns (w, ridge).

    ridge None: chosen from ``RIDGE_GRID`` by generalised cross-validation, GCV = n RSS / (n - tr H)^2
    (Golub, Heath & Wahba), all candidates from one SVD of A."""
    U, s, Vt = np.linalg.svd(A, full_matrices=False)
    scale = max(float(np.sum(s * s)) / A.shape[1], 1e-300)
    grid = RIDGE_GRID if ridge is None else np.array([ridge])
    f = s * s / (s * s + grid[:, None] * scale)  # filter factors (g, r)
    Uy = U.T @ y
    if len(grid) > 1:
        n = len(y)
        rss = np.sum((f * Uy) ** 2 - 2.0 * f * Uy ** 2, axis=1) + float(y @ y)
        dof = np.maximum(n - f.sum(axis=1), 1e-9)
        best = int(np.argmin(n * np.maximum(rss, 0.0) / dof ** 2))
    else:
        best = 0
    return Vt.T @ (f[best] / s * Uy), float(grid[best])


def kmeans_centres(x: np.ndarray, k: int, seed: int = 0) -> np.ndarray:
    """Sorted distinct 1-D k-means centres (at most k) of samples x (n,)."""
    x = np.asarray(x, dtype=float)
    k = max(1, min(k, len(np.unique(x))))
    c, _ = kmeans2(x[:, None], k, minit="++", rng=np.random.default_rng(seed))
    c = np.sort(c[:, 0])
    keep = np.concatenate([[True], np.diff(c) > 1e-9 * max(1.0, float(np.ptp(x)))])
    return c[keep]


def rbf_design(x: np.ndarray, c: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Gaussian unit outputs (eq. 5) for inputs x (n,), centres c (l,), widths s (l,): (n, l)."""
    return np.exp(-0.5 * ((np.asarray(x, float)[:, None] - c) / s) ** 2)


class Rbfn:
    """Single-input single-output RBF network (eqs. 5-6)."""

    def __init__(self, centres: int = 10, width_scale: float = 2.0, ridge: float | None = None, seed: int = 0
                 ) -> None:
        self.n_centres, self.width_scale, self.ridge, self.seed = centres, width_scale, ridge, seed
        self.c = self.s = self.w = None
        self.mean, self.std = 0.0, 1.0

    def fit(self, x: np.ndarray, y: np.ndarray) -> "Rbfn":
        """Train on samples x (n,), y (n,): normalise x, k-means centres, widths, least-squares weights."""
        x, y = np.asarray(x, float), np.asarray(y, float)
        self.mean, self.std = _normaliser(x)
        xn = (x - self.mean) / self.std
        c = kmeans_centres(xn, self.n_centres, self.seed)
        if len(c) > 1:
            gap = np.diff(c)
            s = np.minimum(np.concatenate([[np.inf], gap]), np.concatenate([gap, [np.inf]]))
        else:
            s = np.ones(1)
        self.c, self.s = c, self.width_scale * np.maximum(s, 1e-3)
        self.w, self.ridge_used = ridge_solve(rbf_design(xn, self.c, self.s), y, self.ridge)
        return self

    @property
    def centres(self) -> np.ndarray:
        """Centres in input units (l,)."""
        return self.mean + self.std * self.c

    def predict(self, x: np.ndarray) -> np.ndarray:
        """Outputs (n,) for inputs x (n,) (eq. 6)."""
        return rbf_design((np.asarray(x, float) - self.mean) / self.std, self.c, self.s) @ self.w


def delay_rows(x: np.ndarray, taps: int) -> np.ndarray:
    """Tapped-delay rows (n, taps) of a series x (n,): row n = [x_n, x_{n-1}, ...], padded with x_0."""
    x = np.asarray(x, float)
    padded = np.concatenate([np.full(taps - 1, x[0]), x])
    return sliding_window_view(padded, taps)[:, ::-1]


class Tdln:
    """Single-input single-output linear network with a tapped delay line, y_n = b + sum_j w_j x_{n-j}."""

    def __init__(self, taps: int = 200, ridge: float | None = None) -> None:
        self.taps, self.ridge = taps, ridge
        self.w = None  # (taps + 1,): bias, then taps on the normalised input
        self.mean, self.std = 0.0, 1.0

    def fit(self, x: np.ndarray, y: np.ndarray) -> "Tdln":
        """x (n,) the input series, one sample per step; y (n,) targets, NaN where there is none."""
        x, y = np.asarray(x, float), np.asarray(y, float)
        ok = np.isfinite(y)
        self.mean, self.std = _normaliser(x[ok])
        A = self._rows(x)[ok]
        self.w, self.ridge_used = ridge_solve(A, y[ok], self.ridge)
        return self

    def _rows(self, x: np.ndarray) -> np.ndarray:
        d = delay_rows((x - self.mean) / self.std, self.taps)
        return np.hstack([np.ones((len(d), 1)), d])

    @property
    def fir(self) -> tuple[float, np.ndarray]:
        """(bias, taps (taps,)) in input units: y_n = bias + sum_j taps_j x_{n-j}."""
        h = self.w[1:] / self.std
        return float(self.w[0] - h.sum() * self.mean), h

    def predict(self, x: np.ndarray) -> np.ndarray:
        """Outputs (n,) along a series x (n,) (the delay line starts at x_0)."""
        return self._rows(np.asarray(x, float)) @ self.w


class OutagePredictor:
    """The six channels of one method (``"rbfn"`` or ``"tdln"`` networks) and their training history.

    Fed once per GPS epoch by the fusion loop: :meth:`train` at a usable epoch (input and target),
    :meth:`predict` at an outage epoch (input; returns the predicted target). History is bounded:
    ``window`` epochs (+ ``taps`` for the delay line).

    A prediction is clipped to the range of the targets the network was trained on. The correction
    feeds the INS, whose state is the networks' next input: a linear network extrapolating outside its
    training range (the TDLN's 200 weights act like a high-gain differentiator on a smooth input) would
    otherwise close an unstable loop and diverge within seconds.
    """

    def __init__(self, kind: str, config: PredictorConfig | None = None) -> None:
        if kind not in ("rbfn", "tdln"):
            raise ValueError(f"unknown network {kind!r}")
        self.kind = kind
        self.cfg = config or PredictorConfig()
        cap = self.cfg.window + (self.cfg.taps if kind == "tdln" else 0)
        self._u: deque[np.ndarray] = deque(maxlen=cap)
        self._y: deque[np.ndarray] = deque(maxlen=cap)
        self._models: list[Rbfn | Tdln | None] | None = None
        self._settle_until = -math.inf
        self._in_outage = True  # the filter starts unaided
        self._lo, self._hi = np.full(N_CHANNELS, -np.inf), np.full(N_CHANNELS, np.inf)
        self.fits = 0

    def train(self, t_s: float, u: np.ndarray, y: np.ndarray) -> None:
        """A usable epoch at t_s (s): input u (6,), target y (6,) (NaN for a component not observed)."""
        if self._in_outage:
            self._settle_until = t_s + self.cfg.settle_s
            self._in_outage = False
        self._push(u, y if t_s >= self._settle_until else np.full(N_CHANNELS, np.nan))
        self._models = None

    def predict(self, u: np.ndarray) -> np.ndarray:
        """An outage epoch with input u (6,): the predicted target (6,), NaN for a channel without a model."""
        self._in_outage = True
        self._push(u, np.full(N_CHANNELS, np.nan))
        if self._models is None:
            self._models = self._fit()
        out = np.full(N_CHANNELS, np.nan)
        U = np.array(self._u)
        for i, m in enumerate(self._models):
            if m is None:
                continue
            # the RBFN maps the current input; the TDLN needs its delay line, the last `taps` inputs
            out[i] = m.predict(U[-1:, i])[0] if self.kind == "rbfn" else m.predict(U[-self.cfg.taps:, i])[-1]
        return np.clip(out, self._lo, self._hi)

    def _push(self, u: np.ndarray, y: np.ndarray) -> None:
        self._u.append(np.asarray(u, float).copy())
        self._y.append(np.asarray(y, float).copy())

    def _fit(self) -> list[Rbfn | Tdln | None]:
        c = self.cfg
        U, Y = np.array(self._u), np.array(self._y)
        Y[:-c.window] = np.nan  # the TDLN's extra history is delay line only
        models: list[Rbfn | Tdln | None] = []
        for i in range(N_CHANNELS):
            ok = np.isfinite(Y[:, i]) & np.isfinite(U[:, i])
            if ok.sum() < c.min_train:
                models.append(None)
                continue
            self._lo[i], self._hi[i] = Y[ok, i].min(), Y[ok, i].max()
            if self.kind == "rbfn":
                models.append(Rbfn(c.centres, c.width_scale, c.ridge, c.seed).fit(U[ok, i], Y[ok, i]))
            else:
                models.append(Tdln(c.taps, c.ridge).fit(U[:, i], Y[:, i]))
        self.fits += 1
        return models
