"""``fieldlog info``: what a drive holds and how good its timing is.

Fast path: the summary (channels, statistics) and the metadata records, among them ``fieldlog.info``, which the
recorder writes at close (``drive.drivestats``): no message is read, so an hour-long drive answers in about
a second. A file without that record (recovered, or written by another tool) is scanned: the topics' message
indexes and the /imu, /gps/fix, /time/sync and /truth/imu messages, through the same functions. A drive of
several files (a rotated session, a rosbag2 directory: ``drive.files``) is scanned as one drive.
"""
from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from fieldlog.drive import drivestats, messages, metavalue
from fieldlog.drive.drivestats import Quality
from fieldlog.drive import reader
from fieldlog.replay import inputs
from fieldlog.drive.files import DriveSpec, drive_files, open_drive

NS = 1_000_000_000


@dataclass
class DriveInfo(Quality):
    path: Path = Path()
    duration_s: float = 0.0
    topics: list[reader.TopicInfo] = field(default_factory=list)
    counters: dict[str, str] = field(default_factory=dict)
    drive: dict[str, str] = field(default_factory=dict)
    port_events: list[dict[str, str]] = field(default_factory=list)   # the daemon's lost/back port records
    scanned: bool = False       # figures from reading the messages (no fieldlog.info record)
    files: list[Path] = field(default_factory=list)   # the drive's files (drive.files)
    # what `ros2 bag info` shows too: bytes on disk, first and last log time (UTC ns), messages, chunks and their
    # compression ("" = none; several when the files differ)
    size_bytes: int = 0
    start_ns: int = 0
    end_ns: int = 0
    message_total: int = 0
    chunks: int = 0
    compression: list[str] = field(default_factory=list)

    def to_json(self) -> str:
        d = asdict(self)
        d["path"] = str(self.path.resolve())
        d["files"] = [str(f.resolve()) for f in self.files]
        d["topics"] = [dict(asdict(t), rate_hz=topic_rate(t)) for t in self.topics]
        return json.dumps(_nan_to_none(d), indent=2)


def _nan_to_none(d):
    """NaN (a figure the drive cannot give) as JSON null."""
    if isinstance(d, float):
        return d if np.isfinite(d) else None
    if isinstance(d, dict):
        return {k: _nan_to_none(v) for k, v in d.items()}
    if isinstance(d, list):
        return [_nan_to_none(v) for v in d]
    return d


def topic_rate(t: reader.TopicInfo) -> float:
    """A topic's mean message rate over its span, Hz (0 with fewer than two messages)."""
    span = (t.last_ns - t.first_ns) / NS
    return (t.count - 1) / span if t.count > 1 and span > 0 else 0.0


def _spans(rec: dict[str, str]) -> dict[str, tuple[int, int]] | None:
    """The record's per-topic (first, last) log times; None when one is damaged (the file is scanned)."""
    try:
        out = {}
        for k, v in rec.items():
            if k.startswith("span."):
                out[k[len("span."):]] = metavalue.wholes(metavalue.load(v), k, 2)
        return out
    except ValueError:
        return None


def _summary_topics(path: Path, spans: dict[str, tuple[int, int]]) -> list[reader.TopicInfo] | None:
    """Topics from the message indexes' counts and the record's per-topic spans; None when a topic has no span
    or a chunk no message index."""
    (f,) = open_drive(path)
    counts = f.message_counts()
    if counts is None:
        return None
    out = []
    for cid, ch in sorted(f.channels.items()):
        n = counts.get(cid, 0)
        span = spans.get(ch.topic)
        if span is None and n:
            return None
        out.append(reader.TopicInfo(ch.topic, f.type_of(cid), n, *(span or (0, 0))))
    return out


