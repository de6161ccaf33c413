"""``fieldlog view DRIVE.mcap [FUSED.mcap ...] [--rrd OUT.rrd]``: a drive and its fused solutions in rerun.

The drive may be several files (a rotated session's directory, a rosbag2 directory, or more files before the
fused ones: ``split_fused``); they are shown as one drive.

Everything is logged on one timeline, ``gps_time`` (UTC timestamps: the MCAP ``log_time`` of the derived
topics), with ``rr.send_columns``. The drive itself is read in one pass on the second core
(``replay.viewdata``: the IMU decimated block by block, so memory does not grow with the 500 Hz data), while
this module's import of rerun-sdk runs. A default blueprint is sent with the recording (``blueprint()``).

Entity paths (``<src>`` is ``gps``, ``truth`` or ``fusion/<method>``; ``<axis>`` is ``east``, ``north``, ``up``):

====================================  =============================================================================
``map/gps``                           GeoPoints, one row per ``/gps/fix`` epoch with a fix (finite lat/lon)
``map/truth``                         GeoPoints at 10 Hz (every ``TRUTH_DECIMATION``-th ``/truth/fix`` row)
``map/fusion/<method>``               GeoPoints, one row per ``/fusion/<method>/fix`` message (10 Hz)
``map/fusion/<method>/kf1``, ``/kf2``   the distributed methods' local solutions (``/fusion/<method>/kf{1,2}/fix``:
                                      the INS corrected by KF_I's or KF_II's estimate alone, the paper's Fig. 5)
``map/<src>/track``                   static GeoLineStrings: the whole track, so the map shows it at any time
``map/<src>/sigma``                   GeoPoints (``<src>``: ``gps``, ``fusion/<method>``), one row per ``map/<src>``
                                      row with a sigma: the position, radius max(sigma E, sigma N) in m (the
                                      circle around the 1-sigma ellipse of ``/fusion/<method>/std``, of the
                                      receiver's ``position_covariance`` for gps); the map shows the latest,
                                      a translucent disc that follows the car
``map/no_fix``                        GeoPoints, one row per GPS epoch without a fix, at the last fix position
``map/outage``                        static GeoLineStrings: the reference track (truth, else GPS) inside each
                                      outage window of ``/fusion/outage`` (merged over all files)
``enu/<src>``                         LineStrips3D in the local ENU frame, m (origin = first GPS fix, else the
                                      first truth or fused position; one tangent plane for the whole drive):
                                      row i is the segment from point i-1 to point i (row 0 degenerate), same
                                      rows as ``map/<src>``; the 3D view shows everything up to the time
                                      cursor, so the path grows as you scrub
``enu/fusion/<method>/sigma``         Ellipsoids3D: the 1-sigma ellipsoid of ``/fusion/<method>/std``,
                                      half sizes sigma E, N, U in m, centred on the ENU position; one row per
                                      ``SIGMA_PERIOD_S`` of the track (its first row with a sigma in each
                                      period), so that the 3D view, which shows every row up to the cursor,
                                      stays light
``errors/pos/<axis>/<method>``        Scalars [error, +sigma, -sigma], m: fused minus reference position (ENU);
                                      sigma from ``/fusion/<method>/std``
``errors/vel/<axis>/<method>``        Scalars [error, +sigma, -sigma], m/s: sigma from the ``/vel`` covariance
``status/outage``                     Scalars 0/1 (step): 1 inside a ``/fusion/outage`` window; rows at the
                                      drive start and at every merged window's start and end
``status/no_fix``                     Scalars 0/1 (step), one row per ``/gps/fix`` epoch: 1 = no fix
``<plot>/outage``                     Scalars, the outages shaded in the time plots (``<plot>``: ``errors/pos``,
                                      ``errors/vel``, ``errors/att`` and ``attitude``, each axis or angle): a
                                      wide translucent band at 0 across each merged window (rows at its start
                                      and end, then NaN to break the line until the next)
``solution_status/<method>``          Scalars (step), one row per ``/fusion/<method>/status`` message: the
                                      solution status code (``fusion.output.STATUS``: 0 aligning, 1 aligned,
                                      2 aided, 3 coasting, 4 degraded, 5 diverged)
``imu/gyro``, ``imu/accel``           Scalars x, y, z (body RFU): rad/s and m/s^2, DECIMATED by means of
                                      ``IMU_DECIMATION`` consecutive valid samples (500 Hz -> 50 Hz), stamped at
                                      the mean sample time; a trailing incomplete group is dropped, so the row
                                      count is ``valid /imu samples // IMU_DECIMATION``
``bias/gyro/<method>``                Scalars x, y, z (body RFU), deg/h: the gyro bias estimate the method's INS
                                      ran with (``/fusion/<method>/imu_bias``), one row per solution row
``bias/accel/<method>``               Scalars x, y, z (body RFU), mg (1 mg = 9.80665e-3 m/s^2): the accelerometer
                                      bias estimate
``bias/{gyro,accel}/truth``           the simulator's ``/truth/imu_bias`` at 10 Hz (every ``TRUTH_DECIMATION``-th
                                      row): the sensor error less its white noise
``speed/wheels``, ``speed/truth``     Scalars, m/s: the forward speed of ``/vehicle/twist`` (the wheels) and of
                                      ``/truth/vehicle/twist`` (simulated drives), one row per message
``speed/<method>``                    Scalars, m/s: the fused forward speed (``/fusion/<method>/odom`` twist x,
                                      base_link), one row per solution row, beside the wheels'
``enu/<src>/base_link``               the vehicle's pose (``<src>``: ``truth``, ``fusion/<method>``): Transform3D
                                      per solution row (truth: per ``TRUTH_DECIMATION``-th row), base_link (REP-103
                                      FLU) in the view's ENU frame, translation m and rotation x, y, z, w; static
                                      Boxes3D (``CAR_HALF_SIZES_M``, in base_link) and TransformAxes3D. base_link is
                                      the IMU's pose through the drive's ``/tf_static`` base_link -> imu (the fused
                                      files' ``odom``/``base_link`` rule: ``replay/solutions.py``, ``Odometry``); the
                                      view's ENU axes are taken as map's (0.16 mrad per km apart)
``attitude/<angle>/<src>``            Scalars, deg (``<angle>``: ``roll``, ``pitch``, ``heading``): the vehicle's
                                      (base_link in RFU axes, ``fusion.earth.dcm_to_euler``); fused methods
                                      [angle, +sigma, -sigma] with sigma from ``/fusion/<method>/attitude_std``
                                      (phi E, N, U turned into the vehicle's pitch and roll axes by the heading;
                                      heading sigma = phi U); truth [angle]; heading in [0, 360)
``errors/att/<angle>/<method>``       Scalars [error, +sigma, -sigma], deg: fused minus truth (``/truth/attitude``
                                      interpolated to the fused times; heading error wrapped to +-180), with truth
``gps/satellites``, ``gps/hdop``,     Scalars, one row per GGA sentence of ``/gps/nmea``: satellites used, HDOP,
``gps/fix_type``                      GGA fix quality (0 none, 1 GPS, 2 DGPS, 4 RTK fixed, 5 RTK float,
                                      6 dead reckoning); a drive without GGA has none
``timesync/state``                    Scalars: FREE=0, HOLDOVER=1, LOCKED=2 (``/time/sync``)
``timesync/rate_ppm``                 Scalars: DAQ oscillator rate error, ppm
``timesync/residual_us``              Scalars: RMS fit residual of the inlier PPS edges, us
====================================  =============================================================================

The error reference is the truth (``/truth/fix``, ``/truth/vel``, interpolated linearly to the fused times)
when the drive has it, otherwise the GPS: fused states interpolated to the GPS fix epochs (no vertical
velocity error then: NMEA has none).
"""

