"""Read a drive (MCAP) back as numpy arrays, whole topics or streaming blocks.

A drive is one MCAP file, several, a rotated session directory or a rosbag2 directory
(``drive.files``); its files are walked once each (``drive.mcapfile``: any valid layout, with or
without summary and indexes, messages in or outside chunks) into *pieces* (chunks, runs of messages
outside chunks), which are read in one log-time order across the files. The hot path never decodes
one message at a time: consecutive pieces are read together (``READ_BYTES`` at a time, so small chunks
cost little more than large ones), decompressed, walked and the records of the topics asked for kept in one
pass (``drive.chunks.read_chunks``), and the payloads of each topic decoded as one batch by the
vectorised CDR decoders in ``drive.messages``. Types without a fixed layout (NMEA sentences,
outages) are decoded per message with mcap_ros2's decoder; they are low rate. ``/raw/*``
(``RawBytes``, high rate) is read in batch by ``read_raw`` / ``iter_raw_batches``
(``decode_raw_batch``: a vectorised walk of its CDR layout); ``read_topic`` keeps the per-message
objects for it.

Every result dict has ``log_time_ns`` (int64 UTC ns, ascending) plus the decoder's fields;
generic types carry ``msgs`` (a list of decoded message objects).
"""

from __future__ import annotations

import os
import queue
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Collection, Iterator, Mapping, Sequence

import numpy as np

from fieldlog.drive import messages
from fieldlog.drive.chunks import ChunkMessages
from fieldlog.drive.files import DriveSpec, label, open_drive
from fieldlog.drive.mcapfile import McapFile, le

if TYPE_CHECKING:
    from fieldlog.fusion.types import GpsBlock


@dataclass(frozen=True)
class TopicCount:
    topic: str
    type: str
    count: int


@dataclass(frozen=True)
class TopicInfo(TopicCount):
    first_ns: int  # first log_time, int64 UTC ns
    last_ns: int  # last log_time


@dataclass(frozen=True)
class Block:
    """Messages with log_time in [t0_ns, t1_ns), per topic."""

    t0_ns: int
    t1_ns: int
    data: dict[str, dict[str, object]]


def decode(type_name: str, log_time_ns: np.ndarray, payloads: messages.Packed,
           fields: Collection[str] | None = None) -> dict[str, object]:
    """Decode a batch of one type; rows are sorted by log_time (stable).

    Parameters
    ----------
    type_name : the messages' type
    log_time_ns : (n,) int64 UTC ns
    payloads : the n CDR payloads
    fields : the decoded keys to keep, for a type of ``drive.messages.BATCH_DECODERS`` (all: None)

    Returns
    -------
    dict : ``log_time_ns`` and the type's decoded fields (``drive.messages.decode_*``), n rows each
    """
    log_time_ns, payloads = _by_log_time(log_time_ns, payloads)
    batch = messages.BATCH_DECODERS.get(type_name)
    if batch is not None:
        out: dict[str, object] = {"log_time_ns": log_time_ns}
        out.update(batch(payloads, fields))
        return out
    if type_name not in messages.MSG_DEFS:
        raise ValueError(f"messages of type {type_name[:80]!r}: not a type fieldlog decodes")
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


def _by_log_time(log_time_ns: np.ndarray, payloads: messages.Packed) -> tuple[np.ndarray, messages.Packed]:
    """The batch sorted by log_time (stable)."""
    order = np.argsort(log_time_ns, kind="stable")
    if not np.all(order == np.arange(len(order))):
        return log_time_ns[order], payloads.take(order)
    return log_time_ns, payloads


def concat(parts: list[tuple[np.ndarray, messages.Packed]]) -> tuple[np.ndarray, messages.Packed]:
    """Batches (log_time_ns, payloads) joined in order into one.

    Parameters
    ----------
    parts : (log_time_ns, payloads) batches

    Returns
    -------
    log_time_ns, payloads : one batch
    """
    if len(parts) == 1:
        return parts[0]
    t = np.concatenate([p[0] for p in parts]) if parts else np.zeros(0, np.int64)
    bufs = [p[1].buf[p[1].offsets[0] : p[1].offsets[-1]] for p in parts]
    lens = np.concatenate([p[1].lengths for p in parts]) if parts else np.zeros(0, np.int64)
    offsets = np.zeros(len(lens) + 1, dtype=np.int64)
    np.cumsum(lens, out=offsets[1:])
    buf = np.concatenate(bufs) if bufs else np.zeros(0, np.uint8)
    return t, messages.Packed(buf, offsets)


