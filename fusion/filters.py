"""The filter each method runs: one object with the interface of ``fusion.kf.KalmanFilter`` (``propagate``,
``update_batch``, ``start_outage``, ``reset``, ``state``, ``covariance`` and the declarations of what it needs).

``hinf``, ``kf-ukf``, ``sckf`` and ``ssr-sckf`` are ``kf`` with another filter object (``fusion.hinf``,
``fusion.ukf``, ``fusion.sckf``); ``dkf`` and the predictor methods run the distributed filter (``fusion.dkf``);
``kf`` with ``[fusion] gps_error_model = "gm-states"`` carries the GPS error as states (``fusion.gpserror``).
"""

from __future__ import annotations

import numpy as np

from fieldlog.fusion import gpserror, hinf, kf, sckf, ukf
from fieldlog.fusion.config import FusionConfig
from fieldlog.fusion.dkf import DistributedKF
from fieldlog.fusion.outages import PREDICTOR_NETWORK


def has_local_filters(method: str) -> bool:
    """Whether the method's filter is the distributed one, whose local filters' solutions are written too."""
    return method == "dkf" or method in PREDICTOR_NETWORK


def make_filter(method: str, P0: np.ndarray, q: np.ndarray, cfg: FusionConfig) -> kf.KalmanFilter | DistributedKF:
    """The filter object of a method, started at P0 (15, 15) with noise PSD q (12, 12)."""
    if has_local_filters(method):
        return DistributedKF(P0, q, cfg.filter.dkf_fusion)
    if method == "hinf":
        return hinf.HInfinityFilter(P0, q, cfg.filter.hinf_gamma, min_ratio=cfg.filter.hinf_min_ratio)
    if method == "kf-ukf":
        return ukf.HybridKfUkf(P0, q)
    if method in sckf.FILTERS:
        return sckf.FILTERS[method](P0, q)
    if cfg.gps.gps_error_model == "gm-states":
        return gpserror.GpsErrorKF(P0, q, cfg.gps.gps_error_tau_s, cfg.gps.gps_error_white_share)
    return kf.KalmanFilter(P0, q)
