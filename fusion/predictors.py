"""Outage predictors of the distributed-KF paper (sections 2.2-2.3): six SISO RBF networks, the TDLN, and
the training history that feeds them from the fusion loop; and :class:`SpeedNetwork`, the same family with several
inputs, the virtual odometer of ``predictor_mode = "pseudo"`` (``fusion.pseudo``).

Networks (pure numpy, one per channel):

- RBFN, eq. 6: y = sum_i w_i exp(-((x - c_i) / s_i)^2 / 2), no bias term. The input is normalised within the
  training window (mean, std); centres by k-means on it (:func:`kmeans_1d`, k-means++ start, fixed
  seed); width s_i = the distance from c_i to its nearest other centre times ``width_scale`` (2). Without a
  bias term (as eq. 6) the output decays to zero for inputs far outside the training data: the correction
  then falls back to none, i.e. to the plain filter.
- TDLN: a linear network with a tapped delay line on its input, y_n = b + sum_{j<taps} w_j x_{n-j},
  taps = 200 as in the paper. Before the line is full it is padded with the oldest input.

Training (``PredictorConfig.training``):

- ``"online"`` (default, the paper's section 2.2: trained in real time while GPS is good):
  :class:`OnlineChannel`. Output weights by recursive least squares with forgetting (:class:`Rls`, memory
  about ``window`` epochs, start P = I / ``rls_delta``), updated at every good epoch; k-means centres and the
  input normaliser refreshed every ``refresh`` trained epochs and whenever an input leaves the centres' span
  (the RLS is then rerun over the window, since its features changed). RLS rather than LMS: see
  :class:`OnlineChannel`.
- ``"batch"`` (for comparison): :class:`Rbfn` / :class:`Tdln` fitted once, at the first epoch of an outage,
  on the window, with a ridge chosen by generalised cross-validation (:func:`ridge_solve`); with 200 taps the
  window often holds fewer epochs than weights, and an unregularised fit extrapolates wildly.

Channels: inputs INS east, north, up position and vE, vN, vU; each network maps one input to the target
of the same component. The positions are given in metres from a fixed origin: an affine map of the
paper's longitude, latitude, altitude, which the normalisation removes anyway.

Eq. 7 in our closed loop (``dkf-rbfn``)
---------------------------------------
The paper splits each local filter's estimate into the state prediction X_i(n|n-1) = Phi X_i(n-1) and the
innovation component dX_i(n) = K_i(n) nu_i(n): X_i(n) = X_i(n|n-1) + dX_i(n) (eq. 7). Our filters are closed
loop: the fused estimate corrects the INS at every epoch. With the paper's distributed filter (``fusion.dkf``)
that does not make X_i(n|n-1) zero: the fused correction x is subtracted from each local estimate
(x_i <- x_i - x, the local filter now estimates the error of the corrected INS), and since the two local
estimates differ from their fusion, each keeps a non-zero remainder that Phi carries to the next epoch. So:

- while GPS is good, every epoch: KF_I's update gives dX_I (velocity, from the GPS velocity), KF_II's gives
  dX_II (position); the networks train on the INS position/velocity before the update (input) and the
  velocity components of dX_I and the position components of dX_II (targets), as Fig. 3(a);
- in an outage, every epoch: X_i(n|n-1) is the local filter's propagated estimate (the remainder above plus
  what the dynamics add); the networks predict dX_I's velocity and dX_II's position components from the
  current INS; their sum is X_i(n) (eq. 7); eqs. 3-4 fuse X_I(n), X_II(n) with the predicted covariances
  (a prediction is not a measurement: P_i is not reduced), and the fused X corrects the INS, as Fig. 3(b);
  the local estimates are shifted by it as at a GPS epoch. ``Engine.hybrid_parts`` records both parts.
- ``dkf`` alone does the same without the networks: in an outage its fused state prediction is fed back at
  every epoch, so ``dkf-rbfn`` differs from ``dkf`` only by the predicted innovations.

With the federated variant (``dkf_fusion = "federated"``) the local filters are reset to the fused estimate
at every epoch, X_i(n|n-1) is identically zero, and the hybrid reduces to "0 + predicted innovation".

``rbfn`` and ``tdln``, the predictors alone (section 2.2): their targets are "the errors between INS
positions & velocities and GPS positions & velocities", i.e. the observations z = INS - GPS of KF_II
(position) and KF_I (velocity) at the epoch, before correction. During an outage the predicted z is
subtracted from the INS in full at each epoch (gain 1), with no KF involved (the local estimates are shifted
by it, a known input).

Consequence, worth knowing when reading the results: in a closed loop, z is the error grown since the
last correction plus GPS noise. In steady state a systematic drift d per epoch gives E[z] = d / K and
E[K z] = d, so the full-gain ``rbfn``/``tdln`` correction over-corrects a systematic drift by a factor
1/K, and carries the GPS noise of z at full weight; the hybrid's target already has the gain in it. In the
paper, the predictors alone seem to correct a free-running INS (Table 3: altitude errors of kilometres),
where z is the whole INS error; we do not reproduce that set-up, since the free INS is our ``ins`` method.

Where the paper is ambiguous
----------------------------
- The rate: targets exist at the GPS epochs (1 Hz); the paper holds GPS values between epochs ("the GPS
  signals maintained the latest receiving values"), which suggests networks run at the IMU rate on
  zero-order-held targets. We train and predict at the GPS epochs only: held targets add no information.
  A 200-step delay is then 200 s of input history (0.4 s at 500 Hz in the paper's reading).
- Window length, number of centres, widths and regularisation are not given; ours are in
  :class:`PredictorConfig`.
- The epochs within ``settle_s`` after the filter starts or GPS returns are left out of training: their
  innovations are the reconvergence from the previous outage, not a function of the INS state.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from fieldlog.fusion import kernels
from fieldlog.fusion.errmodel import cycle_kernel

N_CHANNELS = 6  # position E, N, U (m), velocity E, N, U (m/s)
RBF, TDL = "rbf", "tdl"  # the network kinds: radial basis functions (RBFN), time-delay linear (TDLN)
NETWORKS = (RBF, TDL)
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
    ridge: float | None = None  # batch: relative to the mean diagonal of the normal matrix; None: by GCV
    seed: int = 0  # k-means++ start
    training: str = "online"  # "online": RLS weights at every good epoch (the paper); "batch": ridge fit per outage
    refresh: int = 60  # online: k-means centres and input normaliser recomputed every this many trained epochs
    rls_delta: float = 1e-2  # online: RLS start P = I / delta, a ridge of delta on the normalised features

    @property
    def forget(self) -> float:
        """RLS forgetting factor: a memory of about ``window`` epochs."""
        return 1.0 - 1.0 / self.window


def _normaliser(x: np.ndarray) -> tuple[float, float]:
    return float(np.mean(x)), max(float(np.std(x)), _STD_FLOOR)


RIDGE_GRID = 10.0 ** np.arange(-12.0, 2.0)  # relative ridges tried by generalised cross-validation


def ridge_solve(A: np.ndarray, y: np.ndarray, ridge: float | None = None) -> tuple[np.ndarray, float]:
    """argmin |A w - y|^2 + lam |w|^2 with lam = ridge * mean(diag(A^T A)); returns (w, ridge).

    ridge None: chosen from ``RIDGE_GRID`` by generalised cross-validation, GCV = n RSS / (n - tr H)^2
    (Golub, Heath & Wahba), all candidates from one SVD of A.

    Parameters
    ----------
    A : np.ndarray
        (n, m) the design matrix.
    y : np.ndarray
        (n,) the targets.
    ridge : float or None
        The relative ridge; None: by GCV.

    Returns
    -------
    tuple of (np.ndarray, float)
        The weights (m,) and the relative ridge used.
    """
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
    """Sorted distinct 1-D k-means centres (at most k).

    Parameters
    ----------
    x : np.ndarray
        (n,) the samples.
    k : int
        The number of centres asked for.
    seed : int
        The k-means++ draws' seed.

    Returns
    -------
    np.ndarray
        (at most k,) the centres, ascending.
    """
    x = np.asarray(x, dtype=float)
    k = max(1, min(k, len(np.unique(x))))
    c = np.sort(kmeans_1d(x, k, np.random.default_rng(seed)))
    keep = np.concatenate([[True], np.diff(c) > 1e-9 * max(1.0, float(np.ptp(x)))])
    return c[keep]


def kmeans_1d(x: np.ndarray, k: int, rng: np.random.Generator, iterations: int = 10) -> np.ndarray:
    """k centres (k,) of 1-D samples x (n,): :func:`kmeans` on one column.

    The algorithm of ``scipy.cluster.vq.kmeans2(x[:, None], k, minit="++", rng=rng)``, step for step and draw
    for draw, so the centres equal its to the bit (tests/test_predictors.py holds the two against each other);
    written out in numpy because importing ``scipy.cluster`` costs a predictor method more than all its k-means
    runs over a drive.

    Parameters
    ----------
    x : np.ndarray
        (n,) the samples.
    k, rng, iterations
        As :func:`kmeans`.

    Returns
    -------
    np.ndarray
        (k,) the centres.
    """
    return kmeans(np.asarray(x, float)[:, None], k, rng, iterations)[:, 0]


def kmeans(x: np.ndarray, k: int, rng: np.random.Generator, iterations: int = 10) -> np.ndarray:
    """k centres (k, d) of samples x (n, d): k-means++ seeding (Arthur and Vassilvitskii), then ``iterations``
    Lloyd steps; an emptied cluster keeps its centre. Each step's memory is (n, k, d).

    Parameters
    ----------
    x : np.ndarray
        (n, d) the samples.
    k : int
        The number of centres.
    rng : np.random.Generator
        The k-means++ draws.
    iterations : int
        Lloyd steps.

    Returns
    -------
    np.ndarray
        (k, d) the centres.
    """
    centres = np.empty((k, x.shape[1]))
    for i in range(k):
        if i == 0:
            pick = rng.integers(len(x))
        else:  # the next seed drawn with probability proportional to the squared distance to the nearest one
            d2 = ((centres[:i, None, :] - x[None, :, :]) ** 2).sum(axis=2).min(axis=0)
            pick = int(np.searchsorted((d2 / d2.sum()).cumsum(), rng.uniform()))
        centres[i] = x[pick]
    for _ in range(iterations):
        label = np.argmin(((x[:, None, :] - centres[None, :, :]) ** 2).sum(axis=2), axis=1)
        count = np.bincount(label, minlength=k)
        for j in range(x.shape[1]):  # summed in sample order, as kmeans2's update
            total = np.bincount(label, weights=x[:, j], minlength=k)
            centres[:, j] = np.where(count > 0, total / np.maximum(count, 1), centres[:, j])
    return centres


def rbf_design(x: np.ndarray, c: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Gaussian unit outputs (eq. 5).

    Parameters
    ----------
    x : np.ndarray
        (n,) the inputs.
    c, s : np.ndarray
        (l,) the units' centres and widths, in the inputs' unit.

    Returns
    -------
    np.ndarray
        (n, l) the outputs.
    """
    return np.exp(-0.5 * ((np.asarray(x, float)[:, None] - c) / s) ** 2)


