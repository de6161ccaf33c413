"""First-pass estimates of how the IMU sits in the car: its mounting angles to the car's body frame and its time
offset to the GPS, each with its sigma, from a GPS-aided INS solution run without the vehicle aids (the NHC,
the odometer and the ZUPT assume the IMU's axes are the car's, and would pull the attitude onto that
assumption) and the receiver's velocities.

**Time offset** (``time_offset``): the IMU's rate about the up of its own frame (the direction of its mean
specific force: a car's accelerations average out over a drive), integrated (``GyroTrack``), turns with the
car's heading d after the car when the IMU's samples are stamped d late; the receiver's course (the direction of
its horizontal velocity, at speeds of ``MIN_SPEED_MPS`` or more) is the car's at its epoch. The course changes
between consecutive epochs are compared with the gyro's heading changes over the same intervals shifted by d
(the mounting's constant yaw cancels in a difference; a constant rate, the gyro bias, is fitted out), d searched
over +-``MAX_OFFSET_S`` and refined by a parabola through the least squares; sigma from the residuals and the
cost's curvature (the summed squared changes of yaw rate across the intervals): turns that begin and end carry
the offset, straights and steady turns do not. The gyro's own heading, not the INS's: the GPS updates turn the
INS heading at the epochs. The yaw rate only: the receiver's acceleration is noisier at 1 Hz.

**Mounting** (``mounting``): the car's attitude is taken from the velocity, heading = the course, pitch = the
flight-path angle, roll = 0 (a car does not side-slip at its rear axle and rolls only in turns, as much either
way; the IMU's point ahead of the rear axle by r moves at an angle atan(yaw rate r / speed) to the car's heading
in a turn, taken off), so C_bm = C_bn^T C_mn (IMU frame -> car body frame, RFU) at each row of an aids-off
solution, its IMU on the GPS's time (the time offset applied: a late IMU turns the INS heading against the
course in a turn) and smoothed (the RTS pass: the forward filter's heading error in the straights is of the
order of the mounting's wanted accuracy), where the car moves at ``MIN_SPEED_MPS`` or more and turns slower
than ``MAX_YAW_RATE``, read as [roll, pitch, yaw] (``fusion.earth``'s conventions:
``C_bm = euler_to_dcm(yaw, pitch, roll)``). The angles are averaged over ``BLOCK_S`` blocks; sigma, in
quadrature: the blocks' spread over the root of their number, the INS's own attitude sigma (level for roll and
pitch, heading for yaw: an error common to every row, not averaged away), for pitch the flight-path angle's
(the INS's up-velocity sigma over the speed: a receiver without vertical velocity leaves it to the heights) and
for roll ``ROLL_ROAD_DEG`` (a road's crossfall tilts the car one way for a whole drive). Pitch and yaw are what the NHC and the odometer
need; roll is only as good as the road is level.

Times in s, angles in rad inside and degrees in the results; ENU navigation frame, body RFU.
"""
from __future__ import annotations

import math

import numpy as np

from fieldlog.fusion import earth
from fieldlog.fusion.types import Solution

MIN_SPEED_MPS = 3.0  # the course is the car's heading from this speed
MAX_YAW_RATE = 0.2  # rad/s: the rows of the mounting, sharp turns left out (side slip, roll)
BLOCK_S = 10.0  # s: the mounting's averaging blocks
ROLL_ROAD_DEG = 1.0  # deg: a road's crossfall, the roll's floor
MAX_OFFSET_S = 0.5  # s: the time offsets searched
_STEP_S = 0.001


