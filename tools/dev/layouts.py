"""A drive rewritten in the MCAP layouts other writers produce, with the mcap library's own ``Writer``: the
reader's test corpus (tests/test_layouts.py) and ``make bench`` (reader).

``LAYOUTS`` names the ``Writer`` options: messages outside chunks (``unchunked``), lz4 chunks, uncompressed
chunks, no summary / message indexes / statistics / summary offsets (``no-summary``, as a streaming writer leaves
a file), and 4 KiB chunks. Every copy also gets the drive's metadata records and an attachment.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np

from fieldlog.drive import outputs
from fieldlog.drive import reader
from fieldlog.drive.files import open_drive
from fieldlog.drive.records import CompressionType, IndexType, Writer

LAYOUTS: dict[str, dict] = {
    "unchunked": dict(use_chunking=False),
    "lz4": dict(compression=CompressionType.LZ4),
    "uncompressed": dict(compression=CompressionType.NONE),
    "no-summary": dict(index_types=IndexType.NONE, repeat_channels=False, repeat_schemas=False,
                       use_statistics=False, use_summary_offsets=False),
    "chunks-4k": dict(chunk_size=4096),
}


def merged(src: str | os.PathLike[str], topics: Sequence[str]
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[bytes]]:
    """The messages of ``topics`` in one log-time order: (topic index, log_time, publish_time, payloads)."""
    parts = [reader.read_payloads(src, t) for t in topics]
    k = np.concatenate([np.full(len(p[0]), i) for i, p in enumerate(parts)])
    t = np.concatenate([p[0] for p in parts])
    pub = np.concatenate([p[1] for p in parts])
    data = [d for p in parts for d in p[2]]
    order = np.argsort(t, kind="stable")
    return k[order], t[order], pub[order], [data[i] for i in order.tolist()]


def schema_of(src: str | os.PathLike[str], topic: str):
    """The Schema record of ``topic`` in the (single-file) drive ``src``."""
    (f,) = open_drive(src)
    ch = next(c for c in f.channels.values() if c.topic == topic)
    return f.schemas[ch.schema_id]


def rewrite(src: str | os.PathLike[str], dst: str | os.PathLike[str], layout: str,
            topics: Sequence[str] | None = None) -> Path:
    """``src`` (its ``topics``, default all) rewritten into ``dst`` by mcap's Writer with ``LAYOUTS[layout]``."""
    topics = list(topics) if topics is not None else [t.topic for t in reader.topics(src)]
    with outputs.create(dst) as out:
        w = Writer(out, **LAYOUTS[layout])
        w.start("ros2", "mcap python Writer (fieldlog.tools.dev.layouts)")
        for name, d in reader.read_metadata_records(src):
            w.add_metadata(name, d)
        w.add_attachment(1, 2, "notes.txt", "text/plain", b"an attachment the reader must step over")
        cids = []
        for topic in topics:
            s = schema_of(src, topic)
            cids.append(w.register_channel(topic, "cdr", w.register_schema(s.name, s.encoding, s.data)))
        k, t, pub, data = merged(src, topics)
        for i, ti, pi, d in zip(k.tolist(), t.tolist(), pub.tolist(), data):
            w.add_message(cids[i], ti, d, pi)
        w.finish()
    return Path(dst)
