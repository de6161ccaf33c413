"""TOML and YAML files read with bounds, and a TOML table as a dataclass: the one way the tool reads a config
(``acquire.config`` for the daemon's file, ``acquire.timesync`` for its ``[timesync]`` table), a calibration, a
scenario or a rosbag2 ``metadata.yaml``, and the error it raises.

A file is read up to ``MAX_FILE_BYTES``; its parsed content may nest at most ``MAX_DEPTH`` tables or arrays
deep and hold at most ``MAX_VALUES`` values (a YAML alias counted each time it is used), so neither a parser's
recursion nor a walk over an alias bomb can take the process down. Every refusal is a ``ConfigError``: one line
naming the file and, where there is one, the key.
"""

from __future__ import annotations

import os
import tomllib
from dataclasses import fields
from typing import Any, Callable, TypeVar

T = TypeVar("T")
MAX_FILE_BYTES = 16 << 20
MAX_DEPTH = 32
MAX_VALUES = 1_000_000


class ConfigError(ValueError):
    """A bad configuration; the message names the key."""


def from_table(cls: type[T], table: str, d: dict[str, Any]) -> T:
    """Dataclass ``cls`` from the TOML table ``[table]``; an unknown key raises ConfigError naming it.
    Value checks are the dataclass's own (``__post_init__``).

    Parameters
    ----------
    cls : the dataclass
    table : the table's name, for errors
    d : the table's keys and values

    Returns
    -------
    an instance of ``cls``
    """
    known = {f.name for f in fields(cls)}
    bad = sorted(set(d) - known)
    if bad:
        raise ConfigError(f"[{table}] {', '.join(bad)}: unknown key; known keys: {', '.join(sorted(known))}")
    return cls(**d)


def one_line(e: BaseException) -> str:
    """An exception's text on one line (parsers' messages span several, with a pointer under the line).

    Parameters
    ----------
    e : the exception

    Returns
    -------
    str
    """
    return " ".join(str(e).split()) or type(e).__name__


def read_text(path: str | os.PathLike[str], what: str) -> str:
    """The text of file ``path`` (UTF-8, at most ``MAX_FILE_BYTES``); ConfigError ``"{what} {path} ..."`` in one
    line when it is missing, a directory, larger or not text. ``what`` says what the file is ("config file").

    Parameters
    ----------
    path : the file
    what : what it is, for errors

    Returns
    -------
    str : its text
    """
    try:
        with open(path, "rb") as f:
            raw = f.read(MAX_FILE_BYTES + 1)
    except FileNotFoundError:
        raise ConfigError(f"{what} {path} does not exist") from None
    except IsADirectoryError:
        raise ConfigError(f"{what} {path} is a directory: give a file") from None
    except OSError as e:
        raise ConfigError(f"{what} {path} cannot be read: {e.strerror or one_line(e)}") from None
    if len(raw) > MAX_FILE_BYTES:
        raise ConfigError(f"{what} {path} is larger than {MAX_FILE_BYTES >> 20} MiB: not a file of this kind")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        raise ConfigError(f"{what} {path} is not text (not UTF-8)") from None


def load_toml(text: str, name: str) -> dict[str, Any]:
    """TOML ``text`` (from ``name``: "config file PATH") as a dict, its nesting checked (``check_nesting``).

    Parameters
    ----------
    text : the TOML text
    name : where it comes from, for errors

    Returns
    -------
    dict : the tables
    """
    return _parse(tomllib.loads, tomllib.TOMLDecodeError, "TOML", text, name)


def load_yaml(text: str, name: str) -> Any:
    """YAML ``text`` (from ``name``) through ``yaml.safe_load`` (no object construction), nesting checked.

    Parameters
    ----------
    text : YAML
    name : its source, named in errors

    Returns
    -------
    object : the document
    """
    import yaml

    return _parse(yaml.safe_load, yaml.YAMLError, "YAML", text, name)


def _parse(parse: Callable[[str], Any], errors: type[Exception], kind: str, text: str, name: str) -> Any:
    try:
        d = parse(text)
    except errors as e:
        raise ConfigError(f"{name} is not valid {kind}: {one_line(e)}") from None
    except RecursionError:
        raise ConfigError(f"{name}: nested more than {MAX_DEPTH} deep: not a file of this kind") from None
    check_nesting(d, name)
    return d


def check_nesting(value: Any, name: str) -> None:
    """ConfigError naming the key where ``value`` (parsed TOML or YAML) nests more than ``MAX_DEPTH`` tables or
    arrays deep, or when it holds more than ``MAX_VALUES`` values; walked without recursion.

    Parameters
    ----------
    value : parsed TOML or YAML
    name : where it comes from, for errors
    """
    stack: list[tuple[Any, tuple[str, ...]]] = [(value, ())]
    seen = 0
    while stack:
        v, key = stack.pop()
        seen += 1
        if seen > MAX_VALUES:
            raise ConfigError(f"{name}: more than {MAX_VALUES} values: not a file of this kind")
        if isinstance(v, dict):
            items = [(str(k), x) for k, x in v.items()]
        elif isinstance(v, list):
            items = [(f"[{i}]", x) for i, x in enumerate(v)]
        else:
            continue
        if len(key) >= MAX_DEPTH and items:
            shown = ".".join(key[:4]).replace(".[", "[")
            raise ConfigError(f"{name}: {shown}... nested more than {MAX_DEPTH} deep: not a file of this kind")
        stack += [(x, key + (k,)) for k, x in items]
