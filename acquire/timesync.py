"""GPS time sync: UTC (int64 ns) of every DAQ sample from the PPS edges and the NMEA seconds.

Records from both ports are fed in host-monotonic order: ``add_fix`` for each NMEA epoch, ``add_frames`` for
each read of decoded DAQ frames. Every result is a deterministic function of the fed records, whenever the
outputs are polled, so ``fieldlog rebuild`` reproduces a live drive bit for bit. Splitting a read's frames
across calls moves only its edges' host times (below), which the gates read.

Edges. A flagged frame k gives the edge position k_edge = k - 1 + latch/65536 (latch valid) or k - 0.5
(flag only), in sample-index units. Its host time is that of the read that brought it, less the samples that
came after it in the same call (k_last - k) at the DAQ rate: a read late on the host (a stalled reader, a
loaded machine) returns the frames the port buffered meanwhile, and only its last frame is as late as the
read. Each edge is labelled as gpsd does: the UTC second of the last fix received before that host time,
plus 1. It is rejected when there was no fix (``no_fix``), that fix is older than
``max_fix_age_s`` (``stale_fix``), the label minus the edge's host time disagrees by more than
``max_disagree_s`` with the same offset of the previous edges (``disagree``: a glitch mid-second), its label
was already used (``duplicate``) or it is off the running clock fit (``outlier``). Before the first lock,
candidates wait until ``min_edges`` of them within ``acquire_s`` fit one line (Theil-Sen); those that do not
are ``outlier``, those never part of a lock ``unlocked``.

Implausible PPS. A frame flagged when at least ``PPS_BURST`` others were flagged within the ``PPS_BURST_S``
of samples before it cannot be a once-a-second pulse (a floating or miswired PPS line, a flag on every frame):
it is counted in ``implausible_edges`` and ignored (no edge, no /pps record), decided over the flags in one
vectorised pass, so such a line costs linear time and never reaches the fits below. Every fit then sees a
bounded number of edges: at most ``window_s`` + 1 accepted ones (one per GPS second), and the lock
candidates of ``acquire_s`` (at most ``PPS_BURST`` per ``PPS_BURST_S``); ``fit_edges`` counts the edges all
fits took, the work the robust fits do.

Clock fit. For every accepted edge i, a knot: Theil-Sen then least squares on the inliers of the accepted
edges within +-window_s/2 (on the DAQ clock) around it, fitting k_edge = kr + c + (fs + e) * (label - L_i)
(the noise is in k_edge, the labels are exact); at the first and last edges of the stream the window is
shifted to keep its full length. The knot's UTC is that fit evaluated at k_edge_i; rate error
ppm = e / fs * 1e6. A knot needs ``min_edges`` inliers. With a flag only, the quantisation error is a
sawtooth (the edge slips by frac(samples per second) every second), so the knot's UTC comes from a centred
window of a whole number of beat periods (<= window_s) when one fits, which cancels most of it.

Stamping rule for sample k (i = last knot at or before k, j = first knot after k, H = window_s/2):
  1. i and j, and j - i <= holdover_s: linear interpolation between the two knots' UTC;
  2. only i (or the next knot is more than holdover_s after i): extrapolation of the fit over the window_s
     before knot i ("holdover on the last fit"), kept after holdover_s too, flagged FREE;
  3. no knot before k, j within H after k: the first fit extrapolated backwards (samples just before the
     first lock get the first fit, not the host clock);
  4. otherwise host clock: k / fs plus the lower envelope of (frame wall_ns - k / fs) over the reads within
     +-host_window_s/2, FREE.
  States: LOCKED while the last accepted edge before k (rule 3: the first knot after k) is at most
  max_edge_gap_s away, HOLDOVER up to holdover_s, FREE beyond and for rule 4.
  Stamps never go backwards: the final stamp is M(k) = max(raw(k), M(k-1) + 1 ns), a forward clamp after a
  backward step (e.g. host clock -> first lock), which only ever occurs at a rule change.
A sample is final once nothing that can still arrive can change it: about window_s/2 + 1 s after it is read
when locked (window_s for the first knots of a stream), up to holdover_s + window_s/2 in a PPS gap, and
window_s/2 after the last pending lock candidate before the first lock. Memory is bounded: edges, knots and envelope bins older than
window_s + retain_s are dropped, and final stamps older than retain_s.
"""
from __future__ import annotations

import math
from bisect import bisect_left, bisect_right, insort
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass
from enum import IntEnum
from operator import itemgetter
from typing import Any

import numpy as np

from fieldlog.drive.tables import from_table
from fieldlog.fusion.median import median

FINALISE_BLOCK = 1 << 18     # samples stamped per step when finalising (about 9 min at 500 Hz)
PPS_BURST_S = 2.0            # a flag with PPS_BURST others within this many seconds of samples before it is
PPS_BURST = 4                # implausible (a true PPS and a glitch or two never come that close together)
FIXES_KEPT = 64              # recent fixes (host mono, UTC second) an edge's label is looked up in
_first = itemgetter(0)
_sum = np.add.reduce


def forward_clamp(r: np.ndarray, floor: int | None) -> np.ndarray:
    """Running maximum of r = stamp - k (ns) from ``floor`` (the last one of the previous batch, or None), so
    that stamps never go backwards: at most 1 ns per sample after a backward step of the fit."""
    cm = np.maximum.accumulate(r)
    return cm if floor is None else np.maximum(cm, floor)


class SyncState(IntEnum):
    """Per-sample time-sync state (stored as uint8)."""

    FREE = 0
    HOLDOVER = 1
    LOCKED = 2


