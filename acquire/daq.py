"""DAQ board frame codec, protocol version 1 (contract: docs/daq-protocol.md).

One 38-byte little-endian frame per sample period (500 Hz): sync 0xA5 0x5A, version, flags, 32-bit sample
counter, six 24-bit ADC counts in int32, PPS latch, temperature and a CRC-16/CCITT-FALSE over bytes 2..35.
Encoding and decoding are vectorised over frames; the CRC uses one 256-entry table per byte position, so the
CRC of N frames is one gather and one XOR-reduction (CRC-16 is affine in the message bytes).
"""
from __future__ import annotations

from bisect import bisect_left
from dataclasses import dataclass

import numpy as np

SYNC0, SYNC1 = 0xA5, 0x5A
VERSION = 1
FRAME_SIZE = 38
FLAG_PPS, FLAG_LATCH, FLAG_TEMP = 0x01, 0x02, 0x04
COUNTS_MIN, COUNTS_MAX = -(2**23), 2**23 - 1
_CRC_FROM, _CRC_TO = 2, 36    # CRC covers frame[2:36]

FRAME_DTYPE = np.dtype([
    ("sync", "u1", (2,)), ("version", "u1"), ("flags", "u1"), ("counter", "<u4"), ("counts", "<i4", (6,)),
    ("latch", "<u2"), ("temp_cc", "<i2"), ("crc", "<u2"),
])


def _crc_table(poly: int = 0x1021) -> np.ndarray:
    """The 256-entry table of the MSB-first CRC-16 with generator ``poly``."""
    crc = np.arange(256, dtype=np.uint32) << 8
    for _ in range(8):
        crc = np.where(crc & 0x8000, (crc << 1) ^ poly, crc << 1) & 0xFFFF
    return crc.astype(np.uint16)


CRC_TABLE = _crc_table()


def crc16_columns(data: np.ndarray, init: int = 0xFFFF) -> np.ndarray:
    """CRC-16/CCITT-FALSE of every row of ``data`` (n, m) uint8, looping over the m byte positions.

    Equals ``binascii.crc_hqx(row.tobytes(), init)`` for each row.
    """
    crc = np.full(data.shape[0], init, np.uint16)
    for j in range(data.shape[1]):
        crc = (crc << 8) ^ CRC_TABLE[(crc >> 8) ^ data[:, j]]
    return crc


def _position_tables(m: int) -> tuple[np.ndarray, int]:
    """Per-position tables for m-byte messages: crc(msg) = c0 ^ XOR_j T[j, msg[j]] (init 0xFFFF)."""
    msgs = np.zeros((m, 256, m), np.uint8)
    msgs[np.arange(m), :, np.arange(m)] = np.arange(256, dtype=np.uint8)
    tables = crc16_columns(msgs.reshape(m * 256, m), init=0).reshape(m, 256)
    c0 = int(crc16_columns(np.zeros((1, m), np.uint8))[0])
    return tables, c0


_POS_TABLES, _CRC_ZERO = _position_tables(_CRC_TO - _CRC_FROM)
_RES_VALID = np.uint64(_CRC_ZERO)
_POS_FLAT = _POS_TABLES.ravel()
_POS_OFFSETS = (np.arange(_CRC_TO - _CRC_FROM) * 256).astype(np.uint16)
_CRC_BLOCK = 8192   # rows per gather, to keep the index array in cache


def crc16_frames(body: np.ndarray) -> np.ndarray:
    """CRC-16/CCITT-FALSE of every row of ``body`` (n, 34) uint8 (frame bytes 2..35), vectorised over rows."""
    if body.shape[0] > _CRC_BLOCK:
        return np.concatenate([crc16_frames(body[i:i + _CRC_BLOCK]) for i in range(0, body.shape[0], _CRC_BLOCK)])
    return np.bitwise_xor.reduce(_POS_FLAT[body + _POS_OFFSETS], axis=1) ^ np.uint16(_CRC_ZERO)


