"""u-blox UBX: checked frames (``gpsport.Framer``) decoded with pyubx2 into solutions and time-pulse records.

Decoded: NAV-PVT (UTC, fix type, satellites, lat/lon/ellipsoidal height, hAcc/vAcc, velN/E/D, sAcc) -> one
``gpsport.Solution`` per epoch; TIM-TP (time of the next pulse, qErr) -> ``Pulse``. Every other message is
counted by name and kept in the raw bytes and ``/gps/receiver``. Accuracies follow the ROS ublox driver:
per-axis horizontal variance hAcc^2, vertical vAcc^2, velocity sAcc^2 on each ENU axis.

pyubx2 (maintained, covers every u-blox generation) does the payload decoding; the framing is ours, because
UBX shares the port with NMEA and NovAtel and must resynchronise byte by byte (``gpsport``).
"""
from __future__ import annotations

from dataclasses import dataclass, field

from pyubx2 import UBXReader
from pyubx2.ubxtypes_core import UBX_MSGIDS

from fieldlog.acquire import gnss, gpsport, numbers

NS = 1_000_000_000
# UBX NAV-PVT fixType -> GGA-like quality: 0 no fix, 1 dead reckoning only, 2 2-D, 3 3-D, 4 GNSS + dead
# reckoning, 5 time only
_FIX_QUALITY = {0: 0, 1: 6, 2: 1, 3: 1, 4: 1, 5: 0}


@dataclass(frozen=True)
class Pulse:
    """TIM-TP: the next time pulse is at UTC second ``utc_s``; it comes ``qerr_s`` late (u-blox's quantisation
    error, from the receiver's clock grid), so the true second is at (edge time - qerr_s)."""

    utc_s: int
    qerr_s: float


@dataclass
class UbxStats:
    by_type: dict[str, int] = field(default_factory=dict)
    undecodable: int = 0
    no_time: int = 0
    bad_fields: int = 0       # values refused by the range checks (acquire/numbers.py)


class UbxDecoder:
    """UBX frames in, ``gpsport.Solution`` and ``Pulse`` records out. Never raises."""

    def __init__(self) -> None:
        self.stats = UbxStats()
        self.leap_s: int | None = None   # GPS - UTC, learnt from NAV-PVT (iTOW against its UTC)

    def decode(self, frame: bytes, mono_ns: int) -> tuple[str, list]:
        """(message name, records) of one checked frame."""
        try:
            msg = UBXReader.parse(frame, validate=0)
            name = msg.identity if frame[2:4] in UBX_MSGIDS else "unknown"     # the counters stay bounded
        except Exception:        # pyubx2 raises its own and builtin errors on payloads it cannot read
            self.stats.undecodable += 1
            return "?", []
        self.stats.by_type[name] = self.stats.by_type.get(name, 0) + 1
        try:
            if name == "NAV-PVT":
                return name, self._pvt(msg, mono_ns)
            if name == "TIM-TP":
                return name, self._tp(msg)
        except (AttributeError, TypeError, ValueError, OverflowError):
            self.stats.undecodable += 1
        return name, []

    def _pvt(self, m, mono_ns: int) -> list:
        t = numbers.Tally()
        try:
            return self._pvt_checked(m, mono_ns, t)
        finally:
            self.stats.bad_fields += t.bad

    def _pvt_checked(self, m, mono_ns: int, t: numbers.Tally) -> list:
        if not (m.validDate and m.validTime):
            self.stats.no_time += 1
            return []
        day = t.day(m.year, m.month, m.day, gnss.YEAR_MIN, gnss.YEAR_MAX)
        hour, minute, sec = t.whole(m.hour, 0, 23), t.whole(m.min, 0, 59), t.whole(m.second, 0, 60)
        nano = t.whole(m.nano, -10**9, 10**9)
        if day is None or hour is None or minute is None or sec is None or nano is None:
            self.stats.no_time += 1
            return []
        utc_ns = gnss.utc_ns(day, hour * 3600 + minute * 60 + sec) + nano
        utc_ns = round(utc_ns / 1e6) * 1_000_000     # the epoch, to the ms (nano holds the clock bias)
        tow_utc = (utc_ns / NS - gpsport.GPS_EPOCH_S) % gpsport.WEEK_S
        itow = t.real(m.iTOW, 0, gpsport.WEEK_S * 1000)
        if itow == itow:
            self.leap_s = round((itow / 1000.0 - tow_utc) % gpsport.WEEK_S) % gpsport.WEEK_S
        quality = _FIX_QUALITY.get(t.whole(m.fixType, 0, 255), 0)
        if quality == 1 and t.whole(m.diffSoln, 0, 1):
            quality = 2
        carr = t.whole(m.carrSoln, 0, 3)
        if quality and carr:
            quality = 4 if carr == 2 else 5
        sats = t.whole(m.numSV, 0, 255)
        fix = (not gnss.no_fix_reason(quality, sats, None) and bool(m.gnssFixOk)
               and not t.whole(m.invalidLlh, 0, 1))
        mm = 1 / 1000.0
        h_var = (t.real(m.hAcc, 0) * mm) ** 2
        v_var = (t.real(m.vAcc, 0) * mm) ** 2
        s_var = (t.real(m.sAcc, 0) * mm) ** 2
        vel = (t.real(m.velE) * mm, t.real(m.velN) * mm, -t.real(m.velD) * mm)
        lat, lon = t.real(m.lat, -90, 90), t.real(m.lon, -180, 180)
        fix = fix and lat == lat and lon == lon
        return [gpsport.Solution(
            utc_ns=utc_ns, fix=fix, quality=quality if fix else 0, num_sats=sats or 0,
            lat_deg=lat, lon_deg=lon, h_m=t.real(m.height) * mm, pos_var=(h_var, h_var, v_var),
            pos_var_known=True, vel_enu=vel if fix else None, vel_var=(s_var, s_var, s_var),
            first_mono_ns=mono_ns, source="ubx")]

    def _tp(self, m) -> list:
        if getattr(m, "qErrInvalid", 0):
            return []
        t = numbers.Tally()
        tow_s = t.real(m.towMS, 0, gpsport.WEEK_S * 1000) / 1000.0 + t.real(m.towSubMS, 0) / 1000.0
        week, qerr = t.whole(m.week, 0, gnss.WEEK_MAX), t.real(m.qErr)
        self.stats.bad_fields += t.bad
        if tow_s != tow_s or week is None or qerr != qerr:
            return []
        if t.whole(m.timeBase, 0, 255) == 1:    # the pulse is on UTC: tow is UTC already
            leap = 0
        elif self.leap_s is not None:
            leap = self.leap_s
        else:
            return []
        utc_s = round(gpsport.gps_to_utc_s(week, tow_s, leap))
        return [Pulse(utc_s, qerr * 1e-12)]
