"""Live bus client: the derived messages of a running ``fieldlog acquire`` as the blocks the MCAP reader yields.

The daemon serves the bus on a Unix domain socket (``[daemon] bus`` in its config; frame layout in
``acquire.daemon.BusServer`` and docs/data-model.md). ``iter_blocks`` yields ``replay.reader.Block``s with
the same per-topic dicts as ``replay.reader.iter_blocks`` (decoded by the same ``reader.decode``), so fusion
code cannot tell live from recorded.
"""
from __future__ import annotations

import socket
import struct
from typing import Iterator, Sequence

import numpy as np

from acquire import messages
from replay.reader import Block, decode


def _read_exact(sock: socket.socket, n: int) -> bytes | None:
    buf = bytearray()
    while len(buf) < n:
        part = sock.recv(n - len(buf))
        if not part:
            return None
        buf += part
    return bytes(buf)


def iter_batches(path: str) -> Iterator[tuple[str, np.ndarray, messages.Packed]]:
    """(topic, log_time_ns, payloads) per published batch until the daemon closes the bus."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.connect(path)
        while True:
            head = _read_exact(sock, 4)
            if head is None:
                return
            body = _read_exact(sock, struct.unpack("<I", head)[0])
            if body is None:
                return
            (tlen,) = struct.unpack_from("<H", body, 0)
            topic = body[2:2 + tlen].decode()
            pos = 2 + tlen
            (n,) = struct.unpack_from("<I", body, pos)
            pos += 4
            t = np.frombuffer(body, "<i8", n, pos).astype(np.int64)
            pos += 8 * n
            offsets = np.frombuffer(body, "<i8", n + 1, pos).astype(np.int64)
            pos += 8 * (n + 1)
            yield topic, t, messages.Packed(np.frombuffer(body, np.uint8, offset=pos).copy(), offsets)


def iter_blocks(path: str, topics: Sequence[str], block_s: float, max_lag_s: float = 90.0) -> Iterator[Block]:
    """Consecutive blocks of ``block_s`` seconds of log time, from the first message of ``topics``.

    Topics arrive with different delays (``/imu`` is final about half a time-sync window after it was read,
    fixes at once), so a block [t0, t1) is yielded once every topic seen so far has delivered a message at
    or after t1, or once any topic is ``max_lag_s`` past t1 (a topic that went quiet does not hold the
    others). A message that arrives after its block was yielded goes into the next block. The last partial
    block is yielded when the daemon closes the bus.
    """
    step = int(round(block_s * 1e9))
    if step <= 0:
        raise ValueError("block_s must be > 0")
    lag = int(max_lag_s * 1e9)
    wanted = set(topics)
    pending: dict[str, list[tuple[np.ndarray, messages.Packed]]] = {}
    newest: dict[str, int] = {}
    t0: int | None = None

    def block(t1: int | None) -> Block:
        data = {}
        for topic in topics:
            parts = pending.get(topic, [])
            t = np.concatenate([p[0] for p in parts]) if parts else np.zeros(0, np.int64)
            msgs = [m for p in parts for m in p[1]]
            take = np.ones(len(t), bool) if t1 is None else t < t1
            keep = np.flatnonzero(~take).tolist()
            data[topic] = decode(messages.topic_type(topic), t[take],
                                 messages.Packed.from_list([msgs[i] for i in np.flatnonzero(take).tolist()]))
            pending[topic] = [(t[keep], messages.Packed.from_list([msgs[i] for i in keep]))] if keep else []
        return Block(t0, t1 if t1 is not None else t0 + step, data)

    for topic, t, p in iter_batches(path):
        if topic not in wanted or len(t) == 0:
            continue
        pending.setdefault(topic, []).append((t, p))
        newest[topic] = max(newest.get(topic, t.max()), int(t.max()))
        if t0 is None:
            t0 = int(t.min())
        while min(newest.values()) >= t0 + step or max(newest.values()) >= t0 + step + lag:
            yield block(t0 + step)
            t0 += step
    if t0 is not None and any(pending.values()):
        yield block(None)
