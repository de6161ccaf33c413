"""``replay.loop.run``, the one loop of every front end, on simulated drives: its sinks get the rows ``fuse``
writes (the wheel speeds' too), each the same blocks in the order given; an engine or sink error taken by ``on_error`` stops the sinks
and drains the source; progress reaches the end of the span."""
from __future__ import annotations

import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from fieldlog.drive import reader
from fieldlog.fusion.engine import Engine
from fieldlog.fusion.types import Outage, Solution
from fieldlog.replay.inputs import InputBlock, InputStream, resolve
from fieldlog.replay.loop import Pace, run
from fieldlog.tools.fuse import BLOCK_S, fuse
from fieldlog.tools.fuse_settings import drive_config

SHORT_S = 10.0  # s: blocks shorter than fuse's (BLOCK_S), several in the 90 s drive


@dataclass
class Collect:
    """A sink keeping what it was given; ``fail_at``: raise at that block (0-based) instead."""

    fail_at: int | None = None
    spans: list[tuple[int, int]] = field(default_factory=list)
    rows: list[Solution] = field(default_factory=list)
    finished: int = 0

    def block(self, block: InputBlock, sol: Solution, done: list[Outage]) -> None:
        if self.fail_at is not None and len(self.spans) == self.fail_at:
            raise RuntimeError(f"sink failed at block {self.fail_at}")
        self.spans.append((block.t0_ns, block.t1_ns))
        self.rows.append(sol)

    def finish(self, sol: Solution, done: list[Outage]) -> None:
        self.rows.append(sol)
        self.finished += 1


@pytest.fixture(scope="module")
def drive(simulated) -> Path:
    return simulated("figure8", 90, 1)


@pytest.mark.parametrize("method, can", [("kf", False), ("dkf", False), ("kf", True)])
def test_sinks_get_the_rows_fuse_writes(simulated, tmp_path: Path, method: str, can: bool) -> None:
    drive = simulated("figure8", 90, 1, can=True) if can else simulated("figure8", 90, 1)
    cfg = drive_config(drive)
    imap = resolve(drive)
    fused = fuse(drive, method, tmp_path / "f.mcap", cfg, inputs=imap, keep=True)
    assert (fused.odometer is not None) == can  # with wheel speeds, the loop feeds them to the odometer
    want = fused.solution
    a, b = Collect(), Collect()
    done = []
    tops = [t for t in reader.topics(drive) if t.topic in imap.topics and t.count]
    span = (min(t.first_ns for t in tops), max(t.last_ns for t in tops))
    res = run(InputStream(drive, imap, BLOCK_S), Engine(method, cfg), [a, b], Pace(0.0, span, done.append))
    got = Solution.concat(a.rows)
    assert len(want.t_ns) > 100 and res.blocks == len(a.spans) > 2
    np.testing.assert_array_equal(got.t_ns, want.t_ns)
    np.testing.assert_array_equal(got.lat, want.lat)
    np.testing.assert_array_equal(got.v_n, want.v_n)
    assert a.spans == b.spans and a.finished == b.finished == 1
    assert all(s1 >= s0 for (s0, _), (s1, _) in zip(a.spans, a.spans[1:]))  # in log-time order
    assert res.data_s == pytest.approx((a.spans[-1][1] - a.spans[0][0]) * 1e-9)
    assert len(done) == res.blocks and done[0] < 1.0 and done[-1] == 1.0 and done == sorted(done)
    # the rows do not depend on where the blocks end: shorter blocks split the sums at other samples, to rounding
    short = Collect()
    run(InputStream(drive, imap, SHORT_S), Engine(method, cfg), [short])
    rows = Solution.concat(short.rows)
    assert len(short.spans) > len(a.spans) and np.array_equal(rows.t_ns, want.t_ns)
    for name in ("lat", "lon", "h", "v_n", "q", "sigma", "bias"):
        x, y = getattr(rows, name), getattr(want, name)
        np.testing.assert_allclose(x, y, rtol=0, atol=1e-9 * float(np.abs(y).max()), err_msg=name)


