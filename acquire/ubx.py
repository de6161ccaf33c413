"""u-blox UBX: checked frames (``gpsport.Framer``) decoded with pyubx2 into solutions and time-pulse records.

Decoded: NAV-PVT (UTC, fix type, satellites, lat/lon/ellipsoidal height, hAcc/vAcc, velN/E/D, sAcc) -> one
``gpsport.Solution`` per epoch; TIM-TP (time of the next pulse, qErr) -> ``Pulse``. Every other message is
counted by name and kept in the raw bytes and ``/gps/receiver``. Accuracies follow the ROS ublox driver:
per-axis horizontal variance hAcc^2, vertical vAcc^2, velocity sAcc^2 on each ENU axis.

Receivers without NAV-PVT (u-blox 5 and 6, the timing modules): NAV-POSLLH (position, hAcc/vAcc), NAV-VELNED
(velocity in cm/s, sAcc), NAV-SOL (fix type, gpsFixOK, differential, satellites, week) and NAV-TIMEUTC (UTC)
of the same iTOW make one epoch, as gpsd groups them (``gpsport.EpochGroup``: complete with NAV-POSLLH, NAV-SOL
and whatever else the receiver's epochs hold; NAV-EOE ends an epoch at once).
The epoch needs NAV-POSLLH; its time is NAV-TIMEUTC's when valid, else NAV-SOL's week and iTOW less GPS - UTC;
it is a fix only when NAV-SOL says so. Once a NAV-PVT has come, these messages make no epoch (NAV-PVT is the
same solution).

fixType 5 (time only: a timing receiver on its surveyed position) is a ``Solution`` with ``time_only``: the
position is the surveyed one, not a fix (the pipeline writes it so, docs/data-model.md "Fixes").

HNR-PVT (the M8U/M8L's own 10-30 Hz solution, fused from GNSS and the receiver's IMU and wheel ticks) is
decoded to solutions too; they replace NAV-PVT only with ``use_hnr`` (``[gps] use_hnr``), because they are
not independent of that IMU (a filter fusing them with ours counts the receiver's inertial information twice).

pyubx2 (maintained, covers every u-blox generation) does the payload decoding; the framing is ours, because
UBX shares the port with NMEA and NovAtel and must resynchronise byte by byte (``gpsport``). pyubx2 is imported
at the first UBX frame: a drive without one (an NMEA receiver's) never loads it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

from fieldlog.acquire import gnss, gpsport, novatel, numbers

NS = 1_000_000_000
# UBX NAV-PVT fixType -> GGA-like quality: 0 no fix, 1 dead reckoning only, 2 2-D, 3 3-D, 4 GNSS + dead
# reckoning, 5 time only
_FIX_QUALITY = {0: 0, 1: 6, 2: 1, 3: 1, 4: 1, 5: 0}
TIME_ONLY = 5
UNKNOWN = float("nan")      # a variance the message does not give (the pipeline's default applies)


@dataclass(frozen=True)
class Pulse:
    """TIM-TP: the next time pulse is at UTC second ``utc_s``; it comes ``qerr_s`` late (u-blox's quantisation
    error, from the receiver's clock grid), so the true second is at (edge time - qerr_s)."""

    utc_s: int
    qerr_s: float


OLD_EPOCH = frozenset(("NAV-POSLLH", "NAV-VELNED", "NAV-SOL", "NAV-TIMEUTC"))
CM = 1 / 100.0
MM = 1 / 1000.0


@dataclass
class UbxStats:
    by_type: dict[str, int] = field(default_factory=dict)
    undecodable: int = 0
    no_time: int = 0
    bad_fields: int = 0       # values refused by the range checks (acquire/numbers.py)


class UbxDecoder:
    """UBX frames in, ``gpsport.Solution`` and ``Pulse`` records out. Never raises."""

    def __init__(self, use_hnr: bool = False) -> None:
        self.stats = UbxStats()
        self.leap_s: int | None = None   # GPS - UTC, learnt from NAV-PVT or NAV-TIMEUTC (iTOW against UTC)
        self.use_hnr = use_hnr
        self._has_pvt = False            # a NAV-PVT came: the older messages make no epochs
        self._group = gpsport.EpochGroup("NAV-POSLLH", frozenset({"NAV-SOL"}))
        self._group_time: int | None = None   # UTC of the group in progress, once known
        self.old_late = 0                # NAV-POSLLH/VELNED/SOL/TIMEUTC of an epoch already emitted (not merged)

    def decode(self, frame: bytes, mono_ns: int) -> tuple[str, list]:
        """(message name, records) of one checked frame."""
        from pyubx2 import UBXReader
        from pyubx2.ubxtypes_core import UBX_MSGIDS

        try:
            msg = UBXReader.parse(frame, validate=0)
            name = msg.identity if frame[2:4] in UBX_MSGIDS else "unknown"     # the counters stay bounded
        except Exception:        # pyubx2 raises its own and builtin errors on payloads it cannot read
            self.stats.undecodable += 1
            return "?", []
        self.stats.by_type[name] = self.stats.by_type.get(name, 0) + 1
        t = numbers.Tally()
        try:
            if name == "NAV-PVT":
                self._has_pvt = True
                return name, self._pvt(msg, mono_ns, t, not self.use_hnr)
            if name == "HNR-PVT":
                return name, self._pvt(msg, mono_ns, t, self.use_hnr) if self.use_hnr else []
            if name == "TIM-TP":
                return name, self._tp(msg)
            if name in OLD_EPOCH and not self._has_pvt:
                return name, self._old(name, msg, mono_ns, t)
            if name == "NAV-EOE" and not self._has_pvt:
                return name, self.flush()
        except (AttributeError, TypeError, ValueError, OverflowError):
            self.stats.undecodable += 1
        finally:
            self.stats.bad_fields += t.bad
        return name, []

    def _utc(self, m, t: numbers.Tally, second: str) -> int | None:
        """UTC (ns, to the ms: nano holds the clock bias) of a message's year..nano fields (``second``: the
        seconds field's name), learning GPS - UTC from its iTOW; None when not valid."""
        day = t.day(m.year, m.month, m.day, gnss.YEAR_MIN, gnss.YEAR_MAX)
        hour, minute, sec = t.whole(m.hour, 0, 23), t.whole(m.min, 0, 59), t.whole(getattr(m, second), 0, 60)
        nano = t.whole(m.nano, -10**9, 10**9)
        if day is None or hour is None or minute is None or sec is None or nano is None:
            return None
        utc_ns = gnss.utc_ns(day, hour * 3600 + minute * 60 + sec) + nano
        utc_ns = round(utc_ns / 1e6) * 1_000_000     # the epoch, to the ms (nano holds the clock bias)
        tow_utc = (utc_ns / NS - gpsport.GPS_EPOCH_S) % gpsport.WEEK_S
        itow = t.real(m.iTOW, 0, gpsport.WEEK_S * 1000)
        if itow == itow:
            self.leap_s = round((itow / 1000.0 - tow_utc) % gpsport.WEEK_S) % gpsport.WEEK_S
        return utc_ns

    def _pvt(self, m, mono_ns: int, t: numbers.Tally, solution: bool) -> list:
        """NAV-PVT or HNR-PVT: the solution, or (``solution`` False) only the epoch's time."""
        if not (m.validDate and m.validTime):
            self.stats.no_time += 1
            return []
        utc_ns = self._utc(m, t, "second")
        if utc_ns is None:
            self.stats.no_time += 1
            return []
        if not solution:
            return [gpsport.EpochTime(utc_ns)]
        hnr = m.identity == "HNR-PVT"
        fix_type = t.whole(m.gpsFix if hnr else m.fixType, 0, 255)
        quality = _quality(fix_type, t.whole(m.DiffSoln if hnr else m.diffSoln, 0, 1),
                           0 if hnr else t.whole(m.carrSoln, 0, 3))
        sats = None if hnr else t.whole(m.numSV, 0, 255)
        fix_ok = m.GPSfixOK if hnr else m.gnssFixOk and not t.whole(m.invalidLlh, 0, 1)
        if hnr:
            speed, head = t.real(m.gSpeed) * MM, math.radians(t.real(m.headMot))
            vel = (speed * math.sin(head), speed * math.cos(head), 0.0)
        else:
            vel = (t.real(m.velE) * MM, t.real(m.velN) * MM, -t.real(m.velD) * MM)
        s_var = (t.real(m.sAcc, 0) * MM) ** 2
        return [_solution(utc_ns, fix_type, quality, bool(fix_ok), sats, t.real(m.lat, -90, 90),
                          t.real(m.lon, -180, 180), t.real(m.height) * MM, t.real(m.hAcc, 0) * MM,
                          t.real(m.vAcc, 0) * MM, vel, (s_var, s_var, UNKNOWN if hnr else s_var), mono_ns,
                          "ubx_hnr" if hnr else "ubx")]

    def _old(self, name: str, m, mono_ns: int, t: numbers.Tally) -> list:
        """NAV-POSLLH/VELNED/SOL/TIMEUTC: grouped by iTOW; an ``EpochTime`` once the group's time is known."""
        key = t.whole(m.iTOW, 0, gpsport.WEEK_S * 1000 - 1)
        if key is None:
            self.stats.no_time += 1
            return []
        new = self._group.is_new(key)
        out: list = self.flush() if new else []
        if new or key == self._group.key:
            utc_ns = None
            if name == "NAV-TIMEUTC" and m.validUTC:
                utc_ns = self._utc(m, t, "sec")
            elif name == "NAV-SOL" and m.towSet and m.wknSet:
                week = t.whole(m.week, 0, 9999)
                utc_ns = None if week is None else novatel.utc_ns_of(week, key, self.leap_s)
            if utc_ns is not None and self._group_time is None:
                self._group_time = utc_ns
                out.append(gpsport.EpochTime(utc_ns))
        out += self._solutions(self._group.add(key, name, m, mono_ns))
        self.old_late = self._group.late
        return out

    def flush(self) -> list[gpsport.Solution]:
        """The NAV-POSLLH/VELNED/SOL/TIMEUTC epoch in progress, if it has a position."""
        out = self._solutions(self._group.flush())
        self._group_time = None
        return out

    def _solutions(self, groups: list) -> list[gpsport.Solution]:
        """The solutions of completed groups (one at most: the group in progress), none with ``use_hnr``."""
        out = []
        for _key, parts, mono_ns in groups:
            utc_ns, self._group_time = self._group_time, None
            if utc_ns is None:
                self.stats.no_time += 1
            elif not self.use_hnr:
                t = numbers.Tally()
                out.append(self._old_solution(utc_ns, parts, mono_ns, t))
                self.stats.bad_fields += t.bad
        return out

    @staticmethod
    def _old_solution(utc_ns: int, parts: dict, mono_ns: int, t: numbers.Tally) -> gpsport.Solution:
        pos, vel, sol = parts["NAV-POSLLH"], parts.get("NAV-VELNED"), parts.get("NAV-SOL")
        fix_type = t.whole(sol.gpsFix, 0, 255) if sol is not None else 0
        quality = _quality(fix_type, t.whole(sol.diffSoln, 0, 1) if sol is not None else 0, 0)
        v_enu, s_acc = (math.nan,) * 3, math.nan
        if vel is not None:
            v_enu = (t.real(vel.velE) * CM, t.real(vel.velN) * CM, -t.real(vel.velD) * CM)
            s_acc = t.real(vel.sAcc, 0) * CM
        elif sol is not None:
            s_acc = t.real(sol.sAcc, 0) * CM
        s_var = s_acc ** 2
        return _solution(utc_ns, fix_type, quality, bool(sol is not None and sol.gpsfixOK),
                         t.whole(sol.numSV, 0, 255) if sol is not None else 0, t.real(pos.lat, -90, 90),
                         t.real(pos.lon, -180, 180), t.real(pos.height) * MM, t.real(pos.hAcc, 0) * MM,
                         t.real(pos.vAcc, 0) * MM, v_enu, (s_var, s_var, s_var), mono_ns, "ubx")

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


def _quality(fix_type: int | None, diff: int | None, carr: int | None) -> int:
    """GGA-like quality of a UBX fix type, differential flag and carrier solution (0 none, 1 float, 2 fixed)."""
    quality = _FIX_QUALITY.get(fix_type, 0)
    if quality == 1 and diff:
        quality = 2
    if quality and carr:
        quality = 4 if carr == 2 else 5
    return quality


def _solution(utc_ns: int, fix_type: int | None, quality: int, fix_ok: bool, sats: int | None, lat: float,
              lon: float, h: float, h_acc: float, v_acc: float, vel: tuple[float, float, float],
              vel_var: tuple[float, float, float], mono_ns: int, source: str) -> gpsport.Solution:
    """One epoch's solution: a fix when the receiver says so (gpsd's rules, its fix-OK flag, a position);
    fixType 5 (time only) with a position is ``time_only``. Accuracies (m) give the variances."""
    fix = not gnss.no_fix_reason(quality, sats, None) and fix_ok and lat == lat and lon == lon
    time_only = fix_type == TIME_ONLY and fix_ok and lat == lat and lon == lon
    h_var, v_var = h_acc ** 2, v_acc ** 2
    return gpsport.Solution(
        utc_ns=utc_ns, fix=fix, quality=quality if fix else 0, num_sats=sats or 0, lat_deg=lat, lon_deg=lon, h_m=h,
        pos_var=(h_var, h_var, v_var), pos_var_known=True, vel_enu=vel if fix else None, vel_var=vel_var,
        first_mono_ns=mono_ns, source=source, time_only=time_only)