# -- the file layer: a drive's pieces, read in groups ----------------------------------------------------

Group = tuple[McapFile, np.ndarray]  # pieces of one file (row indexes into ``file.pieces``), read together


def piece_groups(files: list[McapFile], topics: Sequence[str], file_order: bool = False,
                 keep: Callable[[McapFile], np.ndarray] | None = None) -> Iterator[Group]:
    """The pieces that may hold ``topics`` (and pass ``keep``: a mask over a file's pieces), in log-time order
    (by first log_time; ``file_order``: file by file, in file order), grouped so that consecutive pieces of one
    file are read together (``McapFile.read``) up to about ``READ_BYTES``. Vectorised over the pieces.

    Parameters
    ----------
    files : the drive's open files
    topics : the topics wanted
    file_order : file by file instead of in log-time order
    keep : a file -> bool mask over its pieces (None: all)

    Returns
    -------
    Iterator[Group] : (file, piece indexes) groups
    """
    rows = []
    for k, f in enumerate(files):
        mask = f.may_hold({c for c, ch in f.channels.items() if ch.topic in topics})
        if keep is not None:
            mask &= keep(f)
        i = np.flatnonzero(mask)
        rows.append((np.full(len(i), k), i, f.pieces.offset[i], f.pieces.start_ns[i]))
    fk, idx, off, t = (np.concatenate(x) for x in zip(*rows)) if rows else [np.zeros(0, np.int64)] * 4
    order = np.lexsort((off, fk) if file_order else (off, fk, t))
    fk, idx = fk[order], idx[order]
    if not len(fk):
        return
    cut = np.flatnonzero(np.diff(fk)) + 1
    for a, b in zip(np.r_[0, cut].tolist(), np.r_[cut, len(fk)].tolist()):
        f = files[int(fk[a])]
        for g in f.groups(idx[a:b], f.pieces.size[idx[a:b]]):
            yield f, g


def _cids(f: McapFile, topic: str) -> list[int]:
    return [cid for cid, ch in f.channels.items() if ch.topic == topic]


def _select(cm: ChunkMessages, cids: list[int]) -> tuple[np.ndarray, np.ndarray, messages.Packed]:
    """(log_time, publish_time, payloads) of the messages on ``cids``."""
    if len(cids) == 1:
        sel = cm.select(cm.channel_id == cids[0])
    else:
        sel = cm.select(np.isin(cm.channel_id, cids))
    return sel.log_time, sel.publish_time, sel.packed()


def _type(files: list[McapFile], topic: str) -> str | None:
    for f in files:
        for cid in _cids(f, topic):
            return f.type_of(cid)
    return None


def topics(path: DriveSpec) -> list[TopicInfo]:
    """Topics in a drive: type, message count, first/last log_time (exact: from the message indexes, the
    headers of messages outside chunks, or the messages of chunks without indexes). Several files: summed
    per topic.

    Parameters
    ----------
    path : the drive

    Returns
    -------
    list[TopicInfo] : by topic name
    """
    out: dict[str, list] = {}
    for f in open_drive(path):
        stats = f.channel_stats()
        for cid, ch in sorted(f.channels.items()):
            n, lo, hi = stats.get(cid, (0, 0, 0))
            cur = out.setdefault(ch.topic, [f.type_of(cid), 0, 0, 0])
            if n:
                cur[2] = lo if not cur[1] else min(cur[2], lo)
                cur[3] = hi if not cur[1] else max(cur[3], hi)
                cur[1] += n
    return [TopicInfo(t, typ, n, lo, hi) for t, (typ, n, lo, hi) in out.items()]


