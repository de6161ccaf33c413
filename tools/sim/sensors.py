"""MEMS IMU error model for the simulator: true body rates and specific forces -> DAQ ADC counts.

The measured SI value of each triad is::

    x_meas = (I + S) (I + E) x_true + b_turn_on + b_flicker(t) + w(t)

- S = diag(scale-factor errors), E = misalignment (off-diagonal small angles), both relative to the
  nominal calibration and constant over a run;
- b_turn_on: constant run-to-run bias; b_flicker: bias instability (1/f noise, see below);
- w: white noise (angle / velocity random walk) of density N: each sample is the mean of white
  noise over its own sample interval dt_k, so its standard deviation is N / sqrt(dt_k)
  (convention: Allan deviation at tau = 1 s equals N; ARW [deg/sqrt(h)] = 60 N [deg/s/sqrt(Hz)]);
- c(t): optional coloured noise (the coloured-noise case of the KF-versus-H-infinity paper): a first-order
  Gauss-Markov process per axis of standard deviation ``gyro_gm_sigma_dps`` / ``accel_gm_sigma_ug`` and
  correlation time ``gm_tau_s``, discretised exactly on the actual sample times (``gauss_markov``);
  with ``gm_tau_s`` = 0 it is white with that standard deviation per sample. Off by default (sigmas 0);
  its draws come after all the others, so enabling it leaves every other error of a seed unchanged.
The ADC then sees volts from the nominal calibration shifted by an electrical zero-output offset
(``*_zero_bias_V``), quantised and clipped by ``acquire.calib.to_counts``.

Bias instability. A sum of independent first-order Gauss-Markov processes with correlation times
T_i log-spaced by a ratio r between ``bias_corr_time_min_s`` and ``bias_corr_time_max_s``. Each has
the same variance s^2: the sum of Lorentzians 2 s^2 T_i / (1 + (2 pi f T_i)^2) over a log-uniform
set of T_i (density 1/ln r per unit ln T) integrates to the two-sided PSD s^2 / (2 f ln r), i.e. a
one-sided h_-1 / f with h_-1 = s^2 / ln r. Flicker noise has Allan variance 2 ln2 h_-1, and the
IEEE 952 bias instability B is defined by that floor being (0.664 B)^2 = (2 ln2 / pi) B^2, so
s^2 = B^2 ln r / pi. The Allan floor is within 1 % of 0.664 B from about 50 T_min to T_max / 20
(3 % from 20 T_min to T_max / 5); the defaults (2 ms to 1e4 s) keep it flat over any drive. The slow
processes are generated on coarse uniform grids (step <= T_i / 8) and linearly interpolated onto the
sample times, which keeps the cost near a few random draws per sample.

Defaults. From Table 2 of the distributed-KF paper where it gives a figure: accel noise 5 ug/sqrt(Hz),
gyro bias stability 0.02 deg/s. Our choices where it does not:
- gyro noise density 0.01 deg/s/sqrt(Hz) (0.6 deg/sqrt(h)), typical of low-cost MEMS rate gyros;
- accel bias instability 20 ug, typical of a 5 ug/sqrt(Hz) capacitive accelerometer;
- turn-on biases 0.05 deg/s and 1 mg, scale-factor errors 1000 ppm, misalignment 1 mrad (1-sigma):
  the residuals after a unit calibration (Table 2's 0.5 % sensitivity drift and +-0.5 deg/s, 0 +-0.2 V
  zero biases are unit-to-unit and temperature spreads that a calibration file removes);
- electrical zero-output offsets 0 V: set ``gyro_zero_bias_V`` = 0.25 and ``accel_zero_bias_V`` = 0.2
  (Table 2's zero-bias spreads) to simulate a unit running on the nominal, uncalibrated, file.
All error magnitudes are 1-sigma of zero-mean Gaussian draws, per axis.

The IMU in the car (``Installation``, the ``[imu]`` keys ``mounting_rpy_deg``, ``delay_s``, ``filter_hz``; all
off by default). The IMU's axes are rotated from the car's body frame (RFU, ``base_link``) by the mounting
angles [roll, pitch, yaw] in degrees, in the conventions of the vehicle's attitude (``fusion.earth``: the IMU
frame is to the car's what the car's body is to ENU, ``C_bm = euler_to_dcm(yaw, pitch, roll)`` maps IMU-frame
vectors into the car's). The IMU's own low-pass (first order, corner ``filter_hz``, run on the samples) and its
transport delay together make ``delay_s``: a sample stamped t measures the car at t - ``delay_s`` for slow
signals (the filter's low-frequency group delay phi / (1 - phi) sample periods, phi = exp(-2 pi filter_hz /
rate_hz), is taken out of the transport delay). These act on the true signal, before the sensor errors.

Grades. ``[imu] grade = "table2-mems" | "s000-mems" | "tactical" | "navigation"`` takes the error figures of
that datasheet (``fusion.imugrade``, the same figures the filter takes as ``[fusion] imu = NAME``);
``table2-mems`` equals the defaults above.
"""