def test_an_error_taken_stops_the_sinks_and_drains_the_source(drive: Path) -> None:
    imap = resolve(drive)
    cfg = drive_config(drive)
    whole = run(InputStream(drive, imap, 5.0).inputs(), Engine("kf", cfg), [Collect()])
    errors: list[Exception] = []
    bad, good = Collect(fail_at=3), Collect()
    res = run(InputStream(drive, imap, 5.0).inputs(), Engine("kf", cfg), [good, bad], on_error=errors.append)
    assert res.failed and len(errors) == 1 and "block 3" in str(errors[0])
    assert res.blocks == whole.blocks > 4  # the source read to its end
    assert len(bad.spans) == 3 and len(good.spans) == 4  # the sink before the failing one got that block
    assert good.finished == bad.finished == 0
    with pytest.raises(RuntimeError, match="block 3"):  # without on_error it propagates
        run(InputStream(drive, imap, 5.0).inputs(), Engine("kf", cfg), [Collect(fail_at=3)])


def _same_blocks(x: list[InputBlock], y: list[InputBlock]) -> bool:
    fields = ("t_ns", "omega_ib_b", "f_b")
    return len(x) == len(y) and all(
        (a.t0_ns, a.t1_ns) == (b.t0_ns, b.t1_ns)
        and all(np.array_equal(getattr(a.imu, k), getattr(b.imu, k)) for k in fields)
        and len(a.gps.t_ns) == len(b.gps.t_ns) and np.array_equal(a.gps.t_ns, b.gps.t_ns)
        and np.array_equal(a.gps.v_n, b.gps.v_n, equal_nan=True) for a, b in zip(x, y))


@pytest.mark.parametrize("in_process", [False, True])
def test_a_kept_stream_gives_its_blocks_again_without_the_drive(drive: Path, tmp_path: Path, in_process: bool
                                                                ) -> None:
    """``keep``: the second pass reads the blocks the first pass kept (the drive may be gone by then), the same
    blocks and counters as a fresh stream's; a first pass left early keeps nothing, and the next one reads the
    drive again, counting from the start. ``in_process``: another thread runs, so the reads run here, not in a
    forked worker (``replay.ahead``)."""
    done = threading.Event()
    if in_process:
        threading.Thread(target=done.wait, daemon=True).start()
    try:
        _kept_stream_passes(drive, tmp_path)
    finally:
        done.set()


def _kept_stream_passes(drive: Path, tmp_path: Path) -> None:
    copy = tmp_path / "drive.mcap"
    copy.write_bytes(drive.read_bytes())
    imap = resolve(copy)
    fresh = InputStream(copy, imap, SHORT_S)
    want = list(fresh)
    kept = InputStream(copy, imap, SHORT_S, keep=True)
    for b in kept:
        break
    copy.rename(tmp_path / "moved.mcap")
    with pytest.raises(FileNotFoundError):
        list(kept)  # nothing was kept: the drive is read again, and it is gone
    (tmp_path / "moved.mcap").rename(copy)
    first = list(kept)
    copy.unlink()
    second = list(kept)
    assert len(want) > 5 and _same_blocks(first, want) and _same_blocks(second, want)
    assert (kept.samples, kept.gaps, kept.rate_hz) == (fresh.samples, fresh.gaps, fresh.rate_hz) and kept.samples > 0
    kept.close()
    with pytest.raises(FileNotFoundError):
        list(kept)  # closed: read from the drive again, which is gone


def test_the_imu_period_does_not_depend_on_where_the_blocks_end() -> None:
    """The engine's IMU sample period: the median of the drive's first steps, however the blocks cut them (each
    block after the first starts with samples held from the one before, as the engine's do)."""
    from fieldlog.fusion.ins import PERIOD_STEPS, SamplePeriod

    rng = np.random.default_rng(6)
    t = np.cumsum(0.002 + rng.normal(0.0, 2e-6, 3 * PERIOD_STEPS))
    whole = SamplePeriod()
    whole.add(t, 0)
    assert whole.dt_s == float(np.median(np.diff(t[:PERIOD_STEPS + 1])))
    for ends in ([1, 2, 700, 1500], [999, 1000, 1001], [3]):
        split, start = SamplePeriod(), 0
        for k, end in enumerate([*ends, len(t)]):
            held = 0 if k == 0 else int(rng.integers(1, min(4, start) + 1))
            split.add(t[start - held:end], held)
            start = end
        assert split.dt_s == whole.dt_s
