"""The solution rows the engine produces: the (closed-loop) INS state at the first IMU sample of each
1/output_hz slot of UTC (10 Hz by default), stamped with that sample's time, with the filter's sigmas; the
position's with the time-correlated GPS error the filters do not model added (:func:`correlated_variance`);
and their status (:class:`StatusBook`), as an INS receiver reports its solution's (NovAtel SPAN's INS status, a
VBOX's IMU coast).

The status of a row is the highest that applies of

- ``aligning``: no solution yet (the alignment gathers its still interval or waits for speed): a status row at
  each output slot, without a solution row;
- ``aligned``: the INS runs from its alignment; no GNSS fix has updated it yet;
- ``aided`` or ``coasting``: the last GNSS epoch updated the filter, or it did not (an outage: no fix, low
  quality, injected or silent), with the seconds from the last update's fix time to the row in both;
- ``degraded``: the horizontal position sigma is above ``status_max_sigma_m``;
- ``diverged``: the normalised innovation squares (NIS, y^T S^-1 y over the degrees of freedom, S = H P H^T +
  R) of the last ``NIS_FIXES`` GNSS updates average above ``status_diverged_nis``: the filter no longer
  explains the GNSS by its own covariance, as with a wrong IMU frame. A consistent filter's mean is near 1
  and passes 3 by chance with probability below 1e-4 over 5 updates of 3 degrees of freedom: the default 25
  (innovations of 5 sigma RMS) leaves room for the receiver's error the filter does not model. Or the row is
  not finite.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from fieldlog.fusion import earth, kf
from fieldlog.fusion.types import Solution, Status

if TYPE_CHECKING:
    from fieldlog.fusion.config import FilterConfig
    from fieldlog.fusion.ins import NavSolution

NS = 1_000_000_000
STATUS = ("aligning", "aligned", "aided", "coasting", "degraded", "diverged")  # the codes 0..5 of Status.code
ALIGNING, ALIGNED, AIDED, COASTING, DEGRADED, DIVERGED = range(len(STATUS))
NIS_FIXES = 5  # the GNSS updates the divergence test averages over


def sigmas(diag: np.ndarray) -> np.ndarray:
    """Position, velocity, attitude and IMU bias sigmas (..., 15) from covariance diagonals (..., 15).

    Parameters
    ----------
    diag : (..., 15) array_like, covariance diagonals, ``fusion.errmodel`` order and units squared

    Returns
    -------
    (..., 15) ndarray
        Standard deviations (negative variances read as 0), ``fusion.errmodel`` units.
    """
    return np.sqrt(np.maximum(np.asarray(diag)[..., :15], 0.0))


def output_rows(t_ns: np.ndarray, output_hz: float) -> np.ndarray:
    """Indices of the samples t_ns (n,) UTC that start a 1/output_hz slot, after the first sample.

    Parameters
    ----------
    t_ns : (n,) int64 ndarray, sample times, UTC ns
    output_hz : float, output rate, Hz

    Returns
    -------
    (k,) int ndarray
        Sample indices.
    """
    bucket = np.floor(t_ns / (NS / output_hz)).astype(np.int64)
    return np.flatnonzero(np.diff(bucket) != 0) + 1


@dataclass
class Segment:
    """An INS segment whose solution rows are still to be made (:func:`rows`): the INS solution ``sol``
    (``fusion.ins.NavSolution``) over samples t_ns (n >= 2,) UTC; the covariance diagonals diag (m, 15) after the
    filter cycles ending at samples ends (m,); bias (6,) the segment's gyro (rad/s) and accelerometer (m/s^2) bias
    estimate, body RFU; gps_var (3,) m^2 added to the position variances (``correlated_variance``); local: the
    distributed filter's local estimates and variances after each cycle, (m, 2, 15) each, or None, gps_var_local
    (3,) m^2 added to KF_II's; state: the status the ``StatusBook`` gave at the segment's end (``StatusBook.now``)."""

    sol: NavSolution
    t_ns: np.ndarray
    ends: np.ndarray
    diag: np.ndarray
    bias: np.ndarray
    gps_var: np.ndarray
    local: tuple[np.ndarray, np.ndarray] | None
    gps_var_local: np.ndarray
    state: tuple[int, int | None, float]


def rows(segments: list[Segment], output_hz: float) -> tuple[Solution, np.ndarray]:
    """Solution rows of consecutive INS segments (each starts at the sample the one before ended at), made in one
    pass: the rows of each segment's samples after its first, one per output slot started (``output_rows``).

    Parameters
    ----------
    segments : list of Segment, at least one
    output_hz : float, output rate, Hz

    Returns
    -------
    (Solution, (k,) int ndarray)
        The rows (without status), and the index into ``segments`` of each row's segment.
    """
    first = segments[0]
    sizes = np.array([len(g.t_ns) - 1 for g in segments])
    start = np.cumsum(sizes) - sizes  # each segment's first sample, counted over the segments' samples

    def joined(name: str) -> np.ndarray:  # the segments' samples, each shared first one once
        arrays = [getattr(g.sol, name) for g in segments]
        return np.concatenate([arrays[0][:1]] + [a[1:] for a in arrays])

    t_ns = np.concatenate([first.t_ns[:1]] + [g.t_ns[1:] for g in segments])
    r = output_rows(t_ns, output_hz)
    seg = np.searchsorted(start + sizes, r)
    cyc = np.searchsorted(np.concatenate([g.ends + k for g, k in zip(segments, start)]), r)
    sig = sigmas(np.concatenate([g.diag for g in segments]))[cyc]
    sig[:, :3] = np.sqrt(sig[:, :3] ** 2 + np.array([g.gps_var for g in segments])[seg])
    lat, lon, h, v_n = (joined(name)[r] for name in ("lat", "lon", "h", "v_n"))
    loc = None
    if first.local is not None:
        x = np.concatenate([g.local[0] for g in segments])[cyc]  # (k, 2, 15)
        d = np.concatenate([g.local[1] for g in segments])
        d[:, 1, 0:3] += np.repeat([g.gps_var_local for g in segments], [len(g.ends) for g in segments], axis=0)
        d = d[cyc]
        loc = np.empty((len(r), 2, 12))
        for i in range(2):
            loc[:, i, 0:6] = corrected(lat, lon, h, v_n, x[:, i])
            loc[:, i, 6:12] = np.sqrt(np.maximum(d[:, i, 0:6], 0.0))
    return Solution(t_ns[r], lat, lon, h, v_n, joined("q")[r], sig,
                    np.array([np.asarray(g.bias, float) for g in segments])[seg], loc), seg


def finite(s: Solution) -> np.ndarray:
    """Rows (n,) bool of s whose position, velocity, attitude, sigmas and bias are all finite.

    Parameters
    ----------
    s : Solution

    Returns
    -------
    (n,) bool ndarray
    """
    return (np.isfinite(s.lat) & np.isfinite(s.lon) & np.isfinite(s.h) & np.isfinite(s.v_n).all(axis=1)
            & np.isfinite(s.q).all(axis=1) & np.isfinite(s.sigma).all(axis=1) & np.isfinite(s.bias).all(axis=1))


class StatusBook:
    """What the status of the engine's rows depends on (module docstring), kept as the epochs go by: the fix
    time of the last GNSS update, whether the last epoch updated the filter, the NIS of the last ``NIS_FIXES``
    updates. ``cfg``: the ``fusion.config.FilterConfig`` (output rate, the thresholds)."""

    def __init__(self, cfg: FilterConfig) -> None:
        self.cfg = cfg
        self.last_update_ns: int | None = None
        self.aided = False
        self.nis: deque[float] = deque(maxlen=NIS_FIXES)
        self._nis_mean = math.nan  # of the last NIS_FIXES NIS, NaN before as many

    def epoch(self, usable: bool) -> bool:
        """A GPS epoch after the alignment (usable or not: its fix may update the filter); returns usable.

        Parameters
        ----------
        usable : bool, whether the epoch's fix may update the filter

        Returns
        -------
        bool
            ``usable``.
        """
        self.aided = False
        return usable

    def fix(self, t_ns: int, m: kf.Measurement, filt: kf.KalmanFilter) -> None:
        """The fix of the epoch at t_ns UTC updates the filter ``filt`` (any of ``fusion.filters``; called before
        the update: its state and covariance are the prior) with the epoch's observations, stacked as m: their NIS
        is kept.

        Parameters
        ----------
        t_ns : int, fix time, UTC ns
        m : kf.Measurement, the epoch's observations stacked (``kf.stack``)
        filt : kf.KalmanFilter, the filter before the update
        """
        if len(m[0]):  # (a fix whose measurements kept no row has no innovation to test)
            self.nis.append(kf.nis(filt.state, filt.covariance, m))
        if len(self.nis) == NIS_FIXES:
            total = 0.0
            for x in self.nis:  # one after the other, numpy's order for so few (sum() may compensate)
                total += x
            self._nis_mean = total / NIS_FIXES
        self.last_update_ns, self.aided = t_ns, True

    def aligning(self, t_ns: np.ndarray) -> Solution:
        """No solution rows, the status rows of samples t_ns (n,) UTC before the alignment: ``aligning`` at each
        output slot's start after the first sample, nothing else known.

        Parameters
        ----------
        t_ns : (n,) int64 ndarray, sample times before the alignment, UTC ns

        Returns
        -------
        Solution
            No rows, ``status`` with one ``aligning`` row per output slot.
        """
        t = t_ns[output_rows(t_ns, self.cfg.output_hz)]
        nan = np.full(len(t), np.nan)
        empty = Solution.concat([])
        empty.status = Status(t, np.full(len(t), ALIGNING, np.uint8), nan, nan.copy(), nan.copy())
        return empty

    def now(self) -> tuple[int, int | None, float]:
        """What the status of rows made now depends on: their code before the sigma and NIS tests (aligned, aided
        or coasting), the last update's fix time (UTC ns, None before it) and the mean NIS of the last
        ``NIS_FIXES`` updates (NaN before as many).

        Returns
        -------
        (int, int or None, float)
        """
        code = ALIGNED if self.last_update_ns is None else AIDED if self.aided else COASTING
        return code, self.last_update_ns, self._nis_mean

    def of(self, s: Solution, seg: np.ndarray, states: list[tuple[int, int | None, float]]) -> Solution:
        """The solution rows s with their status.

        Parameters
        ----------
        s : Solution, rows without status
        seg : (n,) int ndarray, the index into ``states`` of each row
        states : list of :meth:`now`'s results, each as it was when its rows were made

        Returns
        -------
        Solution
            ``s`` itself, its ``status`` set.
        """
        code, last_ns, nis = (np.array(x)[seg] for x in zip(*[(c, t or 0, m) for c, t, m in states]))
        known = np.array([t is not None for _, t, _ in states], bool)[seg]
        code = code.astype(np.uint8)
        sigma_h = np.hypot(s.sigma[:, 0], s.sigma[:, 1])
        code[sigma_h > self.cfg.status_max_sigma_m] = DEGRADED
        code[nis > self.cfg.status_diverged_nis] = DIVERGED
        code[~finite(s)] = DIVERGED
        since = np.where(known, (s.t_ns - last_ns.astype(np.int64)) * 1e-9, np.nan)
        s.status = Status(s.t_ns.copy(), code, since, sigma_h, nis.astype(float))
        return s


def corrected(lat: np.ndarray, lon: np.ndarray, h: np.ndarray, v_n: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Position and velocity (n,) rad, rad, m and (n, 3) ENU m/s corrected by error states x (n, 15) as
    ``kf.correct_ins`` does: (n, 6) lat, lon, h, v_n.

    Parameters
    ----------
    lat, lon : (n,) ndarray, rad
    h : (n,) ndarray, ellipsoidal height, m
    v_n : (n, 3) ndarray, velocity, ENU, m/s
    x : (n, 15) ndarray, error states (computed - true), ``fusion.errmodel`` order and units

    Returns
    -------
    (n, 6) ndarray
        lat, lon (rad), h (m), v_n (ENU, m/s).
    """
    rm, rn = earth.principal_radii(lat, h)
    return np.column_stack([lat - x[:, 1] / rm, lon - x[:, 0] / (rn * np.cos(lat)), h - x[:, 2], v_n - x[:, 3:6]])


