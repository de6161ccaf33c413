"""The data the fusion loop takes and gives: IMU and GPS blocks in, GPS epochs inside, solution rows and outage
windows out.

Times are int64 UTC nanoseconds; the navigation frame is ENU, the body frame RFU; latitude and longitude are
degrees in the blocks (as the drive stores them) and radians in an :class:`Epoch` and a :class:`Solution`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np


@dataclass
class ImuBlock:
    """IMU samples: t_ns (n,) int64 UTC, omega_ib_b (n, 3) rad/s, f_b (n, 3) m/s^2, body RFU."""

    t_ns: np.ndarray
    omega_ib_b: np.ndarray
    f_b: np.ndarray


@dataclass
class GpsBlock:
    """GPS epochs: t_ns (m,) UTC of the fix; lat_deg, lon_deg, h (m, ellipsoidal); pos_cov (m, 3, 3) ENU m^2;
    status (m,) NavSatFix status (-1 no fix); v_n (m, 3) ENU m/s (NaN where missing); vel_cov (m, 3, 3)."""

    t_ns: np.ndarray
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    h: np.ndarray
    pos_cov: np.ndarray
    status: np.ndarray
    v_n: np.ndarray
    vel_cov: np.ndarray

    @staticmethod
    def empty() -> GpsBlock:
        """A block without epochs.

        Returns
        -------
        GpsBlock
            Every field with length 0 and the class's shapes and dtypes (t_ns int64, status int8).
        """
        z = np.zeros(0)
        return GpsBlock(np.zeros(0, np.int64), z, z, z, np.zeros((0, 3, 3)), np.zeros(0, np.int8),
                        np.zeros((0, 3)), np.zeros((0, 3, 3)))

    def epochs(self) -> list[Epoch]:
        """The block's epochs as objects (1 Hz to 10 Hz: one Python object per epoch is cheap).

        Returns
        -------
        list of Epoch
            One per row, in the block's order: latitude and longitude in rad (degrees in the block).
        """
        return [Epoch(int(self.t_ns[i]), math.radians(float(self.lat_deg[i])), math.radians(float(self.lon_deg[i])),
                      float(self.h[i]), self.pos_cov[i], int(self.status[i]), self.v_n[i], self.vel_cov[i])
                for i in range(len(self.t_ns))]


@dataclass
class OdomBlock:
    """Wheel-speed odometry rows: t_ns (n,) int64 UTC ns; v (n,) the forward speed, m/s (negative in reverse);
    var (n,) its variance, (m/s)^2 (NaN: not given); wheels (n, 4) the speeds of the front left, front right, rear
    left and rear right wheels, m/s, signed as v (NaN, or None: the drive gives the forward speed alone)."""

    t_ns: np.ndarray
    v: np.ndarray
    var: np.ndarray
    wheels: np.ndarray | None = None


@dataclass
class Epoch:
    """One GPS epoch: t_ns UTC of the fix; lat, lon (rad), h (m, ellipsoidal; NaN: a fix without height);
    pos_cov (3, 3) ENU m^2; status (NavSatFix, -1 no fix); v_n (3,) ENU m/s (NaN where missing); vel_cov (3, 3)
    (m/s)^2; silent: a no-fix epoch standing in for a GPS silence (``fusion.outages.Silence``)."""

    t_ns: int
    lat: float
    lon: float
    h: float
    pos_cov: np.ndarray
    status: int
    v_n: np.ndarray
    vel_cov: np.ndarray
    silent: bool = False

    @staticmethod
    def silence(t_ns: int) -> Epoch:
        """A no-fix epoch at t_ns for a GPS silence.

        Parameters
        ----------
        t_ns : int, time of the epoch, UTC ns

        Returns
        -------
        Epoch
            Status -1, NaN position and velocity, ``silent`` True.
        """
        nan3, nan33 = np.full(3, np.nan), np.full((3, 3), np.nan)
        return Epoch(t_ns, math.nan, math.nan, math.nan, nan33, -1, nan3, nan33.copy(), silent=True)


@dataclass
class Solution:
    """Output rows: t_ns (n,), lat, lon (rad), h (m), v_n (n, 3), q (n, 4) [x, y, z, w] of C_bn,
    sigma (n, 15): position ENU m, velocity ENU m/s, attitude (phi E, N, U) rad, gyro bias rad/s, accelerometer
    bias m/s^2; bias (n, 6): the IMU bias estimate the row's INS ran with, gyro rad/s then accelerometer m/s^2,
    body RFU (``fusion.errmodel`` states 9:15 are its residual).

    local (n, 2, 12) or None: the distributed filter's local solutions (KF_I, KF_II), the INS corrected by that
    local estimate alone: lat, lon (rad), h (m), v_n (3) ENU m/s, sigma position ENU (3) m, velocity (3) m/s.

    status: the rows' :class:`Status` and, before the alignment, those of the output slots without a solution;
    None where nobody computed it (a solution put together from a file)."""

    t_ns: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    h: np.ndarray
    v_n: np.ndarray
    q: np.ndarray
    sigma: np.ndarray
    bias: np.ndarray
    local: np.ndarray | None = None
    status: Status | None = None

    @staticmethod
    def concat(parts: list[Solution]) -> Solution:
        """Rows of several solutions in order (the distributed filter's local solutions only if every non-empty
        part has them).

        Parameters
        ----------
        parts : list of Solution

        Returns
        -------
        Solution
            Empty (no rows) for no parts.
        """
        status = [p.status for p in parts if p.status is not None]
        status = Status.concat(status) if status else None
        if not parts:
            return Solution(np.zeros(0, np.int64), *(np.zeros(0),) * 3, np.zeros((0, 3)), np.zeros((0, 4)),
                            np.zeros((0, 15)), np.zeros((0, 6)))
        local = [p.local for p in parts if len(p.t_ns)]
        return Solution(*(np.concatenate([getattr(p, k) for p in parts]) for k in
                          ("t_ns", "lat", "lon", "h", "v_n", "q", "sigma", "bias")),
                        np.concatenate(local) if local and all(x is not None for x in local) else None, status)


@dataclass
class Status:
    """Solution status rows (``fusion.output.StatusBook``): t_ns (n,) int64 UTC; code (n,) uint8, an index of
    ``fusion.output.STATUS``; since_update_s (n,) s from the last GNSS update to the row (NaN before the first);
    sigma_h_m (n,) horizontal position sigma, m (NaN while aligning); nis (n,) mean normalised innovation square
    per degree of freedom of the last GNSS updates (NaN before any)."""

    t_ns: np.ndarray
    code: np.ndarray
    since_update_s: np.ndarray
    sigma_h_m: np.ndarray
    nis: np.ndarray

    @staticmethod
    def concat(parts: list[Status]) -> Status:
        """Rows of several status blocks in order.

        Parameters
        ----------
        parts : list of Status, at least one

        Returns
        -------
        Status
        """
        return Status(*(np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(Status)))

    def take(self, keep: np.ndarray) -> Status:
        """The rows where keep (n,) bool is True.

        Parameters
        ----------
        keep : (n,) bool ndarray

        Returns
        -------
        Status
        """
        return Status(*(getattr(self, f.name)[keep] for f in fields(Status)))


@dataclass
class Outage:
    """A GPS outage window [start_ns, end_ns) UTC; reason "injected", "no_fix", "low_quality" or "silent"."""

    start_ns: int
    end_ns: int
    reason: str
