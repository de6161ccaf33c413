"""``fieldlog report DRIVE [FUSED ...] --out report.html``: one self-contained HTML page of a drive's health and
of its fused solutions, a verdict at the top.

The page answers "did everything record?" at a glance, as the drive-health screens of commercial car loggers
do: a verdict (what is wrong, each item a link to its section, or "nothing found"), then a header (duration,
distance, start and end in UTC and in the local time of the longitude's nautical zone, receiver and IMU, files
and sizes, rotation and recovery, port events), the track coloured by fix type with the outages marked, GNSS
quality, time sync, IMU, CAN and, per fused method, its status, sigmas and errors. A section whose topics the
drive lacks says "no data" and why; it never fails the report.

Why Jinja2 and matplotlib: the page is a template (``tools/templates/report.html.j2``, package data) that Jinja2
fills with every value HTML-escaped (topic names and metadata come from the file), and every plot is a
matplotlib SVG written inline into the page. The file therefore opens with no network, no JavaScript and no
file beside it, prints as it shows and mails as one attachment; the plots stay vector and small (each line
decimated to at most ``MAX_POINTS`` points). An interactive library (plotly, bokeh) would have to inline its
JavaScript bundle, megabytes in every report, for zooming that ``fieldlog view`` already gives. matplotlib is
the plotting library the project keeps anyway (``evaluate``'s figures); the map is drawn in local ENU metres
from the first fix, so no map tile is ever fetched.

Reads go through the existing readers: ``tools.info.drive_info`` (the drive's ``fieldlog.info`` figures or a
scan), ``replay.viewdata.drive_pass`` (the viewer's one pass: IMU decimated block by block, the low-rate topics
whole, GGA quality), ``replay.solutions`` for the fused topics and ``tools.evaluation.evaluate`` for the errors.
Memory is that of the viewer's pass: the 500 Hz IMU is never held whole.
"""
from __future__ import annotations

import io
import math
import os
import re
from dataclasses import dataclass, field
from datetime import datetime, timedelta, timezone
from importlib import resources
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from fieldlog.acquire import calib, daq
from fieldlog.drive import messages, outputs
from fieldlog.fusion import earth
from fieldlog.fusion import output as fusion_output
from fieldlog.replay import inputs, solutions, viewdata
from fieldlog.drive import reader
from fieldlog.drive.files import DriveSpec, label
from fieldlog.tools.info import DriveInfo, bus_line, drive_info, topic_rate

NS = 1_000_000_000
MAX_POINTS = 2000  # per plotted line: a longer series is decimated to every k-th point
LONG_OUTAGE_S = 5.0  # a GNSS outage (no fix, or no epoch at all) longer than this is in the verdict
MIN_LOCKED = 0.9  # time sync: a drive locked for less of its records after the first lock is in the verdict
MAX_REJECTED = 0.1  # PPS: a share of rejected edges above this is in the verdict
FULL_SCALE = 0.98  # IMU: a 50 Hz mean within this share of the ADC full scale counts as saturated
# DAQ and processing counters (acquire.counters) whose being non-zero is a fault, with what they mean
FAULT_COUNTERS = {"daq.lost_frames": "DAQ frames lost", "daq.counter_repeats": "DAQ counters repeated",
                  "daq.counter_implausible": "DAQ counters implausible", "daq.counter_backwards": "DAQ counters "
                  "backwards", "daq.bad_crc": "DAQ frames with a bad CRC", "daq.resyncs": "DAQ resyncs",
                  "processing_errors": "processing errors"}
CAN_ERRORS = ("error_frames", "bus_off", "status_errors", "overruns", "refused", "bad_records", "decode_errors")
FIX_TYPES = ((messages.STATUS_FIX, "fix", "#1f77b4"), (messages.STATUS_SBAS_FIX, "SBAS / DGPS", "#2ca02c"),
             (messages.STATUS_GBAS_FIX, "GBAS / RTK", "#9467bd"))
OUTAGE_COLOR = "#d62728"
SECTIONS = (("verdict", "Verdict"), ("drive", "Drive"), ("map", "Map"), ("gnss", "GNSS quality"),
            ("timesync", "Time sync"), ("imu", "IMU"), ("can", "CAN"), ("fusion", "Fused solutions"))


@dataclass
class Figure:
    svg: str
    caption: str


@dataclass
class Section:
    """One section of the page: facts (label, value), tables (header, rows), figures, or why it has no data."""

    id: str
    title: str
    nodata: str | None = None
    facts: list[tuple[str, str]] = field(default_factory=list)
    tables: list[tuple[list[str], list[list[str]]]] = field(default_factory=list)
    figures: list[Figure] = field(default_factory=list)
    parts: list[Section] = field(default_factory=list)


@dataclass
class Finding:
    """A verdict item: what is wrong, and the section that shows it."""

    text: str
    section: str


@dataclass
class ReportResult:
    path: Path
    findings: list[Finding]
    sections: list[str]
    methods: list[str]


# -- small helpers ---------------------------------------------------------------------------------------------


