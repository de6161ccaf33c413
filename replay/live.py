"""Live bus client: the derived messages of a running ``fieldlog acquire`` as the blocks the MCAP reader yields.

The daemon serves the bus on a Unix domain socket (``[daemon] bus`` in its config; frame layout in
``acquire.daemon.BusServer`` and docs/data-model.md). Two streams share it:

* final messages, exactly as written to the MCAP (same log_time and CDR payload): every derived topic.
  ``/imu`` is final about half a time-sync window (60 s with a sampled PPS) after its bytes were read;
  fixes are final, and published, when their NMEA epoch is complete;
* provisional ``/imu``: each serial read's DAQ frames, published at once (a few ms after the read), stamped
  with the causal time fit (the latest PPS fit extrapolated) and flagged with the per-sample sync state.
  Before the first PPS lock they carry host-clock stamps and the ``host_clock`` flag.

API (stable; ``fieldlog view --live`` and live fusion use it):

``iter_blocks(path, topics, block_s, max_lag_s=None, final=False, host_clock=False)``
    yields ``LiveBlock``s: ``drive.reader.Block``s (``t0_ns``, ``t1_ns``, ``data[topic]`` decoded by the
    same ``drive.reader.decode`` as ``drive.reader.iter_blocks``) so fusion code cannot tell live from
    recorded, plus ``provisional`` (its ``/imu`` rows carry provisional stamps), ``sync_state`` (the worst
    SyncState among them, None without provisional rows), ``read_mono_ns`` (host monotonic time of the newest
    serial read received when the block was yielded) and ``recv_mono_ns`` (when that batch was received). With
    provisional stamps ``data["/imu"]`` also has ``sync_state`` (uint8 per row). ``final=True`` gives the
    MCAP's messages instead (``/imu`` ~60 s late); ``host_clock=True`` keeps the pre-lock host-clock rows,
    which are dropped by default because their time base is not the fixes' UTC.
``iter_batches(path)``
    yields every published ``Batch`` (one topic, n messages, both streams) as received.
``batch_blocks(batches, topics, block_s, ...)``
    ``iter_blocks`` of batches already read (e.g. from ``follow``).
``in_stream(batch, final=False, host_clock=False)``
    whether a batch is part of the stream ``iter_blocks`` reads (one stamp base per topic, never both).
``follow(path, wait_s=30.0, tap=None)``
    a viewer's batches: waits for the bus, drains it in a background thread (``tap`` sees each batch there as
    it arrives), ends when the daemon closes the bus, on Ctrl-C or on SIGTERM.
"""
from __future__ import annotations

import queue
import signal
import socket
import struct
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Iterator, Sequence

import numpy as np

from fieldlog.drive import messages
from fieldlog.drive.reader import Block, concat, decode

FLAG_PROVISIONAL = 1     # acquire.daemon.BUS_PROVISIONAL
FLAG_HOST_CLOCK = 2      # acquire.daemon.BUS_HOST_CLOCK
STATE_FINAL = 255        # per-message state of final messages (acquire.daemon.BUS_STATE_FINAL)
_HEAD = struct.Struct("<BqH")


@dataclass(frozen=True)
class Batch:
    """One bus frame: n messages of one topic."""

    topic: str
    log_time_ns: np.ndarray       # int64 UTC ns (host-clock ns when ``host_clock``)
    payloads: messages.Packed     # CDR
    provisional: bool             # causal stamps, not the file's
    host_clock: bool              # before the first PPS lock: host-clock stamps
    state: np.ndarray             # uint8 per message: SyncState (FREE 0, HOLDOVER 1, LOCKED 2) or STATE_FINAL
    read_mono_ns: int             # host monotonic ns of the serial read whose processing published it
    recv_mono_ns: int             # host monotonic ns when this client had received it


@dataclass(frozen=True)
class LiveBlock(Block):
    """A ``drive.reader.Block`` from the bus, with the provisional / sync state of its ``/imu`` rows."""

    provisional: bool = False
    sync_state: int | None = None
    read_mono_ns: int = 0
    recv_mono_ns: int = 0


