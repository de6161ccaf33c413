"""The time-correlated GPS position error as filter states: ``[fusion] gps_error_model = "gm-states"``.

The alternative to the "consider" term (``fusion.output.correlated_variance``, the default), for ``kf``. The
receiver's position error e (ENU, m; GPS - true) is a first-order Gauss-Markov process per axis with the
correlation time tau = ``gps_error_tau_s``, carried as states 15:18 after the 15 INS error states
(``fusion.errmodel``)::

    e_k+1 = a e_k + w_k,   a = exp(-dt / tau),   var(w_k) = s^2 (1 - a^2)
    z_pos = INS position - GPS position = dr - e + white,   H = [I (position), -I (e)]

The receiver gives one figure per axis, r (its position variance); it is split as s^2 = (1 - f) r correlated and
f r white (R), f = ``gps_error_white_share``. The stationary variance s^2 follows the latest fix's r; e starts at
0 with variance s^2 at the first fix of each axis. The error states are not fed back (they are the receiver's,
not the INS's): the closed-loop reset clears the 15 INS error states only. The printed position sigma is then
the filter's own, with nothing added. Velocity and the vehicle aids do not see e.
"""

from __future__ import annotations

import numpy as np

from fieldlog.fusion.errmodel import N_STATES, POS
from fieldlog.fusion.kf import KalmanFilter, Observation

N_GPS = 3
GPS = slice(N_STATES, N_STATES + N_GPS)


class GpsErrorKF(KalmanFilter):
    """``kf`` with the GPS position error as three Gauss-Markov states (module docstring). ``state`` and
    ``covariance`` are the 15 INS error states' (what the engine feeds back and prints)."""

    wants_cycle_lengths = True
    models_gps_error = True
    keeps_predicted = False  # its P has the GPS error's states too

    def __init__(self, P0: np.ndarray, q: np.ndarray, tau_s: float, white_share: float) -> None:
        super().__init__(P0, q)
        if not tau_s > 0.0:
            raise ValueError("gps_error_model = 'gm-states' needs gps_error_tau_s > 0")
        if not 0.0 < white_share < 1.0:
            raise ValueError("gps_error_white_share must be between 0 and 1 (exclusive)")
        self.tau_s, self.white_share = float(tau_s), float(white_share)
        n = N_STATES + N_GPS
        self.x = np.zeros(n)
        P = np.zeros((n, n))
        P[:N_STATES, :N_STATES] = P0
        self.P = P
        self.s2 = np.full(N_GPS, np.nan)  # stationary variance of e per axis, m^2 (NaN before the axis's first fix)
        self._dt = np.zeros(0)

    @property
    def state(self) -> np.ndarray:
        return self.x[:N_STATES]

    @property
    def covariance(self) -> np.ndarray:
        return self.P[:N_STATES, :N_STATES]

    def cycles(self, dt: np.ndarray) -> None:
        """The lengths (s) of the filter cycles the next :meth:`propagate` call applies, (m,).

        Parameters
        ----------
        dt : (m,) array_like, cycle lengths, s
        """
        self._dt = np.asarray(dt, dtype=float)

    def propagate(self, Phi: np.ndarray, Q: np.ndarray) -> np.ndarray:
        """The INS cycles Phi, Q (m, 15, 15) (lengths given by :meth:`cycles`) with the Gauss-Markov block added;
        returns the INS states' diag(P) after each, (m, 15).

        Parameters
        ----------
        Phi, Q : (m, 15, 15) ndarray, as :meth:`fusion.kf.KalmanFilter.propagate`

        Returns
        -------
        (m, 15) ndarray, diag(P) of the 15 INS error states after each cycle.

        Raises
        ------
        ValueError
            When the cycle lengths were not given first.
        """
        m, n = len(Phi), len(self.x)
        if len(self._dt) != m:
            raise ValueError("GpsErrorKF.propagate: give the cycle lengths first (cycles)")
        a = np.exp(-self._dt / self.tau_s)
        s2 = np.nan_to_num(self.s2)
        Phi_a, Q_a = np.zeros((m, n, n)), np.zeros((m, n, n))
        Phi_a[:, :N_STATES, :N_STATES], Q_a[:, :N_STATES, :N_STATES] = Phi, Q
        i = np.arange(N_STATES, n)
        Phi_a[:, i, i] = a[:, None]
        Q_a[:, i, i] = s2[None] * (1.0 - a[:, None] ** 2)
        self._dt = np.zeros(0)
        return super().propagate(Phi_a, Q_a)[:, :N_STATES]

    def update(self, z: np.ndarray, H: np.ndarray, R: np.ndarray) -> np.ndarray:
        """An INS-only measurement (H (m, 15)) or one with the error columns already set (H (m, 18)).

        Parameters
        ----------
        z : (m,) ndarray, measurement (INS minus aid; m, m/s by kind)
        H : (m, 15) or (m, 18) ndarray, measurement matrix on the INS error states, or on them and the GPS error states
        R : (m, m) ndarray, measurement noise covariance, units of z squared

        Returns
        -------
        (15,) ndarray
            The INS states' part of K (z - H x), ``fusion.errmodel`` order and units.
        """
        if H.shape[1] == N_STATES:
            H = np.hstack([H, np.zeros((len(H), N_GPS))])
        return super().update(z, H, R)[:N_STATES]

    def update_batch(self, obs: list[Observation]) -> None:
        """The observations stacked, the receiver's position rows with the error states' columns (module
        docstring: H = [I, -I], R the white share); the other rows see no GPS error state.

        Parameters
        ----------
        obs : list of Observation, the epoch's observations (z, H (m, 15), R each), in order
        """
        out = []
        for o in obs:
            z, H, R = o.m
            if o.kind == "position" and o.receiver:
                axes = np.argmax(np.abs(H[:, POS]), axis=1)  # the position rows are unit rows
                r = np.diag(R)
                new = np.isnan(self.s2[axes])
                self.s2[axes] = (1.0 - self.white_share) * r
                for k in np.flatnonzero(new):
                    j = N_STATES + axes[k]
                    self.P[j, :], self.P[:, j] = 0.0, 0.0
                    self.P[j, j] = self.s2[axes[k]]
                Hg = np.zeros((len(H), N_GPS))
                Hg[np.arange(len(H)), axes] = -1.0
                out.append(Observation(o.kind, (z, np.hstack([H, Hg]), self.white_share * R), o.receiver))
            else:
                out.append(Observation(o.kind, (z, np.hstack([H, np.zeros((len(H), N_GPS))]), R), o.receiver))
        super().update_batch(out)

    def reset(self) -> None:
        """Closed loop: the INS error states are fed back and cleared; the GPS error states stay."""
        self.x = np.concatenate([np.zeros(N_STATES), self.x[N_STATES:]])
