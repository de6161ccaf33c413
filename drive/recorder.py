"""MCAP recorder that survives a power cut.

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
it and ``acquire.recovery.recover`` can rebuild a valid file from the complete chunks alone. Reading chunks back
is ``drive.chunks``.

Not thread-safe: one thread owns a Recorder. With ``behind`` (offline writers) the recorder itself compresses and
writes each closed chunk, and the schema and channel records between them, on a thread of its own while the owner
goes on; the file's bytes are the same as without.
"""

from __future__ import annotations

import itertools
import os
import struct
import time
from bisect import bisect_left
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Callable, Mapping, NamedTuple, Sequence

import numpy as np
import mcap
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
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

from fieldlog.drive import messages, outputs, typehash
from fieldlog.drive.drivestats import RECORD as INFO_RECORD
from fieldlog.drive.drivestats import DriveStats

MAGIC = b"\x89MCAP0\r\n"
PROFILE = "ros2"
# mcap.writer's LIBRARY_IDENTIFIER, spelled here: importing mcap.writer imports importlib.metadata at every start
LIBRARY = f"fieldlog/0.1 mcap-python/{mcap.__version__}"

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
# A batch of at most this many messages is laid out a record at a time (``Recorder.write_channel``; the pipeline
# writes /gps/fix, /gps/vel, /pps and /time/sync a message or two at a time): below it, the batch's arrays cost
# more than the records' struct calls.
FEW = 8
# Closed chunks a ``behind`` recorder holds while its thread compresses and writes them (chunk_size bytes each,
# uncompressed): enough that the owner goes on through a burst of chunks rather than wait at each one (a simulated
# drive writes all of its /truth/* first, the thread compressing it while the pipeline starts).
BEHIND_CHUNKS = 32


@dataclass
class _OpenChunk:
    """Uncompressed chunk being built: parts joined on close; message index per channel, as pieces of (log
    times, offsets): uint64 arrays from batches, ints from single messages (``_index_column`` joins them)."""

    parts: list = field(default_factory=list)
    size: int = 0
    count: int = 0
    start: int = 0
    end: int = 0
    index: dict[int, list[tuple[np.ndarray | int, np.ndarray | int]]] = field(default_factory=dict)

    def add_block(self, channel_id: int, log_times: list[int], block: "bytes | memoryview", starts: list[int]) -> None:
        """Whole message records laid out in ``block``, record k from ``starts[k]`` bytes into it, logged at
        ``log_times[k]`` (the path of single messages and of records laid out ahead: no arrays).

        Parameters
        ----------
        channel_id : the records' channel id
        log_times : their log times, UTC ns
        block : the records (header and payload each), back to back
        starts : where each record starts in ``block``, bytes
        """
        lo, hi = min(log_times), max(log_times)
        self.start = lo if self.count == 0 else min(self.start, lo)
        self.end = max(self.end, hi)
        self.count += len(log_times)
        base = self.size
        self.index.setdefault(channel_id, []).extend(zip(log_times, [base + x for x in starts]))
        self.parts.append(block)
        self.size = base + len(block)

    def add(self, cid: int, log_t: np.ndarray, pub_t: np.ndarray, p: "messages.Packed", i: int, j: int) -> None:
        """Messages ``i`` to ``j`` of ``p`` as message records of channel ``cid``: equal-length messages
        (fixed-layout types) laid out as one byte matrix, others joined.

        Parameters
        ----------
        cid : channel id
        log_t, pub_t : (j - i,) int64 log and publish times of the messages, UTC ns
        p : the batch's payloads
        i, j : the messages of ``p`` to add, ``p[i:j]``
        """
        m = j - i
        lens = p.offsets[i + 1 : j + 1] - p.offsets[i:j]
        hdr = _headers(cid, lens, log_t, pub_t)
        payload = p.buf[p.offsets[i] : p.offsets[j]]
        if np.all(lens == lens[0]):
            w = int(lens[0])
            block = np.empty((m, 31 + w), dtype=np.uint8)
            block[:, :31] = hdr.view(np.uint8).reshape(m, 31)
            block[:, 31:] = payload.reshape(m, w)
            offsets = self.size + np.arange(m, dtype=np.uint64) * np.uint64(31 + w)
        else:
            hb = hdr.tobytes()
            raw = payload.tobytes()
            o = (p.offsets[i : j + 1] - p.offsets[i]).tolist()
            parts = [b""] * (2 * m)
            parts[0::2] = [hb[31 * k : 31 * k + 31] for k in range(m)]
            parts[1::2] = [raw[o[k] : o[k + 1]] for k in range(m)]
            block = b"".join(parts)
            rec = lens + 31
            offsets = (self.size + np.concatenate(([0], np.cumsum(rec[:-1])))).astype(np.uint64)
        lo, hi = int(log_t.min()), int(log_t.max())
        self.start = lo if self.count == 0 else min(self.start, lo)
        self.end = max(self.end, hi)
        self.count += m
        self.index.setdefault(cid, []).append((log_t.astype(np.uint64), offsets))
        self.parts.append(block)
        self.size += int(lens.sum()) + 31 * m


