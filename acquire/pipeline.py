"""Raw serial reads in, the drive's derived topics out: the one processing path of the daemon, the
simulator, ``import`` and ``rebuild``.

Reads must be fed in host-monotonic order across ports. Everything written is a deterministic function of
the reads, so re-running on ``/raw/*`` reproduces the derived topics bit for bit.
"""
from __future__ import annotations

import datetime as _dt
import itertools
import logging
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field, fields, replace
from functools import cached_property
from operator import attrgetter
from typing import NamedTuple, Protocol

import numpy as np

from fieldlog.acquire import calib, canbus, counterjudge, daq, frames, gnss, gpsport, nmea, novatel, sbf, timesync, ubx
from fieldlog.drive import messages, metavalue
from fieldlog.drive.recorder import Records

log = logging.getLogger(__name__)

NS = 1_000_000_000
EMIT_PERIOD_NS = NS // 4   # derived output is collected every quarter second of reads, not after every read
READ_BLOCK = 2048          # reads feed_reads takes at a time (the DAQ port's decoded ahead in one call)
_FRAME_FIELDS = tuple(f.name for f in fields(daq.DaqFrames))
MAX_HDOP = 99.0             # NMEA's largest HDOP; a larger, missing or non-positive one is taken as this
MAX_SIGMA_M = 1e6           # a GST standard deviation beyond this (or NaN) falls back on HDOP


class RawRead(NamedTuple):
    """One read() from a serial port: host monotonic and wall-clock time at return, and the bytes. A named tuple:
    a drive's reads number in the hundreds of thousands (``sim``, ``rebuild``), and a tuple is made in one step,
    where a frozen dataclass sets its fields one by one."""

    port: str
    mono_ns: int
    wall_ns: int
    data: bytes


PORT_ORDER = {"daq": 0, "gps": 1, "can": 2}


def read_order(port: str, mono_ns: int) -> tuple[int, int]:
    """The order reads are processed in: host monotonic time, DAQ first on a tie. The daemon, the
    simulator and ``rebuild`` all use it, so they feed the pipeline identically."""
    return (mono_ns, PORT_ORDER.get(port, 3))


def raised_at(e: BaseException) -> str:
    """Where ``e`` was raised: "FILE:LINE" of its traceback's last frame ("?" without one), for the one line an
    error that recording survives is logged with.

    Parameters
    ----------
    e : BaseException
        A caught exception.

    Returns
    -------
    str
    """
    tb = e.__traceback__
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    return f"{tb.tb_frame.f_code.co_filename}:{tb.tb_lineno}" if tb is not None else "?"


def in_read_order(reads: Iterable[RawRead]) -> list[RawRead]:
    """``reads`` (``RawRead``-like) sorted by ``read_order``, reads of equal order as they came: grouped by port
    in ``PORT_ORDER`` (each group as it came), then sorted by host monotonic time alone, a stable sort that keeps
    a tie in that port order. The same list as sorting by ``read_order``, with a key of one attribute."""
    groups: dict[int, list[RawRead]] = {}
    for r in reads:
        groups.setdefault(PORT_ORDER.get(r.port, 3), []).append(r)
    out = [r for rank in sorted(groups) for r in groups[rank]]
    out.sort(key=attrgetter("mono_ns"))
    return out


class Sink(Protocol):
    def write(self, topic: str, log_time_ns: int, data: bytes) -> None: ...

    def write_batch(self, topic: str, log_time_ns: np.ndarray, data) -> None: ...

    def write_records(self, recs: Records, i: int, j: int) -> None: ...   # feed_reads only


@dataclass
class PipelineConfig:
    """Processing settings that are not calibration. SI units."""

    gyro_noise_density: float = np.radians(0.01)   # rad/s/sqrt(Hz), for the /imu covariance
    accel_noise_density: float = 5e-6 * 9.80665    # m/s^2/sqrt(Hz) (Table 2: 5 ug/sqrt(Hz))
    gps_vel_sigma_mps: float = 0.1                  # NMEA and NovAtel BESTVEL carry no velocity accuracy
    gps_vvel_sigma_mps: float = 0.2                 # vertical, when the receiver gives a vertical speed only
    uere_m: float = 4.0                             # sigma_h = HDOP * UERE when no GST
    vertical_over_horizontal: float = 2.0
    imu_frame_id: str = frames.IMU                  # frames of /tf_static (acquire/frames.py)
    gps_frame_id: str = frames.GPS_ANTENNA
    gps_service: int = 15                           # NavSatFix service mask: GPS|GLONASS|COMPASS|GALILEO
    gps_protocol: str = "auto"                      # [gps] protocol: which frames are decoded (gpsport.ACCEPTS)
    use_hnr: bool = False                           # [gps] use_hnr: u-blox HNR-PVT as the fixes (acquire/ubx.py)
    receiver_time_tolerance_s: float = 0.5          # receiver time vs the GPS clock fit (GpsInput)
    can: canbus.BusConfig | None = None             # the vehicle bus: how /raw/can is decoded (acquire/canbus.py)
    tf_static: bool = True                          # write /tf_static: off when there is no IMU or antenna (a
                                                    # CAN log imported alone), so the file claims no frame of them


