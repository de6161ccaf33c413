"""The ``fieldlog`` command line (contract names: design section 2)."""
from __future__ import annotations

import argparse
import errno
import os
import sys
import time
from pathlib import Path


# fusion.engine.METHODS, spelled out so that `fieldlog --help` does not import the fusion stack
# (tests/test_drive.py checks the two agree)
METHODS = ("ins", "kf", "dkf", "rbfn", "tdln", "dkf-rbfn", "kf-ukf", "hinf", "sckf", "ssr-sckf")

# Optional dependencies (pyproject.toml extras) by top-level module: a command that needs one that is not
# installed says which extra to install, in one line.
EXTRAS = {"numba": "fusion", "llvmlite": "fusion", "rerun": "view", "polars": "export", "pyarrow": "export",
          "matplotlib": "plots", "dask": "batch", "distributed": "batch"}


class MissingExtra(ValueError):
    """An optional dependency of the command is not installed (reported like a bad argument: one line, exit 2)."""


def needs_extras(func):
    """Wrap a command so that an ImportError of an optional dependency becomes ``MissingExtra``."""

    def run(a: argparse.Namespace) -> int:
        try:
            return func(a)
        except ModuleNotFoundError as e:
            root = (e.name or "").split(".")[0]
            if root not in EXTRAS:
                raise
            raise MissingExtra(f"{root} is not installed: pip install 'fieldlog[{EXTRAS[root]}]' "
                               f"(or 'fieldlog[all]')") from None

    return run


DRIVE_HELP = ("the drive: an MCAP file, several files, a rotated session's directory or a rosbag2 directory (read "
              "as one drive, in log-time order)")


def drive_arg(paths: list[str]) -> str | list[str]:
    """The drive positional(s) as ``replay.drive`` takes them: one path, or the list."""
    return paths[0] if len(paths) == 1 else paths


class Progress:
    """A one-line progress display on a terminal; silent otherwise."""

    def __init__(self, label: str) -> None:
        self.label = label
        self.tty = sys.stderr.isatty()
        self.t0 = time.monotonic()

    def __call__(self, fraction: float) -> None:
        if self.tty:
            sys.stderr.write(f"\r{self.label}: {fraction * 100:5.1f} %  {time.monotonic() - self.t0:6.1f} s")
            if fraction >= 1.0:
                sys.stderr.write("\n")
            sys.stderr.flush()


def output_parent(path: str | None) -> None:
    """Create the directory an output file goes to (an OSError naming it when that is impossible, before any
    work is done)."""
    if path:
        Path(path).parent.mkdir(parents=True, exist_ok=True)


def cmd_sim(a: argparse.Namespace) -> int:
    if a.serve:
        return cmd_sim_serve(a)
    if not a.out:
        raise ValueError("--out is required (or --serve)")
    from fieldlog.tools.sim.simulate import simulate

    t0 = time.monotonic()
    res = simulate(a.scenario, a.duration, a.seed, a.out, pps_mode=a.pps, progress=Progress(f"sim {a.scenario}"),
                   receiver=a.receiver, can=a.can)
    print(f"wrote {res.path}: {res.imu_samples} IMU samples, {res.gps_epochs} GPS epochs, {res.reads} serial reads "
          f"in {time.monotonic() - t0:.1f} s")
    return 0


def cmd_sim_serve(a: argparse.Namespace) -> int:
    from fieldlog.tools.sim.serve import Unplug, parse_clock_jump, serve

    return serve(a.scenario, a.duration, a.seed, a.speed, pps_mode=a.pps, receiver=a.receiver, truth=a.truth,
                 unplug=[Unplug.parse(u) for u in a.unplug], link_dir=a.link_dir, hold=a.hold,
                 corrupt=a.corrupt, clock_jumps=[parse_clock_jump(j) for j in a.clock_jump], board=a.board,
                 board_image=a.board_image, can=a.can)


def cmd_acquire(a: argparse.Namespace) -> int:
    from fieldlog.acquire import config, daemon

    daemon.setup_logging(a.verbose - a.quiet)
    cfg = config.load(a.config, {"daq": a.daq, "gps": a.gps, "can": a.can, "dbc": a.dbc, "out": a.out,
                                 "time_scale": a.time_scale})
    if not (a.view or a.view_rrd):
        return daemon.run_daemon(cfg, quiet=a.quiet > 0)
    import subprocess
    import tempfile

    from fieldlog.replay.view import has_display

    if not a.view_rrd and not has_display():
        raise ValueError("--view: no display to open the viewer on (use --view-rrd FILE)")
    if not cfg.daemon.bus:  # the view needs the live bus
        cfg.daemon.bus = str(Path(tempfile.gettempdir()) / f"fieldlog-{os.getpid()}.sock")
    # the view runs as a child process, so fusion and rendering never take the GIL from the acquisition threads
    viewer = subprocess.Popen([sys.executable, "-m", "fieldlog", "view", "--live", cfg.daemon.bus, "--method",
                               a.view_method, *(["--rrd", a.view_rrd] if a.view_rrd else [])])
    try:
        rc = daemon.run_daemon(cfg, quiet=a.quiet > 0)
    finally:
        try:
            viewer.wait(timeout=30)  # it ends when the daemon closes the bus
        except subprocess.TimeoutExpired:
            viewer.terminate()
            viewer.wait(timeout=10)
    return rc


