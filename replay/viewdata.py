"""What ``fieldlog view`` reads of a drive, without rerun: one pass over the drive's blocks, on the second core.

``start`` forks the pass (``replay.ahead``) so that it runs while the caller imports rerun-sdk, which takes
about as long as the pass itself; ``replay.view`` then logs what it returns. The pass decimates ``/imu`` block by
block (``IMU_BLOCK_S``) by means of ``IMU_DECIMATION`` valid samples, carried across blocks, so the 500 Hz rows
are never held whole; the ``LOW_RATE`` topics and the GGA quality of ``/gps/nmea`` (its messages read in the
same pass, undecoded, and only the GGA sentences decoded) are returned whole. The worker yields the fraction of
the drive read after each block (for a progress bar) and returns a :class:`DrivePass`.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Generator, Sequence

import numpy as np

from fieldlog.acquire import nmea
from fieldlog.drive import messages
from fieldlog.drive import reader
from fieldlog.replay import inputs, solutions
from fieldlog.replay.ahead import Ahead
from fieldlog.drive.files import DriveSpec
from fieldlog.replay.inputs import InputMap

IMU_DECIMATION = 10  # 500 Hz -> 50 Hz by block means
IMU_BLOCK_S = 60.0
IMU_FIELDS = ("omega_ib_b", "f_b", "valid")  # the decoded /imu keys the pass reads (its covariances are not copied)
NMEA = "/gps/nmea"  # read undecoded in the pass: only its GGA sentences are decoded

LOW_RATE = {  # drive topics kept whole (fields needed), read in the same pass as /imu
    "/gps/fix": ("lat_deg", "lon_deg", "alt_m", "status", "position_covariance", "covariance_type"),
    "/gps/vel": ("v_n",),
    "/truth/fix": ("lat_deg", "lon_deg", "alt_m"),
    "/truth/vel": ("v_n",),
    "/truth/attitude": ("q_xyzw",),
    "/truth/imu_bias": ("omega_ib_b", "f_b"),
    "/time/sync": ("state", "rate_ppm", "residual_us"),
    "/vehicle/twist": ("v_n",),
    "/truth/vehicle/twist": ("v_n",),
}


@dataclass
class DrivePass:
    """What the viewer shows of the drive itself."""

    imu_t_ns: np.ndarray  # (m,) int64 UTC ns, the mean time of each group of IMU_DECIMATION valid samples
    imu: np.ndarray  # (m, 6) the group means of omega_ib_b (rad/s) and f_b (m/s^2), body RFU
    low: dict[str, dict[str, np.ndarray]]  # LOW_RATE topic -> {field: array}, topics the drive has
    gga: dict[str, np.ndarray]  # gga_quality's


def topic_names(path: DriveSpec) -> dict[str, int]:
    """Topic -> message count of a drive or file."""
    return {t.topic: t.count for t in reader.topic_counts(path)}


def split_fused(paths: Sequence[str]) -> tuple[list[str], list[str]]:
    """``fieldlog view A B C ...``: the first path and every later one without ``/fusion/*/fix`` topics are the
    drive's files (a directory is one of them); files with fused solutions are the fused ones."""
    drive, fused = [paths[0]], []
    for p in paths[1:]:
        is_fused = Path(p).is_file() and any(t.startswith(solutions.PREFIX) and t.endswith("/fix")
                                             for t in topic_names(p))
        (fused if is_fused else drive).append(p)
    return drive, fused


def decimate_means(t_ns: np.ndarray, x: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Means of consecutive groups of ``n`` rows (trailing partial group dropped): (t_mean int64, x_mean)."""
    m = len(t_ns) // n
    t = t_ns[: m * n].reshape(m, n)
    t_mean = t[:, 0] + np.round((t - t[:, :1]).mean(axis=1)).astype(np.int64)
    return t_mean, x[: m * n].reshape(m, n, x.shape[1]).mean(axis=1)


def gga_quality(log_ns: np.ndarray, payloads: messages.Packed) -> list[tuple[int, list[float]]]:
    """The GGA sentences among ``/gps/nmea`` messages (log_time_ns UTC ns and their payloads, in log-time order):
    (log_time_ns, [satellites, hdop, fix_type (GGA quality)]) each, as float (NaN: field empty). Only payloads
    holding ``GGA,`` are decoded."""
    dec = messages.decoder_for(messages.SENTENCE)
    rows = []
    for t, b in zip(log_ns.tolist(), payloads):
        if b"GGA," not in bytes(b):
            continue
        line = dec(bytes(b)).sentence.strip().encode("ascii", "replace")
        gga = nmea.decode_body(nmea.split_checksum(line)[0])
        if isinstance(gga, nmea.Gga):
            rows.append((t, [np.nan if v is None else float(v) for v in (gga.num_sats, gga.hdop, gga.quality)]))
    return rows


def _gga_arrays(rows: list[tuple[int, list[float]]]) -> dict[str, np.ndarray]:
    """``gga_quality``'s rows as arrays: log_time_ns, satellites, hdop, fix_type."""
    x = np.array([r for _, r in rows], dtype=np.float64).reshape(-1, 3)
    return {"log_time_ns": np.array([t for t, _ in rows], dtype=np.int64), "satellites": x[:, 0], "hdop": x[:, 1],
            "fix_type": x[:, 2]}


def drive_pass(drive: DriveSpec, resolve: Callable[[], InputMap | None]) -> Generator[float, None, DrivePass]:
    """The pass (module docstring). ``resolve()``: the inputs of another logger's drive
    (``replay.inputs.resolve``; None: fieldlog's own topics), read as /imu (body RFU), /gps/fix and /gps/vel on
    their header stamps, re-sequenced as ``fuse`` reads them (``replay.inputs.canonical_blocks``)."""
    imap = resolve()
    names = topic_names(drive)
    if imap is not None and not imap.native:  # another logger's topics, under fieldlog's names
        names = {**names, **{n: names.get(t, 0) for t, n in zip(imap.topics, ("/imu", "/gps/fix", "/gps/vel"))}}
    native = imap is None or imap.native
    wanted = [t for t in ("/imu", *LOW_RATE) if names.get(t)]
    nmea_in_pass = native and bool(names.get(NMEA))
    t_first, t_last = reader.span(drive, wanted) or (0, 1)
    parts: dict[str, list[dict[str, np.ndarray]]] = {t: [] for t in LOW_RATE if names.get(t)}
    carry_t, carry_x = np.zeros(0, np.int64), np.zeros((0, 6))
    imu_t, imu_x = [carry_t], [carry_x]
    gga: list[tuple[int, list[float]]] = []
    read = wanted + ([NMEA] if nmea_in_pass else [])
    kept = {"/imu": IMU_FIELDS, **{t: ("valid", *keep) for t, keep in LOW_RATE.items()}}
    blocks = (reader.iter_blocks(drive, read, IMU_BLOCK_S, undecoded=(NMEA,), fields=kept) if native else
              inputs.canonical_blocks(drive, imap, IMU_BLOCK_S, tuple(wanted)))
    for block in blocks:
        sentences = block.data.get(NMEA)
        if sentences is not None:
            gga += gga_quality(sentences["log_time_ns"], sentences["payloads"])
        for topic, keep in LOW_RATE.items():
            d = block.data.get(topic)
            if d is not None and len(d["log_time_ns"]):
                parts[topic].append({k: d[k] for k in ("log_time_ns", "valid", *keep)})
        imu = block.data.get("/imu")
        if imu is not None and len(imu["log_time_ns"]):
            ok = imu["valid"]
            t = np.concatenate([carry_t, imu["log_time_ns"][ok]])
            x = np.concatenate([carry_x, np.hstack([imu["omega_ib_b"][ok], imu["f_b"][ok]])])
            tm, xm = decimate_means(t, x, IMU_DECIMATION)
            carry_t, carry_x = t[len(tm) * IMU_DECIMATION:], x[len(tm) * IMU_DECIMATION:]
            imu_t.append(tm)
            imu_x.append(xm)
        yield min((block.t1_ns - t_first) / max(t_last - t_first, 1), 1.0)
    low = {t: {k: np.concatenate([p[k] for p in ps]) for k in ps[0]} for t, ps in parts.items() if ps}
    if names.get(NMEA) and not nmea_in_pass:  # another logger's drive: its sentences read apart
        log_ns, _, payloads = reader.read_payloads(drive, NMEA)
        gga = gga_quality(log_ns, payloads)
    return DrivePass(np.concatenate(imu_t), np.concatenate(imu_x), low, _gga_arrays(gga))


def start(drive: DriveSpec, resolve: Callable[[], InputMap | None] = lambda: None) -> Ahead[float, DrivePass]:
    """``drive_pass`` begun now on the second core, the drive's inputs resolved there too (``resolve`` raises
    ValueError for a bad input option: raised when the pass is iterated); iterate the result (once) inside its
    ``with`` block. The drive's topics are counted first, here: the pass and the caller both ask for them, and
    the forked worker inherits the count (the opened files keep it) instead of reading the message indexes
    again."""
    topic_names(drive)
    return Ahead(lambda: drive_pass(drive, resolve))
