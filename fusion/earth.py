"""WGS-84 Earth model, frames and rotation conventions.

Frames: e = ECEF (WGS-84), n = local ENU (x east, y north, z up), b = body right-forward-up.
Angles are radians throughout fusion, including latitude and longitude. Heights are ellipsoidal, in m.

Rotation conventions
- A DCM named ``C_xy`` maps x-frame coordinates to y-frame coordinates: ``v_y = C_xy @ v_x``.
- Euler angles (heading psi, pitch theta, roll phi): heading clockwise from north, pitch nose-up positive,
  roll right-side-down positive; ``C_bn = R_z(-psi) @ R_x(theta) @ R_y(phi)`` (R_* are right-handed
  active rotations about the ENU axes).
- Quaternions are Hamilton, scalar-last ``[x, y, z, w]`` (the ROS ``geometry_msgs/Quaternion`` and scipy order),
  with w >= 0 on output. The quaternion of ``C_bn`` rotates body vectors into ENU, so it is exactly the
  body->ENU orientation that ``sensor_msgs/Imu.orientation`` wants.
- A rotation vector r (axis * angle) corresponds to ``exp([r x])``.

All functions are vectorised over leading axes: vectors are (..., 3), quaternions (..., 4), DCMs (..., 3, 3).
``principal_radii`` and ``gravity`` are written out again, operation for operation, in the INS kernel
(fusion/_ins.c), which takes the constants from here.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

A = 6378137.0  # semi-major axis, m
F = 1.0 / 298.257223563  # flattening
E2 = F * (2.0 - F)  # first eccentricity squared
B = A * (1.0 - F)  # semi-minor axis, m
OMEGA_IE = 7.292115e-5  # Earth rotation rate, rad/s
GM = 3.986004418e14  # m^3/s^2
GAMMA_E = 9.7803253359  # normal gravity at the equator, m/s^2
GAMMA_P = 9.8321849378  # normal gravity at the poles, m/s^2
_K_SOMIGLIANA = B * GAMMA_P / (A * GAMMA_E) - 1.0
_M = OMEGA_IE**2 * A**2 * B / GM
# the constants the compiled kernels (fusion/_ins.c, fusion/_cycles.c) take, in their EARTH_* order
KERNEL_CONSTANTS = np.array([A, E2, F, _M, _K_SOMIGLIANA, GAMMA_E, OMEGA_IE])


def principal_radii(lat: ArrayLike, h: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Meridian and prime-vertical radii of curvature plus height, ``(R_M + h, R_N + h)`` in m.

    lat in rad, h ellipsoidal height in m.

    Parameters
    ----------
    lat, h : as :func:`gravity`

    Returns
    -------
    R_M_h : ndarray, meridian radius of curvature plus height, m
    R_N_h : ndarray, prime-vertical radius of curvature plus height, m
    """
    s2 = np.sin(lat) ** 2
    w = np.sqrt(1.0 - E2 * s2)
    r_n = A / w
    r_m = r_n * (1.0 - E2) / (w * w)
    return r_m + h, r_n + h


def gravity(lat: ArrayLike, h: ArrayLike) -> np.ndarray:
    """Magnitude of WGS-84 normal gravity, m/s^2 (Somigliana on the ellipsoid, 2nd-order height correction).

    lat in rad, h ellipsoidal height in m (NIMA TR8350.2 eq. 4-1 and 4-3). This is the one gravity model of
    the project: the INS and the simulator both use it, with direction along -up of the ENU frame.

    Parameters
    ----------
    lat : array_like, geodetic latitude, rad
    h : array_like, ellipsoidal height, m

    Returns
    -------
    g : ndarray, magnitude of normal gravity, m/s^2
    """
    s2 = np.sin(lat) ** 2
    g0 = GAMMA_E * (1.0 + _K_SOMIGLIANA * s2) / np.sqrt(1.0 - E2 * s2)
    return g0 * (1.0 - 2.0 / A * (1.0 + F + _M - 2.0 * F * s2) * h + 3.0 * h * h / (A * A))


def gravity_n(lat: ArrayLike, h: ArrayLike) -> np.ndarray:
    """Normal gravity vector in ENU, ``[0, 0, -g]``, shape (..., 3), m/s^2.

    Parameters
    ----------
    lat, h : as :func:`gravity`

    Returns
    -------
    g_n : (..., 3) ndarray, gravity in ENU, m/s^2
    """
    g = np.asarray(gravity(lat, h), dtype=float)
    out = np.zeros(g.shape + (3,))
    out[..., 2] = -g
    return out


