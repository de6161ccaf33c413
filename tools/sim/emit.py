"""What the hardware puts on the wire: the GPS receiver model, serial byte timing and the host clocks.

Everything here works on the *true* time axis, seconds since the drive start (float64), and turns it into
raw serial reads ``RawRead(port, mono_ns, wall_ns, data)`` exactly as the daemon would see them. The
acquisition pipeline then processes those reads; nothing downstream sees the truth.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Any

import numpy as np

from fieldlog.acquire import gpsport, nmea, novatel, sbf
from fieldlog.acquire.pipeline import RawRead
from fieldlog.drive.tables import ConfigError, from_table
from fieldlog.fusion import earth
from fieldlog.tools.sim.sensors import gauss_markov

NS = 1_000_000_000
NMEA_TICK_NS = 10_000_000  # NMEA times are written to the centisecond
RECEIVERS = ("nmea", "ublox", "novatel", "septentrio")
LEAP_S = 18                # GPS - UTC of the simulated drives (2017 on)
NOVATEL_UNDULATION_M = 47.0


@dataclass
class GpsConfig:
    """Receiver model, from a scenario's ``[gps]`` table. Metres, seconds, m/s.

    Position error per axis = (white + Gauss-Markov) x noise factor, velocity error = white x noise factor.
    ``noise_tau_s`` > 0 turns the "white" position and velocity terms into first-order Gauss-Markov processes of
    the same standard deviation with that correlation time (coloured noise; exact discretisation at the epochs).
    Noise factor = the ``degraded`` factor (the receiver knows: HDOP and GST grow with it) times the
    ``noise_schedule`` scale (it does not: HDOP and GST keep the nominal figures), e.g. the SSR-SCKF paper's
    changing noise ``[[gps.noise_schedule]] start_s = 200.0, end_s = 400.0, scale = 3.0``.
    """

    rate_hz: float = 1.0
    talker: str = "GN"
    baud: int = 115200
    white_h_m: float = 0.5          # white position noise, per horizontal axis (1 sigma)
    white_v_m: float = 0.8
    gm_h_m: float = 1.2            # first-order Gauss-Markov position error, per horizontal axis
    gm_v_m: float = 2.0
    gm_tau_s: float = 300.0
    vel_noise_mps: float = 0.05    # horizontal velocity noise, per axis
    latency_min_s: float = 0.05    # NMEA burst starts 50-500 ms after the second it reports
    latency_max_s: float = 0.5
    latency_jitter_s: float = 0.03
    dropped_sentences: int = 5
    num_sats: int = 12
    hdop: float = 0.8
    uere_m: float = 1.5            # what the receiver believes; reported through GST
    outages: list = field(default_factory=list)    # [[start_s, len_s], ...]: no fix
    degraded: list = field(default_factory=list)   # [[start_s, len_s, factor], ...]: noise and HDOP x factor
    pps_in_outage: bool = True     # the receiver keeps its time pulse from its own clock through outages
    noise_tau_s: float = 0.0       # correlation time of the white_* and vel_noise terms (0: white)
    noise_schedule: list = field(default_factory=list)  # [{start_s, end_s, scale}, ...]: unreported noise scale
    receiver: str = "nmea"         # what the port sends: 'nmea', 'ublox' (GGA + UBX NAV-PVT + TIM-TP), 'novatel',
                                   # 'septentrio' (SBF PVTGeodetic + PosCovGeodetic + VelCovGeodetic + xPPSOffset)
    qerr_step_ns: float = 1e9 / 48e6   # u-blox, Septentrio: the time pulse is put out on this clock grid
    clock_jumps: list = field(default_factory=list)  # [[start_s, len_s, offset_s], ...]: reported time off

    def __post_init__(self) -> None:
        period_ns = NS / self.rate_hz if self.rate_hz > 0 else 0.0
        if not (period_ns >= NMEA_TICK_NS and abs(period_ns / NMEA_TICK_NS - round(period_ns / NMEA_TICK_NS)) < 1e-9):
            raise ValueError(f"[gps] rate_hz: {self.rate_hz!r}: the epoch period must be a whole number of 10 ms "
                             "(NMEA times have centiseconds)")
        if self.receiver not in RECEIVERS:
            raise ValueError(f"[gps] receiver: {self.receiver!r} is not one of {', '.join(RECEIVERS)}")
        if not self.noise_tau_s >= 0:
            raise ValueError(f"[gps] noise_tau_s: must be >= 0 (0: white), got {self.noise_tau_s!r}")
        for i, w in enumerate(self.noise_schedule):
            if not isinstance(w, dict) or set(w) != {"start_s", "end_s", "scale"}:
                raise ValueError(f"[gps] noise_schedule[{i}]: needs exactly start_s, end_s, scale; got {w!r}")
            if not (w["end_s"] > w["start_s"] and w["scale"] > 0):
                raise ValueError(f"[gps] noise_schedule[{i}]: needs end_s > start_s and scale > 0; got {w!r}")

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "GpsConfig":
        """From a scenario's [gps] table. ``quality = "standalone" | "rtk"`` (``GPS_QUALITY``) sets the noise
        figures of that kind of receiver; the table's other keys override."""
        d = dict(d)
        quality = d.pop("quality", None)
        if quality is not None:
            if quality not in GPS_QUALITY:
                raise ConfigError(f"[gps] quality: {quality!r}; one of {', '.join(GPS_QUALITY)}")
            d = {**GPS_QUALITY[quality], **d}
        return from_table(cls, "gps", d)

    def windows(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per time: (fix available, noise factor) from the outage and degraded windows."""
        valid = np.ones(t_s.shape, bool)
        for start, length in self.outages:
            valid &= ~((t_s >= start) & (t_s < start + length))
        factor = np.ones(t_s.shape)
        for start, length, k in self.degraded:
            factor[(t_s >= start) & (t_s < start + length)] = k
        return valid, factor

    def schedule(self, t_s: np.ndarray) -> np.ndarray:
        """Per time: the ``noise_schedule`` scale (1 outside its windows; windows are [start_s, end_s))."""
        scale = np.ones(np.shape(t_s))
        for w in self.noise_schedule:
            scale[(t_s >= w["start_s"]) & (t_s < w["end_s"])] = w["scale"]
        return scale

    def clock_offset_ns(self, t_s: np.ndarray) -> np.ndarray:
        """Per epoch time (s from the start): how far the time the receiver writes in its messages is off
        (``clock_jumps`` windows, [start_s, start_s + len_s)), int64 ns. Its time pulse and when it sends are
        not affected: the messages' time jumps, the pulse and the timing of the bursts do not."""
        off = np.zeros(np.shape(t_s), np.int64)
        for start, length, offset_s in self.clock_jumps:
            off[(t_s >= start) & (t_s < start + length)] = round(offset_s * NS)
        return off

    def epoch_period_ns(self) -> int:
        """The epoch period, ns (a whole number of centiseconds)."""
        return round(NS / self.rate_hz / NMEA_TICK_NS) * NMEA_TICK_NS


# Receiver kinds: ``standalone`` is GpsConfig's defaults (code-phase, a slow 1.2 m Gauss-Markov error);
# ``rtk`` a fixed RTK solution: 2 cm horizontal, 3 cm vertical and 1 cm/s, white.
GPS_QUALITY: dict[str, dict[str, float]] = {
    "standalone": {},
    "rtk": dict(white_h_m=0.02, white_v_m=0.03, gm_h_m=0.0, gm_v_m=0.0, vel_noise_mps=0.01, uere_m=0.03),
}


@dataclass(frozen=True)
class HostClock:
    """The logging laptop: a monotonic clock with its own rate error and a wall clock that is not synced."""

    boot_s: float = 1234.5          # monotonic clock reading at the drive start
    rate_ppm: float = 12.0
    wall_offset_s: float = 0.37      # host wall clock minus true UTC

    def mono_ns(self, t_s: np.ndarray) -> np.ndarray:
        return np.round((self.boot_s + t_s * (1 + self.rate_ppm * 1e-6)) * 1e9).astype(np.int64)

    def wall_ns(self, t_s: np.ndarray, t0_ns: int) -> np.ndarray:
        return t0_ns + np.round((t_s + self.wall_offset_s) * 1e9).astype(np.int64)


def gps_solution(truth, seconds: np.ndarray, cfg: GpsConfig, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Receiver solutions at the true times ``seconds`` (s since start, one per epoch): truth plus error
    (``GpsConfig``). Returns lat/lon (deg), h (m, ellipsoidal), v_n (ENU m/s), valid, factor (the reported
    degradation), scale (the total noise factor), err_enu (m) and the receiver's own sigma."""
    n = len(seconds)
    ts = truth.evaluate(seconds)
    valid, factor = cfg.windows(seconds)
    z = rng.standard_normal((n, 3))
    z0 = rng.standard_normal(3)
    if n:
        z[0] = z0
    gm = gauss_markov(seconds, cfg.gm_tau_s, z) * np.array([cfg.gm_h_m, cfg.gm_h_m, cfg.gm_v_m])
    white = rng.standard_normal((n, 3))
    vel = rng.standard_normal((n, 3))
    if cfg.noise_tau_s > 0:
        white = gauss_markov(seconds, cfg.noise_tau_s, white)
        vel = gauss_markov(seconds, cfg.noise_tau_s, vel)
    white = white * np.array([cfg.white_h_m, cfg.white_h_m, cfg.white_v_m])
    scale = factor * cfg.schedule(seconds)
    err_enu = (gm + white) * scale[:, None]
    r_m, r_n = earth.principal_radii(ts.lat, ts.h)
    lat = ts.lat + err_enu[:, 1] / r_m
    lon = ts.lon + err_enu[:, 0] / (r_n * np.cos(ts.lat))
    h = ts.h + err_enu[:, 2]
    v_n = ts.v_n + vel * cfg.vel_noise_mps * scale[:, None]
    sigma_h = np.hypot(cfg.white_h_m, cfg.gm_h_m) * factor
    sigma_v = np.hypot(cfg.white_v_m, cfg.gm_v_m) * factor
    return dict(lat_deg=np.degrees(lat), lon_deg=np.degrees(lon), h=h, v_n=v_n, valid=valid, factor=factor,
                scale=scale, err_enu=err_enu, sigma_h=sigma_h, sigma_v=sigma_v)


def pulse_errors(n: int, cfg: GpsConfig, rng: np.random.Generator) -> np.ndarray | None:
    """u-blox and Septentrio: how late each time pulse comes (s), the quantisation of its clock grid (uniform over
    one step); u-blox reports it before the pulse (TIM-TP qErr), Septentrio after it (xPPSOffset). None for the
    other receivers (their pulse error is the clock model's jitter)."""
    if cfg.receiver not in ("ublox", "septentrio"):
        return None
    return rng.uniform(-0.5, 0.5, n) * cfg.qerr_step_ns * 1e-9


def nmea_bursts(sol: dict[str, np.ndarray], utc_ns: np.ndarray, cfg: GpsConfig,
                rng: np.random.Generator, qerr_s: np.ndarray | None = None,
                shown_ns: np.ndarray | None = None) -> tuple[np.ndarray, list[bytes]]:
    """One burst of messages per epoch in the receiver's protocol (``cfg.receiver``). Returns the true time each
    message starts on the wire, s from the first epoch, and the messages (NMEA with CRLF). ``utc_ns`` (int64) is
    the UTC of each epoch (fractional seconds at rates above 1 Hz, written with centisecond times in NMEA).
    ``qerr_s[j]``: the error of the pulse of the j-th UTC second after the first epoch's (u-blox sends it in
    TIM-TP before that pulse). A burst never starts before the previous one ended. ``shown_ns``: the time the
    receiver writes in each epoch's messages, when its clock is off (default ``utc_ns``)."""
    n = len(utc_ns)
    shown = utc_ns if shown_ns is None else shown_ns
    base = rng.uniform(cfg.latency_min_s, cfg.latency_max_s - 0.1)
    latency = np.clip(base + rng.standard_normal(n) * cfg.latency_jitter_s, cfg.latency_min_s, cfg.latency_max_s - 0.06)
    sentences: list[bytes] = []
    starts: list[float] = []
    t_free = -np.inf
    for i in range(n):
        sec, sub_ns = divmod(int(shown[i]), NS)
        dt = datetime.fromtimestamp(sec, tz=timezone.utc)
        tod = dt.hour * 3600 + dt.minute * 60 + dt.second + (sub_ns / NS if sub_ns else 0)
        ok = bool(sol["valid"][i])
        hdop = cfg.hdop * sol["factor"][i]
        vE, vN, _ = sol["v_n"][i]
        speed = float(np.hypot(vE, vN))
        course = float(np.arctan2(vE, vN) % (2 * np.pi))
        lat, lon, h = float(sol["lat_deg"][i]), float(sol["lon_deg"][i]), float(sol["h"][i])
        if cfg.receiver == "ublox":
            # (the first epoch moved by the same offset: TIM-TP still describes this epoch's next pulse)
            burst = _ublox_burst(sol, i, int(shown[i]), tod, lat, lon, h, hdop, ok, cfg, qerr_s,
                                 int(utc_ns[0] + shown[i] - utc_ns[i]))
        elif cfg.receiver == "novatel":
            burst = _novatel_burst(sol, i, int(shown[i]), lat, lon, h, ok, cfg)
        elif cfg.receiver == "septentrio":
            burst = _septentrio_burst(sol, i, int(shown[i]), lat, lon, h, ok, cfg, qerr_s,
                                      int(utc_ns[0] + shown[i] - utc_ns[i]))
        else:
            burst = [
                nmea.format_gga(cfg.talker, tod, lat, lon, 1 if ok else 0, cfg.num_sats if ok else 0, hdop, h, 0.0,
                                valid=ok),
                nmea.format_rmc(cfg.talker, tod, dt.date(), lat, lon, speed, course, valid=ok),
                nmea.format_vtg(cfg.talker, course, speed, valid=ok),
                nmea.format_gst(cfg.talker, tod, float(sol["sigma_h"][i]), float(sol["sigma_h"][i]),
                                float(sol["sigma_h"][i]), float(sol["sigma_v"][i]), valid=ok),
                nmea.format_zda(cfg.talker, tod, dt.date()),
            ]
        t = max((int(utc_ns[i]) - int(utc_ns[0])) / NS + latency[i], t_free)
        for s in burst:
            starts.append(t)
            sentences.append(s)
            t += len(s) * 10.0 / cfg.baud
        t_free = t
    keep = np.ones(len(sentences), bool)
    if cfg.dropped_sentences:
        keep[rng.choice(len(sentences), size=min(cfg.dropped_sentences, len(sentences)), replace=False)] = False
    starts_a = np.asarray(starts)
    return starts_a[keep], [s for s, k in zip(sentences, keep) if k]


def _gps_week_ms(utc_ns: int) -> tuple[int, int]:
    """GPS week and milliseconds of week of a UTC time (GPS - UTC = LEAP_S)."""
    gps_ms = (utc_ns // 1_000_000) + (LEAP_S - gpsport.GPS_EPOCH_S) * 1000
    week, ms = divmod(gps_ms, gpsport.WEEK_S * 1000)
    return int(week), int(ms)


def _ublox_burst(sol: dict[str, np.ndarray], i: int, utc_ns: int, tod: float, lat: float, lon: float, h: float,
                 hdop: float, ok: bool, cfg: GpsConfig, qerr_s: np.ndarray | None, first_ns: int) -> list[bytes]:
    """What a u-blox port sends for an epoch: GGA, NAV-PVT, and on whole seconds TIM-TP for the next pulse."""
    from pyubx2 import UBXMessage

    dt = datetime.fromtimestamp(utc_ns // NS, tz=timezone.utc)
    week, ms = _gps_week_ms(utc_ns)
    vE, vN, vU = (float(v) for v in sol["v_n"][i])
    sacc = cfg.vel_noise_mps * float(sol["factor"][i])
    pvt = UBXMessage("NAV", "NAV-PVT", 0, iTOW=ms, year=dt.year, month=dt.month, day=dt.day, hour=dt.hour,
                     min=dt.minute, second=dt.second, validDate=1, validTime=1, fullyResolved=1,
                     nano=int(utc_ns % NS), fixType=3 if ok else 0, gnssFixOk=int(ok),
                     numSV=cfg.num_sats if ok else 0, lat=lat, lon=lon, height=round(h * 1000),
                     hMSL=round(h * 1000), hAcc=round(float(sol["sigma_h"][i]) * 1000),
                     vAcc=round(float(sol["sigma_v"][i]) * 1000), velN=round(vN * 1000), velE=round(vE * 1000),
                     velD=round(-vU * 1000), gSpeed=round(np.hypot(vE, vN) * 1000), sAcc=round(sacc * 1000),
                     pDOP=hdop * 1.5)
    out = [nmea.format_gga(cfg.talker, tod, lat, lon, 1 if ok else 0, cfg.num_sats if ok else 0, hdop, h, 0.0,
                           valid=ok), pvt.serialize()]
    if utc_ns % NS == 0 and qerr_s is not None:
        j = (utc_ns - first_ns) // NS + 1
        if 0 <= j < len(qerr_s):
            w, ms_next = _gps_week_ms(utc_ns + NS)
            out.append(UBXMessage("TIM", "TIM-TP", 0, towMS=ms_next, towSubMS=0, qErr=round(qerr_s[j] * 1e12),
                                  week=w, timeBase=0, utc=1).serialize())
    return out


def _novatel_burst(sol: dict[str, np.ndarray], i: int, utc_ns: int, lat: float, lon: float, h: float, ok: bool,
                   cfg: GpsConfig) -> list[bytes]:
    """What a NovAtel port logging BESTPOSA and BESTVELA ontime (and TIMEA every 10 s) sends for an epoch."""
    week, ms = _gps_week_ms(utc_ns)
    sd_h, sd_v = float(sol["sigma_h"][i]), float(sol["sigma_v"][i])
    out = [novatel.format_bestposa(week, ms / 1000, lat, lon, h, NOVATEL_UNDULATION_M, (sd_h, sd_h, sd_v),
                                   cfg.num_sats if ok else 0, valid=ok),
           novatel.format_bestvela(week, ms / 1000, tuple(float(v) for v in sol["v_n"][i]), valid=ok)]
    if utc_ns % (10 * NS) == 0:
        dt = datetime.fromtimestamp(utc_ns // NS, tz=timezone.utc)
        out.append(novatel.format_timea(week, ms / 1000, LEAP_S, (dt.year, dt.month, dt.day, dt.hour, dt.minute,
                                                                  dt.second * 1000)))
    return out


def _septentrio_burst(sol: dict[str, np.ndarray], i: int, utc_ns: int, lat: float, lon: float, h: float, ok: bool,
                      cfg: GpsConfig, qerr_s: np.ndarray | None, first_ns: int) -> list[bytes]:
    """What a Septentrio port logging PVTGeodetic, PosCovGeodetic and VelCovGeodetic on each epoch sends, with
    ReceiverTime and, after the pulse of that second, xPPSOffset on whole seconds (SBF blocks by pysbf2)."""
    from pysbf2 import SBFMessage

    week, ms = _gps_week_ms(utc_ns)
    dnu = sbf.DNU_FLOAT
    sd_h, sd_v = float(sol["sigma_h"][i]), float(sol["sigma_v"][i])
    sacc = cfg.vel_noise_mps * float(sol["factor"][i])
    vE, vN, vU = (float(v) for v in sol["v_n"][i]) if ok else (dnu, dnu, dnu)
    mode, err = (1, 0) if ok else (0, 1)
    pvt = SBFMessage("PVTGeodetic", TOW=ms, WNc=week, Type=mode, Error=err,
                     Latitude=np.radians(lat) if ok else dnu, Longitude=np.radians(lon) if ok else dnu,
                     Height=h if ok else dnu, Undulation=0.0, Vn=vN, Ve=vE, Vu=vU, COG=dnu, NrSV=cfg.num_sats if ok else 0,
                     HAccuracy=round(sd_h * sbf.TWO_SQRT2 * 100) if ok else sbf.HACC_DNU_CM,
                     VAccuracy=round(sd_v * 2 * 100) if ok else sbf.HACC_DNU_CM, scaling=False)
    cov = (sd_h**2, sd_h**2, sd_v**2) if ok else (dnu, dnu, dnu)
    pos = SBFMessage("PosCovGeodetic", TOW=ms, WNc=week, Type=mode, Error=err, Cov_latlat=cov[0],
                     Cov_lonlon=cov[1], Cov_hgthgt=cov[2], scaling=False)
    vcov = (sacc**2,) * 3 if ok else (dnu, dnu, dnu)
    vel = SBFMessage("VelCovGeodetic", TOW=ms, WNc=week, Type=mode, Error=err, Cov_VnVn=vcov[0], Cov_VeVe=vcov[1],
                     Cov_VuVu=vcov[2], scaling=False)
    out = [pvt.serialize(), pos.serialize(), vel.serialize()]
    if utc_ns % NS == 0:
        dt = datetime.fromtimestamp(utc_ns // NS, tz=timezone.utc)
        out.append(SBFMessage("ReceiverTime", TOW=ms, WNc=week, UTCYear=dt.year % 100, UTCMonth=dt.month,
                              UTCDay=dt.day, UTCHour=dt.hour, UTCMin=dt.minute, UTCSec=dt.second, DeltaLS=LEAP_S,
                              SyncLevel=7, scaling=False).serialize())
        j = (utc_ns - first_ns) // NS
        if qerr_s is not None and 0 <= j < len(qerr_s):
            out.append(SBFMessage("xPPSOffset", TOW=ms, WNc=week, SyncAge=0, TimeScale=sbf.TIME_SCALE_GPS,
                                  Offset=float(qerr_s[j] * 1e9), scaling=False).serialize())
    return out


def serial_reads(port: str, byte_start_s: np.ndarray, chunks: list[bytes] | bytes, chunk_len: int | None,
                 baud: int, read_period_s: tuple[float, float], clock: HostClock, t0_ns: int,
                 rng: np.random.Generator) -> list[RawRead]:
    """Cut a byte stream into host reads, as a USB-serial adapter delivers it.

    ``byte_start_s`` is the true time each unit (frame or sentence) starts on the wire; units are either the
    fixed-length ``chunk_len`` pieces of ``chunks`` (bytes) or the variable pieces of ``chunks`` (list).
    Bytes arrive at ``baud`` (10 bits each). The host reads every ``read_period_s`` (uniform range) and gets
    every byte that has fully arrived by then; a unit may be split between reads.
    """
    if isinstance(chunks, bytes):
        data = chunks
        lens = np.full(len(byte_start_s), chunk_len, np.int64)
    else:
        data = b"".join(chunks)
        lens = np.fromiter((len(c) for c in chunks), np.int64, len(chunks))
    offsets = np.concatenate(([0], np.cumsum(lens)))
    byte_s = 10.0 / baud
    t_end = byte_start_s[-1] + lens[-1] * byte_s
    n_reads = int(t_end / read_period_s[0]) + 16
    reads_t = byte_start_s[0] + np.cumsum(rng.uniform(read_period_s[0], read_period_s[1], n_reads))
    reads_t = reads_t[: np.searchsorted(reads_t, t_end) + 1]
    # bytes of the unit in progress at each read time
    unit = np.searchsorted(byte_start_s, reads_t, side="right") - 1
    arrived = np.minimum(np.floor((reads_t - byte_start_s[unit]) / byte_s).astype(np.int64), lens[unit])
    cut = offsets[unit] + arrived
    cut = np.maximum.accumulate(cut)
    got = np.flatnonzero(np.diff(cut, prepend=0) > 0)            # the reads that return bytes
    ends = cut[got].tolist()
    return [RawRead(port, m, w, data[a:b]) for a, b, m, w in zip([0] + ends[:-1], ends,
                                                                   clock.mono_ns(reads_t[got]).tolist(),
                                                                   clock.wall_ns(reads_t[got], t0_ns).tolist())]
