"""Hostile bytes and receivers: no sentence stops the daemon or the pipeline, dates are range-checked in one
place, non-fixes are NO_FIX as gpsd has them, and a receiver clock jump is flagged, not mis-stamped."""
from __future__ import annotations

import io
import re
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from fieldlog.acquire import gnss, nmea, recovery, timesync
from fieldlog.drive import messages, recorder
from fieldlog.acquire.pipeline import Pipeline, RawRead, in_read_order, read_order
from fieldlog.drive import reader
from fieldlog.drive.reader import read_metadata
from fieldlog.tools.sim import simulate, trajectory
from fieldlog.tools.sim.serve import Server
from test_daemon import run, start_daemon

NS = 1_000_000_000

# valid checksums, hostile dates: each must be counted, not raised out of the processing thread
CRASHERS = ["GPZDA,120000.00,01,01,3000,00,00",                       # year beyond int64 ns (2262)
            "GPZDA,120000.00,01,01,1500,00,00",                       # year before 1678
            "GPZDA,120000.00,01,01,99999999999999999999,00,00",       # OverflowError in date()
            "GPZDA,235959.00,31,12,9999,00,00", "GPGGA,000000.00,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,"]


def rewrite_gps(reads: list[RawRead], edit) -> list[RawRead]:
    """The reads with every GPS sentence body passed through ``edit(body, mono_ns of its read) -> body`` of the
    same length (checksum redone), cut at the same byte offsets (a read may end mid-sentence)."""
    gps = [r for r in reads if r.port == "gps"]
    stream = b"".join(r.data for r in gps)
    ends = np.cumsum([len(r.data) for r in gps])
    out = bytearray(stream)
    for m in re.finditer(rb"\$([^*$]*)\*..\r\n", stream):
        mono = gps[int(np.searchsorted(ends, m.start(), side="right"))].mono_ns
        new = nmea.sentence(edit(m.group(1).decode(), mono))
        assert len(new) == m.end() - m.start()
        out[m.start():m.end()] = new
    it = iter(np.concatenate(([0], ends)).tolist())
    cuts = dict(zip((id(r) for r in gps), zip(it, ends.tolist())))
    return [RawRead(r.port, r.mono_ns, r.wall_ns, bytes(out[cuts[id(r)][0]:cuts[id(r)][1]])) if r.port == "gps"
            else r for r in reads]


def pipe_drive(path: Path, reads: list[RawRead], ccfg) -> dict[str, str]:
    """Feed the reads through the pipeline into a real MCAP at ``path``; returns the counters."""
    sync = timesync.TimeSyncConfig.from_dict({"pps_mode": ccfg.pps_mode, "fs_hz": ccfg.fs_hz})
    with recorder.Recorder(path) as rec:
        pipe = Pipeline(rec, sync_cfg=sync)
        for r in reads:
            pipe.feed(r.port, r.mono_ns, r.wall_ns, r.data)
        pipe.finish()
        c = pipe.counters_metadata()
        rec.add_metadata("acquire.counters", c)
    return c


@pytest.fixture(scope="module")
def sim60():
    reads, _truth, t0_ns, ccfg, _cal = simulate.make_reads(trajectory.load_scenario("figure8"), 60.0, 4)
    return reads, t0_ns, ccfg


# ------------------------------------------------------------------------------------------- dates

def test_dates_are_range_checked_in_one_place() -> None:
    assert gnss.make_date(2024, 2, 29) is not None and gnss.make_date(2023, 2, 29) is None
    assert gnss.make_date("1979", "12", "31") is None and gnss.make_date(gnss.YEAR_MAX + 1, 1, 1) is None
    assert gnss.make_date("9" * 20, "1", "1") is None and gnss.make_date("x", "1", "1") is None
    d = gnss.make_date(gnss.YEAR_MAX - 1, 12, 31)
    assert gnss.roll_over(d, 10.0, 86000.0) == gnss.make_date(gnss.YEAR_MAX, 1, 1)
    assert gnss.roll_over(gnss.make_date(gnss.YEAR_MAX, 12, 31), 10.0, 86000.0) is None   # leaves the range
    assert gnss.roll_over(d, 86001.0, 86000.0) == d and gnss.roll_over(None, 1.0, 2.0) is None
    assert gnss.utc_ns(gnss.make_date(gnss.YEAR_MAX, 12, 31), 86399.0) < messages.STAMP_END_NS
    st = nmea.NmeaStats()
    for body in CRASHERS[:4]:
        z = nmea.decode_body(body.encode(), stats=st)
        assert isinstance(z, nmea.Zda) and z.date is None
    assert st.bad_fields == 4


