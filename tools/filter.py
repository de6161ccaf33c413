"""``fieldlog filter DRIVE... --start S --end S --topics T,... --out OUT``: a slice of a drive (one file or several,
a session or rosbag2 directory: ``drive.files``) into one file, as ``mcap filter``.

Messages with ``start <= log_time < end`` on the chosen topics are copied as they are (payload, log and publish
time, schema and channel records with their ids and ``offered_qos_profiles``), chunk by chunk; the metadata
records are copied too, plus a ``filter`` record naming the source and the slice. ``/tf_static`` is kept whatever
the slice (it is written once, at the start of a file, and a slice without it cannot be placed). The
``fieldlog.info`` record is recomputed for the slice, so ``fieldlog info`` on it stays fast.

Times: seconds from the drive's first IMU sample (``120``; ``-60``: from its end), the origin ``fuse --outage``
counts from too (a drive without an IMU topic: from its first message), an ISO 8601 UTC time
(``2026-05-04T09:32:00Z``) or UTC nanoseconds (``1777887120000000000``). The IMU topic is found as ``fuse`` finds
it without options (``replay.inputs.detect``: ``/imu``, else the only ``sensor_msgs/msg/Imu`` topic).
"""
from __future__ import annotations

import datetime as _dt
import fnmatch
import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np

from fieldlog.drive import messages, outputs
from fieldlog.drive.drivestats import RECORD as INFO_RECORD
from fieldlog.drive.recorder import Recorder
from fieldlog.drive.records import Channel, Schema
from fieldlog.drive import reader
from fieldlog.drive.files import DriveSpec, drive_files, open_drive
from fieldlog.replay.inputs import NATIVE, detect
from fieldlog.drive.mcapfile import McapFile

NS = 1_000_000_000


@dataclass
class FilterResult:
    path: Path
    messages: dict[str, int]
    start_ns: int
    end_ns: int


def parse_time(text: str, origin_ns: int, last_ns: int) -> int:
    """A ``--start``/``--end`` value -> UTC ns (see the module docstring): seconds count from ``origin_ns``
    (the first IMU sample), negative ones from ``last_ns``."""
    t = text.strip()
    try:
        if t.lstrip("-").isdigit() and abs(int(t)) >= 10**17:
            return int(t)
        s = float(t)
    except ValueError:
        try:
            d = _dt.datetime.fromisoformat(t.replace("Z", "+00:00"))
        except ValueError:
            raise ValueError(f"time {text!r}: expected seconds from the start (e.g. 120), an ISO UTC time "
                             f"(2026-05-04T09:32:00Z) or UTC ns") from None
        if d.tzinfo is None:
            d = d.replace(tzinfo=_dt.timezone.utc)
        return int(round(d.timestamp() * NS))
    return int(round(s * NS)) + (origin_ns if s >= 0 else last_ns + 1)


def select_topics(available: list[str], patterns: list[str] | None) -> list[str]:
    """Topics matching any pattern (exact names or shell patterns such as ``/fusion/*``); all without patterns."""
    if not patterns:
        return list(available)
    unmatched = [p for p in patterns if not fnmatch.filter(available, p)]
    if unmatched:
        raise ValueError(f"no topic matches {', '.join(unmatched)} (topics: {', '.join(available)})")
    return [t for t in available if any(fnmatch.fnmatchcase(t, p) for p in patterns)]


