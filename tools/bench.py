"""``make bench``: speed and accuracy figures. Medians of several runs; ratios where two things are compared.

    python -m tools.bench [--only NAME ...] [--runs N]
"""
from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np


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
    from tools.info import drive_info
    from tools.sim.simulate import simulate

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


def bench_codecs(runs: int, tmp: Path) -> None:
    """DAQ frame decode of a 600 s drive in read-sized chunks; NMEA decode, ours against pynmeagps."""
    from acquire import daq, nmea

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


def bench_recorder(runs: int, tmp: Path) -> None:
    """Encoding and writing 600k IMU messages (a 600 s drive's /imu and /truth/imu)."""
    from acquire import messages, recorder

    n = 300_000
    t = 1_777_000_000_000_000_000 + np.arange(n, dtype=np.int64) * 2_000_000
    w = np.random.default_rng(1).normal(size=(n, 3))

    def write() -> None:
        with recorder.Recorder(tmp / "rec.mcap") as rec:
            for topic in ("/imu", "/truth/imu"):
                for s in range(0, n, 500):
                    sl = slice(s, s + 500)
                    rec.write_batch(topic, t[sl], messages.encode_imu(t[sl], w[sl], w[sl]))

    med, ts, _ = timed(write, runs)
    print(f"encode+write 600k Imu msgs:   median {med:6.2f} s  ({2 * n / med / 1e6:.2f} M msg/s, "
          f"{(tmp / 'rec.mcap').stat().st_size / 1e6:.0f} MB)")


def bench_ins(runs: int, tmp: Path) -> None:
    """Strapdown INS over 300k samples (numba), and the truth it is fed from."""
    from fusion import ins
    from tools.sim import trajectory

    truth = trajectory.generate(trajectory.load_scenario("figure8"), 600)
    t = np.arange(300_000) / 500.0
    med_eval, _, ts = timed(lambda: truth.evaluate(t), runs)
    s0 = ins.NavState(t[0], ts.lat[0], ts.lon[0], ts.h[0], ts.v_n[0], ts.q[0])
    ins.integrate(s0, t[:10], ts.omega_ib_b[:10], ts.f_b[:10])      # compile outside the timing
    med, _, sol = timed(lambda: ins.integrate(s0, t, ts.omega_ib_b, ts.f_b), runs)
    print(f"truth evaluate 300k samples:  median {med_eval:6.3f} s")
    print(f"INS integrate 300k samples:   median {med:6.3f} s  ({300_000 / med / 1e6:.1f} M samples/s)")


def bench_allan(runs: int, tmp: Path) -> None:
    """The 2-hour static drive through the whole chain: Allan deviation recovers ARW/VRW and bias instability."""
    from replay import reader
    from tools.allan import allan_deviation, noise_parameters
    from tools.sim.sensors import ImuErrorConfig
    from tools.sim.simulate import simulate

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


def bench_fusion(runs: int, tmp: Path, duration_s: float = 600.0) -> None:
    """fieldlog fuse of a 600 s figure8 drive by ins, kf, dkf and dkf-rbfn: seconds and real-time factor."""
    from tools.fuse import fuse
    from tools.sim.simulate import simulate

    path, warm = tmp / "fuse_f8.mcap", tmp / "fuse_warm.mcap"
    simulate("figure8", duration_s, 1, path)
    simulate("figure8", 30.0, 2, warm)
    for method in ("ins", "kf", "dkf", "dkf-rbfn"):
        fuse(warm, method, tmp / "fused_warm.mcap")  # numba compile / cache load outside the timing
        med, ts, res = timed(lambda m=method: fuse(path, m, tmp / f"fused_{m}.mcap"), runs)
        print(f"fuse {method:8s} figure8 {duration_s:g} s: median {med:6.2f} s  (runs: {fmt_times(ts)})  "
              f"{res.imu_samples / med / 1e3:7.1f} k samples/s, real-time factor x{duration_s / med:.0f}")


