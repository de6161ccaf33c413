"""NovAtel OEM logs: BESTPOS, BESTVEL and TIME, ASCII ('#...A') and binary (0xAA 0x44 0x12), from checked
frames (``gpsport.Framer``: CRC-32 verified) to ``gpsport.Solution`` records.

Time: the header's GPS week and seconds, converted to UTC with GPS - UTC from the TIME log when the receiver
sent one (its utc_offset), else from the leap-second table. A header whose time status is UNKNOWN gives no
epoch. BESTPOS and BESTVEL of the same header time make one solution, emitted when both are in or when a log
of another time arrives (``flush`` at the end).

Position: lat/lon, ellipsoidal height = hgt (above mean sea level) + undulation; variances from the lat/lon/hgt
standard deviations (NovAtel's 1-sigma). Velocity: horizontal speed, track over ground and vertical speed;
BESTVEL carries no accuracy, so its variance is NaN here (the pipeline's configured default applies).

Our own decoder: no maintained Python library reads NovAtel OEM logs from a mixed stream (NovAtel's EDIE is
a C++ SDK with Python bindings of its whole message database, far more than three logs need); the three
layouts are fixed and documented in the OEM7 Commands and Logs manual.
"""
from __future__ import annotations

import datetime as _dt
import math
import struct
from dataclasses import dataclass, field

from fieldlog.acquire import gnss, gpsport, numbers

NS = 1_000_000_000
BESTPOS_ID, BESTVEL_ID, TIME_ID = 42, 99, 101
HEADER_LEN = 28
UNKNOWN_TIME = 20
# position type -> GGA-like quality (0 none, 1 single, 2 differential, 4 RTK fixed, 5 RTK float, 6 propagated,
# 7 fixed by command); the enum values of the OEM7 manual, table "Position or Velocity Type"
POS_TYPES = {"NONE": (0, 0), "FIXEDPOS": (1, 7), "FIXEDHEIGHT": (2, 7), "DOPPLER_VELOCITY": (8, 1),
             "SINGLE": (16, 1), "PSRDIFF": (17, 2), "WAAS": (18, 2), "PROPAGATED": (19, 6),
             "L1_FLOAT": (32, 5), "IONOFREE_FLOAT": (33, 5), "NARROW_FLOAT": (34, 5), "L1_INT": (48, 4),
             "WIDE_INT": (49, 4), "NARROW_INT": (50, 4), "RTK_DIRECT_INS": (51, 4), "INS_SBAS": (52, 2),
             "INS_PSRSP": (53, 1), "INS_PSRDIFF": (54, 2), "INS_RTKFLOAT": (55, 5), "INS_RTKFIXED": (56, 4),
             "PPP_CONVERGING": (68, 1), "PPP": (69, 2), "OPERATIONAL": (70, 1), "WARNING": (71, 1),
             "OUT_OF_BOUNDS": (72, 0), "PPP_BASIC_CONVERGING": (77, 1), "PPP_BASIC": (78, 2)}
_QUALITY_BY_NUMBER = {n: q for n, q in POS_TYPES.values()}
_TIME_STATUS = {"UNKNOWN": UNKNOWN_TIME}


@dataclass
class NovatelStats:
    by_type: dict[str, int] = field(default_factory=dict)
    undecodable: int = 0
    no_time: int = 0
    bad_fields: int = 0       # values refused by the range checks (acquire/numbers.py)


@dataclass
class _Pos:
    quality: int
    lat: float
    lon: float
    h: float
    sd: tuple[float, float, float]      # E, N, U
    sats: int


