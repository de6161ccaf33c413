"""Sample counters judged against their neighbours (acquire/counterjudge.py): a frame whose CRC matches but whose
counter is wrong costs at most its own samples, never the drive; k steps stay bounded by bytes and host time."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fieldlog.acquire import counterjudge, daq
from fieldlog.drive import reader

L = daq.FRAME_SIZE
FS = 500.0


def frames(counter) -> bytearray:
    counter = np.asarray(counter, np.int64)
    n = counter.size
    rng = np.random.default_rng(n)
    return bytearray(daq.encode_frames(counter, rng.integers(-1000, 1000, (n, 6)), np.arange(n) % 50 == 0))


def set_counter(stream: bytearray, i: int, value: int) -> None:
    """Frame i's counter set to ``value`` (mod 2**32) with its CRC recomputed: it still passes every check."""
    rec = np.frombuffer(bytes(stream[i * L:(i + 1) * L]), daq.FRAME_DTYPE).copy()
    rec["counter"] = value % 2**32
    rec["crc"] = daq.crc16_frames(rec.view(np.uint8).reshape(1, L)[:, 2:36])
    stream[i * L:(i + 1) * L] = rec.tobytes()


def judged(stream: bytes, chunk: int = 10**9, frame_mono_ns: float | None = None,
           cfg: counterjudge.JudgeConfig | None = None) -> tuple[np.ndarray, daq.DaqStats]:
    """k of every frame the judge lets through; reads of ``chunk`` bytes, timed (if ``frame_mono_ns``) as if each
    read came ``frame_mono_ns`` per 38 bytes of the stream after the first."""
    dec = daq.DaqDecoder()
    judge = counterjudge.CounterJudge(dec.stats, cfg)
    ks = []
    for off in range(0, len(stream), chunk):
        mono = None if frame_mono_ns is None else int((off + chunk) / L * frame_mono_ns)
        ks.append(judge.judge(dec.feed(stream[off:off + chunk]), off, mono).k)
    ks.append(judge.flush().k)
    return np.concatenate(ks), dec.stats


@pytest.mark.parametrize("chunk", [L, 7 * L + 5, 500, 10**6])
@pytest.mark.parametrize("jump", [2, 100, 10**7, 2**31, -1, -5, 0])
@pytest.mark.parametrize("at", [1, 37, 198])
def test_one_wrong_counter_is_counted_and_its_frame_placed_by_its_neighbours(jump: int, at: int, chunk: int) -> None:
    counter = np.arange(5000, 5200)
    s = frames(counter)
    set_counter(s, at, counter[at] + jump if jump else counter[at - 1])   # jump 0: a repeat of the previous one
    k, st_ = judged(bytes(s), chunk)
    np.testing.assert_array_equal(k, counter)          # every sample at its own index, the wrong one included
    assert st_.counter_implausible == 1
    assert (st_.counter_gaps, st_.lost_frames) == (0, 0)


def test_wrong_counter_next_to_damaged_frames_is_placed_or_dropped_never_moves_the_rest() -> None:
    counter = np.arange(200)
    s = frames(counter)
    for i in (50, 51):
        s[i * L + 20] ^= 0xFF                          # CRC fails: frames 50, 51 lost
    set_counter(s, 52, 10**9)
    s[120 * L + 3] ^= 1                                 # and a damaged one before a wrong one with garbage after it
    set_counter(s, 121, 3)
    s = s[:122 * L] + b"\x00\x11" + s[122 * L:]
    k, st_ = judged(bytes(s), 64)
    np.testing.assert_array_equal(k, np.delete(counter, [50, 51, 120]))
    assert st_.counter_implausible == 2 and st_.lost_frames == 3


def test_a_board_reset_is_rebased_and_k_never_goes_back() -> None:
    counter = np.concatenate([np.arange(10_000, 10_100), np.arange(0, 100)])
    k, st_ = judged(bytes(frames(counter)), 500)
    np.testing.assert_array_equal(k, np.arange(10_000, 10_200))
    assert (st_.counter_backwards, st_.counter_implausible, st_.lost_frames) == (1, 1, 0)