def bench_daemon(runs: int, tmp: Path, duration_s: float = 600.0) -> None:
    """fieldlog acquire against sim --serve ptys: 10 min at real speed, then x20; loss, timing, CPU."""
    import os
    import signal
    import subprocess
    import sys

    from acquire.timesync import SyncState
    from replay import reader
    from tools.rebuild import read_metadata

    def one(speed: float, duration: float) -> None:
        out, truth = tmp / f"drives_x{speed:g}", tmp / f"truth_x{speed:g}.mcap"
        cli = [sys.executable, "-m", "tools.cli"]
        serve = subprocess.Popen([*cli, "sim", "--serve", "--scenario", "figure8", "--duration", str(duration),
                                  "--seed", "1", "--speed", str(speed), "--hold", "--truth", str(truth)],
                                 stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        paths = dict(serve.stdout.readline().split() for _ in range(2))
        extra = ["--time-scale", str(speed)] if speed != 1 else []
        d = subprocess.Popen([*cli, "acquire", "--daq", paths["daq"], "--gps", paths["gps"], "--out", str(out),
                              "--quiet", *extra], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        while "recording" not in (line := d.stderr.readline()):
            assert line, "the daemon exited early"
        serve.send_signal(signal.SIGUSR1)
        serve.wait()
        d.send_signal(signal.SIGTERM)
        _, status, usage = os.wait4(d.pid, 0)
        d.returncode = os.waitstatus_to_exitcode(status)
        cpu = usage.ru_utime + usage.ru_stime
        sent = read_metadata(truth)["serve"]
        files = sorted(out.glob("*.mcap"))
        counters = read_metadata(files[-1])["acquire.counters"]
        imu = np.concatenate([reader.read_topic(f, "/imu")["log_time_ns"] for f in files])
        state = np.concatenate([reader.read_topic(f, "/time/sync")["state"] for f in files])
        tru = reader.read_topic(truth, "/truth/imu")["log_time_ns"]
        lost_frames = int(sent["daq_frames"]) - int(counters["daq.frames"])
        lost_lines = int(sent["nmea_lines"]) - int(counters["nmea.lines"])
        line = (f"x{speed:<4g} {duration:5.0f} s of data: lost DAQ frames {lost_frames}, lost NMEA lines {lost_lines}, "
                f"daemon CPU {cpu:.1f} s = {100 * cpu * speed / duration:.1f} % of one core")
        if speed == 1 and len(imu) == len(tru):
            # at real speed the serve process sets the drive start to 'now', so stamps compare with truth directly
            locked = np.searchsorted(imu, imu[0]) if (state == SyncState.LOCKED).any() else 0
            err = (imu[locked:] - tru[locked:]) / 1e3
            line += f", timestamp RMS vs truth {np.sqrt(np.mean(err ** 2)):.1f} us"
        print(line)

    one(1.0, duration_s)
    one(20.0, 120.0)


def bench_view(runs: int, tmp: Path) -> None:
    """A 1-hour 500 Hz drive plus one fused method (kf) to .rrd (target <= 10 s), and the file size."""
    from fusion.engine import FusionConfig
    from replay.view import view
    from tools.fuse import fuse
    from tools.sim.simulate import simulate

    drive, fused, rrd = tmp / "hour.mcap", tmp / "hour_kf.mcap", tmp / "hour.rrd"
    simulate("figure8", 3600, 1, drive)
    fuse(drive, "kf", fused, FusionConfig())
    med, ts, _ = timed(lambda: view(drive, [fused], rrd), runs)
    print(f"view 1 h drive + kf -> .rrd:  median {med:6.2f} s  (runs: {fmt_times(ts)})   target <= 10 s; "
          f"{rrd.stat().st_size / 1e6:.1f} MB .rrd from a {drive.stat().st_size / 1e6:.0f} MB drive")


def bench_batch(runs: int, tmp: Path) -> None:
    """fieldlog batch of 4 drives (300 s; kf, dkf; 30 s outages): 2 Dask workers against one by one in-process."""
    from tools.batch import drive_rows, run_batch
    from tools.sim.simulate import simulate

    drives = []
    for seed in range(1, 5):
        drives.append(tmp / f"b{seed}.mcap")
        simulate("figure8", 300, seed, drives[-1])
    t_one, _, _ = timed(lambda: [drive_rows(d, ["kf", "dkf"], [30.0], tmp / "one") for d in drives], 1)
    t_batch, _, _ = timed(lambda: run_batch(drives, ["kf", "dkf"], [30.0], tmp / "batch", workers=2,
                                            say=lambda _m: None), 1)
    print(f"batch 4 drives: one by one {t_one:.1f} s, Dask 2 workers {t_batch:.1f} s (cluster start included) "
          f"-> speed-up {t_one / t_batch:.2f}x")


BENCHES = {"codecs": bench_codecs, "recorder": bench_recorder, "ins": bench_ins, "sim": bench_sim,
           "allan": bench_allan, "fusion": bench_fusion, "daemon": bench_daemon, "view": bench_view, "batch": bench_batch}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--only", nargs="*", choices=sorted(BENCHES), default=None)
    p.add_argument("--runs", type=int, default=3)
    a = p.parse_args()
    with tempfile.TemporaryDirectory() as d:
        for name in a.only or BENCHES:
            print(f"--- {name}: {BENCHES[name].__doc__.splitlines()[0]}")
            BENCHES[name](a.runs, Path(d))


if __name__ == "__main__":
    main()