def filter_drive(src: DriveSpec, out: str | os.PathLike[str], start: str | None = None,
                 end: str | None = None, topics: list[str] | None = None,
                 progress: Callable[[float], None] | None = None, force: bool = False) -> FilterResult:
    """``src`` (a drive of one or several files, ``drive.files``) sliced into ``out`` (module docstring). Several
    files: one output, their messages file by file in the drive's order, each topic on one channel (the first
    file's record; renumbered if its id is taken), the metadata records by name as the drive reads them."""
    out = Path(out)
    src = drive_files(src)  # resolved once: the output may land in the drive's directory
    if any(out.resolve() == f.resolve() for f in src):
        raise ValueError("--out must differ from the drive")
    outputs.check_new(out, force)
    files = open_drive(src)
    for f in files:
        f.channel_stats()  # also defines the channels written only inside chunks
    infos = [t for t in reader.topics(src) if t.count]
    first = min((t.first_ns for t in infos), default=0)
    last = max((t.last_ns for t in infos), default=0)
    imu = detect(infos, messages.IMU, NATIVE[0])
    origin = next(t.first_ns for t in infos if t.topic == imu) if imu else first
    t0 = parse_time(start, origin, last) if start else first
    t1 = parse_time(end, origin, last) if end else last + 1
    if t1 <= t0:
        raise ValueError(f"--end ({t1} ns) must be after --start ({t0} ns)")
    channels = _channels(files)
    chosen = select_topics(list(channels), topics)
    if "/tf_static" in channels and "/tf_static" not in chosen:
        chosen.insert(0, "/tf_static")
    counts: dict[str, int] = {}
    with Recorder(out, flush_interval_s=None, fsync=False, force=force, behind=True) as rec:
        for name, d in reader.read_metadata(src).items():  # by name, the last wins
            if name != INFO_RECORD:
                rec.add_metadata(name, d)
        rec.add_metadata("filter", {"source": " ".join(str(f.path.resolve()) for f in files), "start_ns": str(t0),
                                    "end_ns": str(t1), "topics": ",".join(chosen)})
        for topic in chosen:
            schema, ch = channels[topic]
            if schema is not None:
                rec.register(schema)
            rec.register(ch)

        def latched(f: McapFile) -> list[int]:
            return [c for c, ch in f.channels.items() if ch.topic == "/tf_static"]

        def wanted(f: McapFile) -> np.ndarray:
            p = f.pieces
            return (p.end_ns >= t0) & (p.start_ns < t1) | f.may_hold(latched(f)) & bool(latched(f))

        groups = list(reader.piece_groups(files, chosen, file_order=True, keep=wanted))
        for i, (f, group) in enumerate(groups):
            cm = f.read(group, chosen)
            sel = cm.select((cm.log_time >= t0) & (cm.log_time < t1) | np.isin(cm.channel_id, latched(f)))
            for cid in np.unique(sel.channel_id).tolist():
                part = sel.select(sel.channel_id == cid)
                topic = f.channels[cid].topic
                rec.write_channel(channels[topic][1].id, part.log_time, part.packed(), part.publish_time)
                counts[topic] = counts.get(topic, 0) + len(part.log_time)
            if progress:
                progress((i + 1) / len(groups))
    order = list(channels)
    return FilterResult(out, {t: counts[t] for t in sorted(counts, key=order.index)}, t0, t1)


def _channels(files: list[McapFile]) -> dict[str, tuple[Schema | None, Channel]]:
    """Per topic (in the order of their channel ids in the first file that has them), the schema and channel
    records to write: the first file's, with ids that are free (a later file's clashing id renumbered)."""
    out: dict[str, tuple[Schema | None, Channel]] = {}
    schemas: dict[tuple, Schema] = {}
    for f in files:
        for cid, ch in sorted(f.channels.items()):
            if ch.topic in out:
                continue
            s = f.schemas.get(ch.schema_id)
            if s is not None:
                key = (s.name, s.encoding, s.data)
                if key not in schemas:
                    sid = s.id if s.id not in {x.id for x in schemas.values()} else \
                        max(x.id for x in schemas.values()) + 1
                    schemas[key] = replace(s, id=sid)
                s = schemas[key]
            used = {c.id for _, c in out.values()}
            out[ch.topic] = (s, replace(ch, id=cid if cid not in used else max(used) + 1,
                                        schema_id=s.id if s is not None else ch.schema_id))
    return out
