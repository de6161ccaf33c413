"""GPS outages: which epochs are usable, the outage windows, and bridging them with a predictor.

An epoch is unusable when its status is NO_FIX, its lat/lon are NaN, its horizontal sigma is above
``max_fix_sigma_m``, or it falls in a forced window (``outages``, seconds from the first IMU sample).
Detected windows run from the first unusable epoch to the next usable one (:class:`OutageTracker`). A GPS
silence (no epoch for longer than 1.5 nominal intervals: a receiver that stops talking, a bag with no messages
there) becomes no-fix epochs at the nominal interval (:class:`Silence`), so it opens a window (reason
``silent``) like NO_FIX epochs, and the aids and predictors run inside it at the epoch rate.

Bridging (``rbfn``, ``tdln``, ``dkf-rbfn``; ``fusion.predictors`` for the mapping of the paper onto the closed
loop): :class:`PredictorBridge` gives the predictor, at each usable epoch, the INS position (ENU m from the
alignment point) and velocity before the correction and its target: the observation z = INS - GPS (``rbfn``,
``tdln``) or the local filters' innovation components (``dkf-rbfn``). At each unusable or withheld epoch it
returns the prediction: the correction of the INS (``rbfn``, ``tdln``) or the predicted innovation components
(``dkf-rbfn``, added to the local filters' state prediction, eq. 7).
"""

from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np

from fieldlog.fusion import kf, predictors
from fieldlog.fusion.errmodel import N_STATES, POS, VEL
from fieldlog.fusion.ins import NavState
from fieldlog.fusion.median import median
from fieldlog.fusion.methods import Bridge
from fieldlog.fusion.types import Epoch, Outage

NS = 1_000_000_000


class OutageTracker:
    """Classifies GPS epochs and collects the outage windows, forced and detected."""

    def __init__(self, max_fix_sigma_m: float) -> None:
        self.max_fix_sigma_m = max_fix_sigma_m
        self._open: Outage | None = None
        self._forced: list[tuple[int, int]] = []
        self._outages: list[Outage] = []

    def force(self, t_ref_ns: int, windows: tuple[tuple[float, float], ...]) -> None:
        """Force the outage windows of ``[fusion] outages``.

        Parameters
        ----------
        t_ref_ns : int
            The first IMU sample, ns: the windows' origin.
        windows : tuple of (float, float)
            (start, length) of each window, s from t_ref_ns.
        """
        self._forced = [(t_ref_ns + int(s * NS), t_ref_ns + int((s + n) * NS)) for s, n in windows]
        self._outages += [Outage(a, b, "injected") for a, b in self._forced]

    def classify(self, ep: Epoch) -> bool:
        """Whether an epoch's fix is usable; opens and closes the detected outage windows.

        Parameters
        ----------
        ep : Epoch
            The GPS epoch.

        Returns
        -------
        bool
            True when its fix is usable: a fix, finite, its horizontal sigma within ``max_fix_sigma_m``, and outside
            the forced windows.
        """
        t = ep.t_ns
        good_fix = ep.status >= 0 and math.isfinite(ep.lat) and math.isfinite(ep.lon)  # h may be NaN
        low = good_fix and not math.sqrt(max(ep.pos_cov[0, 0], ep.pos_cov[1, 1])) <= self.max_fix_sigma_m
        usable = good_fix and not low
        if not usable and self._open is None:
            self._open = Outage(t, t, "silent" if ep.silent else "low_quality" if low else "no_fix")
        elif usable and self._open is not None:
            self._open.end_ns = t
            self._outages.append(self._open)
            self._open = None
        forced = any(a <= t < b for a, b in self._forced)
        return usable and not forced

    def finish(self, end_ns: int | None) -> None:
        """Close an outage still open.

        Parameters
        ----------
        end_ns : int or None
            Its end, ns (the last IMU sample); None: at its start.
        """
        if self._open is not None:
            self._open.end_ns = end_ns if end_ns is not None else self._open.start_ns
            self._outages.append(self._open)
            self._open = None

    def take(self) -> list[Outage]:
        """The windows not yet returned.

        Returns
        -------
        list of Outage
            The outages closed since the last call, in time order ([start_ns, end_ns) UTC); the tracker forgets
            them.
        """
        out, self._outages = self._outages, []
        return out


