"""Receiver-independent GNSS rules, shared by every protocol decoder (NMEA today; UBX, NovAtel) and the
pipeline: which dates are believable, the midnight roll-over, and what counts as a fix (as gpsd decides).

A date outside YEAR_MIN..YEAR_MAX, or a GPS week past WEEK_MAX, is treated as a malformed field (counted in
``bad_fields``, the epoch refused): every UTC time the pipeline derives from it then fits an int64 of
nanoseconds and a ROS header stamp (``acquire.messages``: unsigned 32-bit seconds, up to 2106-02-07), whatever
a receiver sends.
"""
from __future__ import annotations

from datetime import date as Date
from datetime import timedelta

from fieldlog.acquire import numbers

YEAR_MIN = 1980          # GPS time starts 1980-01-06
YEAR_MAX = 2105         # the last whole year a header stamp carries
HALF_DAY_S = 43_200.0

# GGA quality indicators that are not fixes (gpsd): 0 invalid, 6 dead reckoning, 7 manual input, 8 simulator
NOT_FIX_QUALITY = frozenset((0, 6, 7, 8))

_UNIX_ORDINAL = Date(1970, 1, 1).toordinal()
WEEK_MAX = (Date(YEAR_MAX, 12, 31).toordinal() - Date(1980, 1, 6).toordinal()) // 7   # GPS week, not rolled over


def make_date(year: int | str, month: int | str, day: int | str) -> Date | None:
    """The calendar date, or None when a field is not a number, the date does not exist or the year is
    outside YEAR_MIN..YEAR_MAX. Never raises."""
    return numbers.day(year, month, day, YEAR_MIN, YEAR_MAX)


def in_range(day: Date | None) -> Date | None:
    """``day`` if its year is within YEAR_MIN..YEAR_MAX, else None (for dates from host clocks and files)."""
    return day if day is not None and YEAR_MIN <= day.year <= YEAR_MAX else None


def roll_over(day: Date | None, tod_s: float, last_tod_s: float | None) -> Date | None:
    """The date of a sentence at time of day ``tod_s`` that carries no date of its own, ``day`` being the date
    of the previous one at ``last_tod_s``: the next day when the time of day went back by more than 12 h
    (midnight passed), else ``day``. None when that leaves YEAR_MIN..YEAR_MAX."""
    if day is None or last_tod_s is None or tod_s >= last_tod_s - HALF_DAY_S:
        return in_range(day)
    return in_range(day + timedelta(days=1)) if day.year <= YEAR_MAX else None


def date_of_utc_ns(utc_ns: int) -> Date | None:
    """The UTC date of ``utc_ns`` (ns since the Unix epoch), None outside YEAR_MIN..YEAR_MAX."""
    days = int(utc_ns) // 86_400_000_000_000
    if not Date(YEAR_MIN, 1, 1).toordinal() <= days + _UNIX_ORDINAL <= Date(YEAR_MAX, 12, 31).toordinal():
        return None
    return Date.fromordinal(days + _UNIX_ORDINAL)


def utc_ns(day: Date, tod_s: float) -> int:
    """UTC of ``day`` + ``tod_s`` (seconds of the UTC day), ns since the Unix epoch."""
    return (day.toordinal() - _UNIX_ORDINAL) * 86_400_000_000_000 + round(tod_s * 1e9)


def no_fix_reason(quality: int | None, num_sats: int | None, status_valid: bool | None) -> str:
    """Why a receiver epoch is not a fix, as gpsd judges it ("" when it is one).

    quality: the GGA fix quality (None: no GGA); num_sats: satellites used (None: not reported);
    status_valid: the RMC status 'A' and mode not 'N' (None: no RMC). Other protocols map their fix type onto
    these (e.g. UBX fixType 0 -> quality 0, 1 (dead reckoning only) -> 6).
    """
    if status_valid is False:
        return "status_void"
    if quality is None:
        return "" if status_valid else "no_quality"
    if quality in NOT_FIX_QUALITY:
        return f"quality_{quality}"
    if num_sats == 0:
        return "no_satellites"
    return ""
