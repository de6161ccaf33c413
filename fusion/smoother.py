"""Rauch-Tung-Striebel smoothing of the closed-loop error-state filter, for post-drive reprocessing.

Formulation. The forward filter (``fusion.engine``) is closed loop: its error state is zero after every
GPS epoch, the correction dx_k = x_{k|k} having been fed into the INS. Records k = 0..N-1 are the ends
of the covariance cycles (``[fusion] cov_step_s``, 0.1 s) plus the alignment; each stores

- Phi_k, the transition from record k-1 to k,
- P-_k, the covariance predicted to k (before any update at k),
- P+_k, the covariance after the update at k (P-_k where there was none),
- dx_k, the correction applied to the INS at k (zero where there was none).

Let y_k = (forward solution after the correction at k) - truth. The error of the INS just before the
correction at k is e_k = y_k + dx_k (``correct_ins`` subtracts dx). Forward, e_{k+1} is predicted from
y_k = 0 as 0 with covariance P-_{k+1}, and filtered at k as y_k = 0 with P+_k. The RTS backward pass on
that linear model is therefore::

    y_{N-1} = 0,   Ps_{N-1} = P+_{N-1}
    C_k  = P+_k Phi_{k+1}^T (P-_{k+1})^-1
    y_k  = C_k (y_{k+1} + dx_{k+1})
    Ps_k = P+_k + C_k (Ps_{k+1} - P-_{k+1}) C_k^T

Predicted corrections (the outage predictors' ``bridge``) are known inputs, not estimates: after one the
forward mean of the error is -b, not 0; the filter never learns of it (its state stays 0), and at its next
update fed back K z computed from a zero prior. The backward pass then runs on the forward means
m-_{k+1} = Phi_{k+1} m+_k, m+_k = P+_k (P-_k)^-1 m-_k - b_k (``_filtered_means``)::

    y_k = m+_k + C_k (y_{k+1} + dx_{k+1} - m-_{k+1})

Treating b as an estimate instead makes the smoother believe a wrong prediction: a predicted velocity
correction is carried back through the outage as a position error, largest at the outage's start.

and the smoothed state is the forward solution corrected by y_k, as ``correct_ins`` would. A solution
row between records k-1 and k (stamped before the update at k) has forward error interpolated linearly
in time between y_{k-1} and y_k + dx_k; the jump of the forward solution at an update disappears.

The consider sensitivity S (``fusion.consider``) is smoothed the same way, Ss_k = S+_k + C_k (Ss_{k+1} - S-_{k+1}),
its variance added to the smoothed accelerometer-bias variance.

Memory: a record is 3 x 15 x 15 + 2 x 15 + 2 x 15 x 9 float64 + the time, 7.8 kB; a 1-hour drive at 10 Hz is
36 000 records, about 280 MB. :class:`SmootherLog` keeps only the last ``chunk`` records in memory and spills the
rest to an anonymous temporary file; :func:`rts` reads that file backwards a chunk at a time and writes, per
record, y, the diagonal of Ps and dx (360 bytes) to another (:class:`Smoothed`), which :func:`row_errors` reads
back for the records a block of rows lies between. Memory then grows only by the records' times (8 bytes per
record); :func:`smoothed_blocks` smooths rows kept out of memory (a spill file) a block at a time.
"""

from __future__ import annotations

from typing import Iterable, Iterator

import numpy as np

from fieldlog.fusion import earth
from fieldlog.fusion.consider import N_PARAMS
from fieldlog.fusion.errmodel import ATT, N_STATES, POS, VEL, cycle_kernel
from fieldlog.fusion.rowfile import RowFile
from fieldlog.fusion.types import Solution

RECORD = np.dtype([("t_ns", "<i8"), ("phi", "<f8", (N_STATES, N_STATES)), ("pm", "<f8", (N_STATES, N_STATES)),
                   ("pp", "<f8", (N_STATES, N_STATES)), ("dx", "<f8", N_STATES), ("b", "<f8", N_STATES),
                   ("sm", "<f8", (N_STATES, N_PARAMS)), ("sp", "<f8", (N_STATES, N_PARAMS))])
_OFFSETS = np.array([RECORD.fields[k][1] for k in ("phi", "pm", "pp", "dx", "sm", "sp")], np.int64)  # bytes


