"""``fieldlog acquire``: the acquisition daemon (serial ports -> crash-safe MCAP), optionally with a live view in
rerun and a live Foxglove server (child processes on the daemon's live bus)."""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import threading
from pathlib import Path

from fieldlog.fusion.methods import KF
from fieldlog.tools.commands.common import METHODS, add_out_dir, command_parser, needs_extras, require_extras


def add_parser(sub) -> None:
    s = command_parser(sub, "acquire", "the acquisition daemon: serial ports -> crash-safe MCAP",
                       quiet_help="no status line (a service's journal gets the events only); twice: warnings and "
                                  "errors only",
                       verbose_help="debug lines too (with -q: the status line once per status interval) (default: "
                                    "info: start, files, port events, stop)")
    s.add_argument("--daq", default=None, metavar="PORT", help="DAQ serial port (default: [daq] port of --config)")
    s.add_argument("--gps", default=None, metavar="PORT",
                   help="GPS serial port, or gpsd://HOST[:PORT][/DEVICE] to read the receiver's own bytes through a "
                        "running gpsd (default: [gps] port of --config)")
    s.add_argument("--can", default=None, metavar="URL",
                   help="the car's CAN bus: slcan://PORT[@BITRATE] (an SLCAN serial adapter; BITRATE in bit/s) or "
                        "socketcan://IFACE (default: [can] url of --config, else none)")
    s.add_argument("--dbc", default=None, metavar="FILE",
                   help="--can: decode through this DBC with the [can.signals] of --config (default: [can] dbc)")
    add_out_dir(s, "output directory (default: [output] dir of --config, else drives/)", default=None)
    s.add_argument("--config", default=None, metavar="FILE",
                   help="TOML config; acquire/config.py documents the keys (default: none, all defaults)")
    s.add_argument("--time-scale", type=float, default=None, metavar="X",
                   help="for simulator playback at `sim --serve --speed X` only: the host clock runs X times "
                        "slower than the data ([timesync] host_time_scale; default: 1, real time)")
    s.add_argument("--view", action="store_true",
                   help="also show the car live in rerun (a child `fieldlog view --live` on the live bus)")
    s.add_argument("--view-rrd", default=None, metavar="FILE",
                   help="--view into this .rrd instead of a viewer (default: a viewer)")
    s.add_argument("--foxglove", default=None, metavar="[HOST:]PORT",
                   help="also serve the car live over the Foxglove WebSocket protocol: the derived topics as on the "
                        "live bus (/imu with its live stamps) and the live fusion's /fusion/<method>/*, /tf, "
                        "/tf_static (a child `fieldlog view --live BUS --foxglove`; HOST default 127.0.0.1, PORT 0: "
                        "any free port; prints 'foxglove: serving ws://HOST:PORT'; needs fieldlog[foxglove])")
    s.add_argument("--view-method", choices=METHODS, default=KF.name, help="--view and --foxglove: fusion method")
    s.set_defaults(func=needs_extras(run))


def run(a: argparse.Namespace) -> int:
    from fieldlog.acquire import config, daemon

    if a.foxglove is not None:
        from fieldlog.tools.foxglove_live import parse_address   # (the fusion stack stays out of this process)

        parse_address(a.foxglove)
        require_extras("foxglove")
    daemon.setup_logging(a.verbose - a.quiet)  # the daemon's own format: timestamped lines for the journal
    cfg = config.load(a.config, {"daq": a.daq, "gps": a.gps, "can": a.can, "dbc": a.dbc, "out": a.out_dir,
                                 "time_scale": a.time_scale})
    view = a.view or a.view_rrd
    if not view and a.foxglove is None:
        return daemon.run_daemon(cfg, quiet=a.quiet > 0)
    import tempfile

    if view:
        from fieldlog.replay.view import has_display

        if not a.view_rrd and not has_display():
            raise ValueError("--view: no display to open the viewer on (use --view-rrd FILE)")
    if not cfg.daemon.bus:  # the viewers need the live bus
        cfg.daemon.bus = str(Path(tempfile.gettempdir()) / f"fieldlog-{os.getpid()}.sock")
    # The viewers run as child processes reading the live bus, so fusion, rendering and their clients never take
    # the GIL from the acquisition threads, and a slow or failed viewer never stalls the recording (the bus drops
    # a client that falls behind). Each ends when the daemon closes the bus.
    live = [sys.executable, "-m", "fieldlog", "view", "--live", cfg.daemon.bus, "--method", a.view_method]
    argvs = []
    if view:
        argvs.append(("view", [*live, *(["--rrd", a.view_rrd] if a.view_rrd else [])]))
    if a.foxglove is not None:
        argvs.append(("foxglove", [*live, "--foxglove", a.foxglove, *(["--config", a.config] if a.config else [])]))
    stopping = threading.Event()
    children: list[subprocess.Popen] = []
    try:
        for name, argv in argvs:
            children.append(subprocess.Popen(argv))
            threading.Thread(target=_watch, args=(name, children[-1], stopping), daemon=True).start()
        rc = daemon.run_daemon(cfg, quiet=a.quiet > 0)
    except BaseException:
        stopping.set()
        for child in children:
            child.terminate()  # the daemon did not run to its end: there may be no bus to wait for
        raise
    finally:
        stopping.set()
        for child in children:
            try:
                child.wait(timeout=30)  # it ends when the daemon closes the bus
            except subprocess.TimeoutExpired:
                child.terminate()
                child.wait(timeout=10)
    return rc


def _watch(name: str, child: subprocess.Popen, stopping: threading.Event) -> None:
    """Log a viewer child that fails while the daemon records (the recording goes on without it)."""
    from fieldlog.acquire.daemon import log

    rc = child.wait()
    if rc and not stopping.is_set():
        log.warning(f"--{name}: the child `fieldlog view --live` ended with exit code {rc}; recording continues")
