"""Vehicle-motion aids of a car: measurements that need no GPS, so they act in outages too.

At every GPS epoch time, before the GPS update, the non-holonomic constraint (body lateral and vertical
velocity 0, ``kf.nhc_measurement``), or, when the vehicle stood still over the epoch interval
(``fusion.align.still``), a zero-velocity + zero-angular-rate update (``kf.stationary_measurement``). The engine
gives the measurement to the filter's ``update_aid`` and feeds the estimate back like a GPS update.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from fieldlog.fusion import kf
from fieldlog.fusion.align import ImuSums, still
from fieldlog.fusion.ins import NavState

if TYPE_CHECKING:
    from fieldlog.fusion.engine import FusionConfig

_DEG = math.pi / 180.0


def vehicle_aid(cfg: FusionConfig, nav: NavState, v_gps: np.ndarray, interval: ImuSums, bg: np.ndarray,
                imu_dt: float) -> kf.Measurement | None:
    """The aid of this epoch: stationary (ZUPT + ZARU) when the vehicle stood still over the interval since the
    last epoch, else the non-holonomic constraint; None when disabled.

    v_gps (3,) the epoch's GPS velocity, ENU m/s, NaN when there is none (the INS speed decides then);
    interval: the IMU sums since the last epoch (raw rates); bg (3,) the gyro bias, rad/s; imu_dt the IMU
    sample period, s."""
    slow = (float(np.hypot(v_gps[0], v_gps[1])) < cfg.static_speed_mps if np.isfinite(v_gps[:2]).all()
            else float(np.linalg.norm(nav.v_n)) < cfg.still_speed_mps)
    if cfg.zupt and still(cfg, interval, slow):
        return kf.stationary_measurement(nav, interval.sum_w / interval.n - bg, interval.n * imu_dt,
                                         cfg.zupt_sigma_mps, cfg.gyro_noise_dps_rthz * _DEG)
    if cfg.nhc and not slow:
        return kf.nhc_measurement(nav, cfg.nhc_sigma_mps)
    return None
