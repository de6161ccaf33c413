"""One MCAP file in any valid layout, as pieces of messages to read.

An MCAP file is a sequence of records, and so is a chunk's content. ``McapFile`` memory-maps the file and finds
what it holds, whatever the writer chose to write:

- chunks (any compression) and the message index records after them (optional, per chunk);
- messages outside chunks (unchunked writers), grouped into runs of about ``LOOSE_RUN_BYTES``;
- schema and channel records in the data section, in the summary, or only inside chunks (found when the
  chunk is read);
- metadata records (``metadata()``); attachments are skipped.

When the file has a summary with chunk indexes, the chunk table comes from them, as every MCAP reader does: the
summary's CRC (when the footer has one) is checked, each chunk index must point at a chunk record, its message index
offsets must tile the bytes after that chunk (without a CRC, each message index record is read and must agree with
the summary), and the few records of the data section between the listed chunks (header, schemas, channels,
metadata, attachments, data end) are walked: a message, chunk or message index among them (messages outside chunks,
which no chunk index lists) sends the file to the walk. Otherwise (no summary or no chunk indexes, a summary that
does not check out, a truncated file) the file's top-level records are walked once (``drive.chunks.walk_records``:
it reads only each record's 9-byte head, so it jumps over chunk bodies). Both give the same table, so a file with or
without a summary, indexes, statistics or summary offsets reads the same; a file of many small chunks opens faster
from its summary than walked. A *piece* is a chunk or a run of loose messages, with its log-time bounds and, when
the file says so (message indexes, or the headers of loose messages), the channels inside it. The pieces are held as
arrays (``Pieces``, one row per piece), never as one Python object each: a file of 4 KiB chunks has tens of
thousands of them, and the walk, the choice of pieces for some topics and the reading of a group of them are all
vectorised (a group's chunks are decompressed, checked against their CRC-32s and walked in one compiled pass that
keeps the records of the topics asked for: ``chunks.read_chunks``).

Complete vs truncated: a valid file starts with the magic and ends with a Footer record followed by the
magic. Anything else (the walk stops before the end, no footer, no closing magic) is ``TruncatedError``:
"cut short, run ``fieldlog recover``", unless the walk passed the Data End record: then the data section is
whole and the damaged or cut summary is left out (as are damaged schema or channel copies in it). A file that
is not MCAP at all is ``NotMcapError``; a chunk whose fields overrun its record, or whose content does not
decompress to its size and CRC, is ``ValueError`` naming its byte offset. All are ValueErrors, so every command
reports them in one line.
"""
from __future__ import annotations

import io
import logging
import mmap
import os
import struct
import threading
from dataclasses import dataclass
from typing import Callable, Collection
from pathlib import Path

import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Metadata, Schema

from zlib_ng.zlib_ng import crc32

from fieldlog.drive.chunks import ChunkError, ChunkMessages, decompress_many, le, read_chunks, walk_records
from fieldlog.drive.recorder import MAGIC

log = logging.getLogger(__name__)
LOOSE_RUN_BYTES = 4 << 20  # messages outside chunks are read in runs of about this many bytes
STATS_ENTRIES = 1 << 18  # message index entries read at a time by ``channel_stats``
PEEK_SPAN = 1 << 24  # bytes of file whose scattered reads (one per chunk or index) are gathered at a time
WALK_WINDOW = 1 << 26  # bytes of file a walk over a file's top-level records takes at a time
FAULT_AROUND = 1 << 16  # bytes the kernel may map around a byte read through the file's mapping (fault-around)
READ_BYTES = 4 << 20  # consecutive pieces (small chunks, loose runs) are read together up to about this many bytes
_CHUNK_HEAD = np.dtype({"names": ["start", "end", "size", "crc", "comp_len"],
                        "formats": ["<u8", "<u8", "<u8", "<u4", "<u4"], "offsets": [0, 8, 16, 24, 28], "itemsize": 32})
_CHUNK_INDEX_HEAD = np.dtype({"names": ["offset", "length", "map_len"], "formats": ["<u8", "<u8", "<u4"],
                              "offsets": [16, 24, 32], "itemsize": 36})
