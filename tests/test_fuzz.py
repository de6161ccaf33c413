"""Fuzzing in CI. Property-based (hypothesis) tests of the NMEA and DAQ decoders and the pipeline's GPS path: valid
checksums and CRCs around hostile field values (dates, times, huge numbers, 'nan', text), over 10^5 sentences
and frames. Then tools/dev/fuzz.py's mutators (checksums and CRCs rewritten after mutating) in its fast seeded loop,
over 10^5 inputs for the NMEA, UBX and NovAtel decoders, the DAQ decoder with the counter judge and the MCAP
reader, and every crash the long campaigns found (tests/data/fuzz/) replayed through the full targets."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fieldlog.acquire import daq, gnss, nmea
from fieldlog.acquire.pipeline import Pipeline
from fieldlog.tools.dev import fuzz

NS = 1_000_000_000
COUNT = {"nmea": 0, "daq": 0, "pipeline": 0}    # inputs fed, printed by test_inputs_fed
SETTINGS = dict(deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])

HOSTILE = ["", "nan", "NaN", "inf", "-inf", "1e999", "-0", "9" * 20, "9" * 40, "-1", "0", "00", "000000", "235959",
           "235960", "240000", "999999.999", "0000000", "311299", "290223", "010180", "3112", "12", "9999", "1677",
           "2262", "2200", "1979", "99999999999999999999", "1_0", "0x10", " 1", "A", "V", "N", "S", "W", "E", "M",
           "4807.038", "01131.000", "6000.0", "9060.0", "18000.0", "6", "7", "8", "12.5.3", "ü", "\x7f"]
TYPES = ["GGA", "RMC", "VTG", "GST", "ZDA", "GSA", "GSV", "GNS", "HDT", "TXT"]
_TEXT = st.text(st.characters(min_codepoint=32, max_codepoint=126, blacklist_characters="$*!,\r\n"), max_size=12)
FIELD = st.one_of(st.sampled_from(HOSTILE), _TEXT,
                  st.integers(-10**25, 10**25).map(str),
                  st.floats(allow_nan=True, allow_infinity=True).map(repr))


FIELDS = st.lists(FIELD, min_size=1, max_size=16)


def expand(fields: list[str]) -> list[bytes]:
    """Every sentence type and talker with the drawn fields, rotated through every position: 16 draws become
    up to 10 x 16 x 2 sentences with valid checksums (cheap inputs, so that a CI run covers 10^5)."""
    out = []
    for r in range(len(fields)):
        rot = fields[r:] + fields[:r]
        for kind in TYPES:
            for talker in ("GP", "GN"):
                body = ",".join([talker + kind, *rot]).encode("ascii", "replace").decode("ascii")
                out.append(nmea.sentence(body))
    return out


@settings(max_examples=500, **SETTINGS)
@given(FIELDS)
def test_nmea_decoder_never_raises_and_keeps_its_values_in_range(fields: list[str]) -> None:
    burst = expand(fields)
    dec = nmea.NmeaDecoder()
    asm = nmea.EpochAssembler()
    for i, s in enumerate(dec.feed(b"".join(burst))):
        d = getattr(s, "date", None)
        assert d is None or gnss.YEAR_MIN <= d.year <= gnss.YEAR_MAX
        tod = getattr(s, "time_of_day_s", None)
        assert tod is None or 0 <= tod < 86401
        for ep in asm.add(s, i):
            assert ep.utc_ns is None or ep.utc_ns < np.iinfo(np.int64).max
            assert math.isnan(ep.lat_deg) or -91 <= ep.lat_deg <= 91
    assert dec.stats.lines == len(burst)
    COUNT["nmea"] += len(burst)


def _frames(rows) -> bytes:
    """DAQ frames with valid sync, version and CRC around arbitrary counter, counts (full int32, beyond the
    24-bit ADC), flags, latch and temperature (docs/daq-protocol.md), each followed by its junk bytes."""
    rec = np.zeros(len(rows), daq.FRAME_DTYPE)
    rec["sync"] = (daq.SYNC0, daq.SYNC1)
    rec["version"] = daq.VERSION
    rec["counter"] = [k for k, *_ in rows]
    rec["counts"] = [v for _, v, *_ in rows]
    rec["flags"] = [f for _, _, f, _ in rows]
    rec["latch"] = [(k * 7919) & 0xFFFF for k, *_ in rows]
    rec["temp_cc"] = [((k * 31) & 0xFFFF) - 32768 for k, *_ in rows]
    raw = rec.view(np.uint8).reshape(len(rows), daq.FRAME_SIZE)
    rec["crc"] = daq.crc16_frames(raw[:, 2:36])
    return b"".join(rec[i:i + 1].tobytes() + junk for i, (*_, junk) in enumerate(rows))


I32 = st.integers(-2**31, 2**31 - 1)


@settings(max_examples=300, **SETTINGS)
@given(st.lists(I32, min_size=1, max_size=8), st.integers(0, 2**32 - 1))
def test_daq_decoder_never_raises_on_valid_crc_frames_with_hostile_values(values: list[int], seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = 200
    counts = np.array(values, np.int64)[rng.integers(0, len(values), (n, 6))]
    counter = np.where(rng.random(n) < 0.9, np.arange(n) + seed, rng.integers(0, 2**32, n)) % 2**32
    junk = [rng.bytes(int(j)) for j in rng.choice([0, 0, 0, 1, 2, 37], n)]
    rows = list(zip(counter.tolist(), counts.tolist(), rng.integers(0, 256, n).tolist(), junk))
    dec = daq.DaqDecoder()
    stream = _frames(rows)
    total = 0
    for off in range(0, len(stream), 500):
        total += len(dec.feed(stream[off:off + 500]).k)
    assert total <= n
    COUNT["daq"] += n


@settings(max_examples=120, **SETTINGS)
@given(FIELDS, st.integers(0, 2**40))
def test_pipeline_gps_path_never_raises_and_stamps_stay_in_range(fields: list[str], wall0: int) -> None:
    burst = expand(fields)
    COUNT["pipeline"] += len(burst)
    class Sink:
        def __init__(self) -> None:
            self.times: list[int] = []

        def write(self, topic: str, t: int, data: bytes) -> None:
            self.times.append(int(t))

        def write_batch(self, topic: str, t, data) -> None:
            self.times += np.asarray(t, np.int64).tolist()

    sink = Sink()
    pipe = Pipeline(sink)
    mono = 10 * NS
    wall = 1_700_000_000 * NS + wall0
    for i in range(0, len(burst), 20):
        pipe.feed("gps", mono + i * NS // 20, wall + i * NS // 20, b"".join(burst[i:i + 20]))
    pipe.finish()
    assert pipe.counters.processing_errors == 0
    assert all(0 < t < np.iinfo(np.int64).max for t in sink.times)


def test_inputs_fed() -> None:
    """(Runs after the three above.) How many inputs they fed: at least 10^5 in all."""
    print(f"\nfuzzed inputs: {COUNT}")
    if all(COUNT.values()):
        assert sum(COUNT.values()) >= 100_000


MUTATED_RUNS = {"nmea": 30_000, "ubx": 15_000, "novatel": 30_000, "daq": 25_000, "mcap": 2_000}
CRASHES = sorted((Path(__file__).parent / "data" / "fuzz").glob("*.bin"))


@pytest.mark.slow
@pytest.mark.parametrize("target", list(MUTATED_RUNS))
def test_mutated_inputs_with_rewritten_checksums_never_crash_a_decoder(target: str) -> None:
    r = fuzz.campaign(target, MUTATED_RUNS[target], seed=2026, fast=True)
    assert r.inputs == MUTATED_RUNS[target] and not r.crashes, dict(r.crashes)
    assert sum(MUTATED_RUNS.values()) >= 100_000


def test_checksum_rewriters_make_mutated_frames_pass_the_checks() -> None:
    from fieldlog.acquire import daq as daq_mod, gpsport

    rng = np.random.default_rng(3)
    for name in ("nmea", "ubx", "novatel"):
        t = fuzz.make_target(name, fast=True)
        framer = gpsport.Framer()
        for s in t.seeds[:200]:
            framer.feed(fuzz.FIXES[name](fuzz.mutate(s, rng)))
        assert sum(framer.stats.frames.values()) > 10      # mutated frames pass their checksums and are framed
        assert sum(framer.stats.bad_checksum.values()) <= 0.5 * sum(framer.stats.frames.values())
    frames = daq_mod.encode_frames(np.arange(50), np.zeros((50, 6), int), np.zeros(50, bool))
    damaged = bytearray(frames)
    damaged[5::38] = b"\x77" * 50                       # every counter's second byte changed
    dec = daq_mod.DaqDecoder()
    assert len(dec.feed(fuzz.fix_daq(bytes(damaged))).k) == 50 and dec.stats.bad_crc == 0


@pytest.mark.parametrize("path", CRASHES, ids=[p.name for p in CRASHES])
def test_every_crash_the_campaigns_found_is_fixed(path: Path) -> None:
    name = path.name.split("-")[0]
    fuzz.replay(name, path.read_bytes())
    fuzz.replay(name, path.read_bytes(), fast=True)


CAN_RUNS = {"slcan": 20_000, "candump": 3_000, "asc": 3_000, "blf": 3_000, "dbc": 3_000}


@pytest.mark.slow
@pytest.mark.parametrize("target", list(CAN_RUNS))
def test_mutated_can_inputs_never_crash_the_can_paths(target: str) -> None:
    """SLCAN bytes, candump/ASC/BLF logs through ``import --can``'s reading and DBC files, mutated with their DLCs
    and BLF object sizes fixed: a bad log or DBC is one line (a ValueError), never anything else."""
    r = fuzz.campaign(target, CAN_RUNS[target], seed=2026)
    assert r.inputs == CAN_RUNS[target] and not r.crashes, dict(r.crashes)


def test_can_length_fixers_make_mutated_records_parse() -> None:
    from fieldlog.acquire import can

    rng = np.random.default_rng(4)
    seeds = fuzz.make_target("slcan").seeds
    plain, fixed = can.SlcanFramer(), can.SlcanFramer()
    for s in seeds[:300]:
        m = fuzz.mutate(s, rng)
        plain.feed(m)
        fixed.feed(fuzz.fix_slcan(m))
    assert fixed.stats.bad_records < plain.stats.bad_records          # more mutated records reach the decoder
    good = can.slcan_record(can.CanFrame(0x123, b"\x01\x02\x03"), 100)
    assert fuzz.fix_slcan(good.replace(b"1233", b"1238")) == good                  # the DLC follows the data
    asc = b" 1.000000 1  123             Rx   d 8 01 02 03\n"
    assert fuzz.fix_asc(asc) == b" 1.000000 1  123             Rx   d 3 01 02 03\n"
