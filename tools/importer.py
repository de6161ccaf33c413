"""``fieldlog import``: build a drive from captures made elsewhere, which carry no host read times.

The bytes are kept exactly (``/raw/*``) and go through the normal pipeline. Host read times have to be
invented, and the rule is stated here because time sync depends on it:

* GPS (NMEA, u-blox UBX, NovAtel OEM ASCII/binary, Septentrio SBF, mixed; auto-detected by ``acquire.gpsport``):
  a message is read 0.2 s after the UTC second of the last time-bearing message at or before it (the typical
  receiver latency; time-bearing: NMEA GGA/RMC/GST/ZDA/GLL, UBX NAV-PVT/NAV-TIMEUTC/NAV-SOL, NovAtel
  BESTPOS/BESTVEL, SBF PVTGeodetic); messages before the first
  one take its time. Reads are the bytes of one such second, cut at message ends. NMEA lines before the first
  date (RMC, ZDA, or a UBX/NovAtel solution) take that date; logs without any date (GGA only) take the
  file's modification date.
* DAQ: both captures are taken to have started together, at T. The log's first epoch E is then the first
  burst that began after T, so T lies in (E - 1 + L, E + L) for a receiver latency L, and the first PPS edge,
  k_pps / fs after T, marks E when k_pps / fs < 1 - L and E + 1 otherwise (L = NMEA_LATENCY_S). Frame k is
  read at that second + 10 ms + (k - k_pps) / fs. A capture without any PPS flag starts at E.
  A latency far from L, or captures started apart, shift the labels by whole seconds: check ``fieldlog info``.
  The sample index k is judged (``acquire.counterjudge``) against the capture's own clock, its bytes at one frame
  per sample period, as the daemon judges it against the host clock: a counter that jumps ahead by more than the
  bytes and a second of slack allow is re-based (a board reset, a jumped register), not taken as a gap, so the
  frames after it keep their times and the PPS after it labels as before.
* CAN (candump ``.log``, Vector ``.asc``, ``.blf`` and the other logs python-can's ``LogReader`` reads): each
  frame is a read of its own (``frames`` records, ``acquire/can.py``) at the log's time stamp, which is also its
  adapter time: absolute times (after 2001, e.g. candump's and an ASC file's ``date``) as they are; relative
  (boot) ones from the UTC given for the first frame (``--start``, or ``--align-to DRIVE``: the drive's first log
  time), else from the GPS log's first second (the captures started together). Without either a relative log is
  refused: a file's modification time says nothing of when the log began. A CAN log imported without a GPS log
  writes no ``/tf_static``: it has no IMU or antenna to place (its ``/vehicle/twist`` is in ``base_link``), so
  the file claims no frame that a drive it is fused with gives.
"""
from __future__ import annotations

import dataclasses
import datetime as _dt
import logging
import os
from pathlib import Path

import numpy as np

from fieldlog.acquire import can, canbus, counterjudge, daq, gnss, gpsport, nmea, novatel, sbf, timesync, ubx
from fieldlog.drive import outputs, recorder
from fieldlog.acquire.pipeline import Pipeline, PipelineConfig, RawRead, in_read_order
from fieldlog.tools.rebuild import RebuildResult

log = logging.getLogger(__name__)
NS = 1_000_000_000
NMEA_LATENCY_S = 0.2
DAQ_READ_BYTES = 512