def scan_quality(path: DriveSpec, topics: list[reader.TopicInfo],
                 progress: Callable[[float], None] | None = None) -> Quality:
    """The figures of ``Quality`` from reading the messages (a file without a ``fieldlog.info`` record)."""
    by = {t.topic: t for t in topics if t.count}
    # another logger's drive: its only Imu and NavSatFix topics (replay.inputs.detect), read as /imu, /gps/fix
    names = {t: n for t, n in ((inputs.detect(topics, messages.IMU, "/imu"), "/imu"),
                               (inputs.detect(topics, messages.NAVSATFIX, "/gps/fix"), "/gps/fix")) if t}
    todo = [t for t in ("/time/sync", "/truth/imu") if t in by] + list(names)
    data = {}
    for i, topic in enumerate(todo):
        data[names.get(topic, topic)] = reader.read_topic(path, topic)
        if progress:
            progress((i + 1) / len(todo))
    stats = drivestats.DriveStats()   # the recorder's accumulators; truth before /imu, as the writers order them
    if "/time/sync" in data:
        stats.sync(*(np.asarray(data["/time/sync"][k]) for k in ("stamp_ns", "state", "rate_ppm", "residual_us")))
    if "/truth/imu" in data:
        stats.truth(np.asarray(data["/truth/imu"]["stamp_ns"]))
    if "/imu" in data:
        stats.imu(np.asarray(data["/imu"]["stamp_ns"]))
    if "/gps/fix" in data:
        stats.fix(np.asarray(data["/gps/fix"]["stamp_ns"]), np.asarray(data["/gps/fix"]["status"]))
    return stats.quality()


def drive_info(path: DriveSpec, scan: bool = False, progress: Callable[[float], None] | None = None) -> DriveInfo:
    """What ``fieldlog info`` prints. ``scan``: read the messages even when the ``fieldlog.info`` record is there.
    ``path``: one MCAP, several files, a session or rosbag2 directory (``drive.files``)."""
    files = drive_files(path)
    records = reader.read_metadata_records(path)
    meta = dict(records)
    rec = meta.get(drivestats.RECORD) if len(files) == 1 else None  # its figures are per file: a session is scanned
    quality = tops = None
    if rec is not None and not scan:
        spans = _spans(rec)
        quality = drivestats.quality_from_record(rec)
        tops = None if spans is None else _summary_topics(files[0], spans)
    scanned = quality is None or tops is None
    if tops is None:
        tops = reader.topics(path)
    if quality is None:
        quality = scan_quality(path, tops, progress)
    first = min((t.first_ns for t in tops if t.count), default=0)
    last = max((t.last_ns for t in tops if t.count), default=0)
    given = Path(path) if isinstance(path, (str, os.PathLike)) else Path(path[0])
    opened = open_drive(path)
    comps = sorted({f.compressions[i] for f in opened for i in set(f.pieces.comp[f.pieces.chunk].tolist())})
    return DriveInfo(**asdict(quality) | {"timing": quality.timing}, path=given, duration_s=(last - first) / NS,
                     topics=tops, counters=meta.get("acquire.counters", {}), drive=meta.get("drive", {}),
                     port_events=[d for name, d in records if name == "acquire.port_event"], scanned=scanned,
                     files=[f.path for f in opened], size_bytes=sum(f.path.stat().st_size for f in opened),
                     start_ns=first, end_ns=last, message_total=sum(t.count for t in tops),
                     chunks=sum(int(f.pieces.chunk.sum()) for f in opened), compression=comps)


def _utc(ns: int) -> str:
    """UTC ns as ISO 8601 with ms, e.g. 2026-11-22T10:15:00.000Z."""
    return np.datetime_as_string(np.datetime64(int(ns), "ns"), unit="ms") + "Z"


