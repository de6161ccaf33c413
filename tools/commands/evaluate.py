"""``fieldlog evaluate``: the outage study (the distributed-KF paper's Table 3), ``tools.evaluation.evaluate``."""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from fieldlog.tools.commands.common import (METHODS, Progress, add_input_args, add_out_dir, command_parser,
                                            input_spec, log, needs_extras, parse_lengths)


def add_parser(sub) -> None:
    s = command_parser(sub, "evaluate", "the outage study (the distributed-KF paper's Table 3)",
                       verbose_help="also each run's errors and the verdict lines as they come (default: the table)")
    s.add_argument("drive", nargs="*", help="drives (MCAP files, session or rosbag2 directories; each one drive); "
                                           "none with --seeds")
    s.add_argument("--outages", default="30,60", help="outage lengths, s, comma separated")
    s.add_argument("--methods", default="ins,kf,dkf",
                   help=f"comma separated: {', '.join(METHODS)}")
    add_out_dir(s, "output directory (table.md, table.csv, fused/)", old="--report", required=True)
    s.add_argument("--seeds", type=int, default=0, help="also simulate this many drives (seeds 1..N, or from --first-seed) into DIR/drives")
    s.add_argument("--first-seed", type=int, default=1, help="--seeds: the first seed (seeds FIRST..FIRST+N-1)")
    s.add_argument("--scenario", default=None,
                   help="--seeds: scenario to simulate (default figure8-varied: the figure-eight with laps that "
                        "vary, so no predictor can learn the track)")
    s.add_argument("--duration", type=float, default=600.0, help="--seeds: seconds per simulated drive")
    s.add_argument("--first-outage", type=float, default=None, metavar="S",
                   help="earliest outage start, s from the first IMU sample (default 120: after the filter has "
                        "converged; later for a predictor that must train first)")
    s.add_argument("--smooth", action="store_true", help="add RTS-smoothed columns (<method>+rts)")
    s.add_argument("--predictor-modes", default="paper", metavar="MODES",
                   help="dkf-rbfn: comma separated [fusion] predictor_mode values, one column each (paper, pseudo: "
                        "the virtual odometer, column 'dkf-rbfn (pseudo)')")
    add_input_args(s)
    s.add_argument("--paper", action="store_true",
                   help="the distributed-KF paper's set-up: GPS only, its dkf, online networks, methods "
                        "kf,dkf,rbfn,tdln,dkf-rbfn, 30 and 60 s outages, 8 simulated drives of figure8-varied "
                        "without DRIVE or --seeds; its Table 3 beside ours, a verdict on each of its absolute "
                        "figures and (paired t test over the drives) on each of its claims")
    s.add_argument("--config", default=None, metavar="FILE",
                   help="TOML with a [fusion] table (FusionConfig keys; default: each drive's fusion.config record) "
                        "and/or an [input] table")
    s.add_argument("--json", action="store_true",
                   help="print the table as JSON (machine-readable: one object per quantity, method and outage "
                        "length) instead of markdown")
    s.set_defaults(func=needs_extras(run))


def run(a: argparse.Namespace) -> int:
    from fieldlog.tools.evaluation.evaluate import StudyConfig, check_methods, evaluate

    methods = [m.strip() for m in a.methods.split(",") if m.strip()]
    check_methods(methods)
    from fieldlog.fusion.config import PREDICTOR_MODES

    modes = [m.strip() for m in a.predictor_modes.split(",") if m.strip()]
    bad = [m for m in modes if m not in PREDICTOR_MODES]
    if bad or not modes:
        raise ValueError(f"--predictor-modes: {', '.join(bad) or 'none given'}; one or more of {', '.join(PREDICTOR_MODES)}")
    lengths = parse_lengths(a.outages, "--outages")
    if not lengths:
        raise ValueError("--outages: lengths must be > 0")
    report = Path(a.out_dir)
    drives = [Path(d) for d in a.drive]
    if a.paper:
        from fieldlog.tools.evaluation.evaluate import PAPER_LENGTHS, PAPER_METHODS, PAPER_SEEDS

        methods, lengths = list(PAPER_METHODS), list(PAPER_LENGTHS)
        if not drives and not a.seeds:
            a.seeds = PAPER_SEEDS
    if a.seeds:
        from fieldlog.tools.evaluation.evaluate import PAPER_SCENARIO
        from fieldlog.tools.sim.simulate import simulate

        from fieldlog.drive.outputs import out_dir

        a.scenario = a.scenario or PAPER_SCENARIO
        out_dir(report, "drives")
        for seed in range(a.first_seed, a.first_seed + a.seeds):
            path = report / "drives" / f"{a.scenario}_s{seed}.mcap"
            log.info(f"simulating {a.scenario} {a.duration:g} s seed {seed} -> {path}")
            simulate(a.scenario, a.duration, seed, path, progress=Progress(f"sim {a.scenario} seed {seed}"),
                     force=a.force)
            drives.append(path)
    for d in drives:
        if not d.exists():
            raise FileNotFoundError(f"{d} does not exist")
    t0 = time.monotonic()
    from fieldlog.drive.tables import TomlFile
    from fieldlog.tools.fuse_settings import load_fusion_config, load_input_spec

    conf = TomlFile.read(a.config)
    table = evaluate(drives, lengths, methods, report, smooth=a.smooth,
                     config=load_fusion_config(conf) if conf and "fusion" in conf.tables else None,
                     spec=load_input_spec(conf).merged(input_spec(a)), paper=a.paper, say=log.debug,
                     note=log.info, progress=Progress("evaluate"), force=a.force, predictor_modes=modes,
                     study=StudyConfig() if a.first_outage is None else StudyConfig(first_s=a.first_outage))
    if a.json:
        print(json.dumps({"drives": [str(d) for d in drives], "out_dir": str(report), "rows": table.to_dicts()}))
    else:
        print((report / "table.md").read_text())  # the product: printed whatever -q says
    figures = [str(f) for f in (report / f"errors_{L:g}s.png" for L in lengths) if f.exists()]
    log.info(f"wrote {', '.join([str(report / 'table.md'), str(report / 'table.csv'), *figures])} in "
             f"{time.monotonic() - t0:.1f} s")
    return 0
