"""The GPS port's byte stream: NMEA 0183, u-blox UBX, NovAtel OEM (ASCII and binary) and Septentrio SBF mixed on
one port,
split into checked frames by protocol, and the receiver-independent solution record the decoders produce.

A u-blox receiver sends UBX and NMEA on the same port, a NovAtel one its logs and NMEA; the framer finds every
protocol's sync pattern wherever it lies, so no configuration is needed ("auto"). Frames:

* ``nmea``: '$' or '!' up to CR/LF (terminator stripped), at most ``nmea.MAX_LINE`` bytes; checked later;
* ``novatel``: OEM ASCII '#' up to CR/LF, at most MAX_ASCII bytes; CRC-32 checked here;
* ``ubx``: 0xB5 0x62, class, id, u16 length, payload, Fletcher-8 checksum; checked here;
* ``novatel_bin``: 0xAA 0x44 0x12, header length, ..., u16 message length at 8, CRC-32; checked here;
* ``sbf``: '$@', CRC-16-CCITT, block id, u16 block length (header included, a multiple of 4); checked here.
  NMEA sentences never start '$@', so a '$' followed by '@' is an SBF block and nothing else.

A frame candidate that fails its check (or is too long) is skipped by one byte, so a real frame hidden behind a
false sync is found again (resynchronisation). Memory is bounded by MAX_FRAME whatever arrives, and nothing
raises. CR, LF and bytes of no frame are counted in ``bytes_discarded``.
"""
from __future__ import annotations

import binascii
import datetime as _dt
import re
import zlib
from dataclasses import dataclass, field

from fieldlog.acquire import nmea

MAX_ASCII = 1024           # NovAtel ASCII logs (BESTPOSA ~ 230 bytes)
MAX_UBX_PAYLOAD = 2048     # NAV-PVT 92, TIM-TP 16; NAV-SAT with many satellites ~ 1 kB
MAX_BIN = 2048
MAX_SBF = 4096             # PVTGeodetic 96 bytes; MeasEpoch of many satellites a few kB
MAX_FRAME = max(MAX_ASCII, MAX_UBX_PAYLOAD + 8, MAX_BIN, MAX_SBF)

UBX_SYNC = b"\xb5\x62"
OEM_SYNC = b"\xaa\x44\x12"
SBF_SYNC = b"$@"
_STARTS = frozenset(b"$!#\xb5\xaa")
_EOL = frozenset(b"\r\n")
_LINE_STOP = re.compile(rb"[\r\n$!#\xb5\xaa]")   # what ends an ASCII line: its CR/LF, or another frame's start
# what each [gps] protocol setting decodes (NMEA always: u-blox and NovAtel ports send it too)
ACCEPTS = {"auto": {"nmea", "ubx", "novatel", "novatel_bin", "sbf"}, "nmea": {"nmea"}, "ubx": {"nmea", "ubx"},
           "novatel": {"nmea", "novatel", "novatel_bin"}, "septentrio": {"nmea", "sbf"}}


def ubx_checksum(body: bytes) -> bytes:
    """UBX 8-bit Fletcher checksum (CK_A, CK_B) over class, id, length and payload."""
    a = b = 0
    for x in body:
        a = (a + x) & 0xFF
        b = (b + a) & 0xFF
    return bytes((a, b))


def sbf_crc(data: bytes) -> int:
    """SBF's CRC-16-CCITT (polynomial 0x1021, initial value 0) over block id, length and body."""
    return binascii.crc_hqx(data, 0)


def crc32(data: bytes) -> int:
    """NovAtel's CRC-32 (polynomial 0xEDB88320, reflected, initial value 0, no final XOR)."""
    return zlib.crc32(data, 0xFFFFFFFF) ^ 0xFFFFFFFF


@dataclass
class FrameStats:
    """Framer counters; ``frames`` by protocol."""

    frames: dict[str, int] = field(default_factory=dict)
    bad_checksum: dict[str, int] = field(default_factory=dict)
    overlong: int = 0
    bytes_discarded: int = 0


