"""``fieldlog sim --serve``: simulated hardware on pseudo-terminals, for running the daemon as in the car.

The byte streams are exactly those of ``fieldlog sim`` (``simulate.make_reads``): every DAQ frame and NMEA
sentence, cut into the reads a USB-serial adapter would deliver. Each read is written to its port's pty at
its simulated time (relative to the first read), divided by ``speed``. The masters are non-blocking: when the
reader does not keep up, the bytes wait in the serve process (never dropped) and the pty's buffer applies
back-pressure, as a UART's flow control would.

Truth (``/truth/*``, as ``fieldlog sim`` writes it) and what was sent go to a side MCAP at the end: metadata
``serve`` holds ``daq_bytes``, ``daq_frames`` (complete frames written), ``gps_bytes``, ``nmea_lines``,
``speed``, ``completed`` and the unplug windows. With ``--can`` a third pty is the car's SLCAN adapter
(``sim.vehicle``: wheel speeds, steering, gear and other traffic as CR-terminated records), printed as ``can
PATH``, with ``can_bytes``, ``can_records``, ``can_gaps`` and the rest as for the other ports. The daemon's host clock is the real machine clock, not the
simulator's, so a live recording is scored by DAQ sample index: the simulator's frame counter starts at 0,
so frame k of ``/raw/daq`` is truth sample k (``/truth/imu`` holds one record per frame, in order), and the
i-th ``/imu`` message is the i-th decoded frame. At ``speed`` 1 the GPS-disciplined ``/imu`` stamps are
simulated UTC and compare directly with ``/truth/imu``. At other speeds the host-time gates of time sync
(fix age, NMEA/PPS agreement) see compressed seconds and the sync does not lock unless the daemon runs with
``--time-scale X`` (X = ``speed``; ``[timesync] host_time_scale``), which rescales them; then the stamps
compare with truth as at speed 1.

Unplugging: ``unplug`` windows (port, start, length in simulated seconds) close the port's pty and open a new
one after the gap; the bytes due meanwhile are lost, as on a pulled adapter. At the start of a window the
device stops sending (what waits in the serve process is lost too) and the pty is closed once the reader has
taken every byte already written (its input queue stayed empty for ``DRAIN_QUIET_S``): the serve process
cannot count what a close would discard, because ``FIONREAD`` sees only the line discipline's queue (at most 4
KiB) and not the kernel's flip buffer behind it, which holds up to about 10 KiB more and reaches the queue
asynchronously. (Counting ``FIONREAD`` at the close, as before, booked up to a few KiB per unplug as delivered
that the reader never got.) Should the reader not drain within ``DRAIN_MAX_S``, the pty is closed anyway, what
``FIONREAD`` still shows is booked as lost, and ``daq_undrained_unplugs`` / ``gps_undrained_unplugs`` count
it: the gap is then exact only to within the flip buffer. Because a new pty has a new path, ``link_dir`` keeps
stable symlinks ``link_dir/daq`` and ``link_dir/gps`` pointing at the current ones (removed while unplugged,
as the device node of a pulled adapter); point the daemon at those. After a replug the device streams on, but
its bytes are lost until the reader has opened the port (pyserial flushes the input on open, so bytes written
before would vanish untracked): the master is in packet mode (TIOCPKT), where the slave's input flush shows up
as TIOCPKT_FLUSHREAD. The bytes lost are recorded as byte ranges of the port's full stream (metadata
``daq_gaps`` / ``gps_gaps``, ``START:LENGTH;...``), so the stream actually delivered is the simulated one
minus those ranges. The host monotonic time (ns) of each reopening is in metadata ``daq_replug_mono_ns`` /
``gps_replug_mono_ns`` (``;``-separated).

Receiver clock jumps: ``clock_jumps`` rows (start, length, offset in simulated seconds; added to the scenario's
``[gps] clock_jumps``) make the receiver write a time that far off in its messages, while its pulse and its
sending keep true time; metadata ``gps_clock_jumps`` (``START:LEN:OFFSET;...``) has them all.

The emulated board: with ``board="emulated"`` the DAQ port is not the simulator's frames but the firmware's
(``tools/sim/board.py``): the serve process starts QEMU with the emulated board's image and writes the board's
input records (one per sample, at its simulated time) to a pty that is QEMU's standard input; the printed
``daq PATH`` is QEMU's pty of the first USART, where the firmware sends its frames. The board always latches
the PPS (metadata ``pps_mode`` = ``latch``); ``daq_bytes`` and ``daq_frames`` count the input records written,
one per sample (frames the board drops show as counter gaps on the DAQ port). Unplugging and corruption are
for the simulated board only.

Corruption: ``corrupt`` > 0 replaces that fraction of the bytes of both streams with other values
(``corrupt_stream``: deterministic from the seed and the port, so a test can redo it and know every
corrupted position); metadata ``daq_corrupt_bytes`` / ``gps_corrupt_bytes`` count them. ``corrupt_counters``
> 0 first gives that fraction of the DAQ frames a wrong sample counter with a recomputed CRC, so that they pass
every check of the decoder (``corrupt_counters``: deterministic from the seed, returning the frames changed;
metadata ``daq_counter_corrupt_frames``), as a CRC collision or a board glitch would.

Repeats: ``repeat_reads`` > 0 delivers each DAQ read (after corruption) twice with that probability, the copy
right after it (``repeated_reads``: deterministic from the seed), as a replaying adapter would; metadata
``daq_repeated_reads`` counts them, and ``daq_bytes`` / ``daq_frames`` include the copies.
"""
from __future__ import annotations

