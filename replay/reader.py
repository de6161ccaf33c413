"""Read a drive (MCAP) back as numpy arrays, whole topics or streaming blocks.

The hot path never decodes one message at a time: chunks are located through the summary's
chunk indexes, decompressed, their message records parsed with a vectorised walk
(``acquire.recorder.chunk_messages``), and the payloads of each topic decoded as one batch by
the vectorised CDR decoders in ``acquire.messages``. Types without a fixed layout (NMEA
sentences, outages) are decoded per message with mcap_ros2's decoder; they are low rate.
``/raw/*`` (``RawBytes``, high rate) is read in batch by ``read_raw`` / ``iter_raw_batches``
(``decode_raw_batch``: a vectorised walk of its CDR layout); ``read_topic`` keeps the per-message
objects for it.

Every result dict has ``log_time_ns`` (int64 UTC ns, ascending) plus the decoder's fields;
generic types carry ``msgs`` (a list of decoded message objects).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import TYPE_CHECKING, Iterator, Sequence

import numpy as np
from mcap.reader import make_reader
from mcap.records import Chunk, ChunkIndex
from mcap.data_stream import ReadDataStream
from mcap.summary import Summary

from fieldlog.acquire import messages
from fieldlog.acquire.recorder import ChunkMessages, chunk_messages, decompress_chunk

if TYPE_CHECKING:
    from fieldlog.fusion.engine import GpsBlock


@dataclass(frozen=True)
class TopicInfo:
    topic: str
    type: str
    count: int
    first_ns: int  # first log_time, int64 UTC ns
    last_ns: int  # last log_time


@dataclass(frozen=True)
class Block:
    """Messages with log_time in [t0_ns, t1_ns), per topic."""

    t0_ns: int
    t1_ns: int
    data: dict[str, dict[str, object]]


def _summary(f) -> Summary:
    summary = make_reader(f).get_summary()
    if summary is None or summary.statistics is None:
        raise ValueError("MCAP file has no summary (cut short?): run `fieldlog recover` first")
    return summary


def _channel_ids(summary: Summary, topics: Sequence[str]) -> dict[int, str]:
    return {cid: ch.topic for cid, ch in summary.channels.items() if ch.topic in topics}


def _type_of(summary: Summary, cid: int) -> str:
    return summary.schemas[summary.channels[cid].schema_id].name


def _read_chunk(f, ci: ChunkIndex) -> ChunkMessages:
    f.seek(ci.chunk_start_offset + 9)
    return chunk_messages(decompress_chunk(Chunk.read(ReadDataStream(f))))


def _chunks_for(summary: Summary, cids: set[int]) -> list[ChunkIndex]:
    out = [
        ci
        for ci in summary.chunk_indexes
        if not ci.message_index_offsets or cids & set(ci.message_index_offsets)
    ]
    return sorted(out, key=lambda ci: (ci.message_start_time, ci.chunk_start_offset))


def decode(type_name: str, log_time_ns: np.ndarray, payloads: messages.Packed) -> dict[str, object]:
    """Decode a batch of one type; rows are sorted by log_time (stable)."""
    order = np.argsort(log_time_ns, kind="stable")
    if not np.all(order == np.arange(len(order))):
        log_time_ns = log_time_ns[order]
        payloads = payloads.take(order)
    batch = messages.BATCH_DECODERS.get(type_name)
    if batch is not None:
        out: dict[str, object] = {"log_time_ns": log_time_ns}
        out.update(batch(payloads))
        return out
    dec = messages.decoder_for(type_name)
    msgs, ok = [], []
    for b in payloads:
        try:
            msgs.append(dec(b))
            ok.append(True)
        except Exception:  # bad payload: count it, carry on
            msgs.append(None)
            ok.append(False)
    return {"log_time_ns": log_time_ns, "msgs": msgs, "valid": np.array(ok, dtype=bool)}


def _select(cm: ChunkMessages, cid: int) -> tuple[np.ndarray, messages.Packed]:
    sel = cm.select(cm.channel_id == cid)
    return sel.log_time, sel.packed()


def concat(parts: list[tuple[np.ndarray, messages.Packed]]) -> tuple[np.ndarray, messages.Packed]:
    """Batches (log_time_ns, payloads) joined in order into one."""
    if len(parts) == 1:
        return parts[0]
    t = np.concatenate([p[0] for p in parts]) if parts else np.zeros(0, np.int64)
    bufs = [p[1].buf[p[1].offsets[0] : p[1].offsets[-1]] for p in parts]
    lens = np.concatenate([p[1].lengths for p in parts]) if parts else np.zeros(0, np.int64)
    offsets = np.zeros(len(lens) + 1, dtype=np.int64)
    np.cumsum(lens, out=offsets[1:])
    buf = np.concatenate(bufs) if bufs else np.zeros(0, np.uint8)
    return t, messages.Packed(buf, offsets)


def topics(path: str | os.PathLike[str]) -> list[TopicInfo]:
    """Topics in a drive from its summary: type, message count, first/last log_time (exact,
    from the message indexes; chunk bounds when a chunk has none)."""
    with open(path, "rb") as f:
        s = _summary(f)
        first: dict[int, int] = {}
        last: dict[int, int] = {}
        for ci in s.chunk_indexes:
            items = ci.message_index_offsets.items()
            for cid, off in items:
                f.seek(off + 1)
                length = int.from_bytes(f.read(8), "little")
                body = f.read(length)
                entries = np.frombuffer(body, dtype="<u8", offset=6).reshape(-1, 2)
                if len(entries):
                    lo, hi = int(entries[:, 0].min()), int(entries[:, 0].max())
                    first[cid] = min(first.get(cid, lo), lo)
                    last[cid] = max(last.get(cid, hi), hi)
            if not items:
                for cid in s.channels:
                    first[cid] = min(first.get(cid, ci.message_start_time), ci.message_start_time)
                    last[cid] = max(last.get(cid, ci.message_end_time), ci.message_end_time)
        counts = s.statistics.channel_message_counts
        return [
            TopicInfo(ch.topic, _type_of(s, cid), counts.get(cid, 0), first.get(cid, 0), last.get(cid, 0))
            for cid, ch in sorted(s.channels.items())
        ]


def read_topic(path: str | os.PathLike[str], topic: str) -> dict[str, object]:
    """All messages of one topic, decoded into arrays, sorted by log_time."""
    with open(path, "rb") as f:
        s = _summary(f)
        cids = _channel_ids(s, [topic])
        if not cids:
            raise KeyError(f"topic {topic!r} not in {path}")
        (cid,) = cids
        parts = [_select(_read_chunk(f, ci), cid) for ci in _chunks_for(s, {cid})]
        t, p = concat(parts)
        return decode(_type_of(s, cid), t, p)


def iter_blocks(
    path: str | os.PathLike[str], topics: Sequence[str], block_s: float
) -> Iterator[Block]:
    """Stream a drive in consecutive blocks of ``block_s`` seconds of log_time.

    Blocks start at the first message of the selected topics and follow each other without
    gaps (a block may be empty for some topics). Memory holds only the chunks that overlap the
    block being built.
    """
    step = int(round(block_s * 1e9))
    if step <= 0:
        raise ValueError("block_s must be > 0")
    with open(path, "rb") as f:
        s = _summary(f)
        cids = _channel_ids(s, topics)
        chunks = _chunks_for(s, set(cids))
        if not chunks:
            return
        types = {cid: _type_of(s, cid) for cid in cids}
        pending: dict[int, list[tuple[np.ndarray, messages.Packed]]] = {cid: [] for cid in cids}
        t0: int | None = None
        k = 0

        def emit(t_end: int | None) -> Iterator[Block]:
            nonlocal t0
            while t0 is not None and (t_end is None or t0 + step <= t_end):
                t1 = t0 + step
                data: dict[str, dict[str, object]] = {}
                left = 0
                for cid, parts in pending.items():
                    t, p = concat(parts) if parts else (np.zeros(0, np.int64), messages.Packed.from_list([]))
                    inside = t < t1
                    idx_in, idx_out = np.flatnonzero(inside), np.flatnonzero(~inside)
                    data[cids[cid]] = decode(types[cid], t[idx_in], _take(p, idx_in))
                    pending[cid] = [(t[idx_out], _take(p, idx_out))] if len(idx_out) else []
                    left += len(idx_out)
                yield Block(t0, t1, data)
                t0 = t1
                if t_end is None and left == 0:
                    t0 = None

        while k < len(chunks):
            ci = chunks[k]
            yield from emit(ci.message_start_time)
            cm = _read_chunk(f, ci)
            for cid in cids:
                t, p = _select(cm, cid)
                if len(t):
                    pending[cid].append((t, p))
                    if t0 is None:
                        t0 = int(t.min())
                    t0 = min(t0, int(t.min()))
            k += 1
        yield from emit(None)


def _take(p: messages.Packed, idx: np.ndarray) -> messages.Packed:
    if len(idx) == len(p):
        return p
    if len(idx) == 0:
        return messages.Packed.from_list([])
    if idx[-1] - idx[0] + 1 == len(idx):  # contiguous: slice without copying
        a, b = p.offsets[idx[0]], p.offsets[idx[-1] + 1]
        return messages.Packed(p.buf[a:b], p.offsets[idx[0] : idx[-1] + 2] - a)
    return p.take(idx)


# -- raw reads in batch ---------------------------------------------------------------------------------


def _le(buf: np.ndarray, pos: np.ndarray, dtype: str) -> np.ndarray:
    """Little-endian ``dtype`` values at byte positions ``pos`` (each must leave room for the value)."""
    k = np.dtype(dtype).itemsize
    return np.ascontiguousarray(buf[pos[:, None] + np.arange(k)]).view(dtype).ravel()


def decode_raw_batch(payloads: messages.Packed) -> dict[str, object]:
    """``fieldlog_msgs/msg/RawBytes`` batch (layout: ``acquire.messages.encode_raw``, CDR little-endian) ->
    ``stamp_ns`` (int64, host wall clock at read), ``mono_ns`` (int64, host monotonic at read), ``port``
    (str array), ``data`` (``Packed``: the bytes read, message i = read i), ``valid``.

    Vectorised over the batch: header.frame_id and port are strings of any length, so every field offset is
    computed per row from the lengths before it. A row that is not a whole RawBytes message gets
    ``valid=False``, zeros, port "" and no data; it never raises.
    """
    n = len(payloads)
    buf, start, lens = payloads.buf, payloads.offsets[:-1], payloads.lengths
    z = np.zeros(n, np.int64)
    ok = lens >= 16  # encapsulation + sec + nanosec + frame_id length
    if len(buf) < 16:
        ok[:] = False
        buf = np.zeros(16, np.uint8)

    def at(rel: np.ndarray, dtype: str, size: int) -> np.ndarray:
        """Values at body offset ``rel`` of the rows still ok (0 elsewhere); rows too short drop out."""
        nonlocal ok
        ok &= 4 + rel + size <= lens
        return np.where(ok, _le(buf, np.where(ok, start + 4 + rel, 0), dtype), 0)

    ok &= (_le(buf, np.where(ok, start, 0), "<u2") == 0x0100)  # CDR_LE representation id, 00 01
    sec, nsec, flen = at(z, "<i4", 4), at(z + 4, "<u4", 4), at(z + 8, "<u4", 4).astype(np.int64)
    ok &= flen >= 1  # a CDR string holds its NUL
    pos = 12 + flen
    pos += -pos % 8
    mono = at(pos, "<i8", 8)
    plen = at(pos + 8, "<u4", 4).astype(np.int64)
    ok &= plen >= 1
    ppos = pos + 12
    pos = ppos + plen
    pos += -pos % 4
    dlen = at(pos, "<u4", 4).astype(np.int64)
    ok &= 4 + pos + 4 + dlen <= lens
    dlen = np.where(ok, dlen, 0)
    d0 = start + 4 + pos + 4

    width = int((plen[ok] - 1).max()) if ok.any() else 0
    port = np.full(n, "", dtype=object)
    if width:
        j = np.arange(width)
        take = ok[:, None] & (j < plen[:, None] - 1)
        raw = np.where(take, buf[np.where(take, (start + 4 + ppos)[:, None] + j, 0)], 0).astype(np.uint8)
        uniq, inv = np.unique(np.ascontiguousarray(raw).view(f"S{width}").ravel(), return_inverse=True)
        names = []
        for u in uniq:
            try:
                names.append(u.decode())
            except UnicodeDecodeError:
                names.append(None)
        bad = np.array([x is None for x in names])[inv]
        ok &= ~bad
        dlen = np.where(ok, dlen, 0)
        port = np.array(["" if x is None else x for x in names], dtype=object)[inv]
        port[~ok] = ""

    mark = np.zeros(len(buf) + 1, np.int8)  # +1 at each data start, -1 at its end: the cumsum is 1 on data bytes
    np.add.at(mark, d0[dlen > 0], 1)
    np.add.at(mark, (d0 + dlen)[dlen > 0], -1)
    np.cumsum(mark, dtype=np.int8, out=mark)
    offsets = np.zeros(n + 1, np.int64)
    np.cumsum(dlen, out=offsets[1:])
    data = messages.Packed(buf[mark[:-1].view(bool)], offsets)
    stamp = np.where(ok, sec.astype(np.int64) * 1_000_000_000 + nsec.astype(np.int64), 0)
    return {"stamp_ns": stamp, "mono_ns": np.where(ok, mono, 0).astype(np.int64), "port": port, "data": data,
            "valid": ok}


def _raw_cid(s: Summary, topic: str) -> int:
    cids = _channel_ids(s, [topic])
    if not cids:
        raise KeyError(f"topic {topic!r} not in the drive")
    (cid,) = cids
    if _type_of(s, cid) != messages.RAWBYTES:
        raise ValueError(f"{topic} is not {messages.RAWBYTES}")
    return cid


def _take_runs(p: messages.Packed, order: np.ndarray) -> messages.Packed:
    """``p.take(order)`` for an order made of few consecutive runs (a nearly sorted batch): one slice per run
    instead of a per-byte index (which would be 8 bytes of index per payload byte)."""
    brk = np.flatnonzero(np.diff(order) != 1) + 1
    if len(brk) > len(order) // 64:
        return p.take(order)
    first = order[np.r_[0, brk]]
    last = order[np.r_[brk - 1, len(order) - 1]]
    buf = np.concatenate([p.buf[p.offsets[a]:p.offsets[b + 1]] for a, b in zip(first.tolist(), last.tolist())])
    offsets = np.zeros(len(order) + 1, np.int64)
    np.cumsum(p.lengths[order], out=offsets[1:])
    return messages.Packed(buf, offsets)


def _raw_chunks(s: Summary, cid: int) -> list[ChunkIndex]:
    """The chunks holding ``cid`` in file order, which is the order of the reads (``_chunks_for`` orders by
    the chunks' first log_time, which the lagging ``/imu`` stamps pull back)."""
    return sorted(_chunks_for(s, {cid}), key=lambda c: c.chunk_start_offset)


def read_raw(path: str | os.PathLike[str], topic: str) -> dict[str, object]:
    """All reads of a ``/raw/*`` topic in log_time order: ``log_time_ns`` plus the ``decode_raw_batch`` fields."""
    with open(path, "rb") as f:
        s = _summary(f)
        cid = _raw_cid(s, topic)
        t, p = concat([_select(_read_chunk(f, ci), cid) for ci in _raw_chunks(s, cid)])
    if np.any(np.diff(t) < 0):  # the host wall clock stepped back
        order = np.argsort(t, kind="stable")
        t, p = t[order], _take_runs(p, order)
    return {"log_time_ns": t, **decode_raw_batch(p)}


def iter_raw_batches(path: str | os.PathLike[str], topic: str) -> Iterator[dict[str, object]]:
    """The reads of a ``/raw/*`` topic in the order they were recorded (file order, one batch per chunk;
    not sorted by log_time, which is the host wall clock): ``log_time_ns`` plus the ``decode_raw_batch``
    fields. A drive without ``topic`` yields nothing (a port that never delivered a byte)."""
    with open(path, "rb") as f:
        s = _summary(f)
        if not _channel_ids(s, [topic]):
            return
        cid = _raw_cid(s, topic)
        for ci in _raw_chunks(s, cid):
            t, p = _select(_read_chunk(f, ci), cid)
            if len(t):
                yield {"log_time_ns": t, **decode_raw_batch(p)}


# -- what fusion reads ---------------------------------------------------------------------------------

IN_TOPICS = ("/imu", "/gps/fix", "/gps/vel")   # the topics ``fusion.engine`` runs on


def gps_block(fix: dict, vel: dict) -> "GpsBlock":
    """Join a block's /gps/fix and /gps/vel (matched by stamp) into engine epochs."""
    from fieldlog.fusion.engine import GpsBlock  # here, so reading a drive never loads the fusion stack

    n = len(fix.get("log_time_ns", ()))
    if n == 0:
        return GpsBlock.empty()
    ok = fix["valid"]
    t = fix["log_time_ns"][ok]
    v_n = np.full((len(t), 3), np.nan)
    vel_cov = np.full((len(t), 3, 3), np.nan)
    if len(vel.get("log_time_ns", ())):
        vok = vel["valid"]
        tv = vel["log_time_ns"][vok]
        idx = np.searchsorted(tv, t).clip(0, max(len(tv) - 1, 0))
        hit = (tv[idx] == t) if len(tv) else np.zeros(len(t), bool)
        v_n[hit] = vel["v_n"][vok][idx[hit]]
        vel_cov[hit] = vel["covariance"][vok][idx[hit]].reshape(-1, 6, 6)[:, :3, :3]
    return GpsBlock(t, fix["lat_deg"][ok], fix["lon_deg"][ok], fix["alt_m"][ok],
                    fix["position_covariance"][ok].reshape(-1, 3, 3), fix["status"][ok].astype(int), v_n, vel_cov)
