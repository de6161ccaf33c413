"""``fieldlog sim``: simulate a drive through the real acquisition code, or serve it on pseudo-terminals."""
from __future__ import annotations

import argparse
import ctypes
import time

from fieldlog.tools.commands.common import Progress, command_parser, log, needs_extras

M_TRIM_THRESHOLD, M_MMAP_THRESHOLD, M_ARENA_MAX = -1, -3, -8   # glibc's mallopt parameters (malloc.h)
MMAP_THRESHOLD = 32 << 20                       # bytes: the largest glibc takes


def add_parser(sub) -> None:
    s = command_parser(sub, "sim", "simulate a drive through the real acquisition code")
    s.add_argument("--scenario", default="figure8", help="scenario name (tools/sim/scenarios) or a TOML path")
    s.add_argument("--duration", type=float, default=None, help="seconds (default: the scenario's)")
    s.add_argument("--seed", type=int, default=1, help="random seed of the sensor errors and clocks")
    s.add_argument("--pps", choices=["flag", "latch"], default=None,
                   help="PPS as a sampled flag or a latch (default: the scenario's, else flag)")
    s.add_argument("--receiver", choices=["nmea", "ublox", "novatel", "septentrio"], default=None,
                   help="the GPS port's protocol (default: the scenario's, NMEA): u-blox sends GGA + UBX NAV-PVT "
                        "+ TIM-TP, NovAtel BESTPOSA + BESTVELA + TIMEA, Septentrio SBF PVTGeodetic + "
                        "PosCovGeodetic + VelCovGeodetic + ReceiverTime + xPPSOffset")
    s.add_argument("--can", action="store_true",
                   help="the car's CAN bus too: wheel speeds, steering, gear on an SLCAN adapter (data/sim-car.dbc)")
    s.add_argument("--mounting", type=_mounting, default=None, metavar="ROLL,PITCH,YAW",
                   help="the IMU's true mounting to base_link, degrees (default: the scenario's [imu] "
                        "mounting_rpy_deg, else 0,0,0); the drive's /tf_static keeps the nominal zero")
    s.add_argument("--imu-delay", type=float, default=None, metavar="S",
                   help="the IMU's true delay (filter and transport), s: its samples are stamped this late "
                        "(default: the scenario's [imu] delay_s, else 0; at least its [imu] filter's own delay, "
                        "figure8-real's 0.0054 s)")
    s.add_argument("--out", default=None, help="output MCAP (required without --serve)")
    s.add_argument("--serve", action="store_true", help="stream to pseudo-terminals instead (prints their paths)")
    s.add_argument("--speed", type=float, default=1.0, help="--serve: times real time")
    s.add_argument("--truth", default=None, metavar="FILE",
                   help="--serve: write /truth/* and what was sent to this MCAP at the end (default: none)")
    s.add_argument("--unplug", action="append", default=[], metavar="PORT:START:LEN",
                   help="--serve: close PORT's pty for LEN s at START s of the drive (repeatable; default: never)")
    s.add_argument("--link-dir", default=None, metavar="DIR",
                   help="--serve: keep symlinks DIR/daq, DIR/gps (and DIR/can) to the current ptys (default: none)")
    s.add_argument("--hold", action="store_true", help="--serve: wait for SIGUSR1 before streaming")
    s.add_argument("--corrupt", type=float, default=0.0, metavar="FRACTION",
                   help="--serve: corrupt this fraction of the bytes of both ports (e.g. 0.01)")
    s.add_argument("--corrupt-counters", type=float, default=0.0, metavar="FRACTION",
                   help="--serve: give this fraction of the DAQ frames a wrong counter with a matching CRC, so that "
                        "they pass the decoder's checks (e.g. 0.001; applied before --corrupt)")
    s.add_argument("--repeat-reads", type=float, default=0.0, metavar="P",
                   help="--serve: deliver each DAQ read twice with probability P, the copy right after it (a "
                        "replaying adapter; e.g. 0.01; applied after --corrupt)")
    s.add_argument("--clock-jump", action="append", default=[], metavar="START:LEN:OFFSET",
                   help="--serve: the receiver writes its time OFFSET s off for LEN s from START s of the drive, "
                        "e.g. 900:30:3600 (repeatable; default: never)")
    s.add_argument("--board", choices=["simulated", "emulated"], default="simulated",
                   help="--serve: the DAQ port is the simulator's frames, or the firmware's under QEMU fed by the "
                        "simulator (firmware/README.md; needs qemu-system-arm and `make firmware`)")
    s.add_argument("--board-image", default=None, metavar="ELF",
                   help="--serve --board emulated: the firmware image (default: firmware/build/qemu/fieldlog-qemu.elf)")
    s.set_defaults(func=needs_extras(run))


