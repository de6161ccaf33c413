"""``fieldlog export``: one Parquet or CSV table per topic, through polars, or the GNSS and fused tracks as KML or
GPX (``replay.export``)."""
from __future__ import annotations

import argparse
import time

from fieldlog.tools.commands.common import (DRIVE_HELP, Progress, add_out_dir, command_parser, drive_arg, log,
                                            needs_extras)


def add_parser(sub) -> None:
    s = command_parser(sub, "export", "one Parquet or CSV table per topic, or the GNSS and fused tracks as KML or "
                       "GPX")
    s.add_argument("drive", nargs="+", help=DRIVE_HELP)
    add_out_dir(s, "output directory (DIR/<topic>.parquet, DIR/tracks.kml)", required=True)
    s.add_argument("--format", choices=["parquet", "csv", "kml", "gpx"], default="parquet",
                   help="table format, or kml/gpx: every NavSatFix topic as a timed track in one file")
    s.add_argument("--topics", default=None, help="comma separated topics (default: all)")
    s.set_defaults(func=needs_extras(run))


def run(a: argparse.Namespace) -> int:
    from fieldlog.replay.export import export

    topics = [t.strip() for t in a.topics.split(",") if t.strip()] if a.topics else None
    t0 = time.monotonic()
    try:
        written = export(drive_arg(a.drive), a.out_dir, a.format, topics, progress=Progress("export"), force=a.force)
    except KeyError as e:
        raise ValueError(e.args[0]) from None
    for topic, (path, rows) in written.items():
        log.debug(f"  {topic:<24} {rows:>9} rows  {path}")
    what = "tracks" if a.format in ("kml", "gpx") else "tables"
    log.info(f"wrote {len(written)} {what} to {a.out_dir} in {time.monotonic() - t0:.1f} s")
    return 0