def correlated_variance(r: np.ndarray, p: np.ndarray, period_s: float, tau_s: float) -> np.ndarray:
    """Variance (m^2, per axis) of the time-correlated GPS position error left in the filter's position: a
    Schmidt "consider" term for the error the 15-state filters do not model (every filter gets it, none changes).

    The filters treat each fix's error (variance r, the receiver's figure) as white: after the update the
    position variance p ~ r / N says the solution averages N = r / p fixes, over T = N x period_s. A first-order
    Gauss-Markov error of correlation time tau_s averaged over T keeps the variance r f(T / tau_s),
    f(x) = 2 (x - 1 + exp(-x)) / x^2 (1 at x = 0: fully correlated; 2 / x for x >> 1: as white). It is added to
    the printed position variance; in an outage it stays, as the error taken in from the last fixes does.
    tau_s = 0: white errors, nothing added. Axes without a figure (NaN) get 0.

    Parameters
    ----------
    r : (3,) ndarray, the fix's position variance per ENU axis, m^2 (NaN: none)
    p : (3,) ndarray, the filter's position variance per ENU axis after the update, m^2
    period_s : float, time between fixes, s
    tau_s : float, correlation time of the GPS error, s (0: white)

    Returns
    -------
    (3,) ndarray
        Variance to add per ENU axis, m^2.
    """
    # per axis in floats, each step the IEEE operation numpy's would be; the exponential numpy's own
    r = [v if math.isfinite(v) else 0.0 for v in r.tolist()]
    if tau_s <= 0.0:
        return np.zeros(len(r))
    x = [max(a / max(b, 1e-12), 1.0) * period_s / tau_s for a, b in zip(r, p.tolist())]
    decay = np.exp(-np.array(x)).tolist()
    f = [1.0 - v / 3.0 if v < 1e-4 else 2.0 * (v - 1.0 + d) / (max(v, 1e-4) * max(v, 1e-4)) for v, d in zip(x, decay)]
    return np.array([a * b for a, b in zip(r, f)])