class Rbfn:
    """Single-input single-output RBF network (eqs. 5-6)."""

    def __init__(self, centres: int = 10, width_scale: float = 2.0, ridge: float | None = None, seed: int = 0
                 ) -> None:
        self.n_centres, self.width_scale, self.ridge, self.seed = centres, width_scale, ridge, seed
        self.c = self.s = self.w = None
        self.mean, self.std = 0.0, 1.0

    def fit(self, x: np.ndarray, y: np.ndarray) -> "Rbfn":
        """Train: normalise x, k-means centres, widths, least-squares weights.

        Parameters
        ----------
        x, y : np.ndarray
            (n,) the inputs and targets.

        Returns
        -------
        Rbfn
            self, trained.
        """
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
        """The network's outputs (eq. 6).

        Parameters
        ----------
        x : np.ndarray
            (n,) the inputs.

        Returns
        -------
        np.ndarray
            (n,) the outputs.
        """
        return rbf_design((np.asarray(x, float) - self.mean) / self.std, self.c, self.s) @ self.w


def delay_rows(x: np.ndarray, taps: int) -> np.ndarray:
    """Tapped-delay rows of a series: row n = [x_n, x_{n-1}, ...], padded with x_0.

    Parameters
    ----------
    x : np.ndarray
        (n,) the series.
    taps : int
        The delay line's length.

    Returns
    -------
    np.ndarray
        (n, taps) the rows.
    """
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
        """Train on a series.

        Parameters
        ----------
        x : np.ndarray
            (n,) the input series, one sample per step.
        y : np.ndarray
            (n,) the targets, NaN where there is none.

        Returns
        -------
        Tdln
            self, trained.
        """
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
        """The outputs along a series (the delay line starts at x_0).

        Parameters
        ----------
        x : np.ndarray
            (n,) the series.

        Returns
        -------
        np.ndarray
            (n,) the outputs.
        """
        return self._rows(np.asarray(x, float)) @ self.w