class NovatelDecoder:
    """Checked NovAtel frames in, ``gpsport.Solution`` out. Never raises."""

    def __init__(self) -> None:
        self.stats = NovatelStats()
        self.leap_s: int | None = None    # GPS - UTC from the TIME log
        self._key: tuple[int, int] | None = None
        self._pos: _Pos | None = None
        self._vel: tuple[float, float, float] | None = None
        self._mono = 0

    def decode(self, kind: str, frame: bytes, mono_ns: int) -> tuple[str, list]:
        """(log name, records) of one frame: the solutions it completes, and an ``EpochTime`` when it starts an
        epoch; ``kind`` is 'novatel' (ASCII) or 'novatel_bin'."""
        t = numbers.Tally()
        try:
            parsed = _ascii(frame, t) if kind == "novatel" else _binary(frame, t)
        except (ValueError, IndexError, struct.error, UnicodeDecodeError):
            parsed = None
        self.stats.bad_fields += t.bad
        if parsed is None:
            self.stats.undecodable += 1
            return "?", []
        name, status, week, ms, body = parsed
        name = name if name in _NAMES.values() else "other"      # the counters stay bounded
        self.stats.by_type[name] = self.stats.by_type.get(name, 0) + 1
        if name == "TIME":
            if body is not None:
                self.leap_s = body
            return name, []
        if name not in ("BESTPOS", "BESTVEL") or body is None:
            return name, []
        if status == UNKNOWN_TIME or week is None or ms is None:
            self.stats.no_time += 1
            return name, []
        out: list = []
        key = (week, ms)
        if key != self._key:
            out = self.flush()
            self._key, self._mono = key, mono_ns
            out.append(gpsport.EpochTime(utc_ns_of(week, ms, self.leap_s)))
        if name == "BESTPOS":
            self._pos = body
        else:
            self._vel = body
        if self._pos is not None and self._vel is not None:
            out += self.flush()
        return name, out

    def flush(self) -> list[gpsport.Solution]:
        """The epoch in progress, if it has a position."""
        key, pos, vel = self._key, self._pos, self._vel
        self._key, self._pos, self._vel = None, None, None
        if key is None or pos is None:
            return []
        week, ms = key
        utc_ns = utc_ns_of(week, ms, self.leap_s)
        fix = (not gnss.no_fix_reason(pos.quality, pos.sats, None)
               and all(math.isfinite(x) for x in (pos.lat, pos.lon, pos.h)))
        nan = math.nan
        return [gpsport.Solution(
            utc_ns=utc_ns, fix=fix, quality=pos.quality if fix else 0, num_sats=pos.sats, lat_deg=pos.lat,
            lon_deg=pos.lon, h_m=pos.h, pos_var=tuple(s * s for s in pos.sd),
            pos_var_known=all(math.isfinite(s) for s in pos.sd),
            vel_enu=vel if fix else None, vel_var=(nan, nan, nan), first_mono_ns=self._mono, source="novatel")]


def utc_ns_of(week: int, ms: int, leap_s: int | None) -> int:
    """UTC (ns since the Unix epoch) of GPS week and milliseconds of week; GPS - UTC from the table if None."""
    if leap_s is None:
        gps_day = _dt.datetime.fromtimestamp(gpsport.gps_to_utc_s(week, ms / 1000, 0), _dt.timezone.utc).date()
        leap_s = gpsport.leap_seconds(gps_day)
    return (gpsport.GPS_EPOCH_S + week * gpsport.WEEK_S - leap_s) * NS + ms * 1_000_000


def log_time_ns(kind: str, frame: bytes, leap_s: int | None = None) -> int | None:
    """UTC of a BESTPOS/BESTVEL frame's header time, or None (another log, unknown time, unreadable)."""
    try:
        name, status, week, ms, _ = (_ascii if kind == "novatel" else _binary)(frame, numbers.Tally())
    except (ValueError, IndexError, struct.error, UnicodeDecodeError):
        return None
    if name not in ("BESTPOS", "BESTVEL") or status == UNKNOWN_TIME or week is None or ms is None:
        return None
    return utc_ns_of(week, ms, leap_s)


MAX_LEAP_S = 1000           # |GPS - UTC| beyond this is not a leap-second count (18 s since 2017)


def _week_ms(week: object, seconds: object, t: numbers.Tally) -> tuple[int | None, int | None]:
    """The header's GPS week (1..``gnss.WEEK_MAX``) and milliseconds of week, None where out of range."""
    sec = t.real(seconds, 0.0, gpsport.WEEK_S - 0.001)
    return t.whole(week, 1, gnss.WEEK_MAX), None if sec != sec else round(sec * 1000)


def _pos(sol_stat: bool, quality: int, lat: object, lon: object, hgt: object, und: object,
         sd: tuple[object, object, object], sats: object, t: numbers.Tally) -> _Pos:
    """BESTPOS fields, range-checked (NaN / 0 where not); quality 0 unless the solution was computed."""
    lat_deg, lon_deg = t.real(lat, -90, 90), t.real(lon, -180, 180)
    h = t.real(hgt, -1e5, 1e8) + t.real(und, -1e3, 1e3)
    return _Pos(quality if sol_stat else 0, lat_deg, lon_deg, h, tuple(t.real(x, 0, 1e7) for x in sd),
                t.whole(sats, 0, 255) or 0)


def _vel(sol_stat: bool, hor: object, trk_deg: object, vert: object,
         t: numbers.Tally) -> tuple[float, float, float] | None:
    if not sol_stat:
        return None
    speed, trk = t.real(hor, -1e5, 1e5), math.radians(t.real(trk_deg, -360, 360))
    return (speed * math.sin(trk), speed * math.cos(trk), t.real(vert, -1e5, 1e5))


def _leap(utc_offset: object, valid: bool, t: numbers.Tally) -> int | None:
    """GPS - UTC (s) from the TIME log's UTC offset, None when not valid or out of range."""
    off = t.real(utc_offset, -MAX_LEAP_S, MAX_LEAP_S)
    return -round(off) if valid and off == off else None


