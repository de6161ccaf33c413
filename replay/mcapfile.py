"""One MCAP file in any valid layout, as pieces of messages to read.

An MCAP file is a sequence of records, and so is a chunk's content. ``McapFile`` memory-maps the file and walks
its top-level records once (``acquire.recorder.walk_records``: it reads only each record's 9-byte head, so it
jumps over chunk bodies; the first ``WALK_PLAIN`` records without numba, so ``info`` on a chunked file never
loads it). That one walk finds everything, whatever the writer chose to write:

- chunks (any compression) and the message index records after them (optional, per chunk);
- messages outside chunks (unchunked writers), grouped into runs of about ``LOOSE_RUN_BYTES``;
- schema and channel records in the data section, in the summary, or only inside chunks (found when the
  chunk is read);
- metadata records (``metadata()``); attachments are skipped.

The summary section (chunk indexes, statistics, summary offsets) is not needed: the walk gives the same
facts, so a file with or without a summary, indexes, statistics or summary offsets reads the same. A *piece*
is a chunk or a run of loose messages, with its log-time bounds and, when the file says so (message indexes,
or the headers of loose messages), the channels inside it.

Complete vs truncated: a valid file starts with the magic and ends with a Footer record followed by the
magic. Anything else (the walk stops before the end, no footer, no closing magic) is ``TruncatedError``:
"cut short, run ``fieldlog recover``". A file that is not MCAP at all is ``NotMcapError``. Both are
ValueErrors, so every command reports them in one line.
"""
from __future__ import annotations

import io
import mmap
import os
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Metadata, Schema

from fieldlog.acquire.recorder import ChunkMessages, decompress, messages_of, walk_records

MAGIC = b"\x89MCAP0\r\n"
WALK_PLAIN = 20_000  # top-level records walked without numba before the compiled walk takes over
LOOSE_RUN_BYTES = 4 << 20  # messages outside chunks are read in runs of about this many bytes
_CHUNK_HEAD = struct.Struct("<QQQII")  # start, end, uncompressed size, crc, compression length


class NotMcapError(ValueError):
    """The file is not MCAP (no magic)."""


class TruncatedError(ValueError):
    """The file is MCAP but cut short (no footer and closing magic)."""


@dataclass(eq=False, slots=True)
class Piece:
    """A chunk, or a run of messages outside chunks: bytes [offset, end) of the file."""

    file: "McapFile" = field(repr=False)
    offset: int  # chunk: start of the Chunk record; loose: start of the first record of the run
    end: int
    start_ns: int  # first / last log_time of its messages
    end_ns: int
    size: int  # uncompressed bytes
    chunk: bool
    channels: frozenset[int] | None  # channel ids inside, None when the file does not say (chunk without indexes)
    index: tuple[tuple[int, int, int], ...] = ()  # (channel, file offset of the entries, n) per message index


