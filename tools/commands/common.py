"""What the commands share: their parser's frame (-v/-q, help format, deprecated aliases), the drive and input
options, the extras check, progress and the log."""
from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path
from typing import Callable

from fieldlog.fusion.methods import METHODS  # imports none of the fusion stack: `fieldlog --help` stays light

# Optional dependencies (pyproject.toml extras) by top-level module: a command that needs one that is not
# installed says which extra to install, in one line.
EXTRAS = {"rerun": "view", "polars": "export", "pyarrow": "export", "fastkml": "export", "pygeoif": "export",
          "gpxpy": "export", "matplotlib": "plots", "jinja2": "report", "dask": "batch", "distributed": "batch", "foxglove": "foxglove"}

# the compiled kernels (setup.py builds them; tests/test_package.py checks the two agree): an install without
# them is told to reinstall, in one line
KERNELS = ("fieldlog.fusion._ins", "fieldlog.fusion._cycles", "fieldlog.drive._chunks", "fieldlog.tools.sim._sensors")

# the extras (pyproject.toml) each command needs beyond the core install, shown in `fieldlog --help`
NEEDS = {"evaluate": "export,plots", "view": "view", "replay": "view", "report": "report",
         "export": "export", "batch": "batch", "study": "all", "demo": "all"}

# the commands that write named outputs: they take --force to replace them (drive/outputs.py)
WRITERS = ("sim", "recover", "filter", "import", "rebuild", "allan", "fuse", "evaluate", "view", "export", "batch",
           "replay", "study", "report")

DRIVE_HELP = ("the drive: an MCAP file, several files, a rotated session's directory or a rosbag2 directory (read "
              "as one drive, in log-time order)")

# The one origin of the times given on the command line (filter --start/--end, fuse --outage), as --help says it.
TIME_ORIGIN = "seconds from the drive's first IMU sample (its first message if it has no IMU topic)"

# the logger every command reports through; the CLI entry configures it from -v/-q
log = logging.getLogger("fieldlog.cli")

Command = Callable[[argparse.Namespace], int]


class MissingExtra(ValueError):
    """An optional dependency of the command is not installed (reported like a bad argument: one line, exit 2)."""


def missing_extra(module: str) -> MissingExtra:
    """The error for the optional dependency ``module`` (a key of ``EXTRAS``), naming its extra."""
    return MissingExtra(f"{module} is not installed: pip install 'fieldlog[{EXTRAS[module]}]' (or 'fieldlog[all]')")


def require_extras(*modules: str) -> None:
    """``MissingExtra`` for the first of ``modules`` (keys of ``EXTRAS``) that is not installed, checked without
    importing it (for a process that only starts another one that needs them)."""
    import importlib.util

    for module in modules:
        if importlib.util.find_spec(module) is None:
            raise missing_extra(module)


def needs_extras(func: Command) -> Command:
    """Wrap a command so that an ImportError of an optional dependency becomes ``MissingExtra``."""

    def run(a: argparse.Namespace) -> int:
        try:
            return func(a)
        except ModuleNotFoundError as e:
            root = (e.name or "").split(".")[0]
            if root not in EXTRAS:
                raise
            raise missing_extra(root) from None

    return run


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Keeps the examples' layout, and shows every option's default (those without one say so in words)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        d = action.default
        if "default" in text or d in (None, False, argparse.SUPPRESS) or d == [] or not action.option_strings:
            return text
        return f"{text} (default: %(default)s)"


def add_out_dir(s: argparse.ArgumentParser, help: str, old: str = "--out", **kw) -> None:
    """``--out-dir DIR`` of a command that writes several files; ``old``, the option's former name, is still
    accepted for one release (deprecated)."""
    s.add_argument("--out-dir", old, dest="out_dir", metavar="DIR", help=f"{help}; {old}: its deprecated name", **kw)


def command_parser(sub, name: str, help: str, quiet_help: str | None = None,
                   verbose_help: str | None = None) -> argparse.ArgumentParser:
    """The subparser of one command, with the -q/--quiet and -v/--verbose every command takes."""
    if name in NEEDS:
        help += f" [{NEEDS[name]}]"
    s = sub.add_parser(name, help=help, description=help, formatter_class=HelpFormatter)
    s.add_argument("-q", "--quiet", action="count", default=0,
                   help=quiet_help or "warnings and errors only, no progress bar (twice: errors only)")
    s.add_argument("-v", "--verbose", action="count", default=0,
                   help=verbose_help or "more detail: settings, steps (default: a short summary)")
    if name in WRITERS:
        s.add_argument("--force", action="store_true",
                       help="replace output files that exist (default: refuse them; a symbolic link is refused even "
                            "so: an output is never written through a link)")
    return s


def drive_arg(paths: list[str]) -> str | list[str]:
    """The drive positional(s) as ``drive.files`` takes them: one path, or the list."""
    return paths[0] if len(paths) == 1 else paths


