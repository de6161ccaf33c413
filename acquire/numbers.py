"""Numbers from receiver input, checked: the one way the GPS decoders (NMEA, UBX, NovAtel) turn field values
into numbers and dates.

Each function takes what a decoder has (the text of a field, or an int/float from a binary layout or pyubx2)
and returns the value, or NaN / None when it is missing, not a plain number, not finite, or outside its range
[lo, hi]. None of them raises, whatever the value (``inf``, ``nan``, 10^20, 4000 digits, ``1_0``, ``0x10``).
``Tally`` does the same and counts the bad values (an empty field is missing, not bad), so that a decoder keeps
the other fields and sentences of a read and reports how many values it refused.
"""
from __future__ import annotations

import math
import re
from datetime import date as Date

MAX_CHARS = 40                       # a numeric field longer than this is not a number a receiver sends
_REAL = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d{1,3})?")
_WHOLE = re.compile(r"[+-]?\d+")


def _missing(v: object) -> bool:
    return v is None or (isinstance(v, (str, bytes)) and not v.strip())


def real(v: object, lo: float = -math.inf, hi: float = math.inf) -> float:
    """``v`` as a finite float in [lo, hi], else NaN. Text must be a plain decimal number."""
    if isinstance(v, bytes):
        v = v.decode("ascii", "replace")
    if isinstance(v, str):
        v = v.strip()
        if len(v) > MAX_CHARS or not _REAL.fullmatch(v):
            return math.nan
    elif isinstance(v, bool):
        return math.nan
    try:
        x = float(v)
    except (TypeError, ValueError, OverflowError):
        return math.nan
    return x if math.isfinite(x) and lo <= x <= hi else math.nan


def whole(v: object, lo: int, hi: int) -> int | None:
    """``v`` as an int in [lo, hi], else None. Text must be a plain integer; a number must be integral."""
    if isinstance(v, bytes):
        v = v.decode("ascii", "replace")
    if isinstance(v, str):
        v = v.strip()
        if len(v) > MAX_CHARS or not _WHOLE.fullmatch(v):
            return None
        x = int(v)
    elif isinstance(v, bool):
        return None
    elif isinstance(v, int):
        x = v
    else:
        f = real(v)
        if math.isnan(f) or f != math.floor(f):
            return None
        x = int(f)
    return x if lo <= x <= hi else None


def day(year: object, month: object, dom: object, year_min: int, year_max: int) -> Date | None:
    """The calendar date, or None when a part is not a whole number in range or the date does not exist."""
    y, m, d = whole(year, year_min, year_max), whole(month, 1, 12), whole(dom, 1, 31)
    if y is None or m is None or d is None:
        return None
    try:
        return Date(y, m, d)
    except ValueError:               # 31 April, 29 February of a common year
        return None


class Tally:
    """``real``, ``whole`` and ``day`` that count the bad values they refuse in ``bad``."""

    __slots__ = ("bad",)

    def __init__(self) -> None:
        self.bad = 0

    def real(self, v: object, lo: float = -math.inf, hi: float = math.inf) -> float:
        x = real(v, lo, hi)
        if math.isnan(x) and not _missing(v):
            self.bad += 1
        return x

    def whole(self, v: object, lo: int, hi: int) -> int | None:
        x = whole(v, lo, hi)
        if x is None and not _missing(v):
            self.bad += 1
        return x

    def day(self, year: object, month: object, dom: object, year_min: int, year_max: int) -> Date | None:
        d = day(year, month, dom, year_min, year_max)
        if d is None and not (_missing(year) and _missing(month) and _missing(dom)):
            self.bad += 1
        return d