@dataclass
class Counters:
    """What the pipeline saw besides good data; every field is a count."""

    daq: daq.DaqStats
    nmea: nmea.NmeaStats
    imu_samples: int = 0
    gps_epochs: int = 0
    gps_no_fix: int = 0
    pps_edges: int = 0
    pps_rejected: int = 0
    pps_implausible: int = 0        # PPS flags ignored: far more often than once a second (timesync)
    processing_errors: int = 0                  # reads whose processing raised (their bytes are in /raw)
    reads: dict = field(default_factory=dict)
    no_fix: dict = field(default_factory=dict)  # epochs that are not fixes, by reason (gnss.no_fix_reason, ...)
    nmea_superseded: int = 0        # NMEA epochs not used: the port also sends UBX/NovAtel solutions
    gps_ignored: int = 0            # checked frames of a protocol the [gps] protocol setting excludes


SPARSE_COUNTERS = ("daq.repeated", "pps_implausible")   # in the counters record only when not zero


@dataclass
class _Ahead:
    """The frames of consecutive DAQ reads (``reads``) from one decoder call: read i's are ``fr``'s
    ``cuts[i]:cuts[i + 1]``, and begin ``starts[i]`` bytes after the first read's first byte; ``base``: the
    decoder's byte count before the first read."""

    fr: daq.DaqFrames
    cuts: list[int]
    starts: list[int]
    base: int
    reads: list[RawRead]

    @cached_property
    def raw(self) -> Records:
        """The reads' /raw/daq messages (what ``Pipeline.record`` writes of each), encoded in one step
        (``messages.encode_raws``) and laid out as records in one more at their first write."""
        wall_ns = np.array([r.wall_ns for r in self.reads], np.int64)
        mono_ns = np.array([r.mono_ns for r in self.reads], np.int64)
        data = messages.Packed.from_list([r.data for r in self.reads])
        return Records("/raw/daq", wall_ns, messages.encode_raws(wall_ns, mono_ns, "daq", data))

    def span(self, i: int, j: int) -> tuple[daq.DaqFrames, int]:
        """Reads i..j-1's frames (end offsets from read i's first byte) and the decoder's byte count before
        read i: what ``DaqDecoder.feed`` of their bytes alone would give, and ``feed``'s ``decoded``."""
        a, b, s = self.cuts[i], self.cuts[j], self.starts[i]
        piece = daq.DaqFrames(*(getattr(self.fr, f)[a:b] for f in _FRAME_FIELDS))
        piece.end_offset = piece.end_offset - s
        return piece, self.base + s

    @classmethod
    def decode(cls, dec: daq.DaqDecoder, reads: list[RawRead]) -> "_Ahead | None":
        """The frames of these consecutive DAQ reads from one decoder call over their bytes; None (each read
        then decoded as it is fed) if there are none or that call fails, the decoder put back as it was."""
        if not reads:
            return None
        datas = [r.data for r in reads]
        saved, stats = dict(vars(dec)), asdict(dec.stats)
        base = dec.stats.bytes_in
        try:
            fr = dec.feed(b"".join(datas))
        except Exception:  # noqa: BLE001 - the reads are then decoded one by one, under feed's guard
            vars(dec).update(saved)
            for k, v in stats.items():
                setattr(dec.stats, k, v)
            return None
        lengths = np.array([len(d) for d in datas], np.int64)
        ends = np.cumsum(lengths)
        read_of = np.searchsorted(ends, fr.end_offset, side="left")  # the read each frame's last byte is in
        cuts = np.searchsorted(read_of, np.arange(len(datas) + 1), side="left")
        return cls(fr, cuts.tolist(), (ends - lengths).tolist(), base, reads)


