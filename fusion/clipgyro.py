"""A clipped yaw gyro, rebuilt from the car's turn kinematics.

A yaw gyro flat at ``gyro_range_dps`` (the Table 2 gyro clips at 20 deg/s; a 90-degree city turn needs 23) is
rebuilt from the car's turn kinematics (yaw rate = -lateral acceleration / forward speed); the engine integrates
the segment again, and the heading process noise grows by the rebuilt rate's uncertainty (:func:`clip_noise`).
"""

from __future__ import annotations

import numpy as np

from fieldlog.fusion import earth, ins
from fieldlog.fusion.errmodel import ATT, N_STATES

CLIP_CORR_S = 3.0  # the rebuilt rate's error is correlated over a turn: white noise of the same variance


def clipped(wz: np.ndarray, limit: float) -> np.ndarray:
    """Saturated samples of a gyro channel (n,) rad/s: at the range limit (rad/s) and flat (equal to a
    neighbour: the ADC clips to one value, a live signal with its noise never repeats exactly).

    Parameters
    ----------
    wz : (n,) ndarray, one gyro channel, rad/s
    limit : float, the gyro's range, rad/s

    Returns
    -------
    (n,) bool ndarray
        True where the sample is saturated.
    """
    at = np.abs(wz) >= limit * (1.0 - 1e-3)
    if not at.any():  # (most segments: nothing near the limit)
        return at
    flat = np.zeros(len(wz), bool)
    same = wz[1:] == wz[:-1]
    flat[1:] |= same
    flat[:-1] |= same
    return flat & at


def turn_rate(wz: np.ndarray, f_b: np.ndarray, sol: ins.NavSolution, clip: np.ndarray) -> np.ndarray:
    """The yaw rate (rad/s, body up) with its clipped samples rebuilt from the car's turn kinematics: a car
    moving along its forward axis turns at omega_z = -a_x / v_y (a_b = f_b + C_nb g_n, the lateral
    acceleration, v_y the forward speed), taken from the INS of the clipped pass (its roll, pitch and speed
    are unaffected). Only magnitudes above the clipped value and of the same sign are taken.

    Parameters
    ----------
    wz : (n,) ndarray, yaw rate about body up as measured, rad/s
    f_b : (n, 3) ndarray, specific force, body RFU, m/s^2
    sol : ins.NavSolution, the INS of the clipped pass at the same n samples
    clip : (n,) bool ndarray, the saturated samples (:func:`clipped`)

    Returns
    -------
    (n,) ndarray
        The yaw rate about body up, rad/s.
    """
    C = earth.quat_to_dcm(sol.q)
    a_b = f_b + np.einsum("nji,nj->ni", C, earth.gravity_n(sol.lat, sol.h))
    v_fwd = np.einsum("nj,nj->n", C[:, :, 1], sol.v_n)
    with np.errstate(divide="ignore", invalid="ignore"):
        rate = -a_b[:, 0] / v_fwd
    ok = clip & (np.abs(v_fwd) > 1.0) & (np.sign(rate) == np.sign(wz))
    return np.where(ok, np.sign(wz) * np.maximum(np.abs(wz), np.abs(rate)), wz)


def clip_noise(clip: np.ndarray, t: np.ndarray, starts: np.ndarray, ends: np.ndarray, C: np.ndarray,
               sigma: float) -> np.ndarray:
    """Process noise (m, 15, 15) of the rebuilt yaw rates over the filter cycles (starts, ends] of samples at
    times t: a rate error of sigma rad/s about the body up axis (C (m, 3, 3) C_bn at the cycles), correlated
    over ``CLIP_CORR_S``, for the clipped time of each cycle.

    Parameters
    ----------
    clip : (n,) bool ndarray, the saturated samples (:func:`clipped`)
    t : (n,) ndarray, sample times, s
    starts, ends : (m,) int ndarray, sample index of each cycle's start and end
    C : (m, 3, 3) ndarray, ``C_bn`` (body RFU -> ENU) of each cycle
    sigma : float, standard deviation of the rebuilt rate, rad/s

    Returns
    -------
    (m, 15, 15) ndarray
        Discrete process noise, non-zero in the attitude block only, rad^2.
    """
    dt = np.diff(t, prepend=t[0]) * clip
    c = np.cumsum(dt)
    secs = c[ends] - c[starts]
    u = C[:, :, 2]
    out = np.zeros((len(ends), N_STATES, N_STATES))
    out[:, ATT, ATT] = (sigma * sigma * CLIP_CORR_S * secs)[:, None, None] * np.einsum("mi,mj->mij", u, u)
    return out
