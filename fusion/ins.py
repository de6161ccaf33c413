"""Strapdown INS mechanisation in the local ENU frame on WGS-84 with normal gravity.

Inputs are *sampled rates*, as an analog MEMS IMU behind an ADC gives them: angular rate omega_ib_b (rad/s)
and specific force f_b (m/s^2) in body RFU at sample times t_k (s, any spacing). State: geodetic lat, lon
(rad), ellipsoidal h (m), ENU velocity v_n (m/s), attitude quaternion q = [x, y, z, w] of C_bn (body -> ENU;
``fusion.earth`` conventions).

One step from t_{k-1} to t_k (dt = t_k - t_{k-1}), with the rates taken as linear in time between samples:

- increments (trapezoid): dtheta = (w0 + w1) dt/2, dv = (f0 + f1) dt/2;
- coning: phi = dtheta + dt^2/12 (w0 x w1), the body rotation vector over the step, exact to second order for
  a linear rate (the two-sample coning term written with rates);
- sculling: dv_sf_b = dv + 1/2 dtheta x dv + dt^2/12 (w0 x f1 + f0 x w1) (rotation compensation plus the
  sculling term of linear rate and linear specific force);
- velocity (Savage): v1 = v0 + [I - 1/2 zeta x] C_bn0 dv_sf_b + (g_n - (2 omega_ie_n + omega_en_n) x v) dt,
  zeta = (omega_ie_n + omega_en_n) dt;
- position: trapezoid on velocity, lat += v_N/(R_M + h) dt, lon += v_E/((R_N + h) cos lat) dt, h += v_U dt;
- attitude: q1 = q(-zeta) * q0 * q(phi), normalised.

Navigation-frame quantities (g, Coriolis, transport rate, radii) are taken at the step's midpoint by a
predictor-corrector: a first pass uses the state at t_{k-1}, the second the mean of that state and the
first pass's result. Every error term is then third order in dt per step.
"""

from __future__ import annotations

import ctypes
import functools
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from fieldlog.fusion import earth, kernels
from fieldlog.fusion.median import median


@dataclass
class NavState:
    """Navigation state at time t (s): lat, lon (rad), h (m), v_n (3,) ENU m/s, q (4,) [x, y, z, w] of C_bn."""

    t: float
    lat: float
    lon: float
    h: float
    v_n: np.ndarray
    q: np.ndarray

    @cached_property
    def C_bn(self) -> np.ndarray:
        """DCM body RFU -> ENU (computed once: a state is replaced, never changed in place).

        Returns
        -------
        (3, 3) ndarray, C_bn of ``q``: v_n = C_bn v_b.
        """
        return earth.quat_to_dcm(self.q)


