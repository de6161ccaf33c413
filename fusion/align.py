"""Initial alignment of the INS from a standing start and the first GPS epochs (the still intervals from
``fusion.still``, the still detector it shares with the stationary aid).

Alignment (:class:`Alignment`):

- **Static interval**: the last run of still intervals before the alignment epoch, trimmed by
  ``still_trim_s`` at each end where the vehicle moved (the start of a creep hides in the last second).
- **Levelling** from its mean specific force; sigma from the accelerometer noise over the static duration,
  the accelerometer bias prior (a horizontal bias tilts the levelling by b / g) and ``init_level_sigma_deg``
  (mounting, residual motion), added in quadrature.
- **Heading** by gyrocompassing when the gyros see the Earth rate: the horizontal rate in the levelled frame
  points north; sigma = (horizontal bias prior, the mean's noise, the tilt's share of the vertical Earth rate)
  / (Omega_ie cos(lat)). Used when that sigma is below the GPS course's and below ``gyrocompass_max_deg``
  (:attr:`Alignment.note` says which). Otherwise the **GPS course** at the first epoch at ``align_speed_mps``,
  sigma = hypot(velocity noise / speed, ``align_sideslip_deg``), the velocity noise from the epoch's covariance
  (or from the fix's when the drive has no velocity). The heading of the static interval is carried to the
  alignment epoch by the yaw gyro (a car that turns as it pulls away).
- **Initial gyro bias**: the static mean minus the Earth rate through the static interval's attitude (the aligned
  one less the heading ``turned`` since: a 3 deg creep turn moves 0.5 deg/h of horizontal Earth rate between the
  body axes); sigma per axis, in quadrature: the mean's standard error from the spread of its intervals (noise and residual motion), the bias
  instability ``init_gyro_bias_sigma_dps`` (the floor: never the static estimate alone), and the Earth-rate
  projection error (Omega_ie cos(lat) x heading sigma on the horizontal axes; a gyrocompass cannot separate the
  horizontal bias from its heading, so there the horizontal sigma is the prior ``gyro_bias_prior_sigma_dps``).
  Without a static interval: bias 0 with the prior sigma, roll and pitch 0 with 5 deg.
- **Optional initial attitude** ``init_attitude_deg = [roll, pitch, heading]`` at the drive's start (with
  ``init_level_sigma_deg``, ``init_heading_sigma_deg``): replaces levelling and heading, carried to the
  alignment epoch by the yaw gyro; position and velocity from the alignment epoch's fix.
- **Optional initial state** (:meth:`Alignment.configured`): with ``init_position_llh = [lat deg, lon deg, h m]``
  (the IMU's, ellipsoidal; sigma ``init_position_sigma_m`` per axis) as well, the INS starts at the first IMU
  sample from the config: that position, ``init_velocity_enu`` (m/s, default 0: standing; sigma
  ``init_vel_sigma_mps``) and ``init_attitude_deg``, the gyro bias 0 with its prior sigma; no alignment, the
  filter runs from the first sample (a static start then levels and calibrates through the GPS updates).

**Re-alignment** (:class:`HeadingCheck`): over the first ``realign_window_s`` after the alignment, the GPS
velocity innovations' normalised squares (NIS; a heading error shows in the velocity as soon as the vehicle
accelerates or turns, and the position's slow receiver error is not in the filter's model) are summed over the
last ``realign_epochs`` epochs; above the chi-square quantile of probability 1 - 1e-4 for their degrees of freedom, the heading is far off its sigma: the heading is
taken again from the GPS course (at ``align_speed_mps`` or more, and only where the course is more than 3 of its
sigmas from the INS heading: in turns the innovations of a well-aligned MEMS filter can pass the quantile too,
from the scale-factor errors the 15 states do not carry) with the course's sigma, the gyro bias sigma
reopened to the prior, the other states kept. Once per drive; not with the RTS smoother (its log has no
record of a jump).

Position and velocity come from the alignment epoch (unless configured). Frames: navigation ENU, body RFU;
IMU sums in rad/s and m/s^2.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from fieldlog.fusion import earth, ins, kf, still
from fieldlog.fusion.still import GpsSpeed, ImuSums
from fieldlog.fusion.types import Epoch

if TYPE_CHECKING:
    from fieldlog.fusion.config import FusionConfig

_DEG = math.pi / 180.0
_UG = 9.80665e-6
_G = 9.80665
_MIN_STATIC_S = 1.0  # a still run shorter than this after its trimmed ends does not replace an earlier one


def level(f_b: np.ndarray) -> tuple[float, float]:
    """Pitch and roll of a vehicle at rest.

    Parameters
    ----------
    f_b : (3,) its mean specific force, body RFU, m/s^2.

    Returns
    -------
    (pitch, roll), rad.
    """
    return math.atan2(f_b[1], math.hypot(f_b[0], f_b[2])), math.atan2(-f_b[0], f_b[2])


def gyrocompass(w_b: np.ndarray, pitch: float, roll: float) -> float:
    """Heading of a vehicle at rest from the Earth rate its gyros see: the horizontal rate, levelled, points north.

    Parameters
    ----------
    w_b : (3,) the mean rate, body RFU, rad/s.
    pitch, roll : its attitude, rad.

    Returns
    -------
    float, the heading, rad clockwise from north.
    """
    w_l = earth.euler_to_dcm(0.0, pitch, roll) @ w_b
    return math.atan2(-w_l[0], w_l[1])


def _total(intervals) -> ImuSums:
    out = ImuSums()
    for s in intervals:
        out.merge(s)
    return out


def _standard_errors(intervals: list[ImuSums]) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis standard errors of the mean rate (rad/s) and specific force (m/s^2) of still intervals: the
    spread of the interval means over their number (noise and residual motion), at least the samples' own."""
    n = np.array([s.n for s in intervals], float)
    w = np.array([s.sum_w / s.n for s in intervals])
    f = np.array([s.sum_f / s.n for s in intervals])
    tot = _total(intervals)
    out = []
    for means, total, squares in ((w, tot.sum_w, tot.sum_ww), (f, tot.sum_f, tot.sum_ff)):
        m = total / tot.n
        within = np.sqrt(np.maximum(squares / tot.n - m * m, 0.0) / tot.n)
        between = means.std(axis=0, ddof=1) / math.sqrt(len(n)) if len(n) > 1 else within
        out.append(np.maximum(within, between))
    return out[0], out[1]