def topic_counts(path: DriveSpec) -> list[TopicCount]:
    """Topics in a drive with their types and message counts, the times not read: the message indexes' lengths
    where every message of a file is in an indexed chunk (``McapFile.message_counts``), else as :func:`topics`
    counts them. Several files: summed per topic.

    Parameters
    ----------
    path : the drive

    Returns
    -------
    list[TopicCount] : by topic name
    """
    out: dict[str, list] = {}
    for f in open_drive(path):
        counts = f.message_counts()
        if counts is None:
            counts = {cid: stats[0] for cid, stats in f.channel_stats().items()}
        for cid, ch in sorted(f.channels.items()):
            out.setdefault(ch.topic, [f.type_of(cid), 0])[1] += counts.get(cid, 0)
    return [TopicCount(t, typ, n) for t, (typ, n) in out.items()]


def span(path: DriveSpec, topics: Collection[str]) -> tuple[int, int] | None:
    """The log-time span (first, last; UTC ns) of the pieces (chunks, runs of loose messages) that may hold
    ``topics``, from the drive's layout alone: it holds theirs and may be wider (a chunk shared with other
    topics). For progress, not for data; None when no piece may hold them.

    Parameters
    ----------
    path : the drive
    topics : the topics

    Returns
    -------
    tuple[int, int] | None
    """
    lo, hi = [], []
    for f in open_drive(path):
        mask = f.may_hold({cid for cid, ch in f.channels.items() if ch.topic in topics})
        if mask.any():
            lo.append(int(f.pieces.start_ns[mask].min()))
            hi.append(int(f.pieces.end_ns[mask].max()))
    return (min(lo), max(hi)) if lo else None


def read_payloads(path: DriveSpec, topic: str, file_order: bool = False
                  ) -> tuple[np.ndarray, np.ndarray, messages.Packed]:
    """All messages of one topic, undecoded: (log_time_ns, publish_time_ns, payloads), sorted by log_time
    (stable), or as recorded (``file_order``). KeyError when no file of the drive has the topic.

    Parameters
    ----------
    path : the drive
    topic : the topic
    file_order : keep the recorded order

    Returns
    -------
    log_time_ns, publish_time_ns : (n,) int64 UTC ns
    payloads : the n payloads
    """
    files = open_drive(path)
    parts = []
    for f, group in piece_groups(files, [topic], file_order):
        cm = f.read(group, [topic])
        t, pub, p = _select(cm, _cids(f, topic))
        if len(t):
            parts.append((t, pub, p))
    if not any(_cids(f, topic) for f in files):
        raise KeyError(f"topic {topic!r} not in {label(path)}")
    t, p = concat([(a, c) for a, _, c in parts])
    pub = np.concatenate([b for _, b, _ in parts]) if parts else np.zeros(0, np.int64)
    if not file_order and len(t) and np.any(np.diff(t) < 0):
        order = np.argsort(t, kind="stable")
        t, pub, p = t[order], pub[order], _take_runs(p, order)
    return t, pub, p


def read_topic(path: DriveSpec, topic: str) -> dict[str, object]:
    """All messages of one topic, decoded into arrays, sorted by log_time.

    Parameters
    ----------
    path : the drive
    topic : a topic of a type ``decode`` knows

    Returns
    -------
    dict : as ``decode``
    """
    t, _, p = read_payloads(path, topic)
    return decode(_type(open_drive(path), topic) or "", t, p)


def read_topics(path: DriveSpec, wanted: Sequence[str]) -> dict[str, dict[str, object]]:
    """Several whole topics in one pass over the drive (a piece that holds more than one of them is read once),
    each decoded as ``read_topic`` decodes it.

    Parameters
    ----------
    path : the drive
    wanted : topics of types ``decode`` knows

    Returns
    -------
    dict : topic -> as ``decode``, for the topics of ``wanted`` that a file of the drive has
    """
    files = open_drive(path)
    parts: dict[str, list[tuple[np.ndarray, messages.Packed]]] = {t: [] for t in wanted}
    for f, group in piece_groups(files, wanted):
        cm = f.read(group, wanted)
        for topic in wanted:
            cids = _cids(f, topic)
            if cids:
                t, _, p = _select(cm, cids)
                parts[topic].append((t, p))
    types = {t: _type(files, t) for t in wanted}
    return {t: decode(types[t], *concat(ps)) for t, ps in parts.items() if types[t] is not None}


