"""What ``fieldlog info`` shows about a drive, gathered while it is written and stored at close.

The recorder feeds every message it writes to a ``DriveStats``; at close it writes ``record()`` as the MCAP
metadata record ``fieldlog.info``. ``fieldlog info`` then answers from the summary, the statistics and the
metadata alone (about a second for an hour-long drive, instead of decoding every /imu message). A file without
the record (recovered, or from another writer) is scanned instead: ``info`` feeds the decoded topics to a
``DriveStats`` (``observe_stamps``), so both paths compute every figure with the same accumulators.

Memory is bounded, whatever the drive's length (the daemon's RSS stays flat):
- medians (the /imu and /gps/fix steps that define "nominal period", the rate and residual while locked) are
  exact medians of values quantised to a fixed quantum (1 us for steps, 1e-4 ppm, 0.01 us), held as counts per
  quantum (``QuantisedMedian``). A clocked sensor's steps fall into a few quanta (the daemon's /imu: 2-3 keys),
  so the count table stays small; if it passes ``QuantisedMedian.MAX_KEYS`` the quantum doubles (pairs of keys
  merge), which bounds it for any input. The final table does not depend on how the values were batched, so
  the recorder (batches as written) and the scan (whole topics) agree. A median of the first window instead
  would be O(1) too, but one bad start (a DAQ that comes up stuttering) would set the period for the whole
  drive; the whole drive's median is what ``info`` always reported. Quantising moves a step only across a
  threshold it is within half a microsecond of.
- gaps (steps > 1.5 nominal periods, the longest one; missing GPS epochs) are read off the same count table at
  the end, since they need the median first.
- the truth-timing figure pairs each /imu stamp with its /truth/imu sample as both stream in (``TimingPairs``):
  one to one in order, and with the nearest truth time, and keeps the first when both topics hold every
  sample (the simulator writes one truth record per DAQ frame); sums, not stamps, are kept (so the figure
  equals the whole-array one to rounding). Pairs before the first locked /time/sync record is seen are held
  (the pipeline writes /time/sync ahead of the /imu it stamps, so that is the time to lock; all of a drive that
  never locks). Otherwise what it holds is the lag between the two topics: the simulator and ``rebuild`` write /truth/imu first (the truth is in their
  memory anyway); the daemon writes no truth and so holds nothing. A writer whose /imu comes before any
  /truth/imu gets a record without ``timing``, and ``info`` scans that file for it.
"""
from __future__ import annotations

import logging
from collections import deque
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field

import numpy as np

from fieldlog.drive import messages, metavalue

log = logging.getLogger(__name__)

NS = 1_000_000_000
RECORD = "fieldlog.info"
SYNC_NAMES = {messages.TIMESYNC_FREE: "free", messages.TIMESYNC_HOLDOVER: "holdover",
              messages.TIMESYNC_LOCKED: "locked"}


@dataclass
class TimingError:
    """IMU time-stamp error against ``/truth/imu`` (simulated drives), after the first lock. Microseconds."""

    samples: int
    rms_us: float
    max_abs_us: float
    mean_us: float


@dataclass
class Quality:
    """The drive's time-sync, gap and timing figures (``fieldlog info``)."""

    sync_states: dict[str, float] = field(default_factory=dict)   # fraction of /time/sync records per state
    rate_ppm: float = float("nan")
    residual_us: float = float("nan")
    first_lock_ns: int | None = None
    timing: TimingError | None = None
    imu_gaps: int = 0
    imu_longest_gap_s: float = 0.0
    gps_missing_epochs: int = 0
    gps_no_fix: int = 0


