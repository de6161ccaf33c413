"""What the fusion loop tells others as it runs: the consider analysis, the correlated GPS error and the smoother's
records listen to it (``fusion.engine.Engine``), none is a branch of the loop.

:class:`Listener` lists the calls, each a no-op by default:

- ``start(t_ns, P0)``: the filter starts (alignment) at t_ns with covariance P0 (15, 15);
- ``cycles(t_end_ns, Phi, P, C_bn, omega_b, dt, diag)``: filter cycles ending at t_end_ns (m,), their Phi (m, 15, 15),
  the predicted covariances (m, 15, 15; None unless some listener ``records_history``), the cycles' attitude C_bn
  (m, 3, 3), mean bias-corrected rate (m, 3) rad/s and lengths dt (m,) s; diag (m, 15) the covariance diagonals the
  solution rows print: a listener may add to it (in place) what the filter's covariance does not hold;
- ``update(P, H, R)``: an update with the stacked H (k, 15) and R (k, k) on covariance P (before it);
- ``feedback(x, P)``: the estimate x (15,) corrects the INS, covariance P after the update;
- ``fix(epoch, filt, period_s)``: a GPS fix was used by filter ``filt``; the fixes come period_s apart;
- ``bridged(x)``: a predicted correction x (15,) (an outage predictor's) went into the INS.

``records_history`` (a listener's attribute): it needs every cycle's predicted covariance, so the loop propagates
one cycle at a time, and it cannot take a re-alignment (its record has no jump).
"""

from __future__ import annotations

import numpy as np

from fieldlog.fusion import consider, output
from fieldlog.fusion.errmodel import BA, POS
from fieldlog.fusion.smoother import SmootherLog
from fieldlog.fusion.types import Epoch


class Listener:
    """The calls of the loop (module docstring); every one a no-op here."""

    records_history = False

    def start(self, t_ns: int, P0: np.ndarray) -> None:
        """The filter started.

        Parameters
        ----------
        t_ns : int, alignment time, UTC ns
        P0 : (15, 15) ndarray, initial error covariance, ``fusion.errmodel`` units squared
        """

    def cycles(self, t_end_ns: np.ndarray, Phi: np.ndarray, P: np.ndarray | None, C_bn: np.ndarray,
               omega_b: np.ndarray, dt: np.ndarray, diag: np.ndarray) -> None:
        """Filter cycles ran.

        Parameters
        ----------
        t_end_ns : (m,) int64 ndarray, cycle end times, UTC ns
        Phi : (m, 15, 15) ndarray, transition matrix of each cycle
        P : (m, 15, 15) ndarray or None, predicted covariance at each cycle end (None unless ``records_history``)
        C_bn : (m, 3, 3) ndarray, attitude of each cycle, body RFU -> ENU
        omega_b : (m, 3) ndarray, mean bias-corrected angular rate of each cycle, body RFU, rad/s
        dt : (m,) ndarray, cycle lengths, s
        diag : (m, 15) ndarray, the printed covariance diagonals, ``fusion.errmodel`` units squared (may be added to)
        """

    def update(self, P: np.ndarray, H: np.ndarray, R: np.ndarray) -> None:
        """An update is about to run.

        Parameters
        ----------
        P : (15, 15) ndarray, covariance before the update
        H : (k, 15) ndarray, stacked measurement matrix
        R : (k, k) ndarray, stacked measurement noise covariance (m^2, (m/s)^2 by row)
        """

    def feedback(self, x: np.ndarray, P: np.ndarray) -> None:
        """An estimate was fed back.

        Parameters
        ----------
        x : (15,) ndarray, the estimate fed back, ``fusion.errmodel`` order and units
        P : (15, 15) ndarray, covariance after the update
        """

    def fix(self, epoch: Epoch, filt, period_s: float) -> None:
        """A GPS fix was used.

        Parameters
        ----------
        epoch : Epoch, the GPS epoch
        filt : KalmanFilter, the filter it updated (``fusion.kf`` interface)
        period_s : float, time between fixes, s
        """

    def bridged(self, x: np.ndarray) -> None:
        """A predicted correction was fed in.

        Parameters
        ----------
        x : (15,) ndarray, the predicted correction, ``fusion.errmodel`` order and units
        """


