"""The fusion loop every method runs in: blocks of IMU samples and GPS epochs in, a solution out.

Streaming: :meth:`Engine.process` takes consecutive blocks (any length) and keeps only one IMU
sample, the navigation state and the filter between calls, so memory does not grow with the drive.

Per block:

1. The INS (numba, ``fusion.ins.integrate``) runs over the bias-corrected IMU samples up to each GPS
   epoch in one call, then to the end of the block.
2. The error covariance is propagated at a lower rate than the IMU: the samples are cut into filter
   cycles of ``cov_step_s`` (0.1 s by default, 50 samples at 500 Hz; a cycle also ends at every GPS
   epoch). F, G, Phi and Q of all the cycles of a segment are built in one vectorised call
   (``fusion.errmodel``), with F taken at the cycle's middle sample and the cycle's mean specific force.
   Only the 15x15 covariance recursion loops in Python, at 10 Hz.
3. At a usable GPS epoch the filter is updated with the velocity and position measurements (lever
   arm from the config), the estimate corrects the INS and the bias estimates, and is reset (closed
   loop).

Initialisation (alignment): levelling from the accelerometers while the vehicle stands still (GPS speed
below ``static_speed_mps`` at both ends of a GPS interval), plus heading from the GPS course at the
first epoch where the speed reaches ``align_speed_mps``; position and velocity come from that epoch.
The static mean gyro output minus the Earth rate gives the initial gyro bias. Without a static start
roll and pitch start at zero with a large variance, and the gyro bias at zero.

Vehicle aids (``nhc``, ``zupt``; no GPS needed, so in outages too; not for ``ins``): at every GPS epoch time,
before the GPS update, the non-holonomic constraint of a car (body lateral and vertical velocity 0,
``kf.nhc_measurement``), or, when the vehicle stood still over the epoch interval (speed and IMU variance
thresholds), a zero-velocity + zero-angular-rate update (``kf.stationary_measurement``). They go through the
filter's ``update_aid`` (``fusion.dkf``: to KF_I only) and are fed back like a GPS update.

Clipped gyro: a yaw gyro flat at ``gyro_range_dps`` (the Table 2 gyro clips at 20 deg/s; a 90-degree city
turn needs 23) is rebuilt from the car's turn kinematics (yaw rate = -lateral acceleration / forward speed)
and the segment integrated again; the heading process noise grows by the rebuilt rate's uncertainty.

Outages: an epoch is unusable when its status is NO_FIX, its lat/lon are NaN, its horizontal sigma
is above ``max_fix_sigma_m``, or it falls in a forced window (``outages``, seconds from the first IMU
sample). Detected windows run from the first unusable epoch to the next usable one. A fix without
height (NaN altitude: the GGA of that second was lost) updates the horizontal position only.

Predictors (``rbfn``, ``tdln``, ``dkf-rbfn``; ``fusion.predictors`` for the mapping of the paper onto
this closed loop): the distributed filter runs as in ``dkf``. At each usable epoch the predictor is given
the INS position (ENU m from the alignment point) and velocity before the correction, and its target:
the observation z = INS - GPS (``rbfn``, ``tdln``) or the position and velocity components of the
correction fed back (``dkf-rbfn``). At each unusable or withheld epoch after the networks have enough
training, the predicted correction is fed into the INS; the error state and covariance are untouched.

``hinf``, ``kf-ukf``, ``sckf`` and ``ssr-sckf`` run the ``kf`` path with another filter object:
``fusion.hinf.HInfinityFilter`` (``hinf_gamma``), ``fusion.ukf.HybridKfUkf`` and the square-root cubature
filters of ``fusion.sckf``. The last three are ``fusion.ukf.CycleFilter`` s: they are given the navigation
solution at the start, middle and end of each covariance cycle (the nodes of their RK4 through the nonlinear
error model: the hybrid filter's in outages, the cubature filters' at every cycle); the hybrid filter is
also told of an outage at its first unusable epoch.

Smoothing: given a ``log`` (``fusion.smoother.SmootherLog``) the engine records, per covariance cycle,
Phi and the predicted covariance, and at each update the correction fed back and the covariance after
it (the covariance is then propagated one cycle per call, to capture each P).

Output: the (closed-loop) INS state at the first IMU sample of each 1/output_hz slot of UTC
(10 Hz by default), stamped with that sample's time, with the filter's sigmas.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from fieldlog.fusion import earth, errmodel, hinf, ins, kf, predictors, sckf, ukf
from fieldlog.fusion.dkf import DistributedKF
from fieldlog.fusion.errmodel import ATT, BA, BG, N_STATES, POS, VEL

if TYPE_CHECKING:
    from fieldlog.fusion.smoother import SmootherLog

METHODS = ("ins", "kf", "dkf", "rbfn", "tdln", "dkf-rbfn", "kf-ukf", "hinf", "sckf", "ssr-sckf")
PREDICTOR_NETWORK = {"rbfn": "rbfn", "tdln": "tdln", "dkf-rbfn": "rbfn"}
NS = 1_000_000_000
_DEG = math.pi / 180.0
_UG = 9.80665e-6


@dataclass
class FusionConfig:
    """Fusion settings. Sensor figures default to the distributed-KF paper's Table 2 class of MEMS
    IMU (gyro 0.01 deg/s/sqrt(Hz), bias stability 0.02 deg/s; accel 5 ug/sqrt(Hz)), inflated to absorb
    the scale-factor and misalignment errors the 15-state model does not carry."""

    lever_arm_b: tuple[float, float, float] = (0.0, 0.0, 0.0)  # IMU -> GPS antenna, body RFU, m
    output_hz: float = 10.0
    cov_step_s: float = 0.1  # covariance propagation cycle, s
    gyro_noise_dps_rthz: float = 0.03
    accel_noise_ug_rthz: float = 300.0
    gyro_bias_rw_dps_rts: float = 2e-4  # deg/s/sqrt(s)
    accel_bias_rw_ug_rts: float = 10.0  # ug/sqrt(s)
    init_vel_sigma_mps: float = 0.2
    init_level_sigma_deg: float = 0.5  # roll/pitch after levelling (5 deg without a static start)
    init_heading_sigma_deg: float = 3.0
    init_gyro_bias_sigma_dps: float = 0.02  # after the static gyro mean (0.1 deg/s without)
    init_accel_bias_sigma_ug: float = 2000.0
    static_speed_mps: float = 0.3
    align_speed_mps: float = 3.0
    vel_var_max: float = 100.0  # velocity components with a larger variance are not fed, (m/s)^2
    max_fix_sigma_m: float = 30.0
    outages: tuple[tuple[float, float], ...] = ()  # forced (start_s, length_s) from the first IMU sample
    gyro_range_dps: float = 20.0  # a gyro flat at this rate (or beyond) is clipped (Table 2: +-20 deg/s)
    clip_rate_sigma_dps: float = 0.5  # 1-sigma of a clipped yaw rate rebuilt from the lateral acceleration
    nhc: bool = True  # non-holonomic constraint of a car (body lateral, vertical velocity 0) at every epoch
    nhc_sigma_mps: float = 0.1
    zupt: bool = True  # zero-velocity and zero-angular-rate update when the vehicle stands still
    zupt_sigma_mps: float = 0.02
    still_speed_mps: float = 0.5  # standing still: INS speed below this (GPS speed below static_speed_mps) ...
    still_accel_std_mps2: float = 0.1  # ... and specific force and rate varying less than these over the epoch
    still_gyro_std_dps: float = 0.5
    hinf_gamma: float = 100.0  # H-infinity bound, position (m) / velocity (m/s) errors; must exceed their sigma
    hinf_min_ratio: float = 1.5  # gamma_k = max(hinf_gamma, ratio x existence bound); 0: fixed gamma (may raise)
    predictor: predictors.PredictorConfig = field(default_factory=predictors.PredictorConfig)

    def noise_psd(self) -> np.ndarray:
        return errmodel.noise_psd(self.gyro_noise_dps_rthz * _DEG, self.accel_noise_ug_rthz * _UG,
                                  self.gyro_bias_rw_dps_rts * _DEG, self.accel_bias_rw_ug_rts * _UG)


@dataclass
class ImuBlock:
    """IMU samples: t_ns (n,) int64 UTC, omega_ib_b (n, 3) rad/s, f_b (n, 3) m/s^2, body RFU."""

    t_ns: np.ndarray
    omega_ib_b: np.ndarray
    f_b: np.ndarray


@dataclass
class GpsBlock:
    """GPS epochs: t_ns (m,) UTC of the fix; lat_deg, lon_deg, h (m, ellipsoidal); pos_cov (m, 3, 3) ENU m^2;
    status (m,) NavSatFix status (-1 no fix); v_n (m, 3) ENU m/s (NaN where missing); vel_cov (m, 3, 3)."""

    t_ns: np.ndarray
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    h: np.ndarray
    pos_cov: np.ndarray
    status: np.ndarray
    v_n: np.ndarray
    vel_cov: np.ndarray

    @staticmethod
    def empty() -> "GpsBlock":
        z = np.zeros(0)
        return GpsBlock(np.zeros(0, np.int64), z, z, z, np.zeros((0, 3, 3)), np.zeros(0, np.int8),
                        np.zeros((0, 3)), np.zeros((0, 3, 3)))


@dataclass
class Solution:
    """Output rows: t_ns (n,), lat, lon (rad), h (m), v_n (n, 3), q (n, 4) [x, y, z, w] of C_bn,
    sigma (n, 9): position ENU m, velocity ENU m/s, attitude (phi E, N, U) rad."""

    t_ns: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    h: np.ndarray
    v_n: np.ndarray
    q: np.ndarray
    sigma: np.ndarray

    @staticmethod
    def concat(parts: list["Solution"]) -> "Solution":
        if not parts:
            return Solution(np.zeros(0, np.int64), *(np.zeros(0),) * 3, np.zeros((0, 3)), np.zeros((0, 4)),
                            np.zeros((0, 9)))
        return Solution(*(np.concatenate([getattr(p, k) for p in parts]) for k in
                          ("t_ns", "lat", "lon", "h", "v_n", "q", "sigma")))


@dataclass
class Outage:
    """A GPS outage window [start_ns, end_ns) UTC; reason "injected", "no_fix" or "low_quality"."""

    start_ns: int
    end_ns: int
    reason: str


@dataclass
class _Static:
    sum_w: np.ndarray = field(default_factory=lambda: np.zeros(3))
    sum_f: np.ndarray = field(default_factory=lambda: np.zeros(3))
    n: int = 0
    sum_ww: np.ndarray = field(default_factory=lambda: np.zeros(3))  # squares: the interval's variances
    sum_ff: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def std(self, total: np.ndarray, squares: np.ndarray) -> float:
        """Root of the summed per-axis variances of the samples, e.g. std(sum_f, sum_ff)."""
        m = total / max(self.n, 1)
        return math.sqrt(max(float(np.sum(squares / max(self.n, 1) - m * m)), 0.0))


class Engine:
    """One fusion run (a method of ``METHODS``) over a stream of blocks."""

    def __init__(self, method: str, config: FusionConfig | None = None, log: SmootherLog | None = None) -> None:
        """log: a ``fusion.smoother.SmootherLog`` to fill for the backward pass, or None."""
        if method not in METHODS:
            raise ValueError(f"unknown method {method!r}; one of {METHODS}")
        self.method = method
        self.log = log
        self.cfg = config or FusionConfig()
        self.lever = np.asarray(self.cfg.lever_arm_b, dtype=float)
        self.q = self.cfg.noise_psd()
        self.t_ref_ns: int | None = None
        self.nav: ins.NavState | None = None
        self.filter: kf.KalmanFilter | DistributedKF | None = None  # hinf, kf-ukf, sckf: KalmanFilter subclasses
        self.bg = np.zeros(3)
        self.ba = np.zeros(3)
        self.updates = 0
        self.predicted = 0  # outage epochs bridged by a predicted correction
        self.predictor = (predictors.OutagePredictor(PREDICTOR_NETWORK[method], self.cfg.predictor)
                          if method in PREDICTOR_NETWORK else None)
        self._origin: tuple[float, float, float] | None = None  # lat, lon, h of the alignment point
        self._carry: tuple[int, np.ndarray, np.ndarray] | None = None  # last sample: t_ns, omega, f (raw)
        self._gps: list[dict] = []  # epochs not yet reached by the IMU
        self._sigma = np.zeros(9)
        self._static = _Static()
        self._interval = _Static()  # IMU sums since the last GPS epoch
        self._imu_dt = 0.002  # median IMU sample period, s
        self._last_speed = math.inf
        self._last_fix: tuple[float, float, float, float] | None = None  # t_s, lat, lon, h of last good fix
        self._open: Outage | None = None
        self._forced: list[tuple[int, int]] = []
        self._outages: list[Outage] = []

    # -- public ---------------------------------------------------------------------------------

    def process(self, imu: ImuBlock, gps: GpsBlock) -> tuple[Solution, list[Outage]]:
        """Consume the next block; returns the solution rows it produced and the outages that closed."""
        ok = np.isfinite(imu.omega_ib_b).all(axis=1) & np.isfinite(imu.f_b).all(axis=1)
        t_ns = np.asarray(imu.t_ns, np.int64)[ok]
        w, f = np.asarray(imu.omega_ib_b, float)[ok], np.asarray(imu.f_b, float)[ok]
        if self._carry is not None:
            keep = t_ns > self._carry[0]
            t_ns = np.concatenate([[self._carry[0]], t_ns[keep]])
            w = np.concatenate([self._carry[1][None], w[keep]])
            f = np.concatenate([self._carry[2][None], f[keep]])
        if self.t_ref_ns is None and len(t_ns):
            self.t_ref_ns = int(t_ns[0])
            self._forced = [(self.t_ref_ns + int(s * NS), self.t_ref_ns + int((s + n) * NS))
                            for s, n in self.cfg.outages]
            self._outages += [Outage(a, b, "injected") for a, b in self._forced]
        self._gps += _epochs(gps)
        if self.t_ref_ns is None or len(t_ns) == 0:
            return Solution.concat([]), self._take_outages()
        t = (t_ns - self.t_ref_ns) * 1e-9
        if len(t) > 1:
            self._imu_dt = float(np.median(np.diff(t)))
        out: list[Solution] = []
        cursor = 0
        while self._gps and self._gps[0]["t_ns"] <= t_ns[-1]:
            ep = self._gps.pop(0)
            k = int(np.searchsorted(t_ns, ep["t_ns"], side="right")) - 1
            if k < cursor:  # the epoch precedes the samples still to process (IMU gap): skip it
                self._classify(ep)
                continue
            if self.nav is None:
                self._accumulate(w, f, cursor, k)
                cursor = k
                self._pre_init_epoch(ep, t, t_ns, w, k)
            else:
                self._accumulate(w, f, cursor, k)
                out.append(self._advance(t, t_ns, w, f, cursor, k))
                cursor = k
                self._epoch(ep, w[k] - self.bg)
        self._accumulate(w, f, cursor, len(t) - 1)
        if self.nav is not None:
            out.append(self._advance(t, t_ns, w, f, cursor, len(t) - 1))
        self._carry = (int(t_ns[-1]), w[-1].copy(), f[-1].copy())
        return Solution.concat(out), self._take_outages()

    def finish(self) -> list[Outage]:
        """Close an outage still open at the end of the drive; returns the outages not yet returned."""
        if self._open is not None:
            self._open.end_ns = self._carry[0] if self._carry else self._open.start_ns
            self._outages.append(self._open)
            self._open = None
        return self._take_outages()

    # -- epochs ---------------------------------------------------------------------------------

    def _classify(self, ep: dict) -> bool:
        """Whether an epoch's fix is usable; opens and closes the detected outage windows."""
        t = ep["t_ns"]
        good_fix = ep["status"] >= 0 and math.isfinite(ep["lat"]) and math.isfinite(ep["lon"])  # h may be NaN
        low = good_fix and not math.sqrt(max(ep["pos_cov"][0, 0], ep["pos_cov"][1, 1])) <= self.cfg.max_fix_sigma_m
        usable = good_fix and not low
        if not usable and self._open is None:
            self._open = Outage(t, t, "low_quality" if low else "no_fix")
        elif usable and self._open is not None:
            self._open.end_ns = t
            self._outages.append(self._open)
            self._open = None
        forced = any(a <= t < b for a, b in self._forced)
        return usable and not forced

    def _velocity(self, ep: dict) -> np.ndarray:
        """GPS velocity, or the difference of this and the previous good fix when the drive has none."""
        if np.isfinite(ep["v_n"][:2]).all():
            return ep["v_n"]
        ts = (ep["t_ns"] - self.t_ref_ns) * 1e-9
        if self._last_fix is None or not 0.0 < ts - self._last_fix[0] <= 2.0:
            return np.full(3, np.nan)
        t0, lat0, lon0, h0 = self._last_fix
        return kf.enu_offset(ep["lat"], ep["lon"], ep["h"], lat0, lon0, h0) / (ts - t0)

    def _pre_init_epoch(self, ep: dict, t: np.ndarray, t_ns: np.ndarray, w: np.ndarray, k: int) -> None:
        usable = self._classify(ep)
        v = self._velocity(ep) if usable else np.full(3, np.nan)
        speed = float(np.hypot(v[0], v[1])) if np.isfinite(v[:2]).all() else math.inf
        if speed < self.cfg.static_speed_mps and self._last_speed < self.cfg.static_speed_mps:
            self._static.sum_w += self._interval.sum_w
            self._static.sum_f += self._interval.sum_f
            self._static.n += self._interval.n
        self._interval = _Static()
        self._last_speed = speed
        if usable:
            self._last_fix = ((ep["t_ns"] - self.t_ref_ns) * 1e-9, ep["lat"], ep["lon"], ep["h"])
        if usable and math.isfinite(ep["h"]) and math.isfinite(speed) and speed >= self.cfg.align_speed_mps:
            self._initialise(ep, v, float(t[k]), int(t_ns[k]))

    def _accumulate(self, w: np.ndarray, f: np.ndarray, i0: int, i1: int) -> None:
        """Add samples (i0, i1] to the current GPS interval's sums (static detection before alignment)."""
        ws, fs = w[i0 + 1:i1 + 1], f[i0 + 1:i1 + 1]
        self._interval.sum_w += ws.sum(axis=0)
        self._interval.sum_f += fs.sum(axis=0)
        self._interval.sum_ww += np.einsum("ij,ij->j", ws, ws)
        self._interval.sum_ff += np.einsum("ij,ij->j", fs, fs)
        self._interval.n += max(i1 - i0, 0)

    def _initialise(self, ep: dict, v: np.ndarray, t_k: float, t_k_ns: int) -> None:
        c = self.cfg
        heading = math.atan2(v[0], v[1])
        static = self._static.n >= 200
        if static:
            fm = self._static.sum_f / self._static.n
            pitch, roll = math.atan2(fm[1], math.hypot(fm[0], fm[2])), math.atan2(-fm[0], fm[2])
        else:
            pitch = roll = 0.0
        C = earth.euler_to_dcm(heading, pitch, roll)
        if static:
            self.bg = self._static.sum_w / self._static.n - C.T @ earth.omega_ie_n(ep["lat"])
        arm = C @ self.lever
        rm, rn = earth.principal_radii(ep["lat"], ep["h"])
        dt = t_k - (ep["t_ns"] - self.t_ref_ns) * 1e-9
        d_enu = v * dt - arm
        v0 = np.array([v[0], v[1], 0.0])
        self.nav = ins.NavState(t_k, ep["lat"] + d_enu[1] / rm, ep["lon"] + d_enu[0] / (rn * math.cos(ep["lat"])),
                                ep["h"] + d_enu[2], v0, earth.dcm_to_quat(C))
        speed = math.hypot(v[0], v[1])
        sd_level = (c.init_level_sigma_deg if static else 5.0) * _DEG
        sd_head = math.hypot(c.init_heading_sigma_deg * _DEG, math.sqrt(max(ep["vel_cov"][0, 0], 0.01)) / speed)
        sd_bg = (c.init_gyro_bias_sigma_dps if static else 0.1) * _DEG
        pos_var = np.diag(ep["pos_cov"]).copy()
        pos_var[~np.isfinite(pos_var) | (pos_var <= 0)] = 25.0
        P0 = np.diag(np.concatenate([pos_var, np.full(3, c.init_vel_sigma_mps ** 2),
                                     [sd_level ** 2, sd_level ** 2, sd_head ** 2], np.full(3, sd_bg ** 2),
                                     np.full(3, (c.init_accel_bias_sigma_ug * _UG) ** 2)]))
        self._origin = (self.nav.lat, self.nav.lon, self.nav.h)
        distributed = self.method == "dkf" or self.predictor is not None
        if distributed:
            self.filter = DistributedKF(P0, self.q)
        elif self.method == "hinf":
            self.filter = hinf.HInfinityFilter(P0, self.q, c.hinf_gamma, min_ratio=c.hinf_min_ratio)
        elif self.method == "kf-ukf":
            self.filter = ukf.HybridKfUkf(P0, self.q)
        elif self.method in sckf.FILTERS:
            self.filter = sckf.FILTERS[self.method](P0, self.q)
        else:
            self.filter = kf.KalmanFilter(P0, self.q)
        self._sigma = _sigmas(np.diag(P0))
        if self.log is not None:
            self.log.start(t_k_ns, self.filter.covariance)

    def _epoch(self, ep: dict, omega_k: np.ndarray) -> None:
        """GPS epoch at the current sample: update, feed back, reset; in an outage, the predicted correction."""
        usable = self._classify(ep)
        if usable:
            self._last_fix = ((ep["t_ns"] - self.t_ref_ns) * 1e-9, ep["lat"], ep["lon"], ep["h"])
        interval, self._interval = self._interval, _Static()
        if self.method == "ins":
            return
        aid = self._aid(ep, usable, interval)
        if aid is not None:
            self.filter.update_aid(aid)
            self._feedback(self.filter.state)
        if not usable:
            if isinstance(self.filter, ukf.HybridKfUkf):
                self.filter.start_outage()
            if self.predictor is not None:
                self._bridge()
            return
        t_g = (ep["t_ns"] - self.t_ref_ns) * 1e-9
        pos = kf.position_measurement(self.nav, t_g, ep["lat"], ep["lon"], ep["h"], ep["pos_cov"], self.lever)
        vel = kf.velocity_measurement(self.nav, ep["v_n"], ep["vel_cov"], omega_k, self.lever, self.cfg.vel_var_max)
        u = self._predictor_input() if self.predictor is not None else None
        self.filter.update_gps(vel, pos)
        x = self.filter.state
        if self.predictor is not None:
            y = np.concatenate([x[POS], x[VEL]]) if self.method == "dkf-rbfn" else _observation(pos, vel)
            self.predictor.train(t_g, u, y)
        self._feedback(x)
        self.updates += 1

    def _feedback(self, x: np.ndarray) -> None:
        """Closed loop: the estimate x (15,) corrects the INS and the biases; the filter is reset."""
        if self.log is not None:
            self.log.update(x.copy(), self.filter.covariance.copy())
        self.nav = kf.correct_ins(self.nav, x)
        self.bg = self.bg + x[BG]
        self.ba = self.ba + x[BA]
        self.filter.reset()
        self._sigma = _sigmas(np.diag(self.filter.covariance))

    def _aid(self, ep: dict, usable: bool, interval: _Static) -> kf.Measurement | None:
        """The vehicle-motion aid of this epoch: stationary (ZUPT + ZARU) when the vehicle stood still over the
        interval since the last epoch, else the non-holonomic constraint; None when disabled. Needs no GPS: in
        outages too. Before the GPS update, so a predictor learns the GPS correction on top of the aided INS."""
        c = self.cfg
        v = self._velocity(ep) if usable else np.full(3, np.nan)
        slow = (float(np.hypot(v[0], v[1])) < c.static_speed_mps if np.isfinite(v[:2]).all()
                else float(np.linalg.norm(self.nav.v_n)) < c.still_speed_mps)
        still = (slow and interval.n >= 50 and interval.std(interval.sum_f, interval.sum_ff) < c.still_accel_std_mps2
                 and interval.std(interval.sum_w, interval.sum_ww) < c.still_gyro_std_dps * _DEG)
        if c.zupt and still:
            return kf.stationary_measurement(self.nav, interval.sum_w / interval.n - self.bg, interval.n * self._imu_dt,
                                             c.zupt_sigma_mps, c.gyro_noise_dps_rthz * _DEG)
        if c.nhc and not slow:
            return kf.nhc_measurement(self.nav, c.nhc_sigma_mps)
        return None

    def _predictor_input(self) -> np.ndarray:
        """INS position (ENU m from the alignment point) and velocity (ENU m/s), (6,)."""
        r = kf.enu_offset(self.nav.lat, self.nav.lon, self.nav.h, *self._origin)
        return np.concatenate([r, self.nav.v_n])

    def _bridge(self) -> None:
        """Outage epoch: feed the predicted position and velocity correction into the INS."""
        d = np.nan_to_num(self.predictor.predict(self._predictor_input()))  # a channel without a model: none
        if not d.any():
            return
        x = np.zeros(N_STATES)
        x[POS], x[VEL] = d[:3], d[3:]
        self.nav = kf.correct_ins(self.nav, x)
        if self.log is not None:
            self.log.bridge(x)
        self.predicted += 1

    # -- INS and covariance between epochs ------------------------------------------------------------

    def _advance(self, t: np.ndarray, t_ns: np.ndarray, w: np.ndarray, f: np.ndarray, i0: int, i1: int
                 ) -> Solution:
        """INS and covariance from sample i0 (the current state) to sample i1; solution rows in (i0, i1]."""
        if i1 <= i0:
            return Solution.concat([])
        wc, fc = w[i0:i1 + 1] - self.bg, f[i0:i1 + 1] - self.ba
        sol = ins.integrate(self.nav, t[i0:i1 + 1], wc, fc)
        clipped = _clipped(w[i0:i1 + 1, 2], self.cfg.gyro_range_dps * _DEG)
        if clipped.any():  # the yaw gyro saturated in a sharp turn: rebuild its rate, integrate again
            wc[:, 2] = _turn_rate(wc[:, 2], fc, sol, clipped)
            sol = ins.integrate(self.nav, t[i0:i1 + 1], wc, fc)
        self.nav = sol.state(-1)
        # filter cycles: end at the first sample of each cov_step_s slot after i0, and at i1
        tt = sol.t
        slot = np.floor((tt - tt[0]) / self.cfg.cov_step_s).astype(np.int64)
        ends = np.flatnonzero(np.diff(slot) != 0) + 1
        if len(ends) == 0 or ends[-1] != len(tt) - 1:
            ends = np.append(ends, len(tt) - 1)
        starts = np.concatenate([[0], ends[:-1]])
        mid = (starts + ends) // 2
        csum = np.cumsum(np.vstack([np.zeros(3), fc[1:]]), axis=0)
        f_mean = (csum[ends] - csum[starts]) / (ends - starts)[:, None]
        C = earth.quat_to_dcm(sol.q[mid])
        F, G = errmodel.system_matrices(sol.lat[mid], sol.h[mid], sol.v_n[mid], C,
                                        np.einsum("kij,kj->ki", C, f_mean))
        Phi, Q = errmodel.discretise(F, G, self.q, tt[ends] - tt[starts])
        if clipped.any():  # the rebuilt rate scales with the INS forward speed: its error counts too
            fwd = C[0, :, 1]
            sd_v = math.sqrt(max(float(fwd @ self.filter.covariance[VEL, VEL] @ fwd), 0.0))
            rel = sd_v / max(abs(float(fwd @ sol.v_n[0])), 1.0)
            sigma = math.hypot(self.cfg.clip_rate_sigma_dps * _DEG, rel * float(np.abs(wc[clipped, 2]).max()))
            Q = Q + _clip_noise(clipped, tt, starts, ends, C, sigma)
        if isinstance(self.filter, ukf.CycleFilter):  # the nodes of its RK4 through the nonlinear model
            self.filter.queue(ukf.cycles_from_ins(sol.lat, sol.h, sol.v_n, sol.q, starts, mid, ends, f_mean,
                                                  tt[ends] - tt[starts]))
        if self.log is None:
            diag = self.filter.propagate(Phi, Q)
        else:
            diag = self._propagate_logged(Phi, Q, t_ns[i0:i1 + 1][ends])
        # output rows: first sample of each 1/output_hz slot of UTC
        tn = t_ns[i0:i1 + 1]
        slot_ns = NS / self.cfg.output_hz
        bucket = np.floor(tn / slot_ns).astype(np.int64)
        rows = np.flatnonzero(np.diff(bucket) != 0) + 1
        sig = _sigmas(diag)
        cyc = np.searchsorted(ends, rows)
        self._sigma = sig[-1]
        return Solution(tn[rows], sol.lat[rows], sol.lon[rows], sol.h[rows], sol.v_n[rows], sol.q[rows], sig[cyc])

    def _propagate_logged(self, Phi: np.ndarray, Q: np.ndarray, t_end_ns: np.ndarray) -> np.ndarray:
        """``filter.propagate`` one cycle at a time, recording Phi and each predicted P; returns diag(P)."""
        P = np.empty_like(Phi)
        for i in range(len(Phi)):
            self.filter.propagate(Phi[i:i + 1], Q[i:i + 1])
            P[i] = self.filter.covariance
        self.log.cycles(t_end_ns, Phi, P)
        return np.diagonal(P, axis1=1, axis2=2).copy()

    def _take_outages(self) -> list[Outage]:
        out, self._outages = self._outages, []
        return out


