"""15-state INS error model (phi-angle form) in the ENU navigation frame, and its discretisation.

State order (the distributed-KF paper's, eq. 1), all errors = computed - true:

====  =========================================================================================
0:3   position error dr_n = [dE, dN, dU] in m. The paper names its first two states "longitude
      error dL, latitude error d-lambda", swapping its own symbols (elsewhere lambda is longitude
      and L latitude; its H^(2) picks states 1, 2, 3 for (d-lambda, dL, dh)). The physically
      consistent order is longitude (east), latitude (north), height (up), which is ENU; we keep it
      and use metres rather than radians so the covariance is well conditioned.
3:6   velocity error dv_n = [dvE, dvN, dvU], m/s.
6:9   attitude error phi = [phiE, phiN, phiU], rad, a small rotation of the nav frame:
      C_bn_computed = (I - [phi x]) C_bn_true. phiE ~ the pitch error, phiN ~ roll, phiU ~ yaw
      (the paper's order: pitch, roll, yaw).
9:12  gyro bias error (residual after the current estimate), body RFU, rad/s.
12:15 accelerometer bias error, body RFU, m/s^2.
====  =========================================================================================

Continuous model x' = F x + G w (hybrid KF-UKF paper eq. 5, phi-angle version with the
transport-rate and Earth-rate perturbations by dv and dr)::

    phi'  = -w_in x phi + dw_in(dr, dv) - C_bn b_g - C_bn w_g
    dv'   = f_n x phi - (2 w_ie + w_en) x dv - (2 dw_ie + dw_en) x v + dg(dU) + C_bn b_a + C_bn w_a
    dr'   = dv - w_en x dr
    b_g'  = w_bg,   b_a' = w_ba            (random walks)

Noise w = [w_g, w_a, w_bg, w_ba] (12,), power spectral densities q = diag(N_g^2, N_a^2, N_bg^2,
N_ba^2) in (rad/s)^2/Hz, (m/s^2)^2/Hz, (rad/s)^2/s, (m/s^2)^2/s.

Discretisation over a filter cycle dT (hybrid KF-UKF paper eq. 13, plus the next term of the same
series for Q)::

    Phi = I + F dT + 1/2 F^2 dT^2
    Q   = G q G^T dT + 1/2 (F G q G^T + G q G^T F^T) dT^2 + 1/3 F G q G^T F^T dT^3

Eq. 13 alone stops at dT^2; that Q is indefinite (the position block gets cross terms with velocity
but no diagonal, since position has no direct noise), which can cost the covariance its positive
definiteness. The dT^3 term gives position its diagonal and makes Q positive semi-definite.

Every function is vectorised over leading axes (a stack of filter cycles is built in one call). The filter loop
builds its cycles with :func:`segment_cycles`: the cycles' means, attitudes and Earth terms and
``discretise(*system_matrices(...))`` (:func:`discrete_cycles`) in one compiled call (fusion/_cycles.c), the same
numbers as the numpy functions, the reference it is tested against.
"""

from __future__ import annotations

import ctypes
import functools
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from fieldlog.fusion import earth, kernels

N_STATES = 15
N_NOISE = 12
POS, VEL, ATT, BG, BA = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12), slice(12, 15)