class SmootherLog:
    """What the forward filter hands to the smoother; ``fusion.engine.Engine(..., log=SmootherLog())`` fills it.

    Records (``RECORD``) beyond the last ``chunk`` are spilled to an anonymous temporary file."""

    def __init__(self, chunk: int = 1024) -> None:
        self.chunk = int(chunk)
        self._spill = RowFile(RECORD)
        self._pending: list[np.ndarray] = []  # record arrays not yet spilled, in order
        self._n_pending = 0
        self.bridged = False
        self.gps_var: list[tuple[int, np.ndarray]] = []  # (t_ns, m^2 E N U) from each GPS update on: output.correlated_variance
        self.var_c: np.ndarray | None = None  # the consider parameters' variances (fusion.consider), None: none

    def __len__(self) -> int:
        return len(self._spill) + self._n_pending

    def close(self) -> None:
        """Delete the spill file."""
        self._spill.close()

    def start(self, t_ns: int, P0: np.ndarray) -> None:
        """The filter's initial covariance at t_ns (alignment).

        Parameters
        ----------
        t_ns : int, alignment time, UTC ns
        P0 : (15, 15) ndarray, initial error covariance, ``fusion.errmodel`` units squared
        """
        self.cycles(np.array([t_ns], np.int64), np.eye(N_STATES)[None], np.asarray(P0, float)[None])

    def cycles(self, t_ns: np.ndarray, Phi: np.ndarray, P_pred: np.ndarray) -> None:
        """Covariance cycles ending at t_ns (m,) int64 UTC: Phi (m, 15, 15), predicted P (m, 15, 15).

        Parameters
        ----------
        t_ns : (m,) int64 ndarray, cycle end times, UTC ns
        Phi : (m, 15, 15) ndarray, transition matrix of each cycle
        P_pred : (m, 15, 15) ndarray, covariance predicted to each cycle end, ``fusion.errmodel`` units squared
        """
        if len(t_ns) == 0:
            return
        r = np.zeros(len(t_ns), RECORD)
        r["t_ns"], r["phi"], r["pm"], r["pp"] = t_ns, Phi, P_pred, P_pred
        if self._n_pending >= self.chunk:  # spill all but the last array: an update may still come to its end
            for a in self._pending[:-1]:
                self._spill.append(a)
            self._pending = self._pending[-1:]
            self._n_pending = len(self._pending[0])
        self._pending.append(r)
        self._n_pending += len(r)

    def update(self, dx: np.ndarray, P_upd: np.ndarray) -> None:
        """The update at the last recorded cycle end (the engine updates only there): correction dx (15,)
        fed back, covariance after it. A second update at the same instant adds its correction (linear).

        Parameters
        ----------
        dx : (15,) ndarray, correction fed into the INS, ``fusion.errmodel`` order and units
        P_upd : (15, 15) ndarray, covariance after the update, ``fusion.errmodel`` units squared
        """
        self._pending[-1]["dx"][-1] += dx
        self._pending[-1]["pp"][-1] = P_upd

    def sensitivity(self, S: np.ndarray) -> None:
        """The consider sensitivity (``fusion.consider``) after each of the cycles last recorded, (m, 15, 9).

        Parameters
        ----------
        S : (m, 15, 9) ndarray, d(error state)/d(consider parameters) at each of the last m cycle ends
        """
        self._pending[-1]["sm"] = S
        self._pending[-1]["sp"] = S

    def sensitivity_update(self, S: np.ndarray) -> None:
        """The consider sensitivity after the update at the last recorded cycle end, (15, 9).

        Parameters
        ----------
        S : (15, 9) ndarray, d(error state)/d(consider parameters) after the update
        """
        self._pending[-1]["sp"][-1] = S

    def bridge(self, b: np.ndarray) -> None:
        """A predicted correction b (15,) fed into the INS at the last recorded cycle end (``rbfn``, ``tdln``,
        ``dkf-rbfn`` in outages): a known input, not an estimate (module docstring).

        Parameters
        ----------
        b : (15,) ndarray, the predicted correction, ``fusion.errmodel`` order and units
        """
        self._pending[-1]["dx"][-1] += b
        self._pending[-1]["b"][-1] += b
        self.bridged = True

    def read(self, i0: int, i1: int) -> np.ndarray:
        """Records [i0, i1) (``RECORD``).

        Parameters
        ----------
        i0, i1 : int, record indices, 0 <= i0 < i1 <= len(self)

        Returns
        -------
        (i1 - i0,) ndarray of ``RECORD``
        """
        parts, spilled = [], len(self._spill)
        if i0 < spilled:
            parts.append(self._spill.read(i0, min(i1, spilled)))
        if i1 > spilled:
            tail = np.concatenate(self._pending)
            parts.append(tail[max(i0 - spilled, 0):i1 - spilled])
        return np.concatenate(parts)

    def arrays(self) -> tuple[np.ndarray, ...]:
        """(t_ns (N,), Phi, P-, P+ (N, 15, 15), dx (N, 15)), all in memory (small logs, tests).

        Returns
        -------
        tuple of ndarray, one row per record: t_ns (N,) int64 UTC ns; Phi (N, 15, 15) from the record before;
        P-, P+ (N, 15, 15) before and after its update, ``fusion.errmodel`` units squared; dx (N, 15) the
        correction fed into the INS there, ``fusion.errmodel`` order and units.
        """
        r = self.read(0, len(self))
        return r["t_ns"], r["phi"], r["pm"], r["pp"], r["dx"]


