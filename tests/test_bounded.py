"""Every read is bounded: a chunk that claims, or holds, more than the chunk limit is refused as damaged and named
by its byte offset, by every command, in bounded memory; ``recover`` skips it and keeps the rest, and writes
about its input's size plus the re-derived tail."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import zstandard
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import Chunk, DataEnd, Footer, Metadata, MessageIndex
from mcap.stream_reader import StreamReader

from fieldlog.acquire import recovery
from fieldlog.drive import chunks, recorder
from fieldlog.drive.drivestats import RECORD as INFO_RECORD
from fieldlog.drive import reader
from fieldlog.tools.sim import simulate
from test_serve import ROOT

GiB = 1 << 30
MEMORY_LIMIT = 1 << 30          # bytes of peak RSS any command may take on these files


def bomb_chunk(channel_id: int, log_time_ns: int, payload: int, claimed: int | None, content_size: bool) -> Chunk:
    """A chunk holding one message of ``payload`` zero bytes, zstd-compressed as a stream (``content_size``: the
    frame header says how long it is); the record claims ``claimed`` bytes uncompressed (None: the truth)."""
    head = np.zeros(1, recorder._MSG_HDR)
    head["op"], head["length"], head["channel"] = Opcode.MESSAGE, 22 + payload, channel_id
    head["log_time"] = head["publish_time"] = log_time_ns
    total = 31 + payload
    z = zstandard.ZstdCompressor(level=1).compressobj(size=total if content_size else -1)
    parts, zero = [z.compress(head.tobytes())], bytes(16 << 20)
    left = payload
    while left:
        parts.append(z.compress(zero[:min(left, len(zero))]))
        left -= min(left, len(zero))
    parts.append(z.flush())
    return Chunk(message_start_time=log_time_ns, message_end_time=log_time_ns, uncompressed_size=claimed or total,
                 uncompressed_crc=0, compression="zstd", data=b"".join(parts))


def with_bomb(src: Path, dst: Path, bomb: Chunk) -> int:
    """``src``'s data section with ``bomb`` after its first chunk, without message indexes, summary and the
    ``fieldlog.info`` record (so every reader has to open the chunks); returns the bomb's byte offset."""
    rb = RecordBuilder()
    at, chunks = 0, 0
    with open(src, "rb") as f:
        for r in StreamReader(f, emit_chunks=True).records:
            if isinstance(r, (MessageIndex, DataEnd)) or (isinstance(r, Metadata) and r.name == INFO_RECORD):
                if isinstance(r, DataEnd):
                    break
                continue
            r.write(rb)
            if isinstance(r, Chunk):
                chunks += 1
                if chunks == 1:
                    at = len(recorder.MAGIC) + rb.count
                    bomb.write(rb)
    assert at > 0
    DataEnd(0).write(rb)
    Footer(0, 0, 0).write(rb)
    dst.write_bytes(recorder.MAGIC + rb.end() + recorder.MAGIC)
    return at


@pytest.fixture(scope="module")
def bombs(tmp_path_factory) -> dict[str, tuple[Path, int]]:
    d = tmp_path_factory.mktemp("bombs")
    base = d / "base.mcap"
    simulate.simulate("figure8", 6.0, 3, base)
    (raw,) = [t for t in reader.topics(base) if t.topic == "/raw/daq"]
    f = next(iter(reader.open_drive(base)))
    cid = next(c for c, ch in f.channels.items() if ch.topic == "/raw/daq")
    t = raw.first_ns + 1
    out = {}
    for name, payload, claimed, content_size in [("honest", 3 * GiB, None, False),
                                                 ("lying", 3 * GiB, 4096, True),
                                                 ("lying-stream", 3 * GiB, 4096, False)]:
        path = d / f"{name}.mcap"
        out[name] = (path, with_bomb(base, path, bomb_chunk(cid, t, payload, claimed, content_size)))
    out["base"] = (base, 0)
    return out


