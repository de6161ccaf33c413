"""Vehicle-motion aids of a car: measurements that need no GPS, so they act in outages too.

At every GPS epoch time, before the GPS update, the non-holonomic constraint (body lateral and vertical
velocity 0, ``kf.nhc_measurement``), or, when the vehicle stood still over the epoch interval
(``fusion.align.still``: slow, steady, and its mean rate and specific force those of standing still, so a car
creeping through a slow turn is not), a zero-velocity + zero-angular-rate update (``kf.stationary_measurement``).
The engine
gives the measurement to the filter's ``update_aid`` and feeds the estimate back like a GPS update.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from fieldlog.fusion import earth, kf
from fieldlog.fusion.align import ImuSums, StillRun
from fieldlog.fusion.errmodel import BA, BG
from fieldlog.fusion.ins import NavState

if TYPE_CHECKING:
    from fieldlog.fusion.config import FusionConfig

_DEG = math.pi / 180.0


def vehicle_aid(cfg: FusionConfig, nav: NavState, v_gps: np.ndarray, speed: tuple[float, float], interval: ImuSums,
                stop: StillRun, bg: np.ndarray, ba: np.ndarray, P: np.ndarray, imu_dt: float
                ) -> kf.Measurement | None:
    """The aid of this epoch: stationary (ZUPT + ZARU) when the vehicle stood still over the interval since the
    last epoch (``fusion.align.still``), else the non-holonomic constraint; None when disabled.

    v_gps (3,) the GPS velocity at this epoch, ENU m/s, NaN when there is none (the INS speed decides then);
    speed: the GPS speed of the interval and its limit, m/s (``fusion.align.GpsSpeed``); interval: the IMU sums since the last epoch (raw rates); stop: the current run of
    still intervals (``fusion.align.StillRun``, updated here); bg, ba (3,) the bias
    estimates, rad/s and m/s^2; P (15, 15) the filter covariance (the sigmas of the still references); imu_dt
    the IMU sample period, s."""
    has_gps = np.isfinite(v_gps[:2]).all()
    slow = (float(np.hypot(v_gps[0], v_gps[1])) < cfg.aids.static_speed_mps if has_gps
            else float(np.linalg.norm(nav.v_n)) < cfg.still.still_speed_mps)
    if not (math.isfinite(speed[0]) or float(np.linalg.norm(nav.v_n)) < cfg.still.still_speed_mps):
        stop.reset()
    elif cfg.aids.zupt and stop.update(interval, speed, *_still_references(nav, bg, ba, P)):
        return kf.stationary_measurement(nav, interval.sum_w / interval.n - bg, interval.n * imu_dt,
                                         cfg.aids.zupt_sigma_mps, cfg.sensor.gyro_noise_dps_rthz * _DEG)
    if cfg.aids.nhc and not slow:
        return kf.nhc_measurement(nav, cfg.aids.nhc_sigma_mps)
    return None


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