from __future__ import annotations

import contextlib
import os
import sys
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from fieldlog.acquire import calib, frames
from fieldlog.drive import outputs, reader
from fieldlog.fusion import earth, output
from fieldlog.fusion.methods import REGISTRY
from fieldlog.replay import solutions
from fieldlog.replay.ahead import Ahead
from fieldlog.drive.files import DriveSpec, drive_files, label
from fieldlog.replay.inputs import InputMap
from fieldlog.replay.viewdata import IMU_DECIMATION, DrivePass, decimate_means, start, topic_names  # noqa: F401


class _WithoutPandas:
    """An import finder that answers "not installed" for pandas (``_pyarrow_without_pandas``)."""

    @staticmethod
    def find_spec(name: str, path: object = None, target: object = None) -> None:
        if name == "pandas":
            raise ModuleNotFoundError("pandas is not imported by the view", name=name)


def _pyarrow_without_pandas() -> None:
    """Tell pyarrow, at its first look, that pandas is absent, so that logging never imports pandas.

    rerun-sdk hands pyarrow Python lists (names, colours, blueprint fields); given a list, ``pyarrow.array`` asks
    whether it is a pandas object, and the first such question imports pandas when it is installed (beside
    rerun by another package, not for rerun), a large import on the view's path. pyarrow asks once and keeps
    the answer; a list converts the same either way. Contract: in this process pyarrow is not given pandas
    objects to convert (pyarrow's explicit pandas calls, such as ``to_pandas``, still import it).
    """
    import pyarrow as pa  # rerun's own dependency, imported after it (a core install lacks both: rerun is named)

    if "pandas" in sys.modules:
        return
    finder = _WithoutPandas()
    sys.meta_path.insert(0, finder)
    try:
        pa.array([0])
    finally:
        sys.meta_path.remove(finder)


_pyarrow_without_pandas()

TIMELINE = "gps_time"
TRUTH_DECIMATION = 10  # 100 Hz -> 10 Hz on the map and the 3D view
SIGMA_PERIOD_S = 2.0  # one sigma ellipsoid per this much of a track in the 3D view
AXES = ("east", "north", "up")
ANGLES = ("roll", "pitch", "heading")
CAR_HALF_SIZES_M = (2.25, 0.9, 0.75)  # a 4.5 x 1.8 x 1.5 m box (base_link FLU), centred 0.75 m above base_link

GPS_COLOR = (255, 140, 0)
WHEELS_COLOR = (120, 60, 200)
TRUTH_COLOR = (20, 160, 20)
NO_FIX_COLOR = (230, 30, 30)
OUTAGE_COLOR = (230, 30, 30, 200)
OUTAGE_BAND_COLOR = (230, 30, 30, 60)
OUTAGE_BAND_WIDTH = 36.0  # ui points
SIGMA_ALPHA = 70  # the map's sigma discs
METHOD_COLORS = {m.name: m.colour for m in REGISTRY.values() if m.colour is not None}
SOLUTION_STATUS_TITLE = "solution status (" + ", ".join(f"{i} {n}" for i, n in enumerate(output.STATUS)) + ")"
_PALETTE = [(0, 150, 150), (180, 0, 120), (100, 100, 0), (0, 80, 160), (160, 80, 0)]


@dataclass
class Track:
    """One source's positions (and velocities) on the timeline."""

    t_ns: np.ndarray  # int64 UTC ns
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    alt_m: np.ndarray
    v_n: np.ndarray | None = None  # (n,3) ENU m/s
    sigma_pos: np.ndarray | None = None  # (n,3) ENU m
    sigma_vel: np.ndarray | None = None  # (n,3) ENU m/s

    def take(self, sel) -> "Track":
        """Rows ``sel`` (mask or slice) of the track."""
        return Track(*(None if v is None else v[sel] for v in (getattr(self, f.name) for f in fields(self))))


@dataclass
class ViewResult:
    rrd: Path | None
    gps_fixes: int
    no_fix: int
    imu_rows: int
    methods: list[str] = field(default_factory=list)
    outages: int = 0


def method_color(method: str, index: int) -> tuple[int, int, int]:
    return METHOD_COLORS.get(method, _PALETTE[index % len(_PALETTE)])


def _times(t_ns: np.ndarray) -> list[rr.TimeColumn]:
    return [rr.TimeColumn(TIMELINE, timestamp=np.asarray(t_ns, dtype=np.int64).astype("datetime64[ns]"))]


def to_enu(lat_deg: np.ndarray, lon_deg: np.ndarray, alt_m: np.ndarray,
           origin: tuple[float, float, float]) -> np.ndarray:
    """Geodetic (deg, deg, m ellipsoidal) -> ENU (n,3) m in the tangent frame at ``origin`` (lat deg, lon deg, h m)."""
    lat0, lon0, h0 = np.radians(origin[0]), np.radians(origin[1]), origin[2]
    r_e = earth.lla_to_ecef(np.radians(lat_deg), np.radians(lon_deg), alt_m) - earth.lla_to_ecef(lat0, lon0, h0)
    return r_e @ earth.C_en(lat0, lon0).T


def _fill_alt(alt: np.ndarray) -> np.ndarray:
    """NaN heights (horizontal-only fixes) filled by interpolation over the finite ones."""
    ok = np.isfinite(alt)
    if ok.all() or not ok.any():
        return np.where(ok, alt, 0.0)
    idx = np.arange(len(alt))
    return np.interp(idx, idx[ok], alt[ok])


def _step_segments(p: np.ndarray) -> np.ndarray:
    """Row i = segment [p[i-1], p[i]] (row 0: [p[0], p[0]]), (n,2,3)."""
    return np.stack([np.concatenate([p[:1], p[:-1]]), p], axis=1)


