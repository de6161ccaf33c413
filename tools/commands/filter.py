"""``fieldlog filter``: a slice of a drive by time and topic, as ``mcap filter``."""
from __future__ import annotations

import argparse

from fieldlog.tools.commands.common import (DRIVE_HELP, TIME_ORIGIN, Progress, add_out_args, command_parser,
                                            drive_arg, finish_out, log, needs_extras, out_file)


def add_parser(sub) -> None:
    s = command_parser(sub, "filter", "a slice of a drive by time and topic, as `mcap filter`")
    s.add_argument("drive", nargs="+", help=DRIVE_HELP)
    s.add_argument("--start", default=None, metavar="TIME",
                   help=f"first log time kept: {TIME_ORIGIN}, as `fuse --outage` counts (negative: from the "
                        "drive's end), an ISO UTC time (2026-05-04T09:32:00Z) or UTC ns (default: the drive's start)")
    s.add_argument("--end", default=None, metavar="TIME",
                   help="log time where the slice ends (excluded), as --start (default: the drive's end)")
    s.add_argument("--topics", default=None, metavar="T,...",
                   help="comma separated topics or shell patterns, e.g. '/imu,/gps/*' (default: all; /tf_static is "
                        "always kept)")
    add_out_args(s)
    s.set_defaults(func=needs_extras(run))


def run(a: argparse.Namespace) -> int:
    from fieldlog.tools.filter import filter_drive

    topics = [t.strip() for t in a.topics.split(",") if t.strip()] if a.topics else None
    out = out_file(a)
    res = filter_drive(drive_arg(a.drive), out, a.start, a.end, topics, progress=Progress("filter"), force=a.force)
    log.info(f"wrote {res.path.resolve()}: {sum(res.messages.values())} messages from {res.start_ns} to "
             f"{res.end_ns} ns")
    for topic, n in res.messages.items():
        log.debug(f"  {topic:<24} {n}")
    finish_out(a, out)
    return 0
