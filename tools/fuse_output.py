"""What ``fieldlog fuse`` writes (the topics: ``tools.fuse``): ``FusedOutput``, the loop's sink
(``replay.loop.Sink``) that writes each block's solution rows, their REP-105 frames and the outage windows into a
Recorder as they come; or, smoothing, the forward rows spilled to a temporary file (``RowSpill``) and written
back smoothed by the RTS pass (``fusion.smoother``) a block at a time after the drive.
"""
from __future__ import annotations

from typing import Iterator

import numpy as np

from fieldlog.acquire import calib
from fieldlog.drive import messages
from fieldlog.drive.recorder import Recorder
from fieldlog.fusion.rowfile import RowFile
from fieldlog.fusion.smoother import SmootherLog, smoothed_blocks
from fieldlog.fusion.types import Outage, Solution
from fieldlog.replay.inputs import InputBlock
from fieldlog.replay.solutions import OUTAGE, Odometry, write_solution, write_status


class RowSpill:
    """The forward solution rows of a smoothed run, spilled block by block to an anonymous temporary file as they
    come (``fusion.rowfile.RowFile``) and read back in the same blocks (``Solution`` without ``local``, which
    smoothing drops, and ``status``, written as it comes)."""

    ROW = np.dtype([("t_ns", "<i8"), ("lat", "<f8"), ("lon", "<f8"), ("h", "<f8"), ("v_n", "<f8", 3),
                    ("q", "<f8", 4), ("sigma", "<f8", 15), ("bias", "<f8", 6)])

    def __init__(self) -> None:
        self._rows = RowFile(self.ROW)
        self._ends: list[int] = []  # one past each block's last row

    def add(self, sol: Solution) -> None:
        """Spill one block's rows (none: nothing)."""
        if len(sol.t_ns):
            rows = np.empty(len(sol.t_ns), self.ROW)
            for name in self.ROW.names:
                rows[name] = getattr(sol, name)
            self._rows.append(rows)
            self._ends.append(len(self._rows))

    def blocks(self) -> Iterator[Solution]:
        """The blocks added, in order."""
        for i0, i1 in zip([0, *self._ends[:-1]], self._ends):
            rows = self._rows.read(i0, i1)
            yield Solution(**{name: np.ascontiguousarray(rows[name]) for name in self.ROW.names})

    def close(self) -> None:
        """Delete the file."""
        self._rows.close()


class FusedOutput:
    """The loop's sink of a fused file (module docstring): ``method``'s rows into ``rec`` with their REP-105
    frames (base_link placed by ``mounting``) and the ``/fusion/outage`` windows; with ``log`` (the engine's
    ``SmootherLog``) the forward rows spilled and written smoothed by ``close``. ``keep``: the rows written are
    also kept (``solution``)."""

    def __init__(self, rec: Recorder, method: str, mounting: calib.Mounting, log: SmootherLog | None = None,
                 keep: bool = False) -> None:
        self.rec, self.method, self.log, self.keep = rec, method, log, keep
        self.odom = Odometry(method, mounting)
        self.spill = RowSpill() if log is not None else None
        self.kept: list[Solution] = []
        self.rows = 0  # forward solution rows
        self.outages = 0  # outage windows written

    def block(self, block: InputBlock, sol: Solution, done: list[Outage]) -> None:
        """Write (or spill) one block's rows and outage windows (``replay.loop.Sink.block``)."""
        self._take(sol, done)

    def finish(self, sol: Solution, done: list[Outage]) -> None:
        """Write (or spill) the engine's last rows and outage windows (``replay.loop.Sink.finish``)."""
        self._take(sol, done)

    def _take(self, sol: Solution, done: list[Outage]) -> None:
        if self.spill is not None:
            self.spill.add(sol)
            write_status(self.rec, self.method, sol)  # the forward pass's: what the filter knew at the row
        else:
            self._write(sol)
        for o in done:
            self.rec.write(OUTAGE, max(o.start_ns, 1), messages.encode_outage(o.start_ns, o.start_ns, o.end_ns,
                                                                              o.reason))
            self.outages += 1
        self.rows += len(sol.t_ns)

    def _write(self, sol: Solution) -> None:
        if self.keep:
            self.kept.append(sol)
        write_solution(self.rec, self.method, sol)
        self.odom.write(self.rec, sol)

    def close(self) -> None:
        """After the drive: the smoothed rows (with ``log``), then the map's datum record (``fusion.map``)."""
        if self.log is not None:
            for sol in smoothed_blocks(self.spill.blocks(), self.log):
                self._write(sol)
            self.log.close()
            self.spill.close()
        if self.odom.origin is not None:
            self.rec.add_metadata("fusion.map", self.odom.metadata())

    @property
    def solution(self) -> Solution | None:
        """The rows written (smoothed with ``log``) when kept, else None."""
        return Solution.concat(self.kept) if self.keep else None