@dataclass
class TimeSyncConfig:
    """Time-sync settings. Seconds unless stated; None picks the default for ``pps_mode``."""

    fs_hz: float = 500.0
    pps_mode: str = "flag"              # 'flag': sampled PPS flag only; 'latch': sub-sample latch
    window_s: float | None = None       # fit window: 120 s for 'flag' (>= 120), 30 s for 'latch'
    holdover_s: float = 30.0
    max_edge_gap_s: float = 2.5         # LOCKED while the last accepted edge is this recent (one drop is fine)
    max_fix_age_s: float = 1.1
    max_disagree_s: float = 0.4
    min_edges: int = 5                  # edges to lock, and inliers for a knot fit
    acquire_s: float = 10.0             # the first lock needs min_edges consistent edges within this span
    inlier_tol_s: float | None = None   # fit residual gate: 1 sample for 'flag', 50 us for 'latch'
    rate_tol_ppm: float = 2.0           # widens the edge gate with the time since the last accepted edge
    max_rate_ppm: float = 500.0         # a lock with a larger DAQ rate error is refused
    host_window_s: float = 10.0         # lower-envelope window of the pre-lock host-clock stamps
    retain_s: float = 300.0             # stamp() answers for samples up to this far behind final_until()
    # For simulator playback at ``sim --serve --speed X`` only: the data runs X times faster than the host
    # clock, so host durations are multiplied by X before the fix-age and disagreement gates and in the
    # locked ``mono_to_utc``. Never set it for real hardware.
    host_time_scale: float = 1.0
    pulse_error: bool = True            # apply the receiver's own time-pulse error (u-blox TIM-TP qErr)

    def __post_init__(self) -> None:
        if self.pps_mode not in ("flag", "latch"):
            raise ValueError(f"[timesync] pps_mode: {self.pps_mode!r} is not 'flag' or 'latch'")
        if self.window_s is None:
            # latch edges carry ~30 ns of noise, so a short window averages enough and follows the wander
            # better (the curvature bias of a linear fit grows as window^2).
            self.window_s = 120.0 if self.pps_mode == "flag" else 30.0
        if self.inlier_tol_s is None:
            self.inlier_tol_s = 1.0 / self.fs_hz if self.pps_mode == "flag" else 50e-6
        if self.pps_mode == "flag" and self.window_s < 120.0:
            raise ValueError(f"[timesync] window_s: {self.window_s} < 120 s with a sampled PPS flag")
        for name in ("fs_hz", "window_s", "holdover_s", "max_edge_gap_s", "max_fix_age_s", "max_disagree_s",
                     "acquire_s", "inlier_tol_s", "rate_tol_ppm", "max_rate_ppm", "host_window_s", "retain_s",
                     "host_time_scale"):
            if not getattr(self, name) > 0:
                raise ValueError(f"[timesync] {name}: must be > 0, got {getattr(self, name)!r}")
        if self.min_edges < 3:
            raise ValueError(f"[timesync] min_edges: must be >= 3, got {self.min_edges!r}")

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "TimeSyncConfig":
        return from_table(cls, "timesync", d)


@dataclass
class PpsEdge:
    """A processed PPS edge: position on the DAQ clock (sample units), host time of its frame, GPS second or -1."""

    k_edge: float
    mono_ns: int
    label: int = -1
    accepted: bool = False
    reason: str = ""          # '' when accepted, else why it was rejected


@dataclass(frozen=True)
class SyncStatus:
    """One /time/sync record, at the whole UTC second ``utc_ns`` (first final sample of that second)."""

    utc_ns: int
    state: SyncState
    rate_ppm: float           # DAQ oscillator rate error (nan without a fit)
    residual_us: float        # RMS residual of the fit's inlier edges (nan without a fit)
    edges_used: int
    edges_rejected_total: int


@dataclass(frozen=True)
class EdgeBatch:
    """Processed edges as arrays (what ``pop_edges`` returns)."""

    k_edge: np.ndarray        # float64, sample-index units
    mono_ns: np.ndarray       # int64 host time of the edge's frame
    label_s: np.ndarray       # int64 GPS second, -1 if none
    accepted: np.ndarray      # bool
    reason: np.ndarray        # str, '' when accepted

    @classmethod
    def of(cls, edges: list[PpsEdge]) -> "EdgeBatch":
        return cls(np.array([e.k_edge for e in edges], np.float64), np.array([e.mono_ns for e in edges], np.int64),
                   np.array([e.label for e in edges], np.int64), np.array([e.accepted for e in edges], bool),
                   np.array([e.reason for e in edges], str))

    def __len__(self) -> int:
        return len(self.k_edge)


@dataclass(frozen=True)
class StatusBatch:
    """/time/sync records as arrays (what ``pop_status`` returns); fields as in SyncStatus."""

    utc_ns: np.ndarray
    state: np.ndarray         # uint8 SyncState
    rate_ppm: np.ndarray
    residual_us: np.ndarray
    edges_used: np.ndarray
    edges_rejected: np.ndarray

    @classmethod
    def of(cls, st: list[SyncStatus]) -> "StatusBatch":
        return cls(np.array([s.utc_ns for s in st], np.int64), np.array([s.state for s in st], np.uint8),
                   np.array([s.rate_ppm for s in st], np.float64), np.array([s.residual_us for s in st], np.float64),
                   np.array([s.edges_used for s in st], np.int64),
                   np.array([s.edges_rejected_total for s in st], np.int64))

    def __len__(self) -> int:
        return len(self.utc_ns)


@dataclass(frozen=True)
class _Fit:
    """k_edge = kr + c + (fs + e) * (label - lr), from ``n`` inliers with RMS residual ``rms`` (samples)."""

    lr: int
    kr: int
    c: float
    e: float
    n: int
    rms: float
    x_mean: float
    sxx: float

    def predict_k(self, label: int, fs: float) -> float:
        return self.kr + self.c + (fs + self.e) * (label - self.lr)


