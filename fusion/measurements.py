"""The measurements of the fusion loop, one object each: at a GPS epoch time each gives (z, H, R) or nothing.

A measurement holds its own noise, lever arm and state (a still detector's run) and reads the epoch from a
:class:`Moment`, what the loop knows at that instant. Its ``compute_matrices(moment)`` returns ``(z, H, R)``
(``fusion.kf.Measurement``: z = INS - measured, H over the 15 error states of ``fusion.errmodel``) or None. Two
attributes tell the filters what it is:

- ``kind``: "velocity" or "position", the domain it observes; the distributed filter (``fusion.dkf``) gives the
  velocity kind to KF_I and the position kind to KF_II;
- ``stage``: "aid" (a vehicle-motion aid: needs no GPS, acts at every epoch time, outages included, and each is
  its own update before the fix) or "fix" (the GPS fix's measurements: at usable epochs, stacked into one
  update); ``receiver`` True when R is the receiver's own figure (the adaptive filters of ``fusion.sckf`` rescale
  only those).

:func:`aids_and_gps` builds the list an aided method runs with (``fusion.methods.Method.measurements``). A new aid (a wheel-speed odometer, say) is one more
class here with the same method and attributes, and one more entry there.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from fieldlog.fusion import earth, kf, odometer, pseudo
from fieldlog.fusion.still import GATE, GpsSpeed, ImuSums, StillRun, gps_moving
from fieldlog.fusion.config import FusionConfig
from fieldlog.fusion.errmodel import ATT, BA, BG, N_STATES, POS, VEL
from fieldlog.fusion.median import median
from fieldlog.fusion.predictors import PredictorConfig
from fieldlog.fusion.ins import NavState
from fieldlog.fusion.types import Epoch, OdomBlock

_I3 = np.eye(3)
_I3.flags.writeable = False

_DEG = math.pi / 180.0


@dataclass
class Moment:
    """What the measurements see at one GPS epoch time. epoch: the GPS epoch; usable: whether its fix is used
    (``fusion.outages.OutageTracker``); t_fix: the fix time, s from the drive's first IMU sample; v_aid (3,) ENU
    m/s: the receiver's velocity the aids test (NaN: none); nav: the INS at the epoch's sample; omega_b (3,) rad/s:
    the rate there, corrected by the bias estimate before this epoch's updates, body RFU; interval: the raw IMU
    sums since the previous epoch; imu_dt: the IMU sample period, s; bg, ba (3,): the bias estimates, rad/s and
    m/s^2; P (15, 15): the filter's covariance. The loop refreshes nav, P, bg and ba after each update it feeds
    back (and nav and P after a re-alignment)."""

    epoch: Epoch
    usable: bool
    t_fix: float
    v_aid: np.ndarray
    nav: NavState
    omega_b: np.ndarray
    interval: ImuSums
    imu_dt: float
    bg: np.ndarray
    ba: np.ndarray
    P: np.ndarray


class MeasurementModel(Protocol):
    """What the loop asks of a measurement (module docstring)."""

    kind: str
    stage: str
    receiver: bool

    def compute_matrices(self, m: Moment) -> kf.Measurement | None:
        """(z, H, R) at the moment, or None.

        Parameters
        ----------
        m : what the loop knows at the epoch.

        Returns
        -------
        (z (k,), H (k, 15), R (k, k)), or None.
        """


@dataclass
class GpsPosition:
    """The fix: z = INS antenna position - GPS position, ENU m (``position_measurement``); lever_b (3,) IMU ->
    antenna, body RFU, m. R is the fix's covariance; a fix without height gives the horizontal rows only."""

    lever_b: np.ndarray
    kind = "position"
    stage = "fix"
    receiver = True

    def compute_matrices(self, m: Moment) -> kf.Measurement | None:
        """The fix's position measurement.

        Parameters
        ----------
        m : the epoch (its fix and covariance), whether it is usable, the fix time and the INS there.

        Returns
        -------
        (z (3,) ENU m, or (2,) for a fix without height; H; R m^2), None at an unusable epoch.
        """
        e = m.epoch
        if not m.usable:
            return None
        return position_measurement(m.nav, m.t_fix, e.lat, e.lon, e.h, e.pos_cov, self.lever_b)


