"""``fieldlog replay DRIVE --foxglove [HOST:]PORT``: a drive and its live fusion served over the Foxglove
WebSocket protocol (``foxglove.websocket.v1``, through foxglove-sdk: the ``[foxglove]`` extra).

The drive is played as ``fuse`` reads it (``replay.inputs.InputStream`` blocks, the incremental
``fusion.engine.Engine``), paced so that data time runs ``speed`` times faster than the wall clock. Each block
publishes, in log-time order within the block, the drive's own messages of the block's span (every topic but
``/raw/*``, as recorded: CDR with the file's ROS 2 schema) and the live fusion's ``/fusion/<method>/*``, ``/tf``,
``/tf_static`` and datum, exactly as ``fuse`` writes them (``replay.solutions.write_solution``, ``Odometry``), with
their ROS 2 Jazzy schemas, so Foxglove's 3D, Map, Plot and Raw Messages panels show them. Messages go to
every connected client that subscribed to the channel; a client that connects late starts from then, one that
disconnects does not stop the others or the replay (the SDK's server runs in its own threads and never
blocks ``log``). At the end the server stays up while a client is subscribed, for at most ``DRAIN_S``, so what
is queued for it is sent before the connection closes. Bound to 127.0.0.1 unless another address is given.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
from mcap.reader import make_reader

from fieldlog.acquire import messages
from fieldlog.fusion.config import FusionConfig
from fieldlog.fusion.engine import Engine
from fieldlog.fusion.filters import has_local_filters
from fieldlog.replay.drive import DriveSpec, drive_files
from fieldlog.replay.inputs import InputMap, InputStream
from fieldlog.replay.solutions import Odometry, topics, write_solution
from fieldlog.tools.fuse import BLOCK_S, drive_config, drive_mounting

DEFAULT_HOST = "127.0.0.1"
PLAY_BLOCK_S = 1.0
# Outgoing messages buffered per client before the oldest is dropped: several seconds of a 500 Hz drive at
# speed 8 with its fused topics (about 100 bytes each, so a few MB per client at most).
BACKLOG_MESSAGES = 1 << 16
# Wall seconds the server stays up after the last message while a client is subscribed, so that what is
# queued for it is sent before the connection closes (the SDK offers no flush).
DRAIN_S = 2.0


def parse_address(text: str) -> tuple[str, int]:
    """``[HOST:]PORT`` -> (host, port); host 127.0.0.1 when not given; ValueError naming the option."""
    host, sep, port = text.rpartition(":")
    host = host.strip("[]") if sep else DEFAULT_HOST
    if not port.isdigit() or not 0 <= int(port) < 65536:
        raise ValueError(f"--foxglove {text!r}: expected [HOST:]PORT with PORT in 0..65535 (0: any free port)")
    return host or DEFAULT_HOST, int(port)


class FoxgloveSink:
    """Publishes what a Recorder would write (``write``, ``write_batch``, ``add_metadata``) on Foxglove channels,
    one per topic, CDR with the ROS 2 schema (``ros2msg``)."""

    def __init__(self, context) -> None:
        import foxglove

        self._fg, self.context = foxglove, context
        self.channels: dict[str, object] = {}
        self.published = 0

    def channel(self, topic: str, schema_name: str | None = None, schema_data: bytes | None = None):
        ch = self.channels.get(topic)
        if ch is None:
            if schema_name is None:
                schema_name = messages.topic_type(topic)
                schema_data = messages.schema_text(schema_name).encode()
            ch = self.channels[topic] = self._fg.Channel(
                topic, schema=self._fg.Schema(name=schema_name, encoding="ros2msg", data=schema_data),
                message_encoding="cdr", context=self.context)
        return ch

    def write(self, topic: str, log_time_ns: int, data: bytes) -> None:
        self.channel(topic).log(data, log_time=int(log_time_ns))
        self.published += 1

    def write_batch(self, topic: str, log_time_ns, data) -> None:
        ch = self.channel(topic)
        for t, d in zip(np.asarray(log_time_ns).tolist(), messages.as_packed(data)):
            ch.log(d, log_time=int(t))
        self.published += len(log_time_ns)

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """(No metadata in the live protocol.)"""


class _Subscriptions:
    """ServerListener counting live subscriptions (a disconnect unsubscribes every channel of the client)."""

    def __init__(self) -> None:
        self.live: set[tuple[int, int]] = set()

    def on_subscribe(self, client, channel) -> None:
        self.live.add((client.id, channel.id))

    def on_unsubscribe(self, client, channel) -> None:
        self.live.discard((client.id, channel.id))


@dataclass
class ServeResult:
    address: str
    blocks: int = 0
    solutions: int = 0
    published: int = 0


def _drive_messages(drive: DriveSpec):
    """The drive's messages but /raw/*, file by file in log-time order: (topic, schema name, schema, t, data)."""
    for path in drive_files(drive):
        with open(path, "rb") as f:
            for schema, ch, m in make_reader(f).iter_messages(log_time_order=True):
                if not ch.topic.startswith("/raw/"):
                    yield ch.topic, schema.name if schema else "", schema.data if schema else b"", m.log_time, m.data


