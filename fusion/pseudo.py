"""The virtual odometer of ``dkf-rbfn`` with ``[fusion] predictor_mode = "pseudo"``: the body-frame forward speed
learnt from the IMU while GNSS is good, its features, and its held-out score.

The measurement itself (z, H, R) is ``fusion.measurements.VirtualOdometer``; this module holds what it is built
from.

Features (:func:`imu_features`, body RFU of the IMU):

- from the last ``FEATURE_S`` of raw IMU samples: the means of the specific force (3, m/s^2) and of the angular
  rate (3, rad/s), and the turn speed -f_x w_z / (w_z^2 + ``TURN_RATE_FLOOR``^2) (m/s): in a turn the lateral
  specific force is the speed times the yaw rate;
- the INS pitch (rad) at the epoch;
- from the last ``SPECTRUM_S`` (several seconds, so that one second's random road vibration does not make the
  features scatter): band powers, log10 of the power of the de-meaned specific force and of the rate (summed over
  the axes) in the bands ``BANDS_HZ`` (10), and the frequency (Hz, :func:`peak_frequency`) of the specific force's
  strongest line in ``PEAK_HZ``, the wheel's first order (its imbalance) where the car vibrates as
  ``tools/sim/vibration.py`` makes it; the samples Hann-windowed for both. The line's frequency is proportional
  to the speed (a wheel turns speed / (2 pi r) times a second), which :class:`SpeedModel` uses.

Models (:class:`SpeedModel`): two candidates, chosen between by their held-out residuals: the wheel's line times
a learnt scale (the distance of one of its periods: the tyre's circumference), which extrapolates to speeds the
training window did not hold; and an RBF network (``fusion.predictors.SpeedNetwork``) on all the features, for a
car whose vibration has no line that follows the speed.

What the set assumes: the car's vibration carries its speed, as a car's does through its wheel orders and a road's
roughness (its power grows with the speed), and the engine's orders in one gear; the wheel's first order is the
strongest line of the specific force between ``PEAK_HZ`` most of the time (the median of ``LINE_MEDIAN`` epochs
drops the rest); the IMU samples fast enough to see those lines (a few to a few tens of Hz: the default band
edges assume a rate of at least 120 Hz); the mounting, the tyres, the road and the gear stay what they were over
the training window, which is the last ``window`` GNSS epochs (``fusion.predictors.PredictorConfig``), so a
changed road or a new gear is learnt again only after GNSS returns. The features lag the speed by about half of
``SPECTRUM_S`` plus half of ``LINE_MEDIAN`` epochs: while the speed changes the prediction trails it. The speed
before the outage is not an input: a model would learn to repeat it (the next epoch's speed is the last one's, to
a few cm/s), which says nothing at 30-60 s. A car whose vibration has no such line (a phone in a car on the
highway, ``tests/comma2k19.py``; an electric car on smooth asphalt) leaves the network, whose held-out R and skill
then say what it is worth.

Held-out score (:class:`HeldOut`): every ``SNAPSHOT_S`` while GNSS is good a copy of the model is frozen, with
a dead reckoning of the forward speed started from the GNSS's (:class:`ForwardReckoner`: the INS's along-track
channel alone, the IMU with the bias estimates of that moment). At each later good epoch the copies frozen
``HORIZON_S`` (30-60 s) before predict the current target with each candidate, before any training on it: what a
model frozen at an outage's start would have said 30-60 s into it. The candidate used is the one with the smaller
R, the variance of a normal distribution with the residuals' median square (:attr:`HeldOut.R`); its skill is
1 - its residuals' mean square over the dead reckoning's, i.e. against what the IMU alone gives the filter along
track over the same horizon. The measurement is used only when the skill is positive.
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np

from fieldlog.fusion import earth
from fieldlog.fusion.ins import NavState
from fieldlog.fusion.median import median
from fieldlog.fusion.predictors import PredictorConfig, SpeedNetwork

FEATURE_S = 1.0  # s of IMU samples the means and the turn speed are taken over
SPECTRUM_S = 4.0  # s of IMU samples the band powers and the wheel's line are taken over
BANDS_HZ = ((0.5, 3.0), (3.0, 6.0), (6.0, 12.0), (12.0, 25.0), (25.0, 60.0))
PEAK_HZ = (2.0, 15.0)  # a wheel's first order from 4 to 30 m/s with a 0.31 m tyre
LINE_MEDIAN = 7  # epochs: the line's frequency is the median of its last estimates (3 wrong in a row dropped)
LINE_MIN_SPEED = 1.0  # m/s: slower targets do not enter the wheel's scale (a standing car has no wheel line)
CHI2_1_MEDIAN = 0.4549364231195724  # the median of the square of a standard normal variable
TURN_RATE_FLOOR = 0.05  # rad/s: below about this yaw rate the turn speed fades to zero
N_FEATURES = 3 + 3 + 1 + 1 + 2 * len(BANDS_HZ) + 1
HORIZON_S = (30.0, 60.0)  # the outage horizon the residuals are scored over
SNAPSHOT_S = 10.0  # a frozen copy this often
SCORED_PER_EPOCH = int((HORIZON_S[1] - HORIZON_S[0]) / SNAPSHOT_S) + 1  # copies within the horizon at an epoch
MIN_SCORED = 30  # scored residuals before R and the skill are trusted
_POWER_FLOOR = 1e-12


class ImuWindow:
    """The last ``SPECTRUM_S`` of raw IMU samples (rate rad/s, specific force m/s^2, body RFU)."""

    def __init__(self) -> None:
        self.w = np.zeros((0, 3))
        self.f = np.zeros((0, 3))
        self.lines: deque[float] = deque(maxlen=LINE_MEDIAN)

    def add(self, w: np.ndarray, f: np.ndarray, i0: int, i1: int, imu_dt: float) -> None:
        """Append samples (i0, i1] and keep the last ``SPECTRUM_S``.

        Parameters
        ----------
        w, f : np.ndarray
            (n, 3) raw angular rate (rad/s) and specific force (m/s^2), body RFU.
        i0, i1 : int
            The samples taken are i0 + 1 to i1.
        imu_dt : float
            The sample period, s.
        """
        keep = max(int(round(SPECTRUM_S / imu_dt)), 1)
        self.w = np.concatenate([self.w, w[i0 + 1:i1 + 1]])[-keep:]
        self.f = np.concatenate([self.f, f[i0 + 1:i1 + 1]])[-keep:]

    def features(self, nav: NavState, imu_dt: float) -> np.ndarray | None:
        """The features of the window, the line's frequency the median of its last ``LINE_MEDIAN`` (one call
        per epoch).

        Parameters
        ----------
        nav : NavState
            The INS state at the epoch.
        imu_dt : float
            The sample period, s.

        Returns
        -------
        np.ndarray or None
            (``N_FEATURES``,) :func:`imu_features`; None while the window holds less than half of ``SPECTRUM_S``.
        """
        if len(self.w) * imu_dt < 0.5 * SPECTRUM_S:
            return None
        x = imu_features(self.w, self.f, imu_dt, nav)
        self.lines.append(float(x[-1]))
        x[-1] = median(self.lines)
        return x


def imu_features(w: np.ndarray, f: np.ndarray, dt: float, nav: NavState) -> np.ndarray:
    """The feature vector of the last IMU samples (module docstring).

    Parameters
    ----------
    w, f : np.ndarray
        (n, 3) raw angular rate (rad/s) and specific force (m/s^2), body RFU, oldest first, the last
        ``SPECTRUM_S`` (or less).
    dt : float
        Their sample period, s.
    nav : NavState
        The INS state at the epoch (its pitch).

    Returns
    -------
    np.ndarray
        (``N_FEATURES``,): mean force, mean rate, pitch, turn speed, band powers, the wheel line's frequency.
    """
    recent = max(int(round(FEATURE_S / dt)), 1)
    mw, mf = w[-recent:].mean(axis=0), f[-recent:].mean(axis=0)
    pitch = math.asin(max(-1.0, min(1.0, float(nav.C_bn[2, 1]))))
    turn = -mf[0] * mw[2] / (mw[2] ** 2 + TURN_RATE_FLOOR ** 2)
    n = len(w)
    freq = np.fft.rfftfreq(n, dt)
    taper = np.hanning(n)[:, None]
    bands = []
    spectra = []
    for x in (f, w):
        p = (np.abs(np.fft.rfft((x - x.mean(axis=0)) * taper, axis=0)) ** 2).sum(axis=1) / n
        spectra.append(p)
        bands += [math.log10(float(p[(freq >= lo) & (freq < hi)].sum()) + _POWER_FLOOR) for lo, hi in BANDS_HZ]
    return np.concatenate([mf, mw, [pitch, turn], bands, [peak_frequency(freq, spectra[0])]])


def peak_frequency(freq: np.ndarray, power: np.ndarray) -> float:
    """The frequency of the strongest line of a power spectrum within ``PEAK_HZ``, between bins by a parabola
    through the log power of the peak bin and its neighbours (a Hann-windowed line's log power is close to a
    parabola near its top).

    Parameters
    ----------
    freq : np.ndarray
        (m,) the spectrum's frequencies, Hz, evenly spaced from 0 (``np.fft.rfftfreq``).
    power : np.ndarray
        (m,) its power, any unit.

    Returns
    -------
    float
        The line's frequency, Hz; 0 when the band holds fewer than three bins.
    """
    idx = np.flatnonzero((freq >= PEAK_HZ[0]) & (freq <= PEAK_HZ[1]))
    if len(idx) < 3:
        return 0.0
    k = int(idx[np.argmax(power[idx])])
    k = min(max(k, 1), len(power) - 2)
    a, b, c = np.log(power[k - 1:k + 2] + _POWER_FLOOR)
    den = a - 2.0 * b + c
    shift = 0.5 * (a - c) / den if den < 0 else 0.0
    return float(freq[k] + max(-0.5, min(0.5, shift)) * (freq[1] - freq[0]))


def forward_speed(nav: NavState, v_n: np.ndarray) -> float:
    """The component of a velocity along the IMU's forward (y) axis.

    Parameters
    ----------
    nav : NavState
        The INS state: its attitude C_bn, and its velocity for any NaN component of v_n.
    v_n : np.ndarray
        (3,) the velocity, ENU, m/s (a NaN vertical: the INS's).

    Returns
    -------
    float
        The forward speed, m/s.
    """
    v = np.where(np.isfinite(v_n), v_n, nav.v_n)
    return float(nav.C_bn[:, 1] @ v)


class ForwardReckoner:
    """The forward speed carried by the IMU alone from a known start: the INS's along-track channel.

    The attitude C_bn runs on the mean rate of each interval less the gyro bias estimate of the start and the
    Earth rate; the forward speed on dv/dt = f_y - ba_y + (C_nb g_n)_y (a car does not move sideways, so the
    rotation terms of the body-frame velocity vanish along y)."""

    def __init__(self, nav: NavState, v_fwd: float, bg: np.ndarray, ba: np.ndarray) -> None:
        self.C_bn = nav.C_bn.copy()
        self.v = v_fwd
        self.bg, self.ba = bg.copy(), ba.copy()
        self.w_ie = earth.omega_ie_n(nav.lat)
        self.g_n = earth.gravity_n(nav.lat, nav.h)

    def step(self, mean_w: np.ndarray, mean_f: np.ndarray, seconds: float) -> None:
        """Carry the attitude and forward speed over an interval.

        Parameters
        ----------
        mean_w, mean_f : np.ndarray
            (3,) the interval's mean raw rate (rad/s) and specific force (m/s^2), body RFU.
        seconds : float
            Its length, s.
        """
        C_nb = self.C_bn.T
        g_b = C_nb @ self.g_n
        self.v += (mean_f[1] - self.ba[1] + g_b[1]) * seconds
        w_nb = mean_w - self.bg - C_nb @ self.w_ie
        self.C_bn = self.C_bn @ earth.rotvec_to_dcm(w_nb * seconds)


class HeldOut:
    """The held-out residuals over the outage horizon (module docstring) of each of :class:`SpeedModel`'s
    candidates: which is used, its R and its skill, over the residuals of the last ``window`` good epochs (each
    scores the copies within the horizon, about ``SCORED_PER_EPOCH``)."""

    def __init__(self, window: int) -> None:
        self.snapshots: deque[tuple[float, SpeedModel, ForwardReckoner]] = deque()
        self.e_net: deque[np.ndarray] = deque(maxlen=window * SCORED_PER_EPOCH)  # squared, per candidate
        self.e_dr: deque[float] = deque(maxlen=window * SCORED_PER_EPOCH)
        self._last = -math.inf

    def score(self, t: float, x: np.ndarray, y: float, mean_w: np.ndarray, mean_f: np.ndarray,
              seconds: float) -> None:
        """A good epoch: the reckoners step over the interval, the copies within the horizon are scored on (x, y),
        the too-old dropped.

        Parameters
        ----------
        t : float
            The epoch, s.
        x : np.ndarray
            (``N_FEATURES``,) its features.
        y : float
            Its target, the forward speed, m/s.
        mean_w, mean_f : np.ndarray
            (3,) the interval's mean raw rate (rad/s) and specific force (m/s^2), body RFU.
        seconds : float
            The interval's length, s.
        """
        for t0, model, dr in self.snapshots:
            dr.step(mean_w, mean_f, seconds)
            if HORIZON_S[0] <= t - t0 <= HORIZON_S[1]:
                p = model.predict_each(x)
                if np.isfinite(p).any():
                    self.e_net.append((y - p) ** 2)
                    self.e_dr.append((y - dr.v) ** 2)
        while self.snapshots and t - self.snapshots[0][0] > HORIZON_S[1]:
            self.snapshots.popleft()

    def freeze(self, t: float, model: SpeedModel, nav: NavState, y: float, bg: np.ndarray, ba: np.ndarray
               ) -> None:
        """A new copy when ``SNAPSHOT_S`` has passed since the last; the live model is told which candidate the
        residuals so far choose.

        Parameters
        ----------
        t : float
            The epoch, s (the model trained up to it).
        model : SpeedModel
            The live model.
        nav : NavState
            The INS state at t (the reckoner's start attitude).
        y : float
            The GNSS's forward speed at t, m/s (the reckoner's start).
        bg, ba : np.ndarray
            (3,) the gyro (rad/s) and accelerometer (m/s^2) bias estimates at t.
        """
        model.use = self.best
        if model.ready and t - self._last >= SNAPSHOT_S:
            self.snapshots.append((t, model.frozen(), ForwardReckoner(nav, y, bg, ba)))
            self._last = t

    def forget_reckoners(self) -> None:
        """GNSS lost: the copies' dead reckoning would run through the outage unscored; they are dropped."""
        self.snapshots.clear()
        self._last = -math.inf

    @property
    def scored(self) -> int:
        """Residuals of the candidate in use scored so far (within the last ``window`` epochs)."""
        return int(np.isfinite(np.array(self.e_net)[:, self.best]).sum()) if self.e_net else 0

    def _robust_variance(self) -> np.ndarray:
        e = np.array(self.e_net)
        with np.errstate(all="ignore"):
            return np.array([np.nanmedian(c) if np.isfinite(c).any() else math.nan for c in e.T]) / CHI2_1_MEDIAN

    @property
    def best(self) -> int:
        """The candidate (index into :meth:`SpeedModel.predict_each`) with the smallest R; 0 before any."""
        if not self.e_net:
            return 0
        r = self._robust_variance()
        return int(np.nanargmin(r)) if np.isfinite(r).any() else 0

    @property
    def R(self) -> float:
        """The held-out residuals' variance, (m/s)^2, of the candidate in use (NaN before any): that of a normal
        distribution with their median square, so that the few wrong picks of the wheel's line the median of
        ``LINE_MEDIAN`` lets through do not decide how much every epoch is trusted."""
        return float(self._robust_variance()[self.best]) if self.e_net else math.nan

    @property
    def skill(self) -> float:
        """1 - the residuals' mean square over the dead reckoning's, the candidate in use (NaN before any)."""
        if not self.e_net:
            return math.nan
        e = np.array(self.e_net)[:, self.best]
        ok = np.isfinite(e)
        return 1.0 - float(np.sum(e[ok])) / max(float(np.sum(np.array(self.e_dr)[ok])), 1e-12)


class SpeedModel:
    """The forward speed from the features (module docstring), two candidates that :class:`HeldOut` chooses
    between by their held-out residuals.

    - 0, the wheel's line: v = k f_line, k (m: the distance of one period of the line, 2 pi r for a wheel's first
      order) the median of the targets over the line's frequency over the last ``window`` trained epochs faster
      than ``LINE_MIN_SPEED``. It extrapolates to speeds the training window did not hold, as a wheel does.
    - 1, the network: a :class:`fusion.predictors.SpeedNetwork` on all the features, for a car whose vibration
      has no line that follows the speed.

    ``use``: the candidate :meth:`predict` gives (set by :meth:`HeldOut.freeze`), named in ``CANDIDATES``."""

    CANDIDATES = ("wheel line", "network")

    def __init__(self, cfg: PredictorConfig) -> None:
        self.ratios: deque[float] = deque(maxlen=cfg.window)
        self.k = math.nan
        self.net = SpeedNetwork(N_FEATURES, cfg)
        self.use = 0

    @property
    def ready(self) -> bool:
        """Whether both candidates predict (a scale and a fitted network), so that each copy scores both."""
        return math.isfinite(self.k) and self.net.ready

    def train(self, x: np.ndarray, y: float) -> None:
        """One epoch.

        Parameters
        ----------
        x : np.ndarray
            (``N_FEATURES``,) the features (:func:`imu_features`).
        y : float
            The target, the forward speed, m/s.
        """
        f_line = float(x[-1])
        if y > LINE_MIN_SPEED and f_line > 0.0 and math.isfinite(y):
            self.ratios.append(y / f_line)
            self.k = median(self.ratios)
        self.net.train(x, y)

    def predict_each(self, x: np.ndarray) -> np.ndarray:
        """Each candidate's forward speed.

        Parameters
        ----------
        x : np.ndarray
            (``N_FEATURES``,) the features.

        Returns
        -------
        np.ndarray
            (2,) the speeds in the order of ``CANDIDATES``, m/s; NaN where not fitted.
        """
        return np.array([self.k * float(x[-1]), self.net.predict(x)])

    def predict(self, x: np.ndarray) -> float:
        """The forward speed of the candidate in use.

        Parameters
        ----------
        x : np.ndarray
            (``N_FEATURES``,) the features of the epoch (:func:`imu_features`).

        Returns
        -------
        float
            m/s; NaN before it is fitted.
        """
        return float(self.predict_each(x)[self.use])

    def frozen(self) -> SpeedModel:
        """A copy that predicts as this one does now, not trained further.

        Returns
        -------
        SpeedModel
            The line's k, the candidate in use and the network (:meth:`SpeedNetwork.frozen`) as they are now.
        """
        out = SpeedModel.__new__(SpeedModel)
        out.ratios, out.k, out.use = deque(), self.k, self.use
        out.net = self.net.frozen()
        return out


def new_network(cfg: PredictorConfig) -> SpeedModel:
    """The virtual odometer's model over the features of :func:`imu_features`.

    Parameters
    ----------
    cfg : PredictorConfig
        The network's settings (window, centres, forgetting).

    Returns
    -------
    SpeedModel
        Untrained.
    """
    return SpeedModel(cfg)
