"""A TOML table as a dataclass: the one helper every configuration of the acquisition reads its tables with, and
the error it raises (``acquire.config`` for the daemon's file, ``acquire.timesync`` for its ``[timesync]`` table)."""

from __future__ import annotations

from dataclasses import fields
from typing import Any, TypeVar

T = TypeVar("T")


class ConfigError(ValueError):
    """A bad configuration; the message names the key."""


def from_table(cls: type[T], table: str, d: dict[str, Any]) -> T:
    """Dataclass ``cls`` from the TOML table ``[table]``; an unknown key raises ConfigError naming it.
    Value checks are the dataclass's own (``__post_init__``)."""
    known = {f.name for f in fields(cls)}
    bad = sorted(set(d) - known)
    if bad:
        raise ConfigError(f"[{table}] {', '.join(bad)}: unknown key; known keys: {', '.join(sorted(known))}")
    return cls(**d)
