"""Noise from the drive: the IMU's white noise from the parked start, and the filter's Q and R adapted to the
innovations (``[fusion] adapt_noise``).

The still start. A parked car with its engine idling shakes the IMU far above its datasheet noise (of order
1 deg/s at the gyros), and that shaking goes on while the car drives. The densities the shaking adds at the
time scale the filter sees (its GNSS interval, about 1 s) are read from the parked intervals the alignment
levelled on (``fusion.align.Alignment.static_intervals``): for white noise of density N the means of intervals
of tau seconds scatter by N / sqrt(tau), so the scatter of consecutive interval means (their Allan deviation,
which a slowly wandering bias does not inflate) gives N = sigma_A sqrt(tau) per axis; the RMS over the axes is
the figure. Fast vibration (the engine's tens of Hz) averages out of a one-second mean and is not counted; the
rocking and bumps of the parked car that survive the averaging are. Each figure replaces the configured white
density when it exceeds it, never when below: the configured one is the sensor's own floor.

Q and R: covariance matching (Mohamed and Schwarz, 1999), not variational Bayes. Both fit the filter's noise to
what its innovations show; variational Bayes iterates each update to a fixed point of R and the posterior,
inside the filter class every method shares, and carries R alone (Q needs a second, less settled, extension),
while covariance matching reads the innovations and residuals the loop already has and rescales Q and R
between updates: a few lines outside the filters, and the same for every method.

The innovations matched are the GNSS velocity's alone. A receiver's position error is correlated over minutes
(multipath, atmosphere: ``gps_error_model`` carries it, as a consider term or as states), so its innovations
are not white and their scatter is not the R of one epoch: matched, they would call for a position R and a Q
many times the true ones (the filter would then bridge an outage on a Q that says the IMU is far worse than it
is). The velocity error is close to white, and the INS's velocity is where the IMU's white noise shows first.
The vehicle aids are not adapted. Over each window of ``WINDOW`` GNSS fixes:

- R, from the residuals after the update (epsilon = z - H x+, whose covariance is R - H P+ H^T):
  rho = mean over the window's rows of (epsilon_i^2 + (H P+ H^T)_ii) / R_ii, and the next window's velocity R is
  scaled by lambda_R = clip(rho, 1, ``MAX_SCALE``);
- Q, from the innovations before the update (nu = z - H x-, of covariance H P- H^T + R): the
  innovations' variance less what the matched R explains, over what the predicted covariance gives:
  need = (sum nu_i^2 - lambda_R sum R_i) / sum (H P- H^T)_ii, 1 when Q is right; the white noise PSD entries
  (gyro and accelerometer) are scaled by lambda_Q <- clip(lambda_Q need, 1, ``MAX_Q_SCALE``).

The floors (1) keep the figures given, or the still start's, as the least noise there is: a receiver that
reports its errors too large, or a GNSS error the innovations call white when it is correlated, never shrinks
them; the ceilings bound what an outlier window can do. Q's ceiling is low (the white PSD at most doubled):
errors Q does not model (an IMU late against the GNSS, a mounting nobody measured) show in the velocity
innovations in every turn and acceleration, raising Q barely changes H P- H^T there, so the matching would
drive Q to any ceiling, and the filter would carry that noise, which the IMU does not have, into the outages
(docs/results.md, "Noise from the drive"). The bias processes are not adapted: the innovations of
a minute cannot tell a bias random walk from the white noise, and a datasheet's bias instability is the
sensor's own.
"""
from __future__ import annotations

import math

import numpy as np

from fieldlog.fusion import align, kf

KIND = "velocity"  # the observations adapted to: the receiver's velocities
CONFIGURED = "configured"  # the source of a figure the drive did not change
WINDOW = 30  # GNSS fixes per adaptation window
MAX_SCALE = 100.0  # the largest factor on the receiver's velocity variance
MAX_Q_SCALE = 2.0  # the largest factor on Q's white PSD
_DEG = math.pi / 180.0
_UG = 9.80665e-6
WHITE = slice(0, 6)  # the gyro and accelerometer white noise entries of the noise PSD (fusion.errmodel.noise_psd)