class Rls:
    """Recursive least squares with exponential forgetting: w minimises sum_k forget^(n-k) (y_k - phi_k w)^2 +
    forget^n delta |w|^2. One O(n^2) update per sample (no matrix inverse), stable in the Joseph-free form with
    symmetrisation."""

    def __init__(self, n: int, forget: float, delta: float) -> None:
        self.w = np.zeros(n)
        self.P = np.eye(n) / delta
        self.forget = forget
        self.updates = 0

    def update(self, Phi: np.ndarray, y: np.ndarray) -> None:
        """Samples in turn, each moving the weights towards its target and discounting the past by ``forget``:
        Pphi = P phi, k = Pphi / (forget + phi Pphi), w += k (y - phi w), P = sym((P - k Pphi^T) / forget);
        compiled (``fieldlog_rls_update`` in fusion/_cycles.c).

        Parameters
        ----------
        Phi : np.ndarray
            (m, n) the samples' feature rows, or (n,) one sample's.
        y : np.ndarray
            (m,) their targets, in the output's unit (a float for one sample).
        """
        Phi = np.ascontiguousarray(np.atleast_2d(Phi), dtype=float)
        y = np.ascontiguousarray(np.atleast_1d(y), dtype=float)
        if Phi.shape != (len(y), len(self.w)):
            raise ValueError(f"RLS of {len(self.w)} weights needs (m, {len(self.w)}) rows and m targets: "
                             f"{Phi.shape}, {y.shape}")
        cycle_kernel().fieldlog_rls_update(len(y), len(self.w), *map(kernels.address, (self.P, self.w, Phi, y)),
                                           float(self.forget))
        self.updates += len(y)