def cmd_recover(a: argparse.Namespace) -> int:
    """One file: recovered whatever it is. A session or rosbag2 directory, or several files: each cut-short file,
    and each complete one with a damaged chunk (every chunk's CRC checked), recovered next to it (the drive then
    reads NAME.recovered.mcap in its place), the complete and sound ones left. A directory's every MCAP file on
    disk is looked at (a session's metadata.yaml lists only the files closed before a crash), and its
    metadata.yaml is written again when a file was recovered or there was none."""
    from fieldlog.acquire.bagdir import METADATA, rewrite_metadata, session_files
    from fieldlog.replay.drive import RECOVERED, drive_files
    from fieldlog.replay.mcapfile import McapFile, TruncatedError

    if len(a.drive) == 1 and not Path(a.drive[0]).is_dir():
        return _recover_one(Path(a.drive[0]), Path(a.out) if a.out else None)
    if a.out:
        raise ValueError(f"{' '.join(a.drive)}: --out takes one damaged file; a drive of several files is recovered "
                         f"next to them (NAME{RECOVERED})")
    for spec in a.drive:
        d = Path(spec)
        recovered = False
        for src in session_files(d) if d.is_dir() else drive_files(spec):
            if src.name.endswith(RECOVERED):
                print(f"{src}: recovered already")
                continue
            try:
                damaged = McapFile(src).damaged()
            except TruncatedError:
                recovered = _recover_one(src, None) == 0 or recovered
                continue
            if damaged:
                print(f"{src}: damaged chunk{'s' * (len(damaged) > 1)} at byte {', '.join(map(str, damaged))}")
                recovered = _recover_one(src, None) == 0 or recovered
            else:
                print(f"{src}: complete, nothing to recover")
        if d.is_dir() and (recovered or not (d / METADATA).exists()):
            meta, left = rewrite_metadata(d)
            print(f"wrote {meta}" + (f" (left out, no summary: {', '.join(str(f) for f in left)})" if left else ""))
    return 0


def _recover_one(src: Path, out: Path | None) -> int:
    from fieldlog.acquire.recovery import recover_drive
    from fieldlog.replay.drive import RECOVERED

    out = out or src.with_name(src.stem + RECOVERED)
    if out.resolve() == src.resolve():
        raise ValueError("--out must differ from the damaged file (it is kept as it is)")
    rep = recover_drive(src, out)
    state = "was already complete" if rep.had_summary else f"{rep.bytes_discarded} bytes after the last complete " \
                                                            f"chunk discarded"
    if rep.damaged:
        state += f"; {len(rep.damaged)} damaged chunk{'s' * (len(rep.damaged) > 1)} skipped, at byte " + \
            ", ".join(str(x) for x in rep.damaged)
    print(f"wrote {out}: {sum(rep.messages.values())} messages in {rep.chunks} chunks ({state}), "
          f"{sum(rep.rederived.values())} tail messages re-derived from the raw reads")
    for topic in sorted(set(rep.messages) | set(rep.rederived)):
        print(f"  {topic:<20} {rep.messages.get(topic, 0)}" + (f" + {rep.rederived[topic]} re-derived"
                                                                 if rep.rederived.get(topic) else ""))
    return 0


def cmd_info(a: argparse.Namespace) -> int:
    from fieldlog.tools.info import drive_info, format_info

    info = drive_info(drive_arg(a.drive), scan=a.scan,
                      progress=None if a.json else Progress("info: reading the messages"))
    print(info.to_json() if a.json else format_info(info))
    return 0


def add_out_args(s: argparse.ArgumentParser) -> None:
    """--out, and --bag to make it a one-file rosbag2 directory (acquire/bagdir.py)."""
    s.add_argument("--out", required=True, help="output MCAP (with --bag: the rosbag2 directory)")
    s.add_argument("--bag", action="store_true",
                   help="write --out as a rosbag2 directory: OUT/OUT.mcap and its metadata.yaml, which `ros2 bag "
                        "info/play` and rosbags open (default: one MCAP file)")


def out_file(a: argparse.Namespace) -> Path:
    """The MCAP file to write: --out, or with --bag the one file of the rosbag2 directory --out."""
    from fieldlog.acquire.bagdir import bag_file

    return bag_file(Path(a.out)) if a.bag else Path(a.out)


def finish_out(a: argparse.Namespace, path: Path) -> None:
    """With --bag: the directory's metadata.yaml for the file just written."""
    if a.bag:
        from fieldlog.acquire.bagdir import write_bag_metadata

        print(f"wrote {write_bag_metadata(path)}")


def cmd_filter(a: argparse.Namespace) -> int:
    from fieldlog.tools.filter import filter_drive

    topics = [t.strip() for t in a.topics.split(",") if t.strip()] if a.topics else None
    out = out_file(a)
    res = filter_drive(drive_arg(a.drive), out, a.start, a.end, topics, progress=Progress("filter"))
    print(f"wrote {res.path.resolve()}: {sum(res.messages.values())} messages from {res.start_ns} to {res.end_ns} ns")
    for topic, n in res.messages.items():
        print(f"  {topic:<24} {n}")
    finish_out(a, out)
    return 0


def import_can_config(a: argparse.Namespace):
    """``[can]`` of ``--config`` with --dbc and --signal KEY=MESSAGE.SIGNAL over it, as the pipeline's BusConfig."""
    from fieldlog.acquire import config

    c = config.from_dict(config.read_toml(a.config)).can if a.config else config.CanConfig()
    c.dbc = a.dbc or c.dbc
    for sig in a.signal:
        key, eq, ref = sig.partition("=")
        if not eq or not key or not ref:
            raise ValueError(f"--signal {sig!r}: expected KEY=MESSAGE.SIGNAL, e.g. wheel_rl=WHEEL_SPEEDS.RL")
        c.signals[key.strip()] = ref.strip()
    return config.bus_config(c, "frames")


