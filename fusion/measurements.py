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
from fieldlog.fusion.align import GATE, GpsSpeed, ImuSums, StillRun
from fieldlog.fusion.config import FusionConfig
from fieldlog.fusion.errmodel import BA, BG
from fieldlog.fusion.predictors import PredictorConfig
from fieldlog.fusion.ins import NavState
from fieldlog.fusion.types import Epoch, OdomBlock

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
        """(z, H, R) at the moment, or None."""


@dataclass
class GpsPosition:
    """The fix: z = INS antenna position - GPS position, ENU m (``kf.position_measurement``); lever_b (3,) IMU ->
    antenna, body RFU, m. R is the fix's covariance; a fix without height gives the horizontal rows only."""

    lever_b: np.ndarray
    kind = "position"
    stage = "fix"
    receiver = True

    def compute_matrices(self, m: Moment) -> kf.Measurement | None:
        e = m.epoch
        if not m.usable:
            return None
        return kf.position_measurement(m.nav, m.t_fix, e.lat, e.lon, e.h, e.pos_cov, self.lever_b)


@dataclass
class GpsVelocity:
    """The receiver's velocity: z = INS antenna velocity - GPS velocity, ENU m/s (``kf.velocity_measurement``);
    components with a variance above max_var ((m/s)^2, NMEA's unobserved vertical) are left out."""

    lever_b: np.ndarray
    max_var: float
    kind = "velocity"
    stage = "fix"
    receiver = True

    def compute_matrices(self, m: Moment) -> kf.Measurement | None:
        if not m.usable:
            return None
        return kf.velocity_measurement(m.nav, m.epoch.v_n, m.epoch.vel_cov, m.omega_b, self.lever_b, self.max_var)


@dataclass
class NonHolonomic:
    """A car's body lateral and vertical velocity are zero (``kf.nhc_measurement``), sigma_mps each; not when the
    car is slow: GPS speed below slow_gps_mps, or (without a GPS velocity) INS speed below slow_ins_mps."""

    sigma_mps: float
    slow_gps_mps: float
    slow_ins_mps: float
    kind = "velocity"
    stage = "aid"
    receiver = False

    def compute_matrices(self, m: Moment) -> kf.Measurement | None:
        v = m.v_aid
        slow = (float(np.hypot(v[0], v[1])) < self.slow_gps_mps if np.isfinite(v[:2]).all()
                else float(np.linalg.norm(m.nav.v_n)) < self.slow_ins_mps)
        return None if slow else kf.nhc_measurement(m.nav, self.sigma_mps)