class Smoothed:
    """The smoothed error of the forward solution after each record (:func:`rts`): the records' times ``t_ns`` (N,)
    in memory; per record, in an anonymous temporary file, y (15,), its covariance diagonal P_diag (15,) and dx
    (15,), the forward correction (for the rows stamped before it). ``fusion.errmodel`` order and units."""

    def __init__(self, t_ns: np.ndarray) -> None:
        self.t_ns = t_ns
        self._rows = RowFile(("<f8", 3 * N_STATES))  # per record: y, P_diag, dx

    def write(self, i0: int, y: np.ndarray, P_diag: np.ndarray, dx: np.ndarray) -> None:
        """Write records [i0, i0 + m).

        Parameters
        ----------
        i0 : int, the first record's index
        y, P_diag, dx : (m, 15) ndarray each, the smoothed error, its variance and the forward correction,
            ``fusion.errmodel`` order and units (squared for P_diag)
        """
        self._rows.write(i0, np.concatenate([y, P_diag, dx], axis=1))

    def read(self, i0: int, i1: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Records [i0, i1).

        Parameters
        ----------
        i0, i1 : int, record indices, 0 <= i0 <= i1 <= N

        Returns
        -------
        (y, P_diag, dx) : (i1 - i0, 15) ndarray each, ``fusion.errmodel`` order and units (squared for P_diag)
        """
        a = self._rows.read(i0, i1)
        return a[:, :N_STATES], a[:, N_STATES:2 * N_STATES], a[:, 2 * N_STATES:]

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every record, all in memory (small logs, tests).

        Returns
        -------
        (y, P_diag, dx) : (N, 15) ndarray each, ``fusion.errmodel`` order and units (squared for P_diag)
        """
        return self.read(0, len(self.t_ns))

    def close(self) -> None:
        """Delete the file."""
        self._rows.close()


def rts(log: SmootherLog) -> Smoothed | None:
    """The backward pass (module docstring) over the records of a :class:`SmootherLog`, a chunk at a time, compiled
    (``fieldlog_rts_chunk`` in fusion/_cycles.c: numpy's formulas, to rounding); None with fewer than two records
    (nothing to smooth).

    Parameters
    ----------
    log : SmootherLog, the records of a forward run

    Returns
    -------
    Smoothed or None
        To be closed by the caller (its temporary file).
    """
    n = len(log)
    if n < 2:
        return None
    sm = Smoothed(np.zeros(n, np.int64))
    m_pred, m_upd = _filtered_means(log) if log.bridged else (None, None)
    Ps, Ss = np.zeros((N_STATES, N_STATES)), np.zeros((N_STATES, N_PARAMS))  # record k + 1's, then k's
    var_c = None if log.var_c is None else np.ascontiguousarray(log.var_c, float)
    nxt = None  # the record after the chunk
    y_next = np.zeros(N_STATES)  # its smoothed error (the kernel reads it after the chunk's rows)
    for i1 in range(n, 0, -log.chunk):
        i0 = max(i1 - log.chunk, 0)
        r = np.ascontiguousarray(log.read(i0, i1))
        y, d = np.zeros((len(r) + 1, N_STATES)), np.zeros((len(r), N_STATES))
        y[-1] = y_next
        if cycle_kernel().fieldlog_rts_chunk(len(r), r.ctypes.data, RECORD.itemsize, _OFFSETS.ctypes.data,
                                             _address(nxt), Ps.ctypes.data, Ss.ctypes.data, _address(m_pred, i0),
                                             _address(m_upd, i0), _address(var_c), y.ctypes.data, d.ctypes.data):
            sm.close()
            raise np.linalg.LinAlgError("Singular matrix: a predicted covariance of the smoother's records")
        sm.t_ns[i0:i1] = r["t_ns"]
        sm.write(i0, y[:-1], d, r["dx"])
        nxt, y_next = r[:1].copy(), y[0]
    return sm


def _address(a: np.ndarray | None, row: int = 0) -> int | None:
    """The address of row ``row`` of a C-contiguous array, None for None (a NULL pointer)."""
    return None if a is None else a[row:].ctypes.data


def _filtered_means(log: SmootherLog) -> tuple[np.ndarray, np.ndarray]:
    """Forward means of the error before (m-) and after (m+) the corrections of each record, (N, 15) each, when
    predicted corrections b were fed in: m-_k = Phi_k m+_{k-1}, m+_k = P+_k (P-_k)^-1 m-_k - b_k (the filter's
    own update, K z, was fed back; (I - K H) m- = P+ (P-)^-1 m- of the input-aware mean remains)."""
    n = len(log)
    m_pred, m_upd = np.zeros((n, N_STATES)), np.zeros((n, N_STATES))
    m = np.zeros(N_STATES)
    for i0 in range(0, n, log.chunk):
        r = log.read(i0, min(i0 + log.chunk, n))
        for j in range(len(r)):
            mp = r["phi"][j] @ m
            m = (r["pp"][j] @ np.linalg.solve(r["pm"][j], mp) if mp.any() else mp) - r["b"][j]
            m_pred[i0 + j], m_upd[i0 + j] = mp, m
    return m_pred, m_upd


def row_errors(sm: Smoothed, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Smoothed error (n, 15) and its covariance diagonal (n, 15) of forward solution rows at t_ns (n,).

    A row in (t_{k-1}, t_k] is the INS before the update at k: the error runs from y_{k-1} to y_k + dx_k.

    Parameters
    ----------
    sm : Smoothed, the backward pass (:func:`rts`)
    t_ns : (n,) int64 array_like, row times, UTC ns

    Returns
    -------
    e : (n, 15) ndarray, smoothed error (computed - true), ``fusion.errmodel`` order and units
    var : (n, 15) ndarray, its variance, units squared
    """
    t_ns = np.asarray(t_ns, np.int64)
    k = np.searchsorted(sm.t_ns, t_ns, side="left").clip(1, max(len(sm.t_ns) - 1, 1))
    t0, t1 = sm.t_ns[k - 1], sm.t_ns[k]
    a = np.clip((t_ns - t0) / np.maximum(t1 - t0, 1), 0.0, 1.0)[:, None]
    lo = int(k.min()) - 1 if len(k) else 0  # the records the rows lie between, read from sm's file
    y, P_diag, dx = sm.read(lo, int(k.max()) + 1 if len(k) else 0)
    k = k - lo
    e = (1.0 - a) * y[k - 1] + a * (y[k] + dx[k])
    return e, (1.0 - a) * P_diag[k - 1] + a * P_diag[k]


def correct(lat: np.ndarray, lon: np.ndarray, h: np.ndarray, v_n: np.ndarray, q: np.ndarray, e: np.ndarray
            ) -> tuple[np.ndarray, ...]:
    """Remove errors e (n, 15) (computed - true, ``fusion.errmodel`` order) from navigation rows: lat, lon
    (rad), h (m), v_n (n, 3) ENU m/s, q (n, 4) [x, y, z, w] of C_bn. Vectorised ``kf.correct_ins``.

    Parameters
    ----------
    lat, lon : (n,) ndarray, rad
    h : (n,) ndarray, ellipsoidal height, m
    v_n : (n, 3) ndarray, velocity, ENU, m/s
    q : (n, 4) ndarray, ``[x, y, z, w]`` quaternion of ``C_bn`` (body RFU -> ENU)
    e : (n, 15) ndarray, errors (computed - true), ``fusion.errmodel`` order and units

    Returns
    -------
    tuple of ndarray
        (lat, lon, h, v_n, q) corrected, same shapes and units; q unit with w >= 0.
    """
    rm, rn = earth.principal_radii(lat, h)
    dr = e[:, POS]
    q2 = earth.quat_multiply(earth.rotvec_to_quat(e[:, ATT]), q)
    q2 /= np.linalg.norm(q2, axis=1, keepdims=True)
    q2 *= np.where(q2[:, 3:4] < 0.0, -1.0, 1.0)
    return lat - dr[:, 1] / rm, lon - dr[:, 0] / (rn * np.cos(lat)), h - dr[:, 2], v_n - e[:, VEL], q2


def smooth_solution(sol: Solution, log: SmootherLog, rows: int = 10_000) -> Solution:
    """The forward solution rows of a whole drive, smoothed with the records of the same run, ``rows`` at a time
    (:func:`smoothed_blocks`: the same rows, its temporaries bounded).

    Parameters
    ----------
    sol : Solution, the forward solution rows of the drive
    log : SmootherLog, the records of the same forward run
    rows : int, the rows smoothed at a time

    Returns
    -------
    Solution
        The smoothed rows (sigma the smoothed standard deviations).
    """
    fields = ("t_ns", "lat", "lon", "h", "v_n", "q", "sigma", "bias")  # what smooth_rows reads of a row
    parts = (Solution(*(getattr(sol, k)[i:i + rows] for k in fields)) for i in range(0, len(sol.t_ns), rows))
    return Solution.concat(list(smoothed_blocks(parts, log)))


def smoothed_blocks(blocks: Iterable[Solution], log: SmootherLog) -> Iterator[Solution]:
    """A drive's forward solution rows, given block by block in order, smoothed block by block with the records of
    the same run (:func:`rts` once, then :func:`smooth_rows` per block); memory bounded by a block and a chunk of
    records, whatever the drive's length.

    Parameters
    ----------
    blocks : iterable of Solution, the forward rows of the run in time order (e.g. read back from a spill file)
    log : SmootherLog, the records of the same forward run

    Returns
    -------
    Iterator of Solution
        Each block's rows smoothed (sigma the smoothed standard deviations).
    """
    sm = rts(log)
    gps_var = ((np.array([t for t, _ in log.gps_var], np.int64), np.array([v for _, v in log.gps_var]))
               if log.gps_var else None)
    try:
        for sol in blocks:
            yield smooth_rows(sol, sm, gps_var)
    finally:
        if sm is not None:
            sm.close()


def smooth_rows(sol: Solution, sm: Smoothed | None, gps_var: tuple[np.ndarray, np.ndarray] | None) -> Solution:
    """Forward solution rows (any block of them) smoothed with ``sm`` (``rts`` of a run's ``SmootherLog``, None:
    too few records to smooth: the rows as they are); row by row, so a drive's rows can be smoothed a block at a
    time.

    Parameters
    ----------
    sol : Solution, forward solution rows
    sm : Smoothed or None, :func:`rts` of the run's log
    gps_var : the log's ``gps_var`` as arrays, fix times (k,) UTC ns and variances (k, 3) m^2 E N U; None: none

    Returns
    -------
    Solution
        The smoothed rows, or ``sol`` itself when there is nothing to smooth.
    """
    if len(sol.t_ns) == 0 or sm is None:
        return sol
    e, var = row_errors(sm, sol.t_ns)
    lat, lon, h, v_n, q = correct(sol.lat, sol.lon, sol.h, sol.v_n, sol.q, e)
    var = np.maximum(var, 0.0)
    if gps_var is not None:  # the correlated GPS error no smoothing removes either
        t, gv = gps_var
        k = np.searchsorted(t, sol.t_ns, side="right") - 1
        var[:, :3] += np.where((k >= 0)[:, None], gv[np.maximum(k, 0)], 0.0)
    return Solution(sol.t_ns, lat, lon, h, v_n, q, np.sqrt(var), sol.bias + e[:, 9:15])  # e 9:15: true - estimate
