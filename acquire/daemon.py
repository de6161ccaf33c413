"""``fieldlog acquire``: live capture from the DAQ and GPS serial ports into crash-safe, rotated MCAP files.

Threads. One reader thread per port (pyserial opens and configures the port; the thread waits with
``select`` and takes whatever ``os.read`` returns, stamping host monotonic and wall-clock time the moment the
read returns) puts ``RawRead``s on that port's bounded queue. The raw path, one thread (``process``), merges the
queues in ``read_order``, records each read in ``/raw/<port>`` (``Pipeline.record``), rotates the files and
shows the status, and hands the read on to the derived path's bounded queue without waiting. The derived path,
one thread (``derive``), owns the rest of the Pipeline and the live bus: it processes the reads in the order
they were recorded (``Pipeline.process``: decoding, the counter judge, time sync, CAN decoding, provisional
``/imu``), so while it keeps up the daemon writes exactly what ``fieldlog rebuild`` of its ``/raw/*`` writes.
Both write through the session's sink, one lock around the Recorder.

Raw first. Nothing the derived path does makes the raw path wait: when the derived queue (``[daemon]
derived_queue_mb``) is full, reads are recorded and not processed until it is half empty, counted
(``daemon.derived_dropped_reads`` / ``_bytes``) and logged when the dropping begins and ends; the derived topics
then have a gap that ``fieldlog rebuild`` fills from the raw bytes, and the status line shows the derived path's
lag and drops.

Merge rule. The raw path holds the head read of each queue and processes the earliest head in
``read_order`` once no read that sorts before it can still come from the other port, that is when the other
port (a) has a head of its own (which sorts later), or (b) is idle: its reader is waiting for bytes or for
the port to come back and its queue is empty (a reader marks itself busy before ``os.read`` and idle only
after the read is queued, so every read it delivers later is stamped after the moment the idle flag was
seen), or (c) is gone (its thread ended). A bounded wait, ``merge_wait_s``, caps this: a head older than that
is processed anyway, so a stalled port never stalls the other. A read that then arrives out of order is
still processed (never dropped) and counted in ``daemon.late_reads``; ``rebuild`` sorts by ``read_order`` and
would differ from the live derived topics only there.

Queues are bounded (``queue_reads`` per port); when one stays full for a second the read is dropped and
counted (``port.<name>.dropped_reads/bytes``); that only happens when the raw path cannot keep up (recording
stalled: a disk that does not take the writes).

The vehicle bus. With ``[can] url`` (``--can``) a third reader takes the CAN adapter (``acquire/canport.py``: an
SLCAN serial port read as the others, or SocketCAN through python-can) as port ``can``, merged by the same rule;
its faults are handled as below.

Faults. A port whose read fails or hits end of file (adapter unplugged, pty closed) is closed and reopened
every ``reconnect_s`` until it comes back; the outage is recorded as an ``acquire.port_event`` metadata
record (``event`` = ``lost`` / ``back``, host mono and wall ns, the error) and counted in
``port.<name>.disconnects``; ``/raw`` has no reads in the gap. Corrupt bytes are the decoders' business
(resynchronised and counted). A full disk (ENOSPC), an exceeded quota (EDQUOT) or file size limit (EFBIG;
SIGXFSZ is ignored so that a ``ulimit -f`` gives the error rather than a kill) stops the daemon with a clear
message naming the file and exit code 2 (the storage given is the problem, as with any bad output); the file
keeps every chunk flushed before (``fieldlog recover`` or the next start rescues it if the summary could not be
written).
The derived path never stops the recording: an exception it raises outside ``Pipeline.process`` (which
already counts and logs its own; a live-bus or finishing failure, say) is logged once as an error, the live bus is
closed, and the raw path records on and queues nothing more for it (``daemon.derived_error``; the reads are counted
in ``daemon.derived_dropped_reads/bytes``; ``acquire.stop`` ``derived`` = ``failed``); only a full disk met there
stops the daemon as above.
SIGINT/SIGTERM finish the file (summary and index) and exit 0 within ``STOP_S`` whatever the derived path is
doing: the readers stop, the raw path records what they had read, and the derived path gets until
``DERIVED_STOP_S`` after the signal to process what is queued and write its pending tail (``Pipeline.finish``);
a derived path still busy then is left behind (its later writes are discarded), and the file is closed with the
derived topics ending where the derived path stood, logged and in the ``acquire.stop`` record (``derived``:
``complete`` or ``cut``, the reads recorded but not processed, and the host mono ns of the signal and of the
close).

Files. A session is a rosbag2 directory, ``DIR/<session start UTC>/`` (``config.session_name``; ``-2``, ``-3``
appended if a session of the same second exists) of ``<session start UTC>_<NNNN>.mcap`` files
(``config.file_name``) and the ``metadata.yaml`` that lists the closed ones, written again at each rotation
and on close (``drive/bagdir.py``), so ``ros2 bag info/play DIR/<session>`` and rosbags open it. One
Pipeline runs for the whole
session and its sink switches files on rotation (by host time since the file was opened or by size), so
decoder and time-sync state carry over: the raw bytes are split between files at a read boundary, and the
derived topics go to the file open when they become final (``/imu`` lags ``/raw/daq`` by about half the
time-sync window). Each file carries the ``drive``, ``calibration`` and ``timesync`` metadata, and at close
the session's cumulative ``acquire.counters``. On start, files in DIR and its session directories without a
summary (a crash or power loss) are recovered to ``NAME.recovered.mcap`` next to the untouched original, and
that session's ``metadata.yaml`` is written again with the recovered file in the cut one's place.

Live bus (``[daemon] bus``). Every derived message is published when it is written to the file (final
stamps), and, while a client is connected, each read's DAQ frames are published at once as a provisional
``/imu`` batch stamped by ``ProvisionalImu`` (``TimeSync.causal_stamp``): the file never sees those.
"""
from __future__ import annotations

import errno
import logging
import os
import queue
import select
import shutil
import signal
import socket
import stat
import struct
import sys
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, TextIO

import numpy as np
import serial

from fieldlog.acquire import calib, canport, nmea, recovery, timesync
from fieldlog.drive import bagdir, messages, outputs, recorder
from fieldlog.acquire.config import (AcquireConfig, CanConfig, GpsPortConfig, PortConfig, RecorderConfig, file_name,
                                     session_name)
from fieldlog.acquire.gpsd import BACKOFF_MAX_S, GpsdLink
from fieldlog.acquire.pipeline import Pipeline, PipelineConfig, RawRead, raised_at, read_order

