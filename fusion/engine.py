"""The fusion loop every method runs in: blocks of IMU samples and GPS epochs in, a solution out.

Streaming: :meth:`Engine.process` takes consecutive blocks (any length) and keeps only the navigation
state, the filter and the IMU samples of the covariance cycle still open at the block's end (under
``cov_step_s``; their rows come with the next block, or :meth:`Engine.finish`) between calls, so memory does
not grow with the drive and the solution does not depend on where the blocks end (fuse, replay and the live
view give the same rows).

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

The pieces the loop calls, one module each:

- alignment (``fusion.align``): static levelling, gyro bias and the GPS-course heading before the filter starts;
- vehicle aids (``fusion.aids``: NHC, ZUPT + ZARU at every GPS epoch time, in outages too; not for ``ins``),
  through the filter's ``update_aid`` and fed back like a GPS update;
- outages (``fusion.outages``): usable epochs, forced and detected windows, and the predictors' bridging
  (``rbfn``, ``tdln``, ``dkf-rbfn``) at the unusable or withheld epochs;
- the clipped yaw gyro (``fusion.clipgyro``), rebuilt from the turn kinematics before the segment is integrated
  again;
- the filter (:func:`make_filter`): every method's filter has the interface of ``fusion.kf.KalmanFilter``
  (``propagate``, ``update_gps``, ``update_aid``, ``start_outage``, ``reset``, ``state``, ``covariance``);
- output (``fusion.output``): the solution rows.

A fix without height (NaN altitude: the GGA of that second was lost) updates the horizontal position only.

``hinf``, ``kf-ukf``, ``sckf`` and ``ssr-sckf`` run the ``kf`` path with another filter object:
``fusion.hinf.HInfinityFilter`` (``hinf_gamma``), ``fusion.ukf.HybridKfUkf`` and the square-root cubature
filters of ``fusion.sckf``. The last three are ``fusion.ukf.CycleFilter`` s: they are given the navigation
solution at the start, middle and end of each covariance cycle (the nodes of their RK4 through the nonlinear
error model: the hybrid filter's in outages, the cubature filters' at every cycle). Every filter is told of an
outage at its unusable epochs (``start_outage``; only the hybrid KF/UKF acts on it).

Smoothing: given a ``log`` (``fusion.smoother.SmootherLog``) the engine records, per covariance cycle,
Phi and the predicted covariance, and at each update the correction fed back and the covariance after
it (the covariance is then propagated one cycle per call, to capture each P).

"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from fieldlog.fusion import aids, align, clipgyro, consider, earth, errmodel, gpserror, hinf, ins, kf, output, sckf, ukf
from fieldlog.fusion.config import GPS_ERROR_MODELS, METHODS, FusionConfig
from fieldlog.fusion.dkf import DistributedKF
from fieldlog.fusion.errmodel import BA, BG, N_STATES, POS, VEL
from fieldlog.fusion.outages import PREDICTOR_NETWORK, OutageTracker, PredictorBridge, Silence
from fieldlog.fusion.types import Epoch, GpsBlock, ImuBlock, Outage, Solution

if TYPE_CHECKING:
    from fieldlog.fusion.smoother import SmootherLog

_DEG = math.pi / 180.0


class Engine:
    """One fusion run (a method of ``METHODS``) over a stream of blocks."""

    def __init__(self, method: str, config: FusionConfig | None = None, log: SmootherLog | None = None) -> None:
        """log: a ``fusion.smoother.SmootherLog`` to fill for the backward pass, or None."""
        if method not in METHODS:
            raise ValueError(f"unknown method {method!r}; one of {METHODS}")
        self.method = method
        self.log = log
        self.cfg = config or FusionConfig()
        if self.cfg.gps.gps_error_model not in GPS_ERROR_MODELS:
            raise ValueError(f"gps_error_model must be one of {GPS_ERROR_MODELS}, got {self.cfg.gps.gps_error_model!r}")
        if self.cfg.gps.gps_error_model == "gm-states" and (method != "kf" or log is not None):
            self.cfg = self.cfg.replace(gps_error_model="consider")  # the states are kf's, without smoothing
        self.lever = self.cfg.gps.lever_rfu()
        self.q = self.cfg.sensor.noise_psd()
        self.t_ref_ns: int | None = None
        self.nav: ins.NavState | None = None
        self.filter: kf.KalmanFilter | DistributedKF | None = None  # hinf, kf-ukf, sckf: KalmanFilter subclasses
        self.bg = np.zeros(3)
        self.ba = np.zeros(3)
        self.updates = 0
        self.predicted = 0  # outage epochs bridged by a predicted correction
        self.hybrid_parts: list[tuple[float, np.ndarray, np.ndarray]] = []  # dkf-rbfn outage epochs: t (s), the
        # fused state prediction and the change the predicted innovations made, position and velocity (6,) each
        self.bridge = (PredictorBridge(method, self.cfg.predictor) if method in PREDICTOR_NETWORK else None)
        self.alignment = align.Alignment(self.cfg)
        self.outages = OutageTracker(self.cfg.gps.max_fix_sigma_m)
        self.silence = Silence()
        self._gps_var = np.zeros(3)  # variance (m^2, E N U) of the correlated GPS error the filter cannot see
        self._gps_var_kf2 = np.zeros(3)  # the same for the distributed filter's KF_II (GPS position) alone
        # samples not yet integrated (t_ns, omega, f; raw): the block's tail after its last covariance-cycle start
        self._carry: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._anchor: float | None = None  # s from t_ref_ns: the sample the covariance cycles count from
        self._gps: list[Epoch] = []  # epochs not yet reached by the IMU
        self._interval = align.ImuSums()  # IMU sums since the last GPS epoch
        self._imu_dt = 0.002  # median IMU sample period, s
        self._last_fix: tuple[float, float, float, float] | None = None  # t_s, lat, lon, h of last good fix
        self._speed = align.GpsSpeed(self.cfg)  # the GPS speed of the still detection after the alignment
        self.stills: list[int] = []  # epoch times (UTC ns) with a stationary update
        self._stop = align.StillRun(self.cfg)
        self._check: align.HeadingCheck | None = None
        self.consider: consider.GyroConsider | None = None

    # -- public ---------------------------------------------------------------------------------

    def process(self, imu: ImuBlock, gps: GpsBlock) -> tuple[Solution, list[Outage]]:
        """Consume the next block; returns the solution rows it produced and the outages that closed."""
        ok = np.isfinite(imu.omega_ib_b).all(axis=1) & np.isfinite(imu.f_b).all(axis=1)
        t_ns = np.asarray(imu.t_ns, np.int64)[ok]
        w, f = np.asarray(imu.omega_ib_b, float)[ok], np.asarray(imu.f_b, float)[ok]
        if self._carry is not None:
            keep = t_ns > self._carry[0][-1]
            t_ns, w, f = (np.concatenate([c, x[keep]]) for c, x in zip(self._carry, (t_ns, w, f)))
        if self.t_ref_ns is None and len(t_ns):
            self.t_ref_ns = int(t_ns[0])
            self.outages.force(self.t_ref_ns, self.cfg.gps.outages)
            if self.cfg.init.init_position_llh:
                self._start(self.alignment.configured(), 0.0, self.t_ref_ns)
        self.silence.add(self._gps, gps.epochs(), int(t_ns[-1]) if len(t_ns) else None)
        if self.t_ref_ns is None or len(t_ns) == 0:
            return Solution.concat([]), self.outages.take()
        t = (t_ns - self.t_ref_ns) * 1e-9
        if len(t) > 1:
            self._imu_dt = float(np.median(np.diff(t)))
        out: list[Solution] = []
        cursor = 0
        while self._gps and self._gps[0].t_ns <= t_ns[-1]:
            ep = self._gps.pop(0)
            k = int(np.searchsorted(t_ns, ep.t_ns, side="right")) - 1
            if k < cursor:  # the epoch precedes the samples still to process (IMU gap): skip it
                self.outages.classify(ep)
                continue
            self._interval.add(w, f, cursor, k)
            if self.nav is None:
                cursor = k
                self._pre_init_epoch(ep, float(t[k]), int(t_ns[k]))
            else:
                out.append(self._advance(t, t_ns, w, f, cursor, k))
                cursor = k
                self._epoch(ep, w[k] - self.bg)
                self._anchor = float(t[k])
        # the tail after the last cycle start waits for the next block, so blocks never cut a cycle short
        held = self._cycle_start(t, cursor, len(t) - 1) if self.nav is not None else len(t) - 1
        self._interval.add(w, f, cursor, held)
        if self.nav is not None:
            out.append(self._advance(t, t_ns, w, f, cursor, held))
        self._carry = (t_ns[held:].copy(), w[held:].copy(), f[held:].copy())
        return Solution.concat(out), self.outages.take()

    def finish(self) -> tuple[Solution, list[Outage]]:
        """End of the drive: the rows of the samples held back for their covariance cycle (under ``cov_step_s``),
        and the outages not yet returned (one still open is closed)."""
        sol = Solution.concat([])
        if self._carry is not None and self.nav is not None:
            t_ns, w, f = self._carry
            sol = self._advance((t_ns - self.t_ref_ns) * 1e-9, t_ns, w, f, 0, len(t_ns) - 1)
            self._carry = (t_ns[-1:], w[-1:], f[-1:])
        self.outages.finish(int(self._carry[0][-1]) if self._carry else None)
        return sol, self.outages.take()

    # -- epochs ---------------------------------------------------------------------------------

    def _usable(self, ep: Epoch) -> bool:
        """Classify the epoch (``OutageTracker``); a usable fix becomes the last good fix."""
        usable = self.outages.classify(ep)
        if usable:
            self._last_fix = ((ep.t_ns - self.t_ref_ns) * 1e-9, ep.lat, ep.lon, ep.h)
        return usable

    def _velocity(self, ep: Epoch) -> np.ndarray:
        """GPS velocity, or the difference of this and the previous good fix when the drive has none."""
        if np.isfinite(ep.v_n[:2]).all():
            return ep.v_n
        ts = (ep.t_ns - self.t_ref_ns) * 1e-9
        if self._last_fix is None or not 0.0 < ts - self._last_fix[0] <= 2.0:
            return np.full(3, np.nan)
        t0, lat0, lon0, h0 = self._last_fix
        return kf.enu_offset(ep.lat, ep.lon, ep.h, lat0, lon0, h0) / (ts - t0)

    def _pre_init_epoch(self, ep: Epoch, t_k: float, t_k_ns: int) -> None:
        """A GPS epoch before the alignment (``fusion.align``); at the alignment epoch, the filter starts."""
        usable = self.outages.classify(ep)
        v = self._velocity(ep) if usable else np.full(3, np.nan)
        if usable:
            self._last_fix = ((ep.t_ns - self.t_ref_ns) * 1e-9, ep.lat, ep.lon, ep.h)
        interval, self._interval = self._interval, align.ImuSums()
        a = self.alignment.epoch(ep, usable, v, interval, t_k, self.t_ref_ns)
        if a is not None:
            self._start(a, t_k, t_k_ns)

    def _start(self, a: align.Aligned, t_k: float, t_k_ns: int) -> None:
        """Start the INS and the filter from the initial state a at time t_k (s from t_ref_ns), t_k_ns UTC."""
        self.nav, self.bg, self._anchor = a.nav, a.bg, t_k
        self.filter = make_filter(self.method, a.P0, self.q, self.cfg)
        if self.cfg.sensor.gyro_scale_factor_ppm > 0.0 or self.cfg.sensor.gyro_misalignment_mrad > 0.0:
            self.consider = consider.GyroConsider(self.cfg.sensor.gyro_scale_factor_ppm * 1e-6,
                                                  self.cfg.sensor.gyro_misalignment_mrad * 1e-3)
            if self.log is not None:
                self.log.var_c = self.consider.var_c
        self._check = align.HeadingCheck(self.cfg, t_k) if self.log is None else None
        if self.bridge is not None:
            self.bridge.origin = (self.nav.lat, self.nav.lon, self.nav.h)
        if self.log is not None:
            self.log.start(t_k_ns, self.filter.covariance)

    def _epoch(self, ep: Epoch, omega_k: np.ndarray) -> None:
        """GPS epoch at the current sample: update, feed back, reset; in an outage, the predicted correction."""
        usable = self._usable(ep)
        interval, self._interval = self._interval, align.ImuSums()
        if self.method == "ins":
            return
        v = self._velocity(ep) if usable else np.full(3, np.nan)
        v_gps = ep.v_n if usable else np.full(3, np.nan)
        speed = self._speed.add((ep.t_ns - self.t_ref_ns) * 1e-9, v_gps, ep)
        aid = aids.vehicle_aid(self.cfg, self.nav, v_gps if np.isfinite(v_gps[:2]).all() else v, speed, interval,
                               self._stop, self.bg, self.ba, self.filter.covariance, self._imu_dt)
        if aid is not None and len(aid[0]) == 6:
            self.stills.append(ep.t_ns)
        if aid is not None:
            self._considered(aid, self.filter.update_aid, aid)
            self._feedback(self.filter.state)
        if not usable:
            self.filter.start_outage()
            if self.bridge is not None:
                self._bridge()
            elif self._distributed and self.filter.state.any():
                self._feedback(self.filter.state)  # the fused state prediction X(n|n-1) of the local filters
            return
        t_g = (ep.t_ns - self.t_ref_ns) * 1e-9
        pos = kf.position_measurement(self.nav, t_g, ep.lat, ep.lon, ep.h, ep.pos_cov, self.lever)
        vel = kf.velocity_measurement(self.nav, ep.v_n, ep.vel_cov, omega_k, self.lever, self.cfg.gps.vel_var_max)
        u = self.bridge.input(self.nav) if self.bridge is not None else None
        if (self._check is not None and vel is not None
                and self._check.far_off(t_g, *vel, self.filter.state, self.filter.covariance) and self._realign(ep)):
            pos = kf.position_measurement(self.nav, t_g, ep.lat, ep.lon, ep.h, ep.pos_cov, self.lever)
            vel = kf.velocity_measurement(self.nav, ep.v_n, ep.vel_cov, omega_k, self.lever,
                                          self.cfg.gps.vel_var_max)
        self._considered(kf.stack(vel, pos), self.filter.update_gps, vel, pos)
        period = self.silence.period_ns * 1e-9 if self.silence.period_ns else 1.0
        if not isinstance(self.filter, gpserror.GpsErrorKF):  # the states carry it: nothing to add
            self._gps_var = output.correlated_variance(np.diag(ep.pos_cov), np.diag(self.filter.covariance)[POS],
                                                       period, self.cfg.gps.gps_error_tau_s)
        if self._distributed:  # KF_II's local solution averages the same fixes (KF_I sees no position)
            self._gps_var_kf2 = output.correlated_variance(np.diag(ep.pos_cov), np.diag(self.filter.kf_pos.P)[POS],
                                                           period, self.cfg.gps.gps_error_tau_s)
        if self.log is not None:
            self.log.gps_var.append((ep.t_ns, self._gps_var.copy()))
        x = self.filter.state
        if self.bridge is not None:
            self.bridge.train(t_g, u, self.filter.innovations, pos, vel)
        self._feedback(x)
        self.updates += 1

    def _considered(self, m: kf.Measurement | None, update, *args) -> None:
        """``update(*args)``, the filter's update with the measurement m (stacked), and the consider sensitivity's."""
        if self.consider is not None and m is not None:
            self.consider.update(consider.gain(self.filter.covariance, m[1], m[2]), m[1])
            if self.log is not None:
                self.log.sensitivity_update(self.consider.S)
        update(*args)

    def _realign(self, ep: Epoch) -> bool:
        """The heading is far off its sigma (``fusion.align.HeadingCheck``): take it again from the GPS course and
        restart the filter with the covariance so far, the heading's and the gyro bias's reopened. False while
        the vehicle is too slow for the course."""
        r = self._check.realign(self.nav, ep, self.filter.covariance)
        if r is None:
            return False
        self.nav, P = r
        self.filter = make_filter(self.method, P, self.q, self.cfg)
        self.alignment.note += "; re-aligned from the GPS course (chi-square test on the GPS velocity innovations)"
        return True

    def _feedback(self, x: np.ndarray) -> None:
        """Closed loop: the estimate x (15,) corrects the INS and the biases; the filter is reset."""
        if self.log is not None:
            self.log.update(x.copy(), self.filter.covariance.copy())
        self.nav = kf.correct_ins(self.nav, x)
        self.bg = self.bg + x[BG]
        self.ba = self.ba + x[BA]
        self.filter.reset()

    def _bridge(self) -> None:
        """Outage epoch of a predictor method. Hybrid (eq. 7): the local filters' state prediction X_i(n|n-1) plus
        the predicted innovation components, fused by eqs. 3-4 and fed back. Predictor alone: the predicted
        correction into the INS, the local estimates shifted by it (a known input, not an estimate)."""
        d = self.bridge.prediction(self.nav)
        if self.bridge.hybrid:
            x_pred = self.filter.state.copy()
            if d is not None:
                dx_vel, dx_pos = np.zeros(N_STATES), np.zeros(N_STATES)
                dx_vel[VEL], dx_pos[POS] = d[3:], d[:3]
                self.filter.predicted_update(dx_vel, dx_pos)
                self.predicted += 1
            self.hybrid_parts.append((self.nav.t, x_pred[:6], self.filter.state[:6] - x_pred[:6]))
            if self.filter.state.any():
                self._feedback(self.filter.state)
            return
        if d is None:
            return
        x = self.bridge.as_state(d)
        self.nav = kf.correct_ins(self.nav, x)
        self.filter.shift(x)
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
        clip = clipgyro.clipped(w[i0:i1 + 1, 2], self.cfg.sensor.gyro_range_dps * _DEG)
        if clip.any():  # the yaw gyro saturated in a sharp turn: rebuild its rate, integrate again
            wc[:, 2] = clipgyro.turn_rate(wc[:, 2], fc, sol, clip)
            sol = ins.integrate(self.nav, t[i0:i1 + 1], wc, fc)
        self.nav = sol.state(-1)
        # filter cycles: end at the first sample of each cov_step_s slot after i0, and at i1
        tt = sol.t
        ends = self._slot_starts(tt)
        if len(ends) == 0 or ends[-1] != len(tt) - 1:
            ends = np.append(ends, len(tt) - 1)
        starts = np.concatenate([[0], ends[:-1]])
        mid = (starts + ends) // 2
        csum = np.cumsum(np.vstack([np.zeros(3), fc[1:]]), axis=0)
        f_mean = (csum[ends] - csum[starts]) / (ends - starts)[:, None]
        wsum = np.cumsum(np.vstack([np.zeros(3), wc[1:]]), axis=0)
        w_mean = (wsum[ends] - wsum[starts]) / (ends - starts)[:, None]
        C = earth.quat_to_dcm(sol.q[mid])
        F, G = errmodel.system_matrices(sol.lat[mid], sol.h[mid], sol.v_n[mid], C,
                                        np.einsum("kij,kj->ki", C, f_mean))
        Phi, Q = errmodel.discretise(F, G, self.q, tt[ends] - tt[starts])
        if clip.any():  # the rebuilt rate scales with the INS forward speed: its error counts too
            fwd = C[0, :, 1]
            sd_v = math.sqrt(max(float(fwd @ self.filter.covariance[VEL, VEL] @ fwd), 0.0))
            rel = sd_v / max(abs(float(fwd @ sol.v_n[0])), 1.0)
            sigma = math.hypot(self.cfg.sensor.clip_rate_sigma_dps * _DEG, rel * float(np.abs(wc[clip, 2]).max()))
            Q = Q + clipgyro.clip_noise(clip, tt, starts, ends, C, sigma)
        if isinstance(self.filter, gpserror.GpsErrorKF):
            self.filter.cycles(tt[ends] - tt[starts])
        if isinstance(self.filter, ukf.CycleFilter):  # the nodes of its RK4 through the nonlinear model
            self.filter.queue(ukf.cycles_from_ins(sol.lat, sol.h, sol.v_n, sol.q, starts, mid, ends, f_mean,
                                                  tt[ends] - tt[starts]))
        if self.log is None:
            diag = self.filter.propagate(Phi, Q)
            local = (self.filter.local_states, self.filter.local_diag) if self._distributed else None
        else:
            diag, local = self._propagate_logged(Phi, Q, t_ns[i0:i1 + 1][ends])
        if self.consider is not None:
            diag = diag.copy()
            S = self.consider.propagate(Phi, consider.gyro_sensitivity(C, w_mean, tt[ends] - tt[starts]))
            diag[:, BA] += self.consider.variance(S)[:, BA]
            if self.log is not None:
                self.log.sensitivity(S)
        if local is not None:
            d = local[1].copy()
            d[:, 1, POS] += self._gps_var_kf2
            local = (local[0], d)
        return output.rows(sol, t_ns[i0:i1 + 1], self.cfg.filter.output_hz, ends, diag, np.concatenate([self.bg, self.ba]),
                           self._gps_var, local)

    def _slot_starts(self, t: np.ndarray) -> np.ndarray:
        """Indexes into t (s) of the samples that start a ``cov_step_s`` slot counted from the last GPS epoch (the
        anchor; t[0] before the first), after t[0]."""
        anchor = t[0] if self._anchor is None else self._anchor
        slot = np.floor((t - anchor) / self.cfg.filter.cov_step_s).astype(np.int64)
        return np.flatnonzero(np.diff(slot) != 0) + 1

    def _cycle_start(self, t: np.ndarray, i0: int, i1: int) -> int:
        """The last sample in [i0, i1] that starts a covariance cycle (i0 if none after it)."""
        s = self._slot_starts(t[i0:i1 + 1])
        return i0 + int(s[-1]) if len(s) else i0

    def _propagate_logged(self, Phi: np.ndarray, Q: np.ndarray, t_end_ns: np.ndarray
                          ) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray] | None]:
        """``filter.propagate`` one cycle at a time, recording Phi and each predicted P; returns diag(P) and, for
        the distributed filter, the local states and variances after each cycle."""
        P = np.empty_like(Phi)
        local = np.empty((2, len(Phi), 2, N_STATES))
        for i in range(len(Phi)):
            self.filter.propagate(Phi[i:i + 1], Q[i:i + 1])
            P[i] = self.filter.covariance
            if self._distributed:
                local[:, i] = self.filter.local_states[-1], self.filter.local_diag[-1]
        self.log.cycles(t_end_ns, Phi, P)
        return np.diagonal(P, axis1=1, axis2=2).copy(), (tuple(local) if self._distributed else None)

    @property
    def _distributed(self) -> bool:
        return isinstance(self.filter, DistributedKF)


def make_filter(method: str, P0: np.ndarray, q: np.ndarray, cfg: FusionConfig) -> kf.KalmanFilter | DistributedKF:
    """The filter object of a method, started at P0 (15, 15) with noise PSD q (12, 12)."""
    if method == "dkf" or method in PREDICTOR_NETWORK:
        return DistributedKF(P0, q, cfg.filter.dkf_fusion)
    if method == "hinf":
        return hinf.HInfinityFilter(P0, q, cfg.filter.hinf_gamma, min_ratio=cfg.filter.hinf_min_ratio)
    if method == "kf-ukf":
        return ukf.HybridKfUkf(P0, q)
    if method in sckf.FILTERS:
        return sckf.FILTERS[method](P0, q)
    if cfg.gps.gps_error_model == "gm-states":
        return gpserror.GpsErrorKF(P0, q, cfg.gps.gps_error_tau_s, cfg.gps.gps_error_white_share)
    return kf.KalmanFilter(P0, q)
