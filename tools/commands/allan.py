"""``fieldlog allan``: Allan deviation and noise parameters of a static drive."""
from __future__ import annotations

import argparse

from fieldlog.tools.commands.common import DRIVE_HELP, command_parser, drive_arg, needs_extras


def add_parser(sub) -> None:
    s = command_parser(sub, "allan", "Allan deviation and noise parameters of a static drive")
    s.add_argument("drive", nargs="+", help=DRIVE_HELP + "; static")
    s.add_argument("--plot", default=None, metavar="PREFIX",
                   help="also write PREFIX_gyro.png and PREFIX_accel.png (needs fieldlog[plots]; default: none)")
    s.set_defaults(func=needs_extras(run))


def run(a: argparse.Namespace) -> int:
    from fieldlog.tools.allan import drive_report

    print(drive_report(drive_arg(a.drive), plot_prefix=a.plot, force=a.force))  # the product: printed whatever -q says
    return 0
