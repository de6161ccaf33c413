"""DAQ frame codec: CRC, encode/decode round trip, counters, resynchronisation, fuzzing."""
from __future__ import annotations

import binascii

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fieldlog.acquire import daq

L = daq.FRAME_SIZE


def make_frames(n: int, start: int = 0, seed: int = 0, latch: bool = True, temp: bool = True):
    rng = np.random.default_rng(seed)
    counter = np.arange(start, start + n, dtype=np.int64)
    counts = rng.integers(daq.COUNTS_MIN, daq.COUNTS_MAX + 1, (n, 6))
    pps = rng.random(n) < 0.05
    lat = rng.integers(0, 65536, n) if latch else None
    t = np.round(rng.uniform(-40, 85, n), 2) if temp else None
    if temp:
        t[rng.random(n) < 0.1] = np.nan
    return counter, counts, pps, lat, t


def feed_all(dec: daq.DaqDecoder, chunks: list[bytes]) -> tuple[daq.DaqFrames, np.ndarray]:
    """Feed chunks; concatenated frames and each frame's absolute end offset in the stream."""
    outs, ends, pos = [dec.feed(b"")], [np.zeros(0, np.int64)], 0
    for c in chunks:
        f = dec.feed(c)
        assert dec.pending < L
        assert np.all((f.end_offset >= 1) & (f.end_offset <= len(c)))
        outs.append(f)
        ends.append(f.end_offset + pos)
        pos += len(c)
    cat = daq.DaqFrames(*(np.concatenate([getattr(o, name) for o in outs]) for name in
                          ("k", "counts", "pps", "latch", "latch_valid", "temperature_c", "end_offset")))
    return cat, np.concatenate(ends)