@dataclass
class NavSolution:
    """INS output at the n sample times of a block: t (n,), lat, lon (rad), h (m), v_n (n, 3), q (n, 4)."""

    t: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    h: np.ndarray
    v_n: np.ndarray
    q: np.ndarray

    def state(self, i: int) -> NavState:
        """State at sample i (use -1 to continue with the next block).

        Parameters
        ----------
        i : int, sample index (negative counts from the end)

        Returns
        -------
        NavState
            A copy of row i (changing it leaves the solution as it is).
        """
        return NavState(float(self.t[i]), float(self.lat[i]), float(self.lon[i]), float(self.h[i]),
                        self.v_n[i].copy(), self.q[i].copy())

    def euler(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(heading, pitch, roll) in rad at every sample.

        Returns
        -------
        heading, pitch, roll : (n,) ndarrays, rad (``fusion.earth.dcm_to_euler``): heading clockwise from north
            in [0, 2 pi), pitch nose-up, roll right-side-down.
        """
        return earth.dcm_to_euler(earth.quat_to_dcm(self.q))


PERIOD_STEPS = 1000  # an IMU's sample period is the median of a drive's first this many sample steps


class SamplePeriod:
    """An IMU's sample period ``dt_s`` (s): the median of the drive's first ``PERIOD_STEPS`` sample steps, so that
    the blocks the drive comes in do not change it (0.002 before the first step)."""

    def __init__(self) -> None:
        self.dt_s = 0.002
        self._first: list[np.ndarray] | None = []  # the steps (s) while fewer than PERIOD_STEPS have been seen

    def add(self, t: np.ndarray, carried: int) -> None:
        """Take a block's sample steps.

        Parameters
        ----------
        t : ndarray (n,)
            The block's sample times, s, strictly increasing.
        carried : int
            How many of its first samples are those held from the block before (their steps were taken then).
        """
        if self._first is None:
            return
        self._first.append(np.diff(t[max(carried - 1, 0):]))
        steps = np.concatenate(self._first)[:PERIOD_STEPS]
        if len(steps):
            self.dt_s = median(steps)
        if len(steps) == PERIOD_STEPS:
            self._first = None


@functools.cache
def _kernel() -> ctypes.CDLL:
    """The compiled step (fusion/_ins.c)."""
    return kernels.load("fieldlog.fusion._ins", {"fieldlog_ins_integrate": ([ctypes.c_int64] + [ctypes.c_void_p] * 10,
                                                                            ctypes.c_int32)})


def integrate(state: NavState, t_s: np.ndarray, omega_ib_b: np.ndarray, f_b: np.ndarray) -> NavSolution:
    """Run the INS over a block of IMU samples.

    state: the navigation state at t_s[0], the time of the block's first sample.
    t_s (n,) strictly increasing sample times, s; omega_ib_b (n, 3) rad/s; f_b (n, 3) m/s^2, body RFU.
    Returns the state at every sample time (row 0 is ``state``). To continue with the next block, pass
    ``solution.state(-1)`` and start that block with the last sample of this one.

    Parameters
    ----------
    state : NavState, the navigation state at ``t_s[0]``
    t_s : (n,) ndarray, strictly increasing sample times, s
    omega_ib_b : (n, 3) ndarray, angular rate of body w.r.t. inertial, body RFU, rad/s
    f_b : (n, 3) ndarray, specific force, body RFU, m/s^2

    Returns
    -------
    NavSolution
        lat, lon (rad), h (m), v_n (ENU, m/s), q (of ``C_bn``) at each of the n sample times.

    Raises
    ------
    ValueError
        For mismatched shapes, times not strictly increasing, or a first sample not at ``state.t``.
    """
    t = np.ascontiguousarray(t_s, dtype=float)
    w = np.ascontiguousarray(omega_ib_b, dtype=float)
    f = np.ascontiguousarray(f_b, dtype=float)
    n = t.shape[0]
    if w.shape != (n, 3) or f.shape != (n, 3):
        raise ValueError("omega_ib_b and f_b must be (n, 3) with n = len(t_s)")
    if n and abs(t[0] - state.t) > 1e-9:
        raise ValueError("the first sample must be at the state's time")
    out = NavSolution(t.copy(), np.empty(n), np.empty(n), np.empty(n), np.empty((n, 3)), np.empty((n, 4)))
    if n:
        p0 = np.concatenate(([state.lat, state.lon, state.h], np.asarray(state.v_n, dtype=float).ravel(),
                             np.asarray(state.q, dtype=float).ravel()))
        if p0.shape != (10,):
            raise ValueError("the state's v_n must have 3 elements and q 4")
        if _kernel().fieldlog_ins_integrate(n, *map(kernels.address, (t, w, f, earth.KERNEL_CONSTANTS, p0, out.lat,
                                                                      out.lon, out.h, out.v_n, out.q))):
            raise ValueError("t_s must be strictly increasing")
    return out


def step(state: NavState, t1: float, omega0: np.ndarray, f0: np.ndarray, omega1: np.ndarray, f1: np.ndarray
         ) -> NavState:
    """One INS step from ``state`` (at the time of sample 0: omega0, f0) to t1 (sample 1: omega1, f1).

    Rates in rad/s, specific forces in m/s^2, body RFU; same algorithm as ``integrate``.

    Parameters
    ----------
    state : NavState, the state at sample 0
    t1 : float, time of sample 1, s (after ``state.t``)
    omega0, omega1 : (3,) array_like, angular rate omega_ib_b at samples 0 and 1, body RFU, rad/s
    f0, f1 : (3,) array_like, specific force at samples 0 and 1, body RFU, m/s^2

    Returns
    -------
    NavState
        The state at t1.
    """
    sol = integrate(state, np.array([state.t, float(t1)]), np.array([omega0, omega1], dtype=float),
                    np.array([f0, f1], dtype=float))
    return sol.state(-1)