def lla_to_ecef(lat: ArrayLike, lon: ArrayLike, h: ArrayLike) -> np.ndarray:
    """Geodetic (lat, lon in rad, h in m) to ECEF position, shape (..., 3), m.

    Parameters
    ----------
    lat : array_like, geodetic latitude, rad
    lon : array_like, longitude, rad
    h : array_like, ellipsoidal height, m

    Returns
    -------
    r_e : (..., 3) ndarray, ECEF position, m
    """
    lat, lon, h = np.broadcast_arrays(*(np.asarray(x, dtype=float) for x in (lat, lon, h)))
    sl, cl = np.sin(lat), np.cos(lat)
    r_n = A / np.sqrt(1.0 - E2 * sl * sl)
    return np.stack(
        [(r_n + h) * cl * np.cos(lon), (r_n + h) * cl * np.sin(lon), (r_n * (1.0 - E2) + h) * sl], axis=-1
    )


def ecef_to_lla(r_e: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ECEF position (..., 3) in m to geodetic ``(lat, lon, h)``: rad, rad, m.

    Bowring's iteration on the reduced latitude (cubic convergence), three passes: round-trip error below
    1e-8 m from below the surface to satellite altitudes (not meant for points near the Earth's centre).

    Parameters
    ----------
    r_e : (..., 3) array_like, ECEF position, m

    Returns
    -------
    lat : ndarray, geodetic latitude, rad
    lon : ndarray, longitude in (-pi, pi], rad
    h : ndarray, ellipsoidal height, m
    """
    r_e = np.asarray(r_e, dtype=float)
    x, y, z = r_e[..., 0], r_e[..., 1], r_e[..., 2]
    p = np.hypot(x, y)
    lon = np.arctan2(y, x)
    ep2 = E2 / (1.0 - E2)
    beta = np.arctan2(z, (1.0 - F) * p)
    for _ in range(3):
        lat = np.arctan2(z + ep2 * B * np.sin(beta) ** 3, p - E2 * A * np.cos(beta) ** 3)
        beta = np.arctan2((1.0 - F) * np.sin(lat), np.cos(lat))
    sl, cl = np.sin(lat), np.cos(lat)
    h = p * cl + z * sl - A * np.sqrt(1.0 - E2 * sl * sl)
    return lat, lon, h


def C_en(lat: ArrayLike, lon: ArrayLike) -> np.ndarray:
    """DCM ECEF -> ENU at (lat, lon) in rad, shape (..., 3, 3): ``v_n = C_en @ v_e``.

    Parameters
    ----------
    lat : array_like, geodetic latitude, rad
    lon : array_like, longitude, rad

    Returns
    -------
    C_en : (..., 3, 3) ndarray, ECEF -> ENU
    """
    lat, lon = np.broadcast_arrays(np.asarray(lat, dtype=float), np.asarray(lon, dtype=float))
    sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    out = np.empty(lat.shape + (3, 3))
    out[..., 0, 0], out[..., 0, 1], out[..., 0, 2] = -so, co, 0.0
    out[..., 1, 0], out[..., 1, 1], out[..., 1, 2] = -sl * co, -sl * so, cl
    out[..., 2, 0], out[..., 2, 1], out[..., 2, 2] = cl * co, cl * so, sl
    return out


def omega_ie_n(lat: ArrayLike) -> np.ndarray:
    """Earth rotation rate in ENU, ``[0, Omega cos(lat), Omega sin(lat)]``, rad/s, shape (..., 3).

    Parameters
    ----------
    lat : array_like, geodetic latitude, rad

    Returns
    -------
    omega_ie_n : (..., 3) ndarray, Earth rate in ENU, rad/s
    """
    lat = np.asarray(lat, dtype=float)
    return np.stack([np.zeros_like(lat), OMEGA_IE * np.cos(lat), OMEGA_IE * np.sin(lat)], axis=-1)


def omega_en_n(lat: ArrayLike, h: ArrayLike, v_n: ArrayLike) -> np.ndarray:
    """Transport rate (n relative to e, in n) for ENU velocity v_n (..., 3) in m/s; rad/s, shape (..., 3).

    Parameters
    ----------
    lat : array_like, geodetic latitude, rad
    h : array_like, ellipsoidal height, m
    v_n : (..., 3) array_like, velocity in ENU, m/s

    Returns
    -------
    omega_en_n : (..., 3) ndarray, transport rate in ENU, rad/s
    """
    v_n = np.asarray(v_n, dtype=float)
    lat = np.asarray(lat, dtype=float)
    rm, rn = principal_radii(lat, np.asarray(h, dtype=float))
    ve, vn = v_n[..., 0], v_n[..., 1]
    return np.stack([-vn / rm, ve / rn, ve * np.tan(lat) / rn], axis=-1)


def cross(a: ArrayLike, b: ArrayLike) -> np.ndarray:
    """a x b over the last axis (broadcast): np.cross's numbers, without its axis handling (most of its time on
    a few vectors).

    Parameters
    ----------
    a, b : (..., 3) array_like, vectors in one frame (any unit), broadcast together

    Returns
    -------
    c : (..., 3) ndarray, a x b in that frame, unit of a times unit of b
    """
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    if a.shape == b.shape == (3,):  # one pair: the same products and differences in floats
        (a0, a1, a2), (b0, b1, b2) = a.tolist(), b.tolist()
        return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def skew(v: ArrayLike) -> np.ndarray:
    """Cross-product matrix ``[v x]`` of (..., 3) vectors, shape (..., 3, 3).

    Parameters
    ----------
    v : (..., 3) array_like, vector (any frame, any unit)

    Returns
    -------
    V : (..., 3, 3) ndarray, with ``V @ w = v x w``
    """
    v = np.asarray(v, dtype=float)
    if v.shape == (3,):  # one vector: built from floats
        x, y, z = v.tolist()
        return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    out = np.zeros(v.shape + (3,))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def euler_to_dcm(heading: ArrayLike, pitch: ArrayLike, roll: ArrayLike) -> np.ndarray:
    """``C_bn`` (body RFU -> ENU) from heading, pitch, roll in rad (conventions in the module docstring).

    Parameters
    ----------
    heading : array_like, clockwise from north, rad
    pitch : array_like, nose-up positive, rad
    roll : array_like, right-side-down positive, rad

    Returns
    -------
    C_bn : (..., 3, 3) ndarray, body RFU -> ENU
    """
    heading, pitch, roll = np.broadcast_arrays(*(np.asarray(x, dtype=float) for x in (heading, pitch, roll)))
    sh, ch = np.sin(heading), np.cos(heading)
    sp, cp = np.sin(pitch), np.cos(pitch)
    sr, cr = np.sin(roll), np.cos(roll)
    out = np.empty(heading.shape + (3, 3))
    out[..., 0, 0] = ch * cr + sh * sp * sr
    out[..., 0, 1] = sh * cp
    out[..., 0, 2] = ch * sr - sh * sp * cr
    out[..., 1, 0] = -sh * cr + ch * sp * sr
    out[..., 1, 1] = ch * cp
    out[..., 1, 2] = -sh * sr - ch * sp * cr
    out[..., 2, 0] = -cp * sr
    out[..., 2, 1] = sp
    out[..., 2, 2] = cp * cr
    return out


def dcm_to_euler(C_bn: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(heading, pitch, roll)`` in rad from ``C_bn``; heading in [0, 2 pi), pitch in [-pi/2, pi/2].

    Parameters
    ----------
    C_bn : (..., 3, 3) array_like, body RFU -> ENU

    Returns
    -------
    heading : ndarray, in [0, 2 pi), rad
    pitch : ndarray, in [-pi/2, pi/2], rad
    roll : ndarray, in (-pi, pi], rad
    """
    C = np.asarray(C_bn, dtype=float)
    pitch = np.arcsin(np.clip(C[..., 2, 1], -1.0, 1.0))
    roll = np.arctan2(-C[..., 2, 0], C[..., 2, 2])
    heading = np.mod(np.arctan2(C[..., 0, 1], C[..., 1, 1]), 2.0 * np.pi)
    return heading, pitch, roll


def rpy_to_dcm(rpy: ArrayLike) -> np.ndarray:
    """The DCM of fixed-axis roll, pitch, yaw (REP-103, as ROS ``tf`` and a calibration's ``imu_rpy_deg``):
    ``R_z(yaw) @ R_y(pitch) @ R_x(roll)``, right-handed active rotations about the parent's axes.

    Parameters
    ----------
    rpy : (..., 3) array_like, [roll, pitch, yaw], rad

    Returns
    -------
    C : (..., 3, 3) ndarray, child-frame vectors -> parent-frame vectors
    """
    r = np.asarray(rpy, dtype=float)
    cr, cp, cy = np.cos(r[..., 0]), np.cos(r[..., 1]), np.cos(r[..., 2])
    sr, sp, sy = np.sin(r[..., 0]), np.sin(r[..., 1]), np.sin(r[..., 2])
    out = np.empty(r.shape[:-1] + (3, 3))
    out[..., 0, 0], out[..., 0, 1], out[..., 0, 2] = cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr
    out[..., 1, 0], out[..., 1, 1], out[..., 1, 2] = sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr
    out[..., 2, 0], out[..., 2, 1], out[..., 2, 2] = -sp, cp * sr, cp * cr
    return out


def dcm_to_rpy(C: ArrayLike) -> np.ndarray:
    """Fixed-axis roll, pitch, yaw (REP-103) of a DCM, the inverse of :func:`rpy_to_dcm`.

    Parameters
    ----------
    C : (..., 3, 3) array_like, child-frame vectors -> parent-frame vectors

    Returns
    -------
    rpy : (..., 3) ndarray, [roll in (-pi, pi], pitch in [-pi/2, pi/2], yaw in (-pi, pi]], rad
    """
    C = np.asarray(C, dtype=float)
    return np.stack([np.arctan2(C[..., 2, 1], C[..., 2, 2]), np.arcsin(np.clip(-C[..., 2, 0], -1.0, 1.0)),
                     np.arctan2(C[..., 1, 0], C[..., 0, 0])], axis=-1)


def quat_to_dcm(q: ArrayLike) -> np.ndarray:
    """DCM of a Hamilton quaternion ``[x, y, z, w]`` (need not be exactly unit; it is normalised).

    Parameters
    ----------
    q : (..., 4) array_like, ``[x, y, z, w]``, non-zero

    Returns
    -------
    C : (..., 3, 3) ndarray, the DCM of the normalised q (for the quaternion of ``C_bn``, body -> ENU)
    """
    q = np.asarray(q, dtype=float)
    if q.shape == (4,):  # one quaternion, in floats: numpy's operations without its per-call cost
        x, y, z, w = q.tolist()
        n = math.sqrt(((x * x + y * y) + z * z) + w * w)  # the order of numpy's sum of 4 elements
        if n > 0.0:
            return np.array(_dcm_rows(x / n, y / n, z / n, w / n))
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    rows = _dcm_rows(q[..., 0], q[..., 1], q[..., 2], q[..., 3])
    out = np.empty(q.shape[:-1] + (3, 3))
    for i in range(3):
        for j in range(3):
            out[..., i, j] = rows[i][j]
    return out


def _dcm_rows(x, y, z, w):
    """The DCM of a unit quaternion as rows of entries (floats or arrays)."""
    return ((1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - z * w), 2.0 * (x * z + y * w)),
            (2.0 * (x * y + z * w), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - x * w)),
            (2.0 * (x * z - y * w), 2.0 * (y * z + x * w), 1.0 - 2.0 * (x * x + y * y)))


