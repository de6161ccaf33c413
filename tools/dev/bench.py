"""``make bench``: speed and accuracy figures. Medians of several runs; ratios where two things are compared.

    python -m fieldlog.tools.dev.bench [--only NAME ...] [--runs N] [--markdown]

Each bench prints its full figures; ``--markdown`` prints, instead (the full output goes to stderr), the headline
figures as rows of docs/results.md's "From make bench" table, so that table is refreshed from a run.
"""
from __future__ import annotations

import argparse
import compileall
import contextlib
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np

from fieldlog.fusion.methods import DKF, DKF_RBFN, INS, KF


ROWS: list[tuple[str, str, str]] = []   # (what [bench], figure, target): the --markdown table


def row(what: str, figure: str, target: str = "") -> None:
    """One row of docs/results.md's table of bench figures; ``what`` names the bench in brackets."""
    ROWS.append((what, figure, target))


def timed(fn: Callable[[], object], runs: int) -> tuple[float, list[float], object]:
    times, out = [], None
    for _ in range(runs):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), times, out


def fmt_times(ts: list[float]) -> str:
    return ", ".join(f"{t:.2f}" for t in ts)


def bench_sim(runs: int, tmp: Path) -> None:
    """fieldlog sim of the 600 s figure8 drive (target <= 30 s), and its time-stamp accuracy (flag <= 100 us)."""
    from fieldlog.tools.info import drive_info
    from fieldlog.tools.sim.simulate import simulate

    rms = []

    def one(seed: list[int] = [0]) -> None:
        seed[0] += 1
        path = tmp / f"f8_{seed[0]}.mcap"
        simulate("figure8", 600, seed[0], path)
        rms.append(drive_info(path).timing.rms_us)

    med, ts, _ = timed(one, runs)
    print(f"sim figure8 600 s:            median {med:6.2f} s  (runs: {fmt_times(ts)})   target <= 30 s")
    print(f"timestamp RMS, sampled PPS:   median {statistics.median(rms):6.1f} us (seeds 1..{runs}: "
          f"{', '.join(f'{r:.1f}' for r in rms)})   target <= 100 us")
    lat = []
    for seed in range(1, runs + 1):
        path = tmp / f"f8l_{seed}.mcap"
        simulate("figure8", 600, seed, path, pps_mode="latch")
        lat.append(drive_info(path).timing.rms_us)
    print(f"timestamp RMS, latched PPS:   median {statistics.median(lat):6.3f} us (seeds 1..{runs}: "
          f"{', '.join(f'{r:.3f}' for r in lat)})   target <= 5 us")
    row("`fieldlog sim`, figure8 600 s [sim]", f"{min(ts):.1f}–{max(ts):.1f} s", "≤ 30 s")
    row("IMU time-stamp RMS vs truth, sampled PPS [sim]", f"{min(rms):.0f}–{max(rms):.0f} µs", "≤ 100 µs")
    row("the same, latched PPS [sim]", f"{statistics.median(lat):.2f} µs", "≤ 5 µs")


def bench_codecs(runs: int, tmp: Path) -> None:
    """DAQ frame decode of a 600 s drive in read-sized chunks; NMEA decode, ours against pynmeagps."""
    from fieldlog.acquire import daq, nmea

    rng = np.random.default_rng(0)
    n = 300_000
    data = daq.encode_frames(np.arange(n), rng.integers(-2**23, 2**23, (n, 6)), rng.random(n) < 0.002)
    cuts = np.sort(rng.integers(0, len(data), len(data) // (20 * daq.FRAME_SIZE)))
    chunks = [data[a:b] for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(data)])]

    def decode_daq() -> int:
        dec = daq.DaqDecoder()
        return sum(len(dec.feed(c).k) for c in chunks)

    med, ts, got = timed(decode_daq, runs)
    assert got == n
    print(f"DAQ decode 300k frames:       median {med:6.3f} s  ({n / med / 1e6:.2f} M frames/s, "
          f"{len(chunks)} chunks)")
    row("DAQ frame decode in read-sized chunks [codecs]", f"{n / med / 1e6:.2f} M frames/s")

    from datetime import date

    lines = []
    for i in range(2000):
        tod = 36000.0 + i
        lines += [nmea.format_gga("GN", tod, 30.7 + i * 1e-6, 103.9, 1, 12, 0.8, 470.0, 0.0),
                  nmea.format_rmc("GN", tod, date(2026, 5, 4), 30.7, 103.9, 10.0, 1.0),
                  nmea.format_vtg("GN", 1.0, 10.0), nmea.format_gst("GN", tod, 1, 1, 1, 2),
                  nmea.format_zda("GN", tod, date(2026, 5, 4))]
    blob = b"".join(lines)
    pieces = [blob[i:i + 64] for i in range(0, len(blob), 64)]

    def ours() -> int:
        dec = nmea.NmeaDecoder()
        return sum(len(dec.feed(p)) for p in pieces)

    med_ours, _, got = timed(ours, runs)
    assert got == len(lines)
    print(f"NMEA decode 10k sentences:    median {med_ours * 1e3:6.1f} ms ({med_ours / len(lines) * 1e6:.1f} us each)")
    try:
        from pynmeagps import NMEAReader
    except ImportError:
        return

    def theirs() -> int:
        fr = nmea.LineFramer()
        return sum(1 for p in pieces for line in fr.feed(p) if NMEAReader.parse(line) is not None)

    med_theirs, _, _ = timed(theirs, runs)
    print(f"  same with pynmeagps.parse:  median {med_theirs * 1e3:6.1f} ms  -> ours is {med_theirs / med_ours:.1f}x faster")
    row("NMEA decode, ours against pynmeagps [codecs]", f"{med_ours / len(lines) * 1e6:.1f} µs a sentence, "
        f"×{med_theirs / med_ours:.1f} faster")


def bench_recorder(runs: int, tmp: Path) -> None:
    """Encoding and writing 600k IMU messages (a 600 s drive's /imu and /truth/imu)."""
    from fieldlog.drive import messages, recorder

    n = 300_000
    t = 1_777_000_000_000_000_000 + np.arange(n, dtype=np.int64) * 2_000_000
    w = np.random.default_rng(1).normal(size=(n, 3))

    def write() -> None:
        with recorder.Recorder(tmp / "rec.mcap", force=True) as rec:   # the same file each run
            for topic in ("/imu", "/truth/imu"):
                for s in range(0, n, 500):
                    sl = slice(s, s + 500)
                    rec.write_batch(topic, t[sl], messages.encode_imu(t[sl], w[sl], w[sl]))

    med, ts, _ = timed(write, runs)
    print(f"encode+write 600k Imu msgs:   median {med:6.2f} s  ({2 * n / med / 1e6:.2f} M msg/s, "
          f"{(tmp / 'rec.mcap').stat().st_size / 1e6:.0f} MB)")
    row("encode and write Imu messages [recorder]", f"{2 * n / med / 1e6:.2f} M messages/s")


def bench_ins(runs: int, tmp: Path) -> None:
    """Strapdown INS over 300k samples (the C kernel), and the truth it is fed from."""
    from fieldlog.fusion import ins
    from fieldlog.tools.sim import trajectory

    truth = trajectory.generate(trajectory.load_scenario("figure8"), 600)
    t = np.arange(300_000) / 500.0
    med_eval, _, ts = timed(lambda: truth.evaluate(t), runs)
    s0 = ins.NavState(t[0], ts.lat[0], ts.lon[0], ts.h[0], ts.v_n[0], ts.q[0])
    ins.integrate(s0, t[:10], ts.omega_ib_b[:10], ts.f_b[:10])      # the kernel loaded outside the timing
    med, _, sol = timed(lambda: ins.integrate(s0, t, ts.omega_ib_b, ts.f_b), runs)
    print(f"truth evaluate 300k samples:  median {med_eval:6.3f} s")
    print(f"INS integrate 300k samples:   median {med:6.3f} s  ({300_000 / med / 1e6:.1f} M samples/s)")
    row("strapdown INS [ins]", f"{300_000 / med / 1e6:.1f} M samples/s")


def bench_allan(runs: int, tmp: Path) -> None:
    """The 2-hour static drive through the whole chain: Allan deviation recovers ARW/VRW and bias instability."""
    from fieldlog.drive import reader
    from fieldlog.tools.allan import allan_deviation, noise_parameters
    from fieldlog.tools.sim.sensors import ImuErrorConfig
    from fieldlog.tools.sim.simulate import simulate

    path = tmp / "static.mcap"
    t0 = time.perf_counter()
    simulate("static", 7200, 11, path)
    t_sim = time.perf_counter() - t0
    imu = reader.read_topic(path, "/imu")
    cfg = ImuErrorConfig()
    taus, adev = allan_deviation(imu["omega_ib_b"], 500.0)
    g = noise_parameters(taus, adev, sensor="gyro")
    taus, adev = allan_deviation(imu["f_b"], 500.0)
    a = noise_parameters(taus, adev, sensor="accel")
    print(f"static 7200 s drive simulated in {t_sim:.1f} s; recovered / configured per axis x, y, z (within 15 %):")
    print("  gyro ARW          " + " ".join(f"{v / cfg.gyro_noise_density_dps_rthz:6.3f}" for v in g["arw_dps_rthz"]))
    print("  gyro bias instab. " + " ".join(f"{v / cfg.gyro_bias_instability_dps:6.3f}" for v in g["bias_instability_dps"]))
    print("  accel VRW         " + " ".join(f"{v / cfg.accel_noise_density_ug_rthz:6.3f}" for v in a["vrw_ug_rthz"]))
    print("  accel bias instab." + " ".join(f"{v / cfg.accel_bias_instability_ug:6.3f}" for v in a["bias_instability_ug"]))

    def span(v: np.ndarray, ref: float) -> str:
        return f"{np.min(v) / ref:.2f}–{np.max(v) / ref:.2f}"

    row("Allan deviation of a 2-hour static drive: recovered / configured gyro ARW, bias instability; accel VRW, "
        "bias instability [allan]", f"{span(g['arw_dps_rthz'], cfg.gyro_noise_density_dps_rthz)}, "
        f"{span(g['bias_instability_dps'], cfg.gyro_bias_instability_dps)}; "
        f"{span(a['vrw_ug_rthz'], cfg.accel_noise_density_ug_rthz)}, "
        f"{span(a['bias_instability_ug'], cfg.accel_bias_instability_ug)}", "within 15 %")


