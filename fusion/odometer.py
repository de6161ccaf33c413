"""The wheel-speed odometer: the car's forward speed (``/vehicle/twist``) with the non-holonomic constraint's
lateral and vertical zeros, as one 3-D body-velocity aid at the rear axle's centre; and the wheels' scale factor.

Measurement. The rear axle's centre moves along the body's forward axis (it is not steered and does not slip
sideways), so its velocity in the IMU's body axes (RFU) is v_r_b = (0, v_wheel / s, 0), with v_wheel the
wheel-speed forward speed and s = 1 + the tyre-radius scale error. The INS predicts it as
C_nb v_n + omega_nb_b x r_b, r_b the rear axle's centre from the IMU (body axes, m). So
z = C_nb v_n + omega_nb_b x r_b - (0, v_wheel / s, 0) and, with the errors of ``fusion.errmodel`` (velocity and
attitude computed minus true, C_computed = (I - [phi x]) C_true, bias state = true minus estimated):
H_vel = C_nb, H_att = -C_nb [v_n x], H_bg = -[r_b x] (the rate is bias-corrected). R = diag(sigma_nhc^2,
var_wheel / s^2 + (v_wheel sigma_s / s^2)^2, sigma_nhc^2): the NHC's side slip and suspension 1-sigma across,
the wheel speed's quantisation and the scale factor's uncertainty along. A stopped wheel (v_wheel = 0) makes
this a zero-velocity update of the whole body velocity.

Scale factor. Estimated inside the aid rather than as a filter state (the 15 states stay as every filter sizes
them): while GPS is good, ``ScaleEstimator`` fits v_wheel = s v_ins (v_ins the INS's forward speed at the rear
axle, GPS-aided) by least squares with a forgetting time ``tau_s``, over samples faster than ``min_speed_mps``;
its sigma is the larger of two readings over the samples the fit holds, taken as independent once a second: the
INS (GPS) speed's sigma, and the fit's own residual scatter (wheel slip, tyre deformation, stamp errors: what the
drive shows, not the wheel speed's quantisation). In an outage the estimate is held; it is never used before
``min_samples`` have been fitted (then s = 1 and sigma_s = ``prior_sigma``).

Slip. A wheel that slips or locks breaks v_wheel = s v: the forward row's innovation is tested against its
variance (the filter's covariance through H plus R), chi^2 over one degree of freedom above ``SLIP_CHI2``
(99.9 %), and such an epoch gives the NHC's zeros only (no wheel speed, and no sample for the scale fit).

With the NHC and without. The aid carries the NHC's lateral and vertical zeros (``[fusion] nhc``); with
``nhc = false`` it is the forward row alone, and ``[fusion] odometer = false`` leaves the NHC alone (the
``FirstOf`` in ``fusion.measurements``: the odometer where it has wheel speeds, the NHC elsewhere).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fieldlog.fusion import earth
from fieldlog.fusion.errmodel import ATT, BG, N_STATES, VEL
from fieldlog.fusion.ins import NavState

Measurement = tuple[np.ndarray, np.ndarray, np.ndarray]
SLIP_CHI2 = 10.83  # chi^2, 1 degree of freedom, 99.9 %: a wheel speed off the INS's forward speed by more slips


def body_velocity_at(nav: NavState, omega_nb_b: np.ndarray, r_b: np.ndarray) -> np.ndarray:
    """The INS's velocity of the point ``r_b`` (body RFU axes from the IMU, m), in body axes, m/s."""
    return nav.C_bn.T @ nav.v_n + earth.cross(omega_nb_b, r_b)


def odometer_measurement(nav: NavState, omega_nb_b: np.ndarray, r_b: np.ndarray, v_wheel: float,
                         var_wheel: float, scale: float, sigma_scale: float, sigma_nhc: float) -> Measurement:
    """The 3-D body-velocity aid of one wheel-speed sample (module docstring). omega_nb_b (3,) rad/s: the
    bias-corrected body rate less the navigation frame's; r_b (3,) m; v_wheel m/s (negative in reverse) and its
    variance (m/s)^2; scale, sigma_scale: the wheels' scale factor and its sigma; sigma_nhc m/s."""
    C_nb = nav.C_bn.T
    v_meas = v_wheel / scale
    z = body_velocity_at(nav, omega_nb_b, r_b) - np.array([0.0, v_meas, 0.0])
    H = np.zeros((3, N_STATES))
    H[:, VEL] = C_nb
    H[:, ATT] = -C_nb @ earth.skew(nav.v_n)
    H[:, BG] = -earth.skew(r_b)
    var_fwd = var_wheel / scale ** 2 + (v_meas * sigma_scale / scale) ** 2
    return z, H, np.diag([sigma_nhc ** 2, var_fwd, sigma_nhc ** 2])


@dataclass
class ScaleEstimator:
    """The wheels' scale factor s (v_wheel = s v_true), fitted while GPS is good (module docstring)."""

    tau_s: float = 600.0
    min_speed_mps: float = 3.0
    min_samples: int = 200
    prior_sigma: float = 0.01
    sxy: float = 0.0          # forgetting sums: v_ins v_wheel, v_ins^2, v_wheel^2, samples, seconds of samples
    sxx: float = 0.0
    syy: float = 0.0
    n: float = 0.0
    seconds: float = 0.0
    var_ins: float = 0.0      # the INS forward speed's variance (m/s)^2, averaged like the sums
    t_last: float | None = None

    def add(self, t: float, v_wheel: float, v_ins: float, var_ins: float) -> None:
        """One sample at time t (s) with GPS good: the wheel speed and the INS's forward speed (m/s) and variance."""
        if abs(v_ins) < self.min_speed_mps or not (math.isfinite(v_wheel) and math.isfinite(v_ins)):
            return
        dt = 0.0 if self.t_last is None else max(t - self.t_last, 0.0)
        self.t_last = t
        k = math.exp(-dt / self.tau_s)
        self.sxy = k * self.sxy + v_ins * v_wheel
        self.sxx = k * self.sxx + v_ins * v_ins
        self.syy = k * self.syy + v_wheel * v_wheel
        self.var_ins = k * self.var_ins + var_ins
        self.n = k * self.n + 1.0
        self.seconds = k * self.seconds + min(dt, 1.0)

    @property
    def ready(self) -> bool:
        return self.n >= self.min_samples and self.sxx > 0

    @property
    def scale(self) -> float:
        return self.sxy / self.sxx if self.ready else 1.0

    @property
    def sigma(self) -> float:
        """sigma of s: the larger of the mean INS speed variance and the fit's residual variance per sample, over
        the fit's mean v^2, per independent second."""
        if not self.ready:
            return self.prior_sigma
        mean_v2 = self.sxx / self.n
        independent = max(self.seconds, 1.0)
        residual = max(self.syy - self.sxy ** 2 / self.sxx, 0.0) / max(self.n - 1.0, 1.0)
        return math.sqrt(max(self.var_ins / self.n, residual) / mean_v2 / independent)