def gps_reads(data: bytes, fallback_date: _dt.date) -> list[RawRead]:
    """Cut a GPS log (NMEA, u-blox UBX, NovAtel OEM, or a mix: auto-detected) into reads, one per UTC second
    of content, timed by the rule above."""
    framer = gpsport.Framer()
    frames: list[tuple[str, bytes]] = []
    ends: list[int] = []
    for off in range(0, len(data), 65536):
        frames += framer.feed(data[off:off + 65536])
        ends += framer.ends
    date = gnss.in_range(_first_date(frames) or fallback_date)
    dec = nmea.NmeaDecoder()
    sentences = [dec.decode_line(frame) if kind == "nmea" else None for kind, frame in frames]
    gll_time = not any(isinstance(s, (nmea.Gga, nmea.Rmc)) for s in sentences)   # GLL only without better
    times: list[float | None] = []
    last_tod = None
    for (kind, frame), s in zip(frames, sentences):
        t = None
        if kind == "nmea":
            own = getattr(s, "date", None)
            tod = getattr(s, "time_of_day_s", None) if gll_time or not isinstance(s, nmea.Gll) else None
            date = own or date
            if tod is not None and np.isfinite(tod):
                if own is None:
                    date = gnss.roll_over(date, tod, last_tod)
                last_tod = tod
                if date is not None:
                    t = gnss.utc_ns(date, np.floor(tod)) / NS
        else:
            ns = _binary_time_ns(kind, frame)
            d = gnss.date_of_utc_ns(ns) if ns is not None else None
            if d is not None:
                t = float(ns // NS)
                date = d
                last_tod = t % 86400
        times.append(t)
    known = [t for t in times if t is not None]
    if not known:
        names: dict[str, dict[str, int]] = {"nmea": dec.stats.by_type}
        for kind, frame in frames:
            if kind != "nmea":
                name = sbf.block_name(frame) if kind == "sbf" else ubx.UbxDecoder().decode(frame, 0)[0] \
                    if kind == "ubx" else "log"
                names.setdefault(kind, {})[name] = names.get(kind, {}).get(name, 0) + 1
        raise ValueError(f"the GPS log has no message with a UTC time (NMEA GGA/RMC/GST/ZDA/GLL, UBX NAV-PVT/"
                         f"NAV-TIMEUTC/NAV-SOL, NovAtel BESTPOS/BESTVEL, SBF PVTGeodetic): it holds "
                         f"{gpsport.describe(data, frames, names)}")
    cur = known[0]
    groups: dict[float, int] = {}            # second -> stream offset where its read ends
    order: list[float] = []
    for end, t in zip(ends, times):
        cur = t if t is not None else cur
        if cur not in groups:
            order.append(cur)
        groups[cur] = end
    groups[order[-1]] = len(data)            # trailing bytes of no frame go with the last read
    reads = []
    last_ns = 0
    start = 0
    for t in order:
        ns = max(int(round((t + NMEA_LATENCY_S) * NS)), last_ns + 1)
        last_ns = ns
        end = max(groups[t], start)
        reads.append(RawRead("gps", ns, ns, data[start:end]))
        start = end
    return reads


def _binary_time_ns(kind: str, frame: bytes) -> int | None:
    """UTC of a UBX NAV-PVT, NAV-TIMEUTC or NAV-SOL, NovAtel BESTPOS/BESTVEL or SBF PVTGeodetic frame, else
    None."""
    if kind == "ubx":
        _, recs = ubx.UbxDecoder().decode(frame, 0)
        return next((r.utc_ns for r in recs if isinstance(r, (gpsport.Solution, gpsport.EpochTime))), None)
    if kind == "sbf":
        return sbf.solution_time_ns(frame)
    return novatel.log_time_ns(kind, frame)


def _first_date(frames: list[tuple[str, bytes]]) -> _dt.date | None:
    """The first date an RMC or ZDA sentence or a UBX/NovAtel solution gives, for the lines before it."""
    dec = nmea.NmeaDecoder()
    for kind, frame in frames:
        if kind == "nmea":
            d = getattr(dec.decode_line(frame), "date", None)
            if d is not None:
                return d
        else:
            ns = _binary_time_ns(kind, frame)
            if ns is not None:
                return _dt.datetime.fromtimestamp(ns // NS, _dt.timezone.utc).date()
    return None


def daq_reads(data: bytes, fs_hz: float, first_epoch_s: float) -> list[RawRead]:
    """Cut a DAQ capture into reads of DAQ_READ_BYTES, timed by the rule above (by the judged sample index, as
    the pipeline will judge it: a wrong counter does not move the reads' times)."""
    dec = daq.DaqDecoder()
    judge = counterjudge.CounterJudge(dec.stats, counterjudge.JudgeConfig(fs_hz=fs_hz))
    ends: list[int] = []
    k_pps = None
    k_first = None
    counters: set[int] = set()        # the counters of the CRC-valid frames, while they are at most two
    for off in range(0, len(data), DAQ_READ_BYTES):
        chunk = data[off:off + DAQ_READ_BYTES]
        decoded = dec.feed(chunk)
        if len(counters) < 2:
            counters.update(np.unique(decoded.k & 0xFFFFFFFF)[:2].tolist())
        fr = judge.judge(decoded, off, int((off + len(chunk)) / daq.FRAME_SIZE / fs_hz * NS))  # the byte clock
        ends.append(int(fr.k[-1]) if len(fr.k) else -1)
        if len(fr.k) and k_first is None:
            k_first = int(fr.k[0])
        if k_pps is None and np.any(fr.pps):
            k_pps = int(fr.k[np.argmax(fr.pps)])
    if k_first is None and len(counters) == 1:
        raise ValueError(f"the sample counter of its {dec.stats.frames} CRC-valid frames is stuck at {counters.pop()} "
                         f"(it never advances, so no sample can be placed)")
    if k_first is None:
        raise ValueError("the DAQ capture holds no valid frame" + (
            f" ({dec.stats.frames} CRC-valid frames, none whose sample counter the next frames continue)"
            if dec.stats.frames else ""))
    if k_pps is None:
        t_ref, k_ref = first_epoch_s, k_first
    else:
        marks = first_epoch_s if (k_pps - k_first + 1) / fs_hz < 1 - NMEA_LATENCY_S else first_epoch_s + 1
        t_ref, k_ref = marks + 0.01, k_pps
    reads = []
    last_k = k_first
    for i, off in enumerate(range(0, len(data), DAQ_READ_BYTES)):
        last_k = ends[i] if ends[i] >= 0 else last_k
        ns = int(round((t_ref + (last_k - k_ref + 1) / fs_hz) * NS)) + i  # +i keeps equal times ordered
        reads.append(RawRead("daq", ns, ns, data[off:off + DAQ_READ_BYTES]))
    return reads


ABSOLUTE_S = 1e9     # a CAN log time stamp past this (2001-09-09) is UTC, an earlier one relative
LAST_S = float(2**32)  # a CAN log time stamp at or past this (2106-02-07) is not believable


def can_reads(path: str | Path, start_ns: int | None, first_ns: int | None = None) -> list[RawRead]:
    """A CAN log's frames as reads, timed by the rule above (``start_ns``: the GPS log's first second). A frame
    python-can reads but which no bus carries (an id beyond 29 bits or 11 without the extended flag, more than
    64 data bytes, a time stamp not in 0..``LAST_S``) is skipped, counted and logged."""
    import can as pycan

    p = Path(path)
    suffix = "".join(p.suffixes[-2:]).lower() if p.suffix.lower() == ".gz" else p.suffix.lower()
    if not p.is_file():
        raise ValueError(f"{path}: no such file: give a CAN log")
    frames: list[tuple[float, can.CanFrame]] = []
    skipped = 0
    try:
        reader = pycan.LogReader(str(p), **({"relative_timestamp": False} if suffix.startswith(".asc") else {}))
    except ValueError:
        raise ValueError(f"{path}: {suffix or 'no suffix'} is not a CAN log format python-can reads: give a "
                         f"candump .log, Vector .asc or .blf file") from None
    except Exception as e:  # noqa: BLE001 - python-can's readers raise what their parsers meet
        raise _unreadable(path, suffix, e) from None
    try:
        with reader:
            for m in reader:
                t, cid, data = float(m.timestamp), int(m.arbitration_id), bytes(m.data)
                if not (0.0 <= t < LAST_S and 0 <= cid <= (can.CAN_EFF_MASK if m.is_extended_id else 0x7FF)
                        and len(data) <= 64):
                    skipped += 1
                    continue
                frames.append((t, can.CanFrame(cid, data if not m.is_remote_frame else b"", bool(m.is_extended_id),
                                               bool(m.is_remote_frame), bool(m.is_error_frame), bool(m.is_fd),
                                               bool(m.bitrate_switch))))
    except Exception as e:  # noqa: BLE001 - python-can's readers raise what their parsers meet
        raise _unreadable(path, suffix, e) from None
    if skipped:
        log.warning(f"{path}: {skipped} frame{'s' * (skipped > 1)} skipped: an id, a length or a time stamp no bus "
                    f"carries")
    if not frames:
        raise ValueError(f"{path}: the CAN log holds no frame")
    if frames[0][0] >= ABSOLUTE_S:
        offset_ns = 0
    elif first_ns is not None:
        offset_ns = first_ns - int(round(frames[0][0] * NS))
    elif start_ns is not None:
        offset_ns = start_ns
    else:
        raise ValueError(f"{path}: its time stamps are relative (from the logger's boot, first "
                         f"{frames[0][0]:.3f} s): give the UTC of its first frame with --start ISO-TIME, or the drive "
                         "it belongs to with --align-to DRIVE")
    reads = []
    last = -(2**62)
    for t, f in frames:
        ns = max(int(round(t * NS)) + offset_ns, last + 1)
        last = ns
        reads.append(RawRead("can", ns, ns, can.encode_records([f._replace(adapter_ns=ns)])))
    return reads


def _unreadable(path: str | Path, suffix: str, e: Exception) -> ValueError:
    first = str(e).strip().splitlines()[0] if str(e).strip() else ""
    return ValueError(f"{path}: not a readable {suffix} CAN log ({type(e).__name__}: {first}): give a candump "
                      f".log, Vector .asc or .blf file")


def import_captures(gps: str | Path | None, daq_path: str | Path | None, out: str | Path, fs_hz: float = 500.0,
                    pps_mode: str = "flag", can_log: str | Path | None = None,
                    can_bus: canbus.BusConfig | None = None, force: bool = False,
                    can_first_ns: int | None = None) -> RebuildResult:
    """Build ``out`` from a GPS log, a DAQ capture (needs the GPS log) and a CAN log decoded by ``can_bus``
    (its ``wire`` is set to ``frames``; None: recorded, not decoded). ``out`` must be new, unless ``force``.
    A CAN log with boot-relative stamps is placed by ``can_first_ns`` (UTC of its first frame, ns), else at the
    GPS log's start; without either it is refused (ValueError naming it)."""
    outputs.check_new(out, force)
    reads: list[RawRead] = []
    if gps is not None:
        gps_bytes = Path(gps).read_bytes()
        mdate = _dt.datetime.fromtimestamp(os.stat(gps).st_mtime, _dt.timezone.utc).date()
        try:
            reads = gps_reads(gps_bytes, mdate)
        except ValueError as e:
            raise ValueError(f"{gps}: {e}") from None
    elif daq_path is not None:
        raise ValueError("--daq needs --gps: the DAQ capture is timed by the GPS log")
    if can_log is not None:
        start_ns = round(reads[0].mono_ns / NS - NMEA_LATENCY_S) * NS if reads else None
        reads += can_reads(can_log, start_ns, can_first_ns)
        can_bus = dataclasses.replace(can_bus or canbus.BusConfig(), wire="frames")
    if daq_path is not None:
        first_epoch = round(reads[0].mono_ns / NS - NMEA_LATENCY_S)
        try:
            reads += daq_reads(Path(daq_path).read_bytes(), fs_hz, first_epoch)
        except ValueError as e:
            raise ValueError(f"{daq_path}: {e}: give a byte capture of the DAQ board") from None
    reads = in_read_order(reads)
    sync_cfg = timesync.TimeSyncConfig.from_dict({"pps_mode": pps_mode, "fs_hz": fs_hz})
    meta = {"source": "fieldlog import", "gps": str(gps or ""), "daq": str(daq_path or ""), "can": str(can_log or "")}
    with recorder.Recorder(out, flush_interval_s=None, fsync=False, metadata=meta, force=force,
                           behind=True) as rec:
        pipe = Pipeline(rec, sync_cfg=sync_cfg, cfg=PipelineConfig(can=can_bus if can_log is not None else None,
                                                                   tf_static=gps is not None))
        for name, d in pipe.metadata().items():
            rec.add_metadata(name, d)
        pipe.feed_reads(reads)
        pipe.finish()
        rec.add_metadata("acquire.counters", pipe.counters_metadata())
    v = pipe.vehicle
    return RebuildResult(pipe.counters.imu_samples, pipe.counters.gps_epochs, len(reads), pipe.counters,
                         v.stats.frames if v else 0, v.twists if v else 0)
