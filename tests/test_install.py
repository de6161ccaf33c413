"""A core install (`pip install fieldlog`, no extras) in a fresh venv: what a car PC gets.

It must hold none of the optional dependencies (rerun, dask, polars, numba, matplotlib), run the commands the
car needs (acquire, info, recover, rebuild) on a drive, and name the extra for a command that needs one. The
drive is simulated here with the full test environment; the core venv only reads and rewrites it.
"""
import os
import subprocess
import sys
import venv
from pathlib import Path

import numpy as np
import pytest

from fieldlog.acquire import chunks
from fieldlog.acquire.recovery import recover_drive
from fieldlog.replay import reader
from fieldlog.replay.drive import open_drive

ROOT = Path(__file__).resolve().parents[1]
OPTIONAL = ("rerun", "dask", "distributed", "polars", "pyarrow", "numba", "matplotlib")


def _run(args, cwd, timeout=600):
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    return subprocess.run([str(a) for a in args], cwd=cwd, capture_output=True, text=True, timeout=timeout,
                          env=env)


@pytest.fixture(scope="module")
def core(tmp_path_factory):
    """A fresh venv with the wheel installed with its core dependencies only (from the pip cache)."""
    tmp = tmp_path_factory.mktemp("core")
    r = _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", tmp / "dist", ROOT], tmp)
    assert r.returncode == 0, r.stderr[-2000:]
    (wheel,) = (tmp / "dist").glob("fieldlog-*.whl")
    venv.create(tmp / "venv", with_pip=True)
    bin_ = tmp / "venv" / "bin"
    r = _run([bin_ / "python", "-m", "pip", "install", "-q", wheel], tmp)
    assert r.returncode == 0, r.stderr[-3000:]
    return bin_


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
    assert not names & {"rerun-sdk", "dask", "distributed", "polars", "pyarrow", "numba", "matplotlib"}, names
    assert {"numpy", "mcap", "pyserial", "fieldlog"} <= names


def test_core_install_runs_the_car_commands(core, drive, tmp_path):
    fl = core / "fieldlog"
    r = _run([fl, "acquire", "--help"], tmp_path)
    assert r.returncode == 0 and "--daq" in r.stdout, r.stderr

    r = _run([fl, "info", drive], tmp_path)
    assert r.returncode == 0, r.stderr
    assert "/imu" in r.stdout and "sensor_msgs/msg/Imu" in r.stdout

    # a drive cut short mid-chunk: recover keeps exactly the messages of the complete chunks and re-derives the
    # same tail (the core build walks chunks without numba; the numba walk of the test environment must find the
    # same records)
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


def test_core_install_names_the_missing_extra(core, drive, tmp_path):
    for argv, extra in ((["view", drive, "--rrd", tmp_path / "x.rrd"], "view"),
                        (["fuse", drive, "--out", tmp_path / "f.mcap"], "fusion"),
                        (["export", drive, "--out", tmp_path / "tables"], "export")):
        r = _run([core / "fieldlog", *argv], tmp_path)
        assert r.returncode == 2, (argv, r.stderr)
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and f"fieldlog[{extra}]" in lines[0], r.stderr


def test_walk_without_numba_matches_numba(drive):
    """The plain-Python chunk walk (core installs) finds the same records as the numba one."""
    (f,) = open_drive(drive)
    for piece in np.flatnonzero(f.pieces.chunk)[:3].tolist():
        buf = np.frombuffer(f.records(piece), np.uint8)
        a, b = chunks._walk(buf), chunks._walk_python(buf, 0, 16)
        for x, y in zip(a[:3], b[:3]):
            np.testing.assert_array_equal(x, y)
        assert a[3] == b[3]
        cut = buf[: len(buf) - 7]     # a record cut short: both stop before it
        assert chunks._walk(cut)[3] == chunks._walk_python(cut, 0, 16)[3] < len(cut)
