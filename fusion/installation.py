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
over +-``MAX_OFFSET_S`` and refined by a parabola fitted to the least squares around their minimum; sigma from the
residuals and the parabola's curvature (the summed squared changes of yaw rate across the intervals), over a span
wider than the kept samples' spacing, whose interpolation kinks the cost: turns that begin and end carry
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
from typing import Iterable, Iterator

import numpy as np

from fieldlog.fusion import earth
from fieldlog.fusion.median import median
from fieldlog.fusion.rowfile import RowFile
from fieldlog.fusion.types import Solution

MIN_SPEED_MPS = 3.0  # the course is the car's heading from this speed
MAX_YAW_RATE = 0.2  # rad/s: the rows of the mounting, sharp turns left out (side slip, roll)
BLOCK_S = 10.0  # s: the mounting's averaging blocks
ROLL_ROAD_DEG = 1.0  # deg: a road's crossfall, the roll's floor
MAX_OFFSET_S = 0.5  # s: the time offsets searched
_STEP_S = 0.001
_FIT_S = 0.02  # s: the parabola through the least squares is fitted over +-this (one GyroTrack spacing)


def _course(v_n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(course rad, horizontal speed m/s) of ENU velocities (n, 3)."""
    return np.arctan2(v_n[:, 0], v_n[:, 1]), np.hypot(v_n[:, 0], v_n[:, 1])


class GyroTrack:
    """The integral of the IMU's rate over a drive, kept at about ``HZ`` (the heading changes ``time_offset``
    reads off it over any interval), and the mean specific force (the IMU frame's up: a car's accelerations
    average out over a drive). Fed block by block; the kept samples (32 bytes each) go to a temporary file
    (``fusion.rowfile.RowFile``) and are read back ``CHUNK`` at a time, so memory is bounded whatever the drive's length."""

    HZ = 50.0
    CHUNK = 1 << 16  # kept samples read back at a time
    _SAMPLE = np.dtype([("t_ns", "<i8"), ("angle", "<f8", 3)])  # UTC ns; the integral, rad, IMU frame

    def __init__(self) -> None:
        self._kept = RowFile(self._SAMPLE)
        self._first_ns = 0
        self._last: tuple[int, np.ndarray, np.ndarray] | None = None  # t_ns, rate (3,), integral (3,)
        self._every = 0  # every how many samples one is kept (0: not yet known), from the first steps
        self.sum_f = np.zeros(3)
        self.n = 0
        self._about: tuple[int, np.ndarray, np.ndarray] | None = None  # n, stamps, integral about up: one chunk

    def add(self, t_ns: np.ndarray, omega_m: np.ndarray, f_m: np.ndarray) -> None:
        """Add IMU samples. The track does not depend on how the drive is cut into blocks: the integral runs on
        from the last sample, and a sample is kept every ``HZ``-th of a second counted from the drive's first (the
        IMU's rate from the first 100 steps).

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
            self._first_ns = int(t[0])
        steps = 0.5 * (w[1:] + w[:-1]) * (np.diff(t) * 1e-9)[:, None]
        angle = np.cumsum(np.concatenate([start[None], steps]), axis=0)  # one running sum over the drive
        if not self._every and len(t) > 1:
            self._every = max(int(round(1e9 / self.HZ / max(median(np.diff(t[:101])), 1.0))), 1)
        every = self._every or 1
        first = self.n - 1 if self._last is not None else 0  # the drive's index of t[0]
        start = (-first) % every
        if self._last is not None and start == 0:
            start = every  # t[0] is the block before's last sample
        keep = slice(start, None, every)
        kept = np.empty(len(t[keep]), self._SAMPLE)
        kept["t_ns"], kept["angle"] = t[keep], angle[keep]
        self._kept.append(kept)
        self._last = (int(t[-1]), w[-1].copy(), angle[-1].copy())
        self.sum_f += np.asarray(f_m, float).sum(axis=0)
        self.n += len(t_ns)

    def close(self) -> None:
        """Delete the file of kept samples."""
        self._kept.close()

    def _chunks(self) -> Iterator[tuple[np.ndarray, np.ndarray, bool]]:
        """The kept samples' (stamps UTC ns, integral about the mean up rad, whether the last chunk), ``CHUNK`` + 1
        at a time, each chunk beginning at the last sample of the one before; a drive of one chunk is read once
        per state of the track."""
        if self._about is not None and self._about[0] == self.n:
            yield self._about[1], self._about[2], True
            return
        up = self.sum_f / max(np.linalg.norm(self.sum_f), 1e-12)
        n = len(self._kept)
        for i0 in range(0, max(n - 1, 1), self.CHUNK):
            i1 = min(i0 + self.CHUNK + 1, n)
            kept = self._kept.read(i0, i1)
            t, about_up = kept["t_ns"].copy(), np.ascontiguousarray(kept["angle"]) @ up
            if i0 == 0 and i1 == n:
                self._about = (self.n, t, about_up)
            yield t, about_up, i1 == n

    def heading_change(self, a_ns: np.ndarray, b_ns: np.ndarray) -> np.ndarray:
        """The heading change over intervals: minus the integrated rate about the mean up; each stamp interpolated
        in the chunk holding its two neighbouring samples (``np.interp`` over the whole track, to the bit).

        Parameters
        ----------
        a_ns, b_ns : (m,) the intervals' ends, UTC ns (any shape, the same for both).

        Returns
        -------
        (m,) rad, clockwise.
        """
        a, b = np.asarray(a_ns), np.asarray(b_ns)
        at_a, at_b = np.empty(a.shape), np.empty(b.shape)
        lo = None  # a chunk's stamps: from its first sample (the first chunk: all before) to its last (excluded)
        for t, about_up, last in self._chunks():
            for q, out in ((a, at_a), (b, at_b)):
                if lo is None and last:
                    out[...] = np.interp(q, t, about_up)
                    continue
                inside = np.ones(q.shape, bool) if lo is None else q >= lo
                if not last:
                    inside &= q < t[-1]
                out[inside] = np.interp(q[inside], t, about_up)
            lo = t[-1]
        return -(at_b - at_a)

    @property
    def span_ns(self) -> tuple[int, int]:
        return (self._first_ns, int(self._last[0])) if len(self._kept) else (0, 0)


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
    pair = ok[:-1] & ok[1:] & (dt < 1.5 * median(dt)) & (tg[:-1] - margin > lo) & (tg[1:] + margin < hi)
    k = np.flatnonzero(pair)
    if len(k) < 10:
        return None
    d_course = np.remainder(course[k + 1] - course[k] + math.pi, 2.0 * math.pi) - math.pi
    a, b, span = tg[k], tg[k + 1], dt[k]

    def _cost(d: np.ndarray) -> np.ndarray:
        """The squared residuals' sum at each lag of d (s), less the best constant rate. Each interval's lags are
        one row of the stamps interpolated: ``np.interp`` starts each search from the point the last one found,
        a step away (the values do not depend on the order)."""
        shift = np.round(d * 1e9).astype(np.int64)
        turned = gyro.heading_change(a[:, None] + shift, b[:, None] + shift)
        r = d_course - np.ascontiguousarray(turned.T)
        r = r - span * (np.sum(r * span, axis=1, keepdims=True) / np.sum(span * span))
        return np.sum(r ** 2, axis=1)

    lags = np.arange(-MAX_OFFSET_S, MAX_OFFSET_S + 0.5 * _STEP_S, _STEP_S)
    per = max(1, _CELLS // len(k))  # lags at a time: memory bounded on a long drive
    cost = np.concatenate([_cost(lags[i:i + per]) for i in range(0, len(lags), per)])
    i = int(np.argmin(cost))
    w = int(round(_FIT_S / _STEP_S))
    if not w <= i < len(lags) - w:  # at the edge of the search: the turns do not show the offset
        return None
    # cost(d) ~ c_min + S (d - d_hat)^2, S the sum of squared sensitivities: the parabola fitted over +-_FIT_S
    x = lags[i - w:i + w + 1] - lags[i]
    c2, c1, c0 = np.polyfit(x, cost[i - w:i + w + 1], 2)
    if not c2 > 0:
        return None
    d_hat = -c1 / (2.0 * c2)
    if abs(d_hat) > _FIT_S:
        return None
    c_min = c0 - c1 * c1 / (4.0 * c2)
    return float(lags[i] + d_hat), math.sqrt(max(float(c_min), 0.0) / max(len(k) - 2, 1) / float(c2))


def mounting(blocks: Iterable[Solution], lever_b: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """The IMU's mounting to the car's body frame (module docstring), reduced block by block (:class:`_Mounting`):
    the rows of any split of a drive give the same estimate, to the bit.

    Parameters
    ----------
    blocks : the aids-off solution's rows in time order, in blocks (a whole solution: ``[sol]``), its IMU on the
        GPS's time (smoothed: its attitude sigma is the estimate's floor).
    lever_b : (3,) IMU -> the rear axle's centre, IMU axes (taken as the car's), m; None: zero.

    Returns
    -------
    ([roll, pitch, yaw], their sigmas), deg (3,) each; None without enough driving.
    """
    sums = _Mounting(0.0 if lever_b is None else float(lever_b[1]))
    try:
        for sol in blocks:
            sums.add(sol.t_ns, sol.v_n, sol.q, sol.sigma)
        return sums.result()
    finally:
        sums.close()


def _unwrap_steps(dd: np.ndarray) -> np.ndarray:
    """``np.unwrap``'s corrections (rad) of the steps ``dd`` (rad) between consecutive angles."""
    ddmod = np.mod(dd + math.pi, 2.0 * math.pi) - math.pi
    np.copyto(ddmod, math.pi, where=(ddmod == -math.pi) & (dd > 0))
    correct = ddmod - dd
    np.copyto(correct, 0, where=np.abs(dd) < math.pi)
    return correct