class OnlineChannel:
    """One channel of a network trained in real time (section 2.2 of the paper).

    RBFN: centres by k-means (``kmeans_centres``) on the window's inputs, normalised by the window's mean and
    std, widths from the centre spacing as :class:`Rbfn`; TDLN: the window's normaliser and the tapped delay line
    of :class:`Tdln`. The output weights are recursive least squares (:class:`Rls`), updated at every epoch with a
    target. RLS rather than the paper's LMS gradient descent: the Gaussian units overlap (width 2x the spacing),
    so the features are strongly correlated and LMS converges at the rate of the smallest eigenvalue of their
    correlation, hundreds of epochs at 1 Hz for a step size that stays stable; RLS converges in about as many
    epochs as there are weights, needs no step size, and forgets at a known rate (``PredictorConfig.forget``).

    Every ``refresh`` trained epochs, first after ``min_train``, and whenever an RBFN input leaves the centres'
    span by more than a width, the centres and normaliser are recomputed on the window; the features then change, so the RLS restarts and is run over the window's samples once (a
    refresh costs what one batch fit does; between refreshes an epoch costs one RLS step)."""

    def __init__(self, kind: str, cfg: PredictorConfig) -> None:
        self.kind, self.cfg = kind, cfg
        self.rls: Rls | None = None
        self.c = self.s = None
        self.mean, self.std = 0.0, 1.0
        self.since = 0

    def features(self, x: np.ndarray) -> np.ndarray:
        """The feature rows.

        Parameters
        ----------
        x : np.ndarray
            (n,) RBFN: the current inputs; TDLN: a series, one row per step.

        Returns
        -------
        np.ndarray
            (n, l) the rows.
        """
        xn = (np.asarray(x, float) - self.mean) / self.std
        if self.kind == RBF:
            return rbf_design(xn, self.c, self.s)
        d = delay_rows(xn, self.cfg.taps)
        return np.hstack([np.ones((len(d), 1)), d])

    def refresh(self, U: np.ndarray, Y: np.ndarray) -> None:
        """New centres and normaliser from the window; the RLS rerun over it.

        Parameters
        ----------
        U : np.ndarray
            (n,) the window's inputs.
        Y : np.ndarray
            (n,) its targets (NaN: none).
        """
        ok = np.isfinite(Y)
        self.mean, self.std = _normaliser(U[ok])
        if self.kind == RBF:
            c = kmeans_centres((U[ok] - self.mean) / self.std, self.cfg.centres, self.cfg.seed)
            if len(c) > 1:
                gap = np.diff(c)
                s = np.minimum(np.concatenate([[np.inf], gap]), np.concatenate([gap, [np.inf]]))
            else:
                s = np.ones(1)
            self.c, self.s = c, self.cfg.width_scale * np.maximum(s, 1e-3)
            A = self.features(U[ok])
        else:
            A = self.features(U)[ok]
        self.rls = Rls(A.shape[1], self.cfg.forget, self.cfg.rls_delta)
        self.rls.update(A, Y[ok])
        self.since = 0

    def stale(self, x: float) -> bool:
        """Whether the centres are due now.

        Parameters
        ----------
        x : float
            The current input.

        Returns
        -------
        bool
            RBFN: the input is beyond the outer centres by more than their width (the vehicle left the
            trained region); TDLN: False.
        """
        if self.kind != RBF:
            return False
        xn = (x - self.mean) / self.std
        return bool(xn < self.c[0] - self.s[0] or xn > self.c[-1] + self.s[-1])

    def step(self, U: np.ndarray, y: float) -> None:
        """One RLS update with the newest sample.

        Parameters
        ----------
        U : np.ndarray
            (n,) the input series, the last one current (TDLN: at least ``taps`` of them).
        y : float
            The current input's target.
        """
        phi = self.features(U[-1:] if self.kind == RBF else U[-self.cfg.taps:])[-1]
        self.rls.update(phi, y)
        self.since += 1

    def predict(self, U: np.ndarray) -> float:
        """The channel's output.

        Parameters
        ----------
        U : np.ndarray
            The input series (the last one is current).

        Returns
        -------
        float
            The output, in the target's unit.
        """
        phi = self.features(U[-1:] if self.kind == RBF else U[-self.cfg.taps:])[-1]
        return float(phi @ self.rls.w)


