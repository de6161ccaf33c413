"""Every valid MCAP layout and every multi-file drive reads as the same drive.

The corpus is written here by third-party writers from one simulated drive: the mcap library's ``Writer``
(``tools.dev.layouts``: unchunked, lz4, uncompressed, no summary/indexes/statistics, 4 KiB chunks; each with an
attachment and the metadata records) and rosbags (a rosbag2 directory, and one split into two files under one
metadata.yaml). Each must give the original's ``info`` counts and its
``kf`` solution (2D RMS against the truth within 1 mm). A rotated session (the daemon's ``RotatingSink``
fed by the real Pipeline, three files) must fuse to exactly the single file's solution, and every command
(allan, filter, recover included) takes it. ``recover`` keeps the messages outside chunks of a cut-short
unchunked file.
"""
from __future__ import annotations

import dataclasses
import heapq
import re
import shutil
import threading
import zlib
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from mcap.opcode import Opcode
from mcap.writer import Writer

from fieldlog.acquire.config import RecorderConfig
from fieldlog.acquire.daemon import RotatingSink
from fieldlog.acquire.pipeline import Pipeline, read_order
from fieldlog.drive import native
from fieldlog.drive.chunks import walk_records
from fieldlog.drive import reader
from fieldlog.drive.files import drive_files, open_drive
from fieldlog.drive.mcapfile import McapFile, TruncatedError, le
from fieldlog.tools.allan import drive_report
from fieldlog.tools.cli import main as fieldlog
from fieldlog.tools.evaluation.evaluate import outage_error_series
from fieldlog.tools.fuse import fuse
from fieldlog.tools.info import drive_info
from fieldlog.tools.dev.layouts import LAYOUTS, merged, rewrite, schema_of
from fieldlog.drive.reader import read_metadata_records
from fieldlog.tools.rebuild import iter_raw
from fieldlog.tools.sim.simulate import simulate

DURATION_S = 150.0


def corpus_topics(path: Path) -> list[str]:
    """What the third-party copies hold: everything but the raw bytes and the truth (scored from the original)."""
    return [t.topic for t in reader.topics(path) if not t.topic.startswith(("/raw/", "/truth/"))]