from __future__ import annotations

import ctypes
import math
from dataclasses import dataclass, fields

import numpy as np

from fieldlog.drive import native
from fieldlog.acquire import rows
from fieldlog.acquire.calib import G0, Calibration, SensorTriadCal, to_counts
from fieldlog.drive.tables import ConfigError, from_table
from fieldlog.fusion import earth, imugrade

_DEG = math.pi / 180.0
_UG = 1e-6 * G0
_CORR_PER_DECADE = 2  # Gauss-Markov processes per decade of correlation time
_GRID_PER_CORR = 8  # grid steps per correlation time for the coarse-grid processes


@dataclass(frozen=True)
class ImuErrorConfig:
    """IMU error magnitudes in datasheet units (1-sigma per axis); see the module docstring."""

    rate_hz: float = 500.0  # nominal sample rate, Hz (the model itself uses the actual sample times)
    gyro_noise_density_dps_rthz: float = 0.01  # deg/s/sqrt(Hz)
    gyro_bias_instability_dps: float = 0.02  # deg/s, Table 2 "bias stability"
    gyro_turn_on_bias_dps: float = 0.05  # deg/s
    gyro_scale_factor_ppm: float = 1000.0
    gyro_misalignment_mrad: float = 1.0
    gyro_zero_bias_V: float = 0.0  # V, electrical zero-rate offset not in the calibration file
    accel_noise_density_ug_rthz: float = 5.0  # ug/sqrt(Hz), Table 2
    accel_bias_instability_ug: float = 20.0  # ug
    accel_turn_on_bias_ug: float = 1000.0  # ug
    accel_scale_factor_ppm: float = 1000.0
    accel_misalignment_mrad: float = 1.0
    accel_zero_bias_V: float = 0.0  # V, electrical zero-g offset not in the calibration file
    bias_corr_time_min_s: float = 0.002  # s, shortest correlation time of the flicker model
    bias_corr_time_max_s: float = 1.0e4  # s, longest
    gm_tau_s: float = 0.0  # s, correlation time of the coloured noise (0: white)
    gyro_gm_sigma_dps: float = 0.0  # deg/s, coloured gyro noise (1-sigma per axis; 0: none)
    accel_gm_sigma_ug: float = 0.0  # ug, coloured accelerometer noise

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"[imu] {f.name}: expected a finite number, got {value!r}")
            if value < 0.0:
                raise ValueError(f"[imu] {f.name}: must be >= 0, got {value!r}")
            object.__setattr__(self, f.name, float(value))
        if self.rate_hz <= 0.0:
            raise ValueError("[imu] rate_hz: must be > 0")
        if not 0.0 < self.bias_corr_time_min_s < self.bias_corr_time_max_s:
            raise ValueError("[imu] bias_corr_time_min_s, bias_corr_time_max_s: need 0 < min < max")

    @classmethod
    def from_dict(cls, d: dict) -> ImuErrorConfig:
        """Build from a scenario's [imu] TOML table; unknown keys raise ValueError naming them. ``grade = NAME``
        (``fusion.imugrade.GRADES``) sets the error figures of that datasheet; the table's other keys override."""
        d = dict(d)
        name = d.pop("grade", None)
        if name is not None:
            try:
                d = {**imugrade.grade(name).simulator(), **d}
            except ValueError as e:
                raise ConfigError(f"[imu] grade: {e}") from None
        return from_table(cls, "imu", d)


def flicker_corr_times(t_min_s: float, t_max_s: float) -> tuple[np.ndarray, float]:
    """Log-spaced correlation times (s) covering [t_min_s, t_max_s] and the unit-B variance of each.

    Returns (T (m,), s2) with s2 = ln(r) / pi: each process has variance s2 * B^2.
    """
    m = max(int(round(_CORR_PER_DECADE * math.log10(t_max_s / t_min_s))), 1) + 1
    T = np.geomspace(t_min_s, t_max_s, m)
    return T, math.log(T[1] / T[0]) / math.pi