_CHUNK_INDEX_TAIL = np.dtype({"names": ["mi_len", "comp_len"], "formats": ["<u8", "<u4"], "offsets": [0, 8],
                              "itemsize": 12})
_MAP_ENTRY = np.dtype({"names": ["channel", "offset"], "formats": ["<u2", "<u8"], "offsets": [0, 2], "itemsize": 10})
_RECORD_HEAD = np.dtype({"names": ["op", "length"], "formats": ["u1", "<u8"], "offsets": [0, 1], "itemsize": 9})
_INDEX_HEAD = np.dtype({"names": ["op", "length", "channel"], "formats": ["u1", "<u8", "<u2"], "offsets": [0, 1, 9],
                        "itemsize": 11})
FOOTER_HEAD = struct.pack("<BQ", Opcode.FOOTER, 20)
MAX_GAPS = 64  # more runs of records between the summary's chunks than this: walk the file instead
_NOT_IN_GAPS = [Opcode.MESSAGE, Opcode.CHUNK, Opcode.MESSAGE_INDEX, Opcode.FOOTER]
_MESSAGE_HEAD = np.dtype({"names": ["channel", "log_time"], "formats": ["<u2", "<i8"], "offsets": [0, 6],
                          "itemsize": 14})


_SCRATCH = threading.local()
SCRATCH_MAX = 64 << 20  # a read needing more gets buffers of its own, not kept


def _scratch(stage: int, batch: int) -> tuple[np.ndarray, np.ndarray]:
    """Buffers of ``stage`` and ``batch`` bytes for ``chunks.read_chunks``: this thread's, reused, so their pages
    are touched once (a fresh 4 MB buffer per read costs as much in page faults as decompressing 4 KiB chunks)."""
    if stage + batch > SCRATCH_MAX:
        return np.empty(stage, np.uint8), np.empty(batch, np.uint8)
    bufs = getattr(_SCRATCH, "bufs", None)
    if bufs is None or len(bufs[0]) < stage or len(bufs[1]) < batch:
        n = (stage, batch) if bufs is None else (max(stage, len(bufs[0])), max(batch, len(bufs[1])))
        bufs = _SCRATCH.bufs = (np.empty(n[0], np.uint8), np.empty(max(n[1], 2 * READ_BYTES), np.uint8))
    return bufs


class NotMcapError(ValueError):
    """The file is not MCAP (no magic)."""


class TruncatedError(ValueError):
    """The file is MCAP but cut short (no footer and closing magic)."""