def encode_frames(counter: np.ndarray, counts: np.ndarray, pps: np.ndarray, latch: np.ndarray | None = None,
                  temperature_c: np.ndarray | None = None) -> bytes:
    """Encode n frames, all at once.

    counter: (n,) integer sample counters, written modulo 2**32.
    counts: (n, 6) signed 24-bit ADC counts (gyro x,y,z then accel x,y,z); ValueError if out of range.
    pps: (n,) bool, PPS edge seen during this sample period.
    latch: (n,) PPS latch in 1/65536 of a sample period, or None when the board has no latch. It is marked
        valid (flag bit1) on the PPS frames only; other frames carry 0.
    temperature_c: (n,) degrees C or None; written in centi-degrees, valid (bit2) where finite.
    """
    counter = np.asarray(counter)
    n = counter.shape[0]
    counts = np.asarray(counts)
    if counts.shape != (n, 6):
        raise ValueError(f"counts must have shape ({n}, 6), got {counts.shape}")
    if n and (counts.min() < COUNTS_MIN or counts.max() > COUNTS_MAX):
        raise ValueError("ADC counts outside the signed 24-bit range")
    pps = np.asarray(pps, bool)
    rec = np.zeros(n, FRAME_DTYPE)
    rec["sync"] = (SYNC0, SYNC1)
    rec["version"] = VERSION
    rec["counter"] = np.mod(counter.astype(np.int64), 2**32).astype(np.uint32)
    rec["counts"] = counts
    flags = np.where(pps, FLAG_PPS, 0).astype(np.uint8)
    if latch is not None:
        latch = np.asarray(latch)
        if n and (latch.min() < 0 or latch.max() > 0xFFFF):
            raise ValueError("latch outside 0..65535")
        rec["latch"] = np.where(pps, latch, 0)
        flags |= np.where(pps, FLAG_LATCH, 0).astype(np.uint8)
    if temperature_c is not None:
        t = np.asarray(temperature_c, np.float64)
        ok = np.isfinite(t)
        rec["temp_cc"] = np.where(ok, np.clip(np.round(np.where(ok, t, 0.0) * 100), -32768, 32767), 0)
        flags |= np.where(ok, FLAG_TEMP, 0).astype(np.uint8)
    rec["flags"] = flags
    rec["crc"] = crc16_frames(rec.view(np.uint8).reshape(n, FRAME_SIZE)[:, _CRC_FROM:_CRC_TO])
    return rec.tobytes()


def counts_on(last: int, counters: list[int]) -> bool:
    """Whether the frame counters ``counters`` are ``last`` + 1, + 2, ... modulo 2**32: a usual read. One list
    comparison where they do not wrap (the usual read has a few dozen frames, checked a hundred times a
    second), else one frame at a time."""
    n = len(counters)
    if counters == list(range(last + 1, last + n + 1)):
        return True
    return all((c - last) & 0xFFFFFFFF == i for i, c in enumerate(counters, 1))


@dataclass
class DaqFrames:
    """Decoded frames, one row per frame, in stream order.

    k: int64 sample index as the counter says (unwrapped, steps taken in [-2**31, 2**31)); the sample index the
    pipeline uses is judged from it by ``counterjudge.CounterJudge``. counts: (n, 6) int32 raw ADC counts. pps: bool.
    latch: uint16 PPS latch (0 where not valid), latch_valid: bool. temperature_c: float64 degC (NaN where
    not valid). end_offset: int64 offset just after the frame's last byte, relative to the start of the chunk
    passed to the ``feed`` call that returned it (>= 1 even when the frame began in an earlier chunk).
    """

    k: np.ndarray
    counts: np.ndarray
    pps: np.ndarray
    latch: np.ndarray
    latch_valid: np.ndarray
    temperature_c: np.ndarray
    end_offset: np.ndarray

    def __len__(self) -> int:
        return len(self.k)


@dataclass
class DaqStats:
    """Running decoder counters (see docs/daq-protocol.md, "Counters"). The ``counter_*`` and ``lost_frames``
    fields are kept by ``counterjudge.CounterJudge`` over the judged k."""

    frames: int = 0
    bytes_in: int = 0
    bytes_skipped: int = 0
    resyncs: int = 0
    bad_crc: int = 0
    bad_version: int = 0
    counter_gaps: int = 0
    lost_frames: int = 0
    counter_repeats: int = 0
    counter_backwards: int = 0
    counter_implausible: int = 0
    repeated: int = 0           # frames delivered twice (same counter, same bytes), dropped