NS = 1_000_000_000
PORTS = ("daq", "gps")
MAX_SKIPPED = 100_000  # taken file names skipped in a row before the daemon gives up
# the room a recovery on start needs: the recovered copy is the kept chunks plus the re-derived tail, and a file cut
# before its /imu (which lags the raw bytes by up to a minute) is mostly tail: /imu takes about twice the raw bytes
# it is derived from, so a copy takes up to ~3.3x its cut file; and the recording that follows needs room too
RECOVER_SPACE_FACTOR = 4
RECOVER_RESERVE_BYTES = 256 << 20
# A read lands in the reader's own buffer and is copied out at its length: os.read(fd, n) mallocs n bytes and
# shrinks them to the read, which, for ~1 KiB reads of 64 KiB blocks handed to another thread, fragments the
# heap: free memory glibc cannot return, and RSS that grows with the drive (docs/results.md, the soak)
READ_SIZE = 65536
STORAGE_FULL = {errno.ENOSPC: "disk full", errno.EDQUOT: "disk quota exceeded", errno.EFBIG: "file size limit"}
STOP_S = 2.0            # SIGINT/SIGTERM to the file closed, at most (host s)
DERIVED_STOP_S = 1.25   # of which the derived path may take this to finish (the rest: draining the ports, closing)


log = logging.getLogger("fieldlog.acquire")
LOG_FORMAT = "%(asctime)s.%(msecs)03dZ %(levelname)s %(name)s: %(message)s"


def setup_logging(verbosity: int = 0, stream: TextIO = sys.stderr) -> None:
    """The daemon's log: one timestamped line (UTC) per event on ``stream`` (under systemd: the journal).
    verbosity: -2 warnings and errors only, -1 and 0 info (events: start, files, port lost/back, stop), 1 debug."""
    handler = logging.StreamHandler(stream)
    fmt = logging.Formatter(LOG_FORMAT, datefmt="%Y-%m-%dT%H:%M:%S")
    fmt.converter = time.gmtime
    handler.setFormatter(fmt)
    root = logging.getLogger("fieldlog")
    root.handlers[:] = [handler]
    root.setLevel(logging.DEBUG if verbosity > 0 else logging.WARNING if verbosity < -1 else logging.INFO)
    root.propagate = False


class PortError(ValueError):
    """A port that cannot be opened at start (a config or wiring problem: exit code 2)."""


@dataclass(frozen=True)
class PortEvent:
    """A port went away (``lost``) or came back (``back``), at host mono/wall ns."""

    port: str
    kind: str
    mono_ns: int
    wall_ns: int
    detail: str


@dataclass
class PortStats:
    reads: int = 0
    bytes: int = 0
    dropped_reads: int = 0
    dropped_bytes: int = 0
    disconnects: int = 0
    connected: bool = False


def open_port(cfg: PortConfig | CanConfig) -> serial.Serial | GpsdLink | canport.SlcanLink | canport.SocketcanLink:
    """The port, raw, at the configured baud rate, non-blocking (the reader waits with select); for a
    ``gpsd://`` GPS port the connection to gpsd in raw mode (acquire/gpsd.py); for ``[can]`` its adapter
    (acquire/canport.py)."""
    if isinstance(cfg, CanConfig):
        return canport.open_link(cfg.url, cfg.baud)
    address = cfg.gpsd if isinstance(cfg, GpsPortConfig) else None
    if address is not None:
        return GpsdLink(address)
    return serial.Serial(cfg.port, cfg.baud, timeout=0, exclusive=True)


class PortReader(threading.Thread):
    """Reads one port into a bounded queue of RawRead / PortEvent; reconnects when the port goes away: a
    serial port every ``reconnect_s``, gpsd with a backoff doubling from ``reconnect_s`` to BACKOFF_MAX_S."""

    def __init__(self, name: str, cfg: PortConfig, ser: serial.Serial | GpsdLink, maxsize: int,
                 wake: threading.Event, stop: threading.Event, reconnect_s: float) -> None:
        super().__init__(name=f"read-{name}", daemon=True)
        self.port, self.cfg, self.ser = name, cfg, ser
        self.q: queue.Queue = queue.Queue(maxsize)
        self.wake, self.stop, self.reconnect_s = wake, stop, reconnect_s
        self.gpsd = isinstance(ser, GpsdLink)
        self.max_retry_s = max(reconnect_s, BACKOFF_MAX_S) if self.gpsd else reconnect_s
        self.stats = PortStats(connected=True)
        self.gpsd_reports = 0     # gpsd's own JSON reports taken out of the stream (all connections)
        self.busy = False     # True from the moment bytes may be read until that read is queued

    def _put(self, item: RawRead | PortEvent) -> None:
        try:
            self.q.put(item, timeout=1.0)
        except queue.Full:
            self.stats.dropped_reads += 1
            self.stats.dropped_bytes += len(getattr(item, "data", b""))
        self.wake.set()

    def _event(self, kind: str, detail: str) -> None:
        self._put(PortEvent(self.port, kind, time.monotonic_ns(), time.time_ns(), detail))

    def run(self) -> None:
        retry_s = self.reconnect_s
        while not self.stop.is_set():
            if self.ser is None:
                device = os.path.realpath(self.cfg.port) if not self.gpsd and os.path.isabs(self.cfg.port) \
                    else self.cfg.port
                try:
                    self.ser = open_port(self.cfg)
                except (serial.SerialException, OSError):
                    self.stop.wait(retry_s)
                    retry_s = min(2 * retry_s, self.max_retry_s)
                    continue
                retry_s = self.reconnect_s
                self.busy = True
                self.stats.connected = True
                self._event("back", self.cfg.port if device == self.cfg.port else f"{self.cfg.port} -> {device}")
                self.busy = False
            self._read_until_lost()
        if self.ser is not None:
            self._close_link()

    def _read_until_lost(self) -> None:
        fd = self.ser.fileno()
        st = self.stats
        buf = memoryview(bytearray(READ_SIZE))
        read_ready = getattr(self.ser, "read_ready", None)     # a link that is no byte stream (SocketCAN)
        while not self.stop.is_set():
            hold_s = self.ser.hold_s() if self.gpsd else None
            ready, _, _ = select.select([fd], [], [], 0.1 if hold_s is None else hold_s)
            if not ready:
                if hold_s is not None:         # nothing followed what might have begun a gpsd report
                    self.busy = True
                    self._deliver(self.ser.release(), time.monotonic_ns(), time.time_ns())
                continue
            self.busy = True
            try:
                data = read_ready() if read_ready is not None else bytes(buf[:os.readv(fd, [buf])])  # (READ_SIZE)
                err = "end of file" if not data and read_ready is None else ""
            except OSError as e:
                data, err = b"", os.strerror(e.errno or 0) or str(e)
            mono, wall = time.monotonic_ns(), time.time_ns()
            if err:
                self._close_link()
                st.connected = False
                st.disconnects += 1
                self._event("lost", err)
                self.busy = False
                return
            self._deliver(self.ser.decode(data) if self.gpsd else data, mono, wall)

    def _deliver(self, data: bytes, mono: int, wall: int) -> None:
        """Queue one read's bytes with the host times at which the read returned; clears ``busy``."""
        if data:                               # (a gpsd read may hold only gpsd's own reports)
            self.stats.reads += 1
            self.stats.bytes += len(data)
            self._put(RawRead(self.port, mono, wall, data))
        self.busy = False

    def _close_link(self) -> None:
        if self.gpsd:
            self.gpsd_reports += self.ser.stream.reports_seen
        self.ser.close()
        self.ser = None


