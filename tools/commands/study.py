"""``fieldlog study``: one of the other papers' studies, with its report (``tools.evaluation.studies``)."""
from __future__ import annotations

import argparse
from pathlib import Path

from fieldlog.fusion.methods import HINF, KF_UKF, SSR_SCKF
from fieldlog.tools.commands.common import add_out_dir, command_parser, log, needs_extras


def add_parser(sub) -> None:
    s = command_parser(sub, "study", "one of the other papers' studies, with its report (tools/evaluation/studies.py)")
    s.add_argument("name", choices=[KF_UKF.name, "cost", SSR_SCKF.name, HINF.name], help="which study")
    s.add_argument("--seeds", type=int, default=3, help="simulated drives per case (seeds 1..N)")
    s.add_argument("--runs", type=int, default=5, help="cost: timing repetitions")
    add_out_dir(s, "report directory (default docs/studies/NAME)", default=None)
    s.add_argument("--work", default=None, metavar="DIR",
                   help="drives and fused solutions (default out/studies/NAME)")
    s.set_defaults(func=needs_extras(run))


def run(a: argparse.Namespace) -> int:
    from fieldlog.tools.evaluation.studies import study

    study(a.name, Path(a.out_dir or f"docs/studies/{a.name}"), Path(a.work or f"out/studies/{a.name}"), a.seeds,
          a.runs, say=log.info, force=a.force)
    return 0