def merge_windows(windows: Iterable[tuple[int, int]]) -> list[tuple[int, int]]:
    """Union of [start, end) windows (int ns), sorted."""
    out: list[list[int]] = []
    for s, e in sorted(windows):
        if out and s <= out[-1][1]:
            out[-1][1] = max(out[-1][1], e)
        else:
            out.append([s, e])
    return [(s, e) for s, e in out]


# ---------------------------------------------------------------------------------------------
# Reading


def gps_track(fix: dict) -> tuple[Track, np.ndarray, np.ndarray]:
    """Decoded ``/gps/fix`` -> (track of the fix epochs, all epoch times, no-fix mask over all epochs); the
    track's sigma from the diagonal of ``position_covariance`` (ENU m^2) where the receiver gives one."""
    ok = fix["valid"] & (fix["status"] >= 0) & np.isfinite(fix["lat_deg"]) & np.isfinite(fix["lon_deg"])
    trk = Track(fix["log_time_ns"][ok], fix["lat_deg"][ok], fix["lon_deg"][ok], _fill_alt(fix["alt_m"][ok]))
    if "position_covariance" in fix and "covariance_type" in fix:
        var = fix["position_covariance"][ok][:, [0, 4, 8]]
        known = (fix["covariance_type"][ok] > 0)[:, None] & (var > 0)
        trk.sigma_pos = np.where(known, np.sqrt(np.where(known, var, 0.0)), np.nan)
    return trk, fix["log_time_ns"][fix["valid"]], ~ok[fix["valid"]]


def truth_track(fix: dict, vel: dict | None) -> Track:
    """Decoded ``/truth/fix`` (and ``/truth/vel``) -> track."""
    ok = fix["valid"]
    trk = Track(fix["log_time_ns"][ok], fix["lat_deg"][ok], fix["lon_deg"][ok], fix["alt_m"][ok])
    if vel is not None and len(vel["log_time_ns"]):
        trk.v_n = _interp(trk.t_ns, vel["log_time_ns"][vel["valid"]], vel["v_n"][vel["valid"]])
    return trk


FUSED_NAMES = ("fix", "std", "vel", "kf1/fix", "kf2/fix", "attitude", "attitude_std", solutions.STATUS, "imu_bias")


def _read_fused(path: str | os.PathLike[str], method: str, wheels: bool) -> dict[str, dict]:
    """What the view shows of ``method`` in the fused file ``path``, read in one pass: name (``FUSED_NAMES``, and
    ``odom`` with ``wheels``) -> its ``/fusion/<method>/<name>`` rows, for the names the file has messages of."""
    names = [*FUSED_NAMES, *(("odom",) if wheels else ())]
    got = reader.read_topics(path, [solutions.topic(method, n) for n in names])
    rows = {n: got.get(solutions.topic(method, n)) for n in names}
    return {n: d for n, d in rows.items() if d is not None and len(d["log_time_ns"])}


def _fused(sol: dict[str, dict]) -> Track:
    """The fused track of ``_read_fused``'s rows: positions, and their sigma and velocity where the file has them."""
    if "fix" not in sol:
        return Track(np.zeros(0, np.int64), np.zeros(0), np.zeros(0), np.zeros(0))
    f = sol["fix"]
    ok = f["valid"]
    t = f["log_time_ns"][ok]
    trk = Track(t, f["lat_deg"][ok], f["lon_deg"][ok], f["alt_m"][ok])
    if "std" in sol:
        s = sol["std"]
        trk.sigma_pos = _interp(t, s["log_time_ns"][s["valid"]], s["xyz"][s["valid"]])
    if "vel" in sol:
        v = sol["vel"]
        vok = v["valid"]
        trk.v_n = _interp(t, v["log_time_ns"][vok], v["v_n"][vok])
        var = v["covariance"][vok][:, [0, 7, 14]]
        trk.sigma_vel = _interp(t, v["log_time_ns"][vok], np.sqrt(np.clip(var, 0.0, None)))
    return trk


def _interp(t: np.ndarray, tp: np.ndarray, xp: np.ndarray) -> np.ndarray:
    """Linear interpolation of (m,k) rows at times tp to times t; NaN outside [tp[0], tp[-1]]."""
    out = np.full((len(t), xp.shape[1]), np.nan)
    if len(tp) == 0:
        return out
    x = (t - tp[0]).astype(np.float64)
    xp_s = (tp - tp[0]).astype(np.float64)
    inside = (t >= tp[0]) & (t <= tp[-1])
    for k in range(xp.shape[1]):
        out[inside, k] = np.interp(x[inside], xp_s, xp[:, k])
    return out


def _outages(paths: Sequence[str | os.PathLike[str]]) -> list[tuple[int, int]]:
    windows = []
    for p in paths:
        if topic_names(p).get(solutions.OUTAGE):
            d = reader.read_topic(p, solutions.OUTAGE)
            windows += [(int(m.start_ns), int(m.end_ns)) for m in d["msgs"] if m is not None]
    return merge_windows(windows)


def _one_path(drive: DriveSpec) -> bool:
    """Whether the drive was given as one path (a file or directory, or a ``Drive`` opened from one), which may
    hold fused topics itself."""
    return isinstance(drive, (str, os.PathLike)) or len(drive) == 1


def discover_methods(paths: Sequence[str | os.PathLike[str]]) -> list[tuple[str, Path]]:
    """(label, file) for every ``/fusion/<method>/fix`` in ``paths``; a method seen twice gets the file's stem."""
    out: list[tuple[str, Path]] = []
    seen: set[str] = set()
    for p in paths:
        for topic in topic_names(p):
            method = solutions.method_of(topic)
            if method is not None:
                label = method if method not in seen else f"{method}@{Path(p).stem}"
                seen.add(method)
                out.append((label, Path(p)))
    return out


# ---------------------------------------------------------------------------------------------
# Logging


def _log_track(rec: rr.RecordingStream, src: str, trk: Track, color, origin, radius: float,
               sigma_3d: bool = True) -> None:
    """``map/<src>``, its track and sigma discs, and ``enu/<src>`` (with its sigma ellipsoids if ``sigma_3d``)."""
    if len(trk.t_ns) == 0:
        return
    times = _times(trk.t_ns)
    rr.send_columns(f"map/{src}", indexes=times,
                    columns=rr.GeoPoints.columns(positions=np.stack([trk.lat_deg, trk.lon_deg], axis=1)),
                    recording=rec)
    rec.log(f"map/{src}", rr.GeoPoints.from_fields(radii=rr.Radius.ui_points(radius), colors=[color]), static=True)
    rec.log(f"map/{src}/track", rr.GeoLineStrings(lat_lon=[np.stack([trk.lat_deg, trk.lon_deg], axis=1)],
                                                  radii=rr.Radius.ui_points(1.5), colors=[color]), static=True)
    p = to_enu(trk.lat_deg, trk.lon_deg, trk.alt_m, origin)
    rr.send_columns(f"enu/{src}", indexes=times, columns=rr.LineStrips3D.columns(strips=_step_segments(p)),
                    recording=rec)
    rec.log(f"enu/{src}", rr.LineStrips3D.from_fields(colors=[color], radii=rr.Radius.ui_points(1.5)), static=True)
    if trk.sigma_pos is not None:
        _log_sigma(rec, src, trk, p if sigma_3d else None, color)


