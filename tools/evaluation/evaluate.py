"""``fieldlog evaluate DRIVE... --outages 30,60 --methods ins,kf,dkf,rbfn,tdln,dkf-rbfn --report DIR [--seeds N]
[--smooth]``.

The outage study of the distributed-KF paper (its Table 3). For each outage length L, windows of L s are
placed in the drive's good GPS (every fix in the window usable), the first starting at ``first_s`` (120 s,
after the filter has converged), the next ``gap_s`` (max(60 s, L)) after the previous one ends, so the
filter reconverges in between; the same windows are forced for every method (``fieldlog fuse --outage``).

Errors during the outages, per quantity, are RMS over all the solution rows inside the windows of a drive:
longitude, latitude, altitude (east, north, up position error, m), vE, vN, vU (m/s), and roll, pitch,
heading (deg). The reference is ``/truth`` when the drive has it; otherwise the withheld GPS fixes (as the
paper does), the solution interpolated to their times, and no attitude. Over several drives the table gives
the mean and the spread (sample standard deviation) of the per-drive RMS.

Writes DIR/table.md (rows = quantities, columns = method x outage length, like the paper's Table 3; then the
heading error and the filter's heading sigma at each outage start), DIR/table.csv (long form: quantity, unit,
method, outage_s, mean, std, drives, windows), DIR/heading.csv (drive, method, outage_s, start_s,
heading_err_deg, heading_sigma_deg: NaN error without /truth), the fused
solutions in DIR/fused/ and, per outage length L, DIR/errors_<L>s.png: horizontal position error (m) and
velocity error magnitude (m/s) against time since the outage start, each window thin, the mean thick.

``--paper`` runs the paper's own set-up (:func:`paper_config`: GPS only, its distributed filter, networks
trained in real time; methods ``PAPER_METHODS``, 30 and 60 s outages, ``PAPER_SEEDS`` simulated drives of
``PAPER_SCENARIO`` when none is given: the figure-eight with laps that vary, so no predictor learns the track) and
adds to the report its Table 3 beside ours, a verdict on each of its absolute figures and on each of its claims by
a paired t test over the drives (:func:`paper_report`). Every report names its route (:func:`route_note`).

The scoring functions take the fused solution as a fused file or as its rows in memory (``fuse(..., keep=True)``,
read through ``replay.solutions.read``: the same arrays), so a study scores the runs it fuses without reading its
fused files back.

Methods: ``fusion.methods.METHODS``. ``rbfn``, ``tdln`` and ``dkf-rbfn`` (``fusion.predictors``) run the
distributed filter while GPS is good and differ from ``dkf`` only inside the outages. ``--predictor-modes paper,pseudo`` runs ``dkf-rbfn`` once per
``[fusion] predictor_mode``, the virtual odometer's column labelled ``dkf-rbfn (pseudo)`` (``fusion.pseudo``).

Below the table, what the run can say (:func:`verdict`): each predictor against the plain filters by the paired t
test over the drives, naming how many drives and windows it rests on; a difference the test does not resolve is
reported as "not resolved", never as a percentage. For the virtual odometer also its drift over the outages (the
error less its value at the outage's start, :func:`drift_2d`) against dkf's.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import polars as pl

from fieldlog.drive import outputs
from fieldlog.fusion import earth
from fieldlog.fusion.config import PREDICTOR_MODES, FusionConfig
from fieldlog.fusion.methods import DKF, DKF_RBFN, INS, KF, METHODS, RBFN, TDLN
from fieldlog.fusion.types import Solution
from fieldlog.drive import reader
from fieldlog.drive.drive import Drive
from fieldlog.replay import solutions
from fieldlog.replay.inputs import InputMap, InputSpec, by_stamp
from fieldlog.replay.inputs import resolve as resolve_inputs
from fieldlog.tools.fuse import NO_ALIGNMENT, fuse
from fieldlog.tools.fuse_settings import drive_config

QUANTITIES = (("longitude", "m"), ("latitude", "m"), ("altitude", "m"), ("vE", "m/s"), ("vN", "m/s"),
              ("vU", "m/s"), ("roll", "deg"), ("pitch", "deg"), ("heading", "deg"))


@dataclass
class StudyConfig:
    first_s: float = 120.0  # earliest outage start, s from the first IMU sample
    min_gap_s: float = 60.0  # good GPS between two outages at least max(min_gap_s, L)
    end_margin_s: float = 5.0  # an outage ends this long before the last fix at the latest
    settle_s: float = 30.0  # good GPS before each outage, so the filter has re-converged after a real one


def check_methods(methods: list[str]) -> None:
    """Raise ValueError naming unknown methods."""
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise ValueError(f"unknown method(s): {', '.join(unknown)} (available: {', '.join(METHODS)})")


def check_drive_names(drives: Sequence[str | Path]) -> None:
    """Raise ValueError naming the drive names (file or directory stems) given more than once: the fused files
    of a drive are named after it, so two drives of one name (in different directories) would share them."""
    stems = [Path(d).stem for d in drives]
    dup = sorted({s for s in stems if stems.count(s) > 1})
    if dup:
        raise ValueError(f"drive names must be unique (the fused files are named after them): {', '.join(dup)}")


def place_outages(t_fix_s: np.ndarray, good: np.ndarray, length_s: float, cfg: StudyConfig = StudyConfig()
                  ) -> list[tuple[float, float]]:
    """Outage windows (start_s, length_s) of one length in good GPS.

    t_fix_s (m,) fix times in s from the first IMU sample; good (m,) bool, usable fix. A window needs
    every fix inside [start - settle_s, start + L] good and at least 0.9 of them at 1 Hz (a forced outage right
    after a tunnel would score the tunnel's drift too); candidates step by 1 s."""
    if len(t_fix_s) == 0:
        return []
    out: list[tuple[float, float]] = []
    s = cfg.first_s
    t_end = t_fix_s[-1] - cfg.end_margin_s
    while s + length_s <= t_end:
        inside = (t_fix_s >= s - cfg.settle_s) & (t_fix_s <= s + length_s)
        if inside.sum() >= 0.9 * (length_s + cfg.settle_s) and good[inside].all():
            out.append((s, length_s))
            s += length_s + max(cfg.min_gap_s, length_s)
        else:
            s += 1.0
    return out


def fix_quality(drive: Path, max_sigma_m: float, imu_topic: str = "/imu", fix_topic: str = "/gps/fix"
                ) -> tuple[np.ndarray, np.ndarray, int]:
    """GPS fix times (s from the first IMU sample), usable flags, first IMU time ns."""
    t0 = min(t.first_ns for t in reader.topics(drive) if t.topic == imu_topic)
    g = reader.read_topic(drive, fix_topic)
    cov = g["position_covariance"].reshape(-1, 3, 3)
    sig = np.sqrt(np.maximum(cov[:, 0, 0], cov[:, 1, 1]))
    good = g["valid"] & (g["status"] >= 0) & np.isfinite(g["lat_deg"]) & np.isfinite(g["lon_deg"]) & \
        (sig <= max_sigma_m)
    return (g["log_time_ns"] - t0) * 1e-9, good, int(t0)


def _interp(t: np.ndarray, tr: np.ndarray, x: np.ndarray) -> np.ndarray:
    return np.stack([np.interp(t, tr, x[:, i]) for i in range(x.shape[1])], axis=1)


def _quat_interp(t: np.ndarray, tr: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Normalised linear interpolation of [x, y, z, w] quaternions (100 Hz truth: exact to ~1e-6 rad)."""
    j = np.searchsorted(tr, t).clip(1, len(tr) - 1)
    a = ((t - tr[j - 1]) / np.maximum(tr[j] - tr[j - 1], 1))[:, None]
    q0, q1 = q[j - 1], q[j]
    q1 = q1 * np.where(np.sum(q0 * q1, axis=1, keepdims=True) < 0.0, -1.0, 1.0)
    qi = (1.0 - a) * q0 + a * q1
    return qi / np.linalg.norm(qi, axis=1, keepdims=True)


def attitudes(drive: Path, fused: Path | Solution, method: str
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(t_ns, C_bn of the solution, C_bn of ``/truth/attitude``, the printed attitude sigma (n, 3) rad: phi E, N,
    U) at every solution row within the truth."""
    a = solutions.read(fused, method, "attitude")
    sd = solutions.read(fused, method, "attitude_std")
    ta = reader.read_topic(drive, "/truth/attitude")
    ts = a["log_time_ns"]
    ok = (ts >= ta["log_time_ns"][0]) & (ts <= ta["log_time_ns"][-1])
    return (ts[ok], earth.quat_to_dcm(a["q_xyzw"][ok]),
            earth.quat_to_dcm(_quat_interp(ts[ok], ta["log_time_ns"], ta["q_xyzw"])), sd["xyz"][ok])


def attitude_errors(drive: Path, fused: Path | Solution, method: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t_ns, attitude error phi E, N, U (n, 3) rad, its printed sigma (n, 3) rad) at every solution row within the
    truth: C_solution = (I - [phi x]) C_truth (``fusion.errmodel``), phi from the skew part of
    I - C_solution C_truth^T."""
    t, C_s, C_t, sd = attitudes(drive, fused, method)
    M = np.eye(3) - C_s @ np.swapaxes(C_t, 1, 2)
    return t, 0.5 * np.stack([M[:, 2, 1] - M[:, 1, 2], M[:, 0, 2] - M[:, 2, 0], M[:, 1, 0] - M[:, 0, 1]], axis=1), sd


def outage_errors(drive: Path, fused: Path | Solution, method: str, windows_ns: list[tuple[int, int]]) -> np.ndarray:
    """Errors (n, 9) in QUANTITIES order (m, m/s, deg) of the rows inside the windows: against /truth
    when the drive has it, else against the withheld GPS fixes (attitude NaN)."""
    return outage_error_series(drive, fused, method, windows_ns)[1]


def outage_error_series(drive: Path, fused: Path | Solution, method: str, windows_ns: list[tuple[int, int]],
                        fix_topic: str = "/gps/fix", vel_topic: str | None = "/gps/vel"
                        ) -> tuple[np.ndarray, np.ndarray]:
    """``outage_errors`` with the times of its rows: (t_ns (n,), errors (n, 9)). Without truth the reference is
    ``fix_topic`` and ``vel_topic`` (None: no velocity errors), timed by their header stamps."""
    s = solutions.read(fused, method, "fix")
    v = solutions.read(fused, method, "vel")
    a = solutions.read(fused, method, "attitude")
    ts = s["log_time_ns"]
    names = {t.topic for t in reader.topic_counts(drive) if t.count}
    truth = "/truth/fix" in names
    ref = reader.read_topic(drive, "/truth/fix") if truth else by_stamp(reader.read_topic(drive, fix_topic))
    tr = ref["log_time_ns"]
    if truth:
        t = ts
        inside = np.zeros(len(t), bool)
        for w0, w1 in windows_ns:
            inside |= (t >= w0) & (t < w1)
        inside &= (t >= tr[0]) & (t <= tr[-1])
        t = t[inside]
        llh = _interp(t, tr, np.stack([ref["lat_deg"], ref["lon_deg"], ref["alt_m"]], axis=1))
        sol = np.stack([s["lat_deg"][inside], s["lon_deg"][inside], s["alt_m"][inside]], axis=1)
        tv = reader.read_topic(drive, "/truth/vel")
        dv = v["v_n"][inside] - _interp(t, tv["log_time_ns"], tv["v_n"])
        ta = reader.read_topic(drive, "/truth/attitude")
        eul_s = earth.dcm_to_euler(earth.quat_to_dcm(a["q_xyzw"][inside]))
        eul_t = earth.dcm_to_euler(earth.quat_to_dcm(_quat_interp(t, ta["log_time_ns"], ta["q_xyzw"])))
        datt = np.stack([np.degrees((eul_s[i] - eul_t[i] + np.pi) % (2 * np.pi) - np.pi) for i in (2, 1, 0)],
                        axis=1)
    else:
        ok = ref["valid"] & (ref["status"] >= 0) & np.isfinite(ref["lat_deg"])
        t = tr[ok]
        inside = np.zeros(len(t), bool)
        for w0, w1 in windows_ns:
            inside |= (t >= w0) & (t < w1)
        inside &= (t >= ts[0]) & (t <= ts[-1])
        t = t[inside]
        llh = np.stack([ref["lat_deg"][ok][inside], ref["lon_deg"][ok][inside], ref["alt_m"][ok][inside]], axis=1)
        sol = _interp(t, ts, np.stack([s["lat_deg"], s["lon_deg"], s["alt_m"]], axis=1))
        vg = np.full((len(t), 3), np.nan)
        if vel_topic in names:
            gv = by_stamp(reader.read_topic(drive, vel_topic))
            j = np.searchsorted(gv["log_time_ns"], t).clip(0, max(len(gv["log_time_ns"]) - 1, 0))
            hit = gv["log_time_ns"][j] == t if len(gv["log_time_ns"]) else np.zeros(len(t), bool)
            vg[hit] = gv["v_n"][j[hit]]
        dv = _interp(t, ts, v["v_n"]) - vg
        datt = np.full((len(t), 3), np.nan)
    lat = np.radians(llh[:, 0])
    rm, rn = earth.principal_radii(lat, np.nan_to_num(llh[:, 2]))
    dpos = np.stack([np.radians(sol[:, 1] - llh[:, 1]) * rn * np.cos(lat), np.radians(sol[:, 0] - llh[:, 0]) * rm,
                     sol[:, 2] - llh[:, 2]], axis=1)
    return t, np.hstack([dpos, dv, datt])


def consistency(drive: Path, fused: Path | Solution, method: str) -> dict[str, float] | None:
    """How honest the printed sigma is, over every solution row of the drive against ``/truth/fix`` (None
    without truth): ``nees`` the mean normalised estimation error squared of the position (E, N, U with their
    sigmas; 3 when honest), and per axis e, n, u the shares of rows within 1 sigma (0.683 when honest) and
    3 sigma (0.997): keys ``in1_e``, ``in3_e``, ...; on a simulated drive the same shares of the IMU bias
    estimate's errors (``bias_errors``, every axis): ``in1_bg``, ``in3_bg`` (gyro), ``in1_ba``, ``in3_ba``
    (accelerometer)."""
    if not any(t.topic == "/truth/fix" and t.count for t in reader.topic_counts(drive)):
        return None
    e, sd = position_errors(drive, fused, method)
    z = e / np.maximum(sd, 1e-9)
    out = {"nees": float(np.mean(np.sum(z * z, axis=1))), "rows": len(z)}
    for i, ax in enumerate("enu"):
        out[f"in1_{ax}"] = float(np.mean(np.abs(z[:, i]) <= 1.0))
        out[f"in3_{ax}"] = float(np.mean(np.abs(z[:, i]) <= 3.0))
    for sensor, key in (("gyro", "bg"), ("accel", "ba")):
        bias = bias_errors(drive, fused, method, sensor)
        if bias is not None and len(bias[0]):
            out[f"in1_{key}"] = float(np.mean(np.abs(bias[1]) <= bias[2]))
            out[f"in3_{key}"] = float(np.mean(np.abs(bias[1]) <= 3.0 * bias[2]))
    return out


BIAS_FIELDS = {"gyro": ("omega_ib_b", "gyro_cov"), "accel": ("f_b", "accel_cov")}  # imu_bias message fields


def bias_errors(drive: Path, fused: Path | Solution, method: str, sensor: str = "gyro", mean_s: float = 10.0
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(t_ns (n,), error, sigma): the method's ``sensor`` ("gyro" rad/s, "accel" m/s^2) bias estimate minus the
    simulator's (``/truth/imu_bias``, its mean over the last ``mean_s``: the truth holds the fast part of the
    flicker too) and the estimate's printed sigma, body RFU, (n, 3) each, at the rows of
    ``/fusion/<method>/imu_bias`` from ``mean_s`` into the truth to its end. None when either topic is missing (a
    drive not simulated, a fused file written before the estimate was published)."""
    if not (any(t.topic == "/truth/imu_bias" and t.count for t in reader.topic_counts(drive))
            and solutions.has(fused, method, "imu_bias")):
        return None
    value, cov = BIAS_FIELDS[sensor]
    b, tr = solutions.read(fused, method, "imu_bias"), reader.read_topic(drive, "/truth/imu_bias")
    tt = tr["log_time_ns"]
    t = b["log_time_ns"]
    m = (t >= tt[0] + int(mean_s * 1e9)) & (t <= tt[-1])
    c = np.cumsum(np.vstack([np.zeros(3), tr[value]]), axis=0)
    j = np.searchsorted(tt, t[m], side="right")
    i = np.searchsorted(tt, t[m] - int(mean_s * 1e9), side="right")
    truth = (c[j] - c[i]) / np.maximum(j - i, 1)[:, None]
    return t[m], b[value][m] - truth, np.sqrt(np.maximum(b[cov][m][:, [0, 4, 8]], 0.0))


def position_errors(drive: Path, fused: Path | Solution, method: str) -> tuple[np.ndarray, np.ndarray]:
    """The method's position error (solution - ``/truth/fix``, ENU m) and its printed sigma (m), (n, 3) each, at
    every solution row within the truth."""
    s = solutions.read(fused, method, "fix")
    sd = solutions.read(fused, method, "std")
    ref = reader.read_topic(drive, "/truth/fix")
    t, tr = s["log_time_ns"], ref["log_time_ns"]
    m = (t >= tr[0]) & (t <= tr[-1])
    llh = _interp(t[m], tr, np.stack([ref["lat_deg"], ref["lon_deg"], ref["alt_m"]], axis=1))
    lat = np.radians(llh[:, 0])
    rm, rn = earth.principal_radii(lat, llh[:, 2])
    e = np.stack([np.radians(s["lon_deg"][m] - llh[:, 1]) * rn * np.cos(lat),
                  np.radians(s["lat_deg"][m] - llh[:, 0]) * rm, s["alt_m"][m] - llh[:, 2]], axis=1)
    return e, sd["xyz"][m]


def pooled(cs: list[dict[str, float]]) -> dict[str, float]:
    """``consistency`` results of several drives as one, weighted by their rows."""
    n = np.array([c["rows"] for c in cs], float)
    keys = [k for k in cs[0] if k != "rows" and all(k in c for c in cs)]
    out = {k: float(np.sum([c[k] for c in cs] * n) / max(n.sum(), 1)) for k in keys}
    out["rows"] = int(n.sum())
    return out


def consistency_line(method: str, c: dict[str, float]) -> str:
    """One line of ``consistency``: NEES and the per-axis shares within 1 and 3 sigma."""
    return (f"{method}: position NEES {c['nees']:.2f} (3 if honest); within 1 sigma E {c['in1_e']:.0%} "
            f"N {c['in1_n']:.0%} U {c['in1_u']:.0%} (68 %), within 3 sigma E {c['in3_e']:.0%} N {c['in3_n']:.0%} "
            f"U {c['in3_u']:.0%} (99.7 %), over {c['rows']} rows"
            + "".join(f"; {name} bias within 1 sigma {c[f'in1_{k}']:.0%}, 3 sigma {c[f'in3_{k}']:.0%}"
                      for k, name in (("bg", "gyro"), ("ba", "accel")) if f"in3_{k}" in c))


def heading_at_starts(drive: Path, fused: Path | Solution, method: str, windows_ns: list[tuple[int, int]]
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Heading error (solution - truth, deg, wrapped to +-180) and the filter's heading sigma (deg, from
    ``/fusion/<method>/attitude_std``: phi up) at the first solution row of each window, (w,) each; NaN where
    the drive has no ``/truth/attitude`` or the window no row."""
    err, sig = np.full(len(windows_ns), np.nan), np.full(len(windows_ns), np.nan)
    a = solutions.read(fused, method, "attitude")
    sd = solutions.read(fused, method, "attitude_std") if solutions.has(fused, method, "attitude_std") else None
    truth = "/truth/attitude" in {t.topic for t in reader.topic_counts(drive) if t.count}
    ta = reader.read_topic(drive, "/truth/attitude") if truth else None
    ts = a["log_time_ns"]
    for i, (w0, w1) in enumerate(windows_ns):
        j = int(np.searchsorted(ts, w0))
        if j >= len(ts) or ts[j] >= w1:
            continue
        if sd is not None:
            sig[i] = math.degrees(float(sd["xyz"][j, 2]))
        if ta is not None and ta["log_time_ns"][0] <= ts[j] <= ta["log_time_ns"][-1]:
            h_s = earth.dcm_to_euler(earth.quat_to_dcm(a["q_xyzw"][j:j + 1]))[0]
            h_t = earth.dcm_to_euler(earth.quat_to_dcm(_quat_interp(ts[j:j + 1], ta["log_time_ns"], ta["q_xyzw"])))[0]
            err[i] = math.degrees((float(h_s[0] - h_t[0]) + math.pi) % (2 * math.pi) - math.pi)
    return err, sig


def vel_cell(rms_enu: np.ndarray) -> str:
    """The 3D velocity RMS, m/s; ``not scored`` for a drive without a velocity reference."""
    v = float(np.linalg.norm(rms_enu))
    return f"{v:.3f} m/s" if math.isfinite(v) else "not scored (no velocity reference)"


def heading_cell(err_deg: float, sigma_deg: float, digits: int, unit: str = "") -> str:
    """``+e ± s`` with ``digits`` decimals; ``σ s (no truth)`` for a drive without ``/truth/attitude``."""
    if math.isnan(err_deg):
        return f"σ {sigma_deg:.{digits}f}{unit} (no truth)"
    return f"{err_deg:+.{digits}f} ± {sigma_deg:.{digits}f}{unit}"


PLOT_DT_S = 0.5  # time step of the error curves, s


def window_curves(t_ns: np.ndarray, err: np.ndarray, windows_ns: list[tuple[int, int]], length_s: float
                  ) -> np.ndarray:
    """Per window, horizontal position error (m) and velocity error magnitude (m/s) on the grid
    0, PLOT_DT_S, ... < length_s s since the outage start: (windows, 2, grid); NaN where the window has no rows."""
    grid = np.arange(0.0, length_s, PLOT_DT_S)
    out = np.full((len(windows_ns), 2, len(grid)), np.nan)
    h = np.hypot(err[:, 0], err[:, 1])
    v = np.linalg.norm(err[:, 3:6], axis=1)
    for i, (w0, w1) in enumerate(windows_ns):
        m = (t_ns >= w0) & (t_ns < w1) & np.isfinite(h) & np.isfinite(v)
        if m.sum() < 2:
            continue
        ts = (t_ns[m] - w0) * 1e-9
        span = (grid >= ts[0]) & (grid <= ts[-1])
        out[i, 0, span] = np.interp(grid[span], ts, h[m])
        out[i, 1, span] = np.interp(grid[span], ts, v[m])
    return out


def drift_2d(t_ns: np.ndarray, err: np.ndarray, windows_ns: list[tuple[int, int]]) -> float:
    """The drift over the outages: per window, the horizontal position error less its value at the window's first
    row; RMS over every row of the windows, m (NaN without rows)."""
    d2 = []
    for w0, w1 in windows_ns:
        m = (t_ns >= w0) & (t_ns < w1) & np.isfinite(err[:, :2]).all(axis=1)
        if m.any():
            e = err[m, :2]
            d2.append(((e - e[0]) ** 2).sum(axis=1))
    return float(np.sqrt(np.mean(np.concatenate(d2)))) if d2 else math.nan


def run_label(method: str, mode: str) -> str:
    """A study column's method label: the method, and for dkf-rbfn a predictor mode other than the paper's."""
    return f"{method} ({mode})" if method == DKF_RBFN.name and mode != PREDICTOR_MODES[0] else method


def plot_errors(curves: dict[str, np.ndarray], length_s: float, path: Path, drives: int, force: bool = False
                ) -> Path:
    """PNG of the outage error curves of one outage length: curves[method] = (windows, 2, grid) from
    ``window_curves``; each window thin, the mean over windows thick. A method has its own colour and line
    style, the first methods the widest lines (so equal curves, such as kf and dkf, both show), its ``+rts``
    variant the lighter shade of that colour; log error axes. ``path``: a new file unless ``force``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 1, figsize=(9, 7.5), sharex=True, constrained_layout=True)
    base = list(dict.fromkeys(m.removesuffix("+rts") for m in curves))
    tab20 = plt.get_cmap("tab20")
    styles = ("-", "--", "-.", ":")
    n_win = 0
    for name, c in curves.items():
        grid = np.arange(c.shape[2]) * PLOT_DT_S
        i = base.index(name.removesuffix("+rts"))
        colour, style = tab20((2 * i + name.endswith("+rts")) % 20), styles[i % len(styles)]
        n_win = max(n_win, c.shape[0])
        for k, ax in enumerate(axes):
            for w in c[:, k]:
                ax.plot(grid, w, color=colour, lw=0.6, alpha=0.3)
            with warnings.catch_warnings():  # all-NaN columns (no window reaches that far): mean NaN
                warnings.simplefilter("ignore", RuntimeWarning)
                mean = np.nanmean(c[:, k], axis=0)
            ax.plot(grid, mean, color=colour, ls=style, lw=3.4 - 1.8 * i / max(len(base) - 1, 1), label=name)
    for ax, label in zip(axes, ("horizontal position error (m)", "velocity error magnitude (m/s)")):
        if any(np.nanmax(np.where(ln.get_ydata() > 0, ln.get_ydata(), np.nan), initial=-1.0) > 0
               for ln in ax.get_lines()):  # a drive without GPS velocity has no velocity errors
            ax.set_yscale("log")
        ax.set_ylabel(label)
        ax.grid(True, which="major", alpha=0.4)
        ax.grid(True, which="minor", alpha=0.12)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=min(len(curves), 6), fontsize=9,
               title="method: mean over the windows thick, each window thin")
    axes[1].set_xlabel("time since outage start (s)")
    axes[1].set_xlim(0.0, length_s)
    fig.suptitle(f"Errors during {length_s:g} s GPS outages: {n_win} windows over {drives} drive(s)")
    with outputs.create(path, force) as f:
        fig.savefig(f, format="png", dpi=110)
    plt.close(fig)
    return path


