"""The DAQ board firmware (firmware/): its core compiled for the host and driven through ctypes, checked
against acquire/daq.py's encoder and decoder; the cross build; the emulated board under QEMU recorded by the
daemon."""
from __future__ import annotations

import binascii
import dataclasses
import ctypes
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from fieldlog.acquire import counterjudge, daq
from fieldlog.tools.sim import board

ROOT = Path(__file__).resolve().parents[1]
FIRMWARE = ROOT / "firmware"
CORE_SOURCES = sorted((FIRMWARE / "core").glob("*.c"))
TWO32 = 2**32



class Sample(ctypes.Structure):
    _fields_ = [("counter", ctypes.c_uint32), ("counts", ctypes.c_int32 * 6), ("latch", ctypes.c_uint16),
                ("temp_cc", ctypes.c_int16), ("flags", ctypes.c_uint8)]


class Counters(ctypes.Structure):
    _fields_ = [(name, ctypes.c_uint32) for name in ("samples", "frames_sent", "dropped", "overruns", "bad_input",
                                                     "pps_edges", "pps_stale", "pps_double")]


class Record(ctypes.Structure):
    _fields_ = [("counts", ctypes.c_int32 * 6), ("sample_ticks", ctypes.c_uint32), ("pps_ticks", ctypes.c_uint32),
                ("temp_cc", ctypes.c_int16), ("flags", ctypes.c_uint8)]


class Core:
    """The firmware core as a host shared library, with typed entry points."""

    def __init__(self, lib: ctypes.CDLL) -> None:
        self.lib = lib
        u8p, u32 = ctypes.POINTER(ctypes.c_uint8), ctypes.c_uint32
        lib.fw_crc16.restype = ctypes.c_uint16
        lib.fw_crc16.argtypes = [ctypes.c_uint16, u8p, ctypes.c_size_t]
        lib.fw_frame_build.argtypes = [ctypes.POINTER(Sample), u8p]
        lib.fw_pps_latch.restype = ctypes.c_uint16
        lib.fw_pps_latch.argtypes = [u32, u32, u32]
        lib.fw_pps_locate.argtypes = [u32, u32, u32]
        lib.fw_daq_pps.argtypes = [ctypes.c_void_p, u32]
        lib.fw_daq_sample.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_int32), u32, ctypes.c_bool,
                                      ctypes.c_int16]
        lib.fw_daq_sample_bad.argtypes = [ctypes.c_void_p]
        lib.fw_daq_next_frame.restype = ctypes.c_bool
        lib.fw_daq_next_frame.argtypes = [ctypes.c_void_p, u8p]
        lib.fw_daq_init.argtypes = [ctypes.c_void_p]
        lib.fw_input_init.argtypes = [ctypes.c_void_p]
        lib.fw_input_feed.argtypes = [ctypes.c_void_p, ctypes.c_uint8, ctypes.POINTER(Record)]
        lib.shim_counters.restype = ctypes.POINTER(Counters)
        lib.shim_counters.argtypes = [ctypes.c_void_p]
        lib.shim_input_bad_crc.restype = u32
        lib.shim_input_bad_crc.argtypes = [ctypes.c_void_p]
        for f in ("shim_daq_size", "shim_input_size"):
            getattr(lib, f).restype = ctypes.c_size_t
        self.ring_capacity = lib.shim_ring_capacity()

    def frame(self, s: Sample) -> bytes:
        out = (ctypes.c_uint8 * daq.FRAME_SIZE)()
        self.lib.fw_frame_build(ctypes.byref(s), out)
        return bytes(out)

    def crc16(self, data: bytes) -> int:
        buf = (ctypes.c_uint8 * len(data)).from_buffer_copy(data)
        return self.lib.fw_crc16(0xFFFF, buf, len(data))


class Sampler:
    """One fw_daq: the sampling-interrupt calls and the transmit path, as the boards make them."""

    def __init__(self, core: Core) -> None:
        self.core = core
        self.buf = ctypes.create_string_buffer(core.lib.shim_daq_size())
        core.lib.fw_daq_init(self.buf)
        self.counters = core.lib.shim_counters(self.buf).contents

    def pps(self, t_pps: int) -> None:
        self.core.lib.fw_daq_pps(self.buf, t_pps % TWO32)

    def sample(self, counts, t_edge: int, temp_cc: int | None = None) -> None:
        c = (ctypes.c_int32 * 6)(*(int(x) for x in counts))
        self.core.lib.fw_daq_sample(self.buf, c, t_edge % TWO32, temp_cc is not None, temp_cc or 0)

    def bad(self) -> None:
        self.core.lib.fw_daq_sample_bad(self.buf)

    def drain(self) -> bytes:
        out = bytearray()
        frame = (ctypes.c_uint8 * daq.FRAME_SIZE)()
        while self.core.lib.fw_daq_next_frame(self.buf, frame):
            out += bytes(frame)
        return bytes(out)


