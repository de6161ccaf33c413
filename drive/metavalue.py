"""Values of MCAP metadata records (strings only, by the format): written as JSON, read without evaluating.

``dump`` writes a number, string, bool, None, list or dict as JSON (NaN and infinities as Python's ``json``
writes them: ``NaN``, ``Infinity``). ``load`` reads it back, and also what drives written before held: Python
literals from ``repr`` (``(1, 2)``, ``nan``, ``None``, ``'flag'``, ``{'a': 1.5}``). Either way the text goes
through one small parser of literals (no ``eval``, no ``ast``), bounded in length and nesting depth; anything
else raises ``ValueError`` saying what it is. Type checks (``number``, ``whole``, ``wholes``) turn a value that is
not what was written into the same ``ValueError``, so a command reports damaged metadata in one line.
"""
from __future__ import annotations

import json
import math
import re
from typing import Any

MAX_DEPTH = 16
MAX_CHARS = 1 << 20
_TOKEN = re.compile(r"""\s*(?:(?P<num>[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)|(?P<name>[+-]?[A-Za-z_]\w*)
                     |(?P<str>"(?:[^"\\]|\\.)*"|'(?:[^'\\]|\\.)*')|(?P<punct>[\[\](){},:]))""", re.X)
_NAMES = {"true": True, "false": False, "null": None, "True": True, "False": False, "None": None,
          "NaN": math.nan, "nan": math.nan, "Infinity": math.inf, "inf": math.inf,
          "-Infinity": -math.inf, "-inf": -math.inf, "+inf": math.inf}
_CLOSE = {"[": "]", "(": ")", "{": "}"}


def dump(v: Any) -> str:
    """``v`` as JSON (tuples as lists).

    Parameters
    ----------
    v : a JSON value (tuples allowed)

    Returns
    -------
    str : its JSON text
    """
    return json.dumps(v)


def load(text: str) -> Any:
    """The value of a metadata string written by ``dump`` (or a Python literal of an older drive).

    Parameters
    ----------
    text : a metadata value

    Returns
    -------
    object : the value
    """
    if not isinstance(text, str) or len(text) > MAX_CHARS:
        raise ValueError("metadata value is not a short text")
    toks = [m for m in _tokens(text)]
    v, i = _value(toks, 0, 0)
    if i != len(toks):
        raise ValueError(f"metadata value {_short(text)}: unexpected text after the value")
    return v


def _short(text: str) -> str:
    return repr(text if len(text) <= 40 else text[:37] + "...")


def _tokens(text: str):
    pos, n = 0, len(text)
    while pos < n:
        m = _TOKEN.match(text, pos)
        if m is None or m.end() == pos:
            if text[pos:].strip() == "":
                return
            raise ValueError(f"metadata value {_short(text)}: not a literal at character {pos}")
        pos = m.end()
        yield m


def _value(toks: list, i: int, depth: int) -> tuple[Any, int]:
    if depth > MAX_DEPTH:
        raise ValueError(f"metadata value nested deeper than {MAX_DEPTH}")
    if i >= len(toks):
        raise ValueError("metadata value ends early")
    m = toks[i]
    if m["num"] is not None:
        s = m["num"]
        return (float(s) if any(c in s for c in ".eE") else int(s)), i + 1
    if m["name"] is not None:
        if m["name"] not in _NAMES:
            raise ValueError(f"metadata value: {m['name'][:20]!r} is not a literal")
        return _NAMES[m["name"]], i + 1
    if m["str"] is not None:
        return _string(m["str"]), i + 1
    p = m["punct"]
    if p not in _CLOSE:
        raise ValueError(f"metadata value: unexpected {p!r}")
    close, items, i = _CLOSE[p], [], i + 1
    while True:
        if i < len(toks) and toks[i]["punct"] == close:
            break
        if p == "{":
            k, i = _value(toks, i, depth + 1)
            if i >= len(toks) or toks[i]["punct"] != ":" or isinstance(k, (list, dict)):
                raise ValueError("metadata value: a dict key without ':'")
            v, i = _value(toks, i + 1, depth + 1)
            items.append((k, v))
        else:
            v, i = _value(toks, i, depth + 1)
            items.append(v)
        if i < len(toks) and toks[i]["punct"] == ",":
            i += 1
            continue
        if i < len(toks) and toks[i]["punct"] == close:
            break
        raise ValueError(f"metadata value: {p!r} not closed")
    return (dict(items) if p == "{" else list(items)), i + 1


def _string(tok: str) -> str:
    body = tok[1:-1]
    if tok[0] == "'":                     # a Python repr: its escapes are JSON's but for \' and \xNN
        body = re.sub(r"\\x([0-9a-fA-F]{2})", r"\\u00\1", body.replace("\\'", "'").replace('"', '\\"'))
    try:
        return json.loads(f'"{body}"')
    except ValueError:
        raise ValueError(f"metadata value: bad string {_short(tok)}") from None


# ------------------------------------------------------------------------------------------ type checks

def number(v: Any, what: str) -> float:
    """``v`` as a float (int, float, NaN; None is NaN), else ValueError naming ``what``.

    Parameters
    ----------
    v : a metadata value
    what : its name, for the error

    Returns
    -------
    float
    """
    if v is None:
        return math.nan
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ValueError(f"{what}: {_short(str(v))} is not a number")
    return float(v)


def whole(v: Any, what: str) -> int:
    """``v`` as an int (an int, or a float with an integral value), else ValueError naming ``what``.

    Parameters
    ----------
    v : the value read
    what : the value's name in the error

    Returns
    -------
    int
    """
    if isinstance(v, bool) or not isinstance(v, int):
        raise ValueError(f"{what}: {_short(str(v))} is not a whole number")
    return v


def wholes(v: Any, what: str, n: int) -> tuple[int, ...]:
    """``v`` as a tuple of ``n`` ints, else ValueError naming ``what``.

    Parameters
    ----------
    v : a metadata value
    what : its name, for the error
    n : how many ints

    Returns
    -------
    tuple[int, ...]
    """
    if not isinstance(v, list) or len(v) != n:
        raise ValueError(f"{what}: {_short(str(v))} is not a list of {n} whole numbers")
    return tuple(whole(x, what) for x in v)
