"""``fieldlog recover``: rescue a drive cut short by a crash or power loss, or with a damaged chunk."""
from __future__ import annotations

import argparse
from pathlib import Path

from fieldlog.tools.commands.common import command_parser, log, needs_extras


def add_parser(sub) -> None:
    s = command_parser(sub, "recover", "rescue a drive cut short by a crash or power loss, or with a damaged chunk")
    s.add_argument("drive", nargs="+", help="the damaged MCAP (kept as it is); or a session or rosbag2 directory, "
                   "or several files: each cut-short one, and each with a damaged chunk, is recovered, the complete "
                   "and sound ones left")
    s.add_argument("--out", default=None, help="output MCAP, one damaged file only (default: NAME.recovered.mcap "
                   "next to each)")
    s.set_defaults(func=needs_extras(run))


def run(a: argparse.Namespace) -> int:
    """One file: recovered whatever it is. A session or rosbag2 directory, or several files: each cut-short file,
    and each complete one with a damaged chunk (every chunk's CRC checked), recovered next to it (the drive then
    reads NAME.recovered.mcap in its place), the complete and sound ones left. A directory's every MCAP file on
    disk is looked at (a session's metadata.yaml lists only the files closed before a crash), and its
    metadata.yaml is written again when a file was recovered or there was none. A ``NAME.recovered.mcap`` that does
    not stand in for its file (a symbolic link, or an older or cut-short file: ``recovery.recovered_state``) is
    never followed nor replaced without --force: one line says what to do, exit code 2."""
    from fieldlog.drive.bagdir import METADATA, RECOVERED, rewrite_metadata, session_files
    from fieldlog.acquire.recovery import recover_folder
    from fieldlog.drive.files import drive_files

    if len(a.drive) == 1 and not Path(a.drive[0]).is_dir():
        return recover_one(Path(a.drive[0]), Path(a.out) if a.out else None, a.force)
    if a.out:
        raise ValueError(f"{' '.join(a.drive)}: --out takes one damaged file; a drive of several files is recovered "
                         f"next to them (NAME{RECOVERED})")
    code = 0
    for spec in a.drive:
        d = Path(spec)
        done, refused = recover_folder(session_files(d) if d.is_dir() else drive_files(spec),
                                       lambda src, _dst: recover_one(src, None, a.force) == 0,
                                       lambda msg, level: log.log(level, msg), a.force, complete_too=True)
        code = 2 if refused else code
        if d.is_dir() and (done or not (d / METADATA).exists()):
            meta, left = rewrite_metadata(d)
            log.info(f"wrote {meta}" + (f" (left out, no summary: {', '.join(str(f) for f in left)})" if left else ""))
    return code


def recover_one(src: Path, out: Path | None, force: bool) -> int:
    from fieldlog.drive.bagdir import RECOVERED
    from fieldlog.acquire.recovery import recover_drive

    out = out or src.with_name(src.stem + RECOVERED)
    if out.resolve() == src.resolve():
        raise ValueError("--out must differ from the damaged file (it is kept as it is)")
    rep = recover_drive(src, out, force)
    state = "was already complete" if rep.had_summary else f"{rep.bytes_discarded} bytes after the last complete " \
                                                            f"chunk discarded"
    if rep.damaged:
        state += f"; {len(rep.damaged)} damaged chunk{'s' * (len(rep.damaged) > 1)} skipped, at byte " + \
            ", ".join(str(x) for x in rep.damaged)
    log.info(f"wrote {out}: {sum(rep.messages.values())} messages in {rep.chunks} chunks ({state}), "
             f"{sum(rep.rederived.values())} tail messages re-derived from the raw reads")
    for topic in sorted(set(rep.messages) | set(rep.rederived)):
        log.debug(f"  {topic:<20} {rep.messages.get(topic, 0)}" + (f" + {rep.rederived[topic]} re-derived"
                                                                     if rep.rederived.get(topic) else ""))
    return 0
