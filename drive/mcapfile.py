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
import threading
import os
from typing import Callable, Collection

import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Metadata, Schema

from fieldlog.drive import layout
from fieldlog.drive.chunks import ChunkError, ChunkMessages, decompress_many, le, read_chunks
from fieldlog.drive.layout import FAULT_AROUND, MappedFile, NotMcapError, Pieces, TruncatedError

__all__ = ["McapFile", "NotMcapError", "Pieces", "TruncatedError", "le"]  # what a reader of a file meets

log = logging.getLogger(__name__)
STATS_ENTRIES = 1 << 18  # message index entries read at a time by ``channel_stats``
READ_BYTES = 4 << 20  # consecutive pieces (small chunks, loose runs) are read together up to about this many bytes


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


class McapFile(MappedFile):
    """A complete MCAP file, memory-mapped, as pieces of messages to read (module docstring).

    Parameters
    ----------
    path : the file; ``NotMcapError`` / ``TruncatedError`` when it is not MCAP or cut short, ``ValueError`` naming
        the byte offset of a corrupt chunk or a damaged schema or channel record in the data section
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        super().__init__(path)
        laid = layout.from_summary(self)
        self.from_summary = laid is not None  # the chunk table came from the summary's chunk indexes
        if laid is None:
            laid = layout.from_walk(self)
        top, chunks, index, loose = laid
        ops, starts, lengths = top
        data_end = np.flatnonzero(ops == Opcode.DATA_END)
        n_data = int(data_end[0]) if len(data_end) else len(ops)
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        for op in (Opcode.SCHEMA, Opcode.CHANNEL):
            for i in np.flatnonzero(ops == op).tolist():
                try:
                    r = self.record(op, int(starts[i]), int(lengths[i]))
                except Exception as e:  # a damaged record: the summary's copy is left out, the data section's named
                    if i >= n_data:
                        continue
                    raise ValueError(f"{self.path}: damaged {Opcode(op).name.lower()} record at byte "
                                     f"{int(starts[i]) - 9} ({e}): the file cannot be read as it is") from None
                self._define(r)
        self._metadata = [(int(starts[i]), int(lengths[i])) for i in np.flatnonzero(ops[:n_data] == Opcode.METADATA)]
        self.pieces, self.compressions, self._index = layout.pieces(self, *chunks, *index, loose)
        self._topics: dict[int, tuple[int, int, int]] | None = None
        self.drop(0, self.size)  # what the layout read (summary, definitions): its pages go back too

    # -- records -----------------------------------------------------------------------------

    def _define(self, r: Schema | Channel) -> None:
        """The first record of an id counts (MCAP: repeats are copies): the data section's, not the summary's copy,
        which a damaged summary without a CRC could hold wrong."""
        (self.schemas if isinstance(r, Schema) else self.channels).setdefault(r.id, r)

    def metadata(self) -> list[Metadata]:
        """The metadata records in file order; a damaged one (its fields overrun it, a name or value is not
        UTF-8) is left out with a warning naming it: the messages can still be read.

        Returns
        -------
        list[Metadata] : the records that read whole
        """
        out = []
        for s, n in self._metadata:
            try:
                out.append(self.record(Opcode.METADATA, s, n))
            except Exception as e:  # noqa: BLE001 - the mcap library's EndOfFile, UnicodeDecodeError, struct.error
                log.warning("warning: %s: damaged metadata record at byte %d (%s: %s) left out", self.path, s - 9,
                            type(e).__name__, e)
        return out

    def type_of(self, cid: int) -> str:
        """The schema name of channel ``cid`` ("" when its schema is not defined).

        Parameters
        ----------
        cid : a channel id of the file

        Returns
        -------
        str : e.g. "sensor_msgs/msg/Imu"
        """
        schema = self.schemas.get(self.channels[cid].schema_id)
        return schema.name if schema is not None else ""

    # -- pieces ------------------------------------------------------------------------------

    def may_hold(self, cids: set[int] | list[int]) -> np.ndarray:
        """Per piece: whether it may hold messages of channels ``cids`` (it does not say which channels it
        holds, or it holds one of them, or one not defined yet: defined inside a chunk).

        Parameters
        ----------
        cids : channel ids

        Returns
        -------
        (len(pieces),) bool
        """
        p = self.pieces
        cols = np.isin(p.cids, list(cids)) | ~np.isin(p.cids, list(self.channels))
        return ~p.indexed | p.has[:, cols].any(axis=1)

    @staticmethod
    def groups(idx: np.ndarray, size: np.ndarray) -> list[np.ndarray]:
        """``idx`` (pieces to read in this order, with uncompressed ``size``) cut into consecutive groups of
        about ``READ_BYTES``.

        Parameters
        ----------
        idx : (k,) piece indexes, in reading order
        size : (k,) their uncompressed sizes, bytes

        Returns
        -------
        list of int64 arrays : the groups, in order
        """
        c = np.cumsum(size) // READ_BYTES
        return np.split(idx, np.flatnonzero(np.diff(c)) + 1) if len(idx) else []

    def records(self, i: int) -> bytes | memoryview:
        """The uncompressed records of piece ``i`` (a chunk's content, or the run's bytes in place).

        Parameters
        ----------
        i : a piece index

        Returns
        -------
        bytes | memoryview : its records
        """
        return self._chunks(decompress_many, np.array([i]))

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
            self.drop(lo - FAULT_AROUND, hi + FAULT_AROUND)
        return out

    def damaged(self) -> list[int]:
        """Byte offsets of the chunks whose content does not decompress to its size and CRC-32 (what ``fieldlog
        recover`` skips): each chunk decompressed and checked once, in groups, nothing copied out.

        Returns
        -------
        list[int] : file offsets, bytes, ascending
        """
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
        take what you keep (``ChunkMessages.packed`` copies) before the next.

        Parameters
        ----------
        idx : piece indexes, in reading order
        topics : the topics to keep (None: every channel)

        Returns
        -------
        ChunkMessages : the messages, in record order
        """
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
        messages are outside chunks (``channel_stats`` counts those).

        Returns
        -------
        dict[int, int] | None : by channel id
        """
        p = self.pieces
        if not (p.chunk.all() and p.indexed.all()):
            return None
        _, cid, _, n = self._index
        u, inv = np.unique(cid, return_inverse=True)
        return dict(zip(u.tolist(), np.bincount(inv.ravel(), weights=n, minlength=len(u)).astype(int).tolist()))

    def channel_stats(self) -> dict[int, tuple[int, int, int]]:
        """channel id -> (message count, first log_time, last log_time): from the message indexes and the
        loose messages' headers; chunks without message indexes are read (once per file object).

        Returns
        -------
        dict[int, tuple[int, int, int]] : by channel id; times UTC ns
        """
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
                self.drop(int(pos.min()) - FAULT_AROUND, int(pos.max()) + FAULT_AROUND)
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
