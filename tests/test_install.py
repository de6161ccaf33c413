"""A core install (`pip install fieldlog`, no extras) in a fresh venv: what a car PC gets.

It must hold none of the optional dependencies (rerun, dask, polars, matplotlib, fastkml, gpxpy), build the
compiled kernels from the sources (setup.py), run the commands the car needs (acquire, info, recover, rebuild,
fuse) on a drive, and name the extra for a command that needs one. The drive is simulated here with the full
test environment; the core venv reads, rewrites and fuses it, to the same bytes as the test environment.
"""
import os
import struct
import subprocess
import sys
import venv
from pathlib import Path

import numpy as np
import pytest
from conftest import _once, _shared

from fieldlog.drive import chunks
from fieldlog.acquire.recovery import recover_drive
from fieldlog.drive import reader
from fieldlog.drive.files import open_drive
from fieldlog.tools.cli import main as cli_main

ROOT = Path(__file__).resolve().parents[1]
OPTIONAL = ("rerun", "dask", "distributed", "polars", "pyarrow", "matplotlib", "fastkml", "gpxpy", "jinja2")


def _run(args, cwd, timeout=600):
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    return subprocess.run([str(a) for a in args], cwd=cwd, capture_output=True, text=True, timeout=timeout,
                          env=env)


@pytest.fixture(scope="module")
def core(tmp_path_factory):
    """A fresh venv with the wheel installed with its core dependencies only (from the pip cache), built once
    per run (two pytest-xdist workers building the checkout's wheel at once would share its build/)."""

    def build(env: Path) -> None:
        tmp = env.parent
        r = _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", tmp / "dist", ROOT], tmp)
        assert r.returncode == 0, r.stderr[-2000:]
        (wheel,) = (tmp / "dist").glob("fieldlog-*.whl")
        venv.create(env, with_pip=True)
        r = _run([env / "bin" / "python", "-m", "pip", "install", "-q", wheel], tmp)
        assert r.returncode == 0, r.stderr[-3000:]

    return _once(_shared(tmp_path_factory, "core_install"), "venv", build) / "bin"


@pytest.fixture(scope="module")
def drive(simulated):
    return simulated("figure8", 90, 1)


def test_core_install_has_no_optional_dependency(core, tmp_path):
    probe = ("import importlib.util as u, sys; "
             f"print(' '.join(m for m in {OPTIONAL!r} if u.find_spec(m) is not None))")
    r = _run([core / "python", "-c", probe], tmp_path)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == ""
    r = _run([core / "python", "-m", "pip", "list", "--format=freeze"], tmp_path)
    names = {line.split("==")[0].lower() for line in r.stdout.split()}
    assert not names & {"rerun-sdk", "dask", "distributed", "polars", "pyarrow", "matplotlib", "numba"}, names
    assert {"numpy", "mcap", "pyserial", "fieldlog"} <= names


def test_core_install_runs_the_car_commands(core, drive, tmp_path):
    fl = core / "fieldlog"
    r = _run([fl, "acquire", "--help"], tmp_path)
    assert r.returncode == 0 and "--daq" in r.stdout, r.stderr

    r = _run([fl, "info", drive], tmp_path)
    assert r.returncode == 0, r.stderr
    assert "/imu" in r.stdout and "sensor_msgs/msg/Imu" in r.stdout

    # a drive cut short mid-chunk: recover keeps exactly the messages of the complete chunks and re-derives the
    # same tail as the test environment's reader
    cut = tmp_path / "cut.mcap"
    data = drive.read_bytes()
    cut.write_bytes(data[: len(data) * 2 // 3])
    r = _run([fl, "recover", cut, "--out", tmp_path / "rec.mcap"], tmp_path)
    assert r.returncode == 0, r.stderr
    ref = tmp_path / "ref.mcap"
    rep = recover_drive(cut, ref)
    assert rep.chunks > 0 and rep.rederived.get("/imu", 0) > 0
    assert {t.topic: t.count for t in reader.topics(tmp_path / "rec.mcap")} == \
        {t.topic: t.count for t in reader.topics(ref)}

    r = _run([fl, "rebuild", drive, "--out", tmp_path / "rebuilt.mcap"], tmp_path)
    assert r.returncode == 0, r.stderr
    got = {t.topic: t.count for t in reader.topics(tmp_path / "rebuilt.mcap")}
    want = {t.topic: t.count for t in reader.topics(drive)}
    for topic in ("/imu", "/gps/fix", "/raw/daq"):
        assert got[topic] == want[topic], topic

    # the car can fuse too: the core wheel's kernels, built here from the sources, give the same bytes
    r = _run([fl, "fuse", drive, "--method", "kf", "--out", tmp_path / "kf.mcap"], tmp_path)
    assert r.returncode == 0, r.stderr
    assert cli_main(["fuse", str(drive), "--method", "kf", "--out", str(tmp_path / "kf_ref.mcap")]) == 0
    assert (tmp_path / "kf.mcap").read_bytes() == (tmp_path / "kf_ref.mcap").read_bytes()


def test_core_install_names_the_missing_extra(core, drive, tmp_path):
    for argv, extra in ((["view", drive, "--rrd", tmp_path / "x.rrd"], "view"),
                        (["export", drive, "--out", tmp_path / "tables"], "export"),
                        (["export", drive, "--out-dir", tmp_path / "tracks", "--format", "kml"], "export"),
                        (["report", drive, "--out", tmp_path / "report.html"], "report")):
        r = _run([core / "fieldlog", *argv], tmp_path)
        assert r.returncode == 2, (argv, r.stderr)
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and f"fieldlog[{extra}]" in lines[0], r.stderr


def _walk_reference(buf: bytes) -> tuple[list, list, list, int]:
    """The MCAP record walk written plainly (opcode, u64 length, body), the compiled walk's oracle."""
    ops, starts, lengths, pos = [], [], [], 0
    while pos + 9 <= len(buf):
        op, length = struct.unpack_from("<BQ", buf, pos)
        if pos + 9 + length > len(buf):
            break
        ops.append(op), starts.append(pos + 9), lengths.append(length)
        pos += 9 + length
    return ops, starts, lengths, pos


def test_the_compiled_walk_matches_a_plain_one(drive):
    """The compiled record walk (drive/_chunks.c) finds the records a plain walk finds, in whole chunks, in
    chunks cut short, and up to a length whose top bit is set; its arrays grow past the capacity it is given."""
    (f,) = open_drive(drive)
    for piece in np.flatnonzero(f.pieces.chunk)[:3].tolist():
        raw = bytes(f.records(piece))
        at = _walk_reference(raw)[1][4] - 9                     # the fifth record: its length's top bit set
        for buf in (raw, raw[: len(raw) - 7], raw[:at + 1] + b"\xff" * 8 + raw[at + 9:]):
            ops, starts, lengths, end = chunks.walk_records(np.frombuffer(buf, np.uint8), 0, 1)
            want = _walk_reference(buf)
            assert (ops.tolist(), starts.tolist(), lengths.tolist(), end) == want
            assert len(want[0]) > 1 and (end < len(buf)) == (buf is not raw)