def _utc(ns: int) -> str:
    return datetime.fromtimestamp(ns / NS, timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")


def _local(ns: int, lon_deg: float) -> str:
    """The time in the nautical zone of the longitude (UTC + round(lon / 15) h): the place's local time to
    within its daylight saving and political zone, known without a time-zone database."""
    if not math.isfinite(lon_deg):
        return "unknown (no position)"
    hours = int(round(lon_deg / 15.0))
    t = datetime.fromtimestamp(ns / NS, timezone(timedelta(hours=hours)))
    return t.strftime("%Y-%m-%d %H:%M:%S") + f" UTC{hours:+d} (nautical zone of longitude {lon_deg:.2f}°)"


def _size(n: int) -> str:
    return f"{n / 1e6:.1f} MB" if n >= 1e5 else f"{n / 1e3:.1f} kB"


def _thin(*xs: np.ndarray) -> tuple[np.ndarray, ...]:
    """Every k-th row of the arrays, at most MAX_POINTS rows."""
    k = max(1, -(-len(xs[0]) // MAX_POINTS))
    return tuple(np.asarray(x)[::k] for x in xs)


def _svg(fig) -> str:
    """A matplotlib Figure as inline SVG (text kept as text; the XML prologue dropped)."""
    import matplotlib

    buf = io.StringIO()
    with matplotlib.rc_context({"svg.fonttype": "none", "svg.hashsalt": "fieldlog"}):  # the same page each run
        fig.savefig(buf, format="svg", bbox_inches="tight", metadata={"Date": None})
    text = buf.getvalue()
    return text[text.index("<svg"):]


def _figure(rows: int, height: float = 2.0):
    """A matplotlib Figure with ``rows`` axes sharing the time axis (no pyplot: no global state, no display)."""
    from matplotlib.figure import Figure as MplFigure

    fig = MplFigure(figsize=(9.0, 0.6 + height * rows))
    axes = fig.subplots(rows, 1, sharex=True, squeeze=False)[:, 0]
    for ax in axes:
        ax.grid(True, alpha=0.3)
    return fig, list(axes)


def _shade(axes, windows: Sequence[tuple[float, float]], label: str | None = "GNSS outage") -> None:
    for ax in axes:
        for i, (a, b) in enumerate(windows):
            ax.axvspan(a, b, color=OUTAGE_COLOR, alpha=0.15, lw=0, label=label if i == 0 and ax is axes[0] else None)


def _windows_s(windows: Sequence[tuple[int, int]], t0: int) -> list[tuple[float, float]]:
    return [((a - t0) / NS, (b - t0) / NS) for a, b in windows]


def _merge(windows: list[tuple[int, int]]) -> list[tuple[int, int]]:
    out: list[tuple[int, int]] = []
    for a, b in sorted(windows):
        if out and a <= out[-1][1]:
            out[-1] = (out[-1][0], max(out[-1][1], b))
        else:
            out.append((a, b))
    return out


def gnss_outages(t_ns: np.ndarray, has_fix: np.ndarray, end_ns: int | None = None
                 ) -> list[tuple[int, int, str]]:
    """Windows [start, end) UTC ns without a fix in the GPS epochs t_ns (n,) with has_fix (n,): runs of no-fix
    epochs ("no fix", from the first no-fix epoch to the next fix) and silences (no epoch at all for more than 1.5
    nominal periods: "silence", from the last epoch to the next), merged where they touch; end_ns: the drive's
    end, which closes a run still open there."""
    if len(t_ns) < 2:
        return []
    period = float(np.median(np.diff(t_ns)))
    out: list[tuple[int, int, str]] = []
    fix_t = t_ns[has_fix]
    # silences: consecutive epochs further apart than 1.5 periods
    for i in np.flatnonzero(np.diff(t_ns) > 1.5 * period):
        out.append((int(t_ns[i]), int(t_ns[i + 1]), "silence"))
    # no-fix runs
    bad = ~has_fix
    edges = np.flatnonzero(np.diff(np.concatenate([[0], bad.astype(np.int8), [0]])))
    for a, b in zip(edges[::2], edges[1::2]):
        j = np.searchsorted(fix_t, t_ns[a], side="right")
        stop = int(fix_t[j]) if j < len(fix_t) else int(end_ns if end_ns is not None else t_ns[b - 1] + period)
        out.append((int(t_ns[a]), stop, "no fix"))
    out.sort()
    merged: list[tuple[int, int, str]] = []
    for a, b, why in out:
        if merged and a <= merged[-1][1]:
            pa, pb, pw = merged[-1]
            merged[-1] = (pa, max(pb, b), pw if pw == why else "no fix, silence")
        else:
            merged.append((a, b, why))
    return merged


def _enu(lat_deg: np.ndarray, lon_deg: np.ndarray, origin: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """East and north (m) of positions from the origin (deg), on the origin's tangent plane (local radii)."""
    lat0 = math.radians(origin[0])
    rm, rn = earth.principal_radii(lat0, 0.0)
    return (np.radians(lon_deg - origin[1]) * rn * math.cos(lat0), np.radians(lat_deg - origin[0]) * rm)


# -- the drive -------------------------------------------------------------------------------------------------


@dataclass
class Drive:
    """What the report reads of the drive: info (``fieldlog info``'s), the viewer's pass, the inputs."""

    spec: DriveSpec
    info: DriveInfo
    data: viewdata.DrivePass
    imap: inputs.InputMap | None
    input_note: str
    metadata: dict[str, dict[str, str]]
    records: list[tuple[str, dict[str, str]]]
    temperature: tuple[np.ndarray, np.ndarray] | None  # per-second means of the DAQ temperature (t_ns, deg C)

    @property
    def t0(self) -> int:
        return self.info.start_ns


def _daq_temperature(spec: DriveSpec, names: dict[str, int], progress: Callable[[float], None]
                     ) -> tuple[np.ndarray, np.ndarray] | None:
    """The DAQ board's temperature from the frames of ``/raw/daq`` (the only place it is recorded): per-second
    means against the reads' host times (UTC ns, deg C); None without raw DAQ bytes or without temperature."""
    if not names.get("/raw/daq"):
        return None
    dec = daq.DaqDecoder()
    t_out, x_out = [], []
    total = max(names["/raw/daq"], 1)
    done = 0
    for d in reader.iter_raw_batches(spec, "/raw/daq"):
        data = d["data"]
        frames = dec.feed(b"".join(data[i] for i in range(len(data))))
        temp = frames.temperature_c
        ok = np.isfinite(temp)
        if ok.any():
            # the batch's frames spread evenly over its reads' host times (a second's mean needs no better)
            t = np.linspace(int(d["log_time_ns"][0]), int(d["log_time_ns"][-1]), len(temp)).astype(np.int64)[ok]
            keys, idx = np.unique(t // NS, return_inverse=True)
            t_out.append(keys * NS)
            x_out.append(np.bincount(idx, temp[ok]) / np.bincount(idx))
        done += len(d["log_time_ns"])
        progress(min(done / total, 1.0))
    if not t_out:
        return None
    return np.concatenate(t_out), np.concatenate(x_out)


def read_drive(spec: DriveSpec, progress: Callable[[float], None]) -> Drive:
    """The drive's figures and the viewer's pass over it (``progress`` from 0 to 1)."""
    info = drive_info(spec, progress=lambda f: progress(0.1 * f))
    try:
        imap = inputs.resolve(spec)
        note = ", ".join(f"{k} {getattr(imap, k)}" for k in ("imu_topic", "fix_topic", "vel_topic", "imu_frame"))
    except ValueError as e:
        imap, note = None, f"not resolved: {e}"
    gen = viewdata.drive_pass(spec, lambda: imap)
    try:
        while True:
            progress(0.1 + 0.7 * next(gen))
    except StopIteration as stop:
        data = stop.value
    records = reader.read_metadata_records(spec)
    names = {t.topic: t.count for t in info.topics}
    temperature = _daq_temperature(spec, names, lambda f: progress(0.8 + 0.1 * f))
    return Drive(spec, info, data, imap, note, dict(records), records, temperature)


# -- sections --------------------------------------------------------------------------------------------------


def _fixes(d: Drive) -> dict[str, np.ndarray] | None:
    fix = d.data.low.get("/gps/fix")
    if fix is None or not len(fix["log_time_ns"]):
        return None
    ok = fix["valid"]
    return {k: v[ok] for k, v in fix.items()}


def _has_fix(fix: dict[str, np.ndarray]) -> np.ndarray:
    return (fix["status"] >= 0) & np.isfinite(fix["lat_deg"]) & np.isfinite(fix["lon_deg"])


def drive_section(d: Drive, findings: list[Finding]) -> Section:
    info = d.info
    s = Section("drive", "Drive")
    fix = _fixes(d)
    lon = math.nan
    distance = math.nan
    if fix is not None and _has_fix(fix).any():
        good = _has_fix(fix)
        lat_f, lon_f = fix["lat_deg"][good], fix["lon_deg"][good]
        lon = float(lon_f[0])
        e, n = _enu(lat_f, lon_f, (float(lat_f[0]), lon))
        distance = float(np.hypot(np.diff(e), np.diff(n)).sum())
    drv = d.metadata.get("drive", {})
    counters = info.counters
    frames = {k[len("gps.frames."):]: v for k, v in counters.items() if k.startswith("gps.frames.")}
    receiver = drv.get("gps_receiver") or d.metadata.get("gps", {}).get("protocol") or "not recorded"
    if frames:
        receiver += " (" + ", ".join(f"{v} {k} frames" for k, v in frames.items()) + ")"
    imu_topic = d.imap.imu_topic if d.imap is not None else "/imu"
    rate = next((t for t in info.topics if t.topic == imu_topic), None)
    imu = f"{imu_topic}, {rate.count} samples at {topic_rate(rate):.1f} Hz" if rate is not None and rate.count > 1 else (
        "no IMU topic")
    if "calibration" in d.metadata:
        imu += "; DAQ board with a calibration record"
    s.facts = [("duration", f"{info.duration_s:.1f} s"),
               ("distance", f"{distance / 1e3:.2f} km (between GNSS fixes)" if math.isfinite(distance)
                else "unknown (no fix)"),
               ("start", f"{_utc(info.start_ns)}; local {_local(info.start_ns, lon)}"),
               ("end", f"{_utc(info.end_ns)}; local {_local(info.end_ns, lon)}"),
               ("receiver", receiver), ("IMU", imu), ("inputs", d.input_note),
               ("source", ", ".join(f"{k}={v}" for k, v in drv.items()) or "not recorded"),
               ("messages", f"{info.message_total} in {info.chunks} chunks, compression "
                            f"{', '.join(c or 'none' for c in info.compression) or 'none'}")]
    s.tables.append((["file", "size"], [[str(f), _size(f.stat().st_size)] for f in info.files]
                     + [["total", _size(info.size_bytes)]]))
    events = []
    if len(info.files) > 1:
        events.append(["rotation", f"{len(info.files)} files read as one drive"])
    for name, rec in d.records:
        if name == "recover":
            events.append(["recovery", ", ".join(f"{k}={v}" for k, v in rec.items())])
        elif name == "rebuild":
            events.append(["rebuild", ", ".join(f"{k}={v}" for k, v in rec.items())])
    for ev in info.port_events:
        events.append([f"port {ev.get('port', '?')} {ev.get('event', '?')}", ev.get("detail", "")])
        if ev.get("event") == "lost":
            findings.append(Finding(f"port {ev.get('port', '?')} lost: {ev.get('detail', '')}", "drive"))
    s.tables.append((["event", "detail"], events or [["none", "one file, no recovery, no port lost"]]))
    s.tables.append((["topic", "type", "messages", "rate (Hz)"],
                     [[t.topic, t.type, str(t.count), f"{topic_rate(t):.2f}" if t.count > 1 else "-"]
                      for t in info.topics]))
    return s


def map_section(d: Drive, fused: list[FusedMethod]) -> Section:
    s = Section("map", "Map")
    fix = _fixes(d)
    truth = d.data.low.get("/truth/fix")
    if fix is None or not _has_fix(fix).any():
        s.nodata = "no GNSS fix in the drive (no /gps/fix topic, or no epoch with a fix)"
        return s
    good = _has_fix(fix)
    origin = (float(fix["lat_deg"][good][0]), float(fix["lon_deg"][good][0]))
    fig, (ax,) = _figure(1, 5.5)
    if truth is not None and len(truth["log_time_ns"]):
        e, n = _enu(*_thin(truth["lat_deg"], truth["lon_deg"]), origin)
        ax.plot(e, n, color="0.6", lw=1, label="truth")
    for m in fused:
        if m.track is not None:
            e, n = _enu(*_thin(m.track[1], m.track[2]), origin)
            ax.plot(e, n, lw=1, label=f"{m.label} (fused)")
    for status, name, color in FIX_TYPES:
        sel = good & (np.where(fix["status"] >= messages.STATUS_GBAS_FIX, messages.STATUS_GBAS_FIX, fix["status"])
                      == status)
        if sel.any():
            e, n = _enu(*_thin(fix["lat_deg"][sel], fix["lon_deg"][sel]), origin)
            ax.scatter(e, n, s=6, color=color, label=f"GNSS {name}", zorder=3)
    windows = [(a, b) for a, b, _ in gnss_outages(fix["log_time_ns"], good, d.info.end_ns)]
    for m in fused:
        windows += m.outages
    windows = _merge(windows)
    ref = (truth["log_time_ns"], truth["lat_deg"], truth["lon_deg"]) if truth is not None and len(
        truth["log_time_ns"]) else next((m.track for m in fused if m.track is not None), None)
    t_fix = fix["log_time_ns"][good]
    for i, (a, b) in enumerate(windows):
        if ref is not None:
            inside = (ref[0] >= a) & (ref[0] <= b)
            e, n = _enu(ref[1][inside], ref[2][inside], origin)
        else:  # no track through it: from the last fix before to the first after
            j = np.searchsorted(t_fix, a, side="right") - 1
            k = np.searchsorted(t_fix, b, side="left")
            sel = [x for x in (j, k) if 0 <= x < len(t_fix)]
            e, n = _enu(fix["lat_deg"][good][sel], fix["lon_deg"][good][sel], origin)
        ax.plot(e, n, color=OUTAGE_COLOR, lw=4, alpha=0.6, label="outage" if i == 0 else None, zorder=2)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.legend(loc="best", fontsize=8)
    s.figures.append(Figure(_svg(fig), f"Track in local ENU metres from the first fix ({origin[0]:.6f}°, "
                                       f"{origin[1]:.6f}°), coloured by fix type; outages in red. No map tiles: "
                                       "the page needs no network."))
    return s


def gnss_section(d: Drive, findings: list[Finding]) -> Section:
    s = Section("gnss", "GNSS quality")
    fix = _fixes(d)
    if fix is None:
        s.nodata = "no /gps/fix topic (nor a NavSatFix topic of another logger)"
        return s
    t = fix["log_time_ns"]
    good = _has_fix(fix)
    outs = gnss_outages(t, good, d.info.end_ns)
    x = (t - d.t0) / NS
    gga = d.data.gga
    rows = 3 if len(gga["log_time_ns"]) else 2
    fig, axes = _figure(rows)
    axes[0].step(*_thin(x, np.where(good, fix["status"], -1)), where="post", color="#1f77b4")
    axes[0].set_yticks([-1, 0, 1, 2], ["none", "fix", "SBAS", "RTK"])
    axes[0].set_ylabel("fix type")
    cov = fix.get("position_covariance")
    sigma = np.sqrt(np.maximum(cov[:, 0] + cov[:, 4], 0.0)) if cov is not None else np.full(len(t), np.nan)
    sigma[~good] = np.nan
    axes[1].plot(*_thin(x, sigma), color="#ff7f0e", lw=1)
    axes[1].set_ylabel("receiver σ horiz. (m)")
    if rows == 3:
        xg = (gga["log_time_ns"] - d.t0) / NS
        axes[2].step(*_thin(xg, gga["satellites"]), where="post", color="#2ca02c", label="satellites")
        ax2 = axes[2].twinx()
        ax2.step(*_thin(xg, gga["hdop"]), where="post", color="#8c564b", label="HDOP")
        axes[2].set_ylabel("satellites")
        ax2.set_ylabel("HDOP")
    _shade(axes, _windows_s([(a, b) for a, b, _ in outs], d.t0))
    axes[-1].set_xlabel(f"time from the drive start (s), {_utc(d.t0)}")
    s.figures.append(Figure(_svg(fig), "Fix type, the receiver's horizontal σ and, from GGA, satellites and HDOP "
                                       "against time; GNSS outages (no fix, or no epoch) shaded."))
    period = float(np.median(np.diff(t))) / NS if len(t) > 1 else math.nan
    s.facts = [("epochs", f"{len(t)}, every {period:.2f} s" if math.isfinite(period) else str(len(t))),
               ("with a fix", f"{int(good.sum())} ({100.0 * good.mean():.1f} %)"),
               ("missing epochs", str(d.info.gps_missing_epochs)),
               ("median receiver σ", f"{np.nanmedian(sigma):.2f} m" if np.isfinite(sigma).any() else "not given")]
    s.tables.append((["outage start", "length (s)", "kind"],
                     [[_utc(a), f"{(b - a) / NS:.1f}", why] for a, b, why in outs] or [["none", "", ""]]))
    for a, b, why in outs:
        if (b - a) / NS > LONG_OUTAGE_S:
            findings.append(Finding(f"GNSS outage of {(b - a) / NS:.1f} s ({why}) from {_utc(a)}", "gnss"))
    return s


def timesync_section(d: Drive, findings: list[Finding]) -> Section:
    s = Section("timesync", "Time sync")
    ts = d.data.low.get("/time/sync")
    counters = d.info.counters
    if ts is None or not len(ts["log_time_ns"]):
        s.nodata = "no /time/sync records: the drive's stamps are another logger's (or the host's)"
        return s
    ok = ts["valid"]
    t, state = ts["log_time_ns"][ok], ts["state"][ok]
    x = (t - d.t0) / NS
    fig, axes = _figure(3)
    axes[0].step(*_thin(x, state), where="post")
    axes[0].set_yticks([0, 1, 2], ["free", "holdover", "locked"])
    axes[1].plot(*_thin(x, ts["residual_us"][ok]), lw=1)
    axes[1].set_ylabel("fit residual (µs)")
    axes[2].plot(*_thin(x, ts["rate_ppm"][ok]), lw=1)
    axes[2].set_ylabel("rate error (ppm)")
    axes[-1].set_xlabel("time from the drive start (s)")
    s.figures.append(Figure(_svg(fig), "Clock state, the PPS fit's residual and the DAQ oscillator's rate error."))
    locked = state == messages.TIMESYNC_LOCKED
    first = int(np.argmax(locked)) if locked.any() else None
    after = float(locked[first:].mean()) if first is not None else 0.0
    edges, rejected = int(counters.get("pps_edges", 0) or 0), int(counters.get("pps_rejected", 0) or 0)
    s.facts = [("states", ", ".join(f"{k} {v * 100:.1f} %" for k, v in d.info.sync_states.items()) or "-"),
               ("first lock", f"{(t[first] - d.t0) / NS:.1f} s after the start" if first is not None else "never"),
               ("locked after the first lock", f"{after * 100:.1f} %"),
               ("DAQ clock rate", f"{d.info.rate_ppm:+.3f} ppm"), ("fit residual", f"{d.info.residual_us:.1f} µs"),
               ("PPS edges used / rejected", f"{edges - rejected} / {rejected}" if "pps_edges" in counters
                else "not counted")]
    if d.info.timing:
        tm = d.info.timing
        s.facts.append(("stamp error vs truth", f"RMS {tm.rms_us:.1f} µs, max {tm.max_abs_us:.1f} µs"))
    if first is None:
        findings.append(Finding("time sync never locked: every stamp is the host's", "timesync"))
    elif after < MIN_LOCKED:
        findings.append(Finding(f"time sync locked only {after * 100:.0f} % of the time after its first lock",
                                "timesync"))
    if edges and rejected / edges > MAX_REJECTED:
        findings.append(Finding(f"{rejected} of {edges} PPS edges rejected", "timesync"))
    return s


def imu_section(d: Drive, findings: list[Finding]) -> Section:
    s = Section("imu", "IMU")
    t, x = d.data.imu_t_ns, d.data.imu
    counters = d.info.counters
    if not len(t):
        s.nodata = "no IMU samples (no /imu topic, nor an Imu topic of another logger)"
        return s
    rel = (t - d.t0) / NS
    sec = np.floor(rel).astype(np.int64)
    keys, counts = np.unique(sec, return_counts=True)
    full = np.arange(keys[0], keys[-1] + 1)
    rate = np.zeros(len(full))
    rate[keys - keys[0]] = counts * viewdata.IMU_DECIMATION
    steps = np.diff(t)
    gap_at = np.flatnonzero(steps > 1.5 * np.median(steps)) if len(steps) else np.zeros(0, int)
    gaps = [(int(t[i]), int(t[i + 1])) for i in gap_at]
    rows = 4 if d.temperature is not None else 3
    fig, axes = _figure(rows)
    axes[0].step(full[1:-1], rate[1:-1], where="post")  # whole seconds only
    axes[0].set_ylabel("rate (Hz)")
    tt, xx = _thin(rel, x)
    axes[1].plot(tt, np.degrees(xx[:, 0:3]), lw=0.8)
    axes[1].set_ylabel("gyro (°/s)")
    axes[1].legend(["x", "y", "z"], fontsize=7, loc="upper right")
    axes[2].plot(tt, xx[:, 3:6], lw=0.8)
    axes[2].set_ylabel("accel (m/s²)")
    if d.temperature is not None:
        axes[3].plot((d.temperature[0] - d.t0) / NS, d.temperature[1], lw=1)
        axes[3].set_ylabel("DAQ temp. (°C)")
    _shade(axes, _windows_s(gaps, d.t0), "IMU gap")
    axes[-1].set_xlabel("time from the drive start (s)")
    s.figures.append(Figure(_svg(fig), f"Samples per second, and the rates and specific forces as means of "
                                       f"{viewdata.IMU_DECIMATION} samples (body RFU); gaps shaded."))
    sat = _saturated(d, x)
    s.facts = [("samples", f"{len(t) * viewdata.IMU_DECIMATION} (counted in groups of {viewdata.IMU_DECIMATION})"),
               ("median rate", f"{np.median(rate[1:-1]) if len(rate) > 2 else rate.mean():.1f} Hz"),
               ("gaps", f"{d.info.imu_gaps} (longest {d.info.imu_longest_gap_s:.3f} s)"),
               ("saturation", sat[0]),
               ("temperature", f"{np.nanmin(d.temperature[1]):.1f} to {np.nanmax(d.temperature[1]):.1f} °C"
                if d.temperature is not None else "not in the DAQ frames (or no raw DAQ bytes)")]
    daq_rows = [[k, v] for k, v in counters.items() if k.startswith("daq.")]
    s.tables.append((["DAQ counter", "value"], daq_rows or [["none", "no acquire.counters record"]]))
    if d.info.imu_gaps:
        findings.append(Finding(f"{d.info.imu_gaps} gap(s) in the IMU samples, the longest "
                                f"{d.info.imu_longest_gap_s:.3f} s", "imu"))
    for k, what in FAULT_COUNTERS.items():
        if int(float(counters.get(k, 0) or 0)):
            findings.append(Finding(f"{counters[k]} {what}", "imu"))
    if sat[1]:
        findings.append(Finding(f"IMU saturated: {sat[0]}", "imu"))
    return s


def _saturated(d: Drive, x: np.ndarray) -> tuple[str, int]:
    """Saturation from the drive's calibration: the 50 Hz means within FULL_SCALE of the ADC full scale
    (+-10 V through each axis's sensitivity and bias); (text, count)."""
    toml = d.metadata.get("calibration", {}).get("toml")
    if not toml:
        return "not known (no calibration record: the sensor's range is not in the drive)", 0
    cal = calib.Calibration.from_toml(toml)
    hi = np.concatenate([cal.gyro.to_si(np.full(3, 10.0)), cal.accel.to_si(np.full(3, 10.0))])
    lo = np.concatenate([cal.gyro.to_si(np.full(3, -10.0)), cal.accel.to_si(np.full(3, -10.0))])
    near = (x >= FULL_SCALE * hi) | (x <= FULL_SCALE * lo)
    n = int(near.any(axis=1).sum())
    return f"{n} of {len(x)} means at the full scale", n


def can_section(d: Drive, findings: list[Finding]) -> Section:
    s = Section("can", "CAN")
    counters = d.info.counters
    names = {t.topic: t for t in d.info.topics}
    line = bus_line(d.info)
    if line:
        s.facts.append(("bus", line[len("can"):].strip()))
    if not any(t.startswith("/vehicle/") or t == "/raw/can" for t in names):
        s.nodata = "no vehicle bus topics in the drive (/raw/can, /vehicle/*)"
        return s
    s.tables.append((["topic", "messages", "rate (Hz)"],
                     [[t, str(i.count), f"{topic_rate(i):.2f}" if i.count > 1 else "-"] for t, i in names.items()
                      if t == "/raw/can" or t.startswith("/vehicle/")]))
    tw = d.data.low.get("/vehicle/twist")
    if tw is not None and len(tw["log_time_ns"]):
        fig, (ax,) = _figure(1, 2.5)
        ok = tw["valid"]
        ax.plot(*_thin((tw["log_time_ns"][ok] - d.t0) / NS, tw["v_n"][ok, 0]), lw=1, label="wheels (CAN)")
        vel = d.data.low.get("/gps/vel")
        if vel is not None and len(vel["log_time_ns"]):
            okv = vel["valid"]
            ax.plot(*_thin((vel["log_time_ns"][okv] - d.t0) / NS, np.hypot(vel["v_n"][okv, 0], vel["v_n"][okv, 1])),
                    lw=1, label="GNSS speed")
        ax.set_ylabel("speed (m/s)")
        ax.set_xlabel("time from the drive start (s)")
        ax.legend(fontsize=8)
        s.figures.append(Figure(_svg(fig), "Decoded forward speed from the wheels against the GNSS speed."))
    errors = {k: int(float(counters.get(f"can.{k}", 0) or 0)) for k in CAN_ERRORS}
    if any(errors.values()):
        findings.append(Finding("CAN errors: " + ", ".join(f"{k} {v}" for k, v in errors.items() if v), "can"))
    return s


# -- fused solutions -------------------------------------------------------------------------------------------


@dataclass
class FusedMethod:
    label: str
    method: str
    path: Path
    track: tuple[np.ndarray, np.ndarray, np.ndarray] | None  # t_ns, lat, lon (deg)
    outages: list[tuple[int, int]]
    injected: list[tuple[int, int]]


def discover(fused: Sequence[str | os.PathLike[str]]) -> list[FusedMethod]:
    """Every ``/fusion/<method>/fix`` of the fused files (a method seen twice is labelled with its file)."""
    out: list[FusedMethod] = []
    seen: set[str] = set()
    for p in fused:
        tops = [t for t in reader.topic_counts(p) if t.count]
        windows, injected = [], []
        if any(t.topic == solutions.OUTAGE for t in tops):
            for m in reader.read_topic(p, solutions.OUTAGE)["msgs"]:
                if m is not None:
                    windows.append((int(m.start_ns), int(m.end_ns)))
                    if m.reason == "injected":
                        injected.append((int(m.start_ns), int(m.end_ns)))
        for t in tops:
            method = solutions.method_of(t.topic)
            if method is None:
                continue
            lab = method if method not in seen else f"{method}@{Path(p).stem}"
            seen.add(method)
            f = solutions.read(p, method, "fix")
            ok = f["valid"]
            track = (f["log_time_ns"][ok], f["lat_deg"][ok], f["lon_deg"][ok]) if ok.any() else None
            out.append(FusedMethod(lab, method, Path(p), track, windows, injected))
    return out


def method_section(d: Drive, m: FusedMethod, findings: list[Finding]) -> Section:
    sid = "fusion-" + re.sub(r"[^A-Za-z0-9_-]", "-", m.label)
    s = Section(sid, f"{m.label} ({m.path.name})")
    names = {t.topic for t in reader.topic_counts(m.path) if t.count}
    has = {n: solutions.topic(m.method, n) in names for n in (solutions.STATUS, "std", "attitude_std")}
    rows = max(1, sum(has.values()))
    fig, axes = _figure(rows)
    i = 0
    if has[solutions.STATUS]:
        st = solutions.read(m.path, m.method, solutions.STATUS)
        ok = st["valid"]
        t, code = st["log_time_ns"][ok], st["status"][ok]
        axes[i].step(*_thin((t - d.t0) / NS, code), where="post")
        axes[i].set_yticks(range(len(fusion_output.STATUS)), fusion_output.STATUS)
        i += 1
        shares = ", ".join(f"{n} {100.0 * np.mean(code == c):.1f} %" for c, n in enumerate(fusion_output.STATUS)
                           if (code == c).any())
        s.facts.append(("status", shares))
        since = st["since_update_s"][ok]
        if np.isfinite(since).any():
            s.facts.append(("longest without a GNSS update", f"{np.nanmax(since):.1f} s"))
        dt = np.diff(t, append=t[-1]) / NS if len(t) else np.zeros(0)
        for c, what in ((fusion_output.DIVERGED, "diverged"), (fusion_output.DEGRADED, "degraded")):
            if (code == c).any():
                first = int(t[np.argmax(code == c)])
                findings.append(Finding(f"{m.label}: {what} for {dt[code == c].sum():.1f} s, first at {_utc(first)}",
                                        sid))
    else:
        s.facts.append(("status", "no status topic in this fused file"))
    sd = solutions.read(m.path, m.method, "std") if has["std"] else None
    if sd is not None:
        ok = sd["valid"]
        axes[i].plot(*_thin((sd["log_time_ns"][ok] - d.t0) / NS, sd["xyz"][ok]), lw=1)
        axes[i].legend(["east", "north", "up"], fontsize=7, loc="upper right")
        axes[i].set_ylabel("position σ (m)")
        i += 1
    if has["attitude_std"]:
        a = solutions.read(m.path, m.method, "attitude_std")
        ok = a["valid"]
        axes[i].plot(*_thin((a["log_time_ns"][ok] - d.t0) / NS, np.degrees(a["xyz"][ok])), lw=1)
        axes[i].legend(["φ east", "φ north", "φ up (heading)"], fontsize=7, loc="upper right")
        axes[i].set_ylabel("attitude σ (°)")
    _shade(axes, _windows_s(_merge(list(m.outages)), d.t0))
    axes[-1].set_xlabel("time from the drive start (s)")
    s.figures.append(Figure(_svg(fig), "Solution status, position and attitude σ; the fused file's outage windows "
                                       "shaded."))
    _errors(d, m, s)
    return s


def _errors(d: Drive, m: FusedMethod, s: Section) -> None:
    """Position errors against the truth (every row), or against the withheld GNSS inside the injected outages."""
    from fieldlog.tools.evaluation.evaluate import outage_error_series

    names = {t.topic for t in d.info.topics if t.count}
    if m.track is None:
        return
    if "/truth/fix" in names:
        windows, against = [(int(m.track[0][0]), int(m.track[0][-1]) + 1)], "the truth"
    elif m.injected and d.imap is not None:
        windows, against = m.injected, "the withheld GNSS fixes"
    else:
        s.facts.append(("errors", "no truth and no GNSS withheld (fuse --outage): no reference"))
        return
    kw = {} if d.imap is None else {"fix_topic": d.imap.fix_topic, "vel_topic": d.imap.vel_topic}
    t, e = outage_error_series(d.spec, m.path, m.method, windows, **kw)
    if not len(t):
        s.facts.append(("errors", f"no rows against {against}"))
        return
    horiz = np.hypot(e[:, 0], e[:, 1])
    fig, (ax,) = _figure(1, 2.5)
    x = (t - d.t0) / NS
    ax.plot(*_thin(x, horiz), lw=1, label="horizontal")
    ax.plot(*_thin(x, np.abs(e[:, 2])), lw=1, label="|vertical|")
    ax.set_ylabel("position error (m)")
    ax.set_xlabel("time from the drive start (s)")
    ax.legend(fontsize=8)
    s.figures.append(Figure(_svg(fig), f"Position error against {against}."))
    s.facts.append(("errors", f"against {against}: horizontal RMS {np.sqrt(np.nanmean(horiz ** 2)):.2f} m, max "
                              f"{np.nanmax(horiz):.2f} m; vertical RMS {np.sqrt(np.nanmean(e[:, 2] ** 2)):.2f} m"))


def fusion_section(d: Drive, methods: list[FusedMethod], findings: list[Finding]) -> Section:
    s = Section("fusion", "Fused solutions")
    if not methods:
        s.nodata = "no fused file given (fieldlog fuse DRIVE --out FUSED.mcap, then report DRIVE FUSED)"
        return s
    s.parts = [method_section(d, m, findings) for m in methods]
    return s


# -- the page --------------------------------------------------------------------------------------------------


def _guarded(sid: str, title: str, build: Callable[[], Section]) -> Section:
    """A section, or one saying "no data" with the reason when the drive cannot give it (damaged or foreign
    topics): one bad topic never costs the whole report."""
    try:
        return build()
    except (KeyError, ValueError, IndexError) as e:
        return Section(sid, title, nodata=f"could not be read: {e}")


def render(sections: list[Section], findings: list[Finding], title: str) -> str:
    """The page: the template filled (every value HTML-escaped, the SVGs as they are)."""
    import jinja2

    env = jinja2.Environment(autoescape=True, undefined=jinja2.StrictUndefined, trim_blocks=True,
                             lstrip_blocks=True)
    template = env.from_string((resources.files("fieldlog.tools") / "templates" / "report.html.j2").read_text())
    return template.render(title=title, sections=sections, findings=findings,
                           generated=datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"))


def report(drive: DriveSpec, fused: Sequence[str | os.PathLike[str]], out: str | os.PathLike[str],
           progress: Callable[[float], None] | None = None, force: bool = False) -> ReportResult:
    """Write the report of ``drive`` and its ``fused`` files to ``out`` (HTML; new unless ``force``)."""
    outputs.check_new(out, force)
    for p in fused:
        if not Path(p).is_file():
            raise FileNotFoundError(f"{p} does not exist")
    step = progress or (lambda f: None)
    d = read_drive(drive, lambda f: step(0.9 * f))
    methods = discover(fused)
    findings: list[Finding] = []
    builders = {"drive": lambda: drive_section(d, findings), "map": lambda: map_section(d, methods),
                "gnss": lambda: gnss_section(d, findings), "timesync": lambda: timesync_section(d, findings),
                "imu": lambda: imu_section(d, findings), "can": lambda: can_section(d, findings),
                "fusion": lambda: fusion_section(d, methods, findings)}
    sections = [_guarded(sid, title, builders[sid]) for sid, title in SECTIONS if sid != "verdict"]
    step(0.97)
    html = render(sections, findings, f"fieldlog report: {label(drive)}")
    outputs.write_bytes(out, html.encode("utf-8"), force)
    step(1.0)
    return ReportResult(Path(out), findings, ["verdict"] + [s.id for s in sections],
                        [m.label for m in methods])