_CLIP_CORR_S = 3.0  # the rebuilt rate's error is correlated over a turn: white noise of the same variance


def _clipped(wz: np.ndarray, limit: float) -> np.ndarray:
    """Saturated samples of a gyro channel (n,) rad/s: at the range limit (rad/s) and flat (equal to a
    neighbour: the ADC clips to one value, a live signal with its noise never repeats exactly)."""
    flat = np.zeros(len(wz), bool)
    same = wz[1:] == wz[:-1]
    flat[1:] |= same
    flat[:-1] |= same
    return flat & (np.abs(wz) >= limit * (1.0 - 1e-3))


def _turn_rate(wz: np.ndarray, f_b: np.ndarray, sol: ins.NavSolution, clipped: np.ndarray) -> np.ndarray:
    """The yaw rate (rad/s, body up) with its clipped samples rebuilt from the car's turn kinematics: a car
    moving along its forward axis turns at omega_z = -a_x / v_y (a_b = f_b + C_nb g_n, the lateral
    acceleration, v_y the forward speed), taken from the INS of the clipped pass (its roll, pitch and speed
    are unaffected). Only magnitudes above the clipped value and of the same sign are taken."""
    C = earth.quat_to_dcm(sol.q)
    a_b = f_b + np.einsum("nji,nj->ni", C, earth.gravity_n(sol.lat, sol.h))
    v_fwd = np.einsum("nj,nj->n", C[:, :, 1], sol.v_n)
    with np.errstate(divide="ignore", invalid="ignore"):
        rate = -a_b[:, 0] / v_fwd
    ok = clipped & (np.abs(v_fwd) > 1.0) & (np.sign(rate) == np.sign(wz))
    return np.where(ok, np.sign(wz) * np.maximum(np.abs(wz), np.abs(rate)), wz)