def _read_exact(sock: socket.socket, n: int) -> bytes | None:
    buf = bytearray()
    while len(buf) < n:
        part = sock.recv(n - len(buf))
        if not part:
            return None
        buf += part
    return bytes(buf)


def parse_frame(body: bytes, recv_mono_ns: int = 0) -> Batch:
    """A frame body (after its u32 length) as a Batch."""
    flags, read_mono, tlen = _HEAD.unpack_from(body, 0)
    pos = _HEAD.size
    topic = body[pos:pos + tlen].decode()
    pos += tlen
    (n,) = struct.unpack_from("<I", body, pos)
    pos += 4
    t = np.frombuffer(body, "<i8", n, pos).astype(np.int64)
    pos += 8 * n
    state = np.frombuffer(body, np.uint8, n, pos).copy()
    pos += n
    offsets = np.frombuffer(body, "<i8", n + 1, pos).astype(np.int64)
    pos += 8 * (n + 1)
    return Batch(topic, t, messages.Packed(np.frombuffer(body, np.uint8, offset=pos).copy(), offsets),
                 bool(flags & FLAG_PROVISIONAL), bool(flags & FLAG_HOST_CLOCK), state, read_mono, recv_mono_ns)


def iter_batches(path: str) -> Iterator[Batch]:
    """Every published batch, as received, until the daemon closes the bus."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.connect(path)
        while True:
            head = _read_exact(sock, 4)
            if head is None:
                return
            body = _read_exact(sock, struct.unpack("<I", head)[0])
            if body is None:
                return
            yield parse_frame(body, time.monotonic_ns())


def _concat(parts: list[tuple[np.ndarray, messages.Packed, np.ndarray]]
            ) -> tuple[np.ndarray, messages.Packed, np.ndarray]:
    """``reader.concat`` of (log_time_ns, payloads, per-message state) batches."""
    if not parts:
        return np.zeros(0, np.int64), messages.Packed.from_list([]), np.zeros(0, np.uint8)
    t, p = concat([(t, p) for t, p, _ in parts])
    return t, p, np.concatenate([st for _, _, st in parts])


def in_stream(b: Batch, final: bool = False, host_clock: bool = False) -> bool:
    """Whether ``b`` belongs to the stream ``iter_blocks`` reads: ``/imu`` from the provisional stream (its
    pre-lock host-clock rows only with ``host_clock``) unless ``final``, every other topic as written to the
    file. Each topic then has one stamp base and its stamps never go backwards (the provisional ``/imu`` steps
    once, from the host clock to GPS time, when ``host_clock`` keeps the pre-lock rows)."""
    if b.topic == "/imu" and not final:
        return b.provisional and (host_clock or not b.host_clock)
    return not b.provisional


def iter_blocks(path: str, topics: Sequence[str], block_s: float, max_lag_s: float | None = None,
                final: bool = False, host_clock: bool = False) -> Iterator[LiveBlock]:
    """``batch_blocks`` of the bus at ``path`` (``iter_batches``)."""
    return batch_blocks(iter_batches(path), topics, block_s, max_lag_s, final, host_clock)


def batch_blocks(batches: Iterable[Batch], topics: Sequence[str], block_s: float, max_lag_s: float | None = None,
                 final: bool = False, host_clock: bool = False) -> Iterator[LiveBlock]:
    """Consecutive blocks of ``block_s`` seconds of log time, from the first message of ``topics``.

    ``final=False`` (default): ``/imu`` from the provisional stream (host-clock rows before the first lock
    only with ``host_clock``), every other topic as written to the file. ``final=True``: the file's messages.
    Topics arrive with different delays, so a block [t0, t1) is yielded once every topic seen so far has
    delivered a message at or after t1, or once any topic is ``max_lag_s`` past t1 (a topic that went quiet
    does not hold the others; default 2 s live, 90 s with ``final``, where ``/imu`` is ~60 s late). A
    message that arrives after its block was yielded goes into the next block. When the daemon closes the
    bus, the blocks holding what is left are yielded.
    """
    step = int(round(block_s * 1e9))
    if step <= 0:
        raise ValueError("block_s must be > 0")
    lag = int((max_lag_s if max_lag_s is not None else 90.0 if final else 2.0) * 1e9)
    wanted = set(topics)
    pending: dict[str, list[tuple[np.ndarray, messages.Packed, np.ndarray]]] = {}
    newest: dict[str, int] = {}
    t0: int | None = None
    read_mono = recv_mono = 0

    def block(t1: int) -> LiveBlock:
        data = {}
        worst: int | None = None
        for topic in topics:
            t, p, st = _concat(pending.get(topic, []))
            take = t < t1
            idx_in, idx_out = np.flatnonzero(take), np.flatnonzero(~take)
            d = decode(messages.topic_type(topic), t[idx_in], p.take(idx_in))
            if topic == "/imu" and not final:
                # decode sorts rows by log_time (stable); the states follow the same order
                d["sync_state"] = st[idx_in][np.argsort(t[idx_in], kind="stable")]
                if len(idx_in):
                    worst = int(d["sync_state"].min())
            data[topic] = d
            pending[topic] = [(t[idx_out], p.take(idx_out), st[idx_out])] if len(idx_out) else []
        return LiveBlock(t0, t1, data, provisional=worst is not None,
                         sync_state=worst, read_mono_ns=read_mono, recv_mono_ns=recv_mono)

    for b in batches:
        if b.topic not in wanted or len(b.log_time_ns) == 0 or not in_stream(b, final, host_clock):
            continue
        t = b.log_time_ns
        pending.setdefault(b.topic, []).append((t, b.payloads, b.state))
        newest[b.topic] = max(newest.get(b.topic, int(t.max())), int(t.max()))
        read_mono, recv_mono = max(read_mono, b.read_mono_ns), b.recv_mono_ns
        if t0 is None:
            t0 = int(t.min())
        while min(newest.values()) >= t0 + step or max(newest.values()) >= t0 + step + lag:
            yield block(t0 + step)
            t0 += step
    while t0 is not None and any(pending.values()):
        yield block(t0 + step)
        t0 += step


def stop_on_sigterm() -> None:
    """SIGTERM ends a live viewer like Ctrl-C (KeyboardInterrupt in the main thread; elsewhere nothing is set)."""

    def stop(signum: int, frame: object) -> None:
        raise KeyboardInterrupt

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, stop)


def _drained(items: Iterator, tap: Callable[[Batch], None] | None) -> Iterator:
    """``items`` read by a background thread (started at once) into an unbounded queue, so the bus socket is
    always drained: the daemon gives a slow client little time when it stops (and drops one that falls 16 MB
    behind). ``tap`` is called in that thread with each item as it arrives; an exception there, or in reading,
    is raised in the consumer."""
    q: queue.Queue = queue.Queue()
    done = object()

    def pump() -> None:
        try:
            for item in items:
                if tap is not None:
                    tap(item)
                q.put(item)
        except Exception as e:  # noqa: BLE001  (re-raised in the consumer)
            q.put(e)
        q.put(done)

    threading.Thread(target=pump, name="live-bus", daemon=True).start()

    def consume() -> Iterator:
        try:
            while (item := q.get()) is not done:
                if isinstance(item, Exception):
                    raise item
                yield item
        except KeyboardInterrupt:
            return

    return consume()


def follow(path: str, wait_s: float = 30.0, tap: Callable[[Batch], None] | None = None) -> Iterator[Batch]:
    """Every batch of the bus at ``path`` (``iter_batches``), for a live viewer: waits up to ``wait_s`` for the
    daemon to open the bus (FileNotFoundError after that), connects at once and drains the socket in a
    background thread (``tap`` sees each batch there, as it arrives, before the consumer does: it must be
    quick). Ends when the daemon closes the bus, or on Ctrl-C or SIGTERM (``stop_on_sigterm``) while the
    consumer waits for the next batch."""
    end = time.monotonic() + wait_s
    while not Path(path).exists():
        if time.monotonic() > end:
            raise FileNotFoundError(f"no live bus at {path} (is `fieldlog acquire` running with [daemon] bus?)")
        time.sleep(0.1)
    stop_on_sigterm()
    return _drained(iter_batches(path), tap)
