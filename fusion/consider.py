"""What the gyros' scale-factor and misalignment errors do to the estimate: a consider (sensitivity) analysis.

The 15-state model (``fusion.errmodel``) has no states for the gyro triad's scale-factor errors s_i and
misalignments m_ij (i != j): the measured rate is (I + S)(I + M) omega_ib_b + bias + noise, and with
``scale_factor_model = "consider"`` (FusionConfig's default) the filter takes the S and M part as noise (its gyro
noise and bias walk are inflated for them). With ``"bias-steps"`` (an IMU grade, ``fusion.imugrade``) the filter
models that part as steps of its bias states, and this analysis is not run. That part is not noise: it is
the constant c = [s_x, s_y, s_z, m_xy, m_xz, m_yx, m_yz, m_zx, m_zy] times the rate, so in a figure-eight its
sign follows the turn. Its tilt error comes and goes with the turns, which in the body frame is what a
horizontal accelerometer bias looks like, and the filter's accelerometer bias estimate takes it in while its
covariance says the two are separated, so (without the consider term below) its printed sigma does not cover the
bias error. The accelerometers' own scale factor and misalignment are not the cause (see below); the gyros'
are. Figures: docs/results.md, "Bias estimates".

Standard consider analysis (Schmidt; Maybeck vol. 1, ch. 6 sensitivity): the estimation error the filter does not
know of is S c, with the sensitivity S (15, 9) propagated beside the covariance and passed through each update
as the error is:

    predict:  S <- Phi S + Gamma,   Gamma = (I + Phi) / 2 B dt,   B = d(x')/dc: phi' = -C_bn (S + M) omega_ib_b
    update:   S <- (I - K H) S      (K the update's gain)

and the consider covariance is S diag(sigma_c^2) S^T, with sigma_c the grade's 1-sigma scale factor and
misalignment (``fusion.imugrade``; ``[fusion] gyro_scale_factor_ppm``, ``gyro_misalignment_mrad``). It is
added to the printed accelerometer-bias variance only (forward and smoothed), so the estimate does not change. Only there: the
filter's noise was inflated (``FusionConfig``) for the position, velocity, attitude and gyro bias to absorb
this error, and their sigmas cover it; the simulator's truth of the gyro bias (``/truth/imu_bias``) holds
(S + M) omega_ib_b itself. The accelerometers' own scale factor and misalignment are left out: their effect
(mainly M x g) is constant in the body frame and the bias states take it (the estimate follows M x g).

Smoothing (``fusion.smoother``) carries S back as it carries the error: Ss_k = S+_k + C_k (Ss_{k+1} - S-_{k+1}).

K is the gain of a linear KF update with the filter's covariance before the update (``gain``): kf's own gain;
for the other methods the gain a KF with their (fused) covariance would use, an approximation of theirs.
"""

from __future__ import annotations

import numpy as np

from fieldlog.fusion import errmodel, kernels
from fieldlog.fusion.errmodel import ATT, N_STATES

N_PARAMS = 9
_MA = [(i, j) for i in range(3) for j in range(3) if i != j]  # misalignment m_ij: rate j read on axis i
_AXIS = np.array([0, 1, 2] + [i for i, _ in _MA])  # per parameter of c: the axis i that reads rate j
_RATE = np.array([0, 1, 2] + [j for _, j in _MA])


def gyro_sensitivity(C_bn: np.ndarray, omega_b: np.ndarray, dt: np.ndarray) -> np.ndarray:
    """B dt: the error-state change over each cycle per unit of c (module docstring).

    Parameters
    ----------
    C_bn : ndarray (m, 3, 3)
        Each cycle's attitude, body RFU -> ENU.
    omega_b : ndarray (m, 3)
        Each cycle's mean bias-corrected rate, rad/s, body RFU.
    dt : ndarray (m,)
        Cycle lengths, s.

    Returns
    -------
    ndarray (m, 15, 9)
        B dt per cycle (``fusion.errmodel`` state order; c as the module docstring orders it).
    """
    B = np.zeros((len(dt), N_STATES, N_PARAMS))
    B[:, ATT] = -C_bn[:, :, _AXIS] * omega_b[:, None, _RATE]  # column p: -C_bn[:, i] times rate j (one pass)
    return B * np.asarray(dt, float)[:, None, None]


