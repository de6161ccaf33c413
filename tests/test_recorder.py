"""drive.recorder (write, flush), acquire.recovery (recover) and drive.reader, checked with mcap's own readers
and with rerun's MCAP importer."""

from __future__ import annotations

import json
import os
import re
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer
from mcap_ros2.decoder import DecoderFactory

from fieldlog.drive import messages as m
from fieldlog.drive.recorder import Recorder, Records
from fieldlog.acquire.recovery import recover
from fieldlog.drive import reader

T0 = 1_700_000_000 * 10**9
DT = 2_000_000  # 500 Hz


def _all_messages(path) -> list[tuple[str, int, bytes]]:
    with open(path, "rb") as f:
        return [(c.topic, msg.log_time, msg.data) for _, c, msg in make_reader(f).iter_messages(log_time_order=False)]


def _drive(path: Path, n: int = 3000, flush_every: int = 250, **kw) -> dict:
    """Offline-style writer: /imu at 500 Hz, /gps/fix and /gps/nmea at 5 Hz, flush by data time."""
    rng = np.random.default_rng(3)
    t = T0 + np.arange(n, dtype=np.int64) * DT
    w, f = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    g = np.arange(0, n, 100)
    lat = 48.0 + rng.normal(size=len(g)) * 1e-4
    with Recorder(path, flush_interval_s=None, metadata={"scenario": "unit", "seed": "3"}, **kw) as rec:
        for k in range(0, n, flush_every):
            sl = slice(k, k + flush_every)
            rec.write_batch("/imu", t[sl], m.encode_imu(t[sl], w[sl], f[sl]))
            gi = g[(g >= k) & (g < k + flush_every)]
            if len(gi):
                rec.write_batch("/gps/fix", t[gi], m.encode_navsatfix(t[gi], lat[gi // 100], lat[gi // 100], lat[gi // 100]))
                for i in gi:
                    rec.write("/gps/nmea", int(t[i]), m.encode_sentence(int(t[i]), f"$GPGGA,{i}*00"))
            rec.flush()
    return {"t": t, "w": w, "f": f, "g": g, "lat": lat}


def test_roundtrip_with_mcap_reader_and_ros2_decoder(tmp_path):
    path = tmp_path / "d.mcap"
    d = _drive(path)
    msgs = _all_messages(path)
    imu = [x for x in msgs if x[0] == "/imu"]
    assert [x[1] for x in imu] == d["t"].tolist()
    assert len([x for x in msgs if x[0] == "/gps/nmea"]) == len(d["g"])
    with open(path, "rb") as fh:
        r = make_reader(fh, decoder_factories=[DecoderFactory()])
        s = r.get_summary()
        assert s.statistics.message_count == len(msgs)
        assert len(s.chunk_indexes) == 12  # one chunk per flush
        meta = {md.name: md.metadata for md in r.iter_metadata()}
        # written at close, as JSON
        assert json.loads(meta.pop("fieldlog.info")["span./imu"]) == [int(d["t"][0]), int(d["t"][-1])]
        assert meta == {"drive": {"scenario": "unit", "seed": "3"}}
        decoded = [x.decoded_message for x in r.iter_decoded_messages(topics=["/imu"])]
    assert decoded[7].angular_velocity.y == d["w"][7, 1]
    assert decoded[-1].header.stamp.sec * 10**9 + decoded[-1].header.stamp.nanosec == d["t"][-1]


def test_write_batch_splits_by_chunk_size_and_rejects_zero_time(tmp_path):
    path = tmp_path / "c.mcap"
    n = 2000
    t = T0 + np.arange(n, dtype=np.int64) * DT
    p = m.encode_imu(t, np.zeros((n, 3)), np.ones((n, 3)))
    with Recorder(path, chunk_size=64 * 1024, flush_interval_s=None, compression="") as rec:
        with pytest.raises(ValueError):
            rec.write("/imu", 0, p[0])
        with pytest.raises(ValueError):
            rec.write_batch("/imu", np.zeros(n, np.int64), p)
        rec.write_batch("/imu", t, p)
    with open(path, "rb") as fh:
        chunks = make_reader(fh).get_summary().chunk_indexes
    assert len(chunks) > 5
    assert all(c.uncompressed_size <= 64 * 1024 for c in chunks)
    assert [x[1] for x in _all_messages(path)] == t.tolist()


def test_write_records_gives_the_file_of_write_of_each_message(tmp_path):
    """``write_records`` of messages in pieces of any size, given as lists or as one batch laid out at the first
    write, writes the file ``write`` of each message in turn does: a chunk is closed after the message that fills
    it, not before the one that would overfill it (``write_batch``)."""
    rng = np.random.default_rng(5)
    n = 600
    t = (T0 + np.arange(n, dtype=np.int64) * DT).tolist()
    msgs = [m.encode_raw(x, 5, "daq", rng.bytes(int(k))) for x, k in zip(t, rng.integers(0, 900, n))]
    one, many = tmp_path / "one.mcap", tmp_path / "many.mcap"
    kw = dict(chunk_size=4096, flush_interval_s=None, compression="")
    with Recorder(one, **kw) as rec:
        for x, d in zip(t, msgs):
            rec.write("/raw/daq", x, d)
    with Recorder(many, **kw) as rec:
        cuts = np.unique(np.concatenate(([0, n], rng.integers(0, n, 60)))).tolist()
        for a, b in zip(cuts[:-1], cuts[1:]):
            rec.write_records(Records("/raw/daq", t[a:b], msgs[a:b]))
        with pytest.raises(ValueError):
            rec.write_records(Records("/raw/daq", [0], msgs[:1]))
    ahead = tmp_path / "ahead.mcap"
    with Recorder(ahead, **kw) as rec:          # one batch, laid out at the first write, written in the same pieces
        recs = Records("/raw/daq", np.array(t), m.Packed.from_list(msgs))
        for a, b in zip(cuts[:-1], cuts[1:]):
            rec.write_records(recs, a, b)
        with pytest.raises(ValueError):
            rec.write_records(Records("/raw/daq", np.array([0]), m.Packed.from_list(msgs[:1])))
    assert one.read_bytes() == many.read_bytes() == ahead.read_bytes()
    with open(one, "rb") as fh:
        sizes = [c.uncompressed_size for c in make_reader(fh).get_summary().chunk_indexes]
    want, size = [], 0          # each chunk closed by the record (31 header bytes + payload) that fills it
    for d in msgs:
        size += 31 + len(d)
        if size >= 4096:
            want, size = want + [size], 0
    assert sizes == want + ([size] if size else []) and len(sizes) > 20
    assert [x[2] for x in _all_messages(one)] == msgs


def test_unclosed_file_after_host_time_flush_recovers_everything_written(tmp_path):
    """flush_interval_s=0 flushes after every write: a copy of the file taken while it is
    still open (as after a power cut) recovers every message written so far."""
    path, cut, out = tmp_path / "live.mcap", tmp_path / "cut.mcap", tmp_path / "rec.mcap"
    rec = Recorder(path, flush_interval_s=0.0)
    t = T0 + np.arange(50, dtype=np.int64) * DT
    for k in range(5):
        sl = slice(10 * k, 10 * k + 10)
        rec.write_batch("/imu", t[sl], m.encode_imu(t[sl], np.zeros((10, 3)), np.zeros((10, 3))))
        rec.write("/raw/gps", int(t[10 * k]), m.encode_raw(int(t[10 * k]), 5, "/dev/ttyS0", b"$GP\r\n"))
    shutil.copy(path, cut)
    rep = recover(cut, out)
    rec.close()
    assert rep.messages == {"/imu": 50, "/raw/gps": 5}
    assert rep.last_log_time_ns == t[-1] and not rep.had_summary and rep.bytes_discarded == 0
    assert len(_all_messages(out)) == 55


def test_recover_at_random_cuts_keeps_exactly_the_complete_chunks(tmp_path):
    path = tmp_path / "d.mcap"
    _drive(path, n=2000, flush_every=100)
    raw = path.read_bytes()
    full = _all_messages(path)
    with open(path, "rb") as fh:
        summary = make_reader(fh).get_summary()
    chunks = summary.chunk_indexes
    md_end = summary.metadata_indexes[0].offset + summary.metadata_indexes[0].length
    info = summary.metadata_indexes[1]     # fieldlog.info, written at close after the last chunk
    assert info.name == "fieldlog.info" and info.offset > chunks[-1].chunk_start_offset
    by_time = {(tp, lt): dat for tp, lt, dat in full}
    rng = np.random.default_rng(11)
    cuts = sorted(set(rng.integers(1, len(raw), 40).tolist()) | {8, md_end - 1, md_end, chunks[0].chunk_start_offset + chunks[0].chunk_length, len(raw) - 1})
    for cut in cuts:
        src, dst = tmp_path / "cut.mcap", tmp_path / "rec.mcap"
        src.write_bytes(raw[:cut])
        rep = recover(src, dst, force=True)   # the same names each cut
        complete = [c for c in chunks if c.chunk_start_offset + c.chunk_length <= cut]
        expected = {(tp, lt) for tp, lt, _ in full if any(c.message_start_time <= lt <= c.message_end_time for c in complete)}
        got = _all_messages(dst)  # make_reader reads the recovered file completely
        assert {(tp, lt) for tp, lt, _ in got} == expected, cut
        assert all(by_time[(tp, lt)] == dat for tp, lt, dat in got)
        assert sum(rep.messages.values()) == len(got)
        assert rep.chunks == len(complete)
        with open(dst, "rb") as fh:
            names = [md.name for md in make_reader(fh).iter_metadata()]
        assert names == (["drive"] if cut >= md_end else []) + (["fieldlog.info"] if cut >= info.offset + info.length
                                                                  else [])


def test_a_few_messages_are_laid_out_as_a_batch_of_them(tmp_path, monkeypatch):
    """``write_batch`` of at most ``FEW`` messages, laid out a record at a time, gives the file the batch's
    arrays give: the same records, message indexes and chunks (a chunk closed before the message that would
    overfill it, an oversized message alone in its chunk), with batches of one size and of mixed sizes."""
    from fieldlog.drive import recorder

    rng = np.random.default_rng(9)
    n = 400
    t = T0 + np.arange(n, dtype=np.int64) * DT
    cuts = np.unique(np.concatenate(([0, n], rng.integers(0, n, 150)))).tolist()
    fixed = m.encode_imu(t, rng.normal(size=(n, 3)), rng.normal(size=(n, 3)))
    mixed = [m.encode_sentence(int(x), "$GPGGA," + "1" * int(k)) for x, k in zip(t, rng.integers(0, 5000, n))]

    def write(path: Path) -> bytes:
        with Recorder(path, chunk_size=4096, flush_interval_s=None, compression="") as rec:
            for a, b in zip(cuts[:-1], cuts[1:]):
                rec.write_batch("/imu", t[a:b], m.Packed.from_list(fixed.to_list()[a:b]), t[a:b] - 7)
                rec.write_batch("/gps/nmea", t[a:b], mixed[a:b])
        return path.read_bytes()

    sizes = np.diff(cuts)
    assert sizes.min() <= recorder.FEW < sizes.max()
    few = write(tmp_path / "few.mcap")
    monkeypatch.setattr(recorder, "FEW", 0)
    assert few == write(tmp_path / "arrays.mcap")


def test_recover_file_from_mcap_writer(tmp_path):
    """Files from other writers keep schemas and channels inside chunks; recover handles them."""
    src = tmp_path / "w.mcap"
    with open(src, "wb") as fh:
        w = Writer(fh, chunk_size=2000)
        w.start()
        sid = w.register_schema(m.IMU, "ros2msg", m.schema_text(m.IMU).encode())
        cid = w.register_channel("/imu", "cdr", sid)
        t = T0 + np.arange(100, dtype=np.int64) * DT
        for i, b in enumerate(m.encode_imu(t, np.zeros((100, 3)), np.zeros((100, 3)))):
            w.add_message(cid, int(t[i]), b, int(t[i]))
        w.finish()
    raw = src.read_bytes()
    cut = tmp_path / "cut.mcap"
    with open(src, "rb") as fh:
        last = make_reader(fh).get_summary().chunk_indexes[-3]
    cut.write_bytes(raw[: last.chunk_start_offset + last.chunk_length // 2])
    rep = recover(cut, tmp_path / "r.mcap")
    got = _all_messages(tmp_path / "r.mcap")
    assert 0 < len(got) == rep.messages["/imu"] < 100
    assert [lt for _, lt, _ in got] == t[: len(got)].tolist()


def test_reader_topics_read_topic_and_blocks(tmp_path):
    path = tmp_path / "d.mcap"
    d = _drive(path, n=3000, flush_every=333)
    info = {ti.topic: ti for ti in reader.topics(path)}
    assert info["/imu"].type == m.IMU and info["/imu"].count == 3000
    assert (info["/imu"].first_ns, info["/imu"].last_ns) == (d["t"][0], d["t"][-1])
    assert info["/gps/fix"].count == len(d["g"])

    imu = reader.read_topic(path, "/imu")
    np.testing.assert_array_equal(imu["log_time_ns"], d["t"])
    np.testing.assert_array_equal(imu["stamp_ns"], d["t"])
    np.testing.assert_array_equal(imu["omega_ib_b"], d["w"])
    np.testing.assert_array_equal(imu["f_b"], d["f"])
    fix = reader.read_topic(path, "/gps/fix")
    np.testing.assert_array_equal(fix["lat_deg"], d["lat"])
    nmea = reader.read_topic(path, "/gps/nmea")
    assert [x.sentence for x in nmea["msgs"]] == [f"$GPGGA,{i}*00" for i in d["g"]]

    blocks = list(reader.iter_blocks(path, ["/imu", "/gps/fix"], block_s=0.7))
    assert blocks[0].t0_ns == d["t"][0]
    assert all(b.t1_ns - b.t0_ns == 700_000_000 for b in blocks)
    assert all(a.t1_ns == b.t0_ns for a, b in zip(blocks, blocks[1:]))
    for b in blocks:
        lt = b.data["/imu"]["log_time_ns"]
        assert ((lt >= b.t0_ns) & (lt < b.t1_ns)).all()
    np.testing.assert_array_equal(np.concatenate([b.data["/imu"]["omega_ib_b"] for b in blocks]), d["w"])
    np.testing.assert_array_equal(np.concatenate([b.data["/gps/fix"]["lat_deg"] for b in blocks]), d["lat"])
    assert len(blocks) == int(np.ceil((d["t"][-1] - d["t"][0] + 1) / 700_000_000))


@pytest.mark.skipif(not (Path(os.sys.executable).parent / "rerun").exists(), reason="rerun CLI not installed")
def test_rerun_shows_imu_as_scalars_and_fix_as_geopoints(tmp_path):
    path = tmp_path / "d.mcap"
    _drive(path, n=500, flush_every=250)
    rerun = str(Path(os.sys.executable).parent / "rerun")
    # CI set -> rerun's analytics pipeline is off; HOME/XDG point at tmp so no config is touched.
    env = dict(os.environ, CI="1", HOME=str(tmp_path), XDG_CONFIG_HOME=str(tmp_path / "cfg"), XDG_DATA_HOME=str(tmp_path / "data"))
    subprocess.run([rerun, "mcap", "convert", str(path), "-o", str(tmp_path / "d.rrd")], env=env, check=True, capture_output=True, timeout=120)
    out = subprocess.run([rerun, "rrd", "print", str(tmp_path / "d.rrd")], env=env, check=True, capture_output=True, text=True, timeout=120).stdout
    lines = out.splitlines()
    fix = [ln for ln in lines if " - /gps/fix - " in ln]
    imu = [ln for ln in lines if " - /imu - " in ln]
    # rerun emits one chunk per MCAP chunk: add the rows up.
    assert _rows(fix, "GeoPoints:positions") == 5, out
    assert _rows(imu, "Scalars:scalars") == 500, out


def _rows(lines: list[str], column: str) -> int:
    return sum(int(re.search(r"with (\d+) rows", ln).group(1)) for ln in lines if column in ln)


def test_decompress_many_takes_empty_and_lying_chunks():
    """Chunks in one call (``decompress_many``): an empty zstd chunk among others reads as nothing (the batch
    decompressor would corrupt memory on it: it goes one by one), and a chunk whose record claims a wrong or an
    absurd size, or whose bytes are damaged, is a ``ChunkError`` naming it, never a crash or wrong data."""
    import zlib

    import zstandard

    from fieldlog.drive.chunks import ChunkError, decompress_many

    rng = np.random.default_rng(3)
    raws = [b"", *(rng.integers(0, 4, n, dtype=np.uint8).tobytes() for n in (4096, 1, 5000))]
    frames = [zstandard.ZstdCompressor().compress(r) for r in raws]
    at = np.cumsum([0] + [len(f) for f in frames])[:-1]
    buf = b"".join(frames)

    def read(size, data=buf):
        return decompress_many(data, ["zstd"], [0] * len(raws), at, [len(f) for f in frames], size,
                               [zlib.crc32(r) for r in raws])

    assert bytes(read([len(r) for r in raws])) == b"".join(raws)
    for wrong in (7, 1 << 40, 1 << 62):
        with pytest.raises(ChunkError) as e:
            read([len(raws[0]), len(raws[1]), wrong, len(raws[3])])
        assert e.value.index == 2
    damaged = bytearray(buf)
    damaged[int(at[3]) + len(frames[3]) // 2] ^= 0x20
    with pytest.raises(ChunkError) as e:
        read([len(r) for r in raws], bytes(damaged))
    assert e.value.index == 3


@pytest.mark.parametrize("compiled", [True, False])
def test_read_chunks_takes_empty_lying_and_damaged_chunks(compiled, monkeypatch):
    """``read_chunks`` (the reader's hot path) by both paths (the compiled pass of ``drive.native``, and
    python-zstandard with the numpy walk): message records in zstd chunks (one empty) and an uncompressed one come
    back with their channels, times and payloads, only those asked for; a chunk whose record claims a wrong or an
    absurd size, whose bytes are damaged, or whose CRC is wrong is a ``ChunkError`` naming it."""
    import zlib

    import zstandard

    from fieldlog.drive import native
    from fieldlog.drive.chunks import ChunkError, read_chunks

    if not compiled:
        monkeypatch.setitem(native._state, "ok", False)
    rng = np.random.default_rng(5)

    def record(cid: int, t: int, payload: bytes) -> bytes:
        return struct.pack("<BQHIqq", 5, 22 + len(payload), cid, t, t, t + 1) + payload

    msgs = [(int(c), 1000 + i, rng.integers(0, 255, int(n), dtype=np.uint8).tobytes())
            for i, (c, n) in enumerate(zip(rng.integers(1, 4, 60), rng.integers(0, 400, 60)))]
    raws = [b"", *(b"".join(record(*m) for m in msgs[a:a + 20]) for a in (0, 20, 40))]
    comp = [0, 0, 0, 1]  # the last one uncompressed
    stored = [zstandard.ZstdCompressor().compress(r) for r in raws[:3]] + [raws[3]]
    at = np.cumsum([0] + [len(f) for f in stored])[:-1]
    buf = b"".join(stored)
    crc = [zlib.crc32(r) for r in raws]

    def read(size, data=buf, crcs=crc, want=(1, 3)):
        mask = np.zeros(1 << 16, bool)
        mask[list(want)] = True
        return read_chunks(data, ["zstd", ""], comp, at, [len(f) for f in stored], size, crcs, mask,
                           lambda a, b: (np.empty(a, np.uint8), np.empty(b, np.uint8)))

    cm, defs = read([len(r) for r in raws])
    kept = [m for m in msgs if m[0] in (1, 3)]
    assert defs == [] and cm.channel_id.tolist() == [m[0] for m in kept]
    assert cm.log_time.tolist() == [m[1] for m in kept] and cm.publish_time.tolist() == [m[1] + 1 for m in kept]
    assert list(cm.packed()) == [m[2] for m in kept]
    for k, wrong in ((2, 7), (1, len(raws[1]) + 1), (3, len(raws[3]) - 1), (2, 1 << 40), (1, 1 << 62)):
        size = [len(r) for r in raws]
        size[k] = wrong
        with pytest.raises(ChunkError) as e:
            read(size)
        assert e.value.index == k
    damaged = bytearray(buf)
    damaged[int(at[2]) + len(stored[2]) // 2] ^= 0x20
    with pytest.raises(ChunkError) as e:
        read([len(r) for r in raws], bytes(damaged))
    assert e.value.index == 2
    with pytest.raises(ChunkError, match="CRC") as e:
        read([len(r) for r in raws], crcs=[*crc[:3], crc[3] ^ 1])
    assert e.value.index == 3


def test_the_library_field_names_mcap_as_its_writer_would():
    """The header's library string spells mcap.writer's identifier without importing it (start-up time)."""
    from mcap.writer import LIBRARY_IDENTIFIER

    from fieldlog.drive import recorder

    assert recorder.LIBRARY == f"fieldlog/0.1 {LIBRARY_IDENTIFIER}"


def _mixed(path: Path, **kw) -> None:
    """Batches over several chunks, a channel and metadata records between them, single messages, a copied
    chunk."""
    n = 3000
    t = T0 + np.arange(n, dtype=np.int64) * DT
    w = np.random.default_rng(5).normal(size=(n, 3))
    with Recorder(path, chunk_size=48 * 1024, flush_interval_s=None, fsync=False, **kw) as rec:
        rec.write_batch("/imu", t[:1000], m.encode_imu(t[:1000], w[:1000], w[:1000]))
        rec.add_metadata("between", {"k": "v"})
        for i in range(1000, 1010):
            rec.write("/gps/nmea", int(t[i]), m.encode_sentence(int(t[i]), f"$GPGGA,{i}*00"))
        rec.flush()
        rec.write_batch("/imu", t[1000:], m.encode_imu(t[1000:], w[1000:], w[1000:]))
        rec.write_chunk(b"", int(t[-1]), int(t[-1]), {})
        rec.write("/raw/gps", int(t[-1]), m.encode_raw(int(t[-1]), 5, "gps", b"$GP\r\n"))


def test_behind_writes_the_same_bytes_and_raises_its_errors(tmp_path, monkeypatch):
    """``behind`` compresses on a thread: the file is the same to the byte, and an error there is raised by the
    owner's next call, not lost."""
    a, b = tmp_path / "a.mcap", tmp_path / "b.mcap"
    _mixed(a)
    _mixed(b, behind=True)
    assert a.read_bytes() == b.read_bytes()
    assert len(_all_messages(b)) == 3011
    rec = Recorder(tmp_path / "c.mcap", chunk_size=48 * 1024, flush_interval_s=None, fsync=False, behind=True)

    def broken(data: bytes) -> tuple[bytes, int]:
        raise MemoryError("no room to compress")

    monkeypatch.setattr(rec._file, "_compress", broken)
    rec.write("/gps/nmea", T0, m.encode_sentence(T0, "$GPGGA,1*00"))
    rec.flush()                           # submitted: the error comes with the next record
    with pytest.raises(MemoryError, match="no room"):
        rec.add_metadata("after", {"k": "v"})
    rec.close()


def test_behind_holds_several_chunks_and_raises_the_first_error(tmp_path, monkeypatch):
    """More closed chunks than ``BEHIND_CHUNKS`` in a row: the owner waits only for the oldest; a failed chunk
    among those in flight raises its own error (the first) at the next record, whatever the later ones do."""
    from fieldlog.drive import recorder

    rec = Recorder(tmp_path / "d.mcap", chunk_size=1024, flush_interval_s=None, fsync=False, behind=True)
    calls = []
    compress = rec._file._compress

    def second_fails(data: bytes) -> tuple[bytes, int]:
        calls.append(len(data))
        if len(calls) == 2:
            raise MemoryError("chunk 2")
        if len(calls) > 2:
            raise ValueError("a later chunk")
        return compress(data)

    monkeypatch.setattr(rec._file, "_compress", second_fails)
    n = 3 * recorder.BEHIND_CHUNKS
    t = T0 + np.arange(n, dtype=np.int64) * DT
    with pytest.raises((MemoryError, ValueError)) as raised:
        for i in range(n):        # a chunk a message; the owner meets an error once chunk 2 leaves the queue
            rec.write("/gps/nmea", int(t[i]), m.encode_sentence(int(t[i]), "$GPGGA," + "1" * 1100 + "*00"))
    assert raised.type is MemoryError
    rec.discard()
