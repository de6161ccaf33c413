"""Initial alignment of the INS from a standing start and the first GPS epochs, and the still detector.

Alignment: levelling from the accelerometers while the vehicle stands still (GPS speed below
``static_speed_mps`` at both ends of a GPS interval), plus heading from the GPS course at the first epoch
where the speed reaches ``align_speed_mps``; position and velocity come from that epoch. The static mean
gyro output minus the Earth rate gives the initial gyro bias. Without a static start roll and pitch start at
zero with a large variance, and the gyro bias at zero.

Still detection (:func:`still`): the vehicle stood still over a GPS interval when it was slow and the specific
force and rate varied little; the ZUPT aid (``fusion.aids``) uses it.

Frames: navigation ENU, body RFU; IMU sums in rad/s and m/s^2.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from fieldlog.fusion import earth, ins

if TYPE_CHECKING:
    from fieldlog.fusion.engine import FusionConfig

_DEG = math.pi / 180.0
_UG = 9.80665e-6


@dataclass
class ImuSums:
    """Sums of IMU samples over an interval: rate (rad/s) and specific force (m/s^2), body RFU, and squares."""

    sum_w: np.ndarray = field(default_factory=lambda: np.zeros(3))
    sum_f: np.ndarray = field(default_factory=lambda: np.zeros(3))
    n: int = 0
    sum_ww: np.ndarray = field(default_factory=lambda: np.zeros(3))  # squares: the interval's variances
    sum_ff: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def std(self, total: np.ndarray, squares: np.ndarray) -> float:
        """Root of the summed per-axis variances of the samples, e.g. std(sum_f, sum_ff)."""
        m = total / max(self.n, 1)
        return math.sqrt(max(float(np.sum(squares / max(self.n, 1) - m * m)), 0.0))

    def add(self, w: np.ndarray, f: np.ndarray, i0: int, i1: int) -> None:
        """Add samples (i0, i1] of w, f (n, 3)."""
        ws, fs = w[i0 + 1:i1 + 1], f[i0 + 1:i1 + 1]
        self.sum_w += ws.sum(axis=0)
        self.sum_f += fs.sum(axis=0)
        self.sum_ww += np.einsum("ij,ij->j", ws, ws)
        self.sum_ff += np.einsum("ij,ij->j", fs, fs)
        self.n += max(i1 - i0, 0)


def still(cfg: FusionConfig, interval: ImuSums, slow: bool) -> bool:
    """Whether the vehicle stood still over a GPS interval: slow (GPS or INS speed, the caller's test), at
    least 50 samples, and specific force and rate varying less than ``still_accel_std_mps2`` and
    ``still_gyro_std_dps``."""
    return (slow and interval.n >= 50 and interval.std(interval.sum_f, interval.sum_ff) < cfg.still_accel_std_mps2
            and interval.std(interval.sum_w, interval.sum_ww) < cfg.still_gyro_std_dps * _DEG)


@dataclass
class Aligned:
    """The result of the alignment: the INS state, the initial gyro bias (rad/s, body) and covariance P0 (15, 15)."""

    nav: ins.NavState
    bg: np.ndarray
    P0: np.ndarray


class Alignment:
    """Accumulates the static IMU data before the alignment epoch and builds the initial state there."""

    def __init__(self, cfg: FusionConfig) -> None:
        self.cfg = cfg
        self.lever = cfg.lever_rfu()
        self._static = ImuSums()
        self._last_speed = math.inf

    def epoch(self, ep: dict, usable: bool, v: np.ndarray, interval: ImuSums, t_k: float, t_ref_ns: int
              ) -> Aligned | None:
        """A GPS epoch before the alignment: ep (``engine`` epoch dict), usable fix, its velocity v (3,) ENU m/s
        (NaN when unknown), the IMU sums of the interval that ends here, the current sample's time t_k (s from
        t_ref_ns). Returns the initial state when this epoch aligns the INS, else None."""
        speed = float(np.hypot(v[0], v[1])) if np.isfinite(v[:2]).all() else math.inf
        if speed < self.cfg.static_speed_mps and self._last_speed < self.cfg.static_speed_mps:
            self._static.sum_w += interval.sum_w
            self._static.sum_f += interval.sum_f
            self._static.n += interval.n
        self._last_speed = speed
        if usable and math.isfinite(ep["h"]) and math.isfinite(speed) and speed >= self.cfg.align_speed_mps:
            return self._initialise(ep, v, t_k, t_ref_ns)
        return None

    def _initialise(self, ep: dict, v: np.ndarray, t_k: float, t_ref_ns: int) -> Aligned:
        c = self.cfg
        heading = math.atan2(v[0], v[1])
        static = self._static.n >= 200
        if static:
            fm = self._static.sum_f / self._static.n
            pitch, roll = math.atan2(fm[1], math.hypot(fm[0], fm[2])), math.atan2(-fm[0], fm[2])
        else:
            pitch = roll = 0.0
        C = earth.euler_to_dcm(heading, pitch, roll)
        bg = np.zeros(3)
        if static:
            bg = self._static.sum_w / self._static.n - C.T @ earth.omega_ie_n(ep["lat"])
        arm = C @ self.lever
        rm, rn = earth.principal_radii(ep["lat"], ep["h"])
        dt = t_k - (ep["t_ns"] - t_ref_ns) * 1e-9
        d_enu = v * dt - arm
        v0 = np.array([v[0], v[1], 0.0])
        nav = ins.NavState(t_k, ep["lat"] + d_enu[1] / rm, ep["lon"] + d_enu[0] / (rn * math.cos(ep["lat"])),
                           ep["h"] + d_enu[2], v0, earth.dcm_to_quat(C))
        speed = math.hypot(v[0], v[1])
        sd_level = (c.init_level_sigma_deg if static else 5.0) * _DEG
        sd_head = math.hypot(c.init_heading_sigma_deg * _DEG, math.sqrt(max(_course_var(ep), 0.01)) / speed)
        sd_bg = (c.init_gyro_bias_sigma_dps if static else 0.1) * _DEG
        pos_var = np.diag(ep["pos_cov"]).copy()
        pos_var[~np.isfinite(pos_var) | (pos_var <= 0)] = 25.0
        P0 = np.diag(np.concatenate([pos_var, np.full(3, c.init_vel_sigma_mps ** 2),
                                     [sd_level ** 2, sd_level ** 2, sd_head ** 2], np.full(3, sd_bg ** 2),
                                     np.full(3, (c.init_accel_bias_sigma_ug * _UG) ** 2)]))
        return Aligned(nav, bg, P0)


def _course_var(ep: dict) -> float:
    """Variance (m/s)^2 of a horizontal GPS velocity component at an epoch: the receiver's, else that of the
    difference of two fixes taken 1 s apart (twice the fix's horizontal variance; 25 m^2 when it has none)."""
    var = float(ep["vel_cov"][0, 0])
    if math.isfinite(var):
        return var
    pos = np.diag(ep["pos_cov"])[:2]
    return 2.0 * float(np.nanmax(pos)) if np.isfinite(pos).any() else 50.0