def sigma_rows(t_ns: np.ndarray, sigma: np.ndarray, period_s: float = SIGMA_PERIOD_S) -> np.ndarray:
    """Indices of the rows with a finite sigma (n,3), the first of each ``period_s`` since the first of them."""
    idx = np.flatnonzero(np.isfinite(sigma).all(axis=1))
    if not len(idx):
        return idx
    k = (t_ns[idx] - t_ns[idx[0]]) // int(period_s * 1e9)
    return idx[np.concatenate([[True], k[1:] != k[:-1]])]


def _log_sigma(rec: rr.RecordingStream, src: str, trk: Track, p_n: np.ndarray | None, color) -> None:
    """``map/<src>/sigma`` (every row with a horizontal sigma) and, given the ENU positions ``p_n`` (m),
    ``enu/<src>/sigma`` (``sigma_rows``)."""
    s = trk.sigma_pos
    on_map = np.flatnonzero(np.isfinite(s[:, :2]).all(axis=1))
    if not len(on_map):
        return
    rr.send_columns(f"map/{src}/sigma", indexes=_times(trk.t_ns[on_map]),
                    columns=rr.GeoPoints.columns(positions=np.stack([trk.lat_deg[on_map], trk.lon_deg[on_map]], 1),
                                                 radii=s[on_map, :2].max(axis=1)), recording=rec)
    rec.log(f"map/{src}/sigma", rr.GeoPoints.from_fields(colors=[(*color, SIGMA_ALPHA)]), static=True)
    rows = sigma_rows(trk.t_ns, s) if p_n is not None else []
    if len(rows):
        rr.send_columns(f"enu/{src}/sigma", indexes=_times(trk.t_ns[rows]),
                        columns=rr.Ellipsoids3D.columns(centers=p_n[rows], half_sizes=s[rows]), recording=rec)
        rec.log(f"enu/{src}/sigma", rr.Ellipsoids3D.from_fields(
            colors=[color], line_radii=rr.Radius.ui_points(0.75),
            fill_mode=rr.components.FillMode.MajorWireframe), static=True)


@dataclass
class Errors:
    """Fused minus reference on the times ``t_ns``, ENU: position m, velocity m/s; sigmas (n,3) or None."""

    t_ns: np.ndarray
    pos: np.ndarray
    sigma_pos: np.ndarray | None
    vel: np.ndarray | None
    sigma_vel: np.ndarray | None


def errors(trk: Track, ref: Track, ref_is_truth: bool, origin: tuple[float, float, float]) -> Errors:
    """Errors of a fused track: against the truth at the fused times (truth interpolated), or against the GPS
    at its fix epochs (fused interpolated; no vertical velocity error, NMEA has none). Rows with no
    reference are dropped."""
    p_f = to_enu(trk.lat_deg, trk.lon_deg, trk.alt_m, origin)
    p_r = to_enu(ref.lat_deg, ref.lon_deg, ref.alt_m, origin)
    has_v = trk.v_n is not None and ref.v_n is not None
    if ref_is_truth:
        t = trk.t_ns
        dp = p_f - _interp(t, ref.t_ns, p_r)
        sp, sv = trk.sigma_pos, trk.sigma_vel
        dv = trk.v_n - _interp(t, ref.t_ns, ref.v_n) if has_v else None
    else:
        t = ref.t_ns
        dp = _interp(t, trk.t_ns, p_f) - p_r
        sp = _interp(t, trk.t_ns, trk.sigma_pos) if trk.sigma_pos is not None else None
        sv = _interp(t, trk.t_ns, trk.sigma_vel) if trk.sigma_vel is not None else None
        dv = _interp(t, trk.t_ns, trk.v_n) - ref.v_n if has_v else None
        if dv is not None:
            dv[:, 2] = np.nan
    keep = np.isfinite(dp).all(axis=1)

    def sel(a: np.ndarray | None) -> np.ndarray | None:
        return a[keep] if a is not None else None

    return Errors(t[keep], dp[keep], sel(sp), sel(dv), sel(sv))


def _log_errors(rec: rr.RecordingStream, method: str, e: Errors, color) -> None:
    """``errors/{pos,vel}/<axis>/<method>`` as [error, +sigma, -sigma]."""
    light = tuple(int(c + (255 - c) * 0.55) for c in color)
    for kind, err, sig, unit in (("pos", e.pos, e.sigma_pos, "m"), ("vel", e.vel, e.sigma_vel, "m/s")):
        if err is None:
            continue
        for k, axis in enumerate(AXES):
            ok = np.isfinite(err[:, k])
            if not ok.any():
                continue
            s = sig[ok, k] if sig is not None else np.full(ok.sum(), np.nan)
            path = f"errors/{kind}/{axis}/{method}"
            rr.send_columns(path, indexes=_times(e.t_ns[ok]),
                            columns=rr.Scalars.columns(scalars=np.stack([err[ok, k], s, -s], axis=1)),
                            recording=rec)
            rec.log(path, rr.SeriesLines(colors=[color, light, light], widths=[2.0, 1.0, 1.0],
                                         names=[f"{method} {axis} ({unit})", f"{method} +σ", f"{method} −σ"]),
                    static=True)


def _log_scalar(rec: rr.RecordingStream, path: str, t_ns: np.ndarray, x: np.ndarray, name: str | list[str],
                color=None, step: bool = False) -> None:
    if len(t_ns) == 0:
        return
    rr.send_columns(path, indexes=_times(t_ns), columns=rr.Scalars.columns(scalars=np.asarray(x, dtype=np.float64)),
                    recording=rec)
    names = name if isinstance(name, list) else [name]
    rec.log(path, rr.SeriesLines(names=names, colors=color,
                                 interpolation_mode=rr.components.InterpolationMode.StepAfter if step else None),
            static=True)


BAND_PLOTS = (("errors/pos", AXES), ("errors/vel", AXES), ("errors/att", ANGLES), ("attitude", ANGLES))


def _log_outage_bands(rec: rr.RecordingStream, windows: Sequence[tuple[int, int]]) -> None:
    """``<plot>/outage`` for every plot of ``BAND_PLOTS``: a wide translucent line at 0 across each window
    [start, end] ns, broken by a NaN row 1 ns after each end."""
    t = np.array([[s, e, e + 1] for s, e in windows], dtype=np.int64).ravel()
    y = np.tile([0.0, 0.0, np.nan], len(windows))
    for group, names in BAND_PLOTS:
        for name in names:
            path = f"{group}/{name}/outage"
            rr.send_columns(path, indexes=_times(t), columns=rr.Scalars.columns(scalars=y), recording=rec)
            rec.log(path, rr.SeriesLines(names=["outage"], colors=[OUTAGE_BAND_COLOR], widths=[OUTAGE_BAND_WIDTH]),
                    static=True)


