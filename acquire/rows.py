"""Products of many rows by one small matrix, on the calling thread.

``dot(x, m)`` is ``np.dot(x, m)`` for an (n, k) ``x`` and a small (k, p) ``m``, bit for bit, computed a block of
rows at a time. OpenBLAS hands a matrix product of more than ``SERIAL_MULADDS`` multiply-adds to its worker
threads, which then spin waiting for more work after the product: for a product this small per row that costs
more CPU than it saves, and takes the second core from the work that runs beside it (a writer's compression
thread). A block of at most ``SERIAL_MULADDS`` multiply-adds runs on the calling thread, and each row's result is
the same whichever block it is in (the kernel sums over k alike for every row), so the result keeps its bits.
No block is a single row of a longer ``x`` (``blocks``): numpy takes a vector-matrix product for one row,
whose kernel rounds otherwise; a caller that splits rows before they reach ``dot`` splits them the same way.
"""
from __future__ import annotations

import numpy as np

SERIAL_MULADDS = 1 << 18  # OpenBLAS's GEMM threading threshold: 65536 * GEMM_MULTITHREAD_THRESHOLD (4)


def dot(x: np.ndarray, m: np.ndarray) -> np.ndarray:
    """``np.dot(x, m)`` for x (n, k) and m (k, p), float64, bit for bit, a block of rows at a time.

    Parameters
    ----------
    x : (n, k) ndarray, float64, the rows (any strides)
    m : (k, p) ndarray, float64, the matrix (any strides)

    Returns
    -------
    (n, p) ndarray, float64, C-ordered: row i is ``x[i] @ m``
    """
    x, m = np.asarray(x, np.float64), np.asarray(m, np.float64)
    if x.ndim != 2 or m.ndim != 2 or x.shape[1] != m.shape[0]:
        raise ValueError(f"rows.dot: expected (n, k) and (k, p), got {x.shape} and {m.shape}")
    out = np.empty((x.shape[0], m.shape[1]))
    for i, j in blocks(x.shape[0], SERIAL_MULADDS // max(1, m.size)):
        np.dot(x[i:j], m, out=out[i:j])
    return out


def blocks(n: int, step: int) -> list[tuple[int, int]]:
    """Row ranges [i, j) covering n rows in order, ``step`` rows each but the last two: none is a single row
    unless n is 1 (the last range of one row takes the row before it).

    Parameters
    ----------
    n : the number of rows
    step : rows a range holds (at least 4 are taken)

    Returns
    -------
    list of (i, j) : the ranges, first row and one past the last
    """
    starts = list(range(0, n, max(4, step)))
    if len(starts) > 1 and n - starts[-1] == 1:
        starts[-1] -= 1
    return list(zip(starts, starts[1:] + [n]))
