"""MCAP recorder that survives a power cut, and recovery of a file cut short.

The recorder writes standard MCAP (chunks, message indexes, summary, footer; records built with
``mcap.records``) so mcap's readers, rerun and Foxglove read it. It builds chunks itself instead
of going through ``mcap.writer.Writer.add_message``: a message record is 31 header bytes plus the
CDR payload, so a whole batch of equal-length messages becomes one numpy byte matrix, and the
per-message Python cost of the mcap writer (a dataclass, five struct.pack calls and a BytesIO
seek per message) disappears from the hot path. Owning the chunk also makes the flush contract
explicit: a chunk is closed, written, flushed to the OS and (optionally) fsync'd at least every
``flush_interval_s`` of host time, so a power cut loses at most that much.

Schema and channel records are written in the data section outside chunks, before the first
chunk that uses them, so every complete chunk in a truncated file has its channels in front of
it and ``recover`` can rebuild a valid file from the complete chunks alone.

Not thread-safe: one thread owns a Recorder.
"""

from __future__ import annotations

import os
import struct
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO, Callable, Protocol, Sequence

import numpy as np
import zstandard
from zlib_ng.zlib_ng import crc32
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Message,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import LIBRARY_IDENTIFIER

from fieldlog.acquire import messages, native, outputs, typehash
from fieldlog.acquire.drivestats import RECORD as INFO_RECORD
from fieldlog.acquire.drivestats import DriveStats

MAGIC = b"\x89MCAP0\r\n"
PROFILE = "ros2"
LIBRARY = f"fieldlog/0.1 {LIBRARY_IDENTIFIER}"

# Message record: opcode u8, record length u64, channel_id u16, sequence u32, log_time u64,
# publish_time u64, then the payload (record length = 22 + payload).
_MSG_HDR = np.dtype(
    {
        "names": ["op", "length", "channel", "sequence", "log_time", "publish_time"],
        "formats": ["u1", "<u8", "<u2", "<u4", "<u8", "<u8"],
        "offsets": [0, 1, 9, 11, 15, 23],
        "itemsize": 31,
    }
)
_MSG_HDR_STRUCT = struct.Struct("<BQHIQQ")
_MSG_INDEX_HDR = struct.Struct("<BQHI")


@dataclass
class _OpenChunk:
    """Uncompressed chunk being built: parts joined on close; message index per channel."""

    parts: list = field(default_factory=list)
    size: int = 0
    count: int = 0
    start: int = 0
    end: int = 0
    index: dict[int, list[tuple[np.ndarray, np.ndarray]]] = field(default_factory=dict)

    def add(self, channel_id: int, log_times: np.ndarray, offsets: np.ndarray, data, nbytes: int) -> None:
        lo, hi = int(log_times.min()), int(log_times.max())
        self.start = lo if self.count == 0 else min(self.start, lo)
        self.end = max(self.end, hi)
        self.count += len(log_times)
        self.index.setdefault(channel_id, []).append((log_times, offsets))
        self.parts.append(data)
        self.size += nbytes