def cmd_import(a: argparse.Namespace) -> int:
    from fieldlog.tools.importer import import_captures

    if a.gps is None and a.can is None:
        raise ValueError("give --gps FILE, --can LOG or both")
    if a.can is None and (a.dbc or a.signal):
        raise ValueError("--dbc and --signal decode a CAN log: give it with --can LOG")
    bus = import_can_config(a) if a.can is not None else None
    res = import_captures(a.gps, a.daq, a.out, fs_hz=a.fs, pps_mode=a.pps, can_log=a.can, can_bus=bus)
    line = (f"wrote {a.out}: {res.imu_samples} IMU samples, {res.gps_epochs} GPS epochs "
            f"({res.counters.gps_no_fix} without fix), {res.counters.nmea.lines} NMEA lines, "
            f"{res.counters.nmea.bad_checksum} bad checksums")
    print(line + (f", {res.vehicle_frames} CAN frames ({res.vehicle_twists} /vehicle/twist)" if a.can else ""))
    return 0


def cmd_rebuild(a: argparse.Namespace) -> int:
    from fieldlog.tools.rebuild import rebuild

    out = out_file(a)
    res = rebuild(drive_arg(a.drive), out, calibration=a.calib, progress=Progress("rebuild"))
    print(f"wrote {out}: {res.imu_samples} IMU samples, {res.gps_epochs} GPS epochs from {res.reads} raw reads")
    finish_out(a, out)
    return 0


def cmd_allan(a: argparse.Namespace) -> int:
    from fieldlog.tools.allan import drive_report

    print(drive_report(drive_arg(a.drive), plot_prefix=a.plot))
    return 0


def input_spec(a: argparse.Namespace):
    """``replay.inputs.InputSpec`` of --imu-topic, --fix-topic, --vel-topic, --imu-frame."""
    from fieldlog.replay.inputs import InputSpec

    return InputSpec(a.imu_topic, a.fix_topic, a.vel_topic, a.imu_frame)


def add_input_args(s: argparse.ArgumentParser) -> None:
    """The input mapping of a drive from another logger (replay/inputs.py; also a config's [input] table)."""
    s.add_argument("--imu-topic", default=None, metavar="T", help="sensor_msgs/msg/Imu topic (default: /imu, else "
                   "the drive's only Imu topic)")
    s.add_argument("--fix-topic", default=None, metavar="T", help="sensor_msgs/msg/NavSatFix topic (default: "
                   "/gps/fix, else the only NavSatFix topic)")
    s.add_argument("--vel-topic", default=None, metavar="T", help="TwistWithCovarianceStamped ENU velocity topic "
                   "(default: /gps/vel if present; 'none': position-only updates)")
    s.add_argument("--imu-frame", choices=["rfu", "flu", "frd"], default=None,
                   help="IMU body frame (default: from /tf_static, else rfu for fieldlog drives, flu (REP-103) else)")


def cmd_fuse(a: argparse.Namespace) -> int:
    from fieldlog.replay.inputs import RATE_HZ
    from fieldlog.tools.fuse import NO_ALIGNMENT, fuse, parse_outage, settings

    drive = drive_arg(a.drive)
    st = settings(drive, a.config, input_spec(a), tuple(parse_outage(o) for o in a.outage or ()))
    for line in st.lines(drive):
        if line.startswith("warning"):
            print(f"fieldlog fuse: {line}", file=sys.stderr)
        else:
            print(line)
    t0 = time.monotonic()
    out = out_file(a)
    res = fuse(drive, a.method, out, st.config, progress=Progress(f"fuse {a.method}"), smooth=a.smooth,
               inputs=st.inputs)
    print(f"wrote {res.path}: {res.rows} solutions from {res.imu_samples} IMU samples ({res.imu_rate_hz:.0f} Hz, "
          f"{res.imu_gaps} gaps bridged, {res.imu_missing} samples missing), {res.updates} GPS updates, "
          f"{res.outages} outage windows in {time.monotonic() - t0:.1f} s")
    if res.alignment:
        print(f"alignment: {res.alignment}")
    lo, hi = RATE_HZ
    if not lo <= res.imu_rate_hz <= hi:
        print(f"fieldlog fuse: warning: IMU rate {res.imu_rate_hz:.0f} Hz is outside {lo:.0f}-{hi:.0f} Hz",
              file=sys.stderr)
    if res.rows == 0 and a.method != "ins":
        print(f"fieldlog fuse: warning: {NO_ALIGNMENT}", file=sys.stderr)
    finish_out(a, out)
    return 0