def dcm_to_quat(C: ArrayLike) -> np.ndarray:
    """Hamilton quaternion ``[x, y, z, w]`` (w >= 0) of a DCM; Shepperd's method, stable for all angles.

    Parameters
    ----------
    C : (..., 3, 3) array_like, a rotation matrix

    Returns
    -------
    q : (..., 4) ndarray, unit ``[x, y, z, w]`` with w >= 0
    """
    C = np.asarray(C, dtype=float)
    tr = C[..., 0, 0] + C[..., 1, 1] + C[..., 2, 2]
    # four candidate 4*q_i^2 values; pick the largest per matrix
    cand = np.stack([1.0 + 2.0 * C[..., 0, 0] - tr, 1.0 + 2.0 * C[..., 1, 1] - tr,
                     1.0 + 2.0 * C[..., 2, 2] - tr, 1.0 + tr], axis=-1)
    i = np.argmax(cand, axis=-1)
    s = 2.0 * np.sqrt(np.maximum(np.take_along_axis(cand, i[..., None], axis=-1)[..., 0], 0.0))
    d21, d12 = C[..., 2, 1] - C[..., 1, 2], C[..., 2, 1] + C[..., 1, 2]
    d02, d20 = C[..., 0, 2] - C[..., 2, 0], C[..., 0, 2] + C[..., 2, 0]
    d10, d01 = C[..., 1, 0] - C[..., 0, 1], C[..., 1, 0] + C[..., 0, 1]
    q = np.empty(C.shape[:-2] + (4,))
    sel = [i == k for k in range(4)]
    q[..., 0] = np.select(sel, [s / 4, d01 / s, d20 / s, d21 / s])
    q[..., 1] = np.select(sel, [d01 / s, s / 4, d12 / s, d02 / s])
    q[..., 2] = np.select(sel, [d20 / s, d12 / s, s / 4, d10 / s])
    q[..., 3] = np.select(sel, [d21 / s, d02 / s, d10 / s, s / 4])
    q *= np.where(q[..., 3:4] < 0.0, -1.0, 1.0)
    return q