class RotatingSink:
    """The Pipeline's sink: writes to the session's current file; ``open_next`` closes it and opens the next.

    Also keeps what the status line shows (the latest /time/sync record and GGA sentence) and forwards
    derived messages to ``publish`` (the live bus)."""

    def __init__(self, out_dir: Path, session_wall_ns: int, rcfg: RecorderConfig,
                 headers: Callable[[int, Path | None], dict[str, dict[str, str]]],
                 publish: Callable[..., None] | None = None,
                 log: Callable[[str, int], None] = lambda msg, level: None) -> None:
        self.out_dir, self.session_wall_ns, self.rcfg, self.headers = out_dir, session_wall_ns, rcfg, headers
        self.log = log
        self.publish = publish
        self.read_mono_ns = 0       # host mono of the read being processed (sent with what it publishes)
        self.rec: recorder.Recorder | None = None
        self.index = 0
        self.opened_mono = 0.0
        self.files: list[Path] = []
        self.closed: list[bagdir.FileInfo] = []      # what metadata.yaml lists
        self.last_sync: bytes | None = None
        self.last_gga: bytes | None = None
        self.skipped = 0            # file names found taken (a file or a link there)
        self.lock = threading.RLock()   # the raw and the derived path both write; a Recorder has one owner at a time
        self.discarded = 0          # messages the derived path wrote after the last file was closed

    def open_next(self, closing: dict[str, dict[str, str]] | None = None) -> Path:
        """Close the current file and open the next free name of the session: a name that exists is skipped (a
        symbolic link there is logged, never followed); ``outputs.Refused`` after ``MAX_SKIPPED`` taken names."""
        with self.lock:
            return self._open_next(closing)

    def _open_next(self, closing: dict[str, dict[str, str]] | None) -> Path:
        prev = self._close(closing) if self.rec is not None else None
        for _ in range(MAX_SKIPPED):
            self.index += 1
            path = self.out_dir / file_name(self.session_wall_ns, self.index)
            try:
                self.rec = recorder.Recorder(path, chunk_size=self.rcfg.chunk_size,
                                             flush_interval_s=self.rcfg.flush_interval_s,
                                             compression=self.rcfg.compression, fsync=self.rcfg.fsync,
                                             root=self.out_dir)
                break
            except outputs.Refused as e:
                if path.is_symlink():
                    self.log(f"{e}; recording to the next name instead", logging.WARNING)
                self.skipped += 1
        else:
            raise outputs.Refused(f"{self.out_dir}: the next {MAX_SKIPPED} file names of the session are taken")
        for name, d in self.headers(self.index, prev).items():
            self.rec.add_metadata(name, d)
        self.rec.flush()
        self.opened_mono = time.monotonic()
        self.files.append(path)
        return path

    def close(self, closing: dict[str, dict[str, str]] | None = None) -> Path:
        """Close the current file (``closing``: metadata records added first); later writes are discarded."""
        with self.lock:
            return self._close(closing)

    def _close(self, closing: dict[str, dict[str, str]] | None) -> Path:
        rec, self.rec = self.rec, None
        for name, d in (closing or {}).items():
            rec.add_metadata(name, d)
        rec.close()
        self.closed.append(bagdir.file_info(rec.path))
        bagdir.write_metadata(self.out_dir, self.closed, fsync=self.rcfg.fsync)
        return rec.path

    @property
    def path(self) -> Path:
        """The file being written."""
        return self.rec.path

    def size(self) -> int:
        return os.path.getsize(self.rec.path)

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        with self.lock:
            self.rec.add_metadata(name, data)

    def maybe_flush(self) -> None:
        with self.lock:
            self.rec.maybe_flush()

    def write(self, topic: str, log_time_ns: int, data: bytes) -> None:
        with self.lock:
            if self.rec is None:
                self.discarded += 1
                return
            self.rec.write(topic, log_time_ns, data)
        if topic == "/gps/nmea" and b"GGA," in data:
            self.last_gga = data
        if self.publish is not None and not topic.startswith("/raw"):
            self.publish(topic, np.array([log_time_ns], np.int64), messages.Packed.from_list([data]),
                         read_mono_ns=self.read_mono_ns)

    def write_batch(self, topic: str, log_time_ns: np.ndarray, data) -> None:
        with self.lock:
            if self.rec is None:
                self.discarded += len(log_time_ns)
                return
            self.rec.write_batch(topic, log_time_ns, data)
        p = messages.as_packed(data)
        if topic == "/time/sync" and len(p):
            self.last_sync = p[len(p) - 1]
        if self.publish is not None:
            self.publish(topic, np.asarray(log_time_ns, np.int64), p, read_mono_ns=self.read_mono_ns)


BUS_PROVISIONAL = 1      # bus frame flag: stamps from the causal time fit, not those of the file
BUS_HOST_CLOCK = 2       # bus frame flag: no GPS time fit yet, stamps from the host clock (with provisional)
BUS_STATE_FINAL = 255    # per-message state of final messages (their sync state is on /time/sync)


class BusError(ValueError):
    """``[daemon] bus`` names a path the bus must not take (a config problem: exit code 2)."""


