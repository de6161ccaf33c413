"""``fieldlog demo``: simulate, look, fuse, evaluate and view: the whole pipeline through the same commands a
user types."""
from __future__ import annotations

import argparse

from fieldlog.fusion.methods import DKF, DKF_RBFN, INS
from fieldlog.tools.commands.common import add_out_dir, command_parser, needs_extras
from fieldlog.tools.commands.view import rerun_exe


def add_parser(sub) -> None:
    s = command_parser(sub, "demo", "simulate, fuse, evaluate and view, on the built-in default")
    add_out_dir(s, "output directory", default="out/demo")
    s.add_argument("--duration", type=float, default=300.0, help="seconds of drive to simulate (>= 240)")
    s.set_defaults(func=needs_extras(run))


def run(a: argparse.Namespace) -> int:
    """Each step through ``a.cli_main`` (the CLI's entry, which sets it), as if typed. The folder is the demo's
    own: each run redoes its files (``--force`` to the steps; never through a link: ``drive.outputs``)."""
    from fieldlog.drive.outputs import out_dir

    out = out_dir(a.out_dir)
    drive, fused, rrd, report = out / "figure8.mcap", out / "dkf-rbfn.mcap", out / "figure8.rrd", out / "report"
    steps = [
        ("simulate a figure8 drive", ["sim", "--scenario", "figure8", "--duration", f"{a.duration:g}", "--seed", "1",
                                      "--out", str(drive), "--force"]),
        ("what the drive holds", ["info", str(drive)]),
        ("fuse with the KF+RBFN hybrid through a 30 s GPS outage",
         ["fuse", str(drive), "--method", DKF_RBFN.name, "--outage", "180:30", "--out", str(fused), "--force"]),
        ("the outage study", ["evaluate", str(drive), "--outages", "30", "--methods", ",".join((INS.name, DKF.name, DKF_RBFN.name)),
                              "--out-dir", str(report), "--force"]),
        ("a rerun recording", ["view", str(drive), str(fused), "--rrd", str(rrd), "--force"]),
    ]
    flags = ["-v"] * a.verbose + ["-q"] * a.quiet
    for i, (title, argv) in enumerate(steps, 1):
        print(f"\n{i}/{len(steps)}  {title}:  fieldlog {' '.join(argv)}\n", flush=True)
        rc = a.cli_main([argv[0], *flags, *argv[1:]])
        if rc:
            return rc
    print(f"\nreport:  {report.resolve() / 'table.md'} (one drive: it shows the errors and resolves no difference "
          "between methods; `fieldlog evaluate --seeds 8 ...` can)\n"
          f"rerun:   {rerun_exe()} {rrd.resolve()}   (or: {rerun_exe()} {drive.resolve()})")
    return 0