def quat_multiply(p: ArrayLike, q: ArrayLike) -> np.ndarray:
    """Hamilton product ``p * q`` of ``[x, y, z, w]`` quaternions (DCM of the product = DCM(p) @ DCM(q)).

    Parameters
    ----------
    p, q : (..., 4) array_like, ``[x, y, z, w]`` quaternions, broadcast together

    Returns
    -------
    pq : (..., 4) ndarray, ``p * q`` (not renormalised)
    """
    p, q = np.asarray(p, dtype=float), np.asarray(q, dtype=float)
    pv, pw = p[..., :3], p[..., 3:]
    qv, qw = q[..., :3], q[..., 3:]
    v = pw * qv + qw * pv + cross(pv, qv)
    w = pw * qw - np.sum(pv * qv, axis=-1, keepdims=True)
    return np.concatenate([v, w], axis=-1)


def rotvec_to_quat(rv: ArrayLike) -> np.ndarray:
    """Quaternion ``[x, y, z, w]`` of rotation vector(s) rv (..., 3) in rad.

    Parameters
    ----------
    rv : (..., 3) array_like, rotation vector (axis times angle), rad

    Returns
    -------
    q : (..., 4) ndarray, unit ``[x, y, z, w]`` (w < 0 when the angle exceeds pi)
    """
    rv = np.asarray(rv, dtype=float)
    a = np.linalg.norm(rv, axis=-1, keepdims=True)
    a2 = a * a
    # sin(a/2)/a with its Taylor series near zero
    k = np.where(a < 1e-4, 0.5 - a2 / 48.0 + a2 * a2 / 3840.0, np.sin(0.5 * a) / np.where(a == 0.0, 1.0, a))
    return np.concatenate([k * rv, np.cos(0.5 * a)], axis=-1)