def cmd_evaluate(a: argparse.Namespace) -> int:
    from fieldlog.tools.evaluate import check_methods, evaluate

    methods = [m.strip() for m in a.methods.split(",") if m.strip()]
    check_methods(methods)
    try:
        lengths = [float(x) for x in a.outages.split(",")]
    except ValueError:
        raise ValueError(f"--outages expects lengths in s separated by commas, got {a.outages!r}") from None
    if not lengths or min(lengths) <= 0:
        raise ValueError("--outages: lengths must be > 0")
    report = Path(a.report)
    drives = [Path(d) for d in a.drive]
    if a.paper:
        from fieldlog.tools.evaluate import PAPER_LENGTHS, PAPER_METHODS, PAPER_SEEDS

        methods, lengths = list(PAPER_METHODS), list(PAPER_LENGTHS)
        if not drives and not a.seeds:
            a.seeds = PAPER_SEEDS
    if a.seeds:
        from fieldlog.tools.sim.simulate import simulate

        (report / "drives").mkdir(parents=True, exist_ok=True)
        for seed in range(1, a.seeds + 1):
            path = report / "drives" / f"{a.scenario}_s{seed}.mcap"
            print(f"simulating {a.scenario} {a.duration:g} s seed {seed} -> {path}")
            simulate(a.scenario, a.duration, seed, path, progress=Progress(f"sim {a.scenario} seed {seed}"))
            drives.append(path)
    for d in drives:
        if not d.exists():
            raise FileNotFoundError(f"{d} does not exist")
    t0 = time.monotonic()
    from fieldlog.tools.fuse import load_fusion_config

    from fieldlog.acquire.config import read_toml
    from fieldlog.tools.fuse import load_input_spec

    evaluate(drives, lengths, methods, report, smooth=a.smooth,
             config=load_fusion_config(a.config) if a.config and "fusion" in read_toml(a.config) else None,
             spec=load_input_spec(a.config).merged(input_spec(a)), paper=a.paper)
    print((report / "table.md").read_text())
    print(f"wrote {report / 'table.md'} and {report / 'table.csv'} in {time.monotonic() - t0:.1f} s")
    return 0


def cmd_study(a: argparse.Namespace) -> int:
    from fieldlog.tools.studies import study

    study(a.name, Path(a.out or f"docs/studies/{a.name}"), Path(a.work or f"out/studies/{a.name}"), a.seeds, a.runs)
    return 0


def cmd_demo(a: argparse.Namespace) -> int:
    """Simulate, look, fuse, evaluate and view: the whole pipeline through the same commands a user types."""
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    drive, fused, rrd, report = out / "figure8.mcap", out / "dkf-rbfn.mcap", out / "figure8.rrd", out / "report"
    steps = [
        ("simulate a figure8 drive", ["sim", "--scenario", "figure8", "--duration", f"{a.duration:g}", "--seed", "1",
                                      "--out", str(drive)]),
        ("what the drive holds", ["info", str(drive)]),
        ("fuse with the KF+RBFN hybrid through a 30 s GPS outage",
         ["fuse", str(drive), "--method", "dkf-rbfn", "--outage", "180:30", "--out", str(fused)]),
        ("the outage study", ["evaluate", str(drive), "--outages", "30", "--methods", "ins,dkf,dkf-rbfn",
                              "--report", str(report)]),
        ("a rerun recording", ["view", str(drive), str(fused), "--rrd", str(rrd)]),
    ]
    for i, (title, argv) in enumerate(steps, 1):
        print(f"\n{i}/{len(steps)}  {title}:  fieldlog {' '.join(argv)}\n", flush=True)
        rc = main(argv)
        if rc:
            return rc
    print(f"\nreport:  {report.resolve() / 'table.md'}\nrerun:   {_rerun()} {rrd.resolve()}   "
          f"(or: {_rerun()} {drive.resolve()})")
    return 0


def cmd_view_live(a: argparse.Namespace) -> int:
    from fieldlog.acquire import config
    from fieldlog.replay.player import live_view

    address = a.live or config.load(a.config, {"daq": "-", "gps": "--"}).daemon.bus
    if not address:
        raise ValueError("no live bus: give its socket path (--live PATH) or a config with [daemon] bus")
    output_parent(a.rrd)
    try:
        res = live_view(address, a.method, rrd=a.rrd, connect=a.connect)
    except KeyboardInterrupt:
        return 130
    print(f"viewed {res.data_s:.1f} s live from {address}: {res.solutions} {a.method} solutions, {res.gps_fixes} GPS "
          f"fixes, {res.imu_rows} IMU rows, {res.outages} outages -> {res.sink}")
    return 0


def cmd_view(a: argparse.Namespace) -> int:
    from fieldlog.replay.view import split_fused, view

    if a.live is not None:
        if a.drive or a.fused:
            raise ValueError("--live takes no drive files")
        return cmd_view_live(a)
    if a.drive is None:
        raise ValueError("a drive is required (or --live)")
    if a.connect:
        raise ValueError("--connect is for --live (and `fieldlog replay`)")
    t0 = time.monotonic()
    from fieldlog.tools.fuse import input_map, load_input_spec

    files, fused = split_fused([a.drive, *a.fused])
    drive = drive_arg(files)
    try:
        imap = input_map(drive, a.config, input_spec(a))
    except ValueError:
        if load_input_spec(a.config).merged(input_spec(a)).given():
            raise
        imap = None  # nothing to map (e.g. a GPS-only drive): show what the drive has
    output_parent(a.rrd)
    res = view(drive, fused, a.rrd, progress=Progress("view"), inputs=imap)
    if res.rrd is None:
        print(f"sent {' '.join(files)} to the rerun viewer")
        return 0
    size = res.rrd.stat().st_size
    print(f"wrote {res.rrd} ({size / 1e6:.1f} MB) in {time.monotonic() - t0:.1f} s: {res.gps_fixes} GPS fixes "
          f"({res.no_fix} epochs without fix), {res.imu_rows} IMU rows (decimated), methods: "
          f"{', '.join(res.methods) or 'none'}, {res.outages} outage windows\n"
          f"Open it with:  {_rerun()} {Path(res.rrd).resolve()}")
    return 0