def _gm_recursion(phi: np.ndarray, z: np.ndarray) -> np.ndarray:
    """x_0 = z_0, x_k = phi_{k-1} x_{k-1} + sqrt(1 - phi_{k-1}^2) z_k along axis 0 of z (n, m)
    (tools/sim/_sensors.c)."""
    z = np.ascontiguousarray(z, np.float64)
    phi = np.ascontiguousarray(phi, np.float64)
    if phi.shape != (max(z.shape[0] - 1, 0),):
        raise ValueError("_gm_recursion: phi needs one factor per step of z")
    x = np.empty_like(z)
    _lib().fieldlog_gm_recursion(z.shape[0], int(np.prod(z.shape[1:])), phi.ctypes.data, z.ctypes.data,
                                 x.ctypes.data)
    return x


def _ar1(b0: float, phi: float, z: np.ndarray, y_prev: np.ndarray) -> np.ndarray:
    """y_k = b0 z_k + phi y_{k-1} along axis 0 of z (n, m), y_{-1} = y_prev (m,): the recursion of
    ``scipy.signal.lfilter([b0], [1, -phi], z, axis=0, zi=phi * y_prev)``, with its operations in its order, so
    the same numbers to the bit without importing scipy.signal, which is slow to import (tools/sim/_sensors.c)."""
    z = np.ascontiguousarray(z, np.float64)
    y_prev = np.ascontiguousarray(y_prev, np.float64)
    if z.ndim != 2 or y_prev.shape != (z.shape[1],):
        raise ValueError("_ar1: z must be (n, m) and y_prev (m,)")
    y = np.empty_like(z)
    _lib().fieldlog_ar1(z.shape[0], z.shape[1], b0, phi, z.ctypes.data, y_prev.ctypes.data, y.ctypes.data)
    return y


_SIGNATURES = {"fieldlog_gm_recursion": (None, [native.I64, native.I64, native.P, native.P, native.P]),
               "fieldlog_ar1": (None, [native.I64, native.I64, ctypes.c_double, ctypes.c_double, native.P, native.P,
                                       native.P])}  # tools/sim/_sensors.c


def _lib():
    return native.library("fieldlog.tools.sim._sensors", _SIGNATURES)


def gauss_markov(t_s: np.ndarray, tau_s: float, z: np.ndarray) -> np.ndarray:
    """Unit-variance first-order Gauss-Markov process at times t_s (n,) s from standard normal draws z (n, m).

    Exact discretisation on each interval: x_k = phi_k x_{k-1} + sqrt(1 - phi_k^2) z_k,
    phi_k = exp(-(t_k - t_{k-1}) / tau_s), started stationary (x_0 = z_0): every x_k is N(0, 1) and
    E[x(t) x(t + d)] = exp(-|d| / tau_s). tau_s = 0 returns z (white). Scale by sigma for the process.
    """
    z = np.asarray(z, dtype=np.float64)
    if tau_s == 0.0 or z.shape[0] < 2:
        return z
    phi = np.exp(-np.diff(np.asarray(t_s, dtype=np.float64)) / tau_s)
    return _gm_recursion(phi, z)


def _lerp_uniform(y: np.ndarray, h: float, t: np.ndarray) -> np.ndarray:
    """Linear interpolation of rows y[k] at times k*h onto times t (0 <= t <= (len(y)-1)*h)."""
    pos = t / h
    k = np.minimum(pos.astype(np.int64), y.shape[0] - 2)
    lo = np.take(y, k, axis=0)  # np.take: several times faster than fancy indexing here
    out = np.take(y, k + 1, axis=0)
    out -= lo
    out *= (pos - k)[:, None]
    out += lo
    return out