import errno
import fcntl
import os
import select
import signal
import sys
import termios
import threading
import time
import tty
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, TextIO

import numpy as np

from fieldlog.acquire import daq
from fieldlog.drive import outputs, recorder
from fieldlog.acquire.pipeline import RawRead
from fieldlog.tools.sim import board as emulated, simulate, trajectory, vehicle
from fieldlog.tools.sim.emit import HostClock

NS = 1_000_000_000
PORTS = ("daq", "gps")
ALL_PORTS = PORTS + ("can",)         # the SLCAN adapter with --can
BOARDS = ("simulated", "emulated")
TIOCPKT = getattr(termios, "TIOCPKT", 0x5420)
TIOCPKT_FLUSHREAD = 0x01
DRAIN_QUIET_S = 1.0     # the reader has drained a pty once its input queue stays empty this long (wall s): the
# kernel moves the flip buffer into the queue in a worker thread, which a loaded host runs late
DRAIN_MAX_S = 5.0       # an unplug closes the pty after this long (wall s) even if the reader did not drain it


def corrupt_stream(data: bytes, fraction: float, seed: int, port: str) -> tuple[bytes, np.ndarray]:
    """``data`` with round(fraction * len) bytes, at random distinct positions, each XORed with a random
    non-zero value (so it really changes); also returns the sorted positions. Deterministic from
    ``seed`` and ``port``."""
    rng = np.random.default_rng([seed, ALL_PORTS.index(port), 0xC0])
    b = np.frombuffer(data, np.uint8).copy()
    pos = np.sort(rng.choice(b.size, size=int(round(fraction * b.size)), replace=False))
    b[pos] ^= rng.integers(1, 256, pos.size, dtype=np.uint8)
    return b.tobytes(), pos


def repeated_reads(n: int, p: float, seed: int) -> np.ndarray:
    """Which of ``n`` DAQ reads are delivered twice, each with probability ``p``: a bool mask, deterministic
    from ``seed``."""
    return np.random.default_rng([seed, 0x2E]).random(n) < p


def corrupt_counters(data: bytes, fraction: float, seed: int) -> tuple[bytes, np.ndarray]:
    """``data`` (whole DAQ frames) with round(fraction * frames) distinct frames given another counter and a
    matching CRC; also returns their sorted indices. A third of them repeat the previous frame's counter, a
    third jump by 2..1000 and a third by any other amount modulo 2**32. Deterministic from ``seed``."""
    rng = np.random.default_rng([seed, 0xC7])
    rec = np.frombuffer(data[:len(data) - len(data) % daq.FRAME_SIZE], daq.FRAME_DTYPE).copy()
    idx = np.sort(rng.choice(np.arange(1, rec.size), size=int(round(fraction * rec.size)), replace=False))
    kind = rng.integers(0, 3, idx.size)
    c = rec["counter"].astype(np.int64)
    new = np.where(kind == 0, c[idx - 1], np.where(kind == 1, c[idx] + rng.integers(2, 1001, idx.size),
                                                    c[idx] + rng.integers(1001, 2**32 - 1, idx.size)))
    rec["counter"][idx] = new % 2**32
    raw = rec.view(np.uint8).reshape(rec.size, daq.FRAME_SIZE)
    rec["crc"][idx] = daq.crc16_frames(raw[idx, 2:36])
    return rec.tobytes() + data[rec.size * daq.FRAME_SIZE:], idx