BIAS_UNITS = (("gyro", "omega_ib_b", 180.0 / np.pi * 3600.0, "deg/h"), ("accel", "f_b", 1e3 / 9.80665, "mg"))


def _log_bias(rec: rr.RecordingStream, src: str, b: dict[str, np.ndarray], color) -> None:
    """``bias/{gyro,accel}/<src>`` from rows of an Imu-typed bias topic (valid rows only)."""
    ok = b["valid"]
    shades = [tuple(int(c * k) for c in color) for k in (1.0, 0.7, 0.45)]
    for kind, key, scale, unit in BIAS_UNITS:
        _log_scalar(rec, f"bias/{kind}/{src}", b["log_time_ns"][ok], b[key][ok] * scale,
                    [f"{src} {kind} bias {a} ({unit})" for a in "xyz"], shades)


# ---------------------------------------------------------------------------------------------
# The vehicle: pose, attitude, GPS quality


def mounting(drive: DriveSpec | None) -> tuple[np.ndarray, np.ndarray]:
    """(imu position in base_link m (3,), C_imu_base (3,3): IMU axes -> base_link axes) from the drive's
    ``/tf_static`` base_link -> imu; without one (or a drive), the default ``[mounting]`` (IMU at base_link,
    RFU -> FLU)."""
    if drive is not None and topic_names(drive).get("/tf_static"):
        for msg in reader.read_topic(drive, "/tf_static")["msgs"]:
            for tf in (msg.transforms if msg is not None else ()):
                if tf.header.frame_id == frames.BASE_LINK and tf.child_frame_id == frames.IMU:
                    t, r = tf.transform.translation, tf.transform.rotation
                    return np.array([t.x, t.y, t.z]), earth.quat_to_dcm(np.array([r.x, r.y, r.z, r.w]))
    return np.zeros(3), frames.C_imu_base(calib.Mounting())


@dataclass
class Pose:
    """base_link's pose in the view's ENU frame: t_ns (n,), p_n (n,3) m, C_base_n (n,3,3) base_link FLU -> ENU."""

    t_ns: np.ndarray
    p_n: np.ndarray
    C_base_n: np.ndarray

    def euler_deg(self, unwrap: bool = False) -> np.ndarray:
        """(n,3) roll, pitch, heading in deg of the vehicle (base_link in RFU axes); heading in [0, 360), or
        continuous from row to row (``unwrap``: for interpolation)."""
        heading, pitch, roll = earth.dcm_to_euler(self.C_base_n @ frames.C_RFU_FLU)
        return np.degrees(np.stack([roll, pitch, np.unwrap(heading) if unwrap else heading], axis=1))


def base_pose(trk: Track, q_bn: np.ndarray, mount: tuple[np.ndarray, np.ndarray],
              origin: tuple[float, float, float]) -> Pose:
    """base_link's pose from the IMU's position (``trk``) and attitude ``q_bn`` (n,4) x, y, z, w (IMU RFU -> ENU)
    on the same rows: C_base_n = C_bn C_imu_base^T, p_base = p_imu - C_base_n r_imu."""
    r_imu, C_imu_base = mount
    C_base_n = earth.quat_to_dcm(q_bn) @ C_imu_base.T
    p_n = to_enu(trk.lat_deg, trk.lon_deg, trk.alt_m, origin) - C_base_n @ r_imu
    return Pose(trk.t_ns, p_n, C_base_n)


def attitude_sigma_deg(phi_sigma_n: np.ndarray, heading_deg: np.ndarray) -> np.ndarray:
    """(n,3) roll, pitch, heading sigmas in deg from the attitude error sigmas phi E, N, U (rad, nav frame):
    the horizontal tilt turned into the vehicle's forward (roll) and right (pitch) axes by the heading,
    correlations ignored; heading sigma = phi U."""
    h = np.radians(heading_deg)
    s_e2, s_n2 = phi_sigma_n[:, 0] ** 2, phi_sigma_n[:, 1] ** 2
    roll = np.sqrt(np.sin(h) ** 2 * s_e2 + np.cos(h) ** 2 * s_n2)
    pitch = np.sqrt(np.cos(h) ** 2 * s_e2 + np.sin(h) ** 2 * s_n2)
    return np.degrees(np.stack([roll, pitch, phi_sigma_n[:, 2]], axis=1))


def wrap_deg(x: np.ndarray) -> np.ndarray:
    """Angles in deg wrapped to [-180, 180)."""
    return np.mod(x + 180.0, 360.0) - 180.0


def _log_pose(rec: rr.RecordingStream, src: str, pose: Pose, color, style: bool = True) -> None:
    """``enu/<src>/base_link``: the rows of ``pose``, and (``style``) the static box and axes."""
    if len(pose.t_ns) == 0:
        return
    path = f"enu/{src}/base_link"
    rr.send_columns(path, indexes=_times(pose.t_ns),
                    columns=rr.Transform3D.columns(translation=pose.p_n,
                                                   quaternion=earth.dcm_to_quat(pose.C_base_n)),
                    recording=rec)
    if style:
        rec.log(path, rr.Boxes3D(half_sizes=[CAR_HALF_SIZES_M], centers=[(0.0, 0.0, CAR_HALF_SIZES_M[2])],
                                 colors=[color], fill_mode="solid"), rr.TransformAxes3D(2.0), static=True)


def _log_attitude(rec: rr.RecordingStream, src: str, pose: Pose, sigma_deg: np.ndarray | None, color,
                  style: bool = True) -> None:
    """``attitude/<angle>/<src>``: [angle, +sigma, -sigma] (sigma None: [angle]); ``style``: the series' names
    and colours too (static)."""
    light = tuple(int(c + (255 - c) * 0.55) for c in color)
    euler = pose.euler_deg()
    for k, angle in enumerate(ANGLES):
        x = euler[:, k:k + 1]
        names, colors, widths = [f"{src} {angle} (deg)"], [color], [2.0]
        if sigma_deg is not None:
            x = np.hstack([x, x + sigma_deg[:, k:k + 1], x - sigma_deg[:, k:k + 1]])
            names, colors, widths = names + [f"{src} +σ", f"{src} −σ"], colors + [light, light], widths + [1.0, 1.0]
        path = f"attitude/{angle}/{src}"
        rr.send_columns(path, indexes=_times(pose.t_ns), columns=rr.Scalars.columns(scalars=x), recording=rec)
        if style:
            rec.log(path, rr.SeriesLines(names=names, colors=colors, widths=widths), static=True)