def peak_run(*args: str, env: dict[str, str] | None = None) -> tuple[subprocess.CompletedProcess, int]:
    """``fieldlog ARGS`` run by a fresh interpreter that reports its child's peak RSS (bytes): RUSAGE_CHILDREN of a
    process with one child is that child's."""
    probe = ("import resource, subprocess, sys, json; r = subprocess.run(sys.argv[1:], capture_output=True, "
             "text=True); print(json.dumps([r.returncode, r.stdout, r.stderr, "
             "resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024]))")
    p = subprocess.run([sys.executable, "-c", probe, sys.executable, "-m", "fieldlog", *args], cwd=ROOT,
                       capture_output=True, text=True, timeout=600, env={**os.environ, **(env or {})})
    code, out, err, rss = json.loads(p.stdout)
    return subprocess.CompletedProcess(args, code, out, err), rss


COMMANDS = {"info": lambda f, o: ["info", f, "--scan"], "fuse": lambda f, o: ["fuse", f, "--out", f"{o}/x.mcap"],
            "rebuild": lambda f, o: ["rebuild", f, "--out", f"{o}/x.mcap"],
            "filter": lambda f, o: ["filter", f, "--out", f"{o}/x.mcap"],
            "export": lambda f, o: ["export", f, "--out", f"{o}/tables"],
            "recover": lambda f, o: ["recover", f, "--out", f"{o}/x.mcap"]}


@pytest.mark.parametrize("bomb", ["honest", "lying", "lying-stream"])
@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_a_zip_bomb_chunk_is_refused_in_bounded_memory(bombs, tmp_path: Path, command: str, bomb: str) -> None:
    path, offset = bombs[bomb]
    assert path.stat().st_size - bombs["base"][0].stat().st_size < 200_000       # a 3 GiB chunk in ~100 KB
    r, rss = peak_run(*COMMANDS[command](str(path), str(tmp_path)))
    print(f"\n{command} {bomb}: exit {r.returncode}, peak RSS {rss / 1e6:.0f} MB")
    assert rss < MEMORY_LIMIT and "Traceback" not in r.stderr, r.stderr
    if command == "recover":                            # the chunk skipped, named; every other one kept
        assert r.returncode == 0 and f"damaged chunk skipped, at byte {offset}" in r.stdout, r.stdout + r.stderr
        got = {t.topic: t.count for t in reader.topics(tmp_path / "x.mcap")}
        want = {t.topic: t.count for t in reader.topics(bombs["base"][0])}
        assert got == want
        return
    err = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(err) == 1 and f"chunk at byte {offset}" in err[0], r.stderr
    assert str(path) in err[0] and "fieldlog recover" in err[0]
    if bomb == "honest":
        assert "limit" in err[0] and chunks.MAX_CHUNK_ENV in err[0]
    assert not (tmp_path / "x.mcap").exists() or command not in ("rebuild", "filter")   # no empty drive


def test_the_chunk_limit_is_configurable_and_applies_to_lz4(bombs, tmp_path: Path) -> None:
    """A 64 MiB lz4 chunk under a 16 MiB limit (``FIELDLOG_MAX_CHUNK_BYTES``): refused, named; the drive's own
    4 MiB chunks still read; a limit that is not a number is one line, exit 2."""
    import lz4.frame

    base, _ = bombs["base"]
    ok = bomb_chunk(1, reader.topics(base)[0].first_ns, 64 << 20, None, False)
    size = ok.uncompressed_size
    lz = Chunk(message_start_time=ok.message_start_time, message_end_time=ok.message_end_time, uncompressed_size=size,
               uncompressed_crc=0, compression="lz4",
               data=lz4.frame.compress(zstandard.ZstdDecompressor().decompress(ok.data, max_output_size=size)))
    path = tmp_path / "lz4.mcap"
    at = with_bomb(base, path, lz)
    small = {chunks.MAX_CHUNK_ENV: str(16 << 20)}
    r, rss = peak_run("info", str(path), "--scan", env=small)
    assert r.returncode == 2 and f"chunk at byte {at}" in r.stderr and str(16 << 20) in r.stderr, r.stderr
    r, _ = peak_run("info", str(base), "--scan", env=small)
    assert r.returncode == 0, r.stderr
    r, _ = peak_run("info", str(path), "--scan", env={chunks.MAX_CHUNK_ENV: "lots"})
    assert r.returncode == 2 and chunks.MAX_CHUNK_ENV in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_a_frame_larger_than_its_chunk_claims_is_never_decompressed_past_the_claim() -> None:
    """The python-zstandard and lz4 paths (no compiled kernel): a frame whose header, or content, says 256 MiB in a
    chunk claiming 4 KiB stops at the claim (the decoders would otherwise size their output by the header)."""
    probe = """
import resource, zstandard, lz4.frame
from fieldlog.drive import chunks
big = bytes(256 << 20)
frames = {"zstd": zstandard.ZstdCompressor(level=1).compress(big),
          "zstd-stream": zstandard.ZstdCompressor(level=1).compressobj().compress(big),
          "lz4": lz4.frame.compress(big)}
frames["zstd-stream"] += zstandard.ZstdCompressor(level=1).compressobj().flush()
del big
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
for name, data in frames.items():
    try:
        chunks.decompress(name.split("-")[0], data, 4096, 0)
        print(name, "read")
    except ValueError as e:
        print(name, "refused:", e)
print((resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) * 1024)
"""
    p = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, capture_output=True, text=True, timeout=300)
    lines = p.stdout.strip().splitlines()
    assert p.returncode == 0 and len(lines) == 4, p.stderr
    assert all("refused" in ln for ln in lines[:3]), lines
    assert int(lines[3]) < 32 << 20                    # the decoders allocated nothing near 256 MiB