@dataclass
class Unplug:
    port: str
    start_s: float      # simulated seconds after the first read
    length_s: float

    @classmethod
    def parse(cls, text: str) -> "Unplug":
        """``PORT:START:LENGTH`` in simulated seconds, e.g. ``gps:20:3``."""
        try:
            port, a, b = text.split(":")
            u = cls(port, float(a), float(b))
        except ValueError:
            raise ValueError(f"--unplug {text!r}: expected PORT:START_S:LENGTH_S") from None
        if port not in ALL_PORTS or u.length_s <= 0 or u.start_s < 0:
            raise ValueError(f"--unplug {text!r}: PORT is daq, gps or can, START_S >= 0, LENGTH_S > 0")
        return u


def simulated_streams(meta: dict[str, str]) -> dict[str, bytes]:
    """Each port's full byte stream as the serve run with this ``serve`` metadata simulated it, before
    corruption and unplugs: what a recording is scored against."""
    sc = trajectory.load_scenario(meta["scenario"])
    jumps = [[float(x) for x in j.split(":")] for j in meta.get("gps_clock_jumps", "").split(";") if j]
    sc = replace(sc, clock={**sc.clock, "start_utc_ns": int(meta["drive_start_utc_ns"])},
                 gps={**sc.gps, "clock_jumps": jumps})
    reads = simulate.make_reads(sc, float(meta["duration_s"]), int(meta["seed"]), meta["pps_mode"],
                                meta.get("receiver"), can=meta.get("can") == "True")[0]
    return {port: b"".join(r.data for r in reads if r.port == port)
            for port in (ALL_PORTS if meta.get("can") == "True" else PORTS)}


def delivered(stream: bytes, gaps: str) -> tuple[bytes, np.ndarray]:
    """``stream`` minus the ``START:LENGTH;...`` byte ranges an unplug lost (metadata ``daq_gaps`` /
    ``gps_gaps``), and a mask over ``stream`` of the bytes delivered."""
    keep = np.ones(len(stream), bool)
    for g in filter(None, gaps.split(";")):
        a, n = map(int, g.split(":"))
        keep[a:a + n] = False
    return np.frombuffer(stream, np.uint8)[keep].tobytes(), keep


def parse_clock_jump(text: str) -> list[float]:
    """``START:LEN:OFFSET`` in simulated seconds, e.g. ``900:30:3600`` (the receiver's clock +1 h for 30 s at
    15 min), as a ``[gps] clock_jumps`` row."""
    try:
        start, length, offset = (float(x) for x in text.split(":"))
    except ValueError:
        raise ValueError(f"--clock-jump {text!r}: expected START_S:LEN_S:OFFSET_S") from None
    if start < 0 or length <= 0:
        raise ValueError(f"--clock-jump {text!r}: START_S >= 0, LEN_S > 0")
    return [start, length, offset]