class Recorder:
    """Write a drive to one MCAP file.

    path: output file. chunk_size: uncompressed bytes per chunk before it is closed.
    flush_interval_s: close and flush the open chunk once this much host monotonic time has
    passed since the last flush (None: only by size or explicit ``flush()``, for offline
    writers that flush by data time). fsync: fsync after every flush (power-cut safety).
    compression: "zstd", "lz4" or "" (none); compression_level: zstd level (1 is about twice as
    fast as 3 on IMU data for ~5 % larger files). metadata: written as an MCAP Metadata record named
    "drive" (string values; e.g. scenario, seed, config, calibration TOML, software version).
    stats: gather what ``fieldlog info`` shows while writing and store it at close as the ``fieldlog.info``
    record (``acquire.drivestats``); off for files whose chunks are copied as they are (``recover``).
    The file is created new (``acquire.outputs.create``: ``outputs.Refused`` if ``path`` exists, unless it is a
    regular file and ``force``; always if it is a symbolic link; ``root``: the output folder ``path`` lies in,
    walked without following a link).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        chunk_size: int = 4 * 1024 * 1024,
        flush_interval_s: float | None = 1.0,
        compression: str = "zstd",
        metadata: dict[str, str] | None = None,
        fsync: bool = True,
        compression_level: int = 1,
        stats: bool = True,
        force: bool = False,
        root: str | os.PathLike[str] | None = None,
    ) -> None:
        if compression not in ("zstd", "lz4", ""):
            raise ValueError(f"unknown compression {compression!r}")
        self.path = Path(path)
        self._f: BinaryIO = outputs.create(self.path, force, root)
        self._chunk_size = chunk_size
        self._flush_interval_s = flush_interval_s
        self._compression = compression
        self._zstd = zstandard.ZstdCompressor(level=compression_level) if compression == "zstd" else None
        self._fsync = fsync
        self._schemas: dict[int, Schema] = {}
        self._schema_ids: dict[str, int] = {}
        self._channels: dict[int, Channel] = {}
        self._channel_ids: dict[str, int] = {}
        self._chunk = _OpenChunk()
        self._chunk_indexes = bytearray()   # the ChunkIndex records, as the summary holds them (~150 B a chunk,
        self._chunks = 0                    # far less than as ChunkIndex objects)
        self._metadata_indexes: list[MetadataIndex] = []
        self._counts: dict[int, int] = {}
        self._msg_start = 0
        self._msg_end = 0
        self._last_flush = time.monotonic()
        self.flush_seconds = 0.0  # host time spent in flush (compress + write + fsync)
        self.stats = DriveStats() if stats else None
        self.closed = False
        self._f.write(MAGIC)
        self._write_record(Header(PROFILE, LIBRARY))
        if metadata:
            self.add_metadata("drive", metadata)

    # -- records outside chunks --------------------------------------------------------------

    def _write_record(self, record) -> int:
        """Write one record to the data section; return its length in bytes."""
        rb = RecordBuilder()
        record.write(rb)
        data = rb.end()
        self._f.write(data)
        return len(data)

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """Write a Metadata record (string keys and values)."""
        offset = self._f.tell()
        length = self._write_record(Metadata(name=name, metadata={k: str(v) for k, v in data.items()}))
        self._metadata_indexes.append(MetadataIndex(offset=offset, length=length, name=name))

    def add_schema(self, schema: Schema) -> int:
        """Register a schema record as it is (keeps its id); returns the id."""
        if schema.id not in self._schemas:
            self._schemas[schema.id] = schema
            self._schema_ids[schema.name] = schema.id
            self._write_record(schema)
        return schema.id

    def add_channel(self, channel: Channel) -> int:
        """Register a channel record as it is (keeps its id); returns the id."""
        if channel.id not in self._channels:
            self._channels[channel.id] = channel
            self._channel_ids[channel.topic] = channel.id
            self._write_record(channel)
        return channel.id

    def channel_id(self, topic: str) -> int:
        """Channel id of a contract topic, registering its schema and channel on first use."""
        cid = self._channel_ids.get(topic)
        if cid is not None:
            return cid
        type_name = messages.topic_type(topic)
        sid = self._schema_ids.get(type_name)
        if sid is None:
            sid = self.add_schema(
                Schema(
                    id=len(self._schemas) + 1,
                    name=type_name,
                    encoding=messages.SCHEMA_ENCODING,
                    data=messages.schema_text(type_name).encode(),
                )
            )
        return self.add_channel(
            Channel(
                id=len(self._channels) + 1,
                topic=topic,
                message_encoding=messages.MESSAGE_ENCODING,
                schema_id=sid,
                metadata={"offered_qos_profiles": messages.offered_qos_profiles(topic),
                          "topic_type_hash": typehash.rihs01(type_name)},
            )
        )

    # -- messages ----------------------------------------------------------------------------

    def write(self, topic: str, log_time_ns: int, data: bytes, publish_time_ns: int | None = None) -> None:
        """Write one message. log_time_ns: int64 UTC ns (> 0)."""
        if log_time_ns <= 0:
            raise ValueError("log_time must be > 0")
        cid = self.channel_id(topic)
        if self.stats is not None:
            self.stats.observe_message(topic, log_time_ns, data)
        pub = log_time_ns if publish_time_ns is None else publish_time_ns
        hdr = _MSG_HDR_STRUCT.pack(Opcode.MESSAGE, 22 + len(data), cid, 0, log_time_ns, pub)
        c = self._chunk
        c.add(cid, np.array([log_time_ns], np.uint64), np.array([c.size], np.uint64), hdr + data, 31 + len(data))
        self._after_write()

    def write_batch(
        self,
        topic: str,
        log_time_ns: np.ndarray,
        msgs: "messages.Packed | Sequence[bytes]",
        publish_time_ns: np.ndarray | None = None,
    ) -> None:
        """Write n messages of one topic; log_time_ns (n,) int64 UTC ns, all > 0.

        Equal-length messages (fixed-layout types) are laid out as one byte matrix; a batch
        larger than the chunk size is split over several chunks.
        """
        if len(msgs) == 0:   # no channel for a topic without messages
            return
        self.write_channel(self.channel_id(topic), log_time_ns, msgs, publish_time_ns)

    def write_channel(
        self,
        channel_id: int,
        log_time_ns: np.ndarray,
        msgs: "messages.Packed | Sequence[bytes]",
        publish_time_ns: np.ndarray | None = None,
    ) -> None:
        """``write_batch`` to a channel already registered (``add_channel``), for any topic and type."""
        log_time_ns = np.asarray(log_time_ns, dtype=np.int64)
        p = messages.as_packed(msgs)
        n = len(p)
        if len(log_time_ns) != n:
            raise ValueError("log_time_ns and msgs differ in length")
        if n == 0:
            return
        if log_time_ns.min() <= 0:
            raise ValueError("log_time must be > 0")
        pub = log_time_ns if publish_time_ns is None else np.asarray(publish_time_ns, np.int64)
        cid = channel_id
        if self.stats is not None:
            self.stats.observe(self._channels[cid].topic, log_time_ns, p)
        lens = p.lengths
        rec_lens = lens + 31
        ends = np.cumsum(rec_lens)
        i = 0
        while i < n:
            room = max(self._chunk_size - self._chunk.size, 1)
            base = ends[i - 1] if i else 0
            j = min(int(np.searchsorted(ends, base + room, side="right")), n)
            if j == i:  # the next message does not fit: close this chunk (or overfill an empty one)
                if self._chunk.count:
                    self.flush()
                    continue
                j = i + 1
            self._append(cid, log_time_ns[i:j], pub[i:j], p, i, j)
            self._after_write()
            i = j

    def _append(self, cid: int, log_t: np.ndarray, pub_t: np.ndarray, p: "messages.Packed", i: int, j: int) -> None:
        m = j - i
        hdr = np.zeros(m, dtype=_MSG_HDR)
        lens = p.offsets[i + 1 : j + 1] - p.offsets[i:j]
        hdr["op"] = Opcode.MESSAGE
        hdr["length"] = lens + 22
        hdr["channel"] = cid
        hdr["log_time"] = log_t
        hdr["publish_time"] = pub_t
        c = self._chunk
        payload = p.buf[p.offsets[i] : p.offsets[j]]
        if np.all(lens == lens[0]):
            w = int(lens[0])
            block = np.empty((m, 31 + w), dtype=np.uint8)
            block[:, :31] = hdr.view(np.uint8).reshape(m, 31)
            block[:, 31:] = payload.reshape(m, w)
            offsets = c.size + np.arange(m, dtype=np.uint64) * np.uint64(31 + w)
        else:
            hb = hdr.tobytes()
            raw = payload.tobytes()
            o = (p.offsets[i : j + 1] - p.offsets[i]).tolist()
            parts = [b""] * (2 * m)
            parts[0::2] = [hb[31 * k : 31 * k + 31] for k in range(m)]
            parts[1::2] = [raw[o[k] : o[k + 1]] for k in range(m)]
            block = b"".join(parts)
            rec = lens + 31
            offsets = (c.size + np.concatenate(([0], np.cumsum(rec[:-1])))).astype(np.uint64)
        c.add(cid, log_t.astype(np.uint64), offsets, block, int(lens.sum()) + 31 * m)

    def _after_write(self) -> None:
        if self._chunk.size >= self._chunk_size:
            self.flush()
        elif (
            self._flush_interval_s is not None
            and time.monotonic() - self._last_flush >= self._flush_interval_s
        ):
            self.flush()

    def maybe_flush(self) -> None:
        """Flush if flush_interval_s of host time has passed (call from an idle loop)."""
        if self._flush_interval_s is not None and time.monotonic() - self._last_flush >= self._flush_interval_s:
            self.flush()

    # -- chunks ------------------------------------------------------------------------------

    def flush(self) -> None:
        """Close the open chunk (if it has messages), write it and its message indexes,
        flush to the OS and fsync (if enabled)."""
        t0 = time.perf_counter()
        c = self._chunk
        if c.count:
            self._write_chunk(b"".join(c.parts), c.start, c.end, c.index)
            self._chunk = _OpenChunk()
        self._f.flush()
        if self._fsync:
            os.fsync(self._f.fileno())
        self._last_flush = time.monotonic()
        self.flush_seconds += time.perf_counter() - t0

    def _write_chunk(
        self, data: bytes, start: int, end: int, index: dict[int, list[tuple[np.ndarray, np.ndarray]]]
    ) -> None:
        if self._compression == "zstd":
            compressed = self._zstd.compress(data)
        elif self._compression == "lz4":
            import lz4.frame

            compressed = lz4.frame.compress(data)
        else:
            compressed = data
        chunk = Chunk(
            compression=self._compression,
            data=compressed,
            message_start_time=start,
            message_end_time=end,
            uncompressed_crc=crc32(data),
            uncompressed_size=len(data),
        )
        chunk_offset = self._f.tell()
        chunk_length = self._write_record(chunk)
        index_offsets: dict[int, int] = {}
        parts = []
        pos = chunk_offset + chunk_length
        for cid, pieces in index.items():
            t = np.concatenate([a for a, _ in pieces])
            o = np.concatenate([b for _, b in pieces])
            entries = np.empty((len(t), 2), dtype="<u8")
            entries[:, 0], entries[:, 1] = t, o
            rec = _MSG_INDEX_HDR.pack(Opcode.MESSAGE_INDEX, 6 + 16 * len(t), cid, 16 * len(t)) + entries.tobytes()
            index_offsets[cid] = pos
            pos += len(rec)
            parts.append(rec)
            self._counts[cid] = self._counts.get(cid, 0) + len(t)
        self._f.write(b"".join(parts))
        rb = RecordBuilder()
        ChunkIndex(
            message_start_time=start,
            message_end_time=end,
            chunk_start_offset=chunk_offset,
            chunk_length=chunk_length,
            message_index_offsets=index_offsets,
            message_index_length=pos - chunk_offset - chunk_length,
            compression=self._compression,
            compressed_size=len(compressed),
            uncompressed_size=len(data),
        ).write(rb)
        self._chunk_indexes += rb.end()
        self._chunks += 1
        self._msg_start = start if self._chunks == 1 else min(self._msg_start, start)
        self._msg_end = max(self._msg_end, end)

    # -- finish ------------------------------------------------------------------------------

    def close(self) -> None:
        """Flush, then write DataEnd, the summary (schemas, channels, statistics, chunk and
        metadata indexes, summary offsets), the footer and the closing magic."""
        if self.closed:
            return
        self.flush()
        if self.stats is not None:   # after the last chunk: a file cut short keeps it only if all chunks are whole
            self.add_metadata(INFO_RECORD, self.stats.record())
        self._write_record(DataEnd(0))
        summary_start = self._f.tell()
        sb = RecordBuilder()
        offsets: list[SummaryOffset] = []

        def group(opcode: int, records: list, written: bytes = b"") -> None:
            start = sb.count
            for r in records:
                r.write(sb)
            sb.write(written)
            if sb.count > start:
                offsets.append(SummaryOffset(opcode, summary_start + start, sb.count - start))

        group(Opcode.SCHEMA, list(self._schemas.values()))
        group(Opcode.CHANNEL, list(self._channels.values()))
        group(
            Opcode.STATISTICS,
            [
                Statistics(
                    attachment_count=0,
                    channel_count=len(self._channels),
                    channel_message_counts=dict(self._counts),
                    chunk_count=self._chunks,
                    message_count=sum(self._counts.values()),
                    message_end_time=self._msg_end,
                    message_start_time=self._msg_start,
                    metadata_count=len(self._metadata_indexes),
                    schema_count=len(self._schemas),
                )
            ],
        )
        group(Opcode.CHUNK_INDEX, [], self._chunk_indexes)
        group(Opcode.METADATA_INDEX, self._metadata_indexes)
        summary_offset_start = summary_start + sb.count
        for o in offsets:
            o.write(sb)
        summary = sb.end()
        crc = crc32(summary)
        crc = crc32(struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start, summary_offset_start), crc)
        self._f.write(summary)
        self._write_record(Footer(summary_start, summary_offset_start, crc))
        self._f.write(MAGIC)
        self._f.flush()
        if self._fsync:
            os.fsync(self._f.fileno())
        self._f.close()
        self.closed = True

    def __enter__(self) -> "Recorder":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# ---------------------------------------------------------------------------------------------
# Chunk content


def _walk_records(buf: np.ndarray, pos: int, cap: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Records in ``buf`` from byte ``pos`` on (a chunk's content, or a whole file after its magic): opcode,
    start of the record body, body length; and the end of the last complete record. ``cap``: the number of
    records expected (the arrays grow past it). Compiled by numba when it is installed (fieldlog[fusion]);
    plain Python otherwise (several times slower)."""
    n = len(buf)
    cap = max(cap, 16)
    ops = np.empty(cap, np.uint8)
    starts = np.empty(cap, np.int64)
    lengths = np.empty(cap, np.int64)
    k = 0
    while pos + 9 <= n:
        length = 0
        for b in range(8):
            length |= np.int64(buf[pos + 1 + b]) << (8 * b)
        if length < 0 or pos + 9 + length > n:
            break
        if k == cap:
            cap *= 2
            ops2 = np.empty(cap, np.uint8)
            s2 = np.empty(cap, np.int64)
            l2 = np.empty(cap, np.int64)
            ops2[:k] = ops[:k]
            s2[:k] = starts[:k]
            l2[:k] = lengths[:k]
            ops, starts, lengths = ops2, s2, l2
        ops[k] = buf[pos]
        starts[k] = pos + 9
        lengths[k] = length
        k += 1
        pos += 9 + length
    return ops[:k], starts[:k], lengths[:k], pos