def _rerun() -> str:
    """The rerun viewer of this installation, as an absolute path (the venv's, next to this Python)."""
    exe = Path(sys.executable).parent / "rerun"
    return str(exe) if exe.exists() else "rerun"


def cmd_export(a: argparse.Namespace) -> int:
    from fieldlog.replay.export import export

    topics = [t.strip() for t in a.topics.split(",") if t.strip()] if a.topics else None
    t0 = time.monotonic()
    try:
        written = export(drive_arg(a.drive), a.out, a.format, topics, progress=Progress("export"))
    except KeyError as e:
        raise ValueError(e.args[0]) from None
    for topic, (path, rows) in written.items():
        print(f"  {topic:<24} {rows:>9} rows  {path}")
    print(f"wrote {len(written)} tables to {a.out} in {time.monotonic() - t0:.1f} s")
    return 0

def cmd_batch(a: argparse.Namespace) -> int:
    import glob

    from fieldlog.tools.batch import run_batch, summary
    from fieldlog.tools.evaluate import check_methods

    methods = [m.strip() for m in a.methods.split(",") if m.strip()]
    check_methods(methods)
    try:
        lengths = [float(x) for x in a.outages.split(",") if x.strip()] if a.outages else []
    except ValueError:
        raise ValueError(f"--outages expects lengths in s separated by commas, got {a.outages!r}") from None
    if lengths and min(lengths) <= 0:
        raise ValueError("--outages: lengths must be > 0")
    drives = sorted({p for pattern in a.drives for p in (glob.glob(pattern) or [pattern])})
    missing = [d for d in drives if not Path(d).exists()]
    if missing:
        raise FileNotFoundError(f"{', '.join(missing)} does not exist")
    if a.workers < 1:
        raise ValueError("--workers must be >= 1")
    res = run_batch(drives, methods, lengths, a.out, scheduler=a.scheduler, workers=a.workers)
    print(summary(res.table))
    print(f"wrote {res.parquet} ({len(res.table)} rows, {len(drives) - len(res.failed)} drives ok, "
          f"{len(res.failed)} failed); batch wall time {res.wall_s:.1f} s")
    return 1 if res.failed and len(res.failed) == len(drives) else 0


def cmd_replay(a: argparse.Namespace) -> int:
    from fieldlog.replay.player import replay

    from fieldlog.tools.fuse import settings

    drive = drive_arg(a.drive)
    st = settings(drive, a.config, input_spec(a))
    output_parent(a.rrd)
    res = replay(drive, a.method, a.speed, rrd=a.rrd, connect=a.connect, config=st.config,
                 progress=Progress(f"replay {a.method}"), imap=st.inputs)
    print(f"played {res.data_s:.1f} s of {' '.join(a.drive)} in {res.wall_s:.1f} s (x{res.data_s / max(res.wall_s, 1e-9):.1f}): "
          f"{res.solutions} {a.method} solutions, {res.updates} GPS updates, {res.gps_fixes} GPS fixes, "
          f"{res.imu_rows} IMU rows, {res.outages} outages -> {res.sink}")
    return 0


EXAMPLES = """\
examples:
  fieldlog acquire --daq /dev/fieldlog-daq --gps /dev/fieldlog-gps --out drives/   # record in the car
  fieldlog info drives/20260504T093000Z_0001.mcap            # topics, rates, sync quality, gaps (--json)
  fieldlog recover drives/20260504T093000Z_0001.mcap         # after a power cut
  fieldlog filter drive.mcap --start 120 --end 300 --topics '/imu,/gps/*' --out slice.mcap
  fieldlog sim --scenario figure8 --duration 600 --out drive.mcap
  fieldlog fuse drive.mcap --method dkf-rbfn --outage 300:60 --out fused.mcap
  fieldlog evaluate --seeds 3 --outages 30,60 --methods ins,kf,dkf --report report/
  fieldlog view drive.mcap fused.mcap --rrd drive.rrd

`fieldlog COMMAND --help` for the options of one command. Commands marked [extra] need
`pip install 'fieldlog[extra]'`; `make setup` installs them all.
"""


# the extras (pyproject.toml) each command needs beyond the core install
NEEDS = {"sim": "fusion", "fuse": "fusion", "evaluate": "fusion,export,plots", "view": "view", "replay": "view",
         "export": "export", "batch": "batch", "study": "all", "demo": "all"}


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Keeps the examples' layout, and shows every option's default (those without one say so in words)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        d = action.default
        if "default" in text or d in (None, False, argparse.SUPPRESS) or d == [] or not action.option_strings:
            return text
        return f"{text} (default: %(default)s)"