def test_a_real_gap_within_host_time_is_kept_a_jump_beyond_it_is_rebased() -> None:
    # 400 frames' bytes lost (an unplug): the reads' host times show the 0.8 s, so the gap is real
    counter = np.arange(1000)
    s = frames(counter)
    lost = s[:300 * L] + s[700 * L:]
    mono = np.concatenate([np.arange(300), np.arange(700, 1000)]) * 2e6      # frame i read at its own time
    dec = daq.DaqDecoder()
    judge = counterjudge.CounterJudge(dec.stats)
    ks = [judge.judge(dec.feed(lost[i * L:(i + 10) * L]), i * L, int(mono[i + 9])).k for i in range(0, 600, 10)]
    k = np.concatenate(ks + [judge.flush().k])
    np.testing.assert_array_equal(k, np.delete(counter, np.s_[300:700]))
    assert (dec.stats.counter_gaps, dec.stats.lost_frames, dec.stats.counter_implausible) == (1, 400, 0)
    # the counter register jumps by 10^7 for good at frame 300: no time passed for that, so it is re-based
    jumped = np.where(counter >= 300, counter + 10**7, counter)
    k, st_ = judged(bytes(frames(jumped)), 380, frame_mono_ns=2e6)
    np.testing.assert_array_equal(k, counter)
    assert (st_.counter_implausible, st_.lost_frames) == (1, 0)



@pytest.mark.parametrize("scale", [1.0, 20.0])
@pytest.mark.parametrize("late_s", [0.0, 0.1, 0.5])
def test_a_gap_after_a_late_read_is_kept_at_any_host_time_scale(scale: float, late_s: float) -> None:
    # Playback at host_time_scale X: frame i read at i / fs / X host s, except the reads before an unplug, which
    # come late_s late (a busy host). The gap then looks longer than the host time between the reads explains,
    # by late_s of host time: X * late_s of data, within the read latency the judge allows at any X.
    n_gap = int(2 * scale * FS * max(late_s, 0.1))                 # the data of 2 * late_s host s (at least 0.2)
    counter = np.arange(300 + n_gap + 600)
    gap = np.s_[300:300 + n_gap]
    s = frames(counter)
    keep = np.delete(counter, gap)
    lost = b"".join(bytes(s[i * L:(i + 1) * L]) for i in keep)
    mono = keep / FS / scale * 1e9 + np.where(keep < 300, late_s * 1e9, 0.0)
    dec = daq.DaqDecoder()
    judge = counterjudge.CounterJudge(dec.stats, counterjudge.JudgeConfig(fs_hz=FS, host_time_scale=scale))
    ks = [judge.judge(dec.feed(lost[i * L:(i + 10) * L]), i * L, int(mono[i + 9])).k for i in range(0, len(keep), 10)]
    k = np.concatenate(ks + [judge.flush().k])
    np.testing.assert_array_equal(k, keep)
    assert (dec.stats.counter_gaps, dec.stats.lost_frames, dec.stats.counter_implausible) == (1, n_gap, 0)
    # the same late reads with the counter register jumped far beyond what any latency explains: re-based
    jumped = np.where(counter >= 300, counter + int(100 * scale * FS), counter)
    s = frames(jumped)
    judge = counterjudge.CounterJudge((dec := daq.DaqDecoder()).stats,
                                      counterjudge.JudgeConfig(fs_hz=FS, host_time_scale=scale))
    mono = counter / FS / scale * 1e9 + np.where(counter < 300, late_s * 1e9, 0.0)
    ks = [judge.judge(dec.feed(bytes(s[i * L:(i + 10) * L])), i * L, int(mono[i + 9])).k
          for i in range(0, len(counter), 10)]
    np.testing.assert_array_equal(np.concatenate(ks + [judge.flush().k]), counter)
    assert (dec.stats.counter_implausible, dec.stats.lost_frames) == (1, 0)


def test_truncated_frame_loss_is_a_gap() -> None:
    counter = np.arange(3)
    s = frames(counter)
    k, st_ = judged(bytes(s[:L] + s[L:2 * L - 3] + s[2 * L:]))      # frame 1 cut short
    np.testing.assert_array_equal(k, [0, 2])
    assert (st_.counter_gaps, st_.lost_frames, st_.counter_implausible) == (1, 1, 0)