def test_hostile_dates_mid_drive_are_counted_and_the_drive_goes_on(tmp_path: Path, sim60) -> None:
    reads, _, ccfg = sim60
    mid = next(i for i, r in enumerate(reads) if r.port == "gps" and r.mono_ns - reads[0].mono_ns > 30 * NS)
    bad = b"".join(nmea.sentence(s) for s in CRASHERS)
    r = reads[mid]
    hostile = reads[:mid] + [RawRead("gps", r.mono_ns, r.wall_ns, r.data + bad)] + reads[mid + 1:]
    c = pipe_drive(tmp_path / "d.mcap", hostile, ccfg)
    clean = pipe_drive(tmp_path / "clean.mcap", reads, ccfg)
    assert c["processing_errors"] == "0" and int(c["nmea.bad_fields"]) == int(clean["nmea.bad_fields"]) + 4
    assert c["imu_samples"] == clean["imu_samples"] == str(60 * 500)
    fix = reader.read_topic(tmp_path / "d.mcap", "/gps/fix")
    assert np.all(np.diff(fix["log_time_ns"]) >= 0) and fix["log_time_ns"][-1] - fix["log_time_ns"][0] < 61 * NS
    texts = [m.sentence for m in reader.read_topic(tmp_path / "d.mcap", "/gps/nmea")["msgs"]]
    assert all(nmea.sentence(s).decode().strip() in texts for s in CRASHERS)        # kept as they came


def test_a_processing_exception_is_counted_logged_once_and_the_read_kept(tmp_path: Path, sim60, monkeypatch,
                                                                          caplog) -> None:
    """Whatever a future decoder bug raises: fault injection into the NMEA epoch assembly for a few reads."""
    reads, _, ccfg = sim60
    add = nmea.EpochAssembler.add
    calls = {"n": 0}

    def faulty(self, s, mono_ns):
        calls["n"] += 1
        if 100 <= calls["n"] < 110:
            raise RuntimeError("injected")
        return add(self, s, mono_ns)

    monkeypatch.setattr(nmea.EpochAssembler, "add", faulty)
    c = pipe_drive(tmp_path / "d.mcap", reads, ccfg)
    assert int(c["processing_errors"]) >= 1 and c["imu_samples"] == str(60 * 500)
    logged = [r for r in caplog.records if "injected" in r.getMessage()]
    assert len(logged) == 1 and "kept in /raw/gps" in logged[0].getMessage()
    raw = reader.read_topic(tmp_path / "d.mcap", "/raw/gps")["msgs"]
    assert b"".join(bytes(m.data) for m in raw) == b"".join(r.data for r in reads if r.port == "gps")


def test_import_survives_a_roll_over_at_the_end_of_the_calendar(tmp_path: Path) -> None:
    log = tmp_path / "gps.nmea"
    log.write_bytes(nmea.sentence(CRASHERS[3]) + nmea.sentence(CRASHERS[4])
                    + nmea.sentence("GPRMC,000001.00,A,4807.038,N,01131.000,E,0.0,0.0,010124,,,A")
                    + nmea.sentence("GPGGA,000001.00,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,"))
    r = run("import", "--gps", str(log), "--out", str(tmp_path / "d.mcap"))
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr


def test_daemon_records_on_through_hostile_sentences_over_a_pty(tmp_path: Path) -> None:
    srv = Server("figure8", 40.0, 6, speed=10)
    gps = srv.ports["gps"]
    mid = int(np.searchsorted(gps.t_s, 10.0))
    gps.data[mid] += b"".join(nmea.sentence(s) for s in CRASHERS)
    srv.open(io.StringIO())
    try:
        d, _ = start_daemon(tmp_path / "drives", {p.name: p.path for p in srv.ports.values()}, "--time-scale", "10")
        t = threading.Thread(target=srv.run)
        t.start()
        sizes = []                   # file size every 0.25 s while streaming (the hostile read goes at 1 s)
        while t.is_alive() and not srv.completed and d.poll() is None:
            t.join(0.25)
            files = list((tmp_path / "drives").glob("*/*.mcap"))
            sizes.append(files[0].stat().st_size if files else 0)
        while d.poll() is None and (len(sizes) < 8 or sizes[-1] != sizes[-8]):   # until it has caught up (2 s)
            time.sleep(0.25)
            sizes.append(files[0].stat().st_size)
        assert d.poll() is None, d.stderr.read()             # still running after every hostile sentence
    finally:
        srv.stop.set()
        t.join()
        srv.close()
    d.send_signal(signal.SIGTERM)
    code, log = d.wait(30), d.stderr.read()
    assert code == 0 and "Traceback" not in log, log
    assert len(sizes) >= 12 and sizes[-1] > sizes[7] > 0         # the file kept growing after mid-drive
    (f,) = (tmp_path / "drives").glob("*/*.mcap")
    c = read_metadata(f)["acquire.counters"]
    assert c["processing_errors"] == "0" and int(c["nmea.bad_fields"]) >= 4
    imu = reader.read_topic(f, "/imu")["log_time_ns"]
    assert len(imu) == int(c["daq.frames"]) == 40 * 500             # /imu kept coming to the end
    texts = [m.sentence for m in reader.read_topic(f, "/gps/nmea")["msgs"]]
    assert nmea.sentence(CRASHERS[2]).decode().strip() in texts


# ------------------------------------------------------------------------------------------- fixes

