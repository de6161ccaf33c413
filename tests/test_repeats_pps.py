"""A DAQ read delivered twice is a repeat, not new samples (acquire/counterjudge.py); a stuck counter is named; a
PPS line flagged far more often than once a second is recognised as implausible and costs the time sync nothing
more than its flags (acquire/timesync.py)."""
from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fieldlog.acquire import counterjudge, daq, timesync
from fieldlog.drive import recorder
from fieldlog.acquire.pipeline import Pipeline
from fieldlog.drive import reader
from fieldlog.drive.reader import read_metadata
from fieldlog.tools.sim import simulate, trajectory
from test_daemon import raw_stream

L = daq.FRAME_SIZE
LOCKED = int(timesync.SyncState.LOCKED)
ROOT = Path(__file__).resolve().parents[1]
NS = 1_000_000_000


def sim_reads(seconds: float, seed: int, pps_mode: str, floating: bool = False) -> list:
    """The simulator's reads of a figure8 drive; ``floating``: the PPS flag set on every frame."""
    sc = trajectory.load_scenario("figure8")
    if floating:
        sc = dataclasses.replace(sc, clock={**sc.clock, "glitch_pps": 10**9})
    return simulate.make_reads(sc, seconds, seed, pps_mode)[0]


def with_repeats(reads: list, p: float, seed: int) -> tuple[list, int]:
    """``reads`` with each DAQ read delivered twice with probability ``p`` (the second copy at the same host
    time, right after it); also the number of reads repeated."""
    rng = np.random.default_rng([seed, 41])
    out, n = [], 0
    for r in reads:
        out.append(r)
        if r.port == "daq" and rng.random() < p:
            out.append(r)
            n += 1
    return out, n


def captures(tmp_path: Path, reads: list, name: str) -> tuple[Path, Path]:
    """The DAQ and GPS byte captures of ``reads`` (what a logger elsewhere would have written)."""
    d, g = tmp_path / f"{name}.daq", tmp_path / f"{name}.nmea"
    d.write_bytes(b"".join(r.data for r in reads if r.port == "daq"))
    g.write_bytes(b"".join(r.data for r in reads if r.port == "gps"))
    return d, g


def fieldlog(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "fieldlog", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=600)


def import_capture(tmp_path: Path, reads: list, name: str, pps_mode: str) -> tuple[Path, subprocess.CompletedProcess]:
    d, g = captures(tmp_path, reads, name)
    out = tmp_path / f"{name}.mcap"
    p = fieldlog("import", "--gps", str(g), "--daq", str(d), "--pps", pps_mode, "--out", str(out))
    assert p.returncode == 0, p.stderr
    return out, p


# ------------------------------------------------------------------------------------------ the judge alone