def _clip_noise(clipped: np.ndarray, t: np.ndarray, starts: np.ndarray, ends: np.ndarray, C: np.ndarray,
                sigma: float) -> np.ndarray:
    """Process noise (m, 15, 15) of the rebuilt yaw rates over the filter cycles (starts, ends] of samples at
    times t: a rate error of sigma rad/s about the body up axis (C (m, 3, 3) C_bn at the cycles), correlated
    over ``_CLIP_CORR_S``, for the clipped time of each cycle."""
    dt = np.diff(t, prepend=t[0]) * clipped
    c = np.cumsum(dt)
    secs = c[ends] - c[starts]
    u = C[:, :, 2]
    out = np.zeros((len(ends), N_STATES, N_STATES))
    out[:, ATT, ATT] = (sigma * sigma * _CLIP_CORR_S * secs)[:, None, None] * np.einsum("mi,mj->mij", u, u)
    return out


def _sigmas(diag: np.ndarray) -> np.ndarray:
    return np.sqrt(np.maximum(np.asarray(diag)[..., :9], 0.0))


def _observation(pos: kf.Measurement, vel: kf.Measurement | None) -> np.ndarray:
    """z = INS - GPS as (6,): position E, N, U (m), velocity E, N, U (m/s); NaN for a component not measured."""
    out = np.full(6, np.nan)
    for m, cols, at in ((pos, POS, 0), (vel, VEL, 3)):
        if m is not None and len(m[0]):
            out[at + np.argmax(np.abs(m[1][:, cols]), axis=1)] = m[0]
    return out


def _epochs(g: GpsBlock) -> list[dict]:
    """GPS epochs as dicts (1 Hz: a Python object per epoch is fine), lat/lon in rad."""
    return [dict(t_ns=int(g.t_ns[i]), lat=math.radians(float(g.lat_deg[i])), lon=math.radians(float(g.lon_deg[i])),
                 h=float(g.h[i]), pos_cov=g.pos_cov[i], status=int(g.status[i]), v_n=g.v_n[i], vel_cov=g.vel_cov[i])
            for i in range(len(g.t_ns))]
