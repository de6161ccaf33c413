"""``fieldlog fuse``: run one fusion method over a drive and write its solution (``tools.fuse``).

By default one summary line (what was read, what was written, the method, the outages) and how the heading was
aligned; the settings and their sources with -v, and each noise figure's value and source (default, the
config, an IMU grade or datasheet key, estimated from the still start, adapted: ``fusion.adaptive``) (they are always in the fused file's ``fusion`` metadata
record); ``--json``: the summary as one JSON object instead."""
from __future__ import annotations

import argparse
import contextlib
import json
import time

from fieldlog.fusion.methods import INS, KF
from fieldlog.tools.commands.common import (DRIVE_HELP, METHODS, TIME_ORIGIN, Progress, add_input_args,
                                            add_out_args, add_tf_from_arg, command_parser, finish_out, input_spec,
                                            log, needs_extras, open_drive, out_file)


def add_parser(sub) -> None:
    s = command_parser(sub, "fuse", "run one fusion method over a drive and write its solution")
    s.add_argument("drive", nargs="+", help=DRIVE_HELP)
    s.add_argument("--method", choices=METHODS, default=KF.name, help="fusion method")
    s.add_argument("--outage", action="append", metavar="START:LEN",
                   help=f"force a GPS outage of LEN s from START, {TIME_ORIGIN}, as `filter --start` counts "
                        "(repeatable; default: none)")
    add_out_args(s)
    s.add_argument("--smooth", action="store_true", help="RTS backward pass after the drive (memory grows with it)")
    add_input_args(s)
    add_tf_from_arg(s)
    s.add_argument("--config", default=None, metavar="FILE",
                   help="TOML with a [fusion] table (FusionConfig keys; default: the drive's fusion.config record) "
                        "and/or an [input] table (imu_topic, fix_topic, vel_topic, imu_frame)")
    s.add_argument("--json", action="store_true", help="print the summary as JSON (machine-readable)")
    s.set_defaults(func=needs_extras(run))


def _installation_line(s: dict, span_s: float) -> str:
    """The summary line of ``tools.fuse.estimate_installation``'s keys in ``s``; ``span_s``: ``[fusion]
    installation_span_s``."""
    parts = []
    if s.get("mounting_rpy_deg"):
        parts.append("mounting roll, pitch, yaw " + ", ".join(
            f"{x:.2f} ± {e:.2f}" for x, e in zip(s["mounting_rpy_deg"], s["mounting_sigma_deg"])) + " deg")
    if s.get("imu_time_offset_s") is not None:
        sigma = s.get("imu_time_offset_sigma_s")
        parts.append(f"IMU late by {s['imu_time_offset_s'] * 1e3:.1f}"
                     + (f" ± {sigma * 1e3:.1f} ms" if sigma is not None else " ms (configured)"))
    source = f"the first {s['installation_read_s']:.0f} s of the drive" if span_s else "the drive"
    return (f"installation (estimated from {source}, used by the NHC, the odometer and the IMU's stamps): "
            + "; ".join(parts))


def _fused(a: argparse.Namespace, drive, st, out):
    """``tools.fuse.fuse`` of the drive with the settings ``st``, after the installation pass where it applies,
    the drive decoded once for both: (FuseResult, the settings used, the installation's ``--json`` keys)."""
    from fieldlog.replay.inputs import InputStream
    from fieldlog.tools.fuse_settings import BLOCK_S, installation_applies

    config, installed = st.config, {}
    install = a.method != INS.name and installation_applies(config, st.inputs)
    whole = install and not config.aids.installation_span_s  # the installation passes read the whole drive
    with contextlib.closing(InputStream(drive, st.inputs, BLOCK_S, keep=whole)) as stream:
        stream.start()  # but for a kept stream (read in place in its one pass: start leaves it), the drive is read
        # on the second core while the fusion's modules load and the installation's span is estimated
        from fieldlog.tools.fuse import estimate_installation, fuse

        if install:
            config, installed = estimate_installation(drive, config, st.inputs, stream if whole else None)
        res = fuse(drive, a.method, out, config, progress=Progress(f"fuse {a.method}"), smooth=a.smooth,
                   inputs=st.inputs, force=a.force, installation=installed, stream=stream)
    return res, config, installed