def _residue_tables() -> np.ndarray:
    """uint64 tables over all 38 positions: XOR_j R[j, frame[j]] == _CRC_ZERO iff the frame is valid.

    Bits 0..15 carry the CRC residue (CRC of bytes 2..35 XOR the CRC field), bits 32..39 and 40..47 the
    difference of each sync byte from its value, bits 48..55 the difference of the version from 1.
    """
    v = np.arange(256, dtype=np.uint64)
    r = np.zeros((FRAME_SIZE, 256), np.uint64)
    r[0] = (v ^ SYNC0) << 32
    r[1] = (v ^ SYNC1) << 40
    r[_CRC_FROM:_CRC_TO] = _POS_TABLES
    r[2] |= (v ^ VERSION) << 48
    r[36] = v
    r[37] = v << 8
    return r


_RES_FLAT = _residue_tables().ravel()
_RES_OFFSETS = (np.arange(FRAME_SIZE) * 256).astype(np.uint16)
_SYNC_CRC_MASK = np.uint64(2**48 - 1)
_ROW = np.arange(FRAME_SIZE, dtype=np.intp)


def _residue(rows: np.ndarray) -> np.ndarray:
    """Residue of each row of ``rows`` (n, 38) uint8: == _CRC_ZERO for a valid frame (see _residue_tables)."""
    if rows.shape[0] > _CRC_BLOCK:
        return np.concatenate([_residue(rows[i:i + _CRC_BLOCK]) for i in range(0, rows.shape[0], _CRC_BLOCK)])
    return np.bitwise_xor.reduce(_RES_FLAT[rows + _RES_OFFSETS], axis=1)