@dataclass
class Aligned:
    """The result of the alignment: the INS state, the initial gyro bias (rad/s, body) and covariance P0 (15, 15)."""

    nav: ins.NavState
    bg: np.ndarray
    P0: np.ndarray


def chi2_quantile(dof: int, z: float = 3.719) -> float:
    """Upper quantile of the chi-square distribution, Wilson-Hilferty (within 1 % from 6 degrees of freedom).

    Parameters
    ----------
    dof : the degrees of freedom.
    z : the standard-normal quantile (3.719: probability 1e-4).

    Returns
    -------
    float
    """
    a = 2.0 / (9.0 * dof)
    return dof * (1.0 - a + z * math.sqrt(a)) ** 3


class HeadingCheck:
    """The chi-square test on the GPS innovations of the first minutes after the alignment (module docstring)."""

    def __init__(self, cfg: FusionConfig, t_align: float) -> None:
        self.cfg = cfg
        self.t_end = t_align + cfg.align.realign_window_s
        self.recent: list[tuple[float, int]] = []
        self.done = not cfg.align.realign_window_s > 0

    def far_off(self, t: float, z: np.ndarray, H: np.ndarray, R: np.ndarray, x: np.ndarray, P: np.ndarray) -> bool:
        """Add an epoch's GPS velocity measurement to the test.

        Parameters
        ----------
        t : the epoch's time, s.
        z : (m,) the measurement, m/s.
        H : (m, 15) its rows over the error states.
        R : (m, m) its covariance, (m/s)^2.
        x : (15,) the filter's predicted error state (zero in the closed-loop filters; the paper's distributed filter
            carries a fused prediction between epochs).
        P : (15, 15) the filter's covariance.

        Returns
        -------
        bool, True when the heading should be taken again.
        """
        if self.done or t > self.t_end or len(z) == 0:
            return False
        nu = z - H @ x
        S = H @ P @ H.T + R
        self.recent = (self.recent + [(float(nu @ np.linalg.solve(S, nu)), len(z))])[-self.cfg.align.realign_epochs:]
        if len(self.recent) < self.cfg.align.realign_epochs:
            return False
        nis, dof = sum(x for x, _ in self.recent), sum(d for _, d in self.recent)
        return nis > chi2_quantile(dof)

    def realign(self, nav: ins.NavState, ep: Epoch, P: np.ndarray) -> tuple[ins.NavState, np.ndarray] | None:
        """The state with the heading taken again from the epoch's GPS course.

        Parameters
        ----------
        nav : the INS state.
        ep : the epoch (its velocity, ENU m/s, and covariance).
        P : (15, 15) the filter's covariance.

        Returns
        -------
        (the INS state with the course's heading, the covariance with its heading sigma and the gyro bias prior), or
        None while the GPS speed is below ``align_speed_mps`` or the course agrees with the INS heading within 3 sigma of
        the course (try again later).
        """
        c = self.cfg
        v = ep.v_n
        speed = float(np.hypot(v[0], v[1])) if np.isfinite(v[:2]).all() else 0.0
        if speed < c.align.align_speed_mps:
            return None
        heading, pitch, roll = (float(x) for x in earth.dcm_to_euler(nav.C_bn))
        course = math.atan2(v[0], v[1])
        sd = math.hypot(still.vel_sigma(ep) / speed, c.align.align_sideslip_deg * _DEG)
        if abs(math.remainder(course - heading, 2.0 * math.pi)) <= 3.0 * sd:
            return None  # the course agrees with the heading: the innovations are large for another reason
        self.done = True
        C = earth.euler_to_dcm(course, pitch, roll)
        P = P.copy()
        P[8, :] = P[:, 8] = 0.0
        P[8, 8] = sd * sd
        for i in range(9, 12):
            P[i, i] = max(P[i, i], (c.init.gyro_bias_prior_sigma_dps * _DEG) ** 2)
        return ins.NavState(nav.t, nav.lat, nav.lon, nav.h, nav.v_n, earth.dcm_to_quat(C)), P


