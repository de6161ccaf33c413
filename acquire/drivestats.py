"""What ``fieldlog info`` shows about a drive, gathered while it is written and stored at close.

The recorder feeds every message it writes to a ``DriveStats``; at close it writes ``record()`` as the MCAP
metadata record ``fieldlog.info``. ``fieldlog info`` then answers from the summary, the statistics and the
metadata alone (about a second for an hour-long drive, instead of decoding every /imu message). A file without
the record (recovered, or from another writer) is scanned instead, through the same functions below, so both
paths give the same figures.

Memory: the /imu stamps (8 bytes per sample, 14 MB per hour at 500 Hz) for the gap and truth-timing figures,
up to ``MAX_IMU_STAMPS``; a longer file gets a record without the /imu figures, which ``info`` then scans for.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from fieldlog.acquire import messages

NS = 1_000_000_000
RECORD = "fieldlog.info"
MAX_IMU_STAMPS = 8_000_000
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


def sync_quality(q: Quality, stamp_ns: np.ndarray, state: np.ndarray, rate_ppm: np.ndarray,
                 residual_us: np.ndarray) -> None:
    """/time/sync records -> the state fractions, and the median rate and residual while locked."""
    if len(state) == 0:
        return
    q.sync_states = {SYNC_NAMES.get(int(s), str(s)): float(np.mean(state == s)) for s in np.unique(state)}
    locked = state == messages.TIMESYNC_LOCKED
    if locked.any():
        q.first_lock_ns = int(stamp_ns[locked][0])
        q.rate_ppm = float(np.median(rate_ppm[locked]))
        q.residual_us = float(np.median(residual_us[locked]))


def imu_gaps(q: Quality, imu_ns: np.ndarray) -> None:
    """Gaps in /imu: steps longer than 1.5 nominal periods (the median step)."""
    fs_nominal = 1.0 / np.median(np.diff(imu_ns) / NS) if len(imu_ns) > 1 else 0.0
    if fs_nominal:
        gaps = np.diff(imu_ns) / NS > 1.5 / fs_nominal
        q.imu_gaps = int(gaps.sum())
        q.imu_longest_gap_s = float(np.max(np.diff(imu_ns)) / NS) if gaps.any() else 0.0


def gps_gaps(q: Quality, fix_ns: np.ndarray, status: np.ndarray) -> None:
    """Epochs without a fix, and epochs missing from /gps/fix (steps of more than the median period)."""
    q.gps_no_fix = int(np.count_nonzero(status < 0))
    if len(fix_ns) > 2:
        dt = np.diff(fix_ns) / NS
        q.gps_missing_epochs = int(np.sum(np.round(dt / np.median(dt)) - 1))


def timing_error(imu_ns: np.ndarray, truth_ns: np.ndarray, first_lock_ns: int | None) -> TimingError | None:
    """Pair each /imu stamp with its true sample time: one to one when both hold every sample (the simulator
    writes one truth record per DAQ frame, in order), otherwise with the nearest truth time."""
    if len(imu_ns) == 0 or len(truth_ns) == 0:
        return None
    if len(imu_ns) == len(truth_ns):
        err = (imu_ns - truth_ns).astype(np.float64)
    else:
        i = np.clip(np.searchsorted(truth_ns, imu_ns), 1, len(truth_ns) - 1)
        j = np.where(np.abs(truth_ns[i - 1] - imu_ns) < np.abs(truth_ns[i] - imu_ns), i - 1, i)
        err = (imu_ns - truth_ns[j]).astype(np.float64)
    if first_lock_ns is not None:
        err = err[imu_ns >= first_lock_ns]
    if len(err) == 0:
        return None
    err_us = err / 1e3
    return TimingError(len(err_us), float(np.sqrt(np.mean(err_us**2))), float(np.max(np.abs(err_us))),
                       float(np.mean(err_us)))


_DECODED = ("/imu", "/truth/imu", "/gps/fix", "/time/sync")


class DriveStats:
    """Fed every message a Recorder writes (``observe``); ``record()`` at close."""

    def __init__(self) -> None:
        self.span: dict[str, list[int]] = {}          # topic -> [first, last] log_time
        self._imu: list[np.ndarray] = []
        self._imu_n = 0
        self._truth: list[np.ndarray] = []
        self._fix: list[tuple[np.ndarray, np.ndarray]] = []
        self._sync: list[dict[str, np.ndarray]] = []

    def _span(self, topic: str, lo: int, hi: int) -> None:
        s = self.span.get(topic)
        if s is None:
            self.span[topic] = [lo, hi]
        else:
            s[0], s[1] = min(s[0], lo), max(s[1], hi)

    def observe_message(self, topic: str, log_time_ns: int, data: bytes) -> None:
        """One message (``Recorder.write``: raw reads, sentences, outages; cheap for those)."""
        if topic in _DECODED:
            self.observe(topic, np.array([log_time_ns], np.int64), messages.Packed.from_list([data]))
        else:
            self._span(topic, log_time_ns, log_time_ns)

    def observe(self, topic: str, log_time_ns: np.ndarray, p: messages.Packed) -> None:
        """A batch of one topic (``Recorder.write_batch``). /imu and /truth/imu stamps are their log times."""
        self._span(topic, int(log_time_ns.min()), int(log_time_ns.max()))
        if topic == "/imu":
            self._imu_n += len(log_time_ns)
            if self._imu_n <= MAX_IMU_STAMPS:
                self._imu.append(log_time_ns.copy())
            else:
                self._imu = []
        elif topic == "/truth/imu":
            self._truth.append(log_time_ns.copy())
        elif topic == "/gps/fix":
            d = messages.decode_navsatfix(p)
            self._fix.append((d["stamp_ns"], d["status"]))
        elif topic == "/time/sync":
            self._sync.append(messages.decode_time_sync(p))

    def quality(self) -> tuple[Quality, bool]:
        """The figures, and whether the /imu ones are complete (False past MAX_IMU_STAMPS)."""
        q = Quality()
        if self._sync:
            cat = {k: np.concatenate([d[k] for d in self._sync]) for k in ("stamp_ns", "state", "rate_ppm",
                                                                           "residual_us")}
            sync_quality(q, cat["stamp_ns"], cat["state"], cat["rate_ppm"], cat["residual_us"])
        if self._fix:
            gps_gaps(q, np.concatenate([a for a, _ in self._fix]), np.concatenate([b for _, b in self._fix]))
        imu_ok = self._imu_n <= MAX_IMU_STAMPS
        if imu_ok and self._imu:
            imu_ns = np.concatenate(self._imu)
            imu_gaps(q, imu_ns)
            if self._truth:
                q.timing = timing_error(imu_ns, np.sort(np.concatenate(self._truth)), q.first_lock_ns)
        return q, imu_ok

    def record(self) -> dict[str, str]:
        """The ``fieldlog.info`` metadata record: Python literals, one key each."""
        q, imu_ok = self.quality()
        out = {f"span.{topic}": repr(tuple(s)) for topic, s in self.span.items()}
        d = asdict(q)
        if not imu_ok:
            for k in ("imu_gaps", "imu_longest_gap_s", "timing"):
                d.pop(k)
        out.update({k: repr(v) for k, v in d.items()})
        return out


def quality_from_record(rec: dict[str, str]) -> Quality | None:
    """The inverse of ``DriveStats.record`` (None when the record lacks a figure: scan the file instead)."""
    import ast

    names = set(Quality.__dataclass_fields__)
    if not names <= set(rec):
        return None
    vals = {k: ast.literal_eval(rec[k].replace("nan", "None")) for k in names}
    for k in ("rate_ppm", "residual_us"):
        vals[k] = float("nan") if vals[k] is None else vals[k]
    if vals["timing"] is not None:
        vals["timing"] = TimingError(**vals["timing"])
    return Quality(**vals)
