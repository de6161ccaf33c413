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

Per-wheel slip. With the four wheel speeds (``/vehicle/wheel_speeds``: front left, front right, rear left, rear
right), each wheel is tested against what the car's motion predicts for it: its hub at r_w (``wheel_positions``:
the rear wheels at the rear axle's centre -+ half the track along the car's right axis, the front wheels a
wheelbase ahead) moves with C_nb v_n + omega_nb_b x r_w and rolls along its own heading (the front wheels are
steered), so its speed is the horizontal magnitude of that velocity (``hub_speeds``): the forward speed -+ yaw
rate x half the track for the rear pair, with the steering's part for the front. Each wheel's own scale s_w
(``ScaleEstimator`` on the predicted hub speed, fed only while GPS is good and the wheel kept) scales the
prediction; a wheel whose speed is off it by more than chi^2 (``SLIP_CHI2``) over the sum of the wheel speed's
variance, the INS's forward-speed variance (s_w^2 H P H^T) and its scale's (v sigma_s_w)^2 is skipped at that
epoch (``WheelSlip.skipped`` counts them per wheel). The forward speed is then the mean of the kept wheels, each
taken to the rear axle's centre by the ratio of the predicted speeds; no wheel kept is a slip of the whole car.
Below ``WHEEL_MIN_SPEED_MPS`` (the ratios are ill-conditioned) and where a drive gives one forward speed only, the
forward speed is the topic's and no wheel is tested.

With the NHC and without. The aid carries the NHC's lateral and vertical zeros (``[fusion] nhc``); with
``nhc = false`` it is the forward row alone, and ``[fusion] odometer = false`` leaves the NHC alone (the
``FirstOf`` in ``fusion.measurements``: the odometer where it has wheel speeds, the NHC elsewhere).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from fieldlog.fusion import earth
from fieldlog.fusion.errmodel import ATT, BG, N_STATES, VEL
from fieldlog.fusion.ins import NavState

Measurement = tuple[np.ndarray, np.ndarray, np.ndarray]
SLIP_CHI2 = 10.83  # chi^2, 1 degree of freedom, 99.9 %: a wheel speed off the INS's forward speed by more slips
WHEELS = ("FL", "FR", "RL", "RR")  # the order of the wheel speeds
WHEEL_MIN_SPEED_MPS = 1.0  # no wheel is tested while a hub is slower than this (module docstring, Per-wheel slip)


def body_velocity_at(nav: NavState, omega_nb_b: np.ndarray, r_b: np.ndarray) -> np.ndarray:
    """The INS's velocity of a point fixed to the body.

    Parameters
    ----------
    nav : NavState
        The INS's state: C_bn (body RFU to ENU), v_n (ENU, m/s).
    omega_nb_b : np.ndarray
        (3,) the body's rate against the navigation frame, body RFU, rad/s.
    r_b : np.ndarray
        (3,) the point from the IMU, body RFU, m; or (k, 3) k points.

    Returns
    -------
    np.ndarray
        (3,) its velocity in body RFU axes, m/s; or (k, 3).
    """
    return nav.C_bn.T @ nav.v_n + earth.cross(omega_nb_b, r_b)


def wheel_positions(r_b: np.ndarray, track_m: float, wheelbase_m: float, C_bm: np.ndarray | None = None
                    ) -> np.ndarray:
    """The wheels' hubs (module docstring, Per-wheel slip).

    Parameters
    ----------
    r_b : np.ndarray
        (3,) the rear axle's centre from the IMU, body RFU, m.
    track_m : float
        The distance between the left and right wheels' centres, m.
    wheelbase_m : float
        The distance from the rear axle to the front axle, m.
    C_bm : np.ndarray, optional
        (3, 3) IMU axes -> the car's (``fusion.measurements.CarFrame``): the track and the wheelbase lie along the
        car's right and forward axes; None: the IMU's axes are the car's.

    Returns
    -------
    np.ndarray
        (4, 3) the hubs of the front left, front right, rear left and rear right wheels from the IMU, body RFU, m.
    """
    half = track_m / 2
    d_car = np.array([[-half, wheelbase_m, 0.0], [half, wheelbase_m, 0.0], [-half, 0.0, 0.0], [half, 0.0, 0.0]])
    return np.asarray(r_b, float) + (d_car if C_bm is None else d_car @ C_bm)


def hub_speeds(nav: NavState, omega_nb_b: np.ndarray, r_w: np.ndarray, C_bm: np.ndarray | None = None
               ) -> np.ndarray:
    """The speeds the car's motion predicts for its wheels: each hub's horizontal speed, along its own heading.

    Parameters
    ----------
    nav, omega_nb_b : NavState, np.ndarray
        As ``body_velocity_at``.
    r_w : np.ndarray
        (k, 3) the hubs from the IMU, body RFU, m (``wheel_positions``).
    C_bm : np.ndarray, optional
        (3, 3) IMU axes -> the car's: the hubs roll in the car's horizontal plane; None: the IMU's axes are the car's.

    Returns
    -------
    np.ndarray
        (k,) the hubs' speeds, m/s, negative where a hub moves backwards.
    """
    v = body_velocity_at(nav, omega_nb_b, r_w)
    v = v if C_bm is None else v @ C_bm.T
    return np.hypot(v[:, 0], v[:, 1]) * np.sign(v[:, 1])


