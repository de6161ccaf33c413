"""NMEA 0183: line framing, checksum, typed decoding of GGA/RMC/VTG/GST/ZDA/GNS/GSA/GSV/HDT/GLL, epoch grouping,
generators. GNS is a Gga subclass, so it gives an epoch's position when the receiver sends no GGA; GLL gives it
when there is neither GGA nor RMC (``EpochAssembler``).

Decoded values are SI: degrees for latitude/longitude (WGS-84, north/east positive), metres, m/s, seconds of
the UTC day, radians for courses (clockwise from true north). Empty fields decode to NaN (floats) or None
(times, integers, courses, dates). Any talker is accepted (GP, GN, GL, GA, BD, GB, QZ, ...).
See docs/daq-protocol.md, "NMEA parser choice", for why the decoding is ours rather than pynmeagps'.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from datetime import date as Date

from fieldlog.acquire import gnss, numbers

KNOT_MPS = 1852.0 / 3600.0
MAX_LINE = 256          # NMEA allows 82 characters; proprietary lines run longer


# ---------------------------------------------------------------------------------------------- framing

class LineFramer:
    """Split a byte stream into sentences: from the last '$' or '!' of a line up to CR and/or LF.

    Bytes outside sentences (noise, comment lines such as '# ...', logger prefixes) are dropped and counted in
    ``bytes_discarded``; a sentence longer than ``max_len`` is dropped and counted in ``overlong``. Memory is
    bounded by ``max_len`` whatever arrives. Terminators are stripped; empty lines are ignored.
    """

    def __init__(self, max_len: int = MAX_LINE) -> None:
        self.max_len = max_len
        self.lines = 0
        self.bytes_discarded = 0
        self.overlong = 0
        self._tail = b""        # the current, unterminated line from its last '$'/'!' on

    @property
    def pending(self) -> int:
        """Bytes held for the next feed (<= max_len)."""
        return len(self._tail)

    def feed(self, data: bytes) -> list[bytes]:
        """Complete sentences in ``data`` (with what was held over), each from '$'/'!' to before the CR/LF."""
        parts = bytes(data).splitlines(keepends=True)
        out: list[bytes] = []
        for i, part in enumerate(parts):
            terminated = part[-1] in b"\r\n"
            line = part.rstrip(b"\r\n") if terminated else part
            if i == 0 and self._tail:
                line = self._tail + line
                self._tail = b""
            start = max(line.rfind(b"$"), line.rfind(b"!"))
            if start < 0:
                self.bytes_discarded += len(line)
                continue
            self.bytes_discarded += start
            if len(line) - start > self.max_len:
                self.bytes_discarded += len(line) - start
                self.overlong += 1
            elif terminated:
                out.append(line[start:])
            else:
                self._tail = line[start:]
        self.lines += len(out)
        return out


# ---------------------------------------------------------------------------------------------- checksum

def checksum(body: bytes | str) -> int:
    """XOR of the bytes between '$'/'!' and '*'."""
    if isinstance(body, str):
        body = body.encode("ascii")
    x, n = int.from_bytes(body, "little"), len(body)
    while n > 1:                     # fold the upper half onto the lower half
        h = (n + 1) // 2
        x = (x & ((1 << (8 * h)) - 1)) ^ (x >> (8 * h))
        n = h
    return x


def sentence(body: str) -> bytes:
    """'$' + body + '*HH' + CRLF."""
    b = body.encode("ascii")
    return b"$" + b + b"*%02X\r\n" % checksum(b)


_HEX = frozenset(b"0123456789ABCDEFabcdef")


def split_checksum(line: bytes) -> tuple[bytes, bool | None]:
    """(body, checksum ok) of a framed line: ok is None without a '*', False for a wrong or malformed '*HH'."""
    star = line.rfind(b"*")
    if star < 0:
        return line[1:], None
    body = line[1:star]
    if len(line) - star != 3 or not (line[-2] in _HEX and line[-1] in _HEX):
        return body, False
    return body, checksum(body) == int(line[star + 1:], 16)


# ---------------------------------------------------------------------------------------------- records

@dataclass(frozen=True)
class Gga:
    """GGA fix. quality: 0 none, 1 GPS, 2 DGPS, 4 RTK fixed, 5 RTK float, 6 dead reckoning."""

    talker: str
    time_of_day_s: float | None
    lat_deg: float
    lon_deg: float
    quality: int | None
    num_sats: int | None
    hdop: float
    alt_msl_m: float
    geoid_sep_m: float
    raw: bytes = field(default=b"", repr=False)


@dataclass(frozen=True)
class Rmc:
    """RMC minimum data. valid: status 'A' and mode indicator (if any) not 'N'."""

    talker: str
    time_of_day_s: float | None
    valid: bool
    lat_deg: float
    lon_deg: float
    speed_mps: float
    course_rad: float | None
    date: Date | None
    raw: bytes = field(default=b"", repr=False)


@dataclass(frozen=True)
class Gll:
    """GLL geographic position. valid: status 'A' and mode indicator (if any) not 'N'."""

    talker: str
    time_of_day_s: float | None
    valid: bool
    lat_deg: float
    lon_deg: float
    raw: bytes = field(default=b"", repr=False)


@dataclass(frozen=True)
class Vtg:
    """VTG course over ground (true) and speed; speed from the km/h field, else from knots."""

    talker: str
    course_rad: float | None
    speed_mps: float
    raw: bytes = field(default=b"", repr=False)


@dataclass(frozen=True)
class Gst:
    """GST pseudorange error statistics, 1-sigma, metres."""

    talker: str
    time_of_day_s: float | None
    rms_m: float
    sd_lat_m: float
    sd_lon_m: float
    sd_alt_m: float
    raw: bytes = field(default=b"", repr=False)


@dataclass(frozen=True)
class Zda:
    """ZDA time and date."""

    talker: str
    time_of_day_s: float | None
    date: Date | None
    raw: bytes = field(default=b"", repr=False)


@dataclass(frozen=True)
class Other:
    """Any other sentence, kept as it came: talker ('P' for proprietary), type (e.g. 'GSV', 'UBX')."""

    talker: str
    type: str
    raw: bytes = field(default=b"", repr=False)


@dataclass(frozen=True)
class Gns(Gga):
    """GNS fix (multi-constellation GGA): a Gga whose quality comes from the mode indicator, kept as ``mode``
    (one letter per constellation: N none, A autonomous, D differential, P precise, R RTK fixed, F RTK float,
    E dead reckoning, M manual, S simulator)."""

    mode: str = ""


@dataclass(frozen=True)
class Gsa:
    """GSA DOP and active satellites. fix_type: 1 none, 2 2-D, 3 3-D; system_id (NMEA 4.1) or None."""

    talker: str
    fix_type: int | None
    prns: tuple[int, ...]
    pdop: float
    hdop: float
    vdop: float
    system_id: int | None
    raw: bytes = field(default=b"", repr=False)


@dataclass(frozen=True)
class Gsv:
    """GSV satellites in view, one sentence of ``total``: (prn, elevation deg, azimuth deg, SNR dB-Hz or None)."""

    talker: str
    total: int | None
    number: int | None
    in_view: int | None
    sats: tuple[tuple[int | None, float, float, int | None], ...]
    raw: bytes = field(default=b"", repr=False)


@dataclass(frozen=True)
class Hdt:
    """HDT true heading, radians clockwise from true north (None when empty)."""

    talker: str
    heading_rad: float | None
    raw: bytes = field(default=b"", repr=False)


Sentence = Gga | Rmc | Vtg | Gst | Zda | Gsa | Gsv | Hdt | Gll | Other


# ---------------------------------------------------------------------------------------------- decoding

def _decimal(s: str) -> bool:
    """Unsigned decimal number: digits with at most one '.'."""
    return s.replace(".", "", 1).isdigit() and s.isascii()


class _Fields(numbers.Tally):
    """Field access that turns malformed values into NaN/None and counts them (``bad``)."""

    __slots__ = ("f",)

    def __init__(self, fields: list[str]) -> None:
        super().__init__()
        self.f = fields

    def s(self, i: int) -> str:
        return self.f[i] if i < len(self.f) else ""

    def num(self, i: int) -> float:
        return self.real(self.s(i))

    def int(self, i: int) -> int | None:
        return self.whole(self.s(i), 0, 10**9)

    def time(self, i: int) -> float | None:
        """hhmmss[.ss] -> seconds of the day."""
        s = self.s(i)
        if not s:
            return None
        h, m = numbers.whole(s[:2], 0, 23), numbers.whole(s[2:4], 0, 59)
        sec = numbers.real(s[4:], 0.0, 61.0)
        if len(s) < 6 or not s[:4].isdigit() or h is None or m is None or not sec < 61:
            self.bad += 1
            return None
        return h * 3600 + m * 60 + sec

    def angle(self, i: int, hemi: int, neg: str, pos: str) -> float:
        """ddmm.mmmm (lat) or dddmm.mmmm (lon) and hemisphere letter -> signed degrees."""
        s, h = self.s(i), self.s(hemi)
        if not s:
            return math.nan
        dot = s.find(".")
        dot = len(s) if dot < 0 else dot
        deg = numbers.whole(s[:dot - 2], 0, 180) if dot >= 3 and s[:dot - 2].isdigit() else None
        minutes = numbers.real(s[dot - 2:], 0.0, 60.0) if dot >= 3 and _decimal(s) else math.nan
        if deg is None or not minutes < 60 or h not in (neg, pos):
            self.bad += 1
            return math.nan
        v = deg + minutes / 60.0
        return -v if h == neg else v

    def course(self, i: int) -> float | None:
        v = self.num(i)
        return None if math.isnan(v) else math.radians(v % 360.0)

    def date(self, day: str, month: str, year: str) -> Date | None:
        return self.day(year, month, day, gnss.YEAR_MIN, gnss.YEAR_MAX)


def _gga(t: str, f: _Fields, raw: bytes) -> Gga:
    return Gga(t, f.time(1), f.angle(2, 3, "S", "N"), f.angle(4, 5, "W", "E"), f.int(6), f.int(7), f.num(8),
               f.num(9), f.num(11), raw)


def _rmc(t: str, f: _Fields, raw: bytes) -> Rmc:
    d = f.s(9)
    if d and (len(d) != 6 or not d.isdigit()):
        f.bad += 1
        day = None
    else:
        yy = d[4:6]
        day = f.date(d[0:2], d[2:4], ("20" if yy < "80" else "19") + yy) if d else None
    valid = f.s(2) == "A" and f.s(12) != "N"
    return Rmc(t, f.time(1), valid, f.angle(3, 4, "S", "N"), f.angle(5, 6, "W", "E"), f.num(7) * KNOT_MPS,
               f.course(8), day, raw)


def _gll(t: str, f: _Fields, raw: bytes) -> Gll:
    return Gll(t, f.time(5), f.s(6) == "A" and f.s(7) != "N", f.angle(1, 2, "S", "N"), f.angle(3, 4, "W", "E"), raw)


def _vtg(t: str, f: _Fields, raw: bytes) -> Vtg:
    kmh = f.num(7)
    speed = kmh / 3.6 if not math.isnan(kmh) else f.num(5) * KNOT_MPS
    return Vtg(t, f.course(1), speed, raw)


def _gst(t: str, f: _Fields, raw: bytes) -> Gst:
    return Gst(t, f.time(1), f.num(2), f.num(6), f.num(7), f.num(8), raw)


def _zda(t: str, f: _Fields, raw: bytes) -> Zda:
    return Zda(t, f.time(1), f.date(f.s(2), f.s(3), f.s(4)), raw)


_GNS_QUALITY = {"A": 1, "D": 2, "P": 3, "R": 4, "F": 5, "E": 6, "M": 7, "S": 8}


def _gns(t: str, f: _Fields, raw: bytes) -> Gns:
    mode = f.s(6)
    best = [_GNS_QUALITY[c] for c in mode if c in _GNS_QUALITY]
    quality = min(best, key=lambda q: (q in (6, 7, 8), -q)) if best else (0 if mode else None)
    return Gns(t, f.time(1), f.angle(2, 3, "S", "N"), f.angle(4, 5, "W", "E"), quality, f.int(7), f.num(8),
               f.num(9), f.num(10), raw, mode)


def _gsa(t: str, f: _Fields, raw: bytes) -> Gsa:
    prns = tuple(p for p in (f.int(i) for i in range(3, 15)) if p is not None)
    return Gsa(t, f.int(2), prns, f.num(15), f.num(16), f.num(17), f.int(18), raw)


def _gsv(t: str, f: _Fields, raw: bytes) -> Gsv:
    n_sat = (len(f.f) - 4) // 4
    sats = tuple((f.int(4 + 4 * i), f.num(5 + 4 * i), f.num(6 + 4 * i), f.int(7 + 4 * i)) for i in range(n_sat))
    return Gsv(t, f.int(1), f.int(2), f.int(3), sats, raw)


def _hdt(t: str, f: _Fields, raw: bytes) -> Hdt:
    return Hdt(t, f.course(1), raw)


_DECODERS = {"GGA": (_gga, 12), "RMC": (_rmc, 10), "VTG": (_vtg, 9), "GST": (_gst, 9), "ZDA": (_zda, 5),
             "GNS": (_gns, 13), "GSA": (_gsa, 18), "GSV": (_gsv, 4), "HDT": (_hdt, 3), "GLL": (_gll, 7)}


@dataclass
class NmeaStats:
    """Decoder counters. by_type counts checked sentences by address ('GNGGA', 'GPGSV', 'PUBX', ...)."""

    lines: int = 0
    bad_checksum: int = 0
    no_checksum: int = 0
    by_type: dict[str, int] = field(default_factory=dict)
    unknown: int = 0
    proprietary: int = 0
    bad_fields: int = 0
    bytes_discarded: int = 0
    overlong: int = 0


def decode_body(body: bytes, raw: bytes = b"", stats: NmeaStats | None = None) -> Sentence:
    """Decode a checked sentence body (between '$' and '*'). Never raises; problems go to ``stats``."""
    fields = body.decode("ascii", "replace").split(",")
    addr = fields[0]
    st = stats if stats is not None else NmeaStats()
    st.by_type[addr] = st.by_type.get(addr, 0) + 1
    if addr[:1] == "P":
        st.proprietary += 1
        return Other("P", addr[1:], raw)
    talker, kind = addr[:2], addr[2:]
    dec = _DECODERS.get(kind) if len(addr) == 5 and addr.isalnum() and addr.isascii() else None
    if dec is None:
        st.unknown += 1
        return Other(talker, kind, raw)
    f = _Fields(fields)
    out = dec[0](talker, f, raw)
    st.bad_fields += f.bad + (len(fields) < dec[1])
    return out


class NmeaDecoder:
    """Bytes in, decoded sentences out: LineFramer + checksum + typed decoding.

    Sentences without a checksum are counted in ``no_checksum`` and dropped unless ``accept_no_checksum``.
    """

    def __init__(self, accept_no_checksum: bool = False, max_len: int = MAX_LINE) -> None:
        self.framer = LineFramer(max_len)
        self.accept_no_checksum = accept_no_checksum
        self.stats = NmeaStats()

    def feed(self, data: bytes) -> list[Sentence]:
        """Sentences completed by ``data``, in order."""
        out = [s for s in map(self.decode_line, self.framer.feed(data)) if s is not None]
        st = self.stats
        st.lines = self.framer.lines
        st.bytes_discarded = self.framer.bytes_discarded
        st.overlong = self.framer.overlong
        return out

    def decode_line(self, line: bytes) -> Sentence | None:
        """One framed line ('$' or '!' up to before CR/LF): the sentence, or None when its checksum fails."""
        st = self.stats
        body, ok = split_checksum(line)
        if ok is None:
            st.no_checksum += 1
            if not self.accept_no_checksum:
                return None
        elif not ok:
            st.bad_checksum += 1
            return None
        return decode_body(body, line, st)


# ---------------------------------------------------------------------------------------------- epochs

@dataclass(frozen=True)
class GnssEpoch:
    """One receiver epoch merged from its sentences. NaN/0/None where no sentence gave the value.

    Position from GGA (GNS), else RMC, else GLL (altitude NaN without GGA); quality from GGA, else 1/0 from
    RMC's or GLL's validity; speed and course from RMC, else VTG; standard deviations from GST; date from
    RMC/ZDA or carried
    over from the last one (with midnight roll-over, ``gnss.roll_over``). first_mono_ns: host monotonic time of its
    first sentence. no_fix: why it is not a fix (``gnss.no_fix_reason``; "" for a fix).
    """

    time_of_day_s: float
    date: Date | None
    lat_deg: float
    lon_deg: float
    alt_ellipsoid_m: float
    quality: int
    num_sats: int
    hdop: float
    speed_mps: float
    course_rad: float | None
    sd_east_m: float
    sd_north_m: float
    sd_up_m: float
    first_mono_ns: int
    no_fix: str = ""

    @property
    def utc_ns(self) -> int | None:
        """UTC of the epoch, ns since the Unix epoch (None without a date)."""
        return None if self.date is None else gnss.utc_ns(self.date, self.time_of_day_s)


class EpochAssembler:
    """Group GGA/RMC/VTG/GST/ZDA of the same time of day (to 1 ms) into GnssEpochs.

    An epoch is emitted when a sentence with another time arrives (or on ``flush``), or at once when it holds
    one of each of the five types (nothing more can belong to it: the live bus gets the fix a second earlier).
    VTG has no time and joins the current epoch; sentences with an empty time, VTG before any epoch, and Other
    records are ignored. A timed sentence of an epoch already emitted complete (a repeat) is counted in
    ``late`` and not merged (it stays in ``/gps/nmea`` and the raw bytes). GLL is the position of a receiver that
    sends nothing better: once a GGA, GNS or RMC has come, GLL sentences are counted in ``gll_ignored`` and not
    used (their time may be another second's: a Garmin 48 writes GLL a second off), and an epoch of GLL alone
    still pending then is dropped.

    ``position_from`` counts the epochs by the sentence their position came from ('GGA' (GGA or GNS), 'RMC',
    'GLL', 'none'). A receiver whose GGA and RMC/GLL carry different seconds gives epochs of each (the seconds
    are never merged: each epoch takes its own sentences' time and position); ``split`` counts consecutive
    epochs within a second of each other of which one has GGA only and the other RMC/GLL only.
    """

    COMPLETE = frozenset((Gga, Rmc, Vtg, Gst, Zda))

    def __init__(self) -> None:
        self.late = 0
        self.position_from: dict[str, int] = {}
        self.split = 0
        self.better = False             # a GGA, GNS or RMC came: GLL is not used from then on
        self.gll_ignored = 0
        self._last_only: tuple[str, int] | None = None   # ('gga' | 'other', key) of the last epoch, if one-sided
        self._done: int | None = None  # key of the last epoch emitted complete
        self._key: int | None = None
        self._parts: list[Sentence] = []
        self._mono = 0
        self._last_date: Date | None = None
        self._last_tod = 0.0

    def add(self, s: Sentence, mono_ns: int) -> list[GnssEpoch]:
        """Add one decoded sentence read at host time ``mono_ns``; returns the epochs it completes."""
        if isinstance(s, Vtg):
            if self._key is not None:
                self._parts.append(s)
            return []
        if isinstance(s, (Gga, Rmc)):
            self.better = True
        elif isinstance(s, Gll) and self.better:
            self.gll_ignored += 1
            return []
        tod = getattr(s, "time_of_day_s", None)
        if tod is None:
            return []
        key = round(tod * 1000)
        if key == self._done:
            self.late += 1
            return []
        out: list[GnssEpoch] = []
        if key != self._key:
            out = self.flush()
            self._key, self._mono = key, mono_ns
        self._parts.append(s)
        if {type(p) for p in self._parts} >= self.COMPLETE:
            self._done = key
            out += self.flush()
        return out

    def flush(self) -> list[GnssEpoch]:
        """Emit the epoch in progress, if any."""
        if self._key is None:
            return []
        if self.better and not any(isinstance(p, (Gga, Rmc, Gst, Zda)) for p in self._parts):
            self.gll_ignored += 1          # GLL alone, from before the receiver's first GGA/RMC
            self._key, self._parts = None, []
            return []
        epoch = self._merge(self._key / 1000.0, self._parts, self._mono)
        self._key, self._parts = None, []
        return [epoch]

    def _merge(self, tod: float, parts: list[Sentence], mono_ns: int) -> GnssEpoch:
        gga = next((p for p in parts if isinstance(p, Gga)), None)
        rmc = next((p for p in parts if isinstance(p, Rmc)), None)
        vtg = next((p for p in parts if isinstance(p, Vtg)), None)
        gst = next((p for p in parts if isinstance(p, Gst)), None)
        gll = next((p for p in parts if isinstance(p, Gll)), None)
        day = next((p.date for p in parts if isinstance(p, (Rmc, Zda)) and p.date is not None), None)
        if day is None:
            day = gnss.roll_over(self._last_date, tod, self._last_tod)
        if day is not None:
            self._last_date, self._last_tod = day, tod
        nan = math.nan
        if gga is not None:
            lat, lon = gga.lat_deg, gga.lon_deg
            alt = gga.alt_msl_m + (0.0 if math.isnan(gga.geoid_sep_m) else gga.geoid_sep_m)
            quality, sats, hdop = gga.quality or 0, gga.num_sats or 0, gga.hdop
        elif rmc is not None:
            lat, lon, alt, quality, sats, hdop = rmc.lat_deg, rmc.lon_deg, nan, int(rmc.valid), 0, nan
        elif gll is not None:
            lat, lon, alt, quality, sats, hdop = gll.lat_deg, gll.lon_deg, nan, int(gll.valid), 0, nan
        else:
            lat = lon = alt = hdop = nan
            quality = sats = 0
        source = "GGA" if gga is not None else "RMC" if rmc is not None else "GLL" if gll is not None else "none"
        self.position_from[source] = self.position_from.get(source, 0) + 1
        only = ("gga" if rmc is None and gll is None else None) if gga is not None else \
            "other" if rmc is not None or gll is not None else None
        key = round(tod * 1000)
        last = self._last_only
        if only and last and last[0] != only and abs(key - last[1]) <= 1000:
            self.split += 1
        self._last_only = (only, key) if only else None
        status = rmc.valid if rmc is not None else gll.valid if gll is not None else None
        vel = rmc if rmc is not None and not math.isnan(rmc.speed_mps) else vtg
        return GnssEpoch(
            time_of_day_s=tod, date=day, lat_deg=lat, lon_deg=lon, alt_ellipsoid_m=alt, quality=quality,
            num_sats=sats, hdop=hdop,
            speed_mps=vel.speed_mps if vel is not None else nan,
            course_rad=vel.course_rad if vel is not None else None,
            sd_east_m=gst.sd_lon_m if gst else nan, sd_north_m=gst.sd_lat_m if gst else nan,
            sd_up_m=gst.sd_alt_m if gst else nan, first_mono_ns=mono_ns,
            no_fix=gnss.no_fix_reason(quality if gga is not None else None, gga.num_sats if gga is not None else None,
                                      status))


# ---------------------------------------------------------------------------------------------- generators

def _hms(tod: float) -> str:
    cs = round(tod * 100) % 8_640_000
    return f"{cs // 360000:02d}{cs // 6000 % 60:02d}{cs // 100 % 60:02d}.{cs % 100:02d}"


def _latlon(value_deg: float, width: int, pos: str, neg: str) -> str:
    """Degrees -> 'ddmm.mmmmmmm,H' with 7 decimals of minutes (~0.2 mm)."""
    units = round(abs(value_deg) * 60e7)
    deg, rem = divmod(units, 60 * 10**7)
    return f"{deg:0{width}d}{rem // 10**7:02d}.{rem % 10**7:07d},{pos if value_deg >= 0 else neg}"


def _ddmmyy(d: Date) -> str:
    return f"{d.day:02d}{d.month:02d}{d.year % 100:02d}"


def format_gga(talker: str, tod: float, lat_deg: float, lon_deg: float, quality: int, num_sats: int, hdop: float,
               alt_msl_m: float, geoid_sep_m: float, valid: bool = True) -> bytes:
    """GGA sentence; when not valid the position, altitude and geoid fields are empty."""
    pos = f"{_latlon(lat_deg, 2, 'N', 'S')},{_latlon(lon_deg, 3, 'E', 'W')}" if valid else ",,,"
    alt = f"{alt_msl_m:.3f},M,{geoid_sep_m:.3f},M" if valid else ",M,,M"
    return sentence(f"{talker}GGA,{_hms(tod)},{pos},{quality:d},{num_sats:02d},{hdop:.2f},{alt},,")


def format_rmc(talker: str, tod: float, day: Date, lat_deg: float, lon_deg: float, speed_mps: float,
               course_rad: float | None, valid: bool = True) -> bytes:
    """RMC sentence (NMEA 2.3 with mode indicator); when not valid: status V, empty position and motion."""
    if valid:
        crs = "" if course_rad is None else f"{math.degrees(course_rad) % 360.0:.2f}"
        mid = f"A,{_latlon(lat_deg, 2, 'N', 'S')},{_latlon(lon_deg, 3, 'E', 'W')},{speed_mps / KNOT_MPS:.3f},{crs}"
    else:
        mid = "V,,,,,,"
    return sentence(f"{talker}RMC,{_hms(tod)},{mid},{_ddmmyy(day)},,,{'A' if valid else 'N'}")


def format_vtg(talker: str, course_rad: float | None, speed_mps: float, valid: bool = True) -> bytes:
    """VTG sentence (true course, knots and km/h, mode indicator)."""
    if not valid:
        return sentence(f"{talker}VTG,,T,,M,,N,,K,N")
    crs = "" if course_rad is None else f"{math.degrees(course_rad) % 360.0:.2f}"
    return sentence(f"{talker}VTG,{crs},T,,M,{speed_mps / KNOT_MPS:.3f},N,{speed_mps * 3.6:.3f},K,A")


def format_gst(talker: str, tod: float, rms_m: float, sd_lat_m: float, sd_lon_m: float, sd_alt_m: float,
               valid: bool = True) -> bytes:
    """GST sentence; the error ellipse is written axis-aligned from sd_lat and sd_lon."""
    if not valid:
        return sentence(f"{talker}GST,{_hms(tod)},,,,,,,")
    major, minor = max(sd_lat_m, sd_lon_m), min(sd_lat_m, sd_lon_m)
    orient = 0.0 if sd_lat_m >= sd_lon_m else 90.0
    return sentence(f"{talker}GST,{_hms(tod)},{rms_m:.3f},{major:.3f},{minor:.3f},{orient:.1f},"
                    f"{sd_lat_m:.3f},{sd_lon_m:.3f},{sd_alt_m:.3f}")


def format_gll(talker: str, tod: float, lat_deg: float, lon_deg: float, valid: bool = True) -> bytes:
    """GLL sentence (NMEA 2.3 with mode indicator); when not valid: status V, mode N, empty position."""
    pos = f"{_latlon(lat_deg, 2, 'N', 'S')},{_latlon(lon_deg, 3, 'E', 'W')}" if valid else ",,,"
    return sentence(f"{talker}GLL,{pos},{_hms(tod)},{'A,A' if valid else 'V,N'}")


def format_zda(talker: str, tod: float, day: Date) -> bytes:
    """ZDA sentence, local zone 00:00."""
    return sentence(f"{talker}ZDA,{_hms(tod)},{day.day:02d},{day.month:02d},{day.year:04d},00,00")