class Pipeline:
    """Feed ``RawRead``-like records; derived messages go to ``sink.write_batch``."""

    def __init__(self, sink: Sink, cal: calib.Calibration | None = None,
                 sync_cfg: timesync.TimeSyncConfig | None = None, cfg: PipelineConfig | None = None) -> None:
        self.sink = sink
        self.cal = cal or calib.load_calibration(None)
        self.cfg = cfg or PipelineConfig()
        self.sync = timesync.TimeSync(sync_cfg or timesync.TimeSyncConfig())
        self.fs = self.sync.cfg.fs_hz
        self._daq = daq.DaqDecoder()
        self._judge = counterjudge.CounterJudge(self._daq.stats, counterjudge.JudgeConfig(
            fs_hz=self.fs, host_time_scale=self.sync.cfg.host_time_scale))
        self._last_daq_read = (0, 0)      # (mono_ns, wall_ns) of the last DAQ read
        self._last_emit_ns = -(2**62)
        self._errors_logged: set[tuple[str, str]] = set()
        self._stuck_logged = False       # the stuck DAQ counter has been logged (until it advances again)
        decoder = nmea.NmeaDecoder()
        self.counters = Counters(daq=self._daq.stats, nmea=decoder.stats)
        self.gps = GpsInput(self.cfg, self.sync, sink, self.counters, decoder)
        self.output = StampedOutput(self.cfg, self.cal, self.sync, sink, self.counters)
        # called with (read mono_ns, k, counts) for each read's decoded frames, once time sync has them (the
        # daemon's live bus publishes provisional /imu from it); it must not feed back into the pipeline
        self.on_frames: Callable[[int, np.ndarray, np.ndarray], None] | None = None
        self._tf_file: object = None     # the file /tf_static was last written to (a rotating sink changes files)
        self.vehicle = canbus.VehicleDecoder(self.cfg.can) if self.cfg.can is not None else None

    def _write_tf_static(self, wall_ns: int) -> None:
        """/tf_static (acquire/frames.py) at the start of every file, stamped with the host clock of its first read."""
        target = getattr(self.sink, "rec", self.sink)
        if target is not self._tf_file and self.cfg.tf_static:
            self._tf_file = target
            self.sink.write("/tf_static", wall_ns, frames.tf_static_message(self.cal.mounting, wall_ns))

    # -- input ---------------------------------------------------------------------------------------
    def feed_reads(self, reads: Iterable[RawRead], progress: Callable[[int], None] | None = None) -> int:
        """``feed`` each read (``RawRead``-like: port, mono_ns, wall_ns, data) in turn, with the same outputs,
        ``READ_BLOCK`` reads at a time: each block's DAQ reads are decoded ahead in one call of the decoder (the
        frames it finds, and its counts, do not depend on how the bytes are split into reads) and their /raw/daq
        messages encoded in one step (``_Ahead.raw``), and the DAQ reads between two reads of another port or two
        emits are recorded in one ``Sink.write_records`` and processed as one where the counter judge and time
        sync take them so (``_feed_run``). For a recorded or simulated stream (``sim``, ``rebuild``, ``import``);
        the daemon feeds each read as it comes. ``progress``: called with the reads fed so far
        after each block. Returns the number of reads."""
        n, it = 0, iter(reads)
        while block := list(itertools.islice(it, READ_BLOCK)):
            ahead = _Ahead.decode(self._daq, [r for r in block if r.port == "daq"])
            run: list[RawRead] = []       # DAQ reads in a row, not recorded or processed yet
            d = 0                         # the block's DAQ reads so far
            for r in block:
                if r.port == "daq" and ahead is not None and self.on_frames is None:
                    run.append(r)
                    d += 1
                    if r.mono_ns - self._last_emit_ns >= EMIT_PERIOD_NS:
                        self._feed_run(run, ahead, d - len(run))
                        run = []
                    continue
                if run:
                    self._feed_run(run, ahead, d - len(run))
                    run = []
                decoded = None
                if r.port == "daq":
                    decoded = ahead.span(d, d + 1) if ahead is not None else None
                    d += 1
                self.feed(r.port, r.mono_ns, r.wall_ns, r.data, decoded)
            if run:
                self._feed_run(run, ahead, d - len(run))
            n += len(block)
            if progress is not None:
                progress(n)
        return n

    def feed(self, port: str, mono_ns: int, wall_ns: int, data: bytes,
             decoded: tuple[daq.DaqFrames, int] | None = None) -> None:
        """Record one read in ``/raw/<port>`` and process it (``record``, then ``process``). ``decoded``: a DAQ
        read's frames and the decoder's byte count before it, when ``feed_reads`` decoded them ahead."""
        self.record(port, mono_ns, wall_ns, data)
        self.process(port, mono_ns, wall_ns, data, decoded)

    def process(self, port: str, mono_ns: int, wall_ns: int, data: bytes,
                decoded: tuple[daq.DaqFrames, int] | None = None) -> None:
        """Derive what one read gives (the read recorded already: ``record``). Reads are processed in
        ``read_order``, each once. Processing never raises for any data: an exception (a decoder bug a byte
        sequence reaches) is counted in ``processing_errors``, logged once per kind with where the read is, and
        the next read is processed as usual. Sink errors (OSError: a full disk) are raised. The daemon records
        on one thread and processes on another (acquire/daemon.py): ``record`` touches only ``/tf_static``,
        ``/raw/*`` and the read counters, ``process`` everything else."""
        try:
            if port == "daq":
                self._feed_daq(mono_ns, wall_ns, data, decoded)
            elif port == "gps":
                self.gps.feed(mono_ns, wall_ns, data)
            elif port == "can" and self.vehicle is not None:
                self.sync.add_host_time(mono_ns, wall_ns)
                self.vehicle.feed(data, int(self.sync.mono_to_utc(np.array([mono_ns], np.int64))[0]), self.sink)
            self._emit_due(mono_ns)
        except OSError:
            raise
        except Exception as e:  # noqa: BLE001 - the contract: no byte stops the recording
            self._processing_error(e, port, mono_ns, wall_ns)

    def record(self, port: str, mono_ns: int, wall_ns: int, data: bytes) -> None:
        """A read into ``/raw/<port>`` (after /tf_static, at a file's start) and the read counters."""
        self._write_tf_static(wall_ns)
        self.sink.write(f"/raw/{port}", wall_ns, messages.encode_raw(wall_ns, mono_ns, port, data))
        self.counters.reads[port] = self.counters.reads.get(port, 0) + 1

    def _emit_due(self, mono_ns: int) -> None:
        """Derived output collected every ``EMIT_PERIOD_NS`` of reads."""
        if mono_ns - self._last_emit_ns >= EMIT_PERIOD_NS:
            self._last_emit_ns = mono_ns
            self.output.emit_sync()
            self.output.emit_imu(final=False)

    def _feed_run(self, run: list[RawRead], ahead: "_Ahead", i: int) -> None:
        """Record DAQ reads in a row, reads ``i..`` of ``ahead``, in one write (``Sink.write_records`` of
        ``_Ahead.raw``: what ``record`` of each gives), then process them; only the last can be due an emit. As
        one when the counter judge takes all their frames as they are (``CounterJudge.usual``; time sync then
        takes them as one, ``TimeSync.add_run``), else read by read, each under ``feed``'s guard."""
        self._write_tf_static(run[0].wall_ns)
        self.sink.write_records(ahead.raw, i, i + len(run))
        wall_ns = [r.wall_ns for r in run]
        self.counters.reads["daq"] = self.counters.reads.get("daq", 0) + len(run)
        last = run[-1]
        fr, base = ahead.span(i, i + len(run))
        cuts = ahead.cuts[i:i + len(run) + 1]
        ends = [c - cuts[0] for c in cuts[1:]]
        with_frames = [r for r, a, b in zip(run, cuts, cuts[1:]) if b > a]
        try:
            usual = self._judge.usual(fr, base, with_frames[-1].mono_ns) if with_frames else None
            if usual is not None:
                self._last_daq_read = (last.mono_ns, last.wall_ns)
                self.sync.add_run(usual.k, usual.pps, usual.latch, usual.latch_valid, ends,
                                  [r.mono_ns for r in run], wall_ns)
                self.output.pending.append((usual.k, usual.counts))
                self._emit_due(last.mono_ns)
                return
        except OSError:
            raise
        except Exception as e:  # noqa: BLE001 - as in feed
            self._processing_error(e, "daq", last.mono_ns, last.wall_ns)
            return
        for j, r in enumerate(run):
            try:
                self._feed_daq(r.mono_ns, r.wall_ns, r.data, ahead.span(i + j, i + j + 1))
                self._emit_due(r.mono_ns)
            except OSError:
                raise
            except Exception as e:  # noqa: BLE001 - as in feed
                self._processing_error(e, "daq", r.mono_ns, r.wall_ns)

    def _processing_error(self, e: Exception, port: str, mono_ns: int, wall_ns: int) -> None:
        self.counters.processing_errors += 1
        where = raised_at(e)
        kind = (type(e).__name__, where)
        if kind in self._errors_logged:
            return
        self._errors_logged.add(kind)
        path = getattr(self.sink, "path", None)
        log.error("processing a %s read failed (%s: %s at %s); the read is kept in /raw/%s (mono_ns %d, wall_ns "
                  "%d%s) and recording goes on; further errors of this kind are only counted "
                  "(acquire.counters processing_errors)", port, type(e).__name__, e, where, port, mono_ns, wall_ns,
                  f", {path}" if path else "")

    def metadata(self) -> dict[str, dict[str, str]]:
        """What a later ``rebuild`` needs to reproduce this run: calibration and time-sync settings."""
        out = {"calibration": {"toml": self.cal.to_toml()},
               "timesync": {k: metavalue.dump(v) for k, v in asdict(self.sync.cfg).items()},
               "gps": {"protocol": self.cfg.gps_protocol, **({"use_hnr": "true"} if self.cfg.use_hnr else {})}}
        if self.cfg.can is not None:
            out["can"] = self.cfg.can.metadata()
        return out

    @staticmethod
    def settings_from_metadata(meta: dict[str, dict[str, str]]) -> tuple[calib.Calibration,
                                                                        timesync.TimeSyncConfig, PipelineConfig]:
        """The inverse of ``metadata``; defaults for what a drive does not record. ValueError when a recorded
        setting is not one (damaged metadata)."""
        cal = calib.Calibration.from_toml(meta["calibration"]["toml"]) if "calibration" in meta else \
            calib.load_calibration(None)
        sync = {}
        for k, v in meta.get("timesync", {}).items():
            try:
                x = metavalue.load(v)
            except ValueError as e:
                raise ValueError(f"metadata timesync.{k}: {e}") from None
            if isinstance(x, (list, dict)):
                raise ValueError(f"metadata timesync.{k}: {v[:40]!r} is not a setting")
            sync[k] = x
        try:
            sync_cfg = timesync.TimeSyncConfig.from_dict(sync)
        except TypeError as e:
            raise ValueError(f"metadata timesync: {e}") from None
        protocol = meta.get("gps", {}).get("protocol", "auto")
        can = canbus.BusConfig.from_metadata(meta["can"]) if "can" in meta else None
        return cal, sync_cfg, PipelineConfig(
            gps_protocol=protocol if protocol in gpsport.ACCEPTS else "auto", can=can,
            use_hnr=meta.get("gps", {}).get("use_hnr") == "true")

    def counters_metadata(self) -> dict[str, str]:
        """The counters, flattened for an MCAP metadata record."""
        c = self.counters
        out = {f"daq.{k}": str(v) for k, v in asdict(c.daq).items()}
        out.update({f"nmea.{k}": str(v) for k, v in asdict(c.nmea).items()})
        out.update({k: str(getattr(c, k)) for k in ("imu_samples", "gps_epochs", "gps_no_fix", "pps_edges",
                                                    "pps_rejected", "pps_implausible", "nmea_superseded",
                                                    "gps_ignored", "processing_errors")})
        out.update({f"gps_no_fix.{k}": str(v) for k, v in c.no_fix.items()})
        self.gps.add_counters(out)
        out.update({f"reads.{k}": str(v) for k, v in c.reads.items()})
        if self.vehicle is not None:
            out.update(self.vehicle.counters())
        for k in SPARSE_COUNTERS:
            if out[k] == "0":
                del out[k]
        return out

    def finish(self) -> None:
        """End of the reads: everything pending is written. Under the same guard as ``feed``."""
        mono_ns, wall_ns = self._last_daq_read
        try:
            self._add_frames(self._judge.flush(), mono_ns, wall_ns)
            self.gps.flush()
            self.sync.finish()
            self.output.emit_sync()
            self.output.emit_imu(final=True)
        except OSError:
            raise
        except Exception as e:  # noqa: BLE001 - as in feed
            self._processing_error(e, "daq", mono_ns, wall_ns)

    def _feed_daq(self, mono_ns: int, wall_ns: int, data: bytes,
                  decoded: tuple[daq.DaqFrames, int] | None = None) -> None:
        self._last_daq_read = (mono_ns, wall_ns)
        if decoded is None:
            base = self._daq.stats.bytes_in
            decoded = self._daq.feed(data), base
        fr, base = decoded
        self._add_frames(self._judge.judge(fr, base, mono_ns), mono_ns, wall_ns)
        stuck = self._judge.stuck_run >= self.fs
        if stuck and not self._stuck_logged:
            log.warning("the DAQ sample counter is stuck at %d (%d frames in a row carry it): their samples cannot be "
                        "placed and are dropped (acquire.counters daq.counter_implausible)", self._judge.last_counter,
                        self._judge.stuck_run)
        self._stuck_logged = stuck

    def _add_frames(self, fr: daq.DaqFrames, mono_ns: int, wall_ns: int) -> None:
        """Judged frames of one read to time sync, the /imu queue and ``on_frames``."""
        if len(fr.k) == 0:
            return
        self.sync.add_frames(fr.k, fr.pps, fr.latch, fr.latch_valid, mono_ns, wall_ns)
        self.output.pending.append((fr.k, fr.counts))
        if self.on_frames is not None:
            self.on_frames(mono_ns, fr.k, fr.counts)