def _upsample2(y: np.ndarray, m: int) -> np.ndarray:
    """Linear interpolation of rows y[k] at times 2k*h onto the first m points of the grid k*h."""
    out = np.empty((m,) + y.shape[1:])
    out[0::2] = y[: (m + 1) // 2]
    out[1::2] = 0.5 * (y[: m // 2] + y[1 : m // 2 + 1])
    return out


def flicker_noise(
    t_rel_s: np.ndarray, n_channels: int, t_min_s: float, t_max_s: float, rng: np.random.Generator
) -> np.ndarray:
    """Unit bias-instability (B = 1) flicker noise at times t_rel_s (n,) >= 0, s -> (n, n_channels).

    Sum of Gauss-Markov processes (module docstring). Each process runs on the coarsest power-of-two
    multiple of the median sample interval that is <= T_i / 8; levels are accumulated from coarse
    to fine by linear interpolation, then interpolated onto t_rel_s.
    """
    T, s2 = flicker_corr_times(t_min_s, t_max_s)
    dt = np.diff(t_rel_s)
    h0 = float(np.median(dt)) if dt.size else 1.0
    span = float(t_rel_s[-1])
    level = np.maximum(np.floor(np.log2(T / (_GRID_PER_CORR * h0))), 0).astype(int)
    acc = None
    for lvl in range(int(level.max()), -1, -1):
        h = h0 * 2.0**lvl
        grid = np.arange(int(math.ceil(span / h)) + 2) * h
        acc = np.zeros((grid.size, n_channels)) if acc is None else _upsample2(acc, grid.size)
        for Ti in T[level == lvl]:
            phi = math.exp(-h / Ti)
            z = rng.standard_normal((grid.size, n_channels))
            x_prev = rng.standard_normal(n_channels)  # stationary start
            acc += _ar1(math.sqrt(1.0 - phi * phi), phi, z, x_prev)
    out = _lerp_uniform(acc, h0, t_rel_s)
    out *= math.sqrt(s2)
    return out


def lowpass(x: np.ndarray, phi: float, start: np.ndarray | None = None) -> np.ndarray:
    """First-order low-pass down the rows of x (n, m): y_k = (1 - phi) x_k + phi y_{k-1}, y_{-1} = start (m,)
    (default x_0: started settled); phi = exp(-2 pi f_c dt) for a corner f_c Hz at sample period dt s."""
    x = np.asarray(x, np.float64)
    return _ar1(1.0 - phi, phi, x, x[0] if start is None else start)


@dataclass(frozen=True)
class Installation:
    """How the IMU sits in the car and what it does to the signal before its errors (module docstring):
    mounting [roll, pitch, yaw] deg, IMU to car body; delay_s, s; filter_hz, Hz (0: no filter)."""

    mounting_rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    delay_s: float = 0.0
    filter_hz: float = 0.0

    KEYS = ("mounting_rpy_deg", "delay_s", "filter_hz")
    MAX_DELAY_S = 1.0

    def __post_init__(self) -> None:
        rpy = self.mounting_rpy_deg
        if not (isinstance(rpy, (list, tuple)) and len(rpy) == 3
                and all(isinstance(x, (int, float)) and not isinstance(x, bool) and abs(x) <= 90.0 for x in rpy)):
            raise ValueError(f"[imu] mounting_rpy_deg: expected [roll, pitch, yaw] within +-90 deg, got {rpy!r}")
        object.__setattr__(self, "mounting_rpy_deg", tuple(float(x) for x in rpy))
        for k in ("delay_s", "filter_hz"):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0.0 <= v < math.inf:
                raise ValueError(f"[imu] {k}: expected a finite number >= 0, got {v!r}")
            object.__setattr__(self, k, float(v))
        if self.delay_s > self.MAX_DELAY_S:
            raise ValueError(f"[imu] delay_s: at most {self.MAX_DELAY_S:g} s, got {self.delay_s:g}")

    @classmethod
    def split(cls, imu: dict) -> tuple[Installation, dict]:
        """A scenario's [imu] table as (its installation keys, the rest: ``ImuErrorConfig``'s)."""
        inst = cls(**{k: v for k, v in imu.items() if k in cls.KEYS})
        return inst, {k: v for k, v in imu.items() if k not in cls.KEYS}

    @property
    def active(self) -> bool:
        return self != Installation()

    def C_bm(self) -> np.ndarray:
        """(3, 3) IMU frame -> car body frame (RFU)."""
        roll, pitch, yaw = (x * _DEG for x in self.mounting_rpy_deg)
        return earth.euler_to_dcm(yaw, pitch, roll)

    def _phi(self, rate_hz: float) -> float:
        return math.exp(-2.0 * math.pi * self.filter_hz / rate_hz) if self.filter_hz > 0.0 else 0.0

    def transport_s(self, rate_hz: float) -> float:
        """The transport delay, s: ``delay_s`` less the filter's low-frequency group delay at rate_hz."""
        phi = self._phi(rate_hz)
        out = self.delay_s - phi / (1.0 - phi) / rate_hz
        if out < 0.0:
            raise ValueError(f"[imu] delay_s: {self.delay_s:g} s is less than the {self.filter_hz:g} Hz filter's "
                             f"own delay ({self.delay_s - out:.4f} s)")
        return out

    def sense(self, omega_b: np.ndarray, f_b: np.ndarray, rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
        """The rate (rad/s) and specific force (m/s^2), (n, 3) in the car's body frame at the delayed times, as the
        IMU's axes see them through its filter."""
        C = self.C_bm()
        out = np.concatenate([rows.dot(omega_b, C), rows.dot(f_b, C)], axis=1)
        phi = self._phi(rate_hz)
        if phi > 0.0:
            out = lowpass(out, phi)
        return out[:, :3], out[:, 3:]


def _si_magnitudes(cfg: ImuErrorConfig) -> dict[str, dict[str, float]]:
    """Error magnitudes per triad in SI units (rad/s or m/s^2; fractions; radians; volts)."""
    return {
        "gyro": {
            "noise_density": cfg.gyro_noise_density_dps_rthz * _DEG,
            "bias_instability": cfg.gyro_bias_instability_dps * _DEG,
            "turn_on_bias": cfg.gyro_turn_on_bias_dps * _DEG,
            "scale_factor": cfg.gyro_scale_factor_ppm * 1e-6,
            "misalignment": cfg.gyro_misalignment_mrad * 1e-3,
            "zero_bias_V": cfg.gyro_zero_bias_V,
            "gm_sigma": cfg.gyro_gm_sigma_dps * _DEG,
        },
        "accel": {
            "noise_density": cfg.accel_noise_density_ug_rthz * _UG,
            "bias_instability": cfg.accel_bias_instability_ug * _UG,
            "turn_on_bias": cfg.accel_turn_on_bias_ug * _UG,
            "scale_factor": cfg.accel_scale_factor_ppm * 1e-6,
            "misalignment": cfg.accel_misalignment_mrad * 1e-3,
            "zero_bias_V": cfg.accel_zero_bias_V,
            "gm_sigma": cfg.accel_gm_sigma_ug * _UG,
        },
    }


def _misalignment_error(rng: np.random.Generator, sigma: float) -> np.ndarray:
    """(3,3) misalignment error E: independent off-diagonal entries, zero diagonal."""
    E = rng.normal(0.0, sigma, (3, 3))
    np.fill_diagonal(E, 0.0)
    return E


def gain(realised: dict[str, np.ndarray], name: str) -> np.ndarray:
    """The (3, 3) matrix a ``name`` ("gyro", "accel") triad of ``imu_counts``' ``realised`` errors applies to the
    true signal: (I + scale factor) (I + misalignment)."""
    return (np.eye(3) + np.diag(realised[f"{name}_scale_factor"])) @ (np.eye(3) + realised[f"{name}_misalignment"])


@dataclass(frozen=True)
class ImuErrorDraws:
    """The random part of ``imu_counts``, drawn before the true signal is known (``draw_errors``): the constant
    errors (``realised``' gyro_/accel_ turn_on_bias, scale_factor, misalignment, zero_bias_V) and, at the n sample
    times, the unit flicker (n, 6), the white noise scaled to each sample interval (n, 6) and the unit coloured
    noise (n, 6), None when both its sigmas are 0; columns gyro x, y, z then accel x, y, z."""

    t_s: np.ndarray
    realised: dict[str, np.ndarray]
    flicker: np.ndarray
    white: np.ndarray
    coloured: np.ndarray | None


def draw_errors(t_s: np.ndarray, cfg: ImuErrorConfig, rng: np.random.Generator) -> ImuErrorDraws:
    """``imu_counts``' draws at the true sample times t_s (n,), s, strictly increasing, in its order: the same
    seed gives the same draws. They need no true signal, so a caller may draw them while it computes that."""
    t_s = np.asarray(t_s, dtype=np.float64)
    n = t_s.shape[0]
    if n < 2:
        raise ValueError("imu_counts: need t_s (n,), omega_ib_b (n,3), f_b (n,3) with n >= 2")
    dt = np.diff(t_s)
    if np.any(dt <= 0.0):
        raise ValueError("imu_counts: t_s must be strictly increasing")
    dt = np.concatenate([dt[:1], dt])
    mag = _si_magnitudes(cfg)
    realised: dict[str, np.ndarray] = {}
    for name, m in mag.items():
        realised[f"{name}_turn_on_bias"] = rng.normal(0.0, m["turn_on_bias"], 3)
        realised[f"{name}_scale_factor"] = rng.normal(0.0, m["scale_factor"], 3)
        realised[f"{name}_misalignment"] = _misalignment_error(rng, m["misalignment"])
        realised[f"{name}_zero_bias_V"] = rng.normal(0.0, m["zero_bias_V"], 3)
    flicker = flicker_noise(t_s - t_s[0], 6, cfg.bias_corr_time_min_s, cfg.bias_corr_time_max_s, rng)
    white = rng.standard_normal((n, 6)) / np.sqrt(dt)[:, None]
    coloured = None
    if mag["gyro"]["gm_sigma"] > 0.0 or mag["accel"]["gm_sigma"] > 0.0:
        coloured = gauss_markov(t_s, cfg.gm_tau_s, rng.standard_normal((n, 6)))
    return ImuErrorDraws(t_s, realised, flicker, white, coloured)


def imu_counts(
    t_s: np.ndarray,
    omega_ib_b: np.ndarray,
    f_b: np.ndarray,
    cfg: ImuErrorConfig,
    cal: Calibration,
    rng: np.random.Generator,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Simulate the DAQ ADC counts of a MEMS IMU.

    t_s: (n,) true sample times, s, increasing (any offset; only differences are used).
    omega_ib_b: (n,3) true angular rate, rad/s; f_b: (n,3) true specific force, m/s^2; body frame RFU.
    cal: the nominal calibration the recording will be converted with.
    Returns (counts (n,6) int32, realised) where realised holds the drawn errors:
      gyro_turn_on_bias (3,) rad/s, accel_turn_on_bias (3,) m/s^2, *_scale_factor (3,) (fraction),
      *_misalignment (3,3) (E), *_zero_bias_V (3,) V, gyro_bias (n,3) rad/s and accel_bias (n,3) m/s^2
      (turn-on + flicker + electrical offset, as seen through the nominal calibration), saturated (6,);
      with coloured noise also gyro_coloured (n,3) rad/s and accel_coloured (n,3) m/s^2.
    The draws come from rng in a fixed order: the same seed gives identical counts.
    """
    return apply_errors(draw_errors(t_s, cfg, rng), omega_ib_b, f_b, cfg, cal)


def apply_errors(draws: ImuErrorDraws, omega_ib_b: np.ndarray, f_b: np.ndarray, cfg: ImuErrorConfig,
                 cal: Calibration) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """``imu_counts`` of the true rate omega_ib_b (n, 3), rad/s, and specific force f_b (n, 3), m/s^2, at the
    sample times of ``draws`` (``draw_errors`` with the same ``cfg``): counts (n, 6) int32 and realised."""
    n = draws.t_s.shape[0]
    omega_ib_b, f_b = np.asarray(omega_ib_b, np.float64), np.asarray(f_b, np.float64)
    if omega_ib_b.shape != (n, 3) or f_b.shape != (n, 3):
        raise ValueError("imu_counts: need t_s (n,), omega_ib_b (n,3), f_b (n,3) with n >= 2")
    x_true = {"gyro": omega_ib_b, "accel": f_b}
    nominal = {"gyro": cal.gyro, "accel": cal.accel}
    realised = dict(draws.realised)
    measured, true_cal = {}, {}
    for j, (name, m) in enumerate(_si_magnitudes(cfg).items()):
        cols = slice(3 * j, 3 * j + 3)
        # summed in place, each term in its turn: these are a whole drive's samples
        bias = m["bias_instability"] * draws.flicker[:, cols]
        bias += realised[f"{name}_turn_on_bias"]
        measured[name] = rows.dot(x_true[name], gain(realised, name).T)
        measured[name] += bias
        measured[name] += m["noise_density"] * draws.white[:, cols]
        if draws.coloured is not None:
            realised[f"{name}_coloured"] = m["gm_sigma"] * draws.coloured[:, cols]
            measured[name] += realised[f"{name}_coloured"]
        nom = nominal[name]
        bias_V = nom.bias_V + realised[f"{name}_zero_bias_V"]
        true_cal[name] = SensorTriadCal(nom.sensitivity, bias_V, nom.misalignment)
        bias += nom.to_si(bias_V)
        realised[f"{name}_bias"] = bias  # as seen through the nominal calibration
    counts, realised["saturated"] = to_counts(Calibration(**true_cal), measured["gyro"], measured["accel"])
    return counts, realised
