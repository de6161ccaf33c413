"""The simulated DAQ clock and PPS input, on the true time axis (seconds since the drive start, float64).

The oscillator runs at fs_hz * (1 + ppm(t) * 1e-6), ppm(t) = rate_offset_ppm + wander_ppm * sin(2 pi t / P + phase);
sample k is taken at its k-th tick (k = 0 at t = 0). The GPS receiver's PPS edge comes at every true whole
UTC second (plus jitter); the DAQ flags the first sample whose clock edge is at or after it and, in 'latch'
mode, latches the edge position inside that sample period as floor(fraction * 65536) from the previous
sample's clock edge (a timer capture), so k_edge = k - 1 + latch / 65536 is 15 ns early on average.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fieldlog.drive.tables import from_table


@dataclass
class ClockConfig:
    """DAQ clock and PPS model, from a scenario's ``[clock]`` table."""

    fs_hz: float = 500.0
    rate_offset_ppm: float = 40.0
    wander_ppm: float = 0.5               # amplitude of a sinusoidal rate wander (random phase)
    wander_period_s: float = 600.0
    pps_mode: str = "flag"                # 'flag' | 'latch'
    pps_jitter_ns: float = 20.0           # 1 sigma, of the receiver's time pulse
    dropped_pps: int = 3                  # edges lost, at random
    glitch_pps: int = 1                   # spurious PPS flags, at random samples
    pps_gaps: list = field(default_factory=list)   # [[start_s, len_s], ...]: no PPS at all
    start_utc_ns: int = 1_750_000_000_370_000_000  # UTC of the drive start; deliberately not a whole second

    def __post_init__(self) -> None:
        if self.pps_mode not in ("flag", "latch"):
            raise ValueError(f"[clock] pps_mode: {self.pps_mode!r} is not 'flag' or 'latch'")
        if not self.fs_hz > 0 or not self.wander_period_s > 0:
            raise ValueError("[clock] fs_hz and wander_period_s must be > 0")

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "ClockConfig":
        return from_table(cls, "clock", d)

    def first_second(self) -> float:
        """True time (s since start) of the first whole UTC second after the drive start."""
        return (1_000_000_000 - self.start_utc_ns % 1_000_000_000) / 1e9

    def first_utc_s(self) -> int:
        """That whole UTC second."""
        return self.start_utc_ns // 1_000_000_000 + 1


@dataclass(frozen=True)
class PpsTruth:
    """True PPS edges: time (s since start), UTC second, flagged sample (-1 if dropped or outside the data)."""

    t_s: np.ndarray
    utc_s: np.ndarray
    k: np.ndarray
    glitch_k: np.ndarray


def sample_times(n: int, cfg: ClockConfig, rng: np.random.Generator) -> np.ndarray:
    """True time (s since start) of DAQ samples k = 0..n-1: Newton inversion of the oscillator phase."""
    w = 2 * np.pi / cfg.wander_period_s
    phase0 = rng.uniform(0, 2 * np.pi)
    r, a = cfg.rate_offset_ppm * 1e-6, cfg.wander_ppm * 1e-6

    k = np.arange(n, dtype=np.float64)
    t = k / (cfg.fs_hz * (1 + r))
    phase, step, scaled = np.empty(n), np.empty(n), np.empty(n)
    for _ in range(3):
        # t -= (ticks(t) - k) / ticks'(t), ticks(t) = fs (t (1 + r) - a / w (cos(w t + phase0) - cos(phase0))),
        # ticks'(t) = fs (1 + r + a sin(w t + phase0)): each operation in that order, in place in three arrays
        np.multiply(w, t, out=phase)
        phase += phase0
        np.cos(phase, out=step)
        step -= np.cos(phase0)
        step *= a / w
        np.multiply(t, 1 + r, out=scaled)
        np.subtract(scaled, step, out=step)
        step *= cfg.fs_hz
        step -= k
        np.sin(phase, out=phase)
        phase *= a
        phase += 1 + r
        phase *= cfg.fs_hz
        step /= phase
        t -= step
    return t


def pps_frames(t_s: np.ndarray, cfg: ClockConfig, rng: np.random.Generator, first_second: float | None = None,
               pulse_late_s: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, PpsTruth]:
    """PPS flag, latch (uint16) and latch-valid per sample for sample times ``t_s``, and the true edges.

    Edges come at ``first_second`` + j (default ``cfg.first_second()``), UTC second ``cfg.first_utc_s()`` + j,
    plus jitter, plus ``pulse_late_s[j]`` when given (the receiver's own quantisation, which it reports).
    """
    n = len(t_s)
    t1 = cfg.first_second() if first_second is None else first_second
    m = int(np.floor(t_s[-1] - t1)) + 1 if n and t_s[-1] >= t1 else 0
    edges = t1 + np.arange(m) + rng.standard_normal(m) * cfg.pps_jitter_ns * 1e-9
    if pulse_late_s is not None:
        edges = edges + pulse_late_s[:m]
    k = np.searchsorted(t_s, edges, "left")
    k[(k == 0) | (k >= n)] = -1
    for start, length in cfg.pps_gaps:
        k[(edges >= start) & (edges < start + length)] = -1
    live = np.flatnonzero(k >= 0)
    if cfg.dropped_pps and live.size:
        k[rng.choice(live, size=min(cfg.dropped_pps, live.size), replace=False)] = -1
    pps = np.zeros(n, bool)
    latch = np.zeros(n, np.uint16)
    kk = k[k >= 0]
    pps[kk] = True
    free = np.flatnonzero(~pps[1:]) + 1  # the samples after the first without a pulse (kk has them set)
    glitch = np.sort(rng.choice(free, size=min(cfg.glitch_pps, free.size), replace=False))
    pps[glitch] = True
    latch_valid = pps.copy() if cfg.pps_mode == "latch" else np.zeros(n, bool)
    if cfg.pps_mode == "latch":
        frac = (edges[k >= 0] - t_s[kk - 1]) / (t_s[kk] - t_s[kk - 1])
        latch[kk] = np.minimum(np.floor(frac * 65536), 65535).astype(np.uint16)
        latch[glitch] = rng.integers(0, 65536, glitch.size).astype(np.uint16)
    truth = PpsTruth(t_s=edges, utc_s=cfg.first_utc_s() + np.arange(m, dtype=np.int64), k=k, glitch_k=glitch)
    return pps, latch, latch_valid, truth