class StampedOutput:
    """The DAQ side's derived topics: ``/pps`` and ``/time/sync`` from time sync, and ``/imu`` of the judged
    samples (queued in ``pending`` as (k, counts)) once their stamps are final.

    Parameters
    ----------
    cfg : PipelineConfig
        Noise densities for the /imu covariances and the IMU's frame id.
    cal : calib.Calibration
        ADC counts -> SI, body RFU.
    sync : timesync.TimeSync
        Stamps the samples and decides the edges.
    sink : Sink
        Where the messages go.
    counters : Counters
        The pipeline's counters (PPS edges, IMU samples).
    """

    def __init__(self, cfg: PipelineConfig, cal: calib.Calibration, sync: timesync.TimeSync, sink: Sink,
                 counters: Counters) -> None:
        self.cfg, self.cal, self.sync, self.sink, self.counters = cfg, cal, sync, sink, counters
        self.fs = sync.cfg.fs_hz
        self.pending: deque[tuple[np.ndarray, np.ndarray]] = deque()  # (k, counts) awaiting final stamps
        bw = self.fs / 2
        self._gyro_cov = np.diag([cfg.gyro_noise_density**2 * bw] * 3).ravel()
        self._accel_cov = np.diag([cfg.accel_noise_density**2 * bw] * 3).ravel()

    def emit_sync(self) -> None:
        """The edges decided and the /time/sync records made final since the last call: /pps, /time/sync."""
        implausible = self.sync.labeller.implausible_edges
        if implausible and not self.counters.pps_implausible:
            log.warning("the PPS is implausible: more than %d flags within %g s of DAQ samples (a floating or "
                        "miswired PPS line?); such flags are ignored and counted (acquire.counters pps_implausible)",
                        timesync.PPS_BURST, timesync.PPS_BURST_S)
        self.counters.pps_implausible = implausible
        edges = self.sync.pop_edges()
        if len(edges):
            self.counters.pps_edges += len(edges)
            self.counters.pps_rejected += int(np.count_nonzero(~edges.accepted))
            stamp = np.where(edges.accepted, edges.label_s * NS, self.sync.mono_to_utc(edges.mono_ns))
            daq_clock_ns = np.round(edges.k_edge / self.fs * NS).astype(np.int64)
            for reason in dict.fromkeys(edges.reason):
                sel = edges.reason == reason
                utc = stamp[sel].astype(np.int64)
                self.sink.write_batch("/pps", utc, messages.encode_time_reference(
                    utc, daq_clock_ns[sel], "pps" if not reason else f"pps rejected: {reason}"))
        st = self.sync.pop_status()
        if len(st):
            self.sink.write_batch("/time/sync", st.utc_ns, messages.encode_time_sync(
                st.utc_ns, st.state, st.rate_ppm, st.residual_us, st.edges_used, st.edges_rejected))

    def emit_imu(self, final: bool) -> None:
        """Stamp, calibrate and write the buffered samples whose time stamps are final."""
        fin = None if final else self.sync.final_until()
        ks, cs = [], []
        while self.pending:
            k, c = self.pending[0]
            if fin is None or k[-1] < fin:
                self.pending.popleft()
            elif k[0] < fin:
                n = int(np.searchsorted(k, fin))
                self.pending[0] = (k[n:], c[n:])
                k, c = k[:n], c[:n]
            else:
                break
            ks.append(k)
            cs.append(c)
        if not ks:
            return
        k = np.concatenate(ks)
        t_ns, _state = self.sync.stamp(k)
        self.counters.imu_samples += len(k)
        self.sink.write_batch("/imu", t_ns, self.imu_messages(t_ns, np.concatenate(cs)))

    def imu_messages(self, t_ns: np.ndarray, counts: np.ndarray) -> messages.Packed:
        """/imu payloads of samples stamped ``t_ns`` (UTC ns) from their ADC ``counts`` (n, 6): calibrated to
        SI in the body frame, with the configured covariances and frame id."""
        omega_ib_b, f_b = calib.apply(self.cal, counts)
        return messages.encode_imu(t_ns, omega_ib_b, f_b, self._gyro_cov, self._accel_cov,
                                   frame_id=self.cfg.imu_frame_id)