def write_with_rosbags(src: Path, dst: Path, parts: int = 1) -> Path:
    """``src`` as a rosbag2 directory written by rosbags. ``parts`` > 1: split as ``ros2 bag record
    --max-bag-size`` leaves it: rosbags writes each part (the messages cut into equal counts in log-time order),
    and the parts' files go into ``dst`` under one metadata.yaml listing them (``relative_file_paths``,
    ``files``, counts summed), rosbag2's format."""
    import yaml
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as BagWriter

    topics = corpus_topics(src)
    k, t, _, data = merged(src, topics)
    cuts = np.linspace(0, len(t), parts + 1).astype(int).tolist()
    bags = [dst] if parts == 1 else [dst.parent / f"{dst.name}.part{j}" for j in range(parts)]
    for bag, a, b in zip(bags, cuts, cuts[1:]):
        with BagWriter(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
            conns = []
            for topic in topics:
                s = schema_of(src, topic)
                conns.append(w.add_connection(topic, s.name, msgdef=s.data.decode(), rihs01="RIHS01_" + "0" * 64))
            for i, ti, d in zip(k[a:b].tolist(), t[a:b].tolist(), data[a:b]):
                w.write(conns[i], ti, d)
    if parts == 1:
        return dst
    dst.mkdir()
    infos = []
    for j, bag in enumerate(bags):
        info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        (bag / info["relative_file_paths"][0]).rename(dst / f"{dst.name}_{j}.mcap")
        info["files"][0]["path"] = f"{dst.name}_{j}.mcap"
        infos.append(info)
    out = infos[0]
    start = min(i["starting_time"]["nanoseconds_since_epoch"] for i in infos)
    end = max(i["starting_time"]["nanoseconds_since_epoch"] + i["duration"]["nanoseconds"] for i in infos)
    out.update(relative_file_paths=[f["path"] for i in infos for f in i["files"]],
               files=[f for i in infos for f in i["files"]], message_count=sum(i["message_count"] for i in infos),
               starting_time={"nanoseconds_since_epoch": start}, duration={"nanoseconds": end - start})
    for j, topic in enumerate(out["topics_with_message_count"]):
        topic["message_count"] = sum(i["topics_with_message_count"][j]["message_count"] for i in infos)
    (dst / "metadata.yaml").write_text(yaml.safe_dump({"rosbag2_bagfile_information": out}))
    return dst


def rotated_session(src: Path, out_dir: Path, files: int = 3) -> list[Path]:
    """``src``'s raw reads through the daemon's Pipeline and RotatingSink, rotating at ``files - 1`` read
    boundaries (as the daemon does by host time), into ``out_dir``."""
    records = read_metadata_records(src)
    cal, sync_cfg, pipe_cfg = Pipeline.settings_from_metadata(dict(records))
    pipe: Pipeline | None = None

    def headers(index: int, prev: Path | None) -> dict[str, dict[str, str]]:
        return {"drive": {"source": "test session", "file_index": str(index),
                          "previous_file": prev.name if prev else ""}, **pipe.metadata()}

    out_dir.mkdir()
    sink = RotatingSink(out_dir, 1_800_000_000_000_000_000, RecorderConfig(fsync=False), headers)
    pipe = Pipeline(sink, cal, sync_cfg, pipe_cfg)
    sink.open_next()
    reads = list(heapq.merge(iter_raw(src, "daq"), iter_raw(src, "gps"), key=lambda r: read_order(r.port, r.mono_ns)))
    cuts = {len(reads) * i // files for i in range(1, files)}
    for i, r in enumerate(reads):
        if i in cuts:
            sink.open_next({"acquire.counters": pipe.counters_metadata()})
        pipe.feed(r.port, r.mono_ns, r.wall_ns, r.data)
    pipe.finish()
    sink.close({"acquire.counters": pipe.counters_metadata()})
    return sink.files


@pytest.fixture(scope="module")
def original(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("layouts") / "figure8.mcap"
    simulate("figure8", DURATION_S, 3, path, pps_mode="latch")   # latch: a 30 s time-sync window, so /imu is in every file
    return path


@pytest.fixture(scope="module")
def corpus(original) -> dict[str, Path]:
    d = original.parent
    out = {name: rewrite(original, d / f"{name}.mcap", name, corpus_topics(original)) for name in LAYOUTS}
    out["rosbag2"] = write_with_rosbags(original, d / "rosbag2")
    out["rosbag2-split"] = write_with_rosbags(original, d / "rosbag2-split", parts=2)
    return out


def rms_2d(drive: Path, fused: Path) -> float:
    t = [(x.first_ns, x.last_ns + 1) for x in reader.topics(drive) if x.topic == "/imu"]
    _, err = outage_error_series(drive, fused, "kf", t)
    return float(np.hypot(np.sqrt(np.mean(err[:, 0] ** 2)), np.sqrt(np.mean(err[:, 1] ** 2))))


@pytest.fixture(scope="module")
def kf_original(original) -> tuple[Path, float]:
    out = original.parent / "kf_original.mcap"
    assert fuse(original, "kf", out).rows > 0
    return out, rms_2d(original, out)


def test_the_corpus_has_the_layouts_it_claims(corpus):
    files = {name: open_drive(p) for name, p in corpus.items()}
    assert not files["unchunked"][0].pieces.chunk.any()           # every message outside chunks
    p = files["no-summary"][0].pieces
    assert p.chunk.all() and not p.indexed.any()                  # no message indexes
    raw = corpus["no-summary"].read_bytes()
    assert raw[-37] == 0x02 and int.from_bytes(raw[-28:-20], "little") == 0    # a footer, and no summary section
    assert len(files["chunks-4k"][0].pieces) > 100 * len(files["lz4"][0].pieces)
    assert [f.path.suffix for f in files["rosbag2"]] == [".mcap"]
    assert (corpus["rosbag2"] / "metadata.yaml").is_file()
    split = files["rosbag2-split"]
    assert len(split) == 2 and split[0].channel_stats() and split[1].channel_stats()   # messages in both files
    assert split[0].pieces.end_ns.max() < split[1].pieces.start_ns.min()


def _layout(path: Path) -> tuple:
    """What ``McapFile`` found in ``path``: whether from the summary, and its tables as comparable values."""
    f = McapFile(path)
    p = f.pieces
    return f.from_summary, ([getattr(p, x.name).tolist() for x in dataclasses.fields(p)], f.compressions, f.channels,
                            f.schemas, f.metadata(), f.message_counts())


def _summary(path: Path) -> tuple[bytearray, int]:
    """The bytes of ``path`` and the offset of its footer record."""
    raw = bytearray(path.read_bytes())
    return raw, len(raw) - 8 - 29


@pytest.mark.parametrize("layout", ["original", *LAYOUTS])
def test_the_summary_gives_the_walks_table_and_a_bad_summary_falls_back(layout, original, corpus, tmp_path):
    """Files whose summary lists their chunks get their table from the chunk indexes, the same table the walk
    of every record gives: a copy whose footer CRC does not match its summary, and one with a chunk index
    pointing off its chunk (no CRC to catch it), are walked and read the same."""
    src = original if layout == "original" else corpus[layout]
    from_summary, table = _layout(src)
    assert from_summary == (layout not in ("unchunked", "no-summary"))   # no chunk indexes: walked
    if not from_summary:
        return
    raw, foot = _summary(src)
    assert raw[foot + 25:foot + 29] != bytes(4)                          # the writer gave the summary a CRC
    raw[foot + 25] ^= 0x01
    bad_crc = tmp_path / "bad_crc.mcap"
    bad_crc.write_bytes(raw)
    raw[foot + 25:foot + 29] = bytes(4)                                  # no CRC, and a chunk index off by one
    start = int.from_bytes(raw[foot + 9:foot + 17], "little")
    ops, starts, _, _ = walk_records(np.frombuffer(bytes(raw), np.uint8), start, 64)
    at = int(starts[np.flatnonzero(ops == Opcode.CHUNK_INDEX)[0]]) + 16
    raw[at:at + 8] = (int.from_bytes(raw[at:at + 8], "little") + 1).to_bytes(8, "little")
    bad_index = tmp_path / "bad_index.mcap"
    bad_index.write_bytes(raw)
    for bad in (bad_crc, bad_index):
        assert _layout(bad) == (False, table)
        assert len(reader.read_topic(bad, "/imu")["log_time_ns"]) == len(reader.read_topic(src, "/imu")["log_time_ns"])


def test_messages_outside_chunks_beside_a_summary_are_read(original, tmp_path):
    """The mcap Writer's chunked file with runs of messages written outside its chunks (valid MCAP; its summary
    lists only the chunks, its statistics count every message): the file is walked and every message read."""
    topics = ["/imu", "/gps/fix"]
    k, t, pub, data = merged(original, topics)
    path = tmp_path / "mixed.mcap"
    with open(path, "wb") as out:
        w = Writer(out)
        w.start("ros2", "mcap python Writer, some messages outside chunks")
        cids = [w.register_channel(x, "cdr", w.register_schema((s := schema_of(original, x)).name, s.encoding,
                                                                  s.data)) for x in topics]
        builder = w._Writer__chunk_builder
        for j, (i, ti, pi, d) in enumerate(zip(k.tolist(), t.tolist(), pub.tolist(), data)):
            loose = j % 20_000 < 300
            if loose:  # the Writer has no option for it: its chunk closed, its chunk builder set aside
                w._Writer__finalize_chunk()
                w._Writer__chunk_builder = None
            w.add_message(cids[i], ti, d, pi)
            w._Writer__chunk_builder = builder
        w.finish()
    f = McapFile(path)
    assert not f.from_summary and (~f.pieces.chunk).sum() >= 3 and f.pieces.chunk.sum() >= 3
    for i, topic in enumerate(topics):
        assert np.array_equal(np.sort(reader.read_topic(path, topic)["log_time_ns"]), np.sort(t[k == i]))


def test_the_split_rosbag2_directory_is_one_bag_to_rosbags(corpus):
    """rosbags' own Reader takes the combined directory as one bag of two files and all the messages (so its
    metadata.yaml is rosbag2's format), with fieldlog's counts per topic."""
    from rosbags.rosbag2 import Reader

    with Reader(corpus["rosbag2-split"]) as bag:
        assert len(bag.storage.storages) == 2
        got: dict[str, int] = {}
        for c, _, _ in bag.messages():
            got[c.topic] = got.get(c.topic, 0) + 1
        assert sum(got.values()) == bag.message_count
    assert got == {t.topic: t.count for t in reader.topics(corpus["rosbag2-split"])}


@pytest.mark.parametrize("layout", [*LAYOUTS, "rosbag2", "rosbag2-split"])
def test_every_layout_has_the_original_counts_and_kf_solution(layout, original, corpus, kf_original, tmp_path):
    path = corpus[layout]
    want = {t.topic: (t.type, t.count, t.first_ns, t.last_ns) for t in reader.topics(original)}
    got = {t.topic: (t.type, t.count, t.first_ns, t.last_ns) for t in reader.topics(path)}
    assert got == {k: want[k] for k in corpus_topics(original)}
    assert {t.topic: (t.type, t.count) for t in reader.topic_counts(path)} == {k: v[:2] for k, v in got.items()}
    for k, (*_, first, last) in got.items():  # the layout's span holds the topic's messages
        lo, hi = reader.span(path, [k])
        assert lo <= first <= last <= hi
    a, b = drive_info(original), drive_info(path)
    assert (b.imu_gaps, b.gps_missing_epochs, b.gps_no_fix, b.sync_states) == \
        (a.imu_gaps, a.gps_missing_epochs, a.gps_no_fix, a.sync_states)
    assert b.drive == a.drive and b.counters == a.counters or layout.startswith("rosbag2")  # rosbags: no metadata
    out = tmp_path / "kf.mcap"
    assert fuse(path, "kf", out).rows > 0
    ref_path, ref_rms = kf_original
    assert abs(rms_2d(original, out) - ref_rms) < 1e-3
    x, y = reader.read_topic(ref_path, "/fusion/kf/fix"), reader.read_topic(out, "/fusion/kf/fix")
    assert np.array_equal(x["log_time_ns"], y["log_time_ns"]) and np.allclose(x["lat_deg"], y["lat_deg"], atol=1e-12)


@pytest.fixture(scope="module")
def session(original) -> Path:
    """``original`` as a rotated session of three files."""
    out = original.parent / "session"
    rotated_session(original, out)
    return out


def test_a_rotated_session_fuses_as_one_drive(original, kf_original, session, tmp_path):
    files = sorted(session.glob("*.mcap"))
    assert len(files) == 3 and drive_files(session) == files
    spans = [(f.pieces.start_ns.min(), f.pieces.end_ns.max()) for f in open_drive(files)]
    assert spans[0][1] > spans[1][0]            # /imu lags /raw: the files overlap in log time
    assert reader.read_topic(session, "/imu")["log_time_ns"].tolist() == \
        reader.read_topic(original, "/imu")["log_time_ns"].tolist()
    info = drive_info(session)
    want = {t.topic: t.count for t in reader.topics(original) if not t.topic.startswith("/truth/")}
    got = {t.topic: t.count for t in info.topics}
    assert got.pop("/tf_static", 0) == 3 * want.pop("/tf_static", 0)     # latched: once in every file
    assert len(info.files) == 3 and got == want
    out = tmp_path / "kf.mcap"
    assert fieldlog(["fuse", *map(str, files), "--method", "kf", "--out", str(out)]) == 0
    assert fieldlog(["fuse", str(original), "--method", "kf", "--out", str(tmp_path / "one.mcap")]) == 0
    ref = reader.read_topic(tmp_path / "one.mcap", "/fusion/kf/fix")   # the same command on the one file
    got = reader.read_topic(out, "/fusion/kf/fix")
    assert np.array_equal(ref["log_time_ns"], got["log_time_ns"])          # no re-alignment at the boundaries
    for k in ("lat_deg", "lon_deg", "alt_m"):
        assert np.array_equal(ref[k], got[k])
    # the second file alone starts over: it aligns again, so it has fewer solutions over its own span
    alone = tmp_path / "second.mcap"
    n_alone = fuse(files[1], "kf", alone).rows
    imu = reader.read_topic(files[1], "/imu")["log_time_ns"]
    t = got["log_time_ns"]
    assert n_alone < np.count_nonzero((t >= imu[0]) & (t <= imu[-1]))


@pytest.mark.slow
def test_every_command_takes_the_session(original, session, tmp_path):
    """rebuild, export, view, replay, evaluate and batch read the three files as the one drive."""
    files = [str(f) for f in sorted(session.glob("*.mcap"))]
    imu = reader.read_topic(original, "/imu")
    assert fieldlog(["rebuild", str(session), "--out", str(tmp_path / "rebuilt.mcap")]) == 0
    rebuilt = reader.read_topic(tmp_path / "rebuilt.mcap", "/imu")          # the same reads through the pipeline
    assert np.array_equal(rebuilt["log_time_ns"], imu["log_time_ns"]) and np.array_equal(rebuilt["f_b"], imu["f_b"])
    assert fieldlog(["export", *files, "--out", str(tmp_path / "tables"), "--topics", "/imu,/raw/gps"]) == 0
    import polars as pl

    assert pl.read_parquet(tmp_path / "tables" / "imu.parquet")["log_time_ns"].to_list() == \
        imu["log_time_ns"].tolist()
    kf = tmp_path / "kf.mcap"
    assert fuse(session, "kf", kf).rows > 0
    assert fieldlog(["view", *files, str(kf), "--rrd", str(tmp_path / "v.rrd")]) == 0      # files, then fused
    assert fieldlog(["replay", str(session), "--speed", "0", "--rrd", str(tmp_path / "r.rrd")]) == 0
    assert fieldlog(["evaluate", str(session), "--outages", "10", "--methods", "kf",
                     "--report", str(tmp_path / "report")]) == 0
    assert fieldlog(["batch", str(session), "--methods", "kf", "--workers", "1", "--out", str(tmp_path / "b")]) == 0
    table = pl.read_parquet(tmp_path / "b" / "results.parquet")
    assert table["status"].to_list() == ["ok"] and table["solutions"][0] == fuse(original, "kf", tmp_path / "o.mcap").rows


def test_truncated_is_told_apart_from_unindexed(corpus, tmp_path, capsys):
    raw = corpus["no-summary"].read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(raw[: len(raw) // 2])
    with pytest.raises(TruncatedError):
        reader.topics(cut)
    assert fieldlog(["info", str(cut)]) == 2
    err = capsys.readouterr().err
    assert "fieldlog recover" in err and len(err.strip().splitlines()) == 1
    # a session directory: the recovered copy stands in for the cut-short original next to it
    d = tmp_path / "session"
    d.mkdir()
    shutil.copy(cut, d / "s_0001.mcap")
    shutil.copy(corpus["lz4"], d / "s_0001.recovered.mcap")
    assert drive_files(d) == [d / "s_0001.recovered.mcap"]


def _damaged(src, tmp_path, k: int):
    """A copy of src with one byte flipped inside the chunk 1/k of the way through those holding /imu:
    (the copy, src's McapFile, the chunk's piece index)."""
    (f,) = open_drive(src)
    p = f.pieces
    imu = {c for c, ch in f.channels.items() if ch.topic == "/imu"}
    held = np.flatnonzero(p.chunk & f.may_hold(imu))
    i = int(held[len(held) // k])
    assert p.crc[i] != 0                                          # the writer gave the chunk a CRC
    raw = bytearray(src.read_bytes())
    raw[int(p.body[i] + p.body_len[i] // 2)] ^= 0x55
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(raw)
    return bad, f, i


@pytest.fixture(params=["compiled", "numpy"])
def read_path(request, monkeypatch) -> str:
    """The reader's two paths for chunks: ``drive.native``'s compiled pass (zstd, uncompressed), or
    python-zstandard and the walk (what runs when zstandard exports no C API, and for lz4)."""
    if request.param == "numpy":
        monkeypatch.setitem(native._state, "ok", False)
    else:
        assert native.ready()
    return request.param


@pytest.mark.parametrize("layout", ["original", *LAYOUTS])
def test_the_compiled_read_equals_the_numpy_read(layout, original, corpus, monkeypatch):
    """Every group of pieces of every layout (channels defined inside chunks in ``no-summary``; messages outside
    chunks in ``unchunked``), read whole and for a few topics, gives the same messages by both paths: channel,
    log and publish time, and payload bytes."""
    src = original if layout == "original" else corpus[layout]

    def batches() -> list:
        f = McapFile(src)  # a new one: the channels defined inside chunks are found again
        out = []
        for topics in (None, ["/imu", "/gps/fix", "/tf_static"]):
            for g in f.groups(np.arange(len(f.pieces)), f.pieces.size):
                cm = f.read(g, topics)
                p = cm.packed()
                out.append((cm.channel_id.copy(), cm.log_time.copy(), cm.publish_time.copy(), p.buf.copy(),
                            p.offsets.copy()))
        return out

    compiled = batches()
    monkeypatch.setitem(native._state, "ok", False)
    numpy_path = batches()
    assert len(compiled) == len(numpy_path) > 0
    for a, b in zip(compiled, numpy_path):
        for x, y in zip(a, b):
            np.testing.assert_array_equal(x, y)
    assert sum(len(a[0]) for a in compiled) > 0


@pytest.mark.parametrize("layout", ["original", *LAYOUTS, "rosbag2-split"])
def test_one_pass_reads_give_what_the_topic_reads_give(layout, original, corpus):
    """``read_topics`` (several topics in one pass) decodes each topic as ``read_topic`` does, and a topic
    ``iter_blocks`` leaves undecoded comes back, block after block, as ``read_payloads`` reads it, in every layout
    (channels defined inside chunks, messages outside chunks, a drive of several files); a topic the drive does
    not have is left out."""
    src = original if layout == "original" else corpus[layout]
    topics = ["/imu", "/gps/fix", "/gps/nmea", "/tf_static", "/no/such/topic"]
    got = reader.read_topics(src, topics)
    assert sorted(got) == sorted(topics[:-1])
    for topic in topics[:-1]:
        one = reader.read_topic(src, topic)
        assert sorted(got[topic]) == sorted(one) and len(one["log_time_ns"]) > 0
        for key, x in one.items():
            if key == "msgs":
                assert got[topic][key] == x
            else:
                np.testing.assert_array_equal(got[topic][key], x)
    blocks = list(reader.iter_blocks(src, ["/imu", "/gps/nmea"], 7.0, undecoded=("/gps/nmea",)))
    t, _, p = reader.read_payloads(src, "/gps/nmea")
    rows = [b.data["/gps/nmea"] for b in blocks if "/gps/nmea" in b.data]
    assert np.array_equal(np.concatenate([r["log_time_ns"] for r in rows]), t)
    assert [bytes(x) for r in rows for x in r["payloads"]] == [bytes(x) for x in p]
    assert all("payloads" not in b.data["/imu"] for b in blocks)


@pytest.mark.parametrize("layout", ["original", *LAYOUTS, "rosbag2-split"])
def test_blocks_decode_what_the_topic_read_decodes(layout, original, corpus):
    """The decoded topics of ``iter_blocks`` (decoded as their pieces are read) join, block after block, into what
    ``read_topic`` decodes, in every layout and at any block length; with ``fields`` each block has those keys
    alone, the same values, as contiguous arrays."""
    src = original if layout == "original" else corpus[layout]
    keys = ("stamp_ns", "f_b", "valid")
    for block_s, fields in ((7.0, None), (0.3, {"/imu": keys})):
        blocks = list(reader.iter_blocks(src, ["/imu", "/gps/fix"], block_s, fields=fields))
        for topic in ("/imu", "/gps/fix"):
            one = reader.read_topic(src, topic)
            rows = [b.data[topic] for b in blocks if topic in b.data]
            kept = keys if fields and topic in fields else tuple(one)
            assert all(set(r) == {"log_time_ns", *kept} for r in rows)
            assert all(v.flags.c_contiguous for r in rows for v in r.values())
            for key in ("log_time_ns", *kept):
                np.testing.assert_array_equal(np.concatenate([r[key] for r in rows]), one[key])


def test_threads_reading_at_once_read_what_one_reads(original, corpus):
    """The compiled read releases the GIL: two threads reading the 4 KiB-chunk file at once (each with its own
    zstd context and buffers) get the messages one thread gets."""
    import concurrent.futures

    def read() -> list:
        f = McapFile(corpus["chunks-4k"])
        out = []
        for g in f.groups(np.arange(len(f.pieces)), f.pieces.size):
            cm = f.read(g, ["/imu", "/gps/fix"])
            out.append((cm.log_time.copy(), cm.packed().buf.copy()))
        return out

    assert native.ready()
    one = read()
    with concurrent.futures.ThreadPoolExecutor(2) as pool:
        both = [job.result() for job in [pool.submit(read) for _ in range(2)]]
    for got in both:
        assert len(got) == len(one) > 1
        for (t, b), (t1, b1) in zip(got, one):
            np.testing.assert_array_equal(t, t1)
            np.testing.assert_array_equal(b, b1)


@pytest.mark.parametrize("layout", ["original", "chunks-4k", "lz4", "uncompressed"])
def test_a_damaged_chunk_is_reported_never_read(layout, read_path, original, corpus, tmp_path, capsys):
    """One byte flipped inside a chunk holding /imu (zstd, 4 KiB zstd, lz4, uncompressed; both read paths):
    reading the topic fails naming the file and the chunk's byte offset (its CRC-32, or the codec, catches it),
    and a command reading it (``allan``) says so in one line with exit code 2; no wrong data comes back."""
    src = original if layout == "original" else corpus[layout]
    bad, f, i = _damaged(src, tmp_path, 2)
    p = f.pieces
    with pytest.raises(ValueError, match=re.escape(f"{bad}: damaged chunk at byte {int(p.offset[i])}: chunk ")):
        reader.read_topic(bad, "/imu")
    assert fieldlog(["allan", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{bad}: damaged chunk at byte {int(p.offset[i])}" in err[0], err
    threads = threading.active_count()  # the block reader reads ahead on a thread: the error still comes here
    with pytest.raises(ValueError, match=re.escape(f"{bad}: damaged chunk at byte {int(p.offset[i])}: chunk ")):
        list(reader.iter_blocks(bad, ["/imu"], 1.0))
    assert threading.active_count() == threads


@pytest.mark.parametrize("cpus", [1, 2])
def test_a_block_read_left_early_leaves_no_thread(original, cpus, monkeypatch):
    """The block reader's read-ahead thread (with a second CPU; none with one) ends with the read: read to its
    end, or closed after one block; the blocks are the same either way."""
    monkeypatch.setattr(reader, "cpus", lambda: cpus)
    threads = threading.active_count()
    blocks = reader.iter_blocks(original, ["/imu", "/gps/fix"], 1.0)
    first = next(blocks)
    assert len(first.data["/imu"]["log_time_ns"]) and threading.active_count() == threads + (cpus > 1)
    blocks.close()
    assert threading.active_count() == threads
    got = list(reader.iter_blocks(original, ["/imu"], 5.0))
    assert len(got) > 1 and threading.active_count() == threads
    np.testing.assert_array_equal(np.concatenate([b.data["/imu"]["f_b"] for b in got]),
                                  reader.read_topic(original, "/imu")["f_b"])


def test_a_bad_record_inside_a_chunk_is_one_line(read_path, corpus, tmp_path, capsys):
    """A channel record inside a chunk (the mcap library's Writer puts them there) whose topic length runs past
    it, the chunk's CRC made to match (a writer's bug, not damage on the way): reading names the file and the
    chunk (both read paths), and a command says so in one line, exit code 2."""
    src = corpus["uncompressed"]
    f = McapFile(src)
    p = f.pieces
    for i in np.flatnonzero(p.chunk).tolist():
        ops, starts, _, _ = walk_records(np.frombuffer(f.records(i), np.uint8), 0, 64)
        if (ops == Opcode.CHANNEL).any():
            break
    raw = bytearray(src.read_bytes())
    topic_len = int(p.body[i]) + int(starts[np.argmax(ops == Opcode.CHANNEL)]) + 4  # after id and schema id
    raw[topic_len:topic_len + 4] = (1 << 30).to_bytes(4, "little")
    body = bytes(raw[int(p.body[i]):int(p.body[i] + p.body_len[i])])
    raw[int(p.offset[i]) + 9 + 24:int(p.offset[i]) + 9 + 28] = zlib.crc32(body).to_bytes(4, "little")
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(raw)
    with pytest.raises(ValueError, match=re.escape(f"{bad}: a damaged channel record inside the chunks from byte")):
        reader.read_topic(bad, "/imu")
    assert fieldlog(["allan", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{bad}: a damaged channel record" in err[0], err


@pytest.mark.parametrize("layout", ["original", "chunks-4k"])
def test_recover_skips_a_damaged_chunk_and_keeps_every_other(layout, original, corpus, tmp_path, capsys):
    """A complete file with one damaged chunk in the middle: ``recover`` keeps every other chunk (not only
    those before the damaged one), names the chunk's byte offset, and the result reads."""
    src = original if layout == "original" else corpus[layout]
    bad, f, i = _damaged(src, tmp_path, 3)
    p = f.pieces
    lost = f.read([i])
    out = tmp_path / "fixed.mcap"
    assert fieldlog(["recover", str(bad), "--out", str(out)]) == 0
    assert f"1 damaged chunk skipped, at byte {int(p.offset[i])}" in capsys.readouterr().out
    before = {t.topic: t.count for t in reader.topics(src)}
    gone = {f.channels[int(c)].topic: int(n) for c, n in zip(*np.unique(lost.channel_id, return_counts=True))}
    after = {t.topic: t.count for t in reader.topics(out)}
    assert gone["/imu"] > 0
    assert after == {k: v - gone.get(k, 0) for k, v in before.items() if v - gone.get(k, 0)}
    t = reader.read_topic(out, "/imu")["log_time_ns"]
    assert t[-1] == reader.read_topic(src, "/imu")["log_time_ns"][-1]  # the drive's end is there


@pytest.mark.parametrize("layout", ["original", "lz4"])
def test_a_damaged_or_cut_summary_is_left_out(layout, original, corpus, tmp_path):
    """The data section is whole, the summary is not: a byte flipped in the summary's schema and channel copies
    (footer CRC zeroed, so nothing catches it), or the file cut inside the summary; our recorder's file and the
    mcap library Writer's. Both read as the original (no decoding error, no "cut short, run recover")."""
    import struct

    src = original if layout == "original" else corpus[layout]
    data = src.read_bytes()
    foot = len(data) - 8 - 29
    start = struct.unpack_from("<Q", data, foot + 9)[0]
    want = reader.read_topic(src, "/imu")["log_time_ns"]
    cases = {}
    for k in range(0, 400, 40):   # the first records of the summary: schemas, channels
        d = bytearray(data)
        d[start + k] ^= 0xFF
        struct.pack_into("<I", d, foot + 25, 0)
        cases[f"flip{k}"] = bytes(d)
    cases["cut"] = data[: start + (foot - start) // 2]
    for name, d in cases.items():
        p = tmp_path / f"{name}.mcap"
        p.write_bytes(d)
        assert np.array_equal(reader.read_topic(p, "/imu")["log_time_ns"], want), name
        assert {t.topic for t in reader.topics(p)} == {t.topic for t in reader.topics(src)}, name


def test_allan_and_filter_take_the_session(original, session, tmp_path):
    """allan and filter read the three files as the one drive: allan gives the single file's report, filter the
    single file's slice (the same messages, byte for byte)."""
    files = [str(f) for f in sorted(session.glob("*.mcap"))]
    assert drive_report(files) == drive_report(original)
    imu = reader.read_topic(original, "/imu")["log_time_ns"]
    t0, t1 = str(imu[len(imu) // 5]), str(imu[4 * len(imu) // 5])     # across both file boundaries
    for name, drive in (("one", [str(original)]), ("session", files)):
        assert fieldlog(["filter", *drive, "--start", t0, "--end", t1, "--topics", "/imu,/gps/*",
                         "--out", str(tmp_path / f"{name}.mcap")]) == 0
    one, many = tmp_path / "one.mcap", tmp_path / "session.mcap"
    counts = {t.topic: t.count for t in reader.topics(one)}
    assert counts["/imu"] == np.count_nonzero((imu >= int(t0)) & (imu < int(t1)))
    got = {t.topic: t.count for t in reader.topics(many)}
    assert got.pop("/tf_static") == 3 * counts.pop("/tf_static") and got == counts   # /tf_static: once per file
    for topic in ("/imu", "/gps/fix", "/gps/vel"):
        a, b = reader.read_payloads(one, topic), reader.read_payloads(many, topic)
        assert np.array_equal(a[0], b[0]) and a[2].to_list() == b[2].to_list()


def test_recover_takes_a_session_directory(session, tmp_path, capsys):
    """A session whose last file was cut short: ``recover DIR`` recovers that file next to it and leaves the
    complete ones; the directory then reads as a drive, and a second run has nothing to do."""
    d = tmp_path / "cut"
    shutil.copytree(session, d)
    last = sorted(d.glob("*.mcap"))[-1]
    last.write_bytes(last.read_bytes()[: last.stat().st_size * 2 // 3])
    assert fieldlog(["info", str(d)]) == 2
    capsys.readouterr()
    assert fieldlog(["recover", str(d)]) == 0
    out = capsys.readouterr().out
    assert out.count("complete, nothing to recover") == 2 and f"wrote {last.with_name(last.stem + '.recovered.mcap')}" in out
    assert drive_files(d)[-1].name.endswith(".recovered.mcap")
    full = {t.topic: t.count for t in reader.topics(session)}
    got = {t.topic: t.count for t in reader.topics(d)}
    first_two = sum(next(t.count for t in reader.topics(f) if t.topic == "/imu") for f in drive_files(d)[:2])
    assert 0 < got["/raw/daq"] < full["/raw/daq"] and first_two < got["/imu"] <= full["/imu"]
    assert fieldlog(["recover", str(d)]) == 0
    assert capsys.readouterr().out.count("recovered already") == 1
    assert fieldlog(["recover", str(d), "--out", str(tmp_path / "x.mcap")]) == 2


def test_recover_takes_a_directory_with_a_damaged_chunk(corpus, session, tmp_path, capsys):
    """A complete file with one byte flipped inside a chunk holding /imu: the middle file of a rotated session, and
    the mcap library Writer's lz4 copy alone in a directory. ``recover DIR`` (it said "complete, nothing to
    recover") checks every chunk, recovers that file next to it naming the chunk's byte offset, leaves the sound
    ones, and the directory then reads as the drive without that chunk's /imu messages (counted from the
    message indexes); a sound directory has nothing to recover, and a second run nothing to do."""
    d = tmp_path / "session"
    shutil.copytree(session, d)
    assert fieldlog(["recover", str(d)]) == 0
    assert capsys.readouterr().out.count("complete, nothing to recover") == 3 and len(list(d.glob("*.mcap"))) == 3
    mid = sorted(d.glob("*.mcap"))[1]
    (tmp_path / "lz4").mkdir()
    for dst, src, sound in ((mid, mid, 2), (tmp_path / "lz4" / "lz4.mcap", corpus["lz4"], 0)):
        want = reader.read_topic(dst.parent if dst == mid else src, "/imu")["log_time_ns"]
        bad, f, i = _damaged(src, tmp_path, 2)
        bad.replace(dst)
        owner, cid, _, n = f._index
        imu = [c for c, ch in f.channels.items() if ch.topic == "/imu"]
        gone = int(n[(owner == i) & np.isin(cid, imu)].sum())
        assert gone > 0
        assert fieldlog(["recover", str(dst.parent)]) == 0
        out = capsys.readouterr().out
        at = int(f.pieces.offset[i])
        fixed = dst.with_name(dst.stem + ".recovered.mcap")
        assert f"{dst}: damaged chunk at byte {at}" in out and f"1 damaged chunk skipped, at byte {at}" in out
        assert f"wrote {fixed}" in out and out.count("complete, nothing to recover") == sound
        assert fixed in drive_files(dst.parent) and dst not in drive_files(dst.parent)
        got = reader.read_topic(dst.parent, "/imu")["log_time_ns"]
        assert len(got) == len(want) - gone and np.isin(got, want).all()
        assert fieldlog(["recover", str(dst.parent)]) == 0
        assert capsys.readouterr().out.count("recovered already") == 1


def test_recover_rederives_the_tail_of_a_complete_file_whose_walk_stops(session, tmp_path):
    """``recover`` copies a complete file's chunks without feeding the pipeline (it has no tail to re-derive) only
    when its walk reaches the data end: a session file with its footer but a chunk record's length damaged mid-file
    stops the walk there, so the tail is re-derived as for a cut-short file (the very file ``TailDeriver`` gives)."""
    import filecmp
    import struct

    from fieldlog.acquire.recovery import TailDeriver, recover, recover_drive

    src = sorted(session.glob("*.mcap"))[1]
    p = McapFile(src).pieces
    raw = bytearray(src.read_bytes())
    struct.pack_into("<Q", raw, int(p.offset[np.flatnonzero(p.chunk)[int(p.chunk.sum()) // 2]]) + 1, 1 << 60)
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(raw)
    rep = recover_drive(bad, tmp_path / "a.mcap")
    recover(bad, tmp_path / "b.mcap", TailDeriver())
    assert not rep.had_summary and rep.rederived.get("/imu", 0) > 0
    assert filecmp.cmp(tmp_path / "a.mcap", tmp_path / "b.mcap", shallow=False)


def test_recover_keeps_messages_outside_chunks(original, corpus, tmp_path):
    """An unchunked file (mcap's Writer) cut short: recover keeps every message whose record is whole before the
    cut, found here by the record walk of the complete file."""
    raw = corpus["unchunked"].read_bytes()
    cut = len(raw) * 2 // 3
    src = tmp_path / "cut.mcap"
    src.write_bytes(raw[:cut])
    assert fieldlog(["recover", str(src)]) == 0
    buf = np.frombuffer(raw, np.uint8)
    ops, starts, lengths, _ = walk_records(buf, 8, len(buf) // 64)
    whole = (ops == Opcode.MESSAGE) & (starts + lengths <= cut)
    (f,) = open_drive(corpus["unchunked"])
    want = Counter(f.channels[c].topic for c in le(buf, starts[whole], "<u2").tolist())
    got = {t.topic: t.count for t in reader.topics(tmp_path / "cut.recovered.mcap") if t.count}
    assert got == dict(want) and 0 < sum(want.values()) < np.count_nonzero(ops == Opcode.MESSAGE)
    a = reader.read_payloads(original, "/imu")
    b = reader.read_payloads(tmp_path / "cut.recovered.mcap", "/imu")
    n = len(b[0])
    assert np.array_equal(a[0][:n], b[0]) and a[2].take(np.arange(n)).to_list() == b[2].to_list()