def system_matrices(lat: ArrayLike, h: ArrayLike, v_n: ArrayLike, C_bn: ArrayLike, f_n: ArrayLike
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Continuous-time ``(F, G)`` of the error model (module docstring), vectorised over leading axes.

    Parameters
    ----------
    lat, h : array_like (...)
        Latitude, rad, and ellipsoidal height, m.
    v_n : array_like (..., 3)
        Velocity, ENU m/s.
    C_bn : array_like (..., 3, 3)
        Attitude, body RFU -> ENU.
    f_n : array_like (..., 3)
        Specific force in ENU, m/s^2 (the mean over the filter cycle).

    Returns
    -------
    F : ndarray (..., 15, 15)
    G : ndarray (..., 15, 12)
    """
    lat = np.asarray(lat, dtype=float)
    h = np.asarray(h, dtype=float)
    v = np.asarray(v_n, dtype=float)
    C = np.asarray(C_bn, dtype=float)
    f = np.asarray(f_n, dtype=float)
    shape = np.broadcast_shapes(lat.shape, h.shape, v.shape[:-1], C.shape[:-2], f.shape[:-1])
    rm, rn = earth.principal_radii(lat, h)
    sl, cl = np.sin(lat), np.cos(lat)
    tl = sl / cl
    ve, vn = v[..., 0], v[..., 1]
    w_ie = earth.omega_ie_n(lat)
    w_en = earth.omega_en_n(lat, h, v)
    g = earth.gravity(lat, h)

    # derivatives of w_ie and w_en with respect to dr (columns E, N, U) and dv (columns vE, vN, vU)
    z = np.zeros(shape)
    d_ie_r = np.zeros(shape + (3, 3))
    d_ie_r[..., 1, 1] = -earth.OMEGA_IE * sl / rm
    d_ie_r[..., 2, 1] = earth.OMEGA_IE * cl / rm
    d_en_r = np.zeros(shape + (3, 3))
    d_en_r[..., 2, 1] = ve / (cl * cl * rn * rm)
    d_en_r[..., 0, 2] = vn / (rm * rm)
    d_en_r[..., 1, 2] = -ve / (rn * rn)
    d_en_r[..., 2, 2] = -ve * tl / (rn * rn)
    d_en_v = np.zeros(shape + (3, 3))
    d_en_v[..., 1, 0] = 1.0 / rn + z
    d_en_v[..., 2, 0] = tl / rn + z
    d_en_v[..., 0, 1] = -1.0 / rm + z

    sv = earth.skew(np.broadcast_to(v, shape + (3,)))
    F = np.zeros(shape + (N_STATES, N_STATES))
    F[..., POS, POS] = -earth.skew(np.broadcast_to(w_en, shape + (3,)))
    F[..., POS, VEL] = np.eye(3)
    F[..., VEL, POS] = sv @ (2.0 * d_ie_r + d_en_r)
    F[..., 5, 2] += 2.0 * g / np.sqrt(rm * rn)  # normal gravity falls off with height: dg_U = +2g/R dU
    F[..., VEL, VEL] = -earth.skew(np.broadcast_to(2.0 * w_ie + w_en, shape + (3,))) + sv @ d_en_v
    F[..., VEL, ATT] = earth.skew(np.broadcast_to(f, shape + (3,)))
    F[..., VEL, BA] = C
    F[..., ATT, POS] = d_ie_r + d_en_r
    F[..., ATT, VEL] = d_en_v
    F[..., ATT, ATT] = -earth.skew(np.broadcast_to(w_ie + w_en, shape + (3,)))
    F[..., ATT, BG] = -C

    G = np.zeros(shape + (N_STATES, N_NOISE))
    G[..., ATT, 0:3] = -C
    G[..., VEL, 3:6] = C
    G[..., BG, 6:9] = np.eye(3)
    G[..., BA, 9:12] = np.eye(3)
    return F, G


def noise_psd(gyro_noise: float, accel_noise: float, gyro_bias_rw: float, accel_bias_rw: float) -> np.ndarray:
    """Diagonal noise PSD matrix from densities.

    Parameters
    ----------
    gyro_noise : float
        Gyro white noise, rad/s/sqrt(Hz).
    accel_noise : float
        Accelerometer white noise, m/s^2/sqrt(Hz).
    gyro_bias_rw, accel_bias_rw : float
        Bias random walks, rad/s/sqrt(s) and m/s^2/sqrt(s).

    Returns
    -------
    ndarray (12, 12)
        q, in the order of the noise vector w (module docstring).
    """
    d = np.repeat([gyro_noise, accel_noise, gyro_bias_rw, accel_bias_rw], 3) ** 2
    return np.diag(d)


def scale_factor_steps(x: np.ndarray, x_prev: np.ndarray, scale_factor: float, misalignment: float) -> np.ndarray:
    """Variance (m, 3) of the step of a triad's effective bias (S + M) x over cycles whose mean signals are x (m, 3),
    the mean before the first being x_prev (3,); S = diag(s_i), M the misalignments m_ij (i != j), independent
    1-sigma ``scale_factor`` (fraction) and ``misalignment`` (rad) per entry, in the signal's unit (rad/s, m/s^2).

    The step of axis i is s_i dx_i + sum_j m_ij dx_j with dx = x_k - x_{k-1}: variance s^2 dx_i^2 + m^2 (|dx|^2 -
    dx_i^2), independent across the axes (each axis has its own s_i and m_ij).

    Parameters
    ----------
    x : ndarray (m, 3)
        The cycles' mean signals, rad/s or m/s^2, body RFU.
    x_prev : ndarray (3,)
        The mean before the first cycle.
    scale_factor, misalignment : float
        1-sigma per entry, fraction and rad.

    Returns
    -------
    ndarray (m, 3)
        The variance of each cycle's bias step per axis, the signal's unit squared.
    """
    dx2 = np.diff(np.vstack([np.asarray(x_prev, float)[None, :], x]), axis=0) ** 2
    return scale_factor ** 2 * dx2 + misalignment ** 2 * (dx2.sum(axis=1, keepdims=True) - dx2)


def discretise(F: np.ndarray, G: np.ndarray, q: np.ndarray, dt: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """``(Phi, Q)`` over a filter cycle of dt seconds (module docstring: hybrid KF-UKF paper eq. 13 + dT^3).

    Parameters
    ----------
    F : ndarray (..., 15, 15)
    G : ndarray (..., 15, 12)
        The continuous model (:func:`system_matrices`).
    q : ndarray (12, 12)
        Noise PSD (:func:`noise_psd`).
    dt : float or array_like (...)
        Cycle length, s.

    Returns
    -------
    Phi, Q : ndarray (..., 15, 15)
    """
    dt = np.asarray(dt, dtype=float)[..., None, None]
    Fdt = F * dt
    Phi = np.eye(F.shape[-1]) + Fdt + 0.5 * (Fdt @ Fdt)
    GqG = G @ q @ np.swapaxes(G, -1, -2)
    FGqG = F @ GqG
    Q = (GqG * dt + 0.5 * (FGqG + np.swapaxes(FGqG, -1, -2)) * dt * dt
         + (FGqG @ np.swapaxes(F, -1, -2)) * (dt * dt * dt / 3.0))
    return Phi, Q


@functools.cache
def cycle_kernel() -> ctypes.CDLL:
    """The compiled cycle matrices, covariance and state cycles, the cycles' slots, updates, fusion, smoothing, the
    predictors' RLS step and the still detector's interval sums (fusion/_cycles.c), loaded once.

    Returns
    -------
    ctypes.CDLL
        The library, its ``fieldlog_*`` functions' argument and return types set.
    """
    p, i64, f64, i32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_double, ctypes.c_int32
    return kernels.load("fieldlog.fusion._cycles", {
        "fieldlog_cycle_matrices": [i64, f64] + [p] * 8,
        "fieldlog_segment_cycles": ([i64, i64] + [p] * 16, i32),
        "fieldlog_propagate_cov": [i64, p, p, f64, i32, p, p],
        "fieldlog_propagate_state": [i64, p, p, p],
        "fieldlog_slot_starts": ([i64, p, f64, f64, p], i64),
        "fieldlog_consider_cycles": [i64, p, p, p, p, p, p],
        "fieldlog_sample_sums": [i64] + [p] * 6,
        "fieldlog_consider_update": ([i64] + [p] * 4, i32),
        "fieldlog_kf_update": ([i64] + [p] * 8 + [i32], i32),
        "fieldlog_nis": ([i64] + [p] * 6, i32),
        "fieldlog_dkf_fuse": ([i64] + [p] * 8, i32),
        "fieldlog_dkf_propagate": ([i64, p, p, f64] + [p] * 11, i32),
        "fieldlog_rts_chunk": ([i64, p, i64] + [p] * 9, i32),
        "fieldlog_rls_update": [i64, i64, p, p, p, p, f64]})


def discrete_cycles(lat: np.ndarray, h: np.ndarray, v_n: np.ndarray, C_bn: np.ndarray, f_n: np.ndarray,
                    q: np.ndarray, dt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(Phi, Q)`` of m cycles: ``discretise(*system_matrices(lat, h, v_n, C_bn, f_n), q, dt)`` to the bit (on a
    machine whose BLAS sums a matrix product as sequential fused multiply-adds), compiled.

    Parameters
    ----------
    lat, h : ndarray (m,)
        Latitude, rad, and height, m, at each cycle's middle.
    v_n : ndarray (m, 3)
        Velocity, ENU m/s.
    C_bn : ndarray (m, 3, 3)
        Attitude, body RFU -> ENU.
    f_n : ndarray (m, 3)
        Mean specific force, ENU m/s^2.
    q : ndarray (12, 12)
        Noise PSD.
    dt : ndarray (m,)
        Cycle lengths, s.

    Returns
    -------
    Phi, Q : ndarray (m, 15, 15)
    """
    lat, h = np.asarray(lat, dtype=float), np.asarray(h, dtype=float)
    v = np.ascontiguousarray(v_n, dtype=float)
    rm, rn = earth.principal_radii(lat, h)
    # the terms the kernel takes in its T_* order: the transcendental functions stay numpy's
    terms = np.column_stack([rm, rn, np.sin(lat), np.cos(lat), earth.gravity(lat, h), earth.omega_ie_n(lat),
                             earth.omega_en_n(lat, h, v)])
    m = len(lat)
    Phi, Q = np.empty((m, N_STATES, N_STATES)), np.empty((m, N_STATES, N_STATES))
    args = tuple(np.ascontiguousarray(a, dtype=float) for a in (terms, v, C_bn, f_n, dt, q))
    shapes = ((m, 11), (m, 3), (m, 3, 3), (m, 3), (m,), (N_NOISE, N_NOISE))
    if tuple(a.shape for a in args) != shapes:
        raise ValueError(f"cycle matrices need lat, h, dt (m,), v_n, f_n (m, 3), C_bn (m, 3, 3), q (12, 12): "
                         f"{[a.shape for a in args[1:]]}")
    cycle_kernel().fieldlog_cycle_matrices(m, earth.OMEGA_IE, *map(kernels.address, (*args, Phi, Q)))
    return Phi, Q


def propagate_covariance(Phi: np.ndarray, Q: np.ndarray, P: np.ndarray, q_scale: float = 1.0, sym: bool = True
                         ) -> np.ndarray:
    """P through the cycles: P <- Phi_i P Phi_i^T + q_scale Q_i, made symmetric (0.5 (P + P^T)) after each when
    ``sym``. P itself is left alone.

    Parameters
    ----------
    Phi, Q : ndarray (m, n, n)
        The cycles' transition matrices and process noise.
    P : ndarray (n, n)
        The covariance before the first cycle (error-state units squared).
    q_scale : float
        Multiplies Q (a federated local filter's 1/beta).
    sym : bool
        Symmetrise after each cycle (False: a cross-covariance).

    Returns
    -------
    ndarray (m, n, n)
        P after each cycle.

    15 states: compiled (fusion/_cycles.c), the same numbers as the numpy loop under the condition of
    :func:`discrete_cycles`. A filter with more states (the GPS error's, ``fusion.gpserror``) runs the numpy loop:
    OpenBLAS sums products of some other sizes (17 to 20 rows, for one) in another order."""
    Phi, Q = np.ascontiguousarray(Phi, dtype=float), np.ascontiguousarray(Q, dtype=float)
    work = np.array(P, dtype=float, order="C")
    hist = np.empty(Phi.shape)
    if work.shape != (N_STATES, N_STATES) or Phi.shape[1:] != work.shape or Q.shape != Phi.shape:
        for i in range(len(Phi)):
            work = Phi[i] @ work @ Phi[i].T + q_scale * Q[i]
            hist[i] = work = 0.5 * (work + work.T) if sym else work
        return hist
    cycle_kernel().fieldlog_propagate_cov(len(Phi), kernels.address(Phi), kernels.address(Q), float(q_scale),
                                          int(sym), kernels.address(work), kernels.address(hist))
    return hist


_SEGMENT_SHAPES = ((), (3,), (3,), (3, 3), (N_STATES, N_STATES), (N_STATES, N_STATES))  # dt, f_mean, w_mean, C_bn,
# Phi, Q of a cycle (segment_cycles), and where each starts in a row of them
_SEGMENT_OFFSETS = tuple(int(x) for x in np.cumsum([0] + [math.prod(s) for s in _SEGMENT_SHAPES]))


@dataclass
class Cycles:
    """The filter cycles of an INS segment: sample indices of each cycle's start, middle and end (m,), lengths dt
    (m,) s, mean bias-corrected specific force f_mean and rate w_mean (m, 3) (m/s^2, rad/s, body RFU) over each,
    the middle sample's C_bn (m, 3, 3), and the discrete Phi, Q (m, 15, 15)."""

    starts: np.ndarray
    mid: np.ndarray
    ends: np.ndarray
    dt: np.ndarray
    f_mean: np.ndarray
    w_mean: np.ndarray
    C_bn: np.ndarray
    Phi: np.ndarray
    Q: np.ndarray


class BiasSteps:
    """The scale factors and misalignments of both triads as steps of the bias states (``scale_factor_model =
    "bias-steps"``, ``fusion.imugrade``): each cycle's bias step (S + M) dx (``scale_factor_steps``), dx the change
    of the cycle's mean rate and specific force from the cycle before (from 0 before the filter's first cycle: the
    first step is (S + M) x_0), taken as a step at the cycle's start and carried through its Phi. Scale factors
    (fractions) and misalignments (rad), 1-sigma per entry."""

    def __init__(self, gyro_sf: float, gyro_ma: float, accel_sf: float, accel_ma: float) -> None:
        self.gyro, self.accel = (gyro_sf, gyro_ma), (accel_sf, accel_ma)
        self.ref = np.zeros(6)  # the last cycle's mean rate (rad/s) and specific force (m/s^2), body RFU

    @classmethod
    def of(cls, sensor) -> BiasSteps | None:
        """The steps of a sensor configuration.

        Parameters
        ----------
        sensor : fusion.config.SensorConfig
            Its scale factors (ppm) and misalignments (mrad).

        Returns
        -------
        BiasSteps or None
            None unless its scale_factor_model is "bias-steps" with a figure above 0.
        """
        f = (sensor.gyro_scale_factor_ppm * 1e-6, sensor.gyro_misalignment_mrad * 1e-3,
             sensor.accel_scale_factor_ppm * 1e-6, sensor.accel_misalignment_mrad * 1e-3)
        return cls(*f) if sensor.scale_factor_model == "bias-steps" and max(f) > 0.0 else None

    def noise(self, Phi: np.ndarray, w_mean: np.ndarray, f_mean: np.ndarray) -> np.ndarray:
        """The covariance the steps of the cycles add; the last cycle's means become the reference.

        Parameters
        ----------
        Phi : ndarray (m, 15, 15)
            The cycles' transition matrices.
        w_mean, f_mean : ndarray (m, 3)
            Their mean bias-corrected rate (rad/s) and specific force (m/s^2), body RFU.

        Returns
        -------
        ndarray (m, 15, 15)
            Added to each cycle's Q.
        """
        var = np.hstack([scale_factor_steps(w_mean, self.ref[:3], *self.gyro),
                         scale_factor_steps(f_mean, self.ref[3:], *self.accel)])
        self.ref = np.concatenate([w_mean[-1], f_mean[-1]])
        Phi_b = Phi[:, :, BG.start:BA.stop]
        return (Phi_b * var[:, None, :]) @ np.swapaxes(Phi_b, 1, 2)


def segment_cycles(sol, ends: np.ndarray, w_b: np.ndarray, f_b: np.ndarray, q: np.ndarray,
                   steps: BiasSteps | None = None) -> Cycles:
    """The cycles of an INS solution ``sol`` (``fusion.ins.NavSolution``: t, lat, h, v_n, q per sample) over
    bias-corrected samples w_b, f_b (n, 3), each cycle ending at a sample of ``ends`` (the first cycle starts at
    sample 0); F taken at each cycle's middle sample with its mean specific force, noise PSD q (12, 12), and the
    scale factors' bias ``steps`` (``BiasSteps``) added to Q when given.

    Parameters
    ----------
    sol : fusion.ins.NavSolution
        The INS solution over the segment.
    ends : ndarray of int (m,)
        The sample each cycle ends at.
    w_b, f_b : ndarray (n, 3)
        The bias-corrected samples, rad/s and m/s^2, body RFU.
    q : ndarray (12, 12)
        Noise PSD.
    steps : BiasSteps, optional
        The scale factors as bias steps.

    Returns
    -------
    Cycles
        The cycles with their Phi and Q.
    """
    ends = np.ascontiguousarray(ends, dtype=np.int64)
    starts = np.concatenate([[0], ends[:-1]])
    mid = (starts + ends) // 2
    lat = sol.lat[mid]
    trig = np.concatenate([np.sin(lat), np.cos(lat), np.tan(lat)])  # the transcendental functions stay numpy's
    m, n = len(ends), len(sol.t)
    ins = tuple(np.ascontiguousarray(a, dtype=float) for a in (sol.t, w_b, f_b, sol.q, sol.h, sol.v_n, q))
    if tuple(a.shape for a in ins) != ((n,), (n, 3), (n, 3), (n, 4), (n,), (n, 3), (N_NOISE, N_NOISE)):
        raise ValueError(f"segment cycles need a solution of n samples, w_b and f_b (n, 3), q (12, 12): "
                         f"{[a.shape for a in ins]}")
    out = np.empty(m * _SEGMENT_OFFSETS[-1])  # one buffer, the cycles' arrays side by side
    dt, f_mean, w_mean, C, Phi, Q = (out[m * a:m * b].reshape((m, *shape)) for a, b, shape in zip(
        _SEGMENT_OFFSETS, _SEGMENT_OFFSETS[1:], _SEGMENT_SHAPES))
    base = out.ctypes.data
    if cycle_kernel().fieldlog_segment_cycles(n, m, kernels.address(ends), *map(kernels.address, ins[:6]),
                                              kernels.address(trig), kernels.address(earth.KERNEL_CONSTANTS),
                                              kernels.address(ins[6]),
                                              *(base + 8 * m * a for a in _SEGMENT_OFFSETS[:-1])):
        raise ValueError("segment cycles need ends strictly increasing, above 0 and below the number of samples")
    if steps is not None:
        Q = Q + steps.noise(Phi, w_mean, f_mean)
    return Cycles(starts, mid, ends, dt, f_mean, w_mean, C, Phi, Q)
