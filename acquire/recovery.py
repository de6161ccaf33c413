"""A drive cut short, made complete: ``fieldlog recover`` and the daemon's recovery on start.

``recover`` keeps every complete chunk: it walks the file record by record with mcap's StreamReader, keeps every
schema, channel and metadata record and every chunk whose content checks (``drive.chunks``), and writes them
with fresh message indexes and a summary (``drive.recorder.Recorder``). The derived topics lag the raw reads
(``/imu`` by about half the time-sync window, a minute with a sampled PPS), so a crash leaves the tail's raw bytes
without their derived messages. ``TailDeriver`` re-derives them as ``fieldlog rebuild`` does: every kept raw read
goes through the pipeline, in file order (the order the daemon processed them), with the drive's calibration and
time-sync settings, and of what the pipeline writes only the messages later than the last kept one of their
topic are added. The tail is then stamped as at the end of a drive (``Pipeline.finish``).
"""
from __future__ import annotations

import logging
import os
import struct
from dataclasses import dataclass, field
from pathlib import Path
from collections.abc import Callable, Iterable
from typing import BinaryIO, Protocol

import numpy as np

from fieldlog.drive import bagdir, messages, outputs
from fieldlog.drive.chunks import ChunkMessages, chunk_definitions, chunk_messages, decompress_chunk
from fieldlog.drive.mcapfile import McapFile, TruncatedError
from fieldlog.acquire.pipeline import Pipeline
from fieldlog.drive.recorder import MAGIC, Recorder
from fieldlog.drive.records import Channel, Chunk, DataEnd, Footer, Message, Metadata, Opcode, Schema, StreamReader


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
    """What ``recover`` can add to the kept chunks (``TailDeriver``)."""

    def chunk(self, rec: Recorder, cm: ChunkMessages, metadata: dict[str, dict[str, str]]) -> None: ...

    def finish(self, rec: Recorder) -> dict[str, int]: ...


def recovered_state(src: Path) -> tuple[Path, str]:
    """``NAME.recovered.mcap`` next to ``src`` (``NAME.mcap``) and what it is: ``"none"`` (no such name),
    ``"done"`` (a complete file that stands in for ``src``: ``bagdir.stand_in``), ``"link"`` (a symbolic link:
    never followed, never replaced) or ``"stale"`` (a file that does not stand in: older than ``src``, or cut
    short)."""
    dst = src.with_name(src.stem + bagdir.RECOVERED)
    if dst.is_symlink():
        return dst, "link"
    if not dst.exists():
        return dst, "none"
    return dst, "done" if bagdir.stand_in(src) == dst and has_footer(dst) else "stale"


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


class _Walk:
    """``_recover``'s walk over the records of a source: what it kept so far (messages per channel id, the latest
    log time, the metadata), where the last complete record ends, and the damaged chunks it skipped."""

    def __init__(self, rec: Recorder, extend: Extend | None) -> None:
        self.rec, self.extend = rec, extend
        self.kept: dict[int, int] = {}
        self.meta: dict[str, dict[str, str]] = {}
        self.last_t = 0
        self.good_end = 0
        self.had_summary = False
        self.loose = [0, 0]  # [start, end) in src of the pending run of messages outside chunks
        self.damaged: list[int] = []

    def keep(self, cm: ChunkMessages) -> None:
        """One chunk's messages copied (and shown to ``extend``)."""
        _copy_chunk(self.rec, cm)
        if self.extend is not None:
            self.extend.chunk(self.rec, cm, self.meta)
        for cid, cnt in zip(*np.unique(cm.channel_id, return_counts=True)):
            self.kept[int(cid)] = self.kept.get(int(cid), 0) + int(cnt)
        if len(cm.log_time):
            self.last_t = max(self.last_t, int(cm.log_time.max()))

    def keep_loose(self, f: BinaryIO) -> None:
        """The pending messages outside chunks (their records as they are in src) kept as one chunk."""
        loose = self.loose
        if loose[1] > loose[0]:
            self.keep(chunk_messages(os.pread(f.fileno(), loose[1] - loose[0], loose[0])))
        loose[0] = loose[1]

    def walk(self, f: BinaryIO, size: int) -> None:
        """Every record of ``f`` (``size`` bytes) up to the first truncated or invalid one, or the summary."""
        rec, loose = self.rec, self.loose
        reader = StreamReader(f, emit_chunks=True, record_size_limit=size)
        it = reader.records
        while True:
            start = f.tell()
            try:
                record = next(it)
            except StopIteration:
                self.had_summary = True
                break
            except Exception:  # truncated or corrupt record: stop here
                break
            if isinstance(record, Chunk):
                try:
                    data = decompress_chunk(record)
                    cm = chunk_messages(data)
                    inner = chunk_definitions(record, data)
                except Exception:  # a whole record with damaged content: skip it, go on
                    self.damaged.append(start)
                    self.keep_loose(f)
                    loose[0] = loose[1] = self.good_end = f.tell()
                    continue
            if isinstance(record, Message):  # outside chunks: kept in runs of consecutive records
                if record.channel_id not in rec.channels:
                    break
                loose[1] = self.good_end = f.tell()
                if loose[1] - loose[0] >= 4 << 20:
                    self.keep_loose(f)
                continue
            self.keep_loose(f)
            loose[0] = loose[1] = f.tell()
            if isinstance(record, (Schema, Channel)):
                rec.register(record)
            elif isinstance(record, Metadata):
                rec.add_metadata(record.name, record.metadata)
                self.meta[record.name] = dict(record.metadata)
            elif isinstance(record, Chunk):
                for r in inner:
                    rec.register(r)
                if not set(np.unique(cm.channel_id).tolist()) <= set(rec.channels):
                    break
                self.keep(cm)
            elif isinstance(record, (DataEnd, Footer)):
                self.good_end = f.tell()
                self.had_summary = True
                break
            self.good_end = f.tell()
        self.keep_loose(f)