class DaqDecoder:
    """Streaming frame decoder: ``feed(bytes) -> DaqFrames``. Never raises on any byte input.

    Frames are accepted greedily: at the expected boundary (38 bytes after the last good frame) frames are
    checked with sync, version and CRC, many at once; on a failure the decoder takes the first later position
    whose 38 bytes are a valid version-1 frame. At most 37 bytes are carried over between calls (``pending``).
    """

    def __init__(self) -> None:
        self.stats = DaqStats()
        self._carry = b""
        self._synced = False          # the carry starts at an expected frame boundary
        self._stream_pos = 0          # absolute stream offset of the carry's first byte
        self._lost_at: int | None = None   # absolute offset of the boundary where the last failure happened
        self._last_counter: int | None = None
        self._last_k = 0

    @property
    def pending(self) -> int:
        """Bytes held over for the next feed (always < 38)."""
        return len(self._carry)

    def feed(self, data: bytes) -> DaqFrames:
        """Decode the frames completed by ``data`` (any bytes-like object)."""
        data = bytes(data)
        self.stats.bytes_in += len(data)
        base = len(self._carry)
        buf = self._carry + data if base else data
        b = np.frombuffer(buf, np.uint8)
        m = len(buf) // FRAME_SIZE
        segments: list[tuple[int, int]] = []   # (start, number of consecutive good frames)
        if self._synced and m and (_residue(b[:m * FRAME_SIZE].reshape(m, FRAME_SIZE)) == _RES_VALID).all():
            segments.append((0, m))            # the usual read: whole good frames from the expected boundary
            pos = m * FRAME_SIZE
        else:
            pos = self._walk(buf, b, segments)
        self._carry = buf[pos:]
        self._stream_pos += pos
        ends = [np.arange(s - base + FRAME_SIZE, s - base + (c + 1) * FRAME_SIZE, FRAME_SIZE, dtype=np.int64)
                for s, c in segments]
        if len(segments) == 1:
            return self._decode(buf, segments[0][0], segments[0][1], ends[0])
        raw = b"".join(buf[s:s + c * FRAME_SIZE] for s, c in segments)
        return self._decode(raw, 0, len(raw) // FRAME_SIZE, np.concatenate(ends) if ends else np.zeros(0, np.int64))

    def _walk(self, buf: bytes, b: np.ndarray, segments: list[tuple[int, int]]) -> int:
        """Accept the good frames of ``buf`` (``b`` its bytes) into ``segments``, count the failures; returns
        where the bytes to carry over start. Every sync pair's 38 bytes are checked at once, then looked up."""
        st = self.stats
        n = len(buf)
        cand = np.flatnonzero((b[:-1] == SYNC0) & (b[1:] == SYNC1))
        n_complete = int(np.searchsorted(cand, n - FRAME_SIZE, "right"))
        res = _residue(b[cand[:n_complete, None] + _ROW])
        valid = res == _RES_VALID
        good_at = cand[:n_complete][valid].tolist()
        good = set(good_at)
        bad_version = cand[:n_complete][~valid & (res & _SYNC_CRC_MASK == _RES_VALID)].tolist()
        pos = 0
        while True:
            if self._synced:
                m = (n - pos) // FRAME_SIZE
                if m == 0:
                    return pos
                n_good = 0
                while n_good < m and pos + n_good * FRAME_SIZE in good:
                    n_good += 1
                if n_good:
                    segments.append((pos, n_good))
                    pos += n_good * FRAME_SIZE
                if n_good == m:
                    continue
                if buf[pos] == SYNC0 and buf[pos + 1] == SYNC1:
                    i = bisect_left(bad_version, pos)
                    if i < len(bad_version) and bad_version[i] == pos:
                        st.bad_version += 1
                    else:
                        st.bad_crc += 1
                self._synced = False
                self._lost_at = self._stream_pos + pos
                skip_from, scan_from = pos, pos + 1
            else:
                skip_from, scan_from = pos, pos
            # the first valid frame at or after scan_from; the frames of another version before it are counted
            i = bisect_left(good_at, scan_from)
            found = good_at[i] if i < len(good_at) else n
            st.bad_version += bisect_left(bad_version, found) - bisect_left(bad_version, scan_from)
            if found == n:
                j = max(n_complete, int(np.searchsorted(cand, scan_from)))    # an incomplete sync pair
                keep = (int(cand[j]) if j < cand.size else
                        n - 1 if n > scan_from and buf[n - 1] == SYNC0 else n)   # a lone 0xA5 may start a sync
                st.bytes_skipped += keep - skip_from
                return keep
            st.bytes_skipped += found - skip_from
            if self._lost_at is not None and self._stream_pos + found != self._lost_at + FRAME_SIZE:
                st.resyncs += 1
            self._synced = True
            pos = found

    def _unwrap(self, counter: np.ndarray) -> np.ndarray:
        """k for int64 counters: each step is the counter step modulo 2**32 taken in [-2**31, 2**31)."""
        d = np.empty(counter.size, np.int64)
        first = self._last_counter is None
        d[0] = 1 if first else counter[0] - self._last_counter
        d[1:] = counter[1:] - counter[:-1]
        d = (d + 2**31) % 2**32 - 2**31
        return (counter[0] - 1 if first else self._last_k) + np.cumsum(d)

    def _decode(self, raw: bytes, pos: int, nf: int, end: np.ndarray) -> DaqFrames:
        rec = np.frombuffer(raw, FRAME_DTYPE, count=nf, offset=pos)
        counter = rec["counter"]
        last = self._last_counter
        if nf == 0:
            k = np.zeros(0, np.int64)
        elif last is not None and counts_on(last, counter.tolist()):
            k = np.arange(self._last_k + 1, self._last_k + nf + 1, dtype=np.int64)   # the usual read
        else:
            k = self._unwrap(counter.astype(np.int64))
        if nf:
            self.stats.frames += nf
            self._last_counter = int(counter[-1])
            self._last_k = int(k[-1])
        bits = np.unpackbits(rec["flags"][:, None], axis=1, count=3, bitorder="little").view(bool)
        return DaqFrames(
            k=k,
            counts=rec["counts"].astype(np.int32),
            pps=bits[:, 0],
            latch=rec["latch"] * bits[:, 1],
            latch_valid=bits[:, 1],
            temperature_c=np.where(bits[:, 2], rec["temp_cc"] / 100.0, np.nan),
            end_offset=end,
        )
