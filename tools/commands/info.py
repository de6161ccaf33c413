"""``fieldlog info``: topics, rates, duration, time-sync quality, gaps, counters."""
from __future__ import annotations

import argparse

from fieldlog.tools.commands.common import DRIVE_HELP, Progress, command_parser, drive_arg, needs_extras


def add_parser(sub) -> None:
    s = command_parser(sub, "info", "topics, rates, duration, time-sync quality, gaps, counters")
    s.add_argument("drive", nargs="+", help=DRIVE_HELP)
    s.add_argument("--json", action="store_true", help="print JSON (machine-readable) instead of the table")
    s.add_argument("--scan", action="store_true",
                   help="read the messages even if the drive has its fieldlog.info record (default: the record)")
    s.set_defaults(func=needs_extras(run))


def run(a: argparse.Namespace) -> int:
    from fieldlog.tools.info import drive_info, format_info

    info = drive_info(drive_arg(a.drive), scan=a.scan,
                      progress=None if a.json else Progress("info: reading the messages"))
    print(info.to_json() if a.json else format_info(info))  # the product: printed whatever -q says
    return 0