def add_tf_from_arg(s: argparse.ArgumentParser) -> None:
    """``--tf-from FILE``: of a drive's files that disagree on a frame's /tf_static, the one to use
    (``drive.drive.Drive.open``)."""
    s.add_argument("--tf-from", default=None, metavar="FILE",
                   help="of a drive's files that give different /tf_static transforms for a frame, the one whose "
                        "transforms to use (default: refuse the drive, naming the files and the frame)")


def open_drive(paths: str | list[str], a: argparse.Namespace, config=None):
    """``drive.drive.Drive.open`` of the drive positional(s) (or one path), checked as one drive before the work:
    with ``--tf-from`` when the command has it, the IMU's axes given when ``--imu-frame`` or the ``[input]``
    table of ``config`` (a ``drive.tables.TomlFile``) gives them."""
    from fieldlog.drive.drive import Drive
    from fieldlog.tools.fuse_settings import load_input_spec

    imu_axes = input_spec(a).imu_frame or load_input_spec(config).imu_frame
    spec = drive_arg(paths) if isinstance(paths, list) else paths
    return Drive.open(spec, getattr(a, "tf_from", None), imu_axes_given=imu_axes is not None)


def input_spec(a: argparse.Namespace):
    """``replay.inputs.InputSpec`` of --imu-topic, --fix-topic, --vel-topic, --imu-frame, --odom-topic."""
    from fieldlog.replay.inputs import InputSpec

    return InputSpec(a.imu_topic, a.fix_topic, a.vel_topic, a.imu_frame, a.odom_topic)


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
    s.add_argument("--odom-topic", default=None, metavar="T",
                   help="wheel odometry: its forward speed (linear.x) from a TwistWithCovarianceStamped, "
                        "nav_msgs/Odometry or TwistStamped topic (default: /vehicle/twist if present; 'none': no "
                        "odometry)")


def parse_lengths(text: str, option: str) -> list[float]:
    """Outage lengths ``30,60`` (s) of ``option``; empty text: none."""
    try:
        lengths = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise ValueError(f"{option} expects lengths in s separated by commas, got {text!r}") from None
    if lengths and min(lengths) <= 0:
        raise ValueError(f"{option}: lengths must be > 0")
    return lengths


def add_out_args(s: argparse.ArgumentParser) -> None:
    """--out, and --bag to make it a one-file rosbag2 directory (drive/bagdir.py)."""
    s.add_argument("--out", required=True, help="output MCAP (with --bag: the rosbag2 directory)")
    s.add_argument("--bag", action="store_true",
                   help="write --out as a rosbag2 directory: OUT/OUT.mcap and its metadata.yaml, which `ros2 bag "
                        "info/play` and rosbags open (default: one MCAP file)")


def out_file(a: argparse.Namespace) -> Path:
    """The MCAP file to write: --out, or with --bag the one file of the rosbag2 directory --out."""
    from fieldlog.drive.bagdir import bag_file

    return bag_file(Path(a.out)) if a.bag else Path(a.out)


def finish_out(a: argparse.Namespace, path: Path) -> None:
    """With --bag: the directory's metadata.yaml for the file just written."""
    if a.bag:
        from fieldlog.drive.bagdir import write_bag_metadata

        log.info(f"wrote {write_bag_metadata(path)}")


def output_parent(path: str | None) -> None:
    """Create the directory an output file goes to (an OSError naming it when that is impossible, before any
    work is done)."""
    if path:
        Path(path).parent.mkdir(parents=True, exist_ok=True)


class Progress:
    """Progress of long work as a tqdm bar with its rate and ETA, on a terminal only (stderr a tty) and not
    with -q; nothing otherwise. Called with the fraction done (0..1); the bar ends once, at the first 1.0 (or
    ``close``): later calls are ignored."""

    STEPS = 1000

    def __init__(self, label: str) -> None:
        self.label = label
        self.on = sys.stderr.isatty() and log.isEnabledFor(logging.INFO)
        self.bar = None
        self.done = False

    def __call__(self, fraction: float) -> None:
        if not self.on or self.done:
            return
        if self.bar is None:
            from tqdm import tqdm

            try:  # a terminal that gives no size (0 x 0, e.g. a bare pty) would hide tqdm's bar
                cols, rows = os.get_terminal_size(sys.stderr.fileno())
            except OSError:
                cols = rows = 0
            self.bar = tqdm(total=self.STEPS, desc=self.label, file=sys.stderr, leave=False, ncols=cols or 80,
                            nrows=rows or 24, bar_format="{desc}: {percentage:3.0f}%|{bar}| {elapsed}<{remaining}")
        n = round(min(max(fraction, 0.0), 1.0) * self.STEPS)
        if n > self.bar.n:
            self.bar.update(n - self.bar.n)
        if n >= self.STEPS:
            self.close()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
        self.done = True