_walk_impl = None


def _walk(buf: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """The records of an uncompressed chunk (``walk_records`` from its start)."""
    return walk_records(buf, 0, len(buf) // 31 + 1)


def walk_records(buf: np.ndarray, pos: int, cap: int, jit: bool = True, limit: int | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """``_walk_records``, numba-compiled on first use when numba is installed (so importing the recorder, as
    ``fieldlog acquire`` and ``info`` do, never loads numba); ``jit`` False: the plain walk, stopping after
    ``limit`` records (a file's top level: a few records, where compiling would cost more than it saves), unless
    the compiled walk is loaded already: then that, to the end."""
    global _walk_impl
    if not jit and (_walk_impl is None or _walk_impl is _walk_python):
        return _walk_python(buf, pos, cap, limit)
    if _walk_impl is None:
        try:
            import numba
        except ImportError:
            _walk_impl = _walk_python
        else:
            _walk_impl = numba.njit(cache=True)(_walk_records)
    return _walk_impl(buf, pos, cap)


def _walk_python(buf: np.ndarray, pos: int, cap: int, limit: int | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """``_walk_records`` without numba: the same walk over the bytes with ``struct`` (indexing numpy scalars in
    an interpreted loop is much slower than unpacking from a buffer)."""
    data = buf if isinstance(buf, (bytes, memoryview)) else memoryview(buf)
    n = len(data)
    ops: list[int] = []
    starts: list[int] = []
    lengths: list[int] = []
    unpack = struct.Struct("<BQ").unpack_from
    while pos + 9 <= n and (limit is None or len(ops) < limit):
        op, length = unpack(data, pos)
        if length >= 1 << 63 or pos + 9 + length > n:
            break
        ops.append(op)
        starts.append(pos + 9)
        lengths.append(length)
        pos += 9 + length
    return (np.array(ops, np.uint8), np.array(starts, np.int64), np.array(lengths, np.int64), pos)


@dataclass(frozen=True)
class ChunkMessages:
    """Message records of one chunk, as arrays; payload i is data[start[i]:start[i]+length[i]]."""

    data: np.ndarray  # uint8: the uncompressed chunk(s), or the records of them a read kept (read_chunks)
    channel_id: np.ndarray  # uint16
    log_time: np.ndarray  # int64 ns
    publish_time: np.ndarray  # int64 ns
    offset: np.ndarray  # int64, record start (opcode byte) inside the chunk
    start: np.ndarray  # int64, payload start
    length: np.ndarray  # int64, payload length

    def select(self, mask: np.ndarray) -> "ChunkMessages":
        return ChunkMessages(
            self.data,
            self.channel_id[mask],
            self.log_time[mask],
            self.publish_time[mask],
            self.offset[mask],
            self.start[mask],
            self.length[mask],
        )

    def packed(self) -> "messages.Packed":
        """Payloads as a Packed batch: one vectorised gather (of whole rows when they have one length)."""
        n = len(self.start)
        if n and np.all(self.length == self.length[0]):
            w = int(self.length[0])
            return messages.Packed.from_matrix(byte_windows(self.data, w)[self.start])
        offsets = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(self.length, out=offsets[1:])
        src = np.repeat(self.start - offsets[:-1], self.length) + np.arange(offsets[-1], dtype=np.int64)
        return messages.Packed(self.data[src], offsets)


def decompress_chunk(chunk: Chunk) -> bytes:
    """Uncompressed chunk bytes; raises ValueError if the size or CRC does not match."""
    return decompress(chunk.compression, chunk.data, chunk.uncompressed_size, chunk.uncompressed_crc)


_ZSTD = threading.local()


def _zstd() -> "zstandard.ZstdDecompressor":
    """This thread's zstd decompressor (making one costs more than decompressing a 4 KiB chunk)."""
    d = getattr(_ZSTD, "d", None)
    if d is None:
        d = _ZSTD.d = zstandard.ZstdDecompressor()
    return d


def decompress(compression: str, data, size: int, crc: int):
    """A chunk's records, uncompressed (``data``: bytes or a buffer; returned as it is when not compressed);
    raises ValueError if the size or the CRC (0: none) does not match."""
    out = decompress_many(data, [compression], [0], [0], [len(data)], [size], [crc])
    return data if compression == "" else out


class ChunkError(ValueError):
    """A chunk that is not what its record says (it does not decompress, or to another size or CRC, or it claims
    more than ``max_chunk_bytes``); ``index``: its position among the chunks of the ``decompress_many`` call."""

    def __init__(self, index: int, what: str) -> None:
        super().__init__(what)
        self.index = index


MAX_CHUNK_ENV = "FIELDLOG_MAX_CHUNK_BYTES"
MAX_CHUNK_BYTES = 256 << 20


def max_chunk_bytes() -> int:
    """The most uncompressed bytes one chunk (or one run of messages outside chunks) may hold to be read:
    ``FIELDLOG_MAX_CHUNK_BYTES`` from the environment, else ``MAX_CHUNK_BYTES`` (256 MiB: 64 times the chunks
    ``Recorder`` writes, and of any writer we know of; a chunk claiming more is damaged, or a decompression bomb)."""
    text = os.environ.get(MAX_CHUNK_ENV, "").strip()
    if not text:
        return MAX_CHUNK_BYTES
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n <= 0:
        raise ValueError(f"{MAX_CHUNK_ENV}={text!r}: give the largest chunk to read, in bytes (> 0)")
    return n


def check_sizes(size: np.ndarray) -> None:
    """``ChunkError`` for the first chunk whose claimed uncompressed ``size`` (int64: one that does not fit is
    negative) exceeds ``max_chunk_bytes``, before any buffer is sized by it."""
    limit = max_chunk_bytes()
    over = np.flatnonzero((size < 0) | (size > limit))
    if len(over):
        k = int(over[0])
        claim = int(size[k]) % (1 << 64)
        raise ChunkError(k, f"chunk claims {claim} bytes uncompressed, more than the limit of {limit} "
                            f"({MAX_CHUNK_ENV}): damaged, or a decompression bomb; not read")


def decompress_many(buf, names: Sequence[str], comp: Sequence[int], at: Sequence[int], length: Sequence[int],
                    size: Sequence[int], crc: Sequence[int]):
    """The records of many chunks, uncompressed and joined in order (one bytes-like object): chunk i is
    compressed with ``names[comp[i]]`` ("": not compressed), the ``length[i]`` bytes at ``at[i]`` of ``buf``
    (bytes, mmap, ...), and ``size[i]`` bytes with CRC-32 ``crc[i]`` (0: none) once uncompressed. Raises
    ``ChunkError`` for the first chunk that does not match. Small chunks are many, so each run of zstd chunks is
    decompressed in one call (python-zstandard's ``multi_decompress_to_buffer``: in C, without the GIL, and it
    checks the sizes) and the CRCs are taken with zlib-ng's SIMD CRC-32. No chunk is decompressed past its claimed
    size, and none claiming more than ``max_chunk_bytes`` is decompressed at all (``check_sizes``)."""
    comp, at, length, size, crc = (np.asarray(x, np.int64) for x in (comp, at, length, size, crc))
    check_sizes(size)
    mv = memoryview(buf).cast("B")
    parts: list = []
    cut = np.r_[0, np.flatnonzero(np.diff(comp)) + 1, len(comp)].tolist()
    for i, j in zip(cut, cut[1:]):
        name = names[comp[i]]
        # multi_decompress_to_buffer corrupts the heap on an empty frame (zstandard 0.25): those go one by one
        if name == "zstd" and ((size[i:j] > 0) & (size[i:j] < 1 << 32)).all():
            segs = np.stack([at[i:j], length[i:j]], axis=1).astype(np.uint64)
            try:
                parts.extend(_zstd().multi_decompress_to_buffer(
                    zstandard.BufferWithSegments(mv, segs.tobytes()),
                    decompressed_sizes=size[i:j].astype(np.uint64).tobytes()))
                continue
            except (zstandard.ZstdError, MemoryError):  # a damaged frame or size: find it
                pass
        parts.extend(_one(name, mv[at[k]:at[k] + length[k]], int(size[k]), k) for k in range(i, j))
    bad = np.fromiter(map(len, parts), np.int64, len(parts)) != size
    check = crc != 0
    bad[check] |= np.fromiter(map(crc32, (p for p, c in zip(parts, check.tolist()) if c)), np.int64) != crc[check]
    if bad.any():
        k = int(np.argmax(bad))
        raise ChunkError(k, native.ERRORS[native.SIZE if len(parts[k]) != size[k] else native.CRC])
    return parts[0] if len(parts) == 1 else b"".join(parts)


def _one(compression: str, data, size: int, k: int):
    """Chunk ``k`` of a ``decompress_many`` call (``size`` bytes uncompressed), uncompressed into at most ``size``
    bytes (python-zstandard sizes its output by the frame's own content size when the frame has one, so that is
    checked first; an lz4 frame longer than ``size`` is cut there and refused)."""
    try:
        if compression == "zstd":
            claimed = zstandard.frame_content_size(data)
            if claimed not in (-1, size):
                raise ChunkError(k, native.ERRORS[native.SIZE])
            return _zstd().decompress(data, max_output_size=size)
        if compression == "lz4":
            import lz4.frame

            d = lz4.frame.LZ4FrameDecompressor()
            out = d.decompress(data, max_length=size)
            if not d.eof:
                raise ChunkError(k, native.ERRORS[native.SIZE])
            return out
    except ChunkError:
        raise
    except Exception as e:  # a damaged frame: the codecs raise their own errors
        raise ChunkError(k, f"chunk does not decompress ({compression}: {e})") from None
    if compression != "":
        raise ChunkError(k, f"unknown compression {compression!r}")
    return data


def chunk_messages(data: bytes) -> ChunkMessages:
    """Parse the Message records of an uncompressed chunk, vectorised (numba record walk)."""
    buf = np.frombuffer(data, dtype=np.uint8)
    return messages_of(buf, *_walk(buf)[:3])


def byte_windows(buf: np.ndarray, k: int) -> np.ndarray:
    """A read-only view (len(buf) - k + 1, k) of a uint8 buffer: row i holds the k bytes from byte i (no copy;
    index it with record positions to gather fixed-size heads or payloads in one step)."""
    return np.lib.stride_tricks.as_strided(buf, shape=(max(len(buf) - k + 1, 0), k), strides=(1, 1),
                                           writeable=False)


def le(buf: np.ndarray, pos: np.ndarray, dtype: str | np.dtype) -> np.ndarray:
    """Little-endian ``dtype`` values (or records of a structured dtype) at byte positions ``pos`` of a uint8
    buffer (each must leave room for the value). Integers are put together from one ``take`` per byte (twice as
    fast as gathering rows of ``byte_windows``, which the records use)."""
    dt, pos = np.dtype(dtype), np.asarray(pos, np.int64)
    if dt.kind not in "iu":
        return byte_windows(buf, dt.itemsize)[pos].view(dt).ravel()
    u = np.dtype(f"<u{dt.itemsize}")
    out = buf.take(pos).astype(u)
    for j in range(1, dt.itemsize):
        out |= buf.take(pos + j).astype(u) << u.type(8 * j)
    return out.view(dt)


def messages_of(buf: np.ndarray, ops: np.ndarray, starts: np.ndarray, lengths: np.ndarray,
                channels: Sequence[int] | None = None) -> ChunkMessages:
    """The Message records among walked records (``walk_records``) of ``buf``, as arrays (only those on
    ``channels``, when given)."""
    is_msg = (ops == Opcode.MESSAGE) & (lengths >= 22)
    s, ln = starts[is_msg], lengths[is_msg]
    windows = byte_windows(buf, 22)
    if channels is not None:
        on = np.isin(le(buf, s, "<u2"), list(channels))
        s, ln = s[on], ln[on]
    hdr = windows[s]
    fields = hdr.reshape(-1).view(
        np.dtype(
            {
                "names": ["channel", "sequence", "log_time", "publish_time"],
                "formats": ["<u2", "<u4", "<i8", "<i8"],
                "offsets": [0, 2, 6, 14],
                "itemsize": 22,
            }
        )
    )
    return ChunkMessages(
        data=buf,
        channel_id=fields["channel"].copy(),
        log_time=fields["log_time"].copy(),
        publish_time=fields["publish_time"].copy(),
        offset=s - 9,
        start=s + 22,
        length=ln - 22,
    )


def read_chunks(buf, names: Sequence[str], comp: Sequence[int], at: Sequence[int], length: Sequence[int],
                size: Sequence[int], crc: Sequence[int], want: np.ndarray,
                scratch: Callable[[int, int], tuple[np.ndarray, np.ndarray]]
                ) -> tuple[ChunkMessages, list[tuple[int, int, int]]]:
    """The messages of many chunks (as ``decompress_many`` takes them) on the channels marked in ``want`` (bool per
    channel id, 65536 long), and the schema and channel records among their records as (opcode, body start in
    the batch's ``data``, body length). When zstd chunks are among them (and uncompressed ones only besides) and
    ``acquire.native`` is ready, in one compiled pass that keeps only those records: ``scratch(a, b)`` gives a
    staging buffer of ``a`` bytes and the batch's buffer of ``b`` bytes. Else the chunks are decompressed and joined
    (``decompress_many``), walked (``walk_records``) and their messages picked (``messages_of``)."""
    comp, size = np.asarray(comp, np.int64), np.asarray(size, np.int64)
    check_sizes(size)
    used = {names[c] for c in np.unique(comp).tolist()}
    if "zstd" in used and used <= {"", "zstd"} and (size < 1 << 32).all() and native.ready():
        stage, out = scratch(int(size.max()), int(size.sum()))
        j, what, n, rec, ch, defs = native.read_chunks(
            buf, np.where(comp == names.index("zstd"), native.ZSTD, native.NONE), np.asarray(at, np.int64),
            np.asarray(length, np.int64), size, np.asarray(crc, np.int64), stage, out, want)
        if j >= 0:
            raise ChunkError(j, native.ERRORS[what])
        cm = ChunkMessages(out[:n], ch, rec[:, 2], rec[:, 3], rec[:, 0], rec[:, 0] + 31, rec[:, 1] - 22)
        return cm, [tuple(d) for d in defs.tolist()]
    data = np.frombuffer(decompress_many(buf, names, comp, at, length, size, crc), np.uint8)
    ops, starts, lengths, _ = _walk(data)
    d = np.flatnonzero(((ops == Opcode.SCHEMA) | (ops == Opcode.CHANNEL)) & (lengths >= 14))
    cm = messages_of(data, ops, starts, lengths, None if want.all() else np.flatnonzero(want))
    return cm, list(zip(ops[d].tolist(), starts[d].tolist(), lengths[d].tolist()))


# ---------------------------------------------------------------------------------------------
# Recovery


@dataclass
class RecoverReport:
    """messages: kept per topic; chunks: complete chunks kept; bytes_discarded: source bytes
    after the last complete record; last_log_time_ns: latest log time kept (0 if none);
    had_summary: the source was already complete (footer read); damaged: byte offsets of whole chunk records whose
    content failed its CRC or codec, skipped (their messages are lost; every other chunk is kept)."""

    messages: dict[str, int]
    chunks: int
    bytes_discarded: int
    last_log_time_ns: int
    had_summary: bool
    rederived: dict[str, int] = field(default_factory=dict)   # tail messages re-derived per topic
    damaged: list[int] = field(default_factory=list)


class Extend(Protocol):
    """What ``recover`` can add to the kept chunks (``acquire.recovery.TailDeriver``)."""

    def chunk(self, rec: "Recorder", cm: "ChunkMessages", metadata: dict[str, dict[str, str]]) -> None: ...

    def finish(self, rec: "Recorder") -> dict[str, int]: ...


def has_footer(path: str | os.PathLike[str]) -> bool:
    """``path`` ends with a Footer record and the magic, as a complete MCAP file does."""
    n = 9 + 20 + len(MAGIC)
    with open(path, "rb") as f:
        if os.fstat(f.fileno()).st_size < len(MAGIC) + n:
            return False
        f.seek(-n, os.SEEK_END)
        tail = f.read(n)
    return tail[:9] == struct.pack("<BQ", Opcode.FOOTER, 20) and tail[-len(MAGIC):] == MAGIC


def recover(src: str | os.PathLike[str], dst: str | os.PathLike[str], extend: Extend | None = None,
            force: bool = False) -> RecoverReport:
    """Rebuild a valid MCAP from ``src`` (cut short by a kill or power loss) into ``dst``.

    Reads ``src`` record by record with mcap's StreamReader and keeps every schema, channel,
    metadata record, every complete chunk whose CRC checks and every message outside chunks (written as
    they come, in runs of up to 4 MB, each as a new chunk), up to the first truncated or invalid record; a chunk
    whose record is whole but whose content fails its CRC or codec, or claims more than ``limits.chunk_bytes()``
    uncompressed, is skipped and counted, and the walk goes on; writes them to ``dst`` with fresh message indexes
    and a summary. ``extend`` sees each kept chunk and adds its messages before the summary. ``src`` must start
    with the MCAP magic (ValueError). ``dst`` must be a new name (``outputs.Refused`` before any work otherwise,
    unless it is a regular file and ``force``) and appears only complete: it is written as ``dst`` + ``.partial``
    (a regular file of that name, left by an interrupted recovery, is replaced; a symbolic link refused) and
    linked into place at the end; on any error (a full disk) the partial file is removed and the error raised, so
    a later attempt starts afresh.
    """
    size = os.path.getsize(src)
    with open(src, "rb") as f:
        if f.read(len(MAGIC)) != MAGIC:
            raise ValueError(f"{src} is not an MCAP file (no MCAP magic at its start): nothing to recover")
    dst = Path(dst)
    outputs.check_new(dst, force)
    tmp = dst.with_name(dst.name + ".partial")
    rec = Recorder(tmp, flush_interval_s=None, fsync=False, stats=False, force=True)
    try:
        report = _recover(src, rec, size, extend)
        outputs.publish(tmp, dst, force)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return report


def _recover(src: str | os.PathLike[str], rec: Recorder, size: int, extend: Extend | None) -> RecoverReport:
    kept: dict[int, int] = {}
    meta: dict[str, dict[str, str]] = {}
    rederived: dict[str, int] = {}
    last_t = 0
    good_end = 0
    had_summary = False
    loose = [0, 0]  # [start, end) in src of the pending run of messages outside chunks
    damaged: list[int] = []

    def keep(cm: ChunkMessages) -> None:
        nonlocal last_t
        _copy_chunk(rec, cm)
        if extend is not None:
            extend.chunk(rec, cm, meta)
        for cid, cnt in zip(*np.unique(cm.channel_id, return_counts=True)):
            kept[int(cid)] = kept.get(int(cid), 0) + int(cnt)
        if len(cm.log_time):
            last_t = max(last_t, int(cm.log_time.max()))

    def keep_loose(f: BinaryIO) -> None:
        """The pending messages outside chunks (their records as they are in src) kept as one chunk."""
        if loose[1] > loose[0]:
            keep(chunk_messages(os.pread(f.fileno(), loose[1] - loose[0], loose[0])))
        loose[0] = loose[1]

    try:
        with open(src, "rb") as f:
            reader = StreamReader(f, emit_chunks=True, record_size_limit=size)
            it = reader.records
            while True:
                start = f.tell()
                try:
                    record = next(it)
                except StopIteration:
                    had_summary = True
                    break
                except Exception:  # truncated or corrupt record: stop here
                    break
                if isinstance(record, Chunk):
                    try:
                        data = decompress_chunk(record)
                        cm = chunk_messages(data)
                        inner = _chunk_definitions(record, data)
                    except Exception:  # a whole record with damaged content: skip it, go on
                        damaged.append(start)
                        keep_loose(f)
                        loose[0] = loose[1] = good_end = f.tell()
                        continue
                if isinstance(record, Message):  # outside chunks: kept in runs of consecutive records
                    if record.channel_id not in rec._channels:
                        break
                    loose[1] = good_end = f.tell()
                    if loose[1] - loose[0] >= 4 << 20:
                        keep_loose(f)
                    continue
                keep_loose(f)
                loose[0] = loose[1] = f.tell()
                if isinstance(record, Schema):
                    rec.add_schema(record)
                elif isinstance(record, Channel):
                    rec.add_channel(record)
                elif isinstance(record, Metadata):
                    rec.add_metadata(record.name, record.metadata)
                    meta[record.name] = dict(record.metadata)
                elif isinstance(record, Chunk):
                    for r in inner:
                        (rec.add_schema if isinstance(r, Schema) else rec.add_channel)(r)
                    if not set(np.unique(cm.channel_id).tolist()) <= set(rec._channels):
                        break
                    keep(cm)
                elif isinstance(record, (DataEnd, Footer)):
                    good_end = f.tell()
                    had_summary = True
                    break
                good_end = f.tell()
            keep_loose(f)
        if extend is not None and not had_summary:
            rederived = extend.finish(rec)
            if rederived:
                rec.add_metadata("recover", {"source": str(src), **{f"rederived.{k}": str(v)
                                                                     for k, v in rederived.items()}})
    finally:
        rec.close()
    topics = {rec._channels[cid].topic: n for cid, n in kept.items()}
    return RecoverReport(
        messages=topics,
        chunks=rec._chunks,
        bytes_discarded=size - good_end if not had_summary else 0,
        last_log_time_ns=last_t,
        had_summary=had_summary,
        rederived=rederived,
        damaged=damaged,
    )


def _chunk_definitions(chunk: Chunk, data: bytes) -> list[Schema | Channel]:
    """Schema and Channel records inside a chunk (other writers put them there)."""
    ops, _, _, _ = _walk(np.frombuffer(data, dtype=np.uint8))
    if not np.isin(ops, (Opcode.SCHEMA, Opcode.CHANNEL)).any():
        return []
    return [r for r in breakup_chunk(chunk) if isinstance(r, (Schema, Channel))]


def _copy_chunk(rec: Recorder, cm: ChunkMessages) -> None:
    """Write the message records of one chunk as one new chunk (offsets kept)."""
    index: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}
    for cid in np.unique(cm.channel_id).tolist():
        sel = cm.channel_id == cid
        index[cid] = [(cm.log_time[sel].astype(np.uint64), cm.offset[sel].astype(np.uint64))]
    if len(cm.log_time) == 0:
        return
    rec._write_chunk(cm.data.tobytes(), int(cm.log_time.min()), int(cm.log_time.max()), index)