def theil_sen(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """(slope, intercept) of the Theil-Sen line: the median of the slopes over pairs with x_j > x_i, and
    median(y) - slope median(x). The same floats as ``scipy.stats.theilslopes(y, x)`` (method "separate"),
    without its confidence interval (a normal quantile and repeat counts), which costs most of scipy's time and
    which the fit does not use."""
    dx = x[:, None] - x
    dy = y[:, None] - y
    pos = dx > 0
    slope = median(dy[pos] / dx[pos])
    return slope, median(y) - slope * median(x)


def robust_fit(label: np.ndarray, k_edge: np.ndarray, lr: int, kr: int, fs: float, tol: float,
               min_inliers: int) -> tuple[_Fit, np.ndarray] | None:
    """Theil-Sen, then least squares on the edges within ``tol`` samples of it. None if too few inliers.

    Each mean is a sum (``np.add.reduce``) over the count, the float ``np.mean`` gives without its own steps,
    which cost more than the sums on the few hundred edges of a fit."""
    x = (label - lr).astype(np.float64)
    y = k_edge - kr - fs * x
    if len(x) < min_inliers or x.min() == x.max():
        return None
    slope, intercept = theil_sen(x, y)
    inl = np.abs(y - intercept - slope * x) <= tol
    xi, yi = x[inl], y[inl]
    n = len(xi)
    if n < min_inliers or xi.min() == xi.max():
        return None
    xm, ym = _sum(xi) / n, _sum(yi) / n
    dx = xi - xm
    sxx = float(_sum(dx * dx))
    e = float(_sum(dx * (yi - ym)) / sxx)
    c = float(ym - e * xm)
    r = yi - c - e * xi
    rms = math.sqrt(_sum(r * r) / n)
    return _Fit(lr, kr, c, e, n, rms, float(xm), sxx), inl


@dataclass(frozen=True)
class _Samples:
    """The settings the pieces compare sample indices with, in samples (``fs`` in Hz)."""

    fs: float
    H: float                  # window_s / 2
    G: float                  # max_edge_gap_s
    HO: float                 # holdover_s
    tol: float                # inlier_tol_s
    bin: int                  # host-envelope bins of ~1 s of samples

    @classmethod
    def of(cls, c: TimeSyncConfig) -> "_Samples":
        fs = float(c.fs_hz)
        return cls(fs, c.window_s / 2 * fs, c.max_edge_gap_s * fs, c.holdover_s * fs, c.inlier_tol_s * fs,
                   max(1, round(fs)))


class HostClock:
    """The host clocks: rule 4's host-clock stamps and ``mono_to_utc`` (module docstring).

    Parameters
    ----------
    cfg : TimeSyncConfig
        ``host_window_s`` (s) sizes the lower envelope, ``host_time_scale`` (data s per host s) scales host
        durations.
    s : _Samples
        The settings in samples.
    """

    def __init__(self, cfg: TimeSyncConfig, s: _Samples) -> None:
        self.cfg = cfg
        self._bin = s.bin
        self.ns_per_sample = 1e9 / s.fs
        self._bin_half = max(1, math.ceil(cfg.host_window_s / 2))
        self.bins: dict[int, int] = {}                           # bin -> min(wall_ns - k*ns_per_sample)
        self.wall_minus_mono: int | None = None
        self.offsets: deque[int] = deque(maxlen=16)              # label - edge mono (ns), accepted edges only

    def put(self, bins: Iterable[int], offsets: Iterable[int]) -> None:
        """Host offsets (wall ns - k * ns per sample) seen in envelope bins ``bins``, in turn: each bin keeps the
        least."""
        kept = self.bins
        for b, v in zip(bins, offsets):
            old = kept.get(b)
            kept[b] = v if old is None or v < old else old

    def add_read(self, k: np.ndarray, wall_ns: int) -> None:
        """The frames ``k`` (sample indices) of one read at host wall time ``wall_ns`` (ns) into the bins."""
        b = k // self._bin
        if b[0] == b[-1]:
            last = [k.size - 1]
        else:
            last = np.flatnonzero(np.diff(b, append=b[-1] + 1)).tolist()   # last frame of each bin in this read
        self.put(b[last].tolist(), [wall_ns - round(x * self.ns_per_sample) for x in k[last].tolist()])

    def _offset(self, b: int) -> int:
        vals = [self.bins[x] for x in range(b - self._bin_half, b + self._bin_half + 1) if x in self.bins]
        if vals:
            return min(vals)
        return self.bins[max(x for x in self.bins if x <= b)]     # a long frame gap: the last bin before

    def stamps(self, k: np.ndarray) -> np.ndarray:
        """Host-clock UTC (int64 ns) of samples ``k``: k / fs plus the lower envelope of the host offsets of their
        bins."""
        bins, inv = np.unique(k // self._bin, return_inverse=True)
        off = np.array([self._offset(b) for b in bins.tolist()], np.int64)[inv]
        return np.round(k * self.ns_per_sample).astype(np.int64) + off

    def host_ns(self, samples: int) -> int:
        """The host duration (ns) of ``samples`` DAQ samples (``host_time_scale``)."""
        return round(samples * self.ns_per_sample / self.cfg.host_time_scale)

    def scaled(self, mono_ns: int | np.ndarray) -> int | np.ndarray:
        """Host time ``mono_ns`` (ns) in data ns (``host_time_scale``; the identity at 1)."""
        x = self.cfg.host_time_scale
        return mono_ns if x == 1.0 else np.round(np.asarray(mono_ns, np.float64) * x).astype(np.int64)

    def add_edge(self, label: int, mono_ns: int) -> None:
        """An accepted edge of GPS second ``label`` read at host ``mono_ns`` (ns): a sample of the host latency."""
        self.offsets.append(label * 1_000_000_000 - int(self.scaled(mono_ns)))

    def mono_to_utc(self, mono_ns: np.ndarray) -> np.ndarray:
        """Host monotonic time (ns) -> UTC (int64 ns): see ``TimeSync.mono_to_utc``.

        Parameters
        ----------
        mono_ns : np.ndarray
            Host monotonic times, ns.

        Returns
        -------
        np.ndarray
            UTC, int64 ns.
        """
        if self.offsets:
            return self.scaled(np.asarray(mono_ns, np.int64)) + np.int64(max(self.offsets))
        if self.wall_minus_mono is None:
            raise RuntimeError("mono_to_utc before any read: pass wall_ns to add_fix")
        return np.asarray(mono_ns, np.int64) + np.int64(self.wall_minus_mono)

    def prune(self, floor: int) -> None:
        """Drop the bins no sample from ``floor`` (sample index) on can use."""
        old = sorted(b for b in self.bins if b < floor // self._bin - self._bin_half - 1)
        for b in old[:-1]:                                          # the last one may still be the nearest
            del self.bins[b]


class EdgeLabeller:
    """PPS edges labelled, gated and locked (module docstring, "Edges" and "Implausible PPS").

    Holds the accepted edges (``acc_k`` in samples, ``acc_label`` in GPS s) the clock fit uses, the rejected ones
    (``rej_k``) the status counts, the lock candidates (``pending``) and the causal fit (``fit``) that gates new
    edges.

    Parameters
    ----------
    cfg : TimeSyncConfig
        The gates' settings.
    s : _Samples
        The settings in samples.
    host : HostClock
        Scales host durations and takes the accepted edges' host latency.
    """

    def __init__(self, cfg: TimeSyncConfig, s: _Samples, host: HostClock) -> None:
        self.cfg, self._s, self._host = cfg, s, host
        self._fixes: deque[tuple[int, int]] = deque(maxlen=FIXES_KEPT)   # (host mono ns, UTC s) of recent fixes
        self._pulse_late: dict[int, float] = {}                  # utc_s -> receiver's pulse error (s)
        self._flags = np.zeros(0, np.int64)                      # the last PPS_BURST flagged samples
        self.implausible_edges = 0
        self.fit_edges = 0                                       # edges taken by all robust fits (their work)
        self._edges: deque[PpsEdge] = deque()                    # in k order, until popped
        self.pending: list[PpsEdge] = []                         # lock candidates
        self._offsets: deque[int] = deque(maxlen=9)              # label - edge mono (ns), recent labelled edges
        self.fit: _Fit | None = None                             # causal fit: the acceptance gate
        self.acc_k: list[float] = []                             # accepted edges (retained)
        self.acc_label: list[int] = []
        self.acc_first: float | None = None                      # first accepted edge ever
        self.rej_k: list[float] = []                             # rejected edges (retained)
        self.rej_dropped = 0

    def add_fix(self, utc_s: int, mono_ns: int) -> None:
        """An NMEA epoch of the whole UTC second ``utc_s`` read at host ``mono_ns`` (ns): the label of the edges
        after it."""
        self._fixes.append((int(mono_ns), int(utc_s)))

    def add_pulse_error(self, utc_s: int, late_s: float) -> None:
        """The receiver's time pulse of UTC second ``utc_s`` comes ``late_s`` (s) late: see
        ``TimeSync.add_pulse_error``."""
        if not self.cfg.pulse_error:
            return
        self._pulse_late[int(utc_s)] = float(late_s)
        while len(self._pulse_late) > 16:
            del self._pulse_late[next(iter(self._pulse_late))]

    def add_flags(self, k: np.ndarray, pps: np.ndarray, latch: np.ndarray, latch_valid: np.ndarray,
                  mono_ns: int) -> None:
        """The PPS flags of one read's frames (sample index ``k``, flag, latch in 1/65536 sample) read at host
        ``mono_ns`` (ns): each plausible flag is an edge, labelled and judged, at the host time of its frame
        (``mono_ns`` less the host duration of the samples after it in ``k``)."""
        last = int(k[-1])
        for i in self._plausible(k, np.flatnonzero(pps)).tolist():
            ke = float(k[i] - 1) + (float(latch[i]) / 65536.0 if latch_valid[i] else 0.5)
            self._on_edge(PpsEdge(ke, mono_ns - self._host.host_ns(last - int(k[i]))))

    def _plausible(self, k: np.ndarray, flagged: np.ndarray) -> np.ndarray:
        """The flagged frames (indices into k) that may be PPS edges: not preceded by ``PPS_BURST`` flags within
        ``PPS_BURST_S`` of samples; the others are counted in ``implausible_edges``."""
        ks = np.concatenate((self._flags, k[flagged]))
        n0 = len(self._flags)
        p = np.arange(n0, len(ks))
        back = p - PPS_BURST
        bad = (back >= 0) & (ks[np.maximum(back, 0)] >= ks[p] - PPS_BURST_S * self._s.fs)
        self._flags = ks[-PPS_BURST:]
        self.implausible_edges += int(bad.sum())
        return flagged[~bad]

    def _reject(self, e: PpsEdge, reason: str) -> None:
        e.reason = reason
        insort(self.rej_k, e.k_edge)

    def _accept(self, e: PpsEdge) -> None:
        e.accepted = True
        if self.acc_first is None:
            self.acc_first = e.k_edge
        self.acc_k.append(e.k_edge)
        self.acc_label.append(e.label)
        self._host.add_edge(e.label, e.mono_ns)

    def _on_edge(self, e: PpsEdge) -> None:
        self._edges.append(e)
        c, s = self.cfg, self._s
        j = bisect_right(self._fixes, e.mono_ns, key=_first) - 1    # the last fix received before the edge
        if j < 0:
            return self._reject(e, "no_fix")
        fix_mono, fix_utc = self._fixes[j]
        if int(self._host.scaled(e.mono_ns - fix_mono)) > c.max_fix_age_s * 1e9:
            return self._reject(e, "stale_fix")
        e.label = fix_utc + 1
        e.k_edge -= self._pulse_late.pop(e.label, 0.0) * s.fs
        off = e.label * 1_000_000_000 - int(self._host.scaled(e.mono_ns))
        ref = median(np.array(self._offsets)) if self._offsets else off
        self._offsets.append(off)
        if abs(off - ref) > c.max_disagree_s * 1e9:
            return self._reject(e, "disagree")
        if self.fit is None:
            return self._acquire(e)
        if self.acc_label and e.label <= self.acc_label[-1]:
            return self._reject(e, "duplicate")
        f = self.fit
        dx = e.label - f.lr - f.x_mean
        sigma = max(f.rms, 0.1 * s.tol) * math.sqrt(1.0 / f.n + dx * dx / f.sxx)
        gate = s.tol + 4.0 * sigma + c.rate_tol_ppm * 1e-6 * s.fs * (e.label - self.acc_label[-1])
        if abs(e.k_edge - f.predict_k(e.label, s.fs)) > gate:
            return self._reject(e, "outlier")
        self._accept(e)
        self._refit(e)

    def counted_fit(self, label: np.ndarray, k_edge: np.ndarray, lr: int, kr: int, min_inliers: int
               ) -> tuple[_Fit, np.ndarray] | None:
        """``robust_fit`` of edges ``k_edge`` (samples) labelled ``label`` (GPS s) within the inlier tolerance,
        counted in ``fit_edges``."""
        self.fit_edges += len(label)
        return robust_fit(label, k_edge, lr, kr, self._s.fs, self._s.tol, min_inliers)

    def _refit(self, e: PpsEdge) -> None:
        """Causal fit over the accepted edges within window_s before ``e``."""
        i0 = bisect_left(self.acc_k, e.k_edge - 2 * self._s.H)
        fit = self.counted_fit(np.asarray(self.acc_label[i0:]), np.asarray(self.acc_k[i0:]), e.label,
                               math.floor(e.k_edge), 2)
        if fit is not None:
            self.fit = fit[0]

    def _acquire(self, e: PpsEdge) -> None:
        span = self.cfg.acquire_s * self._s.fs
        for old in [p for p in self.pending if p.k_edge < e.k_edge - span]:
            self._reject(old, "unlocked")
        self.pending = [p for p in self.pending if p.k_edge >= e.k_edge - span] + [e]
        labels = np.array([p.label for p in self.pending])
        ks = np.array([p.k_edge for p in self.pending])
        fit = self.counted_fit(labels, ks, e.label, math.floor(e.k_edge), self.cfg.min_edges)
        if fit is None:
            return
        f, inl = fit
        if abs(f.e / self._s.fs * 1e6) > self.cfg.max_rate_ppm or len(set(labels[inl].tolist())) < inl.sum():
            return
        for p, good in zip(self.pending, inl):
            self._accept(p) if good else self._reject(p, "outlier")
        self.pending = []
        self.fit = f

    def expire(self, k_max: int) -> None:
        """Reject the lock candidates further than acquire_s from any edge still to come after sample ``k_max``."""
        limit = k_max - 1 - self.cfg.acquire_s * self._s.fs
        while self.pending and self.pending[0].k_edge < limit:
            self._reject(self.pending.pop(0), "unlocked")

    def finish(self) -> None:
        """End of stream: the lock candidates left are ``unlocked``."""
        for e in self.pending:
            self._reject(e, "unlocked")
        self.pending = []

    def pop(self) -> list[PpsEdge]:
        """The edges whose fate is decided, in k order (each returned once)."""
        out = []
        while self._edges and (self._edges[0].accepted or self._edges[0].reason):
            out.append(self._edges.popleft())
        return out

    def prune(self, floor: int, keep_from: float, n_knotted: int) -> int:
        """Drop the edges no stamp from sample ``floor`` on needs: accepted ones before ``keep_from`` (samples)
        not left to turn into knots (of the first ``n_knotted``), and rejected ones before ``floor`` (counted in
        ``rej_dropped``). Returns the number of accepted edges dropped."""
        na = min(bisect_left(self.acc_k, keep_from), n_knotted, max(0, bisect_right(self.acc_k, floor) - 1))
        if na > 0:
            del self.acc_k[:na], self.acc_label[:na]
        nr = bisect_right(self.rej_k, floor)
        if nr > 0:
            self.rej_dropped += nr
            del self.rej_k[:nr]
        return na


class ClockFit:
    """The knots (module docstring, "Clock fit") and the stamping rule over them.

    Parameters
    ----------
    cfg : TimeSyncConfig
        ``pps_mode`` and ``min_edges``.
    s : _Samples
        The settings in samples.
    edges : EdgeLabeller
        The accepted edges the knots are fitted to (and the fits counted by).
    host : HostClock
        Stamps the samples no knot governs (rule 4).
    """

    def __init__(self, cfg: TimeSyncConfig, s: _Samples, edges: EdgeLabeller, host: HostClock) -> None:
        self.cfg, self._s, self._edges, self._host = cfg, s, edges, host
        self.n_knotted = 0                                       # accepted edges already turned into knots
        # knots: (label, d_s = knot UTC - label, s per sample of the knot fit, ppm, rms_us, n) at knot_k
        self.knot_k: list[float] = []
        self.knot: list[tuple[int, float, float, float, float, int]] = []
        self._trail: dict[float, float] = {}                    # knot k_edge -> s/sample of the trailing fit

    def _window(self, idx: int, finished: bool) -> tuple[float, float]:
        """DAQ-clock span of knot idx's fit: +-window_s/2, stretched to the full window_s at the data's ends."""
        acc_k, H = self._edges.acc_k, self._s.H
        ke = acc_k[idx]
        lo, hi = ke - H, max(ke + H, self._edges.acc_first + 2 * H)
        if finished and hi > acc_k[-1]:
            lo = min(lo, acc_k[-1] - 2 * H)
        return lo, hi

    def due(self, kd: float, finished: bool) -> bool:
        """Whether the next knot's window is complete once every edge up to sample ``kd`` is in."""
        return self.n_knotted < len(self._edges.acc_k) and self._window(self.n_knotted, finished)[1] <= kd

    def _fit_span(self, lo: float, hi: float, lab: int, kr: int) -> _Fit | None:
        acc_k = self._edges.acc_k
        i0, i1 = bisect_left(acc_k, lo), bisect_right(acc_k, hi)
        fit = self._edges.counted_fit(np.asarray(self._edges.acc_label[i0:i1]), np.asarray(acc_k[i0:i1]), lab, kr,
                                      self.cfg.min_edges)
        return None if fit is None else fit[0]

    def fit_next(self, finished: bool) -> None:
        """The knot of the next accepted edge (none when its window has too few inliers)."""
        idx = self.n_knotted
        self.n_knotted += 1
        fs = self._s.fs
        ke, lab = self._edges.acc_k[idx], self._edges.acc_label[idx]
        lo, hi = self._window(idx, finished)
        kr = math.floor(ke)
        f = fc = self._fit_span(lo, hi, lab, kr)
        if f is not None and self.cfg.pps_mode == "flag":
            # The flag's quantisation error is a sawtooth: the edge slips by frac(samples per second) each
            # second. A window of whole beat periods centred on the knot averages it out; other windows leave
            # part of a period. At the data's ends (no centred window) the full window does better.
            slip = abs((fs + f.e + 0.5) % 1.0 - 0.5)
            n_beats = math.floor((hi - lo) / fs * slip)
            half = n_beats / slip * fs / 2 if n_beats >= 1 else 0.0   # slip 0: a whole number of samples
            # (Its slope is biased by the sawtooth: the rate and the statistics come from the full window.)
            if n_beats >= 1 and lo <= ke - half and ke + half <= hi:
                fc = self._fit_span(ke - half, ke + half, lab, kr) or f
        if f is None:
            return
        rate = fs + f.e
        d = (ke - kr - fc.c) / (fs + fc.e)
        self.knot_k.append(ke)
        self.knot.append((lab, d, 1.0 / rate, f.e / fs * 1e6, f.rms / rate * 1e6, f.n))

    def _trail_slope(self, j: int) -> float:
        """s/sample of the fit over the window_s before knot j (holdover extrapolation)."""
        ke = self.knot_k[j]
        if ke not in self._trail:
            acc_k = self._edges.acc_k
            i0, i1 = bisect_left(acc_k, ke - 2 * self._s.H), bisect_right(acc_k, ke)
            fit = self._edges.counted_fit(np.asarray(self._edges.acc_label[i0:i1]), np.asarray(acc_k[i0:i1]),
                                          self.knot[j][0], math.floor(ke), self.cfg.min_edges)
            self._trail[ke] = 1.0 / (self._s.fs + fit[0].e) if fit is not None else self.knot[j][2]
        return self._trail[ke]

    def stamps(self, k: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Unclamped stamp (int64 ns), state (uint8) and governing knot (-1: host clock) of samples ``k``, by the
        module docstring's stamping rule."""
        n = len(k)
        raw = np.zeros(n, np.int64)
        state = np.full(n, SyncState.FREE, np.uint8)
        gov = np.full(n, -1, np.int64)
        kk = k.astype(np.float64)
        nk = len(self.knot_k)
        if nk and n:
            # the knots samples k can take, as arrays (indexes below from knot lo on): the last one at or before
            # the first sample to the first one after the last sample
            lo = max(bisect_right(self.knot_k, float(kk.min())) - 1, 0)
            hi = min(bisect_right(self.knot_k, float(kk.max())) + 1, nk)
            K = np.asarray(self.knot_k[lo:hi], np.float64)
            kn = np.asarray(self.knot[lo:hi], np.float64).reshape(-1, 6)
            lab = np.asarray([kn_[0] for kn_ in self.knot[lo:hi]], np.int64)
            HO = self._s.HO
            i = np.searchsorted(K, kk, "right") - 1
            ii, jj = np.maximum(i, 0), np.minimum(i + 1, hi - lo - 1)
            has_i, has_j = i + lo >= 0, i + lo + 1 < nk
            interp = has_i & has_j & (K[jj] - K[ii] <= HO)
            extrap = has_i & ~interp
            back = ~has_i & has_j & (K[jj] - kk <= self._s.H)
            d = kn[:, 1]
            if interp.any():
                a, b = ii[interp], jj[interp]
                span = (lab[b] - lab[a]) + (d[b] - d[a])
                frac = (kk[interp] - K[a]) / (K[b] - K[a])
                raw[interp] = lab[a] * 1_000_000_000 + np.round((d[a] + frac * span) * 1e9).astype(np.int64)
            if extrap.any():
                a = ii[extrap]
                slope = np.array([self._trail_slope(lo + j) for j in a.tolist()])
                raw[extrap] = lab[a] * 1_000_000_000 + np.round((d[a] + (kk[extrap] - K[a]) * slope) * 1e9).astype(
                    np.int64)
            if back.any():
                b = jj[back]
                raw[back] = lab[b] * 1_000_000_000 + np.round((d[b] + (kk[back] - K[b]) * kn[b, 2]) * 1e9).astype(
                    np.int64)
            gov[interp | extrap] = lo + ii[interp | extrap]
            gov[back] = lo + jj[back]
            A = np.asarray(self._edges.acc_k)
            a = np.searchsorted(A, kk, "right") - 1
            age = np.where(a >= 0, kk - A[np.maximum(a, 0)], np.inf)
            age[back] = K[jj[back]] - kk[back]
            synced = interp | extrap | back
            state[synced & (age <= HO)] = SyncState.HOLDOVER
            state[synced & (age <= self._s.G)] = SyncState.LOCKED
        host = gov < 0
        if host.any():
            raw[host] = self._host.stamps(k[host])
        return raw, state, gov

    def prune(self, floor: int) -> float:
        """Drop the knots before the last one at or before sample ``floor``; returns the first accepted edge (in
        samples) a knot kept or still to fit may need."""
        nk = bisect_right(self.knot_k, floor) - 1                   # keep the last knot at or before the floor
        if nk > 0:
            for ke in self.knot_k[:nk]:
                self._trail.pop(ke, None)
            del self.knot_k[:nk], self.knot[:nk]
        return (self.knot_k[0] if self.knot_k else floor) - 2 * self._s.H - 1


class Finaliser:
    """Final stamps: the knots fitted when their windows are complete, the samples they decide stamped, clamped
    forward and reported in /time/sync records, and memory pruned (module docstring, end). The final stamps and
    states are kept as made, for ``stamp``, until they fall below the retained range: nothing that comes later
    changes them (that is what final means).

    Parameters
    ----------
    cfg : TimeSyncConfig
        ``retain_s``.
    s : _Samples
        The settings in samples.
    edges, clock, host : EdgeLabeller, ClockFit, HostClock
        The pieces whose state decides and makes the stamps.
    """

    def __init__(self, cfg: TimeSyncConfig, s: _Samples, edges: EdgeLabeller, clock: ClockFit,
                 host: HostClock) -> None:
        self.cfg, self._s, self._edges, self._clock, self._host = cfg, s, edges, clock, host
        self.first: int | None = None                            # the first sample index seen
        self.final = 0                                           # samples before this one are final
        self.floor = 0                                           # ... and retained from this one
        self._pmax: int | None = None                            # max over final samples of raw(k) - k
        # the final samples' stamps (int64 UTC ns) and states (uint8) in consecutive blocks, each from sample k0
        self._kept: deque[tuple[int, np.ndarray, np.ndarray]] = deque()
        self._status: list[SyncStatus] = []
        self._status_sec: int | None = None

    def begin(self, k0: int) -> None:
        """The stream starts at sample ``k0``."""
        self.first = self.final = self.floor = k0

    def _decided(self, k_max: int, finished: bool) -> float:
        """The last sample before any edge still to be decided (every edge up to it is in)."""
        if finished:
            return math.inf
        kd = k_max - 1
        if self._edges.pending:
            kd = min(kd, math.floor(self._edges.pending[0].k_edge) - 1)
        return kd

    def _target(self, kd: float, k_max: int) -> int:
        """Samples before this one have final stamps once the knots up to kd are fitted."""
        kf = kd                                # every knot at or before kf is known
        acc_k, knot_k = self._edges.acc_k, self._clock.knot_k
        if self._clock.n_knotted < len(acc_k):
            kf = min(kf, math.nextafter(acc_k[self._clock.n_knotted], -math.inf))
        end = k_max + 1
        if knot_k:
            last = knot_k[-1]
            fu = end if kf >= last + self._s.HO else math.ceil(last)
        else:
            fu = end if kf == math.inf else math.floor(kf - self._s.H) + 1
        return min(fu, end)

    def _ready(self, fu: int, finished: bool) -> bool:
        # host-clock stamps (no knot yet) are finalised in steps of >= 1 s, not on every read
        return fu > self.final and bool(self._clock.knot_k or finished or fu - self.final >= self._s.bin)

    def due(self, k_max: int, finished: bool) -> bool:
        """Whether ``advance`` would change anything now."""
        if self.first is None:
            return False
        kd = self._decided(k_max, finished)
        return self._clock.due(kd, finished) or self._ready(self._target(kd, k_max), finished)

    def advance(self, k_max: int, finished: bool) -> None:
        """Fit the knots whose windows are complete, then make final the stamps they decide, with the frames up to
        sample ``k_max`` in (``finished``: and no more to come)."""
        if self.first is None:
            return
        kd = self._decided(k_max, finished)
        while self._clock.due(kd, finished):
            self._clock.fit_next(finished)
        fu = self._target(kd, k_max)
        if self._ready(fu, finished):
            while self.final < fu:       # in blocks: memory stays bounded across a long frame gap
                self._finalise(self.final, min(fu, self.final + FINALISE_BLOCK))

    def _finalise(self, f0: int, f1: int) -> None:
        k = np.arange(f0, f1, dtype=np.int64)
        raw, state, gov = self._clock.stamps(k)
        cm = forward_clamp(raw - k, self._pmax)
        self._pmax = int(cm[-1])
        stamp = cm + k
        self._kept.append((f0, stamp, state))
        sec = stamp // 1_000_000_000
        first = np.flatnonzero(np.diff(sec, prepend=sec[0] - 1) > 0)
        rej = np.asarray(self._edges.rej_k)
        for i in first.tolist():
            s = int(sec[i])
            if self._status_sec is not None and s <= self._status_sec:
                continue
            self._status_sec = s
            g = int(gov[i])
            n_rej = self._edges.rej_dropped + int(np.searchsorted(rej, k[i], "right"))
            if g >= 0:
                _, _, _, ppm, rms_us, used = self._clock.knot[g]
                self._status.append(SyncStatus(s * 1_000_000_000, SyncState(int(state[i])), ppm, rms_us, used, n_rej))
            else:
                self._status.append(SyncStatus(s * 1_000_000_000, SyncState.FREE, math.nan, math.nan, 0, n_rej))
        self.final = f1
        self._prune()

    def _prune(self) -> None:
        floor = max(self.first, self.final - int(self.cfg.retain_s * self._s.fs))
        self.floor = floor
        keep_from = self._clock.prune(floor)
        self._clock.n_knotted -= self._edges.prune(floor, keep_from, self._clock.n_knotted)
        while len(self._kept) > 1 and self._kept[1][0] <= floor:
            self._kept.popleft()
        self._host.prune(floor)

    def stamp(self, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """UTC (int64 ns) and SyncState (uint8) of final samples ``k``: see ``TimeSync.stamp``."""
        k = np.asarray(k, np.int64)
        if not k.size:
            return np.zeros(0, np.int64), np.zeros(0, np.uint8)
        lo, hi = int(k.min()), int(k.max())
        if lo < self.floor or hi >= self.final:
            raise ValueError(f"stamp: k outside the final, retained range [{self.floor}, {self.final})")
        kept = self._kept
        i, j = bisect_right(kept, lo, key=_first) - 1, bisect_right(kept, hi, key=_first)
        k0, stamp, state = kept[i]
        if j - i > 1:
            stamp, state = (np.concatenate([kept[x][y] for x in range(i, j)]) for y in (1, 2))
        at = k - k0
        return stamp[at], state[at]

    def pop_status(self) -> list[SyncStatus]:
        """The /time/sync records of the samples made final since the last call."""
        out, self._status = self._status, []
        return out


class TimeSync:
    """Streaming PPS/NMEA time sync; see the module docstring for the rules.

    Its loop feeds the pieces: ``labeller`` (an ``EdgeLabeller``: edges labelled and gated, the lock) and ``host``
    (a ``HostClock``) take each read, then the ``Finaliser`` has the ``ClockFit`` fit the knots whose windows are
    complete and makes final the stamps they decide. ``labeller.implausible_edges`` counts the implausible PPS
    flags, ``labeller.fit_edges`` the edges all robust fits took.

    Parameters
    ----------
    cfg : TimeSyncConfig, optional
        The settings (default: ``TimeSyncConfig()``).
    """

    def __init__(self, cfg: TimeSyncConfig | None = None) -> None:
        self.cfg = c = cfg or TimeSyncConfig()
        self._s = s = _Samples.of(c)
        self.host = HostClock(c, s)
        self.labeller = EdgeLabeller(c, s, self.host)
        self._clock = ClockFit(c, s, self.labeller, self.host)
        self._final = Finaliser(c, s, self.labeller, self._clock, self.host)
        self._k_max = -1
        self.frames_out_of_order = 0
        self._finished = False

    # ---------------------------------------------------------------- input
    def add_fix(self, utc_s: int, mono_ns: int, wall_ns: int | None = None) -> None:
        """An NMEA epoch for the whole UTC second ``utc_s`` whose first sentence was read at ``mono_ns``."""
        self.labeller.add_fix(utc_s, mono_ns)
        if wall_ns is not None:
            self.add_host_time(mono_ns, wall_ns)

    def add_pulse_error(self, utc_s: int, late_s: float) -> None:
        """The receiver's own figure for the time pulse of UTC second ``utc_s``: it comes ``late_s`` late (u-blox
        TIM-TP qErr); the edge labelled ``utc_s`` is moved back by that much before it is used."""
        self.labeller.add_pulse_error(utc_s, late_s)

    def add_host_time(self, mono_ns: int, wall_ns: int) -> None:
        """A read's host clocks: what ``mono_to_utc`` falls back on before the first lock."""
        self.host.wall_minus_mono = int(wall_ns) - int(mono_ns)

    def add_frames(self, k: np.ndarray, pps: np.ndarray, latch: np.ndarray, latch_valid: np.ndarray,
                   mono_ns: int, wall_ns: int) -> None:
        """Decoded DAQ frames (sample index k, PPS flag, latch) from one read at host ``mono_ns``/``wall_ns``.

        Frames whose k does not increase are counted in ``frames_out_of_order`` and ignored.
        """
        if self._finished:
            raise RuntimeError("TimeSync.add_frames after finish()")
        k = np.asarray(k, np.int64)
        if k.size == 0:
            return
        pps = np.asarray(pps, bool)
        if k[0] <= self._k_max or (k.size > 1 and not (k[1:] > k[:-1]).all()):
            ok = k > np.maximum.accumulate(np.concatenate(([self._k_max], k[:-1])))
            self.frames_out_of_order += int((~ok).sum())
            k, pps, latch, latch_valid = k[ok], pps[ok], np.asarray(latch)[ok], np.asarray(latch_valid)[ok]
            if k.size == 0:
                return
        if self._final.first is None:
            self._final.begin(int(k[0]))
        mono_ns, wall_ns = int(mono_ns), int(wall_ns)
        self.host.wall_minus_mono = wall_ns - mono_ns
        self.host.add_read(k, wall_ns)
        if pps.any():
            self.labeller.add_flags(k, pps, latch, latch_valid, mono_ns)
        self._k_max = int(k[-1])
        self.labeller.expire(self._k_max)
        self._final.advance(self._k_max, self._finished)

    def add_run(self, k: np.ndarray, pps: np.ndarray, latch: np.ndarray, latch_valid: np.ndarray,
                ends: list[int], mono_ns: list[int], wall_ns: list[int]) -> None:
        """The frames of several reads in a row, read i's ``k[ends[i - 1]:ends[i]]`` (``ends[-1] == len(k)``), at
        host ``mono_ns[i]``/``wall_ns[i]``: what ``add_frames`` of each read in turn does.

        Once frames came before, the reads without a PPS edge go in one pass (``_add_quiet``), and each read
        with one through ``add_frames``; otherwise every read goes through ``add_frames``.
        """
        if self._finished or self._final.first is None or not len(k) or k[0] <= self._k_max or not (k[1:] > k[:-1]).all():
            a = 0
            for b, m, w in zip(ends, mono_ns, wall_ns):
                self.add_frames(k[a:b], pps[a:b], latch[a:b], latch_valid[a:b], m, w)
                a = b
            return
        kl = k.tolist()
        r0 = 0                                 # the first read not added yet
        flags = np.flatnonzero(pps)            # most runs have none
        with_flag = sorted(set(np.searchsorted(ends, flags, "right").tolist())) if flags.size else []   # their reads
        for i in with_flag:
            a, b = (ends[i - 1] if i else 0), ends[i]
            if i > r0:
                self._add_quiet(kl, ends, r0, i, mono_ns, wall_ns)
            self.add_frames(k[a:b], pps[a:b], latch[a:b], latch_valid[a:b], mono_ns[i], wall_ns[i])
            r0 = i + 1
        if r0 < len(ends):
            self._add_quiet(kl, ends, r0, len(ends), mono_ns, wall_ns)

    def _add_quiet(self, k: list[int], ends: list[int], r0: int, r1: int, mono_ns: list[int],
                   wall_ns: list[int]) -> None:
        """``add_frames`` of reads ``r0``..``r1 - 1`` of ``add_run``, in a row without a PPS edge, after earlier
        frames, in one pass. Each read's host time goes into the host-clock bins, and the knots and final stamps
        are advanced after just those reads where ``add_frames`` would advance them, with the bins of the reads
        up to there, so each step sees the state it would.

        Without lock candidates to expire, whether an advance is due only grows with the read's last sample
        (``Finaliser.due`` is monotonic in ``k_max`` while nothing else changes), so the reads where one is due
        are found by bisection rather than by asking after every read."""
        bn, ns_per_sample = self._s.bin, self.host.ns_per_sample
        # read, bin and host offset of each bin's last frame in a read
        host_r: list[int] = []
        host_b: list[int] = []
        host_v: list[int] = []
        reads, ks = [], []                         # each read with frames and its last sample
        for r in range(r0, r1):
            a, b = (ends[r - 1] if r else 0), ends[r]
            if a == b:
                continue
            while a < b:
                j = bisect_left(k, (k[a] // bn + 1) * bn, a, b)      # past the last frame of k[a]'s bin
                host_r.append(r)
                host_b.append(k[j - 1] // bn)
                host_v.append(wall_ns[r] - round(k[j - 1] * ns_per_sample))
                a = j
            reads.append(r)
            ks.append(k[b - 1])
        if not reads:
            return
        h = 0

        def bins_until(i: float) -> None:   # the host times of the reads up to i into the bins
            nonlocal h
            e = bisect_right(host_r, i, h)
            self.host.put(host_b[h:e], host_v[h:e])
            h = e

        def due(e: int) -> bool:
            return self._final.due(e, self._finished)

        j, n = 0, len(ks)
        while j < n:
            if self.labeller.pending:
                self.labeller.expire(ks[j])
                if not due(ks[j]):
                    j += 1
                    continue
            else:
                j = bisect_left(ks, True, j, n, key=due)
                if j == n:
                    break
            bins_until(reads[j])
            self._final.advance(ks[j], self._finished)
            j += 1
        self._k_max = ks[-1]
        bins_until(math.inf)
        self.host.wall_minus_mono = int(wall_ns[reads[-1]]) - int(mono_ns[reads[-1]])

    def finish(self) -> None:
        """End of stream: every sample seen becomes final."""
        self.labeller.finish()
        self._finished = True
        self._final.advance(self._k_max, True)

    # ---------------------------------------------------------------- output
    def final_until(self) -> int:
        """First sample index whose stamp is not final yet."""
        return self._final.final

    def stamp(self, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """UTC (int64 ns) and SyncState (uint8) of final samples k, in [final_until() - retain_s, final_until())."""
        return self._final.stamp(k)

    def causal_stamp(self, k: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
        """Provisional UTC (int64 ns) and SyncState (uint8) of samples k from what has been fed so far, and
        whether a GPS clock fit exists.

        With a fit: the latest causal fit (the one gating new edges, over the window_s before the newest
        accepted edge) extrapolated to k; LOCKED while the newest accepted edge is at most max_edge_gap_s
        before k, HOLDOVER up to holdover_s, FREE beyond (still that fit). Before the first lock (False): the
        host clock, k / fs plus the lower envelope of the host offsets seen so far, FREE. Not clamped (it can
        step back when the fit changes) and not final: ``stamp`` replaces it about window_s/2 later.
        """
        k = np.asarray(k, np.int64)
        state = np.full(k.size, SyncState.FREE, np.uint8)
        f = self.labeller.fit
        if f is None:
            if not self.host.bins:
                raise RuntimeError("causal_stamp before any frame")
            return self.host.stamps(k), state, False
        s = (k - f.kr - f.c) / (self._s.fs + f.e)
        t = np.int64(f.lr) * 1_000_000_000 + np.round(s * 1e9).astype(np.int64)
        age = k - self.labeller.acc_k[-1]
        state[age <= self._s.HO] = SyncState.HOLDOVER
        state[age <= self._s.G] = SyncState.LOCKED
        return t, state, True

    @property
    def gps_clock(self) -> bool:
        """True once a PPS edge has been accepted: ``mono_to_utc`` then follows GPS time, not the host clock."""
        return bool(self.host.offsets)

    def mono_to_utc(self, mono_ns: np.ndarray) -> np.ndarray:
        """Host monotonic time -> UTC (int64 ns), with the data fed so far.

        Locked: the largest (label - host time) of the last 16 accepted edges (the one read with the least
        latency). Before that: the host wall clock of the latest read or fix.
        """
        return self.host.mono_to_utc(mono_ns)

    def pop_edges(self) -> EdgeBatch:
        """Edges whose fate is decided, in k order (each returned once)."""
        return EdgeBatch.of(self.labeller.pop())

    def pop_status(self) -> StatusBatch:
        """/time/sync records of the samples made final since the last call, at most one per UTC second."""
        return StatusBatch.of(self._final.pop_status())