def odometer_measurement(nav: NavState, omega_nb_b: np.ndarray, r_b: np.ndarray, v_wheel: float,
                         var_wheel: float, scale: float, sigma_scale: float, sigma_nhc: float) -> Measurement:
    """The 3-D body-velocity aid of one wheel-speed sample (module docstring).

    Parameters
    ----------
    nav : NavState
        The INS's state: C_bn (body RFU to ENU), v_n (ENU, m/s).
    omega_nb_b : np.ndarray
        (3,) the bias-corrected body rate less the navigation frame's, body RFU, rad/s.
    r_b : np.ndarray
        (3,) the rear axle's centre from the IMU, body RFU, m.
    v_wheel : float
        The wheel-speed forward speed, m/s (negative in reverse).
    var_wheel : float
        Its variance, (m/s)^2.
    scale : float
        The wheels' scale factor s (v_wheel = s v_true), dimensionless.
    sigma_scale : float
        Its sigma, dimensionless.
    sigma_nhc : float
        The NHC's lateral and vertical sigma, m/s.

    Returns
    -------
    Measurement
        (z (3,) body RFU m/s, H (3, N_STATES), R (3, 3) (m/s)^2): the innovation, lateral, forward, vertical.
    """
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
        """One sample, taken while GPS is good.

        Parameters
        ----------
        t : float
            Its time, s (any origin, increasing).
        v_wheel : float
            The wheel speed, m/s.
        v_ins : float
            The reference forward speed (GPS-aided), m/s.
        var_ins : float
            The reference's variance, (m/s)^2.
        """
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


@dataclass
class WheelSlip:
    """The per-wheel slip test and the forward speed of the wheels kept (module docstring, Per-wheel slip).

    ``r_w`` (4, 3): the hubs from the IMU, body RFU, m (``wheel_positions``); ``C_bm`` (3, 3): IMU axes -> the
    car's, the speeds are the car's (None: the IMU's axes are the car's); ``tested``: the epochs the wheels were
    tested at; ``skipped`` (4,): those each wheel (``WHEELS`` order) was skipped at."""

    r_w: np.ndarray
    C_bm: np.ndarray | None = None
    tested: int = 0
    skipped: np.ndarray = field(default_factory=lambda: np.zeros(len(WHEELS), np.int64))

    def __post_init__(self) -> None:
        self.scales = [ScaleEstimator(min_samples=30, prior_sigma=0.005) for _ in WHEELS]
        self._last: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # speeds, predicted, kept

    def forward_speed(self, nav: NavState, omega_nb_b: np.ndarray, r_b: np.ndarray, wheels: np.ndarray,
                      var_wheel: float, var_ins: float) -> float | None:
        """The rear axle centre's forward speed from the wheels that pass the slip test.

        Parameters
        ----------
        nav, omega_nb_b, r_b : NavState, np.ndarray, np.ndarray
            As ``odometer_measurement``.
        wheels : np.ndarray
            (4,) the wheel speeds (``WHEELS`` order), m/s, negative in reverse.
        var_wheel : float
            A wheel speed's variance, (m/s)^2.
        var_ins : float
            The variance of the INS's forward speed at the rear axle (H P H^T of the forward row), (m/s)^2.

        Returns
        -------
        float or None
            The mean of the kept wheels taken to the rear axle's centre, along the car's forward axis, m/s (NaN:
            every wheel skipped); None when no wheel is tested (a wheel speed missing, or a hub slower than
            ``WHEEL_MIN_SPEED_MPS``).
        """
        self._last = None
        pred = hub_speeds(nav, omega_nb_b, self.r_w, self.C_bm)
        if not np.isfinite(wheels).all() or np.min(np.abs(pred)) < WHEEL_MIN_SPEED_MPS:
            return None
        s = np.array([e.scale for e in self.scales])
        sigma_s = np.array([e.sigma for e in self.scales])
        var = var_wheel + s ** 2 * var_ins + (pred * sigma_s) ** 2
        kept = (wheels - s * pred) ** 2 <= SLIP_CHI2 * var
        self.tested += 1
        self.skipped += ~kept
        self._last = wheels, pred, kept
        if not kept.any():
            return math.nan
        v_centre = body_velocity_at(nav, omega_nb_b, r_b)
        v_centre = (v_centre if self.C_bm is None else self.C_bm @ v_centre)[1]
        return float(np.mean(wheels[kept] * v_centre / pred[kept]))

    def learn(self, t: float, var_ref: float) -> None:
        """Feed each wheel kept at the last ``forward_speed`` to its scale estimator (call only while GPS is good).

        Parameters
        ----------
        t : float
            The epoch's time, s.
        var_ref : float
            The variance of the reference forward speed, (m/s)^2.
        """
        if self._last is None:
            return
        for est, w, p, k in zip(self.scales, *self._last):
            if k:
                est.add(t, float(w), float(p), var_ref)