def quat_to_rotvec(q: ArrayLike) -> np.ndarray:
    """Rotation vector(s) (..., 3) in rad, angle in [0, pi], of ``[x, y, z, w]`` quaternion(s).

    Parameters
    ----------
    q : (..., 4) array_like, ``[x, y, z, w]``, non-zero (normalised here)

    Returns
    -------
    rv : (..., 3) ndarray, rotation vector, rad
    """
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    q = q * np.where(q[..., 3:4] < 0.0, -1.0, 1.0)
    s = np.linalg.norm(q[..., :3], axis=-1, keepdims=True)
    a = 2.0 * np.arctan2(s, q[..., 3:4])
    k = np.where(s < 1e-8, 2.0 / q[..., 3:4], a / np.where(s == 0.0, 1.0, s))
    return k * q[..., :3]


def rotvec_to_dcm(rv: ArrayLike) -> np.ndarray:
    """DCM ``exp([rv x])`` of rotation vector(s) rv (..., 3) in rad.

    Parameters
    ----------
    rv : as :func:`rotvec_to_quat`

    Returns
    -------
    C : (..., 3, 3) ndarray
    """
    return quat_to_dcm(rotvec_to_quat(rv))


def dcm_to_rotvec(C: ArrayLike) -> np.ndarray:
    """Rotation vector(s) of DCM(s) C, angle in [0, pi].

    Parameters
    ----------
    C : as :func:`dcm_to_quat`

    Returns
    -------
    rv : (..., 3) ndarray, rotation vector, rad
    """
    return quat_to_rotvec(dcm_to_quat(C))


# Body frames of other loggers: C_rfu_x maps a vector in frame x to the body RFU frame (right, forward, up).
# REP-103's vehicle body is FLU (forward, left, up); aerospace IMUs are often FRD (forward, right, down).
BODY_FRAMES: dict[str, np.ndarray] = {
    "rfu": np.eye(3),
    "flu": np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
    "frd": np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]),
}


def C_rfu_from(frame: str) -> np.ndarray:
    """The rotation (3, 3) from a named body frame (``BODY_FRAMES``: rfu, flu, frd) to body RFU.

    Parameters
    ----------
    frame : str, a key of ``BODY_FRAMES`` (any case)

    Returns
    -------
    C_rfu_x : (3, 3) ndarray, maps vectors in ``frame`` to body RFU: ``v_rfu = C_rfu_x @ v_x``

    Raises
    ------
    ValueError
        For an unknown frame name.
    """
    try:
        return BODY_FRAMES[frame.lower()]
    except KeyError:
        raise ValueError(f"unknown body frame {frame!r}; one of {', '.join(BODY_FRAMES)}") from None