def bench_fusion(runs: int, tmp: Path, duration_s: float = 600.0) -> None:
    """fieldlog fuse of a 600 s figure8 drive by ins, kf, dkf and dkf-rbfn: seconds and real-time factor."""
    from fieldlog.tools.fuse import fuse
    from fieldlog.tools.sim.simulate import simulate

    path, warm = tmp / "fuse_f8.mcap", tmp / "fuse_warm.mcap"
    simulate("figure8", duration_s, 1, path)
    simulate("figure8", 30.0, 2, warm)
    for method in (INS.name, KF.name, DKF.name, DKF_RBFN.name):
        fuse(warm, method, tmp / "fused_warm.mcap", force=True)  # kernels loaded, caches warm outside the timing
        med, ts, res = timed(lambda m=method: fuse(path, m, tmp / f"fused_{m}.mcap", force=True), runs)
        print(f"fuse {method:8s} figure8 {duration_s:g} s: median {med:6.2f} s  (runs: {fmt_times(ts)})  "
              f"{res.imu_samples / med / 1e3:7.1f} k samples/s, real-time factor x{duration_s / med:.0f}")
        row(f"`fieldlog fuse --method {method}`, figure8 {duration_s:g} s [fusion]",
            f"{med:.2f} s (×{duration_s / med:.0f} real time)")


def bench_grades(runs: int, tmp: Path) -> None:
    """Outage drift per IMU grade: figure8-tactical (780 s, 200 Hz, creeping pull-away) with the grade in the
    simulator and the filter, kf with aids off, two 60 s outages after 10 minutes of driving; standalone GPS for
    the MEMS grades, RTK for the others."""
    from fieldlog.fusion import imugrade
    from fieldlog.drive import reader
    from fieldlog.tools.evaluation.evaluate import heading_at_starts, outage_error_series
    from fieldlog.tools.fuse import fuse
    from fieldlog.tools.fuse_settings import drive_config
    from fieldlog.tools.sim.simulate import simulate

    outages = ((630.0, 60.0), (720.0, 60.0))
    for grade in imugrade.GRADES:
        gps = "standalone" if grade.endswith("mems") else "rtk"
        sc = tmp / f"grade_{grade}.toml"
        sc.write_text(f'extends = "figure8-tactical"\nname = "{grade}"\n[imu]\ngrade = "{grade}"\n'
                      f'[gps]\nquality = "{gps}"\n[fusion]\nimu = "{grade}"\n')
        drive, out = tmp / f"grade_{grade}.mcap", tmp / f"grade_{grade}_kf.mcap"
        simulate(str(sc), None, 1, drive)
        fuse(drive, KF.name, out, drive_config(drive).replace(outages=outages))
        t0 = min(t.first_ns for t in reader.topics(drive) if t.topic == "/imu")
        win = [(t0 + int(a * 1e9), t0 + int((a + n) * 1e9)) for a, n in outages]
        t, e = outage_error_series(drive, out, KF.name, win)
        h = np.hypot(e[:, 0], e[:, 1])
        drift = [h[(t >= a) & (t < b)].max() for a, b in win]
        err, sig = heading_at_starts(drive, out, KF.name, win)
        print(f"{grade:12s} {gps:10s} 2D RMS {math.sqrt(np.mean(h ** 2)):8.3f} m, max drift per outage "
              + ", ".join(f"{d:.3f}" for d in drift) + " m; heading at the starts "
              + ", ".join(f"{x:+.3f}±{y:.3f}°" for x, y in zip(err, sig)))
        row(f"{grade}, {gps} GPS: 2D RMS in two 60 s outages; max drift per outage; heading error ± σ at the "
            "starts [grades]", f"{math.sqrt(np.mean(h ** 2)):.2f} m; " + ", ".join(f"{d:.2f}" for d in drift)
            + " m; " + ", ".join(f"{x:+.3f} ± {y:.3f}°" for x, y in zip(err, sig)))


# Peak RSS of a child is read from its VmHWM, the high-water mark of its own address space: ru_maxrss (and
# RUSAGE_CHILDREN) would also carry the parent's RSS at fork time, which Linux keeps across exec: here the
# bench's own simulated drive, several GB.
_PEAK_MB = "int(re.search(r'VmHWM:\\s+(\\d+) kB', open('/proc/self/status').read()).group(1)) / 1024"
_CLI_CHILD = ("import re, sys\n"
              "from fieldlog.tools.cli import main\n"
              "rc = main(sys.argv[1:])\n"
              f"print('peak_rss_mb', {_PEAK_MB})\n"
              "sys.exit(rc)\n")


def _fuse_child(drive: Path, method: str, out: Path, smooth: bool = False, config: Path | None = None) -> dict:
    """``fieldlog fuse --json`` as a user runs it (the installation pass included, unless ``config`` turns it off)
    in a fresh Python process: seconds (wall, start-up included), IMU samples and the process's peak RSS (MB)."""
    import json

    cmd = [sys.executable, "-c", _CLI_CHILD, "fuse", str(drive), "--method", method, "--out", str(out), "--force",
           "--json", "-q", *(["--smooth"] if smooth else []), *(["--config", str(config)] if config else [])]
    t0 = time.perf_counter()
    res = subprocess.run(cmd, check=True, capture_output=True, text=True, cwd=Path(__file__).resolve().parents[2])
    s = time.perf_counter() - t0
    lines = res.stdout.strip().splitlines()
    summary = json.loads(next(ln for ln in lines if ln.startswith("{")))
    return {"s": s, "n": summary["imu_samples"], "rss_mb": float(lines[-1].split()[1])}


_LONG_TARGETS = {KF.name: "≤ 2 s; RSS equal", DKF_RBFN.name: "≤ 4 s; RSS equal"}  # the 1-hour drive
ONE_PASS = ", one pass"  # the name's suffix of a fuse without the installation's first pass
SPAN = ", first 600 s"  # ... of a fuse with the installation from the drive's first 600 s
_VARIANTS = {  # suffix: (its [fusion] table, its words in a row)
    ONE_PASS: ("estimate_installation = false", " without the installation passes (`estimate_installation = false`)"),
    SPAN: ("installation_span_s = 600.0", " with the installation from the first 600 s (`installation_span_s = 600`)")}


def _variant_config(tmp: Path, drive: Path, suffix: str) -> Path:
    """A ``fuse --config`` of the variant ``suffix`` (``_VARIANTS``): ``ONE_PASS`` makes the command one engine
    pass, the fusion alone (no time-offset and mounting passes before it); ``SPAN`` estimates the installation
    from the drive's first 600 s. ``--config`` replaces the drive's own settings, so the drive must have none (a
    simulated figure8 drive has no ``fusion.config`` record): the run differs from the default one by that
    setting alone."""
    from fieldlog.tools.fuse_settings import drive_table

    if drive_table(drive):
        raise SystemExit(f"{drive}: has a fusion.config record; the variant's run would not compare with the default")
    path = tmp / f"variant{list(_VARIANTS).index(suffix)}.toml"
    path.write_text(f"[fusion]\n{_VARIANTS[suffix][0]}\n")
    return path


def _shown(name: str) -> tuple[str, str]:
    """A run's ``name`` for a row: (the name without its variant's suffix, that suffix in words)."""
    for suffix, (_, words) in _VARIANTS.items():
        if name.endswith(suffix):
            return name.removesuffix(suffix), words
    return name, ""


def bench_fuse_long(runs: int, tmp: Path, hours: tuple[float, float] = (1.0, 2.0)) -> None:
    """``fieldlog fuse`` of 1-hour and 2-hour 500 Hz figure8 drives by kf and dkf-rbfn (and kf --smooth; both
    in one pass and with the installation from the first 600 s too, :func:`_variant_config`), each a command in
    a child process: samples/s, real-time factor, peak RSS (streaming: the same for both lengths)."""
    from fieldlog.tools.sim.simulate import simulate

    drives = []
    for h in hours:  # cached in the bench directory; the 1-hour one is bench_view's drive
        path = _hour_drive(tmp) if h == 1.0 else tmp / f"hours_{h:g}.mcap"
        if not path.exists():
            t0 = time.perf_counter()
            simulate("figure8", 3600.0 * h, 1, path)
            print(f"  (simulated {h:g} h figure8 in {time.perf_counter() - t0:.0f} s, {path.stat().st_size / 1e9:.1f} GB)")
        drives.append(path)
    warm = tmp / "fuse_warm.mcap"
    if not warm.exists():
        simulate("figure8", 30.0, 2, warm)
    _fuse_child(warm, KF.name, tmp / "fused_warm.mcap")  # a warm run outside the figures
    configs = {v: _variant_config(tmp, drives[0], v) for v in _VARIANTS}
    for method, smooth, variant in ((KF.name, False, ""), (DKF_RBFN.name, False, ""), (KF.name, True, ""),
                                    (KF.name, False, ONE_PASS), (DKF_RBFN.name, False, ONE_PASS),
                                    (KF.name, False, SPAN), (DKF_RBFN.name, False, SPAN)):
        name = method + (" --smooth" if smooth else "") + variant
        config = configs.get(variant)
        r = [_fuse_child(d, method, tmp / f"long_{method}.mcap", smooth, config) for d in drives]
        h0 = hours[0]
        print(f"fuse {name:18s} {h0:g} h: {r[0]['s']:6.1f} s, {r[0]['n'] / r[0]['s'] / 1e3:7.1f} k samples/s, "
              f"real-time factor x{3600.0 * h0 / r[0]['s']:.0f}; peak RSS {h0:g} h {r[0]['rss_mb']:6.0f} MB, "
              f"{hours[1]:g} h {r[1]['rss_mb']:6.0f} MB (ratio {r[1]['rss_mb'] / r[0]['rss_mb']:.2f})")
        shown = "".join(_shown(name))
        row(f"`fieldlog fuse` of a {h0:g}-hour 500 Hz drive, {shown}: time; peak RSS {h0:g} h / {hours[1]:g} h "
            "[fuse-long]", f"{r[0]['s']:.1f} s (×{3600.0 * h0 / r[0]['s']:.0f}); {r[0]['rss_mb']:.0f} / "
            f"{r[1]['rss_mb']:.0f} MB", _LONG_TARGETS.get(name, ""))


