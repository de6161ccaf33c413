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

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from fieldlog.fusion import earth

_gravity = njit(cache=True)(earth.gravity)
_radii = njit(cache=True)(earth.principal_radii)


@dataclass
class NavState:
    """Navigation state at time t (s): lat, lon (rad), h (m), v_n (3,) ENU m/s, q (4,) [x, y, z, w] of C_bn."""

    t: float
    lat: float
    lon: float
    h: float
    v_n: np.ndarray
    q: np.ndarray

    @property
    def C_bn(self) -> np.ndarray:
        """DCM body RFU -> ENU."""
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
        """State at sample i (use -1 to continue with the next block)."""
        return NavState(float(self.t[i]), float(self.lat[i]), float(self.lon[i]), float(self.h[i]),
                        self.v_n[i].copy(), self.q[i].copy())

    def euler(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(heading, pitch, roll) in rad at every sample."""
        return earth.dcm_to_euler(earth.quat_to_dcm(self.q))


@njit(cache=True)
def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


@njit(cache=True)
def _quat_mul(p, q):
    px, py, pz, pw = p
    qx, qy, qz, qw = q
    return (pw * qx + qw * px + py * qz - pz * qy,
            pw * qy + qw * py + pz * qx - px * qz,
            pw * qz + qw * pz + px * qy - py * qx,
            pw * qw - px * qx - py * qy - pz * qz)


@njit(cache=True)
def _rotvec_quat(r):
    a2 = r[0] * r[0] + r[1] * r[1] + r[2] * r[2]
    a = math.sqrt(a2)
    if a < 1e-4:
        k = 0.5 - a2 / 48.0 + a2 * a2 / 3840.0
    else:
        k = math.sin(0.5 * a) / a
    return (k * r[0], k * r[1], k * r[2], math.cos(0.5 * a))


@njit(cache=True)
def _rotate(q, v):
    """C(q) @ v for a unit quaternion [x, y, z, w]."""
    u = (q[0], q[1], q[2])
    t = _cross(u, v)
    t = (2.0 * t[0], 2.0 * t[1], 2.0 * t[2])
    c = _cross(u, t)
    w = q[3]
    return (v[0] + w * t[0] + c[0], v[1] + w * t[1] + c[1], v[2] + w * t[2] + c[2])


@njit(cache=True)
def _step(dt, w0, f0, w1, f1, lat, lon, h, v, q):
    """One mechanisation step (module docstring); vectors and quaternions are tuples."""
    dt2 = dt * dt / 12.0
    dth = (0.5 * (w0[0] + w1[0]) * dt, 0.5 * (w0[1] + w1[1]) * dt, 0.5 * (w0[2] + w1[2]) * dt)
    dv = (0.5 * (f0[0] + f1[0]) * dt, 0.5 * (f0[1] + f1[1]) * dt, 0.5 * (f0[2] + f1[2]) * dt)
    con = _cross(w0, w1)
    phi = (dth[0] + dt2 * con[0], dth[1] + dt2 * con[1], dth[2] + dt2 * con[2])
    rot = _cross(dth, dv)
    s1 = _cross(w0, f1)
    s2 = _cross(f0, w1)
    dv_b = (dv[0] + 0.5 * rot[0] + dt2 * (s1[0] + s2[0]),
            dv[1] + 0.5 * rot[1] + dt2 * (s1[1] + s2[1]),
            dv[2] + 0.5 * rot[2] + dt2 * (s1[2] + s2[2]))
    dv_n0 = _rotate(q, dv_b)
    q_b = _rotvec_quat(phi)

    lat_m, h_m, v_m = lat, h, v
    lat1, lon1, h1, v1, zeta = lat, lon, h, v, (0.0, 0.0, 0.0)
    for _ in range(2):
        rm, rn = _radii(lat_m, h_m)
        sl, cl = math.sin(lat_m), math.cos(lat_m)
        w_ie = (0.0, earth.OMEGA_IE * cl, earth.OMEGA_IE * sl)
        w_en = (-v_m[1] / rm, v_m[0] / rn, v_m[0] * sl / cl / rn)
        zeta = ((w_ie[0] + w_en[0]) * dt, (w_ie[1] + w_en[1]) * dt, (w_ie[2] + w_en[2]) * dt)
        zr = _cross(zeta, dv_n0)
        cor = _cross((2.0 * w_ie[0] + w_en[0], 2.0 * w_ie[1] + w_en[1], 2.0 * w_ie[2] + w_en[2]), v_m)
        g = _gravity(lat_m, h_m)
        v1 = (v[0] + dv_n0[0] - 0.5 * zr[0] - cor[0] * dt,
              v[1] + dv_n0[1] - 0.5 * zr[1] - cor[1] * dt,
              v[2] + dv_n0[2] - 0.5 * zr[2] + (-g - cor[2]) * dt)
        v_m = (0.5 * (v[0] + v1[0]), 0.5 * (v[1] + v1[1]), 0.5 * (v[2] + v1[2]))
        lat1 = lat + v_m[1] / rm * dt
        lon1 = lon + v_m[0] / (rn * cl) * dt
        h1 = h + v_m[2] * dt
        lat_m, h_m = 0.5 * (lat + lat1), 0.5 * (h + h1)

    q_n = _rotvec_quat((-zeta[0], -zeta[1], -zeta[2]))
    q1 = _quat_mul(q_n, _quat_mul(q, q_b))
    nq = math.sqrt(q1[0] ** 2 + q1[1] ** 2 + q1[2] ** 2 + q1[3] ** 2)
    if q1[3] < 0.0:
        nq = -nq
    return lat1, lon1, h1, v1, (q1[0] / nq, q1[1] / nq, q1[2] / nq, q1[3] / nq)


@njit(cache=True)
def _integrate(t, w, f, lat, lon, h, v, q, out_lat, out_lon, out_h, out_v, out_q):
    vv = (v[0], v[1], v[2])
    qq = (q[0], q[1], q[2], q[3])
    out_lat[0], out_lon[0], out_h[0] = lat, lon, h
    out_v[0] = v
    out_q[0] = q
    for k in range(1, t.shape[0]):
        lat, lon, h, vv, qq = _step(t[k] - t[k - 1],
                                    (w[k - 1, 0], w[k - 1, 1], w[k - 1, 2]), (f[k - 1, 0], f[k - 1, 1], f[k - 1, 2]),
                                    (w[k, 0], w[k, 1], w[k, 2]), (f[k, 0], f[k, 1], f[k, 2]),
                                    lat, lon, h, vv, qq)
        out_lat[k], out_lon[k], out_h[k] = lat, lon, h
        for i in range(3):
            out_v[k, i] = vv[i]
        for i in range(4):
            out_q[k, i] = qq[i]


def integrate(state: NavState, t_s: np.ndarray, omega_ib_b: np.ndarray, f_b: np.ndarray) -> NavSolution:
    """Run the INS over a block of IMU samples.

    state: the navigation state at t_s[0], the time of the block's first sample.
    t_s (n,) strictly increasing sample times, s; omega_ib_b (n, 3) rad/s; f_b (n, 3) m/s^2, body RFU.
    Returns the state at every sample time (row 0 is ``state``). To continue with the next block, pass
    ``solution.state(-1)`` and start that block with the last sample of this one.
    """
    t = np.ascontiguousarray(t_s, dtype=float)
    w = np.ascontiguousarray(omega_ib_b, dtype=float)
    f = np.ascontiguousarray(f_b, dtype=float)
    n = t.shape[0]
    if w.shape != (n, 3) or f.shape != (n, 3):
        raise ValueError("omega_ib_b and f_b must be (n, 3) with n = len(t_s)")
    if n > 1 and not np.all(np.diff(t) > 0.0):
        raise ValueError("t_s must be strictly increasing")
    if n and abs(t[0] - state.t) > 1e-9:
        raise ValueError("the first sample must be at the state's time")
    out = NavSolution(t.copy(), np.empty(n), np.empty(n), np.empty(n), np.empty((n, 3)), np.empty((n, 4)))
    if n:
        _integrate(t, w, f, float(state.lat), float(state.lon), float(state.h),
                   np.asarray(state.v_n, dtype=float), np.asarray(state.q, dtype=float),
                   out.lat, out.lon, out.h, out.v_n, out.q)
    return out


def step(state: NavState, t1: float, omega0: np.ndarray, f0: np.ndarray, omega1: np.ndarray, f1: np.ndarray
         ) -> NavState:
    """One INS step from ``state`` (at the time of sample 0: omega0, f0) to t1 (sample 1: omega1, f1).

    Rates in rad/s, specific forces in m/s^2, body RFU; same algorithm as ``integrate``.
    """
    lat, lon, h, v, q = _step(float(t1) - state.t, tuple(map(float, omega0)), tuple(map(float, f0)),
                              tuple(map(float, omega1)), tuple(map(float, f1)),
                              float(state.lat), float(state.lon), float(state.h),
                              tuple(map(float, state.v_n)), tuple(map(float, state.q)))
    return NavState(float(t1), lat, lon, h, np.array(v), np.array(q))