def _advertise(sink: FoxgloveSink, drive: DriveSpec, method: str, has_locals: bool) -> None:
    """Create every channel the replay will publish on before a client can connect: the drive's topics (from
    the files' summaries) and the fused ones. A client then subscribes from the first advertisement, and never
    to a channel the server advertised a moment before it registered it (which it refuses)."""
    for path in drive_files(drive):
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
        if summary is None:
            continue
        for ch in summary.channels.values():
            schema = summary.schemas.get(ch.schema_id)
            if not ch.topic.startswith("/raw/") and schema is not None:
                sink.channel(ch.topic, schema.name, schema.data)
    for topic in topics(method, has_locals):
        sink.channel(topic)


def serve(drive: DriveSpec, method: str, speed: float, address: str, imap: InputMap,
          config: FusionConfig | None = None, on_ready: Callable[[str], None] = print) -> ServeResult:
    """Play ``drive`` with live ``method`` fusion to Foxglove clients at ``address`` ([HOST:]PORT); ``on_ready``
    gets ``ws://HOST:PORT`` once the server listens. ``speed <= 0``: as fast as possible."""
    import foxglove    # (missing: the command says which extra to install)

    host, port = parse_address(address)
    context = foxglove.Context()
    subs = _Subscriptions()
    server = foxglove.start_server(name="fieldlog", host=host, port=port, context=context, server_listener=subs,
                                   message_backlog_size=BACKLOG_MESSAGES)
    res = ServeResult(f"ws://{host}:{server.port}")
    try:
        sink = FoxgloveSink(context)
        engine = Engine(method, config or drive_config(drive))
        _advertise(sink, drive, method, has_local_filters(method))
        on_ready(res.address)
        odom = Odometry(method, drive_mounting(drive))
        own = _drive_messages(drive)
        pending = next(own, None)
        wall0 = t0 = None
        for block in InputStream(drive, imap, PLAY_BLOCK_S if speed > 0 else BLOCK_S):
            while pending is not None and pending[3] < block.t1_ns:
                topic, name, data_schema, t, data = pending
                sink.channel(topic, name, data_schema).log(data, log_time=t)
                sink.published += 1
                pending = next(own, None)
            sol, _done = engine.process(block.imu, block.gps)
            write_solution(sink, method, sol)
            odom.write(sink, sol)
            res.blocks += 1
            res.solutions += len(sol.t_ns)
            if speed > 0:
                wall0 = time.monotonic() if wall0 is None else wall0
                t0 = block.t0_ns if t0 is None else t0
                wait = (block.t1_ns - t0) / 1e9 / speed - (time.monotonic() - wall0)
                if wait > 0:
                    time.sleep(wait)
        sol, _done = engine.finish()
        write_solution(sink, method, sol)
        odom.write(sink, sol)
        res.solutions += len(sol.t_ns)
        res.published = sink.published
        drain_end = time.monotonic() + DRAIN_S
        while subs.live and time.monotonic() < drain_end:
            time.sleep(0.05)
    finally:
        server.stop()
    return res