def _recover(src: str | os.PathLike[str], rec: Recorder, size: int, extend: Extend | None) -> RecoverReport:
    w = _Walk(rec, extend)
    rederived: dict[str, int] = {}
    try:
        with open(src, "rb") as f:
            w.walk(f, size)
        if extend is not None and not w.had_summary:
            rederived = extend.finish(rec)
            if rederived:
                rec.add_metadata("recover", {"source": str(src), **{f"rederived.{k}": str(v)
                                                                     for k, v in rederived.items()}})
    finally:
        rec.close()
    topics = {rec.channels[cid].topic: n for cid, n in w.kept.items()}
    return RecoverReport(
        messages=topics,
        chunks=rec.chunk_count,
        bytes_discarded=size - w.good_end if not w.had_summary else 0,
        last_log_time_ns=w.last_t,
        had_summary=w.had_summary,
        rederived=rederived,
        damaged=w.damaged,
    )


def _copy_chunk(rec: Recorder, cm: ChunkMessages) -> None:
    """Write the message records of one chunk as one new chunk (offsets kept)."""
    index: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}
    for cid in np.unique(cm.channel_id).tolist():
        sel = cm.channel_id == cid
        index[cid] = [(cm.log_time[sel].astype(np.uint64), cm.offset[sel].astype(np.uint64))]
    if len(cm.log_time) == 0:
        return
    rec.write_chunk(cm.data.tobytes(), int(cm.log_time.min()), int(cm.log_time.max()), index)


class TailDeriver:
    """``recover``'s ``extend``: a Pipeline fed the kept raw reads, whose output is held per topic and
    kept only past the last message of that topic in the kept chunks."""

    def __init__(self) -> None:
        self.pipe: Pipeline | None = None
        self.last: dict[str, int] = {}
        self.held: dict[str, list[tuple[np.ndarray, messages.Packed]]] = {}

    # the pipeline's sink: /raw is already in the kept chunks
    def write(self, topic: str, log_time_ns: int, data: bytes) -> None:
        if not topic.startswith("/raw/"):
            self.write_batch(topic, np.array([log_time_ns], np.int64), [data])

    def write_batch(self, topic: str, log_time_ns: np.ndarray, data) -> None:
        t = np.asarray(log_time_ns, np.int64)
        keep = np.flatnonzero(t > self.last.get(topic, -1))
        if len(keep):
            self.held.setdefault(topic, []).append((t[keep], messages.as_packed(data).take(keep)))

    def chunk(self, rec: Recorder, cm: ChunkMessages, metadata: dict[str, dict[str, str]]) -> None:
        topics = {cid: ch.topic for cid, ch in rec.channels.items()}
        raw = np.array([topics.get(int(c), "").startswith("/raw/") for c in cm.channel_id], bool)
        if raw.any():
            if self.pipe is None:
                cal, sync, cfg = Pipeline.settings_from_metadata(metadata)
                self.pipe = Pipeline(self, cal, sync, cfg)
            for payload in cm.select(raw).packed():
                _stamp, mono_ns, port, data = messages.decode_raw(payload)
                self.pipe.feed(port, mono_ns, _stamp, data)
        for cid in np.unique(cm.channel_id[~raw]).tolist():
            topic = topics.get(cid, "")
            self.last[topic] = max(self.last.get(topic, -1), int(cm.log_time[cm.channel_id == cid].max()))
        self._prune()

    def _prune(self) -> None:
        for topic, parts in list(self.held.items()):
            lim = self.last.get(topic, -1)
            kept = [(t[t > lim], p.take(np.flatnonzero(t > lim))) for t, p in parts if t[-1] > lim]
            self.held[topic] = [(t, p) for t, p in kept if len(t)]

    def finish(self, rec: Recorder) -> dict[str, int]:
        """Finish the pipeline and write what it derived past the kept chunks; messages per topic."""
        if self.pipe is None:
            return {}
        self.pipe.finish()
        self._prune()
        out = {}
        for topic, parts in self.held.items():
            for t, p in parts:
                rec.write_batch(topic, t, p)
                out[topic] = out.get(topic, 0) + len(t)
        return out


