"""``fieldlog rebuild``: re-derive every topic from ``/raw/*``."""
from __future__ import annotations

import argparse

from fieldlog.tools.commands.common import (DRIVE_HELP, Progress, add_out_args, command_parser, drive_arg,
                                            finish_out, log, needs_extras, out_file)


def add_parser(sub) -> None:
    s = command_parser(sub, "rebuild", "re-derive every topic from /raw/*")
    s.add_argument("drive", nargs="+", help=DRIVE_HELP)
    add_out_args(s)
    s.add_argument("--calib", default=None, help="calibration TOML (default: the one stored in the drive)")
    s.set_defaults(func=needs_extras(run))


def run(a: argparse.Namespace) -> int:
    from fieldlog.tools.rebuild import rebuild

    out = out_file(a)
    res = rebuild(drive_arg(a.drive), out, calibration=a.calib, progress=Progress("rebuild"), force=a.force)
    log.info(f"wrote {out}: {res.imu_samples} IMU samples, {res.gps_epochs} GPS epochs from {res.reads} raw reads")
    finish_out(a, out)
    return 0