def remove_stale_socket(path: str) -> None:
    """Make room for the bus socket at ``path``: nothing there is fine; a Unix socket of this user that nobody
    listens on (a daemon that was killed) is removed; anything else raises BusError and is left alone."""
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return
    if not stat.S_ISSOCK(st.st_mode) or st.st_uid != os.getuid():
        kind = ("a socket of another user" if stat.S_ISSOCK(st.st_mode) else
                "a symbolic link (never followed), not a socket" if stat.S_ISLNK(st.st_mode) else "not a socket")
        raise BusError(f"[daemon] bus: {path} exists and is {kind}; it is left alone: choose another path")
    probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        probe.connect(path)
    except ConnectionRefusedError:
        Path(path).unlink()
        return
    except OSError:
        pass
    finally:
        probe.close()
    raise BusError(f"[daemon] bus: {path} is in use (another daemon is running): stop it or choose another path")


class BusServer:
    """The live bus: a Unix domain socket (local only, mode 0600) streaming the derived messages.

    Each ``publish`` (one topic, n messages) is one frame, little-endian: u32 length of the rest, u8 flags
    (``BUS_PROVISIONAL``, ``BUS_HOST_CLOCK``), i64 read_mono_ns (host monotonic time of the serial read whose
    processing published the frame), u16 topic length, topic (UTF-8), u32 n, n x i64 log_time_ns, n x u8
    sync state (SyncState, or ``BUS_STATE_FINAL``), (n + 1) x i64 payload offsets, the CDR payloads
    (``replay/live.py`` decodes them into the blocks the MCAP reader yields). It never blocks its callers: sockets
    are non-blocking, each client has an output buffer, and a client more than ``max_buffer`` bytes behind is
    disconnected (counted in ``dropped_clients``). Clients only read: bytes a client sends are read and dropped
    (``pump``), counted in ``ignored_bytes`` and logged once per client. Recording never depends on a client: at
    most ``MAX_CLIENTS`` are served (one more is closed at once, counted in ``refused_clients``), so clients cannot
    take the file descriptors the recorder needs, and a client the daemon cannot take (out of descriptors or
    memory) is left waiting, counted in ``accept_errors``; both logged once. Both paths call it (the derived path
    publishes and pumps; the raw path writes ``/tf_static`` at a file's start): one lock holds the clients and
    their buffers, so no buffer is cut while another thread's send holds it and frames go out whole, in the order
    published.
    """

    MAX_CLIENTS = 16

    def __init__(self, path: str, max_buffer: int = 16 << 20) -> None:
        self.path = path
        remove_stale_socket(path)
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        old = os.umask(0o177)
        try:
            self.sock.bind(path)
        finally:
            os.umask(old)
        self.sock.listen(8)
        self.sock.setblocking(False)
        self.max_buffer = max_buffer
        self.clients: dict[socket.socket, bytearray] = {}
        self.dropped_clients = 0
        self.refused_clients = 0
        self.accept_errors = 0
        self.ignored_bytes = 0
        self._noisy: set[socket.socket] = set()
        self._lock = threading.Lock()  # the clients, their buffers and the listening socket (class docstring)
        self._closed = False

    def active(self) -> bool:
        """Accept waiting clients; True if any is connected (otherwise publishing is a no-op)."""
        with self._lock:
            self._accept()
            return bool(self.clients)

    def publish(self, topic: str, log_time_ns: np.ndarray, p: messages.Packed, *, flags: int = 0,
                state: np.ndarray | None = None, read_mono_ns: int = 0) -> None:
        """One frame to every client: ``p``, stamped ``log_time_ns`` (UTC ns), ``state`` per message."""
        if len(p) == 0 or not self.active():
            return
        t = topic.encode()
        st = np.full(len(p), BUS_STATE_FINAL, np.uint8) if state is None else np.asarray(state, np.uint8)
        body = b"".join((struct.pack("<BqH", flags, read_mono_ns, len(t)), t, struct.pack("<I", len(p)),
                         np.asarray(log_time_ns, "<i8").tobytes(), st.tobytes(),
                         (p.offsets - p.offsets[0]).astype("<i8").tobytes(),
                         p.buf[p.offsets[0]:p.offsets[-1]].tobytes()))
        frame = struct.pack("<I", len(body)) + body
        with self._lock:
            for c, buf in list(self.clients.items()):
                buf += frame
                self._send(c, buf)

    def _accept(self) -> None:
        """Take the clients waiting to connect, up to ``MAX_CLIENTS`` (class docstring); none once closed."""
        while not self._closed:
            try:
                c, _ = self.sock.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as e:
                self.accept_errors += 1
                if self.accept_errors == 1:
                    log.warning(f"live bus {self.path}: cannot take a client ({e.strerror or e}): it is left waiting "
                                f"and recording goes on (counted in bus.accept_errors)")
                return
            if len(self.clients) >= self.MAX_CLIENTS:
                c.close()
                self.refused_clients += 1
                if self.refused_clients == 1:
                    log.warning(f"live bus {self.path}: {self.MAX_CLIENTS} clients already; another is closed at "
                                f"once (counted in bus.refused_clients)")
                continue
            c.setblocking(False)
            self.clients[c] = bytearray()

    def _send(self, c: socket.socket, buf: bytearray) -> None:
        try:
            n = c.send(buf)
            del buf[:n]
        except BlockingIOError:
            pass
        except OSError:
            self._drop(c)
            return
        if len(buf) > self.max_buffer:
            self._drop(c)
            self.dropped_clients += 1

    def _drop(self, c: socket.socket) -> None:
        self.clients.pop(c, None)
        self._noisy.discard(c)
        c.close()

    def _ignore_input(self, c: socket.socket) -> None:
        """Read and drop what client ``c`` sent (at most 1 MB a call), counted, logged once; EOF drops it."""
        for _ in range(16):
            try:
                data = c.recv(65536)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                self._drop(c)
                return
            if not data:
                self._drop(c)
                return
            self.ignored_bytes += len(data)
            if c not in self._noisy:
                self._noisy.add(c)
                log.warning(f"live bus {self.path}: a client sent bytes; the bus only sends, they are dropped "
                            f"(counted in bus.ignored_bytes)")

    def pump(self) -> None:
        """Accept new clients, drop what they sent (``_ignore_input``) and send what is buffered (call when
        idle)."""
        with self._lock:
            self._accept()
            for c, buf in list(self.clients.items()):
                self._ignore_input(c)
                if buf and c in self.clients:
                    self._send(c, buf)

    def close(self, timeout_s: float = 2.0) -> None:
        """Send what is buffered (at most ``timeout_s`` per client), then close; publishing after it does
        nothing, and closing again nothing more."""
        with self._lock:
            self._closed = True
            for c, buf in list(self.clients.items()):
                try:
                    c.settimeout(timeout_s)
                    c.sendall(buf)
                except OSError:
                    pass
                self._drop(c)
            self.sock.close()
            Path(self.path).unlink(missing_ok=True)


