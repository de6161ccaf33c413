"""Allan deviation of inertial sensor data and the noise parameters read from it (pure numpy).

Conventions (IEEE Std 952 / 1293): for a rate signal y with
- white noise of density N (units/sqrt(Hz)):      sigma(tau) = N / sqrt(tau)   (so N = sigma(1 s));
- flicker ("bias instability") B (units):         sigma(tau) = sqrt(2 ln2 / pi) * B ~= 0.664 B (flat);
- rate random walk K (units/sqrt(s)):             sigma(tau) = K * sqrt(tau / 3);
- quantisation Q (units * s):                     sigma(tau) = sqrt(3) * Q / tau.
Gyro: ARW [deg/sqrt(h)] = 60 * N [deg/s/sqrt(Hz)]. Accel: VRW [m/s/sqrt(h)] = 60 * N [m/s^2/sqrt(Hz)].
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Literal

import numpy as np

from fieldlog.drive import outputs

if TYPE_CHECKING:
    from fieldlog.drive.files import DriveSpec

G0 = 9.80665  # m/s^2 per g
FLICKER_ADEV_FACTOR = math.sqrt(2.0 * math.log(2.0) / math.pi)  # 0.6643...
_RAD2DEG = 180.0 / math.pi


def default_taus(n: int, fs_hz: float, per_decade: int = 10) -> np.ndarray:
    """Log-spaced cluster times tau = m / fs_hz, m from 1 to (n-1)//2, s."""
    m_max = max((n - 1) // 2, 1)
    m = np.unique(np.round(np.logspace(0.0, math.log10(m_max), int(per_decade * math.log10(m_max)) + 1)))
    return m / fs_hz


def allan_deviation(x: np.ndarray, fs_hz: float, taus: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Overlapping Allan deviation of rate samples.

    x: (n,) or (n,k) samples at fs_hz (e.g. omega_ib_b in rad/s or f_b in m/s^2).
    taus: cluster times, s; rounded to whole samples, duplicates and those above (n-1)//2 samples dropped.
    Returns (taus (m,), adev (m,) or (m,k)) in the units of x.
    """
    x = np.asarray(x, dtype=np.float64)
    n = x.shape[0]
    if n < 3:
        raise ValueError("allan_deviation: need at least 3 samples")
    if taus is None:
        taus = default_taus(n, fs_hz)
    m = np.unique(np.round(np.asarray(taus, dtype=np.float64) * fs_hz).astype(np.int64))
    m = m[(m >= 1) & (m <= (n - 1) // 2)]
    # Integrated signal, one contiguous row per channel (mean removed: it cancels in the second
    # difference and keeps precision).
    x2 = x.reshape(n, -1).T
    theta = np.zeros((x2.shape[0], n + 1))
    np.cumsum(x2 - x2.mean(axis=1, keepdims=True), axis=1, out=theta[:, 1:])
    buf = np.empty((x2.shape[0], n))
    avar = np.empty((m.size, x2.shape[0]))
    for i, mi in enumerate(m):
        d = buf[:, : n + 1 - 2 * mi]
        np.subtract(theta[:, 2 * mi :], theta[:, mi:-mi], out=d)
        d -= theta[:, mi:-mi]
        d += theta[:, : -2 * mi]
        avar[i] = np.einsum("ij,ij->i", d, d) / (2.0 * mi * mi * d.shape[1])
    return m / fs_hz, np.sqrt(avar).reshape((m.size,) + x.shape[1:])


def _nnls(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """min |A c - b| subject to c >= 0, for a handful of columns: drop the most negative and refit."""
    active = np.ones(A.shape[1], dtype=bool)
    coef = np.zeros(A.shape[1])
    while active.any():
        sol, *_ = np.linalg.lstsq(A[:, active], b, rcond=None)
        if np.all(sol >= 0.0):
            coef[active] = sol
            break
        idx = np.flatnonzero(active)
        active[idx[np.argmin(sol)]] = False
    return coef


def _fit_avar(taus: np.ndarray, avar: np.ndarray, iterations: int = 6) -> np.ndarray:
    """Fit avar = C0/tau^2 + C1/tau + C2 + C3*tau (C >= 0) for one axis; returns C (4,).

    Residuals are relative to the model (an Allan variance estimate scatters in proportion to its
    value) and weighted by 1/tau (its relative variance grows in proportion to tau for a fixed record
    length). Relative-to-model weights need the model: iterate, starting from the data itself.
    """
    basis = np.stack([taus**-2, taus**-1, np.ones_like(taus), taus], axis=1)
    w = 1.0 / np.sqrt(taus)
    scale = np.maximum(avar, np.finfo(float).tiny)
    for _ in range(iterations):
        coef = _nnls(basis * (w / scale)[:, None], avar * w / scale)
        scale = np.maximum(basis @ coef, np.finfo(float).tiny)
    return coef


def noise_parameters(
    taus: np.ndarray, adev: np.ndarray, sensor: Literal["gyro", "accel"] | None = None
) -> dict[str, np.ndarray]:
    """Noise parameters from an Allan deviation curve (per axis when adev is (m,k)).

    All four IEEE 952 terms (quantisation, white, flicker, rate random walk) are fitted together to
    the Allan variance, so each is read from the tau region it dominates; this matters when the
    flicker floor is high enough to hide the white-noise line above a fraction of a second.
    Generic keys, in the units of the data u (e.g. rad/s):
      white_density N [u/sqrt(Hz)] (= the white line read at tau = 1 s), bias_instability B [u]
      (flat-region floor / 0.664), rate_random_walk K [u/sqrt(s)] (NaN unless visible: the K line
      must rise above the other terms by a tenth of the longest tau), quantization Q [u*s],
      adev_min [u] and tau_min [s] (the raw minimum of the curve, for reference: with a short
      record its noise biases it low, which is why B comes from the fit).
    sensor="gyro" (data in rad/s) adds arw_deg_rthr, arw_dps_rthz, bias_instability_deg_hr,
      bias_instability_dps, rrw_deg_hr_rthr.
    sensor="accel" (data in m/s^2) adds vrw_mps_rthr, vrw_ug_rthz, bias_instability_ug, rrw_ug_rthr.
    """
    taus = np.asarray(taus, dtype=np.float64)
    adev = np.asarray(adev, dtype=np.float64)
    avar = adev.reshape(adev.shape[0], -1) ** 2
    coef = np.stack([_fit_avar(taus, avar[:, j]) for j in range(avar.shape[1])], axis=1)
    # RRW counts as visible only if it dominates the fit at a tenth of the longest tau (where the
    # curve still has ~20 clusters for default taus); otherwise the term is just soaking up scatter.
    tau_vis = taus.max() / 10.0
    visible = coef[3] * tau_vis > coef[0] / tau_vis**2 + coef[1] / tau_vis + coef[2]
    coef[3] = np.where(visible, coef[3], np.nan)
    shape = adev.shape[1:]
    i_min = np.argmin(adev, axis=0)
    out = {
        "quantization": (np.sqrt(coef[0] / 3.0)).reshape(shape),
        "white_density": np.sqrt(coef[1]).reshape(shape),
        "bias_instability": (np.sqrt(coef[2]) / FLICKER_ADEV_FACTOR).reshape(shape),
        "rate_random_walk": np.sqrt(3.0 * coef[3]).reshape(shape),
        "adev_min": np.min(adev, axis=0),
        "tau_min": taus[i_min],
    }
    n, b, k = out["white_density"], out["bias_instability"], out["rate_random_walk"]
    if sensor == "gyro":
        out["arw_dps_rthz"] = n * _RAD2DEG
        out["arw_deg_rthr"] = n * _RAD2DEG * 60.0  # deg/sqrt(s) -> deg/sqrt(h): sqrt(3600)
        out["bias_instability_dps"] = b * _RAD2DEG
        out["bias_instability_deg_hr"] = b * _RAD2DEG * 3600.0
        out["rrw_deg_hr_rthr"] = k * _RAD2DEG * 3600.0 * 60.0  # deg/s/sqrt(s) -> deg/h/sqrt(h)
    elif sensor == "accel":
        out["vrw_mps_rthr"] = n * 60.0  # m/s/sqrt(s) -> m/s/sqrt(h)
        out["vrw_ug_rthz"] = n / G0 * 1e6
        out["bias_instability_ug"] = b / G0 * 1e6
        out["rrw_ug_rthr"] = k / G0 * 1e6 * 60.0  # ug/sqrt(s) -> ug/sqrt(h)
    elif sensor is not None:
        raise ValueError(f"noise_parameters: sensor must be 'gyro', 'accel' or None, got {sensor!r}")
    return out


def report(omega_ib_b: np.ndarray, f_b: np.ndarray, fs_hz: float) -> str:
    """Plain-text table of the noise parameters per axis of a static record.

    omega_ib_b (n,3) rad/s and f_b (n,3) m/s^2 in the body frame, sampled at fs_hz.
    """
    taus, adev_g = allan_deviation(omega_ib_b, fs_hz)
    _, adev_a = allan_deviation(f_b, fs_hz, taus)
    g = noise_parameters(taus, adev_g, "gyro")
    a = noise_parameters(taus, adev_a, "accel")
    duration_s = omega_ib_b.shape[0] / fs_hz
    rows = [
        f"Allan analysis: {omega_ib_b.shape[0]} samples at {fs_hz:g} Hz ({duration_s / 3600.0:.2f} h)",
        f"{'gyro':6} {'ARW deg/sqrt(h)':>16} {'deg/s/sqrt(Hz)':>15} {'BI deg/h':>10} {'BI deg/s':>10}"
        f" {'RRW deg/h/sqrt(h)':>18}",
    ]
    for i, axis in enumerate("xyz"):
        rows.append(
            f"{axis:6} {g['arw_deg_rthr'][i]:16.4g} {g['arw_dps_rthz'][i]:15.4g}"
            f" {g['bias_instability_deg_hr'][i]:10.4g} {g['bias_instability_dps'][i]:10.4g}"
            f" {g['rrw_deg_hr_rthr'][i]:18.4g}"
        )
    rows.append(
        f"{'accel':6} {'VRW m/s/sqrt(h)':>16} {'ug/sqrt(Hz)':>15} {'BI ug':>10} {'':>10} {'RRW ug/sqrt(h)':>18}"
    )
    for i, axis in enumerate("xyz"):
        rows.append(
            f"{axis:6} {a['vrw_mps_rthr'][i]:16.4g} {a['vrw_ug_rthz'][i]:15.4g}"
            f" {a['bias_instability_ug'][i]:10.4g} {'':>10} {a['rrw_ug_rthr'][i]:18.4g}"
        )
    return "\n".join(rows) + "\n"


def plot(taus: np.ndarray, adev: np.ndarray, path: str, ylabel: str = "Allan deviation", title: str = "",
         force: bool = False) -> str:
    """Log-log PNG of an Allan deviation curve, one line per axis when adev is (m,3) (x, y, z).

    taus (m,) s; adev (m,) or (m,k) in the units named by ylabel. ``path`` must be new, unless ``force``
    (``drive.outputs``). Returns path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    a = np.asarray(adev, dtype=np.float64).reshape(len(taus), -1)
    fig, ax = plt.subplots(figsize=(7, 5), constrained_layout=True)
    for j in range(a.shape[1]):
        ax.loglog(taus, a[:, j], lw=1.6, label="xyz"[j] if a.shape[1] == 3 else f"channel {j}")
    ax.set_xlabel("cluster time tau (s)")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, which="major", alpha=0.5)
    ax.grid(True, which="minor", alpha=0.15)
    if a.shape[1] > 1:
        ax.legend(title="axis")
    with outputs.create(path, force) as f:
        fig.savefig(f, format="png", dpi=110)
    plt.close(fig)
    return path


def drive_report(path: DriveSpec, plot_prefix: str | None = None, force: bool = False) -> str:
    """``report`` of the /imu topic of a recorded drive (meant for a static drive; one file or several:
    ``drive.files``); rate from the stamps.

    With plot_prefix, also writes <plot_prefix>_gyro.png (deg/h) and <plot_prefix>_accel.png (ug) and
    names them at the end of the text (new files, unless ``force``)."""
    from fieldlog.drive.files import label
    from fieldlog.drive.reader import read_topic

    imu = read_topic(path, "/imu")
    name = label(path)
    stamp_ns = np.asarray(imu["stamp_ns"])
    if stamp_ns.size < 3:
        raise ValueError(f"{name}: /imu has {stamp_ns.size} samples, need at least 3")
    fs_hz = (stamp_ns.size - 1) / ((stamp_ns[-1] - stamp_ns[0]) * 1e-9)
    text = report(np.asarray(imu["omega_ib_b"]), np.asarray(imu["f_b"]), fs_hz)
    if plot_prefix is None:
        return text
    for kind in ("gyro", "accel"):
        outputs.check_new(f"{plot_prefix}_{kind}.png", force)
    taus, adev_g = allan_deviation(np.asarray(imu["omega_ib_b"]), fs_hz)
    _, adev_a = allan_deviation(np.asarray(imu["f_b"]), fs_hz, taus)
    files = [plot(taus, adev_g * _RAD2DEG * 3600.0, f"{plot_prefix}_gyro.png", "gyro Allan deviation (deg/h)",
                  f"gyro, {name}", force),
             plot(taus, adev_a / G0 * 1e6, f"{plot_prefix}_accel.png", "accel Allan deviation (ug)",
                  f"accelerometer, {name}", force)]
    return text + "".join(f"wrote {f}\n" for f in files)
