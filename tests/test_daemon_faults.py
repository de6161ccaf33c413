"""``fieldlog acquire`` riding through faults, as a real subprocess against ``fieldlog sim --serve`` ptys:
corrupt bytes, a port unplugged and replugged, and time sync at ``--speed 20`` with ``--time-scale 20``."""
from __future__ import annotations

import resource
import signal
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from fieldlog.acquire import daq
from fieldlog.drive import messages
from fieldlog.acquire.daemon import is_finished
from fieldlog.drive import reader
from test_daemon import byte_difference, gps_frames, raw_stream, run, start_daemon, wait_caught_up
from test_serve import expected_bytes, start_serve, wait_served
from fieldlog.drive.reader import read_metadata, read_metadata_records
from fieldlog.tools.sim.serve import PORTS, corrupt_stream

SPEED = 20
FRAME_NS = 2_000_000
NS = 1_000_000_000
LOCKED = 2


def record(tmp_path: Path, *serve_args: str, duration: float, seed: int, daemon_args: tuple[str, ...] = (),
           attach: Callable[[dict[str, str]], dict[str, str]] | None = None,
           during: Callable[[], None] | None = None, speed: int = SPEED) -> tuple[Path, Path, str]:
    """Serve a figure8 drive at x``speed`` to a running daemon, stop both; returns the one drive file, the truth
    file and the daemon's log. ``attach`` maps the serve's ports to the daemon's (e.g. through gpsd); ``during``
    runs once the drive has started."""
    truth = tmp_path / "truth.mcap"
    serve, paths = start_serve("--scenario", "figure8", "--duration", str(duration), "--seed", str(seed),
                               "--speed", str(speed), "--hold", "--truth", str(truth), *serve_args)
    links = tmp_path / "ports" if "--link-dir" in serve_args else None
    if links is not None:
        paths = {p: str(links / p) for p in PORTS}
    try:
        if attach is not None:
            paths = attach(paths)
        d, _ = start_daemon(tmp_path / "drives", paths, "--time-scale", str(speed), *daemon_args)
        serve.send_signal(signal.SIGUSR1)
        if during is not None:
            during()
        wait_served(serve, d, 300)                   # the drive ended and the daemon drained the ptys
    finally:
        if serve.poll() is None:
            serve.kill()
    wait_caught_up(d)
    d.send_signal(signal.SIGTERM)
    code, log = d.wait(300), d.stderr.read()
    assert code == 0, log
    (f,) = sorted((tmp_path / "drives").glob("*/*.mcap"))
    assert is_finished(f)
    return f, truth, log


def _latch_config(tmp_path: Path) -> Path:
    """A daemon config for a latched PPS (the sampled flag's rate fit is too coarse for a few ms at x20)."""
    cfg = tmp_path / "acquire.toml"
    cfg.write_text('[timesync]\npps_mode = "latch"\n')
    return cfg


def sentences(path: Path) -> list[str]:
    """The /gps/nmea sentence texts, in log-time order."""
    return [m.sentence for m in reader.read_topic(path, "/gps/nmea")["msgs"]]