@pytest.mark.parametrize("change, reason", [
    (lambda f: f.__setitem__(6, "6"), "quality_6"),
    (lambda f: f.__setitem__(6, "7"), "quality_7"),
    (lambda f: f.__setitem__(6, "8"), "quality_8"),
    (lambda f: f.__setitem__(7, "00"), "no_satellites"),
    (lambda f: f.__setitem__(2, "V"), "status_void"),
])
def test_non_fixes_are_no_fix_counted_and_kept_in_nmea(tmp_path: Path, sim60, change, reason) -> None:
    reads, t0_ns, ccfg = sim60
    lo, hi = t0_ns + 20 * NS, t0_ns + 30 * NS      # receiver times of the altered epochs: [20 s, 30 s)
    kind = "RMC" if reason == "status_void" else "GGA"

    def edit(body: str, mono_ns: int) -> str:
        f = body.split(",")
        if f[0][2:] == kind and f[1]:
            tod = float(f[1][:2]) * 3600 + float(f[1][2:4]) * 60 + float(f[1][4:])
            if lo <= (t0_ns // (86400 * NS)) * 86400 * NS + round(tod * NS) < hi:
                change(f)
        return ",".join(f)

    c = pipe_drive(tmp_path / "d.mcap", rewrite_gps(reads, edit), ccfg)
    fix = reader.read_topic(tmp_path / "d.mcap", "/gps/fix")
    t = fix["log_time_ns"]
    inside = (t >= lo) & (t < hi)
    assert inside.sum() == 10 == int(c[f"gps_no_fix.{reason}"]) == int(c["gps_no_fix"])
    assert np.all(fix["status"][inside] == messages.STATUS_NO_FIX) and np.all(np.isnan(fix["lat_deg"][inside]))
    assert np.all(fix["status"][~inside] != messages.STATUS_NO_FIX)
    nm = "".join(m.sentence for m in reader.read_topic(tmp_path / "d.mcap", "/gps/nmea")["msgs"])
    assert nm.count(f"{kind},") == b"".join(r.data for r in reads if r.port == "gps").count(kind.encode() + b",")


def test_a_receiver_clock_jump_is_flagged_and_stamped_by_the_clock_fit(tmp_path: Path, sim60) -> None:
    reads, t0_ns, ccfg = sim60
    a, b = reads[0].mono_ns + 30 * NS, reads[0].mono_ns + 45 * NS

    def edit(body: str, mono_ns: int) -> str:
        f = body.split(",")
        if a <= mono_ns < b and f[0][2:] in ("GGA", "RMC", "GST", "ZDA") and f[1]:
            f[1] = f"{(int(f[1][:2]) + 1) % 24:02d}{f[1][2:]}"            # the receiver clock +1 h
        return ",".join(f)

    c = pipe_drive(tmp_path / "d.mcap", rewrite_gps(reads, edit), ccfg)
    fix = reader.read_topic(tmp_path / "d.mcap", "/gps/fix")
    t = fix["log_time_ns"]
    assert t.max() - t0_ns < 61 * NS                               # nothing written an hour late
    flagged = fix["status"] == messages.STATUS_NO_FIX
    assert 14 <= flagged.sum() == int(c["gps_no_fix.receiver_time"]) <= 16
    assert np.all((t[flagged] > t0_ns + 29 * NS) & (t[flagged] < t0_ns + 47 * NS))
    assert np.all(np.diff(t) > 0)


def test_a_gps_read_the_host_made_late_is_not_a_clock_jump(tmp_path: Path, sim60) -> None:
    """The host reads the GPS port 3.5 s late (busy): one read brings four epochs. Their receiver times are right,
    so none is flagged, and each is stamped at its receiver time; the same read with the clock +1 h is flagged."""
    reads, t0_ns, ccfg = sim60
    a, b = reads[0].mono_ns + 30 * NS, reads[0].mono_ns + 33 * NS + NS // 2
    late = [r for r in reads if r.port == "gps" and a <= r.mono_ns < b]
    joined = RawRead("gps", b, late[-1].wall_ns + NS // 2, b"".join(r.data for r in late))
    delayed = sorted([r for r in reads if not any(r is x for x in late)] + [joined],
                     key=lambda r: read_order(r.port, r.mono_ns))
    c = pipe_drive(tmp_path / "late.mcap", delayed, ccfg)
    fix = reader.read_topic(tmp_path / "late.mcap", "/gps/fix")
    assert int(c.get("gps_no_fix", 0)) == 0 and np.all(fix["status"] != messages.STATUS_NO_FIX)
    assert len(fix["log_time_ns"]) >= 58 and np.all(fix["log_time_ns"] % NS == t0_ns % NS - t0_ns % NS)  # whole s

    late_epochs = {m.group(1) for m in re.finditer(rb"\$..(?:GGA|RMC|GST|ZDA),([0-9.]+),", joined.data)}

    def jump(body: str, mono_ns: int) -> str:      # the late read's epochs, all their sentences, +1 h
        f = body.split(",")
        if f[0][2:] in ("GGA", "RMC", "GST", "ZDA") and f[1].encode() in late_epochs:
            f[1] = f"{(int(f[1][:2]) + 1) % 24:02d}{f[1][2:]}"
        return ",".join(f)

    c = pipe_drive(tmp_path / "jump.mcap", rewrite_gps(delayed, jump), ccfg)
    assert 3 <= int(c["gps_no_fix.receiver_time"]) == int(c["gps_no_fix"]) <= 5


# ------------------------------------------------------------------------------------------- CLI contract

@pytest.fixture(scope="module")
def bad_inputs(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("bad")
    good = d / "good.mcap"
    simulate.simulate("figure8", 20.0, 1, good)
    data = good.read_bytes()
    rng = np.random.default_rng(14)
    files = {"missing": d / "nope.mcap", "directory": d / "adir.mcap", "empty": d / "empty.mcap",
             "random": d / "random.mcap", "truncated": d / "cut.mcap", "wrong_format": d / "log.csv"}
    files["directory"].mkdir()
    files["empty"].write_bytes(b"")
    files["random"].write_bytes(rng.bytes(50_000))
    files["truncated"].write_bytes(data[:len(data) * 2 // 3])
    files["wrong_format"].write_text("t,x\n1,2\n")
    return {"good": good, **files}


COMMANDS = {"info": lambda f, o: ["info", f], "fuse": lambda f, o: ["fuse", f, "--out", f"{o}/x.mcap"],
            "view": lambda f, o: ["view", f, "--rrd", f"{o}/x.rrd"], "export": lambda f, o: ["export", f, "--out", o],
            "rebuild": lambda f, o: ["rebuild", f, "--out", f"{o}/x.mcap"], "allan": lambda f, o: ["allan", f],
            "recover": lambda f, o: ["recover", f, "--out", f"{o}/x.mcap"],
            "import": lambda f, o: ["import", "--gps", f, "--out", f"{o}/x.mcap"],
            "acquire": lambda f, o: ["acquire", "--config", f, "--daq", "a", "--gps", "b", "--out", o]}


@pytest.mark.parametrize("bad", ["missing", "directory", "empty", "random", "truncated", "wrong_format"])
@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_command_gives_one_line_and_exit_2_for_a_bad_file(bad_inputs, tmp_path, capsys, command, bad) -> None:
    from fieldlog.tools.cli import main

    if (command, bad) in (("recover", "truncated"), ("acquire", "empty")):
        return                              # what recover is for; an empty config is valid (all defaults)
    f = bad_inputs[bad]
    code = main(COMMANDS[command](str(f), str(tmp_path)))
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert str(f) in err[0] or f.name in err[0], err
    if bad == "truncated" and command not in ("import", "acquire"):
        assert "fieldlog recover" in err[0]


@pytest.mark.parametrize("command", ["fuse", "rebuild", "recover", "export", "view"])
def test_an_unwritable_output_is_one_line_and_exit_2(bad_inputs, tmp_path, capsys, command) -> None:
    from fieldlog.tools.cli import main

    blocker = tmp_path / "file"
    blocker.write_text("x")                         # a file where the output directory should be
    code = main(COMMANDS[command](str(bad_inputs["good"]), str(blocker / "sub")))
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "file" in err[0], err


# ------------------------------------------------------------------------------------------- paths

def test_export_keeps_every_table_under_out_whatever_the_topic_names(tmp_path: Path) -> None:
    from mcap_ros2.writer import Writer

    from fieldlog.replay.export import export

    drive = tmp_path / "hostile.mcap"
    names = ["/../../escaped", "/a/../../../b", "//double//slash", "/..", "/gps/fix", "/gps\\fix", "/ü/nul\x00x"]
    with open(drive, "wb") as f:
        w = Writer(f)
        schema = w.register_msgdef(messages.SENTENCE, messages.schema_text(messages.SENTENCE))
        for i, topic in enumerate(names):
            w.write_message(topic, schema, {"header": {"stamp": {"sec": 1, "nanosec": i}, "frame_id": "gps"},
                                            "sentence": "$GPGGA,,,,,,0,,,,,,,,*66"}, log_time=NS + i)
        w.finish()
    out = tmp_path / "out"
    written = export(drive, out, "csv")
    assert set(written) == set(names)
    files = [p for p, _ in written.values()]
    assert len(set(files)) == len(names)
    assert all(p.resolve().is_relative_to(out.resolve()) and p.is_file() for p in files)
    assert sorted(p for p in tmp_path.rglob("*.csv")) == sorted(files)
    assert written["/gps/fix"][0] == out / "gps" / "fix.csv"


def test_the_bus_replaces_only_a_stale_socket_of_its_own(tmp_path: Path) -> None:
    import os
    import socket
    import tty

    ptys = []
    for _ in range(2):
        m, s = os.openpty()
        tty.setraw(s)
        ptys.append((m, s, os.ttyname(s)))
    ports = ["--daq", ptys[0][2], "--gps", ptys[1][2], "--out", str(tmp_path / "d"), "--quiet"]
    bus = tmp_path / "bus"
    cfg = tmp_path / "acquire.toml"
    cfg.write_text(f'[daemon]\nbus = "{bus}"\n')
    try:
        bus.write_text("precious")                                  # a regular file: left alone, exit 2
        r = run("acquire", "--config", str(cfg), *ports)
        assert r.returncode == 2 and bus.read_text() == "precious" and "not a socket" in r.stderr, r.stderr
        assert len(r.stderr.strip().splitlines()) == 1
        bus.unlink()
        live = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)    # someone listening: in use, exit 2
        live.bind(str(bus))
        live.listen(1)
        r = run("acquire", "--config", str(cfg), *ports)
        assert r.returncode == 2 and "in use" in r.stderr and bus.exists(), r.stderr
        live.close()                                                # now stale: replaced, the daemon runs
        d, _ = start_daemon(tmp_path / "d", {"daq": ptys[0][2], "gps": ptys[1][2]}, "--config", str(cfg))
        d.send_signal(signal.SIGTERM)
        assert d.wait(30) == 0, d.stderr.read()
    finally:
        for m, s, _ in ptys:
            os.close(m)
            os.close(s)


# ------------------------------------------------------------------------------------------- recover

def test_recover_after_kill9_gives_imu_to_the_cut_and_a_full_disk_leaves_the_original(tmp_path: Path) -> None:
    """A run at x10 killed after 9 s (90 s of data): the kept chunks hold /imu only up to about a minute
    before the kill (the centred time fit); recover re-derives the tail from /raw, as the daemon's start does,
    and a recovery that hits a file size limit (a full disk) fails in one line and leaves nothing behind."""
    import resource
    import subprocess
    import sys

    from fieldlog.acquire import daq
    from fieldlog.acquire.daemon import is_finished
    from test_daemon import raw_stream
    from test_serve import ROOT, start_serve

    out = tmp_path / "drives"
    serve, paths = start_serve("--scenario", "figure8", "--duration", "170", "--speed", "10", "--hold")
    try:
        d, _ = start_daemon(out, paths, "--time-scale", "10")
        serve.send_signal(signal.SIGUSR1)
        time.sleep(9.0)
        kill_mono = time.monotonic_ns()
        d.send_signal(signal.SIGKILL)
        d.wait(10)
    finally:
        serve.send_signal(signal.SIGTERM)
        serve.wait(10)
    (cut,) = sorted(out.glob("*/*.mcap"))
    before = cut.read_bytes()
    plain = tmp_path / "plain.mcap"
    recovery.recover(cut, plain)                                     # the chunks alone
    n_plain = next((t.count for t in reader.topics(plain) if t.topic == "/imu"), 0)
    # a full disk (here: a file size limit) during recovery: one line, nothing left behind, original intact
    limit = len(before) // 2

    def small_files() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    full = tmp_path / "full.mcap"
    r = subprocess.run([sys.executable, "-m", "fieldlog", "recover", str(cut), "--out", str(full)], cwd=ROOT,
                       capture_output=True, text=True, timeout=120, preexec_fn=small_files)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr, r.stderr
    assert not full.exists() and not list(tmp_path.glob("*.partial")) and cut.read_bytes() == before
    # recover, complete
    r = run("recover", str(cut), "--out", str(full))
    assert r.returncode == 0, r.stderr
    _, mono = raw_stream(full, "daq")
    assert (kill_mono - mono[-1]) / 1e9 <= 1.5                       # raw: at most 1.5 s (host) lost
    frames = daq.DaqDecoder().feed(raw_stream(full, "daq")[0]).k
    imu = reader.read_topic(full, "/imu")["log_time_ns"]
    print(f"\n/imu after recover: {len(imu)} samples (chunks alone: {n_plain}), raw frames {len(frames)}")
    assert len(frames) - 500 <= len(imu) <= len(frames)               # /imu to within 1 s of data of the cut
    assert len(imu) > n_plain + 40 * 500 and np.all(np.diff(imu) > 0)
    assert "rederived./imu" in read_metadata(full)["recover"]
    assert is_finished(full) and cut.read_bytes() == before
    # the daemon's recovery on start: on a full disk it logs, records on and leaves nothing; the next start
    # recovers the same complete drive
    import os
    import tty

    ptys = []
    for _ in range(2):
        m, s = os.openpty()
        tty.setraw(s)
        ptys.append((m, s))
    names = {"daq": os.ttyname(ptys[0][1]), "gps": os.ttyname(ptys[1][1])}
    logs = []
    try:
        for pre in (small_files, None):
            d, log = start_daemon(out, names, preexec_fn=pre)
            d.send_signal(signal.SIGTERM)
            assert d.wait(30) == 0
            logs.append(log + d.stderr.read())
    finally:
        for m, s in ptys:
            os.close(m)
            os.close(s)
    rec = cut.with_name(cut.stem + ".recovered.mcap")
    assert f"could not recover unfinished {cut.name}" in logs[0] and "Traceback" not in logs[0], logs[0]
    assert f"recovered unfinished {cut.name}" in logs[1] and is_finished(rec)
    assert np.array_equal(reader.read_topic(rec, "/imu")["log_time_ns"], imu)


def test_in_read_order_is_a_sort_by_read_order():
    """Ties of time across ports and within one, unknown ports, any input order: the list sorting by
    ``read_order`` gives, each read the same object."""
    rng = np.random.default_rng(4)
    ports = np.array(["daq", "gps", "can", "aux", "zz"])
    reads = [RawRead(str(p), int(m), i, bytes([i % 256])) for i, (p, m) in
             enumerate(zip(rng.choice(ports, 3000), rng.integers(0, 400, 3000)))]
    for case in (reads, sorted(reads, key=lambda r: r.mono_ns), reads[::-1], []):
        got, want = in_read_order(case), sorted(case, key=lambda r: read_order(r.port, r.mono_ns))
        assert len(got) == len(want) and all(a is b for a, b in zip(got, want))