def iter_payloads(path: DriveSpec, topic: str) -> Iterator[tuple[str, bytes]]:
    """The messages of one topic one by one, in log-time order, as (type name, CDR bytes): for a low-rate topic
    read field by field (``/tf_static``: ``messages.decode_tf``) or a message's header alone
    (``messages.header_frame_id``). Channels of another message encoding than CDR are left out.

    Parameters
    ----------
    path : the drive
    topic : the topic

    Returns
    -------
    Iterator[tuple[str, bytes]] : the channel's schema name (e.g. "tf2_msgs/msg/TFMessage") and one message
    """
    for f, group in piece_groups(open_drive(path), [topic]):
        cm = f.read(group, [topic])  # first: it defines the channels written only inside chunks
        cids = [c for c in _cids(f, topic) if f.channels[c].message_encoding == messages.MESSAGE_ENCODING]
        if not cids:
            continue
        t, _, p = _select(cm, cids)
        type_name = f.type_of(cids[0])
        for i in np.argsort(t, kind="stable").tolist():
            yield type_name, p[i]


def read_metadata_records(path: DriveSpec) -> list[tuple[str, dict[str, str]]]:
    """Every metadata record of the drive, in file order (names may repeat, e.g. ``acquire.port_event``); a drive
    of several files: file by file, in log-time order.

    Parameters
    ----------
    path : the drive

    Returns
    -------
    list of (name, keys and values)
    """
    return [(m.name, dict(m.metadata)) for f in open_drive(path) for m in f.metadata()]


def read_metadata(path: DriveSpec) -> dict[str, dict[str, str]]:
    """The drive's metadata records by name; for a repeated name, the last record.

    Parameters
    ----------
    path : the drive

    Returns
    -------
    dict : name -> keys and values
    """
    return dict(read_metadata_records(path))


def iter_blocks(path: DriveSpec, topics: Sequence[str], block_s: float,
                undecoded: Collection[str] = (), fields: Mapping[str, Collection[str]] | None = None
                ) -> Iterator[Block]:
    """Stream a drive in consecutive blocks of ``block_s`` seconds of log_time.

    Blocks start at the first message of the selected topics and follow each other without
    gaps (a block may be empty for some topics). Memory holds only the pieces (chunks, runs of
    messages outside chunks) that overlap the block being built, and the next group of pieces, read on a
    thread meanwhile when the process has a second CPU (``_read_ahead``). Several files are one drive: their
    pieces are read in one log-time order, across the file boundaries. The topics of a type with a batch
    decoder (``drive.messages.BATCH_DECODERS``) are decoded as each group of pieces is read, and only their
    decoded rows wait for their block.

    Parameters
    ----------
    path : the drive
    topics : the topics to read
    block_s : block length, s of log time
    undecoded : topics of ``topics`` whose rows are left as they are stored (``log_time_ns`` and ``payloads``,
        sorted by log_time), for a reader that decodes only the few it wants
    fields : topic -> the decoded keys to keep (``decode``); a topic not named keeps all

    Returns
    -------
    Iterator[Block] : the blocks, in log-time order
    """
    step = int(round(block_s * 1e9))
    if step <= 0:
        raise ValueError("block_s must be > 0")
    files = open_drive(path)
    fields = fields or {}
    types: dict[str, str] = {}
    early: set[str] = set()  # topics decoded as their pieces are read: pending holds their decoded rows
    pending: dict[str, list] = {}  # topic -> (log_time_ns, payloads) batches, or decoded rows (early)
    t0: int | None = None

    def emit(t_end: int | None) -> Iterator[Block]:
        nonlocal t0
        while t0 is not None and (t_end is None or t0 + step <= t_end):
            t1 = t0 + step
            data: dict[str, dict[str, object]] = {}
            left = 0
            for topic, parts in pending.items():
                if topic in early:
                    d = _joined(parts, types[topic], fields.get(topic))
                    inside = d["log_time_ns"] < t1
                    idx_in, idx_out = np.flatnonzero(inside), np.flatnonzero(~inside)
                    data[topic] = _log_time_order(_row_take(d, idx_in))
                    pending[topic] = [_row_take(d, idx_out)] if len(idx_out) else []
                    left += len(idx_out)
                    continue
                t, p = concat(parts) if parts else (np.zeros(0, np.int64), messages.Packed.from_list([]))
                inside = t < t1
                idx_in, idx_out = np.flatnonzero(inside), np.flatnonzero(~inside)
                if topic in undecoded:
                    t_in, p_in = _by_log_time(t[idx_in], _take(p, idx_in))
                    data[topic] = {"log_time_ns": t_in, "payloads": p_in}
                else:
                    data[topic] = decode(types[topic], t[idx_in], _take(p, idx_in))
                pending[topic] = [(t[idx_out], _take(p, idx_out))] if len(idx_out) else []
                left += len(idx_out)
            yield Block(t0, t1, data)
            t0 = t1
            if t_end is None and left == 0:
                t0 = None

    reads = _group_reads(files, topics)
    for start_ns, read in _read_ahead(reads) if cpus() > 1 else reads:
        yield from emit(start_ns)
        for topic, type_name, t, p in read:
            if topic not in types:
                types[topic] = type_name
                pending[topic] = []
                if topic not in undecoded and type_name in messages.BATCH_DECODERS:
                    early.add(topic)
            if len(t):
                pending[topic].append(decode(types[topic], t, p, fields.get(topic)) if topic in early else (t, p))
                t0 = int(t.min()) if t0 is None else min(t0, int(t.min()))
    yield from emit(None)