class McapFile:
    """A complete MCAP file, memory-mapped; raises ``NotMcapError`` / ``TruncatedError`` otherwise."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        with open(self.path, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            if size < len(MAGIC):
                raise NotMcapError(f"{self.path}: empty or not an MCAP file")
            self._mm = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        self.buf = np.frombuffer(self._mm, np.uint8)
        if self._mm[: len(MAGIC)] != MAGIC:
            raise NotMcapError(f"{self.path}: not an MCAP file")
        ops, starts, lengths, end = walk_records(self.buf, len(MAGIC), 1024, jit=False, limit=WALK_PLAIN)
        if len(ops) == WALK_PLAIN:  # many records (messages outside chunks, small chunks): the compiled walk
            more = walk_records(self.buf, end, (size - end) // 64 + 1)
            ops, starts, lengths = (np.concatenate(x) for x in zip((ops, starts, lengths), more[:3]))
            end = more[3]
        if not (len(ops) and ops[-1] == Opcode.FOOTER and end == size - len(MAGIC)
                and self._mm[size - len(MAGIC):] == MAGIC):
            raise TruncatedError(f"{self.path}: cut short (no footer): run `fieldlog recover {self.path}` first")
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        for op in (Opcode.SCHEMA, Opcode.CHANNEL):
            for i in np.flatnonzero(ops == op).tolist():
                self._define(self._record(op, int(starts[i]), int(lengths[i])))
        data_end = np.flatnonzero(ops == Opcode.DATA_END)
        n_data = int(data_end[0]) if len(data_end) else len(ops) - 1
        ops, starts, lengths = ops[:n_data], starts[:n_data], lengths[:n_data]
        self._metadata = [(int(starts[i]), int(lengths[i])) for i in np.flatnonzero(ops == Opcode.METADATA)]
        self.pieces = self._chunks(ops, starts, lengths) + self._loose(ops, starts, lengths)
        self._topics: dict[int, tuple[int, int, int]] | None = None

    # -- records -----------------------------------------------------------------------------

    def _record(self, op: int, start: int, length: int):
        stream = ReadDataStream(io.BytesIO(self._mm[start:start + length]))
        return {Opcode.SCHEMA: Schema, Opcode.CHANNEL: Channel, Opcode.METADATA: Metadata}[op].read(stream)

    def _define(self, r: Schema | Channel) -> None:
        (self.schemas if isinstance(r, Schema) else self.channels)[r.id] = r

    def metadata(self) -> list[Metadata]:
        """The metadata records in file order."""
        return [self._record(Opcode.METADATA, s, n) for s, n in self._metadata]

    def type_of(self, cid: int) -> str:
        schema = self.schemas.get(self.channels[cid].schema_id)
        return schema.name if schema is not None else ""

    # -- pieces ------------------------------------------------------------------------------

    def _chunks(self, ops: np.ndarray, starts: np.ndarray, lengths: np.ndarray) -> list[Piece]:
        ci = np.flatnonzero(ops == Opcode.CHUNK)
        mi = np.flatnonzero(ops == Opcode.MESSAGE_INDEX)
        owner = np.searchsorted(ci, mi) - 1  # a message index belongs to the chunk before it (nondecreasing)
        s = starts[mi]
        cid = (self.buf[s].astype(np.int64) | self.buf[s + 1].astype(np.int64) << 8).tolist()
        n = ((lengths[mi] - 6) // 16).tolist()
        off = (s + 6).tolist()
        bounds = np.searchsorted(owner, np.arange(len(ci) + 1)).tolist()
        cs = starts[ci]
        head = np.ascontiguousarray(self.buf[cs[:, None] + np.arange(24)]).view("<u8").reshape(-1, 3).tolist()
        out = []
        for k, (s0, ln, (t0, t1, usize)) in enumerate(zip(cs.tolist(), lengths[ci].tolist(), head)):
            a, b = bounds[k], bounds[k + 1]
            idx = tuple(zip(cid[a:b], off[a:b], n[a:b]))
            chans = frozenset(cid[a:b]) if idx else None  # writers index only channels with messages
            out.append(Piece(self, s0 - 9, s0 + ln, t0, t1, usize, True, chans, idx))
        return out

    def _loose(self, ops: np.ndarray, starts: np.ndarray, lengths: np.ndarray) -> list[Piece]:
        """Runs of consecutive message records outside chunks (other records between them are kept in the
        run: chunk_messages skips them)."""
        msg = np.flatnonzero((ops == Opcode.MESSAGE) & (lengths >= 22))
        if not len(msg):
            return []
        barrier = np.flatnonzero(ops == Opcode.CHUNK)
        run_of = np.searchsorted(barrier, msg)  # messages between the same two chunks
        s = starts[msg]
        pos = (s[:, None] + np.arange(8)).astype(np.int64)
        cid = self.buf[s].astype(np.int64) | self.buf[s + 1].astype(np.int64) << 8
        t = np.ascontiguousarray(self.buf[pos + 6]).view("<i8").ravel()
        rec_start = s - 9
        rec_end = s + lengths[msg]
        brk = np.flatnonzero(np.diff(run_of) != 0) + 1
        out = []
        for a, b in zip(np.r_[0, brk].tolist(), np.r_[brk, len(msg)].tolist()):
            while a < b:  # split a long run into pieces of about LOOSE_RUN_BYTES
                j = min(int(np.searchsorted(rec_end[a:b], rec_start[a] + LOOSE_RUN_BYTES, side="right")) + a, b)
                j = max(j, a + 1)
                o0, o1 = int(rec_start[a]), int(rec_end[j - 1])
                out.append(Piece(self, o0, o1, int(t[a:j].min()), int(t[a:j].max()), o1 - o0, False,
                                 frozenset(np.unique(cid[a:j]).tolist())))
                a = j
        return out

    def records(self, piece: Piece) -> bytes | memoryview:
        """The uncompressed records of a piece (a chunk's content, or the run's bytes in place)."""
        if not piece.chunk:
            return memoryview(self._mm)[piece.offset:piece.end]
        s = piece.offset + 9
        t0, t1, usize, crc, clen = _CHUNK_HEAD.unpack_from(self._mm, s)
        comp = self._mm[s + 32:s + 32 + clen].decode()
        p = s + 32 + clen
        (rlen,) = struct.unpack_from("<Q", self._mm, p)
        return decompress(comp, memoryview(self._mm)[p + 8:p + 8 + rlen], usize, crc)

    def read(self, pieces: list[Piece]) -> ChunkMessages:
        """The messages of ``pieces`` (of this file) as one batch: their records joined and walked once; schema
        and channel records found inside are added to the file's tables."""
        parts = [self.records(p) for p in pieces]
        data = parts[0] if len(parts) == 1 else b"".join(parts)
        buf = np.frombuffer(data, np.uint8)
        ops, starts, lengths, _ = walk_records(buf, 0, len(buf) // 31 + 1)
        for op in (Opcode.SCHEMA, Opcode.CHANNEL):
            for i in np.flatnonzero(ops == op).tolist():
                stream = ReadDataStream(io.BytesIO(buf[starts[i]:starts[i] + lengths[i]].tobytes()))
                self._define((Schema if op == Opcode.SCHEMA else Channel).read(stream))
        return messages_of(buf, ops, starts, lengths)

    # -- per channel -------------------------------------------------------------------------

    def message_counts(self) -> dict[int, int] | None:
        """channel id -> message count from the message indexes alone (no read); None when a chunk has none or
        messages are outside chunks (``channel_stats`` counts those)."""
        if any(not p.chunk or p.channels is None for p in self.pieces):
            return None
        out: dict[int, int] = {}
        for p in self.pieces:
            for cid, _, n in p.index:
                out[cid] = out.get(cid, 0) + n
        return out

    def channel_stats(self) -> dict[int, tuple[int, int, int]]:
        """channel id -> (message count, first log_time, last log_time): from the message indexes and the
        loose messages' headers; a chunk without message indexes is read (once per file object)."""
        if self._topics is not None:
            return self._topics
        stats: dict[int, tuple[int, int, int]] = {}

        def add(cid: int, t: np.ndarray) -> None:
            if len(t):
                n, lo, hi = stats.get(cid, (0, int(t.min()), int(t.max())))
                stats[cid] = (n + len(t), min(lo, int(t.min())), max(hi, int(t.max())))

        for p in self.pieces:
            if p.chunk and p.channels is not None:
                for cid, off, n in p.index:
                    add(cid, np.frombuffer(self._mm, "<u8", count=2 * n, offset=off)[0::2].astype(np.int64))
            else:
                cm = self.read([p])
                for cid in np.unique(cm.channel_id).tolist():
                    add(int(cid), cm.log_time[cm.channel_id == cid])
        self._topics = stats
        return stats
