"""Where an MCAP file's records are: the file memory-mapped (``MappedFile``), and its table of pieces (``Pieces``)
found from the summary's chunk indexes (``from_summary``) or from one walk over its top-level records
(``from_walk``), both checked as ``drive.mcapfile`` says; ``McapFile`` reads the messages through them.

The reads here touch a record's head or an index entry at a time, scattered over the file: each hands the pages it
mapped back (``MappedFile.drop``), so finding the layout of a drive of any length takes the same memory.
"""
from __future__ import annotations

import io
import mmap
import os
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Metadata, Schema
from zlib_ng.zlib_ng import crc32

from fieldlog.drive.chunks import le, walk_records
from fieldlog.drive.recorder import MAGIC

LOOSE_RUN_BYTES = 4 << 20  # messages outside chunks are read in runs of about this many bytes
PEEK_SPAN = 1 << 24  # bytes of file whose scattered reads (one per chunk or index) are gathered at a time
WALK_WINDOW = 1 << 26  # bytes of file a walk over a file's top-level records takes at a time
FAULT_AROUND = 1 << 16  # bytes the kernel may map around a byte read through the file's mapping (fault-around)
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

class MappedFile:
    """An MCAP file memory-mapped read-only, with reads that hand their pages back.

    Parameters
    ----------
    path : the file; ``NotMcapError`` when it is empty or does not start with the MCAP magic
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        with open(self.path, "rb") as f:
            self.size = os.fstat(f.fileno()).st_size  # bytes
            if self.size < len(MAGIC):
                raise NotMcapError(f"{self.path}: empty or not an MCAP file")
            self._mm = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        self.buf = np.frombuffer(self._mm, np.uint8)
        if self._mm[: len(MAGIC)] != MAGIC:
            raise NotMcapError(f"{self.path}: not an MCAP file")

    def record(self, op: int, start: int, length: int) -> Schema | Channel | Metadata:
        """The schema, channel or metadata record whose content is at ``start``.

        Parameters
        ----------
        op : its opcode (SCHEMA, CHANNEL or METADATA)
        start, length : file offset and length of its content (after the 9-byte head), bytes

        Returns
        -------
        Schema | Channel | Metadata : the record as the mcap library reads it (its errors raised as they come)
        """
        stream = ReadDataStream(io.BytesIO(self._mm[start:start + length]))
        return {Opcode.SCHEMA: Schema, Opcode.CHANNEL: Channel, Opcode.METADATA: Metadata}[op].read(stream)

    def walk(self, pos: int, end: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        """The records from ``pos`` up to ``end``, ``WALK_WINDOW`` bytes of file at a time, each window's pages
        handed back (``drop``): the walk reads each record's head, and the kernel maps the pages around it.

        Parameters
        ----------
        pos, end : file offsets to walk from and to, bytes

        Returns
        -------
        ops, starts, lengths : each record's opcode, content offset and content length (``chunks.walk_records``)
        stop : the offset the walk stopped at (``end`` when the records tile the bytes)
        """
        parts = []
        while True:
            hi = min(end, pos + WALK_WINDOW)
            if end - pos >= 9:  # a record longer than the window: the window takes it whole
                hi = max(hi, min(end, pos + 9 + int.from_bytes(self._mm[pos + 1:pos + 9], "little")))
            ops, starts, lengths, stop = walk_records(self.buf[:hi], pos, (hi - pos) // 64 + 1)
            parts.append((ops, starts, lengths))
            self.drop(pos - FAULT_AROUND, stop + FAULT_AROUND)
            if hi == end or stop == pos:
                return (*(np.concatenate(x) for x in zip(*parts)), stop)
            pos = stop

    def drop(self, lo: int, hi: int) -> None:
        """Hand the mapped pages of bytes [lo, hi) back: a drive is read once, front to back, so its pages need
        not stay in this process's resident memory (the page cache keeps them, and a later read faults them in
        again); reading a drive of any length then takes the same memory.

        Parameters
        ----------
        lo, hi : file offsets, bytes (clipped to the file)
        """
        lo, hi = max(lo, 0), min(hi, len(self._mm))
        start = lo - lo % mmap.PAGESIZE
        if hi > start:
            self._mm.madvise(mmap.MADV_DONTNEED, start, hi - start)

    def peek(self, pos: np.ndarray, dtype: str | np.dtype) -> np.ndarray:
        """``le(self.buf, pos, dtype)`` at positions scattered over the file (in file order), those within each
        ``PEEK_SPAN`` of file at a time, each span's pages handed back (``drop``): the kernel maps up to
        ``FAULT_AROUND`` bytes around each byte read, so gathering one value per chunk of a long drive at once
        would map much of it.

        Parameters
        ----------
        pos : (n,) file offsets, bytes, ascending
        dtype : the little-endian value at each

        Returns
        -------
        (n,) array of ``dtype``
        """
        pos = np.asarray(pos, np.int64)
        cuts = np.flatnonzero(np.diff(pos // PEEK_SPAN)) + 1
        parts = [le(self.buf, pos[:0], dtype)]
        for p in np.split(pos, cuts) if len(pos) else []:
            parts.append(le(self.buf, p, dtype))
            self.drop(int(p.min()) - FAULT_AROUND, int(p.max()) + FAULT_AROUND)
        return np.concatenate(parts)


def from_walk(m: MappedFile) -> tuple:
    """The layout from one walk over every top-level record: (the records (ops, starts, lengths): every one
    but the chunks, message indexes and loose messages' use is read from them; the chunks (content start,
    length); the message indexes (chunk, content start, length); the loose runs). ``TruncatedError`` when the file
    is cut short before its Data End record.

    Parameters
    ----------
    m : the file, walked from its magic to its end

    Returns
    -------
    tuple : (ops, starts, lengths), (chunk content starts, lengths), (message indexes' chunk, channel, content
        start, length), the loose runs (``_loose``); as ``pieces`` takes them
    """
    size = m.size
    ops, starts, lengths, end = m.walk(len(MAGIC), size)
    data_end = np.flatnonzero(ops == Opcode.DATA_END)
    if not (len(ops) and ops[-1] == Opcode.FOOTER and end == size - len(MAGIC)
            and m._mm[size - len(MAGIC):] == MAGIC):
        if not len(data_end):
            raise TruncatedError(f"{m.path}: cut short (no footer): run `fieldlog recover {m.path}` first")
        # the data section is whole (its end record is there): a damaged or cut summary is left out
        ops, starts, lengths = (x[:int(data_end[0]) + 1] for x in (ops, starts, lengths))
    n = int(data_end[0]) if len(data_end) else len(ops) - 1
    d_ops, d_starts, d_lengths = ops[:n], starts[:n], lengths[:n]
    ci = np.flatnonzero(d_ops == Opcode.CHUNK)
    mi = np.flatnonzero(d_ops == Opcode.MESSAGE_INDEX)
    owner = np.cumsum(d_ops == Opcode.CHUNK)[mi] - 1  # a message index belongs to the chunk before it
    mi, owner = mi[owner >= 0], owner[owner >= 0]
    cid = le(m.buf, d_starts[mi], "<u2").astype(np.int64)
    return ((ops, starts, lengths), (d_starts[ci], d_lengths[ci]), (owner, cid, d_starts[mi], d_lengths[mi]),
            _loose(m, d_ops, d_starts, d_lengths))


def from_summary(m: MappedFile) -> tuple | None:
    """The layout of ``from_walk`` from the summary's chunk indexes, or None (walk the file instead) unless
    the file is complete and its summary checks out: its CRC (when the footer has one), every chunk index
    pointing at a chunk record, its message indexes tiling the bytes after the chunk, and the data section
    between those chunks and indexes walked (a few records: header, schemas, channels, metadata, attachments,
    data end) holding no message, chunk or message index the summary does not list.

    Parameters
    ----------
    m : the file, its footer, summary and the data section between the chunks read

    Returns
    -------
    tuple | None : as ``from_walk``'s, or None
    """
    size = m.size
    foot = size - len(MAGIC) - 29
    if foot < len(MAGIC) or m._mm[size - len(MAGIC):] != MAGIC or m._mm[foot:foot + 9] != FOOTER_HEAD:
        return None
    start, _, crc = struct.unpack_from("<QQI", m._mm, foot + 9)
    if not len(MAGIC) < start < foot or (crc and crc32(m._mm[start:foot + 25]) != crc):
        return None
    s_ops, s_starts, s_lengths, end = m.walk(int(start), size)
    if end != size - len(MAGIC) or not len(s_ops) or s_ops[-1] != Opcode.FOOTER or s_starts[-1] != foot + 9:
        return None
    k = np.flatnonzero(s_ops == Opcode.CHUNK_INDEX)
    s, rec_end = s_starts[k], s_starts[k] + s_lengths[k]
    if not len(k) or (s_lengths[k] < 64).any():
        return None
    buf, lim = m.buf, np.uint64(start)
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
    rec = m.peek(co, _RECORD_HEAD)
    if (rec["op"] != Opcode.CHUNK).any() or (rec["length"] != (clen - 9).astype(np.uint64)).any():
        return None
    index = _summary_index(m, s, mlen // 10, co + clen, iv_end, crc != 0)
    gaps = _gaps(m, np.r_[len(MAGIC), iv_end], np.r_[co, start])
    if index is None or gaps is None:
        return None
    top = tuple(np.concatenate(x) for x in zip(gaps, (s_ops, s_starts, s_lengths)))
    return top, (co + 9, clen - 9), index, []


def _summary_index(m: MappedFile, s: np.ndarray, n: np.ndarray, a: np.ndarray, b: np.ndarray, checked: bool
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """The message index records listed by the chunk indexes at ``s`` (``n`` entries each) as ``pieces``
    takes them (chunk, channel, content start, length), or None unless each chunk's records fill its bytes
    ``a``..``b`` one after the other, with their opcode. ``checked`` (the summary's CRC held): their
    channels as the summary lists them; else each record's channel and length are read and must agree (one
    random read per record, cheap against the walk)."""
    owner = np.repeat(np.arange(len(s)), n)
    first = np.cumsum(n) - n
    e = le(m.buf, np.repeat(s + 36 - 10 * first, n) + 10 * np.arange(int(n.sum())), _MAP_ENTRY)
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
        ok = m.peek(off, np.uint8) == Opcode.MESSAGE_INDEX
    else:
        rec = m.peek(off, _INDEX_HEAD)
        ok = (rec["op"] == Opcode.MESSAGE_INDEX) & (rec["length"] == (rec_end - off - 9).astype(np.uint64)) & (
            rec["channel"] == cid)
    return (owner, cid, off + 9, rec_end - off - 9) if ok.all() else None


def _gaps(m: MappedFile, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The records in the file's bytes ``lo[i]``..``hi[i]`` (between the chunks the summary lists), or None
    when they do not walk exactly or hold a message, chunk or message index (a summary that leaves them out)."""
    parts = []
    for a, b in zip(lo[hi > lo].tolist(), hi[hi > lo].tolist()):
        if len(parts) >= MAX_GAPS:
            return None
        ops, starts, lengths, end = walk_records(m.buf[:b], a, 64)
        if end != b or np.isin(ops, _NOT_IN_GAPS).any():
            return None
        parts.append((ops, starts, lengths))
    return tuple(np.concatenate(x) for x in zip(*parts)) if parts else (
        np.zeros(0, np.uint8), np.zeros(0, np.int64), np.zeros(0, np.int64))