@dataclass
class _Port:
    """One simulated serial device: pty pair, the reads scheduled on it, and what was written."""

    name: str
    t_s: np.ndarray                     # due time of each read, simulated seconds from the first read
    data: list[bytes]
    master: int = -1
    slave: int = -1
    path: str = ""
    next_read: int = 0
    pending: bytearray = field(default_factory=bytearray)
    sent: bytearray = field(default_factory=bytearray)
    lost_bytes: int = 0
    gaps: list[tuple[int, int]] = field(default_factory=list)   # (offset in the full stream, length) lost
    corrupt_bytes: int = 0
    wait_reader: bool = False           # bytes are lost until the reader has opened (flushed) the port
    replugged_mono_ns: list[int] = field(default_factory=list)   # host monotonic time of each reopening
    draining_since: float | None = None     # an unplug has stopped the writes (wall monotonic s)
    stopped_at: int = 0                     # offset in the full stream of the first byte not written then
    empty_since: float | None = None        # the input queue has been empty since (wall monotonic s)
    undrained_unplugs: int = 0

    def open(self, link_dir: Path | None, wait_reader: bool = False) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)          # no echo, no CR/LF translation, no line buffering
        os.set_blocking(self.master, False)
        fcntl.ioctl(self.master, TIOCPKT, (1).to_bytes(4, sys.byteorder))
        self.wait_reader = wait_reader
        self.path = os.ttyname(self.slave)
        if link_dir is not None:
            tmp = link_dir / f".{self.name}.tmp"
            tmp.unlink(missing_ok=True)
            tmp.symlink_to(self.path)
            tmp.replace(link_dir / self.name)

    def close(self, link_dir: Path | None) -> None:
        """Remove the link, then close the pty (in that order: a reader retrying through a link to a closed pty
        could open another process's new pty of the same number)."""
        if link_dir is not None:
            (link_dir / self.name).unlink(missing_ok=True)
        for fd in (self.master, self.slave):
            if fd >= 0:
                os.close(fd)
        self.master = self.slave = -1

    def stop_sending(self) -> None:
        """An unplug begins: nothing more is written; what waits here is lost."""
        self.draining_since, self.empty_since = time.monotonic(), None
        self.stopped_at = len(self.sent) + self.lost_bytes
        self.lose(len(self.pending))
        self.pending.clear()

    def unplug(self, link_dir: Path | None) -> None:
        """Close the pty (normally drained by then); what the reader still had not read is lost."""
        unread = self.unread()
        if unread:
            self.undrained_unplugs += 1
            del self.sent[len(self.sent) - unread:]
            self.lost_bytes += unread
            if self.gaps and self.gaps[-1][0] == self.stopped_at:
                self.gaps[-1] = (self.stopped_at - unread, self.gaps[-1][1] + unread)
            else:
                self.gaps.append((self.stopped_at - unread, unread))
        self.draining_since = self.empty_since = None
        self.close(link_dir)

    def drained(self) -> bool:
        """True once the reader has had the pty's input queue empty for DRAIN_QUIET_S (see the module doc)."""
        now = time.monotonic()
        if self.unread():
            self.empty_since = None
            return False
        if self.empty_since is None:
            self.empty_since = now
        return now - self.empty_since >= DRAIN_QUIET_S

    def lose(self, n: int) -> None:
        """The next ``n`` bytes of the stream (after those sent) are lost."""
        if n <= 0:
            return
        start = len(self.sent)
        if self.gaps and sum(self.gaps[-1]) == start + self.lost_bytes:
            self.gaps[-1] = (self.gaps[-1][0], self.gaps[-1][1] + n)
        else:
            self.gaps.append((start + self.lost_bytes, n))
        self.lost_bytes += n

    def reader_opened(self) -> bool:
        """True once the reader has flushed its input, which pyserial does on open (packet mode status)."""
        if not self.wait_reader:
            return True
        while select.select([self.master], [], [], 0)[0]:
            try:
                pkt = os.read(self.master, 4096)
            except OSError:
                return False
            if pkt and pkt[0] & TIOCPKT_FLUSHREAD:
                self.wait_reader = False
        return not self.wait_reader

    def unread(self) -> int:
        """Bytes written to the master that the reader has not read yet."""
        buf = fcntl.ioctl(self.slave, termios.FIONREAD, b"\0\0\0\0")
        return int.from_bytes(buf, sys.byteorder)


