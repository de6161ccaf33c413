"""The fusion loop every method runs in: blocks of IMU samples and GPS epochs in, a solution out.

Streaming: :meth:`Engine.process` takes consecutive blocks (any length) and keeps only the navigation state, the
filter and the samples of the covariance cycle still open (their rows come with the next block, or
:meth:`Engine.finish`): memory does not grow with the drive, and the rows do not depend on where blocks end (but for
the rounding of sums that a block end splits).

Per block: the INS (``fusion.ins.integrate``) runs over the bias-corrected samples up to each GPS epoch, the yaw
rate rebuilt where the gyro clipped (``fusion.clipgyro``); the error covariance is propagated in filter cycles of
``cov_step_s`` (a cycle also ends at every epoch), their Phi and Q built in one vectorised call
(``fusion.errmodel``). Before the alignment (``fusion.align``) the epochs go to the alignment; after it, at each
epoch (``fusion.outages`` classifies it, a GPS silence gives no-fix epochs):

1. each vehicle aid of the method's measurements (``fusion.measurements``, stage "aid") that gives (z, H, R) is an
   update of its own, fed back (closed loop: the estimate corrects the INS and the biases, the filter resets);
2. at an epoch without a usable fix the filter is told of the outage; a predictor method bridges it
   (``fusion.outages.PredictorBridge``), a filter that ``feeds_prediction`` has its state prediction fed back;
3. at a usable fix the fix's measurements (stage "fix") are one update, after the heading check
   (``fusion.align.HeadingCheck``, which may re-align), then fed back.

The filter (the method's factory, ``fusion.methods``) gets what it declares it needs (``fusion.kf.KalmanFilter``) and routes the
observations by kind; the listeners (``fusion.listeners``) are called at each cycle, update, fix and feedback;
the rows get their status (``fusion.output.StatusBook``). The loop names no sensor and no filter type.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from fieldlog.fusion import (adaptive, align, clipgyro, errmodel, ins, kernels, kf, listeners, measurements, methods,
                            output, still, ukf)
from fieldlog.fusion.config import GPS_ERROR_MODELS, FusionConfig
from fieldlog.fusion.errmodel import BA, BG, N_STATES, POS, VEL
from fieldlog.fusion.outages import OutageTracker, PredictorBridge, Silence
from fieldlog.fusion.types import Epoch, GpsBlock, ImuBlock, OdomBlock, Outage, Solution

if TYPE_CHECKING:
    from fieldlog.fusion.smoother import SmootherLog

_DEG = math.pi / 180.0


class Engine:
    """One fusion run (a method of ``fusion.methods``) over a stream of blocks. ``measurements``: the method's;
    ``updates``: fixes used; ``predicted``: outage epochs bridged; ``hybrid_parts`` (``dkf-rbfn``): per outage
    epoch t (s), the fused state prediction and the predicted innovations' change, position and velocity (6,)."""

    def __init__(self, method: str, config: FusionConfig | None = None, log: SmootherLog | None = None,
                 make_predictor: Callable[..., Any] | None = None) -> None:
        """log: a ``fusion.smoother.SmootherLog`` to fill for the backward pass, or None; make_predictor: the
        outage predictor's factory (``fusion.outages.PredictorBridge``'s ``make``), None: one in this process."""
        self.spec = methods.get(method)
        self.method, self.log = method, log
        self.cfg = config or FusionConfig()
        if self.cfg.gps.gps_error_model not in GPS_ERROR_MODELS:
            raise ValueError(f"gps_error_model must be one of {GPS_ERROR_MODELS}, got {self.cfg.gps.gps_error_model!r}")
        if self.cfg.gps.gps_error_model == "gm-states" and (not self.spec.gps_error_states or log is not None):
            self.cfg = self.cfg.replace(gps_error_model="consider")  # the states are the KF's, without smoothing
        self.q = self.cfg.sensor.noise_psd()
        sc = self.cfg.sensor
        self.adapt = (adaptive.Adaptation(self.q, sc.gyro_noise_dps_rthz, sc.accel_noise_ug_rthz)
                      if sc.adapt_noise else None)  # noise from the drive (fusion.adaptive)
        self.measurements = self.spec.measurements(self.cfg)
        self.gps_errors = listeners.GpsErrorBook(self.cfg.gps.gps_error_tau_s, log)
        self.listeners: list[listeners.Listener] = ([listeners.SmootherRecorder(log)] if log is not None else []) + [
            self.gps_errors]
        self.t_ref_ns: int | None = None
        self.nav: ins.NavState | None = None
        self.filter = None  # the method's filter, from the alignment on
        self.bg, self.ba = np.zeros(3), np.zeros(3)
        self.updates = self.predicted = 0
        self.hybrid_parts: list[tuple[float, np.ndarray, np.ndarray]] = []
        self.bridge = (PredictorBridge(self.spec.bridge, self.cfg.predictor, make_predictor)
                       if self.spec.bridge is not None and not self.spec.learns_speed(self.cfg) else None)
        self._imu_readers = [p for p in self._parts() if hasattr(p, "feed_imu")]  # measurements of raw samples
        self.alignment = align.Alignment(self.cfg)
        self.outages, self.silence = OutageTracker(self.cfg.gps.max_fix_sigma_m), Silence()
        # samples not yet integrated (t_ns, omega, f; raw): the block's tail after its last covariance-cycle start
        self._carry: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._anchor: float | None = None  # s from t_ref_ns: the sample the covariance cycles count from
        self._gps: list[Epoch] = []  # epochs not yet reached by the IMU
        self._interval = still.ImuSums()  # IMU sums since the last GPS epoch
        self._period = ins.SamplePeriod()  # the IMU's sample period
        self._imu_late_ns = int(round(self.cfg.sensor.imu_time_offset_s * 1e9))  # taken off every IMU stamp
        self._check: align.HeadingCheck | None = None
        self._history = any(x.records_history for x in self.listeners)
        self._steps = errmodel.BiasSteps.of(self.cfg.sensor)  # scale factors as bias steps, or None
        self.status = output.StatusBook(self.cfg.filter)  # the rows' status, and before the alignment its own

    def used(self, name: str, times: str = "times") -> tuple[int, ...]:
        """Epochs (UTC ns) of the measurement class ``name``'s list ``times`` (default: those it updated at).

        Parameters
        ----------
        name : str
            The class name of a measurement of the method's (those inside a ``FirstOf`` count), e.g. "Stationary".
        times : str
            The name of that measurement's list of epochs, e.g. "zaru_skipped".

        Returns
        -------
        tuple of int
            The epochs, UTC ns, in the order recorded; empty when the method has no such measurement.
        """
        return tuple(t for p in self._parts() if p.__class__.__name__ == name for t in getattr(p, times))

    def _parts(self) -> list[measurements.MeasurementModel]:
        """The measurements, those inside a ``FirstOf`` one by one."""
        return [p for m in self.measurements for p in getattr(m, "parts", (m,))]

    def process(self, imu: ImuBlock, gps: GpsBlock, odom: OdomBlock | None = None) -> tuple[Solution, list[Outage]]:
        """Consume the next block (``odom``: wheel speeds, for measurements that ``feed``): its rows, closed outages.
        The IMU's stamps are taken on the GPS's time: less ``[fusion] imu_time_offset_s``.

        Parameters
        ----------
        imu : ImuBlock
            The next IMU samples: stamps UTC ns, rate rad/s, specific force m/s^2, body RFU; rows with a non-finite
            value are dropped.
        gps : GpsBlock
            The next GPS epochs (UTC ns, ENU covariances and velocities).
        odom : OdomBlock or None
            The next wheel-speed rows (UTC ns, m/s); None: none.

        Returns
        -------
        (Solution, list of Outage)
            The rows up to the last covariance-cycle start in this block (the tail waits for the next block or
            :meth:`finish`; before the alignment no rows, only their status), and the outage windows closed since
            the last call.
        """
        if odom is not None and len(odom.t_ns):
            for p in self._parts():
                if hasattr(p, "feed"):
                    p.feed(odom)
        w, f = np.ascontiguousarray(imu.omega_ib_b, float), np.ascontiguousarray(imu.f_b, float)
        t_ns = np.asarray(imu.t_ns, np.int64) - self._imu_late_ns  # on the GPS's time
        if not (np.isfinite(w).all() and np.isfinite(f).all()):
            # finite rows, tested a column at a time (numpy's all() over rows of three elements is slow)
            ok = np.logical_and.reduce([np.isfinite(a[:, i]) for a in (w, f) for i in range(3)])
            t_ns, w, f = t_ns[ok], w[ok], f[ok]
        carried = len(self._carry[0]) if self._carry is not None else 0  # the last block's tail, held
        if self._carry is not None:
            keep = t_ns > self._carry[0][-1]
            rows = slice(None) if keep.all() else keep
            t_ns, w, f = (np.concatenate([c, x[rows]]) for c, x in zip(self._carry, (t_ns, w, f)))
        if self.t_ref_ns is None and len(t_ns):
            self.t_ref_ns = int(t_ns[0])
            self.outages.force(self.t_ref_ns, self.cfg.gps.outages)
            if self.cfg.init.init_position_llh:
                self._start(self.alignment.configured(), 0.0, self.t_ref_ns)
        self.silence.add(self._gps, gps.epochs(), int(t_ns[-1]) if len(t_ns) else None)
        if self.t_ref_ns is None or len(t_ns) == 0:
            return Solution.concat([]), self.outages.take()
        t = (t_ns - self.t_ref_ns) * 1e-9
        self._period.add(t, carried)
        aligning: list[Solution] = []  # status rows before the alignment, then the INS's segments
        segments: list[output.Segment | None] = []
        cursor = 0
        while self._gps and self._gps[0].t_ns <= t_ns[-1]:
            ep = self._gps.pop(0)
            k = int(np.searchsorted(t_ns, ep.t_ns, side="right")) - 1
            if k < cursor:  # the epoch precedes the samples still to process (IMU gap): skip it
                self.outages.classify(ep)
                continue
            self._add_interval(w, f, cursor, k)
            if self.nav is None:
                aligning.append(self.status.aligning(t_ns[cursor:k + 1]))
                cursor = k
                self._pre_init_epoch(ep, float(t[k]), int(t_ns[k]))
            else:
                segments.append(self._advance(t, t_ns, w, f, cursor, k))
                cursor = k
                self._epoch(ep, w[k] - self.bg)
                self._anchor = float(t[k])
        # the tail after the last cycle start waits for the next block, so blocks never cut a cycle short
        held = (_cycle_start(t, cursor, len(t) - 1, self._anchor, self.cfg.filter.cov_step_s)
                if self.nav is not None else len(t) - 1)
        self._add_interval(w, f, cursor, held)
        if self.nav is not None:
            segments.append(self._advance(t, t_ns, w, f, cursor, held))
        else:
            aligning.append(self.status.aligning(t_ns[cursor:held + 1]))
        self._carry = (t_ns[held:].copy(), w[held:].copy(), f[held:].copy())
        return self._solution(aligning, segments), self.outages.take()

    def _solution(self, aligning: list[Solution], segments: list[output.Segment | None]) -> Solution:
        """A block's rows: the status rows before the alignment, then the rows of its INS segments (the INS runs
        from the alignment on), made in one pass (``output.rows``) with their status."""
        run = [g for g in segments if g is not None]
        if not run:
            return Solution.concat(aligning)
        sol, seg = output.rows(run, self.cfg.filter.output_hz)
        return Solution.concat([*aligning, self.status.of(sol, seg, [g.state for g in run])])

    def _add_interval(self, w: np.ndarray, f: np.ndarray, i0: int, i1: int) -> None:
        """Raw samples (i0, i1] into the interval's sums and to the measurements that read them."""
        self._interval.add(w, f, i0, i1)
        for p in self._imu_readers:
            p.feed_imu(w, f, i0, i1, self._period.dt_s)

    def finish(self) -> tuple[Solution, list[Outage]]:
        """End of the drive: the rows held back for their covariance cycle, the outages not yet returned (closed).

        Returns
        -------
        (Solution, list of Outage)
            The rows held back (none before the alignment), and the outage windows not yet returned, one still
            open closed at the last IMU sample.
        """
        sol = Solution.concat([])
        if self._carry is not None and self.nav is not None:
            t_ns, w, f = self._carry
            sol = self._solution([], [self._advance((t_ns - self.t_ref_ns) * 1e-9, t_ns, w, f, 0, len(t_ns) - 1)])
            self._carry = (t_ns[-1:], w[-1:], f[-1:])
        self.outages.finish(int(self._carry[0][-1]) if self._carry else None)
        return sol, self.outages.take()

    # -- epochs ---------------------------------------------------------------------------------

    def _pre_init_epoch(self, ep: Epoch, t_k: float, t_k_ns: int) -> None:
        """A GPS epoch before the alignment (``fusion.align``); at the alignment epoch, the filter starts."""
        usable = self.outages.classify(ep)
        interval, self._interval = self._interval, still.ImuSums()
        a = self.alignment.epoch(ep, usable, interval, t_k, self.t_ref_ns)
        if a is not None:
            self._start(a, t_k, t_k_ns)

    def _start(self, a: align.Aligned, t_k: float, t_k_ns: int) -> None:
        """Start the INS and the filter from the initial state a at time t_k (s from t_ref_ns), t_k_ns UTC."""
        self.nav, self.bg, self._anchor = a.nav, a.bg, t_k
        if self.adapt is not None:
            self.adapt.still_start(self.alignment.static_intervals)
            self.q = self.adapt.q
        self.filter = self.spec.filter(a.P0, self.q, self.cfg)
        s = self.cfg.sensor
        if s.scale_factor_model == "consider" and (s.gyro_scale_factor_ppm > 0.0 or s.gyro_misalignment_mrad > 0.0):
            self.listeners.append(listeners.GyroConsider(s.gyro_scale_factor_ppm * 1e-6,
                                                         s.gyro_misalignment_mrad * 1e-3, self.log))
        self._check = None if self._history else align.HeadingCheck(self.cfg, t_k)
        if self.bridge is not None:
            self.bridge.origin = (self.nav.lat, self.nav.lon, self.nav.h)
        for x in self.listeners:
            x.start(t_k_ns, self.filter.covariance)

    def _epoch(self, ep: Epoch, omega_k: np.ndarray) -> None:
        """GPS epoch at the current sample: the aids, then the fix or the outage (module docstring)."""
        usable = self.status.epoch(self.outages.classify(ep))
        interval, self._interval = self._interval, still.ImuSums()
        v = ep.v_n if usable and np.isfinite(ep.v_n[:2]).all() else np.full(3, np.nan)
        t_g = (ep.t_ns - self.t_ref_ns) * 1e-9
        at = measurements.Moment(ep, usable, t_g, v, self.nav, omega_k, interval, self._period.dt_s, self.bg, self.ba,
                                 self.filter.covariance)
        for m in self.measurements:
            if m.stage == "aid" and self._update(_observe([m], at)):
                self._feedback(self.filter.state)
                at.nav, at.P, at.bg, at.ba = self.nav, self.filter.covariance, self.bg, self.ba
        if not usable:
            self.filter.start_outage()
            if self.bridge is not None:
                self._bridge()
            elif self.filter.feeds_prediction and self.filter.state.any():
                self._feedback(self.filter.state)  # the fused state prediction X(n|n-1) of the local filters
            return
        fixes = [m for m in self.measurements if m.stage == "fix"]
        obs = _observe(fixes, at)
        if not obs:
            return
        u = self.bridge.input(self.nav) if self.bridge is not None else None
        vel = kf.stack(*(o.m for o in obs if o.kind == "velocity"))
        if (self._check is not None and vel is not None
                and self._check.far_off(t_g, *vel, self.filter.state, self.filter.covariance) and self._realign(ep)):
            at.nav, at.P = self.nav, self.filter.covariance
            obs = _observe(fixes, at)
        if self.adapt is not None:
            obs = self.adapt.before(obs, self.filter.state, self.filter.covariance)
        m = kf.stack(*(o.m for o in obs))
        self.status.fix(ep.t_ns, m, self.filter)
        self._update(obs, m)
        if self.adapt is not None:
            self.adapt.after(self.filter.state, self.filter.covariance)
            self.q = self.adapt.q
        period = self.silence.period_ns * 1e-9 if self.silence.period_ns else 1.0
        for x in self.listeners:
            x.fix(ep, self.filter, period)
        if self.bridge is not None:
            self.bridge.train(t_g, u, self.filter.innovations, kf.stack(*(o.m for o in obs if o.kind == "position")),
                              kf.stack(*(o.m for o in obs if o.kind == "velocity")))
        self._feedback(self.filter.state)
        self.updates += 1

    def _update(self, obs: list[kf.Observation], m: kf.Measurement | None = None) -> bool:
        """One filter update with the observations (the listeners told first, of ``m``: them stacked, when the
        caller has it); False when there are none."""
        if not obs:
            return False
        m = kf.stack(*(o.m for o in obs)) if m is None else m
        for x in self.listeners:
            x.update(self.filter.covariance, m[1], m[2])
        self.filter.update_batch(obs)
        return True

    def _realign(self, ep: Epoch) -> bool:
        """The heading is far off its sigma (``fusion.align.HeadingCheck``): take it again from the GPS course and
        restart the filter with the covariance so far, the heading's and the gyro bias's reopened. False while
        the vehicle is too slow for the course."""
        r = self._check.realign(self.nav, ep, self.filter.covariance)
        if r is None:
            return False
        self.nav, P = r
        self.filter = self.spec.filter(P, self.q, self.cfg)
        self.alignment.note += "; re-aligned from the GPS course (chi-square test on the GPS velocity innovations)"
        return True

    def _feedback(self, x: np.ndarray) -> None:
        """Closed loop: the estimate x (15,) corrects the INS and the biases; the filter is reset."""
        for lis in self.listeners:
            lis.feedback(x, self.filter.covariance)
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
        for lis in self.listeners:
            lis.bridged(x)
        self.predicted += 1

    # -- INS and covariance between epochs ------------------------------------------------------------

    def _advance(self, t: np.ndarray, t_ns: np.ndarray, w: np.ndarray, f: np.ndarray, i0: int, i1: int
                 ) -> output.Segment | None:
        """INS and covariance from sample i0 (the current state) to sample i1; the segment whose rows in (i0, i1]
        are made with the block's (``_solution``), None when there is none."""
        if i1 <= i0:
            return None
        wc, fc = w[i0:i1 + 1] - self.bg, f[i0:i1 + 1] - self.ba
        sol = ins.integrate(self.nav, t[i0:i1 + 1], wc, fc)
        clip = clipgyro.clipped(w[i0:i1 + 1, 2], self.cfg.sensor.gyro_range_dps * _DEG)
        if clip.any():  # the yaw gyro saturated in a sharp turn: rebuild its rate, integrate again
            wc[:, 2] = clipgyro.turn_rate(wc[:, 2], fc, sol, clip)
            sol = ins.integrate(self.nav, t[i0:i1 + 1], wc, fc)
        self.nav = sol.state(-1)
        # filter cycles: end at the first sample of each cov_step_s slot after i0, and at i1
        tt = sol.t
        ends = _slot_starts(tt, self._anchor, self.cfg.filter.cov_step_s)
        if len(ends) == 0 or ends[-1] != len(tt) - 1:
            ends = np.append(ends, len(tt) - 1)
        c = errmodel.segment_cycles(sol, ends, wc, fc, self.q, self._steps)
        Q = c.Q
        if clip.any():  # the rebuilt rate scales with the INS forward speed: its error counts too
            fwd = c.C_bn[0, :, 1]
            sd_v = math.sqrt(max(float(fwd @ self.filter.covariance[VEL, VEL] @ fwd), 0.0))
            rel = sd_v / max(abs(float(fwd @ sol.v_n[0])), 1.0)
            sigma = math.hypot(self.cfg.sensor.clip_rate_sigma_dps * _DEG, rel * float(np.abs(wc[clip, 2]).max()))
            Q = Q + clipgyro.clip_noise(clip, tt, c.starts, ends, c.C_bn, sigma)
        if self.filter.wants_cycle_lengths:
            self.filter.cycles(c.dt)
        if self.filter.wants_nodes:  # the nodes of its RK4 through the nonlinear model
            self.filter.queue(ukf.cycles_from_ins(sol.lat, sol.h, sol.v_n, sol.q, c.starts, c.mid, ends, c.f_mean,
                                                  c.dt))
        diag, P, local = _propagate(self.filter, c.Phi, Q, self._history)
        diag = diag.copy()
        for x in self.listeners:
            x.cycles(t_ns[i0:i1 + 1][ends], c.Phi, P, c.C_bn, c.w_mean, c.dt, diag)
        return output.Segment(sol, t_ns[i0:i1 + 1], ends, diag, np.concatenate([self.bg, self.ba]), self.gps_errors.var,
                              local, self.gps_errors.var_local, self.status.now())