class History:
    """The newest ``cap`` rows (width ``width``) in arrival order: appended in amortised O(1) into a buffer of
    twice the capacity, which is compacted when full, so ``rows`` is one contiguous copy (rather than an array
    built from ``cap`` small ones at every epoch)."""

    def __init__(self, cap: int, width: int) -> None:
        self.cap = cap
        self._buf = np.empty((2 * cap, width))
        self._start = self._end = 0

    def __len__(self) -> int:
        return self._end - self._start

    def append(self, row: np.ndarray) -> None:
        """Append a row, dropping the oldest beyond ``cap``.

        Parameters
        ----------
        row : np.ndarray
            (width,) the row.
        """
        if self._end == len(self._buf):
            n = len(self)
            self._buf[:n] = self._buf[self._start:self._end]
            self._start, self._end = 0, n
        self._buf[self._end] = row
        self._end += 1
        self._start = max(self._start, self._end - self.cap)

    def rows(self) -> np.ndarray:
        """The rows held, oldest first.

        Returns
        -------
        np.ndarray
            (len, width) a copy.
        """
        return self._buf[self._start:self._end].copy()


class OutagePredictor:
    """The six channels of one method (``RBF`` or ``TDL`` networks) and their training history.

    Fed once per GPS epoch by the fusion loop: :meth:`train` at a usable epoch (input and target),
    :meth:`predict` at an outage epoch (input; returns the predicted target). History is bounded:
    ``window`` epochs (+ ``taps`` for the delay line).

    A prediction is clipped to the range of the targets the network was trained on. The correction
    feeds the INS, whose state is the networks' next input: a linear network extrapolating outside its
    training range (the TDLN's 200 weights act like a high-gain differentiator on a smooth input) would
    otherwise close an unstable loop and diverge within seconds.
    """

    def __init__(self, kind: str, config: PredictorConfig | None = None) -> None:
        if kind not in NETWORKS:
            raise ValueError(f"unknown network {kind!r}")
        self.kind = kind
        self.cfg = config or PredictorConfig()
        cap = self.cfg.window + (self.cfg.taps if kind == TDL else 0)
        self._u, self._y = History(cap, N_CHANNELS), History(cap, N_CHANNELS)
        self._models: list[Rbfn | Tdln | None] | None = None
        self._settle_until = -math.inf
        self._in_outage = True  # the filter starts unaided
        self._lo, self._hi = np.full(N_CHANNELS, -np.inf), np.full(N_CHANNELS, np.inf)
        self.fits = 0
        if self.cfg.training not in ("online", "batch"):
            raise ValueError(f"[fusion.predictor] training: {self.cfg.training!r}; one of online, batch")
        self.online = ([OnlineChannel(kind, self.cfg) for _ in range(N_CHANNELS)]
                       if self.cfg.training == "online" else None)

    def train(self, t_s: float, u: np.ndarray, y: np.ndarray) -> None:
        """Train on a usable epoch.

        Parameters
        ----------
        t_s : float
            The epoch, s.
        u : np.ndarray
            (6,) the input.
        y : np.ndarray
            (6,) the target (NaN for a component not observed).
        """
        if self._in_outage:
            self._settle_until = t_s + self.cfg.settle_s
            self._in_outage = False
        self._push(u, y if t_s >= self._settle_until else np.full(N_CHANNELS, np.nan))
        self._models = None
        if self.online is not None:
            self._train_online()

    def _train_online(self) -> None:
        """Real-time training at this epoch: an RLS step per channel with a target, a refresh when due."""
        c = self.cfg
        U, Y = self._u.rows(), self._y.rows()
        Y[:-c.window] = np.nan
        for i, ch in enumerate(self.online):
            if not np.isfinite(Y[-1, i]) or not np.isfinite(U[-1, i]):
                continue
            ok = np.isfinite(Y[:, i]) & np.isfinite(U[:, i])
            self._lo[i], self._hi[i] = Y[ok, i].min(), Y[ok, i].max()  # finite rows: no NaN to skip
            if ch.rls is None and ok.sum() < c.min_train:
                continue
            if ch.rls is None or ch.since >= c.refresh or ch.stale(U[-1, i]):
                ch.refresh(U[:, i], np.where(ok, Y[:, i], np.nan))
                self.fits += 1
            else:
                ch.step(U[:, i], Y[-1, i])

    def predict(self, u: np.ndarray) -> np.ndarray:
        """The prediction at an outage epoch.

        Parameters
        ----------
        u : np.ndarray
            (6,) the input.

        Returns
        -------
        np.ndarray
            (6,) the predicted target, NaN for a channel without a model.
        """
        self._in_outage = True
        self._push(u, np.full(N_CHANNELS, np.nan))
        out = np.full(N_CHANNELS, np.nan)
        U = self._u.rows()
        if self.online is not None:
            for i, ch in enumerate(self.online):
                if ch.rls is not None:
                    out[i] = ch.predict(U[:, i])
            return np.clip(out, self._lo, self._hi)
        if self._models is None:
            self._models = self._fit()
        for i, m in enumerate(self._models):
            if m is None:
                continue
            # the RBFN maps the current input; the TDLN needs its delay line, the last `taps` inputs
            out[i] = m.predict(U[-1:, i])[0] if self.kind == RBF else m.predict(U[-self.cfg.taps:, i])[-1]
        return np.clip(out, self._lo, self._hi)

    def _push(self, u: np.ndarray, y: np.ndarray) -> None:
        self._u.append(u)
        self._y.append(y)

    def _fit(self) -> list[Rbfn | Tdln | None]:
        c = self.cfg
        U, Y = self._u.rows(), self._y.rows()
        Y[:-c.window] = np.nan  # the TDLN's extra history is delay line only
        models: list[Rbfn | Tdln | None] = []
        for i in range(N_CHANNELS):
            ok = np.isfinite(Y[:, i]) & np.isfinite(U[:, i])
            if ok.sum() < c.min_train:
                models.append(None)
                continue
            self._lo[i], self._hi[i] = Y[ok, i].min(), Y[ok, i].max()
            if self.kind == RBF:
                models.append(Rbfn(c.centres, c.width_scale, c.ridge, c.seed).fit(U[ok, i], Y[ok, i]))
            else:
                models.append(Tdln(c.taps, c.ridge).fit(U[:, i], Y[:, i]))
        self.fits += 1
        return models