def run(a: argparse.Namespace) -> int:
    from fieldlog.drive.tables import TomlFile
    from fieldlog.drive.files import label
    from fieldlog.drive.outputs import check_new
    from fieldlog.tools.fuse_settings import parse_outage, settings

    conf = TomlFile.read(a.config)
    drive = open_drive(a.drive, a, conf)  # checked before the work
    out = out_file(a)
    check_new(out, a.force)  # refused before the time-offset and installation passes
    st = settings(drive, conf, input_spec(a), tuple(parse_outage(o) for o in a.outage or ()))
    for line in st.lines(drive):
        if line.startswith("warning: "):
            log.warning(line.removeprefix("warning: "))
        else:
            log.debug(line)
    t0 = time.monotonic()
    res, config, installed = _fused(a, drive, st, out)
    from fieldlog.tools.fuse import NO_ALIGNMENT, noise_sources

    imap, forced = st.inputs, config.get("outages")
    summary = dict(drive=label(drive), out=str(res.path), method=a.method, smooth=a.smooth,
                   imu_topic=imap.imu_topic, imu_frame=imap.imu_frame, fix_topic=imap.fix_topic,
                   vel_topic=imap.vel_topic, imu_samples=res.imu_samples, imu_rate_hz=res.imu_rate_hz,
                   imu_gaps=res.imu_gaps, imu_missing=res.imu_missing, imu_warnings=list(res.imu_warnings), gps_updates=res.updates,
                   solutions=res.rows, outages=res.outages, forced_outages=[list(o) for o in forced],
                   alignment={**(res.alignment_summary or {}), "note": res.alignment}, hinf=res.hinf, stationary_updates=len(res.still_ns),
                   zaru_skipped=len(res.zaru_skipped_ns),
                   odometer_scale=res.odometer["scale"] if res.odometer else None,
                   odometer_scale_sigma=res.odometer["scale_sigma"] if res.odometer else None,
                   odometer_slip_skipped=res.odometer["slip_skipped"] if res.odometer else None,
                   odometer_wheel_epochs=res.odometer["wheel_epochs"] if res.odometer else None,
                   odometer_wheels_skipped=res.odometer["wheels_skipped"] if res.odometer else None,
                   predictor_mode=config.get("predictor_mode"), virtual_odometer=res.virtual_odometer,
                   noise=noise_sources(st, res),
                   wall_s=round(time.monotonic() - t0, 3))
    summary.update(installed)
    if a.json:
        print(json.dumps(summary))
    else:
        windows = f" ({', '.join(f'{s:g}:{n:g}' for s, n in forced)} forced)" if forced else ""
        log.info(f"fused {summary['drive']} with {a.method}{' + RTS' * a.smooth}: IMU {imap.imu_topic} in "
                 f"{imap.imu_frame} ({res.imu_samples} samples, {res.imu_rate_hz:.0f} Hz, {res.imu_gaps} gaps "
                 f"bridged, {res.imu_missing} samples missing), fixes {imap.fix_topic}, velocity "
                 f"{imap.vel_topic or 'none'}: {res.updates} GPS updates, {res.outages} outage windows{windows}; "
                 f"wrote {res.path}: {res.rows} solutions in {summary['wall_s']:.1f} s")
        for key, fig in summary["noise"].items():
            log.debug(f"noise {key} = {fig['value']:.4g}: {fig['source']}")
        if res.alignment:
            how = res.alignment_summary or {}
            where = (f" (static interval {how['start_s']:.1f}-{how['end_s']:.1f} s)" if how.get("start_s") is not None
                     else "")
            log.info(f"alignment: {how.get('method', '?')}{where}, {res.alignment}")
        if summary.get("mounting_rpy_deg") or summary.get("imu_time_offset_s") is not None:
            log.info(_installation_line(summary, config.aids.installation_span_s))
        if res.hinf:
            log.info(f"hinf: {res.hinf['note']}")
        if res.odometer:
            o = res.odometer
            log.info(f"odometer: wheel-speed scale {o['scale']:.5f} +- {o['scale_sigma']:.5f} (1 sigma), "
                     f"{o['epochs']} epochs, {o['slip_skipped']} of them skipped as slip; wheels tested at "
                     f"{o['wheel_epochs']}, skipped " + ", ".join(f"{k} {n}" for k, n in o["wheels_skipped"].items()))
        if res.virtual_odometer:
            v = res.virtual_odometer
            skill = "none yet" if v["held_out_skill"] is None else f"{v['held_out_skill']:.2f}"
            log.info(f"virtual odometer ({v['model']}): held-out skill {skill} over 30-60 s (against the IMU's dead "
                     "reckoning), "
                     f"{'used at ' + str(v['epochs_used']) + ' outage epochs' if v['ran'] else 'did not run'}")
        if res.still_ns:
            log.info(f"stationary updates: {len(res.still_ns)}, of which {len(res.zaru_skipped_ns)} without the "
                     "zero-rate part (its mean rate failed the chi^2 test against the bias estimate)")
    for line in res.imu_warnings:
        log.warning(line)
    if res.rows == 0 and a.method != INS.name:
        log.warning(NO_ALIGNMENT)
    finish_out(a, out)
    return 0
