"""A drive, or the car live, and its live fusion served over the Foxglove WebSocket protocol
(``foxglove.websocket.v1``, through foxglove-sdk: the ``[foxglove]`` extra), so that Foxglove's 3D, Map, Plot and
Raw Messages panels show them: ``fieldlog replay DRIVE --foxglove [HOST:]PORT`` (``serve``) and ``fieldlog
acquire --foxglove [HOST:]PORT``, whose child ``fieldlog view --live BUS --foxglove [HOST:]PORT`` serves the
daemon's live bus (``serve_live``).

Both publish the live ``method`` fusion's ``/fusion/<method>/*``, ``/tf``, ``/tf_static`` and datum exactly as
``fuse`` writes them (``replay.solutions.write_solution``, ``Odometry``), with their ROS 2 Jazzy schemas, and the
source's own topics as CDR with their ROS 2 schemas. Every channel they will publish on is created before the
address is announced (``announce``: one line, ``foxglove: serving ws://HOST:PORT``), so a client subscribes
from the first advertisement and never to a channel the server advertised a moment before it registered it
(which the SDK refuses). Messages go to every connected client that subscribed to the channel; a client that
connects late starts from then, one that disconnects does not stop the others (the SDK's server runs in its
own threads and never blocks ``log``; each client has ``BACKLOG_MESSAGES`` queued at most, the oldest dropped
beyond). At the end the server stays up while a client is subscribed, for at most ``DRAIN_S``, so what is
queued for it is sent before the connection closes. Bound to 127.0.0.1 unless another host is given; port 0
picks a free port.

Both run the loop of every front end (``replay.loop.run``) with the sinks here: ``FusedTopics`` publishes each
block's fused rows, ``DriveMessages`` (replay) the drive's own messages before them.

Replay. The drive is played as ``fuse`` reads it (``replay.inputs.InputStream`` blocks, the incremental
``fusion.engine.Engine``), paced so that data time runs ``speed`` times faster than the wall clock. Each block
publishes, in log-time order within the block, the drive's own messages of the block's span (every topic but
``/raw/*``, as recorded, with the file's schema), then the block's fused rows.

Live. The daemon's live bus (``replay.live``) is drained by a background thread (``replay.live.follow``),
which publishes each batch of the daemon's derived topics the moment the bus delivers it, so neither the
fusion nor a slow client delays them, and the recorder never waits for this process (the bus drops a client
that falls far behind, it never blocks). ``/imu`` carries the provisional stamps of the causal time fit, from
the first PPS lock on (the file's final stamps come about half a time-sync window later and are not sent
again, so its stamps only increase); every other topic is sent as written to the file (``replay.live
.in_stream``). The fusion runs in the main thread on ``PLAY_BLOCK_S`` blocks of the same batches
(``replay.live.batch_blocks``). A fusion error (e.g. a diverged solution) is logged once and stops the fused
topics only; the daemon's go on. The channels of ``LIVE_TOPICS`` and the fused topics are created up front; a
topic outside them gets its channel when it first comes. base_link (``/tf``, odom) follows the daemon's
calibration's mounting when given, else base_link is the IMU. Ends when the daemon closes the bus (it stops),
or on Ctrl-C or SIGTERM.

The fusion stack is imported by the functions that fuse, so that ``fieldlog acquire --foxglove`` checks its
address (``parse_address``) without loading it into the recorder's process.
"""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Iterable, Iterator

import numpy as np

from fieldlog.acquire import calib
from fieldlog.drive import messages
from fieldlog.drive.files import DriveSpec, drive_files
from fieldlog.drive.records import make_reader
from fieldlog.replay.inputs import InputMap, InputStream

if TYPE_CHECKING:
    from fieldlog.fusion.config import FusionConfig
    from fieldlog.fusion.types import Outage, Solution
    from fieldlog.replay.inputs import InputBlock

log = logging.getLogger(__name__)

DEFAULT_HOST = "127.0.0.1"
PLAY_BLOCK_S = 1.0
# Outgoing messages buffered per client before the oldest is dropped: several seconds of a 500 Hz drive at
# speed 8 with its fused topics (about 100 bytes each, so a few MB per client at most).
BACKLOG_MESSAGES = 1 << 16
# Wall seconds the server stays up after the last message while a client is subscribed, so that what is
# queued for it is sent before the connection closes (the SDK offers no flush).
DRAIN_S = 2.0
# The daemon's derived topics (acquire.pipeline, acquire.canbus with [can]): what its live bus carries.
LIVE_TOPICS = ("/imu", "/gps/fix", "/gps/vel", "/gps/nmea", "/gps/receiver", "/pps", "/time/sync", "/tf_static",
               "/vehicle/twist", "/vehicle/wheel_speeds")

# (topic, schema name, ros2msg schema text); None, None: the contract's schema of the topic (drive.messages)
ChannelSpec = tuple[str, str | None, bytes | None]