@pytest.fixture(scope="module")
def core(tmp_path_factory: pytest.TempPathFactory) -> Core:
    if shutil.which("gcc") is None:
        pytest.skip("gcc absent: apt-get install gcc")
    lib = tmp_path_factory.mktemp("fwcore") / "libfwcore.so"
    subprocess.run(["gcc", "-std=c11", "-Wall", "-Wextra", "-Werror", "-O2", "-fPIC", "-shared",
                    f"-I{FIRMWARE / 'core'}", *map(str, CORE_SOURCES), str(ROOT / "tests" / "firmware_shim.c"),
                    "-o", str(lib)], check=True)
    return Core(ctypes.CDLL(str(lib)))


def random_samples(rng: np.random.Generator, n: int) -> dict[str, np.ndarray]:
    counter = (rng.integers(0, TWO32, dtype=np.int64) + np.arange(n)) % TWO32
    counts = rng.integers(daq.COUNTS_MIN, daq.COUNTS_MAX + 1, (n, 6))
    counts[: 12] = np.array([daq.COUNTS_MIN, daq.COUNTS_MAX, 0, -1, 1, 0])[np.arange(12)[:, None] % 6]
    temp = rng.uniform(-40, 85, n)
    temp[rng.random(n) < 0.2] = np.nan
    return dict(counter=counter, counts=counts, pps=rng.random(n) < 0.3, latch=rng.integers(0, 65536, n),
                temperature_c=temp)


def c_frames(core: Core, s: dict[str, np.ndarray], with_latch: bool) -> bytes:
    out = bytearray()
    for i in range(len(s["counter"])):
        t = s["temperature_c"][i]
        flags = (daq.FLAG_PPS | (daq.FLAG_LATCH if with_latch else 0)) if s["pps"][i] else 0
        flags |= daq.FLAG_TEMP if np.isfinite(t) else 0
        temp_cc = int(np.clip(np.round(t * 100), -32768, 32767)) if np.isfinite(t) else 0
        out += core.frame(Sample(int(s["counter"][i]), (ctypes.c_int32 * 6)(*map(int, s["counts"][i])),
                                 int(s["latch"][i]), temp_cc, flags))
    return bytes(out)


def test_crc_is_ccitt_false_and_the_worked_example(core: Core) -> None:
    assert core.crc16(b"123456789") == 0x29B1 == binascii.crc_hqx(b"123456789", 0xFFFF)
    rng = np.random.default_rng(1)
    for n in (0, 1, 34, 500):
        data = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        assert core.crc16(data) == binascii.crc_hqx(data, 0xFFFF)
    # docs/daq-protocol.md's worked example
    s = Sample(1000, (ctypes.c_int32 * 6)(100, -200, 300, 8388607, -8388608, 0), 0x4000, 2345,
               daq.FLAG_PPS | daq.FLAG_LATCH | daq.FLAG_TEMP)
    assert core.frame(s).hex() == ("a55a0107e80300006400000038ffffff2c010000ffff7f00000080ff00000000"
                                   "00402909d2b8")


@pytest.mark.parametrize("with_latch", [True, False])
def test_frames_are_byte_identical_to_the_host_encoder_and_decode_the_same(core: Core, with_latch: bool) -> None:
    rng = np.random.default_rng(7 + with_latch)
    s = random_samples(rng, 3000)
    want = daq.encode_frames(s["counter"], s["counts"], s["pps"], s["latch"] if with_latch else None,
                             s["temperature_c"])
    got = c_frames(core, s, with_latch)
    assert got == want
    f = daq.DaqDecoder().feed(got)
    assert len(f) == 3000
    assert np.array_equal(f.counts, s["counts"]) and np.array_equal(f.pps, s["pps"])
    assert np.array_equal(f.latch_valid, s["pps"] & with_latch)
    assert np.array_equal(f.latch, np.where(s["pps"] & with_latch, s["latch"], 0))
    t = s["temperature_c"]
    assert np.array_equal(np.isnan(f.temperature_c), np.isnan(t))
    assert np.allclose(f.temperature_c[np.isfinite(t)], np.round(t[np.isfinite(t)] * 100) / 100)
    assert np.array_equal(f.k, s["counter"][0] + np.arange(3000))     # the counter unwrapped