def build_parser() -> argparse.ArgumentParser:
    from fieldlog import __version__

    p = argparse.ArgumentParser(prog="fieldlog", description="GPS/INS field logging, fusion and replay",
                                epilog=EXAMPLES, formatter_class=HelpFormatter)
    p.add_argument("--version", action="version", version=f"fieldlog {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    parser = sub.add_parser

    def add_parser(name: str, **kw) -> argparse.ArgumentParser:
        if name in NEEDS:
            kw["help"] += f" [{NEEDS[name]}]"
        return parser(name, formatter_class=HelpFormatter, description=kw.get("help"), **kw)

    sub.add_parser = add_parser

    s = sub.add_parser("sim", help="simulate a drive through the real acquisition code")
    s.add_argument("--scenario", default="figure8", help="scenario name (tools/sim/scenarios) or a TOML path")
    s.add_argument("--duration", type=float, default=None, help="seconds (default: the scenario's)")
    s.add_argument("--seed", type=int, default=1, help="random seed of the sensor errors and clocks")
    s.add_argument("--pps", choices=["flag", "latch"], default=None,
                   help="PPS as a sampled flag or a latch (default: the scenario's, else flag)")
    s.add_argument("--receiver", choices=["nmea", "ublox", "novatel"], default=None,
                   help="the GPS port's protocol (default: the scenario's, NMEA): u-blox sends GGA + UBX NAV-PVT "
                        "+ TIM-TP, NovAtel BESTPOSA + BESTVELA + TIMEA")
    s.add_argument("--can", action="store_true",
                   help="the car's CAN bus too: wheel speeds, steering, gear on an SLCAN adapter (data/sim-car.dbc)")
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
    s.add_argument("--clock-jump", action="append", default=[], metavar="START:LEN:OFFSET",
                   help="--serve: the receiver writes its time OFFSET s off for LEN s from START s of the drive, "
                        "e.g. 900:30:3600 (repeatable; default: never)")
    s.add_argument("--board", choices=["simulated", "emulated"], default="simulated",
                   help="--serve: the DAQ port is the simulator's frames, or the firmware's under QEMU fed by the "
                        "simulator (firmware/README.md; needs qemu-system-arm and `make firmware`)")
    s.add_argument("--board-image", default=None, metavar="ELF",
                   help="--serve --board emulated: the firmware image (default: firmware/build/qemu/fieldlog-qemu.elf)")
    s.set_defaults(func=cmd_sim)

    s = sub.add_parser("acquire", help="the acquisition daemon: serial ports -> crash-safe MCAP")
    s.add_argument("--daq", default=None, metavar="PORT", help="DAQ serial port (default: [daq] port of --config)")
    s.add_argument("--gps", default=None, metavar="PORT",
                   help="GPS serial port, or gpsd://HOST[:PORT][/DEVICE] to read the receiver's own bytes through a "
                        "running gpsd (default: [gps] port of --config)")
    s.add_argument("--can", default=None, metavar="URL",
                   help="the car's CAN bus: slcan://PORT[@BITRATE] (an SLCAN serial adapter; BITRATE in bit/s) or "
                        "socketcan://IFACE (default: [can] url of --config, else none)")
    s.add_argument("--dbc", default=None, metavar="FILE",
                   help="--can: decode through this DBC with the [can.signals] of --config (default: [can] dbc)")
    s.add_argument("--out", default=None, metavar="DIR",
                   help="output directory (default: [output] dir of --config, else drives/)")
    s.add_argument("--config", default=None, metavar="FILE",
                   help="TOML config; acquire/config.py documents the keys (default: none, all defaults)")
    s.add_argument("-q", "--quiet", action="count", default=0,
                   help="no status line (a service's journal gets the events only); twice: warnings and errors only")
    s.add_argument("-v", "--verbose", action="count", default=0,
                   help="debug lines too (with -q: the status line once per status interval) (default: info: start, "
                        "files, port events, stop)")
    s.add_argument("--time-scale", type=float, default=None, metavar="X",
                   help="for simulator playback at `sim --serve --speed X` only: the host clock runs X times "
                        "slower than the data ([timesync] host_time_scale; default: 1, real time)")
    s.add_argument("--view", action="store_true",
                   help="also show the car live in rerun (a child `fieldlog view --live` on the live bus)")
    s.add_argument("--view-rrd", default=None, metavar="FILE",
                   help="--view into this .rrd instead of a viewer (default: a viewer)")
    s.add_argument("--view-method", choices=METHODS, default="kf", help="--view: fusion method")
    s.set_defaults(func=cmd_acquire)

    s = sub.add_parser("recover", help="rescue a drive cut short by a crash or power loss, or with a damaged chunk")
    s.add_argument("drive", nargs="+", help="the damaged MCAP (kept as it is); or a session or rosbag2 directory, "
                   "or several files: each cut-short one, and each with a damaged chunk, is recovered, the complete "
                   "and sound ones left")
    s.add_argument("--out", default=None, help="output MCAP, one damaged file only (default: NAME.recovered.mcap "
                   "next to each)")
    s.set_defaults(func=cmd_recover)

    s = sub.add_parser("info", help="topics, rates, duration, time-sync quality, gaps, counters")
    s.add_argument("drive", nargs="+", help=DRIVE_HELP)
    s.add_argument("--json", action="store_true", help="print JSON (machine-readable) instead of the table")
    s.add_argument("--scan", action="store_true",
                   help="read the messages even if the drive has its fieldlog.info record (default: the record)")
    s.set_defaults(func=cmd_info)

    s = sub.add_parser("filter", help="a slice of a drive by time and topic, as `mcap filter`")
    s.add_argument("drive", nargs="+", help=DRIVE_HELP)
    s.add_argument("--start", default=None, metavar="TIME",
                   help="first log time kept: seconds from the drive's first message (negative: from its end), "
                        "an ISO UTC time (2026-05-04T09:32:00Z) or UTC ns (default: the drive's start)")
    s.add_argument("--end", default=None, metavar="TIME",
                   help="log time where the slice ends (excluded), as --start (default: the drive's end)")
    s.add_argument("--topics", default=None, metavar="T,...",
                   help="comma separated topics or shell patterns, e.g. '/imu,/gps/*' (default: all; /tf_static is "
                        "always kept)")
    add_out_args(s)
    s.set_defaults(func=cmd_filter)

    s = sub.add_parser("import", help="build a drive from raw captures made elsewhere")
    s.add_argument("--gps", default=None, metavar="FILE",
                   help="GPS log from any receiver or logger: NMEA, u-blox UBX, NovAtel OEM (auto-detected, mixed)")
    s.add_argument("--daq", default=None, metavar="FILE", help="DAQ byte capture (default: none, GPS only)")
    s.add_argument("--can", default=None, metavar="LOG",
                   help="CAN log: candump .log, Vector .asc or .blf (python-can's readers) (default: none)")
    s.add_argument("--dbc", default=None, metavar="FILE", help="--can: decode through this DBC (default: [can] dbc "
                   "of --config; none: the frames are recorded only)")
    s.add_argument("--signal", action="append", default=[], metavar="KEY=MESSAGE.SIGNAL",
                   help="--can: a [can.signals] entry, e.g. wheel_rl=WHEEL_SPEEDS.WHEEL_SPEED_RL (repeatable; keys "
                        "wheel_fl/fr/rl/rr, vehicle_speed, gear, reverse, steering)")
    s.add_argument("--config", default=None, metavar="FILE",
                   help="--can: an acquire config whose [can] table (dbc, signals, forward, latency_s) applies")
    s.add_argument("--fs", type=float, default=500.0, help="DAQ sample rate, Hz")
    s.add_argument("--pps", choices=["flag", "latch"], default="flag", help="how the DAQ frames carry the PPS")
    s.add_argument("--out", required=True, help="output MCAP")
    s.set_defaults(func=cmd_import)

    s = sub.add_parser("rebuild", help="re-derive every topic from /raw/*")
    s.add_argument("drive", nargs="+", help=DRIVE_HELP)
    add_out_args(s)
    s.add_argument("--calib", default=None, help="calibration TOML (default: the one stored in the drive)")
    s.set_defaults(func=cmd_rebuild)

    s = sub.add_parser("allan", help="Allan deviation and noise parameters of a static drive")
    s.add_argument("drive", nargs="+", help=DRIVE_HELP + "; static")
    s.add_argument("--plot", default=None, metavar="PREFIX",
                   help="also write PREFIX_gyro.png and PREFIX_accel.png (needs fieldlog[plots]; default: none)")
    s.set_defaults(func=cmd_allan)

    s = sub.add_parser("fuse", help="run one fusion method over a drive and write its solution")
    s.add_argument("drive", nargs="+", help=DRIVE_HELP)
    s.add_argument("--method", choices=METHODS, default="kf", help="fusion method")
    s.add_argument("--outage", action="append", metavar="START:LEN",
                   help="force a GPS outage, seconds from the first IMU sample (repeatable; default: none)")
    add_out_args(s)
    s.add_argument("--smooth", action="store_true", help="RTS backward pass after the drive (memory grows with it)")
    add_input_args(s)
    s.add_argument("--config", default=None, metavar="FILE",
                   help="TOML with a [fusion] table (FusionConfig keys; default: the drive's fusion.config record) "
                        "and/or an [input] table (imu_topic, fix_topic, vel_topic, imu_frame)")
    s.set_defaults(func=cmd_fuse)

    s = sub.add_parser("evaluate", help="the outage study (the distributed-KF paper's Table 3)")
    s.add_argument("drive", nargs="*", help="drives (MCAP files, session or rosbag2 directories; each one drive); "
                                           "none with --seeds")
    s.add_argument("--outages", default="30,60", help="outage lengths, s, comma separated")
    s.add_argument("--methods", default="ins,kf,dkf",
                   help=f"comma separated: {', '.join(METHODS)}")
    s.add_argument("--report", required=True, help="output directory (table.md, table.csv, fused/)")
    s.add_argument("--seeds", type=int, default=0, help="also simulate this many drives (seeds 1..N) into DIR/drives")
    s.add_argument("--scenario", default="figure8", help="--seeds: scenario to simulate")
    s.add_argument("--duration", type=float, default=600.0, help="--seeds: seconds per simulated drive")
    s.add_argument("--smooth", action="store_true", help="add RTS-smoothed columns (<method>+rts)")
    add_input_args(s)
    s.add_argument("--paper", action="store_true",
                   help="the distributed-KF paper's set-up: GPS only, its dkf, online networks, methods "
                        "kf,dkf,rbfn,tdln,dkf-rbfn, 30 and 60 s outages, 5 simulated drives without DRIVE or "
                        "--seeds; its Table 3 beside ours and a verdict on each of its claims")
    s.add_argument("--config", default=None, metavar="FILE",
                   help="TOML with a [fusion] table (FusionConfig keys; default: each drive's fusion.config record) "
                        "and/or an [input] table")
    s.set_defaults(func=cmd_evaluate)

    s = sub.add_parser("view", help="show a drive and fused solutions in rerun, or write an .rrd")
    s.add_argument("drive", nargs="?", default=None, help=DRIVE_HELP + "; none with --live")
    s.add_argument("fused", nargs="*", help="fused MCAPs from `fieldlog fuse` (each adds its methods); other files "
                                            "given here are more files of the drive")
    s.add_argument("--rrd", default=None, metavar="FILE",
                   help="write this .rrd instead of opening the viewer (default: open the viewer)")
    s.add_argument("--live", nargs="?", const="", default=None, metavar="ADDRESS",
                   help="instead of a drive: the running daemon's live bus (its Unix socket; default: [daemon] bus "
                        "of --config), fused incrementally as in `fieldlog replay`, until the daemon stops")
    s.add_argument("--method", choices=METHODS, default="kf", help="--live: fusion method")
    s.add_argument("--connect", default=None, metavar="URL",
                   help="--live: a running viewer, as for `fieldlog replay` (default: spawn one)")
    s.add_argument("--config", default=None, metavar="FILE",
                   help="--live: the daemon's config, for [daemon] bus; else its [input] (default: none)")
    add_input_args(s)
    s.set_defaults(func=cmd_view)

    s = sub.add_parser("export", help="one Parquet or CSV table per topic, through polars")
    s.add_argument("drive", nargs="+", help=DRIVE_HELP)
    s.add_argument("--out", required=True, help="output directory (DIR/<topic>.parquet)")
    s.add_argument("--format", choices=["parquet", "csv"], default="parquet", help="table format")
    s.add_argument("--topics", default=None, help="comma separated topics (default: all)")
    s.set_defaults(func=cmd_export)

    s = sub.add_parser("batch", help="reprocess many drives on Dask distributed into one Parquet table")
    s.add_argument("drives", nargs="+", help="drives or glob patterns (quote them), e.g. 'drives/*.mcap'; a session "
                                            "or rosbag2 directory is one drive")
    s.add_argument("--methods", default="kf,dkf", help=f"comma separated: {', '.join(METHODS)}")
    s.add_argument("--outages", default="", help="also forced outages of these lengths, s, comma separated")
    s.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                   help="a running Dask scheduler (default: a local cluster on 127.0.0.1)")
    s.add_argument("--workers", type=int, default=2, help="local cluster: worker processes (1 thread each)")
    s.add_argument("--out", required=True, help="output directory (results.parquet, fused/)")
    s.set_defaults(func=cmd_batch)

    s = sub.add_parser("replay", help="play a drive through live fusion into rerun at X times real time")
    s.add_argument("drive", nargs="+", help=DRIVE_HELP)
    s.add_argument("--speed", type=float, default=1.0, help="times real time (0: as fast as possible)")
    s.add_argument("--method", choices=METHODS, default="kf", help="fusion method")
    sink = s.add_mutually_exclusive_group()
    sink.add_argument("--rrd", default=None, metavar="FILE",
                      help="stream into this .rrd file instead of a viewer (default: spawn a viewer)")
    sink.add_argument("--connect", default=None, metavar="URL",
                      help="a running viewer or `rerun --serve-grpc`, e.g. rerun+http://127.0.0.1:9876/proxy "
                           "(default: spawn a viewer)")
    s.add_argument("--config", default=None, metavar="FILE",
                   help="fusion TOML ([fusion] table; default: the drive's own, else the defaults)")
    add_input_args(s)
    s.set_defaults(func=cmd_replay)

    s = sub.add_parser("study", help="one of the other papers' studies, with its report (tools/studies.py)")
    s.add_argument("name", choices=["kf-ukf", "cost", "ssr-sckf", "hinf"], help="which study")
    s.add_argument("--seeds", type=int, default=3, help="simulated drives per case (seeds 1..N)")
    s.add_argument("--runs", type=int, default=5, help="cost: timing repetitions")
    s.add_argument("--out", default=None, help="report directory (default docs/studies/NAME)")
    s.add_argument("--work", default=None, help="drives and fused solutions (default out/studies/NAME)")
    s.set_defaults(func=cmd_study)

    s = sub.add_parser("demo", help="simulate, fuse, evaluate and view, on the built-in default")
    s.add_argument("--out", default="out/demo", help="output directory")
    s.add_argument("--duration", type=float, default=300.0, help="seconds of drive to simulate (>= 240)")
    s.set_defaults(func=cmd_demo)
    for s in sub.choices.values():
        s.set_defaults(func=needs_extras(s.get_default("func")))
    return p


