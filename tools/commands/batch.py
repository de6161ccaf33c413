"""``fieldlog batch``: reprocess many drives on Dask distributed into one Parquet table (``tools.batch``)."""
from __future__ import annotations

import argparse
import glob
from pathlib import Path

from fieldlog.fusion.methods import DKF, KF
from fieldlog.tools.commands.common import (METHODS, Progress, add_out_dir, command_parser, log, needs_extras,
                                            parse_lengths)


def add_parser(sub) -> None:
    s = command_parser(sub, "batch", "reprocess many drives on Dask distributed into one Parquet table")
    s.add_argument("drives", nargs="+", help="drives or glob patterns (quote them), e.g. 'drives/*.mcap'; a session "
                                            "or rosbag2 directory is one drive")
    s.add_argument("--methods", default=",".join((KF.name, DKF.name)), help=f"comma separated: {', '.join(METHODS)}")
    s.add_argument("--outages", default="", help="also forced outages of these lengths, s, comma separated")
    s.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                   help="a running Dask scheduler (default: a local cluster on 127.0.0.1)")
    s.add_argument("--workers", type=int, default=2, help="local cluster: worker processes (1 thread each)")
    add_out_dir(s, "output directory (results.parquet, fused/)", required=True)
    s.set_defaults(func=needs_extras(run))


def run(a: argparse.Namespace) -> int:
    from fieldlog.tools.batch import run_batch, summary
    from fieldlog.tools.evaluation.evaluate import check_methods

    methods = [m.strip() for m in a.methods.split(",") if m.strip()]
    check_methods(methods)
    lengths = parse_lengths(a.outages, "--outages")
    drives = sorted({p for pattern in a.drives for p in (glob.glob(pattern) or [pattern])})
    missing = [d for d in drives if not Path(d).exists()]
    if missing:
        raise FileNotFoundError(f"{', '.join(missing)} does not exist")
    if a.workers < 1:
        raise ValueError("--workers must be >= 1")
    res = run_batch(drives, methods, lengths, a.out_dir, scheduler=a.scheduler, workers=a.workers, say=log.info,
                    progress=Progress("batch"), force=a.force)
    print(summary(res.table))  # the product: printed whatever -q says
    log.info(f"wrote {res.parquet} ({len(res.table)} rows, {len(drives) - len(res.failed)} drives ok, "
             f"{len(res.failed)} failed); batch wall time {res.wall_s:.1f} s")
    return 1 if res.failed and len(res.failed) == len(drives) else 0