@pytest.mark.parametrize("chunk", [L, 5 * L + 7, 333, 10**6])
@pytest.mark.parametrize("seed", [1, 2])
def test_a_read_delivered_twice_is_dropped_as_repeated_and_k_stays_the_counter(chunk: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = 3000
    counter = np.arange(10_000, 10_000 + n)
    stream = daq.encode_frames(counter, rng.integers(-30000, 30000, (n, 6)), np.arange(n) % 500 == 7)
    cuts = np.sort(rng.choice(np.arange(1, len(stream)), 150, replace=False))
    pieces = [stream[a:b] for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(stream)])]
    twice = sorted(rng.choice(len(pieces), 6, replace=False).tolist())
    sent = b"".join(p + (p if i in twice else b"") for i, p in enumerate(pieces))
    dec = daq.DaqDecoder()
    judge = counterjudge.CounterJudge(dec.stats)
    ks = [judge.judge(dec.feed(sent[o:o + chunk]), o).k for o in range(0, len(sent), chunk)] + [judge.flush().k]
    np.testing.assert_array_equal(np.concatenate(ks), counter)     # one sample per frame the board made
    # the repeated frames: those whose bytes lie wholly inside a repeated piece
    bounds = list(zip(np.r_[0, cuts], np.r_[cuts, len(stream)]))
    whole = sum(max(0, (b // L) - (-(-a // L))) for i, (a, b) in enumerate(bounds) if i in twice)
    st = dec.stats
    assert whole - 2 * len(twice) <= st.repeated <= whole
    assert st.repeated > 0 and st.counter_implausible == 0 and st.lost_frames == 0


def test_new_frames_with_an_old_counter_are_not_repeats() -> None:
    """A counter stepping back with other sample bytes is a wrong counter or a re-based one, judged as before."""
    counter = np.arange(100, 400)
    counts = np.random.default_rng(3).integers(-1000, 1000, (300, 6))
    stream = bytearray(daq.encode_frames(counter, counts, np.zeros(300, bool)))
    back = daq.encode_frames(counter[100:110], counts[100:110] + 1, np.zeros(10, bool))   # bytes differ
    sent = bytes(stream[:200 * L]) + back + bytes(stream[200 * L:])
    dec = daq.DaqDecoder()
    judge = counterjudge.CounterJudge(dec.stats)
    k = np.concatenate([judge.judge(dec.feed(sent), 0).k, judge.flush().k])
    assert dec.stats.repeated == 0 and dec.stats.counter_implausible > 0
    assert np.all(np.diff(k) >= 1)


# ------------------------------------------------------------------------------------------- import

@pytest.mark.parametrize("p", [0.005, 0.01])
def test_capture_with_reads_delivered_twice_imports_locked_with_one_imu_sample_per_board_sample(
        tmp_path: Path, p: float) -> None:
    reads = sim_reads(40.0, 4, "latch")
    twice, n_rep = with_repeats(reads, p, 4)
    assert n_rep > 0.5 * p * len([r for r in reads if r.port == "daq"])
    clean, _ = import_capture(tmp_path, reads, "clean", "latch")
    got, _ = import_capture(tmp_path, twice, "twice", "latch")
    sync = reader.read_topic(got, "/time/sync")["state"]
    assert np.mean(sync == LOCKED) >= 0.9
    a, b = reader.read_topic(clean, "/imu"), reader.read_topic(got, "/imu")
    assert len(b["log_time_ns"]) == len(a["log_time_ns"]) == 40 * 500     # every sample the board made, once
    np.testing.assert_array_equal(b["omega_ib_b"], a["omega_ib_b"])
    np.testing.assert_array_equal(b["f_b"], a["f_b"])
    assert np.abs(b["log_time_ns"] - a["log_time_ns"]).max() < 1_000_000
    c = read_metadata(got)["acquire.counters"]
    assert int(c["daq.repeated"]) > 0 and int(c["daq.counter_implausible"]) == 0
    assert "daq.repeated" not in read_metadata(clean)["acquire.counters"]     # written only when not zero


@pytest.mark.parametrize("pps_mode", ["flag", "latch"])
def test_a_counter_re_based_mid_capture_keeps_the_samples_in_place_and_the_clock_locked(tmp_path: Path,
                                                                                     pps_mode: str) -> None:
    """The counter jumps by +5000 from frame 7000 on (a board register re-based) with the bytes continuous: k
    continues at the byte slot, the /imu stamps keep their 2 ms grid and the clock is locked again within the fit
    window after the jump."""
    seconds, at = 30.0, 7000
    d, g = captures(tmp_path, sim_reads(seconds, 3, pps_mode), "rebased")
    data = d.read_bytes()
    rec = np.frombuffer(data[:len(data) // L * L], daq.FRAME_DTYPE).copy()
    rec["counter"][at:] += 5000
    rec["crc"] = daq.crc16_frames(rec.view(np.uint8).reshape(rec.size, L)[:, 2:36])
    d.write_bytes(rec.tobytes() + data[rec.size * L:])
    out = tmp_path / "rebased.mcap"
    p = fieldlog("import", "--gps", str(g), "--daq", str(d), "--pps", pps_mode, "--out", str(out))
    assert p.returncode == 0, p.stderr
    imu = reader.read_topic(out, "/imu")["log_time_ns"]
    assert len(imu) == seconds * 500
    assert np.abs(np.diff(imu) - 2_000_000).max() < 1_000_000          # no sample moved by the jump
    sync = reader.read_topic(out, "/time/sync")
    window_ns = timesync.TimeSyncConfig(pps_mode=pps_mode).window_s * NS
    after = sync["log_time_ns"] > imu[at] + window_ns
    assert np.all(sync["state"][after] == LOCKED)
    assert np.mean(sync["state"] == LOCKED) >= 0.9
    assert int(read_metadata(out)["acquire.counters"]["daq.counter_implausible"]) == 1


def test_a_stuck_counter_is_named(tmp_path: Path) -> None:
    reads = sim_reads(4.0, 2, "flag")
    d, g = captures(tmp_path, reads, "stuck")
    data = d.read_bytes()
    rec = np.frombuffer(data[:len(data) // L * L], daq.FRAME_DTYPE).copy()
    rec["counter"] = 77
    rec["crc"] = daq.crc16_frames(rec.view(np.uint8).reshape(rec.size, L)[:, 2:36])
    d.write_bytes(rec.tobytes())
    p = fieldlog("import", "--gps", str(g), "--daq", str(d), "--out", str(tmp_path / "out.mcap"))
    assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1, p.stderr
    assert "stuck at 77" in p.stderr and str(rec.size) in p.stderr and "no valid frame" not in p.stderr
    assert not (tmp_path / "out.mcap").exists()


def test_a_counter_that_stops_advancing_mid_drive_is_logged_as_stuck(tmp_path: Path, caplog) -> None:
    """The daemon's and rebuild's path: after 4 s the counter stays at one value (CRC-valid frames)."""
    reads = sim_reads(8.0, 2, "flag")
    daq_reads = [r for r in reads if r.port == "daq"]
    data = b"".join(r.data for r in daq_reads)
    rec = np.frombuffer(data[:len(data) // L * L], daq.FRAME_DTYPE).copy()
    rec["counter"][2000:] = rec["counter"][2000]
    rec["crc"] = daq.crc16_frames(rec.view(np.uint8).reshape(rec.size, L)[:, 2:36])
    stuck = rec.tobytes() + data[rec.size * L:]
    fed, end = [], 0
    for r in reads:                       # the same reads, the DAQ ones carrying the stuck stream's bytes
        if r.port == "daq":
            r = r._replace(data=stuck[end:end + len(r.data)])
            end += len(r.data)
        fed.append(r)
    with caplog.at_level("WARNING", logger="fieldlog.acquire.pipeline"):
        _, pipe = fit_work(tmp_path, fed, "flag")
    msgs = [m for m in caplog.messages if "stuck" in m]
    assert len(msgs) == 1 and f"stuck at {int(rec['counter'][2000])}" in msgs[0]
    assert pipe.counters.imu_samples <= 2001 and pipe.counters.daq.counter_implausible >= rec.size - 2002


# ---------------------------------------------------------------------------------------- floating PPS

def fit_work(tmp_path: Path, reads: list, pps_mode: str) -> tuple[int, Pipeline]:
    """The edges the time sync's robust fits took over a drive of ``reads`` through the pipeline."""
    with recorder.Recorder(tmp_path / f"work{len(reads)}.mcap", flush_interval_s=None, fsync=False) as rec:
        pipe = Pipeline(rec, sync_cfg=timesync.TimeSyncConfig(pps_mode=pps_mode))
        pipe.feed_reads(reads)
        pipe.finish()
    return pipe.sync.labeller.fit_edges, pipe


@pytest.mark.parametrize("pps_mode", ["flag", "latch"])
def test_a_pps_flag_on_every_frame_is_implausible_and_costs_the_fits_less_than_a_clean_drive_7x_as_long(
        tmp_path: Path, pps_mode: str) -> None:
    seconds = 8.0
    floating = sim_reads(seconds, 5, pps_mode, floating=True)
    work, pipe = fit_work(tmp_path, floating, pps_mode)
    clean_work, clean = fit_work(tmp_path, sim_reads(7 * seconds, 5, pps_mode), pps_mode)
    flags = int(seconds * 500) - 1
    c = pipe.counters
    assert c.pps_implausible >= flags - timesync.PPS_BURST * (seconds / timesync.PPS_BURST_S + 1)
    assert c.pps_edges <= flags - c.pps_implausible + 1          # only the plausible ones are edges
    assert clean.counters.pps_implausible == 0 and clean_work > 0
    assert work <= clean_work
    assert c.imu_samples == seconds * 500 and c.processing_errors == 0


def test_import_of_a_floating_pps_says_so(tmp_path: Path) -> None:
    out, p = import_capture(tmp_path, sim_reads(8.0, 6, "flag", floating=True), "floating", "flag")
    assert "PPS is implausible" in p.stderr
    c = read_metadata(out)["acquire.counters"]
    assert int(c["pps_implausible"]) > 3900
    assert len(reader.read_topic(out, "/imu")["log_time_ns"]) == 4000


# ------------------------------------------------------------------------------------------ the daemon on ptys

@pytest.mark.parametrize("p", [0.005, 0.01])
def test_daemon_fed_reads_delivered_twice_stays_locked_with_one_imu_sample_per_board_sample(
        tmp_path: Path, p: float) -> None:
    """40 s of figure8 (latched PPS) at x20, each DAQ read written to the pty twice with probability p."""
    from test_daemon_faults import _latch_config, record

    from fieldlog.tools.sim.serve import repeated_reads

    seconds, seed = 40.0, 4
    f, truth, _ = record(tmp_path, "--pps", "latch", "--repeat-reads", str(p), duration=seconds, seed=seed,
                         daemon_args=("--config", str(_latch_config(tmp_path))))
    meta = read_metadata(truth)["serve"]
    sc = trajectory.load_scenario("figure8")
    sc = dataclasses.replace(sc, clock={**sc.clock, "start_utc_ns": int(meta["drive_start_utc_ns"])})
    daq_reads = [r for r in simulate.make_reads(sc, seconds, seed, "latch")[0] if r.port == "daq"]
    twice = repeated_reads(len(daq_reads), p, seed)
    assert int(meta["daq_repeated_reads"]) == twice.sum() > 0
    sent = b"".join(r.data * (1 + t) for r, t in zip(daq_reads, twice.tolist()))
    got, _ = raw_stream(f, "daq")
    assert got == sent                                    # every byte as written, the copies included
    sync = reader.read_topic(f, "/time/sync")["state"]
    assert np.mean(sync == LOCKED) >= 0.9
    imu = reader.read_topic(f, "/imu")
    tru = reader.read_topic(truth, "/truth/imu")
    assert len(imu["log_time_ns"]) == len(tru["log_time_ns"]) == seconds * 500      # one per board sample
    steps = np.round(np.diff(imu["log_time_ns"]) / 2e6)
    assert steps.min() == steps.max() == 1
    assert np.sqrt(np.mean((imu["omega_ib_b"] - tru["omega_ib_b"])[:, 2] ** 2)) < 0.01
    c = read_metadata(f)["acquire.counters"]
    assert int(c["daq.repeated"]) > 0 and int(c["daq.counter_implausible"]) == 0 and int(c["daq.lost_frames"]) == 0
