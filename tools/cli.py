"""The ``fieldlog`` command line (contract names: design section 2): the entry, its parser and its log.

Each command lives in ``tools/commands/<name>.py`` with its own parser. Every command takes -q/--quiet and
-v/--verbose, which set the one log the commands report through (``setup_logging``): INFO lines (the summary)
on stdout, -v adds DEBUG lines (settings, steps), -q leaves warnings and errors only (on stderr). A command's
product (a table, a report, ``--json``) is printed whatever -q says."""
from __future__ import annotations

import argparse
import errno
import gc
import logging
import os
import sys
from typing import NoReturn

# One OpenBLAS thread, set before the commands import numpy (which starts OpenBLAS's threads when it loads):
# the commands' matrix products are small, and a command's second core goes to its forked worker; more BLAS
# threads would only spin waiting for work, at start-up and after each product, which costs CPU. A setting in
# the environment wins. Not for the commands that write a drive: its timing record (drive.drivestats) sums the
# stamps' squared errors with a BLAS dot product, whose rounding depends on the thread count, and a drive keeps
# its bytes.
DRIVE_WRITERS = ("acquire", "sim", "rebuild", "recover", "import", "filter")
if sys.argv[1:2] and sys.argv[1] not in DRIVE_WRITERS:
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
# No transparent huge pages for numpy's arrays, also set before numpy loads: numpy advises them for every large
# array, and where the kernel then compacts memory at the first touch (transparent_hugepage/defrag "madvise", a
# common default), each whole-drive array a command makes and drops (``sim`` makes dozens) can stall on it. The
# arrays are walked in order, so the larger pages gain little. A setting in the environment wins.
os.environ.setdefault("NUMPY_MADVISE_HUGEPAGE", "0")

from fieldlog.tools.commands import COMMANDS  # noqa: E402
from fieldlog.tools.commands.common import KERNELS, METHODS, HelpFormatter  # noqa: E402

__all__ = ["METHODS", "build_parser", "main", "setup_logging"]

EXAMPLES = """\
examples:
  fieldlog acquire --daq /dev/fieldlog-daq --gps /dev/fieldlog-gps --out-dir drives/   # record in the car
  fieldlog info drives/20260504T093000Z_0001.mcap            # topics, rates, sync quality, gaps (--json)
  fieldlog recover drives/20260504T093000Z_0001.mcap         # after a power cut
  fieldlog filter drive.mcap --start 120 --end 300 --topics '/imu,/gps/*' --out slice.mcap
  fieldlog sim --scenario figure8 --duration 600 --out drive.mcap
  fieldlog fuse drive.mcap --method dkf-rbfn --outage 300:60 --out fused.mcap
  fieldlog evaluate --seeds 3 --outages 30,60 --methods ins,kf,dkf --out-dir report/
  fieldlog view drive.mcap fused.mcap --rrd drive.rrd
  fieldlog report drive.mcap fused.mcap --out report.html   # the drive's health on one page, a verdict on top

Times on the command line (filter --start/--end, fuse --outage) count in seconds from the drive's first IMU
sample. `fieldlog COMMAND --help` for the options of one command; every command takes -q and -v. Commands
marked [extra] need `pip install 'fieldlog[extra]'`; `make setup` installs them all.
"""


class _Version(argparse.Action):
    """``--version``: the installed version, looked up only when asked for."""

    def __init__(self, option_strings, dest, **kwargs) -> None:
        super().__init__(option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, nargs=0,
                         help="show the version and exit")

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        from fieldlog import __version__

        print(f"fieldlog {__version__}")
        parser.exit()


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="fieldlog", description="GPS/INS field logging, fusion and replay",
                                epilog=EXAMPLES, formatter_class=HelpFormatter)
    p.add_argument("--version", action=_Version)
    p.set_defaults(cli_main=main)  # for `demo`, which runs the other commands as typed
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for command in COMMANDS:
        command.add_parser(sub)
    return p


class ConsoleHandler(logging.Handler):
    """INFO and DEBUG records as plain lines on stdout (stderr with ``--json``, which keeps stdout for the JSON);
    WARNING and above on stderr as ``fieldlog COMMAND: warning: ...``. The streams are looked up for each
    record, so a redirected ``sys.stdout`` is followed."""

    def __init__(self, command: str, json_out: bool) -> None:
        super().__init__(logging.DEBUG)
        self.command, self.json_out = command, json_out

    def emit(self, record: logging.LogRecord) -> None:
        try:
            text = record.getMessage()
            if record.levelno >= logging.WARNING:
                stream, text = sys.stderr, f"fieldlog {self.command}: {record.levelname.lower()}: {text}"
            else:
                stream = sys.stderr if self.json_out else sys.stdout
            stream.write(text + "\n")
            stream.flush()
        except BrokenPipeError:
            raise
        except Exception:  # noqa: BLE001 - logging's own contract: a failing handler reports, never raises
            self.handleError(record)


def setup_logging(command: str, verbosity: int, json_out: bool = False) -> None:
    """The log of one command run: ``verbosity`` = (number of -v) - (number of -q): 1 or more DEBUG, 0 INFO,
    -1 WARNING, -2 or less ERROR. Replaces the handlers of the ``fieldlog`` logger (a second run in the same
    process starts afresh). The libraries' own warnings and errors (python-can, foxglove-sdk, ...: the root
    logger's) go through the same handler, so they read as fieldlog's lines do."""
    level = (logging.DEBUG if verbosity > 0 else logging.INFO if verbosity == 0
             else logging.WARNING if verbosity == -1 else logging.ERROR)
    ours = logging.getLogger("fieldlog")
    ours.handlers[:] = [ConsoleHandler(command, json_out)]
    ours.setLevel(level)
    ours.propagate = False
    others = ConsoleHandler(command, json_out)
    others.setLevel(max(level, logging.WARNING))
    root = logging.getLogger()
    root.handlers[:] = [h for h in root.handlers if not isinstance(h, ConsoleHandler)] + [others]


def main(argv: list[str] | None = None) -> int:
    """Run one command. The error contract: bad input (a path, file, byte or config) is one line on stderr that
    names it and says what to do, exit code 2; anything else is an internal error, one line, exit code 1
    (FIELDLOG_TRACEBACK=1 shows its traceback). Never a traceback for bad input."""
    args = build_parser().parse_args(argv)
    setup_logging(args.command, args.verbose - args.quiet, getattr(args, "json", False))
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
        if isinstance(e, ImportError) and e.name in KERNELS:  # installed without them: what to do, not a bug
            print(f"{prefix} {e}", file=sys.stderr)
            return 2
        if os.environ.get("FIELDLOG_TRACEBACK"):
            raise
        print(f"{prefix} internal error: {type(e).__name__}: {e} (please report it; FIELDLOG_TRACEBACK=1 shows "
              f"where)", file=sys.stderr)
        return 1


def run() -> NoReturn:
    """The ``fieldlog`` program and ``python -m fieldlog``: :func:`main`, exiting with its code. The heap is frozen
    first (``gc.freeze``) so that the interpreter's last garbage collection, a walk over every object of numpy's
    and fieldlog's, skips what exists when the command returns; atexit handlers and thread joins run as usual.
    What it would find is garbage the process's end frees anyway: every command closes its files before it
    returns. Callers of :func:`main` in a process that goes on (the tests) keep their collector as it is."""
    code = main()
    gc.freeze()
    sys.exit(code)


if __name__ == "__main__":
    run()
