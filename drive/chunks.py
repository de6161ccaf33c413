"""Reading MCAP chunks: the record walk, decompression with its size and CRC checks, and the messages as arrays.

Every reader of the project goes through these kernels: ``drive.mcapfile`` (any file layout, complete or cut
short), ``drive.reader`` and ``acquire.recovery``. A chunk is walked record by record in one compiled pass
(``walk_records``, drive/_chunks.c), decompressed in runs
(``decompress_many``: python-zstandard's batch call, zlib-ng's CRC-32; ``read_chunks``: the compiled kernels of
``drive.native`` when they are ready) and its Message records gathered as arrays (``ChunkMessages``), so no
per-message Python runs on a whole drive. No chunk is decompressed past its claimed size, and none claiming more
than ``max_chunk_bytes`` (``FIELDLOG_MAX_CHUNK_BYTES``) is decompressed at all.
"""

from __future__ import annotations

import ctypes
import os
import threading
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import zstandard
from zlib_ng.zlib_ng import crc32
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Schema
from mcap.stream_reader import breakup_chunk

from fieldlog.drive import messages, native


def _walk(buf: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """The records of an uncompressed chunk (``walk_records`` from its start)."""
    return walk_records(buf, 0, len(buf) // 31 + 1)


def walk_records(buf, pos: int, cap: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Records in ``buf`` (a uint8 array or a bytes-like object) from byte ``pos`` on (a chunk's content, or a
    whole file after its magic): opcode, start of the record body, body length; and the end of the last complete
    record. ``cap``: the number of records expected (the arrays grow past it). Compiled (drive/_chunks.c).

    Parameters
    ----------
    buf : the bytes
    pos : where to start, bytes
    cap : records expected

    Returns
    -------
    ops : (k,) uint8 opcodes
    starts, lengths : (k,) int64 body offset in ``buf`` and body length, bytes
    end : the offset after the last complete record
    """
    data = np.frombuffer(buf, np.uint8) if not isinstance(buf, np.ndarray) else np.ascontiguousarray(buf, np.uint8)
    if pos < 0:
        raise ValueError(f"walk_records: pos {pos} < 0")
    n, walk = len(data), native.library("fieldlog.drive._chunks", native.CHUNKS).fieldlog_walk
    parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    cap, end = max(int(cap), 16), ctypes.c_int64(pos)
    while True:
        ops, starts, lengths = np.empty(cap, np.uint8), np.empty(cap, np.int64), np.empty(cap, np.int64)
        k = walk(data.ctypes.data, n, end.value, cap, ops.ctypes.data, starts.ctypes.data, lengths.ctypes.data,
                 ctypes.byref(end))
        parts.append((ops[:k], starts[:k], lengths[:k]))
        if k < cap:
            break
        cap *= 2
    if len(parts) == 1:
        return (*parts[0], end.value)
    return (*(np.concatenate(x) for x in zip(*parts)), end.value)


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
        """The messages where ``mask`` is true (the same ``data``).

        Parameters
        ----------
        mask : (n,) bool, or indexes

        Returns
        -------
        ChunkMessages
        """
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
        """Payloads as a Packed batch: one vectorised gather (of whole rows when they have one length).

        Returns
        -------
        messages.Packed : a copy of the payloads
        """
        n = len(self.start)
        if n and np.all(self.length == self.length[0]):
            w = int(self.length[0])
            return messages.Packed.from_matrix(byte_windows(self.data, w)[self.start])
        offsets = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(self.length, out=offsets[1:])
        src = np.repeat(self.start - offsets[:-1], self.length) + np.arange(offsets[-1], dtype=np.int64)
        return messages.Packed(self.data[src], offsets)


def decompress_chunk(chunk: Chunk) -> bytes:
    """Uncompressed chunk bytes; raises ValueError if the size or CRC does not match.

    Parameters
    ----------
    chunk : a Chunk record

    Returns
    -------
    bytes : its records
    """
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
    raises ValueError if the size or the CRC (0: none) does not match.

    Parameters
    ----------
    compression : "zstd", "lz4" or ""
    data : the compressed records
    size : uncompressed size, bytes
    crc : CRC-32 of the uncompressed records (0: none)

    Returns
    -------
    the records (bytes, or ``data`` itself)
    """
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
    ``Recorder`` writes, and of any writer we know of; a chunk claiming more is damaged, or a decompression bomb).

    Returns
    -------
    int : bytes
    """
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
    negative) exceeds ``max_chunk_bytes``, before any buffer is sized by it.

    Parameters
    ----------
    size : (k,) int64 claimed sizes, bytes
    """
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
    size, and none claiming more than ``max_chunk_bytes`` is decompressed at all (``check_sizes``).

    Parameters
    ----------
    buf : the file's bytes
    names : compression names
    comp : (k,) index into ``names`` per chunk
    at, length : (k,) offset and length of each chunk's compressed records, bytes
    size, crc : (k,) uncompressed size, bytes, and CRC-32 (0: none)

    Returns
    -------
    the joined records (bytes-like)
    """
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
    """Parse the Message records of an uncompressed chunk, vectorised (compiled record walk).

    Parameters
    ----------
    data : a chunk's records, uncompressed

    Returns
    -------
    ChunkMessages
    """
    buf = np.frombuffer(data, dtype=np.uint8)
    return messages_of(buf, *_walk(buf)[:3])


def byte_windows(buf: np.ndarray, k: int) -> np.ndarray:
    """A read-only view (len(buf) - k + 1, k) of a uint8 buffer: row i holds the k bytes from byte i (no copy;
    index it with record positions to gather fixed-size heads or payloads in one step).

    Parameters
    ----------
    buf : (m,) uint8
    k : window length, bytes

    Returns
    -------
    (m - k + 1, k) uint8 view
    """
    return np.lib.stride_tricks.as_strided(buf, shape=(max(len(buf) - k + 1, 0), k), strides=(1, 1),
                                           writeable=False)


def le(buf: np.ndarray, pos: np.ndarray, dtype: str | np.dtype) -> np.ndarray:
    """Little-endian ``dtype`` values (or records of a structured dtype) at byte positions ``pos`` of a uint8
    buffer (each must leave room for the value). Integers are put together from one ``take`` per byte (twice as
    fast as gathering rows of ``byte_windows``, which the records use).

    Parameters
    ----------
    buf : (m,) uint8
    pos : (n,) int64 byte positions
    dtype : the value's dtype (little-endian)

    Returns
    -------
    (n,) array of ``dtype``
    """
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
    ``channels``, when given).

    Parameters
    ----------
    buf : (m,) uint8 the records
    ops, starts, lengths : the walked records (``walk_records``)
    channels : channel ids to keep (None: all)

    Returns
    -------
    ChunkMessages
    """
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
    ``drive.native`` is ready, in one compiled pass that keeps only those records: ``scratch(a, b)`` gives a
    staging buffer of ``a`` bytes and the batch's buffer of ``b`` bytes. Else the chunks are decompressed and joined
    (``decompress_many``), walked (``walk_records``) and their messages picked (``messages_of``).

    Parameters
    ----------
    buf, names, comp, at, length, size, crc : the chunks, as ``decompress_many`` takes them
    want : (65536,) bool per channel id
    scratch : (staging bytes, batch bytes) -> two uint8 buffers

    Returns
    -------
    messages : ChunkMessages
    definitions : (opcode, body start, body length) of the schema and channel records
    """
    comp, size = np.asarray(comp, np.int64), np.asarray(size, np.int64)
    check_sizes(size)
    used = {names[c] for c in set(comp.tolist())}  # not np.unique, whose first call imports numpy.ma
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


def chunk_definitions(chunk: Chunk, data: bytes) -> list[Schema | Channel]:
    """Schema and Channel records inside a chunk (other writers put them there); ``data``: its records,
    uncompressed (``decompress_chunk``).

    Parameters
    ----------
    chunk : the Chunk record
    data : its records, uncompressed

    Returns
    -------
    list[Schema | Channel]
    """
    ops, _, _, _ = _walk(np.frombuffer(data, dtype=np.uint8))
    if not np.isin(ops, (Opcode.SCHEMA, Opcode.CHANNEL)).any():
        return []
    return [r for r in breakup_chunk(chunk) if isinstance(r, (Schema, Channel))]
