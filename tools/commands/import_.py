"""``fieldlog import``: build a drive from raw captures made elsewhere (a receiver log, a DAQ capture, a CAN
log)."""
from __future__ import annotations

import argparse

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


def run(a: argparse.Namespace) -> int:
    from fieldlog.tools.importer import import_captures

    if a.gps is None and a.can is None:
        raise ValueError("give --gps FILE, --can LOG or both")
    if a.can is None and (a.dbc or a.signal):
        raise ValueError("--dbc and --signal decode a CAN log: give it with --can LOG")
    bus = can_config(a) if a.can is not None else None
    res = import_captures(a.gps, a.daq, a.out, fs_hz=a.fs, pps_mode=a.pps, can_log=a.can, can_bus=bus,
                          force=a.force)
    line = (f"wrote {a.out}: {res.imu_samples} IMU samples, {res.gps_epochs} GPS epochs "
            f"({res.counters.gps_no_fix} without fix), {res.counters.nmea.lines} NMEA lines, "
            f"{res.counters.nmea.bad_checksum} bad checksums")
    log.info(line + (f", {res.vehicle_frames} CAN frames ({res.vehicle_twists} /vehicle/twist)" if a.can else ""))
    return 0
