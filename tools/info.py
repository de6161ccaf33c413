"""``fieldlog info``: what a drive holds and how good its timing is."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fieldlog.acquire import messages
from fieldlog.replay import reader
from fieldlog.tools.rebuild import read_metadata_records

NS = 1_000_000_000


@dataclass
class TimingError:
    """IMU time-stamp error against ``/truth/imu`` (simulated drives), after the first lock. Microseconds."""

    samples: int
    rms_us: float
    max_abs_us: float
    mean_us: float


@dataclass
class DriveInfo:
    path: Path
    duration_s: float
    topics: list[reader.TopicInfo]
    sync_states: dict[str, float] = field(default_factory=dict)   # fraction of /time/sync records per state
    rate_ppm: float = float("nan")
    residual_us: float = float("nan")
    first_lock_ns: int | None = None
    timing: TimingError | None = None
    imu_gaps: int = 0
    imu_longest_gap_s: float = 0.0
    gps_missing_epochs: int = 0
    gps_no_fix: int = 0
    counters: dict[str, str] = field(default_factory=dict)
    drive: dict[str, str] = field(default_factory=dict)
    port_events: list[dict[str, str]] = field(default_factory=list)   # the daemon's lost/back port records


def timing_error(imu_ns: np.ndarray, truth_ns: np.ndarray, first_lock_ns: int | None) -> TimingError | None:
    """Pair each /imu stamp with its true sample time: one to one when both hold every sample (the simulator
    writes one truth record per DAQ frame, in order), otherwise with the nearest truth time."""
    if len(imu_ns) == 0 or len(truth_ns) == 0:
        return None
    if len(imu_ns) == len(truth_ns):
        err = (imu_ns - truth_ns).astype(np.float64)
    else:
        i = np.clip(np.searchsorted(truth_ns, imu_ns), 1, len(truth_ns) - 1)
        j = np.where(np.abs(truth_ns[i - 1] - imu_ns) < np.abs(truth_ns[i] - imu_ns), i - 1, i)
        err = (imu_ns - truth_ns[j]).astype(np.float64)
    if first_lock_ns is not None:
        err = err[imu_ns >= first_lock_ns]
    if len(err) == 0:
        return None
    err_us = err / 1e3
    return TimingError(len(err_us), float(np.sqrt(np.mean(err_us**2))), float(np.max(np.abs(err_us))),
                       float(np.mean(err_us)))


def drive_info(path: str | Path) -> DriveInfo:
    path = Path(path)
    tops = reader.topics(path)
    by = {t.topic: t for t in tops}
    first = min((t.first_ns for t in tops if t.count), default=0)
    last = max((t.last_ns for t in tops if t.count), default=0)
    records = read_metadata_records(path)
    meta = dict(records)
    info = DriveInfo(path, (last - first) / NS, tops, counters=meta.get("acquire.counters", {}),
                     drive=meta.get("drive", {}),
                     port_events=[d for name, d in records if name == "acquire.port_event"])

    if "/time/sync" in by and by["/time/sync"].count:
        ts = reader.read_topic(path, "/time/sync")
        states = np.asarray(ts["state"])
        names = {messages.TIMESYNC_FREE: "free", messages.TIMESYNC_HOLDOVER: "holdover",
                 messages.TIMESYNC_LOCKED: "locked"}
        info.sync_states = {names.get(int(s), str(s)): float(np.mean(states == s)) for s in np.unique(states)}
        locked = states == messages.TIMESYNC_LOCKED
        if locked.any():
            info.first_lock_ns = int(np.asarray(ts["stamp_ns"])[locked][0])
            info.rate_ppm = float(np.median(np.asarray(ts["rate_ppm"])[locked]))
            info.residual_us = float(np.median(np.asarray(ts["residual_us"])[locked]))

    imu_ns = None
    if "/imu" in by and by["/imu"].count:
        imu_ns = np.asarray(reader.read_topic(path, "/imu")["stamp_ns"])
        fs_nominal = 1.0 / np.median(np.diff(imu_ns) / NS) if len(imu_ns) > 1 else 0.0
        if fs_nominal:
            gaps = np.diff(imu_ns) / NS > 1.5 / fs_nominal
            info.imu_gaps = int(gaps.sum())
            info.imu_longest_gap_s = float(np.max(np.diff(imu_ns)) / NS) if gaps.any() else 0.0
    if "/gps/fix" in by and by["/gps/fix"].count:
        fix = reader.read_topic(path, "/gps/fix")
        st = np.asarray(fix["stamp_ns"])
        info.gps_no_fix = int(np.count_nonzero(np.asarray(fix["status"]) < 0))
        if len(st) > 2:
            dt = np.diff(st) / NS
            period = np.median(dt)
            info.gps_missing_epochs = int(np.sum(np.round(dt / period) - 1))
    if imu_ns is not None and "/truth/imu" in by:
        truth_ns = np.asarray(reader.read_topic(path, "/truth/imu")["stamp_ns"])
        info.timing = timing_error(imu_ns, truth_ns, info.first_lock_ns)
    return info


def format_info(info: DriveInfo) -> str:
    lines = [f"drive     {info.path}", f"duration  {info.duration_s:.1f} s"]
    if info.drive:
        lines.append("source    " + ", ".join(f"{k}={v}" for k, v in info.drive.items()))
    lines.append("")
    lines.append(f"{'topic':<22} {'type':<46} {'count':>9} {'rate Hz':>9}")
    for t in info.topics:
        span = (t.last_ns - t.first_ns) / NS
        rate = (t.count - 1) / span if t.count > 1 and span > 0 else 0.0
        lines.append(f"{t.topic:<22} {t.type:<46} {t.count:>9} {rate:>9.2f}")
    lines.append("")
    if info.sync_states:
        states = ", ".join(f"{k} {v * 100:.1f} %" for k, v in info.sync_states.items())
        lines.append(f"time sync {states}; DAQ clock {info.rate_ppm:+.3f} ppm; fit residual {info.residual_us:.1f} us")
    else:
        lines.append("time sync no /time/sync records")
    if info.timing:
        t = info.timing
        lines.append(f"timestamp error vs truth after first lock: RMS {t.rms_us:.2f} us, max {t.max_abs_us:.2f} us, "
                     f"mean {t.mean_us:+.2f} us over {t.samples} samples")
    lines.append(f"gaps      IMU {info.imu_gaps} (longest {info.imu_longest_gap_s:.3f} s); "
                 f"GPS epochs missing {info.gps_missing_epochs}, without fix {info.gps_no_fix}")
    for ev in info.port_events:
        lines.append("port      " + ", ".join(f"{k}={v}" for k, v in ev.items()))
    if info.counters:
        keys = ["daq.bytes_skipped", "daq.resyncs", "daq.bad_crc", "daq.counter_gaps", "daq.lost_frames",
                "nmea.bad_checksum", "nmea.unknown", "nmea.proprietary", "pps_edges", "pps_rejected"]
        shown = [f"{k}={info.counters[k]}" for k in keys if k in info.counters]
        lines.append("counters  " + ", ".join(shown))
    return "\n".join(lines)
