"""TOML and YAML files read with bounds, and a TOML table as a dataclass: the one way the tool reads a config
(``acquire.config`` for the daemon's file, ``acquire.timesync`` for its ``[timesync]`` table, ``TomlFile`` for a
command's ``--config``, its values typed by ``typed_value``), a calibration, a scenario or a rosbag2
``metadata.yaml``, and the error it raises.

A file is read up to ``MAX_FILE_BYTES``; its parsed content may nest at most ``MAX_DEPTH`` tables or arrays
deep and hold at most ``MAX_VALUES`` values (a YAML alias counted each time it is used), so neither a parser's
recursion nor a walk over an alias bomb can take the process down. Every refusal is a ``ConfigError``: one line
naming the file and, where there is one, the key.
"""

from __future__ import annotations

import math
import os
import tomllib
from dataclasses import dataclass, fields, is_dataclass
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


def typed_value(where: str, key: str, value: Any, like: Any) -> Any:
    """``value`` of the TOML table ``[where]`` converted to the type of the default ``like``; ConfigError naming
    the key when it does not fit (int accepted for float, lists for tuples, a table for a dataclass).

    Parameters
    ----------
    where : the table's name, for errors
    key : the key, for errors
    value : the value read
    like : the key's default, whose type the value takes (None: a number)

    Returns
    -------
    the value as that type
    """
    def bad(what: str) -> ConfigError:
        return ConfigError(f"[{where}] {key}: expected {what}, got {value!r}")

    if is_dataclass(like):
        if not isinstance(value, dict):
            raise bad("a table")
        return typed_table(type(like), f"{where}.{key}", value)
    if isinstance(like, bool):
        if not isinstance(value, bool):
            raise bad("true or false")
        return value
    if isinstance(like, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise bad("an integer")
        return value
    if isinstance(like, float) or like is None:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise bad("a finite number")
        return float(value)
    if isinstance(like, tuple):
        def tup(v: Any) -> Any:
            if isinstance(v, list):
                return tuple(tup(x) for x in v)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise bad("an array of numbers")
            return float(v)

        out = tup(value) if isinstance(value, list) else None
        if out is None or (like and len(out) != len(like)):
            raise bad(f"an array of {len(like)} numbers" if like else "an array")
        return out
    if not isinstance(value, type(like)):
        raise bad(type(like).__name__)
    return value


def typed_table(cls: type[T], where: str, table: dict[str, Any]) -> T:
    """Dataclass ``cls`` from the TOML table ``[where]``, each value converted by ``typed_value`` against the
    field's default; ConfigError naming an unknown key or a bad value.

    Parameters
    ----------
    cls : the dataclass, every field with a default
    where : the table's name, for errors
    table : the table's keys and values

    Returns
    -------
    an instance of ``cls``
    """
    defaults = cls()
    known = {f.name for f in fields(cls)}
    d = {k: typed_value(where, k, v, getattr(defaults, k)) if k in known else v for k, v in table.items()}
    return from_table(cls, where, d)  # names an unknown key


def read_toml(path: str | os.PathLike[str]) -> dict[str, Any]:
    """A TOML file as a dict; ConfigError with one line when it is missing, not valid TOML or out of bounds
    (``load_toml``).

    Parameters
    ----------
    path : the file

    Returns
    -------
    dict : the tables
    """
    return load_toml(read_text(path, "config file"), f"config file {path}")


@dataclass(frozen=True)
class TomlFile:
    """A TOML file read once: its tables, and its name for messages. A command reads ``--config`` once into one
    of these and hands it on, so a pipe (``--config <(...)``) or ``/dev/stdin``, which give their bytes once,
    work as a file does."""

    path: str
    tables: dict[str, Any]

    @classmethod
    def read(cls, path: str | os.PathLike[str] | None) -> "TomlFile | None":
        """``read_toml`` of path kept with its name; None for no path.

        Parameters
        ----------
        path : the file, or None

        Returns
        -------
        TomlFile or None
        """
        return None if path is None else cls(str(path), read_toml(path))

    def __str__(self) -> str:
        return self.path
