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

K is the gain of a linear KF update with the filter's covariance before the update (``GyroConsider.update``,
compiled): kf's own gain; for the other methods the gain a KF with their (fused) covariance would use, an
approximation of theirs.
"""

from __future__ import annotations

import numpy as np

from fieldlog.fusion import errmodel, kernels
from fieldlog.fusion.errmodel import N_STATES

N_PARAMS = 9  # c: 3 scale factors, then the misalignments m_ij (rate j read on axis i) in row order


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

    def propagate(self, Phi: np.ndarray, C_bn: np.ndarray, omega_b: np.ndarray, dt: np.ndarray) -> np.ndarray:
        """S through cycles, compiled (fusion/_cycles.c): S <- Phi S + 0.5 (B dt + Phi B dt) per cycle, with
        B dt = d(x')/dc dt: its attitude rows, column p, -C_bn[:, i] times rate j (the axis i that reads rate j
        for parameter p of c), times dt; its other rows zero.

        Parameters
        ----------
        Phi : ndarray (m, 15, 15)
            The cycles' transition matrices.
        C_bn : ndarray (m, 3, 3)
            Each cycle's attitude, body RFU -> ENU.
        omega_b : ndarray (m, 3)
            Each cycle's mean bias-corrected rate, rad/s, body RFU.
        dt : ndarray (m,)
            Cycle lengths, s.

        Returns
        -------
        ndarray (m, 15, 9)
            S after each cycle.
        """
        m = len(Phi)
        Phi, C_bn, omega_b, dt = (np.ascontiguousarray(a, dtype=float) for a in (Phi, C_bn, omega_b, dt))
        if (Phi.shape, C_bn.shape, omega_b.shape, dt.shape) != ((m, N_STATES, N_STATES), (m, 3, 3), (m, 3), (m,)):
            raise ValueError(f"consider cycles need Phi (m, 15, 15), C_bn (m, 3, 3), omega_b (m, 3) and dt (m,): "
                             f"{Phi.shape}, {C_bn.shape}, {omega_b.shape}, {dt.shape}")
        S = np.array(self.S, dtype=float, order="C")
        out = np.empty((m, N_STATES, N_PARAMS))
        # compiled (fusion/_cycles.c): B dt, then S <- Phi S + 0.5 (Bdt + Phi Bdt) per cycle, numpy's numbers
        # (errmodel's note)
        errmodel.cycle_kernel().fieldlog_consider_cycles(m, *map(kernels.address, (Phi, C_bn, omega_b, dt, S, out)))
        self.S = S
        return out

    def update(self, P: np.ndarray, H: np.ndarray, R: np.ndarray) -> None:
        """The update x <- x + K (z - H x), K = P H^T (H P H^T + R)^-1, leaves the error (I - K H) times the one
        before it: S likewise, compiled (fusion/_cycles.c).

        Parameters
        ----------
        P : ndarray (15, 15)
            The filter's covariance before the update (``fusion.errmodel`` order and units).
        H : ndarray (m, 15)
            The update's measurement sensitivity (m <= 32).
        R : ndarray (m, m)
            Its noise covariance.

        Raises
        ------
        numpy.linalg.LinAlgError
            When H P H^T + R is singular (S is left as it was).
        """
        P, H, R = (np.ascontiguousarray(a, dtype=float) for a in (P, H, R))
        S = np.array(self.S, dtype=float, order="C")
        if errmodel.cycle_kernel().fieldlog_consider_update(len(H), *map(kernels.address, (H, R, P, S))):
            raise np.linalg.LinAlgError("Singular matrix: the innovation covariance H P H^T + R")
        self.S = S