class GpsInput:
    """The pipeline's GPS side: each GPS read in, ``/gps/nmea``, ``/gps/receiver``, ``/gps/fix`` and ``/gps/vel``
    out, and the fixes (UTC seconds) and pulse errors to time sync.

    Parameters
    ----------
    cfg : PipelineConfig
        Frame ids, the protocol accepted, the accuracies assumed (m, m/s) and the receiver-time tolerance (s).
    sync : timesync.TimeSync
        Takes the fixes and maps host times to UTC.
    sink : Sink
        Where the messages go.
    counters : Counters
        The pipeline's counters (epochs, no-fix reasons, ignored frames).
    decoder : nmea.NmeaDecoder
        The NMEA decoder (its statistics are the counters' ``nmea``).
    """

    def __init__(self, cfg: PipelineConfig, sync: timesync.TimeSync, sink: Sink, counters: Counters,
                 decoder: nmea.NmeaDecoder) -> None:
        self.cfg, self.sync, self.sink, self.counters = cfg, sync, sink, counters
        self._nmea = decoder
        self._port = gpsport.Framer()
        self._ubx = ubx.UbxDecoder(cfg.use_hnr)
        self._oem = novatel.NovatelDecoder()
        self._sbf = sbf.SbfDecoder()
        self._accepts = gpsport.ACCEPTS[cfg.gps_protocol]
        self._binary_solutions = False   # once the receiver sends UBX/NovAtel solutions, NMEA gives no epochs
        self._epochs = nmea.EpochAssembler()
        self._gps_prev_read: dict[int, int] = {}   # mono_ns of a recent GPS read -> of the GPS read before it
        self._gps_last_read = 0
        self._last_fix_key: int | None = None
        self._last_fix_ns = 0                # UTC ns of the latest /gps/fix written
        self._date: _dt.date | None = None
        self._last_tod = -1.0

    def feed(self, mono_ns: int, wall_ns: int, data: bytes) -> None:
        """One GPS port read of ``data`` at host ``mono_ns``/``wall_ns`` (ns): its frames decoded, written to
        /gps/nmea and /gps/receiver, its epochs to /gps/fix and /gps/vel, its times to time sync."""
        frames = self._port.feed(data)
        self._gps_prev_read[mono_ns] = self._gps_last_read or mono_ns
        self._gps_last_read = mono_ns
        if len(self._gps_prev_read) > 64:
            del self._gps_prev_read[next(iter(self._gps_prev_read))]
        st, fs = self._nmea.stats, self._port.stats
        st.lines, st.bytes_discarded, st.overlong = fs.frames.get("nmea", 0), fs.bytes_discarded, fs.overlong
        if not frames:
            return
        self.sync.add_host_time(mono_ns, wall_ns)
        stamp = int(self.sync.mono_to_utc(np.array([mono_ns], np.int64))[0])
        for kind, frame in frames:
            if kind not in self._accepts:
                self.counters.gps_ignored += 1
                continue
            if kind == "nmea":
                s = self._nmea.decode_line(frame)
                if s is None:
                    continue
                self.sink.write("/gps/nmea", stamp, messages.encode_sentence(
                    stamp, s.raw.decode("ascii", "replace"), self.cfg.gps_frame_id))
                if not self._binary_solutions and not (isinstance(s, nmea.Gll) and self._epochs.better):
                    self._note_time(s, mono_ns, wall_ns)
                for ep in self._epochs.add(s, mono_ns):
                    self._emit_epoch(ep)
                continue
            if kind == "ubx":
                name, records = self._ubx.decode(frame, mono_ns)
            elif kind == "sbf":
                name, records = self._sbf.decode(frame, mono_ns)
            else:
                name, records = self._oem.decode(kind, frame, mono_ns)
            self.sink.write("/gps/receiver", stamp, messages.encode_raw(
                stamp, mono_ns, f"{kind}:{name}", frame, self.cfg.gps_frame_id))
            for r in records:
                if isinstance(r, ubx.Pulse):
                    self.sync.add_pulse_error(r.utc_s, r.qerr_s)
                    continue
                self._binary_solutions = True
                self._note_binary_time(r.utc_ns, mono_ns, wall_ns)
                if isinstance(r, gpsport.Solution):
                    self._emit_solution(r)

    def _note_binary_time(self, utc_ns: int, mono_ns: int, wall_ns: int) -> None:
        """As ``_note_time`` for a UBX/NovAtel epoch; it also dates later NMEA sentences without a date."""
        utc_s, frac = divmod(utc_ns, NS)
        self._date = gnss.date_of_utc_ns(utc_ns)
        self._last_tod = utc_s % 86400
        if frac == 0 and self._last_fix_key != utc_s:
            self._last_fix_key = utc_s
            self.sync.add_fix(utc_s, mono_ns, wall_ns)

    def _note_time(self, s, mono_ns: int, wall_ns: int) -> None:
        """Tell time sync about the first sentence of each new whole UTC second (gpsd-style labelling)."""
        date = getattr(s, "date", None)
        if date is not None:
            self._date = date
        tod = getattr(s, "time_of_day_s", None)
        if tod is None or not np.isfinite(tod):
            return
        if self._date is None:
            self._date = gnss.in_range(_dt.datetime.fromtimestamp(wall_ns / NS, _dt.timezone.utc).date())
        elif date is None:
            self._date = gnss.roll_over(self._date, tod, self._last_tod)
        self._last_tod = tod
        if tod != np.floor(tod) or self._date is None:
            return
        utc_s = int(_dt.datetime.combine(self._date, _dt.time(), _dt.timezone.utc).timestamp()) + int(tod)
        if self._last_fix_key != utc_s:
            self._last_fix_key = utc_s
            self.sync.add_fix(utc_s, mono_ns, wall_ns)

    def _emit_epoch(self, ep: nmea.GnssEpoch) -> None:
        """An NMEA epoch as a solution (unless the receiver also sends UBX/NovAtel ones)."""
        if self._binary_solutions:
            self.counters.nmea_superseded += 1
            return
        utc_ns = ep.utc_ns
        if utc_ns is None:
            if self._date is None:
                return
            utc_ns = replace(ep, date=self._date).utc_ns
        why = ep.no_fix or ("" if np.isfinite(ep.lat_deg) else "no_position")
        sd = (ep.sd_east_m, ep.sd_north_m, ep.sd_up_m)
        known = all(np.isfinite(sd[:2])) and all(abs(x) < MAX_SIGMA_M for x in sd if np.isfinite(x))
        if known:
            var = tuple(x**2 for x in sd)
        else:
            hdop = ep.hdop if ep.hdop is not None and 0 < ep.hdop <= MAX_HDOP else MAX_HDOP
            sh = hdop * self.cfg.uere_m
            var = (sh**2, sh**2, (self.cfg.vertical_over_horizontal * sh) ** 2)
        vel = None
        if ep.speed_mps is not None and np.isfinite(ep.speed_mps):
            course = ep.course_rad if ep.course_rad is not None and np.isfinite(ep.course_rad) else 0.0
            vel = (ep.speed_mps * np.sin(course), ep.speed_mps * np.cos(course), 0.0)
        s2 = self.cfg.gps_vel_sigma_mps**2
        self._emit_solution(gpsport.Solution(
            utc_ns, not why, ep.quality, ep.num_sats, ep.lat_deg, ep.lon_deg, ep.alt_ellipsoid_m, var, known, vel,
            (s2, s2, messages.UNKNOWN_VARIANCE), ep.first_mono_ns, "nmea"), why)   # NMEA: no vertical velocity

    def _emit_solution(self, sol: gpsport.Solution, why: str = "") -> None:
        """/gps/fix and /gps/vel of one receiver epoch; ``why`` it is not a fix (counted by reason).

        Once time sync has a GPS clock fit, the epoch must lie between one second before the port's previous
        read (its first message came after that read: a read the host made late holds older epochs) and the
        read of its first message; a receiver time further off than ``receiver_time_tolerance_s`` (a receiver
        clock jump) is NO_FIX ``receiver_time`` and stamped with the fit's time of that read, not the
        receiver's, and 1 ns after the fix before it if a late read holds both."""
        why = why or ("" if sol.fix else "time_only" if sol.time_only else "receiver")
        utc_ns = sol.utc_ns
        if self.sync.gps_clock and sol.first_mono_ns:
            prev = self._gps_prev_read.get(sol.first_mono_ns, sol.first_mono_ns)
            arrival, after = (int(x) for x in self.sync.mono_to_utc(np.array([sol.first_mono_ns, prev], np.int64)))
            tol = int(self.cfg.receiver_time_tolerance_s * NS)
            if not after - NS - tol <= utc_ns <= arrival + tol:
                why, utc_ns = "receiver_time", max(arrival, self._last_fix_ns + 1)
        t_ns = np.array([utc_ns], np.int64)
        self._last_fix_ns = max(self._last_fix_ns, utc_ns)
        fix = not why
        c = self.counters
        c.gps_epochs += 1
        c.gps_no_fix += not fix
        if why:
            c.no_fix[why] = c.no_fix.get(why, 0) + 1
        cov_type = messages.COVARIANCE_TYPE_DIAGONAL_KNOWN if sol.pos_var_known else \
            messages.COVARIANCE_TYPE_APPROXIMATED
        status = messages.fix_status(sol.quality if fix else 0)
        nan = np.nan
        shown = fix or why == "time_only"     # a timing receiver's surveyed position: NO_FIX, covariance unknown
        pos_cov = np.diag(sol.pos_var).ravel()
        if why == "time_only":
            cov_type, pos_cov = messages.COVARIANCE_TYPE_UNKNOWN, np.zeros(9)
        self.sink.write_batch("/gps/fix", t_ns, messages.encode_navsatfix(
            t_ns, [sol.lat_deg if shown else nan], [sol.lon_deg if shown else nan], [sol.h_m if shown else nan],
            pos_cov, cov_type, status, self.cfg.gps_service, frame_id=self.cfg.gps_frame_id))
        if fix and sol.vel_enu is not None and np.all(np.isfinite(sol.vel_enu)):
            lin = np.array([sol.vel_enu])
            default = (self.cfg.gps_vel_sigma_mps**2,) * 2 + (self.cfg.gps_vvel_sigma_mps**2,)
            cov = np.zeros((1, 36))
            cov[0, [0, 7, 14]] = np.where(np.isfinite(sol.vel_var), sol.vel_var, default)
            cov[0, [21, 28, 35]] = messages.UNKNOWN_VARIANCE  # no angular velocity
            self.sink.write_batch("/gps/vel", t_ns, messages.encode_twist(
                t_ns, lin, None, cov, frame_id=self.cfg.gps_frame_id))

    def flush(self) -> None:
        """End of the reads: the epochs and solutions the decoders still hold are written."""
        for ep in self._epochs.flush():
            self._emit_epoch(ep)
        for sol in self._oem.flush() + self._sbf.flush():
            self._emit_solution(sol)

    def add_counters(self, out: dict[str, str]) -> None:
        """The GPS port's frame and decoder counters into ``out`` (the counters record, flattened)."""
        fs = self._port.stats
        out.update({f"gps.frames.{k}": str(v) for k, v in fs.frames.items()})
        out.update({f"gps.bad_checksum.{k}": str(v) for k, v in fs.bad_checksum.items()})
        decoders = [("ubx", self._ubx.stats), ("novatel", self._oem.stats)]
        if fs.frames.get("sbf"):
            decoders.append(("sbf", self._sbf.stats))
        for name, st in decoders:
            out.update({f"{name}.{k}": str(v) for k, v in asdict(st).items() if k != "by_type"})
            out.update({f"{name}.{k}": str(v) for k, v in st.by_type.items()})
        ep = self._epochs
        if ep.split or "GLL" in ep.position_from or ep.gll_ignored:   # which sentence gave the positions
            out["nmea.split_seconds"] = str(ep.split)
            out["nmea.gll_ignored"] = str(ep.gll_ignored)
            out.update({f"nmea.position_from.{k}": str(v) for k, v in ep.position_from.items()})
        if self._ubx.old_late:
            out["ubx.late"] = str(self._ubx.old_late)
        out["nmea.epoch_repeats"] = str(self._epochs.late)