def _headers(cid: int, lens: np.ndarray, log_t: np.ndarray, pub_t: np.ndarray) -> np.ndarray:
    """The message record headers (``_MSG_HDR``) of payloads of ``lens`` bytes on channel ``cid``, logged and
    published at ``log_t`` and ``pub_t`` (UTC ns)."""
    hdr = np.zeros(len(lens), dtype=_MSG_HDR)
    hdr["op"] = Opcode.MESSAGE
    hdr["length"] = lens + 22
    hdr["channel"] = cid
    hdr["log_time"] = log_t
    hdr["publish_time"] = pub_t
    return hdr


def _index_column(pieces: list, i: int) -> np.ndarray:
    """Column ``i`` of a channel's index pieces (``_OpenChunk.index``) as one uint64 array, in order."""
    out, run = [], []
    for p in pieces:
        x = p[i]
        if isinstance(x, int):
            run.append(x)
            continue
        if run:
            out.append(np.array(run, np.uint64))
            run = []
        out.append(x)
    if run:
        out.append(np.array(run, np.uint64))
    return np.concatenate(out)


def _ints(values: Sequence[int] | np.ndarray) -> list[int]:
    """``values`` as a list of Python ints (an array's in one call, a sequence's one by one)."""
    return values.astype(np.int64).tolist() if isinstance(values, np.ndarray) else [int(v) for v in values]


class _Laid(NamedTuple):
    """Message records laid out (``Records.laid_out``): record k is ``buf[starts[k]:starts[k + 1]]``, logged at
    ``log_times[k]`` (UTC ns) on channel ``channel_id``."""

    channel_id: int
    log_times: list[int]
    buf: memoryview
    starts: list[int]


@dataclass(slots=True)
class Records:
    """Messages of one topic to write in pieces as ``Recorder.write`` of each in turn would
    (``Recorder.write_records``): their log times (UTC ns, > 0), payloads (a list, or a ``messages.Packed``
    batch) and publish times (None: the log times). Their message records are laid out once, at the first
    write."""

    topic: str
    log_time_ns: Sequence[int] | np.ndarray
    payloads: "messages.Packed | Sequence[bytes]"
    publish_time_ns: Sequence[int] | np.ndarray | None = None
    _laid: _Laid | None = field(default=None, init=False, repr=False)

    def __len__(self) -> int:
        return len(self.payloads)

    def laid_out(self, channel_id: Callable[[str], int]) -> _Laid:
        """The message records, laid out on the first call: a batch in one vectorised step (``Packed.prefixed``),
        a list a record at a time (ValueError when the times and the payloads differ in length, or a log time is
        not > 0).

        Parameters
        ----------
        channel_id : the recorder's ``channel_id``, asked for the topic's once the times check out

        Returns
        -------
        _Laid : the records, where each starts, their log times and channel
        """
        if self._laid is None:
            times = _ints(self.log_time_ns)
            pub = times if self.publish_time_ns is None else _ints(self.publish_time_ns)
            if len(times) != len(self.payloads) or len(pub) != len(times):
                raise ValueError("log_time_ns and msgs differ in length")
            if times and min(times) <= 0:
                raise ValueError("log_time must be > 0")
            cid = channel_id(self.topic)
            if isinstance(self.payloads, messages.Packed):
                p = self.payloads
                hdr = _headers(cid, p.lengths, np.array(times, np.int64), np.array(pub, np.int64))
                laid = p.prefixed(hdr.view(np.uint8).reshape(len(p), 31))
                self._laid = _Laid(cid, times, memoryview(laid.buf), laid.offsets.tolist())
            else:
                pack, op = _MSG_HDR_STRUCT.pack, Opcode.MESSAGE
                records = [pack(op, 22 + len(d), cid, 0, t, q) + d for t, q, d in zip(times, pub, self.payloads)]
                starts = list(itertools.accumulate(map(len, records), initial=0))
                self._laid = _Laid(cid, times, memoryview(b"".join(records)), starts)
        return self._laid