def parse_address(text: str) -> tuple[str, int]:
    """``[HOST:]PORT`` -> (host, port); host 127.0.0.1 when not given; ValueError naming the option."""
    host, sep, port = text.rpartition(":")
    host = host.strip("[]") if sep else DEFAULT_HOST
    if not port.isdigit() or not 0 <= int(port) < 65536:
        raise ValueError(f"--foxglove {text!r}: expected [HOST:]PORT with PORT in 0..65535 (0: any free port)")
    return host or DEFAULT_HOST, int(port)


def announce(url: str) -> None:
    """The one line that says where the server listens (stdout, at once: a supervisor or a test reads it)."""
    print(f"foxglove: serving {url}", flush=True)


def fused_topics(method: str) -> list[str]:
    """The topics the live ``method`` fusion publishes (``replay.solutions.topics``)."""
    from fieldlog.fusion import methods
    from fieldlog.replay.solutions import topics

    return topics(method, methods.get(method).local_filters)


class FoxgloveSink:
    """Publishes what a Recorder would write (``write``, ``write_batch``, ``add_metadata``) on Foxglove channels,
    one per topic, CDR with the ROS 2 schema (``ros2msg``). Safe to call from several threads."""

    def __init__(self, context) -> None:
        import foxglove

        self._fg, self.context = foxglove, context
        self.channels: dict[str, object] = {}
        self.published = 0
        self._lock = threading.Lock()

    def channel(self, topic: str, schema_name: str | None = None, schema_data: bytes | None = None):
        """The channel of ``topic``, created on first use with this schema (default: the contract's)."""
        with self._lock:
            ch = self.channels.get(topic)
            if ch is None:
                if schema_name is None:
                    schema_name = messages.topic_type(topic)
                    schema_data = messages.schema_text(schema_name).encode()
                ch = self.channels[topic] = self._fg.Channel(
                    topic, schema=self._fg.Schema(name=schema_name, encoding="ros2msg", data=schema_data),
                    message_encoding="cdr", context=self.context)
            return ch

    def _count(self, n: int) -> None:
        with self._lock:
            self.published += n

    def write(self, topic: str, log_time_ns: int, data: bytes, schema_name: str | None = None,
              schema_data: bytes | None = None) -> None:
        self.channel(topic, schema_name, schema_data).log(data, log_time=int(log_time_ns))
        self._count(1)

    def write_batch(self, topic: str, log_time_ns, data) -> None:
        ch = self.channel(topic)
        for t, d in zip(np.asarray(log_time_ns).tolist(), messages.as_packed(data)):
            ch.log(d, log_time=int(t))
        self._count(len(log_time_ns))

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


class _Server:
    """A WebSocket server at ``address`` on a Context of its own, with the channels of ``own`` and of the live
    ``method`` fusion created (a context manager: the server stops on exit)."""

    def __init__(self, address: str, method: str, own: Iterable[ChannelSpec]) -> None:
        import foxglove    # (missing: the command says which extra to install)

        foxglove.set_log_level(logging.WARNING)   # its warnings into Python's logging: fieldlog's lines, not raw
        host, port = parse_address(address)
        context = foxglove.Context()
        self.subs = _Subscriptions()
        try:
            self.server = foxglove.start_server(name="fieldlog", host=host, port=port, context=context,
                                                server_listener=self.subs, message_backlog_size=BACKLOG_MESSAGES)
        except RuntimeError as e:      # FoxgloveError: the address cannot be resolved or bound
            raise ValueError(f"--foxglove {address}: {e}") from None
        self.address = f"ws://{host}:{self.server.port}"
        try:
            self.sink = FoxgloveSink(context)
            for topic, schema_name, schema_data in own:
                self.sink.channel(topic, schema_name, schema_data)
            for topic in fused_topics(method):
                self.sink.channel(topic)
        except BaseException:
            self.server.stop()
            raise

    def __enter__(self) -> _Server:
        return self

    def __exit__(self, *exc) -> None:
        self.server.stop()

    def drain(self) -> None:
        """Stay up while a client is subscribed, for at most ``DRAIN_S``."""
        end = time.monotonic() + DRAIN_S
        while self.subs.live and time.monotonic() < end:
            time.sleep(0.05)


class FusedTopics:
    """The loop's sink (``replay.loop.Sink``) of the live ``method`` fusion: each block's solution rows as
    ``fuse`` writes them, with their REP-105 frames (``Odometry``, base_link placed by ``mounting``)."""

    def __init__(self, sink: FoxgloveSink, method: str, mounting: calib.Mounting) -> None:
        from fieldlog.replay.solutions import Odometry, write_solution

        self.sink, self.method, self._write_solution = sink, method, write_solution
        self.odom = Odometry(method, mounting)
        self.solutions = 0

    def block(self, block: InputBlock, sol: Solution, done: list[Outage]) -> None:
        """Publish the block's solution rows (``replay.loop.Sink.block``)."""
        self._publish(sol)

    def finish(self, sol: Solution, done: list[Outage]) -> None:
        """Publish the last solution rows (``replay.loop.Sink.finish``)."""
        self._publish(sol)

    def _publish(self, sol: Solution) -> None:
        self._write_solution(self.sink, self.method, sol)
        self.odom.write(self.sink, sol)
        self.solutions += len(sol.t_ns)