@dataclass
class Stationary:
    """Zero-velocity and zero-angular-rate update (ZUPT + ZARU, ``kf.stationary_measurement``) when the vehicle
    stood still over the interval since the last epoch and the one before it (``fusion.align.StillRun``).

    A standing car is not still to a good gyro (the engine idles, the body rocks on its springs, people move),
    so the noise comes from the interval itself and from what the still detector admits, never tighter:

    - ZARU, per body axis: sigma_w^2 = gyro_noise^2 / T (white noise over the interval's T s) + the squared
      standard error of the interval's mean rate (its samples' spread over sqrt(n)) + (still_rate_tol / gate)^2,
      the mean rate the detector lets through as "still" (``[fusion] still_rate_tol_dps`` at its gate of
      ``align.GATE`` sigmas);
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
        v_gps = m.epoch.v_n if m.usable else np.full(3, np.nan)
        speed = self.speed.add(m.t_fix, v_gps, m.epoch)
        if not (math.isfinite(speed[0]) or float(np.linalg.norm(m.nav.v_n)) < self.cfg.still.still_speed_mps):
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
        return kf.stationary_measurement(m.nav, mean_w, sigma_v, sigma_w)

    def noise(self, interval: ImuSums, seconds: float) -> tuple[np.ndarray, np.ndarray]:
        """(sigma_v (3,) m/s, sigma_w (3,) rad/s) of the ZUPT and ZARU from a still interval of ``seconds``
        (class docstring)."""
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
    forward row alone). With the four wheel speeds, ``wheels`` tests each (``odometer.WheelSlip``: ``track_m``,
    ``wheelbase_m``) and the forward speed is the mean of those kept."""

    lever_b: np.ndarray
    sigma_mps: float
    nhc_sigma_mps: float
    nhc: bool = True
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
        self.wheels = odometer.WheelSlip(odometer.wheel_positions(self.lever_b, self.track_m, self.wheelbase_m))

    def feed(self, block: OdomBlock) -> None:
        """More rows (UTC ns, m/s, (m/s)^2); those before the last epoch's window are dropped there, so a block's
        rows are held until its epochs have passed."""
        ok = np.isfinite(block.v)
        self._t = np.concatenate([self._t, np.asarray(block.t_ns, np.int64)[ok]])
        self._v = np.concatenate([self._v, np.asarray(block.v, float)[ok]])
        self._var = np.concatenate([self._var, np.asarray(block.var, float)[ok]])
        w = np.full((len(ok), len(odometer.WHEELS)), np.nan) if block.wheels is None else block.wheels
        self._w = np.concatenate([self._w, np.asarray(w, float)[ok]])

    def speed_at(self, t_ns: int) -> tuple[float, float, np.ndarray | None] | None:
        """The wheel speed (m/s) at t_ns, its variance and the four wheels' speeds (None: not all given), or None
        (module docstring of the class)."""
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
        var = float(np.median(var[np.isfinite(var)])) if np.isfinite(var).any() else 0.0
        w = self._w[sel]
        wheels = (np.linalg.lstsq(A, w, rcond=None)[0][0] if np.ptp(dt) > 0 else w.mean(axis=0)
                  ) if np.isfinite(w).all() else None
        return float(coef[0]), var + self.sigma_mps ** 2, wheels

    def compute_matrices(self, m: Moment) -> kf.Measurement | None:
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
        if v_kept is not None:
            v_wheel = v_kept
            z, H, R = measure(v_wheel)
        if not math.isfinite(z[1]) or z[1] ** 2 > odometer.SLIP_CHI2 * (H[1] @ m.P @ H[1] + R[1, 1]):
            self.slip_skipped.append(m.epoch.t_ns)
            rows = [0, 2] if self.nhc else []
        else:
            rows = [0, 1, 2] if self.nhc else [1]
            if m.usable and np.isfinite(m.epoch.v_n[:2]).all() and np.isfinite(m.epoch.vel_cov[:2, :2]).all():
                e = C_nb[1]
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

    While GNSS is good it trains an RBF network (``fusion.predictors.SpeedNetwork``) on the IMU's features
    (``fusion.pseudo.imu_features``) to the GNSS velocity's component along the IMU's forward axis, scoring
    copies frozen 30-60 s before first (``fusion.pseudo.HeldOut``). At an epoch without a usable fix it gives the
    predicted speed as the forward row of the wheel odometer's measurement (``odometer.odometer_measurement``
    at the IMU, scale 1): z = (C_nb v_n)_y - v_pred, R the held-out residuals' mean square; only when the held-out
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
        """Raw IMU samples (i0, i1] of w, f (n, 3), body RFU, at period imu_dt (s)."""
        self.window.add(w, f, i0, i1, imu_dt)

    def compute_matrices(self, m: Moment) -> kf.Measurement | None:
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
        """Held-out skill and R (m/s, as a sigma), residuals scored, epochs trained, outage epochs it ran at, and
        the skill at each outage's start."""
        r = self.held_out.R
        return dict(held_out_skill=_finite(self.held_out.skill), held_out_sigma_mps=_finite(math.sqrt(r)),
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
        for p in self.parts:
            out = p.compute_matrices(m)
            if out is not None:
                return out
        return None


def aids_and_gps(cfg: FusionConfig, learnt_speed: bool = False) -> list[MeasurementModel]:
    """The measurements an aided method runs with, in the order the loop applies them: the vehicle aids
    (``[fusion] zupt``, ``odometer``, ``nhc``: the first that gives one), the virtual odometer when
    ``learnt_speed`` (``fusion.methods.Method.learns_speed``: ``dkf-rbfn`` with ``predictor_mode = "pseudo"``),
    then the GPS velocity and position."""
    lever = cfg.gps.lever_rfu()
    a = cfg.aids
    aids = ([Stationary(cfg, a.zupt_sigma_mps, cfg.sensor.gyro_noise_dps_rthz * _DEG)] if a.zupt else []) + (
        [Odometer(np.asarray(a.odometer_lever_b, float), a.odometer_sigma_mps, a.nhc_sigma_mps, a.nhc,
                  a.odometer_track_m, a.odometer_wheelbase_m)]
        if a.odometer else []) + (
        [NonHolonomic(a.nhc_sigma_mps, a.static_speed_mps, cfg.still.still_speed_mps)] if a.nhc else [])
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