def _mounting(text: str) -> tuple[float, float, float]:
    """``--mounting ROLL,PITCH,YAW`` (degrees)."""
    try:
        out = tuple(float(x) for x in text.split(","))
    except ValueError:
        out = ()
    if len(out) != 3:
        raise argparse.ArgumentTypeError(f"{text!r}: expected ROLL,PITCH,YAW in degrees, e.g. 2,-4,5")
    return out


def run(a: argparse.Namespace) -> int:
    if a.serve and (a.mounting is not None or a.imu_delay is not None):
        raise ValueError("--mounting and --imu-delay: with --out only (a scenario's [imu] sets them for --serve)")
    if a.serve:
        return serve(a)
    if not a.out:
        raise ValueError("--out is required (or --serve)")
    _reuse_freed_memory()
    from fieldlog.tools.sim.simulate import simulate

    t0 = time.monotonic()
    res = simulate(a.scenario, a.duration, a.seed, a.out, pps_mode=a.pps, progress=Progress(f"sim {a.scenario}"),
                   receiver=a.receiver, can=a.can, force=a.force, mounting_rpy_deg=a.mounting,
                   imu_delay_s=a.imu_delay)
    log.info(f"wrote {res.path}: {res.imu_samples} IMU samples, {res.gps_epochs} GPS epochs, {res.reads} serial "
             f"reads in {time.monotonic() - t0:.1f} s")
    return 0


def _reuse_freed_memory() -> None:
    """Have glibc's malloc keep the memory of freed arrays for the next ones. A simulation makes and drops
    whole-drive numpy arrays one after another; by default each one at or above the mmap threshold (which slides
    up to the largest array freed, so an array of that size is mapped again) gets fresh pages of its own, which
    the kernel clears at first touch and takes back when it is freed. The thresholds are fixed where glibc's own
    rule takes them once an array of ``MMAP_THRESHOLD`` bytes is freed (trimming at twice it). All threads share
    one arena: the arrays that the threads beside the simulation's main thread free (its sensor errors' draws) are
    then reused by the next arrays of any thread, where a thread's own arena would keep them from the others, so
    the main thread's next arrays would take fresh pages. A C library without mallopt is left as it is."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return
    mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)
    mallopt(M_TRIM_THRESHOLD, 2 * MMAP_THRESHOLD)
    mallopt(M_ARENA_MAX, 1)


def serve(a: argparse.Namespace) -> int:
    from fieldlog.tools.sim.serve import Unplug, parse_clock_jump, serve

    return serve(a.scenario, a.duration, a.seed, a.speed, pps_mode=a.pps, receiver=a.receiver, truth=a.truth,
                 unplug=[Unplug.parse(u) for u in a.unplug], link_dir=a.link_dir, hold=a.hold,
                 corrupt=a.corrupt, clock_jumps=[parse_clock_jump(j) for j in a.clock_jump], board=a.board,
                 board_image=a.board_image, can=a.can, force=a.force,
                 corrupt_counters_frac=a.corrupt_counters, repeat_reads=a.repeat_reads)