@pytest.mark.parametrize("chunk", [L, 7 * L + 5, 500, 10**6])
@pytest.mark.parametrize("frame_mono_ns", [None, 2.5e6])
def test_samples_the_board_dropped_itself_are_gaps_counted_once(chunk: int, frame_mono_ns: float | None) -> None:
    # a link slower than the ADC: the board's ring overruns and it skips about one sample in five, its frames
    # still back to back, so the gaps are close together (several in a row) and no byte is missing for them
    rng = np.random.default_rng(3)
    counter = 7000 + np.flatnonzero(rng.random(2500) >= 0.2)
    assert np.any((np.diff(counter)[:-1] > 1) & (np.diff(counter)[1:] > 1))
    k, st_ = judged(bytes(frames(counter)), chunk, frame_mono_ns)
    assert st_.frames + st_.lost_frames == counter[-1] - counter[0] + 1      # each sample counted once
    assert (st_.counter_gaps, st_.counter_implausible) == (int((np.diff(counter) > 1).sum()), 0)
    np.testing.assert_array_equal(k, counter)          # every frame at its own index: none judged wrong


def test_a_wrong_counter_frame_dropped_inside_a_gap_is_not_also_a_lost_frame() -> None:
    # two wrong counters in a row: the first agrees with no neighbour and is dropped, the second is placed by
    # the next frame; the sample slot of the dropped frame arrived (it is a frame), so nothing was lost
    counter = np.arange(300)
    s = frames(counter)
    set_counter(s, 100, 10**9)
    set_counter(s, 101, 2 * 10**9)
    k, st_ = judged(bytes(s), 500)
    np.testing.assert_array_equal(k, np.delete(counter, 100))
    assert (st_.counter_implausible, st_.lost_frames) == (2, 0)
    assert st_.frames + st_.lost_frames == counter.size


@settings(max_examples=200, deadline=None, derandomize=True)
@given(st.lists(st.integers(0, 2**32 - 1), min_size=1, max_size=80), st.integers(20, 2000),
       st.integers(0, 2**32 - 1))