class Framer:
    """Bytes in, (protocol, frame) out, in stream order; see the module docstring."""

    def __init__(self) -> None:
        self.stats = FrameStats()
        self._buf = bytearray()
        self.consumed = 0                  # stream offset of the first byte held
        self.ends: list[int] = []          # stream offset just after each frame the last feed returned

    @property
    def pending(self) -> int:
        """Bytes held for the next feed (<= MAX_FRAME)."""
        return len(self._buf)

    def feed(self, data: bytes) -> list[tuple[str, bytes]]:
        buf = self._buf
        buf += data
        out: list[tuple[str, bytes]] = []
        st = self.stats
        pos = 0
        n = len(buf)
        self.ends = []
        while pos < n:
            c = buf[pos]
            if c not in _STARTS:
                nxt = _next_start(buf, pos + 1)
                st.bytes_discarded += sum(1 for x in buf[pos:nxt] if x not in _EOL)
                pos = nxt
                continue
            kind, length = self._frame_at(buf, pos, n)
            if kind == "wait":
                break
            if kind == "skip":
                st.bytes_discarded += length
                pos += length
                continue
            frame = bytes(buf[pos:pos + length])
            st.frames[kind] = st.frames.get(kind, 0) + 1
            out.append((kind, frame.rstrip(b"\r\n") if kind in ("nmea", "novatel") else frame))
            pos += length
            self.ends.append(self.consumed + pos)
        del buf[:pos]
        self.consumed += pos
        return out

    def _frame_at(self, buf: bytearray, pos: int, n: int) -> tuple[str, int]:
        """('wait', 0) for more bytes, ('skip', n) to drop n bytes (a false sync), else (protocol, length)."""
        c = buf[pos]
        st = self.stats
        if c == 0xB5:
            if n - pos < 2:
                return "wait", 0
            if buf[pos + 1] != 0x62:
                return "skip", 1
            if n - pos < 6:
                return "wait", 0
            ln = int.from_bytes(buf[pos + 4:pos + 6], "little")
            if ln > MAX_UBX_PAYLOAD:
                st.overlong += 1
                return "skip", 1
            if n - pos < ln + 8:
                return "wait", 0
            if ubx_checksum(buf[pos + 2:pos + 6 + ln]) != buf[pos + 6 + ln:pos + 8 + ln]:
                st.bad_checksum["ubx"] = st.bad_checksum.get("ubx", 0) + 1
                return "skip", 1
            return "ubx", ln + 8
        if c == 0xAA:
            if n - pos < 3:
                return "wait", 0
            if buf[pos + 1:pos + 3] != b"\x44\x12":
                return "skip", 1
            if n - pos < 10:
                return "wait", 0
            hl, ml = buf[pos + 3], int.from_bytes(buf[pos + 8:pos + 10], "little")
            total = hl + ml + 4
            if hl < 28 or total > MAX_BIN:
                st.overlong += total > MAX_BIN
                return "skip", 1
            if n - pos < total:
                return "wait", 0
            if crc32(bytes(buf[pos:pos + total - 4])) != int.from_bytes(buf[pos + total - 4:pos + total], "little"):
                st.bad_checksum["novatel_bin"] = st.bad_checksum.get("novatel_bin", 0) + 1
                return "skip", 1
            return "novatel_bin", total
        if c == 0x24 and n - pos >= 2 and buf[pos + 1] == 0x40:
            return self._sbf_at(buf, pos, n)
        # ASCII: up to the first CR/LF; another frame start inside means this one was cut off
        limit = nmea.MAX_LINE if c != 0x23 else MAX_ASCII
        stop = min(n, pos + limit + 1)
        m = _LINE_STOP.search(buf, pos + 1, stop)
        end = stop if m is None else m.start()
        if end < stop and buf[end] in _STARTS:   # another frame starts: this line was cut off (the last '$' wins)
            return "skip", end - pos
        if end - pos > limit:
            st.overlong += 1
            return "skip", end - pos
        if end >= n:
            return "wait", 0
        if c == 0x23:
            line = bytes(buf[pos:end])
            if not _novatel_ascii_ok(line):
                if b";" in line and b"*" in line:   # a NovAtel log; other '#' lines are comments (discarded)
                    st.bad_checksum["novatel"] = st.bad_checksum.get("novatel", 0) + 1
                return "skip", 1
            return "novatel", end + 1 - pos
        return "nmea", end + 1 - pos


    def _sbf_at(self, buf: bytearray, pos: int, n: int) -> tuple[str, int]:
        """As ``_frame_at`` for the SBF block whose '$@' is at ``pos``."""
        st = self.stats
        if n - pos < 8:
            return "wait", 0
        ln = int.from_bytes(buf[pos + 6:pos + 8], "little")
        if ln < 8 or ln % 4 or ln > MAX_SBF:
            st.overlong += ln > MAX_SBF
            return "skip", 1
        if n - pos < ln:
            return "wait", 0
        if sbf_crc(bytes(buf[pos + 4:pos + ln])) != int.from_bytes(buf[pos + 2:pos + 4], "little"):
            st.bad_checksum["sbf"] = st.bad_checksum.get("sbf", 0) + 1
            return "skip", 1
        return "sbf", ln


