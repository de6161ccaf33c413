"""``fieldlog report``: one self-contained HTML page of a drive's health and its solutions (``tools.report``)."""
from __future__ import annotations

import argparse
import time

from fieldlog.tools.commands.common import (DRIVE_HELP, Progress, command_parser, drive_arg, log, needs_extras,
                                            output_parent, require_extras)


def add_parser(sub) -> None:
    s = command_parser(sub, "report", "one self-contained HTML page of a drive's health and its solutions")
    s.add_argument("drive", nargs="+", help=DRIVE_HELP + "; then the fused MCAPs from `fieldlog fuse` (each adds "
                                                         "its methods)")
    s.add_argument("--out", required=True, metavar="FILE",
                   help="the HTML page to write (plots inline: opens without network, mails as one file)")
    s.set_defaults(func=needs_extras(run))


def run(a: argparse.Namespace) -> int:
    require_extras("jinja2", "matplotlib", "polars")  # before the drive is read: the page needs all three
    from fieldlog.replay import viewdata
    from fieldlog.tools.report import report

    t0 = time.monotonic()
    files, fused = viewdata.split_fused(a.drive)
    output_parent(a.out)
    res = report(drive_arg(files), fused, a.out, progress=Progress("report"), force=a.force)
    found = "; ".join(f.text for f in res.findings) or "nothing found"
    log.info(f"wrote {res.path} ({res.path.stat().st_size / 1e3:.0f} kB) in {time.monotonic() - t0:.1f} s: "
             f"methods {', '.join(res.methods) or 'none'}; verdict: {found}")
    return 0
