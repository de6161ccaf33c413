"""The solution rows the engine produces: the (closed-loop) INS state at the first IMU sample of each
1/output_hz slot of UTC (10 Hz by default), stamped with that sample's time, with the filter's sigmas."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

NS = 1_000_000_000


@dataclass
class Solution:
    """Output rows: t_ns (n,), lat, lon (rad), h (m), v_n (n, 3), q (n, 4) [x, y, z, w] of C_bn,
    sigma (n, 9): position ENU m, velocity ENU m/s, attitude (phi E, N, U) rad."""

    t_ns: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    h: np.ndarray
    v_n: np.ndarray
    q: np.ndarray
    sigma: np.ndarray

    @staticmethod
    def concat(parts: list["Solution"]) -> "Solution":
        if not parts:
            return Solution(np.zeros(0, np.int64), *(np.zeros(0),) * 3, np.zeros((0, 3)), np.zeros((0, 4)),
                            np.zeros((0, 9)))
        return Solution(*(np.concatenate([getattr(p, k) for p in parts]) for k in
                          ("t_ns", "lat", "lon", "h", "v_n", "q", "sigma")))


def sigmas(diag: np.ndarray) -> np.ndarray:
    """Position, velocity and attitude sigmas (..., 9) from covariance diagonals (..., 15)."""
    return np.sqrt(np.maximum(np.asarray(diag)[..., :9], 0.0))


def output_rows(t_ns: np.ndarray, output_hz: float) -> np.ndarray:
    """Indices of the samples t_ns (n,) UTC that start a 1/output_hz slot, after the first sample."""
    bucket = np.floor(t_ns / (NS / output_hz)).astype(np.int64)
    return np.flatnonzero(np.diff(bucket) != 0) + 1


def rows(sol, t_ns: np.ndarray, output_hz: float, ends: np.ndarray, diag: np.ndarray) -> Solution:
    """Solution rows of an INS segment: sol a ``fusion.ins.NavSolution`` over samples t_ns (n,); the covariance
    diagonals diag (m, 15) after the filter cycles ending at samples ends (m,)."""
    r = output_rows(t_ns, output_hz)
    sig = sigmas(diag)[np.searchsorted(ends, r)]
    return Solution(t_ns[r], sol.lat[r], sol.lon[r], sol.h[r], sol.v_n[r], sol.q[r], sig)