def _next_start(buf: bytearray, i: int) -> int:
    n = len(buf)
    while i < n and buf[i] not in _STARTS:
        i += 1
    return i


def _novatel_ascii_ok(line: bytes) -> bool:
    """'#...*hhhhhhhh': the CRC-32 of the bytes between '#' and '*' matches."""
    star = line.rfind(b"*")
    if star < 0 or len(line) - star != 9:
        return False
    try:
        return crc32(line[1:star]) == int(line[star + 1:], 16)
    except ValueError:
        return False


# ---------------------------------------------------------------------------------------------- solutions

@dataclass(frozen=True)
class Solution:
    """One receiver epoch, whatever the protocol. SI; ENU; NaN where the receiver gave nothing.

    utc_ns: the epoch's UTC (ns since the Unix epoch); fix: the receiver has a position fix (gpsd's rules);
    quality: GGA-like quality (0 none, 1 autonomous, 2 differential, 4 RTK fixed, 5 RTK float);
    lat/lon in degrees, h ellipsoidal metres; pos_var (3,) ENU m^2 and whether it is the receiver's own
    (``pos_var_known``) or approximated; vel_enu (3,) m/s and vel_var (3,) (m/s)^2 (``messages.UNKNOWN_VARIANCE``: not observed);
    first_mono_ns: host time of the epoch's first message; time_only: the receiver gives time, not position (a
    timing receiver on its surveyed position, u-blox fixType 5): lat/lon/h are that position, ``fix`` is False.
    """

    utc_ns: int
    fix: bool
    quality: int
    num_sats: int
    lat_deg: float
    lon_deg: float
    h_m: float
    pos_var: tuple[float, float, float]
    pos_var_known: bool
    vel_enu: tuple[float, float, float] | None
    vel_var: tuple[float, float, float]
    first_mono_ns: int = 0
    source: str = ""
    time_only: bool = False


class EpochGroup:
    """The messages of one receiver epoch (one time key), for protocols that spread a solution over several.

    A group is emitted when it is complete: it holds the ``required`` messages and every message type the groups
    so far held (the receiver's output set, learnt as it goes; the first group, before anything is learnt, is
    never complete); or, if it holds the ``anchor`` message (the one that carries the position), when a message
    of another key arrives or on ``flush``. A message of the group last emitted joins the learnt set and is
    counted in ``late`` (not merged).
    """

    def __init__(self, anchor: str, required: frozenset[str] = frozenset()) -> None:
        self.anchor = anchor
        self.required = required | {anchor}
        self.late = 0
        self.key: object = None
        self.parts: dict[str, object] = {}
        self.mono_ns = 0
        self._expect: set[str] = set()
        self._done: object = None

    def is_new(self, key: object) -> bool:
        """Whether a message of ``key`` starts a group (the caller flushes the one in progress first)."""
        return key != self.key and key != self._done

    def add(self, key: object, name: str, msg: object, mono_ns: int) -> list[tuple[object, dict, int]]:
        """The groups (key, {name: message}, host time of the first message) that ``msg`` completes."""
        if key == self._done:
            self._expect.add(name)
            self.late += 1
            return []
        out = self.flush() if key != self.key else []
        if self.key is None:
            self.key, self.parts, self.mono_ns = key, {}, mono_ns
        self.parts[name] = msg
        if self._done is not None and self.parts.keys() >= self.required | self._expect:
            out += self.flush()
        return out

    def flush(self) -> list[tuple[object, dict, int]]:
        """The group in progress, if it holds the anchor message."""
        key, parts = self.key, self.parts
        self.key, self.parts = None, {}
        if key is None or self.anchor not in parts:
            return []
        self._expect |= parts.keys()
        self._done = key
        return [(key, parts, self.mono_ns)]


@dataclass(frozen=True)
class EpochTime:
    """The first message of a receiver epoch at ``utc_ns`` arrived (its solution may complete later): what labels
    the next PPS edge."""

    utc_ns: int


# ---------------------------------------------------------------------------------------------- GPS time

GPS_EPOCH_S = 315_964_800         # 1980-01-06T00:00:00Z, s since the Unix epoch
WEEK_S = 604_800