def gain(P: np.ndarray, H: np.ndarray, R: np.ndarray) -> np.ndarray:
    """K (15, m) of a linear KF update, compiled (fusion/_cycles.c): K = P H^T (H P H^T + R)^-1.

    Parameters
    ----------
    P : ndarray (15, 15)
        The filter's covariance before the update (``fusion.errmodel`` order and units).
    H : ndarray (m, 15)
        The measurement's sensitivity to the error state (m <= 32).
    R : ndarray (m, m)
        Its noise covariance.

    Returns
    -------
    ndarray (15, m)
        The gain.
    """
    P, H, R = (np.ascontiguousarray(a, dtype=float) for a in (P, H, R))
    K = np.empty((N_STATES, len(H)))
    if errmodel.cycle_kernel().fieldlog_kf_gain(len(H), *map(kernels.address, (H, R, P, K))):
        raise np.linalg.LinAlgError("Singular matrix: the innovation covariance H P H^T + R")
    return K


class GyroConsider:
    """The sensitivity S (15, 9) of the error state to the gyro scale factors and misalignments, and the consider
    variance it gives. scale_factor (fraction) and misalignment (rad): 1-sigma per axis of the unmodelled c."""

    def __init__(self, scale_factor: float, misalignment: float) -> None:
        self.S = np.zeros((N_STATES, N_PARAMS))
        self.var_c = np.repeat([scale_factor ** 2, misalignment ** 2], [3, 6])

    def variance(self, S: np.ndarray | None = None) -> np.ndarray:
        """The consider variance diag(S diag(var_c) S^T).

        Parameters
        ----------
        S : ndarray (..., 15, 9), optional
            Sensitivities; the current one by default.

        Returns
        -------
        ndarray (..., 15)
            The variance each state's error gets from c, in the state's units squared.
        """
        S = self.S if S is None else S
        return (S * S) @ self.var_c

    def propagate(self, Phi: np.ndarray, Bdt: np.ndarray) -> np.ndarray:
        """S through cycles, compiled (fusion/_cycles.c): S <- Phi S + 0.5 (Bdt + Phi Bdt) per cycle.

        Parameters
        ----------
        Phi : ndarray (m, 15, 15)
            The cycles' transition matrices.
        Bdt : ndarray (m, 15, 9)
            Their :func:`gyro_sensitivity`.

        Returns
        -------
        ndarray (m, 15, 9)
            S after each cycle.
        """
        Phi, Bdt = np.ascontiguousarray(Phi, dtype=float), np.ascontiguousarray(Bdt, dtype=float)
        if Phi.shape[1:] != (N_STATES, N_STATES) or Bdt.shape != (len(Phi), N_STATES, N_PARAMS):
            raise ValueError(f"consider cycles need Phi (m, 15, 15) and Bdt (m, 15, 9): {Phi.shape}, {Bdt.shape}")
        S = np.array(self.S, dtype=float, order="C")
        out = np.empty((len(Phi), N_STATES, N_PARAMS))
        # compiled (fusion/_cycles.c): per cycle S <- Phi S + 0.5 (Bdt + Phi Bdt), numpy's numbers (errmodel's note)
        errmodel.cycle_kernel().fieldlog_consider_cycles(len(Phi), *map(kernels.address, (Phi, Bdt, S, out)))
        self.S = S
        return out

    def update(self, K: np.ndarray, H: np.ndarray) -> None:
        """The update x <- x + K (z - H x) leaves the error (I - K H) times the one before it: S likewise.

        Parameters
        ----------
        K : ndarray (15, m)
            The update's gain (:func:`gain`).
        H : ndarray (m, 15)
            Its measurement sensitivity.
        """
        self.S = self.S - K @ (H @ self.S)