@dataclass(eq=False)
class Pieces:
    """A file's pieces, row i = piece i: its chunks in file order, then its runs of messages outside chunks."""

    offset: np.ndarray  # int64: chunk: start of the Chunk record; loose run: start of its first record
    end: np.ndarray  # int64: end of the piece's bytes in the file
    start_ns: np.ndarray  # int64: first / last log_time of its messages
    end_ns: np.ndarray
    size: np.ndarray  # int64: uncompressed bytes
    chunk: np.ndarray  # bool
    indexed: np.ndarray  # bool: the file says which channels are inside (message indexes; loose headers)
    cids: np.ndarray  # int64: the channel ids named by the indexes and loose headers (the columns of ``has``)
    has: np.ndarray  # bool (piece, column of ``cids``): messages of that channel inside (indexed pieces)
    body: np.ndarray  # int64: file offset of the (compressed) records: a chunk's records field, a loose run's start
    body_len: np.ndarray  # int64: their length in the file
    comp: np.ndarray  # int64 (chunk pieces): index into ``McapFile.compressions``
    crc: np.ndarray  # int64 (chunk pieces): CRC-32 of the uncompressed records (0: none)

    def __len__(self) -> int:
        return len(self.offset)


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
        laid = self._from_summary(size)
        self.from_summary = laid is not None  # the chunk table came from the summary's chunk indexes
        if laid is None:
            laid = self._from_walk(size)
        top, chunks, index, loose = laid
        ops, starts, lengths = top
        data_end = np.flatnonzero(ops == Opcode.DATA_END)
        n_data = int(data_end[0]) if len(data_end) else len(ops)
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        for op in (Opcode.SCHEMA, Opcode.CHANNEL):
            for i in np.flatnonzero(ops == op).tolist():
                try:
                    r = self._record(op, int(starts[i]), int(lengths[i]))
                except Exception as e:  # a damaged record: the summary's copy is left out, the data section's named
                    if i >= n_data:
                        continue
                    raise ValueError(f"{self.path}: damaged {Opcode(op).name.lower()} record at byte "
                                     f"{int(starts[i]) - 9} ({e}): the file cannot be read as it is") from None
                self._define(r)
        self._metadata = [(int(starts[i]), int(lengths[i])) for i in np.flatnonzero(ops[:n_data] == Opcode.METADATA)]
        self.compressions: list[str] = []
        self.pieces = self._pieces(*chunks, *index, loose)
        self._topics: dict[int, tuple[int, int, int]] | None = None
        self._drop(0, size)  # what the layout read (summary, definitions): its pages go back too

    # -- records -----------------------------------------------------------------------------

    def _record(self, op: int, start: int, length: int):
        stream = ReadDataStream(io.BytesIO(self._mm[start:start + length]))
        return {Opcode.SCHEMA: Schema, Opcode.CHANNEL: Channel, Opcode.METADATA: Metadata}[op].read(stream)

    def _define(self, r: Schema | Channel) -> None:
        """The first record of an id counts (MCAP: repeats are copies): the data section's, not the summary's copy,
        which a damaged summary without a CRC could hold wrong."""
        (self.schemas if isinstance(r, Schema) else self.channels).setdefault(r.id, r)

    def metadata(self) -> list[Metadata]:
        """The metadata records in file order; a damaged one (its fields overrun it, a name or value is not
        UTF-8) is left out with a warning naming it: the messages can still be read."""
        out = []
        for s, n in self._metadata:
            try:
                out.append(self._record(Opcode.METADATA, s, n))
            except Exception as e:  # noqa: BLE001 - the mcap library's EndOfFile, UnicodeDecodeError, struct.error
                log.warning("warning: %s: damaged metadata record at byte %d (%s: %s) left out", self.path, s - 9,
                            type(e).__name__, e)
        return out

    def type_of(self, cid: int) -> str:
        schema = self.schemas.get(self.channels[cid].schema_id)
        return schema.name if schema is not None else ""

    # -- pieces ------------------------------------------------------------------------------

    def _walk(self, pos: int, end: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        """The records from ``pos`` up to ``end``, ``WALK_WINDOW`` bytes of file at a time, each window's pages
        handed back (``_drop``): the walk reads each record's head, and the kernel maps the pages around it."""
        parts = []
        while True:
            hi = min(end, pos + WALK_WINDOW)
            if end - pos >= 9:  # a record longer than the window: the window takes it whole
                hi = max(hi, min(end, pos + 9 + int.from_bytes(self._mm[pos + 1:pos + 9], "little")))
            ops, starts, lengths, stop = walk_records(self.buf[:hi], pos, (hi - pos) // 64 + 1)
            parts.append((ops, starts, lengths))
            self._drop(pos - FAULT_AROUND, stop + FAULT_AROUND)
            if hi == end or stop == pos:
                return (*(np.concatenate(x) for x in zip(*parts)), stop)
            pos = stop

    def _from_walk(self, size: int) -> tuple:
        """The layout from one walk over every top-level record: (the records (ops, starts, lengths): every one
        but the chunks, message indexes and loose messages' use is read from them; the chunks (content start,
        length); the message indexes (chunk, content start, length); the loose runs)."""
        ops, starts, lengths, end = self._walk(len(MAGIC), size)
        data_end = np.flatnonzero(ops == Opcode.DATA_END)
        if not (len(ops) and ops[-1] == Opcode.FOOTER and end == size - len(MAGIC)
                and self._mm[size - len(MAGIC):] == MAGIC):
            if not len(data_end):
                raise TruncatedError(f"{self.path}: cut short (no footer): run `fieldlog recover {self.path}` first")
            # the data section is whole (its end record is there): a damaged or cut summary is left out
            ops, starts, lengths = (x[:int(data_end[0]) + 1] for x in (ops, starts, lengths))
        n = int(data_end[0]) if len(data_end) else len(ops) - 1
        d_ops, d_starts, d_lengths = ops[:n], starts[:n], lengths[:n]
        ci = np.flatnonzero(d_ops == Opcode.CHUNK)
        mi = np.flatnonzero(d_ops == Opcode.MESSAGE_INDEX)
        owner = np.cumsum(d_ops == Opcode.CHUNK)[mi] - 1  # a message index belongs to the chunk before it
        mi, owner = mi[owner >= 0], owner[owner >= 0]
        cid = le(self.buf, d_starts[mi], "<u2").astype(np.int64)
        return ((ops, starts, lengths), (d_starts[ci], d_lengths[ci]), (owner, cid, d_starts[mi], d_lengths[mi]),
                self._loose(d_ops, d_starts, d_lengths))

    def _from_summary(self, size: int) -> tuple | None:
        """The layout of ``_from_walk`` from the summary's chunk indexes, or None (walk the file instead) unless
        the file is complete and its summary checks out: its CRC (when the footer has one), every chunk index
        pointing at a chunk record, its message indexes tiling the bytes after the chunk, and the data section
        between those chunks and indexes walked (a few records: header, schemas, channels, metadata, attachments,
        data end) holding no message, chunk or message index the summary does not list."""
        foot = size - len(MAGIC) - 29
        if foot < len(MAGIC) or self._mm[size - len(MAGIC):] != MAGIC or self._mm[foot:foot + 9] != FOOTER_HEAD:
            return None
        start, _, crc = struct.unpack_from("<QQI", self._mm, foot + 9)
        if not len(MAGIC) < start < foot or (crc and crc32(self._mm[start:foot + 25]) != crc):
            return None
        s_ops, s_starts, s_lengths, end = self._walk(int(start), size)
        if end != size - len(MAGIC) or not len(s_ops) or s_ops[-1] != Opcode.FOOTER or s_starts[-1] != foot + 9:
            return None
        k = np.flatnonzero(s_ops == Opcode.CHUNK_INDEX)
        s, rec_end = s_starts[k], s_starts[k] + s_lengths[k]
        if not len(k) or (s_lengths[k] < 64).any():
            return None
        buf, lim = self.buf, np.uint64(start)
        head = le(buf, s, _CHUNK_INDEX_HEAD)
        co, clen, mlen = head["offset"], head["length"], head["map_len"].astype(np.int64)
        if (co >= lim).any() or (clen >= lim).any() or (s + 36 + mlen + 12 > rec_end).any() or (mlen % 10).any():
            return None
        co, clen, at = co.astype(np.int64), clen.astype(np.int64), s + 36 + mlen
        tail = le(buf, at, _CHUNK_INDEX_TAIL)
        mil = tail["mi_len"]
        if (mil >= lim).any() or (at + 12 + tail["comp_len"] + 16 > rec_end).any():
            return None
        iv_end = co + clen + mil.astype(np.int64)  # the chunk record and its message indexes
        if ((co < len(MAGIC)) | (clen < 49) | (iv_end > start)).any() or (co[1:] < iv_end[:-1]).any():
            return None
        rec = self._peek(co, _RECORD_HEAD)
        if (rec["op"] != Opcode.CHUNK).any() or (rec["length"] != (clen - 9).astype(np.uint64)).any():
            return None
        index = self._summary_index(s, mlen // 10, co + clen, iv_end, crc != 0)
        gaps = self._gaps(np.r_[len(MAGIC), iv_end], np.r_[co, start])
        if index is None or gaps is None:
            return None
        top = tuple(np.concatenate(x) for x in zip(gaps, (s_ops, s_starts, s_lengths)))
        return top, (co + 9, clen - 9), index, []

    def _summary_index(self, s: np.ndarray, n: np.ndarray, a: np.ndarray, b: np.ndarray, checked: bool
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
        """The message index records listed by the chunk indexes at ``s`` (``n`` entries each) as ``_pieces``
        takes them (chunk, channel, content start, length), or None unless each chunk's records fill its bytes
        ``a``..``b`` one after the other, with their opcode. ``checked`` (the summary's CRC held): their
        channels as the summary lists them; else each record's channel and length are read and must agree (one
        random read per record, cheap against the walk)."""
        owner = np.repeat(np.arange(len(s)), n)
        first = np.cumsum(n) - n
        e = le(self.buf, np.repeat(s + 36 - 10 * first, n) + 10 * np.arange(int(n.sum())), _MAP_ENTRY)
        off, cid = e["offset"], e["channel"].astype(np.int64)
        if (off < a[owner].astype(np.uint64)).any() or (off >= b[owner].astype(np.uint64)).any():
            return None
        off = off.astype(np.int64)
        if (np.diff(off) <= 0).any():  # each lies in its chunk's bytes: sorted by offset, each chunk's stay together
            order = np.argsort(off)
            owner, off, cid = owner[order], off[order], cid[order]
        last = np.r_[owner[1:] != owner[:-1], True]
        rec_end = np.where(last, b[owner], np.r_[off[1:], 0])
        first_of = np.r_[True, last[:-1]]
        bare = np.bincount(owner, minlength=len(a)) == 0
        if (rec_end - off < 15).any() or (off[first_of] != a[owner[first_of]]).any() or (a[bare] != b[bare]).any():
            return None
        if checked:
            ok = self._peek(off, np.uint8) == Opcode.MESSAGE_INDEX
        else:
            rec = self._peek(off, _INDEX_HEAD)
            ok = (rec["op"] == Opcode.MESSAGE_INDEX) & (rec["length"] == (rec_end - off - 9).astype(np.uint64)) & (
                rec["channel"] == cid)
        return (owner, cid, off + 9, rec_end - off - 9) if ok.all() else None

    def _gaps(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The records in the file's bytes ``lo[i]``..``hi[i]`` (between the chunks the summary lists), or None
        when they do not walk exactly or hold a message, chunk or message index (a summary that leaves them out)."""
        parts = []
        for a, b in zip(lo[hi > lo].tolist(), hi[hi > lo].tolist()):
            if len(parts) >= MAX_GAPS:
                return None
            ops, starts, lengths, end = walk_records(self.buf[:b], a, 64)
            if end != b or np.isin(ops, _NOT_IN_GAPS).any():
                return None
            parts.append((ops, starts, lengths))
        return tuple(np.concatenate(x) for x in zip(*parts)) if parts else (
            np.zeros(0, np.uint8), np.zeros(0, np.int64), np.zeros(0, np.int64))

    def _pieces(self, cs: np.ndarray, clen_rec: np.ndarray, owner: np.ndarray, ix_cid: np.ndarray, s: np.ndarray,
                mi_len: np.ndarray, lo_rows: list) -> Pieces:
        """The chunks (content start ``cs``, length ``clen_rec``) and the loose runs, as one table; the message
        indexes (chunk ``owner``, channel ``ix_cid``, content start ``s``, length ``mi_len``) kept per piece."""
        self._index = (owner, ix_cid, s + 6, (mi_len - 6) // 16)  # piece, channel, entries' offset, count
        bad = clen_rec < 40
        if bad.any():
            raise ValueError(f"{self.path}: corrupt chunk at byte {int(cs[bad][0]) - 9}")
        head = self._peek(cs, _CHUNK_HEAD)
        t0, t1, usize, crc, clen = (head[k].astype(np.int64) for k in _CHUNK_HEAD.names)
        bad = clen > clen_rec - 40
        rlen = self._peek(np.where(bad, cs, cs + 32 + clen), "<u8")
        bad |= rlen > (clen_rec - 40 - clen).clip(0).astype(np.uint64)
        if bad.any():
            raise ValueError(f"{self.path}: corrupt chunk at byte {int(cs[bad][0]) - 9}")
        comp = self._compressions(cs + 32, clen)
        cids = np.flatnonzero(np.bincount(np.concatenate([ix_cid, *[r[4] for r in lo_rows]]), minlength=1))
        n_c, n = len(cs), len(cs) + len(lo_rows)
        has = np.zeros((n, len(cids)), bool)
        has[owner, np.searchsorted(cids, ix_cid)] = True
        for k, r in enumerate(lo_rows):
            has[n_c + k, np.searchsorted(cids, r[4])] = True
        indexed = np.ones(n, bool)
        indexed[:n_c] = np.bincount(owner, minlength=n_c) > 0  # writers index only channels with messages
        z = np.zeros(len(lo_rows), np.int64)
        lo = np.array([r[:4] for r in lo_rows], np.int64).reshape(-1, 4).T  # offset, end, start_ns, end_ns
        return Pieces(offset=np.r_[cs - 9, lo[0]], end=np.r_[cs + clen_rec, lo[1]], start_ns=np.r_[t0, lo[2]],
                      end_ns=np.r_[t1, lo[3]], size=np.r_[usize, lo[1] - lo[0]],
                      chunk=np.r_[np.ones(n_c, bool), np.zeros(len(lo_rows), bool)], indexed=indexed, cids=cids,
                      has=has, body=np.r_[cs + 40 + clen, lo[0]], body_len=np.r_[rlen.astype(np.int64), lo[1] - lo[0]],
                      comp=np.r_[comp, z], crc=np.r_[crc, z])

    def _compressions(self, at: np.ndarray, n: np.ndarray) -> np.ndarray:
        """The compression name of each chunk (``n`` bytes at ``at``), as indexes into ``self.compressions``."""
        w = int(n.max()) if len(n) else 0
        if w > 16:
            raise ValueError(f"{self.path}: unknown chunk compression at byte {int(at[np.argmax(n)]) - 41}")
        j = np.arange(max(w, 1))
        take = j < n[:, None]
        pos = np.where(take, at[:, None] + j, at[:, None])
        raw = np.ascontiguousarray(np.where(take, self._peek(pos.ravel(), np.uint8).reshape(pos.shape), 0))
        raw = raw.view(f"S{max(w, 1)}").ravel()
        if len(raw) and (raw == raw[0]).all():  # the usual file: one compression
            names, inv = raw[:1], np.zeros(len(raw), np.int64)
        else:
            names, inv = np.unique(raw, return_inverse=True)
        self.compressions = [x.decode("latin-1") for x in names.tolist()]
        return inv.astype(np.int64).ravel()

    def _loose(self, ops: np.ndarray, starts: np.ndarray, lengths: np.ndarray
               ) -> list[tuple[int, int, int, int, np.ndarray]]:
        """Runs of consecutive message records outside chunks (other records between them are kept in the
        run: ``read`` skips them): (offset, end, first and last log_time, channel ids) per run."""
        msg = np.flatnonzero((ops == Opcode.MESSAGE) & (lengths >= 22))
        if not len(msg):
            return []
        run_of = np.searchsorted(np.flatnonzero(ops == Opcode.CHUNK), msg)  # messages between the same two chunks
        s = starts[msg]
        head = le(self.buf, s, _MESSAGE_HEAD)
        cid, t = head["channel"].astype(np.int64), head["log_time"]
        rec_start, rec_end = s - 9, s + lengths[msg]
        brk = np.flatnonzero(np.diff(run_of) != 0) + 1
        out = []
        for a, b in zip(np.r_[0, brk].tolist(), np.r_[brk, len(msg)].tolist()):
            while a < b:  # split a long run into pieces of about LOOSE_RUN_BYTES
                j = min(int(np.searchsorted(rec_end[a:b], rec_start[a] + LOOSE_RUN_BYTES, side="right")) + a, b)
                j = max(j, a + 1)
                out.append((int(rec_start[a]), int(rec_end[j - 1]), int(t[a:j].min()), int(t[a:j].max()),
                            np.unique(cid[a:j])))
                a = j
        return out

    def may_hold(self, cids: set[int] | list[int]) -> np.ndarray:
        """Per piece: whether it may hold messages of channels ``cids`` (it does not say which channels it
        holds, or it holds one of them, or one not defined yet: defined inside a chunk)."""
        p = self.pieces
        cols = np.isin(p.cids, list(cids)) | ~np.isin(p.cids, list(self.channels))
        return ~p.indexed | p.has[:, cols].any(axis=1)

    @staticmethod
    def groups(idx: np.ndarray, size: np.ndarray) -> list[np.ndarray]:
        """``idx`` (pieces to read in this order, with uncompressed ``size``) cut into consecutive groups of
        about ``READ_BYTES``."""
        c = np.cumsum(size) // READ_BYTES
        return np.split(idx, np.flatnonzero(np.diff(c)) + 1) if len(idx) else []

    def records(self, i: int) -> bytes | memoryview:
        """The uncompressed records of piece ``i`` (a chunk's content, or the run's bytes in place)."""
        return self._bodies(np.array([i]))

    def _bodies(self, idx: np.ndarray) -> bytes | memoryview:
        """The uncompressed records of pieces ``idx``, joined; ``ValueError`` naming the first damaged chunk."""
        return self._chunks(decompress_many, idx)

    def _chunks(self, read: Callable, idx: np.ndarray, *args: object):
        """``read`` (``chunks.decompress_many`` or ``read_chunks``) over pieces ``idx``; ``ValueError`` naming
        the first damaged chunk."""
        try:
            return self._call(read, idx, *args)
        except ChunkError as e:
            raise ValueError(f"{self.path}: damaged chunk at byte {int(self.pieces.offset[idx[e.index]])}: {e} "
                             f"(`fieldlog recover {self.path}` keeps every other chunk)") from None

    def _call(self, read: Callable, idx: np.ndarray, *args: object):
        """``read`` over pieces ``idx`` (``ChunkError``: the first damaged one's position in ``idx``)."""
        p = self.pieces
        comp = np.where(p.chunk[idx], p.comp[idx], len(self.compressions))  # "": loose runs
        out = read(self._mm, [*self.compressions, ""], comp, p.body[idx], p.body_len[idx],
                   np.where(p.chunk[idx], p.size[idx], p.body_len[idx]), p.crc[idx], *args)
        if len(idx):
            lo, hi = int(p.body[idx].min()), int((p.body[idx] + p.body_len[idx]).max())
            self._drop(lo - FAULT_AROUND, hi + FAULT_AROUND)
        return out

    def _drop(self, lo: int, hi: int) -> None:
        """Hand the mapped pages of bytes [lo, hi) back: a drive is read once, front to back, so its pages need
        not stay in this process's resident memory (the page cache keeps them, and a later read faults them in
        again); reading a drive of any length then takes the same memory."""
        lo, hi = max(lo, 0), min(hi, len(self._mm))
        start = lo - lo % mmap.PAGESIZE
        if hi > start:
            self._mm.madvise(mmap.MADV_DONTNEED, start, hi - start)

    def _peek(self, pos: np.ndarray, dtype: str | np.dtype) -> np.ndarray:
        """``le(self.buf, pos, dtype)`` at positions scattered over the file (in file order), those within each
        ``PEEK_SPAN`` of file at a time, each span's pages handed back (``_drop``): the kernel maps up to
        ``FAULT_AROUND`` bytes around each byte read, so gathering one value per chunk of a long drive at once
        would map much of it."""
        pos = np.asarray(pos, np.int64)
        cuts = np.flatnonzero(np.diff(pos // PEEK_SPAN)) + 1
        parts = [le(self.buf, pos[:0], dtype)]
        for p in np.split(pos, cuts) if len(pos) else []:
            parts.append(le(self.buf, p, dtype))
            self._drop(int(p.min()) - FAULT_AROUND, int(p.max()) + FAULT_AROUND)
        return np.concatenate(parts)

    def damaged(self) -> list[int]:
        """Byte offsets of the chunks whose content does not decompress to its size and CRC-32 (what ``fieldlog
        recover`` skips): each chunk decompressed and checked once, in groups, nothing copied out."""
        p = self.pieces
        todo, out = np.flatnonzero(p.chunk), []
        none = np.zeros(1 << 16, bool)
        for g in self.groups(todo, p.size[todo]):
            while len(g):
                try:
                    self._call(read_chunks, g, none, _scratch)
                    break
                except ChunkError as e:
                    out.append(int(p.offset[g[e.index]]))
                    g = g[e.index + 1:]
        return out

    def _want(self, topics: Collection[str] | None) -> np.ndarray:
        """Per channel id (65536): read its messages (on ``topics``; every channel when None)."""
        if topics is None:
            return np.ones(1 << 16, bool)
        want = np.zeros(1 << 16, bool)
        want[[c for c, ch in self.channels.items() if ch.topic in topics]] = True
        return want

    def read(self, idx: np.ndarray | list[int], topics: Collection[str] | None = None) -> ChunkMessages:
        """The messages of pieces ``idx`` (of this file) as one batch (only those on ``topics``, when given):
        their records walked once (``chunks.read_chunks``); schema and channel records found inside are added to
        the file's tables (and the pieces read again when they define a channel on ``topics``). The batch's
        ``data`` may be this thread's read buffer (``_scratch``): it holds until the next read in the thread, so
        take what you keep (``ChunkMessages.packed`` copies) before the next."""
        idx = np.asarray(idx, np.int64)
        want = self._want(topics)
        cm, defs = self._chunks(read_chunks, idx, want, _scratch)
        if defs:
            for op, start, length in defs:
                stream = ReadDataStream(io.BytesIO(cm.data[start:start + length].tobytes()))
                try:
                    r = (Schema if op == Opcode.SCHEMA else Channel).read(stream)
                except Exception as e:  # a writer's bad record (its chunk's CRC held)
                    raise ValueError(f"{self.path}: a damaged {Opcode(op).name.lower()} record inside the chunks "
                                     f"from byte {int(self.pieces.offset[idx[0]])} ({e}): the file cannot be read "
                                     f"as it is") from None
                self._define(r)
            if not np.array_equal(want, self._want(topics)):
                cm, _ = self._chunks(read_chunks, idx, self._want(topics), _scratch)
        return cm

    # -- per channel -------------------------------------------------------------------------

    def message_counts(self) -> dict[int, int] | None:
        """channel id -> message count from the message indexes alone (no read); None when a chunk has none or
        messages are outside chunks (``channel_stats`` counts those)."""
        p = self.pieces
        if not (p.chunk.all() and p.indexed.all()):
            return None
        _, cid, _, n = self._index
        u, inv = np.unique(cid, return_inverse=True)
        return dict(zip(u.tolist(), np.bincount(inv.ravel(), weights=n, minlength=len(u)).astype(int).tolist()))

    def channel_stats(self) -> dict[int, tuple[int, int, int]]:
        """channel id -> (message count, first log_time, last log_time): from the message indexes and the
        loose messages' headers; chunks without message indexes are read (once per file object)."""
        if self._topics is not None:
            return self._topics
        owner, cid, off, n = self._index
        keep = n > 0
        cid, off, n = cid[keep], off[keep], n[keep]
        # (channel, count, first, last) per message index (one channel's entries in one chunk), read in batches of
        # about STATS_ENTRIES entries so that memory does not grow with the drive, and per loose message
        parts = []
        batch = np.searchsorted(np.cumsum(n), np.arange(1, 1 + int(n.sum()) // STATS_ENTRIES) * STATS_ENTRIES)
        for a, b in zip(np.r_[0, batch], np.r_[batch, len(n)]):
            if b > a:
                first = np.cumsum(n[a:b]) - n[a:b]
                pos = np.repeat(off[a:b] - 16 * first, n[a:b]) + 16 * np.arange(int(n[a:b].sum()), dtype=np.int64)
                t = le(self.buf, pos, "<i8")
                parts.append((cid[a:b], n[a:b], np.minimum.reduceat(t, first), np.maximum.reduceat(t, first)))
                self._drop(int(pos.min()) - FAULT_AROUND, int(pos.max()) + FAULT_AROUND)
        p = self.pieces
        todo = np.flatnonzero(~p.chunk | ~p.indexed)
        for g in self.groups(todo, p.size[todo]):
            cm = self.read(g)
            parts.append((cm.channel_id, np.ones(len(cm.channel_id), np.int64), cm.log_time, cm.log_time))
        self._topics = {}
        c, m, lo, hi = (np.concatenate([np.asarray(x, np.int64) for x in col]) for col in zip(*parts, ((), (), (), ())))
        if len(c):  # per channel: the sum of its counts, the least first and the greatest last time
            order = np.argsort(c, kind="stable")
            c, m, lo, hi = c[order], m[order], lo[order], hi[order]
            at = np.r_[0, np.flatnonzero(np.diff(c)) + 1]
            self._topics = dict(zip(c[at].tolist(), zip(np.add.reduceat(m, at).tolist(),
                                                        np.minimum.reduceat(lo, at).tolist(),
                                                        np.maximum.reduceat(hi, at).tolist())))
        return self._topics