def pieces(m: MappedFile, cs: np.ndarray, clen_rec: np.ndarray, owner: np.ndarray, ix_cid: np.ndarray,
           s: np.ndarray, mi_len: np.ndarray, lo_rows: list) -> tuple[Pieces, list[str], tuple]:
    """The chunks and the loose runs as one table; ``ValueError`` naming the first corrupt chunk.

    Parameters
    ----------
    m : the file
    cs, clen_rec : (c,) int64 content start and length of each chunk record, bytes
    owner, ix_cid, s, mi_len : (k,) int64 the message indexes: chunk, channel id, content start and length, bytes
    lo_rows : the loose runs (``_loose``)

    Returns
    -------
    pieces : the table
    compressions : the chunks' compression names (``Pieces.comp`` indexes them)
    index : the message indexes as (piece, channel id, file offset of their entries, entry count), int64 arrays
    """
    bad = clen_rec < 40
    if bad.any():
        raise ValueError(f"{m.path}: corrupt chunk at byte {int(cs[bad][0]) - 9}")
    head = m.peek(cs, _CHUNK_HEAD)
    t0, t1, usize, crc, clen = (head[k].astype(np.int64) for k in _CHUNK_HEAD.names)
    bad = clen > clen_rec - 40
    rlen = m.peek(np.where(bad, cs, cs + 32 + clen), "<u8")
    bad |= rlen > (clen_rec - 40 - clen).clip(0).astype(np.uint64)
    if bad.any():
        raise ValueError(f"{m.path}: corrupt chunk at byte {int(cs[bad][0]) - 9}")
    compressions, comp = _compressions(m, cs + 32, clen)
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
                  comp=np.r_[comp, z], crc=np.r_[crc, z]), compressions, (
        owner, ix_cid, s + 6, (mi_len - 6) // 16)


def _compressions(m: MappedFile, at: np.ndarray, n: np.ndarray) -> tuple[list[str], np.ndarray]:
    """The compression names, and each chunk's (``n`` bytes at ``at``) as an index into them."""
    w = int(n.max()) if len(n) else 0
    if w > 16:
        raise ValueError(f"{m.path}: unknown chunk compression at byte {int(at[np.argmax(n)]) - 41}")
    j = np.arange(max(w, 1))
    take = j < n[:, None]
    pos = np.where(take, at[:, None] + j, at[:, None])
    raw = np.ascontiguousarray(np.where(take, m.peek(pos.ravel(), np.uint8).reshape(pos.shape), 0))
    raw = raw.view(f"S{max(w, 1)}").ravel()
    if len(raw) and (raw == raw[0]).all():  # the usual file: one compression
        names, inv = raw[:1], np.zeros(len(raw), np.int64)
    else:
        names, inv = np.unique(raw, return_inverse=True)
    return [x.decode("latin-1") for x in names.tolist()], inv.astype(np.int64).ravel()


def _loose(m: MappedFile, ops: np.ndarray, starts: np.ndarray, lengths: np.ndarray
           ) -> list[tuple[int, int, int, int, np.ndarray]]:
    """Runs of consecutive message records outside chunks (other records between them are kept in the
    run: ``read`` skips them): (offset, end, first and last log_time, channel ids) per run."""
    msg = np.flatnonzero((ops == Opcode.MESSAGE) & (lengths >= 22))
    if not len(msg):
        return []
    run_of = np.searchsorted(np.flatnonzero(ops == Opcode.CHUNK), msg)  # messages between the same two chunks
    s = starts[msg]
    head = le(m.buf, s, _MESSAGE_HEAD)
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