class Alignment:
    """Collects the still intervals before the alignment epoch and builds the initial state there.
    ``note`` says how the heading was found (after the alignment); ``summary`` which alignment ran: ``method``
    ("gyrocompass": levelled and gyrocompassed on the static interval; "still-level+gps-course": levelled there,
    heading from the GPS course; "gps-course": no static interval, level 0 with 5 deg; "config-attitude":
    ``init_attitude_deg``; "config-state": :meth:`configured`), the static interval used for the levelling and
    the gyro bias (``start_s``, ``end_s``, s from the first IMU sample, trimmed; None without one) and the
    alignment epoch (``epoch_s``)."""

    def __init__(self, cfg: FusionConfig) -> None:
        self.cfg = cfg
        self.lever = cfg.gps.lever_rfu()
        self.note = ""
        self.summary: dict[str, object] = {}  # which alignment ran and on which still interval (class docstring)
        self.static_intervals: list[tuple[ImuSums, float]] = []  # the static interval levelled on: sums, seconds
        self._run: list[tuple[ImuSums, float, float]] = []  # the current run of still intervals, with their seconds
        # and end times (s from the first IMU sample)
        self._run_first = True  # the run started with the drive (its start needs no trimming)
        self._static: list[tuple[ImuSums, float, float]] = []  # the last finished run, trimmed at the alignment
        self._static_first = True
        self._after: list[tuple[ImuSums, float, float]] = []  # the intervals since that run
        self._speed = GpsSpeed(cfg)
        self._t_prev: float | None = None
        self._last_fix: tuple[float, float, float, float] | None = None  # t_s, lat, lon, h of the last good fix

    def _velocity(self, ep: Epoch, t_ref_ns: int) -> np.ndarray:
        """The epoch's GPS velocity (3,) ENU m/s, or the difference of its fix and the last good one (at most 2 s
        before it) when the drive has none; NaN without either."""
        if np.isfinite(ep.v_n[:2]).all():
            return ep.v_n
        ts = (ep.t_ns - t_ref_ns) * 1e-9
        if self._last_fix is None or not 0.0 < ts - self._last_fix[0] <= 2.0:
            return np.full(3, np.nan)
        t0, lat0, lon0, h0 = self._last_fix
        return kf.enu_offset(ep.lat, ep.lon, ep.h, lat0, lon0, h0) / (ts - t0)

    def epoch(self, ep: Epoch, usable: bool, interval: ImuSums, t_k: float, t_ref_ns: int) -> Aligned | None:
        """A GPS epoch before the alignment.

        Parameters
        ----------
        ep : the epoch.
        usable : whether its fix is used.
        interval : the IMU sums of the interval that ends here (rad/s, m/s^2, body RFU).
        t_k : the current sample's time, s from t_ref_ns.
        t_ref_ns : the drive's reference time, UTC ns.

        Returns
        -------
        The initial state when this epoch aligns the INS, else None.
        """
        v = self._velocity(ep, t_ref_ns) if usable else np.full(3, np.nan)
        if usable:
            self._last_fix = ((ep.t_ns - t_ref_ns) * 1e-9, ep.lat, ep.lon, ep.h)
        v_gps = ep.v_n if usable else np.full(3, np.nan)
        dt = t_k - self._t_prev if self._t_prev is not None else 0.0
        self._t_prev = t_k
        verdict = self._verdict(interval, self._speed.add((ep.t_ns - t_ref_ns) * 1e-9, v_gps, ep))
        if verdict == "still":
            self._run.append((interval, dt, t_k))
        elif verdict == "unsure":
            self._after.append((interval, dt, t_k))
        elif interval.n:
            if self._run:
                if not self._static or sum(dt for _, dt, _ in self._run) >= 2.0 * self.cfg.align.still_trim_s + _MIN_STATIC_S:
                    self._static, self._static_first, self._after = self._run, self._run_first, []
                else:  # a lull too short to level from (an aircraft's first metres): the stop before it stays
                    self._after += self._run
                self._run = []
            self._run_first = False
            self._after.append((interval, dt, t_k))
        speed = float(np.hypot(v[0], v[1])) if np.isfinite(v[:2]).all() else math.inf
        if usable and math.isfinite(ep.h) and math.isfinite(speed) and speed >= self.cfg.align.align_speed_mps:
            return self._initialise(ep, v, t_k, t_ref_ns)
        return None

    def _verdict(self, interval: ImuSums, speed: tuple[float, float]) -> str:
        c = self.cfg
        if not self._run:
            prior = math.hypot(c.init.gyro_bias_prior_sigma_dps * _DEG, earth.OMEGA_IE)
            return still.verdict(c, interval, speed, [(np.zeros(3), prior, None, 0.0)])
        run = _total(s for s, _, _ in self._run)  # the bias instability moves the rate between intervals too
        return still.verdict(c, interval, speed, [(run.sum_w / run.n, c.init.init_gyro_bias_sigma_dps * _DEG, run.sum_f / run.n,
                                              0.0)], run)

    def _static_interval(self) -> tuple[list[tuple[ImuSums, float]], list[tuple[ImuSums, float]]]:
        """The still intervals of the static start, trimmed by ``still_trim_s`` where the vehicle moved next to
        them, and the intervals after them (the trimmed end included)."""
        run, first, after = ((self._run, self._run_first, []) if self._run else
                             (self._static, self._static_first, self._after))
        k, secs = 0, 0.0
        while k < len(run) and secs < self.cfg.align.still_trim_s:
            secs += run[len(run) - 1 - k][1]
            k += 1
        j, secs = 0, 0.0
        while not first and j < len(run) - k and secs < self.cfg.align.still_trim_s:
            secs += run[j][1]
            j += 1
        return run[j:len(run) - k], run[len(run) - k:] + after

    def _initialise(self, ep: Epoch, v: np.ndarray, t_k: float, t_ref_ns: int) -> Aligned:
        c = self.cfg
        lat = ep.lat
        intervals, after = self._static_interval()
        tot = _total(s for s, _, _ in intervals)
        static = tot.n >= 200
        speed = math.hypot(v[0], v[1])
        w_h = earth.OMEGA_IE * math.cos(lat)  # horizontal Earth rate, rad/s
        sd_course = math.hypot(still.vel_sigma(ep) / speed, c.align.align_sideslip_deg * _DEG)
        if static:
            fm, wm = tot.sum_f / tot.n, tot.sum_w / tot.n
            pitch, roll = level(fm)
            se_w, se_f = _standard_errors([s for s, _, _ in intervals])
            seconds = sum(dt for _, dt, _ in intervals)
            sd_f = math.hypot(c.sensor.accel_noise_ug_rthz * _UG / math.sqrt(seconds), c.init.init_accel_bias_sigma_ug * _UG)
            sd_level = math.hypot(math.hypot(sd_f, float(np.max(se_f))) / _G, c.init.init_level_sigma_deg * _DEG)
            sd_gc = math.sqrt((c.init.gyro_bias_prior_sigma_dps * _DEG) ** 2 + float(np.max(se_w)) ** 2
                              + (earth.OMEGA_IE * math.sin(lat) * sd_level) ** 2) / w_h
        else:
            pitch = roll = 0.0
            sd_level = 5.0 * _DEG
            sd_gc = math.inf
        # heading change since the static interval (level vehicle: yaw rate = -body up rate, less its rest value)
        rest_z = wm[2] if static else earth.OMEGA_IE * math.sin(lat)
        turned = -sum((s.sum_w[2] / s.n - rest_z) * dt for s, dt, _ in after if s.n)
        gyrocompassed = False
        if c.init.init_attitude_deg:
            roll, pitch = c.init.init_attitude_deg[0] * _DEG, c.init.init_attitude_deg[1] * _DEG
            sd_level = c.init.init_level_sigma_deg * _DEG
            heading, sd_head = c.init.init_attitude_deg[2] * _DEG + turned, c.init.init_heading_sigma_deg * _DEG
            self.note = "heading from the config's init_attitude_deg"
            method = "config-attitude"
        elif static and sd_gc < min(sd_course, c.align.gyrocompass_max_deg * _DEG):
            heading, sd_head = gyrocompass(wm, pitch, roll) + turned, sd_gc
            gyrocompassed = True
            self.note = f"heading by gyrocompassing, sigma {math.degrees(sd_gc):.2f} deg"
            method = "gyrocompass"
        else:
            heading, sd_head = math.atan2(v[0], v[1]), sd_course
            method = "still-level+gps-course" if static else "gps-course"
            self.note = (f"heading from the GPS course, sigma {math.degrees(sd_course):.2f} deg (gyrocompassing: "
                         + (f"sigma {math.degrees(sd_gc):.1f} deg, the gyros cannot see the Earth rate well enough)"
                            if static else "no static start)"))
        C = earth.euler_to_dcm(heading, pitch, roll)
        bg = np.zeros(3)
        sd_bg = np.full(3, c.init.gyro_bias_prior_sigma_dps * _DEG)
        if static:  # the Earth rate as the gyros saw it: through the static interval's attitude, before the turn
            bg = wm - earth.euler_to_dcm(heading - turned, pitch, roll).T @ earth.omega_ie_n(lat)
            horiz = w_h * sd_head  # Earth-rate projection error through the heading sigma
            sd_bg = np.sqrt(se_w ** 2 + (c.init.init_gyro_bias_sigma_dps * _DEG) ** 2
                            + np.array([horiz, horiz, earth.OMEGA_IE * sd_level]) ** 2)
            if gyrocompassed:
                sd_bg[:2] = np.maximum(sd_bg[:2], c.init.gyro_bias_prior_sigma_dps * _DEG)
        arm = C @ self.lever
        rm, rn = earth.principal_radii(lat, ep.h)
        dt = t_k - (ep.t_ns - t_ref_ns) * 1e-9
        d_enu = v * dt - arm
        v0 = np.array([v[0], v[1], 0.0])
        nav = ins.NavState(t_k, lat + d_enu[1] / rm, ep.lon + d_enu[0] / (rn * math.cos(lat)),
                           ep.h + d_enu[2], v0, earth.dcm_to_quat(C))
        pos_var = np.diag(ep.pos_cov).copy()
        pos_var[~np.isfinite(pos_var) | (pos_var <= 0)] = 25.0
        span = (None, None)
        if static:  # the first interval of a drive has no dt: it starts with the drive
            _, first_dt, first_end = intervals[0]
            span = (first_end - first_dt if first_dt else 0.0, intervals[-1][2])
        self.summary = {"method": method, "start_s": span[0], "end_s": span[1], "epoch_s": t_k}
        self.static_intervals = [(s, dt) for s, dt, _ in intervals] if static else []
        return Aligned(nav, bg, self._P0(pos_var, sd_level, sd_head, sd_bg))

    def configured(self) -> Aligned:
        """The initial state from the config at the first IMU sample (t = 0): ``init_position_llh`` (IMU, not the
        antenna), ``init_velocity_enu`` (0: standing), ``init_attitude_deg``, with their sigmas; the gyro bias 0
        with its prior sigma (no static mean: the filter learns it).

        Returns
        -------
        Aligned
            nav at t = 0 s (lat, lon rad, h m, v_n ENU m/s, attitude body RFU -> ENU); bg (3,) zero, rad/s;
            P0 (15, 15) diagonal, ``fusion.errmodel`` order and units squared.
        """
        c = self.cfg
        roll, pitch, heading = (x * _DEG for x in c.init.init_attitude_deg)
        lat, lon, h = c.init.init_position_llh[0] * _DEG, c.init.init_position_llh[1] * _DEG, float(c.init.init_position_llh[2])
        v0 = np.array(c.init.init_velocity_enu, float) if c.init.init_velocity_enu else np.zeros(3)
        nav = ins.NavState(0.0, lat, lon, h, v0, earth.dcm_to_quat(earth.euler_to_dcm(heading, pitch, roll)))
        self.note = "initial state from the config (init_position_llh, init_velocity_enu, init_attitude_deg)"
        self.summary = {"method": "config-state", "start_s": None, "end_s": None, "epoch_s": 0.0}
        return Aligned(nav, np.zeros(3), self._P0(np.full(3, c.init.init_position_sigma_m ** 2), c.init.init_level_sigma_deg * _DEG,
                                                  c.init.init_heading_sigma_deg * _DEG,
                                                  np.full(3, c.init.gyro_bias_prior_sigma_dps * _DEG)))

    def _P0(self, pos_var: np.ndarray, sd_level: float, sd_head: float, sd_bg: np.ndarray) -> np.ndarray:
        """The initial covariance (15, 15): position variances (3,) ENU m^2, velocity ``init_vel_sigma_mps``,
        level and heading sigmas (rad), gyro bias sigmas (3,) rad/s, accel bias ``init_accel_bias_sigma_ug``."""
        c = self.cfg
        return np.diag(np.concatenate([pos_var, np.full(3, c.init.init_vel_sigma_mps ** 2),
                                       [sd_level ** 2, sd_level ** 2, sd_head ** 2], sd_bg ** 2,
                                       np.full(3, (c.init.init_accel_bias_sigma_ug * _UG) ** 2)]))