class ProvisionalImu:
    """The pipeline's ``on_frames`` hook: DAQ frames on the bus at once, as provisional ``/imu``.

    Frames are collected per read and published by ``flush``, which the daemon calls as soon as no further
    DAQ read is waiting (so one batch per read at real speed, fewer larger ones when processing catches up
    a backlog); a batch carries the host mono time of the read that delivered its last frame. Stamps come
    from ``TimeSync.causal_stamp`` (the latest causal fit extrapolated; the host clock, flagged
    ``BUS_HOST_CLOCK``, before the first lock), with the per-sample sync state. They never go backwards
    (the forward clamp of the final stamps, 1 ns per sample after a backward step) except once, at the first
    lock, where they step from the host clock to GPS time. Nothing is kept while no client is connected.
    """

    def __init__(self, pipe: Pipeline, bus: BusServer) -> None:
        self.pipe, self.bus = pipe, bus
        self._k: list[np.ndarray] = []
        self._counts: list[np.ndarray] = []
        self._mono = 0
        self._pmax: int | None = None       # max over published samples of stamp - k
        self._fitted = False

    def __call__(self, mono_ns: int, k: np.ndarray, counts: np.ndarray) -> None:
        if self.bus.active():
            self._k.append(k)
            self._counts.append(counts)
            self._mono = mono_ns

    def flush(self) -> None:
        if not self._k:
            return
        k = np.concatenate(self._k) if len(self._k) > 1 else self._k[0]
        counts = np.concatenate(self._counts) if len(self._counts) > 1 else self._counts[0]
        self._k, self._counts = [], []
        t, state, fitted = self.pipe.sync.causal_stamp(k)
        if fitted != self._fitted:
            self._fitted, self._pmax = fitted, None
        cm = timesync.forward_clamp(t - k, self._pmax)
        self._pmax = int(cm[-1])
        t = cm + k
        self.bus.publish("/imu", t, self.pipe.output.imu_messages(t, counts), state=state, read_mono_ns=self._mono,
                         flags=BUS_PROVISIONAL | (0 if fitted else BUS_HOST_CLOCK))


# a closed MCAP ends with its footer and the magic; a file cut by a crash does not
is_finished = recovery.has_footer


def recover_unfinished(out_dir: Path, log: Callable[[str], None]) -> list[tuple[Path, Path]]:
    """Recover every unfinished ``*.mcap`` in ``out_dir`` and its session directories (no summary) into
    ``NAME.recovered.mcap`` next to it, once, by the folder policy ``recovery.recover_folder`` (the complete chunks
    and the re-derived tail: ``recovery.recover_drive``); the original is left as it is (a symbolic link, or a file
    in a linked directory, is skipped), and a session's ``metadata.yaml`` is written again. A recovery that fails
    (a full disk, not an MCAP file) is logged and leaves nothing behind, so the next start tries again; so is one
    the free space cannot take with room to record left (``RECOVER_SPACE_FACTOR`` times the file, plus
    ``RECOVER_RESERVE_BYTES``), so that the recovery after a full disk does not fill it again. Returns (original,
    recovered) pairs."""

    def recover_file(p: Path, dst: Path) -> bool:
        need, free = RECOVER_SPACE_FACTOR * p.stat().st_size + RECOVER_RESERVE_BYTES, shutil.disk_usage(out_dir).free
        if free < need:
            log(f"not recovering unfinished {p.name} now: that may take {need >> 20} MB with room left to record, "
                f"{free >> 20} MB are free (the next start tries again, or run `fieldlog recover {p} --out FILE` "
                f"elsewhere)")
            return False
        try:
            rep = recovery.recover_drive(p, dst)
        except (OSError, ValueError) as e:
            log(f"could not recover unfinished {p.name}: {getattr(e, 'strerror', None) or e}; it is left as it is "
                f"(the next start tries again, or run `fieldlog recover {p}`)")
            return False
        n = sum(rep.messages.values())
        tail = sum(rep.rederived.values())
        log(f"recovered unfinished {p.name} -> {dst.name}: {n} messages in {rep.chunks} chunks, "
            f"{rep.bytes_discarded} bytes after the last complete chunk discarded, {tail} tail messages "
            f"re-derived from the raw reads")
        return True

    files = [p for p in sorted([*out_dir.glob("*.mcap"), *out_dir.glob("*/*.mcap")])
             if not (p.name.endswith(bagdir.RECOVERED) or p.is_symlink() or p.parent.is_symlink())]
    done, _ = recovery.recover_folder(files, recover_file, lambda msg, _level: log(msg))
    for session in dict.fromkeys(p.parent for p, _ in done if p.parent != out_dir):
        bagdir.rewrite_metadata(session)
    return done


def make_session_dir(out_dir: Path, session_wall_ns: int, log: Callable[[str, int], None]) -> Path:
    """``out_dir/<session start>``, new (``-2``, ``-3``, ... appended while that name is taken; a symbolic link
    there is logged and never followed)."""
    name = session_name(session_wall_ns)
    for n in range(1, 1000):
        d = out_dir / (name if n == 1 else f"{name}-{n}")
        try:
            d.mkdir()
            return d
        except FileExistsError:
            if d.is_symlink():
                log(f"{d} is a symbolic link (never followed): the session goes to the next name", logging.WARNING)
    raise FileExistsError(f"{out_dir}: no free session directory name for {name}")