class SmootherRecorder(Listener):
    """Fills a ``fusion.smoother.SmootherLog`` for the backward pass: per cycle Phi and the predicted covariance,
    at each update the correction fed back and the covariance after it, the predicted corrections."""

    records_history = True

    def __init__(self, log: SmootherLog) -> None:
        self.log = log

    def start(self, t_ns: int, P0: np.ndarray) -> None:
        """Record the initial covariance.

        Parameters
        ----------
        t_ns, P0 : as :meth:`Listener.start`
        """
        self.log.start(t_ns, P0)

    def cycles(self, t_end_ns, Phi, P, C_bn, omega_b, dt, diag) -> None:
        """Record Phi and the predicted covariance of each cycle.

        Parameters
        ----------
        t_end_ns, Phi, P, C_bn, omega_b, dt, diag : as :meth:`Listener.cycles`
        """
        self.log.cycles(t_end_ns, Phi, P)

    def feedback(self, x: np.ndarray, P: np.ndarray) -> None:
        """Record the correction and the covariance after the update.

        Parameters
        ----------
        x, P : as :meth:`Listener.feedback`
        """
        self.log.update(x.copy(), P.copy())

    def bridged(self, x: np.ndarray) -> None:
        """Record the predicted correction.

        Parameters
        ----------
        x : as :meth:`Listener.bridged`
        """
        self.log.bridge(x)


class GyroConsider(Listener):
    """The consider analysis of the gyros' scale factors and misalignments (``fusion.consider``): its sensitivity
    follows the cycles and updates, and its variance is added to the printed accelerometer-bias variance;
    with a ``log``, the sensitivity is recorded for the smoother (after the :class:`SmootherRecorder`'s record
    of the same cycles)."""

    def __init__(self, scale_factor: float, misalignment: float, log: SmootherLog | None) -> None:
        self.analysis = consider.GyroConsider(scale_factor, misalignment)
        self.log = log
        if log is not None:
            log.var_c = self.analysis.var_c

    def cycles(self, t_end_ns, Phi, P, C_bn, omega_b, dt, diag) -> None:
        """Propagate the sensitivity and add its accelerometer-bias variance to ``diag``.

        Parameters
        ----------
        t_end_ns, Phi, P, C_bn, omega_b, dt, diag : as :meth:`Listener.cycles`
        """
        S = self.analysis.propagate(Phi, C_bn, omega_b, dt)
        diag[:, BA] += self.analysis.variance(S)[:, BA]
        if self.log is not None:
            self.log.sensitivity(S)

    def update(self, P: np.ndarray, H: np.ndarray, R: np.ndarray) -> None:
        """Update the sensitivity with the update's gain.

        Parameters
        ----------
        P, H, R : as :meth:`Listener.update`
        """
        self.analysis.update(P, H, R)
        if self.log is not None:
            self.log.sensitivity_update(self.analysis.S)


class GpsErrorBook(Listener):
    """The variance (m^2, E N U) of the time-correlated GPS error left in the position (``output.correlated_variance``)
    after each fix, for the fused rows (``var``) and the distributed filter's KF_II rows (``var_local``); nothing
    for a filter that carries that error as states (``models_gps_error``). With a ``log``, each fix's variance is
    kept for the smoothed rows."""

    def __init__(self, tau_s: float, log: SmootherLog | None) -> None:
        self.tau_s = tau_s
        self.log = log
        self.var = np.zeros(3)
        self.var_local = np.zeros(3)

    def fix(self, epoch: Epoch, filt, period_s: float) -> None:
        """The correlated GPS error variance left after this fix.

        Parameters
        ----------
        epoch, filt, period_s : as :meth:`Listener.fix`
        """
        r = np.diag(epoch.pos_cov)
        if not filt.models_gps_error:
            self.var = output.correlated_variance(r, np.diag(filt.covariance)[POS], period_s, self.tau_s)
        if filt.has_locals:  # KF_II's local solution averages the same fixes (KF_I sees no position)
            self.var_local = output.correlated_variance(r, np.diag(filt.locals[1].covariance)[POS], period_s,
                                                        self.tau_s)
        if self.log is not None:
            self.log.gps_var.append((epoch.t_ns, self.var.copy()))