def test_out_of_range_counts_saturate_at_24_bits(core: Core) -> None:
    counts = [2**23, -(2**23) - 1, 2**31 - 1, -(2**31), 5, -5]
    got = core.frame(Sample(3, (ctypes.c_int32 * 6)(*counts), 0, 0, 0))
    assert got == daq.encode_frames([3], [np.clip(counts, daq.COUNTS_MIN, daq.COUNTS_MAX)], [False])


def test_latch_arithmetic_against_exact_integers(core: Core) -> None:
    rng = np.random.default_rng(3)
    for _ in range(2000):
        t_prev = int(rng.integers(0, TWO32))
        period = int(rng.integers(1, 2**26))
        into = int(rng.integers(1, period + 1))
        t_edge, t_pps = (t_prev + period) % TWO32, (t_prev + into) % TWO32
        assert core.lib.fw_pps_locate(t_prev, t_edge, t_pps) == 0                      # in this period
        assert core.lib.fw_pps_latch(t_prev, t_edge, t_pps) == min(into * 65536 // period, 65535)
        assert core.lib.fw_pps_locate(t_prev, t_edge, (t_edge + into) % TWO32) == 1    # the next period's
        assert core.lib.fw_pps_locate(t_prev, t_edge, (t_prev - into + 1) % TWO32) == 2  # at/before t_prev


def test_sampler_latches_pps_across_the_timer_wrap_and_decodes_as_the_simulator_latches(core: Core) -> None:
    """Sample edges every ~168000 ticks through the 32-bit timer wrap; PPS captures in some periods, one
    captured after its period's edge (before the interrupt ran), one stale: the frames decode to the PPS
    positions the core's arithmetic gives, k_edge = k - 1 + latch / 65536."""
    rng = np.random.default_rng(11)
    n = 3000
    t_edge = TWO32 - 1000 * 168_000 + np.cumsum(rng.integers(167_990, 168_010, n))
    counts = rng.integers(daq.COUNTS_MIN, daq.COUNTS_MAX + 1, (n, 6))
    s = Sampler(core)
    want_latch = {}
    out = bytearray()
    for k in range(n):
        if k % 250 == 100:                         # an edge inside period k
            into = int(rng.integers(1, t_edge[k] - t_edge[k - 1] + 1))
            s.pps(int(t_edge[k - 1]) + into)
            want_latch[k] = min(into * 65536 // int(t_edge[k] - t_edge[k - 1]), 65535)
        if k == 1500:                              # captured just after edge k: it belongs to period k + 1
            s.pps(int(t_edge[k]) + 5)
            want_latch[k + 1] = 5 * 65536 // int(t_edge[k + 1] - t_edge[k])
        s.sample(counts[k], int(t_edge[k]), temp_cc=int(k % 3000))
        if k == 2000:                              # a capture older than the last edge: discarded
            s.pps(int(t_edge[k]) - 10)
        out += s.drain()
    assert s.counters.pps_stale == 1
    f = daq.DaqDecoder().feed(bytes(out))
    assert len(f) == n and np.array_equal(f.counts, counts)
    assert np.array_equal(f.k, np.arange(n))
    assert sorted(want_latch) == list(np.flatnonzero(f.pps)) == list(np.flatnonzero(f.latch_valid))
    assert [int(f.latch[k]) for k in sorted(want_latch)] == [want_latch[k] for k in sorted(want_latch)]
    assert s.counters.pps_edges == len(want_latch) and s.counters.samples == n
    assert int(np.min(t_edge % TWO32)) < 168_010 < int(np.max(t_edge % TWO32))  # the wrap was crossed


def judged(stream: bytes) -> tuple[daq.DaqFrames, daq.DaqStats]:
    """The frames of one byte stream as the pipeline sees them: decoded, then their counters judged."""
    dec = daq.DaqDecoder()
    judge = counterjudge.CounterJudge(dec.stats)
    parts = [judge.judge(dec.feed(stream), 0), judge.flush()]
    return daq.DaqFrames(*(np.concatenate([getattr(p, f) for p in parts]) for f in (x.name for x in dataclasses.fields(daq.DaqFrames)))), dec.stats


def test_ring_overrun_is_counted_and_shows_as_a_counter_gap(core: Core) -> None:
    cap = core.ring_capacity
    s = Sampler(core)
    for k in range(cap + 37):                      # the transmit path stalls: 37 samples find the ring full
        s.sample([k] * 6, k * 1000)
    assert (s.counters.dropped, s.counters.overruns) == (37, 1)
    first = s.drain()
    for k in range(cap + 37, cap + 47):            # it catches up
        s.sample([k] * 6, k * 1000)
    s.sample([0] * 6, 0)
    s.sample([0] * 6, 0)
    assert s.counters.overruns == 1
    f, stats = judged(first + s.drain())
    assert len(f) == cap + 12 == s.counters.frames_sent
    assert (stats.counter_gaps, stats.lost_frames) == (1, 37) == (s.counters.overruns, s.counters.dropped)
    assert np.array_equal(f.counts[cap:cap + 10, 0], np.arange(cap + 37, cap + 47))
    # a second stall is a second overrun; a sample the ADC could not deliver is a gap too
    for k in range(cap + 1):
        s.sample([1] * 6, k)
    s.bad()
    s.drain()
    assert (s.counters.overruns, s.counters.dropped, s.counters.bad_input) == (2, 38, 1)


def test_counter_wraps_at_2_32_without_a_gap(core: Core) -> None:
    s = Sampler(core)
    s.counters.samples = TWO32 - 100
    out = bytearray()
    for k in range(300):
        s.sample([k, -k, 0, 0, 0, 0], k * 168_000)
        out += s.drain()
    raw = np.frombuffer(bytes(out), daq.FRAME_DTYPE)["counter"]
    assert raw[0] == TWO32 - 100 and raw[99] == TWO32 - 1 and raw[100] == 0 and raw[-1] == 199
    f, stats = judged(bytes(out))
    assert np.array_equal(f.k % TWO32, (TWO32 - 100 + np.arange(300)) % TWO32)
    assert np.all(np.diff(f.k) == 1)
    assert stats.counter_gaps == 0 and stats.counter_backwards == 0 and stats.lost_frames == 0


def test_input_records_from_the_simulator_parse_in_the_firmware(core: Core) -> None:
    """tools/sim/board.py's records, with garbage between them and one damaged, through the firmware's
    byte-at-a-time parser: every intact record decodes to what was encoded."""
    rng = np.random.default_rng(5)
    n = 400
    counts = rng.integers(daq.COUNTS_MIN, daq.COUNTS_MAX + 1, (n, 6))
    ticks = rng.integers(0, TWO32, n, dtype=np.int64).astype(np.uint32)
    pps = rng.random(n) < 0.2
    pticks = rng.integers(0, TWO32, n, dtype=np.int64).astype(np.uint32)
    temp = rng.uniform(-20, 60, n)
    temp[::7] = np.nan
    rows = board.encode_records(counts, ticks, pps, pticks, temp)
    rows[50, 10] ^= 0x40                                              # one damaged record
    stream = b"\x5a\xa5\x00" + b"".join(r.tobytes() + (b"\x5a" if i % 9 == 0 else b"") for i, r in enumerate(rows))
    p = ctypes.create_string_buffer(core.lib.shim_input_size())
    core.lib.fw_input_init(p)
    rec = Record()
    got, bad = [], 0
    for b in stream:
        r = core.lib.fw_input_feed(p, b, ctypes.byref(rec))
        if r == 1:
            got.append((list(rec.counts), rec.sample_ticks, rec.pps_ticks, rec.temp_cc, rec.flags))
        bad += r == 2
    keep = np.arange(n) != 50
    assert len(got) == n - 1 and bad >= 1 and core.lib.shim_input_bad_crc(p) == bad
    assert np.array_equal([g[0] for g in got], counts[keep])
    assert np.array_equal([g[1] for g in got], ticks[keep])
    assert np.array_equal([g[2] for g in got], np.where(pps, pticks, 0)[keep])
    assert np.array_equal([g[4] & 1 for g in got], pps[keep])
    assert np.array_equal([g[3] for g in got], np.where(np.isnan(temp), 0, np.round(np.nan_to_num(temp) * 100))[keep])


def cross_build(build: Path, *extra_cflags: str) -> subprocess.CompletedProcess:
    """``make -C firmware`` into ``build`` (both images, or only the emulated one with extra CFLAGS)."""
    args = ["make", "-s", "-C", str(FIRMWARE), f"BUILD={build}"]
    if extra_cflags:
        args += ["qemu", f"EXTRA_CFLAGS={' '.join(extra_cflags)}"]
    return subprocess.run(args, capture_output=True, text=True, check=True)


needs_cross = pytest.mark.skipif(shutil.which("arm-none-eabi-gcc") is None,
                                 reason="arm-none-eabi-gcc absent: apt-get install gcc-arm-none-eabi libnewlib-arm-none-eabi")


@needs_cross
def test_cross_build_makes_both_images_with_a_vector_table(tmp_path: Path) -> None:
    out = cross_build(tmp_path).stdout
    for name in ("stm32f4/fieldlog-stm32f4", "qemu/fieldlog-qemu"):
        assert f"{name}.elf" in out                              # the size table lists it
        image = (tmp_path / f"{name}.bin").read_bytes()
        sp, reset = np.frombuffer(image[:8], "<u4")
        assert sp == 0x20020000                                  # top of the 128 KiB SRAM
        assert reset & 1 and 0x08000000 < reset < 0x08000000 + len(image)   # Thumb code inside the image
        assert len(image) < 64 * 1024


needs_qemu = pytest.mark.skipif(shutil.which("qemu-system-arm") is None,
                                reason="qemu-system-arm absent: apt-get install qemu-system-arm")
LATCH_CONFIG = '[timesync]\npps_mode = "latch"\n'


def record_emulated(tmp_path: Path, image: Path, duration_s: float, seed: int) -> tuple[Path, Path, str]:
    """``sim --serve --board emulated`` at real speed recorded by ``fieldlog acquire`` (latched PPS): the
    recording, the serve truth file and the daemon's stderr."""
    import signal

    from test_daemon import start_daemon
    from test_serve import start_serve

    truth, cfg = tmp_path / "truth.mcap", tmp_path / "acquire.toml"
    cfg.write_text(LATCH_CONFIG)
    serve, paths = start_serve("--board", "emulated", "--board-image", str(image), "--scenario", "figure8",
                               "--duration", str(duration_s), "--seed", str(seed), "--speed", "1", "--hold",
                               "--truth", str(truth))
    d, _ = start_daemon(tmp_path / "drives", paths, "--config", str(cfg))
    serve.send_signal(signal.SIGUSR1)
    assert serve.wait(duration_s + 60) == 0, serve.stderr.read()
    d.send_signal(signal.SIGTERM)
    assert d.wait(30) == 0
    (f,) = sorted((tmp_path / "drives").glob("*/*.mcap"))
    return f, truth, d.stderr.read()


@needs_cross
@needs_qemu
def test_daemon_records_the_emulated_board_as_the_simulated_one(tmp_path: Path) -> None:
    """40 s of figure8 through the firmware under QEMU: /imu at 500 Hz, every sample, no bad CRC, counts and
    PPS flags those the simulator fed, latches within 2 LSB of the simulator's own, time sync locked, and the
    stamps' error against truth within 2x that of the plain simulator (`fieldlog sim`, same drive)."""
    from fieldlog.acquire.timesync import SyncState
    from fieldlog.drive import reader
    from fieldlog.tools import info
    from fieldlog.drive.reader import read_metadata
    from fieldlog.tools.sim.serve import simulated_streams
    from fieldlog.tools.sim.simulate import simulate

    cross_build(tmp_path / "fw")
    f, truth, log = record_emulated(tmp_path, tmp_path / "fw" / "qemu" / "fieldlog-qemu.elf", 40.0, 4)
    sent = read_metadata(truth)["serve"]
    assert sent["board"] == "emulated" and sent["pps_mode"] == "latch" and int(sent["daq_frames"]) == 20000
    c = read_metadata(f)["acquire.counters"]
    assert int(c["daq.frames"]) == 20000
    assert int(c["daq.bad_crc"]) == int(c["daq.counter_gaps"]) == int(c["daq.lost_frames"]) == 0
    assert int(c["daq.bytes_skipped"]) == 0
    # the frames on /raw/daq are the firmware's: the simulator's samples, latched by the firmware
    raw = b"".join(bytes(m.data) for m in reader.read_topic(f, "/raw/daq")["msgs"])
    fw = daq.DaqDecoder().feed(raw)
    sim = daq.DaqDecoder().feed(simulated_streams(sent)["daq"])
    assert np.array_equal(fw.k, np.arange(20000)) and np.array_equal(fw.counts, sim.counts)
    assert np.array_equal(fw.pps, sim.pps) and np.array_equal(fw.latch_valid, sim.pps)
    assert fw.pps.sum() >= 35 and np.abs(fw.latch.astype(int) - sim.latch.astype(int)).max() <= 2
    assert np.array_equal(fw.temperature_c, sim.temperature_c)
    # /imu: every sample at 500 Hz on the time sync's clock, locked
    imu = reader.read_topic(f, "/imu")["log_time_ns"]
    tru = reader.read_topic(truth, "/truth/imu")["log_time_ns"]
    assert len(imu) == len(tru) == 20000
    assert abs(np.median(np.diff(imu)) - 2e6) < 2e6 * 1e-4
    sync = reader.read_topic(f, "/time/sync")
    lock_ns = sync["log_time_ns"][np.flatnonzero(sync["state"] == SyncState.LOCKED)[0]]
    states = sync["state"][sync["log_time_ns"] >= lock_ns]
    print(f"\nafter the first lock: {np.mean(states == SyncState.LOCKED):.3f} locked, states {np.unique(states)}, "
          f"last {sync['state'][-1]}; pps_edges {c.get('pps_edges')} rejected {c.get('pps_rejected')}")
    assert np.mean(states == SyncState.LOCKED) > 0.95 and SyncState.FREE not in states
    after = imu >= lock_ns
    assert after.mean() > 0.6
    rms_us = np.sqrt(np.mean(((imu - tru)[after] / 1e3) ** 2))
    plain = simulate("figure8", 40.0, 4, tmp_path / "plain.mcap", pps_mode="latch")
    assert plain.imu_samples == 20000
    plain_rms_us = info.drive_info(tmp_path / "plain.mcap").timing.rms_us
    print(f"\nemulated board: stamp RMS vs truth {rms_us:.3f} us after lock; plain simulator {plain_rms_us:.3f} us")
    assert rms_us <= 2 * plain_rms_us


@needs_cross
@needs_qemu
def test_a_transmit_path_slower_than_the_adc_shows_as_counted_dropped_samples(tmp_path: Path) -> None:
    """A test build whose link moves at most 800 frames per 1000 samples: the ring overruns, the board drops
    samples, and every drop is a counter gap that the daemon counts and `fieldlog info` prints; frames plus
    lost frames account for every sample fed but the last few (the ring still holds 64 when the input
    stops, covering the last 80 samples)."""
    from fieldlog.drive.reader import read_metadata

    from test_daemon import run

    cross_build(tmp_path / "fw", "-DFW_TX_PER_1000=800")
    f, truth, _ = record_emulated(tmp_path, tmp_path / "fw" / "qemu" / "fieldlog-qemu.elf", 8.0, 2)
    fed = int(read_metadata(truth)["serve"]["daq_frames"])
    c = {k: int(v) for k, v in read_metadata(f)["acquire.counters"].items() if k.startswith("daq.")}
    assert fed == 4000 and c["daq.bad_crc"] == 0 and c["daq.bytes_skipped"] == 0
    assert c["daq.frames"] <= 0.8 * fed and c["daq.counter_gaps"] > 10 and c["daq.lost_frames"] > 0.1 * fed
    assert fed - 64 * 1000 // 800 - 2 <= c["daq.frames"] + c["daq.lost_frames"] <= fed
    out = run("info", str(f)).stdout
    print(f"\nlink at 800 frames per 1000 samples: {fed} samples fed, {c['daq.frames']} frames, {c['daq.counter_gaps']} gaps, "
          f"{c['daq.lost_frames']} lost")
    assert f"daq.counter_gaps={c['daq.counter_gaps']}" in out and f"daq.lost_frames={c['daq.lost_frames']}" in out


def test_emulated_board_without_its_image_or_with_unplugs_is_one_line_exit_2(tmp_path: Path) -> None:
    from test_daemon import run

    missing = tmp_path / "none.elf"
    r = run("sim", "--serve", "--board", "emulated", "--board-image", str(missing), "--duration", "2")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr
    assert ("qemu-system-arm" in r.stderr) if shutil.which("qemu-system-arm") is None else (
        str(missing) in r.stderr and "make firmware" in r.stderr)
    r = run("sim", "--serve", "--board", "emulated", "--unplug", "daq:1:1", "--duration", "2")
    assert r.returncode == 2 and "--unplug" in r.stderr and len(r.stderr.strip().splitlines()) == 1