class StatusLine:
    """The daemon's status line (a terminal's, or a log line per tick): rates between two lines.

    Parameters
    ----------
    daemon : Daemon
        Whose ports, pipeline counters, file and derived path the line shows.
    """

    def __init__(self, daemon: "Daemon") -> None:
        self._d = daemon
        self._status_prev: tuple[float, int, int, int, int] | None = None
        self._can_prev: int | None = None

    def line(self, size: int) -> str:
        """The status line now, the current file being ``size`` bytes: rates since the last line, the sync and
        fix state, the file and the loss counters."""
        d = self._d
        c = d.pipe.counters
        now = time.monotonic()
        frames, lines = c.daq.frames, c.nmea.lines
        db, gb = d.readers["daq"].stats.bytes, d.readers["gps"].stats.bytes
        prev = self._status_prev or (now - 1.0, frames, lines, db, gb)
        dt = max(now - prev[0], 1e-3)
        self._status_prev = (now, frames, lines, db, gb)
        sync = "FREE"
        if d.sink.last_sync is not None:
            s = messages.decode_time_sync([d.sink.last_sync])
            sync = (f"{['FREE', 'HOLDOVER', 'LOCKED'][int(s['state'][0])]} {s['rate_ppm'][0]:+.2f} ppm "
                    f"{s['residual_us'][0]:.0f} us")
        fix = "no GGA"
        if d.sink.last_gga is not None:
            text = messages.decode_message("nmea_msgs/msg/Sentence", d.sink.last_gga).sentence
            body, ok = nmea.split_checksum(text.encode())
            g = nmea.decode_body(body) if ok else None
            if isinstance(g, nmea.Gga):
                fix = f"fix {g.quality} sats {g.num_sats}"

        def port(name: str) -> str:
            return "" if d.readers[name].stats.connected else " DOWN"

        dq, n = c.daq, c.nmea
        drop = sum(r.stats.dropped_reads for r in d.readers.values())
        lag = d.derived_lag_s()
        derived = ""
        if d.derive_failure or lag >= 1.0 or d.derived_dropped_reads:
            state = "FAILED" if d.derive_failure else f"{lag:.1f} s behind"
            derived = f"derived {state}, {d.derived_dropped_reads} reads not processed | "
        bus = ""
        if "can" in d.readers and d.pipe.vehicle is not None:
            cs = d.pipe.vehicle.stats
            prev_can = cs.frames if self._can_prev is None else self._can_prev
            self._can_prev = cs.frames
            bus = (f"can {(cs.frames - prev_can) / dt:.0f} fr/s{port('can')} "
                   f"err {cs.error_frames + cs.status_errors + cs.bad_records} | ")
        return (f"daq {(frames - prev[1]) / dt:.0f} fr/s {(db - prev[3]) / dt / 1e3:.1f} kB/s{port('daq')} | "
                f"gps {(lines - prev[2]) / dt:.0f} ln/s {(gb - prev[4]) / dt:.0f} B/s{port('gps')} | {bus}{derived}"
                f"pps {c.pps_edges - c.pps_rejected} ok {c.pps_rejected} rej | sync {sync} | {fix} | "
                f"{d.sink.rec.path.name} {size / 1e6:.1f} MB | dropped {drop} lost {dq.lost_frames} "
                f"crc {dq.bad_crc} resync {dq.resyncs} nmea-bad {n.bad_checksum} late {d.late_reads}")