def test_one_percent_corruption_is_resynchronised_counted_and_every_intact_frame_recorded(tmp_path: Path) -> None:
    """Served at x2: the time sync's host gates (a fix's age, an edge's disagreement with the fixes' host times)
    are data seconds, so at xS they allow about 0.4 / S s of latency on the GPS port's reads (an edge is at its
    frame's host time, which a late DAQ read does not move), and with the PPS flags the corrupt frames lose every
    remaining edge counts for the lock: x2 allows 200 ms, which a loaded host keeps to; x20 would allow 20 ms."""
    f, truth, _ = record(tmp_path, "--corrupt", "0.01", duration=20, seed=7, speed=2)
    clean = expected_bytes(truth, "figure8", 20.0, 7)
    sent = {p: corrupt_stream(clean[p], 0.01, 7, p) for p in PORTS}
    meta = read_metadata(truth)["serve"]
    for p in PORTS:
        assert int(meta[f"{p}_corrupt_bytes"]) == sent[p][1].size == round(0.01 * len(clean[p]))
        assert raw_stream(f, p)[0] == sent[p][0]        # every byte as sent, corrupt ones included
    # DAQ: the counters follow from where the corrupt bytes fell
    pos = sent["daq"][1]
    n = len(clean["daq"]) // daq.FRAME_SIZE
    bad = np.zeros(n, bool)
    bad[pos // daq.FRAME_SIZE] = True
    intact = np.flatnonzero(~bad)
    sync_hit = np.zeros(n, bool)
    sync_hit[pos[pos % daq.FRAME_SIZE < 2] // daq.FRAME_SIZE] = True
    # a bad frame right after a good one is a bad CRC when its sync bytes survived (else a resync scan)
    want_bad_crc = int((bad[1:] & ~bad[:-1] & ~sync_hit[1:]).sum())
    # a resync is counted when the next good frame is not the one right after the lost one: runs of >= 2
    # bad frames between good ones
    edges = np.diff(np.concatenate(([0], bad.astype(np.int8), [0])))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    inner = (starts > 0) & (ends < n)
    want_resyncs = int(((ends - starts)[inner] >= 2).sum())
    c = read_metadata(f)["acquire.counters"]
    assert 0.25 * n < bad.sum() < 0.4 * n                      # 1 - 0.99**38 of the frames
    assert int(c["daq.frames"]) == intact.size
    assert int(c["daq.lost_frames"]) == intact[-1] - intact[0] + 1 - intact.size
    assert int(c["daq.bad_crc"]) == want_bad_crc > 0
    assert int(c["daq.resyncs"]) == want_resyncs > 0
    # every intact frame is on /imu, in order, with its own sample's stamp (the sync locks with the scale)
    imu = reader.read_topic(f, "/imu")
    tru = reader.read_topic(truth, "/truth/imu")
    assert len(imu["log_time_ns"]) == intact.size
    step = np.round(np.diff(imu["log_time_ns"]) / FRAME_NS).astype(np.int64) - np.diff(intact)
    off = np.flatnonzero(step)
    assert not len(off), ("stamp steps off the frame grid after intact frames", intact[off], step[off],
                          (imu["log_time_ns"] - tru["log_time_ns"][intact])[off], intact[0], intact[-1])
    assert np.abs(imu["log_time_ns"] - tru["log_time_ns"][intact]).max() < 3_000_000
    assert np.sqrt(np.mean((imu["omega_ib_b"] - tru["omega_ib_b"][intact])[:, 2] ** 2)) < 0.01
    assert LOCKED in reader.read_topic(f, "/time/sync")["state"]       # (PPS flags in corrupt frames are lost)
    # NMEA: corrupt lines are counted and dropped; every line whose text and CR are intact is recorded (a
    # corrupt LF alone leaves the line ended by its CR)
    text = bytes(clean["gps"])
    lines = text.split(b"\r\n")[:-1]
    starts_g = np.cumsum([0] + [len(x) + 2 for x in lines[:-1]])
    hit = np.zeros(len(text), bool)
    hit[sent["gps"][1]] = True
    ok = [not hit[s:s + len(x) + 1].any() for s, x in zip(starts_g, lines)]
    got = sentences(f)
    intact_lines = [x.decode() for x, o in zip(lines, ok) if o]
    assert set(intact_lines) <= set(got) <= {x.decode() for x in lines}
    assert len(got) - len(intact_lines) <= ok.count(False)
    assert 0 < int(c["nmea.bad_checksum"]) <= ok.count(False)


@pytest.mark.slow
@pytest.mark.parametrize("receiver", ["nmea", "ublox"])
def test_unplugged_port_is_retried_its_gap_recorded_and_nothing_else_lost(tmp_path: Path, receiver: str) -> None:
    # the DAQ pty disappears 20 s into the drive for 61 simulated s (3.05 s at x20) and comes back as a new pty.
    # (Not exactly 3 s: the daemon notices the loss at once and retries every 0.5 s, so a whole number of
    # retry periods would have it retry right when the pty comes back; 3.05 s is just after a retry, close
    # to the worst case.)
    # (PPS latch: a sampled flag's rate fit over the 40 s around a 60 s hole is too coarse for a few ms.)
    f, truth, log = record(tmp_path, "--unplug", "daq:20:61", "--link-dir", str(tmp_path / "ports"),
                           "--pps", "latch", "--receiver", receiver, duration=120, seed=3,
                           daemon_args=("--config", str(_latch_config(tmp_path))))
    assert "daq port lost" in log and "daq port back" in log
    assert not list((tmp_path / "ports").iterdir())     # no link outlives its pty (another run may get its number)
    clean = expected_bytes(truth, "figure8", 120.0, 3)
    meta = read_metadata(truth)["serve"]
    (gap,) = meta["daq_gaps"].split(";")
    a, n_gap = map(int, gap.split(":"))
    # + until the daemon reopened: host time, x20 (a loaded host retries late), so bounded by the drive only
    assert 59 * 500 * daq.FRAME_SIZE < n_gap < (120 - 20) * 500 * daq.FRAME_SIZE
    assert meta["gps_gaps"] == "" and meta["completed"] == "True" and meta["daq_undrained_unplugs"] == "0"
    # everything the port delivered before and after the gap is recorded, in order; the GPS lost nothing
    got, mono = raw_stream(f, "daq")
    assert (diff := byte_difference(got, clean["daq"][:a] + clean["daq"][a + n_gap:])) is None, diff
    assert (diff := byte_difference(raw_stream(f, "gps")[0], clean["gps"])) is None, diff
    # the gap is in the drive: a lost and a back record, and no DAQ read between them
    events = [d for name, d in read_metadata_records(f) if name == "acquire.port_event"]
    # (both ports are lost again at the end, when sim --serve exits)
    assert [(e["port"], e["event"]) for e in events[:2]] == [("daq", "lost"), ("daq", "back")]
    assert sorted((e["port"], e["event"]) for e in events[2:]) == [("daq", "lost"), ("gps", "lost")]
    lost, back = (int(e["mono_ns"]) for e in events[:2])
    assert not np.any((mono > lost) & (mono < back))
    assert np.any(mono < lost) and np.any(mono > back)
    # it resumes after the pty came back: the reopening (serve's host mono time) to the first read of the new port
    # (retried every [daemon] reconnect_s = 0.5 s; the bound is a generous safety net, not a speed: a loaded
    # host may take a few periods)
    (replug,) = map(int, meta["daq_replug_mono_ns"].split(";"))
    first = int(mono[mono > back][0])
    resume_s = (first - replug) / 1e9
    print(f"\nDAQ port back {(back - replug) / 1e6:.1f} ms after the pty reopened, first read after "
          f"{resume_s * 1e3:.1f} ms")
    assert lost < replug < back < first and resume_s <= 10.0
    # every byte the port delivered before it was lost was read before the loss, and every byte after the
    # gap was read after the reopening
    sizes = np.array([len(m.data) for m in reader.read_topic(f, "/raw/daq")["msgs"]])
    assert sizes[mono < lost].sum() == a and sizes[mono > back].sum() == len(clean["daq"]) - a - n_gap
    info = run("info", str(f))
    assert info.returncode == 0 and "port=daq, event=lost" in info.stdout and "port=daq, event=back" in info.stdout
    # every whole frame outside the gap is decoded, and time sync carries on across it
    n = len(clean["daq"]) // daq.FRAME_SIZE
    start = np.arange(n) * daq.FRAME_SIZE
    whole = (start + daq.FRAME_SIZE <= a) | (start >= a + n_gap)
    c = read_metadata(f)["acquire.counters"]
    assert int(c["port.daq.disconnects"]) == 2 and int(c["port.gps.disconnects"]) == 1
    assert int(c["daq.frames"]) == whole.sum() and int(c["daq.lost_frames"]) == n - whole.sum()
    frames = gps_frames(clean["gps"])
    assert {k: int(c.get(f"gps.frames.{k}", 0)) for k in frames} == frames and int(c["nmea.bad_checksum"]) == 0
    assert int(c["gps_epochs"]) >= 110 and (receiver == "ublox") == (int(c.get("ubx.NAV-PVT", 0)) > 0)
    imu = reader.read_topic(f, "/imu")
    tru = reader.read_topic(truth, "/truth/imu")
    assert len(imu["log_time_ns"]) == whole.sum()
    assert np.abs(imu["log_time_ns"] - tru["log_time_ns"][whole]).max() < 3_000_000
    assert reader.read_topic(f, "/time/sync")["state"][-1] == LOCKED


@pytest.mark.slow
def test_file_size_limit_stops_cleanly_with_a_recoverable_file(tmp_path: Path) -> None:
    """ENOSPC cannot be provoked here (no tmpfs to fill); RLIMIT_FSIZE gives EFBIG at the limit, which the
    daemon handles exactly as a full disk."""
    limit = 600_000
    out = tmp_path / "drives"
    truth = tmp_path / "truth.mcap"
    serve, paths = start_serve("--scenario", "figure8", "--duration", "120", "--seed", "2", "--speed", "20", "--hold",
                               "--truth", str(truth))
    try:
        d, _ = start_daemon(out, paths, preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit)))
        serve.send_signal(signal.SIGUSR1)
        code, log = d.wait(300), d.stderr.read()
    finally:
        serve.send_signal(signal.SIGTERM)
        serve.wait(300)
    assert code == 2, log
    assert "Traceback" not in log and "Exception" not in log
    (err,) = [line for line in log.splitlines() if "error:" in line]
    (f,) = sorted(out.glob("*/*.mcap"))
    assert f"file size limit (EFBIG) writing {f}: recording stopped" in err and "fieldlog recover" in err
    assert not is_finished(f) and f.stat().st_size <= limit
    r = run("recover", str(f), "--out", str(tmp_path / "rescued.mcap"))
    assert r.returncode == 0, r.stderr
    got, _ = raw_stream(tmp_path / "rescued.mcap", "daq")
    assert len(got) > 100 * daq.FRAME_SIZE
    assert got == expected_bytes(truth, "figure8", 120.0, 2)["daq"][:len(got)]    # what it kept is intact