GroupRead = tuple[int, list[tuple[str, str, np.ndarray, messages.Packed]]]


def _group_reads(files: list[McapFile], topics: Sequence[str]) -> Iterator[GroupRead]:
    """Each group of ``piece_groups``, read: its first piece's start (log time, ns) and, per topic of ``topics``
    on a channel of its file, (topic, the channel's type, log_time_ns, payloads), the payloads copied out of the
    thread's read buffer (``McapFile.read``)."""
    for f, group in piece_groups(files, topics):
        cm = f.read(group, topics)
        read = []
        for topic in topics:
            cids = _cids(f, topic)
            if cids:
                t, _, p = _select(cm, cids)
                read.append((topic, f.type_of(cids[0]), t, p))
        yield int(f.pieces.start_ns[group].min()), read


def cpus() -> int:
    """The CPUs this process may run on (its affinity, e.g. one under ``taskset -c 0``): with one, work beside
    the caller (a read-ahead thread, a worker process) would only take turns with it.

    Returns
    -------
    int
    """
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def _read_ahead(items: Iterator[GroupRead]) -> Iterator[GroupRead]:
    """``items`` made on a thread of their own, one ahead of the caller's: the next group is decompressed and
    walked (compiled, without the GIL) while the caller decodes this one. Its exceptions are raised here, in
    order; a caller that stops early stops the thread, and the files are not read once this generator is
    closed."""
    q: queue.Queue = queue.Queue(maxsize=1)
    stop = threading.Event()

    def put(item: tuple) -> bool:
        while not stop.is_set():
            try:
                q.put(item, timeout=0.05)
                return True
            except queue.Full:
                continue
        return False

    def produce() -> None:
        try:
            for item in items:
                if not put((True, item)):
                    return
            put((False, None))
        except BaseException as e:  # noqa: BLE001 - handed to the caller, raised there
            put((False, e))

    thread = threading.Thread(target=produce, name="fieldlog-read-ahead", daemon=True)
    thread.start()
    try:
        while True:
            more, item = q.get()
            if not more:
                if item is not None:
                    raise item
                return
            yield item
    finally:
        stop.set()
        thread.join()


def _joined(parts: list[dict[str, np.ndarray]], type_name: str, fields: Collection[str] | None
            ) -> dict[str, np.ndarray]:
    """Decoded batches of one topic as one (in the order given; none: an empty batch of the type)."""
    if len(parts) == 1:
        return parts[0]
    if not parts:
        return decode(type_name, np.zeros(0, np.int64), messages.Packed.from_list([]), fields)
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def _row_take(d: dict[str, np.ndarray], idx: np.ndarray) -> dict[str, np.ndarray]:
    """Rows ``idx`` of a decoded batch (views when they are contiguous)."""
    n = len(d["log_time_ns"])
    if len(idx) == n:
        return d
    if len(idx) and idx[-1] - idx[0] + 1 == len(idx):
        return {k: v[idx[0] : idx[-1] + 1] for k, v in d.items()}
    return {k: v[idx] for k, v in d.items()}


