"""The fusion methods, one object each: the one place a method's name is spelled.

A :class:`Method` names what the fusion loop (``fusion.engine.Engine``) asks of it: its filter factory, its
measurements, its outage bridge and its output topics; the CLI's choices, the viewer's colours and the
evaluation's lists come from here. Adding a method is one module (its filter, e.g. ``fusion/hinf.py``) and one
line in ``REGISTRY``.

Importing this module imports no numpy and none of the filters (``fieldlog --help`` lists the methods without the
fusion stack): each factory imports its filter when called.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable

if TYPE_CHECKING:
    import numpy as np

    from fieldlog.fusion.config import FusionConfig

FilterFactory = Callable[["np.ndarray", "np.ndarray", "FusionConfig"], Any]


@dataclass(frozen=True)
class Bridge:
    """How a method bridges a GPS outage with a network trained on the epochs before it (``fusion.outages``).

    network: the predictor's network kind (``fusion.predictors.NETWORKS``); hybrid: the prediction goes into the
    distributed filter's local state predictions (the paper's section 2.3, eq. 7) rather than into the INS as the
    correction (section 2.2)."""

    network: str
    hybrid: bool = False


def _centralised(P0: np.ndarray, q: np.ndarray, cfg: FusionConfig) -> Any:
    """The closed-loop 15-state KF (``fusion.kf``); with ``[fusion] gps_error_model = "gm-states"`` the GPS error
    carried as states (``fusion.gpserror``)."""
    if cfg.gps.gps_error_model == "gm-states":
        from fieldlog.fusion import gpserror

        return gpserror.GpsErrorKF(P0, q, cfg.gps.gps_error_tau_s, cfg.gps.gps_error_white_share)
    from fieldlog.fusion import kf

    return kf.KalmanFilter(P0, q)


def _distributed(P0: np.ndarray, q: np.ndarray, cfg: FusionConfig) -> Any:
    """The paper's distributed filter, KF_I (velocity) and KF_II (position) fused by eqs. 3-4 (``fusion.dkf``)."""
    from fieldlog.fusion.dkf import DistributedKF

    return DistributedKF(P0, q, cfg.filter.dkf_fusion)


def _hinf(P0: np.ndarray, q: np.ndarray, cfg: FusionConfig) -> Any:
    """The H-infinity filter (``fusion.hinf``)."""
    from fieldlog.fusion import hinf

    return hinf.HInfinityFilter(P0, q, cfg.filter.hinf_gamma, min_ratio=cfg.filter.hinf_min_ratio)


def _kf_ukf(P0: np.ndarray, q: np.ndarray, cfg: FusionConfig) -> Any:
    """The hybrid KF/UKF (``fusion.ukf``)."""
    from fieldlog.fusion import ukf

    return ukf.HybridKfUkf(P0, q)


def _sckf(P0: np.ndarray, q: np.ndarray, cfg: FusionConfig) -> Any:
    """The square-root cubature KF (``fusion.sckf``)."""
    from fieldlog.fusion import sckf

    return sckf.sckf(P0, q)


def _ssr_sckf(P0: np.ndarray, q: np.ndarray, cfg: FusionConfig) -> Any:
    """The adaptive simplex-radial square-root cubature KF (``fusion.sckf``)."""
    from fieldlog.fusion import sckf

    return sckf.ssr_sckf(P0, q)


@dataclass(frozen=True)
class Method:
    """One fusion method.

    name: as the CLI, the config and the output topics (``/fusion/<name>/...``) spell it; filter: the factory of
    its filter object, ``filter(P0 (15, 15), q (12, 12) noise PSD, FusionConfig)``; aided: it runs the
    measurements (``fusion.measurements.aids_and_gps``: the vehicle aids, then the GPS velocity and position), False
    for the free INS; bridge: its outage bridge, None for none; local_filters: its output topics include the
    distributed filter's local solutions (``/fusion/<name>/kf1/*``, ``kf2/*``); gps_error_states: ``[fusion]
    gps_error_model = "gm-states"`` applies (the states are the centralised filter's); speed_bridge: with
    ``[fusion] predictor_mode = "pseudo"`` it bridges outages with the learnt forward speed (a virtual odometer,
    ``fusion.pseudo``) instead of ``bridge``; colour: the viewer's RGB, None for one of its palette."""

    name: str
    filter: FilterFactory
    aided: bool = True
    bridge: Bridge | None = None
    local_filters: bool = False
    gps_error_states: bool = False
    speed_bridge: bool = False
    colour: tuple[int, int, int] | None = None

    def measurements(self, cfg: FusionConfig) -> list:
        """The measurement objects the loop applies, in its order (``fusion.measurements.aids_and_gps``); none for
        an unaided method.

        Parameters
        ----------
        cfg : FusionConfig, the run's settings

        Returns
        -------
        list
            The measurement objects (``fusion.measurements``).
        """
        if not self.aided:
            return []
        from fieldlog.fusion.measurements import aids_and_gps

        return aids_and_gps(cfg, self.learns_speed(cfg))

    def learns_speed(self, cfg: FusionConfig) -> bool:
        """Whether this run bridges outages with the virtual odometer (``speed_bridge`` and ``[fusion]
        predictor_mode = "pseudo"``) rather than with ``bridge``.

        Parameters
        ----------
        cfg : FusionConfig, as :meth:`measurements`

        Returns
        -------
        bool
        """
        return self.speed_bridge and cfg.filter.predictor_mode == "pseudo"


INS = Method("ins", _centralised, aided=False, colour=(200, 40, 40))
KF = Method("kf", _centralised, gps_error_states=True, colour=(30, 100, 255))
DKF = Method("dkf", _distributed, local_filters=True, colour=(150, 60, 210))
RBFN = Method("rbfn", _distributed, bridge=Bridge("rbf"), local_filters=True, colour=(200, 120, 0))
TDLN = Method("tdln", _distributed, bridge=Bridge("tdl"), local_filters=True, colour=(120, 80, 40))
DKF_RBFN = Method("dkf-rbfn", _distributed, bridge=Bridge("rbf", hybrid=True), local_filters=True, speed_bridge=True,
                  colour=(0, 175, 190))
KF_UKF = Method("kf-ukf", _kf_ukf, colour=(230, 60, 160))
HINF = Method("hinf", _hinf, colour=(40, 40, 140))
SCKF = Method("sckf", _sckf)
SSR_SCKF = Method("ssr-sckf", _ssr_sckf, colour=(90, 90, 90))

REGISTRY: dict[str, Method] = {m.name: m for m in (INS, KF, DKF, RBFN, TDLN, DKF_RBFN, KF_UKF, HINF, SCKF, SSR_SCKF)}
METHODS = tuple(REGISTRY)  # the names, in the order the CLI lists them


def get(name: str) -> Method:
    """The method called ``name``; ValueError naming the known ones otherwise.

    Parameters
    ----------
    name : str, a method name (``METHODS``)

    Returns
    -------
    Method

    Raises
    ------
    ValueError
        For an unknown name.
    """
    try:
        return REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown method {name!r}; one of {METHODS}") from None