@pytest.mark.slow
def test_one_percent_corruption_in_ublox_mode_keeps_every_intact_ubx_message(tmp_path: Path) -> None:
    """u-blox port (GGA + NAV-PVT + TIM-TP) with 1 % of the bytes corrupted: every byte is recorded as sent,
    every UBX message without a corrupt byte is decoded into /gps/receiver, nothing else is (checksums)."""
    from fieldlog.acquire import gpsport

    f, truth, _ = record(tmp_path, "--corrupt", "0.01", "--receiver", "ublox", duration=20, seed=7)
    clean = expected_bytes(truth, "figure8", 20.0, 7)
    sent, pos = corrupt_stream(clean["gps"], 0.01, 7, "gps")
    assert raw_stream(f, "gps")[0] == sent
    framer = gpsport.Framer()
    frames = framer.feed(clean["gps"])
    hit = np.zeros(len(clean["gps"]), bool)
    hit[pos] = True
    intact = {fr for (k, fr), end in zip(frames, framer.ends) if k == "ubx" and not hit[end - len(fr):end].any()}
    got = [bytes(m.data) for m in reader.read_topic(f, "/gps/receiver")["msgs"]]
    assert intact <= set(got) <= {fr for k, fr in frames if k == "ubx"}
    assert len(intact) >= 10               # (a 100-byte NAV-PVT survives 1 % corruption 37 % of the time)
    c = read_metadata(f)["acquire.counters"]
    assert int(c.get("gps.bad_checksum.ubx", 0)) > 0 and int(c.get("ubx.undecodable", 0)) == 0
    # one fix per NAV-PVT, plus the GGA epochs before the first intact NAV-PVT; never two for one second
    stamps = reader.read_topic(f, "/gps/fix")["log_time_ns"]
    assert int(c["gps_epochs"]) >= sum(1 for fr in got if fr[2:4] == b"\x01\x07") and len(set(stamps)) == len(stamps)