class _Mounting:
    """:func:`mounting`'s reduction of row blocks: per row the yaw rate (``np.gradient`` of the unwrapped course,
    second-order central differences, one-sided at the drive's ends: each row waits for the next), the selected
    rows' angles summed per ``BLOCK_S`` block (the open block's sum carried into the next rows' ``np.bincount``, so
    the sums add in the order of the whole drive's) and the sigma terms per selected row spilled to a temporary
    file (``fusion.rowfile.RowFile``, 24 bytes each) for their means at the end. Memory is bounded by a block and the blocks' means
    (24 bytes per ``BLOCK_S``)."""

    def __init__(self, r_fwd: float) -> None:
        self.r_fwd = r_fwd  # m: the IMU ahead of the rear axle
        self.rows = 0
        self.t0 = 0  # the first row's stamp, UTC ns
        self.held: list[np.ndarray] = []  # the last row (its rate waits for the next): ts s, unwrapped course, v_n..
        self.course = 0.0  # rad: the last row's course, as it is
        self.turn = 0.0  # rad: the unwrapping's corrections summed to the last row
        self.before: tuple[float, float] | None = None  # (ts, unwrapped course) of the row before the last
        self.sel0: float | None = None  # the first selected row's ts
        self.open: tuple[int, np.ndarray, int] | None = None  # the last block: index, angle sums (3,), rows
        self.means: list[np.ndarray] = []  # the closed blocks' mean [roll, pitch, yaw], rad
        self.terms = RowFile(("<f8", 3))  # per selected row: level, heading and climb variances

    def close(self) -> None:
        """Delete the file of sigma terms."""
        self.terms.close()

    def add(self, t_ns: np.ndarray, v_n: np.ndarray, q: np.ndarray, sigma: np.ndarray) -> None:
        """Rows (``Solution``'s t_ns, v_n, q, sigma), after those added before."""
        if not len(t_ns):
            return
        if not self.rows:
            self.t0 = t_ns[0]
        course = _course(v_n)[0]
        if self.rows:
            turn = np.cumsum(np.concatenate([[self.turn], _unwrap_steps(np.diff(np.r_[self.course, course]))]))[1:]
            f = course + turn
        else:
            turn = np.concatenate([[0.0], np.cumsum(_unwrap_steps(np.diff(course)))])
            f = np.concatenate([course[:1], course[1:] + turn[1:]])
        self.rows, self.course, self.turn = self.rows + len(t_ns), float(course[-1]), float(turn[-1])
        rows = [(t_ns - self.t0) * 1e-9, f, v_n, q, sigma]
        if self.held:
            rows = [np.concatenate([h, r]) for h, r in zip(self.held, rows)]
        self.held = [r[-1:] for r in rows]
        if len(rows[0]) > 1:
            self._reduce(*(r[:-1] for r in rows), next_row=(float(rows[0][-1]), float(rows[1][-1])))

    def _reduce(self, ts: np.ndarray, f: np.ndarray, v_n: np.ndarray, q: np.ndarray, sigma: np.ndarray,
                next_row: tuple[float, float] | None) -> None:
        """Rows with their yaw rate, from their neighbours, ``self.before`` and ``next_row`` (ts, unwrapped course;
        None: the drive's last row)."""
        n = len(ts)
        ext_t, ext_f = [ts], [f]
        if self.before is not None:
            ext_t.insert(0, [self.before[0]]), ext_f.insert(0, [self.before[1]])
        if next_row is not None:
            ext_t.append([next_row[0]]), ext_f.append([next_row[1]])
        t, y = np.concatenate(ext_t), np.concatenate(ext_f)
        dx = np.diff(t)
        dx1, dx2 = dx[:-1], dx[1:]
        rate = np.empty(len(t))
        rate[1:-1] = (-dx2 / (dx1 * (dx1 + dx2)) * y[:-2] + (dx2 - dx1) / (dx1 * dx2) * y[1:-1]
                      + dx1 / (dx2 * (dx1 + dx2)) * y[2:])
        rate[0] = (y[1] - y[0]) / dx[0]
        rate[-1] = (y[-1] - y[-2]) / dx[-1]
        first = 0 if self.before is None else 1
        self.before = (float(ts[-1]), float(f[-1]))
        self._rows(ts, rate[first:first + n], v_n, q, sigma)

    def _rows(self, ts: np.ndarray, yaw_rate: np.ndarray, v_n: np.ndarray, q: np.ndarray, sigma: np.ndarray
              ) -> None:
        """The selected rows' angles into their blocks' sums, their sigma terms into ``terms``."""
        course, speed = _course(v_n)
        rows = np.flatnonzero((speed >= MIN_SPEED_MPS) & (np.abs(yaw_rate) < MAX_YAW_RATE))
        if not len(rows):
            return
        C_mn = earth.quat_to_dcm(q[rows])
        gamma = np.arctan2(v_n[rows, 2], speed[rows])
        heading = course[rows] + np.arctan2(yaw_rate[rows] * self.r_fwd, speed[rows])  # the IMU's point swings out
        C_bn = earth.euler_to_dcm(heading, gamma, np.zeros(len(rows)))
        C_bm = np.einsum("nji,njk->nik", C_bn, C_mn)
        yaw, pitch, roll = earth.dcm_to_euler(C_bm)
        rpy = np.stack([roll, pitch, np.remainder(yaw + math.pi, 2.0 * math.pi) - math.pi], axis=1)
        if self.sel0 is None:
            self.sel0 = float(ts[rows][0])
        block = ((ts[rows] - self.sel0) // BLOCK_S).astype(np.int64)
        base, sums, count = self.open if self.open is not None else (int(block[0]), np.zeros(3), 0)
        at = np.r_[0, block - base]  # the open block's sum first: 0 + sum + rows, as one bincount of every row
        total = np.stack([np.bincount(at, np.r_[sums[j], rpy[:, j]]) for j in range(3)], axis=1)
        n = np.bincount(block - base, minlength=len(total))
        n[0] += count
        used = n[:-1] > 0
        self.means.extend(total[:-1][used] / n[:-1][used, None])
        self.open = (base + len(total) - 1, total[-1], int(n[-1]))
        sig = sigma[rows]
        terms = np.stack([0.5 * (sig[:, 6] ** 2 + sig[:, 7] ** 2), sig[:, 8] ** 2, (sig[:, 5] / speed[rows]) ** 2],
                         axis=1)
        self.terms.append(terms)

    def result(self) -> tuple[np.ndarray, np.ndarray] | None:
        """:func:`mounting`'s return, after the last rows."""
        if self.rows < 3:
            return None
        self._reduce(*self.held, next_row=None)
        if len(self.terms) < 20:
            return None
        means = np.array(self.means + [self.open[1] / self.open[2]])
        spread = (means.std(axis=0, ddof=1) / math.sqrt(len(means)) if len(means) > 1
                  else np.full(3, math.inf))
        level, head, climb = (math.sqrt(float(np.mean(x))) for x in self.terms.read(0, len(self.terms)).T.copy())
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