class DriveMessages:
    """The loop's sink that publishes a drive's own messages (``_drive_messages``) up to each block's end,
    before that block's fused rows (it comes first among the sinks)."""

    def __init__(self, sink: FoxgloveSink, drive: DriveSpec) -> None:
        self.sink = sink
        self._own = _drive_messages(drive)
        self._pending = next(self._own, None)

    def block(self, block: InputBlock, sol: Solution, done: list[Outage]) -> None:
        """Publish the messages logged before the block's end (``replay.loop.Sink.block``)."""
        while self._pending is not None and self._pending[1] < block.t1_ns:
            self.sink.write(*self._pending)
            self._pending = next(self._own, None)

    def finish(self, sol: Solution, done: list[Outage]) -> None:
        """(Nothing: the drive's messages went with its blocks.)"""


@dataclass
class ServeResult:
    address: str
    blocks: int = 0
    solutions: int = 0
    published: int = 0


def _drive_channels(drive: DriveSpec) -> Iterator[ChannelSpec]:
    """The drive's topics but /raw/*, with their schemas, from the files' summaries."""
    for path in drive_files(drive):
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
        if summary is None:
            continue
        for ch in summary.channels.values():
            schema = summary.schemas.get(ch.schema_id)
            if not ch.topic.startswith("/raw/") and schema is not None:
                yield ch.topic, schema.name, schema.data


def _drive_messages(drive: DriveSpec):
    """The drive's messages but /raw/*, file by file in log-time order: (topic, t, data, schema name, schema)."""
    for path in drive_files(drive):
        with open(path, "rb") as f:
            for schema, ch, m in make_reader(f).iter_messages(log_time_order=True):
                if not ch.topic.startswith("/raw/"):
                    yield ch.topic, m.log_time, m.data, schema.name if schema else "", schema.data if schema else b""


def serve(drive: DriveSpec, method: str, speed: float, address: str, imap: InputMap,
          config: FusionConfig | None = None, on_ready: Callable[[str], None] = announce) -> ServeResult:
    """Play ``drive`` with live ``method`` fusion to Foxglove clients at ``address`` ([HOST:]PORT); ``on_ready``
    gets ``ws://HOST:PORT`` once the server listens with every channel. ``speed <= 0``: as fast as possible."""
    from fieldlog.fusion.engine import Engine
    from fieldlog.replay.loop import Pace, run
    from fieldlog.tools.fuse import BLOCK_S
    from fieldlog.tools.fuse_settings import drive_config, drive_mounting

    with _Server(address, method, _drive_channels(drive)) as srv:
        fused = FusedTopics(srv.sink, method, drive_mounting(drive))
        engine = Engine(method, config or drive_config(drive))
        on_ready(srv.address)
        # read in this process: the server's own (native) threads run, and forking a reader beside them is unsafe
        stream = InputStream(drive, imap, PLAY_BLOCK_S if speed > 0 else BLOCK_S).inputs()
        ran = run(stream, engine, [DriveMessages(srv.sink, drive), fused], Pace(speed))
        res = ServeResult(srv.address, ran.blocks, fused.solutions, srv.sink.published)
        srv.drain()
    return res


def serve_live(bus: str, method: str, address: str, config: FusionConfig | None = None,
               mounting: calib.Mounting | None = None, wait_s: float = 30.0,
               on_ready: Callable[[str], None] = announce) -> ServeResult:
    """Serve the running daemon's live bus at ``bus`` (its Unix socket) with live ``method`` fusion to Foxglove
    clients at ``address`` ([HOST:]PORT) until the daemon closes the bus (module docstring); waits up to
    ``wait_s`` for the bus to appear. ``on_ready`` gets ``ws://HOST:PORT`` once the server listens with every
    channel and the bus is being read. ``mounting``: the daemon's calibration's (None: base_link is the IMU)."""
    from fieldlog.drive.reader import IN_TOPICS
    from fieldlog.fusion.engine import Engine
    from fieldlog.replay import live
    from fieldlog.replay.loop import live_inputs, run

    with _Server(address, method, [(topic, None, None) for topic in LIVE_TOPICS]) as srv:
        fused = FusedTopics(srv.sink, method, mounting or calib.Mounting())
        engine = Engine(method, config)

        def relay(b: live.Batch) -> None:
            if live.in_stream(b):
                srv.sink.write_batch(b.topic, b.log_time_ns, b.payloads)

        def stopped(e: Exception) -> None:  # the fused topics stop there; the car's own are still worth serving
            log.error(f"live {method} fusion stopped: {type(e).__name__}: {e}; the daemon's topics are still "
                      "served")

        batches = live.follow(bus, wait_s, tap=relay)
        on_ready(srv.address)
        ran = run(live_inputs(live.batch_blocks(batches, IN_TOPICS, PLAY_BLOCK_S)), engine, [fused],
                  on_error=stopped)
        res = ServeResult(srv.address, ran.blocks, fused.solutions, srv.sink.published)
        srv.drain()
    return res