def main(argv: list[str] | None = None) -> int:
    """Run one command. The error contract: bad input (a path, file, byte or config) is one line on stderr that
    names it and says what to do, exit code 2; anything else is an internal error, one line, exit code 1
    (FIELDLOG_TRACEBACK=1 shows its traceback). Never a traceback for bad input."""
    args = build_parser().parse_args(argv)
    prefix = f"fieldlog {args.command}: error:"
    try:
        return args.func(args)
    except BrokenPipeError:  # e.g. `fieldlog info X | head`
        sys.stderr.close()
        return 0
    except OSError as e:
        name = e.filename if e.filename is not None else ""
        what = f"{name}: {e.strerror}" if name and e.strerror else str(e)
        hint = {errno.EACCES: "check its permissions", errno.ENOENT: "check the path",
                errno.EISDIR: "give a file, not a directory", errno.ENOTDIR: "check the path",
                errno.ENOSPC: "free some space", errno.EROFS: "choose a writable place"}.get(e.errno, "")
        print(f"{prefix} {what}{'; ' + hint if hint and hint not in what else ''}", file=sys.stderr)
        return 2
    except (ValueError, KeyError) as e:
        print(f"{prefix} {e.args[0] if isinstance(e, KeyError) and e.args else e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except Exception as e:  # noqa: BLE001 - the contract: one line, exit 1
        if os.environ.get("FIELDLOG_TRACEBACK"):
            raise
        print(f"{prefix} internal error: {type(e).__name__}: {e} (please report it; FIELDLOG_TRACEBACK=1 shows "
              f"where)", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
