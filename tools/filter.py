"""``fieldlog filter DRIVE --start S --end S --topics T,... --out OUT``: a slice of a drive, as ``mcap filter``.

Messages with ``start <= log_time < end`` on the chosen topics are copied as they are (payload, log and publish
time, schema and channel records with their ids and ``offered_qos_profiles``), chunk by chunk; the metadata
records are copied too, plus a ``filter`` record naming the source and the slice. ``/tf_static`` is kept whatever
the slice (it is written once, at the start of a file, and a slice without it cannot be placed). The
``fieldlog.info`` record is recomputed for the slice, so ``fieldlog info`` on it stays fast.

Times: seconds from the drive's first message (``120``, ``-60`` from its end), an ISO 8601 UTC time
(``2026-05-04T09:32:00Z``) or UTC nanoseconds (``1777887120000000000``).
"""
from __future__ import annotations

import datetime as _dt
import fnmatch
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from fieldlog.acquire.drivestats import RECORD as INFO_RECORD
from fieldlog.acquire.recorder import Recorder
from fieldlog.replay import reader
from fieldlog.replay.drive import open_drive
from fieldlog.replay.mcapfile import McapFile

NS = 1_000_000_000


@dataclass
class FilterResult:
    path: Path
    messages: dict[str, int]
    start_ns: int
    end_ns: int


def parse_time(text: str, first_ns: int, last_ns: int) -> int:
    """A ``--start``/``--end`` value -> UTC ns (see the module docstring)."""
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
    return int(round(s * NS)) + (first_ns if s >= 0 else last_ns + 1)


def select_topics(available: list[str], patterns: list[str] | None) -> list[str]:
    """Topics matching any pattern (exact names or shell patterns such as ``/fusion/*``); all without patterns."""
    if not patterns:
        return list(available)
    unmatched = [p for p in patterns if not fnmatch.filter(available, p)]
    if unmatched:
        raise ValueError(f"no topic matches {', '.join(unmatched)} (topics: {', '.join(available)})")
    return [t for t in available if any(fnmatch.fnmatchcase(t, p) for p in patterns)]


def filter_drive(src: str | os.PathLike[str], out: str | os.PathLike[str], start: str | None = None,
                 end: str | None = None, topics: list[str] | None = None,
                 progress: Callable[[float], None] | None = None) -> FilterResult:
    src, out = Path(src), Path(out)
    if out.resolve() == src.resolve():
        raise ValueError("--out must differ from the drive")
    (f,) = files = open_drive(src)
    stats = f.channel_stats()  # also defines the channels written only inside chunks
    metadata = reader.metadata_records(src)
    first = min((lo for _, lo, _ in stats.values()), default=0)
    last = max((hi for _, _, hi in stats.values()), default=0)
    t0 = parse_time(start, first, last) if start else first
    t1 = parse_time(end, first, last) if end else last + 1
    if t1 <= t0:
        raise ValueError(f"--end ({t1} ns) must be after --start ({t0} ns)")
    by_topic = {ch.topic: cid for cid, ch in f.channels.items()}
    chosen = select_topics(sorted(by_topic, key=lambda t: by_topic[t]), topics)
    if "/tf_static" in by_topic and "/tf_static" not in chosen:
        chosen.insert(0, "/tf_static")
    cids = {by_topic[t] for t in chosen}
    latched = {by_topic[t] for t in chosen if t == "/tf_static"}
    counts: dict[int, int] = {}
    with Recorder(out, flush_interval_s=None, fsync=False) as rec:
        for name, d in metadata:
            if name != INFO_RECORD:
                rec.add_metadata(name, d)
        rec.add_metadata("filter", {"source": str(src.resolve()), "start_ns": str(t0), "end_ns": str(t1),
                                    "topics": ",".join(chosen)})
        for cid in sorted(cids):
            ch = f.channels[cid]
            rec.add_schema(f.schemas[ch.schema_id])
            rec.add_channel(ch)

        def wanted(f: McapFile) -> np.ndarray:
            p = f.pieces
            return (p.end_ns >= t0) & (p.start_ns < t1) | (f.may_hold(latched) if latched else False)

        groups = list(reader.piece_groups(files, chosen, file_order=True, keep=wanted))
        for i, (f, group) in enumerate(groups):
            cm = f.read(group, chosen)
            keep = np.isin(cm.channel_id, list(cids)) & (cm.log_time >= t0) & (cm.log_time < t1)
            keep |= np.isin(cm.channel_id, list(latched))
            sel = cm.select(keep)
            for cid in np.unique(sel.channel_id).tolist():
                part = sel.select(sel.channel_id == cid)
                rec.write_channel(cid, part.log_time, part.packed(), part.publish_time)
                counts[cid] = counts.get(cid, 0) + len(part.log_time)
            if progress:
                progress((i + 1) / len(groups))
    return FilterResult(out, {f.channels[c].topic: n for c, n in sorted(counts.items())}, t0, t1)