def random_chunks(data: bytes, rng: np.random.Generator, max_len: int) -> list[bytes]:
    sizes = rng.integers(1, max_len + 1, len(data) // max(1, max_len // 2) + 2)
    cuts = np.minimum(np.cumsum(sizes), len(data))
    cuts = np.unique(np.concatenate(([0], cuts, [len(data)])))
    return [data[a:b] for a, b in zip(cuts[:-1], cuts[1:])]


# ---------------------------------------------------------------------------------------------- CRC

def test_crc_check_value():
    """CRC-16/CCITT-FALSE catalogue check value: '123456789' -> 0x29B1."""
    msg = np.frombuffer(b"123456789", np.uint8)[None, :]
    assert int(daq.crc16_columns(msg)[0]) == 0x29B1


def test_crc_equals_crc_hqx_on_random_bodies():
    rng = np.random.default_rng(3)
    body = rng.integers(0, 256, (2000, 34), dtype=np.uint8)
    body[:50] = 0
    body[50:100] = 255
    ref = np.array([binascii.crc_hqx(r.tobytes(), 0xFFFF) for r in body])
    np.testing.assert_array_equal(daq.crc16_frames(body), ref)
    np.testing.assert_array_equal(daq.crc16_columns(body), ref)


def test_encoded_frames_have_crc_hqx_and_layout():
    counter, counts, pps, lat, t = make_frames(20_000, start=2**32 - 7)
    data = daq.encode_frames(counter, counts, pps, lat, t)
    assert len(data) == 20_000 * L
    for i in range(0, 20_000, 97):
        f = data[i * L:(i + 1) * L]
        assert f[:3] == b"\xa5\x5a\x01"
        assert binascii.crc_hqx(f[2:36], 0xFFFF) == int.from_bytes(f[36:38], "little")
        assert int.from_bytes(f[4:8], "little") == counter[i] % 2**32
        assert int.from_bytes(f[8:12], "little", signed=True) == counts[i, 0]
        flags = f[3]
        assert bool(flags & 1) == pps[i] and bool(flags & 2) == pps[i]
        assert bool(flags & 4) == np.isfinite(t[i])
        assert int.from_bytes(f[32:34], "little") == (lat[i] if pps[i] else 0)


def test_encode_rejects_out_of_range_counts():
    with pytest.raises(ValueError):
        daq.encode_frames(np.arange(2), np.full((2, 6), 2**23), np.zeros(2, bool))
    with pytest.raises(ValueError):
        daq.encode_frames(np.arange(2), np.zeros((2, 5)), np.zeros(2, bool))


# ---------------------------------------------------------------------------------------------- round trip

@pytest.mark.parametrize("max_chunk", [1, 7, 38, 39, 500, 10**6])
def test_round_trip_any_chunking(max_chunk):
    n = 300 if max_chunk < 10 else 3000
    counter, counts, pps, lat, t = make_frames(n, start=123456)
    data = daq.encode_frames(counter, counts, pps, lat, t)
    dec = daq.DaqDecoder()
    f, ends = feed_all(dec, random_chunks(data, np.random.default_rng(max_chunk), max_chunk))
    np.testing.assert_array_equal(f.k, counter)
    np.testing.assert_array_equal(f.counts, counts)
    assert f.counts.dtype == np.int32
    np.testing.assert_array_equal(f.pps, pps)
    np.testing.assert_array_equal(f.latch_valid, pps)
    np.testing.assert_array_equal(f.latch, np.where(pps, lat, 0))
    np.testing.assert_allclose(f.temperature_c, t, atol=1e-9)     # NaN where not valid
    np.testing.assert_array_equal(ends, (np.arange(n) + 1) * L)
    s = dec.stats
    assert (s.frames, s.bytes_in, s.bytes_skipped, s.resyncs, s.bad_crc, s.counter_gaps) == (n, len(data), 0, 0, 0, 0)


def test_no_latch_no_temperature():
    counter, counts, pps, _, _ = make_frames(100, latch=False, temp=False)
    f = daq.DaqDecoder().feed(daq.encode_frames(counter, counts, pps))
    assert not f.latch_valid.any() and not f.latch.any() and np.isnan(f.temperature_c).all()
    np.testing.assert_array_equal(f.pps, pps)


def test_counter_wrap_across_feeds():
    counter, counts, pps, lat, t = make_frames(200, start=2**32 - 100)
    data = daq.encode_frames(counter, counts, pps, lat, t)
    dec = daq.DaqDecoder()
    k = np.concatenate([dec.feed(data[i:i + 1000]).k for i in range(0, len(data), 1000)])
    np.testing.assert_array_equal(k, counter)        # continues past 2**32, no wrap back
    assert dec.stats.counter_gaps == 0 and dec.stats.counter_backwards == 0


def test_decoder_k_is_the_counter_unwrapped_through_a_gap_across_the_wrap():
    counter = np.array([2**32 - 3, 2**32 - 2, 2, 3])
    f = daq.DaqDecoder().feed(daq.encode_frames(counter, np.zeros((4, 6), int), np.zeros(4, bool)))
    np.testing.assert_array_equal(f.k, [2**32 - 3, 2**32 - 2, 2**32 + 2, 2**32 + 3])


# ---------------------------------------------------------------------------------------------- corruption

def test_bad_crc_keeps_alignment_without_resync():
    counter, counts, pps, lat, t = make_frames(50)
    data = bytearray(daq.encode_frames(counter, counts, pps, lat, t))
    data[10 * L + 20] ^= 0x40
    dec = daq.DaqDecoder()
    f = dec.feed(bytes(data))
    np.testing.assert_array_equal(f.k, np.delete(counter, 10))
    s = dec.stats
    assert (s.bad_crc, s.resyncs, s.bytes_skipped) == (1, 0, L)


def test_garbage_causes_one_resync_and_is_counted():
    counter, counts, pps, lat, t = make_frames(50)
    data = daq.encode_frames(counter, counts, pps, lat, t)
    garbage = b"\x00\xa5\x5a\x01garbage\xa5"
    stream = data[:20 * L] + garbage + data[20 * L:]
    dec = daq.DaqDecoder()
    f, ends = feed_all(dec, [stream[i:i + 13] for i in range(0, len(stream), 13)])
    np.testing.assert_array_equal(f.k, counter)
    assert ends[20] == 21 * L + len(garbage)
    s = dec.stats
    assert (s.resyncs, s.bytes_skipped, s.bad_crc) == (1, len(garbage), 0)


def test_start_mid_frame_is_not_a_resync():
    counter, counts, pps, lat, t = make_frames(10)
    data = daq.encode_frames(counter, counts, pps, lat, t)
    dec = daq.DaqDecoder()
    f = dec.feed(data[17:])
    np.testing.assert_array_equal(f.k, counter[1:])
    assert (dec.stats.bytes_skipped, dec.stats.resyncs) == (L - 17, 0)


def test_other_version_with_valid_crc_is_skipped_and_counted():
    counter, counts, pps, lat, t = make_frames(5)
    data = bytearray(daq.encode_frames(counter, counts, pps, lat, t))
    frame = data[2 * L:3 * L]
    frame[2] = 2
    frame[36:38] = binascii.crc_hqx(bytes(frame[2:36]), 0xFFFF).to_bytes(2, "little")
    data[2 * L:3 * L] = frame
    dec = daq.DaqDecoder()
    f = dec.feed(bytes(data))
    np.testing.assert_array_equal(f.k, [0, 1, 3, 4])
    assert (dec.stats.bad_version, dec.stats.bad_crc, dec.stats.bytes_skipped) == (1, 0, L)


def test_noise_only_keeps_memory_bounded():
    rng = np.random.default_rng(5)
    dec = daq.DaqDecoder()
    for _ in range(200):
        dec.feed(rng.integers(0, 256, 5000, dtype=np.uint8).tobytes())
        assert dec.pending < L
    dec.feed(b"\xa5\x5a" * 10_000)
    assert dec.pending < L
    assert dec.stats.bytes_skipped + dec.pending + L * dec.stats.frames == dec.stats.bytes_in


# ---------------------------------------------------------------------------------------------- fuzzing

def greedy_reference(stream: bytes) -> list[int]:
    """Start offsets of the frames a greedy byte-by-byte decoder accepts (the documented resync rule)."""
    out, pos = [], 0
    while pos + L <= len(stream):
        f = stream[pos:pos + L]
        if f[:3] == b"\xa5\x5a\x01" and binascii.crc_hqx(f[2:36], 0xFFFF) == int.from_bytes(f[36:], "little"):
            out.append(pos)
            pos += L
        else:
            pos += 1
    return out


def build_corrupted(n: int, seed: int, ops: list[tuple[int, str, int]]):
    """Valid frames with corruption; returns the stream, intact frame (start, end) spans, flipped spans."""
    rng = np.random.default_rng(seed)
    start = int(rng.choice([0, 2**32 - n // 2, rng.integers(0, 2**32)]))
    counter, counts, pps, lat, t = make_frames(n, start=start, seed=seed)
    counts[rng.random((n, 6)) < 0.05] = 0x5AA5          # sync-like bytes inside the data
    data = daq.encode_frames(counter, counts, pps, lat, t)
    frames = [bytearray(data[i * L:(i + 1) * L]) for i in range(n)]
    kind = ["intact"] * n
    prefix = [b""] * n
    for i, op, p in ops:
        if kind[i] != "intact":
            continue                   # one corruption per frame: two flips could cancel or escape the CRC
        if op == "flip":
            frames[i][p % L] ^= 1 + (p >> 6) % 255
            kind[i] = "flipped"
        elif op == "truncate":
            frames[i] = frames[i][:p % L]
            kind[i] = "truncated"
        elif op == "drop":
            frames[i] = bytearray()
            kind[i] = "dropped"
        else:
            junk = rng.integers(0, 256, p % 120, dtype=np.uint8)
            junk[rng.random(junk.size) < 0.2] = 0xA5
            junk[rng.random(junk.size) < 0.1] = 0x5A
            prefix[i] += junk.tobytes()
    stream, intact, flipped = bytearray(), [], []
    for i in range(n):
        stream += prefix[i]
        s = len(stream)
        stream += frames[i]
        if kind[i] == "intact":
            intact.append((s, s + L))
        elif kind[i] == "flipped":
            flipped.append((s, s + L))
    return bytes(stream), intact, flipped


def check_stream(stream: bytes, intact, flipped, chunk_seed: int, max_chunk: int) -> int:
    """Decode ``stream`` in random chunks and check every guarantee; returns the number of feed() calls."""
    dec = daq.DaqDecoder()
    chunks = random_chunks(stream, np.random.default_rng(chunk_seed), max_chunk)
    f, ends = feed_all(dec, chunks)
    starts = ends - L
    # Decoding is chunking-independent and follows the greedy rule exactly.
    assert starts.tolist() == greedy_reference(stream)
    # Each decoded frame is what the bytes at its reported position say.
    for j, s in enumerate(starts.tolist()):
        assert int.from_bytes(stream[s + 4:s + 8], "little") == f.k[j] % 2**32
        assert int.from_bytes(stream[s + 8:s + 12], "little", signed=True) == f.counts[j, 0]
    # Every intact frame is recovered, unless a CRC-valid false frame (one that is not an intact frame
    # itself) overlaps it; a single flipped byte is always caught by the CRC.
    got = set(starts.tolist())
    intact_starts = {s for s, _ in intact}
    false = [s for s in got if s not in intact_starts]
    for s, e in intact:
        assert s in got or any(fs < e and s < fs + L for fs in false), f"intact frame at {s} lost"
    assert not got & {s for s, _ in flipped}
    st_ = dec.stats
    assert st_.bytes_in == len(stream)
    assert st_.frames * L + st_.bytes_skipped + dec.pending == len(stream)
    return len(chunks)


OPS = st.lists(st.tuples(st.integers(0, 10**6), st.sampled_from(["flip", "truncate", "drop", "garbage"]),
                         st.integers(0, 2**20)), max_size=12)


@pytest.mark.slow
def test_fuzz_corrupted_streams():
    """10^5 inputs: 500 hypothesis examples, each a corrupted stream of 20..200 frames fed to one decoder in
    random chunks of 1..24 bytes (~300 feed() calls per example); the total count is asserted below."""
    calls = []

    @settings(max_examples=500, deadline=None, suppress_health_check=[HealthCheck.too_slow])
    @given(n=st.integers(20, 200), seed=st.integers(0, 2**32 - 1), ops=OPS, chunk_seed=st.integers(0, 2**32 - 1))
    def run(n, seed, ops, chunk_seed):
        ops = [(i % n, op, p) for i, op, p in ops]
        stream, intact, flipped = build_corrupted(n, seed, ops)
        calls.append(check_stream(stream, intact, flipped, chunk_seed, 24))

    run()
    assert sum(calls) >= 100_000


@settings(max_examples=200, deadline=None)
@given(data=st.binary(max_size=3000), chunk_seed=st.integers(0, 2**32 - 1))
def test_fuzz_arbitrary_bytes(data, chunk_seed):
    check_stream(data, [], [], chunk_seed, 64)


def test_documented_limit_truncated_frame_can_pass_crc():
    """Greedy acceptance has one known blind spot: a frame cut short by one byte whose CRC high byte happens
    to be 0xA5 still passes (the next frame's first sync byte completes it) and the next frame is lost."""
    counts = np.zeros((3, 6), int)
    for c0 in range(10_000):
        data = daq.encode_frames(np.arange(c0, c0 + 3), counts, np.zeros(3, bool))
        if data[L - 1] == 0xA5:
            break
    stream = data[:L - 1] + data[L:]
    dec = daq.DaqDecoder()
    f = dec.feed(stream)
    np.testing.assert_array_equal(f.k, [c0, c0 + 2])
    assert greedy_reference(stream) == [0, 2 * L - 1]