class QuantisedMedian:
    """Values counted per quantum (``round(x / quantum)``; NaN makes the median NaN, as in ``np.median``): the
    exact median of the quantised values, and the table for sums over it. At most ``MAX_KEYS`` keys: past that
    the quantum doubles, merging pairs of keys, so the final table is that of the smallest doubling of the
    quantum that fits, however the values were batched."""

    MAX_KEYS = 4096

    def __init__(self, quantum: float) -> None:
        self.quantum = quantum
        self.shift = 0                         # a key is round(x / quantum) >> shift
        self.counts: dict[int, int] = {}
        self.n = 0
        self.nan = False

    def add(self, x: np.ndarray) -> None:
        """Count the values ``x`` (NaN: the median becomes NaN).

        Parameters
        ----------
        x : (n,) values, in the units of ``quantum``
        """
        x = np.asarray(x, np.float64)
        finite = np.isfinite(x)
        if not finite.all():
            self.nan = True
            x = x[finite]
        if len(x) == 0:
            return
        keys, n = np.unique(np.round(x / self.quantum).astype(np.int64) >> self.shift, return_counts=True)
        c = self.counts
        for k, m in zip(keys.tolist(), n.tolist()):
            c[k] = c.get(k, 0) + m
        self.n += len(x)
        while len(c) > self.MAX_KEYS:
            self.shift += 1
            merged: dict[int, int] = {}
            for k, m in c.items():
                merged[k >> 1] = merged.get(k >> 1, 0) + m
            self.counts = c = merged

    def table(self) -> tuple[np.ndarray, np.ndarray]:
        """Each key's value (the middle of its interval; the quantised value itself before any doubling) and
        count, in ascending order.

        Returns
        -------
        values, counts : (k,) float64 and int64
        """
        k = np.array(sorted(self.counts), np.int64)
        w = 1 << self.shift
        return (k * w + (w - 1) / 2) * self.quantum, np.array([self.counts[i] for i in k.tolist()], np.int64)

    def median(self) -> float:
        """The median of the quantised values (NaN when none, or a NaN was counted).

        Returns
        -------
        float : in the units of ``quantum``
        """
        if self.nan or self.n == 0:
            return float("nan")
        v, n = self.table()
        c = np.cumsum(n)
        lo, hi = np.searchsorted(c, [(self.n - 1) // 2, self.n // 2], side="right")
        return float((v[lo] + v[hi]) / 2)


class Steps:
    """The steps between consecutive stamps (ns) of one topic, as its batches arrive: counted per microsecond
    (``QuantisedMedian``) and the longest."""

    def __init__(self) -> None:
        self.hist = QuantisedMedian(1000.0)
        self.longest = 0
        self._last: int | None = None

    def add(self, t_ns: np.ndarray) -> None:
        """Count the steps of the next batch of stamps (and the step from the last batch's last stamp).

        Parameters
        ----------
        t_ns : (n,) int64 stamps, ns, in order
        """
        t = np.asarray(t_ns, np.int64)
        if len(t) == 0:
            return
        d = np.diff(t) if self._last is None else np.diff(t, prepend=np.int64(self._last))
        self._last = int(t[-1])
        if len(d):
            self.hist.add(d)
            self.longest = max(self.longest, int(d.max()))


class _ErrorSums:
    """Sums of stamp errors (ns) of the pairs after the first lock; pairs held while it is not known yet."""

    def __init__(self) -> None:
        self.n, self.sum, self.sum2, self.max_abs = 0, 0.0, 0.0, 0.0
        self.lock: int | None = None
        self._held: list[tuple[np.ndarray, np.ndarray]] = []

    def add(self, imu_ns: np.ndarray, err_ns: np.ndarray) -> None:
        if self.lock is None:
            self._held.append((imu_ns, err_ns))
        else:
            self._fold(err_ns[imu_ns >= self.lock])

    def _fold(self, err_ns: np.ndarray) -> None:
        if len(err_ns):
            e = err_ns.astype(np.float64) / 1e3
            self.n += len(e)
            self.sum += float(e.sum())
            self.sum2 += float(np.dot(e, e))
            self.max_abs = max(self.max_abs, float(np.abs(e).max()))

    def set_lock(self, lock_ns: int) -> None:
        self.lock = lock_ns
        for imu_ns, err_ns in self._held:
            self.add(imu_ns, err_ns)
        self._held = []

    def result(self, more: tuple[np.ndarray, np.ndarray] | None = None) -> TimingError | None:
        """The figure, with the pairs ``more`` (imu_ns, err_ns) besides; pairs still held (no lock) all count."""
        s = _ErrorSums()
        s.n, s.sum, s.sum2, s.max_abs = self.n, self.sum, self.sum2, self.max_abs
        for imu_ns, err_ns in self._held + ([more] if more else []):
            s._fold(err_ns if self.lock is None else err_ns[imu_ns >= self.lock])
        if s.n == 0:
            return None
        return TimingError(s.n, float(np.sqrt(s.sum2 / s.n)), s.max_abs, s.sum / s.n)


def _take(q: deque[np.ndarray], m: int) -> np.ndarray:
    """The first m stamps of a queue of arrays, removed from it."""
    out, got = [], 0
    while got < m:
        a = q.popleft()
        if got + len(a) > m:
            q.appendleft(a[m - got:])
            a = a[:m - got]
        out.append(a)
        got += len(a)
    return np.concatenate(out) if out else np.empty(0, np.int64)


def _nearest(truth_ns: np.ndarray, imu_ns: np.ndarray) -> np.ndarray:
    """Index of the nearest stamp in sorted ``truth_ns`` for each of ``imu_ns`` (the later one on a tie)."""
    if len(truth_ns) == 1:
        return np.zeros(len(imu_ns), np.int64)
    i = np.clip(np.searchsorted(truth_ns, imu_ns), 1, len(truth_ns) - 1)
    return np.where(np.abs(truth_ns[i - 1] - imu_ns) < np.abs(truth_ns[i] - imu_ns), i - 1, i)


class TimingPairs:
    """/imu stamps against /truth/imu sample times, paired as both stream in: one to one in order, and with the
    nearest truth time (truth in ascending order); ``result`` keeps the one-to-one figure when both topics
    hold the same number of samples. Holds the unpaired stamps of whichever topic is ahead, and the nearest
    pairing's recent truth window."""

    MARGIN = 64          # truth samples kept before the latest paired /imu stamp (small reorders of /imu)

    def __init__(self) -> None:
        self.n_imu = self.n_truth = 0
        self.incomplete = False        # /imu came before any /truth/imu: those samples were not paired
        self._imu_q: deque[np.ndarray] = deque()
        self._truth_q: deque[np.ndarray] = deque()
        self._q_len = [0, 0]
        self._window = np.empty(0, np.int64)
        self._window_new: list[np.ndarray] = []   # truth times not in _window yet (``_join_window``)
        self._near_pending: deque[np.ndarray] = deque()
        self.one, self.near = _ErrorSums(), _ErrorSums()

    def set_lock(self, lock_ns: int) -> None:
        """The first time-sync lock: errors count from it on.

        Parameters
        ----------
        lock_ns : UTC ns
        """
        self.one.set_lock(lock_ns)
        self.near.set_lock(lock_ns)

    def truth(self, t_ns: np.ndarray) -> None:
        """The next /truth/imu sample times.

        Parameters
        ----------
        t_ns : (n,) int64 UTC ns
        """
        t = np.sort(np.asarray(t_ns, np.int64))
        if len(t) == 0:
            return
        self.n_truth += len(t)
        self._truth_q.append(t)
        self._q_len[1] += len(t)
        self._window_new.append(t)
        self._pair()

    def imu(self, t_ns: np.ndarray) -> None:
        """The next /imu stamps (before any truth: not paired, ``incomplete``).

        Parameters
        ----------
        t_ns : (n,) int64 UTC ns
        """
        t = np.asarray(t_ns, np.int64)
        if len(t) == 0:
            return
        self.n_imu += len(t)
        if self.n_truth == 0:
            self.incomplete = True
            return
        self._imu_q.append(t)
        self._q_len[0] += len(t)
        self._near_pending.append(t)
        self._pair()

    def _pair(self) -> None:
        m = min(self._q_len)
        if m:
            a, b = _take(self._imu_q, m), _take(self._truth_q, m)
            self._q_len = [self._q_len[0] - m, self._q_len[1] - m]
            self.one.add(a, a - b)
        if not self._near_pending:
            return
        self._join_window()
        imu = np.concatenate(self._near_pending)
        ready = imu <= self._window[-1]
        self._near_pending = deque([imu[~ready]] if not ready.all() else [])
        if ready.any():
            t = imu[ready]
            j = _nearest(self._window, t)
            self.near.add(t, t - self._window[j])
            self._window = self._window[max(int(j.min()) - self.MARGIN, 0):]

    def _join_window(self) -> None:
        """The truth times that came since the last pairing onto the nearest pairing's window: joined when /imu
        needs them, once, rather than at each /truth/imu batch (a whole drive's truth comes before its /imu)."""
        if self._window_new:
            self._window = np.concatenate([self._window, *self._window_new])
            self._window_new = []

    def result(self) -> TimingError | None:
        """The stamps' error against the truth: the one-to-one pairing when the counts agree, else the nearest.

        Returns
        -------
        TimingError | None : None without both topics
        """
        if self.n_truth == 0 or self.n_imu == 0:
            return None
        if self.n_imu == self.n_truth:
            return self.one.result()
        # /imu stamps after the last truth sample: that one is the nearest
        self._join_window()
        t = np.concatenate(self._near_pending) if self._near_pending else np.empty(0, np.int64)
        return self.near.result((t, t - self._window[_nearest(self._window, t)]) if len(t) else None)


IMU_HOLD = 4096          # /imu stamps held before their steps are counted
DECODE_HOLD = 4096       # /gps/fix and /time/sync messages held before they are decoded


class DriveStats:
    """The figures of ``Quality`` from a drive's messages as they are written (``observe``, by the recorder) or
    read back (the topics' stamps and fields, by ``fieldlog info``'s scan); ``record()`` at close."""

    def __init__(self) -> None:
        self.span: dict[str, list[int]] = {}          # topic -> [first, last] log_time
        self._states: dict[int, int] = {}
        self._n_sync = 0
        self._first_lock: int | None = None
        self._rate = QuantisedMedian(1e-4)            # ppm
        self._residual = QuantisedMedian(1e-2)        # us
        self._imu = Steps()
        self._imu_held: list[np.ndarray] = []        # /imu stamps not yet in _imu (Steps is batching-independent)
        self._imu_n_held = 0
        self._fix = Steps()
        self._no_fix = 0
        self._timing = TimingPairs()
        self._undecoded: dict[str, list[bytes]] = {"/gps/fix": [], "/time/sync": []}   # payloads held

    def _span(self, topic: str, lo: int, hi: int) -> None:
        s = self.span.get(topic)
        if s is None:
            self.span[topic] = [lo, hi]
        else:
            s[0], s[1] = min(s[0], lo), max(s[1], hi)

    def observe_messages(self, topic: str, log_time_ns: Sequence[int],
                         msgs: "messages.Packed | Sequence[bytes]") -> None:
        """Single messages of one topic (``Recorder.write``, ``write_records``: raw reads, sentences, outages;
        cheap for those).

        Parameters
        ----------
        topic : their topic
        log_time_ns : UTC ns, one per message
        msgs : their CDR payloads
        """
        if topic in ("/imu", "/truth/imu", "/gps/fix", "/time/sync"):
            self.observe(topic, np.array(log_time_ns, np.int64), messages.as_packed(msgs))
        else:
            self._span(topic, min(log_time_ns), max(log_time_ns))

    def observe(self, topic: str, log_time_ns: np.ndarray, p: messages.Packed) -> None:
        """A batch of one topic (``Recorder.write_batch``). /imu and /truth/imu stamps are their log times;
        /gps/fix payloads, and /time/sync ones after the first lock, are held and decoded ``DECODE_HOLD`` at a
        time (``_decode``).

        Parameters
        ----------
        topic : its topic
        log_time_ns : (n,) int64 UTC ns
        p : the n CDR payloads
        """
        self._span(topic, int(log_time_ns.min()), int(log_time_ns.max()))
        if topic == "/imu":
            self.imu(log_time_ns)
        elif topic == "/truth/imu":
            self.truth(log_time_ns)
        elif topic in self._undecoded:
            held = self._undecoded[topic]
            held.extend(p)
            if len(held) >= DECODE_HOLD or (topic == "/time/sync" and self._first_lock is None):
                self._decode(topic)

    def _decode(self, topic: str) -> None:
        """The held /gps/fix or /time/sync payloads into their figures. The pipeline writes them a message or
        two at a time, and decoding costs most per call, not per message; held, they count the same, since
        ``fix`` and ``sync`` are batching-independent. /time/sync is decoded as it comes until the first lock,
        which ``TimingPairs`` waits for with its pairs held."""
        held = self._undecoded[topic]
        if not held:
            return
        p = messages.Packed.from_list(held)
        self._undecoded[topic] = []
        if topic == "/gps/fix":
            d = messages.decode_navsatfix(p)
            self.fix(d["stamp_ns"], d["status"])
        else:
            d = messages.decode_time_sync(p)
            self.sync(d["stamp_ns"], d["state"], d["rate_ppm"], d["residual_us"])

    def imu(self, stamp_ns: np.ndarray) -> None:
        """/imu stamps; their steps are counted IMU_HOLD at a time: the daemon writes /imu a DAQ read at a time
        (a few dozen samples), and the per-call cost of counting dominates such small batches.

        Parameters
        ----------
        stamp_ns : (n,) int64 UTC ns
        """
        t = np.array(stamp_ns, np.int64)
        self._imu_held.append(t)
        self._imu_n_held += len(t)
        if self._imu_n_held >= IMU_HOLD:
            self._fold_imu()
        self._timing.imu(t)

    def _fold_imu(self) -> None:
        if self._imu_held:
            self._imu.add(np.concatenate(self._imu_held))
            self._imu_held, self._imu_n_held = [], 0

    def truth(self, stamp_ns: np.ndarray) -> None:
        """/truth/imu sample times (``TimingPairs.truth``).

        Parameters
        ----------
        stamp_ns : (n,) int64 UTC ns
        """
        self._timing.truth(stamp_ns)

    def fix(self, stamp_ns: np.ndarray, status: np.ndarray) -> None:
        """/gps/fix stamps and statuses: the epoch steps and the epochs without a fix.

        Parameters
        ----------
        stamp_ns : (n,) int64 UTC ns
        status : (n,) NavSatStatus status (< 0: no fix)
        """
        self._fix.add(stamp_ns)
        self._no_fix += int(np.count_nonzero(np.asarray(status) < 0))

    def sync(self, stamp_ns: np.ndarray, state: np.ndarray, rate_ppm: np.ndarray, residual_us: np.ndarray) -> None:
        """/time/sync records: the states, the first lock, the rate and residual while locked.

        Parameters
        ----------
        stamp_ns : (n,) int64 UTC ns
        state : (n,) FREE=0, HOLDOVER=1, LOCKED=2
        rate_ppm : (n,) DAQ oscillator rate error, ppm
        residual_us : (n,) fit residual RMS, µs
        """
        state = np.asarray(state)
        for s, n in zip(*(a.tolist() for a in np.unique(state, return_counts=True))):
            self._states[s] = self._states.get(s, 0) + n
        self._n_sync += len(state)
        locked = state == messages.TIMESYNC_LOCKED
        if locked.any():
            if self._first_lock is None:
                self._first_lock = int(np.asarray(stamp_ns)[locked][0])
                self._timing.set_lock(self._first_lock)
            self._rate.add(np.asarray(rate_ppm)[locked])
            self._residual.add(np.asarray(residual_us)[locked])

    def quality(self) -> Quality:
        """The figures of what was observed.

        Returns
        -------
        Quality
        """
        self._fold_imu()
        for topic in self._undecoded:
            self._decode(topic)
        q = Quality(first_lock_ns=self._first_lock, gps_no_fix=self._no_fix, timing=self._timing.result())
        q.sync_states = {SYNC_NAMES.get(s, str(s)): self._states[s] / self._n_sync for s in sorted(self._states)}
        if self._first_lock is not None:
            q.rate_ppm, q.residual_us = self._rate.median(), self._residual.median()
        period = self._imu.hist.median()
        if period > 0:                       # gaps: steps longer than 1.5 nominal periods (the median step)
            v, n = self._imu.hist.table()
            q.imu_gaps = int(n[v > 1.5 * period].sum())
            q.imu_longest_gap_s = self._imu.longest / NS if q.imu_gaps else 0.0
        period = self._fix.hist.median()
        if self._fix.hist.n > 1 and period > 0:   # GPS epochs missing: steps of more than the median period
            v, n = self._fix.hist.table()
            q.gps_missing_epochs = int(np.sum(n * (np.round(v / period) - 1)))
        return q

    def record(self) -> dict[str, str]:
        """The ``fieldlog.info`` metadata record: JSON values (``drive.metavalue``), one key each (no ``timing``
        when /imu came before /truth/imu: ``info`` scans for it).

        Returns
        -------
        dict[str, str] : key -> JSON text
        """
        out = {f"span.{topic}": metavalue.dump(list(s)) for topic, s in self.span.items()}
        d = asdict(self.quality())
        if self._timing.incomplete and self._timing.n_truth:
            d.pop("timing")
        out.update({k: metavalue.dump(v) for k, v in d.items()})
        return out
def quality_from_record(rec: dict[str, str]) -> Quality | None:
    """The inverse of ``DriveStats.record`` (also of older drives' Python literals); None when the record lacks a
    figure or holds one that is not what ``record`` writes: scan the file instead.

    Parameters
    ----------
    rec : the ``fieldlog.info`` record's keys and values

    Returns
    -------
    Quality | None
    """
    names = set(Quality.__dataclass_fields__)
    if not names <= set(rec):
        return None
    try:
        v = {k: metavalue.load(rec[k]) for k in names}
        states = v["sync_states"]
        if not isinstance(states, dict):
            raise ValueError("sync_states: not a table")
        timing = v["timing"]
        if timing is not None:
            if not isinstance(timing, dict) or set(timing) != set(TimingError.__dataclass_fields__):
                raise ValueError("timing: not a timing table")
            timing = TimingError(metavalue.whole(timing["samples"], "timing.samples"),
                                 *(metavalue.number(timing[k], f"timing.{k}") for k in ("rms_us", "max_abs_us",
                                                                                          "mean_us")))
        lock = v["first_lock_ns"]
        return Quality(
            sync_states={str(k): metavalue.number(x, "sync_states") for k, x in states.items()},
            rate_ppm=metavalue.number(v["rate_ppm"], "rate_ppm"),
            residual_us=metavalue.number(v["residual_us"], "residual_us"),
            first_lock_ns=None if lock is None else metavalue.whole(lock, "first_lock_ns"), timing=timing,
            imu_gaps=metavalue.whole(v["imu_gaps"], "imu_gaps"),
            imu_longest_gap_s=metavalue.number(v["imu_longest_gap_s"], "imu_longest_gap_s"),
            gps_missing_epochs=metavalue.whole(v["gps_missing_epochs"], "gps_missing_epochs"),
            gps_no_fix=metavalue.whole(v["gps_no_fix"], "gps_no_fix"))
    except ValueError as e:
        log.warning("the fieldlog.info record is damaged (%s): its figures are computed from the messages", e)
        return None