def test_any_counters_give_increasing_k_with_bounded_steps(wrong: list[int], chunk: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = 300
    counter = np.arange(n) + int(rng.integers(0, 2**32))
    idx = rng.integers(0, n, len(wrong))
    counter[idx] = wrong
    k, st_ = judged(bytes(frames(counter % 2**32)), chunk)
    assert np.all(np.diff(k) >= 1)
    assert np.all(np.diff(k) <= counterjudge.JudgeConfig().max_gap_s * FS)
    assert len(k) + st_.counter_implausible >= n - 2 * len(wrong)


# --------------------------------------------------------------------------------- import and rebuild

def capture_with_one_wrong_counter(tmp_path: Path, jump: int) -> tuple[Path, Path, int]:
    """A 3 s figure8 drive's DAQ capture and GPS log, made by the simulator's DAQ encoder; frame 700's counter
    is moved by ``jump`` and its CRC recomputed."""
    from fieldlog.tools.sim import simulate, trajectory

    reads = simulate.make_reads(trajectory.load_scenario("figure8"), 3.0, 3)[0]
    s = bytearray(b"".join(r.data for r in reads if r.port == "daq"))
    n = len(s) // L
    c = int(np.frombuffer(bytes(s[700 * L:701 * L]), daq.FRAME_DTYPE)["counter"][0])
    set_counter(s, 700, c + jump)
    cap, log = tmp_path / "cap.bin", tmp_path / "gps.nmea"
    cap.write_bytes(bytes(s))
    log.write_bytes(b"".join(r.data for r in reads if r.port == "gps"))
    return cap, log, n


# The peak RSS of this process alone: VmHWM belongs to the address space made at exec, whereas getrusage's
# ru_maxrss keeps the peak of the process before its exec (pytest's, when the suite has grown).
RUN_MEASURED = """
import json, sys
from fieldlog.tools import cli
try:
    cli.main(sys.argv[1:])
except SystemExit as e:
    code = e.code
else:
    code = 0
hwm = next(int(ln.split()[1]) for ln in open("/proc/self/status") if ln.startswith("VmHWM:"))
print(json.dumps({"code": code, "rss_kb": hwm}))
"""


def run_measured(*args: str) -> dict:
    """``fieldlog ARGS`` in a fresh interpreter: its exit code and its peak RSS (KiB)."""
    p = subprocess.run([sys.executable, "-c", RUN_MEASURED, *args], capture_output=True, text=True, timeout=300)
    return {**json.loads(p.stdout.strip().splitlines()[-1]), "stderr": p.stderr}


@pytest.mark.slow
@pytest.mark.parametrize("jump", [10**2, 10**7, 2**31])
def test_capture_with_one_counter_jumped_frame_imports_and_rebuilds_with_its_imu(tmp_path: Path, jump: int) -> None:
    cap, log, n = capture_with_one_wrong_counter(tmp_path, jump)
    out = tmp_path / "drive.mcap"
    r = run_measured("import", "--gps", str(log), "--daq", str(cap), "--out", str(out))
    assert r["code"] in (0, None), r["stderr"]
    assert r["rss_kb"] < 1_000_000
    imu = reader.read_topic(out, "/imu")["log_time_ns"]
    assert len(imu) >= 0.99 * n
    steps = np.round(np.diff(imu) / (1e9 / FS))
    assert steps.min() >= 1 and steps.max() <= 2            # no sample moved by the jump
    from fieldlog.drive.reader import read_metadata
    c = read_metadata(out)["acquire.counters"]
    assert int(c["daq.counter_implausible"]) == 1 and int(c["processing_errors"]) == 0
    again = tmp_path / "rebuilt.mcap"
    r = run_measured("rebuild", str(out), "--out", str(again))
    assert r["code"] in (0, None), r["stderr"]
    assert r["rss_kb"] < 1_000_000
    np.testing.assert_array_equal(reader.read_topic(again, "/imu")["log_time_ns"], imu)


# --------------------------------------------------------------------------------- the daemon on ptys

@pytest.mark.slow
def test_daemon_with_crc_passing_counter_corruption_loses_no_imu_sample_outside_the_corrupted_frames(
        tmp_path: Path) -> None:
    """10 minutes of data at x20 (30 s of wall time): 1 % of the bytes corrupted and 0.2 % of the frames given a
    wrong counter with a matching CRC. Every frame untouched by either is on /imu at its own sample index."""
    from test_daemon_faults import FRAME_NS, record
    from test_serve import expected_bytes

    from fieldlog.drive.reader import read_metadata
    from fieldlog.tools.sim.serve import corrupt_counters, corrupt_stream

    duration, seed = 600.0, 11
    f, truth, log = record(tmp_path, "--corrupt", "0.01", "--corrupt-counters", "0.002", duration=duration, seed=seed)
    clean = expected_bytes(truth, "figure8", duration, seed)["daq"]
    glitched, wrong = corrupt_counters(clean, 0.002, seed)
    sent, pos = corrupt_stream(glitched, 0.01, seed, "daq")
    meta = read_metadata(truth)["serve"]
    assert int(meta["daq_counter_corrupt_frames"]) == wrong.size > 500
    n = len(clean) // L
    damaged = np.zeros(n, bool)
    damaged[pos // L] = True
    wrong_ok = np.setdiff1d(wrong, np.flatnonzero(damaged))       # wrong counters that reached the daemon
    intact = np.setdiff1d(np.flatnonzero(~damaged), wrong)
    imu = reader.read_topic(f, "/imu")["log_time_ns"]
    rel = np.concatenate(([0], np.cumsum(np.round(np.diff(imu) / FRAME_NS).astype(np.int64))))
    assert np.all(np.diff(rel) >= 1)
    # the sample index of the first /imu message: the first intact frame, or a wrong-counter frame placed before it
    for first in [intact[0], *wrong_ok[wrong_ok < intact[0]][::-1]]:
        got = rel + first
        if np.isin(intact, got).all():
            break
    missing = np.setdiff1d(intact, got)
    assert missing.size == 0, f"{missing.size} intact frames not on /imu, first at {missing[:5]}"
    extra = got[~np.isin(got, np.concatenate([intact, wrong_ok]))]
    assert extra.size == 0, f"{extra.size} /imu samples at no frame sent intact: {extra[:5]}, {damaged[extra[:5]]}"
    c = read_metadata(f)["acquire.counters"]
    assert int(c["processing_errors"]) == 0
    assert wrong_ok.size * 0.9 <= int(c["daq.counter_implausible"]) <= wrong_ok.size + 5
