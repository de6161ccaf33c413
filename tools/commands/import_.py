"""``fieldlog import``: build a drive from raw captures made elsewhere (a receiver log, a DAQ capture, a CAN
log)."""
from __future__ import annotations

import argparse
import datetime as dt

from fieldlog.tools.commands.common import command_parser, log, needs_extras


def add_parser(sub) -> None:
    s = command_parser(sub, "import", "build a drive from raw captures made elsewhere")
    s.add_argument("--gps", default=None, metavar="FILE",
                   help="GPS log from any receiver or logger: NMEA, u-blox UBX, NovAtel OEM (auto-detected, mixed) "
                        "(default: none; give --gps, --can or both)")
    s.add_argument("--daq", default=None, metavar="FILE", help="DAQ byte capture (default: none, GPS only)")
    s.add_argument("--can", default=None, metavar="LOG",
                   help="CAN log: candump .log, Vector .asc or .blf (python-can's readers) (default: none)")
    s.add_argument("--dbc", default=None, metavar="FILE", help="--can: decode through this DBC (default: [can] dbc "
                   "of --config; none: the frames are recorded only)")
    s.add_argument("--signal", action="append", default=[], metavar="KEY=MESSAGE.SIGNAL",
                   help="--can: a [can.signals] entry, e.g. wheel_rl=WHEEL_SPEEDS.WHEEL_SPEED_RL (repeatable; keys "
                        "wheel_fl/fr/rl/rr, vehicle_speed, gear, reverse, steering)")
    s.add_argument("--config", default=None, metavar="FILE",
                   help="--can: an acquire config whose [can] table (dbc, signals, forward, latency_s) applies "
                        "(default: none)")
    when = s.add_mutually_exclusive_group()
    when.add_argument("--start", default=None, metavar="ISO-TIME",
                      help="--can with boot-relative stamps: the UTC of its first frame, e.g. 2024-05-01T09:30:00Z "
                           "(default: the GPS log's start; neither: refused)")
    when.add_argument("--align-to", default=None, metavar="DRIVE",
                      help="--can with boot-relative stamps: its first frame at this drive's first log time "
                           "(default: none)")
    s.add_argument("--fs", type=float, default=500.0, help="DAQ sample rate, Hz")
    s.add_argument("--pps", choices=["flag", "latch"], default="flag", help="how the DAQ frames carry the PPS")
    s.add_argument("--out", required=True, help="output MCAP")
    s.set_defaults(func=needs_extras(run))


def can_config(a: argparse.Namespace):
    """``[can]`` of ``--config`` with --dbc and --signal KEY=MESSAGE.SIGNAL over it, as the pipeline's BusConfig."""
    from fieldlog.acquire import config

    c = config.from_file(a.config).can if a.config else config.CanConfig()
    c.dbc = a.dbc or c.dbc
    for sig in a.signal:
        key, eq, ref = sig.partition("=")
        if not eq or not key or not ref:
            raise ValueError(f"--signal {sig!r}: expected KEY=MESSAGE.SIGNAL, e.g. wheel_rl=WHEEL_SPEEDS.RL")
        c.signals[key.strip()] = ref.strip()
    return config.bus_config(c, "frames")


def can_first_ns(a: argparse.Namespace) -> int | None:
    """The UTC of a boot-relative CAN log's first frame, ns: ``--start``, or ``--align-to``'s drive's first log
    time; None for neither."""
    if a.start is not None:
        try:
            t = dt.datetime.fromisoformat(a.start)
        except ValueError:
            raise ValueError(f"--start {a.start!r}: not an ISO time; give e.g. 2024-05-01T09:30:00Z") from None
        t = t if t.tzinfo is not None else t.replace(tzinfo=dt.timezone.utc)
        return (t - dt.datetime(1970, 1, 1, tzinfo=dt.timezone.utc)) // dt.timedelta(microseconds=1) * 1000
    if a.align_to is not None:
        from fieldlog.drive.drive import Drive

        start = Drive.open(a.align_to).start_ns
        if start is None:
            raise ValueError(f"--align-to {a.align_to}: the drive holds no message to align to")
        return start
    return None


def run(a: argparse.Namespace) -> int:
    from fieldlog.tools.importer import import_captures

    if a.gps is None and a.can is None:
        raise ValueError("give --gps FILE, --can LOG or both")
    if a.can is None and (a.dbc or a.signal):
        raise ValueError("--dbc and --signal decode a CAN log: give it with --can LOG")
    bus = can_config(a) if a.can is not None else None
    res = import_captures(a.gps, a.daq, a.out, fs_hz=a.fs, pps_mode=a.pps, can_log=a.can, can_bus=bus,
                          force=a.force, can_first_ns=can_first_ns(a))
    line = (f"wrote {a.out}: {res.imu_samples} IMU samples, {res.gps_epochs} GPS epochs "
            f"({res.counters.gps_no_fix} without fix), {res.counters.nmea.lines} NMEA lines, "
            f"{res.counters.nmea.bad_checksum} bad checksums")
    log.info(line + (f", {res.vehicle_frames} CAN frames ({res.vehicle_twists} /vehicle/twist)" if a.can else ""))
    return 0