def format_info(info: DriveInfo) -> str:
    lines = [f"drive     {info.path}", f"duration  {info.duration_s:.1f} s",
             f"start     {_utc(info.start_ns)}   end {_utc(info.end_ns)}",
             f"size      {info.size_bytes / 1e6:.1f} MB ({info.size_bytes} bytes); {info.message_total} messages in "
             f"{info.chunks} chunks, compression {', '.join(c or 'none' for c in info.compression) or 'none'}"]
    if len(info.files) > 1:
        lines.insert(1, f"files     {len(info.files)}: " + ", ".join(f.name for f in info.files))
    if info.drive:
        lines.append("source    " + ", ".join(f"{k}={v}" for k, v in info.drive.items()))
    lines.append("")
    lines.append(f"{'topic':<22} {'type':<46} {'count':>9} {'rate Hz':>9}")
    for t in info.topics:
        lines.append(f"{t.topic:<22} {t.type:<46} {t.count:>9} {topic_rate(t):>9.2f}")
    lines.append("")
    if info.sync_states:
        states = ", ".join(f"{k} {v * 100:.1f} %" for k, v in info.sync_states.items())
        lines.append(f"time sync {states}; DAQ clock {info.rate_ppm:+.3f} ppm; fit residual {info.residual_us:.1f} us")
    else:
        lines.append("time sync no /time/sync records")
    if info.timing:
        t = info.timing
        lines.append(f"timestamp error vs truth after first lock: RMS {t.rms_us:.2f} us, max {t.max_abs_us:.2f} us, "
                     f"mean {t.mean_us:+.2f} us over {t.samples} samples")
    lines.append(f"gaps      IMU {info.imu_gaps} (longest {info.imu_longest_gap_s:.3f} s); "
                 f"GPS epochs missing {info.gps_missing_epochs}, without fix {info.gps_no_fix}")
    for ev in info.port_events:
        lines.append("port      " + ", ".join(f"{k}={v}" for k, v in ev.items()))
    if info.counters:
        keys = ["daq.bytes_skipped", "daq.resyncs", "daq.bad_crc", "daq.counter_gaps", "daq.lost_frames",
                "daq.repeated", "nmea.bad_checksum", "nmea.unknown", "nmea.proprietary", "pps_edges", "pps_rejected",
                "pps_implausible", "daemon.derived_dropped_reads"]
        shown = [f"{k}={info.counters[k]}" for k in keys if k in info.counters]
        lines.append("counters  " + ", ".join(shown))
        src = {k.rsplit(".", 1)[1]: v for k, v in info.counters.items() if k.startswith("nmea.position_from.")}
        if src or "nmea.gll_ignored" in info.counters:
            lines.append("NMEA      positions from " + ", ".join(f"{k} {v}" for k, v in src.items())
                         + " (GGA first, then RMC, then GLL); GGA and RMC of different seconds: "
                         + f"{info.counters.get('nmea.split_seconds', '0')} times, each second its own epoch; "
                         + f"GLL not used (the receiver sends GGA/RMC): {info.counters.get('nmea.gll_ignored', '0')}")
    bus = bus_line(info)
    if bus:
        lines.append(bus)
    return "\n".join(lines)


def bus_line(info: DriveInfo) -> str:
    """The vehicle bus in one line (``acquire/canbus.py`` counters): frames, ids, errors, decoded rates."""
    c = info.counters
    if "can.frames" not in c:
        return ""
    ids = sorted(((int(v), k[len("can.id."):]) for k, v in c.items() if k.startswith("can.id.")), reverse=True)
    top = ", ".join(f"{name} {n}" for n, name in ids[:6]) + (", ..." if len(ids) > 6 else "")
    errors = {k: c.get(f"can.{k}", "0") for k in ("error_frames", "bus_off", "status_errors", "overruns", "refused",
                                                   "bad_records", "bytes_discarded", "decode_errors")}
    rates = {t.topic: topic_rate(t) for t in info.topics if t.topic.startswith("/vehicle/")}
    decoded = ", ".join(f"{topic} {r:.1f} Hz" for topic, r in rates.items()) or "none (no DBC signals)"
    return (f"can       {c['can.frames']} frames, {c.get('can.ids', '0')} ids ({top}); errors "
            + ", ".join(f"{k} {v}" for k, v in errors.items()) + f"; decoded {decoded}")