def test_a_receiver_clock_jump_over_the_pty_is_flagged_no_fix_and_not_written_an_hour_late(tmp_path: Path) -> None:
    """sim --serve --clock-jump: the receiver writes its time +1 h for 10 s; the daemon (locked by then) flags
    exactly those epochs NO_FIX, counts them, keeps their sentences, and stamps them by the clock fit."""
    f, truth, _ = record(tmp_path, "--clock-jump", "40:10:3600", "--pps", "latch", duration=70, seed=5,
                         daemon_args=("--config", str(_latch_config(tmp_path))))
    clean = expected_bytes(truth, "figure8", 70.0, 5)
    assert raw_stream(f, "gps")[0] == clean["gps"]
    t0 = int(read_metadata(truth)["serve"]["drive_start_utc_ns"])
    times = [s.split(",")[1] for s in sentences(f) if s[3:6] in ("GGA", "RMC", "GST", "ZDA")]
    sod = [int(x[:2]) * 3600 + int(x[2:4]) * 60 + float(x[4:]) for x in dict.fromkeys(times)]   # epochs in order
    jumped = sum((x - sod[0]) % 86400 > 1800 for x in sod)        # an hour ahead of the drive's first epoch
    assert 9 <= jumped <= 11                              # 10 s at 1 Hz, give or take the window's edges
    c = read_metadata(f)["acquire.counters"]
    fix = reader.read_topic(f, "/gps/fix")
    t = fix["log_time_ns"]
    flagged = fix["status"] == messages.STATUS_NO_FIX
    assert flagged.sum() == int(c["gps_no_fix.receiver_time"]) == int(c["gps_no_fix"]) == jumped
    assert np.all((t[flagged] > t0 + 39 * NS) & (t[flagged] < t0 + 52 * NS)) and np.all(np.diff(t) > 0)
    assert t.max() < t0 + 71 * NS and np.all(np.isnan(fix["lat_deg"][flagged]))    # nothing an hour late