class Server:
    """Streams a simulated drive to two ptys; ``run`` returns when the drive ends or ``stop`` is set."""

    def __init__(self, scenario: str, duration_s: float | None, seed: int, speed: float = 1.0,
                 pps_mode: str | None = None, unplug: list[Unplug] | None = None,
                 link_dir: str | Path | None = None, corrupt: float = 0.0, receiver: str | None = None,
                 clock_jumps: list[list[float]] | None = None, board: str = "simulated",
                 board_image: str | Path | None = None, can: bool = False,
                 corrupt_counters_frac: float = 0.0, repeat_reads: float = 0.0) -> None:
        if not speed > 0:
            raise ValueError(f"--speed {speed}: must be > 0")
        if not 0 <= corrupt < 1:
            raise ValueError(f"--corrupt {corrupt}: must be in [0, 1)")
        if board not in BOARDS:
            raise ValueError(f"--board {board!r}: one of {', '.join(BOARDS)}")
        if board == "emulated" and (unplug or corrupt):
            raise ValueError("--board emulated: --unplug and --corrupt are for the simulated board only")
        self.board = emulated.EmulatedBoard(board_image) if board == "emulated" else None
        if self.board is not None:
            pps_mode = "latch"          # the board latches; the simulator's latches place its glitch edges
        if not 0 <= corrupt_counters_frac < 1:
            raise ValueError(f"--corrupt-counters {corrupt_counters_frac}: must be in [0, 1)")
        if not 0 <= repeat_reads < 1 or (repeat_reads and board == "emulated"):
            raise ValueError(f"--repeat-reads {repeat_reads}: must be in [0, 1), with the simulated board")
        sc = trajectory.load_scenario(scenario)
        # the drive starts now, so at speed 1 GPS time and the daemon's host clock agree as in the car
        sc = replace(sc, clock={**sc.clock, "start_utc_ns": time.time_ns()},
                     gps={**sc.gps, "clock_jumps": [*sc.gps.get("clock_jumps", []), *(clock_jumps or [])]})
        self.clock_jumps = sc.gps["clock_jumps"]
        self.scenario = sc.name
        self.receiver = receiver or sc.gps.get("receiver", "nmea")
        self.duration_s = float(duration_s or sc.duration_s)
        self.seed = seed
        self.speed = speed
        self.can = can = can or vehicle.from_scenario(sc.vehicle)[0]
        reads, self.truth, self.t0_ns, self.ccfg, _ = simulate.make_reads(sc, self.duration_s, seed, pps_mode,
                                                                             receiver, can)
        if self.board is not None:     # the DAQ port carries the board's input records, one per sample
            records = emulated.input_records(self.truth)
            mono = HostClock().mono_ns(self.truth["t_k"])
            reads = [r for r in reads if r.port != "daq"] + [RawRead("daq", m, 0, r.tobytes())
                                                            for m, r in zip(mono.tolist(), records)]
            reads.sort(key=lambda r: r.mono_ns)
        m0 = reads[0].mono_ns
        self.ports = {}
        self.counter_corrupt_frames = np.zeros(0, np.int64)
        self.repeated = 0
        for name in ALL_PORTS if can else PORTS:
            rs = [r for r in reads if r.port == name]
            data = [r.data for r in rs]
            n_corrupt = 0
            whole = b"".join(data)
            if name == "daq" and corrupt_counters_frac > 0:
                whole, self.counter_corrupt_frames = corrupt_counters(whole, corrupt_counters_frac, seed)
            if corrupt > 0:
                whole, pos = corrupt_stream(whole, corrupt, seed, name)
                n_corrupt = pos.size
            if corrupt > 0 or (name == "daq" and corrupt_counters_frac > 0):
                ends = np.cumsum([len(d) for d in data])
                data = [whole[e - len(d):e] for d, e in zip(data, ends)]
            t_s = np.array([(r.mono_ns - m0) / NS for r in rs])
            if name == "daq" and repeat_reads > 0:
                twice = repeated_reads(len(data), repeat_reads, seed)
                self.repeated = int(twice.sum())
                data = [x for d, t in zip(data, twice) for x in ((d, d) if t else (d,))]
                t_s = np.repeat(t_s, 1 + twice)
            self.ports[name] = _Port(name, t_s, data, corrupt_bytes=n_corrupt)
        self.corrupt = corrupt
        self.unplug = sorted(unplug or [], key=lambda u: u.start_s)
        self.link_dir = Path(link_dir) if link_dir else None
        self.stop = threading.Event()
        self.completed = False

    def open(self, out: TextIO = sys.stdout) -> None:
        """Open the ptys (and start the emulated board) and print ``daq PATH``, ``gps PATH`` and, with the CAN bus,
        ``can PATH`` (flushed)."""
        if self.link_dir is not None:
            outputs.out_dir(self.link_dir)
        for p in self.ports.values():
            if p.name == "daq" and self.board is not None:
                p.open(None)
                self.board.start(p.slave)
                path = self.board.daq_path
                if self.link_dir is not None:
                    (self.link_dir / "daq").unlink(missing_ok=True)
                    (self.link_dir / "daq").symlink_to(path)
            else:
                p.open(self.link_dir)
                path = p.path
            out.write(f"{p.name} {path}\n")
        out.flush()

    def _unplugged(self, name: str, t_s: float) -> Unplug | None:
        for u in self.unplug:
            if u.port == name and u.start_s <= t_s < u.start_s + u.length_s:
                return u
        return None

    def run(self, log: Callable[[str], None] = lambda s: None) -> None:
        """Stream until the drive ends (then wait for the reader to drain the ptys, at most 10 s) or stop."""
        start = time.monotonic()
        while not self.stop.is_set():
            t_s = (time.monotonic() - start) * self.speed
            busy = False
            for p in self.ports.values():
                busy |= self._step(p, t_s, log)
            if not busy:
                self.completed = True
                break
            fds = [p.master for p in self.ports.values() if p.pending and p.master >= 0]
            if fds:
                select.select([], fds, [], 0.002)
            else:
                time.sleep(0.002)
        # wait (at most 10 s) for the reader to drain the ptys (one empty reading is not enough: module doc)
        deadline = time.monotonic() + 10.0
        while self.completed and not self.stop.is_set() and time.monotonic() < deadline:
            if all([p.master < 0 or p.drained() for p in self.ports.values()]) and (
                    self.board is None or self.board.drained()):
                break
            time.sleep(0.02)

    def _step(self, p: _Port, t_s: float, log: Callable[[str], None]) -> bool:
        """Queue the reads due by ``t_s`` and write what the pty takes; False once the port has nothing left."""
        j = int(np.searchsorted(p.t_s, t_s, side="right"))
        u = self._unplugged(p.name, t_s)
        if u is not None and p.master >= 0 and p.draining_since is None:
            log(f"{p.name} unplugged for {u.length_s:g} s")
            p.stop_sending()
        if p.draining_since is not None and (p.drained() or time.monotonic() - p.draining_since > DRAIN_MAX_S):
            p.unplug(self.link_dir)
        if u is None and p.master < 0:
            p.open(self.link_dir, wait_reader=True)
            p.replugged_mono_ns.append(time.monotonic_ns())
            log(f"{p.name} back as {p.path}")
        if u is not None or p.draining_since is not None or not p.reader_opened():
            p.lose(sum(len(d) for d in p.data[p.next_read:j]))
            p.next_read = j
            return p.next_read < len(p.data)
        if j > p.next_read:
            p.pending += b"".join(p.data[p.next_read:j])
            p.next_read = j
        if p.pending:
            try:
                n = os.write(p.master, p.pending)
            except BlockingIOError:
                n = 0
            except OSError as e:
                if e.errno != errno.EIO:
                    raise
                n = 0
            p.sent += p.pending[:n]
            del p.pending[:n]
        return p.next_read < len(p.data) or bool(p.pending)

    def sent_metadata(self) -> dict[str, str]:
        d, g = self.ports["daq"], self.ports["gps"]
        return {"scenario": self.scenario, "seed": str(self.seed), "duration_s": repr(self.duration_s),
                "speed": repr(self.speed), "completed": str(self.completed),
                "daq_bytes": str(len(d.sent)), "daq_frames": str(len(d.sent) // daq.FRAME_SIZE),
                "daq_lost_bytes": str(d.lost_bytes), "gps_bytes": str(len(g.sent)),
                "nmea_lines": str(bytes(g.sent).count(b"\n")), "gps_lost_bytes": str(g.lost_bytes),
                "daq_gaps": ";".join(f"{a}:{n}" for a, n in d.gaps),
                "gps_gaps": ";".join(f"{a}:{n}" for a, n in g.gaps), "corrupt": repr(self.corrupt),
                "daq_corrupt_bytes": str(d.corrupt_bytes), "gps_corrupt_bytes": str(g.corrupt_bytes),
                "daq_counter_corrupt_frames": str(self.counter_corrupt_frames.size),
                "daq_repeated_reads": str(self.repeated),
                "unplug": ";".join(f"{u.port}:{u.start_s:g}:{u.length_s:g}" for u in self.unplug),
                "daq_replug_mono_ns": ";".join(map(str, d.replugged_mono_ns)),
                "gps_replug_mono_ns": ";".join(map(str, g.replugged_mono_ns)),
                "daq_undrained_unplugs": str(d.undrained_unplugs), "gps_undrained_unplugs": str(g.undrained_unplugs),
                "gps_clock_jumps": ";".join(":".join(f"{x:g}" for x in j) for j in self.clock_jumps),
                "drive_start_utc_ns": str(self.t0_ns), "receiver": self.receiver,
                "board": "simulated" if self.board is None else "emulated",
                "pps_mode": self.ccfg.pps_mode,
                **({} if self.board is None else {"daq_frames": str(len(d.sent) // emulated.RECORD_SIZE),
                                                  "board_image": str(self.board.image)}),
                "can": str(self.can), **self._can_metadata()}

    def _can_metadata(self) -> dict[str, str]:
        """What the SLCAN adapter sent (``can_records``: CR-terminated records), as for the other ports."""
        c = self.ports.get("can")
        if c is None:
            return {}
        return {"can_bytes": str(len(c.sent)), "can_records": str(bytes(c.sent).count(b"\r")),
                "can_lost_bytes": str(c.lost_bytes), "can_gaps": ";".join(f"{a}:{n}" for a, n in c.gaps),
                "can_corrupt_bytes": str(c.corrupt_bytes), "can_replug_mono_ns": ";".join(map(str, c.replugged_mono_ns)),
                "can_undrained_unplugs": str(c.undrained_unplugs)}

    def write_truth(self, path: str | Path, force: bool = False) -> None:
        """``/truth/*`` and the ``serve`` metadata (what was sent) to ``path`` (new, unless ``force``)."""
        with recorder.Recorder(path, flush_interval_s=None, fsync=False, force=force,
                               metadata={"source": "fieldlog sim --serve", "scenario": self.scenario,
                                         "seed": str(self.seed)}) as rec:
            rec.add_metadata("serve", self.sent_metadata())
            simulate.write_truth(rec, self.truth)

    def close(self) -> None:
        if self.board is not None:
            self.board.stop()
            if self.link_dir is not None:
                (self.link_dir / "daq").unlink(missing_ok=True)
        for p in self.ports.values():
            p.close(self.link_dir if p.name != "daq" or self.board is None else None)


def serve(scenario: str, duration_s: float | None, seed: int, speed: float, pps_mode: str | None = None,
          receiver: str | None = None, truth: str | None = None, unplug: list[Unplug] | None = None,
          link_dir: str | None = None,
          hold: bool = False, corrupt: float = 0.0, clock_jumps: list[list[float]] | None = None,
          board: str = "simulated", board_image: str | None = None, can: bool = False,
          force: bool = False, corrupt_counters_frac: float = 0.0, repeat_reads: float = 0.0) -> int:
    """The ``fieldlog sim --serve`` command: SIGINT/SIGTERM stop it; ``hold`` waits for SIGUSR1 before
    streaming (so a test can start the reader first). ``truth``: a new file unless ``force`` (checked first)."""
    if truth:
        outputs.check_new(truth, force)
    srv = Server(scenario, duration_s, seed, speed, pps_mode, unplug, link_dir, corrupt, receiver, clock_jumps,
                 board, board_image, can, corrupt_counters_frac, repeat_reads)
    go = threading.Event()
    if not hold:
        go.set()

    def on_stop(signum, frame) -> None:
        srv.stop.set()
        go.set()

    signal.signal(signal.SIGINT, on_stop)
    signal.signal(signal.SIGTERM, on_stop)
    signal.signal(signal.SIGUSR1, lambda s, f: go.set())
    try:
        srv.open()
    except Exception:
        srv.close()
        raise
    log = lambda s: print(f"sim --serve: {s}", file=sys.stderr, flush=True)  # noqa: E731
    try:
        while not go.wait(0.1):
            pass
        if not srv.stop.is_set():
            log(f"streaming {srv.scenario} ({srv.duration_s:g} s) at x{speed:g}")
            srv.run(log)
        log("drive ended" if srv.completed else "stopped")
    finally:
        if truth:
            srv.write_truth(truth, force)
        srv.close()
    return 0
