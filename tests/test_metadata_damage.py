"""Damaged metadata is bad input: records that do not parse and values that are not what we wrote give the one-line
error (exit 2) or are left out with a warning where the messages can still be read; nothing is evaluated.
The drives are written with the mcap library's own Writer."""
from __future__ import annotations

import math
import struct
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from fieldlog.drive import metavalue
from fieldlog.acquire.pipeline import Pipeline

DEEP = "[" * 100_000 + "]" * 100_000
GARBAGE = ["__import__('os').system('true')", DEEP, "{" * 50, "(1, 2", "[1, 2]]", "'unterminated", "1 2", "",
           "\x00\xff", "nan nan", "lambda: 0", "{'a': [1, {'b': (2, " * 30]


@pytest.fixture(scope="module")
def sim_drive(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("sim") / "drive.mcap"
    p = subprocess.run([sys.executable, "-m", "fieldlog", "sim", "--scenario", "figure8", "--duration", "20",
                        "--seed", "2", "--out", str(out)], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    return out


def rewrite(src: Path, dst: Path, meta: dict[str, dict[str, str]] | None = None, chunked: bool = True) -> None:
    """``src`` copied with mcap's Writer; the metadata records ``meta`` replace or add to its own."""
    with open(src, "rb") as f:
        r = make_reader(f)
        records = {m.name: dict(m.metadata) for m in r.iter_metadata()}
        records.update(meta or {})
        with open(dst, "wb") as g:
            w = Writer(g, use_chunking=chunked)
            w.start(profile="ros2", library="another writer")
            ids: dict[int, int] = {}
            chans: dict[int, int] = {}
            for schema, channel, msg in r.iter_messages(log_time_order=False):
                if schema.id not in ids:
                    ids[schema.id] = w.register_schema(schema.name, schema.encoding, schema.data)
                if channel.id not in chans:
                    chans[channel.id] = w.register_channel(channel.topic, channel.message_encoding, ids[schema.id])
                w.add_message(chans[channel.id], msg.log_time, msg.data, msg.publish_time)
            for name, d in records.items():
                w.add_metadata(name, d)
            w.finish()


def patch_first(path: Path, opcode: int, field_offset: int, value: int) -> None:
    """Overwrite a u32 inside the first top-level record of ``opcode`` (e.g. a string's length: it then overruns
    its record), leaving the record's own length as it is."""
    b = bytearray(path.read_bytes())
    pos = 8
    while pos < len(b):
        op, n = b[pos], struct.unpack_from("<Q", b, pos + 1)[0]
        if op == opcode:
            struct.pack_into("<I", b, pos + 9 + field_offset, value)
            path.write_bytes(bytes(b))
            return
        pos += 9 + n
    raise AssertionError(f"no record of opcode {opcode:#x}")


def fieldlog(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "fieldlog", *args], capture_output=True, text=True, timeout=300)


def commands(drive: Path, tmp: Path) -> dict[str, list[str]]:
    return {"info": ["info", str(drive)], "rebuild": ["rebuild", str(drive), "--out", str(tmp / "rebuilt.mcap")],
            "filter": ["filter", str(drive), "--out", str(tmp / "filtered.mcap"), "--topics", "/imu"],
            "fuse": ["fuse", str(drive), "--method", "ins", "--out", str(tmp / "fused.mcap")]}


def assert_clean_exit(p: subprocess.CompletedProcess, codes: tuple[int, ...], drive: Path) -> None:
    assert p.returncode in codes, p.stderr
    assert "Traceback" not in p.stderr and "internal error" not in p.stderr, p.stderr
    if p.returncode == 2:
        (line,) = p.stderr.strip().splitlines()[-1:]
        assert str(drive) in line or drive.name in line, line


@pytest.mark.slow
@pytest.mark.parametrize("where", [0, 8])     # the record's name length, its first key's length
def test_unparseable_metadata_record_is_left_out_with_a_warning(sim_drive: Path, tmp_path: Path, where: int) -> None:
    drive = tmp_path / "drive.mcap"
    rewrite(sim_drive, drive)
    patch_first(drive, 0x0C, where, 0xFFFFFF00)
    for name, args in commands(drive, tmp_path).items():
        p = fieldlog(*args)
        assert_clean_exit(p, (0, 2), drive)
        assert f"{drive}: damaged metadata record at byte" in p.stderr, (name, p.stderr)


@pytest.mark.slow
def test_unparseable_schema_or_channel_record_is_the_one_line_error(sim_drive: Path, tmp_path: Path) -> None:
    for opcode in (0x03, 0x04):                    # schema, channel (their name/topic length overruns them)
        drive = tmp_path / f"drive{opcode}.mcap"
        rewrite(sim_drive, drive, chunked=False)
        patch_first(drive, opcode, 2, 0xFFFFFF00)
        for name, args in commands(drive, tmp_path).items():
            p = fieldlog(*args)
            assert_clean_exit(p, (2,), drive)
            assert "damaged" in p.stderr, (name, p.stderr)


@pytest.mark.slow
@pytest.mark.parametrize("value", [GARBAGE[0], DEEP, "(1, 2", "{'gyro': {'x': [1, 2, {'y': 'z'}]}}"])
def test_garbage_or_deeply_nested_values_are_bad_input(sim_drive: Path, tmp_path: Path, value: str) -> None:
    drive = tmp_path / "drive.mcap"
    with open(sim_drive, "rb") as f:
        own = {m.name: dict(m.metadata) for m in make_reader(f).iter_metadata()}
    info = {**own["fieldlog.info"], "rate_ppm": value, "span./imu": value}
    rewrite(sim_drive, drive, {"timesync": {**own["timesync"], "window_s": value}, "fieldlog.info": info,
                               "fusion.config": {"gyro_noise_dps_rthz": value}})
    cmds = commands(drive, tmp_path)
    p = fieldlog(*cmds["info"])                    # the figures are computed from the messages instead
    assert_clean_exit(p, (0,), drive)
    assert "fieldlog.info record is damaged" in p.stderr
    for name in ("rebuild", "fuse"):               # their settings are in the record: one line, exit 2
        p = fieldlog(*cmds[name])
        assert_clean_exit(p, (2,), drive)
        assert ("timesync" if name == "rebuild" else "fusion.config") in p.stderr


def test_values_round_trip_as_json_and_old_python_literals_still_read() -> None:
    for v in [1, -2.5, math.inf, "flag", True, None, [1, [2, 3]], {"a": 1.5, "b": [None, "x"]}, "it's \"q\" \u00fc"]:
        assert metavalue.load(metavalue.dump(v)) == v
    assert math.isnan(metavalue.load(metavalue.dump(math.nan)))
    old = {"(1, 2)": [1, 2], "nan": None, "None": None, "'flag'": "flag", "{'a': 1.5, 'b': (True, -inf)}":
           {"a": 1.5, "b": [True, -math.inf]}, "-3": -3, "1e-06": 1e-6, "'it\\'s \\x41'": "it's A"}
    for text, want in old.items():
        got = metavalue.load(text)
        assert (math.isnan(got) if want is None and text == "nan" else got == want), text
    meta = {"timesync": {"pps_mode": "'latch'", "window_s": "None", "fs_hz": "500.0", "min_edges": "5"}}
    _, sync, _ = Pipeline.settings_from_metadata(meta)
    assert (sync.pps_mode, sync.window_s, sync.fs_hz, sync.min_edges) == ("latch", 30.0, 500.0, 5)


@pytest.mark.parametrize("value", GARBAGE)
def test_load_refuses_garbage_in_one_value_error(value: str) -> None:
    with pytest.raises(ValueError):
        metavalue.load(value)
