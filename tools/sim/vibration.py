"""A car's vibration as its IMU feels it: the engine at idle and under way, the wheels and the road.

A scenario's ``[vibration]`` table (absent: no vibration) adds zero-mean oscillations to the true rate and
specific force at the IMU, in the car's body frame (RFU), on top of the trajectory's smooth motion. Their
displacements (microns) and angles (milli-degrees) are left out of the truth topics: the car's motion is the
smooth one, the vibration is what a filter sees as noise. Three sources:

- **engine**: orders 0.5, 1 and 2 of the crankshaft rotation, with amplitude shares 0.3 : 0.5 : 1 (a
  four-stroke four-cylinder fires twice a revolution, order 2 dominates). The engine speed is
  ``vehicle.engine_rpm`` (idle rpm standing, rising with the speed in one gear: the law of the simulated CAN
  bus's ``ENGINE_RPM``). RMS ``engine_gyro_dps`` and ``engine_accel_mps2`` at every speed: a parked car with the
  engine idling shakes as much as a driving one;
- **wheels**: orders 1 and 2 of the wheel rotation, speed / (2 pi ``tyre_radius_m``) (imbalance, out-of-round
  tyres), shares 1 : 0.5, RMS ``wheel_gyro_dps``, ``wheel_accel_mps2`` at ``ref_speed_mps``, in proportion to the
  speed;
- **road**: band-limited random motion (white noise through two first-order low-passes at ``road_hz``,
  independent per axis), RMS ``road_gyro_dps``, ``road_accel_mps2`` at ``ref_speed_mps``, in proportion to the
  speed.

Each harmonic's phase is the integral of its frequency, so its frequency follows the speed continuously, and
it moves along one direction in the body frame (drawn once per drive from the seed; no coning, no sculling):
the frequencies of the engine and wheel lines carry the speed. A figure is the RMS of the vector, the root of
the summed per-axis variances (what ``fusion.still.ImuSums.std`` measures), rad/s or m/s^2 in the SI form.
Speeds are the true horizontal speed at the IMU, m/s.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fieldlog.drive.tables import from_table
from fieldlog.tools.sim import sensors, vehicle

_DEG = math.pi / 180.0
ENGINE_ORDERS = ((0.5, 0.3), (1.0, 0.5), (2.0, 1.0))   # (order of the crankshaft rotation, amplitude share)
WHEEL_ORDERS = ((1.0, 1.0), (2.0, 0.5))                  # (order of the wheel rotation, amplitude share)


@dataclass(frozen=True)
class VibrationConfig:
    """The [vibration] table (module docstring): RMS of the vector, deg/s and m/s^2; radius m; Hz; m/s."""

    engine_gyro_dps: float = 1.0
    engine_accel_mps2: float = 0.15
    wheel_gyro_dps: float = 0.3
    wheel_accel_mps2: float = 0.2
    road_gyro_dps: float = 0.8
    road_accel_mps2: float = 0.5
    road_hz: float = 15.0
    tyre_radius_m: float = 0.31
    ref_speed_mps: float = 10.0

    def __post_init__(self) -> None:
        for k, v in self.__dict__.items():
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0.0:
                raise ValueError(f"[vibration] {k}: expected a finite number >= 0, got {v!r}")
            object.__setattr__(self, k, float(v))
        if min(self.road_hz, self.tyre_radius_m, self.ref_speed_mps) <= 0.0:
            raise ValueError("[vibration] road_hz, tyre_radius_m, ref_speed_mps: must be > 0")

    @classmethod
    def from_dict(cls, d: dict) -> VibrationConfig:
        """From a scenario's [vibration] table; unknown keys raise ConfigError naming them."""
        return from_table(cls, "vibration", dict(d))


def _directions(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 3) random unit vectors, one per harmonic."""
    u = rng.standard_normal((n, 3))
    return u / np.linalg.norm(u, axis=1, keepdims=True)


def _lines(t_s: np.ndarray, freq_hz: np.ndarray, orders, rms: np.ndarray, rng: np.random.Generator
           ) -> tuple[np.ndarray, np.ndarray]:
    """Harmonics ``orders`` ((order, share), ...) of a rotation at freq_hz (n,) Hz at times t_s (n,) s: (rate
    (n, 3) rad/s, force (n, 3) m/s^2), of RMS rms[:, 0] and rms[:, 1] (n, 2) at each sample."""
    phase0 = np.concatenate([[0.0], np.cumsum(0.5 * (freq_hz[1:] + freq_hz[:-1]) * np.diff(t_s))]) * 2.0 * math.pi
    share = np.array([s for _, s in orders])
    share = share / math.sqrt(float(np.sum(share ** 2)))
    out = []
    for j in range(2):
        dirs = _directions(rng, len(orders))
        phi = rng.uniform(0.0, 2.0 * math.pi, len(orders))
        x = np.zeros((len(t_s), 3))
        for (order, _), s, d, p in zip(orders, share, dirs, phi):
            x += (math.sqrt(2.0) * s * rms[:, j] * np.sin(order * phase0 + p))[:, None] * d
        out.append(x)
    return out[0], out[1]


def _road(t_s: np.ndarray, cfg: VibrationConfig, scale: np.ndarray, rng: np.random.Generator
          ) -> tuple[np.ndarray, np.ndarray]:
    """Band-limited random rate (rad/s) and force (m/s^2), (n, 3) each, RMS ``road_*`` x scale (n,)."""
    dt = float(np.median(np.diff(t_s)))
    phi = math.exp(-2.0 * math.pi * cfg.road_hz * dt)
    z = rng.standard_normal((len(t_s), 6))
    zero = np.zeros(6)
    y = sensors.lowpass(sensors.lowpass(z, phi, zero), phi, zero)
    # white noise through two first-order sections: impulse response (1-phi)^2 (k+1) phi^k, summed squares
    gain2 = (1.0 - phi) ** 4 * (1.0 + phi * phi) / (1.0 - phi * phi) ** 3
    y /= math.sqrt(3.0 * gain2)      # unit RMS of the 3-vector
    return (cfg.road_gyro_dps * _DEG * scale[:, None] * y[:, :3],
            cfg.road_accel_mps2 * scale[:, None] * y[:, 3:])


def vibration(t_s: np.ndarray, speed_mps: np.ndarray, cfg: VibrationConfig, rng: np.random.Generator
              ) -> tuple[np.ndarray, np.ndarray]:
    """The vibration at the IMU at times t_s (n,) s with the true speed speed_mps (n,) m/s: (rate (n, 3) rad/s,
    specific force (n, 3) m/s^2), body RFU (module docstring). The draws come from rng in a fixed order."""
    t_s = np.asarray(t_s, float)
    v = np.abs(np.asarray(speed_mps, float))
    rel = v / cfg.ref_speed_mps
    engine_hz = vehicle.engine_rpm(v) / 60.0
    ones = np.ones_like(v)
    w_e, f_e = _lines(t_s, engine_hz, ENGINE_ORDERS,
                      np.stack([cfg.engine_gyro_dps * _DEG * ones, cfg.engine_accel_mps2 * ones], axis=1), rng)
    w_w, f_w = _lines(t_s, v / (2.0 * math.pi * cfg.tyre_radius_m), WHEEL_ORDERS,
                      np.stack([cfg.wheel_gyro_dps * _DEG * rel, cfg.wheel_accel_mps2 * rel], axis=1), rng)
    w_r, f_r = _road(t_s, cfg, rel, rng)
    return w_e + w_w + w_r, f_e + f_w + f_r