@dataclass
class GpsVelocity:
    """The receiver's velocity: z = INS antenna velocity - GPS velocity, ENU m/s (``velocity_measurement``);
    components with a variance above max_var ((m/s)^2, NMEA's unobserved vertical) are left out."""

    lever_b: np.ndarray
    max_var: float
    kind = "velocity"
    stage = "fix"
    receiver = True

    def compute_matrices(self, m: Moment) -> kf.Measurement | None:
        """The receiver's velocity measurement.

        Parameters
        ----------
        m : the epoch (its velocity and covariance), whether it is usable, the INS and the bias-corrected rate.

        Returns
        -------
        (z (k,) ENU m/s, H (k, 15), R (k, k) (m/s)^2), None at an unusable epoch or with no component left.
        """
        if not m.usable:
            return None
        return velocity_measurement(m.nav, m.epoch.v_n, m.epoch.vel_cov, m.omega_b, self.lever_b, self.max_var)


@dataclass(frozen=True)
class CarFrame:
    """How the IMU sits in the car, for the aids that constrain the car's velocity (the NHC, the odometer).

    C_bm (3, 3): IMU axes -> the car's body axes (RFU), ``fusion.earth.euler_to_dcm(yaw, pitch, roll)`` of the
    mounting (``[fusion] mounting_rpy_deg``); None: the IMU's axes are the car's. sigma_rad (3,): the mounting's
    1-sigma, roll, pitch, yaw, rad: a yaw error turns the forward speed v into a lateral velocity v sigma_yaw, a
    pitch error into a vertical one v sigma_pitch, added to those rows' variances (roll mixes two zeros)."""

    C_bm: np.ndarray | None = None
    sigma_rad: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @classmethod
    def of(cls, rpy_deg: tuple[float, float, float], sigma_deg: tuple[float, float, float]) -> CarFrame:
        """The frame of a mounting.

        Parameters
        ----------
        rpy_deg : (3,) roll, pitch, yaw of the IMU's axes from the car's, deg (all 0: the car's axes).
        sigma_deg : (3,) their 1-sigma, deg.

        Returns
        -------
        CarFrame
        """
        roll, pitch, yaw = (float(x) * _DEG for x in rpy_deg)
        C = earth.euler_to_dcm(yaw, pitch, roll) if any(rpy_deg) else None
        return cls(C, np.asarray(sigma_deg, float) * _DEG)

    def axes(self, C_nb: np.ndarray) -> np.ndarray:
        """The car's axes in the navigation frame's terms.

        Parameters
        ----------
        C_nb : (3, 3) navigation (ENU) -> IMU axes.

        Returns
        -------
        (3, 3) navigation (ENU) -> car axes (RFU), C_bm C_nb.
        """
        return C_nb if self.C_bm is None else self.C_bm @ C_nb

    def extra_var(self, v_fwd: float) -> np.ndarray:
        """The mounting's share of the car-axis velocity variances.

        Parameters
        ----------
        v_fwd : the car's forward speed, m/s.

        Returns
        -------
        (3,) (m/s)^2 on the lateral, forward and vertical car axes: (v sigma_yaw)^2, 0, (v sigma_pitch)^2.
        """
        return np.array([(v_fwd * self.sigma_rad[2]) ** 2, 0.0, (v_fwd * self.sigma_rad[1]) ** 2])

    def rotate(self, z: np.ndarray, H: np.ndarray, w_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A body-velocity measurement from the IMU's axes into the car's.

        Parameters
        ----------
        z : (3,) m/s, the INS's velocity in IMU axes less w_b (``odometer.odometer_measurement``).
        H : (3, 15) its rows over the error states.
        w_b : (3,) m/s, the measured velocity in car axes.

        Returns
        -------
        z (3,) = C_bm (z + w_b) - w_b and H (3, 15) = C_bm H: the same measurement in car axes.
        """
        if self.C_bm is None:
            return z, H
        return self.C_bm @ (z + w_b) - w_b, self.C_bm @ H


@dataclass
class NonHolonomic:
    """A car's body lateral and vertical velocity are zero (``nhc_measurement``), sigma_mps each, in the car's axes
    (``car``: the IMU's mounting); not when the car is slow: GPS speed below slow_gps_mps, or (without a GPS
    velocity) INS speed below slow_ins_mps."""

    sigma_mps: float
    slow_gps_mps: float
    slow_ins_mps: float
    car: CarFrame = field(default_factory=CarFrame)
    kind = "velocity"
    stage = "aid"
    receiver = False

    def compute_matrices(self, m: Moment) -> kf.Measurement | None:
        """The NHC's two rows in the car's axes, unless the car is slow.

        Parameters
        ----------
        m : the INS and the receiver's velocity the slowness is tested on.

        Returns
        -------
        (z (2,) m/s, the car's lateral and vertical velocity; H (2, 15); R (2, 2)), None when slow.
        """
        v = m.v_aid
        slow = (float(np.hypot(v[0], v[1])) < self.slow_gps_mps if np.isfinite(v[:2]).all()
                else float(np.linalg.norm(m.nav.v_n)) < self.slow_ins_mps)
        return None if slow else nhc_measurement(m.nav, self.sigma_mps, self.car)


@dataclass
class Stationary:
    """Zero-velocity and zero-angular-rate update (ZUPT + ZARU, ``stationary_measurement``) when the vehicle
    stood still over the interval since the last epoch and the one before it (``fusion.still.StillRun``).

    A standing car is not still to a good gyro (the engine idles, the body rocks on its springs, people move),
    so the noise comes from the interval itself and from what the still detector admits, never tighter:

    - ZARU, per body axis: sigma_w^2 = gyro_noise^2 / T (white noise over the interval's T s) + the squared
      standard error of the interval's mean rate (its samples' spread over sqrt(n)) + (still_rate_tol / gate)^2,
      the mean rate the detector lets through as "still" (``[fusion] still_rate_tol_dps`` at its gate of
      ``still.GATE`` sigmas);
    - ZUPT, per ENU axis: sigma_v^2 = sigma_mps^2 + (a T)^2, the velocity the admitted mean specific force error
      a would build over the interval: a = the larger of still_accel_tol / gate (the detector's floor) and the
      standard error of the interval's mean specific force (its samples' largest per-axis spread over sqrt(n):
      a vibrating car's mean is admitted within gate of those).

    Before the ZARU is used its residual (the interval's mean bias-corrected rate less the Earth rate) is tested
    against the bias estimate: chi^2 = r^T (P_bg + R_w)^-1 r over 3 degrees of freedom; above ``ZARU_CHI2``
    (99.9 %) the rate is not the bias (the car moved on its springs over the interval) and the update is the ZUPT
    alone. ``times``: the epochs (UTC ns) it gave a measurement at; ``zaru_skipped``: the epochs among them whose
    ZARU failed the test."""

    cfg: FusionConfig
    sigma_mps: float
    gyro_noise: float
    kind = "velocity"
    stage = "aid"
    receiver = False
    times: list[int] = field(default_factory=list)
    zaru_skipped: list[int] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.speed = GpsSpeed(self.cfg)
        self.run = StillRun(self.cfg)

    def compute_matrices(self, m: Moment) -> kf.Measurement | None:
        """The ZUPT (+ ZARU) when the car stood still over this interval and the one before (class docstring).

        Parameters
        ----------
        m : the epoch's GPS velocity, the interval's IMU sums, the INS, the bias estimates and P.

        Returns
        -------
        (z (6,) m/s and rad/s, or (3,) when the ZARU fails its test; H; R), None unless still.
        """
        v_gps = m.epoch.v_n if m.usable else np.full(3, np.nan)
        speed = self.speed.add(m.t_fix, v_gps, m.epoch)
        if gps_moving(speed) or not (math.isfinite(speed[0])
                                     or float(np.linalg.norm(m.nav.v_n)) < self.cfg.still.still_speed_mps):
            self.run.reset()
            return None
        if not self.run.update(m.interval, speed, *_still_references(m.nav, m.bg, m.ba, m.P)):
            return None
        self.times.append(m.epoch.t_ns)
        n = m.interval.n
        mean_w = m.interval.sum_w / n - m.bg
        sigma_v, sigma_w = self.noise(m.interval, n * m.imu_dt)
        r = mean_w - m.nav.C_bn.T @ earth.omega_ie_n(m.nav.lat)
        S = m.P[BG, BG] + np.diag(sigma_w ** 2)
        if float(r @ np.linalg.solve(S, r)) > ZARU_CHI2:
            self.zaru_skipped.append(m.epoch.t_ns)
            sigma_w = None
        return stationary_measurement(m.nav, mean_w, sigma_v, sigma_w)

    def noise(self, interval: ImuSums, seconds: float) -> tuple[np.ndarray, np.ndarray]:
        """The ZUPT's and the ZARU's sigmas from a still interval (class docstring).

        Parameters
        ----------
        interval : the interval's IMU sums (rad/s, m/s^2, body RFU).
        seconds : its length, s.

        Returns
        -------
        (sigma_v (3,) m/s per ENU axis, sigma_w (3,) rad/s per body axis).
        """
        st = self.cfg.still
        n = max(interval.n, 1)
        mean = interval.sum_w / n
        spread2 = np.maximum(interval.sum_ww / n - mean * mean, 0.0)
        T = max(seconds, 1e-3)
        var_w = self.gyro_noise ** 2 / T + spread2 / n + (st.still_rate_tol_dps * _DEG / GATE) ** 2
        mean_f = interval.sum_f / n
        se_f = math.sqrt(float(np.max(np.maximum(interval.sum_ff / n - mean_f * mean_f, 0.0))) / n)
        var_v = self.sigma_mps ** 2 + max(st.still_accel_tol_mps2 * T / GATE, se_f * T) ** 2
        return np.full(3, math.sqrt(var_v)), np.sqrt(var_w)


ZARU_CHI2 = 16.27  # chi^2 with 3 degrees of freedom, 99.9 %


@dataclass
class Odometer:
    """The wheel speeds with the NHC's zeros: the rear axle centre's whole body velocity (``fusion.odometer``).

    The wheel speed at the epoch: a straight line fitted to the samples of the last ``window_s`` (at least
    ``min_samples``, the newest at most ``max_age_s`` before the epoch) and taken at the epoch time, so speed changes
    do not lag it; its variance is the topic's plus ``sigma_mps`` squared (slip, tyre deformation, stamp error).
    The scale factor is fitted while GPS is good against the GPS velocity's forward component
    (``odometer.ScaleEstimator``; not the INS's, which this aid itself corrects). ``feed`` takes the rows as the
    engine reads them; ``times``: the epochs it gave a measurement at; ``slip_skipped``: the epochs whose wheel
    speed failed the slip test (then the NHC's zeros only; without ``nhc`` no measurement). Without rows near an
    epoch it gives none (the NHC then, ``FirstOf``). ``nhc``: with the NHC's lateral and vertical zeros (else the
    forward row alone). ``car``: the IMU's mounting (:class:`CarFrame`): the rows are the car's axes, the
    mounting's sigma widens the lateral and vertical ones, and the scale fit takes the GPS velocity along the car's
    forward axis. With the four wheel speeds, ``wheels`` tests each (``odometer.WheelSlip``: ``track_m``,
    ``wheelbase_m``) and the forward speed is the mean of those kept."""

    lever_b: np.ndarray
    sigma_mps: float
    nhc_sigma_mps: float
    nhc: bool = True
    car: CarFrame = field(default_factory=CarFrame)
    track_m: float = 1.6
    wheelbase_m: float = 2.7
    window_s: float = 0.3
    min_samples: int = 3
    max_age_s: float = 0.1
    kind = "velocity"
    stage = "aid"
    receiver = False
    times: list[int] = field(default_factory=list)
    slip_skipped: list[int] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.scale = odometer.ScaleEstimator(min_samples=30, prior_sigma=0.005)
        self._t = np.zeros(0, np.int64)
        self._v = np.zeros(0)
        self._var = np.zeros(0)
        self._w = np.zeros((0, len(odometer.WHEELS)))
        self.wheels = odometer.WheelSlip(odometer.wheel_positions(self.lever_b, self.track_m, self.wheelbase_m,
                                                                  self.car.C_bm), self.car.C_bm)

    def feed(self, block: OdomBlock) -> None:
        """More wheel-speed rows; those before the last epoch's window are dropped there, so a block's rows are
        held until its epochs have passed.

        Parameters
        ----------
        block : the rows (UTC ns, forward speed m/s, its variance (m/s)^2).
        """
        ok = np.isfinite(block.v)
        self._t = np.concatenate([self._t, np.asarray(block.t_ns, np.int64)[ok]])
        self._v = np.concatenate([self._v, np.asarray(block.v, float)[ok]])
        self._var = np.concatenate([self._var, np.asarray(block.var, float)[ok]])
        w = np.full((len(ok), len(odometer.WHEELS)), np.nan) if block.wheels is None else block.wheels
        self._w = np.concatenate([self._w, np.asarray(w, float)[ok]])

    def speed_at(self, t_ns: int) -> tuple[float, float, np.ndarray | None] | None:
        """The wheel speed at an epoch: the line through the window's rows, taken there (class docstring).

        Parameters
        ----------
        t_ns : the epoch, UTC ns.

        Returns
        -------
        (speed m/s, its variance (m/s)^2 with ``sigma_mps`` added, the four wheels' speeds m/s (None: not all
        given)), or None without enough recent rows.
        """
        if len(self._t) < self.min_samples:  # too few rows at all (a drive without wheel speeds: every epoch)
            return None
        keep = self._t > t_ns - int(self.window_s * 1e9)
        if not keep.all():
            self._t, self._v, self._var, self._w = self._t[keep], self._v[keep], self._var[keep], self._w[keep]
        sel = self._t <= t_ns + int(0.02e9)
        if sel.sum() < self.min_samples or t_ns - int(self._t[sel].max()) > self.max_age_s * 1e9:
            return None
        dt = (self._t[sel] - t_ns) * 1e-9
        v = self._v[sel]
        A = np.stack([np.ones_like(dt), dt], axis=1)
        coef = np.linalg.lstsq(A, v, rcond=None)[0] if np.ptp(dt) > 0 else np.array([v.mean(), 0.0])
        var = self._var[sel]
        var = median(var[np.isfinite(var)]) if np.isfinite(var).any() else 0.0
        w = self._w[sel]
        wheels = (np.linalg.lstsq(A, w, rcond=None)[0][0] if np.ptp(dt) > 0 else w.mean(axis=0)
                  ) if np.isfinite(w).all() else None
        return float(coef[0]), var + self.sigma_mps ** 2, wheels

    def compute_matrices(self, m: Moment) -> kf.Measurement | None:
        """The wheel speed with the NHC's zeros in the car's axes (class docstring).

        Parameters
        ----------
        m : the epoch's time and velocity (for the scale fit), the INS, the bias-corrected rate and P (slip test).

        Returns
        -------
        (z (k,) m/s in the car's axes, the rows that pass the slip test; H; R), None without wheel speeds near the
        epoch.
        """
        got = self.speed_at(m.epoch.t_ns)
        if got is None:
            return None
        v_wheel, var, wheels = got
        C_nb = m.nav.C_bn.T
        omega_nb_b = m.omega_b - C_nb @ earth.omega_ie_n(m.nav.lat)

        def measure(v: float) -> kf.Measurement:
            return odometer.odometer_measurement(m.nav, omega_nb_b, self.lever_b, v, var, self.scale.scale,
                                                 self.scale.sigma, self.nhc_sigma_mps)

        z, H, R = measure(v_wheel)
        v_kept = None if wheels is None else self.wheels.forward_speed(m.nav, omega_nb_b, self.lever_b, wheels, var,
                                                                       float(H[1] @ m.P @ H[1]))
        every_wheel_slips = v_kept is not None and not math.isfinite(v_kept)  # then the NHC rows alone
        if v_kept is not None and not every_wheel_slips:
            v_wheel = v_kept
            z, H, R = measure(v_wheel)
        z, H = self.car.rotate(z, H, np.array([0.0, v_wheel / self.scale.scale, 0.0]))
        R = R + np.diag(self.car.extra_var(v_wheel / self.scale.scale))
        if every_wheel_slips or z[1] ** 2 > odometer.SLIP_CHI2 * (H[1] @ m.P @ H[1] + R[1, 1]):
            self.slip_skipped.append(m.epoch.t_ns)
            rows = [0, 2] if self.nhc else []
        else:
            rows = [0, 1, 2] if self.nhc else [1]
            if m.usable and np.isfinite(m.epoch.v_n[:2]).all() and np.isfinite(m.epoch.vel_cov[:2, :2]).all():
                e = self.car.axes(C_nb)[1]
                v_gps = m.epoch.v_n.copy()
                if not np.isfinite(v_gps[2]):
                    v_gps[2] = m.nav.v_n[2]
                var_gps = float(e[:2] @ m.epoch.vel_cov[:2, :2] @ e[:2])
                self.scale.add(m.t_fix, v_wheel, float(e @ v_gps), var_gps)
                self.wheels.learn(m.t_fix, var_gps)
        if not rows:
            return None
        self.times.append(m.epoch.t_ns)
        return z[rows], H[rows], R[np.ix_(rows, rows)]


@dataclass
class VirtualOdometer:
    """The learnt forward speed (``[fusion] predictor_mode = "pseudo"``, ``fusion.pseudo``): a virtual odometer.

    While GNSS is good it trains a model (``fusion.pseudo.SpeedModel``) on the IMU's features
    (``fusion.pseudo.imu_features``) to the GNSS velocity's component along the IMU's forward axis, scoring
    copies frozen 30-60 s before first (``fusion.pseudo.HeldOut``). At an epoch without a usable fix it gives the
    predicted speed as the forward row of the wheel odometer's measurement (``odometer.odometer_measurement``
    at the IMU, scale 1): z = (C_nb v_n)_y - v_pred, R the held-out residuals' variance; only when the held-out
    skill is positive and ``MIN_SCORED`` residuals were scored. No lateral or vertical zeros: those are the
    NHC's, when it is on. ``preempted_by``: aids whose measurement at the same epoch replaces this one (the
    wheel odometer, the stationary update). ``feed_imu`` takes the raw samples as the engine integrates them;
    ``times``: the epochs it gave a measurement at."""

    cfg: PredictorConfig
    preempted_by: tuple = ()
    kind = "velocity"
    stage = "aid"
    receiver = False
    times: list[int] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.net = pseudo.new_network(self.cfg)
        self.window = pseudo.ImuWindow()
        self.held_out = pseudo.HeldOut(self.cfg.window)
        self.trained = 0
        self.outage_skills: list[float] = []  # the skill at each outage's first epoch
        self._in_outage = False

    def feed_imu(self, w: np.ndarray, f: np.ndarray, i0: int, i1: int, imu_dt: float) -> None:
        """Raw IMU samples for the features.

        Parameters
        ----------
        w, f : (n, 3) rate, rad/s, and specific force, m/s^2, body RFU.
        i0, i1 : the samples after i0 up to i1 are new.
        imu_dt : the sample period, s.
        """
        self.window.add(w, f, i0, i1, imu_dt)

    def compute_matrices(self, m: Moment) -> kf.Measurement | None:
        """The predicted forward speed at an epoch without a usable fix; at the others it trains (class docstring).

        Parameters
        ----------
        m : the epoch, whether its fix is usable, the INS, the interval's IMU sums and the bias estimates.

        Returns
        -------
        (z (1,) m/s along the IMU's forward axis, H (1, 15), R (1, 1)), None while trained or not trusted.
        """
        x = self.window.features(m.nav, m.imu_dt)
        if m.usable and np.isfinite(m.epoch.v_n[:2]).all():
            self._in_outage = False
            if x is not None:
                y = pseudo.forward_speed(m.nav, m.epoch.v_n)
                iv = m.interval
                if iv.n:
                    self.held_out.score(m.t_fix, x, y, iv.sum_w / iv.n, iv.sum_f / iv.n, iv.n * m.imu_dt)
                self.net.train(x, y)
                self.trained += 1
                self.held_out.freeze(m.t_fix, self.net, m.nav, y, m.bg, m.ba)
            return None
        if m.usable:
            return None
        if not self._in_outage:
            self._in_outage = True
            self.held_out.forget_reckoners()
            self.outage_skills.append(self.held_out.skill)
        if any(p.times and p.times[-1] == m.epoch.t_ns for p in self.preempted_by):
            return None
        if x is None or not self.on:
            return None
        v = self.net.predict(x)
        if not math.isfinite(v):
            return None
        omega_nb_b = m.omega_b - m.nav.C_bn.T @ earth.omega_ie_n(m.nav.lat)
        z, H, R = odometer.odometer_measurement(m.nav, omega_nb_b, np.zeros(3), v, self.held_out.R, 1.0, 0.0, 0.0)
        self.times.append(m.epoch.t_ns)
        return z[1:2], H[1:2], R[1:2, 1:2]

    @property
    def on(self) -> bool:
        """Whether the held-out score lets the prediction in: enough residuals scored and a positive skill."""
        return self.held_out.scored >= pseudo.MIN_SCORED and self.held_out.skill > 0.0

    def summary(self) -> dict:
        """The model in use (``fusion.pseudo.SpeedModel.CANDIDATES``), held-out skill and R (m/s, as a sigma),
        residuals scored, epochs trained, outage epochs it ran at, and the skill at each outage's start.

        Returns
        -------
        dict, for the run's report: ``model`` (str); ``held_out_skill`` (dimensionless) and ``held_out_sigma_mps``
        (m/s), None before any residual; ``scored``, ``trained`` and ``epochs_used`` (counts); ``ran`` (bool);
        ``outage_skills`` (list, None where not yet scored).
        """
        r = self.held_out.R
        return dict(model=pseudo.SpeedModel.CANDIDATES[self.held_out.best],
                    held_out_skill=_finite(self.held_out.skill), held_out_sigma_mps=_finite(math.sqrt(r)),
                    scored=self.held_out.scored, trained=self.trained, ran=len(self.times) > 0,
                    epochs_used=len(self.times), outage_skills=[_finite(s) for s in self.outage_skills])


def _finite(x: float) -> float | None:
    return x if math.isfinite(x) else None


@dataclass
class FirstOf:
    """The first of the given measurements that gives one (the others are not asked): the vehicle aids of one
    epoch exclude each other (a standing car gets the stationary update, not the non-holonomic constraint).
    All must share one kind and stage."""

    parts: tuple[MeasurementModel, ...]

    def __post_init__(self) -> None:
        kinds = {(p.kind, p.stage, p.receiver) for p in self.parts}
        if len(kinds) != 1:
            raise ValueError(f"FirstOf: measurements of different kinds or stages: {kinds}")
        self.kind, self.stage, self.receiver = kinds.pop()

    def compute_matrices(self, m: Moment) -> kf.Measurement | None:
        """The first of the parts' measurements.

        Parameters
        ----------
        m : handed to each part in turn.

        Returns
        -------
        the first part's (z, H, R) that is not None, or None.
        """
        for p in self.parts:
            out = p.compute_matrices(m)
            if out is not None:
                return out
        return None


def aids_and_gps(cfg: FusionConfig, learnt_speed: bool = False) -> list[MeasurementModel]:
    """The measurements an aided method runs with, in the order the loop applies them: the vehicle aids (``[fusion]
    zupt``, ``odometer``, ``nhc``: the first that gives one; the NHC and the odometer in the car's axes of
    ``mounting_rpy_deg``), the virtual odometer when asked, then the GPS velocity and position.

    Parameters
    ----------
    cfg : the settings.
    learnt_speed : with the virtual odometer (``fusion.methods.Method.learns_speed``: ``dkf-rbfn`` with
        ``predictor_mode = "pseudo"``).

    Returns
    -------
    list of the measurements.
    """
    lever = cfg.gps.lever_rfu()
    a = cfg.aids
    car = CarFrame.of(a.mounting_rpy_deg, a.mounting_sigma_deg)
    aids = ([Stationary(cfg, a.zupt_sigma_mps, cfg.sensor.gyro_noise_dps_rthz * _DEG)] if a.zupt else []) + (
        [Odometer(np.asarray(a.odometer_lever_b, float), a.odometer_sigma_mps, a.nhc_sigma_mps, a.nhc, car,
                  a.odometer_track_m, a.odometer_wheelbase_m)]
        if a.odometer else []) + (
        [NonHolonomic(a.nhc_sigma_mps, a.static_speed_mps, cfg.still.still_speed_mps, car)] if a.nhc else [])
    learnt = ([VirtualOdometer(cfg.predictor, tuple(p for p in aids if not isinstance(p, NonHolonomic)))]
              if learnt_speed else [])
    return ([FirstOf(tuple(aids))] if aids else []) + learnt + [GpsVelocity(lever, cfg.gps.vel_var_max),
                                                                GpsPosition(lever)]


def _still_references(nav: NavState, bg: np.ndarray, ba: np.ndarray, P: np.ndarray
                      ) -> tuple[np.ndarray, float, np.ndarray, float]:
    """What a vehicle standing still would measure, body: the rate (Earth rate + gyro bias, rad/s) and the
    specific force (gravity through the attitude + accelerometer bias, m/s^2), each with its sigma from P."""
    C_nb = nav.C_bn.T
    w_ref = C_nb @ earth.omega_ie_n(nav.lat) + bg
    f_ref = -C_nb @ earth.gravity_n(nav.lat, nav.h) + ba
    sd_w = math.sqrt(max(float(np.trace(P[BG, BG])), 0.0))
    sd_f = math.hypot(math.sqrt(max(float(P[6, 6] + P[7, 7]), 0.0)) * float(np.linalg.norm(f_ref)),
                      math.sqrt(max(float(np.trace(P[BA, BA])), 0.0)))
    return w_ref, sd_w, f_ref, sd_f


def position_measurement(nav: NavState, t_gps: float, lat: float, lon: float, h: float, cov_enu: np.ndarray,
                         lever_b: np.ndarray) -> kf.Measurement:
    """GPS position measurement: z = INS antenna position - GPS position, ENU m; the INS state extrapolated from nav.t
    to the fix time with its velocity.

    Parameters
    ----------
    nav : the INS state.
    t_gps : the fix time, s (the INS's time base).
    lat, lon : the fix, rad.
    h : its height, m (NaN: a fix without height, horizontal rows only).
    cov_enu : (3, 3) the fix's covariance, ENU m^2.
    lever_b : (3,) IMU -> antenna, body RFU, m.

    Returns
    -------
    (z (k,) m, H (k, 15), R (k, k) m^2).
    """
    C = nav.C_bn
    arm_n = C @ lever_b
    z = kf.enu_offset(nav.lat, nav.lon, nav.h, lat, lon, h) + arm_n + nav.v_n * (t_gps - nav.t)
    H = np.zeros((3, N_STATES))
    H[:, POS] = _I3
    H[:, ATT] = earth.skew(arm_n)
    return _rows(z, H, np.asarray(cov_enu, dtype=float), np.flatnonzero(np.isfinite(z)))


def velocity_measurement(nav: NavState, v_gps: np.ndarray, cov: np.ndarray, omega_ib_b: np.ndarray,
                         lever_b: np.ndarray, max_var: float) -> kf.Measurement | None:
    """GPS velocity measurement: z = INS antenna velocity - GPS velocity, ENU m/s.

    Parameters
    ----------
    nav : the INS state.
    v_gps : (3,) the receiver's velocity, ENU m/s.
    cov : (3, 3) its covariance, ENU (m/s)^2.
    omega_ib_b : (3,) the bias-corrected rate, body RFU, rad/s.
    lever_b : (3,) IMU -> antenna, body RFU, m.
    max_var : components with a variance above this, (m/s)^2, are left out (NMEA's unobserved vertical).

    Returns
    -------
    (z (k,) m/s, H (k, 15), R (k, k) (m/s)^2), or None when nothing is left.
    """
    cov = np.asarray(cov, dtype=float)
    var = cov.diagonal()
    keep = np.flatnonzero((var <= max_var) & np.isfinite(v_gps) & np.isfinite(var))
    if len(keep) == 0:
        return None
    C = nav.C_bn
    arm_v = C @ earth.cross(omega_ib_b, lever_b)
    z = nav.v_n + arm_v - v_gps
    H = np.zeros((3, N_STATES))
    H[:, VEL] = _I3
    H[:, ATT] = earth.skew(arm_v)
    H[:, BG] = -C @ earth.skew(lever_b)
    return _rows(z, H, cov, keep)


def _rows(z: np.ndarray, H: np.ndarray, R: np.ndarray, keep: np.ndarray) -> kf.Measurement:
    """The rows ``keep`` (indexes, ascending) of a measurement (z, H, R); R a copy."""
    if len(keep) == len(z):
        return z, H, R.copy()
    return z[keep], H[keep], R[keep][:, keep]


def nhc_measurement(nav: NavState, sigma_mps: float, car: CarFrame = CarFrame()) -> kf.Measurement:
    """Non-holonomic constraint of a car: the car's body lateral (x) and vertical (z) velocity are zero.

    z = (C_bm C_bn^T v_n)[x, z] of the INS, m/s; with C_computed = (I - [phi x]) C_true,
    dv_b = C_bm C_nb dv_n - C_bm C_nb [v_n x] phi. Assumes the IMU sits near the rear axle's centre line (no
    lever arm to the non-holonomic point).

    Parameters
    ----------
    nav : the INS state (ENU; its attitude the IMU's axes).
    sigma_mps : 1-sigma of the constraint (side slip, suspension), m/s.
    car : the IMU's mounting in the car (:class:`CarFrame`; default: the IMU's axes are the car's); its sigma
        adds to R (``CarFrame.extra_var``).

    Returns
    -------
    (z (2,) m/s, H (2, 15), R (2, 2) (m/s)^2).
    """
    C_cn = car.axes(nav.C_bn.T)
    A = C_cn[[0, 2]]
    H = np.zeros((2, N_STATES))
    H[:, VEL] = A
    H[:, ATT] = -A @ earth.skew(nav.v_n)
    lateral, _, vertical = car.extra_var(float(C_cn[1] @ nav.v_n)).tolist()
    var = sigma_mps ** 2
    return A @ nav.v_n, H, np.array([[var + lateral, 0.0], [0.0, var + vertical]])


def stationary_measurement(nav: NavState, mean_omega_b: np.ndarray, sigma_v: np.ndarray,
                           sigma_w: np.ndarray | None) -> kf.Measurement:
    """Zero-velocity (ZUPT) and zero-angular-rate update (ZARU) of a vehicle standing still: z = [v_n of the INS; the
    mean bias-corrected gyro output over the still interval less the Earth rate in the body frame], the velocity
    error and the residual gyro bias.

    Parameters
    ----------
    nav : the INS state.
    mean_omega_b : (3,) the interval's mean bias-corrected rate, body RFU, rad/s.
    sigma_v : (3,) the ZUPT's 1-sigma per ENU axis, m/s.
    sigma_w : (3,) the ZARU's 1-sigma per body axis, rad/s; None: the ZUPT alone (3 rows).

    Returns
    -------
    (z (6,) or (3,) m/s and rad/s, H, R).
    """
    C_nb = nav.C_bn.T
    rows = 3 if sigma_w is None else 6
    H = np.zeros((rows, N_STATES))
    H[0:3, VEL] = np.eye(3)
    if sigma_w is None:
        return nav.v_n.copy(), H, np.diag(np.asarray(sigma_v, float) ** 2)
    H[3:6, BG] = np.eye(3)
    z = np.concatenate([nav.v_n, mean_omega_b - C_nb @ earth.omega_ie_n(nav.lat)])
    return z, H, np.diag(np.concatenate([sigma_v, sigma_w]) ** 2)
