"""Rauch-Tung-Striebel smoothing of the closed-loop error-state filter, for post-drive reprocessing.

Formulation. The forward filter (``fusion.engine``) is closed loop: its error state is zero after every
GPS epoch, the correction dx_k = x_{k|k} having been fed into the INS. Records k = 0..N-1 are the ends
of the covariance cycles (``FusionConfig.cov_step_s``, 0.1 s) plus the alignment; each stores

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

and the smoothed state is the forward solution corrected by y_k, as ``correct_ins`` would. A solution
row between records k-1 and k (stamped before the update at k) has forward error interpolated linearly
in time between y_{k-1} and y_k + dx_k; the jump of the forward solution at an update disappears.

Memory: four arrays per record, 3 x 15 x 15 + 15 float64 = 5.5 kB; a 1-hour drive at 10 Hz is 36 000
records, about 200 MB. The forward pass itself stays bounded; the smoother is what grows with the drive.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fusion import earth
from fusion.engine import Solution
from fusion.errmodel import ATT, N_STATES, POS, VEL


class SmootherLog:
    """What the forward filter hands to the smoother; ``fusion.engine.Engine(..., log=SmootherLog())`` fills it."""

    def __init__(self) -> None:
        self._t: list[np.ndarray] = []
        self._phi: list[np.ndarray] = []
        self._pm: list[np.ndarray] = []
        self._pp: list[np.ndarray] = []
        self._dx: list[np.ndarray] = []

    def __len__(self) -> int:
        return sum(len(t) for t in self._t)

    def start(self, t_ns: int, P0: np.ndarray) -> None:
        """The filter's initial covariance at t_ns (alignment)."""
        self.cycles(np.array([t_ns], np.int64), np.eye(N_STATES)[None], np.asarray(P0, float)[None])

    def cycles(self, t_ns: np.ndarray, Phi: np.ndarray, P_pred: np.ndarray) -> None:
        """Covariance cycles ending at t_ns (m,) int64 UTC: Phi (m, 15, 15), predicted P (m, 15, 15)."""
        self._t.append(np.asarray(t_ns, np.int64))
        self._phi.append(np.asarray(Phi, float))
        self._pm.append(np.asarray(P_pred, float))
        self._pp.append(np.array(P_pred, float))
        self._dx.append(np.zeros((len(t_ns), N_STATES)))

    def update(self, dx: np.ndarray, P_upd: np.ndarray) -> None:
        """The update at the last recorded cycle end (the engine updates only there): correction dx (15,)
        fed back, covariance after it. A second update at the same instant adds its correction (linear)."""
        self._dx[-1][-1] += dx
        self._pp[-1][-1] = P_upd

    def arrays(self) -> tuple[np.ndarray, ...]:
        """(t_ns (N,), Phi, P-, P+ (N, 15, 15), dx (N, 15))."""
        return tuple(np.concatenate(x) for x in (self._t, self._phi, self._pm, self._pp, self._dx))


@dataclass
class Smoothed:
    """The smoothed error of the forward solution after each record: t_ns (N,), y (N, 15), P (N, 15, 15);
    dx (N, 15) the forward corrections (for the rows stamped before them)."""

    t_ns: np.ndarray
    y: np.ndarray
    P: np.ndarray
    dx: np.ndarray


def rts(t_ns: np.ndarray, Phi: np.ndarray, P_pred: np.ndarray, P_upd: np.ndarray, dx: np.ndarray) -> Smoothed:
    """The backward pass (module docstring) over the records of a :class:`SmootherLog`."""
    n = len(t_ns)
    y = np.zeros((n, N_STATES))
    Ps = np.array(P_upd, float)
    for k in range(n - 2, -1, -1):
        C = np.linalg.solve(P_pred[k + 1], Phi[k + 1] @ P_upd[k]).T
        y[k] = C @ (y[k + 1] + dx[k + 1])
        P = P_upd[k] + C @ (Ps[k + 1] - P_pred[k + 1]) @ C.T
        Ps[k] = 0.5 * (P + P.T)
    return Smoothed(np.asarray(t_ns, np.int64), y, Ps, np.asarray(dx, float))


def row_errors(sm: Smoothed, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Smoothed error (n, 15) and its covariance diagonal (n, 15) of forward solution rows at t_ns (n,).

    A row in (t_{k-1}, t_k] is the INS before the update at k: the error runs from y_{k-1} to y_k + dx_k."""
    t_ns = np.asarray(t_ns, np.int64)
    k = np.searchsorted(sm.t_ns, t_ns, side="left").clip(1, max(len(sm.t_ns) - 1, 1))
    t0, t1 = sm.t_ns[k - 1], sm.t_ns[k]
    a = np.clip((t_ns - t0) / np.maximum(t1 - t0, 1), 0.0, 1.0)[:, None]
    e = (1.0 - a) * sm.y[k - 1] + a * (sm.y[k] + sm.dx[k])
    d = np.diagonal(sm.P, axis1=1, axis2=2)
    return e, (1.0 - a) * d[k - 1] + a * d[k]


def correct(lat: np.ndarray, lon: np.ndarray, h: np.ndarray, v_n: np.ndarray, q: np.ndarray, e: np.ndarray
            ) -> tuple[np.ndarray, ...]:
    """Remove errors e (n, 15) (computed - true, ``fusion.errmodel`` order) from navigation rows: lat, lon
    (rad), h (m), v_n (n, 3) ENU m/s, q (n, 4) [x, y, z, w] of C_bn. Vectorised ``kf.correct_ins``."""
    rm, rn = earth.principal_radii(lat, h)
    dr = e[:, POS]
    q2 = earth.quat_multiply(earth.rotvec_to_quat(e[:, ATT]), q)
    q2 /= np.linalg.norm(q2, axis=1, keepdims=True)
    q2 *= np.where(q2[:, 3:4] < 0.0, -1.0, 1.0)
    return lat - dr[:, 1] / rm, lon - dr[:, 0] / (rn * np.cos(lat)), h - dr[:, 2], v_n - e[:, VEL], q2


def smooth_solution(sol: Solution, log: SmootherLog) -> Solution:
    """The forward solution rows of a whole drive, smoothed with the records of the same run."""
    if len(sol.t_ns) == 0 or len(log) < 2:
        return sol
    e, var = row_errors(rts(*log.arrays()), sol.t_ns)
    lat, lon, h, v_n, q = correct(sol.lat, sol.lon, sol.h, sol.v_n, sol.q, e)
    return Solution(sol.t_ns, lat, lon, h, v_n, q, np.sqrt(np.maximum(var[:, :9], 0.0)))
