"""``fieldlog replay``: play a drive through live fusion into rerun at X times real time."""
from __future__ import annotations

import argparse

from fieldlog.fusion.methods import KF
from fieldlog.tools.commands.common import (DRIVE_HELP, METHODS, Progress, add_input_args, add_tf_from_arg,
                                            command_parser, input_spec, log, needs_extras, open_drive,
                                            output_parent)


def add_parser(sub) -> None:
    s = command_parser(sub, "replay", "play a drive through live fusion into rerun at X times real time")
    s.add_argument("drive", nargs="+", help=DRIVE_HELP)
    s.add_argument("--speed", type=float, default=1.0, help="times real time (0: as fast as possible)")
    s.add_argument("--method", choices=METHODS, default=KF.name, help="fusion method")
    sink = s.add_mutually_exclusive_group()
    sink.add_argument("--rrd", default=None, metavar="FILE",
                      help="stream into this .rrd file instead of a viewer (default: spawn a viewer)")
    sink.add_argument("--connect", default=None, metavar="URL",
                      help="a running viewer or `rerun --serve-grpc`, e.g. rerun+http://127.0.0.1:9876/proxy "
                           "(default: spawn a viewer)")
    sink.add_argument("--foxglove", default=None, metavar="[HOST:]PORT",
                      help="serve the drive and the live fusion over the Foxglove WebSocket protocol instead of "
                           "rerun (HOST default 127.0.0.1, PORT 0: any free port; needs fieldlog[foxglove])")
    s.add_argument("--config", default=None, metavar="FILE",
                   help="fusion TOML ([fusion] table; default: the drive's own, else the defaults)")
    add_input_args(s)
    add_tf_from_arg(s)
    s.set_defaults(func=needs_extras(run))


def run(a: argparse.Namespace) -> int:
    from fieldlog.drive.tables import TomlFile
    from fieldlog.drive.outputs import check_new
    from fieldlog.replay.player import replay
    from fieldlog.tools.fuse_settings import settings

    conf = TomlFile.read(a.config)
    drive = open_drive(a.drive, a, conf)  # checked before the work
    st = settings(drive, conf, input_spec(a))
    if a.foxglove is not None:
        from fieldlog.tools.foxglove_live import serve

        res = serve(drive, a.method, a.speed, a.foxglove, st.inputs, st.config)
        log.info(f"served {res.blocks} blocks, {res.solutions} {a.method} solutions, {res.published} messages "
                 f"-> {res.address}")
        return 0
    output_parent(a.rrd)
    if a.rrd is not None:
        check_new(a.rrd, a.force)  # refused before rerun-sdk is imported and the drive read
    res = replay(drive, a.method, a.speed, rrd=a.rrd, connect=a.connect, config=st.config,
                 progress=Progress(f"replay {a.method}"), imap=st.inputs, force=a.force)
    log.info(f"played {res.data_s:.1f} s of {' '.join(a.drive)} in {res.wall_s:.1f} s "
             f"(x{res.data_s / max(res.wall_s, 1e-9):.1f}): {res.solutions} {a.method} solutions, {res.updates} GPS "
             f"updates, {res.gps_fixes} GPS fixes, {res.imu_rows} IMU rows, {res.outages} outages -> {res.sink}")
    return 0
