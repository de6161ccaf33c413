"""Fixed-size rows kept in an anonymous temporary file, out of memory: what a pass over a whole drive must read
back later (the smoother's records and smoothed errors, the installation pass's rate integral and mounting
terms), so that its memory does not grow with the drive.
"""
from __future__ import annotations

import tempfile

import numpy as np
from numpy.typing import DTypeLike


class RowFile:
    """Rows of one numpy ``dtype`` (a record, or a sub-array such as ``("<f8", 3)``) in an anonymous temporary
    file: written at any row or appended, read back by range. The file is deleted by :meth:`close`."""

    def __init__(self, dtype: DTypeLike) -> None:
        self.dtype = np.dtype(dtype)
        self.rows = 0  # one past the last row written
        self._file = tempfile.TemporaryFile()  # noqa: SIM115 (lives as long as this object; close())

    def __len__(self) -> int:
        return self.rows

    def write(self, i0: int, rows: np.ndarray) -> None:
        """Write rows [i0, i0 + len(rows)).

        Parameters
        ----------
        i0 : int, the first row's index
        rows : ndarray, len(rows) rows of ``dtype``'s layout (a structured array of it, or a float array shaped
            (n, *sub-array shape)); their bytes are written as they are

        Raises
        ------
        ValueError
            When the rows' size is not that of ``dtype``.
        """
        data = np.ascontiguousarray(rows)
        if data.nbytes != len(data) * self.dtype.itemsize:
            raise ValueError(f"RowFile: rows of {data.nbytes // max(len(data), 1)} bytes, not {self.dtype.itemsize}")
        self._file.seek(i0 * self.dtype.itemsize)
        self._file.write(data.tobytes())
        self.rows = max(self.rows, i0 + len(data))

    def append(self, rows: np.ndarray) -> None:
        """Write rows after the last one (:meth:`write`).

        Parameters
        ----------
        rows : ndarray, as :meth:`write` takes them
        """
        self.write(self.rows, rows)

    def read(self, i0: int, i1: int) -> np.ndarray:
        """Rows [i0, i1), read-only.

        Parameters
        ----------
        i0, i1 : int, row indices, 0 <= i0 <= i1 <= len(self)

        Returns
        -------
        ndarray of ``dtype`` (a sub-array dtype gives its float array, shaped (i1 - i0, *sub-array shape))
        """
        self._file.seek(i0 * self.dtype.itemsize)
        return np.frombuffer(self._file.read((i1 - i0) * self.dtype.itemsize), self.dtype)

    def close(self) -> None:
        """Delete the file."""
        self._file.close()