def recover_drive(src: str | os.PathLike[str], dst: str | os.PathLike[str], force: bool = False
                  ) -> RecoverReport:
    """The complete recovery of ``src`` into ``dst``: its complete chunks, then the derived tail. A complete file
    (one with a damaged chunk) has no tail: its chunks are copied without feeding the pipeline (several times
    faster: ``make bench`` recover), unless the walk stops before its data end (a damaged record):
    then it goes again with the pipeline (replacing the first copy). ``force``: as ``recover``."""
    if has_footer(src):
        rep = recover(src, dst, force=force)
        if rep.had_summary:
            return rep
        force = True
    return recover(src, dst, TailDeriver(), force=force)


def recover_folder(files: Iterable[Path], recover_file: Callable[[Path, Path], bool],
                   say: Callable[[str, int], None], force: bool = False, complete_too: bool = False
                   ) -> tuple[list[tuple[Path, Path]], bool]:
    """The recovery policy for the files of a drive folder, the daemon's on start and ``fieldlog recover``'s.

    Each file of ``files`` (``NAME.recovered.mcap`` stands for ``NAME.mcap`` when that exists, else it is recovered
    already; each file once) that was cut short (no footer) is recovered, and with ``complete_too`` each complete
    one with a damaged chunk (every chunk's CRC checked; a complete, sound one is said to be so; without it
    complete files are not read). A file is recovered into ``NAME.recovered.mcap`` next to it, the original kept,
    and once: a copy that stands in for it (``recovered_state``) is left (said with ``complete_too``); a symbolic
    link there, or a copy that does not stand in (unless ``force``), is never replaced: one error line through
    ``say`` names it and what to do, and the file is left.

    Parameters
    ----------
    files : Iterable[Path]
        The MCAP files of the folder.
    recover_file : Callable[[Path, Path], bool]
        Recovers one file into the name given (the caller's checks, messages and error handling); True when it
        wrote it.
    say : Callable[[str, int], None]
        Takes one line for the user and its ``logging`` level.
    force : bool
        Replace a recovered copy that does not stand in for its file (never a symbolic link).
    complete_too : bool
        Check the complete files' chunks too, and say what is done with each file.

    Returns
    -------
    list[tuple[Path, Path]]
        The (original, recovered) pairs written.
    bool
        Whether a file was left because its recovered name is taken (a link, or a copy that does not stand in).
    """
    done, refused, seen = [], False, set()
    for src in files:
        if src.name.endswith(bagdir.RECOVERED):
            orig = src.with_name(src.name[:-len(bagdir.RECOVERED)] + ".mcap")
            if not orig.is_file():
                if complete_too:
                    say(f"{src}: recovered already", logging.INFO)
                continue
            src = orig
        if src in seen:
            continue
        seen.add(src)
        if has_footer(src):
            if not complete_too:
                continue
            try:
                damaged = McapFile(src).damaged()
            except TruncatedError:
                damaged = None
            if damaged == []:
                say(f"{src}: complete, nothing to recover", logging.INFO)
                continue
            if damaged:
                say(f"{src}: damaged chunk{'s' * (len(damaged) > 1)} at byte {', '.join(map(str, damaged))}", logging.INFO)
        dst, state = recovered_state(src)
        if state == "done":
            if complete_too:
                say(f"{src}: recovered already, as {dst}", logging.INFO)
        elif state == "link" or (state == "stale" and not force):
            say(f"{src}: not recovered: {dst} " + ("is a symbolic link (never followed): remove it" if state == "link"
                else "exists but does not stand in for it (older, or cut short): remove it or give `fieldlog recover` "
                "--force") + f", or run `fieldlog recover {src} --out FILE`", logging.ERROR)
            refused = True
        elif recover_file(src, dst):
            done.append((src, dst))
    return done, refused
