"""The one fusion loop of every front end: ``run(source, engine, sinks)``.

A source is any iterable of ``replay.inputs.InputBlock``: a drive read as ``fuse`` reads it
(``replay.inputs.InputStream``, on the second core or in this process with each block's data kept for a viewer),
or the daemon's live bus (``live_inputs`` of ``replay.live.batch_blocks``). Each block goes through the
incremental ``fusion.engine.Engine``; then every sink, in the order given, gets the block with the solution rows
and the closed outage windows it produced, and at the end what ``Engine.finish`` gives. The sinks are the
front ends: ``fuse``'s fused file (``tools.fuse_output``), the rerun player (``replay.player``), the Foxglove
server (``tools.foxglove_live``). ``Pace`` paces the loop so that data time runs ``speed`` times faster than
the wall clock and reports the fraction of a span done.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Iterable, Iterator, Protocol, Sequence

from fieldlog.drive import reader
from fieldlog.fusion.engine import Engine
from fieldlog.fusion.types import Outage, Solution
from fieldlog.replay.inputs import InputBlock, input_block


class Sink(Protocol):
    """A front end of the loop: it gets each block with what the engine made of it, then the engine's last rows."""

    def block(self, block: InputBlock, sol: Solution, done: list[Outage]) -> None:
        """One block of the source and the engine's output for it.

        Parameters
        ----------
        block : InputBlock
            The block's engine inputs, log-time span (ns) and, when the source keeps it, its data per topic.
        sol : Solution
            The solution rows the engine gave for the block (UTC ns, WGS-84 rad and m, ENU m/s).
        done : list of Outage
            The outage windows the block closed (UTC ns).
        """

    def finish(self, sol: Solution, done: list[Outage]) -> None:
        """The rows and outage windows ``Engine.finish`` gave after the last block (as in ``block``).

        Parameters
        ----------
        sol : Solution
            The last solution rows.
        done : list of Outage
            The last outage windows.
        """


@dataclass
class Pace:
    """How the loop runs against the wall clock: ``speed`` times real time (``<= 0``: as fast as possible), and
    ``progress`` told the fraction of ``span_ns`` (first, last log time, ns) done after each block."""

    speed: float = 0.0
    span_ns: tuple[int, int] | None = None
    progress: Callable[[float], None] | None = None


@dataclass
class RunResult:
    blocks: int = 0
    data_s: float = 0.0  # log time run through, s
    wall_s: float = 0.0
    failed: bool = False  # the engine raised and ``on_error`` took it: the sinks stopped there


def run(source: Iterable[InputBlock], engine: Engine, sinks: Sequence[Sink], pace: Pace = Pace(),
        on_error: Callable[[Exception], None] | None = None) -> RunResult:
    """Run ``source`` through ``engine`` into ``sinks`` (module docstring).

    Parameters
    ----------
    source : iterable of InputBlock
        The blocks, in log-time order.
    engine : Engine
        The fusion engine, fresh.
    sinks : sequence of Sink
        The front ends, each given every block and the last rows in this order.
    pace : Pace
        Pacing against the wall clock and progress.
    on_error : callable, optional
        Given an exception the engine or a sink raises: the engine and the sinks stop there and the source is drained to
        its end (a live bus whose other consumers go on). None: the exception propagates.

    Returns
    -------
    RunResult
        Blocks run, log time and wall time taken (s), whether the engine failed.
    """
    res = RunResult()
    wall0 = time.monotonic()
    t0: int | None = None
    t1 = 0
    for b in source:
        t0 = b.t0_ns if t0 is None else t0
        t1 = b.t1_ns
        res.blocks += 1
        if not res.failed:
            res.failed = _step(engine.process, on_error, sinks, b, b.imu, b.gps, b.odom)
        _pace(pace, wall0, t0, t1)
    if not res.failed:
        res.failed = _step(engine.finish, on_error, sinks, None)
    res.data_s = (t1 - t0) * 1e-9 if t0 is not None else 0.0
    res.wall_s = time.monotonic() - wall0
    return res


def _step(step: Callable[..., tuple[Solution, list[Outage]]], on_error: Callable[[Exception], None] | None,
          sinks: Sequence[Sink], block: InputBlock | None, *args) -> bool:
    """One engine step and its sinks (``block`` None: the finish); True when it or a sink (a solution that
    diverged) failed into ``on_error``."""
    try:
        sol, done = step(*args)
        for s in sinks:
            if block is None:
                s.finish(sol, done)
            else:
                s.block(block, sol, done)
    except Exception as e:  # noqa: BLE001  (any fusion error, e.g. a diverged solution, when the caller takes it)
        if on_error is None:
            raise
        on_error(e)
        return True
    return False


def _pace(pace: Pace, wall0: float, t0_ns: int, t1_ns: int) -> None:
    if pace.speed > 0:
        wait = wall0 + (t1_ns - t0_ns) * 1e-9 / pace.speed - time.monotonic()
        if wait > 0:
            time.sleep(wait)
    if pace.progress and pace.span_ns:
        first, last = pace.span_ns
        pace.progress(min((t1_ns - first) / max(last - first, 1), 1.0))


def live_inputs(blocks: Iterable[reader.Block]) -> Iterator[InputBlock]:
    """Blocks of the daemon's live bus (``replay.live.batch_blocks``) as the loop's source, each with its data.

    Parameters
    ----------
    blocks : iterable of drive.reader.Block
        The bus's blocks, ``/imu`` in body RFU under fieldlog's topic names.

    Returns
    -------
    iterator of InputBlock
        The same blocks with their engine inputs.
    """
    return (input_block(b, keep_data=True) for b in blocks)
