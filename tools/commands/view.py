"""``fieldlog view``: show a drive and fused solutions in rerun, or write an .rrd; or the daemon's live bus (in
rerun, or served to Foxglove)."""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from fieldlog.fusion.methods import KF
from fieldlog.tools.commands.common import (DRIVE_HELP, METHODS, Progress, add_input_args, add_tf_from_arg,
                                            command_parser, input_spec, log, needs_extras, open_drive,
                                            output_parent)

if TYPE_CHECKING:
    from fieldlog.replay.inputs import InputMap


def add_parser(sub) -> None:
    s = command_parser(sub, "view", "show a drive and fused solutions in rerun, or write an .rrd")
    s.add_argument("drive", nargs="?", default=None, help=DRIVE_HELP + "; none with --live")
    s.add_argument("fused", nargs="*", help="fused MCAPs from `fieldlog fuse` (each adds its methods); other files "
                                            "given here are more files of the drive")
    s.add_argument("--rrd", default=None, metavar="FILE",
                   help="write this .rrd instead of opening the viewer (default: open the viewer)")
    s.add_argument("--live", nargs="?", const="", default=None, metavar="ADDRESS",
                   help="instead of a drive: the running daemon's live bus (its Unix socket; default: [daemon] bus "
                        "of --config), fused incrementally as in `fieldlog replay`, until the daemon stops")
    s.add_argument("--method", choices=METHODS, default=KF.name, help="--live: fusion method")
    s.add_argument("--connect", default=None, metavar="URL",
                   help="--live: a running viewer, as for `fieldlog replay` (default: spawn one)")
    s.add_argument("--foxglove", default=None, metavar="[HOST:]PORT",
                   help="--live: serve the bus's derived topics (/imu with its live stamps) and the live fusion's "
                        "/fusion/<method>/*, /tf, /tf_static over the Foxglove WebSocket protocol instead of rerun "
                        "(HOST default 127.0.0.1, PORT 0: any free port; prints 'foxglove: serving ws://HOST:PORT'; "
                        "needs fieldlog[foxglove]; what `fieldlog acquire --foxglove` runs)")
    s.add_argument("--config", default=None, metavar="FILE",
                   help="--live: the daemon's config, for [daemon] bus and (--foxglove) its calibration's mounting; "
                        "else its [input] (default: none)")
    add_input_args(s)
    add_tf_from_arg(s)
    s.set_defaults(func=needs_extras(run))


def rerun_exe() -> str:
    """The rerun viewer of this installation, as an absolute path (the venv's, next to this Python)."""
    exe = Path(sys.executable).parent / "rerun"
    return str(exe) if exe.exists() else "rerun"


def run_live(a: argparse.Namespace) -> int:
    from fieldlog.acquire import calib, config

    cfg = config.load(a.config, {"daq": "-", "gps": "--"}) if a.config or not a.live else None
    address = a.live or cfg.daemon.bus
    if not address:
        raise ValueError("no live bus: give its socket path (--live PATH) or a config with [daemon] bus")
    if a.foxglove is not None:
        from fieldlog.tools.foxglove_live import serve_live

        if a.rrd or a.connect:
            raise ValueError("--foxglove serves instead of rerun: it takes no --rrd or --connect")
        mounting = calib.load_calibration(cfg.calibration_file or None).mounting if cfg else None
        try:
            res = serve_live(address, a.method, a.foxglove, mounting=mounting)
        except KeyboardInterrupt:
            return 130
        log.info(f"served {res.blocks} blocks live from {address}, {res.solutions} {a.method} solutions, "
                 f"{res.published} messages -> {res.address}")
        return 0
    from fieldlog.replay.player import live_view

    output_parent(a.rrd)
    try:
        res = live_view(address, a.method, rrd=a.rrd, connect=a.connect, force=a.force)
    except KeyboardInterrupt:
        return 130
    log.info(f"viewed {res.data_s:.1f} s live from {address}: {res.solutions} {a.method} solutions, {res.gps_fixes} "
             f"GPS fixes, {res.imu_rows} IMU rows, {res.outages} outages -> {res.sink}")
    return 0


def run(a: argparse.Namespace) -> int:
    if a.live is not None:
        if a.drive or a.fused:
            raise ValueError("--live takes no drive files")
        return run_live(a)
    if a.foxglove is not None:
        raise ValueError("--foxglove is for --live (and `fieldlog replay`)")
    from fieldlog.replay import viewdata

    if a.drive is None:
        raise ValueError("a drive is required (or --live)")
    if a.connect:
        raise ValueError("--connect is for --live (and `fieldlog replay`)")
    t0 = time.monotonic()
    from fieldlog.drive.tables import TomlFile
    from fieldlog.drive.outputs import check_new
    from fieldlog.tools.fuse_settings import input_map, load_input_spec

    conf = TomlFile.read(a.config)
    files, fused = viewdata.split_fused([a.drive, *a.fused])
    drive = open_drive(files, a, conf)  # checked before the work

    def inputs() -> InputMap | None:
        try:
            return input_map(drive, conf, input_spec(a))
        except ValueError:
            if load_input_spec(conf).merged(input_spec(a)).given():
                raise
            return None  # nothing to map (e.g. a GPS-only drive): show what the drive has

    output_parent(a.rrd)
    if a.rrd is not None:
        check_new(a.rrd, a.force)  # refused before the drive is read and rerun-sdk imported
    with viewdata.start(drive, inputs) as early:  # the drive is resolved and read while rerun-sdk is imported
        from fieldlog.replay.view import view

        res = view(drive, fused, a.rrd, progress=Progress("view"), force=a.force, early=early)
    if res.rrd is None:
        log.info(f"sent {' '.join(files)} to the rerun viewer")
        return 0
    size = res.rrd.stat().st_size
    log.info(f"wrote {res.rrd} ({size / 1e6:.1f} MB) in {time.monotonic() - t0:.1f} s: {res.gps_fixes} GPS fixes "
             f"({res.no_fix} epochs without fix), {res.imu_rows} IMU rows (decimated), methods: "
             f"{', '.join(res.methods) or 'none'}, {res.outages} outage windows\n"
             f"Open it with:  {rerun_exe()} {Path(res.rrd).resolve()}")
    return 0