def _serve_and_acquire(duration_s: float, speed: float, truth: Path, out: Path, *daemon_args: str,
                       serve_args: tuple[str, ...] = ()) -> tuple[subprocess.Popen[str], subprocess.Popen[str]]:
    """``sim --serve --hold`` of figure8 (truth to ``truth``) and ``acquire`` on its ptys into ``out``, the daemon
    recording; the caller releases the stream with SIGUSR1 to the first."""
    cli = [sys.executable, "-m", "fieldlog"]
    serve = subprocess.Popen([*cli, "sim", "--serve", "--scenario", "figure8", "--duration", str(duration_s),
                              "--seed", "1", "--speed", str(speed), "--hold", "--truth", str(truth), *serve_args],
                             stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    paths = dict(serve.stdout.readline().split() for _ in range(2))
    if "--link-dir" in serve_args:
        link = Path(serve_args[serve_args.index("--link-dir") + 1])
        paths = {name: str(link / name) for name in paths}
    scale = ["--time-scale", str(speed)] if speed != 1 else []
    d = subprocess.Popen([*cli, "acquire", "--daq", paths["daq"], "--gps", paths["gps"], "--out", str(out),
                          "--quiet", *scale, *daemon_args], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                         text=True)
    while "recording" not in (line := d.stderr.readline()):
        assert line, "the daemon exited early"
    return serve, d


def bench_daemon(runs: int, tmp: Path, duration_s: float = 600.0) -> None:
    """fieldlog acquire against sim --serve ptys: 10 min at real speed, then x20; loss, timing, CPU."""
    import os
    import signal

    from fieldlog.acquire.timesync import SyncState
    from fieldlog.drive import reader
    from fieldlog.drive.reader import read_metadata

    def one(speed: float, duration: float) -> None:
        out, truth = tmp / f"drives_x{speed:g}", tmp / f"truth_x{speed:g}.mcap"
        serve, d = _serve_and_acquire(duration, speed, truth, out)
        serve.send_signal(signal.SIGUSR1)
        serve.wait()
        d.send_signal(signal.SIGTERM)
        _, status, usage = os.wait4(d.pid, 0)
        d.returncode = os.waitstatus_to_exitcode(status)
        cpu = usage.ru_utime + usage.ru_stime
        sent = read_metadata(truth)["serve"]
        files = sorted(out.glob("*/*.mcap"))
        counters = read_metadata(files[-1])["acquire.counters"]
        imu = np.concatenate([reader.read_topic(f, "/imu")["log_time_ns"] for f in files])
        state = np.concatenate([reader.read_topic(f, "/time/sync")["state"] for f in files])
        tru = reader.read_topic(truth, "/truth/imu")["log_time_ns"]
        lost_frames = int(sent["daq_frames"]) - int(counters["daq.frames"])
        lost_lines = int(sent["nmea_lines"]) - int(counters["nmea.lines"])
        line = (f"x{speed:<4g} {duration:5.0f} s of data: lost DAQ frames {lost_frames}, lost NMEA lines {lost_lines}, "
                f"daemon CPU {cpu:.1f} s = {100 * cpu * speed / duration:.1f} % of one core")
        figure = f"{lost_frames} / {lost_lines}, {100 * cpu * speed / duration:.1f} % of a core"
        if speed == 1 and len(imu) == len(tru):
            # at real speed the serve process sets the drive start to 'now', so stamps compare with truth directly
            locked = np.searchsorted(imu, imu[0]) if (state == SyncState.LOCKED).any() else 0
            err = (imu[locked:] - tru[locked:]) / 1e3
            line += f", timestamp RMS vs truth {np.sqrt(np.mean(err ** 2)):.1f} us"
            figure += f", {np.sqrt(np.mean(err ** 2)):.1f} µs"
        print(line)
        row(f"daemon on ptys at x{speed:g}, {duration / 60:g} min of data: lost frames / lines, CPU, time-stamp RMS "
            "[daemon]", figure, "0 / 0, ≤ 10 %, ≤ 100 µs" if speed == 1 else "0 / 0")

    one(1.0, duration_s)
    one(20.0, 120.0)


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` so far (all its threads), from /proc."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def bench_soak(runs: int, tmp: Path, duration_s: float = 1800.0, speed: float = 20.0) -> None:
    """soak: acquire at x20 for 30 min of data (--soak-minutes), 1 % corrupt bytes, the DAQ unplugged 5 s every
    2 min and the receiver's clock +1 h for 30 s halfway: frames and lines lost outside the unplugged intervals,
    the jump's fixes, RSS over data time (warm-up against growth), CPU (also per minute of data)."""
    import os
    import re
    import signal
    from collections import Counter

    from fieldlog.acquire import daq
    from fieldlog.drive.messages import STATUS_NO_FIX
    from fieldlog.drive import reader
    from fieldlog.drive.reader import read_metadata
    from fieldlog.tools.sim.serve import PORTS, corrupt_stream, delivered, simulated_streams

    out, truth, links = tmp / "soak", tmp / "soak_truth.mcap", tmp / "soak_ports"
    unplug = [a for t in range(120, int(duration_s) - 10, 120) for a in ("--unplug", f"daq:{t}:5")]
    jump_s = round(duration_s / 2) + 0.5                     # (mid-second: the window's edges are unambiguous)
    serve, d = _serve_and_acquire(duration_s, speed, truth, out, serve_args=(
        "--corrupt", "0.01", "--link-dir", str(links), "--clock-jump", f"{jump_s:g}:30:3600", *unplug))
    rss: list[tuple[float, float]] = []                      # (s of data, MB)

    def sample() -> None:
        try:
            text = Path(f"/proc/{d.pid}/status").read_text()
            rss.append(((time.monotonic() - t0) * speed, int(text.split("VmRSS:")[1].split()[0]) / 1024))
        except (OSError, IndexError):
            pass

    cpu0 = _cpu_s(d.pid)                                     # (startup: imports, first file, ports)
    t0 = time.monotonic()
    serve.send_signal(signal.SIGUSR1)
    while serve.poll() is None:
        sample()
        time.sleep(1.0)
    d.send_signal(signal.SIGTERM)
    _, status, usage = os.wait4(d.pid, 0)
    wall = time.monotonic() - t0
    sent = read_metadata(truth)["serve"]
    files = sorted(out.glob("*/*.mcap"))
    c = read_metadata(files[-1])["acquire.counters"]
    # what the ports delivered: the simulated streams, corrupted as served, minus the unplugs' byte ranges
    clean = simulated_streams(sent)
    stream = {p: corrupt_stream(clean[p], 0.01, int(sent["seed"]), p) for p in PORTS}
    daq_ok, daq_keep = delivered(clean["daq"], sent["daq_gaps"])
    hit = np.zeros(len(clean["daq"]), bool)
    hit[stream["daq"][1]] = True
    n = len(clean["daq"]) // daq.FRAME_SIZE
    whole = (daq_keep & ~hit)[:n * daq.FRAME_SIZE].reshape(n, daq.FRAME_SIZE).all(axis=1)
    got_daq = b"".join(bytes(m.data) for f in files for m in reader.read_topic(f, "/raw/daq")["msgs"])
    want_daq = delivered(stream["daq"][0], sent["daq_gaps"])[0]
    text, pos = clean["gps"], stream["gps"][1]
    lines = text.split(b"\r\n")[:-1]
    starts = np.cumsum([0] + [len(x) + 2 for x in lines[:-1]])
    ghit = np.zeros(len(text), bool)
    ghit[pos] = True
    gkeep = delivered(text, sent["gps_gaps"])[1]
    intact = Counter(x.decode() for s0, x in zip(starts, lines)
                     if not ghit[s0:s0 + len(x) + 1].any() and gkeep[s0:s0 + len(x) + 2].all())
    got_lines = Counter(m.sentence for f in files for m in reader.read_topic(f, "/gps/nmea")["msgs"])
    # the jumped epochs that reached the daemon: their timed sentences carry the drive's time + 1 h
    sod0 = (int(sent["drive_start_utc_ns"]) / 1e9 + jump_s + 3600) % 86400
    shown = {f[1] for f in (x.split(",") for x in got_lines if x[3:6] in ("GGA", "RMC", "GST", "ZDA"))
             if len(f) > 1 and re.fullmatch(r"\d{6}(\.\d*)?", f[1])}    # (1/256 corrupt lines pass the checksum)
    jumped = sum(0 <= (int(x[:2]) * 3600 + int(x[2:4]) * 60 + float(x[4:]) - sod0) % 86400 < 30 for x in shown)
    fix = {k: np.concatenate([reader.read_topic(f, "/gps/fix")[k] for f in files]) for k in ("log_time_ns", "status")}
    t_start = int(sent["drive_start_utc_ns"])
    t_fix = (fix["log_time_ns"] - t_start) / 1e9
    flagged = t_fix[fix["status"] == STATUS_NO_FIX]
    # (a flagged epoch is stamped at the read that brought it; the jumped epochs arrive up to 1.5 s later)
    in_jump = int(((flagged >= jump_s) & (flagged < jump_s + 31.5)).sum())
    print(f"soak {duration_s / 60:.0f} min of data at x{speed:g} in {wall:.0f} s: exit {os.waitstatus_to_exitcode(status)}, "
          f"{len(files)} file(s), {c['port.daq.disconnects']} DAQ disconnects, {sent['daq_undrained_unplugs']} "
          f"undrained unplugs")
    print(f"  DAQ: bytes delivered {len(want_daq)} (+{sent['daq_lost_bytes']} lost while unplugged), recorded "
          f"{len(got_daq)}, recorded == delivered: {got_daq == want_daq}; whole uncorrupted frames outside the "
          f"unplugs {int(whole.sum())}, decoded {c['daq.frames']}: lost outside the unplugged intervals "
          f"{int(whole.sum()) - int(c['daq.frames'])}; bad CRC {c['daq.bad_crc']}, resyncs {c['daq.resyncs']}")
    print(f"  GPS: bytes delivered {sent['gps_bytes']}, read {c['port.gps.bytes']}; intact NMEA lines "
          f"{sum(intact.values())}, of them not recorded {sum((intact - got_lines).values())}; bad checksum "
          f"{c['nmea.bad_checksum']}; epochs {c['gps_epochs']}, NO_FIX {c['gps_no_fix']}: receiver_time "
          f"{c.get('gps_no_fix.receiver_time', 0)}, NO_FIX in the jump window {in_jump} (30 epochs jumped +1 h at "
          f"{jump_s:g} s, {jumped} of them recorded in /gps/nmea), no_quality (GGA lost to corruption) {c.get('gps_no_fix.no_quality', 0)}; latest fix "
          f"{t_fix.max():.1f} s after the drive start ({duration_s:g} s long)")
    print(f"  processing errors {c['processing_errors']}, dropped reads {c['port.daq.dropped_reads']}/"
          f"{c['port.gps.dropped_reads']}; daemon CPU {usage.ru_utime + usage.ru_stime:.0f} s "
          f"({(usage.ru_utime + usage.ru_stime) / wall * 100:.0f} % of one core)")
    print(f"  daemon CPU per minute of data: {(usage.ru_utime + usage.ru_stime - cpu0) / (duration_s / 60):.3f} s "
          f"(from the release of the stream to the exit; startup {cpu0:.2f} s before it)")
    t_rss, mb = np.array(rss).T
    at = ", ".join(f"{m:g} min {mb[np.argmin(np.abs(t_rss - 60 * m))]:.0f} MB" for m in (1, 5, 10, 20, 30, 45, 60)
                   if 60 * m <= t_rss[-1] + 60)

    def slope(after: np.ndarray) -> str:
        """MB per 10 min of data: least squares, and Theil-Sen (the median of pairwise slopes)."""
        x, y = t_rss[after] / 600, mb[after]
        if x.size < 3:
            return "n/a (too short)"
        i, j = np.triu_indices(len(x), 1)
        return f"{np.polyfit(x, y, 1)[0]:+.2f} ({np.median((y[j] - y[i]) / (x[j] - x[i])):+.2f})"

    # (the second half starts at the clock jump, whose few MB held for seconds then freed tilt its slope)
    print(f"  daemon RSS at {at}; max {mb.max():.0f} MB; slope per 10 min of data, least squares (Theil-Sen): after "
          f"the 5-min warm-up {slope(t_rss >= 300)} MB, over the second half {slope(t_rss >= t_rss[-1] / 2)} MB")
    what = f"soak, x{speed:g}, {duration_s / 60:g} min of data"
    row(f"{what}: DAQ frames lost outside the unplugs, intact NMEA lines not recorded, processing errors [soak]",
        f"{int(whole.sum()) - int(c['daq.frames'])} of {int(whole.sum())} "
        f"({'byte-exact' if got_daq == want_daq else 'recording differs'}), "
        f"{sum((intact - got_lines).values())} of {sum(intact.values())}, {c['processing_errors']}", "0, 0, 0")
    row(f"{what}: jumped epochs flagged NO_FIX, of those recorded [soak]", f"{in_jump} of {jumped}", "all")
    minutes = [m for m in (1, 5, 10, 20, 30, 45, 60) if 60 * m <= t_rss[-1] + 60]
    row(f"{what}: daemon RSS at {' / '.join(map(str, minutes))} min; slope per 10 min after the warm-up, least "
        "squares (Theil-Sen) [soak]", " / ".join(f"{mb[np.argmin(np.abs(t_rss - 60 * m))]:.0f}" for m in minutes)
        + f" MB; {slope(t_rss >= 300)} MB", "flat")
    row(f"{what}: daemon CPU, whole run; per minute of data [soak]",
        f"{usage.ru_utime + usage.ru_stime:.0f} s ({(usage.ru_utime + usage.ru_stime) / wall * 100:.0f} % of a core); "
        f"{(usage.ru_utime + usage.ru_stime - cpu0) / (duration_s / 60):.2f} s")


def bench_bus(runs: int, tmp: Path, duration_s: float = 60.0) -> None:
    """The live bus: fieldlog acquire against sim --serve ptys at real speed, one client; provisional /imu latency
    from the serial read (target median <= 50 ms) and provisional stamps against final and truth."""
    import os
    import signal
    import threading

    from fieldlog.acquire.timesync import SyncState
    from fieldlog.drive import reader
    from fieldlog.replay import live

    out, truth, bus, cfg = tmp / "drives_bus", tmp / "truth_bus.mcap", tmp / "bus.sock", tmp / "bus.toml"
    cfg.write_text(f'[daemon]\nbus = "{bus}"\n')
    serve, d = _serve_and_acquire(duration_s, 1.0, truth, out, "--config", str(cfg))
    batches: list = []
    client = threading.Thread(target=lambda: batches.extend(live.iter_batches(str(bus))))
    client.start()
    time.sleep(0.5)
    serve.send_signal(signal.SIGUSR1)
    serve.wait()
    d.send_signal(signal.SIGTERM)
    usage = os.wait4(d.pid, 0)[2]
    client.join(30)
    cpu = usage.ru_utime + usage.ru_stime
    prov = [b for b in batches if b.topic == "/imu" and b.provisional]
    lat = np.array([(b.recv_mono_ns - b.read_mono_ns) / 1e6 for b in prov])
    print(f"provisional /imu on the bus, x1 {duration_s:g} s: {len(prov)} batches (one per DAQ read), latency serial "
          f"read -> client median {np.median(lat):.2f} ms, p95 {np.percentile(lat, 95):.2f} ms, max {lat.max():.1f} ms"
          f"   target median <= 50 ms; daemon CPU {100 * cpu / duration_s:.1f} % of one core")
    row("live bus: serial read to client, IMU block latency median / p95 [bus]",
        f"{np.median(lat):.2f} ms / {np.percentile(lat, 95):.1f} ms", "≤ 50 ms median")
    (f,) = sorted(out.glob("*/*.mcap"))
    final = reader.read_topic(f, "/imu")["log_time_ns"]
    tru = reader.read_topic(truth, "/truth/imu")["log_time_ns"]
    t = np.concatenate([b.log_time_ns for b in prov])
    state = np.concatenate([b.state for b in prov])
    fitted = np.concatenate([np.full(len(b.log_time_ns), not b.host_clock) for b in prov])
    i0 = len(final) - len(t)                # rows read before the client connected
    sel = fitted & (state == SyncState.LOCKED)
    d_us = (t - final[i0:])[sel] / 1e3
    e_us = (t - tru[i0:])[sel] / 1e3
    ef_us = (final[i0:] - tru[i0:])[sel] / 1e3
    def rms(x: np.ndarray) -> float:
        return float(np.sqrt(np.mean(x ** 2)))

    print(f"  provisional - final stamps (LOCKED, {sel.sum()} samples): RMS {rms(d_us):.0f} us, max "
          f"{np.abs(d_us).max():.0f} us; vs truth: provisional RMS {rms(e_us):.0f} us, final RMS {rms(ef_us):.0f} us "
          f"(sampled PPS); before the first lock {np.count_nonzero(~fitted)} samples on the host clock")
    from fieldlog.acquire.daemon import ProvisionalImu
    from fieldlog.acquire.pipeline import Pipeline
    from fieldlog.acquire.timesync import TimeSyncConfig
    from fieldlog.tools.sim import simulate, trajectory

    class Collect:
        """The bus side of ProvisionalImu: keeps what it publishes."""

        def __init__(self) -> None:
            self.t: list[np.ndarray] = []
            self.state: list[np.ndarray] = []

        def active(self) -> bool:
            return True

        def publish(self, topic: str, t: np.ndarray, p: object, state: np.ndarray, **_: object) -> None:
            self.t.append(t)
            self.state.append(state)

    for mode in ("flag", "latch"):
        reads, tr, *_ = simulate.make_reads(trajectory.load_scenario("figure8"), 300.0, 1, mode)
        sink, bus = _ImuStamps(), Collect()
        pipe = Pipeline(sink, sync_cfg=TimeSyncConfig(pps_mode=mode))
        prov = pipe.on_frames = ProvisionalImu(pipe, bus)
        for r in reads:
            pipe.feed(r.port, r.mono_ns, r.wall_ns, r.data)
            prov.flush()
        pipe.finish()
        t, fin, st = np.concatenate(bus.t), np.concatenate(sink.imu), np.concatenate(bus.state)
        tru = tr["t0_ns"] + np.round(tr["t_k"] * 1e9).astype(np.int64)
        late = (st == SyncState.LOCKED) & (np.arange(len(t)) >= 60 * 500)
        print(f"  same code on a simulated 300 s drive, {mode} PPS, LOCKED after the first minute: provisional - "
              f"final RMS {rms((t - fin)[late] / 1e3):.2f} us; vs truth provisional {rms((t - tru)[late] / 1e3):.2f} "
              f"us, final {rms((fin - tru)[late] / 1e3):.2f} us")


class _ImuStamps:
    """A pipeline sink that keeps only the ``/imu`` time stamps (ns), one array per batch."""

    def __init__(self) -> None:
        self.imu: list[np.ndarray] = []

    def write(self, *_: object) -> None:
        pass

    def write_batch(self, topic: str, t: np.ndarray, _: object) -> None:
        if topic == "/imu":
            self.imu.append(np.asarray(t))


def bench_qerr(runs: int, tmp: Path) -> None:
    """u-blox TIM-TP qErr: IMU time-stamp RMS vs truth with and without it (300 s figure8, seeds 1..runs)."""
    from fieldlog.acquire.pipeline import Pipeline
    from fieldlog.acquire.timesync import TimeSyncConfig
    from fieldlog.tools.sim import simulate, trajectory

    for mode in ("flag", "latch"):
        res: dict[bool, list[float]] = {True: [], False: []}
        for seed in range(1, runs + 1):
            reads, tr, *_ = simulate.make_reads(trajectory.load_scenario("figure8"), 300.0, seed, mode, "ublox")
            tru = tr["t0_ns"] + np.round(tr["t_k"] * 1e9).astype(np.int64)
            for use in (True, False):
                sink = _ImuStamps()
                pipe = Pipeline(sink, sync_cfg=TimeSyncConfig(pps_mode=mode, pulse_error=use))
                for r in reads:
                    pipe.feed(r.port, r.mono_ns, r.wall_ns, r.data)
                pipe.finish()
                err = (np.concatenate(sink.imu) - tru)[60 * 500:]     # after the first minute
                res[use].append(float(np.sqrt(np.mean((err / 1e3) ** 2))))
        unit = "us"
        print(f"  {mode} PPS, u-blox: IMU stamp RMS vs truth with qErr {statistics.mean(res[True]):.4f} {unit}, "
              f"without {statistics.mean(res[False]):.4f} {unit} (per seed with: "
              f"{', '.join(f'{x:.4f}' for x in res[True])}; without: {', '.join(f'{x:.4f}' for x in res[False])})")
        row(f"u-blox receiver, {mode} PPS: IMU stamp RMS with / without TIM-TP qErr [qerr]",
            f"{statistics.mean(res[True]):.4f} / {statistics.mean(res[False]):.4f} µs")


def bench_view(runs: int, tmp: Path) -> None:
    """A 1-hour 500 Hz drive plus one fused method (kf) to .rrd (target <= 10 s), and the file size."""
    from fieldlog.fusion.config import FusionConfig
    from fieldlog.replay.view import view
    from fieldlog.tools.fuse import fuse

    drive, fused, rrd = _hour_drive(tmp), tmp / "hour_kf.mcap", tmp / "hour.rrd"
    fuse(drive, KF.name, fused, FusionConfig(), force=True)
    med, ts, _ = timed(lambda: view(drive, [fused], rrd, force=True), runs)
    print(f"view 1 h drive + kf -> .rrd:  median {med:6.2f} s  (runs: {fmt_times(ts)})   target <= 10 s; "
          f"{rrd.stat().st_size / 1e6:.1f} MB .rrd from a {drive.stat().st_size / 1e6:.0f} MB drive")
    row("`fieldlog view` of a 1-hour drive plus kf to `.rrd` [view]",
        f"{med:.1f} s, {rrd.stat().st_size / 1e6:.0f} MB from a {drive.stat().st_size / 1e6:.0f} MB drive", "≤ 10 s")


def bench_export(runs: int, tmp: Path) -> None:
    """fieldlog export of a 1-hour 500 Hz drive to Parquet, in a child process: time and peak RSS."""

    from fieldlog.tools.sim.simulate import simulate

    drive = tmp / "hour.mcap"  # bench_view's drive, cached in the bench directory
    if not drive.exists():
        simulate("figure8", 3600, 1, drive)

    peaks = []

    def one() -> int:
        out = tmp / "hour_export"
        r = subprocess.run([sys.executable, "-c", _CLI_CHILD, "export", str(drive), "--out", str(out), "--force"],
                           capture_output=True, text=True, cwd=Path(__file__).resolve().parents[2])
        assert r.returncode == 0, r.stderr
        peaks.append(float(r.stdout.split()[-1]))
        return sum(f.stat().st_size for f in out.rglob("*.parquet"))

    med, ts, size = timed(one, runs)
    rss = max(peaks)
    print(f"export 1 h drive -> Parquet:  median {med:6.2f} s  (runs: {fmt_times(ts)}); peak RSS {rss:.0f} MB; "
          f"{size / 1e6:.0f} MB of Parquet from a {drive.stat().st_size / 1e6:.0f} MB drive")
    row("`fieldlog export` of a 1-hour drive to Parquet: time, peak RSS [export]", f"{med:.0f} s, {rss:.0f} MB")


def bench_batch(runs: int, tmp: Path, duration_s: float = 300.0) -> None:
    """fieldlog batch of 4 drives (300 s; kf, dkf; 30 s outages) in drive-hours per core-hour: one by one
    in-process (one core, the reference), a local cluster of 2 workers (started by each batch), and 2 ``dask
    worker`` processes of a scheduler on 127.0.0.1 (``tools.dev.cluster``: started before, as a cluster runs)."""
    from fieldlog.tools.batch import drive_rows, run_batch
    from fieldlog.tools.dev.cluster import loopback_cluster
    from fieldlog.tools.sim.simulate import simulate

    drives = []
    for seed in range(1, 5):
        drives.append(tmp / f"b{seed}.mcap")
        simulate("figure8", duration_s, seed, drives[-1])
    hours = len(drives) * duration_s / 3600.0

    def batch(**where) -> None:
        run_batch(drives, [KF.name, DKF.name], [30.0], tmp / "batch", say=lambda _m: None, force=True, **where)

    t_one, w_one, _ = timed(lambda: [drive_rows(d, [KF.name, DKF.name], [30.0], tmp / "one", force=True) for d in drives],
                            runs)
    t_local, w_local, _ = timed(lambda: batch(workers=2), runs)
    with loopback_cluster(2, tmp / "cluster") as address:
        t_sched, w_sched, _ = timed(lambda: batch(scheduler=address), runs)
    rate = {"one by one, in-process": hours / (t_one / 3600.0),
            "local cluster, 2 workers": hours / (2 * t_local / 3600.0),
            "scheduler on 127.0.0.1, 2 workers": hours / (2 * t_sched / 3600.0)}
    load = os.getloadavg()[0]
    for (what, r), ts in zip(rate.items(), (w_one, w_local, w_sched)):
        print(f"batch of {len(drives)} x {duration_s:g} s drives, {what}: {r:.0f} drive-hours per core-hour "
              f"(runs {fmt_times(ts)} s)")
    print(f"load {load:.1f}")
    row("`fieldlog batch`, 4 drives of 300 s, kf + dkf with 30 s outages: drive-hours per core-hour, one by one / "
        "local cluster / scheduler on 127.0.0.1 (2 workers each) [batch]",
        " / ".join(f"{r:.0f}" for r in rate.values()) + f" (load {load:.1f})")


def bench_cycle(runs: int, tmp: Path) -> None:
    """Per-cycle cost at n = 15 of kf, kf-ukf (outage), sckf, ssr-sckf, hinf: prediction alone and with a GPS update."""
    from fieldlog.tools.evaluation.studies import CYCLE_REPS, cycle_costs, cycle_flops

    n = 15
    med = cycle_costs(runs)
    flops = cycle_flops(n, 6)
    kp, kt = med[KF.name]["predict_us"], med[KF.name]["total_us"]
    fp, ft = flops[KF.name][2], flops[KF.name][2] + flops[KF.name][3]
    print(f"n = {n}, m = 6 GPS rows, {CYCLE_REPS} cycles x {runs} runs, medians; kf-ukf in outage mode (UT every cycle)")
    print(f"{'method':9s} {'predict us':>10s} {'x kf':>6s} {'pred+upd us':>11s} {'x kf':>6s} {'(upd us)':>8s} "
          f"{'pred kflop':>10s} {'x kf':>6s} {'total kflop':>11s} {'x kf':>6s}")
    for name, c in med.items():
        p, t, u = c["predict_us"], c["total_us"], c["update_us"]
        fl_p, fl_t = flops[name][2], flops[name][2] + flops[name][3]
        print(f"{name:9s} {p:10.1f} {p / kp:6.1f} {t:11.1f} {t / kt:6.1f} {u:8.1f} "
              f"{fl_p / 1e3:10.1f} {fl_p / fp:6.1f} {fl_t / 1e3:11.1f} {fl_t / ft:6.1f}")
        if name != KF.name:
            row(f"filter cycle cost of {name} against kf, prediction / with a GPS update [cycle]",
                f"×{p / kp:.1f} / ×{t / kt:.1f}")
    print("flop formulas (n states, m rows, c = 4 c_f + 12 n per point RK4 step, c_f ~ 450):")
    for name, (fp_s, fu_s, _, _) in flops.items():
        print(f"  {name:9s} predict: {fp_s};  update: {fu_s}")


def _hour_drive(tmp: Path) -> Path:
    """The 1-hour 500 Hz figure8 drive, simulated once per bench directory (shared with fuse-long and view)."""
    from fieldlog.tools.sim.simulate import simulate

    path = tmp / "hour.mcap"
    if not path.exists():
        t0 = time.perf_counter()
        simulate("figure8", 3600.0, 1, path)
        print(f"  (simulated 1 h figure8 in {time.perf_counter() - t0:.0f} s, {path.stat().st_size / 1e9:.1f} GB)")
    return path


def bench_cli(runs: int, tmp: Path) -> None:
    """`fieldlog --help` start-up time, and `fieldlog info` on a 1-hour drive (target <= 2 s), as a user types them."""
    exe = [sys.executable, "-m", "fieldlog"]

    def run(*args: str) -> None:
        r = subprocess.run([*exe, *args], capture_output=True, text=True)
        assert r.returncode == 0, r.stderr

    for args in (["--help"], ["acquire", "--help"], ["info", "--help"]):
        med, ts, _ = timed(lambda: run(*args), max(runs, 5))
        print(f"fieldlog {' '.join(args):<16}  median {med:6.3f} s  (runs: {fmt_times(ts)})")
    hour = _hour_drive(tmp)
    size = hour.stat().st_size / 1e9
    med, ts, _ = timed(lambda: run("info", str(hour)), runs)
    print(f"fieldlog info, 1 h drive:     median {med:6.2f} s  (runs: {fmt_times(ts)}; {size:.1f} GB; the "
          f"fieldlog.info record)   target <= 2 s")
    row("`fieldlog info` of a 1-hour drive [cli]", f"{med:.2f} s", "≤ 2 s")
    med, ts, _ = timed(lambda: run("info", "--scan", str(hour)), 1)
    print(f"fieldlog info --scan, 1 h:    {med:6.2f} s  (reading every /imu, /gps/fix, /time/sync, /truth/imu message)")


def bench_reader(runs: int, tmp: Path, duration_s: float = 300.0) -> None:
    """Reading what fuse reads (/imu, /gps/fix, /gps/vel in 10 s blocks) of a 300 s drive in every MCAP layout."""
    # Wall and CPU time both: under contention the wall ratio is not the CPU ratio. The 4 KiB-chunk file is the
    # hard case: every chunk holds /imu, so every chunk is decompressed (about 2.3x the own file's bytes).
    from fieldlog.drive import files as drive, reader
    from fieldlog.tools.dev.layouts import LAYOUTS, rewrite
    from fieldlog.tools.sim.simulate import simulate

    own = tmp / "reader_own.mcap"
    simulate("figure8", duration_s, 1, own)
    files = {"own (recorder)": own, **{k: rewrite(own, tmp / f"reader_{k}.mcap", k) for k in LAYOUTS}}

    def read(path: Path) -> int:
        drive._OPEN.clear()  # the file walk is part of the cost
        return sum(len(b.data["/imu"]["log_time_ns"]) for b in reader.iter_blocks(path, reader.IN_TOPICS, 10.0)
                   if "/imu" in b.data)

    read(own)  # kernels loaded, caches warm outside the timing
    wall: dict[str, list[float]] = {k: [] for k in files}
    cpu: dict[str, list[float]] = {k: [] for k in files}
    n = {}
    for _ in range(runs):  # interleaved: every layout once per round, so a change of load hits them all
        for name, path in files.items():
            w0, c0 = time.perf_counter(), time.process_time()
            n[name] = read(path)
            wall[name].append(time.perf_counter() - w0)
            cpu[name].append(time.process_time() - c0)
    print(f"load average {os.getloadavg()[0]:.1f} (1 min) after the runs; medians of {runs} interleaved runs")
    w_base, c_base = statistics.median(wall["own (recorder)"]), statistics.median(cpu["own (recorder)"])
    for name, path in files.items():
        w, c = statistics.median(wall[name]), statistics.median(cpu[name])
        print(f"read {name:15s} {path.stat().st_size / 1e6:6.1f} MB: wall {w:5.2f} s x{w / w_base:.2f}, "
              f"CPU {c:5.2f} s x{c / c_base:.2f} of the own file (target <= x2)  (wall runs: {fmt_times(wall[name])})  "
              f"{n[name]} IMU samples")
        if path != own:
            row(f"reading what `fuse` reads of a 300 s drive, {name} against our own file, wall / CPU [reader]",
                f"×{w / w_base:.2f} / ×{c / c_base:.2f}", "≤ ×2" if name == "chunks-4k" else "")


def bench_recover(runs: int, tmp: Path, duration_s: float = 300.0) -> None:
    """``recover DIR``'s check of a complete file (every chunk's CRC), and the recovery of one with a damaged chunk."""
    from fieldlog.acquire.recovery import TailDeriver, recover, recover_drive
    from fieldlog.drive.mcapfile import McapFile
    from fieldlog.tools.dev.layouts import rewrite
    from fieldlog.tools.sim.simulate import simulate

    own = tmp / "recover_own.mcap"
    simulate("figure8", duration_s, 1, own)
    for path in (own, rewrite(own, tmp / "recover_4k.mcap", "chunks-4k")):
        f = McapFile(path)
        f.damaged()  # kernels loaded, caches warm outside the timing
        p = f.pieces
        i = int(np.flatnonzero(p.chunk)[int(p.chunk.sum()) // 2])
        raw = bytearray(path.read_bytes())
        raw[int(p.body[i] + p.body_len[i] // 2)] ^= 0x55
        bad = path.with_name(path.stem + "_bad.mcap")
        bad.write_bytes(raw)
        check, _, _ = timed(lambda: McapFile(path).damaged(), runs)
        fast, _, _ = timed(lambda: recover_drive(bad, tmp / "r.mcap", force=True), runs)
        slow, _, _ = timed(lambda: recover(bad, tmp / "r.mcap", TailDeriver(), force=True), runs)
        print(f"{duration_s:.0f} s drive, {path.name} ({path.stat().st_size / 1e6:.1f} MB, {int(p.chunk.sum())} "
              f"chunks, {p.size.sum() / 1e6:.0f} MB uncompressed): open + check every chunk {check * 1e3:.0f} ms; recover with "
              f"one damaged chunk {fast:.2f} s (feeding the pipeline: {slow:.2f} s)")
        row(f"{duration_s:.0f} s drive, {'own file' if path == own else '4 KiB chunks'}: check every chunk; recover "
            "one damaged chunk, copying / feeding the pipeline [recover]",
            f"{check * 1e3:.0f} ms; {fast:.2f} / {slow:.2f} s")


def _rerun_exe() -> str:
    """The rerun CLI of this Python's environment (the ``rerun-sdk`` wheel's), else the one on PATH."""
    import shutil

    here = Path(sys.executable).with_name("rerun")
    return str(here) if here.exists() else (shutil.which("rerun") or "rerun")


def machine_line() -> str:
    """The CPU model (with its family and model numbers: a virtual machine may name only the vendor's line), its
    cores (those this process may run on), numpy's version and BLAS (numpy's build configuration, and the library
    loaded at run time when threadpoolctl can tell), the per-call costs (:func:`call_costs`) and the load
    average."""
    model = "unknown CPU"
    with contextlib.suppress(OSError):
        info = dict(ln.split(":", 1) for ln in open("/proc/cpuinfo").read().split("\n\n")[0].splitlines()
                    if ":" in ln)
        info = {k.strip(): v.strip() for k, v in info.items()}
        model = info.get("model name", model)
        if "cpu family" in info:
            model += f" (family {info['cpu family']}, model {info.get('model', '?')})"
    blas = "unknown BLAS"
    with contextlib.suppress(Exception):
        b = np.show_config(mode="dicts")["Build Dependencies"]["blas"]
        blas = f"{b.get('name', '?')} {b.get('version', '')}".strip()
    with contextlib.suppress(ImportError):
        import threadpoolctl

        libs = [f"{i['internal_api']} {i.get('version') or ''} {i.get('architecture') or ''}".strip()
                for i in threadpoolctl.threadpool_info() if i.get("user_api") == "blas"]
        blas += f" (loaded: {', '.join(libs)})" if libs else ""
    from fieldlog.drive import reader

    cores = reader.cpus()
    load = " / ".join(f"{x:.1f}" for x in os.getloadavg())
    return (f"machine: {model}, {cores} cores, numpy {np.__version__}, BLAS {blas}, {call_costs()}, load {load} "
            "(1 / 5 / 15 min)")


def call_costs() -> str:
    """What one interpreted step and one small numpy call cost here, the best of 5 runs each: a pure-Python loop
    of 10^6 additions, and the product of two 15 x 15 matrices (the filter's size). A fieldlog command is mostly
    such steps and the rerun CLI none, so its ratio to rerun rises on a machine where they are slow: with these
    figures beside them, ratios measured on different machines can be compared."""
    import timeit

    loop = min(timeit.repeat("for i in r: s += i", setup="r = range(10 ** 6); s = 0", number=1, repeat=5))
    a = np.eye(15)
    product = min(timeit.repeat(lambda: a @ a, number=10_000, repeat=5)) / 10_000
    return f"Python 10^6 additions {loop * 1e3:.0f} ms, numpy 15x15 product {product * 1e6:.2f} us"


def _run_cpu(cmd: list[str], cwd: Path, pin: bool = False) -> tuple[float, float]:
    """Wall and CPU seconds (user + system, the command and the children it waited for) of one command as a user
    types it (its output discarded; a failure raises); ``pin``: on one core (``taskset -c 0``), its workers too."""
    import resource

    env = {**os.environ, "RERUN_ANALYTICS": "0"}
    cmd = ["taskset", "-c", "0", *cmd] if pin else cmd
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    r = subprocess.run(cmd, cwd=cwd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    s = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    assert r.returncode == 0, f"{' '.join(cmd)}: {r.stderr[-2000:]}"
    return s, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def _run_s(cmd: list[str], cwd: Path, pin: bool = False) -> float:
    """Wall seconds of one command (:func:`_run_cpu`)."""
    return _run_cpu(cmd, cwd, pin)[0]


def bench_rerun(runs: int, tmp: Path, duration_s: float = 600.0) -> None:
    """fieldlog against the rerun CLI on one simulated 600 s figure8 drive: fuse kf / dkf-rbfn, view --rrd, sim,
    info, each as a ratio to `rerun mcap convert` (`rerun mcap info` for info) run just before it, as is and with
    both commands pinned to one core (`taskset -c 0`), and a warm fuse of a 60 s drive. `fuse --method ins` (one
    read of the drive, the strapdown INS and the same writing, no filter and no installation pass) is the floor
    of every fuse: what no filter can go below. `fuse --method kf, one pass` (and dkf-rbfn's) is the same method
    without the installation's time-offset and mounting passes (:func:`_variant_config`): the fusion pass alone."""
    fl, rr = [sys.executable, "-m", "fieldlog"], _rerun_exe()
    drive, short = tmp / "rr_drive.mcap", tmp / "rr_short.mcap"
    _run_s([*fl, "sim", "--duration", str(duration_s), "--seed", "1", "--out", str(drive), "-q"], tmp)
    _run_s([*fl, "sim", "--duration", "60", "--seed", "2", "--out", str(short), "-q"], tmp)
    convert = [rr, "mcap", "convert", str(drive), "-o", str(tmp / "rr_convert.rrd")]
    fused, one_pass = tmp / "rr_kf.mcap", _variant_config(tmp, drive, ONE_PASS)
    cmds = {  # name: (fieldlog command, reference command, target as is, target pinned to one core)
        "fuse --method kf": ([*fl, "fuse", str(drive), "--method", KF.name, "--out", str(fused), "--force", "-q"],
                             convert, "≤ ×0.5", "≤ ×0.8"),
        "fuse --method kf" + ONE_PASS: ([*fl, "fuse", str(drive), "--method", KF.name, "--config",
                                         str(one_pass), "--out", str(tmp / "rr_kf1.mcap"),
                                         "--force", "-q"], convert, "", ""),
        "fuse --method ins": ([*fl, "fuse", str(drive), "--method", INS.name, "--out", str(tmp / "rr_ins.mcap"),
                               "--force", "-q"], convert, "", ""),
        "fuse --method dkf-rbfn": ([*fl, "fuse", str(drive), "--method", DKF_RBFN.name, "--out",
                                    str(tmp / "rr_rbfn.mcap"), "--force", "-q"], convert, "≤ ×0.8", ""),
        "fuse --method dkf-rbfn" + ONE_PASS: ([*fl, "fuse", str(drive), "--method", DKF_RBFN.name, "--config",
                                               str(one_pass), "--out", str(tmp / "rr_rbfn1.mcap"),
                                               "--force", "-q"], convert, "", ""),
        "view DRIVE FUSED --rrd": ([*fl, "view", str(drive), str(fused), "--rrd", str(tmp / "rr_view.rrd"),
                                    "--force", "-q"], convert, "≤ ×0.8", ""),
        f"sim --duration {duration_s:g}": ([*fl, "sim", "--duration", str(duration_s), "--seed", "3", "--out",
                                           str(tmp / "rr_sim.mcap"), "--force", "-q"], convert, "≤ ×2.5", ""),
        "info": ([*fl, "info", str(drive)], [rr, "mcap", "info", str(drive)], "", ""),
    }
    warm60 = [*fl, "fuse", str(short), "--method", KF.name, "--out", str(tmp / "rr_short_kf.mcap"), "--force", "-q"]
    for name in ("fuse --method kf", "fuse --method dkf-rbfn"):
        _run_s(cmds[name][0], tmp)  # a warm run outside the figures (page cache); kf's output feeds view
    _run_s(warm60, tmp)
    print(machine_line())
    for pin in (False, True):
        _rerun_ratios(cmds, runs, tmp, pin, f"figure8 {duration_s:g} s ({drive.stat().st_size / 1e6:.0f} MB)")
    short_s = [_run_s(warm60, tmp) for _ in range(runs)]
    med, load = statistics.median(short_s), f"load {os.getloadavg()[0]:.1f}"
    print(f"fieldlog fuse --method kf, 60 s drive, warm: median {med:.2f} s (runs: {fmt_times(short_s)})  "
          "target <= 0.6 s")
    row("`fieldlog fuse --method kf` of a 60 s drive, warm [rerun]", f"{med:.2f} s ({load})", "≤ 0.6 s")


def _rerun_ratios(cmds: dict, runs: int, tmp: Path, pin: bool, drive: str) -> None:
    """The rounds of :func:`bench_rerun`, alternated (each command right after its reference, so a change of load
    hits both), as is or both pinned to one core; prints and records the median ratios of wall time."""
    ratios: dict[str, list[float]] = {k: [] for k in cmds}
    secs: dict[str, list[tuple[float, float]]] = {k: [] for k in cmds}
    refs: dict[str, list[tuple[float, float]]] = {k: [] for k in cmds}
    loads = []
    for _ in range(runs):
        for name, (cmd, ref, *_t) in cmds.items():
            refs[name].append(_run_cpu(ref, tmp, pin))
            secs[name].append(_run_cpu(cmd, tmp, pin))
            ratios[name].append(secs[name][-1][0] / refs[name][-1][0])
        loads.append(os.getloadavg()[0])
    load = f"load {min(loads):.1f}–{max(loads):.1f}"
    how = "pinned to one core (taskset -c 0)" if pin else "as is"
    print(f"{drive}, {how}, {runs} alternated rounds, {load} (1 min, after each round)")
    for name, (cmd, ref, target, target_pinned) in cmds.items():
        q, target = statistics.median(ratios[name]), target_pinned if pin else target
        wall = [w for w, _ in secs[name]]
        cpu, ref_cpu = (statistics.median(c for _, c in x) for x in (secs[name], refs[name]))
        print(f"fieldlog {name:32s} median x{q:5.2f} of `rerun {' '.join(ref[1:3])}` (fieldlog {fmt_times(wall)} s, "
              f"CPU {cpu:.2f} s; rerun {fmt_times([w for w, _ in refs[name]])} s, CPU {ref_cpu:.2f} s)  "
              f"target {target or '-'}")
        shown = "`fieldlog {}`{}".format(*_shown(name))
        row(f"{shown}, {drive.split(' (')[0]}, against `rerun {' '.join(ref[1:3])}` of the same drive"
            f"{', both on one core' if pin else ''} [rerun]",
            f"×{q:.2f} ({statistics.median(wall):.2f} s against {statistics.median(w for w, _ in refs[name]):.2f}"
            f" s; {load})", target)


def bench_peer(runs: int, tmp: Path, kfgins: Path | None = None, duration_s: float = 600.0) -> None:
    """fieldlog against a C++ filter: `fuse --method kf` and KF-GINS on one KF-GINS-format data set, CPU time.

    ``kfgins``: a KF-GINS checkout (built there with its CMake when it has no bin/KF-GINS) or its executable
    (tools/dev/README.md); its own example set when the checkout has its IMU file, else a set made from a
    simulated figure8 drive of ``duration_s``. The set is converted to a drive, both run alternated with the same
    IMU figures and the vehicle aids off; the ratio is of CPU seconds (each with the workers it waited for)."""
    from fieldlog.tools.dev import kfgins as peer

    if kfgins is None:
        print("skipped: give --kfgins PATH (a KF-GINS checkout or executable; tools/dev/README.md)")
        return
    exe = peer.kfgins_binary(kfgins)
    yaml_path, what, sim = peer.copy_dataset(kfgins, tmp / "kfgins"), "its example set", tmp / "peer_sim.mcap"
    if yaml_path is None:
        what = f"made from a simulated figure8 drive of {duration_s:g} s"
        _run_s([sys.executable, "-m", "fieldlog", "sim", "--duration", str(duration_s), "--seed", "1", "--out",
                str(sim), "-q", "--force"], tmp)
        yaml_path = peer.dataset_from_drive(sim, tmp / "kfgins" / "dataset")
    drive = peer.drive_from_dataset(yaml_path, tmp / "peer.mcap")
    (tmp / "peer.toml").write_text(peer.fusion_toml(yaml_path))
    fuse = [sys.executable, "-m", "fieldlog", "fuse", str(drive), "--method", KF.name, "--config",
            str(tmp / "peer.toml"), "--out", str(tmp / "peer_kf.mcap"), "--force", "-q"]
    run_peer = lambda: _run_cpu([str(exe), str(yaml_path.resolve())], yaml_path.resolve().parent.parent)  # noqa: E731
    run_peer(), _run_s(fuse, tmp)  # warm runs outside the figures (page cache)
    ours, theirs = [], []
    for _ in range(runs):
        theirs.append(run_peer())
        ours.append(_run_cpu(fuse, tmp))
    q = statistics.median(o[1] / t[1] for o, t in zip(ours, theirs))
    cpu, load = [statistics.median(c for _, c in x) for x in (ours, theirs)], f"load {os.getloadavg()[0]:.1f}"
    print(f"{machine_line()}\n{drive.stat().st_size / 1e6:.0f} MB drive from the KF-GINS set ({what}), {runs} "
          f"alternated rounds: fieldlog fuse kf CPU {cpu[0]:.2f} s (wall {fmt_times([w for w, _ in ours])}), "
          f"KF-GINS CPU {cpu[1]:.2f} s (wall {fmt_times([w for w, _ in theirs])}): median CPU ratio x{q:.2f}; {load}")
    if sim.exists():  # the same accuracy, or the ratio would compare unequal work
        rms = peer.horizontal_rms(sim, yaml_path.parent / "KF_GINS_Navresult.nav", tmp / "peer_kf.mcap")
        print(f"horizontal RMS against the truth: KF-GINS {rms[0]:.2f} m, fieldlog kf {rms[1]:.2f} m")
    row("`fieldlog fuse --method kf` against KF-GINS on a KF-GINS-format set, same IMU figures, aids off: CPU "
        "[peer]", f"×{q:.2f} ({cpu[0]:.2f} s against {cpu[1]:.2f} s; {load})", "≤ ×0.5")


# The stages of `make bench --only profile`: a profiled function's own time goes to the stage of its file (and, in
# drive/recorder.py, of its name); a library function's (numpy, zstd ...) to its callers' stages.
_STAGES = ("reading and decoding", "input mapping and resequencing", "INS and covariance cycles",
           "measurement updates", "predictors", "fusion loop (engine)", "output encoding and writing", "other")
_WRITE = {"Recorder", "_OpenChunk", "_FileWriter", "write", "write_each", "write_batch", "write_channel",
          "maybe_flush", "flush", "write_chunk", "write_record", "add_metadata", "register", "channel_id", "close",
          "__enter__", "__exit__", "add", "add_block", "records", "write_records", "_add_few"}
_CYCLE = {"predict", "propagate", "cycle_matrices", "segment_cycles", "system_matrices", "discretise"}


def _stage_of(path: str, name: str) -> str | None:
    """The stage of a project function (file, name), None for a library one."""
    p = Path(path)
    root = Path(__file__).resolve().parents[2]  # the checkout: tools/dev/bench.py
    try:
        rel = p.resolve().relative_to(root).as_posix()
    except (ValueError, OSError):
        return None
    if ".venv" in rel or rel.startswith("tools/dev/"):
        return None
    if rel == "drive/recorder.py":
        return "output encoding and writing" if name in _WRITE else "reading and decoding"
    if rel in ("drive/messages.py", "fusion/output.py", "tools/fuse.py", "drive/outputs.py", "fusion/smoother.py"):
        return "output encoding and writing" if rel != "tools/fuse.py" or name not in ("fuse", "settings",
                                                                                      "input_map") else "other"
    if rel == "replay/inputs.py":
        return "input mapping and resequencing"
    if rel.startswith("replay/") or rel in ("drive/native.py", "drive/bagdir.py"):
        return "reading and decoding"
    if rel in ("fusion/ins.py", "fusion/errmodel.py", "fusion/clipgyro.py", "fusion/earth.py"):
        return "INS and covariance cycles"
    if rel == "fusion/predictors.py" or name in ("PredictorBridge", "train", "prediction", "input"):
        return "predictors"
    if rel in ("fusion/kf.py", "fusion/dkf.py", "fusion/ukf.py", "fusion/sckf.py", "fusion/hinf.py"):
        if name in _CYCLE:
            return "INS and covariance cycles"
        return "measurement updates" if "update" in name or "measurement" in name else None  # helpers: callers'
    if rel in ("fusion/measurements.py", "fusion/gpserror.py", "fusion/listeners.py", "fusion/align.py",
               "fusion/outages.py", "fusion/odometer.py", "fusion/consider.py"):
        return "measurement updates"
    if rel == "fusion/engine.py":
        return "INS and covariance cycles" if name in ("_cycles", "_integrate") else "fusion loop (engine)"
    return "other"


def stage_times(stats) -> dict[str, float]:
    """Seconds per stage of a ``pstats.Stats``: every function's own time, a library function's split over its
    callers in proportion to the time spent under each."""
    st = stats.stats
    memo: dict[tuple, dict[str, float]] = {}

    def dist(f: tuple, seen: frozenset) -> dict[str, float]:
        if f in memo:
            return memo[f]
        own = _stage_of(f[0], f[2]) if not f[0].startswith("~") else None
        if own is not None:
            out = {own: 1.0}
        else:
            callers = st.get(f, (0, 0, 0, 0, {}))[4]
            tot = sum(c[3] for c in callers.values())
            out: dict[str, float] = {}
            for c, v in callers.items():
                if c in seen or tot <= 0:
                    continue
                for k, w in dist(c, seen | {f}).items():
                    out[k] = out.get(k, 0.0) + w * v[3] / tot
            out = out or {"other": 1.0}
        if not seen:
            memo[f] = out
        return out

    res = dict.fromkeys(_STAGES, 0.0)
    for f, (_cc, _nc, tt, _ct, _callers) in st.items():
        for k, w in dist(f, frozenset()).items():
            res[k] += tt * w
    return res


def bench_profile(runs: int, tmp: Path, duration_s: float = 600.0) -> None:
    """Where `fieldlog fuse` spends its time, per stage, for kf and dkf-rbfn, on the 600 s figure8 drive and on the
    1-hour one (cProfile of a warm in-process run; start-up measured in fresh processes). Every stage runs in the
    profiled process: a second thread is kept alive meanwhile, and with one fuse runs its reading and predictor
    workers in place (replay.ahead), so the figures are the stages' own cost, on one core."""
    import threading

    parked = threading.Event()
    threading.Thread(target=parked.wait, daemon=True).start()
    try:
        _profile_stages(runs, tmp, duration_s)
    finally:
        parked.set()


def _profile_stages(runs: int, tmp: Path, duration_s: float) -> None:
    import cProfile
    import pstats

    from fieldlog.tools.fuse import fuse
    from fieldlog.tools.sim.simulate import simulate

    drive, warm = tmp / "prof_drive.mcap", tmp / "prof_warm.mcap"
    simulate("figure8", duration_s, 1, drive)
    simulate("figure8", 30.0, 2, warm)
    # start-up: the import of the fuse path, and the kernels' first load, each in a fresh process
    w, o = str(warm), str(tmp / "prof_warm_kf.mcap")
    code = (f"import time\nt0 = time.perf_counter()\nimport fieldlog.tools.fuse as f\nt1 = time.perf_counter()\n"
            f"f.fuse({w!r}, 'kf', {o!r}, force=True)\nt2 = time.perf_counter()\n"
            f"f.fuse({w!r}, 'kf', {o!r}, force=True)\nprint(t1 - t0, t2 - t1, time.perf_counter() - t2)\n")
    start = []
    for _ in range(max(runs, 3)):
        out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True)
        start.append([float(x) for x in out.stdout.split()])
    imp = statistics.median(s[0] for s in start)
    first = statistics.median(s[1] - s[2] for s in start)   # the first fuse's excess over a second one
    load = os.getloadavg()[0]
    print(f"start-up of a fuse process (medians of {len(start)}): import {imp:.2f} s, first call's excess (lazy "
          f"imports, kernel load) {first:.2f} s; load {load:.1f}")
    table = {}
    for (label, path, n) in ((f"{duration_s:g} s", drive, runs), ("1 h", _hour_drive(tmp), 1)):
        for method in (KF.name, DKF_RBFN.name):
            fuse(warm, method, tmp / "prof_w.mcap", force=True)
            walls = []
            for _ in range(n):
                t0 = time.perf_counter()
                fuse(path, method, tmp / "prof_out.mcap", force=True)
                walls.append(time.perf_counter() - t0)
            prof = cProfile.Profile()
            t0 = time.perf_counter()
            prof.runcall(fuse, path, method, tmp / "prof_out.mcap", force=True)
            pwall = time.perf_counter() - t0
            stages = stage_times(pstats.Stats(prof))
            table[method, label] = (statistics.median(walls), pwall, stages)
            print(f"fuse {method}, {label}: {statistics.median(walls):.2f} s unprofiled (runs {fmt_times(walls)}), "
                  f"{pwall:.2f} s profiled; load {os.getloadavg()[0]:.1f}")
            top = pstats.Stats(prof, stream=sys.stdout)
            top.sort_stats("tottime").print_stats(12)
    load = os.getloadavg()[0]
    print("\n| stage | " + " | ".join(f"{m} {label}, s (share)" for m, label in table) + " |")
    print("|---|" + "---|" * len(table))
    print("| start-up: imports | " + " | ".join(f"{imp:.2f}" for _ in table) + " |")
    print("| start-up: the first call's excess (lazy imports, kernel load) | "
          + " | ".join(f"{first:.2f}" for _ in table) + " |")
    for s in _STAGES:
        cells = [f"{st[s]:.2f} ({st[s] / sum(st.values()):.0%})" for _, _, st in table.values()]
        print(f"| {s} | {' | '.join(cells)} |")
    print("| whole run, profiled / unprofiled | "
          + " | ".join(f"{pwall:.2f} / {wall:.2f}" for wall, pwall, _ in table.values()) + " |")
    print(f"(load {load:.1f}, 1 min, at the end)")
    for (m, label), (wall, pwall, stages) in table.items():
        big = max(stages, key=stages.get)
        row(f"`fieldlog fuse --method {m}`, figure8 {label}: the largest stage, profiled [profile]",
            f"{big}, {stages[big] / sum(stages.values()):.0%} of {pwall:.1f} s (unprofiled {wall:.2f} s; "
            f"start-up {imp + first:.2f} s; load {load:.1f})")


BENCHES = {"cli": bench_cli, "reader": bench_reader, "codecs": bench_codecs, "recorder": bench_recorder, INS.name: bench_ins, "sim": bench_sim,
           "allan": bench_allan, "fusion": bench_fusion, "grades": bench_grades, "daemon": bench_daemon, "soak": bench_soak, "bus": bench_bus, "view": bench_view,
           "export": bench_export, "qerr": bench_qerr,
           "batch": bench_batch, "cycle": bench_cycle, "fuse-long": bench_fuse_long, "recover": bench_recover,
           "rerun": bench_rerun, "profile": bench_profile, "peer": bench_peer}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--only", nargs="*", choices=sorted(BENCHES), default=None)
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--soak-minutes", type=float, default=30.0, help="minutes of data the soak records (30)")
    p.add_argument("--kfgins", type=Path, default=None,
                   help="the peer bench's KF-GINS: a checkout of its repository or its executable (tools/dev/README.md)")
    p.add_argument("--markdown", action="store_true",
                   help="print the headline figures as rows of docs/results.md's table (the full output to stderr)")
    a = p.parse_args()
    # the commands are timed as an installed wheel runs them, with their bytecode compiled (pip compiles it at
    # install); a checkout with PYTHONDONTWRITEBYTECODE set would otherwise compile every module in every run.
    # Forced: compileall keeps a file's bytecode when its recorded time matches to the second, but the import
    # also checks the size and compiles again (a file rewritten within the second of its compilation)
    root = Path(__file__).resolve().parents[2]
    for folder in ("acquire", "drive", "fusion", "replay", "tools", "src"):
        compileall.compile_dir(root / folder, quiet=1, force=True)
    full = contextlib.redirect_stdout(sys.stderr) if a.markdown else contextlib.nullcontext()
    with tempfile.TemporaryDirectory() as d, full:
        print(machine_line())
        for name in a.only or BENCHES:
            print(f"--- {name}: {BENCHES[name].__doc__.splitlines()[0]}")
            extra = {"duration_s": a.soak_minutes * 60} if name == "soak" else {}
            extra = {"kfgins": a.kfgins} if name == "peer" else extra
            BENCHES[name](a.runs, Path(d), **extra)
    if a.markdown:
        print("| what [bench] | figure | target |\n|---|---|---|")
        for what, figure, target in ROWS:
            print(f"| {what} | {figure} | {target} |")
        print(f"\n{machine_line()}")
        print(f"`python -m fieldlog.tools.dev.bench --runs {a.runs} --markdown"
              + (f" --only {' '.join(a.only)}" if a.only else "") + f"`, load average {os.getloadavg()[0]:.1f} "
              "(1 min) at the end")


if __name__ == "__main__":
    main()
