"""``fieldlog rebuild``: re-derive every topic of a drive from its ``/raw/*`` reads (a drive of several files,
e.g. a rotated session, is rebuilt into one file).

The reads go through the same pipeline, in the same order (``acquire.pipeline.read_order``), so with the same
calibration and time-sync settings the derived topics come out bit for bit identical; with new ones they
come out re-derived. ``/truth/*`` is copied as it is.
"""
from __future__ import annotations

import heapq
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

from fieldlog.acquire import calib
from fieldlog.drive import outputs, recorder
from fieldlog.drive import reader
from fieldlog.drive.files import DriveSpec, label
from fieldlog.acquire.pipeline import PORT_ORDER, Counters, Pipeline, RawRead, read_order

RAW_PORTS = tuple(PORT_ORDER)      # /raw/daq, /raw/gps, /raw/can


@dataclass
class RebuildResult:
    imu_samples: int
    gps_epochs: int
    reads: int
    counters: Counters
    vehicle_frames: int = 0
    vehicle_twists: int = 0


def iter_raw(path: DriveSpec, port: str) -> Iterator[RawRead]:
    """The reads of one port in the order they were recorded (file order, not log-time order), decoded a
    chunk at a time (``drive.reader.iter_raw_batches``); a payload that is not a RawBytes message is skipped."""
    for b in reader.iter_raw_batches(path, f"/raw/{port}"):
        raw, o = b["data"].buf.tobytes(), b["data"].offsets.tolist()
        for i, (ok, mono_ns, wall_ns) in enumerate(zip(b["valid"].tolist(), b["mono_ns"].tolist(),
                                                       b["stamp_ns"].tolist())):
            if ok:
                yield RawRead(port, mono_ns, wall_ns, raw[o[i]:o[i + 1]])


def rebuild(src: DriveSpec, dst: str | Path, calibration: str | Path | None = None,
            progress: Callable[[float], None] | None = None, force: bool = False) -> RebuildResult:
    outputs.check_new(dst, force)
    records = reader.read_metadata_records(src)
    try:
        cal, sync_cfg, pipe_cfg = Pipeline.settings_from_metadata(dict(records))
    except ValueError as e:
        raise ValueError(f"{label(src)}: {e}: the drive's recorded settings are damaged") from None
    if calibration is not None:
        cal = calib.load_calibration(calibration)
    total = max(sum(t.count for t in reader.topic_counts(src) if t.topic.startswith("/raw/")), 1)
    with recorder.Recorder(dst, flush_interval_s=None, fsync=False, force=force, behind=True) as rec:
        for name, d in records:
            if name not in ("calibration", "timesync", "acquire.counters", "fieldlog.info"):
                rec.add_metadata(name, d)
        rec.add_metadata("rebuild", {"source": label(src)})
        pipe = Pipeline(rec, cal, sync_cfg, pipe_cfg)
        for name, d in pipe.metadata().items():
            rec.add_metadata(name, d)
        for topic in (t.topic for t in reader.topic_counts(src) if t.topic.startswith("/truth/") and t.count):
            t, pub, p = reader.read_payloads(src, topic, file_order=True)   # first: drivestats pairs /imu with it
            rec.write_batch(topic, t, p, pub)
        merged = heapq.merge(*(iter_raw(src, port) for port in RAW_PORTS), key=lambda r: read_order(r.port, r.mono_ns))
        n = pipe.feed_reads(merged, (lambda i: progress(i / total)) if progress else None)
        pipe.finish()
        rec.add_metadata("acquire.counters", pipe.counters_metadata())
    if progress:
        progress(1.0)
    return RebuildResult(pipe.counters.imu_samples, pipe.counters.gps_epochs, n, pipe.counters)
