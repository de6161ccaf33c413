"""The virtual odometer of ``dkf-rbfn`` with ``[fusion] predictor_mode = "pseudo"``: the body-frame forward speed
learnt from the IMU while GNSS is good, its features, and its held-out score.

The measurement itself (z, H, R) is ``fusion.measurements.VirtualOdometer``; this module holds what it is built
from.

Features (:func:`imu_features`, from the last ``FEATURE_S`` of raw IMU samples, body RFU of the IMU):

- the means of the specific force (3, m/s^2) and of the angular rate (3, rad/s);
- the INS pitch (rad) at the epoch;
- the turn speed -f_x w_z / (w_z^2 + ``TURN_RATE_FLOOR``^2) (m/s): in a turn the lateral specific force is the
  speed times the yaw rate;
- band powers: log10 of the power of the de-meaned specific force and of the rate (summed over the axes) in the
  bands ``BANDS_HZ`` (10);
- the frequency of the specific force's strongest line in ``PEAK_HZ`` (Hz, :func:`peak_frequency`; the samples
  Hann-windowed for this and the band powers).

What the set assumes: the car's vibration carries its speed, as a car's does through its wheel orders (a wheel
turns speed / (2 pi r) times a second) and a road's roughness (its power grows with the speed), and the
engine's orders in one gear; the IMU samples fast enough to see those lines (a few to a few tens of Hz: the
default band edges assume a rate of at least 120 Hz); the mounting, the tyres, the road and the gear stay what
they were over the training window, which is the last ``window`` GNSS epochs (``fusion.predictors.
PredictorConfig``), so a changed road or a new gear is learnt again only after GNSS returns. The speed before the
outage is not an input: the model would learn to repeat it (the next epoch's speed is the last one's, to a few
cm/s), which says nothing at 30-60 s. A car that does not vibrate (an electric car on smooth asphalt) gives the
network only the mean force and rate and the turn speed; its held-out R then says so (a large R, a measurement the
filter weighs little).

Held-out score (:class:`HeldOut`): every ``SNAPSHOT_S`` while GNSS is good a copy of the network is frozen, with
a dead reckoning of the forward speed started from the GNSS's (:class:`ForwardReckoner`: the INS's along-track
channel alone, the IMU with the bias estimates of that moment). At each later good epoch the copies frozen
``HORIZON_S`` (30-60 s) before predict the current target, before any training on it: what a network frozen at an
outage's start would have said 30-60 s into it. R is the mean square of those residuals; the skill is
1 - that mean square over the dead reckoning's, i.e. against what the IMU alone gives the filter along track over
the same horizon. The measurement is used only when the skill is positive.
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np

from fieldlog.fusion import earth
from fieldlog.fusion.ins import NavState
from fieldlog.fusion.predictors import PredictorConfig, SpeedNetwork

FEATURE_S = 1.0  # s of IMU samples the features are taken over
BANDS_HZ = ((0.5, 3.0), (3.0, 6.0), (6.0, 12.0), (12.0, 25.0), (25.0, 60.0))
PEAK_HZ = (2.0, 15.0)  # a wheel's first order from 4 to 30 m/s with a 0.31 m tyre
TURN_RATE_FLOOR = 0.05  # rad/s: below about this yaw rate the turn speed fades to zero
N_FEATURES = 3 + 3 + 1 + 1 + 2 * len(BANDS_HZ) + 1
HORIZON_S = (30.0, 60.0)  # the outage horizon the residuals are scored over
SNAPSHOT_S = 10.0  # a frozen copy this often
SCORED_PER_EPOCH = int((HORIZON_S[1] - HORIZON_S[0]) / SNAPSHOT_S) + 1  # copies within the horizon at an epoch
MIN_SCORED = 30  # scored residuals before R and the skill are trusted
_POWER_FLOOR = 1e-12


class ImuWindow:
    """The last ``FEATURE_S`` of raw IMU samples (rate rad/s, specific force m/s^2, body RFU)."""

    def __init__(self) -> None:
        self.w = np.zeros((0, 3))
        self.f = np.zeros((0, 3))

    def add(self, w: np.ndarray, f: np.ndarray, i0: int, i1: int, imu_dt: float) -> None:
        """Samples (i0, i1] of w, f (n, 3); imu_dt the sample period, s."""
        keep = max(int(round(FEATURE_S / imu_dt)), 1)
        self.w = np.concatenate([self.w, w[i0 + 1:i1 + 1]])[-keep:]
        self.f = np.concatenate([self.f, f[i0 + 1:i1 + 1]])[-keep:]

    def features(self, nav: NavState, imu_dt: float) -> np.ndarray | None:
        """:func:`imu_features` of the window; None while it holds less than half of ``FEATURE_S``."""
        if len(self.w) * imu_dt < 0.5 * FEATURE_S:
            return None
        return imu_features(self.w, self.f, imu_dt, nav)


def imu_features(w: np.ndarray, f: np.ndarray, dt: float, nav: NavState) -> np.ndarray:
    """The feature vector (``N_FEATURES``,) of samples w, f (n, 3) at period dt (s) with the INS state nav
    (module docstring)."""
    mw, mf = w.mean(axis=0), f.mean(axis=0)
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
    """The frequency (Hz) of the strongest line of a power spectrum within ``PEAK_HZ``, between bins by a parabola
    through the log power of the peak bin and its neighbours (a Hann-windowed line's log power is close to a
    parabola near its top); 0 when the band holds fewer than three bins."""
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
    """The component of an ENU velocity v_n (3,) along the IMU's forward (y) axis, m/s (NaN vertical: the INS's)."""
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
        """An interval of ``seconds`` with mean raw rate (rad/s) and specific force (m/s^2), body."""
        C_nb = self.C_bn.T
        g_b = C_nb @ self.g_n
        self.v += (mean_f[1] - self.ba[1] + g_b[1]) * seconds
        w_nb = mean_w - self.bg - C_nb @ self.w_ie
        self.C_bn = self.C_bn @ earth.rotvec_to_dcm(w_nb * seconds)


class HeldOut:
    """The held-out residuals over the outage horizon (module docstring): R and the skill, over the residuals of
    the last ``window`` good epochs (each scores the copies within the horizon, about ``SCORED_PER_EPOCH``)."""

    def __init__(self, window: int) -> None:
        self.snapshots: deque[tuple[float, SpeedNetwork, ForwardReckoner]] = deque()
        self.e_net: deque[float] = deque(maxlen=window * SCORED_PER_EPOCH)
        self.e_dr: deque[float] = deque(maxlen=window * SCORED_PER_EPOCH)
        self._last = -math.inf

    def score(self, t: float, x: np.ndarray, y: float, mean_w: np.ndarray, mean_f: np.ndarray,
              seconds: float) -> None:
        """A good epoch at t (s) with input x and target y: the reckoners step over the interval (its mean raw rate
        and force, its length in s), the copies within the horizon are scored on (x, y), the too-old dropped."""
        for t0, net, dr in self.snapshots:
            dr.step(mean_w, mean_f, seconds)
            if HORIZON_S[0] <= t - t0 <= HORIZON_S[1]:
                p = net.predict(x)
                if math.isfinite(p):
                    self.e_net.append((y - p) ** 2)
                    self.e_dr.append((y - dr.v) ** 2)
        while self.snapshots and t - self.snapshots[0][0] > HORIZON_S[1]:
            self.snapshots.popleft()

    def freeze(self, t: float, net: SpeedNetwork, nav: NavState, y: float, bg: np.ndarray, ba: np.ndarray) -> None:
        """A new copy at t when ``SNAPSHOT_S`` has passed since the last (the network trained up to t)."""
        if net.ready and t - self._last >= SNAPSHOT_S:
            self.snapshots.append((t, net.frozen(), ForwardReckoner(nav, y, bg, ba)))
            self._last = t

    def forget_reckoners(self) -> None:
        """GNSS lost: the copies' dead reckoning would run through the outage unscored; they are dropped."""
        self.snapshots.clear()
        self._last = -math.inf

    @property
    def scored(self) -> int:
        return len(self.e_net)

    @property
    def R(self) -> float:
        """Mean square of the held-out residuals, (m/s)^2 (NaN before any)."""
        return float(np.mean(self.e_net)) if self.e_net else math.nan

    @property
    def skill(self) -> float:
        """1 - the residuals' mean square over the dead reckoning's (NaN before any)."""
        if not self.e_net:
            return math.nan
        return 1.0 - float(np.sum(self.e_net)) / max(float(np.sum(self.e_dr)), 1e-12)


def new_network(cfg: PredictorConfig) -> SpeedNetwork:
    """The virtual odometer's network over the features of :func:`imu_features`."""
    return SpeedNetwork(N_FEATURES, cfg)