def gps_to_utc_s(week: int, tow_s: float, leap_s: int) -> float:
    """GPS week and seconds of week -> UTC seconds since the Unix epoch (``leap_s`` = GPS - UTC)."""
    return GPS_EPOCH_S + week * WEEK_S + tow_s - leap_s


# GPS - UTC leap seconds from each date on (the IERS table since GPS time began)
_LEAPS = [(_dt.date(1981, 7, 1), 1), (_dt.date(1982, 7, 1), 2), (_dt.date(1983, 7, 1), 3),
          (_dt.date(1985, 7, 1), 4), (_dt.date(1988, 1, 1), 5), (_dt.date(1990, 1, 1), 6),
          (_dt.date(1991, 1, 1), 7), (_dt.date(1992, 7, 1), 8), (_dt.date(1993, 7, 1), 9),
          (_dt.date(1994, 7, 1), 10), (_dt.date(1996, 1, 1), 11), (_dt.date(1997, 7, 1), 12),
          (_dt.date(1999, 1, 1), 13), (_dt.date(2006, 1, 1), 14), (_dt.date(2009, 1, 1), 15),
          (_dt.date(2012, 7, 1), 16), (_dt.date(2015, 7, 1), 17), (_dt.date(2017, 1, 1), 18)]


def leap_seconds(day: _dt.date) -> int:
    """GPS - UTC on ``day`` from the table (a receiver's own figure, when it sends one, is preferred)."""
    n = 0
    for d, s in _LEAPS:
        if day >= d:
            n = s
    return n


# ---------------------------------------------------------------------------------------------- unknown logs

_PROTOCOL_NAMES = {"nmea": "NMEA", "ubx": "UBX", "novatel": "NovAtel ASCII", "novatel_bin": "NovAtel binary",
                   "sbf": "Septentrio SBF"}
_SIRF_START, _SIRF_END = b"\xa0\xa2", b"\xb0\xb3"
_UNDECODED = "not decoded; set the receiver to NMEA, UBX, NovAtel OEM or SBF output"


def _sirf_messages(data: bytes) -> int:
    """SiRF binary messages (0xA0 0xA2, u16 big-endian length, payload, 15-bit sum, 0xB0 0xB3) in ``data``."""
    n, i = 0, data.find(_SIRF_START)
    while 0 <= i <= len(data) - 8:
        ln = int.from_bytes(data[i + 2:i + 4], "big") & 0x7FFF
        end = i + 4 + ln
        if data[end + 2:end + 4] == _SIRF_END and sum(data[i + 4:end]) & 0x7FFF == int.from_bytes(
                data[end:end + 2], "big"):
            n += 1
            i = data.find(_SIRF_START, end + 4)
        else:
            i = data.find(_SIRF_START, i + 1)
    return n


def describe(data: bytes, frames: list[tuple[str, bytes]], names: dict[str, dict[str, int]]) -> str:
    """What a GPS log holds, for a log that gives no time: each protocol with its count of messages and the
    commonest message types (``names``: protocol -> message name -> count, of the checked ``frames``), and the
    receiver protocols we do not decode (SiRF binary, Trimble TSIP, Motorola Oncore, Javad GREIS) found by their
    framing; e.g. "SiRF binary, 615 messages: not decoded; set the receiver to ...". "" for an empty log."""
    parts = []
    counts: dict[str, int] = {}
    for kind, _ in frames:
        counts[kind] = counts.get(kind, 0) + 1
    for kind, n in counts.items():
        n = sum(names[kind].values()) if kind in names else n      # NMEA: the sentences whose checksum holds
        if not n:
            continue
        top = sorted(names.get(kind, {}).items(), key=lambda kv: -kv[1])[:4]
        what = ", ".join(f"{name} {c}" for name, c in top)
        parts.append(f"{_PROTOCOL_NAMES[kind]}, {n} messages" + (f" ({what})" if what else ""))
    foreign = {"SiRF binary": _sirf_messages(data),
               "Trimble TSIP": data.count(b"\x10\x03\x10"),          # DLE ETX ends a packet, DLE starts the next
               "Motorola Oncore": data.count(b"\r\n@@"),
               "Javad GREIS": data.count(b"~~005")}                   # the RT (receiver time) message
    parts += [f"{name}, {n} messages: {_UNDECODED}" for name, n in foreign.items() if n >= 2]
    if not parts:
        return f"{len(data)} bytes of no receiver protocol" if data else "no bytes"
    return "; ".join(parts)