def _log_attitude_errors(rec: rr.RecordingStream, method: str, pose: Pose, sigma_deg: np.ndarray, truth: Pose,
                         color) -> None:
    """``errors/att/<angle>/<method>``: fused minus truth (truth interpolated to the fused times)."""
    ref = _interp(pose.t_ns, truth.t_ns, truth.euler_deg(unwrap=True))
    err = pose.euler_deg() - ref
    err[:, 2] = wrap_deg(err[:, 2])
    ok = np.isfinite(err).all(axis=1)
    if not ok.any():
        return
    light = tuple(int(c + (255 - c) * 0.55) for c in color)
    for k, angle in enumerate(ANGLES):
        path = f"errors/att/{angle}/{method}"
        s = sigma_deg[ok, k]
        rr.send_columns(path, indexes=_times(pose.t_ns[ok]),
                        columns=rr.Scalars.columns(scalars=np.stack([err[ok, k], s, -s], axis=1)), recording=rec)
        rec.log(path, rr.SeriesLines(colors=[color, light, light], widths=[2.0, 1.0, 1.0],
                                     names=[f"{method} {angle} (deg)", f"{method} +σ", f"{method} −σ"]),
                static=True)


def _plot(origin: str, name: str) -> rrb.TimeSeriesView:
    """A time series whose time axis spans the whole drive."""
    whole = rr.TimeRange(start=rrb.TimeRangeBoundary.infinite(), end=rrb.TimeRangeBoundary.infinite())
    return rrb.TimeSeriesView(origin=origin, name=name, axis_x=rrb.TimeAxis(view_range=whole))


def _row(plots: Sequence[rrb.TimeSeriesView], name: str) -> rrb.Horizontal:
    return rrb.Horizontal(*plots, name=name)


def blueprint(map_zoom: float | None = None, follow: str | None = None) -> rrb.Blueprint:
    """Map, the 3D trajectory with the vehicle and a view following it on the left; on the right, rows side by
    side: position errors E/N/U, attitude with its sigma, attitude errors, then GPS outage/no fix, GPS quality
    and the time-sync state on one row, and the rest in tabs. Side panels collapsed, the time cursor
    following the newest data (the whole drive at once, outages in red on the map).
    ``map_zoom``: the map's web-mercator zoom level (None: the viewer fits the data); ``follow``: the source
    (``fusion/<method>``, ``truth``) whose ``enu/<follow>/base_link`` is the close-up view's origin (None: no
    close-up)."""
    up_to_cursor = rrb.VisibleTimeRange(TIMELINE, start=rrb.TimeRangeBoundary.infinite(),
                                        end=rrb.TimeRangeBoundary.cursor_relative())
    err = {kind: [_plot(f"errors/{kind}/{axis}", f"{label} error {axis}") for axis in axes]
           for kind, label, axes in (("pos", "position", AXES), ("vel", "velocity", AXES),
                                     ("att", "attitude", ANGLES))}
    attitude = [_plot(f"attitude/{angle}", f"{angle} ±σ (deg)") for angle in ANGLES]
    # the close-up's space is base_link's: the view moves with the car, the tracks drawn around it
    close_up = rrb.Spatial3DView(
        origin=f"enu/{follow}/base_link", contents="enu/**", name=f"vehicle pose: {follow} base_link",
        time_ranges=up_to_cursor,
        eye_controls=rrb.EyeControls3D(position=(-14.0, 9.0, 7.0), look_target=(0.0, 0.0, CAR_HALF_SIZES_M[2]),
                                       eye_up=(0.0, 0.0, 1.0))) if follow else None
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.MapView(origin="map", name="Map", zoom=map_zoom),
                rrb.Horizontal(*(v for v in (
                    rrb.Spatial3DView(origin="enu", name="Local ENU trajectory (m)", time_ranges=up_to_cursor),
                    close_up) if v is not None)),
                row_shares=[1, 1],
            ),
            rrb.Vertical(
                _row(err["pos"], "position error"),
                _row(attitude, "attitude"),
                _row(err["att"], "attitude error (truth)"),
                _row([_plot("status", "outage / no fix"), _plot("solution_status", SOLUTION_STATUS_TITLE),
                      _plot("gps/satellites", "satellites"),
                      _plot("gps/hdop", "HDOP"), _plot("gps/fix_type", "fix type (1 GPS, 2 DGPS, 4 RTK)"),
                      _plot("timesync/state", "time sync (2 locked)")], "GPS quality and time sync"),
                rrb.Tabs(
                    _row(err["vel"], "velocity error"),
                    _plot("imu/gyro", f"gyro (means of {IMU_DECIMATION} samples)"),
                    _plot("imu/accel", f"accel (means of {IMU_DECIMATION} samples)"),
                    rrb.Vertical(_plot("bias/gyro", "gyro bias estimate (deg/h)"),
                                 _plot("bias/accel", "accel bias estimate (mg)"), name="IMU bias estimates"),
                    _plot("speed", "forward speed: wheels and fused (m/s)"),
                    rrb.Vertical(
                        _plot("timesync/rate_ppm", "rate error (ppm)"),
                        _plot("timesync/residual_us", "fit residual (us)"),
                        name="time sync",
                    ),
                ),
                row_shares=[2, 2, 2, 1.6, 1.8],
            ),
            column_shares=[1, 1.3],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=TIMELINE, play_state="following"),
    )


def follow_source(drive: DriveSpec, fused: Sequence[str | os.PathLike[str]]) -> str | None:
    """The source the close-up view tracks: the first fused method, else the truth, else none."""
    methods = discover_methods([drive, *fused] if _one_path(drive) else fused)
    if methods:
        return f"fusion/{methods[0][0]}"
    return "truth" if topic_names(drive).get("/truth/attitude") else None


def _log_imu(rec: rr.RecordingStream, got: DrivePass) -> int:
    """The decimated IMU rows as ``imu/gyro`` and ``imu/accel``; returns their count."""
    if not len(got.imu_t_ns):
        return 0
    for path, cols in (("imu/gyro", slice(0, 3)), ("imu/accel", slice(3, 6))):
        rr.send_columns(path, indexes=_times(got.imu_t_ns), columns=rr.Scalars.columns(scalars=got.imu[:, cols]),
                        recording=rec)
    xyz = [(220, 50, 50), (40, 160, 40), (40, 90, 230)]
    rec.log("imu/gyro", rr.SeriesLines(names=["gyro x (rad/s)", "gyro y", "gyro z"], colors=xyz), static=True)
    rec.log("imu/accel", rr.SeriesLines(names=["accel x (m/s²)", "accel y", "accel z"], colors=xyz), static=True)
    return len(got.imu_t_ns)