def test_recover_writes_about_its_input_plus_the_rederived_tail(tmp_path: Path) -> None:
    """A drive cut at 60 %: the chunks alone are no larger than the cut file, and the complete recovery adds no
    more than its re-derived messages take in the drive itself (per message of each topic), give or take the
    summary; a daemon file cut before its /imu (which lags the raw bytes) is mostly tail: /imu takes about twice
    the raw bytes it comes from, hence the daemon's free-space check before recovering (``recover_unfinished``)."""
    from fieldlog.tools.filter import filter_drive

    full = tmp_path / "full.mcap"
    simulate.simulate("figure8", 120.0, 4, full)
    data = full.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:len(data) * 6 // 10])
    plain = tmp_path / "plain.mcap"
    rep = recovery.recover(cut, plain)
    assert plain.stat().st_size <= cut.stat().st_size + (64 << 10)
    out = tmp_path / "rec.mcap"
    rep2 = recovery.recover_drive(cut, out)
    assert rep2.messages == rep.messages and sum(rep2.rederived.values()) > 1000
    allowance = 0.0
    for topic, n in rep2.rederived.items():             # what n messages of the topic take in the drive itself
        alone = filter_drive(full, tmp_path / f"{topic.strip('/').replace('/', '_')}.mcap", topics=[topic])
        allowance += n / alone.messages[topic] * alone.path.stat().st_size
    extra = out.stat().st_size - plain.stat().st_size
    print(f"\ncut {cut.stat().st_size} B -> chunks {plain.stat().st_size} B + tail {extra} B "
          f"({sum(rep2.rederived.values())} messages; as in the drive: {allowance:.0f} B)")
    assert extra <= 1.1 * allowance + (64 << 10)


_RSS_PROBE = """import sys
import numpy as np
from fieldlog.drive import native
from fieldlog.drive.mcapfile import McapFile

def status(key):  # this process's own figures (ru_maxrss would start from the parent's, as exec keeps it)
    return next(int(x.split()[1]) for x in open("/proc/self/status") if x.startswith(key)) * 1024

native.ready(), native.library("fieldlog.drive._chunks", native.CHUNKS)
before = status("VmRSS:")
f = McapFile(sys.argv[1])
every = np.arange(len(f.pieces.size))
f.channel_stats()
for g in f.groups(every, f.pieces.size):
    f.read(g)
print(status("VmHWM:") - before)
"""


def test_reading_a_drive_through_takes_the_same_memory_for_any_length(simulated, figure8_600s_seed1) -> None:
    """Opening a drive (a few bytes read at every chunk and index), then reading every chunk and its message
    indexes (the topic table) hands the file's mapped pages back as it goes: the reader's peak resident memory
    grows by the same amount for a 400 s and a 600 s drive, not by the 200 s of file between them."""
    grown = {}
    for path in (simulated("figure8", 400.0, 1), figure8_600s_seed1):
        p = subprocess.run([sys.executable, "-c", _RSS_PROBE, str(path)], capture_output=True, text=True,
                           timeout=300, check=True)
        grown[path] = int(p.stdout)
    short, long = grown
    more_file = long.stat().st_size - short.stat().st_size
    assert more_file > 15e6 and grown[long] - grown[short] < 0.25 * more_file, (grown, more_file)