def _observe(ms: list[measurements.MeasurementModel], at: measurements.Moment) -> list[kf.Observation]:
    """The observations the measurements ms give at the moment."""
    out = []
    for m in ms:
        z_H_R = m.compute_matrices(at)
        if z_H_R is not None:
            out.append(kf.Observation(m.kind, z_H_R, m.receiver))
    return out


def _propagate(f, Phi: np.ndarray, Q: np.ndarray, history: bool
               ) -> tuple[np.ndarray, np.ndarray | None, tuple[np.ndarray, np.ndarray] | None]:
    """``f.propagate`` of the filter f over the cycles: diag(P) after each (m, 15); each predicted P (m, 15, 15)
    when a listener records the ``history`` (the filter's ``predicted``, or one cycle per call when it
    ``keeps_predicted`` not), else None; the local states and variances after each cycle ((m, 2, 15) each) of a
    filter with local filters, else None."""
    if not history or f.keeps_predicted:
        diag = f.propagate(Phi, Q)
        return diag, (f.predicted if history else None), ((f.local_states, f.local_diag) if f.has_locals else None)
    P = np.empty_like(Phi)
    local = np.empty((2, len(Phi), 2, N_STATES))
    for i in range(len(Phi)):
        f.propagate(Phi[i:i + 1], Q[i:i + 1])
        P[i] = f.covariance
        if f.has_locals:
            local[:, i] = f.local_states[-1], f.local_diag[-1]
    return np.diagonal(P, axis1=1, axis2=2).copy(), P, (tuple(local) if f.has_locals else None)


def _slot_starts(t: np.ndarray, anchor: float | None, step_s: float) -> np.ndarray:
    """Indexes into t (s, strictly increasing) of the samples that start a ``step_s`` slot counted from the anchor
    (s, the last GPS epoch; t[0] when None), after t[0]: where floor((t - anchor) / step_s) steps (compiled)."""
    t = np.ascontiguousarray(t, dtype=float)
    out = np.empty(len(t), np.int64)
    start = float(t[0] if anchor is None else anchor)
    n = errmodel.cycle_kernel().fieldlog_slot_starts(len(t), kernels.address(t), start, step_s, kernels.address(out))
    return out[:n]


def _cycle_start(t: np.ndarray, i0: int, i1: int, anchor: float | None, step_s: float) -> int:
    """The last sample in [i0, i1] that starts a covariance cycle (i0 if none after it)."""
    s = _slot_starts(t[i0:i1 + 1], anchor, step_s)
    return i0 + int(s[-1]) if len(s) else i0