class Silence:
    """Turns a GPS silence into no-fix epochs (``silent``) at the nominal fix interval: the median of the first
    ``SPACINGS`` intervals."""

    SPACINGS = 10

    def __init__(self) -> None:
        self.real_ns: int | None = None  # the last real epoch
        self.last_ns: int | None = None  # the last epoch queued, real or silent
        self.spacings: list[int] = []
        self.period_ns: float | None = None

    def add(self, queue: list[Epoch], epochs: list[Epoch], horizon_ns: int | None) -> None:
        """Append ``epochs`` to ``queue``. In a silence (more than 1.5 intervals since the last real epoch) a
        silent epoch goes in at every nominal interval up to the next real epoch (not within half an interval of
        it) and up to ``horizon_ns``.

        Parameters
        ----------
        queue : list of Epoch
            The engine's epoch queue, appended to in place.
        epochs : list of Epoch
            The block's real epochs, in time order.
        horizon_ns : int or None
            The IMU's last sample, ns (a fix before it would be in this block); None: no silent epochs after the
            last real one.
        """
        for ep in epochs:
            t = ep.t_ns
            if self.real_ns is not None and t > self.real_ns:
                if not self._fill(queue, t, t - 0.5 * (self.period_ns or 0.0)) and len(self.spacings) < self.SPACINGS:
                    self.spacings.append(t - self.real_ns)
                    self.period_ns = median(self.spacings)
            queue.append(ep)
            self.real_ns = max(t, self.real_ns or t)
            self.last_ns = max(t, self.last_ns or t)
        if horizon_ns is not None:
            self._fill(queue, horizon_ns, horizon_ns)

    def _fill(self, queue: list[Epoch], until_ns: int, last_ns: float) -> bool:
        """Silent epochs up to ``last_ns`` when the silence lasts until ``until_ns``; whether there were any."""
        if self.period_ns is None or self.real_ns is None or until_ns - self.real_ns <= 1.5 * self.period_ns:
            return False
        while self.last_ns + self.period_ns < last_ns:
            self.last_ns += int(round(self.period_ns))
            queue.append(Epoch.silence(self.last_ns))
        return True


class PredictorBridge:
    """The outage predictor of a method with a bridge (``fusion.methods.Bridge``), fed and asked by the engine at GPS
    epochs.

    Not hybrid (``rbfn``, ``tdln``): the predictor alone (section 2.2); targets z = INS - GPS, the prediction is the
    correction. Hybrid (``dkf-rbfn``): section 2.3, eq. 7; targets the local filters' innovation components, velocity from
    KF_I and position from KF_II; the prediction is added to the local filters' state prediction
    (``DistributedKF.predicted_update``)."""

    def __init__(self, bridge: Bridge, config: predictors.PredictorConfig,
                 make: Callable[[str, predictors.PredictorConfig], Any] | None = None) -> None:
        """``make(network, config)``: the predictor, anything with the ``train`` and ``predict`` of
        :class:`fusion.predictors.OutagePredictor` (one that trains it elsewhere, e.g. in another process); None:
        an OutagePredictor here."""
        self.hybrid = bridge.hybrid
        self.predictor = (make or predictors.OutagePredictor)(bridge.network, config)
        self.origin: tuple[float, float, float] | None = None  # lat, lon, h of the alignment point

    def input(self, nav: NavState) -> np.ndarray:
        """The networks' input.

        Parameters
        ----------
        nav : NavState
            The INS state.

        Returns
        -------
        np.ndarray
            (6,) its position (ENU, m from the alignment point) and velocity (ENU, m/s).
        """
        r = kf.enu_offset(nav.lat, nav.lon, nav.h, *self.origin)
        return np.concatenate([r, nav.v_n])

    def train(self, t_s: float, u: np.ndarray, innovations: tuple[np.ndarray, np.ndarray], pos: kf.Measurement,
              vel: kf.Measurement | None) -> None:
        """Train on a usable epoch.

        Parameters
        ----------
        t_s : float
            The epoch, s.
        u : np.ndarray
            (6,) the input (:meth:`input`) before the update.
        innovations : tuple of np.ndarray
            The local filters' innovation components (KF_I, KF_II) of this update, (15,) each.
        pos, vel : kf.Measurement
            The GPS position and velocity measurements (vel None without one).
        """
        if self.hybrid:
            dx_vel, dx_pos = innovations
            y = np.concatenate([dx_pos[POS], dx_vel[VEL]])
            if vel is None:
                y[3:] = np.nan
        else:
            y = _observation(pos, vel)
        self.predictor.train(t_s, u, y)

    def prediction(self, nav: NavState) -> np.ndarray | None:
        """The prediction at an outage epoch.

        Parameters
        ----------
        nav : NavState
            The INS state at the epoch (the networks' input, :meth:`input`).

        Returns
        -------
        np.ndarray or None
            (6,) the predicted target (position E, N, U, m; velocity ENU, m/s), NaN-free; None if no channel
            predicts.
        """
        d = np.nan_to_num(self.predictor.predict(self.input(nav)))  # a channel without a model: none
        return d if d.any() else None

    @staticmethod
    def as_state(d: np.ndarray) -> np.ndarray:
        """A prediction as an error state.

        Parameters
        ----------
        d : np.ndarray
            (6,) predicted position (m) and velocity (m/s), ENU.

        Returns
        -------
        np.ndarray
            (15,) the error state with them in its position and velocity rows.
        """
        x = np.zeros(N_STATES)
        x[POS], x[VEL] = d[:3], d[3:]
        return x


def _observation(pos: kf.Measurement, vel: kf.Measurement | None) -> np.ndarray:
    """z = INS - GPS as (6,): position E, N, U (m), velocity E, N, U (m/s); NaN for a component not measured."""
    out = np.full(6, np.nan)
    for m, cols, at in ((pos, POS, 0), (vel, VEL, 3)):
        if m is not None and len(m[0]):
            out[at + np.argmax(np.abs(m[1][:, cols]), axis=1)] = m[0]
    return out
