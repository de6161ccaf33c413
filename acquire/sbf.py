"""Septentrio SBF: checked blocks (``gpsport.Framer``: CRC-16 verified) decoded with pysbf2 into solutions and
time-pulse records.

Decoded: PVTGeodetic (GPS week and time of week, Mode, Error, latitude/longitude in radians, ellipsoidal height,
Vn/Ve/Vu, NrSV, HAccuracy/VAccuracy), PosCovGeodetic and VelCovGeodetic (the receiver's own variances, m^2 and
(m/s)^2), ReceiverTime (GPS - UTC, DeltaLS) and xPPSOffset (how late the last xPPS pulse came, ``ubx.Pulse``).
Every other block is counted by name and kept in the raw bytes and ``/gps/receiver``.

An epoch: the blocks of one (WNc, TOW). It is emitted once it holds a PVTGeodetic and every block type the
epochs so far held (the receiver's output set, learnt as it goes: a block of an epoch already emitted joins the
set and is counted in ``late``), or when a block of another time arrives (``flush`` at the end).
A fix only when the receiver says so: PVT Error 0 and a Mode type other than 0 (no PVT) and 3 (fixed location:
a position typed in, not measured). Without PosCovGeodetic the position variance comes from HAccuracy (2DRMS:
per axis (HAccuracy / (2 sqrt 2))^2) and VAccuracy (2 sigma), marked approximated; without VelCovGeodetic the
velocity variance is unknown (the pipeline's default applies).

Time: GPS week and TOW to UTC with ReceiverTime's DeltaLS when the receiver sent one, else the leap-second
table. Do-not-use values (-2e10 for floats, all ones for integers) fail the range checks and count as missing.

pysbf2 (by pyubx2's author, maintained) decodes the block bodies, unscaled (``scaling=False``: its scaling
rounds to 1e-12, a nanosecond pulse offset would lose its digits); the framing is ours (``gpsport``). pysbf2 is
imported at the first SBF block: a drive without one never loads it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

from fieldlog.acquire import gnss, gpsport, novatel, numbers
from fieldlog.acquire.ubx import Pulse

NS = 1_000_000_000
# PVT Mode type -> GGA-like quality: 0 no PVT, 1 stand-alone, 2 differential, 3 fixed location (typed in: not a
# fix), 4 RTK fixed, 5 RTK float, 6 SBAS aided, 7 moving-base RTK fixed, 8 moving-base RTK float, 10 PPP
MODE_QUALITY = {0: 0, 1: 1, 2: 2, 3: 7, 4: 4, 5: 5, 6: 2, 7: 4, 8: 5, 10: 2}
DECODED = frozenset(("PVTGeodetic", "PosCovGeodetic", "VelCovGeodetic", "ReceiverTime", "xPPSOffset"))
TIME_SCALE_GPS, TIME_SCALE_UTC = 1, 2          # xPPSOffset TimeScale (3 receiver time, 4 GLONASS: not used)
HACC_DNU_CM = 65535
DNU_FLOAT = -2e10                              # SBF's do-not-use value of F4 and F8 fields
TWO_SQRT2 = 2.0 * math.sqrt(2.0)


def _real(t: numbers.Tally, x: object, lo: float = -math.inf, hi: float = math.inf) -> float:
    """A float field in [lo, hi]; NaN, and not counted as bad, when it holds the do-not-use value."""
    if isinstance(x, float) and x <= DNU_FLOAT / 2:
        return math.nan
    return t.real(x, lo, hi)


@dataclass
class SbfStats:
    by_type: dict[str, int] = field(default_factory=dict)
    undecodable: int = 0
    no_time: int = 0
    bad_fields: int = 0       # values refused by the range checks (acquire/numbers.py)
    late: int = 0             # blocks of an epoch already emitted (not merged)


def block_number(frame: bytes) -> int:
    """The block number of an SBF frame (the id's low 13 bits; the top 3 are the revision)."""
    return int.from_bytes(frame[4:6], "little") & 0x1FFF


def block_name(frame: bytes) -> str:
    """pysbf2's name of the frame's block, 'unknown' for a number it does not list (the counters stay bounded)."""
    from pysbf2.sbftypes_core import SBF_MSGIDS

    entry = SBF_MSGIDS.get(block_number(frame))
    return entry[0] if entry else "unknown"


class SbfDecoder:
    """Checked SBF frames in, ``gpsport.Solution``, ``gpsport.EpochTime`` and ``Pulse`` records out. Never
    raises."""

    def __init__(self) -> None:
        self.stats = SbfStats()
        self.leap_s: int | None = None          # GPS - UTC from ReceiverTime
        self._group = gpsport.EpochGroup("PVTGeodetic")

    def decode(self, frame: bytes, mono_ns: int) -> tuple[str, list]:
        """(block name, records) of one checked frame."""
        name = block_name(frame)
        self.stats.by_type[name] = self.stats.by_type.get(name, 0) + 1
        if name not in DECODED:
            return name, []
        from pysbf2 import SBFReader

        t = numbers.Tally()
        try:
            msg = SBFReader.parse(frame, validate=0, scaling=False)
            return name, self._records(name, msg, mono_ns, t)
        except Exception:        # pysbf2 raises its own and builtin errors on bodies it cannot read
            self.stats.undecodable += 1
            return name, []
        finally:
            self.stats.bad_fields += t.bad

    def _records(self, name: str, m, mono_ns: int, t: numbers.Tally) -> list:
        week, tow_ms = t.whole(m.WNc, 0, gnss.WEEK_MAX), t.whole(m.TOW, 0, gpsport.WEEK_S * 1000 - 1)
        if name == "ReceiverTime":
            leap = t.whole(m.DeltaLS, 0, novatel.MAX_LEAP_S)
            if leap is not None:
                self.leap_s = leap
            return []
        if week is None or tow_ms is None:
            self.stats.no_time += 1
            return []
        if name == "xPPSOffset":
            return self._pulse(m, week, tow_ms, t)
        key = (week, tow_ms)
        out: list = []
        if self._group.is_new(key):
            out = self.flush()
            out.append(gpsport.EpochTime(novatel.utc_ns_of(week, tow_ms, self.leap_s)))
        out += self._solutions(self._group.add(key, name, m, mono_ns))
        self.stats.late = self._group.late
        return out

    def _pulse(self, m, week: int, tow_ms: int, t: numbers.Tally) -> list:
        scale, late_ns = t.whole(m.TimeScale, 0, 255), _real(t, m.Offset, -1e9, 1e9)
        if late_ns != late_ns or scale not in (TIME_SCALE_GPS, TIME_SCALE_UTC):
            return []
        leap = 0 if scale == TIME_SCALE_UTC else self.leap_s
        utc_ns = novatel.utc_ns_of(week, tow_ms, leap)
        return [Pulse(round(utc_ns / NS), late_ns / 1e9)]

    def flush(self) -> list[gpsport.Solution]:
        """The epoch in progress, if it has a PVTGeodetic."""
        return self._solutions(self._group.flush())

    def _solutions(self, groups: list) -> list[gpsport.Solution]:
        out = []
        for key, parts, mono_ns in groups:
            t = numbers.Tally()
            try:
                out.append(self._solution(key, parts, mono_ns, t))
            except (AttributeError, TypeError, ValueError, OverflowError):
                self.stats.undecodable += 1
            finally:
                self.stats.bad_fields += t.bad
        return out

    def _solution(self, key: tuple[int, int], parts: dict, mono_ns: int, t: numbers.Tally) -> gpsport.Solution:
        p = parts["PVTGeodetic"]
        quality = MODE_QUALITY.get(t.whole(p.Type, 0, 15), 0) if t.whole(p.Error, 0, 255) == 0 else 0
        sats = t.whole(p.NrSV, 0, 254) or 0
        lat = math.degrees(_real(t, p.Latitude, -math.pi / 2, math.pi / 2))
        lon = math.degrees(_real(t, p.Longitude, -math.pi, math.pi))
        h = _real(t, p.Height, -1e5, 1e8)
        fix = not gnss.no_fix_reason(quality, sats, None) and all(x == x for x in (lat, lon, h))
        vel = (_real(t, p.Ve, -1e5, 1e5), _real(t, p.Vn, -1e5, 1e5), _real(t, p.Vu, -1e5, 1e5))
        pos_var, known = _pos_var(p, parts.get("PosCovGeodetic"), t)
        vel_var = (math.nan,) * 3
        c = parts.get("VelCovGeodetic")
        if c is not None:
            vel_var = tuple(_real(t, x, 0, 1e10) for x in (c.Cov_VeVe, c.Cov_VnVn, c.Cov_VuVu))
        week, tow_ms = key
        return gpsport.Solution(
            utc_ns=novatel.utc_ns_of(week, tow_ms, self.leap_s), fix=fix, quality=quality if fix else 0,
            num_sats=sats, lat_deg=lat, lon_deg=lon, h_m=h, pos_var=pos_var, pos_var_known=known,
            vel_enu=vel if fix and all(v == v for v in vel) else None, vel_var=vel_var, first_mono_ns=mono_ns,
            source="sbf")


def _pos_var(p, c, t: numbers.Tally) -> tuple[tuple[float, float, float], bool]:
    """ENU position variances (m^2) of PVTGeodetic ``p`` and PosCovGeodetic ``c`` (or None), and whether they
    are the receiver's own covariance."""
    if c is not None:
        var = tuple(_real(t, x, 0, 1e10) for x in (c.Cov_lonlon, c.Cov_latlat, c.Cov_hgthgt))
        if all(v == v for v in var):
            return var, True
    h_cm, v_cm = t.whole(p.HAccuracy, 0, HACC_DNU_CM - 1), t.whole(p.VAccuracy, 0, HACC_DNU_CM - 1)
    sh = h_cm / 100 / TWO_SQRT2 if h_cm is not None else math.nan
    sv = v_cm / 100 / 2 if v_cm is not None else math.nan
    return (sh * sh, sh * sh, sv * sv), False


def solution_time_ns(frame: bytes) -> int | None:
    """UTC of a PVTGeodetic frame (GPS - UTC from the table), or None (another block, no time, unreadable)."""
    if block_name(frame) != "PVTGeodetic":
        return None
    recs = SbfDecoder().decode(frame, 0)[1]
    return next((r.utc_ns for r in recs if isinstance(r, gpsport.EpochTime)), None)