def _log_time_order(d: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """A decoded batch sorted by log_time (stable), as ``decode`` sorts its rows."""
    order = np.argsort(d["log_time_ns"], kind="stable")
    if np.all(order == np.arange(len(order))):
        return d
    return {k: v[order] for k, v in d.items()}


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


def decode_raw_batch(payloads: messages.Packed) -> dict[str, object]:
    """``fieldlog_msgs/msg/RawBytes`` batch (layout: ``drive.messages.encode_raw``, CDR little-endian) ->
    ``stamp_ns`` (int64, host wall clock at read), ``mono_ns`` (int64, host monotonic at read), ``port``
    (str array), ``data`` (``Packed``: the bytes read, message i = read i), ``valid``.

    Vectorised over the batch: header.frame_id and port are strings of any length, so every field offset is
    computed per row from the lengths before it. A row that is not a whole RawBytes message gets
    ``valid=False``, zeros, port "" and no data; it never raises.

    Parameters
    ----------
    payloads : n RawBytes payloads

    Returns
    -------
    dict : the fields named above, n rows each
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
        return np.where(ok, le(buf, np.where(ok, start + 4 + rel, 0), dtype), 0)

    ok &= (le(buf, np.where(ok, start, 0), "<u2") == 0x0100)  # CDR_LE representation id, 00 01
    sec, nsec, flen = at(z, "<u4", 4), at(z + 4, "<u4", 4), at(z + 8, "<u4", 4).astype(np.int64)
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


def _raw_type(path: DriveSpec, topic: str) -> None:
    typ = _type(open_drive(path), topic)
    if typ is not None and typ != messages.RAWBYTES:
        raise ValueError(f"{topic} is not {messages.RAWBYTES}")


def read_raw(path: DriveSpec, topic: str) -> dict[str, object]:
    """All reads of a ``/raw/*`` topic in log_time order: ``log_time_ns`` plus the ``decode_raw_batch`` fields.

    Parameters
    ----------
    path : the drive
    topic : a ``/raw/*`` topic

    Returns
    -------
    dict : ``log_time_ns`` (UTC ns) and the ``decode_raw_batch`` fields
    """
    t, _, p = read_payloads(path, topic)  # KeyError without the topic
    _raw_type(path, topic)
    return {"log_time_ns": t, **decode_raw_batch(p)}


def iter_raw_batches(path: DriveSpec, topic: str) -> Iterator[dict[str, object]]:
    """The reads of a ``/raw/*`` topic in the order they were recorded (file by file, in file order; one batch
    per group of chunks; not sorted by log_time, which is the host wall clock): ``log_time_ns`` plus the
    ``decode_raw_batch`` fields. A drive without ``topic`` yields nothing (a port that never delivered a byte).

    Parameters
    ----------
    path : the drive
    topic : ``/raw/daq``, ``/raw/gps`` or ``/raw/can``

    Returns
    -------
    Iterator[dict] : as ``read_raw``'s, a batch at a time
    """
    files = open_drive(path)
    for f, group in piece_groups(files, [topic], file_order=True):
        cm = f.read(group, [topic])
        cids = _cids(f, topic)
        if not cids:
            continue
        if f.type_of(cids[0]) != messages.RAWBYTES:
            raise ValueError(f"{topic} is not {messages.RAWBYTES}")
        t, _, p = _select(cm, cids)
        if len(t):
            yield {"log_time_ns": t, **decode_raw_batch(p)}


# -- what fusion reads ---------------------------------------------------------------------------------

IN_TOPICS = ("/imu", "/gps/fix", "/gps/vel")   # the topics ``fusion.engine`` runs on


def gps_block(fix: dict, vel: dict) -> "GpsBlock":
    """Join a block's /gps/fix and /gps/vel (matched by stamp) into engine epochs.

    Parameters
    ----------
    fix : the block's decoded /gps/fix (``decode``)
    vel : its decoded /gps/vel (may be empty)

    Returns
    -------
    GpsBlock : the valid fixes, with the velocity (ENU, m/s) and its covariance where a /gps/vel has the same stamp
    """
    from fieldlog.fusion.types import GpsBlock  # here, so reading a drive never loads the fusion stack

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