class _FileWriter:
    """The file side of a ``Recorder``: records outside chunks, closed chunks (compressed, with their message
    indexes; with ``behind``, on a thread of its own), what the summary counts, and the summary and footer at the
    end. ``f``: the new output file (``outputs.create``); the other arguments are the Recorder's."""

    def __init__(self, f: outputs.Output, compression: str, compression_level: int, fsync: bool,
                 behind: bool) -> None:
        self._f = f
        self._compression = compression
        self._zstd = zstandard.ZstdCompressor(level=compression_level) if compression == "zstd" else None
        self._fsync = fsync
        self._chunk_indexes = bytearray()   # the ChunkIndex records, as the summary holds them (~150 B a chunk,
        self.chunks = 0                     # far less than as ChunkIndex objects)
        self._metadata_indexes: list[MetadataIndex] = []
        self._counts: dict[int, int] = {}
        self._msg_start = 0
        self._msg_end = 0
        self._behind = ThreadPoolExecutor(1, thread_name_prefix="recorder") if behind else None
        self._pending: deque[Future] = deque()   # the chunks and records being written behind, in order
        self._f.write(MAGIC)
        self._put_record(Header(PROFILE, LIBRARY))

    def write_record(self, record) -> None:
        """Write one record to the data section after the chunks handed over before it; with ``behind``, on that
        thread too, so that a schema or channel first used mid-stream does not hold the owner up until the chunks
        in flight are written."""
        if self._behind is None:
            self._put_record(record)
        else:
            self._pending.append(self._behind.submit(self._put_record, record))

    def _put_record(self, record) -> int:
        """Write one record at the file's end now; return its length in bytes."""
        rb = RecordBuilder()
        record.write(rb)
        data = rb.end()
        self._f.write(data)
        return len(data)

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """``Recorder.add_metadata``."""
        self._drain()
        offset = self._f.tell()
        length = self._put_record(Metadata(name=name, metadata={k: str(v) for k, v in data.items()}))
        self._metadata_indexes.append(MetadataIndex(offset=offset, length=length, name=name))

    def flush(self, c: _OpenChunk) -> None:
        """Write the closed chunk ``c`` (when it has messages) and its message indexes, flush to the OS and fsync
        (if enabled); with ``behind``, hand it to the thread that does."""
        if self._behind is None:
            if c.count:
                self.write_chunk(b"".join(c.parts), c.start, c.end, c.index)
            self._sync()
        elif c.count:
            while len(self._pending) >= BEHIND_CHUNKS:
                self._pending.popleft().result()
            self._pending.append(self._behind.submit(self._write_behind, c.parts, c.start, c.end, c.index))

    def _sync(self) -> None:
        self._f.flush()
        if self._fsync:
            os.fsync(self._f.fileno())

    def _write_behind(self, parts: list[bytes], start: int, end: int, index: dict) -> None:
        """``write_chunk`` of the records ``parts`` joined, and ``_sync``, on the behind thread (the join too: it
        copies the whole chunk): the owner waits for it (``_drain``) before it touches the file or the chunk
        bookkeeping; chunks are written in the order they were handed over (one thread)."""
        self._write_data(b"".join(parts), start, end, index)
        self._sync()

    def write_chunk(self, data: bytes, start: int, end: int,
                    index: dict[int, list[tuple[np.ndarray, np.ndarray]]]) -> None:
        """``Recorder.write_chunk``."""
        self._drain()
        self._write_data(data, start, end, index)

    def _compress(self, data: bytes) -> tuple[bytes, int]:
        """A chunk's content compressed, and its CRC-32 (on the ``behind`` thread, if there is one)."""
        if self._compression == "zstd":
            compressed = self._zstd.compress(data)
        elif self._compression == "lz4":
            import lz4.frame

            compressed = lz4.frame.compress(data)
        else:
            compressed = data
        return compressed, crc32(data)

    def _drain(self) -> None:
        """Wait for the chunks and records written behind, if there are any (the first one's error is raised
        here)."""
        pending, self._pending = self._pending, deque()
        errors = [e for e in (f.exception() for f in pending) if e is not None]
        if errors:
            raise errors[0]

    def settle(self) -> None:
        """Wait for the chunks and records written behind (the first one's error is raised here), then stop the
        thread."""
        try:
            self._drain()
        finally:
            if self._behind is not None:
                self._behind.shutdown()

    def _write_data(self, data: bytes, start: int, end: int,
                    index: dict[int, list[tuple[np.ndarray, np.ndarray]]]) -> None:
        compressed, crc = self._compress(data)
        chunk = Chunk(
            compression=self._compression,
            data=compressed,
            message_start_time=start,
            message_end_time=end,
            uncompressed_crc=crc,
            uncompressed_size=len(data),
        )
        chunk_offset = self._f.tell()
        chunk_length = self._put_record(chunk)
        index_offsets: dict[int, int] = {}
        parts = []
        pos = chunk_offset + chunk_length
        for cid, pieces in index.items():
            t, o = _index_column(pieces, 0), _index_column(pieces, 1)
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
        self.chunks += 1
        self._msg_start = start if self.chunks == 1 else min(self._msg_start, start)
        self._msg_end = max(self._msg_end, end)

    def close(self, schemas: Mapping[int, Schema], channels: Mapping[int, Channel]) -> None:
        """Write DataEnd, the summary (``schemas``, ``channels``, statistics, chunk and metadata indexes, summary
        offsets), the footer and the closing magic; flush, fsync (if enabled) and close the file. After ``settle``:
        nothing is written behind any more."""
        self._put_record(DataEnd(0))
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

        group(Opcode.SCHEMA, list(schemas.values()))
        group(Opcode.CHANNEL, list(channels.values()))
        group(
            Opcode.STATISTICS,
            [
                Statistics(
                    attachment_count=0,
                    channel_count=len(channels),
                    channel_message_counts=dict(self._counts),
                    chunk_count=self.chunks,
                    message_count=sum(self._counts.values()),
                    message_end_time=self._msg_end,
                    message_start_time=self._msg_start,
                    metadata_count=len(self._metadata_indexes),
                    schema_count=len(schemas),
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
        self._put_record(Footer(summary_start, summary_offset_start, crc))
        self._f.write(MAGIC)
        self._f.flush()
        if self._fsync:
            os.fsync(self._f.fileno())
        self._f.close()

    def discard(self) -> None:
        """Stop the thread (dropping a chunk not begun) and remove the file (``outputs.Output.discard``)."""
        if self._behind is not None:
            self._behind.shutdown(cancel_futures=True)
        self._f.discard()


class Recorder(outputs.Closing):
    """Write a drive to one MCAP file.

    The recorder lays out message records into the open chunk (``_OpenChunk``) and decides when to close it; the
    file side (``_FileWriter``) writes records, chunks and the summary. Used in a ``with`` block, it is closed at
    its end, or discarded on an error (``outputs.Closing``).

    Parameters
    ----------
    path : output file, created new (``drive.outputs.create``: ``outputs.Refused`` if it exists, unless it is a
        regular file and ``force``; always if it is a symbolic link)
    chunk_size : uncompressed bytes per chunk before it is closed
    flush_interval_s : close and flush the open chunk once this much host monotonic time, s, has passed since the
        last flush (None: only by size or explicit ``flush()``, for offline writers that flush by data time)
    compression : "zstd", "lz4" or "" (none)
    metadata : written as an MCAP Metadata record named "drive" (string values; e.g. scenario, seed, config,
        calibration TOML, software version)
    fsync : fsync after every flush (power-cut safety)
    compression_level : zstd level (1 is about twice as fast as 3 on IMU data for ~5 % larger files)
    stats : gather what ``fieldlog info`` shows while writing and store it at close as the ``fieldlog.info``
        record (``drive.drivestats``); off for files whose chunks are copied as they are (``recover``)
    force : replace a regular file at ``path``
    root : the output folder ``path`` lies in, walked without following a link
    behind : compress and write each closed chunk (and the schema and channel records after it) on a thread
        while the caller goes on (at most ``BEHIND_CHUNKS`` chunks in flight), for offline writers: a chunk is
        sure to be in the file only at the next metadata record, copied chunk or ``close``, so ``flush`` does not
        bound what a power cut loses
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
        behind: bool = False,
    ) -> None:
        if compression not in ("zstd", "lz4", ""):
            raise ValueError(f"unknown compression {compression!r}")
        self.path = Path(path)
        self._chunk_size = chunk_size
        self._flush_interval_s = flush_interval_s
        self._schemas: dict[int, Schema] = {}
        self._schema_ids: dict[str, int] = {}
        self._channels: dict[int, Channel] = {}
        self._channel_ids: dict[str, int] = {}
        self._chunk = _OpenChunk()
        self._last_flush = time.monotonic()
        self.flush_seconds = 0.0  # host time spent in flush (compress + write + fsync)
        self.stats = DriveStats() if stats else None
        self.closed = False
        self._file = _FileWriter(outputs.create(self.path, force, root), compression, compression_level, fsync,
                                 behind)
        if metadata:
            self.add_metadata("drive", metadata)

    # -- records outside chunks --------------------------------------------------------------

    @property
    def channels(self) -> Mapping[int, Channel]:
        """The channels defined so far, by id (read only)."""
        return MappingProxyType(self._channels)

    @property
    def chunk_count(self) -> int:
        """Chunks written so far."""
        return self._file.chunks

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """Write a Metadata record.

        Parameters
        ----------
        name : the record's name
        data : its keys and values (values written as ``str(value)``)
        """
        self._file.add_metadata(name, data)

    def register(self, record: Schema | Channel) -> int:
        """Register a schema or channel record as it is (keeps its id), written on first use.

        Parameters
        ----------
        record : the record (a channel's schema registered before it)

        Returns
        -------
        int : its id
        """
        if isinstance(record, Schema):
            known, ids, name = self._schemas, self._schema_ids, record.name
        else:
            known, ids, name = self._channels, self._channel_ids, record.topic
        if record.id not in known:
            known[record.id] = record
            ids[name] = record.id
            self._file.write_record(record)
        return record.id

    def channel_id(self, topic: str) -> int:
        """Channel id of a contract topic, registering its schema and channel on first use.

        Parameters
        ----------
        topic : a topic of the data model (``messages.topic_type``)

        Returns
        -------
        int : its channel id
        """
        cid = self._channel_ids.get(topic)
        if cid is not None:
            return cid
        type_name = messages.topic_type(topic)
        sid = self._schema_ids.get(type_name)
        if sid is None:
            sid = self.register(
                Schema(
                    id=len(self._schemas) + 1,
                    name=type_name,
                    encoding=messages.SCHEMA_ENCODING,
                    data=messages.schema_text(type_name).encode(),
                )
            )
        return self.register(
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
        """Write one message.

        Parameters
        ----------
        topic : a topic of the data model (``channel_id``)
        log_time_ns : log time, UTC ns (> 0)
        data : the CDR payload
        publish_time_ns : publish time, UTC ns (None: ``log_time_ns``)
        """
        self.write_records(Records(topic, (log_time_ns,), (data,),
                                   None if publish_time_ns is None else (publish_time_ns,)))

    def write_records(self, recs: Records, i: int = 0, j: int | None = None) -> None:
        """``write`` of each of messages ``i`` to ``j - 1`` of ``recs`` in turn, in one call: the same records and
        chunks (a chunk is closed after the message that fills it), the flush by ``flush_interval_s`` checked
        once, at the end. For a writer with many single messages of one topic at once, which ``write_batch``
        would lay out in other chunks (it closes a chunk before the message that overfills it); ``recs`` is laid
        out at its first write, so a writer that writes many in pieces (``Pipeline.feed_reads``: a block's raw
        DAQ reads, a run of reads at a time) lays them out once.

        Parameters
        ----------
        recs : the messages
        i, j : the ones to write, ``recs``' i..j-1 (None: to the last)
        """
        j = len(recs) if j is None else j
        if i >= j:
            return
        laid = recs.laid_out(self.channel_id)
        times, starts = laid.log_times, laid.starts
        if self.stats is not None:
            self.stats.observe_messages(recs.topic, times[i:j], recs.payloads[i:j])
        while i < j:
            # up to the record that fills the open chunk (or all of them), then close it as write does
            a = starts[i]
            k = min(bisect_left(starts, a + self._chunk_size - self._chunk.size, i + 1, j + 1), j)
            self._chunk.add_block(laid.channel_id, times[i:k], laid.buf[a:starts[k]], [x - a for x in starts[i:k]])
            if self._chunk.size >= self._chunk_size:
                self.flush()
            i = k
        self.maybe_flush()

    def write_batch(
        self,
        topic: str,
        log_time_ns: np.ndarray,
        msgs: "messages.Packed | Sequence[bytes]",
        publish_time_ns: np.ndarray | None = None,
    ) -> None:
        """Write n messages of one topic (none: no channel either).

        Equal-length messages (fixed-layout types) are laid out as one byte matrix; a batch
        larger than the chunk size is split over several chunks.

        Parameters
        ----------
        topic : a topic of the data model (``channel_id``)
        log_time_ns : (n,) int64 log times, UTC ns, all > 0
        msgs : the n CDR payloads
        publish_time_ns : (n,) int64 publish times, UTC ns (None: ``log_time_ns``)
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
        """``write_batch`` to a channel already registered (``register``), for any topic and type.

        Parameters
        ----------
        channel_id : the channel's id
        log_time_ns : (n,) int64 log times, UTC ns, all > 0
        msgs : the n payloads, in the channel's encoding
        publish_time_ns : (n,) int64 publish times, UTC ns (None: ``log_time_ns``)
        """
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
        if n <= FEW:   # a record at a time, closing the open chunk before a message that would overfill it
            o = p.offsets.tolist()
            for t, q, a, b in zip(log_time_ns.tolist(), pub.tolist(), o, o[1:]):
                record = _MSG_HDR_STRUCT.pack(Opcode.MESSAGE, 22 + b - a, cid, 0, t, q) + p.buf[a:b].tobytes()
                if self._chunk.count and self._chunk.size + len(record) > self._chunk_size:
                    self.flush()
                self._chunk.add_block(cid, [t], record, [0])
                self.maybe_flush()
            return
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
            self._chunk.add(cid, log_time_ns[i:j], pub[i:j], p, i, j)
            self.maybe_flush()
            i = j

    def maybe_flush(self) -> None:
        """Flush if the open chunk is full or flush_interval_s of host time has passed (also from an idle loop)."""
        if self._chunk.size >= self._chunk_size or (
            self._flush_interval_s is not None and time.monotonic() - self._last_flush >= self._flush_interval_s
        ):
            self.flush()

    # -- chunks ------------------------------------------------------------------------------

    def flush(self) -> None:
        """Close the open chunk (if it has messages), write it and its message indexes,
        flush to the OS and fsync (if enabled); with ``behind``, hand it to the thread that does."""
        t0 = time.perf_counter()
        self._file.flush(self._chunk)
        if self._chunk.count:
            self._chunk = _OpenChunk()
        self._last_flush = time.monotonic()
        self.flush_seconds += time.perf_counter() - t0

    def write_chunk(
        self, data: bytes, start: int, end: int, index: dict[int, list[tuple[np.ndarray, np.ndarray]]]
    ) -> None:
        """Write message records as one chunk with its message indexes: the open chunk's flush, and recovery's
        copy of a file's chunks.

        Parameters
        ----------
        data : the message records (a chunk's content)
        start, end : the first and last log time of its messages, UTC ns
        index : channel id -> pieces of (log times, offsets into ``data``): uint64 arrays, or ints
            (``_OpenChunk``)
        """
        self._file.write_chunk(data, start, end, index)

    # -- finish ------------------------------------------------------------------------------

    def close(self) -> None:
        """Flush, then write DataEnd, the summary (schemas, channels, statistics, chunk and
        metadata indexes, summary offsets), the footer and the closing magic."""
        if self.closed:
            return
        try:
            self.flush()
        finally:
            self._file.settle()
        if self.stats is not None:   # after the last chunk: a file cut short keeps it only if all chunks are whole
            self.add_metadata(INFO_RECORD, self.stats.record())
        self._file.close(self._schemas, self._channels)
        self.closed = True

    def discard(self) -> None:
        """Stop writing and remove the file (``outputs.Output.discard``): what an offline writer does on an error,
        so that it leaves no half-written drive behind."""
        if self.closed:
            return
        self.closed = True
        self._file.discard()