def _ascii(frame: bytes, t: numbers.Tally):
    """(name, time status, week, ms of week, body) of an ASCII log; body None when the log is not valid;
    week and ms None when out of range. Values are range-checked (``t`` counts the bad ones)."""
    text = frame[1:frame.rindex(b"*")].decode("ascii")
    header, _, rest = text.partition(";")
    h = header.split(",")
    name = h[0][:-1] if h[0].endswith("A") else h[0]
    status = _TIME_STATUS.get(h[4], 0)
    week, ms = _week_ms(h[5], h[6], t)
    f = rest.split(",")
    body = None
    if name == "BESTPOS":
        q = POS_TYPES.get(f[1], (0, 0))[1]
        body = _pos(f[0] == "SOL_COMPUTED", q, f[2], f[3], f[4], f[5], (f[8], f[7], f[9]), f[14], t)
    elif name == "BESTVEL":
        body = _vel(f[0] == "SOL_COMPUTED", f[4], f[5], f[6], t)
    elif name == "TIME":
        body = _leap(f[3], f[10] == "VALID", t)
    return name, status, week, ms, body


_NAMES = {BESTPOS_ID: "BESTPOS", BESTVEL_ID: "BESTVEL", TIME_ID: "TIME"}


def _binary(frame: bytes, t: numbers.Tally):
    """As ``_ascii`` for a binary log."""
    hl = frame[3]
    msg_id, = struct.unpack_from("<H", frame, 4)
    status = frame[13]
    week, ms = struct.unpack_from("<HI", frame, 14)
    week, ms = _week_ms(week, ms / 1000, t)
    name = _NAMES.get(msg_id, "other")
    b = hl
    body = None
    if msg_id == BESTPOS_ID:
        sol, ptype, lat, lon, hgt, und, _datum, sd_lat, sd_lon, sd_h = struct.unpack_from("<IIdddfIfff", frame, b)
        sats = frame[b + 65]
        body = _pos(sol == 0, _QUALITY_BY_NUMBER.get(ptype, 0), lat, lon, hgt, und, (sd_lon, sd_lat, sd_h), sats, t)
    elif msg_id == BESTVEL_ID:
        sol, _vt, _lat, _age, hor, trk, vert = struct.unpack_from("<IIffddd", frame, b)
        body = _vel(sol == 0, hor, trk, vert, t)
    elif msg_id == TIME_ID:
        _cs, _off, _std, utc_off = struct.unpack_from("<Iddd", frame, b)
        utc_status, = struct.unpack_from("<I", frame, b + 40)
        body = _leap(utc_off, utc_status == 1, t)
    return name, status, week, ms, body


# ---------------------------------------------------------------------------------------------- generators

def ascii_log(name: str, week: int, seconds: float, body: str, port: str = "COM1",
              time_status: str = "FINESTEERING") -> bytes:
    """'#NAMEA,header;body*crc' + CRLF, with the CRC-32 of everything between '#' and '*'."""
    text = f"{name}A,{port},0,50.0,{time_status},{week},{seconds:.3f},02000000,0000,16809;{body}"
    return b"#" + text.encode() + b"*%08x\r\n" % gpsport.crc32(text.encode())


def format_bestposa(week: int, seconds: float, lat_deg: float, lon_deg: float, h_ell_m: float,
                    undulation_m: float, sd_enu_m: tuple[float, float, float], sats: int,
                    valid: bool = True) -> bytes:
    """BESTPOSA (OEM7 layout); height written above the geoid with ``undulation_m``."""
    stat, ptype = ("SOL_COMPUTED", "SINGLE") if valid else ("INSUFFICIENT_OBS", "NONE")
    e, n, u = sd_enu_m
    body = (f"{stat},{ptype},{lat_deg:.11f},{lon_deg:.11f},{h_ell_m - undulation_m:.4f},{undulation_m:.4f},"
            f"WGS84,{n:.4f},{e:.4f},{u:.4f},\"\",0.000,0.000,{sats},{sats},{sats},{sats},00,06,00,33")
    return ascii_log("BESTPOS", week, seconds, body)


def format_bestvela(week: int, seconds: float, v_enu: tuple[float, float, float], latency_s: float = 0.0,
                    valid: bool = True) -> bytes:
    """BESTVELA (OEM7 layout) from an ENU velocity."""
    stat, vtype = ("SOL_COMPUTED", "DOPPLER_VELOCITY") if valid else ("INSUFFICIENT_OBS", "NONE")
    e, n, u = v_enu
    trk = math.degrees(math.atan2(e, n)) % 360.0
    body = f"{stat},{vtype},{latency_s:.3f},0.000,{math.hypot(e, n):.4f},{trk:.6f},{u:.4f},0.0"
    return ascii_log("BESTVEL", week, seconds, body)


def format_timea(week: int, seconds: float, leap_s: int, utc: tuple[int, int, int, int, int, int]) -> bytes:
    """TIMEA with GPS - UTC = ``leap_s``; utc = (year, month, day, hour, minute, ms)."""
    y, mo, d, h, mi, ms = utc
    body = f"VALID,0.000000000,0.000000000,{-leap_s:.9f},{y},{mo},{d},{h},{mi},{ms},VALID"
    return ascii_log("TIME", week, seconds, body)