def _drain(read: Ahead[float, DrivePass], progress: Callable[[float], None] | None) -> DrivePass:
    """The drive pass's result, its progress passed on as the first 80 % of the view's."""
    it = iter(read)
    while True:
        try:
            done = next(it)
        except StopIteration as stop:
            return stop.value
        if progress:
            progress(0.8 * done)


def build(rec: rr.RecordingStream, drive: DriveSpec, fused: Sequence[str | os.PathLike[str]] = (),
          progress: Callable[[float], None] | None = None, inputs: InputMap | None = None,
          early: Ahead[float, DrivePass] | None = None) -> ViewResult:
    """Log a drive and its fused files into ``rec`` (which must already have its sink); ``inputs``: the topics
    and IMU frame of another logger's drive (``replay.inputs.resolve``); ``early``: the drive pass
    (``replay.viewdata.start``) the caller began, else it is begun here."""
    files = [drive, *fused]
    methods = discover_methods(files if _one_path(drive) else fused)
    with early if early is not None else start(drive, lambda: inputs) as read:
        # what the drive pass does not give is read while it runs
        wheels = bool(topic_names(drive).get("/vehicle/twist"))
        fused_rows = [_read_fused(p, m.split("@")[0], wheels) for m, p in methods]
        mount = mounting(drive)
        got = _drain(read, progress)
    imu_rows = _log_imu(rec, got)
    low = got.low
    gps, epochs_t, no_fix = None, np.zeros(0, np.int64), np.zeros(0, bool)
    if "/gps/fix" in low:
        gps, epochs_t, no_fix = gps_track(low["/gps/fix"])
    truth = truth_track(low["/truth/fix"], low.get("/truth/vel")) if "/truth/fix" in low else None
    fused_trk = [(m, _fused(sol)) for (m, _), sol in zip(methods, fused_rows)]
    candidates = [t for t in [gps, truth, *(f for _, f in fused_trk)] if t is not None and len(t.t_ns)]
    if not candidates:
        raise ValueError(f"{label(drive)}: no /gps/fix, /truth/fix or /fusion/*/fix positions to show")
    o = candidates[0]
    ok_alt = np.isfinite(o.alt_m)
    origin = (float(o.lat_deg[0]), float(o.lon_deg[0]), float(o.alt_m[ok_alt][0]) if ok_alt.any() else 0.0)

    if gps is not None:
        _log_gps(rec, gps, epochs_t, no_fix, low, origin)
    truth_map, truth_pose = _log_truth(rec, truth, low, mount, origin)
    ref = _Reference(truth if truth is not None else gps, truth is not None, truth_pose, mount)
    for i, ((m, trk), sol) in enumerate(zip(fused_trk, fused_rows)):
        _log_fused(rec, m, trk, sol, method_color(m.split("@")[0], i), origin, ref)
    for topic, src, color in (("/vehicle/twist", "wheels", WHEELS_COLOR), ("/truth/vehicle/twist", "truth",
                                                                           TRUTH_COLOR)):
        if topic in low:
            d = low[topic]
            ok = d["valid"]
            _log_scalar(rec, f"speed/{src}", d["log_time_ns"][ok], d["v_n"][ok, 0], f"{src} forward speed (m/s)",
                        [color])

    windows = _outages(files)
    if windows:
        _log_outage_windows(rec, windows, min(int(c.t_ns[0]) for c in candidates),
                            truth_map if truth_map is not None else gps)
    _log_receiver(rec, got.gga, low)
    if progress:
        progress(1.0)
    return ViewResult(None, len(gps.t_ns) if gps is not None else 0, int(no_fix.sum()), imu_rows,
                      [m for m, _ in fused_trk], len(windows))


def _log_gps(rec: rr.RecordingStream, gps: Track, epochs_t: np.ndarray, no_fix: np.ndarray, low: dict,
             origin: tuple[float, float, float]) -> None:
    """The GPS track (its velocity from ``/gps/vel``) and the epochs without a fix, in time and on the map."""
    if "/gps/vel" in low:
        v = low["/gps/vel"]
        gps.v_n = _interp(gps.t_ns, v["log_time_ns"][v["valid"]], v["v_n"][v["valid"]])
    _log_track(rec, "gps", gps, GPS_COLOR, origin, 3.0, sigma_3d=False)  # the 3D view: the fused sigma alone
    _log_scalar(rec, "status/no_fix", epochs_t, no_fix.astype(float), "GPS no fix", [NO_FIX_COLOR], step=True)
    if no_fix.any() and len(gps.t_ns):
        idx = np.searchsorted(gps.t_ns, epochs_t[no_fix], side="right") - 1
        has = idx >= 0
        pos = np.stack([gps.lat_deg[idx[has]], gps.lon_deg[idx[has]]], axis=1)
        rr.send_columns("map/no_fix", indexes=_times(epochs_t[no_fix][has]),
                        columns=rr.GeoPoints.columns(positions=pos), recording=rec)
        rec.log("map/no_fix", rr.GeoPoints.from_fields(radii=rr.Radius.ui_points(6.0), colors=[NO_FIX_COLOR]),
                static=True)


def _log_truth(rec: rr.RecordingStream, truth: Track | None, low: dict, mount: tuple[np.ndarray, np.ndarray],
               origin: tuple[float, float, float]) -> tuple[Track | None, Pose | None]:
    """The truth's track (decimated), pose, attitude and IMU biases; (the decimated track, the whole pose), None
    for what the drive does not have."""
    truth_map, truth_pose = None, None
    if truth is not None:
        sl = slice(None, None, TRUTH_DECIMATION)
        truth_map = Track(truth.t_ns[sl], truth.lat_deg[sl], truth.lon_deg[sl], truth.alt_m[sl])
        _log_track(rec, "truth", truth_map, TRUTH_COLOR, origin, 2.0)
        if "/truth/attitude" in low:
            att = low["/truth/attitude"]
            q = _interp(truth.t_ns, att["log_time_ns"][att["valid"]], att["q_xyzw"][att["valid"]])
            ok = np.isfinite(q).all(axis=1)
            truth_pose = base_pose(truth.take(ok), q[ok], mount, origin)
            dec = Pose(truth_pose.t_ns[sl], truth_pose.p_n[sl], truth_pose.C_base_n[sl])
            _log_pose(rec, "truth", dec, TRUTH_COLOR)
            _log_attitude(rec, "truth", dec, None, TRUTH_COLOR)
    if "/truth/imu_bias" in low:
        _log_bias(rec, "truth", {k: v[::TRUTH_DECIMATION] for k, v in low["/truth/imu_bias"].items()}, TRUTH_COLOR)
    return truth_map, truth_pose