def still_densities(means_w: np.ndarray, means_f: np.ndarray, tau_s: float) -> tuple[float, float] | None:
    """White noise densities from the means of consecutive parked intervals of ``tau_s`` seconds.

    Parameters
    ----------
    means_w, means_f : (n, 3) arrays
        Mean rate (rad/s) and specific force (m/s^2) of each interval, body RFU, in time order.
    tau_s : float
        The intervals' mean length, s.

    Returns
    -------
    (gyro deg/s/sqrt(Hz), accel ug/sqrt(Hz)), the Allan deviation at tau_s times sqrt(tau_s), RMS over the axes;
    None with fewer than 3 intervals.
    """
    if len(means_w) < 3 or not tau_s > 0:
        return None
    out = []
    for m in (np.asarray(means_w, float), np.asarray(means_f, float)):
        avar = 0.5 * np.mean(np.diff(m, axis=0) ** 2, axis=0)
        out.append(math.sqrt(float(np.mean(avar)) * tau_s))
    return out[0] / _DEG, out[1] / _UG


class Adaptation:
    """Covariance matching of Q's white noise and the receiver's R (module docstring), and the still start's
    densities. ``q_scale``: lambda_Q; ``r_scale``: lambda_R of ``KIND``; ``windows``: windows closed."""

    def __init__(self, q: np.ndarray, gyro_dps_rthz: float, accel_ug_rthz: float) -> None:
        """q (12, 12): the configured noise PSD (``fusion.errmodel.noise_psd``); the configured white densities
        (deg/s/sqrt(Hz), ug/sqrt(Hz)), whose source is ``CONFIGURED`` until the drive replaces them."""
        self.q0 = np.array(q, dtype=float)
        self.q_scale = 1.0
        self.r_scale = {KIND: 1.0}
        self.windows = 0
        self.noise = {"gyro_noise_dps_rthz": (gyro_dps_rthz, CONFIGURED),  # key -> (value in its unit, source)
                      "accel_noise_ug_rthz": (accel_ug_rthz, CONFIGURED)}
        self._nu2 = self._hph = self._r0 = 0.0  # the window's sums: nu_i^2, (H P- H^T)_ii, the receiver's R_ii
        self._res = {k: [0.0, 0] for k in self.r_scale}
        self._fixes = 0
        self._pending: list[kf.Observation] = []

    def still_start(self, intervals: list[tuple[align.ImuSums, float]]) -> None:
        """The parked start's intervals (their IMU sums and seconds, ``fusion.align.Alignment.static_intervals``):
        a density of ``still_densities`` above the configured one replaces it in Q.

        Parameters
        ----------
        intervals : list of (ImuSums, float)
            Each parked interval in time order: its IMU sums (rate rad/s and specific force m/s^2 summed over its
            samples, body RFU) and its length, s. Fewer than 3 intervals with samples change nothing.
        """
        full = [(s, dt) for s, dt in intervals if s.n and dt > 0]
        if len(full) < 3:
            return
        means_w = np.array([s.sum_w / s.n for s, _ in full])
        means_f = np.array([s.sum_f / s.n for s, _ in full])
        tau_s = float(np.mean([dt for _, dt in full]))
        est = still_densities(means_w, means_f, tau_s)
        if est is None:
            return
        for i, key in enumerate(("gyro_noise_dps_rthz", "accel_noise_ug_rthz")):
            given, _ = self.noise[key]
            if est[i] > given:
                self.noise[key] = (est[i], f"estimated from the still start ({tau_s * len(full):.0f} s)")
                unit = _DEG if i == 0 else _UG
                self.q0[3 * i:3 * i + 3, 3 * i:3 * i + 3] = np.eye(3) * (est[i] * unit) ** 2

    @property
    def q(self) -> np.ndarray:
        """The noise PSD (12, 12) to propagate with: the white entries scaled by lambda_Q."""
        out = self.q0.copy()
        out[WHITE, WHITE] *= self.q_scale
        return out

    def before(self, obs: list[kf.Observation], x: np.ndarray, P: np.ndarray) -> list[kf.Observation]:
        """A fix's observations before the update: the receiver's R scaled by lambda_R of its kind, the
        innovations' NIS summed.

        Parameters
        ----------
        obs : list of Observation
            The fix's observations (``fusion.kf.Observation``); only the receiver's ``KIND`` ones are adapted.
        x : np.ndarray
            (15,) the prior error state (``fusion.errmodel`` order and units).
        P : np.ndarray
            (15, 15) its covariance.

        Returns
        -------
        list of Observation
            The observations to update with, in the given order: the receiver's velocities with R (m/s)^2 times
            lambda_R, the others as given.
        """
        out = [kf.Observation(o.kind, (o.m[0], o.m[1], o.m[2] * self.r_scale[KIND]), o.receiver)
               if o.receiver and o.kind == KIND else o for o in obs]
        rec = [o for o in out if o.receiver and o.kind == KIND]
        for o in rec:
            z, H, R = o.m
            self._nu2 += float(np.sum((z - H @ x) ** 2))
            self._hph += float(np.trace(H @ P @ H.T))
            self._r0 += float(np.trace(R)) / self.r_scale[KIND]
        self._pending = rec
        return out

    def after(self, x: np.ndarray, P: np.ndarray) -> None:
        """After the update: the residuals summed; a full window rescales.

        Parameters
        ----------
        x : np.ndarray
            (15,) the posterior error state (``fusion.errmodel`` order and units), before the feedback resets it.
        P : np.ndarray
            (15, 15) its covariance.
        """
        for o in self._pending:
            z, H, R = o.m
            eps = z - H @ x
            ratio = (eps ** 2 + np.einsum("ij,jk,ik->i", H, P, H)) / np.maximum(np.diag(R) / self.r_scale[o.kind],
                                                                                 1e-12)
            acc = self._res[o.kind]
            acc[0] += float(np.sum(ratio))
            acc[1] += len(z)
        self._pending = []
        self._fixes += 1
        if self._fixes >= WINDOW:
            self._close()

    def _close(self) -> None:
        for kind, (total, n) in self._res.items():
            if n:
                self.r_scale[kind] = min(max(total / n, 1.0), MAX_SCALE)
        if self._hph > 0:
            need = (self._nu2 - self.r_scale[KIND] * self._r0) / self._hph
            self.q_scale = min(max(self.q_scale * need, 1.0), MAX_Q_SCALE)
        self._nu2 = self._hph = self._r0 = 0.0
        self._res = {k: [0.0, 0] for k in self.r_scale}
        self._fixes = 0
        self.windows += 1

    def figures(self) -> dict[str, tuple[float, str]]:
        """The white densities the run ended with, and the receiver's velocity variance factor.

        Returns
        -------
        dict
            Key -> (value, source). ``gyro_noise_dps_rthz`` (deg/s/sqrt(Hz)) and ``accel_noise_ug_rthz``
            (ug/sqrt(Hz)): the density in Q, sqrt(lambda_Q) times the configured one or the still start's; their
            source ``CONFIGURED`` or the still start's estimate, with the adaptation's factor when it scaled Q.
            ``gnss_velocity_variance_scale``: lambda_R, dimensionless, ``CONFIGURED`` (1) before a window closed.
        """
        root = math.sqrt(self.q_scale)
        out = {k: (v * root, src if self.q_scale == 1.0 else
                   f"{src}, adapted x{root:.3g} from the GNSS velocity innovations over {self.windows} windows")
               for k, (v, src) in self.noise.items()}
        out["gnss_velocity_variance_scale"] = (self.r_scale[KIND], "adapted from the GNSS velocity residuals over "
                                               f"{self.windows} windows" if self.windows else CONFIGURED)
        return out