class SpeedNetwork:
    """A multi-input RBF network trained in real time on a scalar target (the virtual odometer of
    ``fusion.pseudo``): the same family as the paper's channels, with d inputs instead of one.

    y = w_0 + sum_j w_j xn_j + sum_i w_i exp(-|xn - c_i|^2 / (2 s_i^2)), xn the input normalised by the window's
    mean and std per component. Centres by k-means (:func:`kmeans`, k-means++ start, ``seed``) on the window's
    normalised inputs, width s_i = ``width_scale`` x the distance to the nearest other centre; output weights by
    recursive least squares with forgetting (:class:`Rls`), refreshed as :class:`OnlineChannel` (every
    ``refresh`` trained epochs, first after ``min_train``). The bias and linear terms (which eq. 6 lacks) carry
    the output outside the centres' span, where the Gaussian units fall to zero: a speed does not fall to zero
    because an input left the training range. Predictions are clipped to the trained targets' range."""

    def __init__(self, dim: int, cfg: PredictorConfig) -> None:
        self.cfg = cfg
        self._x, self._y = History(cfg.window, dim), History(cfg.window, 1)
        self.rls: Rls | None = None
        self.c = self.s = None
        self.mean, self.std = np.zeros(dim), np.ones(dim)
        self.lo = self.hi = math.nan
        self.since = 0

    @property
    def ready(self) -> bool:
        return self.rls is not None

    def features(self, x: np.ndarray) -> np.ndarray:
        """The feature rows: bias, normalised inputs, Gaussian units.

        Parameters
        ----------
        x : np.ndarray
            (n, d) or (d,) the inputs.

        Returns
        -------
        np.ndarray
            (n, 1 + d + l) the rows.
        """
        xn = (np.atleast_2d(x) - self.mean) / self.std
        d2 = ((xn[:, None, :] - self.c[None, :, :]) ** 2).sum(axis=2)
        return np.hstack([np.ones((len(xn), 1)), xn, np.exp(-0.5 * d2 / self.s ** 2)])

    def train(self, x: np.ndarray, y: float) -> None:
        """One epoch: an RLS step, or a refresh when due.

        Parameters
        ----------
        x : np.ndarray
            (d,) the input.
        y : float
            The target.
        """
        if not (np.isfinite(x).all() and math.isfinite(y)):
            return
        self._x.append(x)
        self._y.append(np.array([y]))
        X, Y = self._x.rows(), self._y.rows()[:, 0]
        self.lo, self.hi = float(Y.min()), float(Y.max())
        if self.rls is None and len(Y) < self.cfg.min_train:
            return
        if self.rls is None or self.since >= self.cfg.refresh:
            self._refresh(X, Y)
        else:
            self.rls.update(self.features(x)[0], y)
            self.since += 1

    def _refresh(self, X: np.ndarray, Y: np.ndarray) -> None:
        self.mean = X.mean(axis=0)
        self.std = np.maximum(X.std(axis=0), _STD_FLOOR)
        xn = (X - self.mean) / self.std
        k = max(1, min(self.cfg.centres, len(np.unique(xn, axis=0))))
        c = kmeans(xn, k, np.random.default_rng(self.cfg.seed))
        if len(c) > 1:
            d = np.sqrt(((c[:, None, :] - c[None, :, :]) ** 2).sum(axis=2))
            np.fill_diagonal(d, np.inf)
            s = d.min(axis=1)
        else:
            s = np.ones(1)
        self.c, self.s = c, self.cfg.width_scale * np.maximum(s, 1e-3)
        A = self.features(X)
        self.rls = Rls(A.shape[1], self.cfg.forget, self.cfg.rls_delta)
        self.rls.update(A, Y)
        self.since = 0

    def frozen(self) -> "SpeedNetwork":
        """A copy that predicts as this one does now (its history not copied: it is not trained further).

        Returns
        -------
        SpeedNetwork
            Its centres, widths, normaliser, clip range and output weights; for :meth:`predict` only.
        """
        out = SpeedNetwork.__new__(SpeedNetwork)
        out.cfg, out.c, out.s, out.mean, out.std, out.lo, out.hi = (self.cfg, self.c, self.s, self.mean, self.std,
                                                                    self.lo, self.hi)
        out.rls = Rls.__new__(Rls)
        out.rls.w = self.rls.w.copy()
        return out

    def predict(self, x: np.ndarray) -> float:
        """The output, clipped to the trained targets' range.

        Parameters
        ----------
        x : np.ndarray
            (d,) the input.

        Returns
        -------
        float
            The output, in the target's unit; NaN before the first fit.
        """
        if self.rls is None or not np.isfinite(x).all():
            return math.nan
        return float(np.clip(self.features(x)[0] @ self.rls.w, self.lo, self.hi))