def _course(v_n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(course rad, horizontal speed m/s) of ENU velocities (n, 3)."""
    return np.arctan2(v_n[:, 0], v_n[:, 1]), np.hypot(v_n[:, 0], v_n[:, 1])


class GyroTrack:
    """The integral of the IMU's rate over a drive, kept at about ``HZ`` (the heading changes ``time_offset``
    reads off it over any interval), and the mean specific force (the IMU frame's up: a car's accelerations
    average out over a drive). Fed block by block; memory grows by 32 bytes per kept sample."""

    HZ = 50.0

    def __init__(self) -> None:
        self._t: list[np.ndarray] = []
        self._angle: list[np.ndarray] = []
        self._last: tuple[int, np.ndarray, np.ndarray] | None = None  # t_ns, rate (3,), integral (3,)
        self.sum_f = np.zeros(3)
        self.n = 0
        self._about: tuple[int, np.ndarray, np.ndarray] | None = None  # n, stamps, integral about the mean up

    def add(self, t_ns: np.ndarray, omega_m: np.ndarray, f_m: np.ndarray) -> None:
        """Add IMU samples.

        Parameters
        ----------
        t_ns : (n,) their stamps, UTC ns.
        omega_m : (n, 3) rate, rad/s, IMU frame.
        f_m : (n, 3) specific force, m/s^2, IMU frame.
        """
        if not len(t_ns):
            return
        t = np.asarray(t_ns, np.int64)
        w = np.asarray(omega_m, float)
        if self._last is not None:
            t = np.concatenate([[self._last[0]], t])
            w = np.concatenate([self._last[1][None], w])
            start = self._last[2]
        else:
            start = np.zeros(3)
        steps = 0.5 * (w[1:] + w[:-1]) * (np.diff(t) * 1e-9)[:, None]
        angle = start + np.concatenate([np.zeros((1, 3)), np.cumsum(steps, axis=0)])
        every = max(int(round(1e9 / self.HZ / max(float(np.median(np.diff(t))) if len(t) > 1 else 1e9, 1.0))), 1)
        keep = slice(1 if self._last is not None else 0, None, every)
        self._t.append(t[keep].copy())  # copies: a strided view would keep the block's every sample
        self._angle.append(angle[keep].copy())
        self._last = (int(t[-1]), w[-1].copy(), angle[-1].copy())
        self.sum_f += np.asarray(f_m, float).sum(axis=0)
        self.n += len(t_ns)

    def heading_change(self, a_ns: np.ndarray, b_ns: np.ndarray) -> np.ndarray:
        """The heading change over intervals: minus the integrated rate about the mean up.

        Parameters
        ----------
        a_ns, b_ns : (m,) the intervals' ends, UTC ns.

        Returns
        -------
        (m,) rad, clockwise.
        """
        if self._about is None or self._about[0] != self.n:  # joined once per state of the track, not per call
            t = np.concatenate(self._t) if self._t else np.zeros(0, np.int64)
            angle = np.concatenate(self._angle) if self._angle else np.zeros((0, 3))
            up = self.sum_f / max(np.linalg.norm(self.sum_f), 1e-12)
            self._about = (self.n, t, angle @ up)
        _, t, about_up = self._about
        return -(np.interp(b_ns, t, about_up) - np.interp(a_ns, t, about_up))

    @property
    def span_ns(self) -> tuple[int, int]:
        return (int(self._t[0][0]), int(self._last[0])) if self._t else (0, 0)


_CELLS = 1 << 18  # lag x interval residuals computed at once by time_offset


def time_offset(gyro: GyroTrack, t_gps_ns: np.ndarray, v_gps_n: np.ndarray) -> tuple[float, float] | None:
    """How late the IMU's stamps are against the GPS's (module docstring); a constant rate (the gyro bias, the Earth
    rate) is fitted with it.

    Parameters
    ----------
    gyro : the IMU's rate integral.
    t_gps_ns : (m,) the receiver's epochs, UTC ns.
    v_gps_n : (m, 3) its velocities, ENU m/s.

    Returns
    -------
    (d, sigma), s; None when the drive has too few moving epochs or the least squares lie at the edge of the
    search (too few turns: a straight flight).
    """
    tg = np.asarray(t_gps_ns, np.int64)
    if len(tg) < 12:
        return None
    course, speed = _course(np.asarray(v_gps_n, float))
    ok = np.isfinite(course) & (speed >= MIN_SPEED_MPS)
    lo, hi = gyro.span_ns
    margin = int(MAX_OFFSET_S * 1e9)
    dt = np.diff(tg) * 1e-9
    pair = ok[:-1] & ok[1:] & (dt < 1.5 * float(np.median(dt))) & (tg[:-1] - margin > lo) & (tg[1:] + margin < hi)
    k = np.flatnonzero(pair)
    if len(k) < 10:
        return None
    d_course = np.remainder(course[k + 1] - course[k] + math.pi, 2.0 * math.pi) - math.pi
    a, b, span = tg[k], tg[k + 1], dt[k]

    def _cost(d: np.ndarray) -> np.ndarray:
        """The squared residuals' sum at each lag of d (s), less the best constant rate."""
        shift = np.round(d * 1e9).astype(np.int64)[:, None]
        r = d_course - gyro.heading_change(a + shift, b + shift)
        r = r - span * (np.sum(r * span, axis=1, keepdims=True) / np.sum(span * span))
        return np.sum(r ** 2, axis=1)

    lags = np.arange(-MAX_OFFSET_S, MAX_OFFSET_S + 0.5 * _STEP_S, _STEP_S)
    per = max(1, _CELLS // len(k))  # lags at a time: memory bounded on a long drive
    cost = np.concatenate([_cost(lags[i:i + per]) for i in range(0, len(lags), per)])
    i = int(np.argmin(cost))
    if not 0 < i < len(lags) - 1:  # at the edge of the search: the turns do not show the offset
        return None
    c0, c1, c2 = cost[i - 1], cost[i], cost[i + 1]
    curv = c0 - 2.0 * c1 + c2
    if not curv > 0:
        return None
    d = float(lags[i] + 0.5 * _STEP_S * (c0 - c2) / curv)
    # cost(d) ~ c_min + S (d - d_hat)^2 with S = sum of squared sensitivities: curv = 2 S step^2
    s2 = curv / (2.0 * _STEP_S ** 2)
    return d, math.sqrt(float(c1) / max(len(k) - 2, 1) / s2)


def mounting(sol: Solution, lever_b: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """The IMU's mounting to the car's body frame (module docstring).

    Parameters
    ----------
    sol : the aids-off solution, its IMU on the GPS's time (smoothed: its attitude sigma is the estimate's floor).
    lever_b : (3,) IMU -> the rear axle's centre, IMU axes (taken as the car's), m; None: zero.

    Returns
    -------
    ([roll, pitch, yaw], their sigmas), deg (3,) each; None without enough driving.
    """
    if len(sol.t_ns) < 3:
        return None
    ts = (sol.t_ns - sol.t_ns[0]) * 1e-9
    course, speed = _course(sol.v_n)
    yaw_rate = np.gradient(np.unwrap(course), ts)
    sel = (speed >= MIN_SPEED_MPS) & (np.abs(yaw_rate) < MAX_YAW_RATE)
    if sel.sum() < 20:
        return None
    rows = np.flatnonzero(sel)
    C_mn = earth.quat_to_dcm(sol.q[rows])
    gamma = np.arctan2(sol.v_n[rows, 2], speed[rows])
    r_fwd = 0.0 if lever_b is None else float(lever_b[1])
    heading = course[rows] + np.arctan2(yaw_rate[rows] * r_fwd, speed[rows])  # the IMU's point swings out in turns
    C_bn = earth.euler_to_dcm(heading, gamma, np.zeros(len(rows)))
    C_bm = np.einsum("nji,njk->nik", C_bn, C_mn)
    yaw, pitch, roll = earth.dcm_to_euler(C_bm)
    rpy = np.stack([roll, pitch, np.remainder(yaw + math.pi, 2.0 * math.pi) - math.pi], axis=1)
    block = ((ts[rows] - ts[rows][0]) // BLOCK_S).astype(np.int64)
    n = np.bincount(block)
    used = n > 0
    means = np.stack([np.bincount(block, rpy[:, j])[used] / n[used] for j in range(3)], axis=1)
    spread = (means.std(axis=0, ddof=1) / math.sqrt(len(means)) if len(means) > 1
              else np.full(3, math.inf))
    sig = sol.sigma[rows]
    level = math.sqrt(float(np.mean(0.5 * (sig[:, 6] ** 2 + sig[:, 7] ** 2))))
    head = math.sqrt(float(np.mean(sig[:, 8] ** 2)))
    climb = math.sqrt(float(np.mean((sig[:, 5] / speed[rows]) ** 2)))  # the flight-path angle's, from the up velocity
    sigma = np.sqrt(spread ** 2 + np.array([level, math.hypot(level, climb), head]) ** 2
                    + np.array([math.radians(ROLL_ROAD_DEG), 0.0, 0.0]) ** 2)
    return np.degrees(means.mean(axis=0)), np.degrees(sigma)


def combine(prior: np.ndarray, prior_sigma: np.ndarray, estimate: np.ndarray, sigma: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
    """The configured mounting and the drive's estimate, each angle weighted by its inverse variance.

    Parameters
    ----------
    prior, prior_sigma : (3,) the configured [roll, pitch, yaw] and their 1-sigma, deg (a sigma of inf: none).
    estimate, sigma : (3,) the drive's (:func:`mounting`), deg.

    Returns
    -------
    ((3,) the combined angles, (3,) their 1-sigma), deg.
    """
    w0, w1 = 1.0 / np.square(prior_sigma), 1.0 / np.square(sigma)
    return (w0 * prior + w1 * estimate) / (w0 + w1), 1.0 / np.sqrt(w0 + w1)