def rms_columns(e: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        n = np.isfinite(e).sum(axis=0)
        return np.where(n > 0, np.sqrt(np.nansum(e ** 2, axis=0) / np.maximum(n, 1)), np.nan)


def evaluate(drives: list[Path], lengths: list[float], methods: list[str], report: Path, smooth: bool = False,
             config: FusionConfig | None = None, study: StudyConfig = StudyConfig(),
             say: Callable[[str], None] = print, spec: InputSpec | None = None, paper: bool = False,
             progress: Callable[[float], None] | None = None, force: bool = False,
             note: Callable[[str], None] | None = None, predictor_modes: Sequence[str] = ("paper",)
             ) -> pl.DataFrame:
    """Run the study; writes DIR/table.md, DIR/table.csv, DIR/fused/*.mcap, DIR/errors_<L>s.png.
    Returns the long table.

    smooth adds a ``<method>+rts`` column per method (RTS-smoothed, ``fusion.smoother``); a drive with wheel
    speeds (``replay.inputs``: /vehicle/twist or the spec's odometry topic) fused with the odometer also gets a
    ``<method>-no-odometer`` column per method, the same run with ``[fusion] odometer = false``. config None: each
    drive's own ``fusion.config`` record (``tools.fuse_settings.drive_config``). spec: the input mapping of drives from
    another logger (``replay.inputs``). paper: the distributed-KF paper's set-up (:func:`paper_config` on each
    drive's config) and, in the report, its Table 3 beside ours and a verdict on each of its absolute figures and
    each of its claims (:func:`paper_report`). Drive names (stems) must be unique (:func:`check_drive_names`),
    checked before anything is written. progress: called with the fraction of the runs done. Every file is new
    (``drive.outputs``) unless ``force``; DIR and DIR/fused are never symbolic links. note: the lines about
    runs that could not be scored (default: ``say``). predictor_modes: ``[fusion] predictor_mode`` values
    ``dkf-rbfn`` runs with, each its own column (``run_label``: ``dkf-rbfn (pseudo)``)."""
    check_methods(methods)
    if not drives:
        raise ValueError("no drive to evaluate")
    check_drive_names(drives)
    opened = [Drive.open(d, imu_axes_given=spec is not None and spec.imu_frame is not None) for d in drives]
    report = Path(report)
    outputs.out_dir(report, "fused")
    runs = [(m, sm, True, mode) for m in methods for sm in ((False, True) if smooth and m != INS.name else (False,))
            for mode in (predictor_modes if m == DKF_RBFN.name else ("paper",))]
    plans = []
    for path, drive in zip(map(Path, drives), opened):
        base = config or drive_config(drive)
        base = paper_config(base) if paper else base
        imap = resolve_inputs(drive, spec)
        plans.append((path, drive, base, imap, runs + ([(m, sm, False, mode) for m, sm, _, mode in runs if m != INS.name]
                                                      if imap.odom_topic and base.aids.odometer else [])))
    for name in ("table.csv", "heading.csv", "table.md", *(f"errors_{L:g}s.png" for L in lengths)):
        outputs.check_new(report / name, force)  # every output refused before the first run
    for path, _, _, _, drive_runs in plans:
        for L in lengths:
            for run in drive_runs:
                outputs.check_new(_fused_path(report, path, run, L), force)
    acc = _Study(total=len(lengths) * sum(len(p[-1]) for p in plans), progress=progress or (lambda fraction: None),
                 say=say, note=note or say)
    for plan in plans:
        _study_drive(acc, *plan, lengths, study, report, force)
    table = acc.table()
    with outputs.create(report / "table.csv", force, root=report) as f:
        table.write_csv(f)
    heading = acc.heading_table()
    with outputs.create(report / "heading.csv", force, root=report) as f:
        heading.write_csv(f)
    _write_report(acc, table, heading, [Path(d) for d in drives], base, paper, report, force)
    return table


@dataclass
class _Study:
    """The study's scores as the runs come (``evaluate``): per (column, outage length) each drive's RMS errors,
    windows, 2D drifts, error curves and sigma consistency; the heading at each outage start; runs done of
    ``total`` (``progress`` told the fraction)."""

    total: int
    progress: Callable[[float], None]
    say: Callable[[str], None]
    note: Callable[[str], None]
    done: int = 0
    per: dict = field(default_factory=dict)  # (name, L) -> [rms errors (9,)]
    windows: dict = field(default_factory=dict)  # (name, L) -> windows scored
    drifts: dict = field(default_factory=dict)  # (name, L) -> [2D drift]
    curves: dict = field(default_factory=dict)  # L -> name -> [error curves]
    honesty: dict = field(default_factory=dict)  # (name, L) -> [consistency]
    headings: list = field(default_factory=list)

    def step(self, n: int = 1) -> None:
        self.done += n
        self.progress(self.done / self.total)

    def table(self) -> pl.DataFrame:
        """The long table: each quantity's mean and std over the drives per column and outage length."""
        rows = []
        for (name, L), vals in self.per.items():
            arr = np.array(vals)
            std = arr.std(axis=0, ddof=1) if len(arr) > 1 else np.full(arr.shape[1], np.nan)
            for i, (q, unit) in enumerate(QUANTITIES):
                rows.append(dict(quantity=q, unit=unit, method=name, outage_s=float(L),
                                 mean=float(np.nanmean(arr[:, i])) if np.isfinite(arr[:, i]).any() else None,
                                 std=float(std[i]) if np.isfinite(std[i]) else None, drives=len(arr),
                                 windows=self.windows[(name, L)]))
        return pl.DataFrame(rows, schema={"quantity": pl.Utf8, "unit": pl.Utf8, "method": pl.Utf8,
                                          "outage_s": pl.Float64, "mean": pl.Float64, "std": pl.Float64,
                                          "drives": pl.Int64, "windows": pl.Int64})

    def heading_table(self) -> pl.DataFrame:
        """The heading error and sigma at each outage start."""
        return pl.DataFrame(self.headings, schema={"drive": pl.Utf8, "method": pl.Utf8, "outage_s": pl.Float64,
                                                   "start_s": pl.Float64, "heading_err_deg": pl.Float64,
                                                   "heading_sigma_deg": pl.Float64})


def _run_name(run: tuple[str, bool, bool, str]) -> str:
    """A run's column: method (predictor mode), ``+rts`` when smoothed, ``-no-odometer`` without the odometer."""
    m, sm, odo, mode = run
    return run_label(m, mode) + ("+rts" if sm else "") + ("" if odo else "-no-odometer")


def _fused_path(report: Path, path: Path, run: tuple[str, bool, bool, str], L: float) -> Path:
    """Where a run of the drive ``path`` at outage length L (s) writes its solution."""
    file_name = _run_name(run).replace(" (", "-").replace(")", "")
    return report / "fused" / f"{path.stem}_{file_name}_{L:g}s.mcap"


def _study_drive(acc: _Study, path: Path, drive: Drive, base: FusionConfig, imap: InputMap,
                 drive_runs: list[tuple[str, bool, bool, str]], lengths: list[float], study: StudyConfig,
                 report: Path, force: bool) -> None:
    """Every run of one drive (opened from ``path``, its inputs ``imap``) at every outage length, scored into
    ``acc``."""
    t_fix, good, t0 = fix_quality(drive, base.gps.max_fix_sigma_m, imap.imu_topic, imap.fix_topic)
    for L in lengths:
        win = place_outages(t_fix, good, L, study)
        if not win:
            acc.note(f"{path.name}: no room for a {L:g} s outage in good GPS after {study.first_s:g} s; skipped")
            acc.step(len(drive_runs))
            continue
        win_ns = [(t0 + int(round(s * 1e9)), t0 + int(round((s + n) * 1e9))) for s, n in win]
        cfg = base.replace(outages=tuple(win))
        for run in drive_runs:
            m, sm, odo, mode = run
            name = _run_name(run)
            run_cfg = (cfg if odo else cfg.replace(odometer=False)).replace(predictor_mode=mode)
            res = fuse(drive, m, _fused_path(report, path, run, L), run_cfg, smooth=sm, inputs=imap, force=force,
                       keep=True)
            if res.rows == 0:
                acc.step()
                acc.note(f"[{acc.done}/{acc.total}] {path.name} {name:8s} {L:g} s: not scored, {NO_ALIGNMENT}")
                continue
            _score(acc, path, drive, m, name, L, win, win_ns, imap, res.solution)


def _score(acc: _Study, path: Path, drive: Drive, method: str, name: str, L: float, win: list[tuple[float, float]],
           win_ns: list[tuple[int, int]], imap: InputMap, sol: Solution) -> None:
    """One run's errors over its outage windows, its sigma consistency and headings, into ``acc``."""
    t_err, err = outage_error_series(drive, sol, method, win_ns, imap.fix_topic, imap.vel_topic)
    rms = rms_columns(err)
    c = consistency(drive, sol, method)
    if c is not None:
        acc.honesty.setdefault((name, L), []).append(c)
    h_err, h_sig = heading_at_starts(drive, sol, method, win_ns)
    acc.headings += [dict(drive=path.name, method=name, outage_s=float(L), start_s=s0, heading_err_deg=e,
                          heading_sigma_deg=sg) for (s0, _), e, sg in zip(win, h_err, h_sig)]
    acc.curves.setdefault(L, {}).setdefault(name, []).append(window_curves(t_err, err, win_ns, L))
    acc.per.setdefault((name, L), []).append(rms)
    acc.drifts.setdefault((name, L), []).append(drift_2d(t_err, err, win_ns))
    acc.windows[(name, L)] = acc.windows.get((name, L), 0) + len(win)
    acc.step()
    acc.say(f"[{acc.done}/{acc.total}] {path.name} {name:8s} {L:g} s x {len(win)}: "
            f"2D {math.hypot(rms[0], rms[1]):.2f} m, 3D vel {vel_cell(rms[3:6])}; heading "
            "at the starts " + ", ".join(heading_cell(e, sg, 2, "°") for e, sg in zip(h_err, h_sig)))


def _write_report(acc: _Study, table: pl.DataFrame, heading: pl.DataFrame, drives: list[Path], base: FusionConfig,
                  paper: bool, report: Path, force: bool) -> None:
    """The figures and table.md: the table, the route, the aids, the verdicts (or the paper's) and the sigma's
    honesty."""
    say = acc.say
    figures = [plot_errors({m: np.concatenate(c) for m, c in by.items()}, L, report / f"errors_{L:g}s.png",
                           max(map(len, by.values())), force) for L, by in acc.curves.items()]
    for f in figures:
        say(f"wrote {f}")
    route = route_note(drives)
    say(route)
    conclusions = paper_report(acc.per, route) if paper else verdict(acc.per, acc.windows, acc.drifts)
    for line in (conclusions if paper else [x for x in conclusions if x.startswith("- ")]):
        say(line)
    sigma_lines = [f"- {L:g} s outages, " + consistency_line(name, pooled(cs)) for (name, L), cs in acc.honesty.items()]
    for line in sigma_lines:
        say(line[2:])
    if sigma_lines:
        conclusions = [*conclusions, "## Is the printed sigma honest?", "",
                       "Position error over every solution row (outages included) against the truth, in units of "
                       "the sigma the method printed:", "", *sigma_lines, ""]
    text = markdown(table, [p.name for p in drives], [f.name for f in figures],
                    route + "\n\n" + aids_note(base), conclusions) + heading_markdown(heading)
    outputs.write_bytes(report / "table.md", text.encode(), force, root=report)


def heading_markdown(heading: pl.DataFrame) -> str:
    """The heading error and sigma at each outage start, per method and length (a slow convergence shows)."""
    if heading.height == 0:
        return ""
    lines = ["", "## Heading error ± the filter's σ at each outage start (deg)", "",
             "| method | outage | " + "drive @ start: error ± σ |", "|---|---|---|"]
    for (m, L), g in heading.group_by(["method", "outage_s"], maintain_order=True):
        cells = ", ".join(f"{r['drive']} @ {r['start_s']:g} s: {heading_cell(r['heading_err_deg'], r['heading_sigma_deg'], 3)}"
                          for r in g.iter_rows(named=True))
        lines.append(f"| {m} | {L:g} s | {cells} |")
    return "\n".join(lines) + "\n"


def route_note(drives: Sequence[Path]) -> str:
    """One line naming the drives' route: the simulator's scenario of each (``drive`` metadata) and whether its
    laps vary (``[motion] lap_*_jitter``); drives not simulated are counted as recorded."""
    from fieldlog.tools.sim.trajectory import load_scenario

    names: dict[str, int] = {}
    for d in drives:
        meta = reader.read_metadata(d).get("drive", {})
        key = meta.get("scenario", "") if meta.get("source") == "fieldlog sim" else ""
        names[key] = names.get(key, 0) + 1
    parts = []
    for name, n in names.items():
        if not name:
            parts.append(f"{n} recorded drive(s)")
            continue
        try:
            sc = load_scenario(name)
            how = "laps that vary lap to lap (seeded)" if sc.motion.jittered() else \
                "laps that repeat exactly" if sc.motion.lap else "no laps"
        except (OSError, ValueError):
            how = "scenario not found here"
        parts.append(f"{n} x simulated `{name}` ({how})")
    return "Route: " + "; ".join(parts) + "."


def aids_note(cfg: FusionConfig) -> str:
    """One line on the vehicle-motion aids the filters used (they need no GPS, so they act in the outages)."""
    on = [n for n, flag in (("non-holonomic constraint (NHC)", cfg.aids.nhc), ("ZUPT + zero-rate update when stopped",
                                                                          cfg.aids.zupt)) if flag]
    if not on:
        return "Vehicle constraints: none (GPS-only filters, as in the paper)."
    return (f"Vehicle constraints: {' and '.join(on)} at every GPS epoch time, in the outages too, for every method "
            "but ins (the free INS); the paper used none. Methods are compared under the same aids.")


PAPER_HYBRID_60S_2D_M = 9.3  # the distributed-KF paper's conclusion: its hybrid's 2D RMS in 60 s outages
MIN_PAIRED_DRIVES = 3  # fewer drives than this: a paired difference is "not resolved" whatever its size
CONFIDENCE = 0.95  # two-sided, of the paired t interval


@dataclass(frozen=True)
class Paired:
    """A paired comparison over drives: per-drive differences' mean, the half width of its two-sided
    ``CONFIDENCE`` t interval (t quantile at n - 1 degrees of freedom times the standard error), n."""

    mean: float
    half: float
    n: int

    @property
    def resolved(self) -> bool:
        return self.n >= MIN_PAIRED_DRIVES and abs(self.mean) > self.half

    def cell(self, unit: str = "m") -> str:
        return (f"{self.mean:+.2f} ± {self.half:.2f} {unit} ({CONFIDENCE:.0%} paired t, {self.n - 1} dof)"
                if self.n >= 2 else f"{self.mean:+.2f} {unit} (one drive)")


def paired(diff: np.ndarray) -> Paired:
    """The paired t interval of per-drive differences diff (n,)."""
    from scipy.stats import t as student_t

    diff = np.asarray(diff, float)
    n = len(diff)
    if n < 2:
        return Paired(float(diff.mean()) if n else math.nan, math.inf, n)
    half = float(student_t.ppf(0.5 + CONFIDENCE / 2, n - 1) * diff.std(ddof=1) / math.sqrt(n))
    return Paired(float(diff.mean()), half, n)


def _d2(per: dict[tuple[str, float], list[np.ndarray]], L: float, cols: tuple[int, int] = (0, 1)
        ) -> dict[str, np.ndarray]:
    """Per method, the per-drive horizontal RMS hypot(col0, col1) at outage length L."""
    return {m: np.hypot(np.array(v)[:, cols[0]], np.array(v)[:, cols[1]]) for (m, L2), v in per.items() if L2 == L}


def compare(name: str, ours: np.ndarray, other_name: str, other: np.ndarray, unit: str = "m") -> str:
    """One paired comparison of per-drive values (n,) each: how much better or worse ``name`` is than
    ``other_name`` when the paired t test (``paired``) resolves it, else "not resolved against" it; the other's
    mean and the interval either way. A difference the drives cannot resolve is never stated as one."""
    pt = paired(other - ours)  # per drive, > 0: ours is better
    if pt.resolved:
        word = "better" if pt.mean > 0 else "worse"
        return (f"{abs(pt.mean) / other.mean() * 100:.0f} % {word} than {other_name} ({other.mean():.2f} {unit}, "
                f"resolved: {pt.cell(unit)})")
    why = pt.cell(unit) if pt.n >= MIN_PAIRED_DRIVES else f"{pt.n} drive{'s' if pt.n != 1 else ''}: a paired test needs {MIN_PAIRED_DRIVES}"
    return f"not resolved against {other_name} ({other.mean():.2f} {unit}; {why})"


PSEUDO = run_label(DKF_RBFN.name, PREDICTOR_MODES[1])


def verdict(per: dict[tuple[str, float], list[np.ndarray]], windows: dict[tuple[str, float], int] | None = None,
            drifts: dict[tuple[str, float], list[float]] | None = None) -> list[str]:
    """What the run can say of the predictors, per outage length, by 2D position RMS (mean over drives) and the
    paired t test over the drives (``compare``), each line naming its drives and windows: the paper's hybrid
    (dkf-rbfn) against RBFN-only, TDLN and the plain filters, with the paper's 60 s target; the virtual odometer
    (``dkf-rbfn (pseudo)``) against dkf, the paper's hybrid and kf, and by its drift over the outages
    (``drift_2d``) against dkf's. Lines of markdown; none when neither was run."""
    windows, drifts = windows or {}, drifts or {}

    def lines_for(cand: str, others: tuple[str, ...], L: float, d: dict[str, np.ndarray], what: str) -> str | None:
        if cand not in d:
            return None
        h = d[cand]
        parts = [compare(cand, h, o, d[o]) for o in others if o in d and len(d[o]) == len(h)]
        w = windows.get((cand, L), 0)
        count = f"{len(h)} drive{'s' if len(h) != 1 else ''}, {w} window{'s' if w != 1 else ''}"
        return f"- {L:g} s ({count}): {cand} {what} {h.mean():.2f} m; " + "; ".join(parts) + "."

    hybrid, pseudo = [], []
    for L in sorted({L for _, L in per}):
        d2 = _d2(per, L)
        line = lines_for(DKF_RBFN.name, (RBFN.name, TDLN.name, DKF.name, KF.name), L, d2, "2D RMS")
        if line is not None:
            if L == 60.0:
                line += (f" The paper's figure is {PAPER_HYBRID_60S_2D_M} m: "
                         + ("met." if d2[DKF_RBFN.name].mean() <= PAPER_HYBRID_60S_2D_M else "not met."))
            hybrid.append(line)
        line = lines_for(PSEUDO, (DKF.name, DKF_RBFN.name, KF.name), L, d2, "2D RMS")
        if line is not None:
            pseudo.append(line)
            dd = {m: np.array(v) for (m, L2), v in drifts.items() if L2 == L}
            line = lines_for(PSEUDO, (DKF.name,), L, dd, "drift (error less its value at the outage start)")
            if line is not None and DKF.name in dd:
                pseudo.append(line + f" Ratio of the means to dkf's: {dd[PSEUDO].mean() / dd[DKF.name].mean():.2f}.")
    out = ["## Does the hybrid beat RBFN-only and TDLN, as the paper claims?", "", *hybrid, ""] if hybrid else []
    if pseudo:
        out += ["## Does the virtual odometer (`predictor_mode = \"pseudo\"`) beat dkf?", "", *pseudo, ""]
    return out


PAPER_METHODS = (KF.name, DKF.name, RBFN.name, TDLN.name, DKF_RBFN.name)
PAPER_LENGTHS = (30.0, 60.0)
PAPER_SEEDS = 8
PAPER_SCENARIO = "figure8-varied"  # the paper's figure-eight with laps that vary (no predictor learns the track)
# the paper's Table 3: RMS longitude, latitude, altitude (m), east, north, up velocity (m/s) in its outages
PAPER_TABLE3 = {
    (TDLN.name, 30.0): (48.8457, 4.8964, 2.837e3, 0.5132, 0.2328, 133.4138),
    (TDLN.name, 60.0): (368.5379, 2.7340, 2.2941e4, 2.7722, 0.1926, 248.3301),
    (RBFN.name, 30.0): (6.7454, 4.7034, 6.8774e3, 0.1886, 0.1615, 30.4365),
    (RBFN.name, 60.0): (12.0465, 3.3548, 3.2891e4, 1.5799, 0.2314, 158.1367),
    (DKF_RBFN.name, 30.0): (2.9495, 4.9846, 0.3719, 0.1162, 0.5534, 0.0190),
    (DKF_RBFN.name, 60.0): (8.8609, 3.0110, 2.5718, 0.2351, 0.4023, 0.0500),
}
# the paper's claims: (better, worse, words); "dkf >= kf" is section 2.1's information loss of distributed fusion
PAPER_CLAIMS = ((DKF_RBFN.name, RBFN.name, "hybrid < RBFN"), (DKF_RBFN.name, TDLN.name, "hybrid < TDLN"),
                (DKF_RBFN.name, DKF.name, "hybrid < dkf"), (KF.name, DKF.name, "dkf >= centralised kf"))


def paper_config(cfg: FusionConfig) -> FusionConfig:
    """The paper's set-up on a drive's config: GPS only (no vehicle aids), its distributed filter (eqs. 3-4), the
    networks trained in real time."""
    return cfg.replace(nhc=False, zupt=False, dkf_fusion="paper",
                   predictor=replace(cfg.predictor, training="online"))


def claim_word(pt: Paired, equality_claim: bool = False) -> str:
    """The verdict on a claim "difference > 0" from its paired interval: confirmed, contradicted, not resolved
    (too few drives, or the interval spans 0); an equality claim spanning 0 is consistent."""
    if pt.n < MIN_PAIRED_DRIVES:
        return f"not resolved ({pt.n} drive{'s' if pt.n != 1 else ''}: a paired test needs {MIN_PAIRED_DRIVES})"
    if pt.resolved:
        return "confirmed" if pt.mean > 0 else "contradicted"
    return "consistent (the interval spans 0)" if equality_claim else "not resolved (the interval spans 0)"


def absolute_word(ours: np.ndarray, paper: float) -> tuple[str, str]:
    """(verdict, interval text) on a paper's absolute figure against our per-drive values (n,): its t interval
    of the mean over drives holds the figure (reproduced), lies above it (not reproduced: ours larger), or
    below it (ours smaller); not resolved with fewer than MIN_PAIRED_DRIVES drives."""
    pt = paired(ours - paper)
    text = f"{ours.mean():.2f} ± {pt.half:.2f}"
    if pt.n < MIN_PAIRED_DRIVES:
        return f"not resolved ({pt.n} drives)", text
    if not pt.resolved:
        return "reproduced (within the interval)", text
    return ("not reproduced: ours larger" if pt.mean > 0 else "not reproduced: ours smaller"), text


def paper_report(per: dict[tuple[str, float], list[np.ndarray]], route: str = "") -> list[str]:
    """Markdown lines: the paper's Table 3 beside ours (mean over drives); a verdict on each of its absolute 2D
    figures (position hypot(longitude, latitude), velocity hypot(east, north): its conclusion's "about 9.3 m
    and 0.45 m/s" is the hybrid's 60 s column) by the t interval of our mean over drives; then a verdict on
    each relative claim by the paired t test of the per-drive 2D position RMS (``paired``, ``claim_word``).
    route: one line naming the drives' route."""
    lines = ["## The paper's Table 3 beside ours (GPS only, paper's dkf, online networks)", "",
             *((route, "") if route else ()),
             "| quantity | unit | " + " | ".join(f"{m} {L:g} s ours | paper" for m in (TDLN.name, RBFN.name, DKF_RBFN.name)
                                                for L in PAPER_LENGTHS) + " |",
             "|---|---|" + "---|---|" * 3 * len(PAPER_LENGTHS)]
    for i, (q, unit) in enumerate(QUANTITIES[:6]):
        cells = []
        for m in (TDLN.name, RBFN.name, DKF_RBFN.name):
            for L in PAPER_LENGTHS:
                ours = np.nanmean(np.array(per[(m, L)])[:, i]) if (m, L) in per else math.nan
                cells.append(f"{ours:.3f} | {PAPER_TABLE3[(m, L)][i]:.4g}")
        lines.append(f"| {q} | {unit} | " + " | ".join(cells) + " |")
    lines += ["", f"## Verdicts on the paper's absolute figures (2D RMS; ours: mean over drives ± {CONFIDENCE:.0%} "
              "t interval)", "", "| method | outage | quantity | paper | ours | verdict |", "|---|---|---|---|---|---|"]
    for m in (TDLN.name, RBFN.name, DKF_RBFN.name):
        for L in PAPER_LENGTHS:
            if (m, L) not in per:
                continue
            t3 = PAPER_TABLE3[(m, L)]
            for q, unit, cols in (("2D position", "m", (0, 1)), ("2D velocity", "m/s", (3, 4))):
                ours = _d2(per, L, cols)[m]
                if not np.isfinite(ours).all():
                    continue
                word, text = absolute_word(ours, math.hypot(t3[cols[0]], t3[cols[1]]))
                lines.append(f"| {m} | {L:g} s | {q} | {math.hypot(t3[cols[0]], t3[cols[1]]):.3g} {unit} | "
                             f"{text} {unit} | **{word}** |")
    lines += ["", f"## Verdicts on the paper's claims (2D position RMS per drive; paired t test, {CONFIDENCE:.0%})",
              ""]
    for L in sorted({L for _, L in per}):
        d2 = _d2(per, L)
        for better, worse, words in PAPER_CLAIMS:
            if better not in d2 or worse not in d2 or len(d2[better]) != len(d2[worse]):
                continue
            pt = paired(d2[worse] - d2[better])  # > 0: the claim's direction
            lines.append(f"- {L:g} s, {words}: {better} {d2[better].mean():.2f} m, {worse} {d2[worse].mean():.2f} m; "
                         f"{worse} - {better} = {pt.cell()} over {pt.n} drives: "
                         f"**{claim_word(pt, equality_claim=better == KF.name)}**.")
    if len({len(v) for v in per.values()}) == 1 and len(next(iter(per.values()), [])) < PAPER_SEEDS:
        lines.append(f"- Fewer than {PAPER_SEEDS} drives: the paper's set-up asks for at least {PAPER_SEEDS}.")
    return lines + [""]


def paper_verdicts(lines: Sequence[str]) -> list[str]:
    """The bold verdict words of ``paper_report``'s lines, in order (what two runs on different drives must
    share)."""
    return [ln.split("**")[1] for ln in lines if ln.count("**") >= 2]


def markdown(table: pl.DataFrame, drives: list[str], figures: Sequence[str] = (), note: str = "",
             conclusions: Sequence[str] = ()) -> str:
    """The long table laid out like the paper's Table 3: rows = quantity, columns = method x outage length;
    then image links to the figures (file names relative to the report directory)."""
    cols = table.select("method", "outage_s").unique(maintain_order=True).sort("outage_s", maintain_order=True).rows()
    head = "| quantity | unit | " + " | ".join(f"{m} {L:g} s" for m, L in cols) + " |"
    lines = ["# RMS errors during GPS outages", "",
             f"Drives: {', '.join(drives)}. Mean over drives, ± sample standard deviation when more than one.", "",
             *((note, "") if note else ()), head, "|" + "---|" * (len(cols) + 2)]
    for q, unit in QUANTITIES:
        cells = []
        for m, L in cols:
            r = table.filter((pl.col("quantity") == q) & (pl.col("method") == m) & (pl.col("outage_s") == L))
            mean, std = (r["mean"][0], r["std"][0]) if len(r) else (None, None)
            cells.append("–" if mean is None else f"{mean:.3f}" + (f" ± {std:.3f}" if std is not None else ""))
        lines.append(f"| {q} | {unit} | " + " | ".join(cells) + " |")
    n = table.select("method", "outage_s", "windows").unique(maintain_order=True).rows()
    lines += ["", "Outage windows per column: " + ", ".join(f"{m} {L:g} s: {w}" for m, L, w in n), "",
              *conclusions]
    for f in figures:
        lines += [f"![errors against time in the outages: {f}]({f})", ""]
    return "\n".join(lines)