@dataclass
class _Reference:
    """What a fused solution is shown against: ``track`` (the truth, else the GPS; None: neither), whether it is
    the truth, the truth's pose (None without), and the drive's base_link -> imu mounting (``mounting``)."""

    track: Track | None
    is_truth: bool
    pose: Pose | None
    mount: tuple[np.ndarray, np.ndarray]


def _log_fused(rec: rr.RecordingStream, m: str, trk: Track, sol: dict[str, dict], color,
               origin: tuple[float, float, float], ref: _Reference) -> None:
    """One fused method's track (labelled ``m``; ``sol``: its rows, ``_read_fused``), its local filters' tracks,
    its errors against ``ref``, pose, attitude with its sigma and errors, status, IMU biases and (with
    ``odom``: the drive has wheel speeds) forward speed."""
    _log_track(rec, f"fusion/{m}", trk, color, origin, 2.5)
    for k, shade in (("kf1", 0.55), ("kf2", 0.8)):
        if f"{k}/fix" in sol:
            f = sol[f"{k}/fix"]
            ok = f["valid"]
            local = Track(f["log_time_ns"][ok], f["lat_deg"][ok], f["lon_deg"][ok], f["alt_m"][ok])
            _log_track(rec, f"fusion/{m}/{k}", local, tuple(int(c * shade) for c in color), origin, 1.5)
    if ref.track is not None and len(ref.track.t_ns):
        _log_errors(rec, m, errors(trk, ref.track, ref.is_truth, origin), color)
    if "attitude" in sol:
        att = sol["attitude"]
        q = _interp(trk.t_ns, att["log_time_ns"][att["valid"]], att["q_xyzw"][att["valid"]])
        ok = np.isfinite(q).all(axis=1)
        pose = base_pose(trk.take(ok), q[ok], ref.mount, origin)
        _log_pose(rec, f"fusion/{m}", pose, color)
        sigma = None
        if "attitude_std" in sol:
            a = sol["attitude_std"]
            phi = _interp(pose.t_ns, a["log_time_ns"][a["valid"]], a["xyz"][a["valid"]])
            sigma = attitude_sigma_deg(phi, pose.euler_deg()[:, 2])
        _log_attitude(rec, m, pose, sigma, color)
        if ref.pose is not None and sigma is not None:
            _log_attitude_errors(rec, m, pose, sigma, ref.pose, color)
    if solutions.STATUS in sol:  # a fused file may have none
        st = sol[solutions.STATUS]
        ok = st["valid"]
        _log_scalar(rec, f"solution_status/{m}", st["log_time_ns"][ok], st["status"][ok].astype(float),
                    f"{m} status", [color], step=True)
    if "imu_bias" in sol:  # fused files before it: none
        _log_bias(rec, m, sol["imu_bias"], color)
    if "odom" in sol:
        od = sol["odom"]
        keep = [i for i, msg in enumerate(od["msgs"]) if msg is not None]
        fwd = np.array([od["msgs"][i].twist.twist.linear.x for i in keep])
        _log_scalar(rec, f"speed/{m}", od["log_time_ns"][keep], fwd, f"{m} forward speed (m/s)", [color])


def _log_outage_windows(rec: rr.RecordingStream, windows: list[tuple[int, int]], t_start: int,
                        track: Track | None) -> None:
    """The outage windows (UTC ns) as a step from ``t_start`` on, as bands in the time plots and as strips of
    ``track`` (the truth, else the GPS) on the map."""
    t_edges = np.array([t_start] + [x for w in windows for x in w], dtype=np.int64)
    level = np.array([0.0] + [1.0, 0.0] * len(windows))
    order = np.argsort(t_edges, kind="stable")
    _log_scalar(rec, "status/outage", t_edges[order], level[order], "outage", [OUTAGE_COLOR[:3]], step=True)
    _log_outage_bands(rec, windows)
    if track is not None and len(track.t_ns):
        strips = []
        for s, e in windows:
            inside = (track.t_ns >= s) & (track.t_ns <= e)
            if inside.sum() >= 2:
                strips.append(np.stack([track.lat_deg[inside], track.lon_deg[inside]], axis=1))
        if strips:
            rec.log("map/outage", rr.GeoLineStrings(lat_lon=strips, radii=rr.Radius.ui_points(5.0),
                                                    colors=[OUTAGE_COLOR]), static=True)


def _log_receiver(rec: rr.RecordingStream, q: dict, low: dict) -> None:
    """The receiver's GGA quality (satellites, HDOP, fix type: ``q``) and the time sync's state, rate error and
    fit residual (``/time/sync`` in ``low``)."""
    if len(q["log_time_ns"]):
        _log_scalar(rec, "gps/satellites", q["log_time_ns"], q["satellites"], "satellites used", [GPS_COLOR], step=True)
        _log_scalar(rec, "gps/hdop", q["log_time_ns"], q["hdop"], "HDOP", [GPS_COLOR], step=True)
        _log_scalar(rec, "gps/fix_type", q["log_time_ns"], q["fix_type"],
                    "GGA quality", [GPS_COLOR], step=True)
    if "/time/sync" in low:
        ts = low["/time/sync"]
        ok = ts["valid"]
        t = ts["log_time_ns"][ok]
        _log_scalar(rec, "timesync/state", t, ts["state"][ok], "state (0 free, 1 holdover, 2 locked)", step=True)
        _log_scalar(rec, "timesync/rate_ppm", t, ts["rate_ppm"][ok], "rate error (ppm)")
        _log_scalar(rec, "timesync/residual_us", t, ts["residual_us"][ok], "fit residual (us)")


def has_display() -> bool:
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def view(drive: DriveSpec, fused: Sequence[str | os.PathLike[str]] = (),
         rrd: str | os.PathLike[str] | None = None, progress: Callable[[float], None] | None = None,
         inputs: InputMap | None = None, force: bool = False, early: Ahead[float, DrivePass] | None = None
         ) -> ViewResult:
    """Write ``rrd`` (streamed to the file as it is logged; a new name unless ``force``: ``outputs.staged``), or
    spawn the rerun viewer when ``rrd`` is None. ``early``: as ``build``'s."""
    drive_files(drive)  # FileNotFoundError naming a missing file
    for p in fused:
        if not Path(p).is_file():
            raise FileNotFoundError(f"{p} does not exist")
    if rrd is None and not has_display():
        raise ValueError("no display to open the viewer on: pass --rrd OUT.rrd")
    rec = rr.RecordingStream("fieldlog")
    bp = blueprint(follow=follow_source(drive, fused))
    with outputs.staged(rrd, force) if rrd is not None else contextlib.nullcontext() as work:
        if work is not None:
            rec.save(work, default_blueprint=bp)
        else:
            rec.spawn(default_blueprint=bp)
        try:
            res = build(rec, drive, fused, progress, inputs, early)
        finally:
            rec.flush()
            if work is not None:
                rec.disconnect()
    res.rrd = Path(rrd) if rrd is not None else None
    return res
