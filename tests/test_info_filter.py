"""`fieldlog info` from the record written at close (the same figures as a scan), `fieldlog filter`, and a CLI that
starts without the optional heavy modules and documents every option."""
import argparse
import json
import subprocess
import sys

import numpy as np
import pytest
from mcap.reader import make_reader

from fieldlog.acquire import recovery
from fieldlog.drive import reader
from fieldlog.tools.cli import build_parser, main
from fieldlog.tools.filter import filter_drive
from fieldlog.tools.info import drive_info, format_info
from fieldlog.tools.sim.simulate import simulate

NS = 1_000_000_000


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    path = tmp_path_factory.mktemp("info") / "drive.mcap"
    simulate("urban", 120, 2, path)      # tunnels: GPS epochs without fix
    return path


def test_info_from_the_record_equals_the_scan(drive, tmp_path, capsys):
    fast, scan = drive_info(drive), drive_info(drive, scan=True)
    assert not fast.scanned and scan.scanned
    assert format_info(fast) == format_info(scan)
    assert fast.timing is not None and fast.timing.samples > 10_000
    assert main(["info", "--json", str(drive)]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["path"] == str(drive.resolve())
    assert {t["topic"]: t["count"] for t in d["topics"]} == {t.topic: t.count for t in reader.topics(drive)}
    assert d["timing"]["samples"] == fast.timing.samples and d["gps_no_fix"] == fast.gps_no_fix

    # a file cut short and recovered has no record: info scans it
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(drive.read_bytes()[: drive.stat().st_size // 2])
    recovery.recover(cut, tmp_path / "rec.mcap")
    rec = drive_info(tmp_path / "rec.mcap")
    assert rec.scanned and rec.topics and rec.imu_gaps == drive_info(tmp_path / "rec.mcap", scan=True).imu_gaps


def test_filter_slices_by_time_and_topic(drive, tmp_path, capsys):
    out = tmp_path / "slice.mcap"
    assert main(["filter", str(drive), "--start", "30", "--end", "75.5", "--topics", "/imu,/gps/*",
                 "--out", str(out)]) == 0
    assert str(out.resolve()) in capsys.readouterr().out
    t_imu = int(reader.read_topic(drive, "/imu")["log_time_ns"][0])  # times count from the first IMU sample
    with open(drive, "rb") as f:
        assert make_reader(f).get_summary().statistics.message_start_time < t_imu  # (not the first message)
    t0, t1 = t_imu + 30 * NS, t_imu + int(75.5 * NS)
    got = {t.topic: t for t in reader.topics(out)}
    assert set(got) == {"/imu", "/gps/fix", "/gps/vel", "/gps/nmea", "/tf_static"}
    for topic in ("/imu", "/gps/fix", "/gps/nmea"):
        t = reader.read_topic(drive, topic)["log_time_ns"]
        want = t[(t >= t0) & (t < t1)]
        sliced = reader.read_topic(out, topic)
        np.testing.assert_array_equal(sliced["log_time_ns"], want, err_msg=topic)
    imu = reader.read_topic(out, "/imu")
    full = reader.read_topic(drive, "/imu")
    i = np.searchsorted(full["log_time_ns"], t0)
    np.testing.assert_array_equal(imu["f_b"], full["f_b"][i:i + len(imu["f_b"])])
    # channels as they were (qos profiles), the drive's metadata, and a record of the slice; info is fast on it
    with open(out, "rb") as f:
        r = make_reader(f)
        chans = {c.topic: c.metadata for c in r.get_summary().channels.values()}
        meta = {m.name: m.metadata for m in r.iter_metadata()}
    assert all("offered_qos_profiles" in m for m in chans.values())
    assert meta["filter"]["start_ns"] == str(t0) and "calibration" in meta
    fast = drive_info(out)
    assert not fast.scanned and format_info(fast) == format_info(drive_info(out, scan=True))

    # ISO times and times from the end select the same slice
    iso = np.datetime_as_string(np.datetime64(t0, "ns"), unit="ns") + "Z"
    res = filter_drive(drive, tmp_path / "b.mcap", iso, str(t1), ["/imu"])
    assert res.messages["/imu"] == got["/imu"].count
    for bad in (["--start", "soon"], ["--topics", "/nothing*"], ["--start", "50", "--end", "40"]):
        assert main(["filter", str(drive), *bad, "--out", str(tmp_path / "x.mcap")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("fieldlog filter: error:")


def test_cli_starts_without_rerun_polars(drive):
    """`fieldlog --help`, `info` and `acquire --help` import none of the heavy optional modules."""
    probe = ("import sys, contextlib, io\n"
             "from fieldlog.tools.cli import main\n"
             "for argv in (['--help'], ['acquire', '--help'], ['info', sys.argv[1]]):\n"
             "    with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit):\n"
             "        main(argv)\n"
             "import fieldlog.acquire.daemon, fieldlog.tools.info, fieldlog.tools.filter, fieldlog.tools.rebuild\n"
             "print(' '.join(m for m in ('rerun', 'polars', 'pyarrow', 'dask', 'matplotlib', "
             "'fieldlog.fusion.engine') if m in sys.modules))\n")
    r = subprocess.run([sys.executable, "-c", probe, str(drive)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == ""


def test_every_option_has_help_and_the_top_help_has_examples():
    p = build_parser()
    assert "examples:" in p.format_help() and "fieldlog filter" in p.format_help()
    sub = next(a for a in p._actions if isinstance(a, argparse._SubParsersAction))
    for name, s in sub.choices.items():
        for a in s._actions:
            if isinstance(a, argparse._HelpAction):
                continue
            assert a.help, f"{name} {a.dest}: no help text"
            if a.option_strings and a.default not in (None, False, []) and not a.required:
                assert "(default:" in s._get_formatter()._get_help_string(a), f"{name} {a.dest}"
            elif a.option_strings and a.default is None and not a.required:   # the default said in words
                assert "default" in a.help or "required" in a.help, f"{name} {a.dest}: {a.help}"
