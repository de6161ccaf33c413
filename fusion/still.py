"""The still detector, shared by the alignment (``fusion.align``) and the stationary aid
(``fusion.measurements.Stationary``): whether a car stood still over a GPS interval, from the interval's IMU sums
(:class:`ImuSums`) and the GPS speed (:class:`GpsSpeed`).

The vehicle stood still over a GPS interval when

- the GPS speed is below its limit (:class:`GpsSpeed`): the horizontal speed of the mean of the GPS velocities
  of the last second (at least the interval's two ends), below ``still_gps_speed_mps`` or, for a noisier
  receiver, below ``SPEED_K`` = 1.5 sigmas of that mean (from the reported velocity covariance: sigma_v /
  sqrt(N) for N velocities). Between the limit and twice it the interval is "unsure" (left out; the still run
  goes on), beyond twice it "moving": a standing car's speed (Rayleigh) passes 2 x 1.5 = 3 sigmas in 1.1 % of
  its intervals, and a 10 Hz receiver's 0.1 m/s per axis averages to 0.03 m/s over a second. Skipped when the
  drive has no velocity;
- the specific force and rate vary less than ``still_accel_std_mps2`` and ``still_gyro_std_dps`` over it, or,
  for a car whose engine idles (its vibration alone is of order 1 deg/s and 0.1 m/s^2, above those limits), they
  vary as steadily as the still run they would join: a GPS speed measured and below its limit, and the
  interval's spread of rate and of specific force each within a factor ``STEADY_RATIO`` of the run's own (the
  signal's moving baseline; the first interval of a run is its own baseline). The vibration is fast (the engine
  fires at tens of Hz) and averages out of the interval's mean, so the mean tests below, whose gates grow with
  the interval's standard error, still tell a car that moves from one that shakes; a creeping car has a GPS
  speed, a car that pulls away or is bumped changes its spread;
- the mean rate and the mean specific force are where standing still puts them, within 4 sigma plus the
  floors ``still_rate_tol_dps`` and ``still_accel_tol_mps2``: before the alignment the means of the still
  interval so far (and a rate within the Earth rate plus the bias prior), after it the Earth rate plus the
  estimated gyro bias and gravity through the estimated attitude. A steady turn or a creep has a small spread
  but a mean rate or force that is off.

Frames: body RFU; IMU sums in rad/s and m/s^2; speeds in m/s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from fieldlog.fusion import errmodel, kernels
from fieldlog.fusion.types import Epoch

if TYPE_CHECKING:
    from fieldlog.fusion.config import FusionConfig

_DEG = math.pi / 180.0
GATE = 4.0  # sigmas: a bias's flicker gives the interval means heavier tails than white noise


@dataclass
class ImuSums:
    """Sums of IMU samples over an interval: rate (rad/s) and specific force (m/s^2), body RFU, and squares."""

    sum_w: np.ndarray = field(default_factory=lambda: np.zeros(3))
    sum_f: np.ndarray = field(default_factory=lambda: np.zeros(3))
    n: int = 0
    sum_ww: np.ndarray = field(default_factory=lambda: np.zeros(3))  # squares: the interval's variances
    sum_ff: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def std(self, total: np.ndarray, squares: np.ndarray) -> float:
        """Root of the summed per-axis variances of the samples, e.g. std(sum_f, sum_ff).

        Parameters
        ----------
        total : (3,) one of the sums (``sum_w`` rad/s or ``sum_f`` m/s^2).
        squares : (3,) its sums of squares (``sum_ww`` or ``sum_ff``).

        Returns
        -------
        float, the samples' spread in the unit of ``total``.
        """
        m = total / max(self.n, 1)
        return math.sqrt(max(float(np.sum(squares / max(self.n, 1) - m * m)), 0.0))

    def add(self, w: np.ndarray, f: np.ndarray, i0: int, i1: int) -> None:
        """Add samples (i0, i1] of w, f.

        Parameters
        ----------
        w : (n, 3) rate, rad/s, body RFU.
        f : (n, 3) specific force, m/s^2, body RFU.
        i0, i1 : the samples after i0 up to i1 are added.
        """
        ws, fs = (np.ascontiguousarray(a[i0 + 1:i1 + 1], float) for a in (w, f))
        # compiled (fusion/_cycles.c): numpy's sums over the rows and einsum("ij,ij->j"), to the bit
        errmodel.cycle_kernel().fieldlog_sample_sums(len(ws), *map(kernels.address, (ws, fs, self.sum_w, self.sum_f,
                                                                                     self.sum_ww, self.sum_ff)))
        self.n += max(i1 - i0, 0)

    def merge(self, other: ImuSums) -> None:
        """Add another interval's sums.

        Parameters
        ----------
        other : the interval whose samples join these.
        """
        self.sum_w += other.sum_w
        self.sum_f += other.sum_f
        self.sum_ww += other.sum_ww
        self.sum_ff += other.sum_ff
        self.n += other.n


STEADY_RATIO = 2.0  # a vibrating interval's spread within this factor of its still run's: the run goes on
SPEED_K = 1.5  # the GPS speed limit of the still detector: at least this many sigmas of the tested mean
_SPEED_SPAN_S = 1.0  # the GPS velocities of the last second are averaged for the tested speed


class GpsSpeed:
    """The GPS speed the still detector tests at each epoch, and its limit (module docstring)."""

    def __init__(self, cfg: FusionConfig) -> None:
        self.floor = cfg.still.still_gps_speed_mps
        self.recent: list[tuple[float, float, float, float]] = []  # t (s), velocity east, north (m/s), sigma per axis

    def add(self, t: float, v: np.ndarray, ep: Epoch) -> tuple[float, float]:
        """The GPS speed the still detector tests at an epoch, and its limit.

        Parameters
        ----------
        t : the epoch's time, s.
        v : (3,) its GPS velocity, ENU m/s (NaN: none).
        ep : the epoch (its covariances give the velocity's sigma, :func:`vel_sigma`).

        Returns
        -------
        (the horizontal speed of the mean velocity of the last second and the epoch before it, m/s, NaN without two
        velocities in a row; the limit, m/s: max(``still_gps_speed_mps``, SPEED_K x the mean's per-axis sigma)).
        """
        v_east, v_north = float(v[0]), float(v[1])
        if not (math.isfinite(v_east) and math.isfinite(v_north)):
            self.recent = []
            return math.nan, self.floor
        keep = [r for r in self.recent if r[0] >= t - _SPEED_SPAN_S - 1e-6]
        self.recent = (keep or self.recent[-1:]) + [(t, v_east, v_north, vel_sigma(ep))]
        if len(self.recent) < 2:
            return math.nan, self.floor
        n = len(self.recent)
        east = north = 0
        for r in self.recent:  # one after the other, from 0 (sum() may compensate)
            east, north = east + r[1], north + r[2]
        sigma = math.sqrt(sum(r[3] ** 2 for r in self.recent)) / n
        return float(np.hypot(east / n, north / n)), max(self.floor, SPEED_K * sigma)


_MIN_SAMPLES = 10  # per GPS interval, for its spread: 20 at 200 Hz with a 10 Hz receiver (aircraft)


def still(cfg: FusionConfig, interval: ImuSums, speed: tuple[float, float], w_ref: np.ndarray | None,
          w_sigma: float, f_ref: np.ndarray | None, f_sigma: float, baseline: ImuSums | None = None) -> bool:
    """Whether the vehicle stood still over a GPS interval (module docstring).

    Parameters
    ----------
    cfg : the settings (``[fusion]`` still keys).
    interval : the interval's IMU sums.
    speed : (the GPS speed, m/s, NaN: no GPS velocity, not tested; its limit, m/s) (:class:`GpsSpeed`).
    w_ref : (3,) rad/s, body: the mean rate standing still would give (None: not tested).
    w_sigma : its sigma, rad/s, to which the interval's own standard error is added.
    f_ref : (3,) m/s^2, body: the mean specific force standing still would give (None: not tested).
    f_sigma : its sigma, m/s^2.
    baseline : the still run the interval would join (None: it starts one), whose spread a vibrating interval's
        must match (:func:`steady`).

    Returns
    -------
    bool
    """
    if interval.n < _MIN_SAMPLES or (math.isfinite(speed[0]) and not speed[0] < speed[1]):
        return False
    sd_f = interval.std(interval.sum_f, interval.sum_ff)
    sd_w = interval.std(interval.sum_w, interval.sum_ww)
    if not ((sd_f < cfg.still.still_accel_std_mps2 and sd_w < cfg.still.still_gyro_std_dps * _DEG)
            or (math.isfinite(speed[0]) and steady(interval, baseline))):
        return False
    rn = math.sqrt(interval.n)
    if w_ref is not None and np.linalg.norm(interval.sum_w / interval.n - w_ref) > (
            GATE * math.hypot(sd_w / rn, w_sigma) + cfg.still.still_rate_tol_dps * _DEG):
        return False
    if f_ref is not None and np.linalg.norm(interval.sum_f / interval.n - f_ref) > (
            GATE * math.hypot(sd_f / rn, f_sigma) + cfg.still.still_accel_tol_mps2):
        return False
    return True


def steady(interval: ImuSums, baseline: ImuSums | None) -> bool:
    """Whether the interval's spreads of rate and of specific force are each within a factor ``STEADY_RATIO`` of the
    baseline's (a still run's: the same vibration).

    Parameters
    ----------
    interval : the interval's IMU sums.
    baseline : the still run's (None or empty: the interval starts one).

    Returns
    -------
    bool, True without a baseline.
    """
    if baseline is None or baseline.n == 0:
        return True
    for total, squares in (("sum_w", "sum_ww"), ("sum_f", "sum_ff")):
        sd = interval.std(getattr(interval, total), getattr(interval, squares))
        ref = baseline.std(getattr(baseline, total), getattr(baseline, squares))
        if not ref / STEADY_RATIO <= sd <= ref * STEADY_RATIO:
            return False
    return True


def gps_moving(speed: tuple[float, float]) -> bool:
    """Whether the GPS speed alone makes :func:`verdict` "moving", whatever the IMU shows: at twice its limit or
    more.

    Parameters
    ----------
    speed : as :func:`still`.

    Returns
    -------
    bool
    """
    return math.isfinite(speed[0]) and not 0.5 * speed[0] < speed[1]


def verdict(cfg: FusionConfig, interval: ImuSums, speed: tuple[float, float], refs: list[tuple],
            baseline: ImuSums | None = None) -> str:
    """The still detector's word on an interval.

    Parameters
    ----------
    cfg, interval, speed, baseline : as :func:`still`.
    refs : the references (w_ref, w_sigma, f_ref, f_sigma) the interval is tested against, each as :func:`still`.

    Returns
    -------
    "still" when the interval passes :func:`still` against every reference and the baseline; "unsure" when it
    fails only on a GPS speed below twice its limit (a noisy velocity: the interval is left out, the still run goes
    on); else "moving".
    """
    if all(still(cfg, interval, speed, *r, baseline) for r in refs):
        return "still"
    if math.isfinite(speed[0]) and all(still(cfg, interval, (0.5 * speed[0], speed[1]), *r, baseline)
                                       for r in refs):
        return "unsure"
    return "moving"


class StillRun:
    """The current run of still intervals (a stop), for the ZUPT aid: an interval is still when it passes
    :func:`still` against the absolute references and, within a run, against the run's own mean rate and
    specific force (a creep starting from a stop shows against the stop itself). The first still interval of
    a stop only starts the run (``trimmed``: it may hold the last of the braking)."""

    def __init__(self, cfg: FusionConfig) -> None:
        self.cfg = cfg
        self.run = ImuSums()
        self.count = 0

    def reset(self) -> None:
        self.run, self.count = ImuSums(), 0

    def update(self, interval: ImuSums, speed: tuple[float, float], w_ref: np.ndarray, w_sigma: float,
               f_ref: np.ndarray, f_sigma: float) -> bool:
        """Test the next interval against the references and the run.

        Parameters
        ----------
        interval, speed, w_ref, w_sigma, f_ref, f_sigma : as :func:`still`.

        Returns
        -------
        bool, True when the vehicle stood still over this interval and over the one before it.
        """
        c = self.cfg
        refs = [(w_ref, w_sigma, f_ref, f_sigma)]
        if self.count:
            refs.append((self.run.sum_w / self.run.n, c.init.init_gyro_bias_sigma_dps * _DEG, self.run.sum_f / self.run.n,
                         0.0))
        said = verdict(c, interval, speed, refs, self.run if self.count else None)
        if said == "moving":
            self.reset()
        if said != "still":
            return False
        self.run.merge(interval)
        self.count += 1
        return self.count > 1


def vel_sigma(ep: Epoch) -> float:
    """1-sigma of a horizontal GPS velocity component at an epoch.

    Parameters
    ----------
    ep : the epoch.

    Returns
    -------
    float, m/s: from its velocity covariance, else (a drive without velocity: differenced fixes 1 s apart) sqrt(2) x
    the fix's horizontal sigma, else 1.
    """
    for cov, k in ((ep.vel_cov, 1.0), (ep.pos_cov, math.sqrt(2.0))):
        var = 0.5 * (float(cov[0, 0]) + float(cov[1, 1]))
        if math.isfinite(var) and var > 0:
            return k * math.sqrt(var)
    return 1.0