class Daemon:
    """The acquisition daemon; ``start`` opens the ports and the first file, ``run`` processes until stopped."""

    def __init__(self, cfg: AcquireConfig, quiet: bool = False, err: TextIO = sys.stderr) -> None:
        self.cfg = cfg
        self.quiet = quiet
        self.err = err
        self.tty = err.isatty()
        self.stop = threading.Event()
        self.wake = threading.Event()
        self.cal = calib.load_calibration(cfg.calibration_file or None)
        self.sync_cfg = cfg.sync_config()
        self.out_dir = Path(cfg.out_dir)
        self.session_wall_ns = time.time_ns()
        self.readers: dict[str, PortReader] = {}
        self.sink: RotatingSink | None = None
        self.pipe: Pipeline | None = None
        self.bus = None
        self.provisional: ProvisionalImu | None = None
        self.events: list[PortEvent] = []
        self.late_reads = 0
        self.merge_timeouts = 0
        self.error = ""
        # the derived path: its queue, its thread, what it has done, and how it ends
        self.derived: queue.Queue[RawRead] = queue.Queue()    # bounded in bytes: derived_queue_mb
        self.derived_max_bytes = int(cfg.daemon.derived_queue_mb * 1e6)
        self.derived_put_bytes = 0               # bytes of reads queued (raw path) ...
        self.derived_got_bytes = 0               # ... and taken (derived path): each counter has one writer
        self.deriver: threading.Thread | None = None
        self.derive_end = threading.Event()      # set by the raw path: nothing more is queued
        self.derive_cut = threading.Event()      # set by the raw path: stop processing at once
        self.derive_error: BaseException | None = None   # the raw path stops on it (a full disk)
        self.derive_failure = ""                 # why the derived path ended early; the raw path records on
        self.derive_done = False                 # the derived path processed every read queued and finished
        self.derived_mono = 0                    # host mono of the last read processed
        self.recorded_mono = 0                   # host mono of the last read recorded
        self.derived_dropped_reads = 0
        self.derived_dropped_bytes = 0
        self._dropping = 0                       # reads dropped since the dropping began (0: not dropping)
        self.stop_mono_ns: int | None = None     # host mono of SIGINT/SIGTERM
        self._last_mono = 0
        self.status = StatusLine(self)
        self.port_names: tuple[str, ...] = PORTS

    def log(self, msg: str, level: int = logging.INFO) -> None:
        """One event through ``logging`` (``setup_logging``), clearing the status line first on a terminal."""
        if self.tty and not self.quiet and log.isEnabledFor(level):
            self.err.write("\r\033[K")
            self.err.flush()
        log.log(level, msg)

    # -- start -------------------------------------------------------------------------------------
    def start(self) -> None:
        """Open both ports (PortError if one cannot be opened), recover unfinished files, open the first file,
        start the readers."""
        sers = {}
        self.port_names = PORTS + (("can",) if self.cfg.can.url else ())
        for name in self.port_names:
            pc: PortConfig | CanConfig = getattr(self.cfg, name)
            try:
                sers[name] = open_port(pc)
            except (serial.SerialException, OSError, ValueError) as e:
                for s in sers.values():
                    s.close()
                raise PortError(f"[{name}] port: cannot open {pc.port}: {getattr(e, 'strerror', None) or e}") \
                    from None
        outputs.out_dir(self.out_dir)
        recover_unfinished(self.out_dir, self.log)
        if self.cfg.daemon.bus:
            self.bus = BusServer(self.cfg.daemon.bus)
        self.session_dir = make_session_dir(self.out_dir, self.session_wall_ns, self.log)
        self.sink = RotatingSink(self.session_dir, self.session_wall_ns, self.cfg.recorder, self._headers,
                                 self.bus.publish if self.bus else None, self.log)
        self.pipe = Pipeline(self.sink, self.cal, self.sync_cfg, PipelineConfig(gps_protocol=self.cfg.gps.protocol,
                                                                               can=self.cfg.can_bus(),
                                                                               use_hnr=self.cfg.gps.use_hnr))
        if self.bus is not None:
            self.provisional = self.pipe.on_frames = ProvisionalImu(self.pipe, self.bus)
        path = self.sink.open_next()
        self.deriver = threading.Thread(target=self._derive_loop, name="derive", daemon=True)
        self.deriver.start()
        can_port = f", {self.cfg.can.url} (can)" if self.cfg.can.url else ""
        self.log(f"recording {self.cfg.daq.port} (daq), {self.cfg.gps.port} (gps){can_port} to {path}")
        dm = self.cfg.daemon
        for name in self.port_names:
            r = PortReader(name, getattr(self.cfg, name), sers[name], dm.queue_reads, self.wake, self.stop,
                           dm.reconnect_s)
            self.readers[name] = r
            r.start()

    def _headers(self, index: int, prev: Path | None) -> dict[str, dict[str, str]]:
        c = self.cfg
        drive = {"source": "fieldlog acquire", "session_start_wall_ns": str(self.session_wall_ns),
                 "file_index": str(index), "previous_file": prev.name if prev else "",
                 "daq_port": c.daq.port, "daq_baud": str(c.daq.baud), "gps_port": c.gps.port,
                 "gps_baud": str(c.gps.baud), "can_url": c.can.url, "pps_mode": self.sync_cfg.pps_mode,
                 "calibration_file": c.calibration_file}
        return {"drive": drive, **self.pipe.metadata()}

    def counters(self) -> dict[str, str]:
        while True:
            try:
                out = self.pipe.counters_metadata()
                break
            except RuntimeError:     # a counter dict the derived path grew while it was read: read again
                continue
        for name, r in self.readers.items():
            out.update({f"port.{name}.{k}": str(v) for k, v in asdict(r.stats).items() if k != "connected"})
            if r.gpsd:
                link = r.ser                   # (the reader may drop it meanwhile)
                live = link.stream.reports_seen if link is not None else 0
                out[f"port.{name}.gpsd_reports"] = str(r.gpsd_reports + live)
        out["daemon.late_reads"] = str(self.late_reads)
        out["daemon.merge_timeouts"] = str(self.merge_timeouts)
        out["daemon.derived_dropped_reads"] = str(self.derived_dropped_reads)
        out["daemon.derived_dropped_bytes"] = str(self.derived_dropped_bytes)
        if self.derive_failure:
            out["daemon.derived_error"] = self.derive_failure
        out["daemon.names_skipped"] = str(self.sink.skipped if self.sink is not None else 0)
        if self.bus is not None:
            out["bus.dropped_clients"] = str(self.bus.dropped_clients)
            out["bus.refused_clients"] = str(self.bus.refused_clients)
            out["bus.accept_errors"] = str(self.bus.accept_errors)
            out["bus.ignored_bytes"] = str(self.bus.ignored_bytes)
        return out

    # -- the raw path ---------------------------------------------------------------------------------
    def run(self) -> int:
        """The raw path: record until stopped and the queues are drained, let the derived path finish (at most
        until ``DERIVED_STOP_S`` after the signal), finish the file. Returns the exit code."""
        heads: dict[str, RawRead | PortEvent | None] = {name: None for name in self.readers}
        wait_ns = int(self.cfg.daemon.merge_wait_s * NS)
        next_tick = time.monotonic() + self.cfg.daemon.status_interval_s
        code = 0
        try:
            while True:
                self.wake.clear()
                if self.derive_error is not None:
                    raise self.derive_error
                for name, r in self.readers.items():
                    if heads[name] is None:
                        try:
                            heads[name] = r.q.get_nowait()
                        except queue.Empty:
                            pass
                ready = [h for h in heads.values() if h is not None]
                if ready:
                    h = min(ready, key=lambda x: read_order(x.port, x.mono_ns))
                    if self._may_process(h, heads, wait_ns):
                        heads[h.port] = None
                        self._process(h)
                        if time.monotonic() >= next_tick:
                            next_tick = time.monotonic() + self.cfg.daemon.status_interval_s
                            self._tick()
                        continue
                elif self.stop.is_set() and not any(r.is_alive() or not r.q.empty()
                                                    for r in self.readers.values()):
                    break
                self.sink.maybe_flush()
                if time.monotonic() >= next_tick:
                    next_tick = time.monotonic() + self.cfg.daemon.status_interval_s
                    self._tick()
                self.wake.wait(0.05)
            self._finish_derived()
            if self.derive_error is not None:
                raise self.derive_error
        except OSError as e:
            if e.errno not in STORAGE_FULL:
                raise
            self.error = (f"{STORAGE_FULL[e.errno]} ({errno.errorcode[e.errno]}) writing {self.sink.rec.path}: "
                          f"recording stopped; the file keeps every chunk flushed before this")
            code = 2
        finally:
            self.stop.set()
            for r in self.readers.values():
                r.join(2.0)
            self._finish_derived()
            self._close(code)
        return code

    def _finish_derived(self) -> None:
        """Let the derived path process what is queued and finish, until ``DERIVED_STOP_S`` after the signal (or
        from now, when stopping for another reason); then leave it behind."""
        if self.deriver is None or self.derive_cut.is_set():
            return
        self.derive_end.set()
        start = self.stop_mono_ns if self.stop_mono_ns is not None else time.monotonic_ns()
        self.deriver.join(max(0.0, (start - time.monotonic_ns()) / NS + DERIVED_STOP_S))
        self.derive_cut.set()

    def _may_process(self, h: RawRead | PortEvent, heads: dict, wait_ns: int) -> bool:
        now = time.monotonic_ns()
        for name, r in self.readers.items():
            if name == h.port or heads[name] is not None:
                continue
            if (not r.busy and r.q.empty()) or not r.is_alive():
                continue
            if now - h.mono_ns >= wait_ns:
                self.merge_timeouts += 1
                continue
            return False
        return True

    def _process(self, h: RawRead | PortEvent) -> None:
        """Record one read (or port event) and queue it for the derived path, never waiting for it."""
        if isinstance(h, PortEvent):
            self.events.append(h)
            self.sink.add_metadata("acquire.port_event", {"port": h.port, "event": h.kind,
                                                              "mono_ns": str(h.mono_ns), "wall_ns": str(h.wall_ns),
                                                              "detail": h.detail})
            self.log(f"{h.port} port {'lost' if h.kind == 'lost' else 'back'}: {h.detail}"
                     + ("; retrying" if h.kind == "lost" else ""), logging.WARNING if h.kind == "lost" else logging.INFO)
            return
        if h.mono_ns < self._last_mono:
            self.late_reads += 1
        self._last_mono = max(self._last_mono, h.mono_ns)
        self.pipe.record(h.port, h.mono_ns, h.wall_ns, h.data)
        self.recorded_mono = h.mono_ns
        queued = self.derived_put_bytes - self.derived_got_bytes
        if self.derive_failure or (self._dropping and queued > self.derived_max_bytes // 2):
            pass  # not processed: the derived path failed, or its queue is still half full
        elif queued + len(h.data) > self.derived_max_bytes:
            self.log(f"the derived path is {self.derived_lag_s():.1f} s behind and its queue full: reads are "
                     f"recorded and not processed until it has caught up half of it (their derived topics have a gap; "
                     f"`fieldlog rebuild` fills it from the raw bytes)", logging.WARNING)
        else:
            self.derived_put_bytes += len(h.data)
            self.derived.put(h)
            if self._dropping:
                self.log(f"the derived path takes reads again: {self._dropping} reads not processed", logging.WARNING)
                self._dropping = 0
            return
        self.derived_dropped_reads += 1
        self.derived_dropped_bytes += len(h.data)
        self._dropping += 1

    def derived_lag_s(self) -> float:
        """How far the derived path is behind the raw path: host seconds between the last read recorded and the
        last read processed."""
        return max(0, self.recorded_mono - self.derived_mono) / NS if self.derived_mono else 0.0

    # -- the derived path -----------------------------------------------------------------------------
    def _derive_loop(self) -> None:
        """The derived path's thread: process the queued reads in order; publish provisional /imu and serve the
        live bus; when the raw path ends it (``derive_end``), process what is left and finish the Pipeline, unless
        it is cut first (``derive_cut``: abandoned, nothing more is written)."""
        q = self.derived
        try:
            while not self.derive_cut.is_set():
                try:
                    h = q.get(timeout=0.05)
                except queue.Empty:
                    if self.provisional is not None:
                        self.provisional.flush()
                    if self.bus is not None:
                        self.bus.pump()
                    if self.derive_end.is_set() and q.empty():
                        break
                    continue
                self.derived_got_bytes += len(h.data)
                self.derive_read(h)
                if self.provisional is not None and q.empty():
                    self.provisional.flush()      # no read waiting: publish at once
            else:
                return
            if self.provisional is not None:
                self.provisional.flush()
            self.pipe.finish()
            self.derive_done = True
        except BaseException as e:  # noqa: BLE001 - the recording goes on without it, or stops (_derived_ended)
            self._derived_ended(e)

    def _derived_ended(self, e: BaseException) -> None:
        """The derived path raised ``e``. A full disk (or what is no ``Exception``) goes to the raw path, which
        stops the daemon on it. Anything else ends the derived path alone: one error line (where it was raised),
        the live bus closed (its clients see the end at once), and the raw path records every read on and queues
        none (``_process``)."""
        if not isinstance(e, Exception) or (isinstance(e, OSError) and e.errno in STORAGE_FULL):
            self.derive_error = e
            self.stop.set()
            self.wake.set()
            return
        self.derive_failure = f"{type(e).__name__}: {e} at {raised_at(e)}"
        self.log(f"the derived path failed ({self.derive_failure}): recording goes on, the reads are recorded "
                 f"and no longer processed, so the derived topics end here; `fieldlog rebuild` derives them from "
                 f"the raw bytes", logging.ERROR)
        if self.bus is not None:
            self.bus.close(timeout_s=0.0)

    def derive_read(self, h: RawRead) -> None:
        """Process one recorded read (the derived path's step)."""
        self.sink.read_mono_ns = h.mono_ns
        self.pipe.process(h.port, h.mono_ns, h.wall_ns, h.data)
        self.derived_mono = h.mono_ns

    def _tick(self) -> None:
        """Once a second: rotation, status line."""
        rot = self.cfg.rotation
        size = self.sink.size()
        if (rot.max_duration_s and time.monotonic() - self.sink.opened_mono >= rot.max_duration_s) or \
                (rot.max_size_mb and size >= rot.max_size_mb * 1e6):
            path = self.sink.open_next({"acquire.counters": self.counters()})
            self.log(f"rotated to {path}")
            size = 0
        if self.tty and not self.quiet:
            self.err.write("\r\033[K" + self.status.line(size))
            self.err.flush()
        elif log.isEnabledFor(logging.DEBUG if self.quiet else logging.INFO):   # a log line (journal) per tick
            log.log(logging.DEBUG if self.quiet else logging.INFO, self.status.line(size))

    def _close(self, code: int) -> None:
        complete = self.derive_done
        unprocessed = self.derived.qsize() + self.derived_dropped_reads
        stop = {"signal_mono_ns": str(self.stop_mono_ns or 0), "close_mono_ns": str(time.monotonic_ns()),
                "derived": "complete" if complete else "failed" if self.derive_failure else "cut",
                "reads_not_processed": str(unprocessed)}
        if not complete and not self.derive_failure:
            self.log(f"stopping with the derived path {self.derived_lag_s():.1f} s behind the raw bytes: the derived "
                     f"topics end there ({unprocessed} reads recorded and not processed); `fieldlog rebuild` "
                     f"re-derives them all", logging.WARNING)
        try:
            self.sink.close({"acquire.counters": self.counters(), "acquire.stop": stop})
        except OSError as e:
            self.error = self.error or f"closing {self.sink.files[-1]}: {e}"
            self.error += "; the file has no summary: run `fieldlog recover` on it (or restart, which does)"
        finally:
            if self.bus is not None:
                self.bus.close()
        if self.tty and not self.quiet:
            self.err.write("\n")
        if self.error:
            self.log(f"error: {self.error}", logging.ERROR)
        else:
            files = ", ".join(str(p) for p in self.sink.files)
            self.log(f"stopped; finished {files}")


def run_daemon(cfg: AcquireConfig, quiet: bool = False, daemon_class: type[Daemon] = Daemon) -> int:
    """The ``fieldlog acquire`` command: SIGINT/SIGTERM stop it cleanly. Returns the exit code. ``daemon_class``:
    a Daemon or a subclass of it (a test's derived path made slow on purpose)."""
    d = daemon_class(cfg, quiet)

    def on_signal(signum: int, frame: object) -> None:
        if d.stop_mono_ns is None:
            d.stop_mono_ns = time.monotonic_ns()
        d.stop.set()
        d.wake.set()

    # before start: a signal while it starts stops the daemon after its first file is open, cleanly
    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    d.start()
    result: list[int] = []
    worker = threading.Thread(target=lambda: result.append(d.run()), name="process")
    worker.start()
    while worker.is_alive():
        worker.join(0.2)
    return result[0] if result else 1
